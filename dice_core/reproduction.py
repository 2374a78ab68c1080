"""Our numbers beside the paper's: the rows of ``tables/paper_comparison.csv``.

Every number the workflow regenerates of Crouzier et al. (A&A) is listed in
:data:`PAPER` with the section it comes from, its value and unit; the
functions below take our products and return rows of (quantity, section,
paper, ours, error, unit, dataset, note), one per quantity: where one paper
number is regenerated several ways (the unweighted fit beside the pipeline's,
each baseline's Allan deviation), each way is its own quantity, the paper's
name with the way in brackets. Our numbers that the paper gives none for (the
rms of each offset-bias map) have an empty ``paper``. ``error`` is our
number's 1-sigma error where one is known, NaN otherwise.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass

import numpy as np

from dice_core import accuracies, error_budget, superimposition

__all__ = ["PAPER", "Row", "comparison_csv", "nominal_configurations", "procrustes_deflation", "accuracy_rows",
           "allan_rows", "offset_bias_rows", "error_propagation_rows", "stray_light_note", "stray_light_rows",
           "stray_light_study_rows", "chromatic_rows"]

SIMULATIONS = "Numerical simulations"
EXPERIMENT = "Experimental data analysis"

#: The paper's numbers: key -> (quantity, section, value, unit).
PAPER = {
    "bias_paper_2e-3": ("offset bias rms of the paper's method, PRNU RSD 2e-3", SIMULATIONS, 1e-4, "pixel"),
    "bias_paper_5e-5": ("offset error rms of the paper's method, PRNU RSD 5e-5 (photon floor)", SIMULATIONS, 2e-5,
                        "pixel"),
    "allan_pixel": ("Allan deviation of the largest group, individual pixels", SIMULATIONS, 2e-5, "pixel"),
    "allan_block": ("Allan deviation of the largest group, 10x10-pixel blocks", SIMULATIONS, 2e-6, "pixel"),
    "coefficient_prnu": ("centroid error per unit PRNU RSD", SIMULATIONS, error_budget.PAPER_COEFFICIENTS["prnu"], "pixel"),
    "coefficient_photon": ("centroid error per unit relative photon noise of the brightest pixel", SIMULATIONS, error_budget.PAPER_COEFFICIENTS["photon"],
                           "pixel"),
    "coefficient_offsets": ("centroid error per unit pixel-offset rms", SIMULATIONS, error_budget.PAPER_COEFFICIENTS["offsets"],
                            "pixel per pixel"),
    "coefficient_read": ("centroid error per unit relative read noise of the brightest pixel", SIMULATIONS, error_budget.PAPER_COEFFICIENTS["read"],
                         "pixel"),
    "requirement_prnu": ("PRNU calibration for a 5e-6 pixel centroid error", SIMULATIONS, error_budget.PAPER_REQUIREMENTS["prnu"], "1"),
    "requirement_offsets": ("pixel-offset calibration for a 5e-6 pixel centroid error", SIMULATIONS, error_budget.PAPER_REQUIREMENTS["offsets"],
                            "pixel"),
    "deflation": ("Procrustes deflation factor, 5 stars, 33 positions", SIMULATIONS, 1.4, "1"),
    "accuracy_raw_position": ("accuracy, no flat, no metrology (p)", EXPERIMENT, 2.1e-4, "pixel"),
    "accuracy_raw_group": ("accuracy, no flat, no metrology (g)", EXPERIMENT, 1.4e-4, "pixel"),
    "accuracy_flat_position": ("accuracy, flat (p)", EXPERIMENT, 1.7e-4, "pixel"),
    "accuracy_flat_group": ("accuracy, flat (g)", EXPERIMENT, 1.6e-4, "pixel"),
    "accuracy_metrology_position": ("accuracy, metrology (p)", EXPERIMENT, 2.9e-4, "pixel"),
    "accuracy_metrology_group": ("accuracy, metrology (g)", EXPERIMENT, 2.1e-4, "pixel"),
    "accuracy_flat+metrology_position": ("accuracy, flat and metrology (p)", EXPERIMENT, 9.7e-5, "pixel"),
    "accuracy_flat+metrology_group": ("accuracy, flat and metrology (g)", EXPERIMENT, 5.9e-5, "pixel"),
    "calibration_gain": ("accuracy gain of flat and metrology over raw (p)", EXPERIMENT, 2.2, "1"),
    "offset_accuracy": ("pixel-offset accuracy, stray light its main noise (Bias on pixel offsets)", EXPERIMENT,
                        4e-4, "pixel"),
    "coherence_gain": ("gain on the offsets from a 1 cm coherence length (Bias on pixel offsets: none)", EXPERIMENT,
                       1.0, "1"),
    "tip_averaging_gain": ("gain on the offsets from averaging 9 fiber-tip positions (Bias on pixel offsets: none)",
                           EXPERIMENT, 1.0, "1"),
}

PAPER_ALLAN_FRAMES = 100_000  # frames per group of the paper's largest Allan group

#: The offset-bias study's maps (the figure's panels), each one's rms a row: variable -> what it is.
BIAS_MAPS = {"error_paper": "offset error rms of the paper's method, with photon noise",
             "error_ours": "offset error rms of ours (true flat), with photon noise",
             "bias_paper": "offset bias rms of the paper's method, noiseless, rms over the PRNU patterns",
             "bias_ours": "offset bias rms of ours (true flat), noiseless, rms over the PRNU patterns",
             "photon_floor": "photon-noise floor rms of the offsets"}

COLUMNS = ("quantity", "section", "paper", "ours", "error", "unit", "dataset", "note")


@dataclass
class Row:
    """One line of the comparison.

    ``key`` names the paper's number in :data:`PAPER`; ``variant`` (e.g.
    "unweighted fit", a baseline) tells apart several of ours for the same
    number, in brackets after the paper's quantity. A row of ours that the
    paper has no number for has ``key`` None and gives its own ``quantity``,
    ``section`` and ``unit`` (its ``paper`` is NaN).
    """

    key: str | None
    ours: float
    error: float = math.nan
    dataset: str = ""
    note: str = ""
    variant: str = ""
    quantity: str = ""
    section: str = SIMULATIONS
    unit: str = "pixel"

    def as_dict(self) -> dict:
        if self.key is None:
            quantity, section, paper, unit = self.quantity, self.section, math.nan, self.unit
        else:
            quantity, section, paper, unit = PAPER[self.key]
        if self.variant:
            quantity = f"{quantity} ({self.variant})"
        return {"quantity": quantity, "section": section, "paper": paper, "ours": self.ours, "error": self.error,
                "unit": unit, "dataset": self.dataset, "note": self.note}


def comparison_csv(rows) -> str:
    """CSV text of :class:`Row` s, the products contract's columns first (floats to 4 significant digits).

    Raises
    ------
    ValueError
        Two rows with the same quantity (the table has one row per number).
    """
    quantities = [row.as_dict()["quantity"] for row in rows]
    twice = sorted({q for q in quantities if quantities.count(q) > 1})
    if twice:
        raise ValueError(f"the comparison table has more than one row for {twice}: one row per quantity")
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        values = row.as_dict()
        writer.writerow(["" if isinstance(v, float) and math.isnan(v) else f"{v:.4g}" if isinstance(v, float) else v
                         for v in (values[c] for c in COLUMNS)])
    return buffer.getvalue()


def nominal_configurations(n_positions: int = 33, *, side: float = 40.0, step=(0.0, 0.17)) -> np.ndarray:
    """The paper's star geometry: a central star and four corners of a square of ``side`` pixel, moved
    by ``step`` pixel per position; (position, star, 2) in pixel, the central star first."""
    half = side / 2
    pattern = np.array([[0.0, 0.0], [-half, -half], [half, -half], [half, half], [-half, half]])
    return pattern[None] + np.arange(n_positions)[:, None, None] * np.asarray(step, float)[None, None, :]


def procrustes_deflation(n_positions: int = 33, *, trials: int = 2000, seed: int = 0) -> tuple[float, float]:
    """The paper's Procrustes deflation factor by Monte Carlo for its geometry: (factor, 1-sigma error)."""
    result = superimposition.procrustes(nominal_configurations(n_positions))
    return accuracies.correction_factor(result, trials=trials, seed=seed)


