"""Global fringe solution of one metrology baseline: pixel phases, projected offsets, K(t).

Model (paper, section "Metrology"; appendix B)::

    I(p, t) = B(t) iota(p) + A(t) alpha(p) sin(K.r_p + phi(t) + K.delta_p)

for pixel p at nominal position r_p = (col, row). Written with
theta_p = K.r_p + K.delta_p it is a product of per-frame and per-pixel factors,

    I(p, t) = F(t) . G(p),   F = (B, A cos phi, A sin phi),   G = (iota, alpha sin theta, alpha cos theta),

a rank-3 factorisation. The solution alternates two linear least-squares fits
with small shared design matrices: frame factors with the pixel factors fixed
(the paper's spatial fit, linearised), then pixel factors with the frame
factors fixed (the paper's temporal sine fit of appendix B). Each pass reads
the cube once, in chunks: a chunk's frame factors first, then that chunk's
contribution to the per-pixel normal equations.

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
from typing import Iterable

import numpy as np
import scipy.linalg
import xarray as xr

from dice_core.geometry import BaselineGeometry, TwoSourceFit, fit_two_source, wrapped_about_mean
from dice_core.io import Chunk, first_chunk
from dice_core.parallel import (LANES, blas_threads, lane_executor, lane_workers, map_lanes, one_blas_thread,
                                threads_report)
from dice_core.polynomials import polynomial_design

__all__ = [
    "FringeError",
    "FringeSolution",
    "initial_wavevector",
    "fit_baseline",
    "fix_gauge",
    "projected_offsets",
    "wrapped_about_mean",
    "photon_floor",
    "frame_moments",
    "solution_dataset",
]

log = logging.getLogger(__name__)


class FringeError(ValueError):
    """Metrology data that cannot give pixel offsets (no contrast, phase sweep too short...)."""


def initial_wavevector(frame: np.ndarray, mask: np.ndarray, *, pad: int = 8) -> np.ndarray:
    """Fringe wavevector (kx, ky) in rad/pixel from the Fourier transform of one frame.

    The frame's mean is removed over ``mask``, the masked area is zero-padded
    ``pad`` times, and the peak of the power spectrum (one half-plane) is
    refined by a parabola through its neighbours. Precise to about 1e-4
    rad/pixel on an 80x84 frame, enough for the linearised fits that follow.
    """
    rows, cols = np.nonzero(mask)
    r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    sub = np.where(mask[r0:r1, c0:c1], frame[r0:r1, c0:c1], np.nan)
    sub = np.nan_to_num(sub - np.nanmean(sub))
    ny, nx = pad * sub.shape[0], pad * sub.shape[1]
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


def _smooth_basis(x, y, weight, degree):
    return polynomial_design(x, y, degree=degree) * weight[:, None]


def fix_gauge(frame_factors, pixel_factors, *, flat, x, y, smooth_degree: int = 6):
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
    # 1. pixel side: the combination of pixel factors that is smooth times the flat is iota
    S = _smooth_basis(x, y, np.ones_like(x) if flat is None else flat, smooth_degree)
    q, _ = np.linalg.qr(S)
    rough = G - q @ (q.T @ G)
    values, vectors = scipy.linalg.eigh(rough.T @ rough, G.T @ G)
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
    smooth = _smooth_basis(x, y, np.ones_like(x), smooth_degree)
    for _ in range(8):
        Gp = G @ np.linalg.inv(M).T
        rho = Gp[:, 1:] / Gp[:, :1]
        rho2 = np.sum(rho**2, axis=1)
        v = np.sqrt(np.median(rho2))
        theta = np.arctan2(rho[:, 0], rho[:, 1])
        design = np.column_stack([smooth, v * np.sin(theta), v * np.cos(theta)])
        coef, *_ = np.linalg.lstsq(design, rho2, rcond=None)
        boost = -coef[-2:] / (2 * (1 - v**2))
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


def projected_offsets(theta, x, y, k_guess):
    """Wavevector and offsets from pixel phases theta = K.r + K.delta + constant.

    The plane K.r + constant is fitted (by least squares, after unwrapping
    against ``k_guess``) and removed; the residual divided by |K| is the offset
    projected on K, with zero mean and zero gradient over the pixels given, as
    the dataset format defines it.

    Returns
    -------
    k : ndarray (2,)
        (kx, ky), rad/pixel, the sign that makes theta increase along K.
    offsets : ndarray (pixel,)
        Projected offsets, pixel.
    """
    design = np.column_stack([np.ones_like(x), x, y])
    best = None
    for sign in (1.0, -1.0):  # theta may run along -K_guess
        k = sign * np.asarray(k_guess, float)
        for _ in range(3):
            psi = wrapped_about_mean(theta - k[0] * x - k[1] * y)
            coef, *_ = np.linalg.lstsq(design, psi, rcond=None)
            k = k + coef[1:]
        psi = wrapped_about_mean(theta - k[0] * x - k[1] * y)
        coef, *_ = np.linalg.lstsq(design, psi, rcond=None)
        residual = psi - design @ coef
        if best is None or np.std(residual) < np.std(best[1]):
            best = (k + coef[1:], residual)
    k, residual = best
    return k, residual / np.hypot(*k)


@dataclass
class FringeSolution:
    """Result of :func:`fit_baseline`; pixel arrays run over the science area (see ``rows``, ``cols``).

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


