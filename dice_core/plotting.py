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
import numpy as np  # noqa: E402

from dice_core.manifest import Detector  # noqa: E402

__all__ = ["map_figure", "save"]


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
    rows, cols = detector.science_rows, detector.science_cols
    shown = image[slice(*rows), slice(*cols)] * scale
    finite = shown[np.isfinite(shown)]
    if finite.size:
        lo, hi = np.percentile(finite, [clip_percentile, 100 - clip_percentile])
    else:
        lo, hi = 0.0, 1.0
    if symmetric:
        hi = max(abs(lo), abs(hi))
        lo = -hi
    fig, ax = plt.subplots(figsize=(6.0, 5.2), constrained_layout=True)
    # extent in pixel-centre coordinates: x = col, y = row, origin at the bottom like the paper's maps
    extent = (cols[0] - 0.5, cols[1] - 0.5, rows[0] - 0.5, rows[1] - 0.5)
    im = ax.imshow(shown, origin="lower", extent=extent, vmin=lo, vmax=hi, interpolation="nearest",
                   cmap=cmap or ("RdBu_r" if symmetric else "viridis"))
    ax.set_xlabel("column x [pixel]")
    ax.set_ylabel("row y [pixel]")
    ax.set_title(title if note is None else f"{title}\n{note}", fontsize=10)
    bar = fig.colorbar(im, ax=ax, shrink=0.9)
    bar.set_label(units)
    return fig


def save(fig, png, pdf=None):
    """Write a figure as PNG (150 dpi) and, optionally, PDF; then close it."""
    for path in (png, pdf):
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            fig.savefig(path, dpi=150)
    plt.close(fig)
