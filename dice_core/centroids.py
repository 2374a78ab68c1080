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
import xarray as xr
from scipy.optimize import least_squares

__all__ = [
    "WindowError",
    "Window",
    "star_window",
    "science_area_problem",
    "GaussianFit",
    "gaussian_fit",
    "cramer_rao",
    "isolated_half_size",
    "fourier_displacement",
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
    """Model values (pixel,) and their derivatives (pixel, 7) at pixel centres xs, ys."""
    b, amp, x, y, a, bb, c = p
    u, v = xs - x, ys - y
    e = np.exp(-0.5 * (a * u * u + 2 * bb * u * v + c * v * v))
    ae = amp * e
    jacobian = np.column_stack([np.ones_like(e), e, ae * (a * u + bb * v), ae * (bb * u + c * v),
                                -0.5 * ae * u * u, -ae * u * v, -0.5 * ae * v * v])
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
    xg, yg = window.grid()
    xs, ys, data = xg.ravel(), yg.ravel(), np.asarray(image, dtype=float).ravel()
    w = np.ones_like(data) if weights is None else np.asarray(weights, dtype=float).ravel()
    # start: background from the border, position and shape from the second moments
    border = np.concatenate([image[0], image[-1], image[1:-1, 0], image[1:-1, -1]])
    b0 = float(np.median(border))
    signal = np.clip(data - b0, 0, None) * (w > 0)  # pixels of weight 0 (left out) do not start it either
    total = signal.sum()
    if not total > 0:
        raise WindowError(f"{label}: no signal above the background in its window (rows {window.row0}-"
                          f"{window.row0 + window.size - 1}, cols {window.col0}-{window.col0 + window.size - 1})")
    x0, y0 = (signal * xs).sum() / total, (signal * ys).sum() / total
    cxx = (signal * (xs - x0) ** 2).sum() / total
    cyy = (signal * (ys - y0) ** 2).sum() / total
    cxy = (signal * (xs - x0) * (ys - y0)).sum() / total
    inverse = np.linalg.inv(np.array([[cxx, cxy], [cxy, cyy]]))
    start = np.array([b0, signal.max(), x0, y0, inverse[0, 0], inverse[0, 1], inverse[1, 1]])

    def residual(p):
        return w * (_gaussian_model(p, xs, ys)[0] - data)

    def jacobian(p):
        return w[:, None] * _gaussian_model(p, xs, ys)[1]

    result = least_squares(residual, start, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                           max_nfev=2000)
    b, amp, x, y, a, bb, c = result.x
    covariance = np.linalg.inv(np.array([[a, bb], [bb, c]]))
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    angle = float(np.arctan2(eigenvectors[1, 1], eigenvectors[0, 1]))
    return GaussianFit(float(b), float(amp), float(x), float(y), float(np.sqrt(eigenvalues[1])),
                       float(np.sqrt(eigenvalues[0])), angle, float(2 * result.cost), result.x.copy())


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

    Raises
    ------
    ValueError
        Windows of different or even sizes; no convergence.
    """
    reference, image = np.asarray(reference, float), np.asarray(image, float)
    if reference.shape != image.shape:
        raise ValueError(f"windows of different shapes {reference.shape} and {image.shape}")
    if reference.shape[0] % 2 == 0 or reference.shape[1] % 2 == 0:
        raise ValueError(f"windows must have odd sides for a real resampling, got {reference.shape}")
    cross = np.conj(np.fft.fft2(image)) * np.fft.fft2(reference)
    fx, fy = _frequencies(image.shape)
    # start from the best integer shift of the circular cross-correlation
    correlation = np.fft.ifft2(np.conj(cross)).real
    iy, ix = np.unravel_index(np.argmax(correlation), correlation.shape)
    t = np.array([ix if ix <= image.shape[1] // 2 else ix - image.shape[1],
                  iy if iy <= image.shape[0] // 2 else iy - image.shape[0]], dtype=float)
    wx, wy = 2 * np.pi * fx, 2 * np.pi * fy
    for _ in range(max_iterations):
        # C(t) = Re sum conj(F_image) F_reference exp(-i w.t); maximise it
        term = cross * np.exp(-1j * (wx * t[0] + wy * t[1]))
        gradient = np.array([np.sum((-1j * wx * term).real), np.sum((-1j * wy * term).real)])
        hessian = -np.array([[np.sum((wx * wx * term).real), np.sum((wx * wy * term).real)],
                             [np.sum((wx * wy * term).real), np.sum((wy * wy * term).real)]])
        step = -np.linalg.solve(hessian, gradient)
        if not np.all(np.isfinite(step)):
            raise ValueError("Fourier resampling: singular curvature (flat windows?)")
        step = np.clip(step, -0.5, 0.5)  # stay in the basin of the integer start
        t = t + step
        if np.max(np.abs(step)) < tolerance:
            return t if weights is None else _weighted_displacement(reference, image, weights, t, tolerance,
                                                                    max_iterations)
    raise ValueError(f"Fourier resampling did not converge in {max_iterations} iterations")


def _shifted(spectrum, wx, wy, t):
    """The image of ``spectrum`` shifted by t, and its derivatives along t_x and t_y."""
    ramp = spectrum * np.exp(-1j * (wx * t[0] + wy * t[1]))
    return (np.fft.ifft2(ramp).real, np.fft.ifft2(-1j * wx * ramp).real, np.fft.ifft2(-1j * wy * ramp).real)


def _weighted_displacement(reference, image, weights, t, tolerance, max_iterations):
    spectrum = np.fft.fft2(reference)
    fx, fy = _frequencies(image.shape)
    wx, wy = 2 * np.pi * fx, 2 * np.pi * fy
    w = np.asarray(weights, float).ravel()
    data = image.ravel()
    shifted, _, _ = _shifted(spectrum, wx, wy, t)
    design = np.column_stack([shifted.ravel(), np.ones(data.size)])
    scale, background = np.linalg.lstsq(design * w[:, None], data * w, rcond=None)[0]
    params = np.array([t[0], t[1], scale, background])
    for _ in range(max_iterations):
        shifted, d_x, d_y = _shifted(spectrum, wx, wy, params[:2])
        model = params[2] * shifted + params[3]
        jac = np.column_stack([params[2] * d_x.ravel(), params[2] * d_y.ravel(), shifted.ravel(),
                               np.ones(data.size)])
        step = np.linalg.lstsq(jac * w[:, None], (data - model.ravel()) * w, rcond=None)[0]
        params = params + step
        if np.max(np.abs(step[:2])) < tolerance:
            return params[:2]
    raise ValueError(f"weighted Fourier resampling did not converge in {max_iterations} iterations")


def _fourier_derivatives(image):
    """First and second derivatives (x, y, xx, xy, yy) of the band-limited interpolant at the pixels."""
    spectrum = np.fft.fft2(image)
    fx, fy = _frequencies(image.shape)
    wx, wy = 2j * np.pi * fx, 2j * np.pi * fy
    return [np.fft.ifft2(spectrum * factor).real for factor in (wx, wy, wx * wx, wx * wy, wy * wy)]


def offset_corrected(image: np.ndarray, dx: np.ndarray, dy: np.ndarray, *, iterations: int = 4) -> np.ndarray:
    """The window as perfect pixels would have recorded it, given the pixels' offsets.

    Pixel p of true centre r_p + delta_p records P(r_p + delta_p), where P is
    the (band-limited) image on the perfect grid; this returns P(r_p) by
    fixed-point iteration, P <- image - [P(r + delta) - P(r)], with
    P(r + delta) to second order in delta from FFT derivatives (delta of
    1e-3 pixel leaves a third-order error of about 1e-10 of the peak).

    Parameters
    ----------
    image : ndarray (size, size)
        Dark-subtracted, flat-corrected window (odd side), adu.
    dx, dy : ndarray (size, size)
        The window's pixel offsets, pixel (from the metrology's deprojection).
    """
    image = np.asarray(image, float)
    dx, dy = np.nan_to_num(np.asarray(dx, float)), np.nan_to_num(np.asarray(dy, float))
    corrected = image.copy()
    for _ in range(iterations):
        px, py, pxx, pxy, pyy = _fourier_derivatives(corrected)
        shifted_minus_grid = dx * px + dy * py + 0.5 * (dx * dx * pxx + 2 * dx * dy * pxy + dy * dy * pyy)
        corrected = image - shifted_minus_grid
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
    image : ndarray (size, size)
        Dark-subtracted, flat-corrected window (odd side), adu.
    dx, dy : ndarray (size, size)
        The window's pixel offsets, pixel.
    variance_x, variance_y : ndarray (size, size)
        Each pixel's PRF variance minus the mean kernel's, pixel^2 (``width^2 - mean_width^2``).
    """
    image = np.asarray(image, float)
    dx, dy = np.nan_to_num(np.asarray(dx, float)), np.nan_to_num(np.asarray(dy, float))
    vx, vy = np.nan_to_num(np.asarray(variance_x, float)), np.nan_to_num(np.asarray(variance_y, float))
    corrected = image.copy()
    for _ in range(iterations):
        px, py, pxx, pxy, pyy = _fourier_derivatives(corrected)
        recorded_minus_grid = (dx * px + dy * py + 0.5 * (dx * dx * pxx + 2 * dx * dy * pxy + dy * dy * pyy)
                               + 0.5 * (vx * pxx + vy * pyy))
        corrected = image - recorded_minus_grid
    return corrected


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


