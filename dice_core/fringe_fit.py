"""The streaming fringe fit of one metrology baseline: its passes over the frames and the state they carry.

The fit finds the rank-3 factorisation I(p, t) = F(t) . G(p) of the fringe
model (:mod:`dice_core.fringes`, which also says what the factors mean). It
alternates two linear least-squares fits with small shared design matrices:
frame factors with the pixel factors fixed (the paper's spatial fit,
linearised), then pixel factors with the frame factors fixed (the paper's
temporal sine fit of appendix B). Each pass reads the cube once, in chunks: a
chunk's frame factors first, then that chunk's contribution to the per-pixel
normal equations. The frames are read in consecutive parts (lanes) summed in
order, in one process, in worker processes or in separate jobs, for the same
bits.

:func:`fit_baseline` runs the whole fit in one process; a fit split across
jobs (docs/metrology.md, "Splitting a fit across jobs") runs its steps
(:func:`start_fit`, :func:`accumulate_part`, :func:`reduce_pass`,
:func:`finish_fit`) as separate jobs, its state and part products written and
read through :mod:`dice_core.io`. The gauge, the offsets, the photon floor and
the solution's product are :mod:`dice_core.fringes`'.

Units: pixel for positions and offsets, rad for phases, rad/pixel for K,
adu for B and A.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from dice_core import io, lazy
from dice_core.fringes import (FringeError, FringeSolution, fix_gauge, frame_moments, initial_wavevector,
                               perfect_pixel_design, photon_floor, projected_offsets, wavevector_per_frame)
from dice_core.geometry import BaselineGeometry, TwoSourceFit, fit_two_source
from dice_core.io import Chunk, FrameStream, first_chunk
from dice_core.parallel import (LANES, blas_threads, lane_executor, lane_workers, map_lanes, one_blas_thread,
                                threads_report)
from dice_core.pixel_blocks import pixel_blocks

xr = lazy.module("xarray")  # products only: a fit job reaches its first line before xarray and pandas load

__all__ = [
    "fit_baseline",
    "FitState",
    "check_state_options",
    "metrology_stream",
    "PassInputs",
    "start_fit",
    "fit_stream",
    "accumulate_part",
    "reduce_pass",
    "finish_fit",
    "state_dataset",
    "state_from_dataset",
    "part_dataset",
    "reduce_dataset",
]

log = logging.getLogger(__name__)


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


@dataclass
class PassInputs:
    """What each part of a pass needs besides its frames: the projector onto the frame factors.

    Attributes
    ----------
    projector : ndarray (grid, m)
        Over every detector pixel (row-major), zero outside ``pixels``: the
        least-squares projector ``design (design' design)^-1`` of the pass's
        pixel design (3 pixel factors, plus the 4 K(t) terms in pass 1).
    offset : ndarray (m,)
        What the reference level minus the dark adds to the frame products, -(r - d) projector, adu.
    pixels : ndarray (pixel,) of int
        Row-major indices of the pixels of the design.
    centre : ndarray (grid,)
        The reference frame r, adu.
    subtract_centre : bool
        Whether the part subtracts r from each chunk itself (its chunks do not hold X - r already).
    """

    projector: np.ndarray
    offset: np.ndarray
    pixels: np.ndarray
    centre: np.ndarray
    subtract_centre: bool


def _pass_inputs(level, pixels, G, extra=None, *, centre, subtract_centre) -> PassInputs:
    """The projector of the design ``G`` (``extra`` appended) of ``pixels``; ``level`` (grid,) is r - d."""
    design = G if extra is None else np.column_stack([G, extra])
    projector = np.zeros((level.size, design.shape[1]))
    projector[pixels] = design @ np.linalg.inv(design.T @ design)
    return PassInputs(projector, -(level @ projector), pixels, centre, bool(subtract_centre))


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
    in lane order (:func:`_combine`): the result does not depend on which.
    ``extra`` (pixel, m) adds regressors to the frame fit only (the K(t) terms).
    Returns what :func:`_combine` returns.
    """
    centre = np.zeros(dark.size) if reference is None else reference.ravel().astype(np.float64)
    level = centre - dark.ravel()  # X - d = (X - r) + (r - d)
    inputs = _pass_inputs(level, idx, G, extra, centre=centre, subtract_centre=reference is not None and not centred)
    results = map_lanes(executor, _accumulate, lanes, inputs.projector, inputs.offset, centre, inputs.subtract_centre)
    return _combine(results, inputs=inputs, level=level, n_lanes=len(lanes))


def _combine(results, *, inputs: PassInputs, level, n_lanes):
    """Sum the lanes' results of a pass (:func:`_accumulate`), in lane order, into the pass's normal equations.

    ``results`` is an iterable of the ``n_lanes`` lanes' results, consumed
    one at a time (a split fit reads them from files: one lane's F'X in
    memory at once, whatever the number of lanes). ``level`` (grid,) is r - d.

    Returns frame factors (frame, 3 [+m]), F'I (3, pixel), F'F (3, 3), the
    third moments sum_t F_tk F_t F_t' (3, 3, 3), the pixels of ``inputs.pixels``
    holding a saturated sample, the BLAS threads each lane ran with, and the
    frame factors (frame of the half, 3) and F'I (3, pixel) of each half of the
    lanes, the first ``n_lanes // 2`` and the others (one part for one lane),
    for diagnostics that compare independent parts of the frames.
    """
    idx, offset = inputs.pixels, inputs.offset
    n_pixels = level.size
    products, threads = [], []
    FtX, saturated = np.zeros((3, n_pixels)), np.zeros(n_pixels, bool)
    halves, half_frames = [None, None], [0, 0]
    for lane, (lane_products, lane_FtX, lane_saturated, lane_threads) in enumerate(results):
        products.append(lane_products)
        FtX += lane_FtX
        saturated |= lane_saturated
        threads.append(lane_threads)
        half = 0 if lane < n_lanes // 2 else 1
        if halves[half] is None:
            halves[half] = lane_FtX[:, idx]
        else:
            for k in range(3):  # a factor at a time: a third of the copy of the lane's F'X at the pixels
                halves[half][k] += lane_FtX[k, idx]
        half_frames[half] += lane_products.shape[0]
    if len(products) != n_lanes:
        raise ValueError(f"{len(products)} lane result(s) for a pass of {n_lanes} lane(s)")
    coef = np.concatenate(products).astype(np.float64) - offset
    if coef.shape[0] == 0:
        raise FringeError("no frames to fit")
    F = coef[:, :3]
    # Sums over frames, from the frame factors kept for the product anyway: vectorised once
    # per pass instead of a few small operations per chunk.
    level_idx = level[idx]
    FtI = _add_level(FtX[:, idx], F, level_idx)
    del FtX  # (3, grid): the pass's largest array
    FtF, third = frame_moments(F)
    parts, start = [], 0
    for half_FtX, n in zip(halves, half_frames):
        if half_FtX is None:
            continue
        F_half = F[start:start + n]
        start += n
        parts.append((F_half, _add_level(half_FtX, F_half, level_idx)))
    return coef, FtI, FtF, third, saturated[idx], threads, parts


def _add_level(FtX, F, level):
    """F'(X - d) from F'X (3, pixel) of frames X - r: F'X + (F'1) (r - d)', with ``level`` = r - d (pixel,);
    in place, a factor at a time (the bits of the outer product's sum, without forming it)."""
    for k, total in enumerate(F.sum(axis=0)):
        FtX[k] += total * level
    return FtX


def _phase_coverage(phase, bins=16):
    """Fraction of 2 pi visited by the wrapped phase, in ``bins`` equal sectors."""
    sectors = np.floor(np.mod(phase, 2 * np.pi) / (2 * np.pi) * bins).astype(int)
    return np.unique(np.clip(sectors, 0, bins - 1)).size / bins


@one_blas_thread
def fit_baseline(stream, dark, *, detector, flat=None, read_noise=None, tolerance=1e-7, max_passes=10,
                 min_contrast=0.02, min_relative_contrast=0.5, smooth_degree=6, workers=1, parts=LANES,
                 geometry: BaselineGeometry | None = None, bad_pixels=None, label="baseline") -> FringeSolution:
    """Global fringe solution of one metrology acquisition.

    Pass 1 fits every frame with perfect pixels (iota = alpha = 1, no
    offsets) and the wavevector free per frame, linearised about the FFT
    estimate of frame 0: it gives K(t) and a first set of frame factors. Each
    later pass reads the cube once with the pixel factors of the previous one.
    After each pass the gauge is fixed (:func:`dice_core.fringes.fix_gauge`),
    the pixel phases give the mean K and the projected offsets, and the passes
    stop when no offset moves by more than ``tolerance``. With a ``geometry`` (spherical
    waves), the converged pixel phases are then measured against the two-source
    surface of the refined fiber tips (:func:`dice_core.geometry.fit_two_source`):
    the passes themselves do not depend on the shape of the fringes, only this
    last step does.

    The fit is the loop of :func:`start_fit`, a pass over each part of the
    frames (:func:`accumulate_part`), :func:`reduce_pass`, then
    :func:`finish_fit`; a split fit runs the same steps as separate jobs
    (docs/metrology.md, "Splitting a fit across jobs").

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
        Processes that read the stream's parts at once. The result does not
        depend on ``workers``, only the time does. Every process runs one BLAS
        thread, whatever the environment says (:mod:`dice_core.parallel`).
    parts : int
        A stream with a ``split`` method (:class:`dice_core.io.FrameStream`) is
        reduced in up to this many consecutive parts (groups of whole files),
        summed in order: the same parts give the same result bit for bit,
        whether one process reads them, several, or separate jobs.
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
    state = start_fit(stream, dark, detector=detector, flat=flat, tolerance=tolerance, max_passes=max_passes,
                      min_contrast=min_contrast, min_relative_contrast=min_relative_contrast,
                      smooth_degree=smooth_degree, bad_pixels=bad_pixels, label=label)
    stream = fit_stream(stream, state.next_pass)
    lanes = stream.split(parts) if hasattr(stream, "split") else [stream]
    with lane_executor(workers, len(lanes)) as executor:
        log.info("%s: each pass reads %d part(s) of the frames, in %d process(es)", label, len(lanes),
                 lane_workers(workers, len(lanes)))
        while not state.done:
            results = map_lanes(executor, accumulate_part, lanes, state.next_pass)
            if state.n_pass == 0:
                log.info("%s: %s", label, threads_report(executor, [lane[3] for lane in results]))
            state = reduce_pass(state, results, n_lanes=len(lanes))
    return finish_fit(state, detector=detector, read_noise=read_noise, geometry=geometry)


@dataclass
class FitState:
    """What the passes of a fringe fit carry from one to the next (:func:`start_fit`, :func:`reduce_pass`).

    Pixel arrays run over the science area (``rows``, ``cols``; ``pixel``),
    those of the fit over its active pixels in that order (``active``), grid
    arrays over every detector pixel, row-major. A split fit writes it
    between its jobs (:func:`state_dataset`, :func:`state_from_dataset`); every
    value round-trips exactly, so the next job computes what the same
    process would have.

    Attributes
    ----------
    rows, cols : ndarray (pixel,) of int
        Science-area pixels.
    n_cols : int
        Columns of the detector (row-major index = row n_cols + col).
    centre : ndarray (grid,)
        Reference frame r the samples are centred on (the first chunk's mean), adu.
    level : ndarray (grid,)
        r - d, the reference minus the dark, adu. These two and ``FtI`` are None in a done state
        read back (:func:`state_dataset`): only a pass reads them.
    subtract_centre : bool
        Whether a pass subtracts r from each chunk itself (a stream that cannot centre its samples).
    k0 : ndarray (2,)
        Wavevector of frame 0's Fourier transform, rad/pixel.
    flat : ndarray (pixel,) or None
        PRNU at the science pixels (NaN where unknown), for the gauge.
    options : dict
        tolerance, max_passes, min_contrast, min_relative_contrast, smooth_degree, label (see :func:`fit_baseline`).
    n_pass : int
        Passes reduced so far.
    done, converged : bool
        No pass left to read; the last pass met the tolerance.
    next_pass : PassInputs or None
        The projector of the next pass (None when done).
    flagged, saturated, faint, unconverged, active : ndarray (pixel,) of bool
        Pixels left out (bad, saturated sample, no contrast, not converged) and those fitted.
    k_frame : ndarray (frame, 2)
        K(t) from pass 1, rad/pixel.
    offsets : ndarray (pixel,)
        Projected offsets of the last pass, pixel (NaN off the active pixels).
    change : ndarray (active,)
        Their change from the pass before, pixel.
    FtF, FtI : ndarray (3, 3), (3, active)
        Normal equations of the last pass (its own gauge): the next pass's pixel factors.
    F, G, FtF_phys, third_phys, k :
        Physical frame factors (frame, 3), pixel factors (active, 3), frame moments (3, 3) and
        (3, 3, 3), mean wavevector (2,), rad/pixel.
    history : list of dict
        Per pass from the second: max and rms change of the offsets, pixel.
    parts : list of (ndarray (frame, 3), ndarray (3, part pixel))
        Each half of the frames' factors and F'I in the last pass (:func:`_combine`), over ``parts_idx``.
    """

    rows: np.ndarray
    cols: np.ndarray
    n_cols: int
    centre: np.ndarray
    level: np.ndarray
    subtract_centre: bool
    k0: np.ndarray
    flat: np.ndarray | None
    options: dict
    n_pass: int = 0
    done: bool = False
    converged: bool = False
    next_pass: PassInputs | None = None
    flagged: np.ndarray = None
    saturated: np.ndarray = None
    faint: np.ndarray = None
    unconverged: np.ndarray = None
    active: np.ndarray = None
    k_frame: np.ndarray = None
    offsets: np.ndarray = None
    change: np.ndarray = None
    FtF: np.ndarray = None
    FtI: np.ndarray = None
    F: np.ndarray = None
    G: np.ndarray = None
    FtF_phys: np.ndarray = None
    third_phys: np.ndarray = None
    k: np.ndarray = None
    history: list = field(default_factory=list)
    parts: list = field(default_factory=list)
    parts_idx: np.ndarray = None

    @property
    def idx(self) -> np.ndarray:
        """Row-major indices of the science pixels."""
        return self.rows * self.n_cols + self.cols

    def coordinates(self, pixels=None) -> tuple[np.ndarray, np.ndarray]:
        """x, y (pixel) of the science pixels ``pixels`` selects (a bool mask or indices; all without), as
        floats formed for those pixels only."""
        cols, rows = (self.cols, self.rows) if pixels is None else (self.cols[pixels], self.rows[pixels])
        return cols.astype(float), rows.astype(float)


def start_fit(stream, dark, *, detector, flat=None, tolerance=1e-7, max_passes=10, min_contrast=0.02,
              min_relative_contrast=0.5, smooth_degree=6, bad_pixels=None, label="baseline") -> FitState:
    """The state of a fit before its first pass: reference frame, initial wavevector, pass 1's projector.

    Reads the first chunk of ``stream`` only. Parameters as :func:`fit_baseline`'s.
    """
    if max_passes < 2:
        raise ValueError(f"max_passes must be >= 2 (the convergence test compares two passes), got {max_passes}")
    mask = detector.science_mask()
    dark0 = np.nan_to_num(dark)
    first = first_chunk(stream)
    reference = first.frames.mean(axis=0)  # centres the float32 products (see _pass)
    # A stream that can centre its samples does it while converting, at no extra pass (fit_stream);
    # the passes then only fold r into the algebra.
    subtract_centre = not hasattr(stream, "centred")
    bad = _left_out(bad_pixels, mask)
    k0 = initial_wavevector(first.frames[0] - dark0, mask & ~bad)
    log.info("%s: wavevector from the FFT of frame 0: (%.5f, %.5f) rad/pixel", label, *k0)
    rows, cols = np.nonzero(mask)
    centre = reference.ravel().astype(np.float64)
    options = {"tolerance": float(tolerance), "max_passes": int(max_passes), "min_contrast": float(min_contrast),
               "min_relative_contrast": float(min_relative_contrast), "smooth_degree": int(smooth_degree),
               "label": str(label)}
    state = FitState(rows, cols, detector.shape[1], centre, centre - dark0.ravel(), subtract_centre, k0,
                     None if flat is None else np.asarray(flat, np.float64).ravel()[rows * detector.shape[1] + cols],
                     options, flagged=bad.ravel()[rows * detector.shape[1] + cols])
    x, y = state.coordinates()
    G, extra = perfect_pixel_design(k0, x - x.mean(), y - y.mean())
    G[state.flagged] = 0.0  # bad pixels out of the frame fits from the first pass on
    extra[state.flagged] = 0.0
    state.next_pass = _pass_inputs(state.level, state.idx, G, extra, centre=centre, subtract_centre=subtract_centre)
    return state


def fit_stream(stream, inputs: PassInputs):
    """The stream a pass reads: centred on the reference frame of ``inputs`` where the stream can do it
    (a :class:`dice_core.io.FrameStream`; other streams are centred chunk by chunk by the pass itself)."""
    if inputs.subtract_centre:
        return stream
    return stream.centred(inputs.centre.reshape(stream.shape[1:]))


@one_blas_thread
def accumulate_part(chunks, inputs: PassInputs):
    """One part's (lane's) share of a pass (:func:`_accumulate`), with one BLAS thread.

    ``chunks`` come from :func:`fit_stream` (of the whole acquisition, or of
    one of its parts). Its memory: a chunk, the projector (grid, m) and F'X
    (3, grid), and the part's frame products (frame, m): what the part's own
    files hold, whatever the other parts.
    """
    return _accumulate(chunks, inputs.projector, inputs.offset, inputs.centre, inputs.subtract_centre)


def reduce_pass(state: FitState, results, *, n_lanes) -> FitState:
    """Sum a pass's part results (:func:`accumulate_part`, in part order) and take the pass's step.

    After each pass the gauge is fixed, pixels without fringe contrast leave
    the fit, and the projected offsets are compared with the previous pass's;
    the state is done when they moved by less than the tolerance (and no
    pixel left), or after ``max_passes``. ``state`` is updated and returned.
    """
    if state.done:
        raise ValueError(f"{state.options['label']}: the fit has no pass left to reduce")
    options, label = state.options, state.options["label"]
    coef, FtI, FtF, third, saturated, _, parts = _combine(results, inputs=state.next_pass, level=state.level,
                                                         n_lanes=n_lanes)
    idx = state.idx
    if state.n_pass == 0:
        _check_sweep(coef, min_contrast=options["min_contrast"], label=label)
        state.k_frame = wavevector_per_frame(coef, state.k0)
        log.info("%s: pass 1, K(t) mean (%.6f, %.6f), rms (%.2e, %.2e) rad/pixel", label,
                 *state.k_frame.mean(axis=0), *state.k_frame.std(axis=0))
        flagged = state.flagged
        saturated &= ~flagged
        state.active = ~saturated & ~flagged
        state.saturated = saturated
        if flagged.any():
            log.info("%s: %d bad pixel(s) of the mask left out of the fit", label, flagged.sum())
        if saturated.any():
            log.warning("%s: %d pixel(s) with saturated samples left out of the fit", label, saturated.sum())
        FtI = FtI[:, state.active]
        state.faint, state.unconverged = np.zeros(idx.size, bool), np.zeros(idx.size, bool)
        state.offsets = np.full(idx.size, np.nan)
    state.n_pass = n_pass = state.n_pass + 1
    state.parts, state.parts_idx = parts, state.next_pass.pixels
    active = state.active
    F = coef[:, :3]
    G_new = np.linalg.solve(FtF, FtI).T
    fx, fy = state.coordinates(active)
    flat_px = None if state.flat is None else np.nan_to_num(state.flat[active], nan=1.0)
    M = fix_gauge(F, G_new, flat=flat_px, x=fx, y=fy, smooth_degree=options["smooth_degree"])
    F_phys, G_phys = F @ M, G_new @ np.linalg.inv(M).T
    low = _without_contrast(F_phys, G_phys, min_contrast=options["min_contrast"],
                            min_relative_contrast=options["min_relative_contrast"], label=label)
    if low.any():
        log.warning("%s: pass %d, %d pixel(s) without fringe contrast left out", label, n_pass, low.sum())
        where = np.flatnonzero(active)[low]
        state.faint[where] = True
        active[where] = False
        G_phys, FtI = G_phys[~low], FtI[:, ~low]
        fx, fy = fx[~low], fy[~low]
    k, fitted = projected_offsets(np.arctan2(G_phys[:, 1], G_phys[:, 2]), fx, fy, state.k_frame.mean(axis=0))
    new_offsets = _on_active(fitted, active)
    history = state.history
    if n_pass > 1:
        change = (new_offsets - state.offsets)[active]
        history.append({"pass": n_pass, "max_change": float(np.max(np.abs(change))),
                        "rms_change": float(np.sqrt(np.mean(change**2)))})
        log.info("%s: pass %d, offsets changed by %.2e pixel max, %.2e rms", label, n_pass,
                 history[-1]["max_change"], history[-1]["rms_change"])
        state.change = change
    state.offsets = new_offsets
    state.FtF, state.FtI = FtF, FtI
    state.F, state.G, state.k = F_phys, G_phys, k
    state.FtF_phys, state.third_phys = M.T @ FtF @ M, np.einsum("ak,bi,cj,abc->kij", M, M, M, third)
    state.converged = bool(history and history[-1]["max_change"] < options["tolerance"] and not low.any())
    state.done = state.converged or n_pass >= options["max_passes"]
    state.next_pass = None if state.done else _pass_inputs(
        state.level, idx[active], np.linalg.solve(FtF, FtI).T, centre=state.centre,
        subtract_centre=state.subtract_centre)
    return state


def _converged_passes(state: FitState) -> _Passes:
    """The passes' result of a done state; pixels still moving masked if the passes did not converge."""
    options, label = state.options, state.options["label"]
    if not state.done:
        raise ValueError(f"{label}: the fit is not done (pass {state.n_pass} of at most {options['max_passes']})")
    active, unconverged = state.active.copy(), state.unconverged.copy()
    F_phys, G_phys, FtF_phys, third_phys, k = state.F, state.G, state.FtF_phys, state.third_phys, state.k
    offsets = state.offsets
    if not state.converged:
        # A pixel still moving by more than the tolerance has no offset to trust: masked,
        # and the plane of K and the offsets' normalisation taken over the others.
        tolerance, max_passes = options["tolerance"], options["max_passes"]
        moving = np.abs(state.change) >= tolerance
        log.warning("%s: not converged to %.1e pixel after %d passes; %d pixel(s) still moving masked",
                    label, tolerance, max_passes, moving.sum())
        where = np.flatnonzero(active)[moving]
        unconverged[where] = True
        active[where] = False
        if not active.any():
            raise FringeError(f"{label}: no pixel converged to {tolerance:.1e} pixel in {max_passes} passes")
        G_phys = G_phys[~moving]
        fx, fy = state.coordinates(active)
        k, fitted = projected_offsets(np.arctan2(G_phys[:, 1], G_phys[:, 2]), fx, fy, state.k_frame.mean(axis=0))
        offsets = _on_active(fitted, active)
    else:
        log.info("%s: converged to %.1e pixel at pass %d", label, options["tolerance"], state.n_pass)
    return _Passes(active, state.flagged, state.saturated, state.faint, unconverged, offsets, F_phys, G_phys,
                   FtF_phys, third_phys, k, state.history, state.parts, state.parts_idx)


def finish_fit(state: FitState, *, detector, read_noise=None,
               geometry: BaselineGeometry | None = None) -> FringeSolution:
    """The solution of a done fit (:func:`reduce_pass`): pixel phases, offsets, floors, the gauge diagnostic.

    ``read_noise`` (row, col) and ``geometry`` as in :func:`fit_baseline`.
    Pixels still moving after the last pass of an unconverged fit are masked
    here, the plane of K taken over the others. The state is spent: its pixel
    factors, the halves' F'I and the flat are dropped from it once used,
    before the two-source fit, so that a caller holding no other reference to
    them (the split fit's ``fit_finish`` job, :func:`fit_baseline`) frees them
    (64 bytes a pixel); a spent state cannot be finished again.
    """
    label, smooth_degree = state.options["label"], state.options["smooth_degree"]
    if state.done and state.G is None:
        raise ValueError(f"{label}: the state was finished already (finish_fit drops its pixel factors)")
    passes = _converged_passes(state)
    active = passes.active
    # the active pixels' coordinates only, formed once (every array here spans the pixels)
    x, y = state.coordinates(active)
    idx = state.idx[active]
    noise = None if read_noise is None else read_noise.ravel()[idx]
    phases = None
    if state.flat is not None:  # the diagnostic's gauges while the pixel factors and halves are there
        phases = _diagnostic_phases(passes, x, y, np.nan_to_num(state.flat[active], nan=1.0),
                                    np.isin(passes.parts_idx, idx), smooth_degree=smooth_degree, label=label)
    del idx

    def spend():
        state.G = state.flat = state.parts_idx = passes.G = None
        state.parts, passes.parts = [], []

    factors = _pixel_solution(passes, x, y, geometry=geometry, read_noise=noise, gain=detector.gain, label=label,
                              spend=spend)
    del noise
    offsets = passes.offsets if factors.two_source is None else _on_active(factors.two_source.offsets, active)
    if passes.faint.any():
        log.warning("%s: %d pixel(s) without fringe contrast masked", label, passes.faint.sum())
    offsets_prnu_free = gauge_floor = None
    if phases is not None:
        offsets_prnu_free, gauge_floor = _diagnostic_offsets(phases, factors, x, y, label=label)
        offsets_prnu_free = _on_active(offsets_prnu_free, active)
    reasons = {"bad_pixel": int(passes.flagged.sum()), "saturated": int(passes.saturated.sum()),
               "no_contrast": int(passes.faint.sum()), "unconverged": int(passes.unconverged.sum())}
    iota, alpha = factors.iota, factors.alpha
    return FringeSolution(state.rows, state.cols, offsets, _on_active(iota / iota.mean(), active),
                          _on_active(alpha / alpha.mean(), active), _on_active(factors.floor, active), factors.k,
                          state.k_frame, factors.level, factors.amplitude, factors.phase, passes.history, ~active,
                          reasons, offsets_prnu_free, _on_active(factors.theta, active), factors.two_source,
                          gauge_floor)


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


@dataclass
class _Passes:
    """What the passes leave (:func:`_converged_passes`): the pixels and the last pass's factors.

    ``active`` (pixel,) the pixels with an offset; ``flagged``, ``saturated``,
    ``faint``, ``unconverged`` (pixel,) those left out and why; ``offsets``
    (pixel,) the plane-wave projected offsets, pixel; ``F``, ``G`` the
    physical frame and pixel factors (frame, 3), (active pixel, 3); ``FtF``
    and ``third`` the frame moments in the physical gauge; ``k`` the mean
    wavevector, rad/pixel; ``history`` the changes per pass; ``parts`` and
    ``parts_idx`` each half's frame factors and F'I of the last pass, over the
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

# --- A fit split across jobs (docs/metrology.md, "Splitting a fit across jobs") ---------------------------
# Each job's product is a netCDF file: float64 values, float32 frame products and integers round-trip
# exactly, so the next job starts from the bits this process would have held.

_OPTIONS = ("tolerance", "max_passes", "min_contrast", "min_relative_contrast", "smooth_degree", "label")
_MASKS = ("flagged", "saturated", "faint", "unconverged", "active")
#: What only a pass reads of a state (the reference frame, r - d, the last pass's normal equations).
_PASS_ONLY = ("centre", "level", "FtI")

#: The variables of a fit's state product: name: (dims, units, long_name). ``pixel``: the science pixels,
#: ``fitted``: the active ones, ``grid``: every detector pixel, row-major.
_STATE_VARIABLES = {
    "rows": (("pixel",), "1", "row of each science-area pixel"),
    "cols": (("pixel",), "1", "column of each science-area pixel"),
    "centre": (("grid",), "adu", "reference frame r the samples are centred on (row-major)"),
    "level": (("grid",), "adu", "reference frame minus the dark, r - d (row-major)"),
    "k0": (("xy",), "rad/pixel", "wavevector of the Fourier transform of frame 0"),
    "flat": (("pixel",), "1", "PRNU at the science pixels, for the gauge"),
    **{name: (("pixel",), "1", f"1 where the pixel is {meaning}") for name, meaning in (
        ("flagged", "a bad pixel of the mask"), ("saturated", "left out for a saturated sample"),
        ("faint", "left out for no fringe contrast"), ("unconverged", "masked for not converging"),
        ("active", "still fitted"))},
    "k_frame": (("frame", "xy"), "rad/pixel", "wavevector per frame from pass 1"),
    "offsets": (("pixel",), "pixel", "projected offset of the last pass"),
    "change": (("fitted",), "pixel", "change of the offsets in the last pass"),
    "FtF": (("factor", "factor_b"), "adu2", "F'F of the last pass (its own gauge)"),
    "FtI": (("factor", "fitted"), "adu2", "F'I of the last pass (its own gauge)"),
    "F": (("frame", "factor"), "adu", "physical frame factors (B, A cos phi, A sin phi)"),
    "G": (("fitted", "factor"), "1", "physical pixel factors (iota, alpha sin theta, alpha cos theta)"),
    "FtF_phys": (("factor", "factor_b"), "adu2", "F'F of the physical frame factors"),
    "third_phys": (("factor", "factor_b", "factor_c"), "adu3", "third moments of the physical frame factors"),
    "k": (("xy",), "rad/pixel", "mean wavevector of the last pass"),
    "projector": (("grid", "design"), "1", "projector of the next pass's pixel design (row-major)"),
    "offset": (("design",), "adu", "frame products of r - d in the next pass"),
    "pixels": (("design_pixel",), "1", "row-major index of the pixels of the next pass's design"),
    "parts_idx": (("part_pixel",), "1", "row-major index of the pixels of the halves' F'I"),
}


def state_dataset(state: FitState) -> xr.Dataset:
    """A fit's state (:class:`FitState`) as a dataset (the split fit's ``state`` products); see
    :func:`state_from_dataset`. Scalars and options are attributes ``fit_*``. A done state leaves out what
    only a further pass reads (:data:`_PASS_ONLY`: 40 bytes a pixel that ``fit_finish`` would hold unused)."""
    values = {name: None if state.done and name in _PASS_ONLY else getattr(state, name, None)
              for name in _STATE_VARIABLES}
    if state.next_pass is not None:
        values.update(projector=state.next_pass.projector, offset=state.next_pass.offset,
                      pixels=state.next_pass.pixels)
    variables = {name: (_STATE_VARIABLES[name][0], value, {"units": _STATE_VARIABLES[name][1],
                                                           "long_name": _STATE_VARIABLES[name][2]})
                 for name, value in values.items() if value is not None}
    for h, (F_half, FtI_half) in enumerate(state.parts):
        variables[f"part_F_{h}"] = ((f"part_frame_{h}", "factor"), F_half,
                                    {"units": "adu", "long_name": f"frame factors of half {h} of the frames"})
        variables[f"part_FtI_{h}"] = (("factor", "part_pixel"), FtI_half,
                                      {"units": "adu2", "long_name": f"F'I of half {h} of the frames"})
    if state.history:
        for key, units in (("pass", "1"), ("max_change", "pixel"), ("rms_change", "pixel")):
            variables[f"history_{key}"] = (("iteration",), [h[key] for h in state.history],
                                           {"units": units, "long_name": f"convergence history: {key}"})
    attrs = {"fit_n_cols": int(state.n_cols), "fit_subtract_centre": int(state.subtract_centre),
             "fit_n_pass": int(state.n_pass), "fit_done": int(state.done), "fit_converged": int(state.converged),
             "fit_parts": len(state.parts), **{f"fit_{key}": state.options[key] for key in _OPTIONS}}
    return xr.Dataset(variables, attrs=attrs)


def state_from_dataset(ds: xr.Dataset) -> FitState:
    """The :class:`FitState` of :func:`state_dataset`'s dataset (loaded whole)."""
    def get(name):
        return ds[name].values if name in ds.data_vars else None

    attrs = ds.attrs
    missing = [key for key in ("fit_n_cols", "fit_n_pass", "fit_done", "fit_parts", *(f"fit_{k}" for k in _OPTIONS))
               if key not in attrs]
    if missing:
        raise FringeError(f"{ds.encoding.get('source', 'dataset')}: not a split fringe-fit state "
                          f"(no attribute {missing[0]})")
    options = {key: attrs[f"fit_{key}"] for key in _OPTIONS}
    options = {**options, "tolerance": float(options["tolerance"]), "max_passes": int(options["max_passes"]),
               "min_contrast": float(options["min_contrast"]),
               "min_relative_contrast": float(options["min_relative_contrast"]),
               "smooth_degree": int(options["smooth_degree"]), "label": str(options["label"])}
    subtract_centre = bool(attrs["fit_subtract_centre"])
    state = FitState(get("rows"), get("cols"), int(attrs["fit_n_cols"]), get("centre"), get("level"),
                     subtract_centre, get("k0"), get("flat"), options, n_pass=int(attrs["fit_n_pass"]),
                     done=bool(attrs["fit_done"]), converged=bool(attrs["fit_converged"]))
    for name in ("k_frame", "offsets", "change", "FtF", "FtI", "F", "G", "FtF_phys", "third_phys", "k",
                 "parts_idx", *_MASKS):
        setattr(state, name, get(name))
    if "projector" in ds.data_vars:
        state.next_pass = _pass_inputs_of(ds, state.centre)
    state.parts = [(get(f"part_F_{h}"), get(f"part_FtI_{h}")) for h in range(int(attrs["fit_parts"]))]
    if "history_pass" in ds.data_vars:
        state.history = [{"pass": int(p), "max_change": float(m), "rms_change": float(r)} for p, m, r in
                         zip(get("history_pass"), get("history_max_change"), get("history_rms_change"))]
    return state


