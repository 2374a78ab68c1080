"""Allan deviations of projected pixel offsets (paper: section "Allan deviations").

The metrology acquisition is cut into consecutive *batches* of one length,
the shortest such that any run of that many frames sweeps a full fringe
period (the unwrapped fringe phase spans 2 pi), so that every pixel sees a
full period in every batch. Each batch gives one map of projected offsets:
each pixel's phase fitted to the batch's frames alone, with the frame
factors of the global solution (B(t), A(t), phi(t)) and the pixel's iota and
alpha held fixed. (Batches of unequal length, or refitting iota in each,
put the single-batch deviation up to 1.3x above the floor scaled to a batch:
docs/metrology.md, "Batches of one length".) Groups of m consecutive
batches, for a logarithmic set of m from 1 to half the number of batches,
are fitted as a whole (and, the paper's way, averaged), and two statistics
are formed per pixel:

- the deviation between group means, the paper's definition: the standard
  deviation (ddof 1) of the n_groups = floor(n_batches / m) group means;
- the classical (non-overlapping) Allan deviation,
  sqrt(sum_j (g_{j+1} - g_j)^2 / (2 (n_groups - 1))), as allantools' ``adev``
  computes it for frequency data.

Averages over pixels (and over 10x10-pixel blocks of pixel-averaged offsets)
average the variances and take the root: with two or three groups left, a
mean of per-pixel deviations is biased low.

Photon-noise limit of one pixel's offset from N frames (the paper's formula,
with its sqrt(N/2) moved to the denominator, see docs/metrology.md):

    sigma(N) = sqrt(B iota / g + sigma_r^2) / (A alpha |K| sqrt(N / 2))

with B and A the mean level and fringe amplitude (adu), iota and alpha the
pixel's relative intensity and amplitude, g the gain (e-/adu) and sigma_r the
read noise (adu). A block of n pixels averages n independent offsets.

Units: pixel for offsets and deviations, frames for integration lengths.
"""

from __future__ import annotations

import contextlib
import functools
import logging
from dataclasses import InitVar, dataclass

import numpy as np

from dice_core import lazy
from dice_core.fringes import frame_moments, photon_floor
from dice_core.io import first_chunk
from dice_core.parallel import (LANES, blas_threads, inherited, lane_executor, lane_workers, map_lanes,
                                one_blas_thread, threads_report)
from dice_core.pixel_blocks import pixel_blocks
from dice_core.polynomials import polynomial_design
from dice_core.scratch import ScratchArray, scratch_directory

xr = lazy.module("xarray")  # scipy too is imported where used: a job reaches its first line sooner

__all__ = [
    "AllanError",
    "MIN_BATCHES",
    "MIN_GROUPS_PIXEL",
    "few_batches",
    "fringe_batches",
    "batch_offsets",
    "batch_floors",
    "group_fits",
    "group_sizes",
    "group_deviation",
    "allan_deviation",
    "block_weights",
    "photon_limit",
    "first_frame_limit",
    "AllanStatistics",
    "allan_statistics",
    "statistics_dataset",
    "allan_dataset",
]

log = logging.getLogger(__name__)


class AllanError(ValueError):
    """An acquisition that cannot give an Allan deviation (too few frames for two batches...)."""


#: Fewest groups a single pixel's deviation is drawn from (the Allan figure): over K groups it is uncertain by
#: 1/sqrt(2 (K - 1)), 35% at 5; over fewer, one pixel's curve is noise that reaches far below every limit.
MIN_GROUPS_PIXEL = 5

#: Fewest batches whose Allan deviations have a slope (two group sizes, 1 and 2 batches: 4) and a single pixel's
#: curve (:data:`MIN_GROUPS_PIXEL` groups of one batch).
MIN_BATCHES = max(4, MIN_GROUPS_PIXEL)


def few_batches(n_batches: int, frames_per_batch: float) -> str | None:
    """The sentence saying a baseline has too few batches for Allan deviations (fewer than :data:`MIN_BATCHES`:
    no slope, or no pixel's curve), or None: the Allan step's warning and its figure's title."""
    if n_batches >= MIN_BATCHES:
        return None
    return (f"too few batches for Allan deviations: {n_batches} batches of {frames_per_batch:.0f} frames; at least "
            f"{MIN_BATCHES} needed")


def fringe_batches(phase, *, span: float = 2 * np.pi, equal_length: bool = True) -> np.ndarray:
    """Consecutive batches of frames, each of which sweeps ``span`` of fringe phase.

    Parameters
    ----------
    phase : ndarray (frame,)
        Fringe phase phi(t), rad (wrapped or not; unwrapped here, so that
        consecutive frames must differ by less than pi).
    span : float
        Phase range a batch must cover, rad: 2 pi makes every pixel see at
        least one full fringe period whatever its own phase.
    equal_length : bool
        True (the Allan step's): every batch has the same length L, the
        shortest such that *any* L consecutive frames sweep ``span``; batches
        tile the frames from the first. False: each batch is the shortest run
        from the previous one's end that sweeps ``span`` (the lengths then
        follow the sweep's speed).

    Returns
    -------
    ndarray (batch, 2) of int
        [start, stop) frame indices. Frames after the last complete batch are
        left out.

    Raises
    ------
    AllanError
        Fewer than two complete batches.

    Notes
    -----
    Why equal lengths: a batch's offset error goes as 1/sqrt(its frames), so
    the deviation between batches of lengths N_b is that of batches of the
    mean length times sqrt(mean(1/N_b) mean(N_b)) (Jensen), while a group of
    many batches averages the lengths out. On the simulator's exponential
    sweeps the shortest runs range over 43-343 frames and that factor is 1.29
    for one batch per group, about 1 for large groups: a curve steeper than
    N^-1/2 (docs/metrology.md, "Batches of one length").
    """
    from scipy.ndimage import maximum_filter1d, minimum_filter1d

    unwrapped = np.unwrap(np.asarray(phase, dtype=float))
    if not equal_length:
        return _shortest_runs(unwrapped, span)
    n = unwrapped.size

    def sweeps(length):  # does every run of ``length`` frames sweep ``span``? (monotone in length)
        lo = length // 2  # the filters centre their window: output i covers [i - lo, i - lo + length)
        top = maximum_filter1d(unwrapped, length)[lo:n - length + lo + 1]
        bottom = minimum_filter1d(unwrapped, length)[lo:n - length + lo + 1]
        return bool(np.all(top - bottom >= span))

    if n < 2 or not sweeps(n):
        raise AllanError(f"{n} frames hold no batch of a full fringe period; at least two are needed for an "
                         "Allan deviation")
    shortest, longest = 1, n  # sweeps(longest) holds, sweeps(shortest) does not (a single frame spans 0)
    while longest - shortest > 1:
        middle = (shortest + longest) // 2
        shortest, longest = (shortest, middle) if sweeps(middle) else (middle, longest)
    count = n // longest
    if count < 2:
        raise AllanError(f"{n} frames hold {count} batch(es) of {longest} frames (the shortest length over "
                         "which any run of frames sweeps a full fringe period); at least two are needed for an "
                         "Allan deviation")
    starts = np.arange(count) * longest
    return np.column_stack([starts, starts + longest])


def _shortest_runs(unwrapped, span):
    """:func:`fringe_batches` with ``equal_length=False``: the shortest runs, one after the other."""
    edges = []
    start, window = 0, 1024
    while start < unwrapped.size:
        # the running range of the phase from ``start``, over a window that grows until it spans ``span``
        ahead = unwrapped[start:start + window]
        spanned = np.maximum.accumulate(ahead) - np.minimum.accumulate(ahead) >= span
        if spanned.any():
            stop = start + int(np.argmax(spanned)) + 1
            edges.append((start, stop))
            start, window = stop, max(1024, 2 * (stop - edges[-1][0]))
        elif start + window >= unwrapped.size:
            break
        else:
            window *= 2
    if len(edges) < 2:
        raise AllanError(f"{len(unwrapped)} frames hold {len(edges)} batch(es) of a full fringe period; "
                         "at least two are needed for an Allan deviation")
    return np.array(edges, dtype=int)


