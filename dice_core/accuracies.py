"""Differential astrometric accuracies: barycentre residuals, corrected accuracies with error bars, the tables.

Paper: sections "Differential astrometry dispersion metrics", "Pseudo stars
simulation results" and the experimental accuracy table. Units: pixel.

Configurations are arrays (position, star, 2) of (x, y) centroids.

- :func:`barycentre_residuals`: for each position, each star's (x, y) minus the
  barycentre of the others, minus its mean over positions.
- :func:`correction_factor`: the superimposition absorbs part of any random
  error (5 parameters per position fit 10 coordinates, and M is fitted too):
  by Monte Carlo on the actual geometry and number of positions, the ratio of
  an injected white jitter to the rms residual it leaves (about sqrt(2),
  1.4 and a little more, for 5 stars; see :func:`correction_factor`).
- :func:`accuracy`: each star's rms residual corrected by its own Monte
  Carlo factor, their rms, and its error bar by Monte Carlo with independent
  jitter per star.
- :func:`mode_accuracies` and :func:`accuracy_tables`: the accuracies of every
  calibration mode, centroid method and superimposition, over positions and
  groups of positions, as the workflow's table (:func:`latex_table`,
  :func:`accuracy_csv`) and residual products (:func:`residuals_dataset`).

The superimpositions themselves (Procrustes, projective, pose) and what they
absorb are :mod:`dice_core.superimposition`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dice_core import lazy
from dice_core.centroids import MODES, mode_needs
from dice_core.parallel import one_blas_thread
from dice_core.superimposition import (SUPERIMPOSITIONS, AstrometryError, PoseGeometry, check_configurations,
                                       pose_identifiability, superimpose, tangent_space, tip_tilt_removal)

xr = lazy.module("xarray")

__all__ = [
    "barycentre_residuals",
    "correction_factor",
    "star_factors",
    "Accuracy",
    "accuracy",
    "group_means",
    "select_positions",
    "mode_accuracies",
    "AccuracyTables",
    "accuracy_tables",
    "latex_table",
    "CSV_COLUMNS",
    "ACCURACY_UNIT",
    "accuracy_csv",
    "residuals_dataset",
    "REMOVAL_BOUND_LOW",
    "pose_removal",
    "removal_notes",
]


def barycentre_residuals(configurations) -> np.ndarray:
    """Each star's position minus the barycentre of the others, minus its mean over positions (position, star, 2)."""
    c = check_configurations(configurations)
    n = c.shape[1]
    others = (c.sum(axis=1, keepdims=True) - c) / (n - 1)
    distance = c - others
    return distance - distance.mean(axis=0)


def _residuals(basis, errors):
    """Residuals (trial, observation) of errors after the superimposition absorbs its part."""
    return errors - (errors @ basis) @ basis.T