def _noise_weights(window_image, n_frames, gain, read_noise):
    """1 / sigma of each pixel of a mean of ``n_frames`` frames, adu."""
    return 1.0 / np.sqrt((np.clip(window_image, 0, None) / gain + read_noise**2) / n_frames)


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
    fits = []
    for s, (r, c) in enumerate(centres):
        w = star_window(r, c, half_size=half_size, shape=detector.shape, label=f"star {s} at {where}",
                        area=(detector.science_rows, detector.science_cols))
        fits.append(gaussian_fit(mean[w.slices] - dark[w.slices], w, weights=(flags[w.slices] == 0).astype(float),
                                 label=f"star {s} at {where}"))
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

    def corrected(self, frame, window, *, star, where):
        """The window of ``frame`` minus the dark, divided by the flat, corrected for offsets (and widths)."""
        sl = window.slices
        image = frame[sl] - self.dark[sl]
        bad = self.flags[sl] != 0
        if self.prnu is not None:
            with np.errstate(divide="ignore", invalid="ignore"):  # a dead pixel's PRNU is about 0
                image = image / self.prnu[sl]
        if bad.any():  # left out (weight 0) or the star refused: a placeholder, never used
            image = np.where(bad, 0.0, image)
        if self.variance_x is not None:
            image = response_corrected(image, self.dx[sl], self.dy[sl], self.variance_x[sl], self.variance_y[sl])
        elif self.dx is not None:
            image = offset_corrected(image, self.dx[sl], self.dy[sl])
        if not np.all(np.isfinite(image)):
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
    """Positions in detector coordinates: a Gaussian fit, or Fourier resampling against each star's first
    window, tied to the central star's, whose Gaussian fit anchors them all."""

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

    def __call__(self, image, window, star, weights, *, where=""):
        if self.method == "gaussian":
            fit = gaussian_fit(image, window, weights=weights, label=f"star {star}" + (f" at {where}" if where else ""))
            return np.array([fit.x, fit.y])
        ref_window, ref_image = self.references[star]
        shift = fourier_displacement(ref_image, image, weights=weights)
        origin = np.array([window.col0 - ref_window.col0, window.row0 - ref_window.row0])
        return np.array([self.anchor.x, self.anchor.y]) + self.ties[star] + shift + origin


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
        n, n_batches = stack.n_frames, stack.n_batches
        mean, batch_means, saturated = stack.mean, stack.batch_means, stack.n_saturated
        n_frames[i] = n
        if locate is None:
            half_size = _isolated_windows_half_size(mean, dark, centres, flags, half_size, detector,
                                                    where=where, label=label, log=log)
        windows = [star_window(r, c, half_size=half_size, shape=detector.shape, label=f"star {s} at {where}",
                               area=(detector.science_rows, detector.science_cols))
                   for s, (r, c) in enumerate(centres)]
        images = [calibrations.corrected(mean, w, star=s, where=where) for s, w in enumerate(windows)]
        batch_images = [[calibrations.corrected(frame, w, star=s, where=where) for s, w in enumerate(windows)]
                        for frame in batch_means]
        noise = [np.where(flags[w.slices] != 0, 0.0, _noise_weights(image, n, detector.gain, read_noise[w.slices]))
                 for image, w in zip(images, windows)]
        for s, (weights, w) in enumerate(zip(noise, windows)):
            if not np.all(np.isfinite(weights)):  # no signal and no read noise: a weight of 1/0
                r, c = np.argwhere(~np.isfinite(weights))[0]
                raise WindowError(f"star {s} at {where}: pixel row {w.row0 + r}, col {w.col0 + c} has zero noise "
                                  "(no signal above the dark and no read noise, e.g. zero in every frame and in the "
                                  "dark): flag it in the bad-pixel mask or check the data")
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
            # the shape and flux of the bound
            fit = gaussian_fit(images[s], window, weights=noise[s], label=f"star {s} at {where}")
            xy = np.array([fit.x, fit.y]) if method == "gaussian" else locate(images[s], window, s, noise[s],
                                                                                where=where)
            batch_xy = np.array([locate(b[s], window, s, noise[s] / np.sqrt(n_batches), where=f"{where}, batch {k}")
                                 for k, b in enumerate(batch_images)])
            limit = cramer_rao(fit, window, gain=detector.gain * n, read_noise=read_noise[window.slices] / np.sqrt(n),
                               used=flags[window.slices] == 0)
            out["x"][i, s], out["y"][i, s] = xy
            out["px"][i, s], out["py"][i, s] = batch_xy.std(axis=0, ddof=1) / np.sqrt(n_batches)
            out["lx"][i, s], out["ly"][i, s] = limit
            centres[s] = (xy[1], xy[0])
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
