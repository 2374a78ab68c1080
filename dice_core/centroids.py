"""Pseudo-star centroids: windows, the 7-parameter Gaussian fit, Fourier resampling, pixel-offset correction.

Paper: section "Pseudo stars". Conventions: x along columns, y along rows,
pixel units; a pixel's nominal centre is at its integer (col, row); windows
are square, of odd side 2h + 1, and positions are returned in detector
coordinates.

- :func:`gaussian_fit`: background, intensity, x, y and the elliptical
  Gaussian's shape (fitted as the quadratic form A u^2 + 2B uv + C v^2, well
  conditioned also for a round PSF; reported as two widths and an angle),
  sampled at the pixel centres.
- :func:`fourier_displacement`: the displacement t minimising
  sum |PSF_1 - FT^-1[exp(-2 pi i t.f) FT[PSF_2]]|^2. By Parseval the residual
  is a constant minus twice the band-limited cross-correlation
  Re sum_f conj(F1) F2 exp(-2 pi i t.f), which is evaluated, with its
  gradient and Hessian, directly in the Fourier domain: Newton's method from
  the best integer shift converges to machine precision, on no grid and
  with no upsampling factor.
- :func:`offset_corrected`: the window as a detector of perfect pixels would
  have recorded it (the paper's corrected PSF), given each pixel's offset:
  PSF_c solves PSF(r + delta) = measured, with PSF_c band-limited
  (its values and derivatives from the FFT of the window).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dice_core import lazy

xr = lazy.module("xarray")

__all__ = [
    "WindowError",
    "Window",
    "star_window",
    "science_area_problem",
    "GaussianFit",
    "gaussian_fit",
    "gaussian_fits",
    "cramer_rao",
    "isolated_half_size",
    "fourier_displacement",
    "fourier_displacements",
    "offset_corrected",
    "response_corrected",
    "Mode",
    "MODES",
    "METHODS",
    "mode_descriptions",
    "method_descriptions",
    "mode_needs",
    "mode_corrections",
    "PositionCentroids",
    "measure_positions",
    "centroids_dataset",
]


class WindowError(ValueError):
    """A star window that cannot be cut (too close to the detector edge...)."""


@dataclass(frozen=True)
class Window:
    """A square window of the detector: rows ``row0 .. row0 + size - 1``, cols ``col0 ..``."""

    row0: int
    col0: int
    size: int

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.row0, self.row0 + self.size), slice(self.col0, self.col0 + self.size)

    def grid(self):
        """Pixel centres (x, y) of the window, each (size, size), detector coordinates."""
        y, x = np.mgrid[self.row0:self.row0 + self.size, self.col0:self.col0 + self.size]
        return x.astype(float), y.astype(float)


def star_window(approx_row: float, approx_col: float, *, half_size: int, shape, label: str = "star",
                area=None) -> Window:
    """The (2 half_size + 1)-pixel window centred on the pixel nearest (approx_row, approx_col).

    ``area``, the science area's (rows, cols) half-open ranges (the dark is measured there only), bounds
    the window further when given.

    Raises
    ------
    WindowError
        The window would leave the detector (``shape`` rows, cols) or the
        area; the message starts with ``label`` (e.g. "star 3 at position 12").
    """
    row, col = int(round(approx_row)), int(round(approx_col))
    size = 2 * half_size + 1
    r0, c0 = row - half_size, col - half_size
    if r0 < 0 or c0 < 0 or r0 + size > shape[0] or c0 + size > shape[1]:
        raise WindowError(f"{label}: its {size}x{size} window around row {approx_row:.1f}, col {approx_col:.1f} "
                          f"leaves the {shape[0]}x{shape[1]} detector")
    if area is not None:
        (top, bottom), (left, right) = area
        if r0 < top or c0 < left or r0 + size > bottom or c0 + size > right:
            raise WindowError(f"{label}: its {size}x{size} window around row {approx_row:.1f}, col "
                              f"{approx_col:.1f} (rows {r0}-{r0 + size - 1}, cols {c0}-{c0 + size - 1}) leaves "
                              f"the science area, rows {top}-{bottom - 1} and cols {left}-{right - 1}, where the "
                              "dark is measured")
    return Window(r0, c0, size)


def science_area_problem(detector, half_size: int) -> str | None:
    """Why the detector's science area cannot hold a star window of ``half_size`` (a configuration key,
    ``centroids.half_size``), or None: one line naming the manifest's key."""
    size = 2 * half_size + 1
    rows, cols = (hi - lo for lo, hi in (detector.science_rows, detector.science_cols))
    if rows >= size and cols >= size:
        return None
    return (f"detector.science_area holds {rows} row(s) x {cols} col(s), too few for the {size}x{size} star "
            f"windows of centroids.half_size {half_size}")


@dataclass(frozen=True)
class GaussianFit:
    """Result of :func:`gaussian_fit`: adu for levels, pixel for positions and widths, rad for the angle.

    ``width_x`` is the standard deviation along the direction ``angle`` (from
    +x towards +y; the major axis), ``width_y`` across it; ``cost`` is the
    (weighted) sum of squared residuals; ``params`` the fitted
    (background, intensity, x, y, A, B, C) of the quadratic form.
    """

    background: float
    intensity: float
    x: float
    y: float
    width_x: float
    width_y: float
    angle: float
    cost: float
    params: np.ndarray


def _gaussian_model(p, xs, ys):
    """Model values (..., pixel) and their derivatives (..., pixel, 7) at pixel centres xs, ys (..., pixel), for
    parameters p (..., 7)."""
    b, amp, x, y, a, bb, c = (p[..., i, None] for i in range(7))
    u, v = xs - x, ys - y
    e = np.exp(-0.5 * (a * u * u + 2 * bb * u * v + c * v * v))
    ae = amp * e
    jacobian = np.stack([np.ones_like(e), e, ae * (a * u + bb * v), ae * (bb * u + c * v),
                         -0.5 * ae * u * u, -ae * u * v, -0.5 * ae * v * v], -1)
    return b + ae, jacobian