def metrology_stream(acquisition, detector, *, chunk_frames="auto"):
    """The frames of a metrology acquisition as every fringe fit reads them (the single job and each job of a
    split fit alike, whose bits depend on it): float32 chunks of ``chunk_frames`` frames (config
    ``chunk_frames``), at least 16 frames."""
    return FrameStream(acquisition, detector, chunk_frames=chunk_frames, min_frames=16, purpose="a fringe solution",
                       dtype="float32")


def check_state_options(ds: xr.Dataset, *, tolerance: float, max_passes: int, smooth_degree: int) -> None:
    """Refuse a split fit's state (or part) product made with other options than the run's.

    A rerun that follows file times only (``--rerun-triggers mtime``) would otherwise carry a state made
    with, say, 4 passes into a run configured for 10, and the product would record options it was not
    fitted with. Raises :class:`FringeError` naming the file and the first option that differs.
    """
    source = ds.encoding.get("source", "state")
    wanted = {"fit_tolerance": float(tolerance), "fit_max_passes": int(max_passes),
              "fit_smooth_degree": int(smooth_degree)}
    for key, value in wanted.items():
        if key in ds.attrs and type(value)(ds.attrs[key]) != value:
            raise FringeError(f"{source}: made with metrology.{key[4:]} = {ds.attrs[key]}, the run has {value}: "
                              "remove metrology/split/ of this baseline and run again")