def accuracy_rows(rows, *, dataset: str, note: str) -> list[Row]:
    """Rows from ``tables/accuracy.csv`` records (dicts with mode, grouping, accuracy, error).

    Only the Procrustes rows (the paper's superimposition): records of
    another ``superimposition`` (projective, pose) are left out.
    """
    out, found = [], {}
    for record in rows:
        if record.get("superimposition", "procrustes") != "procrustes":
            continue
        key = f"accuracy_{record['mode']}_{record['grouping']}"
        if key in PAPER:
            out.append(Row(key, float(record["accuracy"]), float(record["error"]), dataset, note))
            found[key] = (float(record["accuracy"]), float(record["error"]))
    raw, best = found.get("accuracy_raw_position"), found.get("accuracy_flat+metrology_position")
    if raw and best:
        gain = raw[0] / best[0]
        error = gain * math.hypot(raw[1] / raw[0], best[1] / best[0])
        out.append(Row("calibration_gain", gain, error, dataset, note))
    return out


def allan_rows(allan, *, dataset: str) -> list[Row]:
    """Largest-group Allan deviations of one ``allan/<baseline>.nc`` product (pixels and blocks), as measured.

    The paper's numbers are at :data:`PAPER_ALLAN_FRAMES` frames per group;
    ours at this product's largest group, which the quantity names with the
    baseline. The note gives ours scaled there as white noise (1/sqrt(N)),
    which the measured slope and the photon limit let a reader check, but the
    row holds the measured value: a scaled one is not a measurement.
    """
    n = int(allan["n_frames"].values[-1])
    baseline = allan.attrs.get("baseline", "")
    to_paper = math.sqrt(n / PAPER_ALLAN_FRAMES)
    rows = []
    for key, measured, limit in (("allan_pixel", "deviation_mean", "photon_limit_pixel"),
                                 ("allan_block", "deviation_block_mean", "photon_limit_block")):
        value, photon = float(allan[measured].values[-1]), float(allan[limit].values[-1])
        note = (f"measured at {n} frames per group (the paper's: {PAPER_ALLAN_FRAMES}); photon limit there "
                f"{photon:.2e} pixel; slope {float(allan['slope']):.2f}; as white noise (1/sqrt(N)) at the paper's "
                f"{PAPER_ALLAN_FRAMES} frames: {value * to_paper:.2e} pixel")
        rows.append(Row(key, value, math.nan, f"{dataset} {baseline}".strip(), note,
                        variant=", ".join(filter(None, (baseline, f"{n} frames per group")))))
    return rows