def gaussian_fit(image: np.ndarray, window: Window, *, weights=None, label: str = "star") -> GaussianFit:
    """Fit background + intensity x elliptical Gaussian to a window, sampled at pixel centres.

    Parameters
    ----------
    image : ndarray (size, size)
        Dark-subtracted (and, if wanted, flat-corrected) window, adu.
    window : Window
        Where the window lies, for detector coordinates.
    weights : ndarray (size, size), optional
        1 / sigma of each pixel (e.g. from photon noise); uniform if omitted.
    label : str
        Names the star in errors ("star 3 at position 12").

    Returns
    -------
    GaussianFit

    Raises
    ------
    WindowError
        No signal above the background in the window.
    """
    return gaussian_fits(np.asarray(image, float)[None], [window], weights=None if weights is None else
                         np.asarray(weights, float)[None], labels=[label])[0]


def gaussian_fits(images: np.ndarray, windows, *, weights=None, labels=None) -> list[GaussianFit]:
    """:func:`gaussian_fit` of each window of ``images`` (k, size, size) (``windows``: k Windows; ``weights``
    (k, size, size); ``labels``: k names for errors), fitted together by a Levenberg-Marquardt iteration on all
    of them at once (each with its own damping, stopping at its own convergence), which spares the Python
    overhead of k small fits. Converged when a step moves no parameter by more than 1e-6 of its precision,
    or when no step lowers the cost any more (to the rounding of the cost): :func:`_levenberg_marquardt`."""
    images = np.asarray(images, float)
    k = len(images)
    grids = [w.grid() for w in windows]
    xs, ys = (np.array([g[i].ravel() for g in grids]) for i in (0, 1))
    data = images.reshape(k, -1)
    w = np.ones_like(data) if weights is None else np.asarray(weights, float).reshape(k, -1)
    start = _gaussian_starts(images, data, w, xs, ys, windows, labels or ["star"] * k)

    def residual_jacobian(p, rows):
        model, jac = _gaussian_model(p, xs[rows], ys[rows])
        return w[rows] * (model - data[rows]), w[rows][..., None] * jac

    params = _levenberg_marquardt(residual_jacobian, start)
    residual, _ = residual_jacobian(params, np.arange(k))
    covariance = np.linalg.inv(np.stack([params[:, 4:6], params[:, 5:7]], -2))
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    fits = []
    for i, (b, amp, x, y, _, _, _) in enumerate(params):
        angle = float(np.arctan2(eigenvectors[i, 1, 1], eigenvectors[i, 0, 1]))
        fits.append(GaussianFit(float(b), float(amp), float(x), float(y), float(np.sqrt(eigenvalues[i, 1])),
                                float(np.sqrt(eigenvalues[i, 0])), angle, float(np.sum(residual[i] ** 2)),
                                params[i].copy()))
    return fits


def _gaussian_starts(images, data, w, xs, ys, windows, labels):
    """The fits' starts (k, 7): background from the window's border, position and shape from the second
    moments of the signal above it."""
    border = np.concatenate([images[:, 0], images[:, -1], images[:, 1:-1, 0], images[:, 1:-1, -1]], axis=1)
    b0 = np.median(border, axis=1)
    signal = np.clip(data - b0[:, None], 0, None) * (w > 0)  # pixels of weight 0 (left out) do not start it either
    total = signal.sum(axis=1)
    if not np.all(total > 0):
        i = int(np.flatnonzero(~(total > 0))[0])
        window = windows[i]
        raise WindowError(f"{labels[i]}: no signal above the background in its window (rows {window.row0}-"
                          f"{window.row0 + window.size - 1}, cols {window.col0}-{window.col0 + window.size - 1})")
    x0, y0 = (signal * xs).sum(axis=1) / total, (signal * ys).sum(axis=1) / total
    u, v = xs - x0[:, None], ys - y0[:, None]
    cxx, cyy, cxy = ((signal * m).sum(axis=1) / total for m in (u**2, v**2, u * v))
    inverse = np.linalg.inv(np.stack([np.stack([cxx, cxy], -1), np.stack([cxy, cyy], -1)], -2))
    return np.column_stack([b0, signal.max(axis=1), x0, y0, inverse[:, 0, 0], inverse[:, 0, 1], inverse[:, 1, 1]])


def _levenberg_marquardt(residual_jacobian, start, *, xtol=1e-6, max_iterations=500):
    """Minimise each problem's sum of squared residuals: ``residual_jacobian(p, rows)`` gives the residuals
    (m, n) and Jacobians (m, n, q) of the problems ``rows`` at their parameters p (m, q). Marquardt's damping
    (of the normal matrix's diagonal), raised tenfold on a step that does not lower the cost, lowered tenfold
    on one that does; a problem stops when a step of damping at most 1 moves every parameter by less than
    ``xtol`` of its precision (1 / sqrt of the normal matrix's diagonal entry, the residuals being weighted:
    1e-6 of the Cramer-Rao bound, about), or when its damping is so large that no step is left. Smaller steps
    are rounding: at the minimum of a bright star's window, the Gauss-Newton step is a few 1e-7 of the
    precision and changes the cost by less than its rounding (measured on the paper preset's stars)."""
    params = start.astype(float).copy()
    k, q = params.shape
    rows = np.arange(k)
    residual, jac = residual_jacobian(params, rows)
    cost = np.sum(residual**2, axis=1)
    damping = np.full(k, 1e-3)
    active = np.ones(k, bool)
    for _ in range(max_iterations):
        a = np.flatnonzero(active)
        jac_t = jac[a].transpose(0, 2, 1)
        normal = jac_t @ jac[a]
        gradient = (jac_t @ residual[a][..., None])[..., 0]
        diagonal = np.diagonal(normal, axis1=1, axis2=2)
        damped = normal + (damping[a, None] * np.where(diagonal > 0, diagonal, 1.0))[..., None] * np.eye(q)
        with np.errstate(all="ignore"):
            step = -_solve_or_nan(damped, gradient)
        trial = params[a] + step
        trial_residual, trial_jac = residual_jacobian(trial, a)
        trial_cost = np.sum(trial_residual**2, axis=1)
        better = np.isfinite(trial_cost) & (trial_cost < cost[a])
        accepted = a[better]
        params[accepted], residual[accepted], jac[accepted] = trial[better], trial_residual[better], trial_jac[better]
        cost[accepted] = trial_cost[better]
        # a step measured in its parameter's own precision (1 / sqrt of the normal matrix's diagonal), of a
        # damping that leaves it at least half the Gauss-Newton step: below it, the minimum is reached (a
        # smaller step is rounding, which may or may not lower the cost)
        small = np.all(np.abs(step) * np.sqrt(diagonal) <= xtol, axis=1) & (damping[a] <= 1)
        damping[a] = np.where(better, np.maximum(damping[a] / 10, 1e-15), damping[a] * 10)
        active[a[small | (damping[a] > 1e16)]] = False
        if not active.any():
            break
    return params


