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
from dice_core.polynomials import polynomial_design
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


class TemporalStatistics:
    """Per-pixel mean and variance over frames, accumulated chunk by chunk.

    Uses the pairwise update of Chan, Golub & LeVeque (1979) in float64, so
    the result does not depend on chunking beyond rounding, and memory is a few
    maps whatever the number of frames. Masked samples (``valid`` False) are
    left out and counted.
    """

    def __init__(self, shape):
        self.count = np.zeros(shape, dtype=np.int64)
        self.mean = np.zeros(shape)
        self._m2 = np.zeros(shape)
        self.masked = np.zeros(shape, dtype=np.int64)

    def update(self, frames: np.ndarray, valid: np.ndarray | None = None):
        """Add frames (frame, row, col); ``valid`` marks the samples to use."""
        if valid is None:
            n_b = np.full(frames.shape[1:], frames.shape[0], dtype=np.int64)
            chunk_sum = frames.sum(axis=0)
        else:
            n_b = valid.sum(axis=0)
            frames = np.where(valid, frames, 0.0)
            chunk_sum = frames.sum(axis=0)
            self.masked += frames.shape[0] - n_b
        with np.errstate(invalid="ignore", divide="ignore"):
            mean_b = np.where(n_b > 0, chunk_sum / np.maximum(n_b, 1), 0.0)
        dev = frames - mean_b
        if valid is not None:
            dev = np.where(valid, dev, 0.0)
        m2_b = np.einsum("tij,tij->ij", dev, dev)
        n_a = self.count
        n = n_a + n_b
        delta = mean_b - self.mean
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = np.where(n > 0, n_b / np.maximum(n, 1), 0.0)
        self.mean = self.mean + delta * frac
        self._m2 = self._m2 + m2_b + delta**2 * n_a * frac
        self.count = n

    @property
    def variance(self) -> np.ndarray:
        """Unbiased per-pixel variance (NaN with fewer than 2 samples)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 1, self._m2 / np.maximum(self.count - 1, 1), np.nan)


def _science_only(values: np.ndarray, detector: Detector) -> np.ndarray:
    out = np.full(detector.shape, np.nan)
    sl = detector.science_slices
    out[sl] = values[sl]
    return out


def _coords(detector: Detector):
    return {"row": np.arange(detector.shape[0]), "col": np.arange(detector.shape[1])}


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
        stats.update(chunk.frames, ~chunk.saturated)
        _progress("dark", chunk, n_frames)
    if stats is None:
        raise ValueError("no dark frames")
    n = int(stats.count.max())
    if stats.masked.any():
        log.warning("dark: %d saturated samples masked in %d pixels",
                    stats.masked.sum(), np.count_nonzero(stats.masked))
    dark = _science_only(stats.mean, detector)
    noise = _science_only(np.sqrt(stats.variance), detector)
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
    returned exactly flat.
    """
    if degree < 0:
        raise ValueError(f"degree must be >= 0, got {degree}")
    use = mask & np.isfinite(image)
    rows, cols = np.indices(image.shape)
    design = polynomial_design(cols.ravel(), rows.ravel(), degree=degree)  # scaled on the whole map
    coef, *_ = np.linalg.lstsq(design[use.ravel()], image[use], rcond=None)
    surface = (design @ coef).reshape(image.shape)
    return image / surface, surface


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
        frames = chunk.frames - dark_filled
        valid = ~chunk.saturated
        if stats is None:
            stats = TemporalStatistics(frames.shape[1:])
            raw_sum = np.zeros(frames.shape[1:])
        # Step 2: scale each frame to the first frame's mean level over the science area.
        v = valid[:, sl[0], sl[1]]
        f = frames[:, sl[0], sl[1]]
        level = np.where(v, f, 0.0).sum(axis=(1, 2)) / np.maximum(v.sum(axis=(1, 2)), 1)
        if np.any(level <= 0):
            raise ValueError(f"{label}: frame {chunk.start + int(np.argmin(level))} has no positive signal "
                             "after dark subtraction")
        if reference_level is None:
            reference_level = level[0]
        levels.append(level)
        stats.update(frames * (reference_level / level)[:, None, None], valid)
        raw_sum += np.where(valid, frames, 0.0).sum(axis=0)
        _progress(label, chunk, n_frames)
    if stats is None:
        raise ValueError(f"{label}: no frames")

    mean = stats.mean  # step 3
    if stats.masked.any():
        log.warning("%s: %d saturated samples masked in %d pixels", label,
                    stats.masked.sum(), np.count_nonzero(stats.masked))
    # Step 4: divide out the smooth illumination; step 5: mean 1 over the science area. A dead pixel
    # or column would pull both (a dead column of 78 pixels shifts the mean by 1.4e-2 on 80x84), so
    # the pixels below half the light, judged once the illumination of a first fit is divided out
    # (vignetting must not make a dim, healthy pixel dead), are left out of both.
    measured = science & (stats.count > 0)
    first, _ = remove_gradient(np.where(measured, mean, np.nan), measured, degree=gradient_degree)
    with np.errstate(invalid="ignore"):
        responding = measured & (first > DEAD_BELOW * np.nanmedian(np.where(measured, first, np.nan)))
    not_responding = measured & ~responding
    if not_responding.any():
        rows, cols = np.nonzero(not_responding)
        shown = ", ".join(f"(row {r}, col {c})" for r, c in list(zip(rows, cols))[:5])
        log.warning("%s: %d pixel(s) respond to less than %.0f%% of the median level, left out of the "
                    "illumination fit and the normalisation: %s%s", label, rows.size, 100 * DEAD_BELOW, shown,
                    ", ..." if rows.size > 5 else "")
    fit_mask = responding
    flattened, surface = remove_gradient(np.where(measured, mean, np.nan), fit_mask, degree=gradient_degree)
    prnu = flattened / np.nanmean(np.where(fit_mask, flattened, np.nan)[sl])

    with np.errstate(invalid="ignore", divide="ignore"):
        signal = raw_sum / stats.count  # mean before normalisation: the photon count
        variance_expected = signal / detector.gain + dark_noise**2
        limit = prnu * np.sqrt(variance_expected / stats.count) / signal
        measured = prnu * np.sqrt(stats.variance / stats.count) / mean
    frame_level = np.concatenate(levels)
    relative_surface = surface / np.nanmean(surface[sl])
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
            "prnu_rms": ((), area_rms(np.where(responding, prnu, np.nan), detector),
                         {"units": "1", "long_name": "PRNU rms over the responding pixels of the science area"}),
            "n_not_responding": ((), int(not_responding.sum()),
                                 {"units": "1", "long_name": f"science pixels below {DEAD_BELOW:g} of the median "
                                                             "level, left out of the normalisation"}),
            "photon_noise_limit_rms": ((), float(np.sqrt(np.nanmean(np.where(responding, limit, np.nan)[sl] ** 2))),
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
    """Median of the valid (finite) pixels of each pixel's size x size neighbourhood (NaN: left out)."""
    import warnings

    from scipy.ndimage import generic_filter

    with warnings.catch_warnings():  # windows wholly outside the science area: NaN, as wanted
        warnings.simplefilter("ignore", RuntimeWarning)
        return generic_filter(image, np.nanmedian, size=size, mode="constant", cval=np.nan)


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