def _accumulate(chunks: Iterable[Chunk], projector, offset, centre, subtract_centre):
    """The streaming part of a pass over one run of chunks (see :func:`_pass`).

    Returns the frame products X P (frame, m) in the chunks' type, F'X (3,
    pixel) in float64, with F = X P[:, :3] - offset[:3], the pixels holding a
    saturated sample, and the BLAS threads of the process that ran it (for the
    log). Module-level, so that a worker process can run it.
    """
    n_pixels = projector.shape[0]
    projector_c = centre_c = offset_c = work = None
    products, FtX = [], np.zeros((3, n_pixels))
    saturated = np.zeros(n_pixels, bool)
    for chunk in chunks:
        n = chunk.frames.shape[0]
        X = chunk.frames.reshape(n, -1)
        if projector_c is None or projector_c[0].dtype != X.dtype:
            # Products with at most 4 columns: OpenBLAS runs pass 1's 3 + 4 columns in
            # three quarters of the time of one product with 7 (BENCHMARKS.md).
            projector_c = [np.ascontiguousarray(projector[:, i:i + 4], dtype=X.dtype)
                           for i in range(0, projector.shape[1], 4)]
            centre_c = centre.astype(X.dtype)
            offset_c = offset[:3].astype(X.dtype)
        if subtract_centre:
            if work is None or work.shape[0] < n or work.dtype != X.dtype:
                work = np.empty((max(n, 1), n_pixels), dtype=X.dtype)
            X = np.subtract(X, centre_c, out=work[:n])
        coef = np.hstack([X @ block for block in projector_c])
        # F'X while the chunk is in the cache, F formed in the chunk's type
        np.add(FtX, (coef[:, :3] - offset_c).T @ X, out=FtX)
        if chunk.any_saturated:
            saturated |= chunk.saturated.reshape(n, -1).any(axis=0)
        products.append(coef)
    products = np.concatenate(products) if products else np.empty((0, projector.shape[1]))
    return products, FtX, saturated, blas_threads()