def cramer_rao(fit: GaussianFit, window: Window, *, gain: float, read_noise, used=None) -> np.ndarray:
    """Cramer-Rao bound (sigma_x, sigma_y), pixel, for the position of a star of this shape and flux.

    Photon noise of the model counts (variance model / gain, adu^2) plus read
    noise (adu, scalar or per pixel of the window), all 7 parameters free:
    the bound is sqrt of the diagonal of the inverse Fisher matrix. ``used``
    (bool, size x size) leaves the other pixels out of the Fisher sum.
    """
    xg, yg = window.grid()
    model, jac = _gaussian_model(fit.params, xg.ravel(), yg.ravel())
    variance = np.clip(model, 0, None) / gain + np.ravel(np.broadcast_to(read_noise, (window.size,) * 2)) ** 2
    if used is not None:
        keep = np.ravel(used)
        jac, variance = jac[keep], variance[keep]
    fisher = jac.T @ (jac / variance[:, None])
    return np.sqrt(np.diag(np.linalg.inv(fisher))[2:4])


def isolated_half_size(approx, half_size: int, *, width: float, contrast: float = 1e-3) -> int:
    """The largest half-size up to ``half_size`` whose windows keep every other star's light out.

    Fourier resampling takes a window for one period of a band-limited image,
    so its edges must be at background: a neighbour's light cut by the edge
    neither leaves through it nor wraps around as a shift of the star would
    have it, and pulls every displacement measured in that window (and every
    tie between stars) towards the window's frame. A star of Gaussian width
    ``width`` (pixel) is below ``contrast`` of its peak beyond
    width sqrt(2 ln(1 / contrast)); the window on the pixel nearest each star
    (``approx``: (row, col) of every star) keeps its pixel centres that far
    from every other star, for any sub-pixel phase of the stars (they move
    together with the stage). The contrast is relative to the neighbour's own
    peak (stars of very different fluxes need a smaller one).
    """
    clearance = width * np.sqrt(2 * np.log(1 / contrast))
    xy = np.array([(c, r) for r, c in approx], dtype=float)
    half = half_size
    for s in range(len(xy)):
        for k in range(len(xy)):
            # windows sit on the pixel nearest the star, up to 0.5 pixel off it along each axis
            # whatever the position: the worst case
            distance = np.abs(xy[k] - xy[s]) - 0.5
            while k != s and half > 0 and np.hypot(*np.clip(distance - half, 0, None)) < clearance:
                half -= 1
    return half


def _frequencies(shape):
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.fftfreq(shape[1])[None, :]
    return fx, fy


def _fft2(images):
    return np.fft.fft2(images, axes=(-2, -1))


def _ifft2(spectra):
    return np.fft.ifft2(spectra, axes=(-2, -1))


def _per_item(t):
    """(k, 2) shifts as two (k, 1, 1) arrays, to broadcast against (k, rows, cols) spectra."""
    return t[:, 0, None, None], t[:, 1, None, None]


def fourier_displacement(reference: np.ndarray, image: np.ndarray, *, weights=None, tolerance: float = 1e-12,
                         max_iterations: int = 50) -> np.ndarray:
    """Displacement (dx, dy) of ``image`` relative to ``reference``, pixel, by Fourier resampling.

    The t that minimises sum |image - reference shifted by t|^2, the shift
    made by the phase ramp exp(-2 pi i t.f) in the Fourier domain (the
    paper's equation, with the roles named: ``image`` = PSF_1,
    ``reference`` = PSF_2). A scale and a background between the two are
    free (distinct stars differ in flux), which leaves the unweighted
    solution unchanged. Both windows have the same odd side, so that the
    phase ramp keeps a real image real; positions within the windows are
    compared, so add the difference of the windows' origins for detector
    coordinates.

    ``weights`` (1 / sigma of each pixel of ``image``) make it the weighted
    least-squares estimate, which reaches the Cramer-Rao bound under photon
    noise (the unweighted one is about 1.3x above it for a bright star);
    solved by Gauss-Newton on (t, scale, background) from the unweighted t.
    One pair of windows of :func:`fourier_displacements`.

    Raises
    ------
    ValueError
        Windows of different or even sizes; no convergence.
    """
    reference, image = np.asarray(reference, float), np.asarray(image, float)
    if reference.shape != image.shape:
        raise ValueError(f"windows of different shapes {reference.shape} and {image.shape}")
    return fourier_displacements(reference[None], image[None], weights=None if weights is None else
                                 np.asarray(weights, float)[None], tolerance=tolerance,
                                 max_iterations=max_iterations)[0]


