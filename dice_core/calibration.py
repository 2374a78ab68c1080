"""Dark and flat-field (PRNU) calibration maps.

Functions take streams of :class:`dice_core.io.Chunk` (frames in ADU, with
their saturation masks) and return xarray Datasets with units; they never open
files. Maps are (row, col); outside the science area every map is NaN, as the
products contract requires.

The PRNU follows the paper's five steps (section "Dark subtraction and
flat-field correction"): dark subtraction, per-frame normalisation to the first
frame's level, temporal mean, gradient removal, normalisation to 1.
"""

from __future__ import annotations

import logging
from typing import Iterable

import numpy as np

from dice_core import lazy
from dice_core.io import Chunk
from dice_core.polynomials import polynomial_design, polynomial_scaling, polynomial_terms
from dice_core.manifest import Detector

xr = lazy.module("xarray")

__all__ = [
    "fringe_fit_calibrations",
    "TemporalStatistics",
    "dark_maps",
    "prnu_map",
    "prnu_difference",
    "remove_gradient",
    "area_rms",
    "BAD_PIXEL_FLAGS",
    "bad_pixel_mask",
]

log = logging.getLogger(__name__)


#: Samples (frames x pixels) of a chunk that :class:`TemporalStatistics` and :func:`prnu_map` take at a time:
#: a chunk is worked on in bands of whole rows of about this many samples (a row at least), so that each
#: float64 temporary of the arithmetic is about 8 MiB whatever the chunk (4 frames of 4096x4096 are 64
#: times more). Each pixel's sums run over the same frames in the same order whatever the bands: the
#: maps do not depend on them, bit for bit.
BAND_SAMPLES = 1 << 20


def row_bands(frames: int, shape, *, samples: int | None = None) -> list[slice]:
    """Consecutive slices of the rows of ``shape`` (rows, cols), each about ``samples`` samples
    (:data:`BAND_SAMPLES` if None) of a chunk of ``frames`` frames (a row at least), covering every row once."""
    rows, cols = shape
    samples = BAND_SAMPLES if samples is None else samples
    step = max(1, samples // max(1, frames * cols))
    return [slice(first, min(first + step, rows)) for first in range(0, rows, step)]


class TemporalStatistics:
    """Per-pixel mean and variance over frames, accumulated chunk by chunk.

    Uses the pairwise update of Chan, Golub & LeVeque (1979) in float64, so
    the result does not depend on chunking beyond rounding, and memory is a few
    maps whatever the number of frames. Masked samples (``valid`` False) are
    left out and counted. A chunk is added a band of rows at a time
    (:meth:`update_rows`, bands of :func:`row_bands`, as :func:`dark_maps`
    and :func:`prnu_map` take it): its temporaries stay a few MiB.
    """

    def __init__(self, shape):
        self.count = np.zeros(shape, dtype=np.int64)
        self.mean = np.zeros(shape)
        self._m2 = np.zeros(shape)
        self.masked = np.zeros(shape, dtype=np.int64)

    def update_rows(self, rows: slice, frames: np.ndarray, valid: np.ndarray | None = None):
        """Add frames (frame, row, col) of the rows ``rows`` only; ``valid`` marks the samples to use."""
        if valid is None:
            n_b = np.full(frames.shape[1:], frames.shape[0], dtype=np.int64)
            chunk_sum = frames.sum(axis=0)
        else:
            n_b = valid.sum(axis=0)
            frames = np.where(valid, frames, 0.0)
            chunk_sum = frames.sum(axis=0)
            self.masked[rows] += frames.shape[0] - n_b
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_b = np.where(n_b > 0, chunk_sum / np.maximum(n_b, 1), 0.0)
        dev = frames - mean_b
        if valid is not None:
            dev = np.where(valid, dev, 0.0)
        m2_b = np.einsum("tij,tij->ij", dev, dev)
        n_a = self.count[rows]
        n = n_a + n_b
        delta = mean_b - self.mean[rows]
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = np.where(n > 0, n_b / np.maximum(n, 1), 0.0)
        self.mean[rows] = self.mean[rows] + delta * frac
        self._m2[rows] = self._m2[rows] + m2_b + delta**2 * n_a * frac
        self.count[rows] = n

    @property
    def variance(self) -> np.ndarray:
        """Unbiased per-pixel variance (NaN with fewer than 2 samples)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 1, self._m2 / np.maximum(self.count - 1, 1), np.nan)

    def pop_variance(self) -> np.ndarray:
        """:attr:`variance`, formed in the accumulator's own memory (a map less at a step's peak): the
        statistics cannot be updated, nor their variance taken, after."""
        m2, self._m2 = self._m2, None
        with np.errstate(invalid="ignore", divide="ignore"):
            np.divide(m2, np.maximum(self.count - 1, 1), out=m2)
        m2[self.count <= 1] = np.nan
        return m2


def _science_only(values: np.ndarray, detector: Detector) -> np.ndarray:
    """``values`` (a float map the caller gives up) with NaN outside the science area, in place."""
    values[~detector.science_mask()] = np.nan
    return values


def _coords(detector: Detector):
    return {"row": np.arange(detector.shape[0]), "col": np.arange(detector.shape[1])}


def _valid(chunk: Chunk, rows: slice) -> np.ndarray | None:
    """The unsaturated samples of a chunk's rows ``rows`` (frame, row, col); None where none saturates."""
    return ~chunk.saturated[:, rows] if chunk.any_saturated else None