def _pass(lanes, dark, idx, G, *, extra=None, reference=None, centred=False, executor=None):
    """One streaming pass: frame factors per chunk, then per-pixel normal equations.

    Works on whole frames, so that a chunk is never copied: pixels outside
    ``idx`` get zero rows in the projector, and the dark is folded into the
    algebra, F = (X - d) P = X P - d P and F'(X - d) = F'X - (F'1) d', instead
    of being subtracted from every sample. Products of a chunk are formed in
    the chunk's type (float32 holds the integer samples exactly) and summed
    over chunks in float64. With a ``reference`` frame r (row, col; e.g. a
    mean frame), each chunk is first centred on it, X - r, into a work buffer
    of the pass (the caller's frames are never modified), unless ``centred``
    says the chunks already hold X - r (see :meth:`FrameStream.centred`): the
    large mean level then no longer cancels inside the float32 products,
    whose rounding would otherwise show at 1e-7 pixel; r - d folds into the
    algebra like the dark.

    ``lanes`` are consecutive runs of chunks (re-iterables), reduced one after
    the other or, given an ``executor``, in its worker processes, and summed
    in lane order: the result does not depend on which.
    ``extra`` (pixel, m) adds regressors to the frame fit only (the K(t) terms).
    Returns frame factors (frame, 3 [+m]), F'I (3, pixel), F'F (3, 3), the
    third moments sum_t F_tk F_t F_t' (3, 3, 3), the pixels of ``idx``
    holding a saturated sample, the BLAS threads each lane ran with, and each
    lane's own frame factors (frame of the lane, 3) and F'I (3, pixel), for
    diagnostics that compare independent parts of the frames.
    """
    design = G if extra is None else np.column_stack([G, extra])
    n_pixels = dark.size
    projector = np.zeros((n_pixels, design.shape[1]))
    projector[idx] = design @ np.linalg.inv(design.T @ design)
    centre = np.zeros(n_pixels) if reference is None else reference.ravel().astype(np.float64)
    level = centre - dark.ravel()  # X - d = (X - r) + (r - d)
    offset = -(level @ projector)
    subtract_centre = reference is not None and not centred
    results = map_lanes(executor, _accumulate, lanes, projector, offset, centre, subtract_centre)
    coef = np.concatenate([products for products, _, _, _ in results]).astype(np.float64) - offset
    if coef.shape[0] == 0:
        raise FringeError("no frames to fit")
    FtX, saturated = np.zeros((3, n_pixels)), np.zeros(n_pixels, bool)
    for _, lane_FtX, lane_saturated, _ in results:
        FtX += lane_FtX
        saturated |= lane_saturated
    F = coef[:, :3]
    # Sums over frames, from the frame factors kept for the product anyway: vectorised once
    # per pass instead of a few small operations per chunk.
    FtI = FtX[:, idx] + np.outer(F.sum(axis=0), level[idx])
    FtF, third = frame_moments(F)
    parts, start = [], 0
    for products, lane_FtX, _, _ in results:
        F_lane = F[start:start + products.shape[0]]
        start += products.shape[0]
        parts.append((F_lane, lane_FtX[:, idx] + np.outer(F_lane.sum(axis=0), level[idx])))
    return coef, FtI, FtF, third, saturated[idx], [threads for _, _, _, threads in results], parts


def frame_moments(F):
    """F'F (3, 3) and the third moments sum_t F_tk F_t F_t' (3, 3, 3) of frame factors F (frame, 3)."""
    third = ((F[:, :, None] * F[:, None, :]).reshape(-1, 9).T @ F).reshape(3, 3, 3).transpose(2, 0, 1)
    return F.T @ F, third


def photon_floor(G_phys, FtF, *, third, gain, read_noise, k_norm):
    """Per-pixel 1-sigma offset error from photon and read noise for the unweighted temporal fit.

    Sample variance (adu^2) of pixel p at frame t: F_t.G_p / g + sigma_r^2; so
    cov(G_p) = (F'F)^-1 [sum_k G_pk/g M_k + sigma_r^2 F'F] (F'F)^-1 with
    M_k = sum_t F_tk F_t F_t'. Then theta = atan2(g2, g3) and
    delta = theta / |K| propagate it linearly: var(theta) = u' [...] u with
    u = (F'F)^-1 d theta / dG, formed without the per-pixel 3x3 covariances.
    """
    inv = np.linalg.inv(FtF)
    a, b = G_phys[:, 1], G_phys[:, 2]  # alpha sin theta, alpha cos theta
    r2 = a**2 + b**2
    gradient = np.column_stack([np.zeros_like(a), b / r2, -a / r2])  # d theta / d G
    u = gradient @ inv  # (F'F)^-1 is symmetric
    outer = (u[:, :, None] * u[:, None, :]).reshape(-1, 9)
    photon = np.sum(G_phys / gain * (outer @ third.reshape(3, 9).T), axis=1)  # sum_k G_pk/g u'M_k u
    read = np.asarray(read_noise) ** 2 * (outer @ FtF.ravel())
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


def _phase_coverage(phase, bins=16):
    """Fraction of 2 pi visited by the wrapped phase, in ``bins`` equal sectors."""
    sectors = np.floor(np.mod(phase, 2 * np.pi) / (2 * np.pi) * bins).astype(int)
    return np.unique(np.clip(sectors, 0, bins - 1)).size / bins


