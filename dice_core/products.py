"""The catalogue of what the workflow writes: each product's path, what it holds, and the step that writes it.

One entry per product, said once: the workflow's rules build their output paths
from it (:func:`pattern`), :func:`dice_core.io.write_product` checks every
netCDF product it writes against its entry (:func:`problems`), the contract
tests iterate it, and ``docs/products.md`` is generated from it
(:func:`markdown`; ``python -m dice_core.products --write docs/products.md``).

A path template is relative to the dataset's results folder
(``results/<name>/``, base ``"dataset"``) or to the sweeps folder
(``results/sweeps/``, base ``"sweeps"``); ``{baseline}`` and the like are the
manifest's names or a configured value. A figure is one entry for its PNG and
its PDF. ``stable`` products are the contract shared with outside tools: their
paths, listed variables, dims and units change only with a new version of the
products page. The variables an entry lists are those it promises; a product
may carry more, each with its units (``io.write_product`` refuses a variable
without).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

__all__ = ["Variable", "Product", "CATALOGUE", "SWEEPS_FOLDER", "entry", "pattern", "path_of", "match", "problems",
           "markdown"]

#: The sweeps' folder, beside the datasets' own under the results folder (base ``"sweeps"``).
SWEEPS_FOLDER = "sweeps"


@dataclass(frozen=True)
class Variable:
    """A variable a product promises: its dims (axis order), units and meaning; ``optional`` where it may be
    absent (its meaning says when)."""

    name: str
    dims: tuple[str, ...]
    units: str
    meaning: str
    optional: bool = False


@dataclass(frozen=True)
class Product:
    """One product of the workflow (see the module's docstring for the fields' conventions)."""

    key: str
    path: str
    step: str
    kind: str  # netcdf, csv, tex, figure, fits, yaml, pdf
    meaning: str
    variables: tuple[Variable, ...] = ()
    columns: tuple[str, ...] = ()
    stable: bool = False
    base: str = "dataset"
    temporary: bool = False
    stage: str = ""
    extra: tuple[str, ...] = field(default=(), compare=False)

    @property
    def wildcards(self) -> tuple[str, ...]:
        """The names in the path template, in order."""
        return tuple(re.findall(r"{(\w+)}", self.path))

    def files(self) -> tuple[str, ...]:
        """The path templates of its files: the PNG and PDF of a figure, else the path itself."""
        return (f"{self.path}.png", f"{self.path}.pdf") if self.kind == "figure" else (self.path,)


def _V(name, dims, units, meaning, optional=False):  # a short constructor for the table below
    return Variable(name, tuple(dims.split()) if isinstance(dims, str) else tuple(dims), units, meaning, optional)


RC = "row col"

_PRODUCTS = [
    # ------------------------------------------------------------------ the simulated testbed
    Product("truth", "raw/truth.nc", "simulate_truth", "netcdf", stage="simulation",
            meaning="the simulated bench's truth, which the reduction never reads (the dataset format's truth)",
            variables=(_V("dx", RC, "pixel", "true pixel offset along x"),
                       _V("dy", RC, "pixel", "true pixel offset along y"),
                       _V("sensitivity", RC, "1", "relative quantum efficiency, mean 1 over the science area"),
                       _V("kx", "baseline", "rad/pixel", "fringe wavevector of each baseline, x"),
                       _V("ky", "baseline", "rad/pixel", "fringe wavevector of each baseline, y"),
                       _V("phase", "baseline frame", "rad", "fringe phase of each frame"),
                       _V("star_x", "position star", "pixel", "true star centre x"),
                       _V("star_y", "position star", "pixel", "true star centre y"))),
    Product("cube", "raw/{relpath}.fits", "simulate_file", "fits", stage="simulation",
            meaning="one FITS cube of the simulated dataset (dark, flat, metrology or star frames)"),
    Product("manifest", "raw/dataset.yaml", "simulate_manifest", "yaml", stage="simulation",
            meaning="the simulated dataset's manifest (docs/dataset-format.md)"),
    # ------------------------------------------------------------------ dark and flat field
    Product("dark", "calibration/dark.nc", "measure_dark", "netcdf", stable=True, stage="dark and flat field",
            meaning="the dark's temporal mean and noise",
            variables=(_V("dark", RC, "adu", "mean dark frame"),
                       _V("noise", RC, "adu", "temporal noise of each pixel (its read noise)"),
                       _V("saturated_count", RC, "1", "saturated dark samples left out"))),
    Product("flat_prnu", "calibration/flats/prnu_{flat}.nc", "measure_prnu", "netcdf", stage="dark and flat field",
            meaning="the PRNU map of one flat (the paper's five steps), with its photon-noise limit",
            variables=(_V("prnu", RC, "1", "relative sensitivity, mean 1 over the science area"),
                       _V("photon_noise_limit", RC, "1", "1-sigma photon-noise error of the PRNU"),
                       _V("mean_signal", RC, "adu", "mean dark-subtracted flat level"),
                       _V("frame_level", "frame", "adu", "mean science-area level of each frame"))),
    Product("prnu", "calibration/prnu.nc", "select_reference_prnu", "netcdf", stable=True,
            stage="dark and flat field", meaning="the reference flat's PRNU (the manifest's first flat)",
            variables=(_V("prnu", RC, "1", "relative sensitivity from the reference flat, mean 1 over the science "
                                          "area"),
                       _V("photon_noise_limit", RC, "1", "1-sigma photon-noise error of the PRNU"))),
    Product("prnu_difference", "calibration/prnu_difference_{flat}.nc", "compare_prnu", "netcdf", stable=True,
            stage="dark and flat field", meaning="another flat's PRNU minus the reference's",
            variables=(_V("difference", RC, "1", "flat <flat>'s PRNU minus the reference's"),
                       _V("photon_noise_limit", RC, "1", "1-sigma photon-noise error of the difference"),
                       _V("photon_noise_limit_rms", "", "1", "rms of photon_noise_limit over the science area"))),
    Product("bad_pixels", "calibration/bad_pixels.nc", "find_bad_pixels", "netcdf", stage="dark and flat field",
            meaning="dead, hot, dust and column flags from the dark and the reference PRNU; the metrology and the "
                    "star windows leave the dead, hot and column pixels out",
            variables=(_V("bad_pixel", RC, "1", "flags (CF flag_masks: dead, hot, dust, column)"),)),
    # ------------------------------------------------------------------ metrology
    Product("fit_state", "metrology/split/{baseline}/state_{npass}.nc", "fit_start", "netcdf", temporary=True,
            stage="metrology", extra=("fit_reduce",),
            meaning="a split fit's state after a pass (fit_start writes pass 0's, fit_reduce the others)"),
    Product("fit_part", "metrology/split/{baseline}/pass_{npass}/part_{part}.nc", "fit_part", "netcdf",
            temporary=True, stage="metrology",
            meaning="one part's share of a split fit's pass"),
    Product("metrology", "metrology/{baseline}.nc", "fit_fringes", "netcdf", stable=True, stage="metrology",
            extra=("fit_finish",),
            meaning="the global fringe solution of one baseline (fit_finish writes it when the fit is split, bit "
                    "for bit the same)",
            variables=(_V("projected_offset", RC, "pixel", "pixel offset along the fringe wavevector"),
                       _V("iota", RC, "1", "relative intensity of each pixel"),
                       _V("alpha", RC, "1", "relative fringe amplitude of each pixel"),
                       _V("kx", "", "rad/pixel", "mean fringe wavevector, x (points the way the fitted phase grows)"),
                       _V("ky", "", "rad/pixel", "mean fringe wavevector, y"),
                       _V("phase", "frame", "rad", "fringe phase phi(t) of each frame"),
                       _V("photon_noise_floor", RC, "pixel", "1-sigma photon-noise error of projected_offset"))),
    Product("allan", "allan/{baseline}.nc", "allan_deviation", "netcdf", stable=True, stage="metrology",
            meaning="Allan deviations of the projected offsets against the number of frames averaged",
            variables=(_V("deviation", "n_frames row col", "pixel", "standard deviation of the projected offsets "
                                                                  "between groups of frames (the paper's statistic)"),
                       _V("allan_deviation", "n_frames row col", "pixel", "non-overlapping Allan deviation"),
                       _V("deviation_mean", "n_frames", "pixel", "the deviation between groups, rms over pixels, each "
                                                                "group fitted as a whole"),
                       _V("allan_deviation_mean", "n_frames", "pixel", "allan_deviation, rms over pixels"),
                       _V("photon_limit_pixel", "n_frames", "pixel", "photon-noise limit of deviation_mean, from the "
                                                                    "fits' own errors"))),
    Product("prf", "calibration/prf.nc", "prf_widths", "netcdf", stable=True, stage="metrology",
            meaning="each pixel's PRF width from the fringe contrast of every baseline (docs/centroids.md, "
                    "\"PRF widths\")",
            variables=(_V("width_x", RC, "pixel", "PRF standard deviation along x"),
                       _V("width_y", RC, "pixel", "PRF standard deviation along y"),
                       _V("error_width_x", RC, "pixel", "1-sigma error of width_x"),
                       _V("error_width_y", RC, "pixel", "1-sigma error of width_y"))),
    Product("offsets", "calibration/offsets_{pair}.nc", "deproject_offsets", "netcdf", stable=True,
            stage="metrology", meaning="x and y pixel offsets from a pair of baselines",
            variables=(_V("dx", RC, "pixel", "pixel offset along x (columns)"),
                       _V("dy", RC, "pixel", "pixel offset along y (rows)"),
                       _V("dx_photon_noise_floor", RC, "pixel", "1-sigma photon-noise error of dx"),
                       _V("dy_photon_noise_floor", RC, "pixel", "1-sigma photon-noise error of dy"),
                       _V("unobservable_dx", "mode row col", "1", "smooth offset modes beyond the affine part that the "
                                                                "metrology cannot see, x part (with spherical waves: "
                                                                "those refining the fiber tips absorbs); dx, dy are "
                                                                "orthogonal to them. Absent when there are none",
                         optional=True),
                       _V("unobservable_dy", "mode row col", "1", "the same modes, y part", optional=True))),
    Product("chromatic", "calibration/chromatic.nc", "chromatic_calibration", "netcdf", stable=True,
            stage="metrology",
            meaning="every wavelength's calibration (format 1.2, datasets with pairs at several wavelengths): its "
                    "reference pair's offsets, its baselines' PRF widths and its laser flat's PRNU, with the model "
                    "the chromatic mode interpolates them with across wavelength (attribute model; "
                    "docs/centroids.md, \"Chromatic pixels\")",
            variables=(_V("dx", "wavelength row col", "pixel", "pixel offset along x at each wavelength"),
                       _V("dy", "wavelength row col", "pixel", "pixel offset along y at each wavelength"),
                       _V("sensitivity", "wavelength row col", "1", "relative sensitivity at each wavelength, from "
                                                                    "its laser flat (NaN: none)"),
                       _V("width_x", "wavelength row col", "pixel", "PRF standard deviation along x at each "
                                                                    "wavelength"),
                       _V("width_y", "wavelength row col", "pixel", "PRF standard deviation along y at each "
                                                                    "wavelength"))),
    Product("offsets_difference", "calibration/offsets_difference_{pair}.nc", "compare_pairs", "netcdf",
            stage="metrology", meaning="a pair's offsets minus the reference pair's (the manifest's first)",
            variables=(_V("ddx", RC, "pixel", "dx difference"), _V("ddy", RC, "pixel", "dy difference"),
                       _V("ddx_photon_noise_floor", "", "pixel", "photon-noise floor of ddx's standard deviation"),
                       _V("ddy_photon_noise_floor", "", "pixel", "photon-noise floor of ddy's standard deviation"))),
    # ------------------------------------------------------------------ pseudo stars
    Product("stack", "stars/{position}.nc", "stack_position", "netcdf", stage="pseudo stars",
            meaning="one star position's frames read once: their mean, batch means and saturated samples",
            variables=(_V("mean", RC, "adu", "mean frame"), _V("batch_mean", "batch row col", "adu", "batch means"),
                       _V("n_saturated", RC, "1", "saturated samples"))),
    Product("centroids", "centroids/{mode}.nc", "measure_centroids", "netcdf", stable=True, stage="pseudo stars",
            meaning="star centroids at every position in one calibration mode, with centroids.method",
            variables=(_V("x", "position star", "pixel", "centroid of each star at each position, x"),
                       _V("y", "position star", "pixel", "centroid, y"),
                       _V("precision_x", "position star", "pixel", "batch precision of x (standard error)"),
                       _V("precision_y", "position star", "pixel", "batch precision of y"),
                       _V("photon_limit_x", "position star", "pixel", "Cramer-Rao bound of x"),
                       _V("photon_limit_y", "position star", "pixel", "Cramer-Rao bound of y"))),
    Product("centroids_by_method", "centroids/{method}/{mode}.nc", "measure_centroids_by_method", "netcdf",
            stage="pseudo stars", meaning="the same with each other method of centroids.methods",
            variables=(_V("x", "position star", "pixel", "centroid x"), _V("y", "position star", "pixel", "centroid y"))),
    # ------------------------------------------------------------------ astrometry
    Product("accuracy_table", "tables/accuracy.csv", "accuracy_table", "csv", stable=True, stage="astrometry",
            meaning="one row per centroid method, calibration mode, grouping and superimposition; select rows by "
                    "mode (the width mode shares flat and metrology with flat+metrology); accuracy, error and "
                    "rms_residual in pixel",
            columns=("flat", "metrology", "grouping", "accuracy", "error", "mode", "method", "superimposition")),
    Product("accuracy_latex", "tables/accuracy.tex", "accuracy_table", "tex", stage="astrometry",
            meaning="the accuracy table as the paper prints it"),
    Product("procrustes_residuals", "tables/procrustes_residuals.nc", "accuracy_table", "netcdf", stage="astrometry",
            meaning="the Procrustes residuals of every calibration mode",
            variables=(_V("residual", "mode position star axis", "pixel", "residual after the superimposition"),
                       _V("accuracy", "mode", "pixel", "accuracy over positions"))),
    Product("model_residuals", "tables/{model}_residuals.nc", "accuracy_table", "netcdf", stage="astrometry",
            meaning="the residuals of another superimposition of astrometry.superimposition (projective, pose: "
                    "with the pose's tip and tilt where the data identify them)",
            variables=(_V("residual", "mode position star axis", "pixel", "residual after the superimposition"),)),
    # ------------------------------------------------------------------ the paper's simulations and comparison
    Product("sweep_point", "{sweep}/{point}/point.nc", "sweep_point", "netcdf", base="sweeps", stage="sweeps",
            meaning="one point of a configured simulation study (config sweeps)"),
    Product("sweep_summary", "{sweep}/summary.csv", "sweep_summary", "csv", base="sweeps", stage="sweeps",
            extra=("reduction_sweep_summary",), meaning="every point of a sweep, a row each"),
    Product("sweep_accuracy_figure", "{sweep}/accuracy", "plot_star_accuracy", "figure", base="sweeps",
            stage="sweeps", extra=("reduction_sweep_summary",),
            meaning="accuracy against the swept parameter (star_accuracy and reduction sweeps)"),
    Product("chromatic_study_figure", "{sweep}/chromatic", "plot_chromatic_study", "figure", base="sweeps",
            stage="sweeps", meaning="broadband stars' accuracy against the number of calibration wavelengths, and the "
                                    "633 nm calibration's gain against the paper's 2.2 (chromatic sweeps)"),
    Product("tip_tilt_figure", "{sweep}/tip_tilt", "plot_tip_tilt", "figure", base="sweeps", stage="sweeps",
            meaning="each superimposition against tip-tilt (tip_tilt sweeps)"),
    Product("error_propagation", "tables/error_propagation.csv", "error_propagation_table", "csv", stable=True,
            stage="paper", meaning="one row per error source; coefficient_units says which unit the coefficient "
                                   "and its error are in",
            columns=("source", "normalisation", "coefficient", "error", "paper_coefficient", "coefficient_units")),
    Product("procrustes_deflation", "tables/procrustes_deflation.csv", "procrustes_deflation", "csv", stage="paper",
            meaning="the Procrustes deflation factor of the paper's 5 stars and 33 positions, with its Monte Carlo "
                    "error", columns=("factor", "error", "trials", "positions", "stars")),
    Product("paper_comparison", "tables/paper_comparison.csv", "paper_comparison", "csv", stable=True, stage="paper",
            meaning="one row per regenerated number of the paper; several ways to one paper number are separate "
                    "quantities; values in unit",
            columns=("quantity", "section", "paper", "ours", "error", "unit", "dataset", "note")),
    Product("paper_report", "report/paper_reproduction.pdf", "paper_pdf", "pdf", stage="paper",
            meaning="the reproduction report: the paper's figures regenerated, with captions"),
]

# ---------------------------------------------------------------------- figures: (key, path, step, meaning)
_FIGURES = [
    ("figure_dark", "figures/dark", "plot_dark", "mean dark frame", "dark and flat field"),
    ("figure_dark_noise", "figures/dark_noise", "plot_dark", "temporal noise of the dark", "dark and flat field"),
    ("figure_prnu", "figures/prnu_{flat}", "plot_prnu", "a flat's PRNU map", "dark and flat field"),
    ("figure_prnu_difference", "figures/prnu_difference_{flat}", "plot_prnu_difference",
     "a flat's PRNU minus the reference's", "dark and flat field"),
    ("figure_metrology", "figures/metrology_{baseline}", "plot_metrology",
     "a baseline's offsets, convergence, frame parameters and gauges", "metrology"),
    ("figure_allan", "figures/allan_{baseline}", "plot_allan", "a baseline's Allan deviations", "metrology"),
    ("figure_offsets", "figures/offsets_{pair}", "plot_offsets", "a pair's dx and dy maps", "metrology"),
    ("figure_offsets_difference", "figures/offsets_difference_{pair}", "plot_offsets_difference",
     "a pair's offsets minus the reference pair's", "metrology"),
    ("figure_prf", "figures/prf", "plot_prf", "the PRF width maps and their errors", "metrology"),
    ("figure_chromatic", "figures/chromatic", "plot_chromatic", "each wavelength's offsets and sensitivity against "
     "the reference wavelength's, and what a spectrum takes of each wavelength", "metrology"),
    ("figure_centroids", "figures/centroids_{mode}", "plot_centroids", "a mode's centroids and precisions",
     "pseudo stars"),
    ("figure_procrustes_residuals", "figures/procrustes_residuals", "plot_procrustes_residuals",
     "Procrustes residuals of every mode", "astrometry"),
    ("figure_barycentre_residuals", "figures/barycentre_residuals", "plot_procrustes_residuals",
     "the stars' barycentre residuals", "astrometry"),
    ("figure_model_residuals", "figures/{model}_residuals", "plot_superimposition_residuals",
     "another superimposition's residuals", "astrometry"),
    ("figure_offset_bias", "figures/offset_bias", "plot_offset_bias", "the paper's pixel-offset bias figure",
     "paper"),
    ("figure_error_propagation", "figures/error_propagation", "plot_error_propagation",
     "error-propagation coefficients", "paper"),
    ("figure_paper_comparison", "figures/paper_comparison", "paper_comparison", "every regenerated number beside "
                                                                                "the paper's", "paper"),
]
_PRODUCTS += [Product(key, path, step, "figure", meaning=meaning, stage=stage)
              for key, path, step, meaning, stage in _FIGURES]

#: Every product by its key.
CATALOGUE: dict[str, Product] = {p.key: p for p in _PRODUCTS}


def entry(key: str) -> Product:
    """The catalogue's entry ``key``; a KeyError names the known keys."""
    try:
        return CATALOGUE[key]
    except KeyError:
        raise KeyError(f"no product {key!r} in the catalogue (products: {', '.join(CATALOGUE)})") from None


