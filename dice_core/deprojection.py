"""Deprojection of offsets measured along two wavevectors into x and y offsets (paper, appendix A).

A baseline measures, for each pixel, the projection p = delta . k_hat of the
pixel offset delta = (dx, dy) on its unit wavevector k_hat. Two baselines of
non-colinear wavevectors give two such lines, and delta is their
intersection: the solution of

.. math:: \\begin{pmatrix} k_{x,1} & k_{y,1} \\\\ k_{x,2} & k_{y,2} \\end{pmatrix}
          \\begin{pmatrix} dx \\\\ dy \\end{pmatrix} = \\begin{pmatrix} p_1 \\\\ p_2 \\end{pmatrix},

which is the paper's closed form written as a 2x2 solve. Summing the two
projections (the paper's point F) is right only for orthogonal wavevectors.

Erratum: the paper gives y as "analog (indexes 1 and 2 are switched)" to x;
switching the indexes of its x formula describes the same intersection and
returns x again. The y used here eliminates x from the same two line
equations; ``tests/test_deprojection.py`` checks both against known offsets.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

__all__ = ["deproject", "deproject_floor", "pair_difference", "offsets_dataset", "MIN_SINE"]

#: Smallest |sin| of the angle between the two wavevectors accepted; below it the
#: intersection is ill-conditioned (errors grow as 1 / sin).
MIN_SINE = 0.2


def deproject(p1, k1, p2, k2, *, min_sine: float = MIN_SINE, label: str = "pair"):
    """x and y offsets from two projected offset maps.

    Parameters
    ----------
    p1, p2 : ndarray
        Offsets projected on the wavevectors, pixel (any shape, the same).
    k1, k2 : (float, float)
        The wavevectors (kx, ky), rad/pixel (only their directions matter).
    min_sine : float
        Refuse wavevectors closer than asin(min_sine) to colinear.
    label : str
        Names the pair in errors.

    Returns
    -------
    dx, dy : ndarray
        Offsets along x (columns) and y (rows), pixel.

    Raises
    ------
    ValueError
        Colinear (or nearly colinear) wavevectors.
    """
    n1 = np.asarray(k1, float) / np.hypot(*k1)
    n2 = np.asarray(k2, float) / np.hypot(*k2)
    sine = n1[0] * n2[1] - n1[1] * n2[0]
    if abs(sine) < min_sine:
        angle = np.degrees(np.arccos(np.clip(abs(n1 @ n2), 0, 1)))
        raise ValueError(f"{label}: wavevectors {tuple(k1)} and {tuple(k2)} are {angle:.1f} degrees from colinear; "
                         f"a pair needs at least {np.degrees(np.arcsin(min_sine)):.0f} degrees")
    p1, p2 = np.asarray(p1, float), np.asarray(p2, float)
    # inverse of [[n1x, n1y], [n2x, n2y]]
    dx = (n2[1] * p1 - n1[1] * p2) / sine
    dy = (-n2[0] * p1 + n1[0] * p2) / sine
    return dx, dy


def pair_difference(dx_a, dy_a, dx_b, dy_b):
    """Differences between two pairs' offset maps and their standard deviations (NaN ignored).

    Returns
    -------
    ddx, ddy : ndarray
        dx_b - dx_a and dy_b - dy_a, pixel.
    std_dx, std_dy : float
        Their standard deviations over the finite pixels, pixel.
    """
    ddx, ddy = np.asarray(dx_b) - np.asarray(dx_a), np.asarray(dy_b) - np.asarray(dy_a)
    return ddx, ddy, float(np.nanstd(ddx)), float(np.nanstd(ddy))


def deproject_floor(s1, k1, s2, k2):
    """1-sigma errors of dx and dy from independent errors s1, s2 (pixel) of the two projections."""
    n1 = np.asarray(k1, float) / np.hypot(*k1)
    n2 = np.asarray(k2, float) / np.hypot(*k2)
    sine = n1[0] * n2[1] - n1[1] * n2[0]
    sdx = np.sqrt((n2[1] * s1) ** 2 + (n1[1] * s2) ** 2) / abs(sine)
    sdy = np.sqrt((n2[0] * s1) ** 2 + (n1[0] * s2) ** 2) / abs(sine)
    return sdx, sdy


def offsets_dataset(first, second, *, label: str = "pair"):
    """The ``calibration/offsets_<pair>.nc`` product from two ``metrology/<baseline>.nc`` datasets.

    ``label`` names the pair in errors (colinear wavevectors).
    """
    k1 = (float(first["kx"]), float(first["ky"]))
    k2 = (float(second["kx"]), float(second["ky"]))
    dx, dy = deproject(first["projected_offset"].values, k1, second["projected_offset"].values, k2, label=label)
    fdx, fdy = deproject_floor(first["photon_noise_floor"].values, k1, second["photon_noise_floor"].values, k2)
    rc = ("row", "col")
    return xr.Dataset(
        {
            "dx": (rc, dx, {"units": "pixel", "long_name": "pixel offset along x (columns)"}),
            "dy": (rc, dy, {"units": "pixel", "long_name": "pixel offset along y (rows)"}),
            "dx_photon_noise_floor": (rc, fdx, {"units": "pixel", "long_name": "1-sigma photon-noise error of dx"}),
            "dy_photon_noise_floor": (rc, fdy, {"units": "pixel", "long_name": "1-sigma photon-noise error of dy"}),
            "dx_rms": ((), float(np.nanstd(dx)), {"units": "pixel", "long_name": "rms of dx"}),
            "dy_rms": ((), float(np.nanstd(dy)), {"units": "pixel", "long_name": "rms of dy"}),
        },
        coords={"row": first["row"].values, "col": first["col"].values},
    )
