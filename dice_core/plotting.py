"""Figures of the paper, from arrays: maps of the science area with colour bars in physical units.

Functions return a :class:`matplotlib.figure.Figure` and never read products;
:func:`save` writes it as PNG and PDF. The Agg backend is used, so no display
is needed.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.container  # noqa: E402
import matplotlib.legend_handler  # noqa: E402
import matplotlib.ticker  # noqa: E402
import matplotlib.transforms  # noqa: E402
import numpy as np  # noqa: E402

from dice_core import error_budget  # noqa: E402
from dice_core.allan import MIN_GROUPS_PIXEL, few_batches  # noqa: E402
from dice_core.manifest import Detector  # noqa: E402

__all__ = ["map_figure", "maps_figure", "metrology_figure", "allan_figure", "centroids_figure", "procrustes_figure",
           "chromatic_figure", "chromatic_study_figure", "PAPER_CALIBRATION_GAIN",
           "barycentre_figure", "offset_bias_figure", "paper_comparison_figure", "error_propagation_figure",
           "star_accuracy_figure", "tip_tilt_sweep_figure", "reduction_sweep_figure", "parameter_axis",
           "PARAMETER_AXES", "reproduction_pdf", "save", "stray_light_figure", "stray_light_study_figure"]


def map_figure(image: np.ndarray, detector: Detector, *, title: str, units: str, scale: float = 1.0,
               symmetric: bool = False, clip_percentile: float = 0.5, note: str | None = None,
               cmap: str | None = None):
    """Map of a (row, col) image over the science area.

    Parameters
    ----------
    image : ndarray (row, col)
    detector : Detector
        Gives the science area shown.
    title : str
    units : str
        Colour-bar label, e.g. ``"adu"`` or ``"1e-3"``; when ``scale`` is not
        1 the values are multiplied by ``scale`` before display, so say so in
        ``units`` (``scale=1e3, units="1e-3"``).
    symmetric : bool
        Colour scale symmetric about 0 with a diverging map (for differences).
    clip_percentile : float
        Colour limits at this percentile and its complement, so that a few dust
        or hot pixels do not flatten the rest.
    note : str, optional
        A line of statistics printed under the title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    import textwrap

    fig, ax = plt.subplots(figsize=(6.0, 5.2), constrained_layout=True)
    if note is not None:  # lines that fit the axes' width: a longer title is cut at the figure's edges
        title = f"{title}\n" + textwrap.fill(note, 70)
    _show_map(ax, fig, image, detector, title=title, units=units,
              scale=scale, symmetric=symmetric, clip_percentile=clip_percentile, cmap=cmap)
    return fig


def _show_map(ax, fig, image, detector, *, title, units, scale, symmetric, clip_percentile=0.5, cmap=None):
    """Draw a (row, col) map of the science area on ``ax``, with a colour bar in ``units``."""
    rows, cols = detector.science_rows, detector.science_cols
    shown = image[slice(*rows), slice(*cols)] * scale
    finite = shown[np.isfinite(shown)]
    lo, hi = np.percentile(finite, [clip_percentile, 100 - clip_percentile]) if finite.size else (0.0, 1.0)
    if symmetric:
        hi = max(abs(lo), abs(hi))
        lo = -hi
    extent = (cols[0] - 0.5, cols[1] - 0.5, rows[0] - 0.5, rows[1] - 0.5)
    # extent in pixel-centre coordinates: x = col, y = row, origin at the bottom like the paper's maps
    im = ax.imshow(shown, origin="lower", extent=extent, vmin=lo, vmax=hi, interpolation="nearest",
                   cmap=cmap or ("RdBu_r" if symmetric else "viridis"))
    ax.set_xlabel("column x [pixel]\n" + _science_note(detector.shape, rows, cols), fontsize=9)
    ax.set_ylabel("row y [pixel]")
    ax.set_title(title, fontsize=9)
    # colours clipped to the percentiles (a few dust or hot pixels would flatten the rest): the bar's arrows
    # and its label say so
    below, above = bool(finite.size and finite.min() < lo), bool(finite.size and finite.max() > hi)
    extend = {(True, True): "both", (True, False): "min", (False, True): "max"}.get((below, above), "neither")
    label = units if extend == "neither" else f"{units}; colours clipped (arrows)"
    fig.colorbar(im, ax=ax, shrink=0.85, extend=extend).set_label(label)


def _science_note(shape, rows, cols):
    """The line under a map saying that it shows the science area alone, and where that lies on the detector:
    ``rows``, ``cols`` are (first, end) as the manifest gives them, ``shape`` (rows, cols)."""
    return (f"science area only: rows {rows[0]}-{rows[1] - 1}, cols {cols[0]}-{cols[1] - 1} (inclusive) of "
            f"{shape[0]}x{shape[1]}")


def maps_figure(images, detector, *, titles, units, scale=1.0, suptitle=None):
    """Maps side by side (e.g. dx and dy), each with its colour bar; symmetric diverging colours."""
    fig, axes = plt.subplots(1, len(images), figsize=(5.6 * len(images), 4.8), constrained_layout=True)
    for ax, image, title in zip(np.atleast_1d(axes), images, titles):
        _show_map(ax, fig, image, detector, title=title, units=units, scale=scale, symmetric=True)
    if suptitle:
        fig.suptitle(suptitle, fontsize=11)
    return fig


def metrology_figure(ds, detector, *, title):
    """Summary of one baseline's fringe solution (a ``metrology/<baseline>.nc`` dataset).

    Panels: projected offsets (1e-3 pixel); per-frame wavevector minus its
    mean (rad/pixel), kx shifted up and ky down so that neither hides the
    other; B(t) and A(t) (adu); convergence (offset change per pass) against
    the offsets' photon floor, the last change over that floor in the title.
    With a flat, a row for the gauge diagnostic: the flat gauge's offsets
    minus the PRNU-free gauge's (1e-3 pixel; a first harmonic of the fringe
    phase, hence its stripes), and the rms of that difference against its
    noise floor and the offsets' photon floor, the title answering whether
    the gauges agree (:func:`_gauge_answer`). With spherical
    waves, a row with what a plane-wave fit would have put into the offsets
    (1e-3 pixel), and each tip coordinate's refinement from its nominal value
    with its 1-sigma error (mm).
    """
    spherical = "fiber_position" in ds
    gauges = "projected_offset_prnu_free_gauge" in ds
    n_rows = 2 + gauges + spherical
    fig, axes = plt.subplots(n_rows, 2, figsize=(11, 4.2 * n_rows + 0.1), constrained_layout=True)
    offsets = ds["projected_offset"].values
    _show_map(axes[0, 0], fig, offsets, detector, scale=1e3, symmetric=True, units="offset [1e-3 pixel]",
              title=f"projected offsets: rms {np.nanstd(offsets):.2e} pixel, photon floor "
                    f"{float(ds['photon_noise_floor_rms']):.1e} pixel")
    frame = ds["frame"].values
    ax = axes[0, 1]
    spread = max(np.nanmax(np.abs(ds[name].values - ds[name].values.mean())) for name in ("kx_frame", "ky_frame"))
    exponent = int(np.floor(np.log10(spread))) if np.isfinite(spread) and spread > 0 else 0
    shift = float(np.ceil(1.05 * spread / 10.0**exponent))  # kx above, ky below: drawn apart, not one on the other
    for name, colour, sign in (("kx_frame", "C0", 1), ("ky_frame", "C1", -1)):
        values = ds[name].values
        ax.plot(frame, (values - values.mean()) / 10.0**exponent + sign * shift, lw=0.4, color=colour,
                label=f"{name[:2]}: mean {values.mean():.6f} rad/pixel, rms {values.std():.1e} rad/pixel\n"
                      f"(drawn shifted by {'+' if sign > 0 else '-'}{shift:g}e{exponent} rad/pixel, its zero dashed)")
        ax.axhline(sign * shift, color=colour, lw=0.6, ls="--")
    ax.set_xlabel("frame")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(nbins=5, integer=True))  # 200000 frames: labels apart
    ax.set_ylabel(f"K(t) - mean [1e{exponent} rad/pixel]" if exponent else "K(t) - mean [rad/pixel]")
    ax.set_title("wavevector fitted per frame (pass 1)", fontsize=9)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14))  # under the axes: the curves fill them
    ax = axes[1, 0]
    ax.plot(frame, ds["level"].values, lw=0.4, label="B(t), mean level")
    ax.plot(frame, ds["amplitude"].values, lw=0.4, label="A(t), amplitude")
    ax.set_xlabel("frame")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(nbins=5, integer=True))
    ax.set_ylabel("adu")
    ax.set_title("fringe level and amplitude", fontsize=9)
    ax.legend(fontsize=8, loc="center right")  # between B and A; "best" searches 200,000 frames' points slowly
    ax = axes[1, 1]
    iteration = ds["iteration"].values
    floor = float(ds["photon_noise_floor_rms"])
    ax.semilogy(iteration, ds["max_change"].values, "o-", label="largest change")
    ax.semilogy(iteration, ds["rms_change"].values, "s-", label="rms change")
    # what a change is measured against: the photon floor of the offsets, drawn across the passes
    ax.semilogy([iteration.min() - 0.5, iteration.max() + 0.5], [floor] * 2, color="0.4", ls="--",
                label="the offsets' photon floor (rms)")
    last = float(ds["max_change"].values[-1])
    for name in ("max_change", "rms_change"):
        value = float(ds[name].values[-1])
        ax.annotate(f"{value:.1e} pixel", (iteration[-1], value), textcoords="offset points", xytext=(8, 0),
                    va="center", fontsize=8)
    changes = np.concatenate([ds["max_change"].values, ds["rms_change"].values, [floor]])
    changes = changes[np.isfinite(changes) & (changes > 0)]
    if changes.size:  # whole decades, each labelled: every point between two labelled ticks
        ax.set_ylim(10.0 ** np.floor(np.log10(changes.min() * 0.999)), 10.0 ** np.ceil(np.log10(changes.max() * 1.001)))
        ax.yaxis.set_major_locator(matplotlib.ticker.LogLocator(numticks=99))
    ax.set_xlabel("pass")
    _integer_ticks(ax.xaxis)
    ax.set_xlim(iteration.min() - 0.5, iteration.max() + 0.5)
    ax.set_ylabel("offset change from previous pass [pixel]")
    ax.set_title(f"convergence: {iteration.max()} passes; the last moved the offsets\nby at most "
                 f"{last / floor:.1e} x their photon floor", fontsize=9)
    ax.legend(fontsize=8)  # "best": a few points, quickly placed off them
    row = 2
    if gauges:
        difference = offsets - ds["projected_offset_prnu_free_gauge"].values
        _show_map(axes[row, 0], fig, difference, detector, scale=1e3, symmetric=True, units="offset [1e-3 pixel]",
                  title="flat gauge minus PRNU-free gauge: stripes along the fringes,\nas a gauge's error is a "
                        "first harmonic of the fringe phase K.r (a boost)")
        ax = axes[row, 1]
        bars = {"gauge\ndifference": float(ds["gauge_difference_rms"])}  # two lines: labels apart
        if "gauge_difference_floor" in ds:
            bars["its noise\nfloor"] = float(ds["gauge_difference_floor"])
        bars["offsets'\nphoton floor"] = float(ds["photon_noise_floor_rms"])
        for i, ((name, value), colour) in enumerate(zip(bars.items(), ("C3", "C0", "0.5"))):
            ax.semilogy([i], [value], "o", ms=9, color=colour)
            ax.annotate(f"{value:.1e} pixel", (i, value), textcoords="offset points", xytext=(10, 0), va="center",
                        fontsize=8)
        ax.set_xticks(range(len(bars)), list(bars))
        ax.set_xlim(-0.5, len(bars) - 0.1)  # room for the last point's label
        ax.set_ylabel("rms [pixel]")
        ax.set_title(_gauge_answer(ds), fontsize=9)
        ax.set_ylim(min(bars.values()) / 2, max(bars.values()) * 3)  # room for the points' labels
        row += 1
    if spherical:
        departure = ds["plane_wave_departure"].values
        _show_map(axes[row, 0], fig, departure, detector, scale=1e3, symmetric=True, units="offset [1e-3 pixel]",
                  title=f"spherical minus plane wave: rms {np.nanstd(departure):.2e} pixel "
                        f"({ds.sizes.get('mode', 0)} mode(s) declared unobservable)")
        ax = axes[row, 1]
        shift = (ds["fiber_position"] - ds["fiber_position_nominal"]).values * 1e3
        error = ds["fiber_position_error"].values * 1e3
        labels = [f"{fiber} {axis}" for fiber in ds["fiber"].values for axis in ds["xyz"].values]
        ax.errorbar(np.arange(shift.size), shift.ravel(), yerr=error.ravel(), fmt="o", capsize=3)
        ax.axhline(0, color="0.5", lw=0.8)
        ax.set_xticks(np.arange(shift.size), labels, rotation=45, fontsize=8)
        ax.set_ylabel("refined - nominal [mm]")
        ax.set_title("fiber tips refined from the phases (1-sigma errors)", fontsize=9)
    fig.suptitle(title, fontsize=11)
    return fig


