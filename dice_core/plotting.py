"""Figures of the paper, from arrays: maps of the science area with colour bars in physical units.

Functions return a :class:`matplotlib.figure.Figure` and never read products;
:func:`save` writes it as PNG and PDF. The Agg backend is used, so no display
is needed.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

from dice_core.manifest import Detector  # noqa: E402

__all__ = ["map_figure", "maps_figure", "metrology_figure", "allan_figure", "centroids_figure", "procrustes_figure", "barycentre_figure", "save"]


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
    fig, ax = plt.subplots(figsize=(6.0, 5.2), constrained_layout=True)
    _show_map(ax, fig, image, detector, title=title if note is None else f"{title}\n{note}", units=units,
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
    ax.set_xlabel("column x [pixel]")
    ax.set_ylabel("row y [pixel]")
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, shrink=0.85).set_label(units)


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
    mean (rad/pixel); B(t) and A(t) (adu); convergence (offset change per pass).
    With a flat, a row for the gauge diagnostic: the flat gauge's offsets
    minus the PRNU-free gauge's (1e-3 pixel), and the rms of that difference
    against its noise floor and the offsets' photon floor. With spherical
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
    for name, colour in (("kx_frame", "C0"), ("ky_frame", "C1")):
        values = ds[name].values
        ax.plot(frame, values - values.mean(), lw=0.4, color=colour,
                label=f"{name[:2]}: mean {values.mean():.6f}, rms {values.std():.1e}")
    ax.set_xlabel("frame")
    ax.set_ylabel("K(t) - mean [rad/pixel]")
    ax.set_title("wavevector fitted per frame (pass 1)", fontsize=9)
    ax.legend(fontsize=8)
    ax = axes[1, 0]
    ax.plot(frame, ds["level"].values, lw=0.4, label="B(t), mean level")
    ax.plot(frame, ds["amplitude"].values, lw=0.4, label="A(t), amplitude")
    ax.set_xlabel("frame")
    ax.set_ylabel("adu")
    ax.set_title("fringe level and amplitude", fontsize=9)
    ax.legend(fontsize=8)
    ax = axes[1, 1]
    iteration = ds["iteration"].values
    ax.semilogy(iteration, ds["max_change"].values, "o-", label="largest change")
    ax.semilogy(iteration, ds["rms_change"].values, "s-", label="rms change")
    ax.set_xlabel("pass")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_xlim(1.5, iteration.max() + 0.5)
    ax.set_ylabel("offset change from previous pass [pixel]")
    ax.set_title(f"convergence: {iteration.max()} passes", fontsize=9)
    ax.legend(fontsize=8)
    row = 2
    if gauges:
        difference = offsets - ds["projected_offset_prnu_free_gauge"].values
        _show_map(axes[row, 0], fig, difference, detector, scale=1e3, symmetric=True, units="offset [1e-3 pixel]",
                  title="flat gauge minus PRNU-free gauge")
        ax = axes[row, 1]
        bars = {"gauge difference": float(ds["gauge_difference_rms"])}
        if "gauge_difference_floor" in ds:
            bars["its noise floor"] = float(ds["gauge_difference_floor"])
        bars["offsets' photon floor"] = float(ds["photon_noise_floor_rms"])
        for i, ((name, value), colour) in enumerate(zip(bars.items(), ("C3", "C0", "0.5"))):
            ax.semilogy([i], [value], "o", ms=9, color=colour)
            ax.annotate(f"{value:.1e}", (i, value), textcoords="offset points", xytext=(10, 0), va="center",
                        fontsize=8)
        ax.set_xticks(range(len(bars)), list(bars))
        ax.set_xlim(-0.5, len(bars) - 0.3)
        ax.set_ylabel("rms [pixel]")
        ax.set_title("do the two gauges agree?", fontsize=9)
        ax.set_ylim(min(bars.values()) / 2, max(bars.values()) * 3)  # room for the points' labels and the note
        ax.text(0.02, 0.95, "noise alone exceeds 3x its floor 1 time in 10, 5x 1 time in 26",
                transform=ax.transAxes, fontsize=7, color="0.3", va="top")
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


def allan_figure(ds, *, title):
    """The paper's Allan figure from an ``allan/<baseline>.nc`` dataset, log-log against frames per group.

    Sample pixels (thin green), their rms (black) and the rms of 10x10-pixel
    blocks (blue), each group fitted as a whole; the pixels' rms with groups
    as means of their batch fits, the paper's way (grey, with its limit); white
    noise of matched single-batch scatter (dotted); the photon-noise limits
    from the fits' own errors (dashed) and the paper's formula (dash-dotted).
    """
    fig, ax = plt.subplots(figsize=(8, 6), constrained_layout=True)
    n = ds["n_frames"].values
    ax.loglog(n, ds["sample_deviation"].values, color="tab:green", lw=0.5, alpha=0.5)
    ax.loglog([], [], color="tab:green", lw=0.5, label=f"{ds.sizes['sample']} individual pixels")
    block = int(ds.attrs.get("block_size", 10))
    curves = (("pixel", "deviation_mean", "white_deviation_mean", "black", f"pixels, rms (slope "
               f"{float(ds['slope']):.2f})"),
              ("block", "deviation_block_mean", "white_deviation_block_mean", "tab:blue",
               f"{block}x{block} blocks, rms"))
    if "deviation_mean_batch_means" in ds:
        ax.loglog(n, ds["deviation_mean_batch_means"].values, color="0.55", lw=1.6,
                  label=f"pixels, groups as means of batch fits (slope {float(ds['slope_batch_means']):.2f})")
        ax.loglog(n, ds["photon_limit_pixel_batch_means"].values, color="0.55", ls="--", lw=0.8,
                  label="its photon limit")
    for kind, measured, white, colour, label in curves:
        ax.loglog(n, ds[measured].values, color=colour, lw=2, label=label)
        ax.loglog(n, ds[white].values, color=colour, ls=":", lw=1.2,
                  label=f"white noise of the single-batch scatter, {kind}s")
        ax.loglog(n, ds[f"photon_limit_{kind}"].values, color=colour, ls="--", lw=1, label=f"photon limit, {kind}s")
        ax.loglog(n, ds[f"photon_limit_{kind}_paper"].values, color=colour, ls="-.", lw=0.8, alpha=0.7,
                  label=f"paper's photon limit, {kind}s")
    ax.set_xlabel("frames per group")
    ax.set_ylabel("deviation of projected offsets [pixel]")
    ax.set_title(f"{ds.sizes['batch']} batches of {ds.attrs['frames_per_batch']:.0f} frames (one fringe period) "
                 f"on average", fontsize=9)
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.legend(fontsize=7, ncol=2)
    fig.suptitle(title, fontsize=11)
    return fig


def centroids_figure(ds, *, title):
    """Star windows and the central star's path, from a ``centroids/<mode>.nc`` dataset.

    Top: each star's corrected mean window at the first position (adu).
    Bottom: the central star (nearest the stars' mean position) in x and y
    against the position index, with the precision of each position from its
    batches (error bars) and the Cramer-Rao bound (band); and its path, x
    against y.
    """
    n_star = ds.sizes["star"]
    fig = plt.figure(figsize=(max(10, 2.4 * n_star), 8), constrained_layout=True)
    grid = fig.add_gridspec(2, max(n_star, 3))
    x0, y0 = ds["x"].values[0], ds["y"].values[0]
    central = int(np.nanargmin(np.hypot(x0 - np.nanmean(x0), y0 - np.nanmean(y0))))
    for s in range(n_star):
        ax = fig.add_subplot(grid[0, s])
        image = ax.imshow(ds["window"].values[s], origin="lower", cmap="magma")
        fig.colorbar(image, ax=ax, shrink=0.7, label="adu")
        ax.set_title(f"star {s}" + (" (central)" if s == central else "") + f"\nx {x0[s]:.3f}, y {y0[s]:.3f}",
                     fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    position = ds["position"].values
    half = max(n_star, 3) // 2
    ax = fig.add_subplot(grid[1, :half])
    for axis, colour in (("x", "C0"), ("y", "C1")):
        values = ds[axis].values[:, central]
        offset = np.nanmean(values)
        ax.errorbar(position, values - offset, yerr=ds[f"precision_{axis}"].values[:, central], fmt="o-",
                    color=colour, ms=3, lw=0.8, capsize=2, label=f"{axis} - {offset:.3f} (batch precision)")
        limit = ds[f"photon_limit_{axis}"].values[:, central]
        ax.fill_between(position, values - offset - limit, values - offset + limit, color=colour, alpha=0.15)
    ax.set_xlabel("position")
    ax.set_ylabel("central star [pixel]")
    ax.set_title("central star over the positions (bands: Cramer-Rao bound)", fontsize=9)
    ax.legend(fontsize=8)
    ax = fig.add_subplot(grid[1, half:])
    ax.plot(ds["x"].values[:, central], ds["y"].values[:, central], "o-", ms=3, lw=0.8)
    ax.set_xlabel("x [pixel]")
    ax.set_ylabel("y [pixel]")
    ax.set_title("stage path seen by the central star", fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    fig.suptitle(f"{title} ({ds.attrs.get('method', '')})", fontsize=11)
    return fig


def procrustes_figure(ds, *, title="Procrustes residuals"):
    """Residuals of every star (x plain, y dotted) against the position, one panel per mode (pixel)."""
    modes = list(ds["mode"].values)
    fig, axes = plt.subplots(len(modes), 1, figsize=(9, 2.6 * len(modes)), sharex=True, squeeze=False,
                             constrained_layout=True)
    position = ds["position"].values
    for ax, mode in zip(axes[:, 0], modes):
        residual = ds["residual"].sel(mode=mode).values
        for s in range(residual.shape[1]):
            colour = "black" if s == 0 else f"C{s}"
            ax.plot(position, residual[:, s, 0], color=colour, lw=0.9, label=f"star {s}")
            ax.plot(position, residual[:, s, 1], color=colour, lw=0.9, ls=":")
        accuracy = float(ds["accuracy"].sel(mode=mode))
        for sign in (-1, 1):
            ax.axhline(sign * accuracy, color="grey", ls="--", lw=0.7)
        ax.set_ylabel("residual [pixel]")
        ax.set_title(f"{mode}: corrected accuracy {accuracy:.2e} pixel (dashed); x plain, y dotted", fontsize=9)
    axes[0, 0].legend(fontsize=7, ncol=5)
    axes[-1, 0].set_xlabel("position")
    fig.suptitle(title, fontsize=11)
    return fig


def barycentre_figure(ds, *, title="Barycentre residuals"):
    """The paper's barycentre-residual figures, one row per mode: against the position (x plain,
    y dotted; the positions used for the accuracies between dotted lines), and x against y."""
    modes = list(ds["mode"].values)
    fig, axes = plt.subplots(len(modes), 2, figsize=(12, 2.8 * len(modes)), squeeze=False, constrained_layout=True,
                             gridspec_kw={"width_ratios": [2, 1]})
    position = ds["all_position"].values
    used = ds["position"].values
    for row, mode in zip(axes, modes):
        residual = ds["barycentre_residual"].sel(mode=mode).values
        for s in range(residual.shape[1]):
            colour = "black" if s == 0 else f"C{s}"
            row[0].plot(position, residual[:, s, 0], color=colour, lw=0.9, label=f"star {s}")
            row[0].plot(position, residual[:, s, 1], color=colour, lw=0.9, ls=":")
            row[1].plot(residual[:, s, 0], residual[:, s, 1], color=colour, lw=0.6, marker=".", ms=3)
        for edge in (used.min(), used.max()):
            row[0].axvline(edge, color="grey", ls=":", lw=0.8)
        row[0].set_ylabel("residual [pixel]")
        row[0].set_title(f"{mode}: x plain, y dotted; positions {used.min()}-{used.max()} used", fontsize=9)
        row[1].set_xlabel("x residual [pixel]")
        row[1].set_ylabel("y residual [pixel]")
        row[1].set_aspect("equal", adjustable="datalim")
    axes[0, 0].legend(fontsize=7, ncol=5)
    axes[-1, 0].set_xlabel("position")
    fig.suptitle(title, fontsize=11)
    return fig


def save(fig, png, pdf=None):
    """Write a figure as PNG (150 dpi) and, optionally, PDF; then close it."""
    for path in (png, pdf):
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            fig.savefig(path, dpi=150)
    plt.close(fig)