@dataclass(frozen=True)
class _BatchFit:
    """What turns a batch's sums F'X into its offsets (see :func:`batch_offsets`).

    With ``iota`` and ``alpha`` (the global solution's), a batch fits each
    pixel's phase alone; without, appendix B's three linear terms.
    """

    idx: np.ndarray  # flat indices of the fitted pixels
    level: np.ndarray  # (reference - dark) at those pixels, adu
    reference_phase: np.ndarray  # rad
    # affine design over the pixels: only its basis is kept (24 bytes a pixel less held through the job)
    design: InitVar[np.ndarray]
    k_norm: float  # rad/pixel
    iota: np.ndarray = None  # (pixel,) relative intensity, held fixed: the phase-only fit
    alpha: np.ndarray = None  # (pixel,) relative fringe amplitude, held fixed
    basis: np.ndarray = None  # orthonormal columns spanning ``design``: the affine part removed by a projection
    rotation: np.ndarray = None  # exp(-i reference_phase)

    def __post_init__(self, design):
        if self.basis is None:
            object.__setattr__(self, "basis", np.linalg.qr(design)[0])
        if self.rotation is None:
            object.__setattr__(self, "rotation", np.exp(-1j * self.reference_phase))

    def normal_sums(self, F, FtX):
        """F'I (3, pixel of idx) of frames with factors F (frame, 3) and sums F'X: the level folded back in."""
        return FtX + np.outer(F.sum(axis=0), self.level)

    def phases_of_sums(self, FtF, FtI):
        """Each pixel's fitted phase as a unit complex number exp(i theta) (pixel,), 0 for a pixel without
        signal, from the normal equations F'F (3, 3), F'I (3, pixel)."""
        if self.alpha is not None:
            return np.exp(1j * _phase_only(FtF, FtI, self.iota, self.alpha))
        G = np.linalg.inv(FtF) @ FtI  # a 3x3 inverse: a fraction of the cost of solve() for 5600 pixels
        turned = G[2] + 1j * G[1]
        size = np.abs(turned)
        return np.where(size > 0, turned / np.where(size > 0, size, 1.0), 0.0)

    def turned(self, FtF, FtI):
        """exp(i (theta - reference_phase)) (pixel,) of the fit with normal equations F'F (3, 3), F'I (3, pixel)."""
        return self.phases_of_sums(FtF, FtI) * self.rotation

    def offsets_of_sums(self, FtF, FtI):
        """Projected offsets (pixel,) of the least-squares fit with normal equations F'F (3, 3), F'I (3, pixel)."""
        # theta - reference as unit complex numbers, wrapped about their circular mean: the difference is
        # the constant phase the gauge leaves free plus the batch's small offset changes, and that
        # constant may be near pi (wrapped_about_mean, cheaper)
        turned = self.turned(FtF, FtI)
        delta = _wrapped_about(turned, np.mean(turned))
        return (delta - self.basis @ (self.basis.T @ delta)) / self.k_norm

    def band(self, pixels: slice) -> _BatchFit:
        """The fit of the pixels ``pixels`` (a slice of this fit's): the affine basis is this fit's, over every
        pixel, cut to them (not one of their own)."""
        held = {} if self.iota is None else {"iota": self.iota[pixels], "alpha": self.alpha[pixels]}
        return _BatchFit(idx=None, level=None, reference_phase=self.reference_phase[pixels],
                         design=None, k_norm=self.k_norm, basis=self.basis[pixels],
                         rotation=self.rotation[pixels], **held)


def _wrapped_about(turned, centre):
    """The angles (rad) of unit complex numbers ``turned`` about the direction of ``centre``, in [-pi, pi]."""
    return np.angle(turned * np.conj(centre / np.abs(centre)))


def _phase_only(FtF, FtI, iota, alpha, *, steps: int = 2):
    """Each pixel's phase theta (pixel,), rad, fitted alone: the least squares of
    I - B iota = A alpha sin(theta + phi) over the frames, iota and alpha given.

    The start is the fit of the two fringe terms (alpha sin theta, alpha cos
    theta) with iota fixed, a linear fit whose phase is within the noise of
    the optimum; Newton steps on theta with alpha fixed converge
    quadratically from there (two take a 1e-3 rad start to 1e-12 rad).
    With v = (sin theta, cos theta), g = dv/dtheta, M the 2x2 F'F of the
    fringe terms and s = F'(I - B iota) over them, the cost is
    -2 alpha v.s + alpha^2 v'Mv.
    """
    s = FtI[1:] - np.outer(FtF[1:, 0], iota)  # (2, pixel), adu^2
    M = FtF[1:, 1:]
    a, b = np.linalg.solve(M, s)
    theta = np.arctan2(a, b)
    for _ in range(steps):
        v = np.stack([np.sin(theta), np.cos(theta)])
        g = np.stack([v[1], -v[0]])
        Mv, Mg = M @ v, M @ g
        gradient = -np.sum(g * s, axis=0) + alpha * np.sum(g * Mv, axis=0)
        curvature = np.sum(v * s, axis=0) + alpha * (np.sum(g * Mg, axis=0) - np.sum(v * Mv, axis=0))
        step = gradient / np.where(curvature != 0, curvature, np.inf)
        theta = theta - np.where(np.isfinite(step), step, 0.0)
    return theta


def _inherited_lane(index, lanes, *arguments):
    """:func:`_lane_batch_offsets` of lane ``index`` of ``lanes`` (read through a worker's fork: see
    :func:`_fit_batches`)."""
    return _lane_batch_offsets(lanes[index], *arguments)


def _lane_batch_offsets(chunks, batches, frame_factors, fit: _BatchFit, kept, label):
    """One lane's part of :func:`batch_offsets`: the batches its chunks hold whole, and the others' partial sums.

    Each batch the lane's chunks hold whole has its normal sums F'I (3, pixel of ``fit.idx``) written
    to ``kept[b]`` (float32) as soon as its last frame is summed: no lane holds more than the batches it is
    summing. Returns ``(done, partial, blas_threads)``: ``done`` the batches written, ``partial`` maps a
    batch the chunks hold only part of to its sums F'X over those frames (3, pixel of ``fit.idx``) and the
    number of those frames; ``blas_threads`` those of the process that ran it (for the log). Module-level,
    so that a worker process can run it.
    """
    n_total = len(batches)
    lengths = batches[:, 1] - batches[:, 0]
    done, sums, covered = [], {}, {}
    for chunk in chunks:
        n = chunk.frames.shape[0]
        X = chunk.frames.reshape(n, -1)
        lo_frame, hi_frame = chunk.start, chunk.start + n
        # batches overlapping this chunk: those whose stop is after its first frame and start before its end
        first = int(np.searchsorted(batches[:, 1], lo_frame, side="right"))
        for b in range(first, n_total):
            start, stop = batches[b]
            if start >= hi_frame:
                break
            lo, hi = max(lo_frame, start), min(hi_frame, stop)
            F = frame_factors[lo:hi].astype(X.dtype)
            if b not in sums:
                sums[b] = np.zeros((3, X.shape[1]))
            # F'X on whole frames (a chunk is never copied), summed in float64
            np.add(sums[b], F.T @ X[lo - lo_frame:hi - lo_frame], out=sums[b])
            covered[b] = covered.get(b, 0) + hi - lo
            if covered[b] == lengths[b]:  # float32: a phase to 1e-7 rad, half the memory, disk and pipe
                kept[b] = fit.normal_sums(frame_factors[start:stop], sums.pop(b)[:, fit.idx]).astype(np.float32)
                done.append(b)
                del covered[b]
                if len(done) % 100 == 0:
                    log.info("%s: %d batches fitted in one part of the frames", label, len(done))
    return done, {b: (part[:, fit.idx], covered[b]) for b, part in sums.items()}, blas_threads()


@one_blas_thread
def batch_offsets(chunks, batches, frame_factors, dark, reference_phase, k, rows, cols, *,
                  pixel_factors=None, reference=None, workers: int = 1, return_sums: bool = False,
                  scratch=None, label="baseline", finite=None):
    """Projected offsets of every pixel in every batch, in one pass over the frames.

    For each batch b, with the frame factors F_t = (B, A cos phi, A sin phi)(t)
    of the global solution, each pixel's batch phase theta_b is fitted to the
    batch's frames I_b: with ``pixel_factors``, theta_b alone, the pixel's
    iota and alpha held at the global solution's (least squares of
    I - B iota = A alpha sin(theta + phi)); without, appendix B's temporal
    sine fit G_b = (F_b'F_b)^-1 F_b' I_b, theta_b = atan2(G_b1, G_b2). The
    offsets are theta_b's difference to ``reference_phase``, wrapped about
    its circular mean (the constant phase the gauge leaves free), divided by
    |K|, with their affine part removed (as every offset map is defined).

    Fitting the phase alone is what a batch can do best: iota and alpha are
    constant in the model and known sqrt(batches) times better from all the
    frames, while a batch whose phases do not cover the circle evenly (any
    batch of an irregular sweep but whole periods of a uniform one) mixes
    its own iota into its phase. On the simulator's sweeps, with batches of
    one length, the three-term fit's error is 1.07-1.22x the uniform
    sqrt(N/2) floor, the phase's alone 1.01-1.05x (docs/metrology.md).

    Parameters
    ----------
    chunks : iterable of Chunk
        The acquisition's frames in order, adu (float32 or float64); if
        ``reference`` is given, each chunk holds frames minus ``reference``
        (see :meth:`dice_core.io.FrameStream.centred`). A stream with a
        ``split`` method is read in :data:`dice_core.parallel.LANES` parts.
    batches : ndarray (batch, 2)
        From :func:`fringe_batches`.
    frame_factors : ndarray (frame, 3)
        (B, A cos phi, A sin phi) per frame, adu.
    dark : ndarray (row, col)
        Mean dark, adu.
    reference_phase : ndarray (pixel,)
        Phase of the pixels ``rows``, ``cols`` that the offsets are measured from, rad.
    k : (float, float)
        Mean wavevector, rad/pixel.
    rows, cols : ndarray (pixel,)
        Pixels to fit.
    pixel_factors : ndarray (pixel, 3), optional
        (iota, alpha sin theta, alpha cos theta) of the global solution: given,
        each batch fits the phase alone with that iota and alpha.
    reference : ndarray (row, col), optional
        Frame subtracted from the chunks by the reader, adu.
    workers : int
        Processes reading the parts at once, one BLAS thread each; the result
        does not depend on it (the parts are fixed and summed in order).
    return_sums : bool
        Also return each batch's normal sums F'I, for fits of groups of
        batches as a whole (:func:`group_fits`).
    scratch : path, optional
        A folder (:func:`dice_core.scratch.scratch_directory`): the offsets
        and sums are returned as :class:`~dice_core.scratch.ScratchArray`
        files there, and the job holds one batch's at a time (besides each
        lane's batches being summed). None: the offsets and sums returned in
        memory (the sums still pass through a file of a temporary folder of
        the system's, which the lanes write into).
    finite : bool ndarray (pixel,), optional
        Set False, in place, at each pixel whose offset is not finite in some
        batch: which pixels have an offset in every batch, found as the batches
        are fitted (no second read of the offsets).

    Returns
    -------
    ndarray (batch, pixel)
        Each batch's projected offsets minus those of ``reference_phase`` (the
        global solution's), pixel, affine part removed.
    ndarray (batch, 3, pixel), float32
        With ``return_sums``: each batch's F'I, adu^2 (float32 holds them to
        6e-8, a phase to 1e-7 rad).
    """
    n_cols = np.shape(dark)[1]
    idx = rows * n_cols + cols
    centre = np.zeros(np.size(dark)) if reference is None else np.ravel(reference).astype(np.float64)
    level = (centre - np.ravel(dark))[idx]  # X - d = (X - r) + (r - d)
    del centre  # (not held through the pass)
    fit = _BatchFit(idx=idx, level=level,
                    reference_phase=np.asarray(reference_phase, float),
                    design=polynomial_design(cols.astype(float), rows.astype(float), degree=1),
                    k_norm=float(np.hypot(*k)), **_held(pixel_factors))
    batches = np.asarray(batches)
    with contextlib.ExitStack() as stack:
        folder = scratch if scratch is not None else stack.enter_context(scratch_directory())
        kept = ScratchArray(folder, (len(batches), 3, idx.size), np.float32, name="sums")
        out = (ScratchArray(folder, (len(batches), idx.size), np.float64, name="offsets") if scratch is not None
               else np.full((len(batches), idx.size), np.nan))
        _fit_batches(chunks, batches, frame_factors, fit, kept, out, workers, label, finite)
        if scratch is None:  # in memory, the files go with their folder
            kept = kept[...] if return_sums else None
    return (out, kept) if return_sums else out