@one_blas_thread
def fit_baseline(stream, dark, *, detector, flat=None, read_noise=None, tolerance=1e-7, max_passes=10,
                 min_contrast=0.02, min_relative_contrast=0.5, smooth_degree=6, workers=1,
                 geometry: BaselineGeometry | None = None, bad_pixels=None, label="baseline") -> FringeSolution:
    """Global fringe solution of one metrology acquisition.

    Pass 1 fits every frame with perfect pixels (iota = alpha = 1, no
    offsets) and the wavevector free per frame, linearised about the FFT
    estimate of frame 0: it gives K(t) and a first set of frame factors. Each
    later pass reads the cube once with the pixel factors of the previous one.
    After each pass the gauge is fixed (:func:`fix_gauge`), the pixel phases
    give the mean K and the projected offsets, and the passes stop when no
    offset moves by more than ``tolerance``. With a ``geometry`` (spherical
    waves), the converged pixel phases are then measured against the two-source
    surface of the refined fiber tips (:func:`dice_core.geometry.fit_two_source`):
    the passes themselves do not depend on the shape of the fringes, only this
    last step does.

    Parameters
    ----------
    stream : re-iterable of Chunk
        Raw frames (e.g. :class:`dice_core.io.FrameStream`); read once per pass.
    dark : ndarray (row, col)
        Mean dark, adu.
    detector : Detector
        Science area (the pixels fitted) and gain (e-/adu).
    flat : ndarray (row, col), optional
        PRNU map; used only to tell the intensity map from the fringe (iota /
        flat is smooth), never to correct the data. Without it the gauge falls
        back on the smoothness of the pixel contrast, which the pixel-to-pixel
        spread of PRF widths makes slightly noisier.
    read_noise : ndarray (row, col), optional
        Read noise, adu rms, for the photon-noise floor (0 if not given).
    tolerance : float
        Convergence: largest change of any offset between passes, pixel.
        Pixels still changing by more after ``max_passes`` are masked.
    max_passes : int
        At least 2.
    min_contrast : float
        Fringe contrast (alpha A / iota B) below which the fit is refused (for
        the median pixel) or a pixel is masked.
    min_relative_contrast : float
        A pixel whose contrast is below this fraction of the median is masked:
        its phase does not come from the fringe (PRNU and dust scale iota and
        alpha alike and leave the contrast unchanged).
    smooth_degree : int
        Degree of the polynomial that iota / flat follows.
    workers : int
        Processes that read the stream's parts at once. A stream with a
        ``split`` method (:class:`dice_core.io.FrameStream`) is always reduced
        in the same consecutive parts (``LANES``, groups of whole files), one
        after the other with one worker: the result does not depend on
        ``workers``, only the time does. Every process runs one BLAS thread,
        whatever the environment says (:mod:`dice_core.parallel`).
    geometry : BaselineGeometry, optional
        The baseline's fiber tips (nominal) and bench: spherical-wave fringes.
        Without it the fringes are plane waves.
    bad_pixels : ndarray (row, col), optional
        Pixels to leave out from the start: a bool map, or the bad-pixel
        mask's flags (``bad_pixel`` of ``calibration/bad_pixels.nc``), of which
        the unusable ones (dead, hot, column: :data:`dice_core.calibration.UNUSABLE`;
        dust pixels are kept). They enter neither the frame fits nor the plane
        of K, and have no offset.
    label : str
        Name in log messages and errors.

    Returns
    -------
    FringeSolution

    Raises
    ------
    FringeError
        Phase sweep not covering 2 pi, no fringe contrast, no pixel converged.
    ValueError
        ``max_passes`` under 2.
    """
    if max_passes < 2:
        raise ValueError(f"max_passes must be >= 2 (the convergence test compares two passes), got {max_passes}")
    mask = detector.science_mask()
    dark0 = np.nan_to_num(dark)
    first = first_chunk(stream)
    reference = first.frames.mean(axis=0)  # centres the float32 products (see _pass)
    centred = hasattr(stream, "centred")
    if centred:  # the reader subtracts it while converting, at no extra pass; _pass only folds it in
        stream = stream.centred(reference)
    bad = _left_out(bad_pixels, mask)
    k0 = initial_wavevector(first.frames[0] - dark0, mask & ~bad)
    log.info("%s: wavevector from the FFT of frame 0: (%.5f, %.5f) rad/pixel", label, *k0)
    rows, cols = np.nonzero(mask)
    idx = rows * detector.shape[1] + cols
    x, y = cols.astype(float), rows.astype(float)

    lanes = stream.split(LANES) if hasattr(stream, "split") else [stream]
    with lane_executor(workers, len(lanes)) as executor:
        log.info("%s: each pass reads %d part(s) of the frames, in %d process(es)", label, len(lanes),
                 lane_workers(workers, len(lanes)))

        def read(pixels, G, extra=None):
            """One pass over the frames (:func:`_pass`) with the pixel factors ``G`` of ``pixels``."""
            return _pass(lanes, dark0, pixels, G, extra=extra, reference=reference, centred=centred,
                         executor=executor)

        first_pass, k_frame = _first_pass(read, k0, idx, x, y, bad.ravel()[idx], executor=executor,
                                          min_contrast=min_contrast, label=label)
        passes = _converge(read, first_pass, idx, x, y, bad.ravel()[idx], k_frame.mean(axis=0), flat=flat,
                           tolerance=tolerance, max_passes=max_passes, min_contrast=min_contrast,
                           min_relative_contrast=min_relative_contrast, smooth_degree=smooth_degree, label=label)
    active = passes.active
    factors = _pixel_solution(passes, x[active], y[active], geometry=geometry,
                              read_noise=None if read_noise is None else read_noise.ravel()[idx[active]],
                              gain=detector.gain, label=label)
    offsets = passes.offsets if factors.two_source is None else _on_active(factors.two_source.offsets, active)
    if passes.faint.any():
        log.warning("%s: %d pixel(s) without fringe contrast masked", label, passes.faint.sum())
    offsets_prnu_free = gauge_floor = None
    if flat is not None:
        offsets_prnu_free, gauge_floor = _gauge_diagnostic(
            passes, factors, x[active], y[active], np.nan_to_num(flat.ravel()[idx[active]], nan=1.0),
            np.isin(passes.parts_idx, idx[active]), smooth_degree=smooth_degree, label=label)
        if offsets_prnu_free is not None:
            offsets_prnu_free = _on_active(offsets_prnu_free, active)
    reasons = {"bad_pixel": int(passes.flagged.sum()), "saturated": int(passes.saturated.sum()),
               "no_contrast": int(passes.faint.sum()), "unconverged": int(passes.unconverged.sum())}
    iota, alpha = factors.iota, factors.alpha
    return FringeSolution(rows, cols, offsets, _on_active(iota / iota.mean(), active),
                          _on_active(alpha / alpha.mean(), active), _on_active(factors.floor, active), factors.k,
                          k_frame, factors.level, factors.amplitude, factors.phase, passes.history, ~active, reasons,
                          offsets_prnu_free, _on_active(factors.theta, active), factors.two_source, gauge_floor)