def _pass_inputs_of(ds, centre) -> PassInputs:
    return PassInputs(ds["projector"].values, ds["offset"].values, ds["pixels"].values, centre,
                      bool(ds.attrs["fit_subtract_centre"]))


def part_dataset(stream, state: xr.Dataset, *, part, parts) -> xr.Dataset:
    """One part's share of a split fit's next pass: the job ``fit_part`` (a small product).

    Parameters
    ----------
    stream : FrameStream
        The whole acquisition (headers only are read but for this part's files).
    state : xr.Dataset
        The fit's state before the pass (:func:`state_dataset`), opened lazily: this job reads its
        projector and reference frame only, so that its memory is its own files' (a chunk, F'X
        (3, grid), the part's frame products (frame, m)), whatever the other parts.
    part, parts : int
        This part (from 0) of ``parts`` (``stream.split(parts)``, groups of whole files; a part
        beyond the groups there are is empty).

    Returns
    -------
    xr.Dataset
        ``products`` (frame, design): the frames' products with the projector in the samples' type;
        ``FtX`` (factor, grid): F'X; ``saturated`` (grid): pixels with a saturated sample; attributes
        ``fit_pass``, ``fit_part``, ``fit_lanes`` (the parts there are) and ``fit_empty`` (1 for a part
        without files, or a pass after the fit converged: no variables).
    """
    n_pass, label = int(state.attrs["fit_n_pass"]) + 1, state.attrs["fit_label"]
    attrs = {"fit_pass": n_pass, "fit_part": int(part), "fit_lanes": 0, "fit_empty": 1}
    if state.attrs["fit_done"]:
        log.info("%s: the fit is done after pass %d: nothing to read in pass %d", label, n_pass - 1, n_pass)
        return xr.Dataset(attrs=attrs)
    inputs = _pass_inputs_of(state, state["centre"].values)
    pieces = fit_stream(stream, inputs).split(parts)
    attrs["fit_lanes"] = len(pieces)
    if part >= len(pieces):
        log.info("%s: the frames make %d part(s): part %d has no file", label, len(pieces), part + 1)
        return xr.Dataset(attrs=attrs)
    piece = pieces[part]
    log.info("%s: pass %d, part %d of %d: %d frames of %d file(s)", label, n_pass, part + 1, len(pieces),
             piece.n_frames, len(piece.cubes))
    products, FtX, saturated, threads = accumulate_part(piece, inputs)
    log.info("%s: BLAS threads: %d", label, threads)
    first = piece.first_frame
    return xr.Dataset(
        {"products": (("frame", "design"), products,
                      {"units": "adu", "long_name": "frame products X P with the pass's projector"}),
         "FtX": (("factor", "grid"), FtX, {"units": "adu2", "long_name": "F'X of the part's frames (row-major)"}),
         "saturated": (("grid",), saturated, {"units": "1", "long_name": "1 where a sample saturated"})},
        coords={"frame": np.arange(first, first + products.shape[0])},
        attrs={**attrs, "fit_lanes": len(pieces), "fit_empty": 0, "fit_threads": int(threads)})


