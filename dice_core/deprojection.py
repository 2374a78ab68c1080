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

Spherical waves. Each pixel then has its own wavevector per baseline (the
gradient of the two-source phase, ``kx_local``, ``ky_local`` of the metrology
product), and the 2x2 solve is made pixel by pixel with them. The affine part
of (dx, dy) and each baseline's unobservable modes, carried through the same
solve, are then removed from the offsets and the latter declared
(``unobservable_dx``, ``unobservable_dy``).
"""

from __future__ import annotations

import json
import logging

import numpy as np

from dice_core import lazy, stray_light
from dice_core.geometry import UNOBSERVABLE_MODE, affine_basis, orthonormal_modes, remove_modes

xr = lazy.module("xarray")

__all__ = ["deproject", "deproject_floor", "pair_difference", "offsets_dataset", "difference_dataset", "MIN_SINE",
           "DeprojectionError", "without_stray_light"]

#: Smallest |sin| of the angle between the two wavevectors accepted; below it the
#: intersection is ill-conditioned (errors grow as 1 / sin).
MIN_SINE = 0.2


class DeprojectionError(ValueError):
    """Two baselines whose fringes are too close to parallel to give x and y offsets."""


def deproject(p1, k1, p2, k2, *, min_sine: float = MIN_SINE, label: str = "pair"):
    """x and y offsets from two projected offset maps.

    Parameters
    ----------
    p1, p2 : ndarray
        Offsets projected on the wavevectors, pixel (any shape, the same).
    k1, k2 : (float, float) or (ndarray, ndarray)
        The wavevectors (kx, ky), rad/pixel (only their directions matter):
        one for all pixels, or one per pixel (arrays of the shape of p1).
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
    DeprojectionError
        Colinear (or nearly colinear) wavevectors.
    """
    n1 = np.asarray(k1, float) / np.hypot(*k1)
    n2 = np.asarray(k2, float) / np.hypot(*k2)
    sine = n1[0] * n2[1] - n1[1] * n2[0]
    if np.nanmin(np.abs(sine)) < min_sine:
        cosine = np.nanmax(np.abs(n1[0] * n2[0] + n1[1] * n2[1]))
        angle = np.degrees(np.arccos(np.clip(cosine, 0, 1)))
        where = "" if np.ndim(sine) == 0 else " at some pixels"
        shown = "" if np.ndim(sine) else " ({:.4g}, {:.4g}) and ({:.4g}, {:.4g}) rad/pixel".format(*k1, *k2)
        raise DeprojectionError(f"{label}: wavevectors{shown} are {angle:.1f} degrees from colinear{where}; "
                                f"a pair needs at least {np.degrees(np.arcsin(min_sine)):.0f} degrees to "
                                "separate x from y")
    p1, p2 = np.asarray(p1, float), np.asarray(p2, float)
    # inverse of [[n1x, n1y], [n2x, n2y]]
    dx = (n2[1] * p1 - n1[1] * p2) / sine
    dy = (-n2[0] * p1 + n1[0] * p2) / sine
    return dx, dy


def pair_difference(dx_a, dy_a, dx_b, dy_b, *, modes=()):
    """Differences between two pairs' offset maps and their standard deviations (NaN ignored).

    ``modes`` lists (mode_dx, mode_dy) arrays (mode, row, col), the pairs'
    unobservable modes (spherical waves): each pair's offsets are orthogonal
    to its own modes only, so the difference is taken orthogonal to all of
    them and to the affine part.

    Returns
    -------
    ddx, ddy : ndarray
        dx_b - dx_a and dy_b - dy_a, pixel.
    std_dx, std_dy : float
        Their standard deviations over the finite pixels, pixel.
    """
    ddx, ddy = np.asarray(dx_b) - np.asarray(dx_a), np.asarray(dy_b) - np.asarray(dy_a)
    if len(modes):
        ddx, ddy = _orthogonal(ddx, ddy, np.concatenate([mode_dx for mode_dx, _ in modes]),
                               np.concatenate([mode_dy for _, mode_dy in modes]))
    return ddx, ddy, float(np.nanstd(ddx)), float(np.nanstd(ddy))


def _orthogonal(dx, dy, mode_dx, mode_dy):
    """dx, dy (row, col) minus their least-squares projection on the affine part of (dx, dy) and on the
    modes (mode, row, col), over the pixels where both are finite (NaN elsewhere)."""
    good = np.isfinite(dx) & np.isfinite(dy)
    rows, cols = np.nonzero(good)
    basis = np.vstack([_affine_fields(rows, cols), np.concatenate([mode_dx[:, good], mode_dy[:, good]], axis=1)])
    values = remove_modes(np.concatenate([dx[good], dy[good]]), basis)
    out_dx, out_dy = np.full(dx.shape, np.nan), np.full(dy.shape, np.nan)
    out_dx[good], out_dy[good] = values[:rows.size], values[rows.size:]
    return out_dx, out_dy


def _affine_fields(rows, cols):
    """The six affine (dx, dy) fields at pixels rows, cols, each as dx values then dy values: (6, 2 pixel)."""
    basis, zeros = affine_basis(cols, rows), np.zeros((3, rows.size))
    return np.vstack([np.hstack([basis, zeros]), np.hstack([zeros, basis])])


def deproject_floor(s1, k1, s2, k2):
    """1-sigma errors of dx and dy from independent errors s1, s2 (pixel) of the two projections."""
    n1 = np.asarray(k1, float) / np.hypot(*k1)
    n2 = np.asarray(k2, float) / np.hypot(*k2)
    sine = n1[0] * n2[1] - n1[1] * n2[0]
    sdx = np.sqrt((n2[1] * s1) ** 2 + (n1[1] * s2) ** 2) / abs(sine)
    sdy = np.sqrt((n2[0] * s1) ** 2 + (n1[0] * s2) ** 2) / abs(sine)
    return sdx, sdy


def _wavevector(metrology):
    """A metrology product's wavevector: per pixel (spherical waves) or its mean (plane waves), rad/pixel."""
    if "kx_local" in metrology:
        return metrology["kx_local"].values, metrology["ky_local"].values
    return float(metrology["kx"]), float(metrology["ky"])