def _on_active(values, active):
    """Values of the ``active`` pixels placed on all the pixels (pixel,), NaN elsewhere."""
    out = np.full(active.size, np.nan)
    out[active] = values
    return out


def _left_out(bad_pixels, mask):
    """The pixels of ``mask`` left out from the start (row, col) of bool: the unusable ones of ``bad_pixels``
    (a bool map, or the bad-pixel mask's flags: :func:`dice_core.calibration.unusable_pixels`)."""
    bad = np.zeros(mask.shape, bool)
    if bad_pixels is not None:
        from dice_core.calibration import unusable_pixels

        bad_pixels = np.asarray(bad_pixels)
        bad = (bad_pixels if bad_pixels.dtype == bool else unusable_pixels(bad_pixels)) & mask
    return bad


def _check_sweep(coef, *, min_contrast, label):
    """Refuse a pass-1 fit (frame coefficients (frame, 3 + m)) without fringe contrast or whose phase sweep
    does not cover 2 pi (:class:`FringeError`)."""
    u1, u2 = coef[:, 1], coef[:, 2]
    amp2 = u1**2 + u2**2
    if np.median(np.sqrt(amp2) / np.abs(coef[:, 0])) < min_contrast:
        raise FringeError(f"{label}: no fringe contrast (amplitude/level "
                          f"{np.median(np.sqrt(amp2) / np.abs(coef[:, 0])):.1e} < {min_contrast})")
    coverage = _phase_coverage(np.arctan2(u2, u1))
    if coverage < 1:
        raise FringeError(f"{label}: the phase sweep covers only {coverage * 360:.0f} of 360 degrees; "
                          "every pixel must see at least a full fringe period")