def reduce_dataset(state: xr.Dataset, parts) -> xr.Dataset:
    """The job ``fit_reduce``: a split fit's state after one more pass, from its parts' products.

    ``state`` is the state before the pass (:func:`state_dataset`, loaded), ``parts`` the paths or
    datasets of the pass's part products (:func:`part_dataset`) in part order, read one at a time. A
    fit already done carries its state over. Otherwise the variables the pass replaces without reading
    them (the projector, ``FtI``, ``G``, the halves' ``part_*``) are dropped from ``state``, to free
    their memory: the dataset is the state before the pass no more.
    """
    fit = state_from_dataset(state)
    label = fit.options["label"]
    if fit.done:
        log.info("%s: done after pass %d (%s): state carried over", label, fit.n_pass,
                 "converged" if fit.converged else "at max_passes")
        return state_dataset(fit)
    n_pass = fit.n_pass + 1
    headers = [_part_attrs(part) for part in parts]
    lanes = {h["fit_lanes"] for h in headers if not h["fit_empty"]}
    wrong = [_name(part) for part, h in zip(parts, headers) if h["fit_pass"] != n_pass]
    if wrong or len(lanes) != 1:
        raise FringeError(f"{label}: the part products of pass {n_pass} do not match the state after pass "
                          f"{fit.n_pass} (of another pass: {', '.join(wrong) or 'none'}; part counts "
                          f"{sorted(lanes)})")
    # the parts are summed in their order: the order given must be theirs, or the bits would change
    misplaced = [_name(part) for i, (part, h) in enumerate(zip(parts, headers)) if int(h["fit_part"]) != i]
    if misplaced:
        raise FringeError(f"{label}: part products of pass {n_pass} out of part order: {', '.join(misplaced)}")
    n_lanes = lanes.pop()
    full = [part for part, h in zip(parts, headers) if not h["fit_empty"]]
    if len(full) != n_lanes:
        raise FringeError(f"{label}: pass {n_pass} has {len(full)} part product(s) for {n_lanes} part(s): "
                          f"{', '.join(_name(part) for part in full)}")
    _release_replaced(fit, state)
    fit = reduce_pass(fit, (_part_result(part) for part in full), n_lanes=n_lanes)
    if fit.done:
        log.info("%s: %s after pass %d", label, "converged" if fit.converged else "not converged (max_passes)",
                 fit.n_pass)
    return state_dataset(fit)


