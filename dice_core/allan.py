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

import logging
from dataclasses import dataclass

import numpy as np

from dice_core import lazy
from dice_core.fringes import frame_moments, photon_floor
from dice_core.io import first_chunk
from dice_core.parallel import (LANES, blas_threads, lane_executor, lane_workers, map_lanes, one_blas_thread,
                                threads_report)
from dice_core.polynomials import polynomial_design

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
    design: np.ndarray  # affine design over the pixels
    k_norm: float  # rad/pixel
    iota: np.ndarray = None  # (pixel,) relative intensity, held fixed: the phase-only fit
    alpha: np.ndarray = None  # (pixel,) relative fringe amplitude, held fixed
    basis: np.ndarray = None  # orthonormal columns spanning ``design``: the affine part removed by a projection
    rotation: np.ndarray = None  # exp(-i reference_phase)

    def __post_init__(self):
        if self.basis is None:
            object.__setattr__(self, "basis", np.linalg.qr(self.design)[0])
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

    def offsets_of_sums(self, FtF, FtI):
        """Projected offsets (pixel,) of the least-squares fit with normal equations F'F (3, 3), F'I (3, pixel)."""
        # theta - reference as unit complex numbers, wrapped about their circular mean: the difference is
        # the constant phase the gauge leaves free plus the batch's small offset changes, and that
        # constant may be near pi (wrapped_about_mean, cheaper)
        turned = self.phases_of_sums(FtF, FtI) * self.rotation
        centre = np.mean(turned)
        delta = np.angle(turned * np.conj(centre / np.abs(centre)))
        return (delta - self.basis @ (self.basis.T @ delta)) / self.k_norm


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


def _lane_batch_offsets(chunks, batches, frame_factors, fit: _BatchFit, label):
    """One lane's part of :func:`batch_offsets`: the batches its chunks hold whole, and the others' partial sums.

    Returns ``(done, partial, blas_threads)``: ``done`` maps a batch index to its normal
    sums F'I (3, pixel of ``fit.idx``), ``partial`` maps a batch the chunks hold only part of to its
    sums F'X over those frames (3, pixel of ``fit.idx``) and the number of
    those frames; ``blas_threads`` those of the process that ran it (for the
    log). Module-level, so that a worker process can run it.
    """
    n_total = len(batches)
    lengths = batches[:, 1] - batches[:, 0]
    done, sums, covered = {}, {}, {}
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
            if covered[b] == lengths[b]:  # float32: a phase to 1e-7 rad, half the memory and the pipe
                done[b] = fit.normal_sums(frame_factors[start:stop], sums.pop(b)[:, fit.idx]).astype(np.float32)
                del covered[b]
                if len(done) % 100 == 0:
                    log.info("%s: %d batches fitted in one part of the frames", label, len(done))
    return done, {b: (part[:, fit.idx], covered[b]) for b, part in sums.items()}, blas_threads()