def _first_pass(read, k0, idx, x, y, bad, *, executor, min_contrast, label):
    """Pass 1: perfect pixels, the wavevector free per frame and linearised about ``k0`` (rad/pixel).

    ``read(pixels, G, extra)`` runs a pass (:func:`_pass`); ``bad`` (pixel,)
    leaves pixels out of the frame fits. Returns the pass's results and K(t)
    (frame, 2), rad/pixel; raises :class:`FringeError` on a sweep without
    contrast or short of a period.
    """
    G, extra = perfect_pixel_design(k0, x - x.mean(), y - y.mean())
    G[bad] = 0.0  # bad pixels out of the frame fits from the first pass on
    extra[bad] = 0.0
    result = read(idx, G, extra)
    log.info("%s: %s", label, threads_report(executor, result[5]))
    _check_sweep(result[0], min_contrast=min_contrast, label=label)
    k_frame = wavevector_per_frame(result[0], k0)
    log.info("%s: pass 1, K(t) mean (%.6f, %.6f), rms (%.2e, %.2e) rad/pixel", label,
             *k_frame.mean(axis=0), *k_frame.std(axis=0))
    return result, k_frame


@dataclass
class _Passes:
    """What the passes of :func:`_converge` leave: the pixels and the last pass's factors.

    ``active`` (pixel,) the pixels with an offset; ``flagged``, ``saturated``,
    ``faint``, ``unconverged`` (pixel,) those left out and why; ``offsets``
    (pixel,) the plane-wave projected offsets, pixel; ``F``, ``G`` the
    physical frame and pixel factors (frame, 3), (active pixel, 3); ``FtF``
    and ``third`` the frame moments in the physical gauge; ``k`` the mean
    wavevector, rad/pixel; ``history`` the changes per pass; ``parts`` and
    ``parts_idx`` each lane's frame factors and F'I of the last pass, over the
    pixels ``parts_idx``.
    """

    active: np.ndarray
    flagged: np.ndarray
    saturated: np.ndarray
    faint: np.ndarray
    unconverged: np.ndarray
    offsets: np.ndarray
    F: np.ndarray
    G: np.ndarray
    FtF: np.ndarray
    third: np.ndarray
    k: np.ndarray
    history: list
    parts: list
    parts_idx: np.ndarray