def _release_replaced(fit: FitState, state: xr.Dataset) -> None:
    """Drop what a pass replaces without reading it from a state about to take the pass, and from its
    dataset: the projector (the parts used it; the reduction needs its pixels and offset only), the normal
    equations, pixel factors and halves of the pass before. Up to 150 bytes a pixel that would otherwise
    stay in memory beside their successors (the caller's dataset holds them)."""
    fit.next_pass.projector = None
    fit.FtI = fit.G = None
    fit.parts = []
    for name in [name for name in state.data_vars if name in ("projector", "FtI", "G") or name.startswith("part_")]:
        del state[name]


def _name(part) -> str:
    """A part product's file (its source for a dataset opened from one)."""
    return str(part.encoding.get("source", "a part dataset")) if isinstance(part, xr.Dataset) else str(part)


def _open_part(part):
    return part if isinstance(part, xr.Dataset) else io.read_product(part)


def _part_attrs(part) -> dict:
    # a part's header alone: the check of every part comes before any part's variables are read
    return dict(part.attrs) if isinstance(part, xr.Dataset) else io.product_attrs(part)


def _part_result(part):
    """A part product as :func:`_accumulate`'s result."""
    ds = _open_part(part)
    return ds["products"].values, ds["FtX"].values, ds["saturated"].values, int(ds.attrs["fit_threads"])


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