#: Curves closer than this ratio at every point are drawn once, their legend entries merged: on a log axis
#: spanning several decades 3% is under a line's width, so the later curve would hide under the earlier.
COINCIDENT = 1.03


def _coincides(a, b, tolerance=COINCIDENT):
    """Whether two positive curves agree within the ratio ``tolerance`` wherever both are finite."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return False
    both = np.isfinite(a) & np.isfinite(b) & (a > 0) & (b > 0)
    return bool(both.any() and np.all(np.abs(np.log(a[both] / b[both])) < np.log(tolerance)))


def _also_names(line, label):
    """Add ``label`` to the legend entry of ``line``, a curve it coincides with (:func:`_coincides`)."""
    line.set_label(f"{line.get_label()}\n   = {label} (within {100 * (COINCIDENT - 1):.0f}%)")


def _plot_distinct(ax, x, curves):
    """Draw ``curves`` ((y, label, keywords) in order of priority) on log-log ``ax``, each curve that coincides
    with one drawn before it (:func:`_coincides`) not drawn but named in that one's legend entry."""
    drawn = []
    for y, label, keywords in curves:
        same = next((line for line in drawn if _coincides(line.get_ydata(), y)), None)
        if same is None:
            drawn.append(ax.loglog(x, y, label=label, **keywords)[0])
        else:
            _also_names(same, label)
    return drawn


#: Chance below which pure noise is said not to make a gauge difference that large (the metrology figure).
GAUGE_CHANCE = 0.05


def _gauge_answer(ds) -> str:
    """The gauge panel's title: whether the two gauges agree, as the difference over its noise floor and the
    chance that noise alone gives that much. The difference is a boost, two numbers, so its ratio r to the
    floor scatters like sqrt(F(2, 2)), whose tail is P(ratio > r) = 1 / (1 + r^2) (docs/metrology.md)."""
    if "gauge_difference_floor" not in ds:
        return "do the two gauges agree? (no noise floor: the frames are one file)"
    ratio = float(ds["gauge_difference_rms"]) / float(ds["gauge_difference_floor"])
    chance = 1.0 / (1.0 + ratio**2)
    verdict = "yes, within noise" if chance >= GAUGE_CHANCE else "no, beyond noise"
    return (f"do the two gauges agree? {verdict}: the difference is\n{ratio:.2g} x its noise floor, "
            f"which noise alone exceeds {_how_often(chance)}")


def _how_often(chance) -> str:
    """A probability in words a reader compares at a glance: '30% of the time', or '1 time in 21' below 10%."""
    return f"{100 * chance:.0f}% of the time" if chance >= 0.1 else f"1 time in {1 / chance:.0f}"


def allan_figure(ds, *, title):
    """The paper's Allan figure from an ``allan/<baseline>.nc`` dataset, log-log against frames per group.

    Sample pixels (thin green) where their deviation is over at least
    ``MIN_GROUPS_PIXEL`` groups, their rms (black) and the rms of 10x10-pixel
    blocks (blue), each group fitted as a whole, with 1-sigma error bars from
    the number of groups K and of pixels (blocks) M averaged, the rms of M
    independent deviations over K groups, 1 / sqrt(2 (K - 1) M) relative; the pixels' rms with
    groups as means of their batch fits, the paper's way (grey, with its
    limit); white noise of matched single-batch scatter (dotted); the
    photon-noise limits from the fits' own errors (dashed: the batches' and
    groups' own floors) and the paper's formula (dash-dotted); where the
    product holds ``photon_limit_pixel_global``, the global solution's floor
    scaled to each group (thin grey line); and, where it holds
    ``photon_limit_pixel_first_frame``, the paper's red line: the pixels'
    limit from the noise measured on the first frame
    (:func:`dice_core.allan.first_frame_limit`). Curves that coincide within
    3% are drawn once with one legend entry naming them all, the drawn curve's
    name first, beside its key (:func:`_first_line_keys`).
    """
    fig, ax = plt.subplots(figsize=(8, 7.5), layout="constrained")
    n = ds["n_frames"].values
    groups = ds["n_groups"].values if "n_groups" in ds else np.full(n.shape, np.inf)
    few = groups < MIN_GROUPS_PIXEL
    samples = np.where(few[:, None], np.nan, ds["sample_deviation"].values)
    pixel_lines = ax.loglog(n, samples, color="tab:green", lw=0.5, alpha=0.5,  # one size: a point, no line
                            marker="." if (~few).sum() < 2 else None, ms=3)
    if pixel_lines:  # one entry for all: the first pixel's curve stands for them
        pixel_lines[0].set_label(f"{ds.sizes['sample']} individual pixels (where {MIN_GROUPS_PIXEL} groups or more)")
    if few.any() and not few.all():  # where one pixel's curve is noise: said on the figure, not left to guess
        ax.axvspan(np.sqrt(n[~few].max() * n[few].min()), n.max() * 1.05, color="0.5", alpha=0.1, lw=0,
                   label=f"fewer than {MIN_GROUPS_PIXEL} groups: single pixels not drawn")
    block = int(ds.attrs.get("block_size", 10))
    pixels = int(np.isfinite(ds["deviation"].values[0]).sum()) if "deviation" in ds else 0
    counts = {"pixel": pixels, "block": pixels // block**2}
    curves = []
    if "photon_limit_pixel_first_frame" in ds:  # first: the limits it nearly equals merge into its red entry
        noise = f", {float(ds['first_frame_noise']):.3g} adu rms" if "first_frame_noise" in ds else ""
        curves.append((ds["photon_limit_pixel_first_frame"].values,
                       f"measured photon limit (first frame{noise}), pixels", dict(color="red", lw=1.2, gid="first frame")))
    measured = []
    for kind, colour, label in (("pixel", "black", f"pixels, rms ({_slope_text(ds['slope'])})"),
                                ("block", "tab:blue", f"{block}x{block} blocks, rms")):
        values = ds["deviation_mean" if kind == "pixel" else "deviation_block_mean"].values
        error = values / np.sqrt(2 * np.maximum(groups - 1, 1) * max(counts[kind], 1))
        # markers and a thin line: a limit it meets, drawn over it, stays visible
        measured.append(ax.errorbar(n, values, yerr=error if counts[kind] else None, fmt="o-", ms=4, color=colour,
                                    lw=1.2, capsize=2, zorder=2,
                                    label=label + (f", 1-sigma from the groups and {kind}s" if counts[kind] else "")))
        curves += [(ds[f"white_deviation_{'mean' if kind == 'pixel' else 'block_mean'}"].values,
                    f"white noise of the single-batch scatter, {kind}s", dict(color=colour, ls=":", lw=1.2)),
                   (ds[f"photon_limit_{kind}"].values, f"photon limit, {kind}s", dict(color=colour, ls="--", lw=1)),
                   (ds[f"photon_limit_{kind}_paper"].values, f"paper's photon limit, {kind}s",
                    dict(color=colour, ls="-.", lw=0.8, alpha=0.7))]
    if "deviation_mean_batch_means" in ds:
        batch_means = ds["deviation_mean_batch_means"].values
        label = f"pixels, groups as means of batch fits ({_slope_text(ds['slope_batch_means'])})"
        if _coincides(batch_means, ds["deviation_mean"].values):  # the paper's way gives ours: one curve
            _also_names(measured[0], label)
        else:
            ax.loglog(n, batch_means, "s-", ms=3, color="0.55", lw=1.2, zorder=2, label=label)
        curves.append((ds["photon_limit_pixel_batch_means"].values, "the batch means' photon limit",
                       dict(color="0.55", ls="--", lw=0.8)))
    if "photon_limit_pixel_global" in ds:
        curves.append((ds["photon_limit_pixel_global"].values, "global solution's floor scaled to the group, pixels",
                       dict(color="0.3", lw=0.8)))
    for line in _plot_distinct(ax, n, curves):
        line.set_zorder(2.5)  # the limits over the measured curves' markers
        if n.size == 1:  # one group size: a line of one point shows nothing; a marker (one a line style) does
            line.set_marker(_SINGLE_POINT_MARKERS.get(line.get_linestyle(), "_"))
            line.set_markersize(12)
            line.set_markeredgewidth(1.5)
    ax.set_xlabel("frames per group")
    _frame_ticks(ax.xaxis)
    ax.set_ylabel("deviation of projected offsets [pixel]")
    too_few = few_batches(ds.sizes["batch"], ds.attrs["frames_per_batch"])
    ax.set_title(too_few or f"{ds.sizes['batch']} batches of {ds.attrs['frames_per_batch']:.0f} frames, each "
                 f"sweeping a fringe period; each fits the pixels' phases alone",
                 fontsize=11 if too_few else 9, color="firebrick" if too_few else "black")
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    # off the curves; one column when the labels are long (no slope to give, said in two of them)
    handles, labels = _drawn_entries(ax)
    fig.legend(handles, labels, loc="outside lower center", fontsize=7, ncol=1 if too_few else 2,
               handler_map=_first_line_keys(handles, labels))
    fig.suptitle(title, fontsize=11)
    return fig


def _first_line_keys(handles, labels) -> dict:
    """A legend's handler map drawing the key of each entry of several lines (a curve's name, then those of
    the curves merged into it: :func:`_also_names`) beside its first line. Matplotlib centres a key on its
    text: a six-line entry had its key beside a merged name, three lines down, and its own name, with no key,
    read as the end of the entry above it."""
    keys = {}
    for handle, label in zip(handles, labels):
        if "\n" in label:
            kind = (_FirstLineErrorbar if isinstance(handle, matplotlib.container.ErrorbarContainer)
                    else _FirstLineLine2D)
            keys[handle] = kind(label.count("\n"))
    return keys


#: Line spacing of a legend's texts, in font sizes (matplotlib's default).
LEGEND_LINESPACING = 1.2


class _FirstLine:
    """A legend handler's mixin: the key raised by half the ``lines`` lines of text below the first, from the
    middle of the entry's text (where the legend centres it) to its first line."""

    def __init__(self, lines: int, **kwargs):
        super().__init__(**kwargs)
        self.lines = lines

    def create_artists(self, legend, orig_handle, xdescent, ydescent, width, height, fontsize, trans):
        up = matplotlib.transforms.Affine2D().translate(0, self.lines * LEGEND_LINESPACING * fontsize / 2)
        return super().create_artists(legend, orig_handle, xdescent, ydescent, width, height, fontsize, up + trans)


class _FirstLineLine2D(_FirstLine, matplotlib.legend_handler.HandlerLine2D):
    pass


class _FirstLineErrorbar(_FirstLine, matplotlib.legend_handler.HandlerErrorbar):
    pass


#: The marker of a limit drawn at one group size, by the line style it has at several (solid, dashed, dotted,
#: dash-dotted), so that the legend still tells them apart.
_SINGLE_POINT_MARKERS = {"-": "_", "--": "1", ":": "x", "-.": "+"}


def _slope_text(slope) -> str:
    """'slope -0.49' of a log-log slope, or 'no slope' where it is NaN (one group size)."""
    return f"slope {float(slope):.2f}" if np.isfinite(float(slope)) else "no slope: one group size"


def _drawn_entries(ax):
    """(handles, labels) of ``ax``'s legend entries for what shows: a line or error bars with a finite point (a
    curve of NaN alone, as a pixel's where every size has too few groups, is not listed), any other artist."""
    def shows(handle):
        line = handle.lines[0] if isinstance(handle, matplotlib.container.ErrorbarContainer) else handle
        if not isinstance(line, matplotlib.lines.Line2D):
            return True
        x, y = (np.asarray(v, float) for v in line.get_data())
        return bool(np.any(np.isfinite(x) & np.isfinite(y)))

    entries = [(h, label) for h, label in zip(*ax.get_legend_handles_labels()) if shows(h)]
    return [h for h, _ in entries], [label for _, label in entries]


#: Mantissas of the labelled ticks on a log axis, sparsest first (:class:`_LogTicks` takes the first that reads).
TICK_MANTISSAS = ((1,), (1, 2, 5), (1, 2, 3, 5), (1, 1.5, 2, 3, 4, 5, 6, 8),
                  (1, 1.2, 1.4, 1.6, 1.8, 2, 2.5, 3, 3.5, 4, 5, 6, 7, 8, 9))


def log_ticks(low, high):
    """Labelled tick values (in the axis's unit) of a log axis viewing ``low``-``high``: the sparsest mantissas
    of :data:`TICK_MANTISSAS` giving at least three ticks in view and no stretch without a label (between two
    ticks, or a tick and the view's end) longer than 0.2 decade or, on a longer axis, 30% of it. So a view of
    320-2000 frames is labelled 400, 500, 600, 800, 1000, 1500 (not up to 1000 alone), one of 10-30000 at the
    powers of ten. A view too narrow for any (one group size) is labelled at its middle, to 3 digits."""
    low, high = sorted((float(low), float(high)))
    if not (low > 0 and np.isfinite(high) and high > low):
        return np.array([])
    edges = np.log10([low, high])
    longest = max(0.2, 0.3 * (edges[1] - edges[0]))
    decades = np.arange(np.floor(edges[0]), np.ceil(edges[1]) + 1)
    for mantissas in TICK_MANTISSAS:
        ticks = np.array([m * 10.0**k for k in decades for m in mantissas])
        ticks = ticks[(ticks >= low * (1 - 1e-9)) & (ticks <= high * (1 + 1e-9))]
        gaps = np.diff(np.concatenate([edges[:1], np.log10(ticks), edges[1:]]))
        if ticks.size >= 3 and gaps.max() <= longest:
            break
    if ticks.size == 0:  # a view narrower than any mantissa step (one group size): label its middle
        ticks = np.array([float(f"{np.sqrt(low * high):.3g}")])
    return ticks


class _LogTicks(matplotlib.ticker.Locator):
    """:func:`log_ticks` of the axis's view, as it is when the figure is drawn."""

    def __call__(self):
        return self.tick_values(*self.axis.get_view_interval())

    def tick_values(self, vmin, vmax):
        return log_ticks(vmin, vmax)


def _frame_ticks(axis):
    """A log axis of frames labelled by :func:`log_ticks`, in plain numbers (1500, not 1.5x10^3); unlabelled
    minor ticks at every integer mantissa for the grid."""
    axis.set_major_locator(_LogTicks())
    axis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda value, _: f"{value:g}"))
    axis.set_minor_locator(matplotlib.ticker.LogLocator(subs=np.arange(2, 10), numticks=99))
    axis.set_minor_formatter(matplotlib.ticker.NullFormatter())