def pattern(key: str, *, dataset_root: str, sweeps_root: str, suffix: str = "") -> str:
    """The path pattern of product ``key`` under its base folder, wildcards kept as ``{name}``; ``suffix``
    (``.png``, ``.pdf``) for a figure's file."""
    product = entry(key)
    if product.kind == "figure" and suffix not in (".png", ".pdf"):
        raise ValueError(f"figure {key}: ask for its .png or .pdf")
    root = dataset_root if product.base == "dataset" else sweeps_root
    return f"{root}/{product.path}{suffix}"


def path_of(key: str, *, dataset_root: str, sweeps_root: str, suffix: str = "", **wildcards) -> str:
    """The path of one instance of product ``key``: :func:`pattern` with the wildcards filled in."""
    template = pattern(key, dataset_root=dataset_root, sweeps_root=sweeps_root, suffix=suffix)
    missing = [name for name in entry(key).wildcards if name not in wildcards]
    if missing:
        raise KeyError(f"product {key}: no value for {', '.join(missing)}")
    return template.format(**wildcards)


def _regex(product: Product, file_template: str) -> re.Pattern:
    parts = re.split(r"({\w+})", file_template)
    body = "".join((r"(?P<%s>.+)" % p[1:-1]) if p.startswith("{") and p[1:-1] in ("point", "relpath")
                   else (r"(?P<%s>[^/]+)" % p[1:-1]) if p.startswith("{") else re.escape(p) for p in parts)
    base = "" if product.base == "dataset" else re.escape(SWEEPS_FOLDER) + "/"
    return re.compile(r"(?:^|.*/)" + base + body + "$")