def _level(prnu: float) -> str:
    """A PRNU level as the paper writes it: 5e-5, 2e-3."""
    mantissa, exponent = f"{prnu:.1e}".split("e")
    return f"{float(mantissa):g}e{int(exponent)}"


def offset_bias_rows(points) -> list[Row]:
    """Rows from the offset-bias study: ``points`` maps a PRNU RSD to its study dataset.

    The paper's two numbers (its method's offset error with photon noise at
    5e-5, and its bias at 2e-3, which we compare with the noiseless bias, rms
    over the PRNU patterns), then the rms of each map of the figure
    (:data:`BIAS_MAPS`) at each level, the paper's number where it is one.

    Raises
    ------
    ValueError
        The sweep lacks one of the paper's PRNU levels, 5e-5 and 2e-3.
    """
    missing = [level for level in (5e-5, 2e-3) if not any(math.isclose(level, p, rel_tol=1e-6) for p in points)]
    if missing:
        raise ValueError(f"the offset-bias sweep has no point at PRNU RSD {missing} (the paper's levels); its "
                         f"points: {sorted(points)}")
    out = []
    for prnu, ds in sorted(points.items()):
        draws = ds["draw_bias_paper"].values
        # the paper's number is one PRNU pattern's: the error is the spread between patterns
        spread = float(np.std(draws, ddof=1)) if draws.size > 1 else math.nan
        ours = (f"our reduction {float(ds['rms_error_ours']):.2e} with the true flat, "
                f"{float(ds['rms_error_ours_no_flat']):.2e} without a flat" if "rms_error_ours_no_flat" in ds
                else f"our reduction {float(ds['rms_error_ours']):.2e}")
        if math.isclose(prnu, 2e-3, rel_tol=1e-6):
            out.append(Row("bias_paper_2e-3", float(ds["rms_bias_paper"]), spread, "offset_bias study",
                           f"the paper's method reproduced, noiseless, rms over {draws.size} PRNU patterns (error: "
                           f"their spread); with photon noise {float(ds['rms_error_paper']):.2e} against a floor of "
                           f"{float(ds['rms_photon_floor']):.2e}; {ours}; docs/metrology.md"))
        paper_row = math.isclose(prnu, 5e-5, rel_tol=1e-6)  # the paper's 2e-5 is the noisy map's rms at 5e-5
        for name, what in BIAS_MAPS.items():
            value = float(ds[f"rms_{name}"])
            if paper_row and name == "error_paper":
                out.append(Row("bias_paper_5e-5", value, math.nan, "offset_bias study",
                               f"the paper's method reproduced, with photon noise, floor "
                               f"{float(ds['rms_photon_floor']):.2e}; {ours}"))
                continue
            noisy = name.startswith(("error", "photon"))
            frames = ds.attrs.get("frames" if noisy else "noiseless_frames", "?")
            where = ("the figure's map" if noisy else "rms over every noiseless PRNU pattern (the figure's map is the "
                     "first)")
            out.append(Row(None, value, math.nan, "offset_bias study",
                           f"{where}, {frames} frames {'with' if noisy else 'without'} noise; not in the paper",
                           quantity=f"{what}, PRNU RSD {_level(prnu)}"))
    return out