def _without_unobservable(dx, dy, first, second, k1, k2, label):
    """dx, dy with their affine part and the baselines' unobservable modes removed; the modes (mode, row, col) x 2.

    Each baseline's modes (``unobservable_offset``, along its local wavevector)
    become (dx, dy) fields through the same per-pixel solve, with the other
    baseline's projection zero. They are orthonormalised against the affine
    part of (dx, dy) (1, x, y in each) under the mean over the finite pixels
    of both components together, so that each returned mode has unit rms over
    the dx and dy values.
    """
    good = np.isfinite(dx) & np.isfinite(dy)
    rows, cols = np.nonzero(good)
    affine = _affine_fields(rows, cols)
    fields = []
    for which, dataset in ((0, first), (1, second)):
        own = [dataset[name].values for name in ("unobservable_offset", "stray_mode") if name in dataset]
        for mode in (m for modes in own for m in modes):
            zeros = np.zeros_like(mode)
            mx, my = deproject(*(((mode, k1, zeros, k2)) if which == 0 else (zeros, k1, mode, k2)), label=label)
            fields.append(np.concatenate([mx[good], my[good]]))
    modes = orthonormal_modes(np.array(fields).reshape(len(fields), 2 * rows.size), against=affine)
    mode_dx, mode_dy = np.full((len(modes), *dx.shape), np.nan), np.full((len(modes), *dy.shape), np.nan)
    mode_dx[:, rows, cols], mode_dy[:, rows, cols] = modes[:, :rows.size], modes[:, rows.size:]
    # (the affine part removed is that of (dx, dy); each baseline removed the affine part of its projection,
    # whose image through the per-pixel solve differs from it by the variation of K, 1e-4 across the detector)
    return (*_orthogonal(dx, dy, mode_dx, mode_dy), mode_dx, mode_dy)