def _fit_batches(chunks, batches, frame_factors, fit, kept, out, workers, label, finite=None):
    """:func:`batch_offsets`' pass: each batch's F'I written to ``kept`` (batch, 3, pixel), its offsets to
    ``out`` (batch, pixel), one batch in memory at a time besides the lanes' own; ``finite`` (pixel,), if
    given, set False where a batch's offset is not."""
    lanes = chunks.split(LANES) if hasattr(chunks, "split") else [chunks]
    # the fit's per-pixel arrays (about 100 bytes a pixel) and the lanes (each with the centre frame it
    # subtracts, 8 bytes a detector pixel) reach the workers through their fork, shared with this process, not
    # as a pickled copy each (which held it twice in a worker while it was unpickled)
    with (inherited(fit) as shared_fit, inherited(lanes) as shared_lanes,
          lane_executor(workers, len(lanes)) as executor):
        log.info("%s: %d batch fits over %d part(s) of the frames, in %d process(es)", label, len(batches),
                 len(lanes), lane_workers(workers, len(lanes)))
        results = map_lanes(executor, _inherited_lane, list(range(len(lanes))), shared_lanes, batches,
                            frame_factors, shared_fit, kept, label)
    log.info("%s: %s", label, threads_report(executor, [threads for _, _, threads in results]))
    fitted = np.zeros(len(batches), bool)
    partial, covered = {}, {}

    def finish(b, FtI):
        start, stop = batches[b]
        F = frame_factors[start:stop]
        out[b] = offsets = fit.offsets_of_sums(F.T @ F, FtI.astype(np.float64))
        fitted[b] = True
        if finite is not None:
            np.logical_and(finite, np.isfinite(offsets), out=finite)

    for _, sums, _ in results:  # in lane order, so that a batch cut between parts sums the same way always
        for b, (part, n_frames) in sums.items():
            partial[b] = part if b not in partial else partial[b] + part
            covered[b] = covered.get(b, 0) + n_frames
        sums.clear()  # each lane's part dropped once summed: no more than one sum of a batch held
    for b in list(partial):  # the batches cut between parts first, each dropped once fitted
        start, stop = batches[b]
        if covered[b] == stop - start:
            # every batch's sums rounded alike, wherever the lanes cut
            kept[b] = FtI = np.asarray(fit.normal_sums(frame_factors[start:stop], partial.pop(b)), np.float32)
            finish(b, FtI)
            del FtI
    for done, _, _ in results:
        for b in done:
            finish(b, kept[b])
    if not fitted.all():
        raise AllanError(f"{label}: the frames ended in batch {np.flatnonzero(~fitted)[0]} of {len(batches)}")


def _held(pixel_factors):
    """The iota and alpha a phase-only :class:`_BatchFit` holds, from pixel factors (pixel, 3); none without."""
    if pixel_factors is None:
        return {}
    pixel_factors = np.asarray(pixel_factors, float)
    # iota copied: a view would hold the whole (pixel, 3) array as long as the fit
    return {"iota": pixel_factors[:, 0].copy(), "alpha": np.hypot(pixel_factors[:, 1], pixel_factors[:, 2])}


class _PixelFactors:
    """(iota, alpha sin phase, alpha cos phase) (pixel, 3) of the global solution, made when read: ``[pixels]``
    (a slice) for those pixels, ``np.asarray`` for all; each the same numbers as that slice of
    ``np.column_stack`` of the whole (elementwise), without 24 bytes a pixel held through the job."""

    def __init__(self, iota, alpha, phase):
        # contiguous, so that numpy's sin and cos take the same loop on a slice as on the whole
        self.iota, self.alpha, self.phase = (np.ascontiguousarray(v) for v in (iota, alpha, phase))
        self.shape = (np.size(phase), 3)

    def __getitem__(self, pixels):
        if not isinstance(pixels, slice):
            raise IndexError("_PixelFactors gives a slice of pixels")
        alpha, phase = self.alpha[pixels], self.phase[pixels]
        return np.column_stack([self.iota[pixels], alpha * np.sin(phase), alpha * np.cos(phase)])

    def __array__(self, dtype=None, copy=None):
        whole = self[:]
        return whole if dtype is None else whole.astype(dtype, copy=False)


def batch_floors(frame_factors, batches, *, pixel_factors, gain, read_noise, k_norm,
                 phase_only: bool = True) -> np.ndarray:
    """1-sigma photon-noise error of each batch's offset of each pixel, pixel (batch, pixel).

    The exact error of the unweighted fit on the batch's own frames
    (:func:`dice_core.fringes.photon_floor`, from the third moments of the
    batch's frame factors), of the phase alone (``phase_only``, as
    :func:`batch_offsets` with pixel factors) or of the three linear terms:
    unlike :func:`photon_limit`, it knows how unevenly a batch of an
    irregular sweep samples the phase.
    """
    out = np.empty((len(batches), pixel_factors.shape[0]))
    for b, (start, stop) in enumerate(batches):
        FtF, third = frame_moments(frame_factors[start:stop])
        out[b] = photon_floor(pixel_factors, FtF, third=third, gain=gain, read_noise=read_noise, k_norm=k_norm,
                              phase_only=phase_only)
    return out


class _BatchFloors:
    """:func:`batch_floors` (batch, pixel) made when read, for the pixels asked (``floors[:, pixels]``, pixels a
    slice): nothing of pixels times batches kept (each pixel's floors are its own, the same to rounding)."""

    def __init__(self, frame_factors, batches, *, pixel_factors, read_noise, **floor):
        self.frame_factors, self.batches, self.pixel_factors, self.floor = frame_factors, batches, pixel_factors, floor
        self.read_noise = np.broadcast_to(np.asarray(read_noise, float), (pixel_factors.shape[0],))
        self.shape = (len(batches), pixel_factors.shape[0])

    def __getitem__(self, key):
        batches, pixels = key
        if batches != slice(None) or not isinstance(pixels, slice):
            raise IndexError("_BatchFloors gives every batch of a slice of pixels")
        return batch_floors(self.frame_factors, self.batches, pixel_factors=self.pixel_factors[pixels],
                            read_noise=self.read_noise[pixels], **self.floor)


#: Batch-pixel numbers of one band of pixels the statistics hold at once (each several times over, float64):
#: :func:`allan_of_baseline`'s bands have about this over the number of batches pixels.
BAND_NUMBERS = 2**21


def _pixel_bands(weights, pixels_per_block):
    """Consecutive slices of the pixels, each at most ``pixels_per_block`` long where a block allows, none
    cutting a block of ``weights`` (:func:`block_weights`, pixel, block); one of every pixel if
    ``pixels_per_block`` is None."""
    n = weights.shape[0]
    if pixels_per_block is None or n <= pixels_per_block:
        return [slice(0, n)]
    column = np.full(n, -1)
    column[np.diff(weights.indptr) > 0] = weights.indices  # the block of each pixel (one weight a pixel at most)
    seen = np.maximum.accumulate(column)  # the last block at or before each pixel
    ahead = np.minimum.accumulate(np.where(column >= 0, column, n)[::-1])[::-1]  # the first at or after
    cuts = (np.flatnonzero(seen[:-1] < ahead[1:]) + 1).tolist()  # a cut before these pixels splits no block
    bands, start, last = [], 0, 0
    for cut in [*cuts, n]:
        if cut - start > pixels_per_block and last > start:
            bands.append(slice(start, last))
            start = last
        last = cut
    return [*bands, slice(start, n)]


def _band_weights(weights, band):
    """The rows ``band`` of ``weights`` cut to the columns (blocks) they weigh, and those columns' slice."""
    rows = weights[band.start:band.stop]
    if rows.nnz == 0:
        return rows[:, :0], slice(0, 0)
    columns = slice(int(rows.indices.min()), int(rows.indices.max()) + 1)
    return rows[:, columns], columns