def _science_levels(chunk: Chunk, dark: np.ndarray, science: tuple[slice, slice]) -> np.ndarray:
    """Mean of each frame of a chunk less ``dark`` over the ``science`` slices (adu), its unsaturated samples
    only: a frame at a time, so that a frame's temporaries are all it holds (the same sums, bit for bit, as
    over the chunk at once)."""
    rows, cols = science
    levels = np.empty(chunk.frames.shape[0])
    for k, frame in enumerate(chunk.frames):
        signal = frame[rows, cols] - dark[rows, cols]
        if chunk.any_saturated:
            valid = ~chunk.saturated[k, rows, cols]
            levels[k] = np.where(valid, signal, 0.0).sum() / max(int(valid.sum()), 1)
        else:
            levels[k] = signal.sum() / max(signal.size, 1)
    return levels


def _progress(label, chunk: Chunk, n_frames: int | None, every: int = 10_000):
    """Log progress about every ``every`` frames of a long pass."""
    end = chunk.start + chunk.frames.shape[0]
    if n_frames and end // every != chunk.start // every:
        log.info("%s: %d / %d frames (%.0f%%)", label, end, n_frames, 100 * end / n_frames)


def dark_maps(chunks: Iterable[Chunk], detector: Detector, *, n_frames: int | None = None) -> xr.Dataset:
    """Temporal mean and temporal noise of a dark acquisition.

    Parameters
    ----------
    chunks : iterable of Chunk
        The dark frames, in ADU.
    detector : Detector
    n_frames : int, optional
        Total frames, only for progress messages.

    Returns
    -------
    xarray.Dataset
        ``dark`` (row, col): temporal mean, adu. ``noise`` (row, col): temporal
        standard deviation (unbiased), adu. ``saturated_count`` (row, col):
        saturated samples left out. Scalars ``n_frames``, ``noise_median`` (adu).
        NaN outside the science area.
    """
    stats = None
    for chunk in chunks:
        if stats is None:
            stats = TemporalStatistics(chunk.frames.shape[1:])
        for rows in row_bands(chunk.frames.shape[0], chunk.frames.shape[1:]):
            stats.update_rows(rows, chunk.frames[:, rows], _valid(chunk, rows))
        _progress("dark", chunk, n_frames)
        del chunk  # let go of its samples before the stream reads the next chunk: one chunk held, not two
    if stats is None:
        raise ValueError("no dark frames")
    n = int(stats.count.max())
    if stats.masked.any():
        log.warning("dark: %d saturated samples masked in %d pixels",
                    stats.masked.sum(), np.count_nonzero(stats.masked))
    dark = _science_only(stats.mean, detector)
    variance = stats.pop_variance()
    noise = _science_only(np.sqrt(variance, out=variance), detector)
    ds = xr.Dataset(
        {
            "dark": (("row", "col"), dark, {"units": "adu", "long_name": "temporal mean of the dark frames"}),
            "noise": (("row", "col"), noise,
                      {"units": "adu", "long_name": "temporal standard deviation of the dark frames"}),
            "saturated_count": (("row", "col"), stats.masked.astype(np.int32),
                                {"units": "1", "long_name": "saturated dark samples left out"}),
            "n_frames": ((), n, {"units": "1", "long_name": "frames in the dark acquisition"}),
            "noise_median": ((), float(np.nanmedian(noise)),
                             {"units": "adu", "long_name": "median temporal noise over the science area"}),
        },
        coords=_coords(detector),
    )
    return ds