def _used_positions(position, positions):
    """Mask of the positions in the inclusive index range ``positions`` ((first, last); None: all)."""
    position = np.asarray(position)
    if positions is None:
        return np.ones(position.shape, bool)
    first, last = positions
    return (position >= first) & (position <= last)


def _range_text(position, used):
    """'positions a-b' of the used ones, or a note that none is."""
    return f"positions {position[used].min()}-{position[used].max()}" if used.any() else "no position in the range"


def _integer_ticks(axis):
    """Ticks of an axis (``ax.xaxis``, ``ax.yaxis``) of an integer quantity at integers only, even when the
    view holds one integer (MaxNLocator's integer option otherwise needs two)."""
    axis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True, min_n_ticks=1))


def centroids_figure(ds, *, title, positions=None):
    """Star windows, the central star's path and its precision, from a ``centroids/<mode>.nc`` dataset.

    Top: each star's corrected mean window at the first position (adu, one
    colour scale for all). Middle: the central star (nearest the stars' mean
    position), x and y each against the position index (one panel each, minus
    its mean), with the precision of each position from its batches (error
    bars); and its path, y against x, each axis to its own scale (the paper's
    figure). The positions used for the accuracies, the inclusive index range
    ``positions`` (config ``astrometry.positions``; None: all), are drawn in
    red in these three. Bottom: the central star's precision from its batches
    (points) against the Cramer-Rao bound (lines), x and y, log scale (pixel):
    at the scale of the path, a fraction of a pixel, both would be invisible.
    """
    n_star = ds.sizes["star"]
    columns = max(n_star, 3)
    fig = plt.figure(figsize=(max(10, 2.2 * n_star + 1), 13), constrained_layout=True)
    grid = fig.add_gridspec(4, columns, height_ratios=[1.0, 1, 1, 1.1])
    x0, y0 = ds["x"].values[0], ds["y"].values[0]
    central = int(np.nanargmin(np.hypot(x0 - np.nanmean(x0), y0 - np.nanmean(y0))))
    windows = ds["window"].values
    finite = windows[np.isfinite(windows)]
    low, high = (finite.min(), finite.max()) if finite.size else (0.0, 1.0)
    window_axes = []
    half = windows.shape[-1] // 2
    for s in range(n_star):
        ax = fig.add_subplot(grid[0, s])
        # the window sits on the pixel nearest the star at the first position: its detector pixels
        col, row = np.rint(x0[s]), np.rint(y0[s])
        image = ax.imshow(windows[s], origin="lower", cmap="magma", vmin=low, vmax=high, interpolation="nearest",
                          extent=(col - half - 0.5, col + half + 0.5, row - half - 0.5, row + half + 0.5))
        # the centroid short enough to stay over its own window (the position said once, on the colour bar)
        ax.set_title(f"star {s}" + (" (central)" if s == central else "") +
                     f"\nx {x0[s]:.3f} pixel, y {y0[s]:.3f} pixel", fontsize=8)
        for axis, centre in ((ax.xaxis, col), (ax.yaxis, row)):
            axis.set_major_locator(matplotlib.ticker.FixedLocator([centre - half, centre, centre + half]))
            axis.set_tick_params(labelsize=7)
        ax.set_xlabel("column x [pixel]", fontsize=7, labelpad=1)
        if s == 0:  # one y label for the row of windows: each would take the width the windows need
            ax.set_ylabel("row y [pixel]", fontsize=7, labelpad=1)
        window_axes.append(ax)
    position = ds["position"].values
    fig.colorbar(image, ax=window_axes, shrink=0.8, label=f"mean window at position {position[0]} [adu]")
    used = _used_positions(position, positions)
    used_text = _range_text(position, used)
    half = columns // 2
    for row, axis in ((1, "x"), (2, "y")):
        ax = fig.add_subplot(grid[row, :half])
        values = ds[axis].values[:, central]
        offset = np.nanmean(values)
        error = ds[f"precision_{axis}"].values[:, central]
        factor = _visible_factor(error, values, ax, fig)
        ax.errorbar(position, values - offset, yerr=error * factor, fmt="o-", color="C0", ms=3, lw=0.8, capsize=3,
                    elinewidth=1.2, gid=f"precision bars {axis}", label="batch precision (error bars, enlarged as "
                                                                      "each title says; true size below)")
        ax.plot(position[used], values[used] - offset, "o", ls="none", color="red", ms=3.5, zorder=3,
                gid="used positions", label=f"{used_text} (accuracies)")
        ax.set_xlabel("position index")
        _integer_ticks(ax.xaxis)
        ax.set_ylabel(f"{axis} - {offset:.3f} [pixel]")
        ax.set_title(f"central star's {axis} against the position index"
                     + (f" (error bars x{factor:g})" if factor != 1 else ""), fontsize=9)
        if axis == "y":  # one legend for both panels, under the lower one: inside, it would hide points
            ax.legend(fontsize=7, ncol=1, loc="upper center", bbox_to_anchor=(0.5, -0.2), title="both panels",
                      title_fontsize=7)
    ax = fig.add_subplot(grid[1:3, half:])
    x, y = ds["x"].values[:, central], ds["y"].values[:, central]
    ax.plot(x, y, "-", color="0.6", lw=0.8)
    if not used.all():  # a legend entry only for what is drawn
        ax.plot(x[~used], y[~used], "o", ls="none", color="C0", ms=3, label="other positions")
    ax.plot(x[used], y[used], "o", ls="none", color="red", ms=3.5, gid="used positions", label=used_text)
    for end in (0, -1):
        if np.isfinite(x[end]) and np.isfinite(y[end]):
            ax.annotate(str(position[end]), (x[end], y[end]), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_xlabel("x [pixel]")
    ax.set_ylabel("y [pixel]")
    ax.set_title("stage path seen by the central star, y against x\n(each axis to its own scale; "
                 "first and last index marked)", fontsize=9)
    ax.legend(fontsize=8, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.08))  # the path fills the axes
    ax = fig.add_subplot(grid[3, :])
    ratios = []
    bounds = [ds[f"photon_limit_{axis}"].values[:, central] for axis in "xy"]
    same = _coincides(*bounds)  # a round star: one line for both, not y's hiding x's
    for axis, colour, marker, line, limit in (("x", "C0", "o", "-", bounds[0]), ("y", "C1", "s", "--", bounds[1])):
        precision = ds[f"precision_{axis}"].values[:, central]
        ax.plot(position, precision, marker, ls="none", color=colour, ms=4, gid=f"precision {axis}",
                label=f"{axis}: precision from the batches")
        if not (same and axis == "y"):
            ax.plot(position, limit, line, color="0.2" if same else colour, lw=1.2, gid=f"Cramer-Rao {axis}",
                    label=f"x and y: Cramer-Rao bound (equal within {100 * (COINCIDENT - 1):.0f}%)" if same
                    else f"{axis}: Cramer-Rao bound")
        ratios.append(float(np.nanmedian(precision / limit)))
    shown = np.concatenate([ds[f"{name}_{axis}"].values[:, central] for name in ("precision", "photon_limit")
                            for axis in "xy"])
    shown = shown[np.isfinite(shown) & (shown > 0)]
    if shown.size:  # a decade around the points, so that a factor 2 between them reads
        ax.set_yscale("log")
        ax.set_ylim(shown.min() / 2, shown.max() * 2)
        # some minor ticks labelled up to two decades: 1e-4 and 1e-3 alone would be the only labels
        ax.yaxis.set_minor_formatter(matplotlib.ticker.LogFormatterSciNotation(minor_thresholds=(2, 0.5)))
    for first, last in ((position[used].min(), position[used].max()),) if used.any() and not used.all() else ():
        ax.axvspan(first - 0.5, last + 0.5, color="red", alpha=0.07, lw=0, label=f"{used_text} (accuracies)")
    ax.set_xlabel("position index")
    _integer_ticks(ax.xaxis)
    ax.set_ylabel("1-sigma error of the centroid [pixel]")
    ax.set_title(f"central star's precision against its Cramer-Rao bound: median ratio {ratios[0]:.2f} (x), "
                 f"{ratios[1]:.2f} (y)", fontsize=9)
    ax.grid(True, which="both", axis="y", alpha=0.3)
    ax.legend(fontsize=7, ncol=5)
    fig.suptitle(f"{title} ({ds.attrs.get('method', '')})", fontsize=11)
    return fig