class _RootMeanSquare:
    """sqrt(nanmean(deviations**2)) over pixels (size, pixel), summed a band of pixels at a time."""

    def __init__(self, n):
        self.total, self.count = np.zeros(n), np.zeros(n)

    def add(self, deviations):
        square = np.square(deviations)
        finite = np.isfinite(square)
        self.total += np.where(finite, square, 0.0).sum(axis=1)
        self.count += finite.sum(axis=1)
        return self

    def root(self):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(self.total / self.count)


def _pixel_array(shape, scratch, name):
    """A (..., pixel) float64 array filled band by band: in memory, or a ScratchArray in ``scratch``."""
    return np.full(shape, np.nan) if scratch is None else ScratchArray(scratch, shape, np.float64, name=name)


def group_fits(sums, batches, frame_factors, reference_phase, k, rows, cols, sizes, *, pixel_factors, gain,
               read_noise, good, weights, phase_only: bool = True, pixels_per_block=None, scratch=None):
    """Deviations and photon-noise limits of consecutive groups of batches, each group fitted as a whole.

    A group's normal equations are the sums of its batches' (F'F and F'I from
    :func:`batch_offsets` with ``return_sums``): its fit is the least-squares
    fit of all its frames at once, whose phases cover the circle evenly once
    the group spans several periods, where the mean of its one-period batch
    fits keeps each batch's uneven sampling (docs/metrology.md).

    Parameters
    ----------
    sums : ndarray or ScratchArray (batch, 3, pixel)
        Each batch's F'I, adu^2.
    batches : ndarray (batch, 2)
        Consecutive batches (:func:`fringe_batches`).
    frame_factors : ndarray (frame, 3)
        (B, A cos phi, A sin phi), adu.
    reference_phase, k, rows, cols
        As for :func:`batch_offsets`.
    sizes : sequence of int
        Batches per group (:func:`group_sizes`).
    pixel_factors : ndarray (pixel, 3)
        (iota, alpha sin theta, alpha cos theta) of the global solution: the floors', and with
        ``phase_only`` the iota and alpha each group's phase is fitted with.
    gain : float
        e-/adu.
    read_noise : ndarray (pixel,)
        adu.
    good : bool ndarray (pixel,)
        Pixels with an offset in every batch.
    weights : ndarray (pixel, block)
        Block averages (:func:`block_weights`).
    phase_only : bool
        Fit each group's phases alone (as :func:`batch_offsets` with pixel
        factors); False: the three linear terms.
    pixels_per_block : int, optional
        Pixels of a band the groups are fitted over at a time (never cutting
        a block of ``weights``; None: every pixel at once). A group's offsets
        are wrapped about one circular mean and have one affine part removed
        over every pixel: the means are summed over the bands in a sweep of
        their own, the affine part's projections in a second, and removed in
        a third. The same values whatever the bands, to rounding.
    scratch : path, optional
        A folder for ``deviation`` and ``allan`` as ScratchArrays (None: in memory).

    Returns
    -------
    dict of ndarray, one row per size
        ``deviation`` and ``allan`` (size, pixel; NaN off ``good``),
        ``block_deviation`` and ``block_allan`` (size, block): the paper's
        deviation and the Allan deviation between the groups' offsets (affine
        part removed) of each pixel and block; ``limit_pixel`` and
        ``limit_block`` (size,): their photon-noise limits, the groups'
        variances from their own fits averaged over groups, then over pixels or
        blocks. All in pixel. One group size's groups of a band in memory at a time.
    """
    fit = _BatchFit(idx=None, level=None, reference_phase=np.asarray(reference_phase, float),
                    design=polynomial_design(np.asarray(cols, float), np.asarray(rows, float), degree=1),
                    k_norm=float(np.hypot(*k)), **(_held(pixel_factors) if phase_only else {}))
    moments = [frame_moments(frame_factors[start:stop]) for start, stop in batches]
    # running sums of the small moments: a group's are two differences. The F'I are summed group by
    # group instead (a running sum would hold another float64 copy of a band of them).
    cum_FtF = np.concatenate([np.zeros((1, 3, 3)), np.cumsum([m[0] for m in moments], axis=0)])
    cum_third = np.concatenate([np.zeros((1, 3, 3, 3)), np.cumsum([m[1] for m in moments], axis=0)])
    groups = [[(g * m, (g + 1) * m) for g in range(len(batches) // m)] for m in sizes]
    bands = _pixel_bands(weights, pixels_per_block)
    n_pixels, n_blocks = len(fit.reference_phase), weights.shape[1]
    read_noise = np.broadcast_to(np.asarray(read_noise, float), (n_pixels,))
    out = {"deviation": _pixel_array((len(sizes), n_pixels), scratch, "deviation"),
           "allan": _pixel_array((len(sizes), n_pixels), scratch, "allan"),
           "block_deviation": np.full((len(sizes), n_blocks), np.nan),
           "block_allan": np.full((len(sizes), n_blocks), np.nan)}
    centres, projections = {}, {}
    if len(bands) > 1:
        # each group's wrapping centre, its circular mean over every pixel, before any band is wrapped: the
        # centre of one band alone may be its bad pixels' (a dead edge's random phases), which would put the
        # good pixels' common phase on the cut at +-pi; a sweep of its own, every group fitted once more
        for band in bands:
            band_fit, band_sums = fit.band(band), sums[:, :, band]
            for size_groups in groups:
                for lo, hi in size_groups:
                    turned = band_fit.turned(cum_FtF[hi] - cum_FtF[lo], band_sums[lo:hi].sum(axis=0, dtype=np.float64))
                    centres[lo, hi] = centres.get((lo, hi), 0j) + turned.sum()  # its direction: the mean's
    variance_pixel, variance_block = np.zeros(len(sizes)), np.zeros(len(sizes))
    for band in bands:  # the next sweep: the affine parts and the limits (and the centres, where one band is all)
        band_fit, band_sums, band_factors = fit.band(band), sums[:, :, band], pixel_factors[band]
        weights_band = _band_weights(weights, band)[0]
        for i, size_groups in enumerate(groups):
            for lo, hi in size_groups:
                FtF = cum_FtF[hi] - cum_FtF[lo]
                turned = band_fit.turned(FtF, band_sums[lo:hi].sum(axis=0, dtype=np.float64))
                delta = _wrapped_about(turned, centres.setdefault((lo, hi), np.mean(turned)))
                projections[lo, hi] = projections.get((lo, hi), 0.0) + band_fit.basis.T @ delta
                variance = np.where(good[band], photon_floor(
                    band_factors, FtF, third=cum_third[hi] - cum_third[lo], gain=gain,
                    read_noise=read_noise[band], k_norm=fit.k_norm, phase_only=phase_only), 0.0) ** 2
                variance_pixel[i] += variance.sum()
                variance_block[i] += (variance @ weights_band**2).sum()
    for band in bands:  # the last: each band's group offsets, their deviations
        band_fit, band_sums, band_good = fit.band(band), sums[:, :, band], good[band]
        weights_band, columns = _band_weights(weights, band)
        for i, size_groups in enumerate(groups):
            group_offsets = np.zeros((len(size_groups), band.stop - band.start))
            for g, (lo, hi) in enumerate(size_groups):
                FtF = cum_FtF[hi] - cum_FtF[lo]
                delta = _wrapped_about(band_fit.turned(FtF, band_sums[lo:hi].sum(axis=0, dtype=np.float64)),
                                       centres[lo, hi])
                group_offsets[g, band_good] = ((delta - band_fit.basis @ projections[lo, hi]) / fit.k_norm)[band_good]
            blocks = group_offsets @ weights_band
            out["deviation"][i, band] = np.where(band_good, _deviation_of_means(group_offsets), np.nan)
            out["allan"][i, band] = np.where(band_good, _allan_of_means(group_offsets), np.nan)
            out["block_deviation"][i, columns] = _deviation_of_means(blocks)
            out["block_allan"][i, columns] = _allan_of_means(blocks)
    n_groups = np.array([len(size_groups) for size_groups in groups])
    out["limit_pixel"] = np.sqrt(variance_pixel / (n_groups * good.sum()))
    out["limit_block"] = np.sqrt(variance_block / (n_groups * n_blocks))
    return out


def group_sizes(n_batches: int, *, per_decade: int = 10) -> np.ndarray:
    """Batches per group, 1 to n_batches // 2, about ``per_decade`` sizes per factor of 10."""
    top = n_batches // 2
    if top < 1:
        raise AllanError(f"{n_batches} batch(es): at least two are needed")
    sizes = np.unique(np.round(np.logspace(0, np.log10(top), max(2, int(per_decade * np.log10(top)) + 1))))
    return sizes.astype(int)


def _group_means(series, m):
    n_groups = series.shape[0] // m
    return series[:n_groups * m].reshape(n_groups, m, *series.shape[1:]).mean(axis=1)


def group_deviation(series, m: int) -> np.ndarray:
    """Standard deviation (ddof 1) of the means of consecutive groups of ``m`` samples (the paper's).

    ``series`` is (sample, ...); samples after the last whole group are left out.
    """
    return _deviation_of_means(_group_means(np.asarray(series, dtype=float), m))


def allan_deviation(series, m: int) -> np.ndarray:
    """Non-overlapping Allan deviation of ``series`` (sample, ...) at averaging factor ``m``.

    sqrt(sum_j (g_{j+1} - g_j)^2 / (2 (n_groups - 1))) over the group means g_j;
    equal to allantools' ``adev(series, rate=1, data_type="freq", taus=[m])``.
    """
    return _allan_of_means(_group_means(np.asarray(series, dtype=float), m))


def _deviation_of_means(means):
    return means.std(axis=0, ddof=1)


def _allan_of_means(means):
    return np.sqrt(np.mean(np.diff(means, axis=0) ** 2, axis=0) / 2)


def block_weights(rows, cols, *, good, block: int = 10):
    """Averaging matrix (pixel, block) over block x block squares of the ``good`` pixels, a scipy.sparse csr_array.

    Blocks tile the bounding box of the pixels from its first row and column;
    only whole blocks are kept, and a block's weights are 1 / (its good
    pixels). ``maps @ weights`` gives block means (an ndarray), and
    ``weights**2`` squares each weight. Sparse, one weight a pixel: dense,
    the matrix would hold pixels^2 / block^2 numbers (85 GB on a 1024x1024
    detector).
    """
    from scipy import sparse

    r0, c0 = rows.min(), cols.min()
    n_r, n_c = (rows.max() - r0 + 1) // block, (cols.max() - c0 + 1) // block
    br, bc = (rows - r0) // block, (cols - c0) // block
    inside = np.flatnonzero(good & (br < n_r) & (bc < n_c))
    members = (br * n_c + bc)[inside]
    counts = np.bincount(members, minlength=n_r * n_c)
    column = np.cumsum(counts > 0) - 1  # the blocks holding a good pixel, in block order
    return sparse.csr_array((1.0 / counts[members], (inside, column[members])),
                            shape=(rows.size, int(np.count_nonzero(counts))))


def photon_limit(n_frames, level, *, amplitude, iota, alpha, gain, read_noise, k_norm):
    """1-sigma photon-noise limit of each pixel's projected offset from ``n_frames`` frames, pixel.

    sqrt(B iota / g + sigma_r^2) / (A alpha |K| sqrt(N / 2)); ``n_frames`` may be
    an array (broadcast against the pixel arrays as (n, 1) x (pixel,)).
    """
    noise = np.sqrt(level * iota / gain + read_noise**2)  # adu, one frame
    per_frame = np.atleast_1d(noise / (amplitude * alpha * k_norm))  # pixel, one frame at the best phase
    return per_frame[None, :] / np.sqrt(np.asarray(n_frames, dtype=float)[:, None] / 2)


def first_frame_limit(n_frames, first_frame, *, amplitude, alpha, gain, read_noise, k_norm):
    """Photon-noise limit of the pixels' offsets from the noise measured on one frame, rms over pixels, pixel.

    The paper's "measured photon noise using the first frame of the data
    cube": each pixel's noise in one frame from that frame's own signal,
    Delta f = sqrt(f / g + sigma_r^2) (adu, f the frame minus the dark, a
    negative f counted as 0), propagated with the paper's formula
    Delta r = Delta f / (A alpha |K| sqrt(N / 2)); the rms over pixels of
    Delta r. Where :func:`photon_limit` takes the model's level B iota, this
    takes the counts recorded, fringe included: averaged over pixels that
    sample the fringe's phases evenly, the two agree.

    Returns
    -------
    limit : ndarray (n,)
        For each ``n_frames``, pixel.
    noise : float
        rms over pixels of Delta f, adu.
    """
    noise = np.sqrt(np.clip(np.asarray(first_frame, float), 0.0, None) / gain + np.asarray(read_noise, float) ** 2)
    per_frame = noise / (amplitude * np.asarray(alpha, float) * k_norm)  # pixel, one frame at the best phase
    limit = np.sqrt(np.mean(per_frame**2)) / np.sqrt(np.asarray(n_frames, dtype=float) / 2)
    return limit, float(np.sqrt(np.mean(noise**2)))


def _deviations(series, sizes):
    """:func:`group_deviation` and :func:`allan_deviation` of ``series`` (sample, ...) at each size (size, ...).

    Each size's group means are formed once, for both statistics.
    """
    series = np.asarray(series, dtype=float)
    deviation, allan = [], []
    for m in sizes:  # one size's means in memory at a time
        means = _group_means(series, m)
        deviation.append(_deviation_of_means(means))
        allan.append(_allan_of_means(means))
    return np.stack(deviation), np.stack(allan)


def _mean_variance_root(deviations, axis=-1):
    """Root of the mean variance over ``axis``: a mean of deviations is biased low with few groups."""
    return np.sqrt(np.nanmean(np.square(deviations), axis=axis))


@dataclass
class AllanStatistics:
    """The statistics of :func:`allan_statistics`: plain arrays, pixel arrays over ``rows``, ``cols``.

    Each attribute is named as the ``allan/<baseline>.nc`` variable it becomes
    (:func:`allan_dataset` adds units, long names and maps); deviations and
    limits in pixel, slopes without unit. The optional ones are None when their
    input was not given.

    Attributes
    ----------
    group_size, n_groups, n_frames : ndarray (size,)
        Batches per group, groups the deviations are taken over, mean frames per group.
    frames_per_batch : float
    deviation, allan_deviation : ndarray or ScratchArray (size, pixel)
        Per pixel (the groups fitted as a whole when given, else means of batch fits); on disk when made there.
    deviation_mean, allan_deviation_mean, deviation_block_mean, allan_deviation_block_mean : ndarray (size,)
        Root of the mean variance over pixels, and over blocks of pixel-averaged offsets.
    white_deviation_mean, white_deviation_block_mean : ndarray (size,)
        The same of white noise with the single-batch scatter of the pixels, of the blocks.
    photon_limit_pixel, photon_limit_block : ndarray (size,)
        Photon-noise limits from the fits' own errors.
    photon_limit_pixel_paper, photon_limit_block_paper : ndarray (size,)
        The paper's formula (:func:`photon_limit`).
    slope : float
        Log-log slope of ``deviation_mean`` against ``n_frames``, over every group size.
    sample_pixel : ndarray (sample,)
        Pixels (indices into ``rows``, ``cols``) whose curves ``sample_deviation`` (size, sample) holds.
    batch_start, batch_frames : ndarray (batch,)
        First frame and frames of each batch.
    batch_offset : ndarray or ScratchArray (batch, pixel)
        The batch offsets (the statistics' input, on disk or not).
    deviation_mean_batch_means, photon_limit_pixel_batch_means, slope_batch_means : optional
        With the groups fitted as a whole: the groups as means of batch fits (the paper's) beside them.
    photon_limit_pixel_first_frame : ndarray (size,), optional
        With a first frame: the limit from the noise measured on it, and ``first_frame_noise`` (adu).
    first_frame_noise : float, optional
    photon_limit_pixel_global : ndarray (size,), optional
        With the global solution's floors: their rms scaled to each group's frames, sqrt(N_total / N).
    """

    group_size: np.ndarray
    n_groups: np.ndarray
    n_frames: np.ndarray
    frames_per_batch: float
    deviation: np.ndarray
    allan_deviation: np.ndarray
    deviation_mean: np.ndarray
    allan_deviation_mean: np.ndarray
    deviation_block_mean: np.ndarray
    allan_deviation_block_mean: np.ndarray
    white_deviation_mean: np.ndarray
    white_deviation_block_mean: np.ndarray
    photon_limit_pixel: np.ndarray
    photon_limit_block: np.ndarray
    photon_limit_pixel_paper: np.ndarray
    photon_limit_block_paper: np.ndarray
    slope: float
    sample_pixel: np.ndarray
    sample_deviation: np.ndarray
    batch_start: np.ndarray
    batch_frames: np.ndarray
    batch_offset: np.ndarray
    deviation_mean_batch_means: np.ndarray | None = None
    photon_limit_pixel_batch_means: np.ndarray | None = None
    slope_batch_means: float | None = None
    photon_limit_pixel_first_frame: np.ndarray | None = None
    first_frame_noise: float | None = None
    photon_limit_pixel_global: np.ndarray | None = None


#: Bytes of an input product's (row, col) map read at a time (:func:`_at_pixels`).
MAP_BAND_BYTES = 2**24


def _map_bands(variable):
    """Consecutive slices of the rows of a (row, col) variable, about :data:`MAP_BAND_BYTES` of it each
    (:func:`dice_core.calibration.row_bands`, a byte a "sample" of an itemsize-frame chunk)."""
    from dice_core.calibration import row_bands

    return row_bands(variable.dtype.itemsize, variable.shape, samples=MAP_BAND_BYTES)


def _finite_pixels(variable):
    """``rows, cols`` (pixel,) where a (row, col) variable is finite, in row order (as np.nonzero gives
    them), read a band of rows at a time."""
    found = [(band.start, np.nonzero(np.isfinite(variable[band].values))) for band in _map_bands(variable)]
    return (np.concatenate([start + r for start, (r, _) in found] or [np.zeros(0, int)]),
            np.concatenate([c for _, (_, c) in found] or [np.zeros(0, int)]))


def _at_pixels(variable, rows, cols):
    """A (row, col) variable's values at ``rows``, ``cols`` (in row order), read a band of rows at a time:
    of a lazily opened product, no more than a band is held beside the values."""
    out = np.empty(rows.size, variable.dtype)
    for band in _map_bands(variable):
        lo, hi = np.searchsorted(rows, [band.start, band.stop])
        if hi > lo:
            out[lo:hi] = variable[band].values[rows[lo:hi] - band.start, cols[lo:hi]]
    return out


def _plain_bands(n, pixels_per_block):
    """Consecutive slices of ``n`` pixels, ``pixels_per_block`` long (one of all if None; one empty if none)."""
    step = n if pixels_per_block is None else int(pixels_per_block)
    return list(pixel_blocks(n, max(1, step))) or [slice(0, 0)]


def _rms_of(deviations, pixels_per_block):
    """:func:`_mean_variance_root` over the pixels of (size, pixel) ``deviations``, a band at a time."""
    total = _RootMeanSquare(deviations.shape[0])
    for band in _plain_bands(deviations.shape[1], pixels_per_block):
        total.add(deviations[:, band])
    return total.root()


def _batch_mean_sweep(offsets, sizes, pixels_per_block, keep, scratch):
    """The pixels' own statistics, a band at a time: which have an offset in every batch, their single-batch
    scatter (ddof 1), and the rms over pixels of the deviations of groups as means of batch fits (the
    deviations themselves, (size, pixel), if ``keep``)."""
    n_pixels = offsets.shape[1]
    good, scatter = np.zeros(n_pixels, bool), np.zeros(n_pixels)
    rms = [_RootMeanSquare(len(sizes)), _RootMeanSquare(len(sizes))]
    kept = [_pixel_array((len(sizes), n_pixels), scratch, name) for name in ("means", "means_allan")] if keep else None
    for band in _plain_bands(n_pixels, pixels_per_block):
        values = offsets[:, band]
        good[band], scatter[band] = np.isfinite(values).all(axis=0), np.std(values, axis=0, ddof=1)
        for i, deviations in enumerate(_deviations(values, sizes)):
            rms[i].add(deviations)
            if keep:
                kept[i][:, band] = deviations
    return good, scatter, [r.root() for r in rms], kept


def _white_noise(rng, scatter, n_batches, scratch):
    """White noise (batch, pixel) of the pixels' ``scatter``: ``rng.standard_normal((n_batches, pixel))``
    times it, drawn a batch at a time (the same numbers, in the same order)."""
    white = _pixel_array((n_batches, scatter.size), scratch, "white")
    for b in range(n_batches):
        white[b] = rng.standard_normal(scatter.size) * scatter
    return white


def _block_sweep(offsets, floors, white, weights, good, sizes, pixels_per_block, paper_limit):
    """What needs whole blocks, a band of them at a time: the blocks' mean offsets (batch, block), the sums
    over pixels and blocks of the batches' floors' variances (batch,) and of the paper's limits' (size,),
    and the rms over pixels of the white noise's deviations (size,)."""
    n_batches, n_blocks = offsets.shape[0], weights.shape[1]
    blocks = np.zeros((n_batches, n_blocks))
    sums = {name: np.zeros(n) for name, n in (("pixel", n_batches), ("block", n_batches), ("paper", len(sizes)),
                                              ("paper_block", len(sizes)))}
    white_rms = _RootMeanSquare(len(sizes))
    for band in _pixel_bands(weights, pixels_per_block):
        band_good = good[band]
        band_weights, columns = _band_weights(weights, band)
        blocks[:, columns] = np.where(band_good, offsets[:, band], 0.0) @ band_weights
        variance = np.where(band_good, floors[:, band], 0.0) ** 2
        sums["pixel"] += variance.sum(axis=1)
        sums["block"] += (variance @ band_weights**2).sum(axis=1)  # independent pixels in a block
        white_rms.add(_deviations(white[:, band], sizes)[0])
        paper = np.where(band_good, paper_limit(band), 0.0) ** 2
        sums["paper"] += paper.sum(axis=1)
        sums["paper_block"] += (paper @ band_weights**2).sum(axis=1)
    return blocks, sums, white_rms.root()


def allan_statistics(offsets, floors, batches, rows, cols, *, gain, level, amplitude, iota, alpha, read_noise, k,
                     block: int = 10, seed: int = 0, n_sample_pixels: int = 40, groups=None,
                     first_frame=None, global_floor=None, pixels_per_block=None, scratch=None,
                     weights=None) -> AllanStatistics:
    """Deviations, their white-noise references and photon-noise limits from the batch offsets (arrays only).

    Parameters are those of :func:`allan_dataset`, with the detector's
    ``gain`` (e-/adu) for the detector; the pixels are ``rows``, ``cols``.
    ``offsets`` and ``floors`` may be ScratchArrays (or anything giving
    ``[:, pixels]`` for a slice of pixels): they are read
    ``pixels_per_block`` pixels at a time (in bands of whole blocks where
    blocks are formed; None: all at once), the white-noise cube goes to
    ``scratch`` if given, and so do the per-pixel deviations (size, pixel)
    that are not ``groups``'. The same values whatever the bands, to rounding.
    ``weights``: the :func:`block_weights` of the pixels with an offset in
    every batch, if the caller has them (made here if None).

    Returns
    -------
    AllanStatistics
    """
    n_batches, n_pixels = offsets.shape
    sizes = group_sizes(n_batches)
    frames_per_batch = float(np.mean(batches[:, 1] - batches[:, 0]))
    n_frames = sizes * frames_per_batch
    # groups as means of their batch fits (kept per pixel only if they are the product's curves)
    good, scatter, (mean_batch_means, mean_allan_batch_means), kept = _batch_mean_sweep(
        offsets, sizes, pixels_per_block, groups is None, scratch)
    if weights is None:
        weights = block_weights(rows, cols, good=good, block=block)
    # white noise of the same per-pixel (and per-block) scatter as the data at one batch per group
    rng = np.random.default_rng(seed)
    white = _white_noise(rng, scatter, n_batches, scratch)
    k_norm = float(np.hypot(*k))
    pixel_values = [np.broadcast_to(np.asarray(v, float), (n_pixels,)) for v in (iota, alpha, read_noise)]

    def paper_limit(band):
        return photon_limit(n_frames, level, amplitude=amplitude, iota=pixel_values[0][band],
                            alpha=pixel_values[1][band], gain=gain, read_noise=pixel_values[2][band], k_norm=k_norm)

    blocks, sums, white_mean = _block_sweep(offsets, floors, white, weights, good, sizes, pixels_per_block,
                                            paper_limit)
    del white
    white_blocks = rng.standard_normal(blocks.shape) * np.std(blocks, axis=0, ddof=1)
    per_block, per_block_allan = _deviations(blocks, sizes)
    white_block, _ = _deviations(white_blocks, sizes)
    # The limits: the variance of a group mean is the sum of its batches' variances over m^2,
    # averaged over groups (as the deviation between group means is), then over pixels or blocks:
    # the mean batch variance over the batches the groups use, over m.
    pixel_variance = sums["pixel"] / good.sum()  # (batch,): mean over good pixels
    block_variance = sums["block"] / weights.shape[1]
    used = (n_batches // sizes) * sizes
    limit_pixel = np.sqrt(np.array([pixel_variance[:n].mean() for n in used]) / sizes)
    limit_block = np.sqrt(np.array([block_variance[:n].mean() for n in used]) / sizes)
    batch_means = {}
    mean, allan_mean = mean_batch_means, mean_allan_batch_means
    per_pixel, per_pixel_allan = kept if kept is not None else (None, None)
    if groups is not None:
        # the contract's curves: each group fitted as a whole; the means of batch fits kept beside them
        if groups["deviation"].shape != (len(sizes), n_pixels) or groups["block_deviation"].shape != per_block.shape:
            raise ValueError(f"group statistics of shape {groups['deviation'].shape} and "
                             f"{groups['block_deviation'].shape} for {len(sizes)} group sizes, "
                             f"{n_pixels} pixels and {per_block.shape[1]} blocks")
        batch_means = {"deviation_mean_batch_means": mean_batch_means, "photon_limit_pixel_batch_means": limit_pixel}
        per_pixel, per_pixel_allan = groups["deviation"], groups["allan"]
        mean, allan_mean = _rms_of(per_pixel, pixels_per_block), _rms_of(per_pixel_allan, pixels_per_block)
        per_block, per_block_allan = groups["block_deviation"], groups["block_allan"]
        limit_pixel, limit_block = groups["limit_pixel"], groups["limit_block"]
    first = {}
    if first_frame is not None:
        use = good & np.isfinite(first_frame)
        pixels = [np.broadcast_to(np.asarray(v, float), good.shape)[use] for v in (first_frame, alpha, read_noise)]
        first["photon_limit_pixel_first_frame"], first["first_frame_noise"] = first_frame_limit(
            n_frames, pixels[0], amplitude=amplitude, alpha=pixels[1], gain=gain, read_noise=pixels[2], k_norm=k_norm)

    def log_slope(values):
        return float(np.polyfit(np.log(n_frames), np.log(values), 1)[0]) if len(sizes) > 1 else np.nan

    if global_floor is not None:  # the whole acquisition's floors (pixel,) and its frames
        floor, total = global_floor
        first["photon_limit_pixel_global"] = np.sqrt(np.mean(floor[good] ** 2) * total / n_frames)
    if batch_means:
        batch_means["slope_batch_means"] = log_slope(batch_means["deviation_mean_batch_means"])
    sample = np.flatnonzero(good)[np.linspace(0, good.sum() - 1, min(n_sample_pixels, good.sum())).astype(int)]
    return AllanStatistics(
        group_size=sizes, n_groups=n_batches // sizes, n_frames=n_frames, frames_per_batch=frames_per_batch,
        deviation=per_pixel, allan_deviation=per_pixel_allan, deviation_mean=mean, allan_deviation_mean=allan_mean,
        deviation_block_mean=_mean_variance_root(per_block),
        allan_deviation_block_mean=_mean_variance_root(per_block_allan),
        white_deviation_mean=white_mean, white_deviation_block_mean=_mean_variance_root(white_block),
        photon_limit_pixel=limit_pixel, photon_limit_block=limit_block,
        photon_limit_pixel_paper=np.sqrt(sums["paper"] / good.sum()),
        photon_limit_block_paper=np.sqrt(sums["paper_block"] / weights.shape[1]),
        slope=log_slope(mean),
        sample_pixel=sample, sample_deviation=per_pixel[:, sample],
        batch_start=batches[:, 0], batch_frames=batches[:, 1] - batches[:, 0], batch_offset=offsets,
        **batch_means, **first)


def allan_dataset(offsets, floors, batches, rows, cols, detector, *, level, amplitude, iota, alpha, read_noise,
                  k, block: int = 10, seed: int = 0, n_sample_pixels: int = 40, groups=None,
                  first_frame=None, global_floor=None, pixels_per_block=None, scratch=None,
                  weights=None) -> xr.Dataset:
    """The ``allan/<baseline>.nc`` product from the batch offsets.

    The statistics are :func:`allan_statistics`'s; this adds the maps, units
    and long names (:func:`statistics_dataset`).

    Parameters
    ----------
    offsets : ndarray (batch, pixel)
        From :func:`batch_offsets`, pixel.
    floors : ndarray (batch, pixel)
        Their photon-noise errors (:func:`batch_floors`), pixel.
    batches : ndarray (batch, 2)
    rows, cols : ndarray (pixel,)
    detector : Detector
        Shape and gain.
    level, amplitude : float
        Mean B and A of the acquisition, adu.
    iota, alpha, read_noise : ndarray (pixel,)
        Relative intensity and amplitude (1), read noise (adu).
    k : (float, float)
        Wavevector, rad/pixel.
    block : int
        Side of the pixel blocks, pixel.
    seed : int
        Of the white-noise reference cube.
    n_sample_pixels : int
        Pixels whose own deviation curves the figure draws (evenly spread).
    groups : dict, optional
        The statistics of the groups fitted as a whole (:func:`group_fits`,
        with the sizes of :func:`group_sizes` and this function's blocks).
        Given, they make the deviations and their limits; the means of batch
        fits (the paper's) stay as ``deviation_mean_batch_means``,
        ``photon_limit_pixel_batch_means`` and ``slope_batch_means``.
    first_frame : ndarray (pixel,), optional
        The acquisition's first frame minus the dark at ``rows``, ``cols``,
        adu: given, the limit from the noise measured on it
        (:func:`first_frame_limit`) is added as
        ``photon_limit_pixel_first_frame``, with ``first_frame_noise``.
    global_floor : (ndarray (pixel,), int), optional
        The global solution's photon_noise_floor at ``rows``, ``cols`` (pixel)
        and the frames it was fitted on: given, their rms scaled to each
        group, sqrt(frames / n_frames), is added as
        ``photon_limit_pixel_global`` (the reference every group's deviation
        should meet: docs/metrology.md).
    pixels_per_block : int, optional
        Pixels read at a time (:func:`allan_statistics`); None: all at once.
    scratch : path, optional
        A folder for the (batch, pixel) and (size, pixel) arrays the
        statistics make (None: in memory).
    weights : scipy.sparse array (pixel, block), optional
        :func:`block_weights` of the pixels with an offset in every batch
        (``block`` a side), if already made (:func:`group_fits` takes them
        too); None: made from the offsets.

    Returns
    -------
    xarray.Dataset
        Coordinate ``n_frames`` (mean frames per group). Per pixel:
        ``deviation`` and ``allan_deviation`` (n_frames, row, col). Averaged:
        ``deviation_mean``, ``allan_deviation_mean``, ``deviation_block_mean``,
        ``allan_deviation_block_mean``, the white-noise references
        ``white_deviation_mean`` and ``white_deviation_block_mean``, and the
        photon-noise limits ``photon_limit_pixel``, ``photon_limit_block``;
        ``slope`` of log deviation_mean against log n_frames; the batch offsets
        and lengths. With ``groups``, also ``deviation_mean_batch_means``,
        ``photon_limit_pixel_batch_means`` (the groups as means of batch fits).
        With ``first_frame``, also ``photon_limit_pixel_first_frame``
        (n_frames) and ``first_frame_noise`` (scalar, adu). With
        ``global_floor``, ``photon_limit_pixel_global`` (n_frames).
        Pixel arrays held on disk (``offsets``, and with ``scratch`` the
        deviations) give maps read lazily from there.
    """
    statistics = allan_statistics(offsets, floors, batches, rows, cols, gain=detector.gain, level=level,
                                  amplitude=amplitude, iota=iota, alpha=alpha, read_noise=read_noise, k=k,
                                  block=block, seed=seed, n_sample_pixels=n_sample_pixels, groups=groups,
                                  first_frame=first_frame, global_floor=global_floor,
                                  pixels_per_block=pixels_per_block, scratch=scratch, weights=weights)
    return statistics_dataset(statistics, rows, cols, detector.shape, block=block)


def _allan_variables(statistics: AllanStatistics, block: int) -> dict:
    """Each variable of the product: (dims, units, long_name), in the product's order; those of the
    statistics that are None left out."""
    grouped = statistics.deviation_mean_batch_means is not None
    n, maps = ("n_frames",), ("n_frames", "row", "col")
    blocks = f"{block}x{block}-pixel"
    variables = {
        "group_size": (n, "1", "batches per group"),
        "n_groups": (n, "1", "groups the deviation is taken over"),
        "deviation": (maps, "pixel", "standard deviation between groups (the paper's statistic)"),
        "allan_deviation": (maps, "pixel", "non-overlapping Allan deviation"),
        "deviation_mean": (n, "pixel", "deviation between groups, rms over pixels" + (
            ", each group fitted as a whole" if grouped else ", each group the mean of its batch fits")),
        "deviation_mean_batch_means": (n, "pixel", "deviation between groups as means of their batch fits (the "
                                                   "paper's), rms over pixels"),
        "photon_limit_pixel_batch_means": (n, "pixel", "photon-noise limit of deviation_mean_batch_means"),
        "allan_deviation_mean": (n, "pixel", "Allan deviation, rms over pixels"),
        "deviation_block_mean": (n, "pixel", f"deviation of {blocks} block means, rms over blocks"),
        "allan_deviation_block_mean": (n, "pixel", f"Allan deviation of {blocks} block means, rms over blocks"),
        "white_deviation_mean": (n, "pixel", "deviation_mean of white noise of the data's single-batch scatter"),
        "white_deviation_block_mean": (n, "pixel", "deviation_block_mean of white noise of the blocks' "
                                                   "single-batch scatter"),
        "photon_limit_pixel": (n, "pixel", "photon-noise limit of deviation_mean, from the fits' own errors"),
        "photon_limit_block": (n, "pixel", "photon-noise limit of deviation_block_mean, from the fits' own errors"),
        "photon_limit_pixel_paper": (n, "pixel", "paper's photon-noise limit of one pixel, "
                                                 "sqrt(Bi/g+sr^2)/(Aa|K|sqrt(N/2))"),
        "photon_limit_block_paper": (n, "pixel", f"paper's photon-noise limit of a {blocks} block"),
        "photon_limit_pixel_first_frame": (n, "pixel", "photon-noise limit of one pixel from the noise measured on "
                                                       "the first frame, sqrt(f/g+sr^2)/(Aa|K|sqrt(N/2)), rms over "
                                                       "pixels"),
        "first_frame_noise": ((), "adu", "noise of one frame from the first frame's signal f (minus dark), "
                                         "sqrt(f/g+sr^2), rms over pixels"),
        "photon_limit_pixel_global": (n, "pixel", "the global solution's photon_noise_floor scaled to the group, "
                                                  "rms over pixels times sqrt(frames of the solution / n_frames)"),
        "slope": ((), "1", "log-log slope of deviation_mean against n_frames"),
        "slope_batch_means": ((), "1", "log-log slope of deviation_mean_batch_means against n_frames"),
        "sample_pixel": (("sample",), "1", "index of pixels drawn in the figure"),
        "sample_deviation": (("n_frames", "sample"), "pixel", "deviation of the sample pixels"),
        "batch_start": (("batch",), "1", "first frame of the batch"),
        "batch_frames": (("batch",), "1", "frames in the batch"),
        "batch_offset": (("batch", "row", "col"), "pixel", "projected offset of each batch minus the global "
                                                           "solution's, affine part removed"),
    }
    return {name: spec for name, spec in variables.items() if getattr(statistics, name) is not None}


class _PixelMaps:
    """(n, row, col) maps of ``dtype`` of a (n, pixel) array at ``rows``, ``cols`` (NaN elsewhere), made a few
    rows of the detector at a time when read: an xarray backend array (a product variable that stays on disk,
    read lazily, and that :func:`dice_core.io.write_product` writes a slice at a time)."""

    def __init__(self, values, rows, cols, shape, dtype):
        self.values, self.rows, self.cols = values, rows, cols
        self.shape, self.dtype = (values.shape[0], *shape), np.dtype(dtype)

    @staticmethod
    @functools.cache
    def lazy_type():
        """This class as an xarray backend array (xarray imported when first needed)."""
        from xarray.backends import BackendArray

        return type("PixelMaps", (_PixelMaps, BackendArray), {})

    def __getitem__(self, key):
        from xarray.core import indexing

        return indexing.explicit_indexing_adapter(key, self.shape, indexing.IndexingSupport.OUTER, self._outer)

    def _outer(self, key):
        n, rows, cols = key  # each an int, a slice or an array of ints (outer indexing)
        wanted = np.arange(self.shape[1])[rows]
        lo, hi = (int(np.min(wanted)), int(np.max(wanted)) + 1) if np.size(wanted) else (0, 0)
        inside = np.flatnonzero((self.rows >= lo) & (self.rows < hi))
        # the pixels of these rows: one slice when the pixels are in row order, as np.nonzero gives them
        pixels = slice(inside[0], inside[-1] + 1) if inside.size and inside[-1] - inside[0] + 1 == inside.size \
            else inside
        values = (self.values[n, pixels] if isinstance(n, slice)
                  else np.stack([self.values[i, pixels] for i in np.atleast_1d(n)]))
        out = np.full((values.shape[0], hi - lo, self.shape[2]), np.nan, self.dtype)
        out[:, self.rows[inside] - lo, self.cols[inside]] = values  # cast as astype() would
        out = out[:, np.asarray(wanted) - lo][..., cols]
        return out[0] if np.ndim(n) == 0 and not isinstance(n, slice) else out


def statistics_dataset(statistics: AllanStatistics, rows, cols, shape, *, block: int = 10) -> xr.Dataset:
    """The ``allan/<baseline>.nc`` product of :func:`allan_statistics`: pixel arrays as (row, col) maps of
    the detector's ``shape`` (NaN off ``rows``, ``cols``), units and long names; the batch offsets stored
    as float32. Pixel arrays held on disk (ScratchArrays) stay there: their maps are read lazily
    (:class:`_PixelMaps`)."""

    def as_maps(values, dtype):
        if not isinstance(values, np.ndarray):
            from xarray.core import indexing

            return indexing.LazilyIndexedArray(_PixelMaps.lazy_type()(values, rows, cols, shape, dtype))
        out = np.full((values.shape[0], *shape), np.nan, dtype)
        out[:, rows, cols] = values  # cast as astype() would, with no float64 map of the detector on the way
        return out

    data = {}
    for name, (dims, units, long_name) in _allan_variables(statistics, block).items():
        values = getattr(statistics, name)
        if "row" in dims:
            values = as_maps(values, np.float32 if name == "batch_offset" else np.float64)
        data[name] = (dims, values, {"units": units, "long_name": long_name})
    n_batches = statistics.batch_start.size
    return xr.Dataset(
        data,
        coords={"n_frames": ("n_frames", statistics.n_frames, {"units": "1", "long_name": "mean frames per group"}),
                "row": np.arange(shape[0]), "col": np.arange(shape[1]), "batch": np.arange(n_batches)},
        attrs={"frames_per_batch": statistics.frames_per_batch, "block_size": block},
    )


def _parked(values, folder, name):
    """``values`` (an array) moved to a :class:`ScratchArray` in ``folder``: ``[...]`` gives them back."""
    parked = ScratchArray(folder, values.shape, values.dtype, name=name)
    parked[...] = values
    return parked


@one_blas_thread
def allan_of_baseline(stream, metrology: xr.Dataset, *, dark: xr.Dataset, detector, block: int = 10,
                      workers: int = 1, label: str = "baseline", scratch=None, pixels_per_block=None) -> xr.Dataset:
    """Allan deviations of one baseline from its raw frames and its global solution.

    Parameters
    ----------
    stream : FrameStream
        The metrology acquisition (read once, centred on its first chunk's mean
        frame so that the float32 products stay exact).
    metrology : xarray.Dataset
        The baseline's ``metrology/<baseline>.nc`` product: phase, level and
        amplitude per frame; kx, ky; the maps projected_offset, iota, alpha,
        pixel_phase and photon_noise_floor, read at the fitted pixels a band
        of rows at a time (no other variable is read): opened lazily
        (:func:`dice_core.io.open_product`), it is never held whole.
    dark : xarray.Dataset
        ``calibration/dark.nc``: dark and noise (read noise), adu; the dark
        map read whole, the noise at the pixels (lazily opened, as ``metrology``).
    detector : Detector
    block : int
        Side of the pixel blocks, pixel.
    workers : int
        Processes reading the stream's parts at once (see :func:`batch_offsets`).
    scratch : path, optional
        Folder in which a temporary folder (:func:`dice_core.scratch.scratch_directory`,
        removed on return or error) holds what grows with pixels times
        batches: the batches' sums and offsets, the white-noise cube,
        the per-pixel deviations (the job's output folder: the disk of the
        results, not the system's temporary one). None: the system's
        temporary folder.
    pixels_per_block : int, optional
        Pixels the statistics read at a time (in bands of whole blocks); None:
        :data:`BAND_NUMBERS` over the batches. The product is the same whatever
        it is, to rounding.

    Returns
    -------
    xarray.Dataset
        The ``allan/<baseline>.nc`` product (:func:`allan_dataset`). Its maps
        over batches and group sizes (``batch_offset``, ``deviation``,
        ``allan_deviation``) stay on disk, in files already unlinked whose
        space is freed with the dataset: read lazily, and written a slice at
        a time by :func:`dice_core.io.write_product`.

    Raises
    ------
    AllanError
        Too few frames for two batches; a stream shorter than the solution.
    """
    phase = metrology["phase"].values
    if stream.n_frames != phase.size:
        raise AllanError(f"{label}: the acquisition has {stream.n_frames} frames, its solution {phase.size}")
    batches = fringe_batches(phase)
    log.info("%s: %d batches of %d frames (any %d frames sweep a fringe period), %d frames left over",
             label, len(batches), batches[0, 1] - batches[0, 0], batches[0, 1] - batches[0, 0],
             phase.size - batches[-1, 1])
    if too_few := few_batches(len(batches), batches[0, 1] - batches[0, 0]):  # the figure says it too, in its title
        log.warning("%s: %s", label, too_few)
    # the input products' maps are read at the pixels only, a band of rows at a time: a lazily opened product
    # (io.open_product) is never held whole, nor its variables this step does not use
    rows, cols = _finite_pixels(metrology["projected_offset"])
    k = np.array([float(metrology["kx"]), float(metrology["ky"])])
    if "pixel_phase" in metrology:  # the fitted pixel phases, whatever the shape of the fringes
        reference_phase = _at_pixels(metrology["pixel_phase"], rows, cols)
    else:  # a product from before pixel_phase (plane waves): the same up to a constant
        reference_phase = (k[0] * cols + k[1] * rows
                           + np.hypot(*k) * _at_pixels(metrology["projected_offset"], rows, cols))
    level, amplitude = metrology["level"].values, metrology["amplitude"].values
    frame_factors = np.column_stack([level, amplitude * np.cos(phase), amplitude * np.sin(phase)])
    dark_map = np.nan_to_num(dark["dark"].values)  # whole: the pass subtracts it (one map of the detector)
    head = first_chunk(stream)
    reference = head.frames.mean(axis=0)
    first_frame = head.frames[0][rows, cols].astype(np.float64) - dark_map[rows, cols]
    del head
    iota, alpha = _at_pixels(metrology["iota"], rows, cols), _at_pixels(metrology["alpha"], rows, cols)
    pixel_factors = _PixelFactors(iota, alpha, reference_phase)  # made a band at a time where read
    read_noise = np.nan_to_num(_at_pixels(dark["noise"], rows, cols))
    sizes = group_sizes(len(batches))
    band = max(1, BAND_NUMBERS // len(batches)) if pixels_per_block is None else pixels_per_block
    with scratch_directory(scratch) as folder:
        # what only the product's last variables use waits on disk (read back at the end), not in memory
        # through the pass and the groups' fits, where the job's memory peaks
        first_frame = _parked(first_frame, folder, "first_frame")
        good = np.ones(rows.size, bool)  # the pixels with an offset in every batch, found by the pass
        offsets, sums = batch_offsets(stream.centred(reference), batches, frame_factors, dark_map, reference_phase,
                                      k, rows, cols, pixel_factors=pixel_factors, reference=reference,
                                      workers=workers, return_sums=True, scratch=folder, label=label, finite=good)
        del dark_map, reference
        weights = block_weights(rows, cols, good=good, block=block)
        groups = group_fits(sums, batches, frame_factors, reference_phase, k, rows, cols, sizes,
                            pixel_factors=pixel_factors, gain=detector.gain, read_noise=read_noise, good=good,
                            weights=weights, pixels_per_block=band, scratch=folder)
        del sums  # its file's space freed: the groups are reduced
        floors = _BatchFloors(frame_factors, batches, pixel_factors=pixel_factors, gain=detector.gain,
                              read_noise=read_noise, k_norm=np.hypot(*k))  # made a band at a time
        log.info("%s: %d group sizes fitted as a whole, from %d to %d batches", label, len(sizes), sizes[0],
                 sizes[-1])
        global_floor = None
        if "photon_noise_floor" in metrology:  # the whole acquisition's floor, for the curves' reference
            global_floor = (_at_pixels(metrology["photon_noise_floor"], rows, cols), phase.size)
        first_frame = first_frame[...]
        return allan_dataset(offsets, floors, batches, rows, cols, detector, level=float(np.mean(level)),
                             amplitude=float(np.mean(amplitude)), iota=iota, alpha=alpha, read_noise=read_noise,
                             k=k, block=block, groups=groups, first_frame=first_frame, global_floor=global_floor,
                             pixels_per_block=band, scratch=folder, weights=weights)