def _pixel_solution(passes: _Passes, x, y, *, geometry, read_noise, gain, label, spend=None) -> _PixelSolution:
    """Pixel phases, iota, alpha and photon floors (at the active pixels ``x``, ``y``), B(t), A(t), phi(t)
    and the mean K of the converged factors; with a ``geometry``, the phases measured against the
    two-source surface of the refined tips (K then the mean of the local wavevectors). ``spend()`` is called
    once the pixel factors are used, before the two-source fit."""
    F_phys, G_phys, k = passes.F, passes.G, passes.k
    theta = np.arctan2(G_phys[:, 1], G_phys[:, 2])
    iota = G_phys[:, 0].copy()
    alpha = np.hypot(G_phys[:, 1], G_phys[:, 2])
    noise_px = np.zeros(x.size) if read_noise is None else np.nan_to_num(read_noise)
    # at |K| = 1, divided by each pixel's |K| once known: the same bits (x / 1 is x)
    floor = photon_floor(G_phys, passes.FtF, third=passes.third, gain=gain, read_noise=noise_px, k_norm=1.0)
    del G_phys, noise_px
    if spend is not None:
        spend()
    two_source, k_norm = None, np.hypot(*k)
    if geometry is not None:
        two_source = fit_two_source(theta, x, y, *geometry.nominal, wavelength=geometry.wavelength,
                                    pixel_pitch=geometry.pixel_pitch, k_plane=k, tip_sigma=geometry.tip_sigma,
                                    fibers=geometry.fibers, label=label)
        k, k_norm = two_source.k_local.mean(axis=0), np.hypot(*two_source.k_local.T)
    floor /= k_norm
    return _PixelSolution(theta=theta, iota=iota, alpha=alpha, floor=floor, k=k, level=F_phys[:, 0] * iota.mean(),
                          amplitude=np.hypot(F_phys[:, 1], F_phys[:, 2]) * alpha.mean(),
                          phase=np.arctan2(F_phys[:, 2], F_phys[:, 1]), two_source=two_source)