def remove_gradient(image: np.ndarray, mask: np.ndarray, *, degree: int = 1):
    """Divide a map by its least-squares 2-D polynomial fit over ``mask``.

    Parameters
    ----------
    image : ndarray (row, col)
    mask : bool ndarray (row, col)
        Pixels used in the fit (non-finite pixels are also left out).
    degree : int, keyword-only
        0 removes only the level, 1 a plane (the paper's gradient), 2 adds curvature.

    Returns
    -------
    flattened, surface : ndarray
        ``image / surface`` and the fitted surface, both (row, col).

    Notes
    -----
    The PRNU is multiplicative, so the illumination surface is divided out
    rather than subtracted; a flat image times a polynomial of ``degree`` is
    returned exactly flat. Memory: the design of the pixels used (8 bytes a
    term and pixel) and the least-squares solver's copy of it, then that of
    every pixel for the surface, never both; the bits of a fit of the whole
    map's design.
    """
    if degree < 0:
        raise ValueError(f"degree must be >= 0, got {degree}")
    use = np.flatnonzero(mask & np.isfinite(image))
    # scaled on the whole map; the design of the pixels used only, then of every pixel for the surface
    scaling = polynomial_scaling(np.array([0, image.shape[1] - 1]), np.array([0, image.shape[0] - 1]))
    design = _design(image.shape, degree, scaling, use)
    values = image.ravel()[use]
    del use
    coef, *_ = np.linalg.lstsq(design, values, rcond=None)
    del design, values
    surface = (_design(image.shape, degree, scaling) @ coef).reshape(image.shape)
    return image / surface, surface


#: Pixels whose polynomial terms :func:`_design` forms at a time.
DESIGN_PIXELS = 1 << 16


def _design(shape, degree: int, scaling, pixels: np.ndarray | None = None) -> np.ndarray:
    """Design matrix (pixel, term) of a map of ``shape`` (rows, cols) for the pixels of C-order indices
    ``pixels`` (all if None), their columns as x and rows as y scaled by ``scaling``: the rows of the whole
    map's design, bit for bit (:func:`dice_core.polynomials.polynomial_design`), formed a block of
    :data:`DESIGN_PIXELS` at a time so that only the design itself is a full-size array."""
    n = shape[0] * shape[1] if pixels is None else pixels.size
    design = np.empty((n, polynomial_terms(degree)))
    for first in range(0, n, DESIGN_PIXELS):
        last = min(first + DESIGN_PIXELS, n)
        rows, cols = np.divmod(np.arange(first, last) if pixels is None else pixels[first:last], shape[1])
        design[first:last] = polynomial_design(cols, rows, degree=degree, scaling=scaling)
    return design


def area_rms(image: np.ndarray, detector: Detector) -> float:
    """Standard deviation of a map over the finite pixels of the science area."""
    values = image[detector.science_slices]
    return float(np.nanstd(values))


#: A pixel of a flat whose mean level is below this fraction of the science area's median does not
#: respond: it is left out of the illumination fit and the normalisation (and flagged dead later).
DEAD_BELOW = 0.5