def _visible_factor(error, values, ax, fig, *, marker_points=3.0):
    """A power of ten by which 1-sigma error bars ``error`` are enlarged so that the median bar reaches beyond
    a marker of ``marker_points`` on ``ax``, whose data span ``values`` (1 when they already do)."""
    error = np.asarray(error, float)
    error = error[np.isfinite(error) & (error > 0)]
    span = np.nanmax(values) - np.nanmin(values) if np.isfinite(values).any() else 0.0
    if not error.size or span <= 0:
        return 1.0
    height = ax.get_position().height * fig.get_figheight() * 72  # points, before the layout's small changes
    needed = 2 * marker_points * span * 1.1 / height  # half a bar two markers long, in data units
    return float(10.0 ** max(0, np.ceil(np.log10(needed / np.median(error)))))


def _central_star(ds, mode):
    """The star nearest the pattern's mean position in ``mode`` (star 0 without ``star_x``, ``star_y``)."""
    if "star_x" not in ds or "star_y" not in ds:
        return 0
    x, y = ds["star_x"].sel(mode=mode).values, ds["star_y"].sel(mode=mode).values
    return int(np.nanargmin(np.hypot(x - np.nanmean(x), y - np.nanmean(y))))


#: The stars' colours after the central star's black: matplotlib's cycle without its grey (C7), which the line-style
#: key's grey (:data:`KEY_GREY`) would look like.
STAR_COLOURS = tuple(f"C{i}" for i in range(10) if i != 7)

#: The colour of the line-style key (x plain, y dotted): a mid grey, which no star is drawn in.
KEY_GREY = "0.65"


def _star_style(s, central):
    """Colour and legend label of star ``s``: the central star black, the others :data:`STAR_COLOURS`."""
    return ("black", f"star {s} (central)") if s == central else (STAR_COLOURS[s % len(STAR_COLOURS)], f"star {s}")


def _axis_key():
    """The line-style key's entries of the residual figures, in words too: its grey is no star's colour."""
    return (("x residual: solid, in the star's colour", dict(color=KEY_GREY, lw=1.2)),
            ("y residual: dotted, in the star's colour", dict(color=KEY_GREY, lw=1.2, ls=":")))


def _removal_line(ds, mode) -> str:
    """A pose product's line for a mode's panel: what the pose removes of Procrustes's tip-tilt excess and the
    noise-limited bound (:func:`dice_core.accuracies.pose_removal`); empty elsewhere."""
    if "removal_bound" not in ds or not np.isfinite(float(ds["removal_bound"].sel(mode=mode))):
        return ""
    bound = float(ds["removal_bound"].sel(mode=mode))
    return (f"\nProcrustes's tip-tilt excess {float(ds['tip_tilt_excess'].sel(mode=mode)):.1e} pixel: removed "
            f"{100 * float(ds['removal_measured'].sel(mode=mode)):.0f}%, noise-limited bound {100 * bound:.0f}%"
            + ("; no gain the data can show" if bound < float(ds.attrs.get("removal_bound_low", 0.5)) else ""))


def _scaled_ticks(axis, exponent):
    """Tick labels of ``axis`` (values in pixel) in 1e``exponent`` pixel; returns the unit for the axis label."""
    # rounded, so that the tick at 0 reads "0", not "-0" or "1e-17"
    axis.set_major_formatter(matplotlib.ticker.FuncFormatter(
        lambda value, _, e=exponent: f"{round(value / 10.0**e, 6) + 0.0:g}"))
    return f"1e{exponent} pixel" if exponent else "pixel"


def _pixel_exponent(values):
    """The power of ten of the pixel that the largest finite |value| of ``values`` (pixel) is in (0 if none)."""
    values = np.abs(np.asarray(values, float))
    top = np.nanmax(values) if np.isfinite(values).any() else 0.0
    return int(np.floor(np.log10(top))) if top > 0 else 0


def _style_key(*entries):
    """Legend handles drawn on no axes, for a line-style key: (label, keywords of Line2D) each."""
    from matplotlib.lines import Line2D

    return [Line2D([], [], label=label, **keywords) for label, keywords in entries]


def procrustes_figure(ds, *, title="Procrustes residuals"):
    """Residuals of every star (x plain, y dotted) against the position, one panel per mode.

    All panels share one y range, in one power of ten of the pixel, so that
    modes compare by eye. The dashed lines are +-sigma, sigma the rms of the
    residuals shown (over the positions, stars and both axes: the paper's
    dotted lines); the title gives sigma and the mode's corrected accuracy
    (sigma corrected for what the superimposition absorbs). The central star
    is black; the legend under the panels names the stars and the line styles.
    A pose product adds, per mode, what the pose removes of Procrustes's
    tip-tilt excess and the noise-limited bound its Fisher information allows
    (:func:`dice_core.accuracies.pose_removal`).
    """
    modes = list(ds["mode"].values)
    fig, axes = plt.subplots(len(modes), 1, figsize=(9, 2.7 * len(modes) + 0.6), sharex=True, sharey=True,
                             squeeze=False, constrained_layout=True)
    position = ds["position"].values
    exponent = _pixel_exponent(ds["residual"].values)
    for ax, mode in zip(axes[:, 0], modes):
        residual = ds["residual"].sel(mode=mode).values
        central = _central_star(ds, mode)
        for s in range(residual.shape[1]):
            colour, label = _star_style(s, central)
            ax.plot(position, residual[:, s, 0], color=colour, lw=0.9, label=label)
            ax.plot(position, residual[:, s, 1], color=colour, lw=0.9, ls=":")
        sigma = float(np.sqrt(np.nanmean(residual**2)))
        accuracy = float(ds["accuracy"].sel(mode=mode))
        for sign in (-1, 1):
            ax.axhline(sign * sigma, color="0.35", ls="--", lw=0.8, gid="sigma")
        ax.set_ylabel(f"residual [{_scaled_ticks(ax.yaxis, exponent)}]")
        ax.set_title(f"{mode}: σ = {sigma:.2e} pixel (rms of these residuals), corrected accuracy "
                     f"{accuracy:.2e} pixel{_removal_line(ds, mode)}", fontsize=9)  # the longest mode fits
        ax.grid(True, axis="y", alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    key = _style_key(*_axis_key(), ("±σ", dict(color="0.35", ls="--", lw=0.8)))
    fig.legend(handles + key, labels + [k.get_label() for k in key], loc="outside lower center", fontsize=7,
               ncol=4)  # off the data
    axes[-1, 0].set_xlabel("position index")
    _integer_ticks(axes[-1, 0].xaxis)
    method = ds.attrs.get("centroid_method")  # products before it was recorded have none
    fig.suptitle(f"{title}{f' ({method} centroids)' if method else ''}, positions {position.min()}-{position.max()}; "
                 "every panel on one scale", fontsize=11)
    return fig


def _downscaled_layout(residual, star_xy, spread):
    """Offsets (star, 2) placing each star's residual path in the pattern's layout, and the scale.

    The offsets are the stars' mean positions minus the pattern's mean, times
    a scale that makes the layout span ``spread`` times the largest extent
    (peak to peak, over stars and axes) of the residual paths.
    """
    centred = star_xy - np.nanmean(star_xy, axis=0)
    extent = np.nanmax(np.nanmax(residual, axis=0) - np.nanmin(residual, axis=0)) if np.isfinite(residual).any() \
        else 0.0
    span = np.nanmax(np.nanmax(centred, axis=0) - np.nanmin(centred, axis=0))
    scale = spread * extent / span if span > 0 and extent > 0 else 0.0
    return centred * scale, float(scale)


def _symmetric_square(ax, points, *, margin=1.1, bins=4):
    """Equal, symmetric limits about 0 on both axes of ``ax`` holding all ``points`` (arrays (n, 2), pixel),
    with at most ``bins`` + 1 ticks labelled in a power of ten of the pixel, so that they never overlap.
    Returns the unit of the labels (e.g. ``"1e-3 pixel"``)."""
    values = np.concatenate([np.abs(p).ravel() for p in points]) if points else np.zeros(0)
    values = values[np.isfinite(values)]
    half = margin * values.max() if values.size and values.max() > 0 else 1.0
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal", adjustable="box")
    exponent = int(np.floor(np.log10(half)))
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(matplotlib.ticker.MaxNLocator(nbins=bins, symmetric=True))
        unit = _scaled_ticks(axis, exponent)
    return unit


def _layout_words(scale):
    """How the pattern is drawn beside the residual paths, in words: 'shrunk 1,205 times' for a scale of 8.3e-4."""
    if scale >= 1:
        return f"enlarged {scale:,.0f} times" if scale >= 1.5 else "at its own size"
    return f"shrunk {1 / scale:,.0f} times"


def barycentre_figure(ds, *, title="Barycentre residuals", spread: float = 3.0):
    """The paper's barycentre-residual figures, one row per mode (pixel).

    Left: each star's residual against the position index (x plain, y
    dotted), all modes on one y range in one power of ten of the pixel; the
    positions used for the accuracies shaded (when some are not). Right: each
    star's residual path, y against x, drawn at that star's place in the
    pattern shrunk to the residuals (mean position minus the pattern's mean,
    times a scale that makes the layout span ``spread`` times the largest
    extent of the paths; the title says how many times), the corner stars
    joined by the dashed shrunk square and the used positions circled in
    black; needs the product's ``star_x``, ``star_y`` (without them, the
    paths are drawn centred). The central star is black; the legend under
    the panels names the stars and every line style.
    """
    modes = list(ds["mode"].values)
    fig, axes = plt.subplots(len(modes), 2, figsize=(13, 3.4 * len(modes) + 0.8), squeeze=False,
                             constrained_layout=True, gridspec_kw={"width_ratios": [1.7, 1]})
    position = ds["all_position"].values
    used = ds["position"].values
    circled = np.isin(position, used)
    exponent = _pixel_exponent(ds["barycentre_residual"].values)
    for row, mode in zip(axes, modes):
        residual = ds["barycentre_residual"].sel(mode=mode).values
        n_star = residual.shape[1]
        central = _central_star(ds, mode)
        if "star_x" in ds and "star_y" in ds:
            star_xy = np.column_stack([ds["star_x"].sel(mode=mode).values, ds["star_y"].sel(mode=mode).values])
            offsets, scale = _downscaled_layout(residual, star_xy, spread)
        else:
            offsets, scale = np.zeros((n_star, 2)), None
        for s in range(n_star):
            colour, label = _star_style(s, central)
            row[0].plot(position, residual[:, s, 0], color=colour, lw=0.9, label=label)
            row[0].plot(position, residual[:, s, 1], color=colour, lw=0.9, ls=":")
            px, py = residual[:, s, 0] + offsets[s, 0], residual[:, s, 1] + offsets[s, 1]
            row[1].plot(px, py, color=colour, lw=0.6, marker=".", ms=2.5)
            row[1].plot(px[circled], py[circled], "o", ls="none", ms=4.5, mfc="none", mec="black", mew=0.5,
                        gid="used positions")
        if scale is not None:
            corners = [s for s in range(n_star) if s != central] if n_star > 3 else list(range(n_star))
            angle = np.arctan2(offsets[corners, 1], offsets[corners, 0])
            ring = [corners[i] for i in np.argsort(angle)]
            ring.append(ring[0])
            row[1].plot(offsets[ring, 0], offsets[ring, 1], color="0.55", ls="--", lw=0.8, gid="layout square")
            row[1].plot(offsets[:, 0], offsets[:, 1], "+", ls="none", color="0.55", ms=6, gid="layout stars")
        if not circled.all():  # a band, not lines: lines at the first and last positions sat on the axes' edges
            row[0].axvspan(used.min() - 0.5, used.max() + 0.5, color="tab:orange", alpha=0.12, lw=0,
                           gid="used span")
        row[0].set_xlim(position.min() - 0.5, position.max() + 0.5)
        _integer_ticks(row[0].xaxis)
        row[0].set_ylabel(f"residual [{_scaled_ticks(row[0].yaxis, exponent)}]")
        row[0].set_title(f"{mode}: residuals against the position index", fontsize=9)
        unit = _symmetric_square(row[1], [line.get_xydata() for line in row[1].get_lines()])
        row[1].set_xlabel(f"x residual [{unit}]")
        row[1].set_ylabel(f"y residual [{unit}]")
        row[1].set_title(f"{mode}: y against x" if scale is None else
                         f"{mode}: y against x at each star's place\n(the pattern {_layout_words(scale)})",
                         fontsize=9)
    shared = [min(ax.get_ylim()[0] for ax in axes[:, 0]), max(ax.get_ylim()[1] for ax in axes[:, 0])]
    for ax in axes[:, 0]:  # one range for every mode: they compare by eye
        ax.set_ylim(*shared)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    from matplotlib.patches import Patch

    key = _style_key(*_axis_key(),
                     ("used position (circled)", dict(ls="none", marker="o", ms=4.5, mfc="none", mec="black",
                                                      mew=0.5)),
                     *([("the corner stars' square, shrunk (+: each star's place)", dict(color="0.55", ls="--",
                                                                                          lw=0.8))]
                       if "star_x" in ds else []))
    key += [Patch(color="tab:orange", alpha=0.12, label=f"positions {used.min()}-{used.max()} used")] \
        if not circled.all() else []
    fig.legend(handles + key, labels + [k.get_label() for k in key], loc="outside lower center", fontsize=7,
               ncol=5)  # off the data
    axes[-1, 0].set_xlabel("position index")
    fig.suptitle(f"{title}: positions {used.min()}-{used.max()} used"
                 + (" (all)" if circled.all() else f" of {position.min()}-{position.max()}"), fontsize=11)
    return fig


def save(fig, png, *, pdf=None):
    """Write a figure as PNG (150 dpi) and, optionally, PDF; then close it.

    The layout (constrained layout, laid out again at every save) is made once, for the PNG, and kept for the
    PDF: a PDF laid out anew puts the axes within 2e-3 of the figure of where they are (tested), and the
    layout is a third of the PDF's time (BENCHMARKS.md, "A figure's two saves").
    """
    from dice_core.io import atomic_write

    for path in (png, pdf):
        if path is not None:
            with atomic_write(path) as tmp:
                fig.savefig(tmp, dpi=150, format=Path(path).suffix[1:])
            fig.set_layout_engine("none")  # keeps the axes where the layout just put them
    plt.close(fig)


def _finite_window(image):
    """The bounding box of an image's finite values (the science area of a NaN-padded map)."""
    rows, cols = np.nonzero(np.isfinite(image))
    return slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1)