def _converge(read, first_pass, idx, x, y, flagged, k_guess, *, flat, tolerance, max_passes, min_contrast,
              min_relative_contrast, smooth_degree, label) -> _Passes:
    """Passes from pass 1's results until no offset moves by more than ``tolerance`` (pixel).

    Pixels leave the fit when found unusable, so that they bias neither the
    frame fits nor the plane of K: first the ``flagged`` ones and those with
    saturated samples, then, pass by pass, those without fringe contrast;
    after ``max_passes``, those still moving.
    """
    coef, FtI, FtF, third, saturated, _, parts = first_pass
    parts_idx = idx
    saturated &= ~flagged
    active = ~saturated & ~flagged
    if flagged.any():
        log.info("%s: %d bad pixel(s) of the mask left out of the fit", label, flagged.sum())
    if saturated.any():
        log.warning("%s: %d pixel(s) with saturated samples left out of the fit", label, saturated.sum())
    FtI = FtI[:, active]
    faint, unconverged = np.zeros(idx.size, bool), np.zeros(idx.size, bool)
    history, offsets, state = [], np.full(idx.size, np.nan), None
    for n_pass in range(1, max_passes + 1):
        fit_idx = idx[active]
        if n_pass > 1:
            coef, FtI, FtF, third, _, _, parts = read(fit_idx, np.linalg.solve(FtF, FtI).T)
            parts_idx = fit_idx
        F = coef[:, :3]
        G_new = np.linalg.solve(FtF, FtI).T
        fx, fy = x[active], y[active]
        flat_px = None if flat is None else np.nan_to_num(flat.ravel()[fit_idx], nan=1.0)
        M = fix_gauge(F, G_new, flat=flat_px, x=fx, y=fy, smooth_degree=smooth_degree)
        F_phys, G_phys = F @ M, G_new @ np.linalg.inv(M).T
        low = _without_contrast(F_phys, G_phys, min_contrast=min_contrast,
                                min_relative_contrast=min_relative_contrast, label=label)
        if low.any():
            log.warning("%s: pass %d, %d pixel(s) without fringe contrast left out", label, n_pass, low.sum())
            where = np.flatnonzero(active)[low]
            faint[where] = True
            active[where] = False
            G_phys, FtI = G_phys[~low], FtI[:, ~low]
            fx, fy = fx[~low], fy[~low]
        k, fitted = projected_offsets(np.arctan2(G_phys[:, 1], G_phys[:, 2]), fx, fy, k_guess)
        new_offsets = _on_active(fitted, active)
        if n_pass > 1:
            change = (new_offsets - offsets)[active]
            history.append({"pass": n_pass, "max_change": float(np.max(np.abs(change))),
                            "rms_change": float(np.sqrt(np.mean(change**2)))})
            log.info("%s: pass %d, offsets changed by %.2e pixel max, %.2e rms", label, n_pass,
                     history[-1]["max_change"], history[-1]["rms_change"])
        offsets = new_offsets
        state = (F_phys, G_phys, M.T @ FtF @ M, np.einsum("ak,bi,cj,abc->kij", M, M, M, third), k)
        if history and history[-1]["max_change"] < tolerance and not low.any():
            break
    else:
        # A pixel still moving by more than the tolerance has no offset to trust: masked,
        # and the plane of K and the offsets' normalisation taken over the others.
        moving = np.abs(change) >= tolerance
        log.warning("%s: not converged to %.1e pixel after %d passes; %d pixel(s) still moving masked",
                    label, tolerance, max_passes, moving.sum())
        where = np.flatnonzero(active)[moving]
        unconverged[where] = True
        active[where] = False
        if not active.any():
            raise FringeError(f"{label}: no pixel converged to {tolerance:.1e} pixel in {max_passes} passes")
        F_phys, G_phys, FtF_phys, third_phys, _ = state
        G_phys = G_phys[~moving]
        k, fitted = projected_offsets(np.arctan2(G_phys[:, 1], G_phys[:, 2]), fx[~moving], fy[~moving], k_guess)
        offsets = _on_active(fitted, active)
        state = (F_phys, G_phys, FtF_phys, third_phys, k)
    return _Passes(active, flagged, saturated, faint, unconverged, offsets, *state, history, parts, parts_idx)


def _without_contrast(F_phys, G_phys, *, min_contrast, min_relative_contrast, label):
    """The pixels (rows of ``G_phys``) whose fringe contrast alpha A / (iota B), with the frame factors at
    their median level and amplitude, is below ``min_contrast`` or ``min_relative_contrast`` times the
    median; :class:`FringeError` when the median itself is below ``min_contrast``."""
    contrast = (np.hypot(G_phys[:, 1], G_phys[:, 2]) / G_phys[:, 0]
                * np.median(np.hypot(F_phys[:, 1], F_phys[:, 2])) / np.median(F_phys[:, 0]))
    if np.median(contrast) < min_contrast:
        raise FringeError(f"{label}: no fringe contrast (median {np.median(contrast):.1e} < {min_contrast})")
    return contrast < max(min_contrast, min_relative_contrast * np.median(contrast))


@dataclass
class _PixelSolution:
    """The physical quantities of the converged factors (:func:`_pixel_solution`), over the active pixels."""

    theta: np.ndarray
    iota: np.ndarray
    alpha: np.ndarray
    floor: np.ndarray
    k: np.ndarray
    level: np.ndarray
    amplitude: np.ndarray
    phase: np.ndarray
    two_source: TwoSourceFit | None