def _phases(G, inv_t):
    """Pixel phases (rad) of pixel factors ``G`` (pixel, 3) under the gauge ``inv(M).T`` (3, 3), a block of
    pixels at a time (the gauged factors never over every pixel)."""
    theta = np.empty(G.shape[0])
    for s in pixel_blocks(G.shape[0]):
        Gp = G[s] @ inv_t
        theta[s] = np.arctan2(Gp[:, 1], Gp[:, 2])
    return theta


def _part_factors(F_part, FtI_part, keep):
    """The pixel factors (pixel, 3) of a part of the frames, at the pixels ``keep`` selects of its F'I
    (3, part pixel): solved a block of pixels at a time (no copy of the part's F'I at the pixels)."""
    FtF, pixels = F_part.T @ F_part, np.flatnonzero(keep)
    G = np.empty((pixels.size, 3))
    for s in pixel_blocks(pixels.size):
        G[s] = np.linalg.solve(FtF, FtI_part[:, pixels[s]]).T
    return G


def _diagnostic_phases(passes: _Passes, x, y, flat, keep, *, smooth_degree, label):
    """The pixel phases of the gauge diagnostic (:func:`_diagnostic_offsets`), at the active pixels ``x``,
    ``y``: (the whole frames' under the PRNU-free gauge, [(a part's under the flat's gauge, under the
    PRNU-free gauge, the part's frames) for each independent part of the frames] or None), or None; what
    cannot be formed is logged.

    The diagnostic of a flat that is not the laser's response (chromatic PRNU,
    speckle): the same factorisation under the PRNU-free gauge (the pixel
    contrast's smoothness), which the flat (``flat``, at the active pixels)
    does not enter. The passes do not depend on the gauge, so this costs no
    pass. The noise comes from the gauge difference of each independent part
    of the frames (the lanes; ``keep`` selects the active pixels among
    ``passes.parts_idx``). Phases only, one number a pixel each, taken before
    the two-source fit: the parts' F'I and pixel factors are not held beside it.
    """
    def phases_under(F_any, G_any, use_flat):
        M_any = fix_gauge(F_any, G_any, flat=flat if use_flat else None, x=x, y=y, smooth_degree=smooth_degree)
        return _phases(G_any, np.linalg.inv(M_any).T)

    try:
        free = phases_under(passes.F, passes.G, False)
    except FringeError as exc:  # a diagnostic must not fail a fit the flat's gauge made
        log.warning("%s: no PRNU-free gauge for the diagnostic (%s)", label, exc)
        return None
    try:
        halves = []
        for F_part, FtI_part in passes.parts:
            G_part = _part_factors(F_part, FtI_part, keep)
            halves.append((phases_under(F_part, G_part, True), phases_under(F_part, G_part, False), F_part.shape[0]))
            del G_part
    except (FringeError, np.linalg.LinAlgError) as exc:
        log.warning("%s: no noise floor for the gauge difference (%s)", label, exc)
        halves = None
    return free, halves