def prnu_map(chunks: Iterable[Chunk], dark: np.ndarray, *, dark_noise: np.ndarray, detector: Detector,
             gradient_degree: int = 1, n_frames: int | None = None, label: str = "flat") -> xr.Dataset:
    """PRNU map of a flat-field acquisition, with its photon-noise limit.

    Parameters
    ----------
    chunks : iterable of Chunk
        Raw flat frames, ADU.
    dark : ndarray (row, col)
        Mean dark frame, ADU (NaN outside the science area is fine).
    dark_noise : ndarray (row, col)
        Temporal dark noise (read noise), ADU rms.
    detector : Detector
        Science area and gain (electrons per ADU).
    gradient_degree : int, keyword-only
        Degree of the illumination surface removed in step 4 (1: plane).
    n_frames : int, optional
        Total frames, only for progress messages.
    label : str, keyword-only
        Name in log messages.

    Returns
    -------
    xarray.Dataset
        ``prnu`` (row, col), mean 1 over the science area. ``photon_noise_limit``
        (row, col): its 1-sigma error expected from photon and read noise.
        ``temporal_error`` (row, col): the same error measured from the scatter
        of the normalised frames. ``mean_signal`` (row, col): dark-subtracted
        mean level, adu. ``illumination`` (row, col): the removed surface,
        relative. ``frame_level`` (frame): mean science-area level of each
        dark-subtracted frame, adu. Scalars ``n_frames``, ``prnu_rms``,
        ``photon_noise_limit_rms``, ``saturated_samples``, ``n_not_responding``.
        Pixels that do not respond (mean level below :data:`DEAD_BELOW` of the
        median: dead pixels and columns) keep their measured PRNU but are left
        out of the illumination fit, the normalisation and ``prnu_rms``, with
        a warning naming the first of them.

    Notes
    -----
    For a pixel of mean dark-subtracted signal :math:`S` (ADU), gain :math:`g`
    (e-/ADU) and read noise :math:`\\sigma_r` (ADU), one frame has variance
    :math:`S/g + \\sigma_r^2` ADU², so the relative error of its mean over
    :math:`N` frames, and of the PRNU, is

    .. math:: \\sigma_{\\rm PRNU} = \\mathrm{PRNU} \\, \\sqrt{(S/g + \\sigma_r^2)/N} \\,/\\, S .

    The per-frame normalisation (step 2) and the final normalisation are
    common to all pixels and do not change this to first order.
    """
    sl = detector.science_slices
    science = detector.science_mask()
    dark_filled = np.where(np.isfinite(dark), dark, 0.0)
    stats = raw_sum = None
    levels = []
    reference_level = None
    for chunk in chunks:
        if stats is None:
            stats = TemporalStatistics(chunk.frames.shape[1:])
            raw_sum = np.zeros(chunk.frames.shape[1:])
        # Step 2: scale each frame to the first frame's mean level over the science area.
        level = _science_levels(chunk, dark_filled, sl)
        if np.any(level <= 0):
            raise ValueError(f"{label}: frame {chunk.start + int(np.argmin(level))} has no positive signal "
                             "after dark subtraction")
        if reference_level is None:
            reference_level = level[0]
        levels.append(level)
        scale = (reference_level / level)[:, None, None]
        for rows in row_bands(chunk.frames.shape[0], chunk.frames.shape[1:]):
            frames, valid = chunk.frames[:, rows] - dark_filled[rows], _valid(chunk, rows)
            stats.update_rows(rows, frames * scale, valid)
            raw_sum[rows] += (frames if valid is None else np.where(valid, frames, 0.0)).sum(axis=0)
        _progress(label, chunk, n_frames)
        del chunk, frames, valid  # let go of its samples before the stream reads the next: one chunk held
    if stats is None:
        raise ValueError(f"{label}: no frames")

    del dark_filled  # the maps below are formed in place where they can be
    if stats.masked.any():
        log.warning("%s: %d saturated samples masked in %d pixels", label,
                    stats.masked.sum(), np.count_nonzero(stats.masked))
    # steps 3 (the temporal mean), 4 and 5
    prnu, relative_surface, responding, not_responding = _normalised_response(
        stats.mean, science & (stats.count > 0), sl, degree=gradient_degree, label=label)
    with np.errstate(invalid="ignore", divide="ignore"):
        signal = np.divide(raw_sum, stats.count, out=raw_sum)  # mean before normalisation: the photon count
        variance_expected = signal / detector.gain
        variance_expected += dark_noise**2
        limit = _relative_error(prnu, variance_expected, stats.count, signal)
        measured = _relative_error(prnu, stats.pop_variance(), stats.count, stats.mean)
    frame_level = np.concatenate(levels)
    # the scalars first: _science_only below writes NaN into the maps it is given, in place
    prnu_rms = area_rms(np.where(responding, prnu, np.nan), detector)
    limit_rms = float(np.sqrt(np.nanmean(np.where(responding, limit, np.nan)[sl] ** 2)))
    ds = xr.Dataset(
        {
            "prnu": (("row", "col"), _science_only(prnu, detector),
                     {"units": "1", "long_name": "pixel response non-uniformity (relative sensitivity)"}),
            "photon_noise_limit": (("row", "col"), _science_only(limit, detector),
                                   {"units": "1", "long_name": "1-sigma PRNU error expected from photon and read noise"}),
            "temporal_error": (("row", "col"), _science_only(measured, detector),
                               {"units": "1", "long_name": "1-sigma PRNU error from the scatter of normalised frames"}),
            "mean_signal": (("row", "col"), _science_only(signal, detector),
                            {"units": "adu", "long_name": "dark-subtracted temporal mean signal"}),
            "illumination": (("row", "col"), _science_only(relative_surface, detector),
                             {"units": "1", "long_name": f"removed illumination surface (degree {gradient_degree})"}),
            "frame_level": (("frame",), frame_level,
                            {"units": "adu", "long_name": "mean science-area level of each dark-subtracted frame"}),
            "n_frames": ((), int(frame_level.size), {"units": "1", "long_name": "frames in the flat acquisition"}),
            "prnu_rms": ((), prnu_rms,
                         {"units": "1", "long_name": "PRNU rms over the responding pixels of the science area"}),
            "n_not_responding": ((), int(not_responding.sum()),
                                 {"units": "1", "long_name": f"science pixels below {DEAD_BELOW:g} of the median "
                                                             "level, left out of the normalisation"}),
            "photon_noise_limit_rms": ((), limit_rms,
                                       {"units": "1", "long_name": "rms photon-noise limit over the responding "
                                                                   "pixels of the science area"}),
            "saturated_samples": ((), int(stats.masked.sum()), {"units": "1", "long_name": "saturated samples left out"}),
        },
        coords={**_coords(detector), "frame": np.arange(frame_level.size)},
    )
    ds.attrs["gradient_degree"] = gradient_degree
    ds.attrs["normalisation"] = (f"mean 1 over the responding pixels of the science area (those above "
                                 f"{DEAD_BELOW:g} of the median level once the illumination is divided out)")
    return ds