def offset_bias_figure(datasets, *, title="Pixel-offset error against truth: the paper's method and ours"):
    """The paper's pixel-offset-bias figure, one row per PRNU level (datasets of the offset_bias study).

    Columns: the paper's method and ours with photon noise (one colour scale
    for both, 1e-5 pixel), then the same without noise (the bias alone), each
    on its own colour scale in its own power of ten of the pixel: ours can be
    four decades below the paper's, blank on a shared scale. Each map's rms
    in its title.
    """
    datasets = list(datasets)
    fig, axes = plt.subplots(len(datasets), 4, figsize=(16, 3.6 * len(datasets)), squeeze=False,
                             constrained_layout=True)
    scale = 1e5
    for row, ds in zip(axes, datasets):
        window = _finite_window(ds["error_ours"].values)
        r0, c0 = window[0].start, window[1].start
        floor = float(ds["rms_photon_floor"])
        groups = ((("error_paper", "the paper's method"), ("error_ours", "ours")),
                  (("bias_paper", "the paper's method, noiseless"), ("bias_ours", "ours, noiseless")))
        for g, group in enumerate(groups):
            values = [ds[name].values[window] * scale for name, _ in group]
            shared = max(np.nanpercentile(np.abs(v), 99.5) for v in values) or 1.0
            for k, ((name, label), shown) in enumerate(zip(group, values)):
                ax = row[2 * g + k]
                unit, limit = "1e-5 pixel", shared
                if g == 1:  # its own scale, in the power of ten of its own 99.5th percentile
                    own = np.nanpercentile(np.abs(shown), 99.5) / scale
                    exponent = int(np.floor(np.log10(own))) if np.isfinite(own) and own > 0 else -5
                    shown = shown / scale / 10.0**exponent
                    limit = np.nanpercentile(np.abs(shown), 99.5) or 1.0
                    unit, label = f"1e{exponent} pixel", f"{label} (own colour scale)"
                rows_, cols_ = shown.shape
                im = ax.imshow(shown, origin="lower", cmap="RdBu_r", vmin=-limit, vmax=limit, interpolation="nearest",
                               extent=(c0 - 0.5, c0 + cols_ - 0.5, r0 - 0.5, r0 + rows_ - 0.5))
                shown_rms = float(np.sqrt(np.nanmean(np.square(ds[name].values[window]))))  # of this map, pixel
                if name.startswith("error"):
                    extra = f" = {shown_rms / floor:.2f} x floor"
                else:  # the map is the first PRNU pattern; the study also gives the rms over all
                    extra = (f" (this pattern);\n{float(ds[f'rms_{name}']):.2e} pixel over "
                             f"{ds.attrs.get('noiseless_draws', 1)} patterns")
                ax.set_title(f"PRNU {ds.attrs['prnu_rms']:.0e}: {label}\nrms {shown_rms:.2e} pixel{extra}", fontsize=8)
                ax.set_xlabel("column x [pixel]\n" + _science_note(ds["error_ours"].shape, (r0, r0 + rows_),
                                                                   (c0, c0 + cols_)), fontsize=8)
                ax.set_ylabel("row y [pixel]")
                fig.colorbar(im, ax=ax, shrink=0.8).set_label(unit)
    fig.suptitle(f"{title}\nprojected offsets of {datasets[0].attrs.get('baseline', '')}, "
                 f"{datasets[0].attrs.get('frames', '?')} frames (photon floor "
                 f"{float(datasets[0]['rms_photon_floor']):.2e} pixel), "
                 f"noiseless maps {datasets[0].attrs.get('noiseless_frames', '?')} frames", fontsize=10)
    return fig


def paper_comparison_figure(rows, *, title="Regenerated numbers against the paper's"):
    """Ours over the paper's for every row of the comparison table (log scale), with our 1-sigma errors."""
    records = [r.as_dict() for r in rows]
    fig, ax = plt.subplots(figsize=(14, 0.3 * len(records) + 1.8), constrained_layout=True)
    ratios = np.array([r["ours"] / r["paper"] for r in records])
    errors = np.array([r["error"] / r["paper"] if np.isfinite(r["error"]) else 0.0 for r in records])
    y = np.arange(len(records))[::-1]
    colours = ["tab:blue" if r["section"].startswith("Numerical") else "tab:orange" for r in records]
    for yy, ratio, error, colour in zip(y, ratios, errors, colours):  # markers: bar lengths mean nothing on a log axis
        low = min(error, 0.9 * ratio)  # a symmetric error bar must not cross zero on a log axis
        ax.errorbar([ratio], [yy], xerr=[[low], [error]], fmt="o", color=colour, ms=5, ecolor="black", lw=0.8,
                    capsize=2)
    ax.axvline(1.0, color="black", lw=0.8)
    ax.set_xscale("log")
    # limits just beyond labelled ticks that bracket every point and error bar: the last label inside the data
    # would leave the farthest points (the Allan rows, 20x) past the last number
    candidates = np.array([0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000])
    reach = np.concatenate([ratios - np.minimum(errors, 0.9 * ratios), ratios + errors, [1.0]])
    reach = reach[np.isfinite(reach) & (reach > 0)]
    low = candidates[candidates <= reach.min()].max(initial=candidates[0])
    high = candidates[candidates >= reach.max()].min(initial=candidates[-1])
    ticks = candidates[(candidates >= low) & (candidates <= high)]
    ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # within a decade matplotlib labels the minor ticks over them
    ax.set_xlim(low / 1.2, high * 1.2)
    ax.set_yticks(y, [f"{r['quantity']} ({r['dataset']})" for r in records], fontsize=7)
    ax.set_xlabel("ours / paper's\nblue: numerical simulations; orange: experimental section, on the simulated bench")
    ax.grid(True, axis="x", which="both", alpha=0.3)
    ax.set_title(title, fontsize=10)
    return fig


_ERROR_SOURCE_COLOURS = {"prnu": "tab:blue", "photon": "tab:orange", "offsets": "tab:green", "read": "tab:red"}