def _pixel_solution(passes: _Passes, x, y, *, geometry, read_noise, gain, label) -> _PixelSolution:
    """Pixel phases, iota, alpha and photon floors (at the active pixels ``x``, ``y``), B(t), A(t), phi(t)
    and the mean K of the converged factors; with a ``geometry``, the phases measured against the
    two-source surface of the refined tips (K then the mean of the local wavevectors)."""
    F_phys, G_phys, k = passes.F, passes.G, passes.k
    theta = np.arctan2(G_phys[:, 1], G_phys[:, 2])
    two_source, k_norm = None, np.hypot(*k)
    if geometry is not None:
        two_source = fit_two_source(theta, x, y, *geometry.nominal, wavelength=geometry.wavelength,
                                    pixel_pitch=geometry.pixel_pitch, k_plane=k, tip_sigma=geometry.tip_sigma,
                                    fibers=geometry.fibers, label=label)
        k, k_norm = two_source.k_local.mean(axis=0), np.hypot(*two_source.k_local.T)
    noise_px = np.zeros(x.size) if read_noise is None else np.nan_to_num(read_noise)
    iota = G_phys[:, 0]
    alpha = np.hypot(G_phys[:, 1], G_phys[:, 2])
    return _PixelSolution(theta=theta, iota=iota, alpha=alpha,
                          floor=photon_floor(G_phys, passes.FtF, third=passes.third, gain=gain,
                                                     read_noise=noise_px, k_norm=k_norm), k=k,
                          level=F_phys[:, 0] * iota.mean(), amplitude=np.hypot(F_phys[:, 1], F_phys[:, 2]) * alpha.mean(),
                          phase=np.arctan2(F_phys[:, 2], F_phys[:, 1]), two_source=two_source)


def _gauge_diagnostic(passes: _Passes, solution: _PixelSolution, x, y, flat, keep, *, smooth_degree, label):
    """The offsets under the PRNU-free gauge (active pixels ``x``, ``y``) and the noise of their difference
    from the flat gauge's (pixel); None for what cannot be formed.

    The diagnostic of a flat that is not the laser's response (chromatic PRNU,
    speckle): the same factorisation under the PRNU-free gauge (the pixel
    contrast's smoothness), which the flat (``flat``, at the active pixels)
    does not enter. The passes do not depend on the gauge, so this costs no
    pass. The noise comes from the gauge difference of each independent part
    of the frames (the lanes; ``keep`` selects the active pixels among
    ``passes.parts_idx``): for two halves, the full data's difference has the
    noise of half their difference.
    """
    k, two_source = solution.k, solution.two_source

    def offsets_under(F_any, G_any, use_flat):
        """Offsets (active pixels) of a factorisation under one gauge, turned the way of ``k``."""
        M_any = fix_gauge(F_any, G_any, flat=flat if use_flat else None, x=x, y=y, smooth_degree=smooth_degree)
        G_gauged = G_any @ np.linalg.inv(M_any).T
        theta_any = np.arctan2(G_gauged[:, 1], G_gauged[:, 2])
        k_any, plane = projected_offsets(theta_any, x, y, k)
        if two_source is not None:  # against the same surface, the phases turned the same way
            return two_source.offsets_of(theta_any if k_any @ k > 0 else -theta_any)
        return plane if k_any @ k > 0 else -plane

    try:
        free = offsets_under(passes.F, passes.G, False)
    except FringeError as exc:  # a diagnostic must not fail a fit the flat's gauge made
        log.warning("%s: no PRNU-free gauge for the diagnostic (%s)", label, exc)
        return None, None
    try:
        halves = []
        for F_part, FtI_part in passes.parts:
            G_part = np.linalg.solve(F_part.T @ F_part, FtI_part[:, keep]).T
            halves.append(offsets_under(F_part, G_part, True) - offsets_under(F_part, G_part, False))
    except (FringeError, np.linalg.LinAlgError) as exc:
        log.warning("%s: no noise floor for the gauge difference (%s)", label, exc)
        return free, None
    if len(halves) != 2:
        log.info("%s: the frames are one part (one file): no noise floor for the gauge difference", label)
        return free, None
    # the whole is (n1 d1 + n2 d2) / (n1 + n2): of noise rms(d1 - d2) sqrt(n1 n2) / (n1 + n2)
    n1, n2 = (F_part.shape[0] for F_part, _ in passes.parts)
    return free, float(np.sqrt(np.mean((halves[0] - halves[1]) ** 2) * n1 * n2) / (n1 + n2))


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
                    **({"mode": np.arange(len(solution.two_source.modes))} if len(solution.two_source.modes) else {})
                })},
    )