def correction_factor(result, *, trials: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Ratio of a white jitter to the rms Procrustes residual it leaves, by Monte Carlo.

    For the actual geometry (``result``'s mean configuration, transforms and
    number of positions): each trial draws independent unit Gaussian errors
    on every coordinate and superimposes them (to first order, exact for
    errors this small against the star separations). Returns the mean over
    trials of jitter / rms residual, and its standard error. With S stars and
    N positions, 2SN coordinates lose 5N transform and 2S - 4 mean-shape
    degrees of freedom (4: the gauge): about sqrt(2SN / (2SN - 5N - 2S + 4)),
    sqrt(2) = 1.41 for 5 stars and many positions (the paper's 1.4).
    """
    ratios = 1.0 / np.sqrt(np.mean(_white_residuals(result, trials, seed) ** 2, axis=(1, 2, 3)))
    return float(ratios.mean()), float(ratios.std(ddof=1) / np.sqrt(trials))


def _factors(white):
    """Per-star and global correction factors from white-jitter residuals (trial, position, star, 2)."""
    # per star: the jitter over the mean rms residual (unbiased for the accuracy, which multiplies
    # a measured rms); globally, as correction_factor: the mean of jitter / rms over trials
    per_star = 1.0 / np.sqrt(np.mean(white**2, axis=(1, 3))).mean(axis=0)
    return per_star, float((1.0 / np.sqrt(np.mean(white**2, axis=(1, 2, 3)))).mean())


def _white_residuals(result, trials: int, seed: int, basis=None) -> np.ndarray:
    """Residuals (trial, position, star, 2) that the superimposition leaves of unit white errors."""
    basis = tangent_space(result) if basis is None else basis
    rng = np.random.default_rng(seed)
    errors = rng.standard_normal((trials, basis.shape[0]))
    return _residuals(basis, errors).reshape(trials, *result.residuals.shape)


def star_factors(result, *, trials: int = 2000, seed: int = 0) -> np.ndarray:
    """The correction factor of each star (star,): white jitter over the mean rms of that star's residuals.

    The superimposition does not absorb all stars alike: the transforms have
    little leverage on a star near the centre of the pattern (factor about
    1.1 for the central star of 5) and much on the corners (about 1.6).
    Correcting each star by its own factor keeps the accuracy unbiased when
    the stars' errors differ, where one global factor would not (6% low for
    the spread of :func:`accuracy`'s test).
    """
    return _factors(_white_residuals(result, trials, seed))[0]


@dataclass
class Accuracy:
    """A corrected Procrustes accuracy (pixel) with its Monte Carlo error bar (pixel).

    ``factor`` is the global correction factor (rms residual to accuracy, for
    equal errors); ``star_accuracy`` each star's own corrected accuracy;
    ``result`` the superimposition's (:class:`~dice_core.superimposition.ProcrustesResult`,
    :class:`~dice_core.superimposition.ProjectiveResult` or
    :class:`~dice_core.superimposition.PoseResult`).
    """

    accuracy: float
    error: float
    rms_residual: float
    factor: float
    star_accuracy: np.ndarray
    result: object


def _corrected(residuals, factors):
    """Accuracy from residuals (..., position, star, 2): each star's rms times its factor, rms over stars."""
    per_star = factors * np.sqrt(np.mean(residuals**2, axis=(-3, -1)))
    return np.sqrt(np.mean(per_star**2, axis=-1)), per_star


@one_blas_thread  # SVDs of a few hundred columns: 10x slower with the default threads on busy cores
def accuracy(configurations, *, model: str = "procrustes", geometry=None, trials: int = 2000,
             seed: int = 0) -> Accuracy:
    """Differential astrometric accuracy of the configurations: corrected rms residual of a superimposition.

    ``model`` is one of :data:`~dice_core.superimposition.SUPERIMPOSITIONS` (``geometry`` labels the
    pose model's parameters); each has its own Monte Carlo deflation factors,
    from its own tangent space at the solution.

    Each star's rms residual is multiplied by its Monte Carlo correction
    factor for this geometry and number of positions (:func:`star_factors`),
    and the accuracy is the rms over stars. The error bar is the scatter of
    the same estimate over Monte Carlo data sets with independent jitter per
    star, each star's jitter its own corrected accuracy (as in the paper).
    """
    c = check_configurations(configurations)
    result = superimpose(c, model, geometry=geometry)
    basis = tangent_space(result)  # one SVD for the factors and the error bar
    factors, global_factor = _factors(_white_residuals(result, trials, seed, basis))
    value, per_star = _corrected(result.residuals, factors)
    rng = np.random.default_rng(seed + 1)
    jitter = rng.standard_normal((trials, *c.shape)) * per_star[None, None, :, None]
    estimates, _ = _corrected(_residuals(basis, jitter.reshape(trials, -1)).reshape(trials, *c.shape), factors)
    return Accuracy(float(value), float(np.std(estimates, ddof=1)), result.rms, global_factor, per_star, result)


def group_means(configurations, n_groups: int) -> np.ndarray:
    """Mean configuration of each of ``n_groups`` groups of contiguous positions (equal sizes, the rest left out).

    Raises
    ------
    AstrometryError
        Fewer positions than groups.
    """
    c = np.asarray(configurations, float)
    if c.shape[0] < n_groups:
        raise AstrometryError(f"{c.shape[0]} position(s) for {n_groups} groups")
    size = c.shape[0] // n_groups
    return c[:size * n_groups].reshape(n_groups, size, *c.shape[1:]).mean(axis=1)


def select_positions(ds, positions=None):
    """The (position, star, 2) configurations of a centroids dataset, over an inclusive index range.

    Raises
    ------
    AstrometryError
        A range that selects no position, or an unmeasured (NaN) star in it.
    """
    if positions is not None:
        first, last = positions
        ds = ds.sel(position=(ds["position"] >= first) & (ds["position"] <= last))
        if ds.sizes["position"] == 0:
            raise AstrometryError(f"no position with an index in [{first}, {last}]")
    return np.stack([ds["x"].values, ds["y"].values], axis=-1), ds["position"].values


#: The calibration modes of the paper's table (its cells: flat or not, metrology or not).
# the paper's table: the modes that apply the flat, the pixel offsets, both or neither, and nothing else
_PAPER_MODES = tuple(name for name, mode in MODES.items() if mode.needs <= {"flat", "offsets"})


def mode_accuracies(datasets: dict, *, positions=None, groups: int = 3, trials: int = 2000, seed: int = 0,
                    model: str = "procrustes", geometry=None):
    """Accuracies of every calibration mode, over positions (p) and over groups of positions (g).

    Parameters
    ----------
    datasets : dict
        Mode name -> its ``centroids/<mode>.nc`` dataset.
    positions : (int, int), optional
        Inclusive range of position indices.
    groups : int
        Contiguous groups of positions for (g).
    model : str
        The superimposition (:data:`~dice_core.superimposition.SUPERIMPOSITIONS`).
    geometry : PoseGeometry, optional
        For the pose model; its ``centre`` None: the stars' mean position.

    Returns
    -------
    rows : list of dict
        One per mode and grouping: mode, method, flat, metrology, grouping
        ("position" or "group"), n (positions or groups), accuracy and error
        (pixel), rms_residual (pixel), factor, superimposition.
    residuals : dict
        Mode -> (position indices, residuals (position, star, 2)) over positions.
    """
    rows, residuals, _ = _mode_accuracies(datasets, positions=positions, groups=groups, trials=trials, seed=seed,
                                          model=model, geometry=geometry)
    return rows, residuals


def _mode_accuracies(datasets, *, positions, groups, trials, seed, model, geometry):
    """:func:`mode_accuracies`, and each mode's :class:`Accuracy` over positions (mode -> Accuracy)."""
    rows, residuals, results = [], {}, {}
    for mode, ds in datasets.items():
        configurations, index = select_positions(ds, positions)
        mode_geometry = geometry
        if model == "pose":
            mode_geometry = geometry or PoseGeometry(centre=None)
            if mode_geometry.centre is None:
                mode_geometry = PoseGeometry(mode_geometry.distance, mode_geometry.off_axis,
                                             tuple(np.nanmean(configurations, axis=(0, 1))))
        for grouping, data in (("position", configurations), ("group", group_means(configurations, groups))):
            result = accuracy(data, model=model, geometry=mode_geometry, trials=trials, seed=seed)
            needs = mode_needs(mode)  # what the mode corrects with: one mapping, in dice_core.centroids
            rows.append({"mode": mode, "method": ds.attrs.get("method", ""), "flat": "flat" in needs,
                         "metrology": "offsets" in needs, "grouping": grouping, "n": data.shape[0],
                         "accuracy": result.accuracy, "error": result.error, "rms_residual": result.rms_residual,
                         "factor": result.factor, "superimposition": model})
            if grouping == "position":
                residuals[mode] = (index, result.result.residuals)
                results[mode] = result
    return rows, residuals, results


@dataclass
class AccuracyTables:
    """What :func:`accuracy_tables` gathers: the table's rows, its LaTeX and each model's residual product.

    ``residuals`` maps each superimposition to the product of the first
    method's residuals (:func:`residuals_dataset`); ``reports`` each pose
    identifiability summary (``"<method> <mode>"`` -> text).
    """

    rows: list
    latex: str
    residuals: dict
    reports: dict


def accuracy_tables(datasets, methods, *, models=("procrustes",), positions=None, groups: int = 3,
                    trials: int = 2000, geometry=None) -> AccuracyTables:
    """Every method's, mode's and superimposition's accuracies: the accuracy table of the workflow.

    Parameters
    ----------
    datasets : iterable of xarray.Dataset
        Centroid products, each with its ``method`` and ``mode`` attributes.
    methods : list of str
        The configured methods, in order; those without a product are left
        out, and the first one present gives the residual products.
    models : sequence of str
        Superimpositions (:data:`~dice_core.superimposition.SUPERIMPOSITIONS`), each with its own rows.
    geometry : PoseGeometry, optional
        The pose model's nominal bench.

    Raises
    ------
    AstrometryError
        No product of any configured method, an unknown model.
    """
    by_method = {}
    for ds in datasets:
        by_method.setdefault(ds.attrs["method"], {})[ds.attrs["mode"]] = ds
    present = [m for m in methods if m in by_method]
    if not present:
        raise AstrometryError(f"no centroid product of the configured methods {list(methods)} "
                              f"(products of {sorted(by_method)})")
    for model in models:
        if model not in SUPERIMPOSITIONS:
            raise AstrometryError(f"unknown superimposition {model!r}: one of {', '.join(SUPERIMPOSITIONS)}")
    rows, tables, products, reports = [], [], {}, {}
    for method in present:
        procrustes = {}
        for model in models:
            model_rows, model_residuals, results = _mode_accuracies(
                by_method[method], positions=positions, groups=groups, trials=trials, seed=0, model=model,
                geometry=geometry)
            rows += model_rows
            identifiability, removals = {}, {}
            if model == "procrustes":  # the first (configured_superimpositions)
                procrustes = results
            if model == "pose":
                for mode, result in results.items():
                    identifiability[mode] = pose_identifiability(result.result, sigma=result.accuracy)
                    reports[f"{method} {mode}"] = identifiability[mode].summary()
                    if mode in procrustes:
                        removals[mode] = pose_removal(procrustes[mode], result)
            tables.append(f"% centroid method: {method}, superimposition: {model}\n"
                          + latex_table(model_rows, notes=removal_notes(removals)))
            if method == present[0]:
                products[model] = residuals_dataset(by_method[method], model_rows, residuals=model_residuals,
                                                    identifiability=identifiability, removals=removals)
    return AccuracyTables(rows, "\n".join(tables), products, reports)


#: Below this noise-limited bound the tables say that the data cannot show the pose's gain over Procrustes.
REMOVAL_BOUND_LOW = 0.5


def pose_removal(procrustes: Accuracy, pose: Accuracy) -> dict:
    """What the pose removes of Procrustes's tip-tilt excess on one data set, beside what the data allow.

    From the pose's fitted tip and tilt and its Fisher information
    (:func:`dice_core.superimposition.tip_tilt_removal`): ``excess``, the
    tip-tilt excess Procrustes's accuracy carries (pixel, in quadrature);
    ``bound``, the noise-limited share of it the data allow to remove;
    ``snr``; and ``measured``, the share the pose's accuracy removes,
    (accuracy_procrustes^2 - accuracy_pose^2) / excess^2 (NaN without an
    excess). Without an untilted twin, the removal with the true tip and
    tilt given is a simulation's only (:func:`dice_core.studies.tip_tilt_removals`).
    """
    found = tip_tilt_removal(pose.result, procrustes.result, sigma=pose.accuracy, factor=procrustes.factor)
    measured = (procrustes.accuracy**2 - pose.accuracy**2) / found.excess**2 if found.excess > 0 else float("nan")
    return {"excess": found.excess, "bound": found.bound, "snr": found.snr, "measured": float(measured)}


def removal_notes(removals: dict) -> list:
    """One line per mode of :func:`pose_removal`'s numbers, for the table's notes (none without)."""
    notes = []
    for mode, r in removals.items():
        line = (f"{mode}: Procrustes's tip-tilt excess {r['excess']:.1e} pixel, removed {100 * r['measured']:.0f}% "
                f"(noise-limited bound {100 * r['bound']:.0f}%, the tip-tilt at {r['snr']:.1f} sigma)")
        if r["bound"] < REMOVAL_BOUND_LOW:
            line += "; no gain over Procrustes the data can show"
        notes.append(line)
    return notes


#: The macros :func:`latex_table` uses beyond LaTeX's own, each provided (not redefined) at the table's top.
LATEX_MACROS = (r"\providecommand{\e}[1]{\times10^{#1}}",
                r"\providecommand{\specialcell}[1]{\begin{tabular}[c]{@{}c@{}}#1\end{tabular}}")


def _latex_value(value, error):
    exponent = int(np.floor(np.log10(abs(value)))) if value else 0
    return rf"${value / 10**exponent:.2f}\pm{error / 10**exponent:.2f}\e{{{exponent}}}$"


def latex_table(rows, *, notes=()) -> str:
    """The accuracies laid out as the paper's table of calibrations: metrology in rows, flat in columns.

    Modes that add a calibration beyond the paper's two (``flat+metrology+width``) get a row of their own
    under the flat column, after the paper's rows. ``notes`` (lines of text) follow, each a row across the
    table's columns (the pose's tip-tilt removal: :func:`removal_notes`).
    """
    cell = {(r["metrology"], r["flat"], r["grouping"]): r for r in rows if r["mode"] in _PAPER_MODES}
    extra = {}
    for r in rows:
        if r["mode"] not in _PAPER_MODES:
            extra.setdefault(r["mode"], {})[r["grouping"]] = r
    lines = [r"% Accuracies (pixel) with different calibrations; (p) over positions, (g) over groups.",
             r"% \e{n} stands for x10^n and \specialcell makes a two-line cell, as in the paper; both defined here",
             r"% unless the document defines them (\providecommand), so that the file can be \input as it is.",
             *LATEX_MACROS, r"\begin{tabular}{lcc}", r"\hline", r" & No flat & Flat \\", r"\hline"]
    for metrology in (False, True):
        entries = []
        for flat in (False, True):
            parts = [f"({g[0]}) " + _latex_value(cell[metrology, flat, g]["accuracy"], cell[metrology, flat, g]["error"])
                     for g in ("position", "group") if (metrology, flat, g) in cell]
            entries.append(r"\specialcell{" + r"\\".join(parts) + "}" if parts else "--")
        lines.append(f"{'Metrology' if metrology else 'No metrology'} & {entries[0]} & {entries[1]} " + r"\\")
    for mode, by_grouping in extra.items():
        parts = [f"({g[0]}) " + _latex_value(by_grouping[g]["accuracy"], by_grouping[g]["error"])
                 for g in ("position", "group") if g in by_grouping]
        cells = ["--", r"\specialcell{" + r"\\".join(parts) + "}"]
        if not next(iter(by_grouping.values()))["flat"]:
            cells.reverse()
        label = {"flat+metrology+width": "Metrology + widths",
                 "flat+metrology+chromatic": "Metrology + chromatic"}.get(mode, mode.replace("_", r"\_"))
        lines.append(f"{label} & {cells[0]} & {cells[1]} " + r"\\")
    lines.append(r"\hline")
    lines += [r"\multicolumn{3}{l}{\footnotesize " + note.replace("%", r"\%") + r"} \\" for note in notes]
    lines += [r"\end{tabular}", ""]
    return "\n".join(lines)


#: Columns of ``tables/accuracy.csv``: the contract's first, then what makes each row traceable, then ``unit``,
#: the unit of the columns that have one (accuracy, error, rms_residual; n and factor are pure numbers), last so
#: that the columns before it stay where they were.
CSV_COLUMNS = ("flat", "metrology", "grouping", "accuracy", "error", "mode", "method", "n", "rms_residual", "factor",
               "superimposition", "unit")
#: The unit of the accuracy table's accuracy, error and rms_residual, in its column ``unit``.
ACCURACY_UNIT = "pixel"


def accuracy_csv(rows) -> str:
    """The rows of :func:`mode_accuracies` as CSV text (booleans as true/false, floats to 7 digits), with the
    unit (:data:`ACCURACY_UNIT`) of accuracy, error and rms_residual in the column ``unit``."""
    def text(value):
        if isinstance(value, (bool, np.bool_)):
            return str(bool(value)).lower()
        return f"{value:.6e}" if isinstance(value, float) else str(value)

    defaults = {"superimposition": "procrustes", "unit": ACCURACY_UNIT}
    return "\n".join([",".join(CSV_COLUMNS), *(",".join(text(row.get(c, defaults.get(c, ""))) for c in CSV_COLUMNS)
                                               for row in rows)]) + "\n"


def _complete_barycentre_residuals(configurations):
    """Barycentre residuals over the positions where every star was measured (NaN elsewhere)."""
    complete = np.isfinite(configurations).all(axis=(1, 2))
    out = np.full(configurations.shape, np.nan)
    if complete.sum() >= 2:
        out[complete] = barycentre_residuals(configurations[complete])
    return out


def residuals_dataset(datasets: dict, rows, *, residuals: dict, identifiability=None, removals=None) -> xr.Dataset:
    """A superimposition's residuals over the selected positions and barycentre residuals over all, per mode.

    ``datasets``, ``rows`` and ``residuals`` are one method's and one
    superimposition's: its centroid datasets by mode, and what
    :func:`mode_accuracies` returned for them.
    ``star_x`` and ``star_y`` (mode, star) are each star's mean centroid over
    the positions where it was measured: the pattern's layout, which the
    barycentre figure draws downscaled to the residuals. With
    ``identifiability`` (mode -> :class:`~dice_core.superimposition.PoseIdentifiability`), the fitted
    tip and tilt and their Cramer-Rao bounds where the data support them
    (NaN where not: no pose accuracy is claimed), and each mode's report in
    the attributes. With ``removals`` (mode -> :func:`pose_removal`), what
    the pose removes of Procrustes's tip-tilt excess and its noise-limited
    bound, per mode (NaN for a mode without).
    """
    modes = list(residuals)
    accuracy_p = {r["mode"]: r["accuracy"] for r in rows if r["grouping"] == "position"}
    configurations = [select_positions(datasets[m])[0] for m in modes]
    barycentre = [_complete_barycentre_residuals(c) for c in configurations]
    star_mean = np.stack([np.nanmean(c, axis=0) for c in configurations])  # (mode, star, 2)
    ds = xr.Dataset(
        {"residual": (("mode", "position", "star", "axis"), np.stack([residuals[m][1] for m in modes]),
                      {"units": "pixel", "long_name": "Procrustes residual of each star"}),
         "accuracy": (("mode",), [accuracy_p[m] for m in modes],
                      {"units": "pixel", "long_name": "corrected accuracy (p)"}),
         "barycentre_residual": (("mode", "all_position", "star", "axis"), np.stack(barycentre),
                                 {"units": "pixel", "long_name": "star minus the barycentre of the others, minus "
                                                                 "its mean over positions"}),
         "star_x": (("mode", "star"), star_mean[..., 0],
                    {"units": "pixel", "long_name": "mean centroid x of each star over the positions"}),
         "star_y": (("mode", "star"), star_mean[..., 1],
                    {"units": "pixel", "long_name": "mean centroid y of each star over the positions"})},
        coords={"mode": modes, "position": residuals[modes[0]][0],
                "all_position": datasets[modes[0]]["position"].values, "axis": ["x", "y"]})
    model = {r.get("superimposition", "procrustes") for r in rows}
    ds.attrs["superimposition"] = model.pop() if len(model) == 1 else ""
    method = {r["method"] for r in rows if "method" in r}  # the centroids' (one method's rows; none: unsaid)
    ds.attrs["centroid_method"] = method.pop() if len(method) == 1 else ""
    if identifiability:
        n_pos = ds.sizes["position"]
        for name, k, what in (("tip", 3, "detector tip (about x)"), ("tilt", 4, "detector tilt (about y)")):
            values = np.full((len(modes), n_pos), np.nan)
            bounds = np.full((len(modes), n_pos), np.nan)
            for i, mode in enumerate(modes):
                report = identifiability.get(mode)
                if report is not None and report.identifiable[name]:
                    values[i] = getattr(report, name)
                    bounds[i] = report.crlb[:, k]
            ds[name] = (("mode", "position"), values, {"units": "rad", "long_name": f"{what} fitted by the pose "
                        "model, zero mean; NaN where the data do not identify it"})
            ds[f"{name}_crlb"] = (("mode", "position"), bounds, {"units": "rad", "long_name": f"Cramer-Rao bound "
                                  f"of the {name} from the data alone; NaN where not identifiable"})
        for mode, report in identifiability.items():
            ds.attrs[f"identifiability {mode}"] = report.summary()
    for name, key, units, what in (
            ("tip_tilt_excess", "excess", "pixel", "Procrustes's tip-tilt excess from the pose's fitted tip and tilt, "
                                                   "in quadrature"),
            ("removal_measured", "measured", "1", "share of that excess the pose's accuracy removes"),
            ("removal_bound", "bound", "1", "noise-limited share the pose's Fisher information allows"),
            ("tip_tilt_snr", "snr", "1", "that excess over its noise part")):
        if removals:
            ds[name] = (("mode",), [removals.get(m, {}).get(key, np.nan) for m in modes],
                        {"units": units, "long_name": what})
    if removals:  # below it the figure says the data cannot show a gain, as the table does
        ds.attrs["removal_bound_low"] = REMOVAL_BOUND_LOW
    return ds