def error_propagation_figure(sweeps, *, title: str | None = None):
    """Per-axis centroid error (pixel) against each source's amplitude, log-log, one panel per source.

    For each :class:`dice_core.error_budget.Sweep`, in its colour: the Monte Carlo rms per-axis
    errors with their 1-sigma error bars (label ``"<source> MC"``), the
    analytic prediction (solid, ``"<source> analytic"``) and the paper's
    coefficient (dashed, ``"<source> paper"``), the lines over the amplitudes
    swept (a factor 2 beyond each end), and the 5e-6 pixel budget (dotted).
    Amplitudes are relative, except the offsets' (pixel).

    Returns
    -------
    matplotlib.figure.Figure
    """
    sweeps = list(sweeps)
    sources = [src for src in error_budget.SOURCES if any(sw.source == src for sw in sweeps)]
    cols = min(2, len(sources))
    rows = -(-len(sources) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.6 * cols, 3.6 * rows), constrained_layout=True, squeeze=False)
    markers = {"pipeline": ("o", "-"), "uniform": ("s", "-.")}
    for ax, source in zip(axes.ravel(), sources):
        colour = _ERROR_SOURCE_COLOURS.get(source)
        span = None
        for sw in (sw for sw in sweeps if sw.source == source):
            a = sw.amplitudes
            marker, line = markers.get(sw.weighting, ("^", ":"))
            rms = np.array([r.coefficient * r.amplitude for r in sw.runs])
            err = np.array([r.error * r.amplitude for r in sw.runs])
            ax.errorbar(a, rms, yerr=err, fmt=marker, color=colour, ms=4, capsize=2,
                        mfc=colour if sw.weighting == "pipeline" else "none",
                        label=f"{sw.weighting} fit, MC ({sw.coefficient:.3f} +- {sw.error:.3f})")
            span = np.geomspace(a.min() / 2, a.max() * 2, 20)
            ax.plot(span, sw.prediction.coefficient * span, line, color=colour, lw=1,
                    label=f"{sw.weighting} fit, analytic ({sw.prediction.coefficient:.3f})")
        ax.plot(span, error_budget.PAPER_COEFFICIENTS[source] * span, "--", color="black", lw=0.8, alpha=0.6,
                label=f"paper ({error_budget.PAPER_COEFFICIENTS[source]:.2f})")
        ax.axhline(error_budget.REQUIRED_ERROR, color="0.5", lw=0.8, ls=":", label="5e-6 pixel")
        ax.set_xscale("log")
        ax.set_yscale("log")
        unit = "pixel" if error_budget.SOURCE_UNITS[source] == "pixel" else "relative"
        ax.set_xlabel(f"{source} amplitude [{unit}]")
        ax.set_ylabel("centroid error per axis, rms [pixel]")
        ax.set_title(source, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    for ax in axes.ravel()[len(sources):]:
        ax.set_visible(False)
    fig.suptitle(title or "Error propagation into the Gaussian centroid: Monte Carlo (points), linear propagation "
                          "(lines), the paper (dashed)", fontsize=9)
    return fig


#: How a swept parameter is named on a figure: (its words, its unit, the factor from the config's value to
#: that unit). A parameter not listed is shown by its dotted key, unscaled.
PARAMETER_AXES = {
    "detector.prf_width_spread": ("PRF width spread", "%", 100.0),
    "simulation.detector.prf_width_spread": ("PRF width spread", "%", 100.0),
    "stars.frames": ("frames a position", "", 1.0),
    "simulation.stars.frames": ("frames a position", "", 1.0),
    "stars.tip_tilt_pv": ("tip-tilt peak to valley", "rad", 1.0),
    "simulation.stars.tip_tilt_pv": ("tip-tilt peak to valley", "rad", 1.0),
}


def parameter_axis(key):
    """(words, axis label with its unit, factor) of a swept parameter's dotted key (``PARAMETER_AXES``)."""
    words, unit, factor = PARAMETER_AXES.get(key, (key, "", 1.0))
    return words, f"{words} [{unit}]" if unit else words, factor


def star_accuracy_figure(datasets, points, *, title="Centroid accuracy with perfect calibrations"):
    """Each calibration mode's error against truth (solid) and Procrustes accuracy (dashed, with its error),
    pixel, against a star_accuracy sweep's parameter (or the point's number when several vary), in the
    parameter's unit (``PARAMETER_AXES``: the PRF width spread in %)."""
    keys = sorted({k for p in points for k in p})
    numeric = len(keys) == 1 and all(isinstance(p[keys[0]], (int, float)) for p in points)
    words, label, factor = parameter_axis(keys[0]) if numeric else (", ".join(keys), None, 1.0)
    x = [p[keys[0]] * factor for p in points] if numeric else list(range(len(points)))
    order = sorted(range(len(points)), key=lambda i: x[i])
    fig, ax = plt.subplots(figsize=(8, 5), constrained_layout=True)
    for k, mode in enumerate(datasets[0]["mode"].values):
        colour = f"C{k}"
        xs = [x[i] for i in order]
        ax.plot(xs, [float(datasets[i]["truth_error"].sel(mode=mode)) for i in order], "o-", color=colour,
                label=f"{mode}: against truth")
        ax.errorbar(xs, [float(datasets[i]["accuracy_position"].sel(mode=mode)) for i in order],
                    yerr=[float(datasets[i]["error_position"].sel(mode=mode)) for i in order], fmt="s--",
                    color=colour, ms=4, capsize=2, alpha=0.7, label=f"{mode}: Procrustes accuracy (p)")
    ax.set_yscale("log")
    ax.set_xlabel(label if numeric else f"point ({words})")
    ax.set_ylabel("centroid error [pixel]")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    ax.set_title(f"{title}: centroid error [pixel] of each calibration mode against the {label or words}\n"
                 f"{datasets[0].attrs.get('method', '')} centroids, {datasets[0].attrs.get('positions', '?')} "
                 "positions, perfect flat and offsets; solid: against truth, dashed: Procrustes accuracy (p)",
                 fontsize=9)
    return fig


def reduction_sweep_figure(rows, parameters, *, title="Accuracy against the swept parameter"):
    """A reduction sweep's accuracies (pixel, with errors) of each mode and grouping against its parameter,
    one panel per superimposition (Procrustes first).

    ``rows``: records of the points' ``tables/accuracy.csv`` with the point's ``parameters`` as keys
    (strings or numbers); the first method's rows are drawn. A parameter that every point sets alike is
    said in the title, not drawn; one numeric parameter left is the x axis, in its unit
    (``PARAMETER_AXES``), several are the points' labels.
    """
    method = rows[0]["method"]
    rows = [r for r in rows if r["method"] == method]
    fixed = [p for p in parameters if len({str(r[p]) for r in rows}) == 1]
    varying = [p for p in parameters if p not in fixed] or list(parameters)
    numeric = len(varying) == 1
    words, label, factor = parameter_axis(varying[0]) if numeric else (", ".join(varying), None, 1.0)
    if numeric:
        try:
            x_of = {id(r): float(r[varying[0]]) * factor for r in rows}
        except (TypeError, ValueError):
            numeric, label = False, None
    points = list(dict.fromkeys(tuple(str(r[p]) for p in varying) for r in rows))
    if not numeric:
        x_of = {id(r): points.index(tuple(str(r[p]) for p in varying)) for r in rows}
    models = list(dict.fromkeys(["procrustes", *(r.get("superimposition", "procrustes") for r in rows)]))
    models = [m for m in models if any(r.get("superimposition", "procrustes") == m for r in rows)]
    fig, axes = plt.subplots(1, len(models), figsize=(8 * len(models) ** 0.5 + 1, 5), constrained_layout=True,
                             squeeze=False, sharey=True)
    modes = list(dict.fromkeys(r["mode"] for r in rows))
    for ax, model in zip(axes[0], models):
        for k, mode in enumerate(modes):
            for grouping, style in (("position", "o-"), ("group", "s--")):
                chosen = sorted((r for r in rows if r["mode"] == mode and r["grouping"] == grouping
                                 and r.get("superimposition", "procrustes") == model), key=lambda r: x_of[id(r)])
                if chosen:
                    ax.errorbar([x_of[id(r)] for r in chosen], [float(r["accuracy"]) for r in chosen],
                                yerr=[float(r["error"]) for r in chosen], fmt=style, color=f"C{k}", ms=4,
                                capsize=2, alpha=1.0 if grouping == "position" else 0.6,
                                label=f"{mode} ({grouping[0]})")
        if not numeric:
            ax.set_xticks(range(len(points)), [", ".join(p) for p in points], fontsize=7)
        elif factor == 1.0 and all(float(r[varying[0]]) > 0 for r in rows) and \
                max(x_of.values()) / min(x_of.values()) >= 10:
            ax.set_xscale("log")  # e.g. frames a position over decades
        ax.set_yscale("log")
        ax.set_xlabel(label if numeric else words)
        ax.set_title(model, fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("corrected accuracy [pixel]")
    axes[0][0].legend(fontsize=7, ncol=2)
    constant = "; ".join(f"{p} = {rows[0][p]}" for p in fixed if p not in varying)
    fig.suptitle(f"{title}: corrected accuracy [pixel] of each mode against the {label or words}, {method} centroids, "
                 f"(p) over positions, (g) over groups" + (f"\n{constant}" if constant else ""), fontsize=9)
    return fig


def reproduction_pdf(path, pages, *, title: str, summary_lines=()):
    """A PDF of figures with their captions (A4 portrait, one figure per page), after a title page.

    ``pages``: (PNG path, caption text) in order; ``summary_lines``: the title page's text (e.g. the
    comparison table, one line per number). Written through a temporary name, then renamed.
    """
    import textwrap

    from matplotlib.backends.backend_pdf import PdfPages

    from dice_core.io import atomic_write

    path = Path(path)
    with atomic_write(path) as tmp:
        with PdfPages(tmp) as pdf:
            fig = plt.figure(figsize=(8.27, 11.69))
            fig.text(0.06, 0.96, title, fontsize=13, va="top", weight="bold")
            fig.text(0.06, 0.92, "\n".join(summary_lines), fontsize=5.6, va="top", family="monospace")
            pdf.savefig(fig)
            plt.close(fig)
            for png, caption in pages:
                image = plt.imread(png)
                fig = plt.figure(figsize=(8.27, 11.69))
                height, width = image.shape[:2]
                ax_height = min(0.72, 0.88 * height / width * 8.27 / 11.69)
                ax = fig.add_axes([0.06, 0.96 - ax_height, 0.88, ax_height])
                ax.imshow(image)
                ax.axis("off")
                fig.text(0.06, 0.94 - ax_height, f"{Path(png).stem}\n\n" + textwrap.fill(caption, 110), fontsize=7.5,
                         va="top")
                pdf.savefig(fig)
                plt.close(fig)
    return path


def stripe_ratios(image, detector):
    """Whether a map is striped, as two numbers: the variance of its row means, and of its column means, over
    the science area, each over what independent pixels of the map's own scatter give (the variance over the
    pixels in a row, or a column). About 1 without stripes; rows or columns that share an offset make it
    grow with their length (NaN pixels left out)."""
    shown = np.asarray(image, float)[detector.science_slices]
    shown = shown - np.nanmean(shown)
    total = np.nanvar(shown)
    ratios = []
    for axis in (1, 0):  # row means (over the columns), then column means (over the rows)
        counts = np.sum(np.isfinite(shown), axis=axis)
        keep = counts > 1
        means = np.nansum(shown, axis=axis)[keep] / counts[keep]
        ratios.append(float(np.var(means) / np.mean(total / counts[keep])) if keep.sum() > 1 and total > 0
                      else float("nan"))
    return tuple(ratios)


def _stripes_line(image, detector):
    """A map title's line that measures its stripes (:func:`stripe_ratios`): what the eye reads as rows or
    columns is then a number, 1 for none."""
    rows, cols = stripe_ratios(image, detector)
    return f"stripes: row-mean ratio {rows:.2f}, column-mean ratio {cols:.2f} (1: none)"


def prf_widths_figure(ds, detector, *, title="PRF widths from the fringe contrast"):
    """Width maps (relative to their mean width) and their 1-sigma pixel-scale errors along x and y.

    ``ds`` is a ``calibration/prf.nc`` dataset; top row: width - mean_width in
    1e-3 pixel, the mean with its error in the title; bottom row:
    error_width_pixel (photon noise and the kernel shape's uncertainty in the
    deviations' scale) in 1e-3 pixel, with its median. Each map's title
    measures its row and column stripes (:func:`stripe_ratios`). A direction
    without a baseline stays blank.
    """
    fig, axes = plt.subplots(2, 2, figsize=(11.2, 9.2), constrained_layout=True)
    for j, axis in enumerate("xy"):
        mean, mean_error = float(ds[f"mean_width_{axis}"]), float(ds[f"error_mean_width_{axis}"])
        width, error = ds[f"width_{axis}"].values, ds[f"error_width_pixel_{axis}"].values
        spread = float(np.sqrt(np.nanmean((width - mean) ** 2))) if np.isfinite(width).any() else float("nan")
        # a median: the errors are positive and skewed by the few pixels of low contrast (an rms weighs those)
        shown = error[detector.science_slices]  # the median of what the map draws
        err = float(np.nanmedian(shown)) if np.isfinite(shown).any() else float("nan")
        _show_map(axes[0, j], fig, width - mean, detector, scale=1e3, units="width - mean [1e-3 pixel]",
                  symmetric=True, title=f"width along {axis} minus its mean ({mean:.4f} pixel +- {mean_error:.4f} pixel); "
                                        f"rms {spread:.2e} pixel\n{_stripes_line(width, detector)}")
        _show_map(axes[1, j], fig, error, detector, scale=1e3, units="1-sigma error [1e-3 pixel]", symmetric=False,
                  title=f"1-sigma error of the width along {axis} minus its mean\n(photon noise, kernel "
                        f"shape): median {err:.2e} pixel\n{_stripes_line(error, detector)}")
    chi2 = float(ds["chi2"])
    fig.suptitle(f"{title} ({', '.join(map(str, ds['baseline'].values))}; chi2/dof between baselines "
                 f"{chi2:.2f})", fontsize=11)
    return fig


def tip_tilt_sweep_figure(datasets, *, title="Tip-tilt: what each superimposition leaves, and when the pose is "
                          "identifiable", snr_min: float = 3.0):
    """A tip_tilt sweep (:func:`dice_core.studies.tip_tilt` points) against the stage's tip-tilt amplitude.

    Left: each superimposition's flat+metrology accuracy (pixel, with its Monte
    Carlo error), one line per number of positions. Middle: the pose's tip and
    tilt variation over positions in Cramer-Rao bounds (SNR) with the
    identifiability threshold ``snr_min``; filled markers where the
    identifiability report accepted the angle. Right: the rms of fitted minus
    true tip and tilt, in units of the bound with the field's direction known,
    where identified (1 is the bound).
    """
    points = [(json.loads(ds.attrs["point"]), ds) for ds in datasets]  # each point's parameters
    positions = sorted({int(ds.attrs["positions"]) for _, ds in points})
    markers = dict(zip(positions, "osD^v<>"))
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6), constrained_layout=True)
    models = list(datasets[0]["model"].values)
    for n in positions:
        chosen = sorted(((p["stars.tip_tilt_pv"], ds) for p, ds in points if int(ds.attrs["positions"]) == n),
                        key=lambda point: point[0])
        pv = np.array([value for value, _ in chosen])
        for k, model in enumerate(models):
            axes[0].errorbar(pv, [float(ds["accuracy"].sel(model=model)) for _, ds in chosen],
                             yerr=[float(ds["error"].sel(model=model)) for _, ds in chosen], fmt=f"{markers[n]}-",
                             color=f"C{k}", ms=4, capsize=2, label=f"{model}, {n} positions")
        for angle, style in (("tip", "-"), ("tilt", ":")):
            snr = np.array([float(ds[f"pose_{angle}_snr"]) for _, ds in chosen])
            ok = np.array([bool(ds[f"pose_{angle}_identifiable"]) for _, ds in chosen])
            colour = f"C{positions.index(n) + len(models)}"
            axes[1].plot(pv, snr, style, color=colour, label=f"{angle}, {n} positions")
            axes[1].plot(pv[ok], snr[ok], markers[n], color=colour, ms=6)
            axes[1].plot(pv[~ok], snr[~ok], markers[n], color=colour, ms=6, mfc="none")
            ratio = np.array([float(ds[f"pose_{angle}_error"]) / float(ds[f"pose_{angle}_crlb_nominal_field"])
                              for _, ds in chosen])
            axes[2].plot(pv[ok], ratio[ok], f"{markers[n]}{style}", color=colour, label=f"{angle}, {n} positions")
    axes[0].set_yscale("log")
    axes[0].set_ylabel("flat+metrology accuracy [pixel]")
    axes[0].set_title("accuracy per superimposition", fontsize=9)
    # below the panel: Procrustes rises across the whole height the other models leave free
    axes[0].legend(fontsize=6, ncol=len(positions), loc="upper center", bbox_to_anchor=(0.5, -0.14))
    axes[1].axhline(snr_min, color="k", lw=0.8, ls="--", label=f"identifiable above {snr_min:g}")
    axes[1].set_ylabel("pose tip/tilt variation [Cramer-Rao bounds]")
    axes[1].set_title("pose identifiability (filled: identified)", fontsize=9)
    axes[1].legend(fontsize=6, loc="upper left")
    axes[2].axhline(1.0, color="k", lw=0.8, ls="--", label="the bound")
    axes[2].set_ylabel("rms(fitted - true) / CRLB (field known) [1]")
    axes[2].set_title("pose tip and tilt against truth, where identified", fontsize=9)
    axes[2].set_ylim(0, max(2.0, axes[2].get_ylim()[1]))
    axes[2].legend(fontsize=6, loc="upper left")
    for ax in axes:
        ax.set_xlabel("stage tip-tilt amplitude [rad peak to valley]")
        ax.grid(True, which="both", alpha=0.3)
    fig.suptitle(f"{title} ({datasets[0].attrs.get('method', '')} centroids)", fontsize=10)
    return fig