def _normalised_response(mean: np.ndarray, measured: np.ndarray, sl, *, degree: int, label: str):
    """Steps 4 and 5 of :func:`prnu_map` on the temporal ``mean`` (row, col, adu) of the ``measured`` pixels:
    (PRNU, the removed surface relative to its science-area mean, the responding pixels, the measured ones that
    do not respond).

    A dead pixel or column would pull both the surface and the normalisation (a dead column of 78 pixels
    shifts the mean by 1.4e-2 on 80x84), so the pixels below :data:`DEAD_BELOW` of the light, judged once the
    illumination of a first fit is divided out (vignetting must not make a dim, healthy pixel dead), are
    left out of both.
    """
    image = np.where(measured, mean, np.nan)
    first, _ = remove_gradient(image, measured, degree=degree)
    with np.errstate(invalid="ignore"):
        responding = measured & (first > DEAD_BELOW * np.nanmedian(np.where(measured, first, np.nan)))
    del first
    not_responding = measured & ~responding
    if not_responding.any():
        rows, cols = np.nonzero(not_responding)
        shown = ", ".join(f"(row {r}, col {c})" for r, c in list(zip(rows, cols))[:5])
        log.warning("%s: %d pixel(s) respond to less than %.0f%% of the median level, left out of the "
                    "illumination fit and the normalisation: %s%s", label, rows.size, 100 * DEAD_BELOW, shown,
                    ", ..." if rows.size > 5 else "")
    prnu, surface = remove_gradient(image, responding, degree=degree)
    del image
    prnu /= np.nanmean(np.where(responding, prnu, np.nan)[sl])
    surface /= np.nanmean(surface[sl])
    return prnu, surface, responding, not_responding


def _relative_error(prnu: np.ndarray, variance: np.ndarray, count: np.ndarray, level: np.ndarray) -> np.ndarray:
    """``prnu * sqrt(variance / count) / level``, the PRNU's 1-sigma error from a sample ``variance`` (adu²)
    of ``count`` samples about the mean ``level`` (adu), formed in ``variance``'s memory."""
    np.divide(variance, count, out=variance)
    np.sqrt(variance, out=variance)
    np.multiply(prnu, variance, out=variance)
    return np.divide(variance, level, out=variance)