def _diagnostic_offsets(phases, solution: _PixelSolution, x, y, *, label):
    """The offsets under the PRNU-free gauge (active pixels ``x``, ``y``) and the noise of their difference
    from the flat gauge's (pixel; None when it cannot be formed), from :func:`_diagnostic_phases`' phases:
    each measured as the solution's offsets are (against the same two-source surface, or the plane), the
    phases turned the way of the solution's K. For two halves, the full data's difference has the noise of
    half their difference."""
    k, two_source = solution.k, solution.two_source

    def offsets_of(theta_any):
        """Offsets (active pixels) of phases under one gauge, turned the way of ``k``."""
        k_any, plane = projected_offsets(theta_any, x, y, k)
        if two_source is not None:  # against the same surface, the phases turned the same way
            return two_source.offsets_of(theta_any if k_any @ k > 0 else -theta_any)
        return plane if k_any @ k > 0 else -plane

    free_phases, halves = phases
    free = offsets_of(free_phases)
    if halves is None:
        return free, None
    if len(halves) != 2:
        log.info("%s: the frames are one part (one file): no noise floor for the gauge difference", label)
        return free, None
    differences = []
    for flat_phases, free_part_phases, _ in halves:
        difference = offsets_of(flat_phases)
        difference -= offsets_of(free_part_phases)
        differences.append(difference)
    # the whole is (n1 d1 + n2 d2) / (n1 + n2): of noise rms(d1 - d2) sqrt(n1 n2) / (n1 + n2)
    (_, _, n1), (_, _, n2) = halves
    return free, float(np.sqrt(np.mean((differences[0] - differences[1]) ** 2) * n1 * n2) / (n1 + n2))