def stray_light_figure(ds, detector, *, title, prefix: str = ""):
    """A map's stray-light diagnosis (a ``calibration/stray_light_<baseline>.nc`` dataset, or an offsets
    difference's ``ddx_``/``ddy_`` part with ``prefix``): the power spectrum over the white level (log scale)
    with the components found circled at f and -f, and the phase error (or, without it, the offset error)
    they make (1e-3 rad or 1e-3 pixel)."""
    p = prefix
    fig, axes = plt.subplots(1, 2, figsize=(11.6, 4.9), constrained_layout=True)
    fx, fy = ds["frequency_x"].values, ds["frequency_y"].values
    step = (fx[1] - fx[0], fy[1] - fy[0])
    power = np.log10(np.maximum(ds[f"{p}power"].values, 1e-3))
    im = axes[0].imshow(power, origin="lower", interpolation="nearest", cmap="magma", vmin=-1,
                        vmax=max(np.log10(float(ds[f"{p}threshold"])) + 0.5, float(power.max())),
                        extent=(fx[0] - step[0] / 2, fx[-1] + step[0] / 2, fy[0] - step[1] / 2, fy[-1] + step[1] / 2))
    fig.colorbar(im, ax=axes[0], shrink=0.85).set_label("log10 power / white level")
    n = int(ds[f"{p}n_components"])
    for i in range(n):
        f = np.array([float(ds[f"{p}component_frequency_x"][i]), float(ds[f"{p}component_frequency_y"][i])])
        for sign in (1, -1):
            axes[0].plot(*(sign * f), "o", mfc="none", mec="cyan", ms=14, mew=1.2)
        axes[0].annotate(f"{i + 1}: {float(ds[f'{p}component_amplitude'][i]):.1e} px", f, xytext=(8, 8),
                         textcoords="offset points", color="cyan", fontsize=8)
    excluded = ds[f"{p}excluded_frequency"].values if f"{p}excluded_frequency" in ds else np.empty((0, 2))
    # a frequency past Nyquist (0.5 cycles/pixel) is drawn where the pixels see it, folded back into the band
    folded = " (those past 0.5 folded back)" if (np.abs(excluded) >= 0.5).any() else ""
    for j, f in enumerate(excluded):
        aliased = (np.outer([1, -1], f) + 0.5) % 1.0 - 0.5  # the fringes' own K and 2K, left out of the search
        axes[0].plot(*aliased.T, "x", color="w", ms=9, mew=1.5, ls="none", clip_on=False,  # whole at the edge
                     label=f"left out: the fringes' K, 2K{folded}" if j == 0 else None)
    if f"{p}excluded_frequency" in ds and ds.sizes.get(f"{p}excluded", 0):
        axes[0].legend(fontsize=7, loc="lower left")
    axes[0].set_xlim(fx[0] - step[0] / 2, fx[-1] + step[0] / 2)
    axes[0].set_ylim(fy[0] - step[1] / 2, fy[-1] + step[1] / 2)
    axes[0].set_xlabel("spatial frequency x [cycles/pixel]")
    axes[0].set_ylabel("spatial frequency y [cycles/pixel]")
    axes[0].set_title(f"spectrum of the offsets: {n} component(s) above {float(ds[f'{p}threshold']):.1f} x white\n"
                      f"(false-alarm rate {float(ds[f'{p}false_alarm']):g}); white level "
                      f"{np.sqrt(float(ds[f'{p}white_level'])):.1e} pixel rms", fontsize=8)
    if f"{p}phase_error" in ds:
        image, unit, what = ds[f"{p}phase_error"].values, "rad", "phase error"
    else:
        image, unit, what = ds[f"{p}offset_error"].values, "pixel", "offset error"
    _show_map(axes[1], fig, image, detector, scale=1e3, symmetric=True, units=f"{what} [1e-3 {unit}]",
              title=f"{what} of the components: rms {np.sqrt(np.nanmean(image**2)):.2e} {unit}" if n else
              "no component: no stray light seen")
    fig.suptitle(title, fontsize=11)
    return fig


def _study_points(datasets, **fixed):
    """The stray-light study's points whose scalars equal ``fixed`` (NaN-safe), sorted by what varies."""
    def keep(ds):
        return all(np.isclose(float(ds[k]), v, equal_nan=True) for k, v in fixed.items())

    return [ds for ds in datasets if keep(ds)]