def without_stray_light(metrology, stray):
    """A ``metrology/<baseline>.nc`` dataset with the stray-light components of its ``stray_light`` product
    (:func:`dice_core.stray_light.stray_light_dataset`) taken out of its projected offsets, and what fitting
    them takes (``stray_mode``) declared beside its unobservable modes; the dataset itself if none was found."""
    if stray is None or int(stray["n_components"]) == 0:
        return metrology
    out = metrology.copy()
    component = np.nan_to_num(stray["offset_error"].values)
    out["projected_offset"] = (("row", "col"), metrology["projected_offset"].values - component,
                               metrology["projected_offset"].attrs)
    out["stray_mode"] = stray["stray_mode"]
    return out


def offsets_dataset(first, second, *, label: str = "pair", stray=(None, None)):
    """The ``calibration/offsets_<pair>.nc`` product from two ``metrology/<baseline>.nc`` datasets.

    With spherical waves (products holding ``kx_local``), the solve is made
    with each pixel's wavevectors, and the offsets are reported orthogonal to
    the affine part and to the unobservable modes, which the product holds as
    ``unobservable_dx``, ``unobservable_dy`` (mode, row, col). ``label`` names
    the pair in errors (colinear wavevectors). ``stray``: the two baselines'
    ``calibration/stray_light_<baseline>.nc`` datasets (or None) whose
    components are removed (:func:`without_stray_light`): what fitting them
    took joins the unobservable modes.
    """
    first, second = without_stray_light(first, stray[0]), without_stray_light(second, stray[1])
    k1, k2 = _wavevector(first), _wavevector(second)
    dx, dy = deproject(first["projected_offset"].values, k1, second["projected_offset"].values, k2, label=label)
    fdx, fdy = deproject_floor(first["photon_noise_floor"].values, k1, second["photon_noise_floor"].values, k2)
    rc = ("row", "col")
    modes = {}
    with_modes = np.ndim(k1[0]) or np.ndim(k2[0]) or "stray_mode" in first or "stray_mode" in second
    if with_modes:
        dx, dy, mode_dx, mode_dy = _without_unobservable(dx, dy, first, second, k1, k2, label)
    if modes_found := with_modes and len(mode_dx) > 0:  # none: absent (the contract)
        attrs = {"units": "1", "long_name": "unobservable offset mode beyond the affine part (unit rms over dx "
                                            "and dy together); dx, dy are orthogonal to every mode"}
        modes = {"unobservable_dx": (("mode", *rc), mode_dx, {**attrs, "long_name": attrs["long_name"] + ", x part"}),
                 "unobservable_dy": (("mode", *rc), mode_dy, {**attrs, "long_name": attrs["long_name"] + ", y part"})}
    # the fringes' own frequencies (K / 2 pi, 2K / 2 pi), which a spectrum of the pairs' difference leaves out
    harmonics = [list(map(float, f)) for d in (first, second) for f in stray_light.fringe_harmonics(
        (float(d["kx"]), float(d["ky"])))]
    product = xr.Dataset(
        {
            "dx": (rc, dx, {"units": "pixel", "long_name": "pixel offset along x (columns)"}),
            "dy": (rc, dy, {"units": "pixel", "long_name": "pixel offset along y (rows)"}),
            "dx_photon_noise_floor": (rc, fdx, {"units": "pixel", "long_name": "1-sigma photon-noise error of dx"}),
            "dy_photon_noise_floor": (rc, fdy, {"units": "pixel", "long_name": "1-sigma photon-noise error of dy"}),
            "dx_rms": ((), float(np.nanstd(dx)), {"units": "pixel", "long_name": "rms of dx"}),
            "dy_rms": ((), float(np.nanstd(dy)), {"units": "pixel", "long_name": "rms of dy"}),
            **modes,
        },
        coords={"row": first["row"].values, "col": first["col"].values,
                **({"mode": ("mode", np.arange(mode_dx.shape[0]), UNOBSERVABLE_MODE)} if modes_found else {})},
    )
    product.attrs["fringe_frequencies"] = json.dumps(harmonics)
    return product


