"""The fringe model of one metrology baseline and its gauge: pixel phases, projected offsets, photon floor.

Model (paper, section "Metrology"; appendix B)::

    I(p, t) = B(t) iota(p) + A(t) alpha(p) sin(K.r_p + phi(t) + K.delta_p)

for pixel p at nominal position r_p = (col, row). Written with
theta_p = K.r_p + K.delta_p it is a product of per-frame and per-pixel factors,

    I(p, t) = F(t) . G(p),   F = (B, A cos phi, A sin phi),   G = (iota, alpha sin theta, alpha cos theta),

a rank-3 factorisation, which the streaming fit of :mod:`dice_core.fringe_fit`
finds from the frames. This module holds what the factors mean: the first
wavevector, the gauge that makes them physical, the offsets and their noise
floor, and the solution's product; it reads no frame.

Identifiability. Alternating fits determine F and G only up to an invertible
3x3 mixing M (F -> F M, G -> G M^-T): a mixing that adds part of iota to the
fringe terms, or of the fringe terms to iota, fits the data equally well, and
where iota, the envelope or the visibility vary over the detector it turns
into a ripple of the pixel phases at K and 2K that no plane removal takes out.
:func:`fix_gauge` pins M with physical constraints:

1. pixel side: iota divided by the flat field is smooth (a low-order
   polynomial), while alpha sin theta and alpha cos theta oscillate at K;
   the iota direction is the generalised eigenvector of least non-smooth
   power;
2. frame side: (A cos phi, A sin phi) / B traces a centred circle, since the
   amplitude-to-level ratio does not depend on the phase; fitting that cone
   fixes the part of the fringe terms mixed into B and the ellipticity of the
   fringe plane;
3. what is left, a rotation (a constant phase) and scales, is the physical
   gauge, fixed by the normalisations (mean iota and alpha 1, offsets with
   zero mean and gradient).

Units: pixel for positions and offsets, rad for phases, rad/pixel for K,
adu for B and A.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from dice_core import lazy
from dice_core.geometry import UNOBSERVABLE_MODE, TwoSourceFit, wrapped_about_mean
from dice_core.pixel_blocks import pixel_blocks, stacked_r
from dice_core.polynomials import polynomial_design, polynomial_scaling

xr = lazy.module("xarray")

__all__ = [
    "FringeError",
    "FringeSolution",
    "initial_wavevector",
    "fix_gauge",
    "projected_offsets",
    "wrapped_about_mean",
    "photon_floor",
    "frame_moments",
    "solution_dataset",
    "metrology_product",
]

log = logging.getLogger(__name__)


class FringeError(ValueError):
    """Metrology data that cannot give pixel offsets (no contrast, phase sweep too short...)."""


#: Padded length (per axis) beyond which :func:`initial_wavevector` pads no further: a frame of
#: 1024 pixels a side is padded twice (64 MiB of complex spectrum), one of 4096 not at all
#: (256 MiB), where eightfold would take 1 and 17 GB.
WAVEVECTOR_PADDED_MAX = 2048


def initial_wavevector(frame: np.ndarray, mask: np.ndarray, *, pad: int = 8) -> np.ndarray:
    """Fringe wavevector (kx, ky) in rad/pixel from the Fourier transform of one frame.

    The frame's mean is removed over ``mask``, the masked area is zero-padded
    ``pad`` times, but to no more than :data:`WAVEVECTOR_PADDED_MAX` samples
    per axis (never fewer than the area's own), and the peak of the power
    spectrum (one half-plane) is refined by a parabola through its
    neighbours. Precise to about 1e-4 rad/pixel on an 80x84 frame (0.01
    rad across it) and 2e-4 on a 1024x1024 one (0.2 rad across it), which
    pass 1's K(t) terms take up: the fits that follow are linearised about
    it.
    """
    rows, cols = np.nonzero(mask)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    sub = np.where(mask[r0:r1, c0:c1], frame[r0:r1, c0:c1], np.nan)
    sub = np.nan_to_num(sub - np.nanmean(sub))
    ny, nx = (max(n, min(pad * n, WAVEVECTOR_PADDED_MAX)) for n in sub.shape)
    power = np.abs(np.fft.fft2(sub, s=(ny, nx))) ** 2
    fy, fx = np.fft.fftfreq(ny), np.fft.fftfreq(nx)
    # half-plane fx > 0 (or fx == 0, fy > 0), away from the zero frequency
    keep = (fx[None, :] > 0) | ((fx[None, :] == 0) & (fy[:, None] > 0))
    keep &= np.hypot(fx[None, :], fy[:, None]) > 1.5 / min(sub.shape)
    iy, ix = np.unravel_index(np.argmax(np.where(keep, power, -1)), power.shape)

    def vertex(m, c, p):
        denom = m - 2 * c + p
        return 0.0 if denom == 0 else 0.5 * (m - p) / denom

    dy = vertex(power[iy - 1, ix], power[iy, ix], power[(iy + 1) % ny, ix])
    dx = vertex(power[iy, ix - 1], power[iy, ix], power[iy, (ix + 1) % nx])
    return 2 * np.pi * np.array([fx[ix] + dx / nx, fy[iy] + dy / ny])


def _smooth_residual_gram(G, x, y, weight, degree, block):
    """rough' rough (3, 3), rough = G minus its least-squares fit by the smooth basis (the polynomials of
    ``degree`` times ``weight``, or unweighted for None): R22' R22 of the QR of [basis | G], swept over
    pixel blocks."""
    scaling = polynomial_scaling(x, y)

    def rows(s):
        basis = polynomial_design(x[s], y[s], degree=degree, scaling=scaling)
        if weight is not None:
            basis *= weight[s, None]
        return np.hstack([basis, G[s]])

    R = stacked_r(rows(s) for s in pixel_blocks(G.shape[0], block))
    rough = R[-3:, -3:]
    return rough.T @ rough


def _boost_regression(G, M, x, y, degree, block):
    """The boost (2,) that removes the first harmonic of |rho|^2 in theta under the gauge M (:func:`fix_gauge`,
    step 3). Two sweeps over pixel blocks: |rho|^2 (for its median v^2), then the least-squares fit of
    |rho|^2 by the smooth polynomials and (v sin theta, v cos theta), by the QR of [design | |rho|^2]."""
    import scipy.linalg

    inv_t = np.linalg.inv(M).T
    rho2 = np.empty(G.shape[0])
    for s in pixel_blocks(G.shape[0], block):
        Gp = G[s] @ inv_t
        rho2[s] = np.sum((Gp[:, 1:] / Gp[:, :1]) ** 2, axis=1)
    v = np.sqrt(np.median(rho2))
    scaling = polynomial_scaling(x, y)

    def rows(s):
        Gp = G[s] @ inv_t
        rho = Gp[:, 1:] / Gp[:, :1]
        theta = np.arctan2(rho[:, 0], rho[:, 1])
        return np.column_stack([polynomial_design(x[s], y[s], degree=degree, scaling=scaling),
                                v * np.sin(theta), v * np.cos(theta), rho2[s]])

    R = stacked_r(rows(s) for s in pixel_blocks(G.shape[0], block))
    coef = scipy.linalg.solve_triangular(R[:-1, :-1], R[:-1, -1])
    return -coef[-2:] / (2 * (1 - v**2))


def fix_gauge(frame_factors, pixel_factors, *, flat, x, y, smooth_degree: int = 6, block: int | None = None):
    """Physical frame and pixel factors from any rank-3 factorisation of the fringe data.

    Parameters
    ----------
    frame_factors : ndarray (frame, 3)
    pixel_factors : ndarray (pixel, 3)
        Any factorisation ``I ~ frame_factors @ pixel_factors.T``.
    flat : ndarray (pixel,)
        Relative sensitivity of each pixel (ones if unknown): iota / flat is smooth.
    x, y : ndarray (pixel,)
        Pixel positions, pixel.
    smooth_degree : int
        Degree of the polynomial that iota / flat is assumed to follow.
    block : int
        Pixels per block of the sweeps over the pixels (None: :data:`dice_core.pixel_blocks.PIXEL_BLOCK`, 8 MB
        of smooth basis at degree 6, never over every pixel: 224 bytes a pixel): the smooth basis is
        formed a block at a time; the result is the same for any block, to rounding.

    Returns
    -------
    transform : ndarray (3, 3)
        M such that ``frame_factors @ M`` = (B, A cos phi, A sin phi) (up to a
        common rotation of the phase and scales) and
        ``pixel_factors @ inv(M).T`` = (iota, alpha sin theta, alpha cos theta).

    Raises
    ------
    FringeError
        When the frame factors do not trace a cone (no fringe contrast).
    """
    F, G = np.asarray(frame_factors, float), np.asarray(pixel_factors, float)
    x, y = np.asarray(x, float), np.asarray(y, float)
    # 1. pixel side: the combination of pixel factors that is smooth times the flat is iota
    import scipy.linalg

    values, vectors = scipy.linalg.eigh(_smooth_residual_gram(G, x, y, flat, smooth_degree, block), G.T @ G)
    if values[1] < 100 * max(values[0], 1e-300):
        raise FringeError("cannot separate the fringe from the mean level: the pixel factors have no "
                          "second oscillating component (no fringe contrast?)")
    N = vectors  # columns: iota direction first (least rough), then two fringe directions
    Fn = F @ np.linalg.inv(N).T  # frame factors pairing with G @ N
    f1, xf = Fn[:, 0], Fn[:, 1:]
    # 2. frame side: x' S x = (f1 - c.x)^2, i.e. x'(S - cc')x + 2 f1 c.x = f1^2, linear in (S - cc', c)
    scale = 1.0 / f1**2
    design = np.column_stack([xf[:, 0] ** 2, 2 * xf[:, 0] * xf[:, 1], xf[:, 1] ** 2,
                              2 * f1 * xf[:, 0], 2 * f1 * xf[:, 1]]) * np.sqrt(scale)[:, None]
    solution, *_ = np.linalg.lstsq(design, np.sqrt(scale) * f1**2, rcond=None)
    c = solution[3:]
    quad = np.array([[solution[0], solution[1]], [solution[1], solution[2]]]) + np.outer(c, c)
    try:
        upper = np.linalg.cholesky(quad).T  # quad = U' U
    except np.linalg.LinAlgError:
        raise FringeError("the frame factors do not trace a circle: no usable fringe contrast") from None
    R = np.zeros((3, 3))
    R[0, 0] = 1.0
    R[1:, 0] = -c
    R[1:, 1:] = upper.T  # (B, u) = (f1 - c.x, U x)
    M = np.linalg.inv(N).T @ R
    # 3. The cone |u| = B is kept by Lorentz boosts, which mix B with u and so iota with the
    # fringe factors. Fix them on the pixel side with a PRNU-free property: the ratios
    # rho = (alpha sin theta, alpha cos theta) / iota = V h (sin theta, cos theta) cancel the
    # PRNU and the envelope, and |rho|^2 is smooth; a boost b adds 2 (1 - v^2) b.rho to it,
    # a first harmonic in theta that the regression below measures and removes.
    if flat is not None:
        return M
    for _ in range(8):
        boost = _boost_regression(G, M, x, y, smooth_degree, block)
        M = M @ _lorentz_boost(boost)
        if np.hypot(*boost) < 1e-14:
            break
    return M


def _lorentz_boost(b):
    """Boost L(b) acting on frame vectors (B, u1, u2) as F @ L; keeps B^2 - |u|^2."""
    b = np.asarray(b, float)
    speed = np.hypot(*b)
    if speed == 0:
        return np.eye(3)
    if speed >= 1:
        raise FringeError("gauge boost out of range: the fringe model does not fit the data")
    gamma = 1 / np.sqrt(1 - speed**2)
    n = b / speed
    L = np.empty((3, 3))
    L[0, 0] = gamma
    L[0, 1:] = L[1:, 0] = -gamma * b
    L[1:, 1:] = np.eye(2) + (gamma - 1) * np.outer(n, n)
    return L


def projected_offsets(theta, x, y, k_guess, *, block: int | None = None):
    """Wavevector and offsets from pixel phases theta = K.r + K.delta + constant.

    The plane K.r + constant is fitted (by least squares, after unwrapping
    against ``k_guess``) and removed; the residual divided by |K| is the offset
    projected on K, with zero mean and zero gradient over the pixels given, as
    the dataset format defines it. The fits' sums are taken ``block`` pixels at
    a time (:mod:`dice_core.pixel_blocks`): its temporaries are a few arrays of
    one number a pixel, never the (pixel, 3) design.

    Returns
    -------
    k : ndarray (2,)
        (kx, ky), rad/pixel, the sign that makes theta increase along K.
    offsets : ndarray (pixel,)
        Projected offsets, pixel.
    """
    theta, x, y = (np.asarray(v, float) for v in (theta, x, y))

    def wrapped(k):
        psi = theta - k[0] * x
        psi -= k[1] * y
        return wrapped_about_mean(psi, block=block)

    def plane(psi):  # least-squares coefficients of 1, x, y
        R = stacked_r(np.column_stack([np.ones(s.stop - s.start), x[s], y[s], psi[s]])
                      for s in pixel_blocks(psi.size, block))
        return np.linalg.lstsq(R[:3, :3], R[:3, 3], rcond=None)[0]

    best = None
    for sign in (1.0, -1.0):  # theta may run along -K_guess
        k = sign * np.asarray(k_guess, float)
        for _ in range(3):
            k = k + plane(wrapped(k))[1:]
        residual = wrapped(k)
        coef = plane(residual)
        residual -= coef[0]
        residual -= coef[1] * x
        residual -= coef[2] * y
        if best is None or np.std(residual) < np.std(best[1]):
            best = (k + coef[1:], residual)
        del residual
    k, residual = best
    residual /= np.hypot(*k)
    return k, residual


@dataclass
class FringeSolution:
    """Result of :func:`dice_core.fringe_fit.fit_baseline`; pixel arrays run over the science area (``rows``, ``cols``).

    Attributes
    ----------
    rows, cols : ndarray (pixel,)
        Positions of the science-area pixels; masked pixels hold NaN.
    offsets : ndarray (pixel,)
        Offset projected on K, pixel (zero mean and gradient).
    iota, alpha : ndarray (pixel,)
        Relative intensity and relative amplitude (mean 1).
    photon_floor : ndarray (pixel,)
        1-sigma error of ``offsets`` from photon and read noise, pixel.
    k : ndarray (2,)
        Mean wavevector, rad/pixel.
    k_frame : ndarray (frame, 2)
        Per-frame wavevector from the first pass, rad/pixel.
    level, amplitude, phase : ndarray (frame,)
        B(t) (adu, for iota 1), A(t) (adu, for alpha 1), phi(t) (rad).
    history : list of dict
        Per pass from the second: max and rms change of the offsets (pixel).
    masked : ndarray (pixel,) of bool
        Pixels left without an offset (bad pixels, saturated samples, no contrast, not converged).
    masked_by_reason : dict
        Number of masked pixels by reason: ``bad_pixel``, ``saturated``, ``no_contrast``, ``unconverged``.
    offsets_prnu_free : ndarray (pixel,) or None
        With a flat: the offsets under the PRNU-free gauge instead (pixel), the
        diagnostic of a flat that is not the laser's response; their difference
        from ``offsets`` is what the flat's gauge adds.
    pixel_phase : ndarray (pixel,)
        Fitted phase theta of each pixel, rad, wrapped (the constant is the gauge's).
    two_source : TwoSourceFit or None
        With a bench geometry (spherical waves): the refined tips, each pixel's
        local wavevector and the unobservable offset modes; ``offsets`` are then
        along the local wavevectors and ``k`` is their mean.
    gauge_difference_floor : float or None
        With a flat, and frames in two parts (files): the rms noise of
        ``offsets - offsets_prnu_free`` from the metrology frames, pixel,
        measured from the two parts' own gauge differences (half the rms of
        their difference for equal parts). The flat's own noise, the same in
        both parts, is not in it. The difference is a boost, two numbers, so
        its ratio to the floor scatters like sqrt(F(2, 2)): pure noise passes
        3x the floor one time in 10, 5x one time in 26.
    """

    rows: np.ndarray
    cols: np.ndarray
    offsets: np.ndarray
    iota: np.ndarray
    alpha: np.ndarray
    photon_floor: np.ndarray
    k: np.ndarray
    k_frame: np.ndarray
    level: np.ndarray
    amplitude: np.ndarray
    phase: np.ndarray
    history: list = field(default_factory=list)
    masked: np.ndarray = None
    masked_by_reason: dict = field(default_factory=dict)
    offsets_prnu_free: np.ndarray | None = None
    pixel_phase: np.ndarray = None
    two_source: TwoSourceFit | None = None
    gauge_difference_floor: float | None = None


def frame_moments(F):
    """F'F (3, 3) and the third moments sum_t F_tk F_t F_t' (3, 3, 3) of frame factors F (frame, 3)."""
    third = ((F[:, :, None] * F[:, None, :]).reshape(-1, 9).T @ F).reshape(3, 3, 3).transpose(2, 0, 1)
    return F.T @ F, third


def photon_floor(G_phys, FtF, *, third, gain, read_noise, k_norm, phase_only: bool = False,
                 block: int | None = None):
    """Per-pixel 1-sigma offset error from photon and read noise for the unweighted temporal fit.

    Sample variance (adu^2) of pixel p at frame t: F_t.G_p / g + sigma_r^2; so
    cov(G_p) = (F'F)^-1 [sum_k G_pk/g M_k + sigma_r^2 F'F] (F'F)^-1 with
    M_k = sum_t F_tk F_t F_t'. Then theta = atan2(g2, g3) and
    delta = theta / |K| propagate it linearly: var(theta) = u' [...] u with
    u = (F'F)^-1 d theta / dG, formed without the per-pixel 3x3 covariances.

    With ``phase_only``, the error of a fit of the pixel's phase alone, its
    iota and alpha known (:func:`dice_core.allan.batch_offsets`): the model's
    derivative along theta is J = dG/dtheta = (0, alpha cos theta,
    -alpha sin theta), the linearised estimate theta_hat - theta =
    J'F'n / (J'F'F J), so u = J / (J'F'F J).

    ``read_noise`` (adu) and ``k_norm`` (rad/pixel) are per pixel or one
    value. Formed ``block`` pixels at a time (its temporaries, 9 numbers a
    pixel, never over every pixel): the same values whatever the block, to
    rounding (3e-16 relative at blocks of 7 pixels).
    """
    G_phys = np.asarray(G_phys)
    n = G_phys.shape[0]
    read_noise = np.broadcast_to(np.asarray(read_noise, float), (n,))
    k_norm = np.broadcast_to(np.asarray(k_norm, float), (n,))
    floor = np.empty(n)
    for s in pixel_blocks(n, block):
        floor[s] = _photon_floor_block(G_phys[s], FtF, third, gain, read_noise[s], k_norm[s], phase_only)
    return floor


def _photon_floor_block(G_phys, FtF, third, gain, read_noise, k_norm, phase_only):
    """:func:`photon_floor` of a block of pixels (``read_noise``, ``k_norm`` per pixel)."""
    a, b = G_phys[:, 1], G_phys[:, 2]  # alpha sin theta, alpha cos theta
    if phase_only:
        J = np.column_stack([np.zeros_like(a), b, -a])
        u = J / np.einsum("pi,ij,pj->p", J, FtF, J)[:, None]
    else:
        r2 = a**2 + b**2
        gradient = np.column_stack([np.zeros_like(a), b / r2, -a / r2])  # d theta / d G
        u = gradient @ np.linalg.inv(FtF)  # (F'F)^-1 is symmetric
    outer = (u[:, :, None] * u[:, None, :]).reshape(-1, 9)
    photon = np.sum(G_phys / gain * (outer @ third.reshape(3, 9).T), axis=1)  # sum_k G_pk/g u'M_k u
    read = read_noise ** 2 * (outer @ FtF.ravel())
    return np.sqrt(photon + read) / k_norm


def perfect_pixel_design(k0, xc, yc):
    """Pass 1's frame design: perfect pixels (iota = alpha = 1, no offsets) and K free, linearised about k0.

    sin(theta + phi + dK.r) ~ sin(theta + phi) + (dK.r)(u1 cos theta - u2 sin theta), with
    theta = k0.r over the pixels' centred positions ``xc``, ``yc`` (pixel). Returns G (pixel, 3), the
    factors (1, sin theta, cos theta), and the four K regressors (pixel, 4) of :func:`wavevector_per_frame`.
    """
    theta = k0[0] * xc + k0[1] * yc
    G = np.column_stack([np.ones(xc.size), np.sin(theta), np.cos(theta)])
    extra = np.column_stack([xc * G[:, 2], xc * G[:, 1], yc * G[:, 2], yc * G[:, 1]])
    return G, extra


def wavevector_per_frame(coef, k0):
    """K(t) (frame, 2), rad/pixel, from pass 1's frame coefficients (frame, 7) on :func:`perfect_pixel_design`."""
    u1, u2 = coef[:, 1], coef[:, 2]
    amp2 = u1**2 + u2**2
    return np.column_stack([k0[0] + (coef[:, 3] * u1 - coef[:, 4] * u2) / amp2,
                            k0[1] + (coef[:, 5] * u1 - coef[:, 6] * u2) / amp2])


def metrology_product(solution: FringeSolution, detector, *, baseline: str, geometry=None) -> xr.Dataset:
    """A baseline's metrology product (:func:`solution_dataset`, with the fibers of a spherical-wave
    ``geometry`` and the ``baseline`` attribute), its summary logged: the single fit's and the split fit's."""
    product = solution_dataset(solution, detector, fibers=None if geometry is None else geometry.fibers)
    log.info("baseline %s: K = (%.6f, %.6f) rad/pixel, offsets rms %.3e pixel, photon floor %.3e pixel, "
             "%d pixel(s) masked", baseline, *solution.k, float(product["projected_offset"].std()),
             float(product["photon_noise_floor_rms"]), int(product["n_masked"]))
    product.attrs["baseline"] = baseline
    return product


def _two_source_variables(solution: FringeSolution, as_map) -> dict:
    """The spherical-wave variables of :func:`solution_dataset`."""
    fit = solution.two_source
    active = ~solution.masked

    def on_active(values):
        out = np.full(solution.rows.size, np.nan)
        out[active] = values
        return as_map(out)

    fxyz = ("fiber", "xyz")
    modes = {} if not len(fit.modes) else {  # none: absent, as the products contract says of the offsets'
        "unobservable_offset": (("mode", "row", "col"), np.stack([on_active(m) for m in fit.modes]),
                                {"units": "1", "long_name": "offset modes along the local wavevector, beyond the "
                                                            "affine part, absorbed by the tips (unit rms)"})}
    return {
        **modes,
        "kx_local": (("row", "col"), on_active(fit.k_local[:, 0]),
                     {"units": "rad/pixel", "long_name": "local wavevector along x (gradient of the fitted phase)"}),
        "ky_local": (("row", "col"), on_active(fit.k_local[:, 1]),
                     {"units": "rad/pixel", "long_name": "local wavevector along y (gradient of the fitted phase)"}),
        "fiber_position": (fxyz, fit.tips, {"units": "m", "long_name": "refined fiber-tip position, detector frame"}),
        "fiber_position_error": (fxyz, fit.tip_errors,
                                 {"units": "m", "long_name": "1-sigma error of the refined fiber-tip position"}),
        "fiber_position_nominal": (fxyz, fit.nominal,
                                   {"units": "m", "long_name": "nominal fiber-tip position (the manifest's)"}),
        "tip_information": (("tip_mode",), fit.information,
                            {"units": "1", "long_name": "information ratio, data over prior, of each tip mode"}),
        "plane_wave_departure": (("row", "col"), on_active(fit.plane_wave_departure),
                                 {"units": "pixel", "long_name": "fitted phase surface minus its best plane, over "
                                                                 "|K|: what a plane-wave fit puts into the offsets"}),
        "surface_phase_rms": ((), fit.phase_rms,
                              {"units": "rad", "long_name": "rms of the pixel phases about the fitted surface"}),
    }


def solution_dataset(solution: FringeSolution, detector, *, fibers=None) -> xr.Dataset:
    """The ``metrology/<baseline>.nc`` product of a solution: maps (row, col), NaN outside the fit.

    ``fibers`` names the baseline's two fibers; required for a spherical-wave solution.

    Contract variables: projected_offset (pixel), iota and alpha (1), kx and ky
    (the mean wavevector, rad/pixel), phase (frame, rad). Also the photon-noise
    floor of the offsets, K(t), B(t), A(t), the mask and the convergence history;
    with a flat, the offsets under the PRNU-free gauge
    (projected_offset_prnu_free_gauge, pixel) and the rms of their difference
    from projected_offset (gauge_difference_rms, pixel). The fitted pixel
    phases (pixel_phase, rad). With spherical waves also each pixel's local
    wavevector (kx_local, ky_local, rad/pixel), the refined and nominal fiber
    tips and the refined ones' errors (fiber_position, fiber_position_error,
    fiber_position_nominal, m) and the unobservable offset modes along the
    local wavevector (unobservable_offset, 1, orthonormal: unit rms over the
    fitted pixels).
    """
    if solution.two_source is not None and fibers is None:
        raise ValueError("a spherical-wave solution's product needs the names of its two fibers")

    def as_map(values, fill=np.nan):
        out = np.full(detector.shape, fill, dtype=np.result_type(values, type(fill)))
        out[solution.rows, solution.cols] = values
        return out

    rc = ("row", "col")
    floor = solution.photon_floor
    history = solution.history or [{"pass": 1, "max_change": np.nan, "rms_change": np.nan}]
    return xr.Dataset(
        {
            "projected_offset": (rc, as_map(solution.offsets),
                                 {"units": "pixel", "long_name": "pixel offset projected on the wavevector"}),
            "iota": (rc, as_map(solution.iota), {"units": "1", "long_name": "relative pixel intensity"}),
            "alpha": (rc, as_map(solution.alpha), {"units": "1", "long_name": "relative pixel fringe amplitude"}),
            "photon_noise_floor": (rc, as_map(floor),
                                   {"units": "pixel", "long_name": "1-sigma offset error from photon and read noise"}),
            "masked": (rc, as_map(solution.masked.astype(np.int8), np.int8(0)),
                       {"units": "1", "flag_values": np.array([0, 1], np.int8), "flag_meanings": "measured masked",
                        "long_name": "1 where the pixel has no offset (bad pixel, saturated, no contrast or "
                                     "not converged)"}),
            "kx": ((), float(solution.k[0]), {"units": "rad/pixel", "long_name": "mean wavevector along x"}),
            "ky": ((), float(solution.k[1]), {"units": "rad/pixel", "long_name": "mean wavevector along y"}),
            "phase": (("frame",), solution.phase, {"units": "rad", "long_name": "fringe phase phi(t)"}),
            "level": (("frame",), solution.level, {"units": "adu", "long_name": "mean level B(t) for iota = 1"}),
            "amplitude": (("frame",), solution.amplitude,
                          {"units": "adu", "long_name": "fringe amplitude A(t) for alpha = 1"}),
            "kx_frame": (("frame",), solution.k_frame[:, 0],
                         {"units": "rad/pixel", "long_name": "wavevector along x fitted per frame (pass 1)"}),
            "ky_frame": (("frame",), solution.k_frame[:, 1],
                         {"units": "rad/pixel", "long_name": "wavevector along y fitted per frame (pass 1)"}),
            "max_change": (("iteration",), [h["max_change"] for h in history],
                           {"units": "pixel", "long_name": "largest offset change from the previous pass"}),
            "rms_change": (("iteration",), [h["rms_change"] for h in history],
                           {"units": "pixel", "long_name": "rms offset change from the previous pass"}),
            "photon_noise_floor_rms": ((), float(np.sqrt(np.nanmean(floor**2))),
                                       {"units": "pixel", "long_name": "rms photon-noise floor of the offsets"}),
            "n_masked": ((), int(solution.masked.sum()), {"units": "1", "long_name": "pixels without an offset"}),
            **({} if solution.offsets_prnu_free is None else {
                "projected_offset_prnu_free_gauge": (
                    rc, as_map(solution.offsets_prnu_free),
                    {"units": "pixel", "long_name": "projected offset with the PRNU-free gauge (the flat unused)"}),
                "gauge_difference_rms": (
                    (), float(np.sqrt(np.nanmean((solution.offsets - solution.offsets_prnu_free) ** 2))),
                    {"units": "pixel", "long_name": "rms of the flat gauge's offsets minus the PRNU-free gauge's"}),
                **({} if solution.gauge_difference_floor is None else {"gauge_difference_floor": (
                    (), solution.gauge_difference_floor,
                    {"units": "pixel", "long_name": "noise of gauge_difference_rms, from the two halves of the "
                                                    "frames"})}),
            }),
            **{f"n_masked_{reason}": ((), count, {"units": "1", "long_name": f"pixels masked: {reason.replace('_', ' ')}"})
               for reason, count in solution.masked_by_reason.items()},
            "pixel_phase": (rc, as_map(solution.pixel_phase),
                            {"units": "rad", "long_name": "fitted pixel phase theta (wrapped; constant of the gauge)"}),
            **({} if solution.two_source is None else _two_source_variables(solution, as_map)),
        },
        coords={"row": np.arange(detector.shape[0]), "col": np.arange(detector.shape[1]),
                "frame": np.arange(solution.phase.size), "iteration": [h["pass"] for h in history],
                **({} if solution.two_source is None else {
                    "fiber": list(fibers), "xyz": ["x", "y", "z"], "tip_mode": np.arange(6),
                    **({"mode": ("mode", np.arange(len(solution.two_source.modes)), UNOBSERVABLE_MODE)}
                       if len(solution.two_source.modes) else {})
                })},
    )