def prnu_difference(reference: xr.Dataset, other: xr.Dataset, *, detector: Detector) -> xr.Dataset:
    """Difference of two PRNU maps with its photon-noise limit.

    Parameters
    ----------
    reference, other : xarray.Dataset
        Outputs of :func:`prnu_map`.

    Returns
    -------
    xarray.Dataset
        ``difference`` = other - reference (row, col), ``photon_noise_limit``
        (row, col) = the two limits added in quadrature, scalars
        ``difference_rms`` and ``photon_noise_limit_rms`` over the science area.
    """
    diff = other["prnu"].values - reference["prnu"].values
    limit = np.hypot(other["photon_noise_limit"].values, reference["photon_noise_limit"].values)
    sl = detector.science_slices
    return xr.Dataset(
        {
            "difference": (("row", "col"), diff, {"units": "1", "long_name": "PRNU difference (other - reference)"}),
            "photon_noise_limit": (("row", "col"), limit,
                                   {"units": "1", "long_name": "1-sigma photon-noise limit of the difference"}),
            "difference_rms": ((), area_rms(diff, detector),
                               {"units": "1", "long_name": "rms of the difference over the science area"}),
            "photon_noise_limit_rms": ((), float(np.sqrt(np.nanmean(limit[sl] ** 2))),
                                       {"units": "1", "long_name": "rms photon-noise limit of the difference"}),
        },
        coords=_coords(detector),
    )


#: Bits of the bad-pixel mask: what each flag means (a pixel may carry several).
BAD_PIXEL_FLAGS = {"dead": 1, "hot": 2, "dust": 4, "column": 8}

#: The flags that make a pixel unusable, which the metrology and the star windows leave out. A dust
#: pixel only loses a few percent of its light, which the flat measures and corrects: it is flagged,
#: for the record, and used.
UNUSABLE = BAD_PIXEL_FLAGS["dead"] | BAD_PIXEL_FLAGS["hot"] | BAD_PIXEL_FLAGS["column"]


def unusable_pixels(flags) -> np.ndarray:
    """Bool map of the pixels a mask's flags (``bad_pixel``, row x col) make unusable (:data:`UNUSABLE`)."""
    return (np.asarray(flags).astype(np.int64) & UNUSABLE) != 0


def _local_median(image, size=5):
    """Median of the valid (finite) pixels of each pixel's size x size neighbourhood (NaN: left out; NaN where
    none is valid, as for windows wholly outside the science area).

    Vectorised over bands of rows (:func:`row_bands`, a window's ``size``**2 samples a pixel), the same numbers
    as ``scipy.ndimage.generic_filter(image, np.nanmedian, size, mode="constant", cval=nan)`` (tested), which
    calls Python once a pixel: 25 minutes for the two maps of a 4096x4096 detector (library,
    ``benchmarks/calibration_memory.py --bad-pixels``, not the workflow's run).
    """
    import warnings

    from numpy.lib.stride_tricks import sliding_window_view

    half = size // 2
    windows = sliding_window_view(np.pad(np.asarray(image, float), half, constant_values=np.nan), (size, size))
    out = np.empty(np.shape(image))
    with warnings.catch_warnings():  # an all-NaN window: NaN, as wanted
        warnings.simplefilter("ignore", RuntimeWarning)
        for band in row_bands(size * size, out.shape):
            block = windows[band]
            out[band] = np.nanmedian(block.reshape(block.shape[:2] + (size * size,)), axis=-1)
    return out