@one_blas_thread
def batch_offsets(chunks, batches, frame_factors, dark, reference_phase, k, rows, cols, *,
                  pixel_factors=None, reference=None, workers: int = 1, return_sums: bool = False,
                  label="baseline"):
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
    fit = _BatchFit(idx=idx, level=(centre - np.ravel(dark))[idx],  # X - d = (X - r) + (r - d)
                    reference_phase=np.asarray(reference_phase, float),
                    design=polynomial_design(cols.astype(float), rows.astype(float), degree=1),
                    k_norm=float(np.hypot(*k)), **_held(pixel_factors))
    batches = np.asarray(batches)
    lanes = chunks.split(LANES) if hasattr(chunks, "split") else [chunks]
    with lane_executor(workers, len(lanes)) as executor:
        log.info("%s: %d batch fits over %d part(s) of the frames, in %d process(es)", label, len(batches),
                 len(lanes), lane_workers(workers, len(lanes)))
        results = map_lanes(executor, _lane_batch_offsets, lanes, batches, frame_factors, fit, label)
    log.info("%s: %s", label, threads_report(executor, [threads for _, _, threads in results]))
    out = np.full((len(batches), idx.size), np.nan)
    kept = np.zeros((len(batches), 3, idx.size), np.float32) if return_sums else None
    fitted = np.zeros(len(batches), bool)
    partial, covered = {}, {}

    def finish(b, FtI):
        start, stop = batches[b]
        F = frame_factors[start:stop]
        FtI = np.asarray(FtI, np.float32)  # every batch's sums rounded alike, wherever the lanes cut
        out[b], fitted[b] = fit.offsets_of_sums(F.T @ F, FtI.astype(np.float64)), True
        if kept is not None:
            kept[b] = FtI

    for done, sums, _ in results:  # in lane order, so that a batch cut between parts sums the same way always
        while done:  # each lane's sums released as they are kept: one copy of them in memory, not two
            b, FtI = done.popitem()
            finish(b, FtI)
        for b, (part, n_frames) in sums.items():
            partial[b] = part if b not in partial else partial[b] + part
            covered[b] = covered.get(b, 0) + n_frames
    for b, part in partial.items():
        start, stop = batches[b]
        if covered[b] == stop - start:
            finish(b, fit.normal_sums(frame_factors[start:stop], part))
    if not fitted.all():
        raise AllanError(f"{label}: the frames ended in batch {np.flatnonzero(~fitted)[0]} of {len(batches)}")
    return (out, kept) if return_sums else out


def _held(pixel_factors):
    """The iota and alpha a phase-only :class:`_BatchFit` holds, from pixel factors (pixel, 3); none without."""
    if pixel_factors is None:
        return {}
    pixel_factors = np.asarray(pixel_factors, float)
    return {"iota": pixel_factors[:, 0], "alpha": np.hypot(pixel_factors[:, 1], pixel_factors[:, 2])}


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


def group_fits(sums, batches, frame_factors, reference_phase, k, rows, cols, sizes, *, pixel_factors, gain,
               read_noise, good, weights, phase_only: bool = True):
    """Deviations and photon-noise limits of consecutive groups of batches, each group fitted as a whole.

    A group's normal equations are the sums of its batches' (F'F and F'I from
    :func:`batch_offsets` with ``return_sums``): its fit is the least-squares
    fit of all its frames at once, whose phases cover the circle evenly once
    the group spans several periods, where the mean of its one-period batch
    fits keeps each batch's uneven sampling (docs/metrology.md).

    Parameters
    ----------
    sums : ndarray (batch, 3, pixel)
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

    Returns
    -------
    dict of ndarray, one row per size
        ``deviation`` and ``allan`` (size, pixel; NaN off ``good``),
        ``block_deviation`` and ``block_allan`` (size, block): the paper's
        deviation and the Allan deviation between the groups' offsets (affine
        part removed) of each pixel and block; ``limit_pixel`` and
        ``limit_block`` (size,): their photon-noise limits, the groups'
        variances from their own fits averaged over groups, then over pixels or
        blocks. All in pixel. Each size's groups are reduced as they are
        fitted: at most n_batches / 2 maps in memory.
    """
    fit = _BatchFit(idx=None, level=None, reference_phase=np.asarray(reference_phase, float),
                    design=polynomial_design(np.asarray(cols, float), np.asarray(rows, float), degree=1),
                    k_norm=float(np.hypot(*k)), **(_held(pixel_factors) if phase_only else {}))
    moments = [frame_moments(frame_factors[start:stop]) for start, stop in batches]
    # running sums of the small moments: a group's are two differences. The F'I are summed group by
    # group instead (a running sum would hold another float64 copy of them all).
    cum_FtF = np.concatenate([np.zeros((1, 3, 3)), np.cumsum([m[0] for m in moments], axis=0)])
    cum_third = np.concatenate([np.zeros((1, 3, 3, 3)), np.cumsum([m[1] for m in moments], axis=0)])
    out = {name: [] for name in ("deviation", "allan", "block_deviation", "block_allan", "limit_pixel",
                                 "limit_block")}
    for m in sizes:
        n_groups = len(batches) // m
        group_offsets = np.zeros((n_groups, sums.shape[2]))
        variance = np.zeros_like(group_offsets)
        for g in range(n_groups):
            lo, hi = g * m, (g + 1) * m
            FtF = cum_FtF[hi] - cum_FtF[lo]
            group_offsets[g, good] = fit.offsets_of_sums(FtF, sums[lo:hi].sum(axis=0, dtype=np.float64))[good]
            variance[g, good] = photon_floor(pixel_factors, FtF, third=cum_third[hi] - cum_third[lo], gain=gain,
                                             read_noise=read_noise, k_norm=fit.k_norm,
                                             phase_only=phase_only)[good] ** 2
        blocks = group_offsets @ weights
        out["deviation"].append(np.where(good, _deviation_of_means(group_offsets), np.nan))
        out["allan"].append(np.where(good, _allan_of_means(group_offsets), np.nan))
        out["block_deviation"].append(_deviation_of_means(blocks))
        out["block_allan"].append(_allan_of_means(blocks))
        out["limit_pixel"].append(np.sqrt(variance.mean() * good.size / good.sum()))
        out["limit_block"].append(np.sqrt((variance @ weights**2).mean()))
    return {name: np.array(values) for name, values in out.items()}


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
    deviation, allan_deviation : ndarray (size, pixel)
        Per pixel (the groups fitted as a whole when given, else means of batch fits).
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
    batch_offset : ndarray (batch, pixel)
        The batch offsets.
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