def fourier_displacements(references: np.ndarray, images: np.ndarray, *, weights=None, tolerance: float = 1e-12,
                          max_iterations: int = 50) -> np.ndarray:
    """Displacements (k, 2) of ``images`` relative to ``references`` (both (k, size, size)), pixel: each pair's
    :func:`fourier_displacement`, solved together (the same iterations, each pair stopping at its own
    convergence), which spares the Python overhead of k small FFTs and solves. ``weights``: (k, size, size)."""
    references, images = np.asarray(references, float), np.asarray(images, float)
    if references.shape != images.shape:
        raise ValueError(f"windows of different shapes {references.shape[1:]} and {images.shape[1:]}")
    if references.shape[-2] % 2 == 0 or references.shape[-1] % 2 == 0:
        raise ValueError(f"windows must have odd sides for a real resampling, got {references.shape[1:]}")
    rows, cols = images.shape[-2:]
    cross = np.conj(_fft2(images)) * _fft2(references)
    fx, fy = _frequencies((rows, cols))
    # start from the best integer shift of the circular cross-correlation
    correlation = _ifft2(np.conj(cross)).real.reshape(len(images), -1)
    iy, ix = np.unravel_index(np.argmax(correlation, axis=1), (rows, cols))
    t = np.column_stack([np.where(ix <= cols // 2, ix, ix - cols), np.where(iy <= rows // 2, iy, iy - rows)])
    t = t.astype(float)
    wx, wy = 2 * np.pi * fx, 2 * np.pi * fy
    active = np.ones(len(images), bool)
    for _ in range(max_iterations):
        # C(t) = Re sum conj(F_image) F_reference exp(-i w.t); maximise it
        tx, ty = _per_item(t[active])
        term = cross[active] * np.exp(-1j * (wx * tx + wy * ty))
        gradient = np.stack([(-1j * wx * term).real.sum(axis=(1, 2)), (-1j * wy * term).real.sum(axis=(1, 2))], -1)
        hxy = (wx * wy * term).real.sum(axis=(1, 2))
        hessian = -np.stack([np.stack([(wx * wx * term).real.sum(axis=(1, 2)), hxy], -1),
                             np.stack([hxy, (wy * wy * term).real.sum(axis=(1, 2))], -1)], -2)
        with np.errstate(all="ignore"):
            step = -_solve_or_nan(hessian, gradient)
        if not np.all(np.isfinite(step)):
            raise ValueError("Fourier resampling: singular curvature (flat windows?)")
        step = np.clip(step, -0.5, 0.5)  # stay in the basin of the integer start
        t[active] += step
        active[np.flatnonzero(active)[np.max(np.abs(step), axis=1) < tolerance]] = False
        if not active.any():
            return t if weights is None else _weighted_displacements(references, images, np.asarray(weights, float),
                                                                     t, tolerance, max_iterations)
    raise ValueError(f"Fourier resampling did not converge in {max_iterations} iterations")


def _solve_or_nan(matrices, vectors):
    """Each matrices[i]^-1 vectors[i]; NaN for a singular matrix (a flat window), for the caller's message."""
    out = np.full(vectors.shape, np.nan)
    regular = np.abs(np.linalg.det(matrices)) > 0
    if regular.any():
        out[regular] = np.linalg.solve(matrices[regular], vectors[regular][..., None])[..., 0]
    return out


def _least_squares_steps(design, rhs):
    """Each item's least-squares solution of design[i] x = rhs[i] ((k, n, p), (k, n)), by QR."""
    q, r = np.linalg.qr(design)
    return np.linalg.solve(r, np.einsum("knp,kn->kp", q, rhs)[..., None])[..., 0]


def _shifted(spectra, wx, wy, t):
    """The images of ``spectra`` (k, rows, cols) shifted by t (k, 2), and their derivatives along t_x and t_y:
    (3, k, rows, cols)."""
    tx, ty = _per_item(t)
    ramp = spectra * np.exp(-1j * (wx * tx + wy * ty))
    return _ifft2(np.stack([ramp, -1j * wx * ramp, -1j * wy * ramp])).real


def _weighted_displacements(references, images, weights, t, tolerance, max_iterations):
    spectra = _fft2(references)
    fx, fy = _frequencies(images.shape[-2:])
    wx, wy = 2 * np.pi * fx, 2 * np.pi * fy
    k = len(images)
    w = weights.reshape(k, -1)
    data = images.reshape(k, -1)
    ones = np.ones_like(data)
    shifted = _shifted(spectra, wx, wy, t)[0].reshape(k, -1)
    design = np.stack([shifted, ones], -1)
    scale_background = _least_squares_steps(design * w[..., None], data * w)
    params = np.column_stack([t, scale_background])
    active = np.ones(k, bool)
    for _ in range(max_iterations):
        p, wa, da = params[active], w[active], data[active]
        shifted, d_x, d_y = (a.reshape(len(p), -1) for a in _shifted(spectra[active], wx, wy, p[:, :2]))
        model = p[:, 2, None] * shifted + p[:, 3, None]
        jac = np.stack([p[:, 2, None] * d_x, p[:, 2, None] * d_y, shifted, ones[active]], -1)
        step = _least_squares_steps(jac * wa[..., None], (da - model) * wa)
        params[active] = p + step
        active[np.flatnonzero(active)[np.max(np.abs(step[:, :2]), axis=1) < tolerance]] = False
        if not active.any():
            return params[:, :2]
    raise ValueError(f"weighted Fourier resampling did not converge in {max_iterations} iterations")


def _fourier_derivatives(images):
    """First and second derivatives (x, y, xx, xy, yy) of the band-limited interpolant at the pixels: (5, ...)
    for images (..., rows, cols)."""
    spectrum = _fft2(images)
    fx, fy = _frequencies(images.shape[-2:])
    wx, wy = 2j * np.pi * fx, 2j * np.pi * fy
    return _ifft2(np.stack([spectrum * factor for factor in (wx, wy, wx * wx, wx * wy, wy * wy)])).real


def offset_corrected(image: np.ndarray, dx: np.ndarray, dy: np.ndarray, *, iterations: int = 4) -> np.ndarray:
    """The window as perfect pixels would have recorded it, given the pixels' offsets.

    Pixel p of true centre r_p + delta_p records P(r_p + delta_p), where P is
    the (band-limited) image on the perfect grid; this returns P(r_p) by
    fixed-point iteration, P <- image - [P(r + delta) - P(r)], with
    P(r + delta) to second order in delta from FFT derivatives (delta of
    1e-3 pixel leaves a third-order error of about 1e-10 of the peak).

    Parameters
    ----------
    image : ndarray (..., size, size)
        Dark-subtracted, flat-corrected window (odd side), adu; or several (leading axes), corrected together.
    dx, dy : ndarray (..., size, size)
        The window's pixel offsets, pixel (from the metrology's deprojection); broadcast against ``image``.
    """
    return _recorded_corrected(image, dx, dy, None, None, iterations)


def _recorded_corrected(image, dx, dy, variance_x, variance_y, iterations):
    """:func:`offset_corrected` (variances None) or :func:`response_corrected`."""
    image = np.asarray(image, float)
    dx, dy = np.nan_to_num(np.asarray(dx, float)), np.nan_to_num(np.asarray(dy, float))
    if variance_x is not None:
        vx, vy = np.nan_to_num(np.asarray(variance_x, float)), np.nan_to_num(np.asarray(variance_y, float))
    corrected = image.copy()
    for _ in range(iterations):
        px, py, pxx, pxy, pyy = _fourier_derivatives(corrected)
        recorded_minus_grid = dx * px + dy * py + 0.5 * (dx * dx * pxx + 2 * dx * dy * pxy + dy * dy * pyy)
        if variance_x is not None:
            recorded_minus_grid = recorded_minus_grid + 0.5 * (vx * pxx + vy * pyy)
        corrected = image - recorded_minus_grid
    return corrected


def response_corrected(image: np.ndarray, dx: np.ndarray, dy: np.ndarray, variance_x: np.ndarray,
                       variance_y: np.ndarray, *, iterations: int = 4) -> np.ndarray:
    """The window as identical pixels, on the perfect grid, would have recorded it: offsets and PRF widths.

    Pixel p integrates the image against its PRF. With the mean PRF's image
    P (the band-limited interpolant of the window, on the perfect grid), a
    pixel whose symmetric PRF has the variance of the mean kernel's plus
    (vx_p, vy_p) along x and y, centred at r_p + delta_p, records

        P(r_p + delta_p) + (vx_p / 2) P_xx(r_p) + (vy_p / 2) P_yy(r_p)

    to second order in the offsets and first order in the variances (the
    characteristic function's k^2 term; the next terms, of order k^4 m4 and
    vx vy, are about 2% of it for a 1.3-pixel PSF; docs/centroids.md). P is
    found by fixed-point iteration, as in :func:`offset_corrected`.

    Parameters
    ----------
    image : ndarray (..., size, size)
        Dark-subtracted, flat-corrected window (odd side), adu; or several (leading axes), corrected together.
    dx, dy : ndarray (..., size, size)
        The window's pixel offsets, pixel.
    variance_x, variance_y : ndarray (..., size, size)
        Each pixel's PRF variance minus the mean kernel's, pixel^2 (``width^2 - mean_width^2``).
    """
    return _recorded_corrected(image, dx, dy, variance_x, variance_y, iterations)


@dataclass(frozen=True)
class Mode:
    """A calibration mode: the calibrations it corrects a star window with, a subset of ``flat`` (the
    reference PRNU), ``offsets`` (a pair's pixel offsets), ``widths`` (the PRF width maps) and ``chromatic``
    (every wavelength's, evaluated for the stars' spectrum: :func:`dice_core.chromatic.star_calibration`), and
    what that means, in words. Dark subtraction is always on."""

    needs: frozenset
    description: str


#: Every calibration mode by name: the one list the configuration's choices, the workflow's products and
#: their docs are derived from. A mode that adds a calibration appends it with ``+``.
MODES = {
    "raw": Mode(frozenset(), "dark subtracted only"),
    "flat": Mode(frozenset({"flat"}), "divided by the reference PRNU (calibration/prnu.nc)"),
    "metrology": Mode(frozenset({"offsets"}), "resampled for the pixel offsets of the centroid pair "
                                              "(calibration/offsets_<pair>.nc)"),
    "flat+metrology": Mode(frozenset({"flat", "offsets"}), "both: the paper's calibrated mode"),
    "flat+metrology+width": Mode(frozenset({"flat", "offsets", "widths"}),
                                 "both, and each pixel's PRF width (calibration/prf.nc): beyond the paper"),
    "flat+metrology+chromatic": Mode(frozenset({"flat", "offsets", "chromatic"}),
                                     "both as the stars' spectrum sees them, and the PRF widths' change from the "
                                     "reference pair's wavelength, from every wavelength's calibration "
                                     "(calibration/chromatic.nc; datasets of several wavelengths)"),
}

#: Every centroid method by name, with what it does (:func:`measure_positions`).
METHODS = {
    "fourier": "each window resampled against the star's window at the first position (Fourier shift), tied to "
               "the central star's Gaussian fit",
    "gaussian": "a 7-parameter elliptical Gaussian fitted to each window",
}


def mode_descriptions() -> dict[str, str]:
    """{mode: what it corrects}, for documentation."""
    return {name: mode.description for name, mode in MODES.items()}


def method_descriptions() -> dict[str, str]:
    """{method: what it does}, for documentation."""
    return dict(METHODS)


def mode_needs(mode: str) -> frozenset:
    """The calibrations a mode uses: a subset of {"flat", "offsets", "widths", "chromatic"} (:data:`MODES`)."""
    if mode not in MODES:
        raise ValueError(f"unknown calibration mode {mode!r}; modes are {', '.join(MODES)}")
    return MODES[mode].needs


def mode_corrections(mode: str) -> tuple[bool, bool]:
    """(flat, metrology) corrections of a calibration mode (dark subtraction is always on); see :func:`mode_needs`."""
    needs = mode_needs(mode)
    return "flat" in needs, "offsets" in needs


@dataclass
class PositionCentroids:
    """Centroids of every star at every position (arrays (position, star)), pixel; see :func:`measure_positions`."""

    x: np.ndarray
    y: np.ndarray
    precision_x: np.ndarray
    precision_y: np.ndarray
    limit_x: np.ndarray
    limit_y: np.ndarray
    n_frames: np.ndarray
    n_saturated: np.ndarray
    windows: np.ndarray  # (star, size, size): the corrected mean windows of the first position, adu
    n_bad_pixels: np.ndarray = None  # (position, star): bad pixels of the mask in the star's window


def _noise_variance(image, n_frames, gain, read_noise):
    """Variance (adu^2) of each pixel of a mean of ``n_frames`` frames: photon noise of ``image`` (adu, at
    ``gain`` e-/adu) plus ``read_noise`` (adu)."""
    return (np.clip(image, 0, None) / gain + read_noise**2) / n_frames


def _noise_weights(images, windows, flags, n_frames, gain, read_noise, *, where):
    """1 / sigma (1/adu) of each pixel of the stars' mean windows of ``n_frames`` frames, 0 at a flagged pixel.

    Raises
    ------
    WindowError
        An unflagged pixel of zero (or not finite) noise: no signal above the dark and no read noise, whose
        weight would be 1/0; said before any division.
    """
    weights = []
    for s, (image, w) in enumerate(zip(images, windows)):
        variance = _noise_variance(image, n_frames, gain, read_noise[w.slices])
        usable = flags[w.slices] == 0
        if not np.all(variance[usable] > 0):  # NaN included
            r, c = np.argwhere(usable & ~(variance > 0))[0]
            raise WindowError(f"star {s} at {where}: pixel row {w.row0 + r}, col {w.col0 + c} has zero noise "
                              "(no signal above the dark and no read noise, e.g. zero in every frame and in the "
                              "dark): flag it in the bad-pixel mask or check the data")
        weight = np.zeros(variance.shape)
        np.divide(1.0, np.sqrt(variance, where=usable, out=np.ones(variance.shape)), out=weight, where=usable)
        weights.append(weight)
    return weights


def _pixel_list(window, bad, flags):
    """'row r, col c (dead, column)' for the bad pixels of a window, for messages."""
    from dice_core.calibration import BAD_PIXEL_FLAGS

    rows, cols = np.nonzero(bad)
    items = []
    for r, c in zip(rows, cols):
        kinds = [kind for kind, bit in BAD_PIXEL_FLAGS.items() if flags[r, c] & bit]
        items.append(f"row {window.row0 + r}, col {window.col0 + c} ({', '.join(kinds) or 'flagged'})")
    return "; ".join(items[:4]) + ("; ..." if len(items) > 4 else "")


def _position_stack(stacks, position, i, n_pos, label):
    """The next stack of the iterator ``stacks``, checked to be ``position``'s, of two batches or more."""
    where = f"position {position}"
    stack = next(stacks, None)
    if stack is None:
        raise ValueError(f"{label}: no frames given for {where} ({i} stack(s) for {n_pos} positions)")
    if stack.position is not None and stack.position != position:
        raise ValueError(f"{label}: the stack given for {where} is that of position {stack.position}")
    if stack.n_batches < 2:
        raise ValueError(f"{label}: {where} has {stack.n_batches} batch; a precision needs two at least")
    return stack


def _isolated_windows_half_size(mean, dark, centres, flags, half_size, detector, *, where, label, log):
    """The half-size whose windows hold one star's light, from the widest Gaussian fit at the first position."""
    windows = [star_window(r, c, half_size=half_size, shape=detector.shape, label=f"star {s} at {where}",
                           area=(detector.science_rows, detector.science_cols)) for s, (r, c) in enumerate(centres)]
    fits = gaussian_fits(np.array([mean[w.slices] - dark[w.slices] for w in windows]), windows,
                         weights=np.array([(flags[w.slices] == 0).astype(float) for w in windows]),
                         labels=[f"star {s} at {where}" for s in range(len(windows))])
    width = max(max(f.width_x, f.width_y) for f in fits)
    isolated = isolated_half_size(centres, half_size, width=width)
    size = 2 * half_size + 1
    if isolated < 2:
        raise WindowError(f"{label}: at {where} the stars are too close for windows holding one star's light "
                          f"alone (PSF width {width:.2f} pixel; 5x5 windows at least)")
    if isolated < half_size and log is not None:
        log.warning("%s: %dx%d windows would hold other stars' light (PSF width %.2f pixel): %dx%d windows",
                    label, size, size, width, 2 * isolated + 1, 2 * isolated + 1)
    return isolated


@dataclass
class _Calibrations:
    """What a mode corrects a window with (maps (row, col) or None) and the unusable pixels' flags."""

    dark: np.ndarray
    flags: np.ndarray
    prnu: np.ndarray = None
    dx: np.ndarray = None
    dy: np.ndarray = None
    variance_x: np.ndarray = None
    variance_y: np.ndarray = None

    def corrected(self, frames, windows, *, where):
        """The windows (frame, star, size, size) of ``frames`` (frame, row, col) minus the dark, divided by the
        flat, corrected for offsets (and widths): every star's window of every frame at once."""
        rows = np.array([np.arange(w.row0, w.row0 + w.size) for w in windows])[:, :, None]
        cols = np.array([np.arange(w.col0, w.col0 + w.size) for w in windows])[:, None, :]
        image = np.asarray(frames)[:, rows, cols] - self.dark[rows, cols]
        bad = self.flags[rows, cols] != 0
        if self.prnu is not None:
            with np.errstate(divide="ignore", invalid="ignore"):  # a dead pixel's PRNU is about 0
                image = image / self.prnu[rows, cols]
        if bad.any():  # left out (weight 0) or the star refused: a placeholder, never used
            image = np.where(bad, 0.0, image)
        if self.variance_x is not None:
            image = response_corrected(image, self.dx[rows, cols], self.dy[rows, cols], self.variance_x[rows, cols],
                                       self.variance_y[rows, cols])
        elif self.dx is not None:
            image = offset_corrected(image, self.dx[rows, cols], self.dy[rows, cols])
        unfinished = ~np.isfinite(image).all(axis=(2, 3))
        if unfinished.any():
            star = np.argwhere(unfinished)[0][1]
            raise WindowError(f"star {star} at {where}: its window reaches pixels without calibration "
                              "(outside the science area)")
        return image


def _unreferenced_stars(windows, flags, n_bad, central, *, where, label, log):
    """Fourier method, first position: the stars whose reference window holds a bad pixel (an error for the
    central star, which ties all the others)."""
    out = set()
    for s in np.flatnonzero(n_bad):
        listed = _pixel_list(windows[s], flags[windows[s].slices] != 0, flags[windows[s].slices])
        if s == central:
            raise WindowError(f"star {s} at {where}: its window, the reference every star is tied to, holds "
                              f"bad pixel(s) {listed}; the fourier method cannot leave pixels out (the "
                              "gaussian method without metrology can)")
        out.add(int(s))
        if log is not None:
            log.warning("%s: star %d at %s: its reference window holds bad pixel(s) %s; the fourier method "
                        "cannot leave pixels out: the star is not measured at any position", label, s,
                        where, listed)
    return out


class _Locator:
    """Positions in detector coordinates by Fourier resampling against each star's first window, tied to the
    central star's, whose Gaussian fit anchors them all (``method`` "gaussian": the fits' own, no ties)."""

    def __init__(self, method, windows, images, noise, central, no_reference):
        self.method = method
        self.references = list(zip(windows, images))
        self.anchor = gaussian_fit(images[central], windows[central], weights=noise[central],
                                   label=f"star {central} (central) at the first position")
        # each star's reference tied to the central one's, by the method itself, with the weights
        # its reference is measured with later: that window's noise then cancels between tie and shift
        self.ties = [np.zeros(2) if s == central or method == "gaussian" or s in no_reference else
                     fourier_displacement(images[central], images[s], weights=noise[s]) + np.array(
                         [windows[s].col0 - windows[central].col0, windows[s].row0 - windows[central].row0])
                     for s in range(len(windows))]

    def __call__(self, images, windows, stars, weights):
        """Fourier method: positions (k, 2) of the star ``stars[i]`` in ``images[i]`` (window ``windows[i]``,
        weights ``weights[i]``), all located together. (The Gaussian method's positions are its fits'.)"""
        shifts = fourier_displacements(np.array([self.references[s][1] for s in stars]), images, weights=weights)
        origins = np.array([[w.col0 - self.references[s][0].col0, w.row0 - self.references[s][0].row0]
                            for w, s in zip(windows, stars)])
        ties = np.array([self.ties[s] for s in stars])
        return np.array([self.anchor.x, self.anchor.y]) + ties + shifts + origins


def _measure_stars(locate, measured, windows, images, batch_images, noise, *, where, n, detector, read_noise,
                   flags):
    """The ``measured`` stars' centroids at one position (x, y), their precision from the batches (px, py) and
    their Cramer-Rao bound (lx, ly): {name: (star,)}. The mean's and every batch's windows located together
    (one call: the small fits' Python overhead shared)."""
    n_batches, m = len(batch_images), len(measured)
    stars = measured * (1 + n_batches)  # the mean's windows, then each batch's (batch-major)
    every_image = np.concatenate([images[measured], batch_images[:, measured].reshape(-1, *images.shape[1:])])
    every_weight = np.array([noise[s] for s in measured] + [noise[s] / np.sqrt(n_batches) for s in stars[m:]])
    every_window = [windows[s] for s in stars]
    labels = [f"star {s} at {where}" + (f", batch {i // m - 1}" if i >= m else "") for i, s in enumerate(stars)]
    if locate.method == "gaussian":  # the bound's fit is the position's
        fits = gaussian_fits(every_image, every_window, weights=every_weight, labels=labels)
        every_xy = np.array([[fit.x, fit.y] for fit in fits])
    else:
        fits = gaussian_fits(every_image[:m], every_window[:m], weights=every_weight[:m], labels=labels[:m])
        every_xy = locate(every_image, every_window, stars, every_weight)
    xy, batch_xy = every_xy[:m], every_xy[m:].reshape(n_batches, m, 2)
    limits = np.array([cramer_rao(fit, windows[s], gain=detector.gain * n,
                                  read_noise=read_noise[windows[s].slices] / np.sqrt(n),
                                  used=flags[windows[s].slices] == 0) for s, fit in zip(measured, fits)])
    precision = batch_xy.std(axis=0, ddof=1) / np.sqrt(n_batches)
    return {"x": xy[:, 0], "y": xy[:, 1], "px": precision[:, 0], "py": precision[:, 1], "lx": limits[:, 0],
            "ly": limits[:, 1]}


def measure_positions(stacks, positions, *, approx, detector, dark, read_noise, prnu=None, dx=None, dy=None,
                      bad_pixels=None, method: str = "fourier", half_size: int = 7, label: str = "stars",
                      log=None, variance_x=None, variance_y=None) -> PositionCentroids:
    """Centroids of the stars at every detector position, with their precision and photon-noise limit.

    Parameters
    ----------
    stacks : iterable of dice_core.stacks.PositionStack
        Each position's mean and batch-mean frames (:func:`dice_core.stacks.stack_position`),
        in the order of ``positions``; consumed one at a time, so that a
        generator reading them from their products keeps one in memory.
    positions : sequence
        Position labels (indices), in acquisition order.
    approx : sequence of (row, col)
        Approximate star positions at the first position; fix the star order.
        Each later position's windows are centred on the previous position's
        centroids, so that they follow the stage.
    detector : Detector
        Shape and gain (e-/adu).
    dark, read_noise : ndarray (row, col)
        Mean dark and read noise, adu.
    prnu : ndarray (row, col), optional
        Flat-field correction (windows divided by it).
    dx, dy : ndarray (row, col), optional
        Pixel offsets for the offset correction (:func:`offset_corrected`).
    variance_x, variance_y : ndarray (row, col), optional
        Each pixel's PRF variance along x and y minus the mean kernel's,
        pixel^2 (from ``calibration/prf.nc``: width^2 - mean_width^2); with
        the offsets, the correction is :func:`response_corrected` (requires dx, dy).
    bad_pixels : int ndarray (row, col), optional
        The bad-pixel mask's flags (``bad_pixel`` of ``calibration/bad_pixels.nc``);
        its unusable pixels (dead, hot, column: :data:`dice_core.calibration.UNUSABLE`)
        are the bad ones, dust pixels being the flat's to correct. A Gaussian
        fit without the offset correction leaves a window's bad pixels out
        (weight 0, and out of the Cramer-Rao bound). The Fourier method and the
        offset correction resample the whole window, which one bad value
        spoils: a star with a bad pixel in its window is then not measured at
        that position (NaN, logged with the star and the pixels). With the
        Fourier method, a bad pixel in a star's window at the first position,
        its reference, leaves that star unmeasured at every position (logged);
        in the central star's, which ties the others, it is an error naming
        the pixels.
    method : {"fourier", "gaussian"}
        Fourier resampling against each star's window at the first position,
        tied to the central star's Gaussian fit there (stars tied to one
        another by Fourier resampling too); or a Gaussian fit per star.
        Both weight pixels by their photon and read noise.
    half_size : int
        Windows are 2 half_size + 1 pixels square, or smaller where other
        stars' light would reach them (:func:`isolated_half_size`, with the
        widest Gaussian fit at the first position; logged).

    Returns
    -------
    PositionCentroids
        x, y: centroids of the mean of all frames; precision_x, precision_y:
        the standard deviation of the stacks' batch centroids over
        sqrt(batches), the standard error of x and y; limit_x, limit_y: the Cramer-Rao bound
        of the mean of all frames. A star with a saturated sample in its
        window at a position is NaN there (logged).

    Raises
    ------
    WindowError
        A science area smaller than a window; a star's window leaves the
        science area or the calibrated area, or holds no signal; stars too
        close for 5x5 windows holding one star's light.
    ValueError
        Unknown method; fewer stacks than positions, a stack of another
        position, or a stack of one batch;
        with the Fourier method, a saturated star at the first position (its
        window is every later one's reference).
    """
    if method not in METHODS:
        raise ValueError(f"unknown centroid method {method!r}; methods are {', '.join(METHODS)}")
    if (variance_x is None) != (variance_y is None) or (variance_x is not None and dx is None):
        raise ValueError("the PRF width correction needs both variance maps and the pixel offsets")
    if (problem := science_area_problem(detector, half_size)) is not None:
        raise WindowError(problem)
    n_pos, n_star = len(positions), len(approx)
    out = {name: np.full((n_pos, n_star), np.nan) for name in ("x", "y", "px", "py", "lx", "ly")}
    n_saturated = np.zeros((n_pos, n_star), dtype=np.int64)
    n_bad = np.zeros((n_pos, n_star), dtype=np.int64)
    from dice_core.calibration import unusable_pixels

    flags = np.zeros(detector.shape, np.int64)
    if bad_pixels is not None:
        flags = np.where(unusable_pixels(bad_pixels), np.asarray(bad_pixels).astype(np.int64), 0)
    calibrations = _Calibrations(dark, flags, prnu, dx, dy, variance_x, variance_y)
    leave_out = method == "gaussian" and dx is None  # else a bad value is resampled over the window
    no_reference = set()  # stars whose reference window (Fourier, first position) holds a bad pixel
    n_frames = np.zeros(n_pos, dtype=np.int64)
    centres = [(float(r), float(c)) for r, c in approx]
    locate, first_windows = None, None
    central = int(np.argmin([np.hypot(r - np.mean([a[0] for a in approx]), c - np.mean([a[1] for a in approx]))
                             for r, c in approx]))
    stacks = iter(stacks)
    for i, position in enumerate(positions):
        where = f"position {position}"
        stack = _position_stack(stacks, position, i, n_pos, label)
        n = stack.n_frames
        mean, batch_means, saturated = stack.mean, stack.batch_means, stack.n_saturated
        n_frames[i] = n
        if locate is None:
            half_size = _isolated_windows_half_size(mean, dark, centres, flags, half_size, detector,
                                                    where=where, label=label, log=log)
        windows = [star_window(r, c, half_size=half_size, shape=detector.shape, label=f"star {s} at {where}",
                               area=(detector.science_rows, detector.science_cols))
                   for s, (r, c) in enumerate(centres)]
        corrected = calibrations.corrected(np.concatenate([mean[None], batch_means]), windows, where=where)
        images, batch_images = corrected[0], corrected[1:]
        noise = _noise_weights(images, windows, flags, n, detector.gain, read_noise, where=where)
        for s, w in enumerate(windows):
            n_bad[i, s] = int(np.count_nonzero(flags[w.slices]))
        if locate is None:
            if method == "fourier" and n_bad[i].any():
                no_reference = _unreferenced_stars(windows, flags, n_bad[i], central, where=where, label=label,
                                                   log=log)
            if method == "fourier" and any(saturated[w.slices].any() for w in windows):
                s = next(s for s, w in enumerate(windows) if saturated[w.slices].any())
                raise ValueError(f"star {s} at {where}: saturated samples in the window every later position "
                                 "is resampled against; the fourier method needs an unsaturated first position")
            first_windows = np.array(images)
            locate = _Locator(method, windows, images, noise, central, no_reference)

        measured = []
        for s, window in enumerate(windows):
            n_saturated[i, s] = int(saturated[window.slices].sum())
            if s in no_reference:
                continue
            if n_bad[i, s] and not leave_out:
                if log is not None:
                    log.warning("%s: star %d at %s has bad pixel(s) in its window, %s: not measured", label, s,
                                where, _pixel_list(window, flags[window.slices] != 0, flags[window.slices]))
                continue
            if n_bad[i, s] and log is not None:
                log.info("%s: star %d at %s: bad pixel(s) left out of its window, %s", label, s, where,
                         _pixel_list(window, flags[window.slices] != 0, flags[window.slices]))
            if n_saturated[i, s]:
                if log is not None:
                    log.warning("%s: star %d at %s has %d saturated sample(s) in its window: not measured",
                                label, s, where, n_saturated[i, s])
                continue
            measured.append(s)
        if measured:
            found = _measure_stars(locate, measured, windows, images, batch_images, noise, where=where, n=n,
                                   detector=detector, read_noise=read_noise, flags=flags)
            for name, values in found.items():
                out[name][i, measured] = values
            for s in measured:
                centres[s] = (out["y"][i, s], out["x"][i, s])
        if log is not None:
            log.info("%s: %s, %d frames: central star at x %.4f, y %.4f pixel", label, where, n,
                     out["x"][i, central], out["y"][i, central])
    return PositionCentroids(out["x"], out["y"], out["px"], out["py"], out["lx"], out["ly"], n_frames, n_saturated,
                             first_windows, n_bad)

def centroids_dataset(result: PositionCentroids, positions, *, mode: str, method: str):
    """The ``centroids/<mode>.nc`` product: x, y (position, star) and their error budget, pixel."""
    dims = ("position", "star")
    n_star = result.x.shape[1]
    size = result.windows.shape[-1]
    return xr.Dataset(
        {
            "x": (dims, result.x, {"units": "pixel", "long_name": "star centroid along x (columns)"}),
            "y": (dims, result.y, {"units": "pixel", "long_name": "star centroid along y (rows)"}),
            "precision_x": (dims, result.precision_x, {"units": "pixel", "long_name": "standard error of x from "
                                                       "the scatter of the position's batches"}),
            "precision_y": (dims, result.precision_y, {"units": "pixel", "long_name": "standard error of y from "
                                                       "the scatter of the position's batches"}),
            "photon_limit_x": (dims, result.limit_x, {"units": "pixel", "long_name": "Cramer-Rao bound of x"}),
            "photon_limit_y": (dims, result.limit_y, {"units": "pixel", "long_name": "Cramer-Rao bound of y"}),
            "n_frames": (("position",), result.n_frames, {"units": "1", "long_name": "frames averaged"}),
            "n_saturated": (dims, result.n_saturated, {"units": "1", "long_name": "saturated samples in the "
                                                       "star's window (the star is not measured)"}),
            **({} if result.n_bad_pixels is None else {
                "n_bad_pixels": (dims, result.n_bad_pixels,
                                 {"units": "1", "long_name": "bad pixels of the mask in the star's window (left "
                                                             "out by a Gaussian fit, else the star not measured)"})}),
            "window": (("star", "window_row", "window_col"), result.windows,
                       {"units": "adu", "long_name": "corrected mean window of each star at the first position"}),
        },
        coords={"position": np.asarray(positions), "star": np.arange(n_star),
                "window_row": np.arange(size), "window_col": np.arange(size)},
        attrs={"mode": mode, "method": method},
    )