def match(path) -> tuple[Product, dict] | None:
    """(entry, wildcards) of the product a file path is an instance of, or None: among the entries whose
    template ends the path, the one with the fewest wildcards, then the most literal text
    (``tables/procrustes_residuals.nc`` is the Procrustes entry, not ``tables/{model}_residuals.nc``;
    ``offsets_difference_P24.nc`` a difference, not the offsets of a pair ``difference_P24``, which
    :meth:`dice_core.planning.Plan.check_names` refuses)."""
    text = str(path).replace("\\", "/")
    found = []
    for product in CATALOGUE.values():
        for template in product.files():
            hit = _regex(product, template).match(text)
            if hit:
                literal = len(re.sub(r"{\w+}", "", template))
                found.append((len(product.wildcards), -literal, product.key, product, hit.groupdict()))
    if not found:
        return None
    *_, product, wildcards = min(found, key=lambda f: f[:3])
    return product, wildcards


def problems(ds, product: Product) -> list[str]:
    """What a netCDF dataset lacks of what its catalogue entry promises: a variable missing (unless
    optional), on other dims, or in other units; one line each."""
    found = []
    for variable in product.variables:
        if variable.name not in ds:
            if not variable.optional:
                found.append(f"variable {variable.name} is missing")
            continue
        dims, units = tuple(ds[variable.name].dims), ds[variable.name].attrs.get("units")
        if dims != variable.dims:
            found.append(f"variable {variable.name} has dims {dims}, the catalogue says {variable.dims}")
        if units != variable.units:
            found.append(f"variable {variable.name} is in {units!r}, the catalogue says {variable.units!r}")
    return found