def difference_dataset(reference, other, *, reference_pair: str, pair: str, spectrum: bool = False) -> xr.Dataset:
    """The ``calibration/offsets_difference_<pair>.nc`` product: ``other``'s offsets minus ``reference``'s.

    Both are ``calibration/offsets_<pair>.nc`` datasets (:func:`offsets_dataset`).
    With spherical waves (products holding ``unobservable_dx``), the
    difference is taken orthogonal to both pairs' unobservable modes and to
    the affine part (:func:`pair_difference`). Its photon-noise floor is each
    pixel's two floors added in quadrature, then the rms over pixels.

    Returns
    -------
    xarray.Dataset
        ``ddx``, ``ddy`` (row, col), their standard deviations ``ddx_std``,
        ``ddy_std`` and rms photon-noise floors ``ddx_photon_noise_floor``,
        ``ddy_photon_noise_floor``, all pixel; attributes ``reference_pair``
        and ``pair``. With ``spectrum``, each map's stray-light diagnosis
        (:func:`dice_core.stray_light.diagnose`): ``ddx_power``, ``ddy_power``
        (frequency_y, frequency_x) over their white levels, the components
        found in each (``ddx_component_*``...), their sums.
    """
    modes = [(p["unobservable_dx"].values, p["unobservable_dy"].values) for p in (reference, other)
             if "unobservable_dx" in p]
    ddx, ddy, sdx, sdy = pair_difference(reference["dx"].values, reference["dy"].values,
                                         other["dx"].values, other["dy"].values, modes=modes)
    floor_dx = np.hypot(reference["dx_photon_noise_floor"].values, other["dx_photon_noise_floor"].values)
    floor_dy = np.hypot(reference["dy_photon_noise_floor"].values, other["dy_photon_noise_floor"].values)
    rc = ("row", "col")
    product = xr.Dataset(
        {
            "ddx": (rc, ddx, {"units": "pixel", "long_name": f"dx({pair}) - dx({reference_pair})"}),
            "ddy": (rc, ddy, {"units": "pixel", "long_name": f"dy({pair}) - dy({reference_pair})"}),
            "ddx_std": ((), sdx, {"units": "pixel", "long_name": "standard deviation of ddx"}),
            "ddy_std": ((), sdy, {"units": "pixel", "long_name": "standard deviation of ddy"}),
            "ddx_photon_noise_floor": ((), float(np.sqrt(np.nanmean(floor_dx**2))),
                                       {"units": "pixel", "long_name": "rms photon-noise floor of ddx"}),
            "ddy_photon_noise_floor": ((), float(np.sqrt(np.nanmean(floor_dy**2))),
                                       {"units": "pixel", "long_name": "rms photon-noise floor of ddy"}),
        },
        coords={"row": reference["row"].values, "col": reference["col"].values},
    )
    product.attrs.update({"reference_pair": reference_pair, "pair": pair})
    if spectrum:  # the fringes' own frequencies of both pairs' baselines left out (offsets_dataset's attribute)
        exclude = [f for p in (reference, other) for f in json.loads(p.attrs.get("fringe_frequencies", "[]"))]
        product = _with_spectra(product, f"{pair} - {reference_pair}", exclude)
    return product


def _with_spectra(product, what, exclude):
    """The difference product with the stray-light diagnosis of its ddx and ddy maps, the frequencies
    ``exclude`` (cycles/pixel) left out."""
    variables = {}
    for name in ("ddx", "ddy"):
        diagnosis, rows, cols = stray_light.diagnose_map(product[name].values, exclude=exclude)
        variables.update(stray_light.diagnosis_variables(diagnosis, rows, cols, product[name].shape,
                                                         prefix=f"{name}_", modes=False))
        logging.getLogger(__name__).info("%s", stray_light.summary_line(diagnosis, f"{name} of {what}"))
    return product.assign(variables).assign_coords(
        frequency_x=("frequency_x", diagnosis.frequency_x, {"units": "1/pixel", "long_name": "spatial frequency"}),
        frequency_y=("frequency_y", diagnosis.frequency_y, {"units": "1/pixel", "long_name": "spatial frequency"}),
        axis=["x", "y"])