def bad_pixel_mask(dark: xr.Dataset, prnu: np.ndarray, *, detector: Detector, dead_below: float = 0.5,
                   dust_below: float = 0.99, hot_sigma: float = 10.0, column_fraction: float = 0.5) -> xr.Dataset:
    """Dead, hot, dust and column defects of the science area, from the dark and a PRNU map.

    Parameters
    ----------
    dark : xarray.Dataset
        ``calibration/dark.nc``: mean dark ``dark`` and temporal noise ``noise``, adu.
    prnu : ndarray (row, col)
        A PRNU map (mean 1 over the responding pixels of the science area), e.g. the reference flat's.
    detector : Detector
    dead_below : float
        A pixel whose PRNU is below this responds to less than this fraction of
        the light: dead.
    dust_below : float
        One responding to less than this fraction of its 5x5 neighbourhood's
        median (but more than ``dead_below``): dust (a 1% loss is 5 sigma of a
        2e-3 PRNU).
    hot_sigma : float
        A pixel whose dark stands above its 5x5 neighbourhood's median, or whose
        noise above the median noise, by more than this many robust standard
        deviations (1.4826 MAD) of the whole area: hot.
    column_fraction : float
        A column with more than this fraction of its science pixels dead or
        hot is flagged whole: a column defect.

    Returns
    -------
    xarray.Dataset
        ``bad_pixel`` (row, col), int8 bits of :data:`BAD_PIXEL_FLAGS` (0 good;
        with CF ``flag_masks`` and ``flag_meanings``); ``n_<kind>`` counts; and
        ``bad_columns``, the flagged columns.
    """
    mask = detector.science_mask()
    flags = np.zeros(detector.shape, np.int8)
    with np.errstate(invalid="ignore"):
        dead = mask & (prnu < dead_below)
        flags[dead] |= BAD_PIXEL_FLAGS["dead"]
        # dust against the pixel's neighbourhood of responding pixels: the map's own normalisation and
        # gradient took the dead pixels in, and are off by their share
        responding = np.where(mask & ~dead, prnu, np.nan)
        flags[mask & ~dead & (responding / _local_median(responding) < dust_below)] |= BAD_PIXEL_FLAGS["dust"]

    def robust_outliers(values):
        inside = values[mask]
        spread = 1.4826 * np.median(np.abs(inside - np.median(inside)))
        return mask & (values - np.median(inside) > hot_sigma * max(spread, 1e-12))

    dark_map, noise = np.where(mask, dark["dark"].values, np.nan), np.where(mask, dark["noise"].values, np.nan)
    # (a hot pixel's neighbourhood median is its neighbours': the bias has column structure, not pixel)
    hot = robust_outliers(np.nan_to_num(dark_map - _local_median(dark_map))) | robust_outliers(np.nan_to_num(noise))
    flags[hot] |= BAD_PIXEL_FLAGS["hot"]
    rows = slice(*detector.science_rows)
    dead_or_hot = (flags & (BAD_PIXEL_FLAGS["dead"] | BAD_PIXEL_FLAGS["hot"])) > 0
    columns = [c for c in range(*detector.science_cols) if dead_or_hot[rows, c].mean() > column_fraction]
    for c in columns:
        flags[rows, c] |= BAD_PIXEL_FLAGS["column"]
    counts = {kind: int(((flags & bit) > 0).sum()) for kind, bit in BAD_PIXEL_FLAGS.items()}
    for kind, n in counts.items():
        if n:
            log.warning("%d pixel(s) flagged %s", n, kind)
    return xr.Dataset(
        {
            "bad_pixel": (("row", "col"), flags,
                          {"units": "1", "long_name": "bad-pixel flags (0: good)",
                           "flag_masks": np.array(list(BAD_PIXEL_FLAGS.values()), np.int8),
                           "flag_meanings": " ".join(BAD_PIXEL_FLAGS)}),
            **{f"n_{kind}": ((), n, {"units": "1", "long_name": f"pixels flagged {kind}"})
               for kind, n in counts.items()},
            "bad_columns": (("bad_column",), np.array(columns, dtype=np.int64),
                            {"units": "1", "long_name": "columns flagged whole"}),
        },
        coords=_coords(detector),
    )


def fringe_fit_calibrations(prnu_paths, bad_pixel_paths, *, label: str):
    """(flat, bad pixel flags) a fringe fit uses, from the products the workflow gives it (each list empty
    or one path): the PRNU map (row, col; None without) and the bad-pixel flags (row, col; None without),
    of which the fit leaves the unusable ones out (logged with ``label``)."""
    from dice_core.io import read_product

    flat = read_product(prnu_paths[0])["prnu"].values if prnu_paths else None
    bad_pixels = None
    if bad_pixel_paths:  # dead, hot and column defects out; dust pixels kept (the flat measures them)
        bad_pixels = read_product(bad_pixel_paths[0])["bad_pixel"].values
        log.info("%s: %d unusable pixel(s) of the bad-pixel mask left out", label, unusable_pixels(bad_pixels).sum())
    return flat, bad_pixels