def markdown(*, modes=None, methods=None) -> str:
    """The generated part of ``docs/products.md``: every product by stage, its path, the step that writes it,
    what it holds (variables with dims and units, or columns), stable or not; the calibration modes and
    centroid methods (``modes``, ``methods``: name to description) that name products; and each step's
    settings (:mod:`dice_core.steps`)."""
    lines = ["<!-- generated by `python -m dice_core.products --write docs/products.md`: edit dice_core/products.py "
             "and regenerate -->", ""]
    stages = list(dict.fromkeys(p.stage for p in CATALOGUE.values()))
    for stage in stages:
        lines += [f"### {stage[0].upper()}{stage[1:]}", "", "| path | written by | what it holds |", "|---|---|---|"]
        for product in (p for p in CATALOGUE.values() if p.stage == stage):
            where = "results/sweeps/" if product.base == "sweeps" else ""
            files = " ".join(f"`{where}{f}`" for f in product.files())
            flags = [*(["**stable**"] if product.stable else []), *(["temporary, internal"] if product.temporary
                                                                    else [])]
            what = product.meaning + (f" ({', '.join(flags)})" if flags else "")
            if product.variables:
                what += ": " + "; ".join(
                    f"`{v.name}` ({', '.join(v.dims) or 'scalar'}, {v.units}{', optional' if v.optional else ''}): "
                    f"{v.meaning}" for v in product.variables)
            if product.columns:
                what += ": columns " + ", ".join(f"`{c}`" for c in product.columns)
            steps = ", ".join(f"`{s}`" for s in (product.step, *product.extra))
            lines.append(f"| {files} | {steps} | {what} |")
        lines.append("")
    if modes:
        lines += ["### Calibration modes and centroid methods", "",
                  "`<mode>` in a path is one of these (`centroids.modes`; the dark is always subtracted):", ""]
        lines += [f"- `{name}`: {text}" for name, text in modes.items()]
    if methods:
        lines += ["", "`<method>` is one of these (`centroids.method`, `centroids.methods`):", ""]
        lines += [f"- `{name}`: {text}" for name, text in methods.items()]
    from dice_core import steps

    lines += ["", "### Steps and the settings each reads", "",
              "A step re-runs when one of its settings changes, and its products record them as their "
              "`configuration` (`dice_core/steps.py`; a step that stands for others reads theirs too).", "",
              "| step | settings | writes |", "|---|---|---|"]
    for name in steps.STEPS:
        keys = ", ".join(f"`{key}`" for key in steps.settings_keys(name)) or "none"
        lines.append(f"| `{name}` | {keys} | {', '.join(f'`{key}`' for key in steps.step(name).writes)} |")
    lines += ["", "Configuration keys no step reads, which choose what is made or where:", ""]
    lines += [f"- `{key}`: {why}" for key, why in steps.PLANNING_KEYS.items()]
    lines.append("")
    lines.append("<!-- end of the generated part -->")
    return "\n".join(lines) + "\n"


def _main(argv=None):
    import argparse
    from pathlib import Path

    from dice_core import centroids

    parser = argparse.ArgumentParser(prog="python -m dice_core.products",
                                     description="Print (or write into a page) the products catalogue as Markdown.")
    parser.add_argument("--write", metavar="PAGE", help="replace the generated part of PAGE (docs/products.md)")
    args = parser.parse_args(argv)
    text = markdown(modes=centroids.mode_descriptions(), methods=centroids.method_descriptions())
    if not args.write:
        print(text, end="")
        return
    page = Path(args.write)
    print(f"{page}: generated part rewritten", flush=True)
    page.write_text(replace_generated(page.read_text(), text))


def replace_generated(page: str, generated: str) -> str:
    """``page`` with its generated part (between the two markers :func:`markdown` writes) replaced by
    ``generated``; a ValueError if the page has no such part."""
    start = page.find("<!-- generated by")
    end_marker = "<!-- end of the generated part -->"
    end = page.find(end_marker)
    if start < 0 or end < start:
        raise ValueError("the page has no generated part (its two markers)")
    return page[:start] + generated + page[end + len(end_marker) + 1:]


if __name__ == "__main__":
    _main()