def error_propagation_rows(records) -> list[Row]:
    """Rows from ``tables/error_propagation.csv`` records (dicts: source, coefficient, error, ...): the
    pipeline's weighted fit, and the unweighted fit's where the table has it (``*_uniform`` columns), the
    latter as their own quantities ("... (unweighted fit)")."""
    out = []
    for record in records:
        source = record["source"]
        fits = [("", "pipeline's weighted fit", "")]
        if record.get("coefficient_uniform"):
            fits.append(("_uniform", "unweighted fit", "unweighted fit"))
        for suffix, fit, variant in fits:
            coefficient, error = float(record[f"coefficient{suffix}"]), float(record[f"error{suffix}"])
            dataset = f"error_propagation study, {fit}"
            if f"coefficient_{source}" in PAPER:
                note = f"per axis; 2-D {float(record[f'coefficient_2d{suffix}']):.3g}; analytic " \
                       f"{float(record[f'analytic{suffix}']):.3g}; matches: {record[f'convention_matching_paper{suffix}']}"
                out.append(Row(f"coefficient_{source}", coefficient, error, dataset, note, variant=variant))
            if f"requirement_{source}" in PAPER:
                requirement = error_budget.REQUIRED_ERROR / coefficient
                out.append(Row(f"requirement_{source}", requirement, requirement * error / coefficient, dataset,
                               "5e-6 pixel / the per-axis coefficient", variant=variant))
    return out


def stray_light_note(stray) -> str:
    """What a ``calibration/stray_light_<baseline>.nc`` product found, for a note ("" if nothing)."""
    n = int(stray["n_components"])
    if n == 0:
        return ""
    frequencies = ", ".join(f"({float(fx):+.3f}, {float(fy):+.3f})" for fx, fy in zip(
        stray["component_frequency_x"].values, stray["component_frequency_y"].values))
    return (f"coherent stray light: {n} component(s) at {frequencies} cycles/pixel, rms "
            f"{float(np.sqrt(np.nanmean(stray['offset_error'].values ** 2))):.2e} pixel "
            f"(calibration/stray_light_{stray.attrs.get('baseline', '')}.nc)")


def stray_light_rows(stray, *, dataset: str, removed: bool) -> list[Row]:
    """A baseline's coherent stray light beside the paper's 4e-4 pixel offset accuracy, which its section
    "Bias on pixel offsets" blames on stray light: the rms of the components found in the projected offsets,
    a row only where there are some."""
    note = stray_light_note(stray)
    if not note:
        return []
    rms = float(np.sqrt(np.nanmean(stray["offset_error"].values ** 2)))
    baseline = stray.attrs.get("baseline", "")
    return [Row("offset_accuracy", rms, math.nan, f"{dataset} {baseline}".strip(),
                note + ("; removed from the pairs' offsets (metrology.stray_light: remove)" if removed else
                        "; left in the offsets (metrology.stray_light: detect)"),
                variant=f"{baseline}, rms of the stray-light components found")]


def _excess(error: float, floor: float) -> float:
    """The part of an rms error beyond the photon floor, in quadrature (0 at or under it)."""
    return math.sqrt(max(error**2 - floor**2, 0.0))