def allan_statistics(offsets, floors, batches, rows, cols, *, gain, level, amplitude, iota, alpha, read_noise, k,
                     block: int = 10, seed: int = 0, n_sample_pixels: int = 40, groups=None,
                     first_frame=None, global_floor=None) -> AllanStatistics:
    """Deviations, their white-noise references and photon-noise limits from the batch offsets (arrays only).

    Parameters are those of :func:`allan_dataset`, with the detector's
    ``gain`` (e-/adu) for the detector; the pixels are ``rows``, ``cols``.

    Returns
    -------
    AllanStatistics
    """
    n_batches = offsets.shape[0]
    sizes = group_sizes(n_batches)
    frames_per_batch = float(np.mean(batches[:, 1] - batches[:, 0]))
    n_frames = sizes * frames_per_batch
    good = np.isfinite(offsets).all(axis=0)
    weights = block_weights(rows, cols, good=good, block=block)
    blocks = np.where(good, offsets, 0.0) @ weights
    # white noise of the same per-pixel (and per-block) scatter as the data at one batch per group
    rng = np.random.default_rng(seed)
    # in place, and dropped once its statistics are taken: memory grows with batches x pixels here
    white = rng.standard_normal(offsets.shape)
    white *= np.std(offsets, axis=0, ddof=1)
    white_blocks = rng.standard_normal(blocks.shape) * np.std(blocks, axis=0, ddof=1)

    per_pixel, per_pixel_allan = _deviations(offsets, sizes)  # groups as means of their batch fits
    per_block, per_block_allan = _deviations(blocks, sizes)
    white_pixel, _ = _deviations(white, sizes)
    del white
    white_block, _ = _deviations(white_blocks, sizes)
    # The limits: the variance of a group mean is the sum of its batches' variances over m^2,
    # averaged over groups (as the deviation between group means is), then over pixels or blocks:
    # the mean batch variance over the batches the groups use, over m.
    variance = np.where(good, floors, 0.0)
    variance **= 2
    pixel_variance = variance.mean(axis=1) * good.size / good.sum()  # (batch,): mean over good pixels
    block_variance = (variance @ weights**2).mean(axis=1)  # independent pixels in a block
    used = (n_batches // sizes) * sizes
    limit_pixel = np.sqrt(np.array([pixel_variance[:n].mean() for n in used]) / sizes)
    limit_block = np.sqrt(np.array([block_variance[:n].mean() for n in used]) / sizes)
    batch_means = {}
    if groups is not None:
        # the contract's curves: each group fitted as a whole; the means of batch fits kept beside them
        if groups["deviation"].shape != per_pixel.shape or groups["block_deviation"].shape != per_block.shape:
            raise ValueError(f"group statistics of shape {groups['deviation'].shape} and "
                             f"{groups['block_deviation'].shape} for {len(sizes)} group sizes, "
                             f"{per_pixel.shape[1]} pixels and {per_block.shape[1]} blocks")
        batch_means = {"deviation_mean_batch_means": _mean_variance_root(per_pixel),
                       "photon_limit_pixel_batch_means": limit_pixel}
        per_pixel, per_pixel_allan = groups["deviation"], groups["allan"]
        per_block, per_block_allan = groups["block_deviation"], groups["block_allan"]
        limit_pixel, limit_block = groups["limit_pixel"], groups["limit_block"]
    k_norm = float(np.hypot(*k))
    paper = np.where(good, photon_limit(n_frames, level, amplitude=amplitude, iota=iota, alpha=alpha, gain=gain,
                                        read_noise=read_noise, k_norm=k_norm), 0.0)
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
    mean = _mean_variance_root(per_pixel)
    if batch_means:
        batch_means["slope_batch_means"] = log_slope(batch_means["deviation_mean_batch_means"])
    sample = np.flatnonzero(good)[np.linspace(0, good.sum() - 1, min(n_sample_pixels, good.sum())).astype(int)]
    return AllanStatistics(
        group_size=sizes, n_groups=n_batches // sizes, n_frames=n_frames, frames_per_batch=frames_per_batch,
        deviation=per_pixel, allan_deviation=per_pixel_allan, deviation_mean=mean,
        allan_deviation_mean=_mean_variance_root(per_pixel_allan),
        deviation_block_mean=_mean_variance_root(per_block),
        allan_deviation_block_mean=_mean_variance_root(per_block_allan),
        white_deviation_mean=_mean_variance_root(white_pixel), white_deviation_block_mean=_mean_variance_root(white_block),
        photon_limit_pixel=limit_pixel, photon_limit_block=limit_block,
        photon_limit_pixel_paper=np.sqrt(np.sum(paper**2, axis=1) / good.sum()),
        photon_limit_block_paper=np.sqrt(np.mean(paper**2 @ weights**2, axis=1)),
        slope=log_slope(mean),
        sample_pixel=sample, sample_deviation=per_pixel[:, sample],
        batch_start=batches[:, 0], batch_frames=batches[:, 1] - batches[:, 0], batch_offset=offsets,
        **batch_means, **first)


def allan_dataset(offsets, floors, batches, rows, cols, detector, *, level, amplitude, iota, alpha, read_noise,
                  k, block: int = 10, seed: int = 0, n_sample_pixels: int = 40, groups=None,
                  first_frame=None, global_floor=None) -> xr.Dataset:
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
    """
    statistics = allan_statistics(offsets, floors, batches, rows, cols, gain=detector.gain, level=level,
                                  amplitude=amplitude, iota=iota, alpha=alpha, read_noise=read_noise, k=k,
                                  block=block, seed=seed, n_sample_pixels=n_sample_pixels, groups=groups,
                                  first_frame=first_frame, global_floor=global_floor)
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


def statistics_dataset(statistics: AllanStatistics, rows, cols, shape, *, block: int = 10) -> xr.Dataset:
    """The ``allan/<baseline>.nc`` product of :func:`allan_statistics`: pixel arrays as (row, col) maps of
    the detector's ``shape`` (NaN off ``rows``, ``cols``), units and long names; the batch offsets stored
    as float32."""

    def as_maps(values, dtype):
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


@one_blas_thread
def allan_of_baseline(stream, metrology: xr.Dataset, *, dark: xr.Dataset, detector, block: int = 10,
                      workers: int = 1, label: str = "baseline") -> xr.Dataset:
    """Allan deviations of one baseline from its raw frames and its global solution.

    Parameters
    ----------
    stream : FrameStream
        The metrology acquisition (read once, centred on its first chunk's mean
        frame so that the float32 products stay exact).
    metrology : xarray.Dataset
        The baseline's ``metrology/<baseline>.nc`` product: phase, level and
        amplitude per frame; projected_offset, iota, alpha, kx, ky.
    dark : xarray.Dataset
        ``calibration/dark.nc``: dark and noise (read noise), adu.
    detector : Detector
    block : int
        Side of the pixel blocks, pixel.
    workers : int
        Processes reading the stream's parts at once (see :func:`batch_offsets`).

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
    offsets_map = metrology["projected_offset"].values
    rows, cols = np.nonzero(np.isfinite(offsets_map))
    k = np.array([float(metrology["kx"]), float(metrology["ky"])])
    if "pixel_phase" in metrology:  # the fitted pixel phases, whatever the shape of the fringes
        reference_phase = metrology["pixel_phase"].values[rows, cols]
    else:  # a product from before pixel_phase (plane waves): the same up to a constant
        reference_phase = k[0] * cols + k[1] * rows + np.hypot(*k) * offsets_map[rows, cols]
    level, amplitude = metrology["level"].values, metrology["amplitude"].values
    frame_factors = np.column_stack([level, amplitude * np.cos(phase), amplitude * np.sin(phase)])
    head = first_chunk(stream)
    reference = head.frames.mean(axis=0)
    first_frame = (head.frames[0].astype(np.float64) - np.nan_to_num(dark["dark"].values))[rows, cols]
    del head
    iota, alpha = metrology["iota"].values[rows, cols], metrology["alpha"].values[rows, cols]
    pixel_factors = np.column_stack([iota, alpha * np.sin(reference_phase), alpha * np.cos(reference_phase)])
    offsets, sums = batch_offsets(stream.centred(reference), batches, frame_factors,
                                  np.nan_to_num(dark["dark"].values), reference_phase, k, rows, cols,
                                  pixel_factors=pixel_factors, reference=reference, workers=workers,
                                  return_sums=True, label=label)
    read_noise = np.nan_to_num(dark["noise"].values[rows, cols])
    sizes = group_sizes(len(batches))
    good = np.isfinite(offsets).all(axis=0)
    groups = group_fits(sums, batches, frame_factors, reference_phase, k, rows, cols, sizes,
                        pixel_factors=pixel_factors, gain=detector.gain, read_noise=read_noise, good=good,
                        weights=block_weights(rows, cols, good=good, block=block))
    del sums  # the groups are reduced: only the batch offsets go on
    # the batches' floors once the sums are gone: the groups' fits hold two maps a group at one batch a
    # group, so the job's peak is there; the floors beside them would add an eighth map a batch
    floors = batch_floors(frame_factors, batches, pixel_factors=pixel_factors, gain=detector.gain,
                          read_noise=read_noise, k_norm=np.hypot(*k))
    global_floor = None
    if "photon_noise_floor" in metrology:  # the whole acquisition's floor, for the curves' reference
        global_floor = (metrology["photon_noise_floor"].values[rows, cols], phase.size)
    log.info("%s: %d group sizes fitted as a whole, from %d to %d batches", label, len(sizes), sizes[0], sizes[-1])
    return allan_dataset(offsets, floors, batches, rows, cols, detector, level=float(np.mean(level)),
                         amplitude=float(np.mean(amplitude)), iota=iota, alpha=alpha, read_noise=read_noise, k=k,
                         block=block, groups=groups, first_frame=first_frame,
                         global_floor=global_floor)