def stray_light_study_figure(datasets, *, title="Coherent stray light: a pair's offset error, left in and removed"):
    """The stray-light study (:func:`dice_core.studies.stray_light` points): dx, dy error rms against the field
    ratio (one tip position, the longest coherence), against the coherence length (field ratio 1e-3) and for
    one tip position against the mean of several; the photon floor and the paper's 4e-4 pixel."""
    fig, axes = plt.subplots(1, 3, figsize=(15.5, 4.8), constrained_layout=True)
    single = [ds for ds in datasets if float(ds["tip_positions"]) == 1]
    short = [ds for ds in single if float(ds["path_scale"]) != 1]  # sub-mm paths: their own marker
    single = [ds for ds in single if float(ds["path_scale"]) == 1]
    longest = max((float(ds["coherence_length"]) for ds in single), default=np.nan)
    styles = {"detect": ("o", "C3", "left in"), "remove": ("s", "C0", "removed")}

    def series(ax, points, key, xscale):
        points = sorted(points, key=lambda ds: float(ds[key]))
        x = [float(ds[key]) * xscale for ds in points]
        for way, (marker, colour, label) in styles.items():
            for axis, fill in (("dx", colour), ("dy", "none")):
                ax.plot(x, [float(ds[f"error_{axis}_{way}"]) for ds in points], marker=marker, color=colour,
                        mfc=fill, ls="-" if axis == "dx" else "--", label=f"{axis}, stray light {label}")
        ax.plot(x, [float(ds["floor_dx"]) for ds in points], color="k", lw=1, ls=":", label="photon floor (dx)")
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")

    ratio = _study_points(single, coherence_length=longest)
    if ratio:
        series(axes[0], ratio, "field_ratio", 1.0)
        axes[0].axhline(4e-4, color="C2", lw=1.5, label="the paper's offset accuracy, 4e-4 pixel")
        axes[0].set_xscale("log")
        axes[0].set_xlabel("field ratio sqrt(I1 / I0) of each vane")
        axes[0].set_title(f"against the field ratio (coherence length {longest * 100:g} cm)", fontsize=9)
    coherence = _study_points(single, field_ratio=1e-3)
    if coherence:
        series(axes[1], coherence, "coherence_length", 100.0)
        axes[1].set_xscale("log")
        axes[1].set_xlabel("coherence length [cm] (|gamma| = exp(-(OPD / Lc)^2); vanes' OPD 0.6-1.5 cm)")
        axes[1].set_title("against the laser's coherence length (field ratio 1e-3)", fontsize=9)
        for ds in _study_points(short, field_ratio=1e-3):
            axes[1].plot(float(ds["coherence_length"]) * 100, float(ds["error_dx_detect"]), "*", color="C4", ms=12,
                         label=f"dx, left in, vanes' paths x {float(ds['path_scale']):g} (sub-mm)")
        axes[1].legend(fontsize=7)
    averaged = sorted((ds for ds in datasets if float(ds["tip_positions"]) > 1), key=lambda ds: float(ds["tip_step"]))
    for i, ds in enumerate(averaged):
        n = int(ds["tip_positions"])
        for j, (key, label) in enumerate((("error_dx_detect", "one position"),
                                          ("average_error_dx_detect", f"mean of {n}"),
                                          ("average_error_dx_remove", f"mean of {n}, removed"))):
            axes[2].bar(i + 0.27 * (j - 1), float(ds[key]), width=0.25, color=f"C{[3, 1, 0][j]}",
                        label=label if i == 0 else None)
        axes[2].plot([i - 0.4, i + 0.4], [float(ds["average_floor_dx"])] * 2, "k:", label=None if i else
                     f"floor of the mean of {n}")
    if averaged:
        axes[2].set_xticks(range(len(averaged)), [
            f"{float(ds['tip_step']) * 1e6:g} um" if float(ds["tip_step"]) < 1e-3 else
            f"{float(ds['tip_step']) * 1e3:g} mm" for ds in averaged])
        axes[2].set_xlabel("fiber-tip positions' spacing (3x3 grid, vanes fixed)")
        axes[2].set_yscale("log")
        top = max(float(ds["error_dx_detect"]) for ds in averaged)
        axes[2].set_ylim(top=4 * top)
        axes[2].set_title("dx: one fiber-tip position or the mean of 9 (field ratio 1e-3)", fontsize=9)
    for ax in axes:
        ax.set_ylabel("rms error against truth [pixel]")
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=11)
    return fig


def chromatic_figure(ds, detector, *, title="Calibration across wavelength"):
    """Each wavelength's offsets and sensitivity against the reference wavelength's (calibration/chromatic.nc).

    One row per wavelength other than the reference: dx and dy minus the reference's (1e-3 pixel) and the
    sensitivity's ratio to the reference's minus 1 (1e-3; blank without laser flats at both). Last row: the rms
    over the science area of each change against wavelength, each point a calibration wavelength.
    """
    wavelengths = ds["wavelength"].values
    reference = float(ds.attrs["reference_wavelength"])
    ref = int(np.argmin(np.abs(wavelengths - reference)))
    others = [i for i in range(wavelengths.size) if i != ref]
    fig, axes = plt.subplots(len(others) + 1, 3, figsize=(14, 4.2 * (len(others) + 1)), constrained_layout=True,
                             squeeze=False)
    mask = detector.science_mask()
    changes = {"dx": [], "dy": [], "sensitivity": []}
    for row, i in enumerate(others):
        nm = f"{wavelengths[i] * 1e9:g} nm"
        for j, name in enumerate(changes):
            if name == "sensitivity":
                change = ds[name].values[i] / ds[name].values[ref] - 1
            else:
                change = ds[name].values[i] - ds[name].values[ref]
            finite = np.isfinite(change) & mask
            rms = float(np.sqrt(np.mean(change[finite] ** 2))) if finite.any() else float("nan")
            changes[name].append(rms)
            if finite.any():
                _show_map(axes[row, j], fig, change, detector, scale=1e3, symmetric=True,
                          units=f"{'ratio - 1' if name == 'sensitivity' else name + ' change'} [1e-3"
                                f"{'' if name == 'sensitivity' else ' pixel'}]",
                          title=f"{name} at {nm} against {reference * 1e9:g} nm, rms {rms:.2e}")
            else:
                axes[row, j].set_axis_off()
                axes[row, j].set_title(f"{name} at {nm}: no laser flat", fontsize=9)
    last = axes[-1, 0]
    order = np.argsort(wavelengths[others])
    for name, values in changes.items():
        values = np.array(values)[order]
        if np.isfinite(values).any():
            last.plot(wavelengths[others][order] * 1e9, values, "o-", label=name)
    last.axvline(reference * 1e9, color="0.6", ls=":", label="reference")
    last.set_xlabel("wavelength [nm]")
    last.set_ylabel("rms change from the reference [pixel, or 1]")
    last.set_yscale("log")
    last.legend(fontsize=8)
    last.set_title("the detector's change with wavelength", fontsize=9)
    for ax in axes[-1, 1:]:
        ax.set_axis_off()
    fig.suptitle(f"{title}: pairs {', '.join(map(str, ds['pair'].values))}", fontsize=11)
    return fig


#: The paper's gain of flat and metrology over raw, (p) (its accuracy table: 2.1e-4 / 9.7e-5).
PAPER_CALIBRATION_GAIN = 2.2


def chromatic_study_figure(datasets, *, title="Broadband stars on a chromatic detector"):
    """A chromatic sweep (:func:`dice_core.studies.chromatic_accuracy` points): what colour costs each calibration.

    Top, one panel per star spectrum: the chromatic mode's (p) accuracy (pixel, with its Monte Carlo error)
    against the number of calibration wavelengths (1: 633 nm alone, the paper's calibration), one line per
    chromatic amplitude; dashed, the achromatic twin's flat+metrology (the same noise draws), dotted, the photon
    limit a position. Bottom left: the flat+metrology gain over raw (p) at 633 nm alone against the amplitude (0:
    the twin), one line per spectrum, beside the paper's 2.2; bottom middle: the chromatic mode's (p) accuracy over
    the twin's flat+metrology's against the number of wavelengths, every point, beside 1.2.
    """
    spectra = [s for s in ("flat", "warm", "cool") if any(ds.attrs["spectrum"] == s for ds in datasets)]
    spectra += sorted({ds.attrs["spectrum"] for ds in datasets} - set(spectra))
    amplitudes = sorted({float(ds.attrs["amplitude"]) for ds in datasets})
    fig = plt.figure(figsize=(4.6 * max(len(spectra), 2), 8.6), constrained_layout=True)
    grid = fig.add_gridspec(2, max(len(spectra), 2))
    top = [fig.add_subplot(grid[0, j]) for j in range(len(spectra))]
    for ax, spectrum in zip(top, spectra):
        chosen = [ds for ds in datasets if ds.attrs["spectrum"] == spectrum]
        for k, amplitude in enumerate(amplitudes):
            for ds in (d for d in chosen if float(d.attrs["amplitude"]) == amplitude):
                n = ds["wavelengths"].values
                ax.errorbar(n, ds["chromatic_accuracy_position"].values, yerr=ds["chromatic_error_position"].values,
                            fmt="o-", color=f"C{k}", capsize=2, label=f"chromatic mode, amplitude {amplitude:g}")
        twin = chosen[0]
        fm = float(twin["accuracy_position"].sel(mode="achromatic flat+metrology"))
        error = float(twin["error_position"].sel(mode="achromatic flat+metrology"))
        ax.axhline(fm, color="k", ls="--", label="achromatic twin, flat+metrology")
        ax.axhspan(fm - error, fm + error, color="k", alpha=0.08)
        ax.axhline(float(twin["photon_limit"]), color="0.5", ls=":", label="photon limit a position")
        ax.set_yscale("log")
        ax.set_xticks(sorted({int(n) for ds in chosen for n in ds["wavelengths"].values}))
        ax.set_xlabel("calibration wavelengths (1: 633 nm alone)")
        ax.set_ylabel("accuracy (p) [pixel]")
        ax.set_title(f"{spectrum} stars", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    top[0].legend(fontsize=7)
    gains = fig.add_subplot(grid[1, 0])
    for j, spectrum in enumerate(spectra):
        chosen = sorted((d for d in datasets if d.attrs["spectrum"] == spectrum), key=lambda d: d.attrs["amplitude"])
        x = [0.0, *(float(d.attrs["amplitude"]) for d in chosen)]
        y = [float(chosen[0]["achromatic_gain"]), *(float(d["gain"]) for d in chosen)]
        gains.plot(x, y, "o-", color=f"C{j + 3}", label=f"{spectrum} stars")
    gains.axhline(PAPER_CALIBRATION_GAIN, color="k", ls="--", label=f"the paper's {PAPER_CALIBRATION_GAIN}")
    gains.set_xlabel("chromatic amplitude (0: the achromatic twin)")
    gains.set_ylabel("raw / flat+metrology at 633 nm, (p)")
    gains.set_title("what a 633 nm calibration gains", fontsize=10)
    gains.grid(True, alpha=0.3)
    gains.legend(fontsize=7)
    ratios = fig.add_subplot(grid[1, 1])
    for j, spectrum in enumerate(spectra):
        for k, amplitude in enumerate(amplitudes):
            for ds in (d for d in datasets if d.attrs["spectrum"] == spectrum and float(d.attrs["amplitude"]) == amplitude):
                ratios.plot(ds["wavelengths"].values, ds["chromatic_over_achromatic"].values, "os^D"[k % 4] + "-",
                            color=f"C{j + 3}", label=f"{spectrum} stars, amplitude {amplitude:g}")
    ratios.axhline(1.2, color="k", ls="--", label="1.2")
    ratios.axhline(1.0, color="0.6", ls=":")
    ratios.set_yscale("log")
    ratios.set_xlabel("calibration wavelengths (1: 633 nm alone)")
    ratios.set_ylabel("chromatic mode / twin's flat+metrology, (p)")
    ratios.set_title("how close colour's correction comes to the achromatic twin", fontsize=10)
    ratios.grid(True, which="both", alpha=0.3)
    ratios.legend(fontsize=7)
    first = datasets[0]
    fig.suptitle(f"{title}: {first.attrs.get('positions', '?')} positions, {first.attrs.get('method', '')} "
                 "centroids, perfect calibrations at each wavelength", fontsize=11)
    return fig