def stray_light_study_rows(points) -> list[Row]:
    """The stray-light study's numbers beside the paper's (:func:`dice_core.studies.stray_light` points): at
    field ratio 1e-3, the dx, dy error with the stray light left in and removed beside the 4e-4 pixel the paper
    blamed on it; the gain of a 1 cm coherence length (the longest's error over its, the photon floor taken out
    in quadrature); the gain of averaging the tip positions (one position's error over the mean's)."""
    rows, single = [], [p for p in points if float(p["tip_positions"]) == 1]
    short = [p for p in single if float(p["path_scale"]) != 1]
    single = [p for p in single if float(p["path_scale"]) == 1]
    longest = max((float(p["coherence_length"]) for p in single), default=math.nan)
    reference = next((p for p in single if np.isclose(float(p["field_ratio"]), 1e-3)
                      and np.isclose(float(p["coherence_length"]), longest)), None)
    dataset = "stray-light study bench"
    if reference is None:
        return rows
    for axis in ("dx", "dy"):
        for way, what in (("detect", "left in"), ("remove", "removed")):
            rows.append(Row("offset_accuracy", float(reference[f"error_{axis}_{way}"]), math.nan, dataset,
                            f"photon floor {float(reference[f'floor_{axis}']):.2e} pixel; "
                            f"{int(reference['components'])} component(s) found",
                            variant=f"{axis}, field ratio 1e-3, stray light {what}, study"))
    for point in single + short:
        if np.isclose(float(point["field_ratio"]), 1e-3) and np.isclose(float(point["coherence_length"]), 0.01):
            gain = _excess(float(reference["error_dx_detect"]), float(reference["floor_dx"])) / max(
                _excess(float(point["error_dx_detect"]), float(point["floor_dx"])), 1e-300)
            scale = float(point["path_scale"])
            paths = f"{6 * scale:g}-{15 * scale:g} mm"
            rows.append(Row("coherence_gain", gain, math.nan, dataset,
                            f"stray part of the dx error (floor out in quadrature) at coherence {longest * 100:g} cm "
                            f"over 1 cm; vanes' extra paths {paths}", variant=f"dx, vanes' paths {paths}, study"))
    for point in (p for p in points if float(p["tip_positions"]) > 1):
        # the stray parts, each floor taken out in quadrature: the mean of n positions also has a photon floor
        # sqrt(n) lower, which is not what the paper hoped averaging would gain
        gain = _excess(float(point["error_dx_detect"]), float(point["floor_dx"])) / max(
            _excess(float(point["average_error_dx_detect"]), float(point["average_floor_dx"])), 1e-300)
        rows.append(Row("tip_averaging_gain", gain, math.nan, dataset,
                        f"stray part of the dx error (floor out in quadrature) of one position over that of the mean "
                        f"of {int(point['tip_positions'])} (its floor {float(point['average_floor_dx']):.1e} pixel, "
                        f"one position's {float(point['floor_dx']):.1e}); vanes fixed",
                        variant=f"dx, tips {float(point['tip_step']) * 1e3:g} mm apart, study"))
    return rows


def _ratio_error(ds, numerator: str, denominator: str, value: float) -> float:
    """1-sigma error of a ratio of two modes' (p) accuracies of a chromatic study point (independent errors)."""
    a, b = (ds[["accuracy_position", "error_position"]].sel(mode=m) for m in (numerator, denominator))
    return value * math.hypot(float(a["error_position"] / a["accuracy_position"]),
                              float(b["error_position"] / b["accuracy_position"]))


def chromatic_rows(points) -> list[Row]:
    """Rows from the chromatic study (issue 26): its points' datasets (:func:`dice_core.studies.chromatic_accuracy`).

    Beside the paper's 2.2 (``calibration_gain``): each point's flat+metrology gain over raw (p) at 633 nm alone
    on the chromatic detector, and each spectrum's achromatic twin's; then, with no paper number, the chromatic
    mode's (p) accuracy over the twin's flat+metrology's at each number of calibration wavelengths.
    """
    out, twins = [], {}
    for ds in sorted(points, key=lambda d: (d.attrs["spectrum"], float(d.attrs["amplitude"]))):
        spectrum, amplitude = ds.attrs["spectrum"], float(ds.attrs["amplitude"])
        where = f"{spectrum} stars, {ds.attrs.get('positions', '?')} positions"
        gain = float(ds["gain"])
        out.append(Row("calibration_gain", gain, _ratio_error(ds, "raw", "flat+metrology", gain), "chromatic study",
                       "perfect calibrations at 633 nm (white flat, 633 nm offsets); docs/centroids.md",
                       variant=f"chromatic detector of amplitude {amplitude:g}, {where}, calibrated at 633 nm"))
        if spectrum not in twins:
            twin = float(ds["achromatic_gain"])
            twins[spectrum] = Row("calibration_gain", twin, _ratio_error(ds, "achromatic raw",
                                                                         "achromatic flat+metrology", twin),
                                  "chromatic study", "the same noise draws as the chromatic detector's",
                                  variant=f"its achromatic twin, {where}")
        for n, ratio in zip(ds["wavelengths"].values, ds["chromatic_over_achromatic"].values):
            out.append(Row(None, float(ratio), math.nan, "chromatic study",
                           "perfect calibrations at each wavelength; the issue asks for at most 1.2 with 3",
                           quantity=f"chromatic mode's accuracy (p) over the achromatic twin's flat+metrology, {int(n)} "
                                    f"calibration wavelength(s), amplitude {amplitude:g}, {where}",
                           section="Beyond the paper: chromatic pixels", unit="1"))
    return out + list(twins.values())
