"""The catalogue of what the workflow writes: each product's path, what it holds, and the step that writes it.

One entry per product, said once: the workflow's rules build their output paths
from it (:func:`pattern`), :func:`dice_core.io.write_product` checks every
netCDF product it writes against its entry (:func:`problems`), the contract
tests iterate it, and ``docs/products.md`` is generated from it
(:mod:`dice_core.products_page`; ``python -m dice_core.products_page --write docs/products.md``).

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

import os
import re
from dataclasses import dataclass, field

__all__ = ["Variable", "Product", "CATALOGUE", "COORDINATE_ATTRS", "INDEX_DIMS", "SWEEPS_FOLDER", "entry", "pattern", "path_of", "match", "problems"]

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
            stage="dark and flat field", meaning="another flat's PRNU minus the first flat's of the same light (white, or the same laser's wavelength: "
                                                "format 1.2)",
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
            variables=(_V("width_x", RC, "pixel", "PRF standard deviation along x: the mean width plus the pixel's "
                                                "pixel-scale deviation (smooth variations are not measured)"),
                       _V("width_y", RC, "pixel", "PRF standard deviation along y"),
                       _V("error_width_x", RC, "pixel", "1-sigma error of width_x: photon noise and the kernel "
                                                      "shape's uncertainty, which scales the deviations and sets "
                                                      "the mean"),
                       _V("error_width_y", RC, "pixel", "1-sigma error of width_y"),
                       _V("error_width_pixel_x", RC, "pixel", "1-sigma error of width_x minus its mean over the map"),
                       _V("error_width_pixel_y", RC, "pixel", "1-sigma error of width_y minus its mean over the map"),
                       _V("variance_deviation_x", RC, "pixel2", "PRF variance along x minus the mean one, pixel-scale "
                                                              "part: what the contrast measures, what the width "
                                                              "mode's centroids use"),
                       _V("variance_deviation_y", RC, "pixel2", "the same along y"),
                       _V("mean_width_x", "", "pixel", "mean PRF standard deviation along x over the kernels the "
                                                     "two periods allow, with its error error_mean_width_x"),
                       _V("mean_width_y", "", "pixel", "the same along y, error error_mean_width_y"))),
    Product("offsets", "calibration/offsets_{pair}.nc", "deproject_offsets", "netcdf", stable=True,
            stage="metrology", meaning="x and y pixel offsets from a pair of baselines",
            variables=(_V("dx", RC, "pixel", "pixel offset along x (columns)"),
                       _V("dy", RC, "pixel", "pixel offset along y (rows)"),
                       _V("dx_photon_noise_floor", RC, "pixel", "1-sigma photon-noise error of dx"),
                       _V("dy_photon_noise_floor", RC, "pixel", "1-sigma photon-noise error of dy"),
                       _V("unobservable_dx", "mode row col", "1", "smooth offset modes beyond the affine part that the "
                                                                "metrology cannot see, x part (with spherical waves: "
                                                                "those refining the fiber tips absorbs); dx, dy are "
                                                                "orthogonal to them; with metrology.stray_light: "
                                                                "remove, also the removed stray-light components' "
                                                                "directions. Absent when there are none",
                         optional=True),
                       _V("unobservable_dy", "mode row col", "1", "the same modes, y part", optional=True))),
    Product("stray_light", "calibration/stray_light_{baseline}.nc", "find_stray_light", "netcdf", stable=True,
            stage="metrology",
            meaning="the coherent stray light found in a baseline's projected offsets (docs/metrology.md, \"Coherent "
                    "stray light\"): their power spectrum over the white level, the components above the threshold "
                    "(a cos(2 pi (f.(r - r0) + g |r - r0|^2 / 2) + phi), r0 the attribute reference_pixel; none: "
                    "empty) and the phase-error map they make; with metrology.stray_light: remove, the offsets "
                    "product removes them",
            variables=(_V("power", "frequency_y frequency_x", "1", "power spectrum of the projected offsets over "
                                                                   "the white level"),
                       _V("white_level", "", "pixel2", "variance per pixel of the offsets without the components: "
                                                       "the pixels' own offsets and photon noise"),
                       _V("threshold", "", "1", "detection threshold over the white level"),
                       _V("false_alarm", "", "1", "probability that offsets without stray light show a component "
                                                  "(at most)"),
                       _V("n_components", "", "1", "number of components found"),
                       _V("excluded_frequency", "excluded axis", "1/pixel", "frequencies left out of the search: "
                                                                            "the fringes' own K and 2K (x, y)"),
                       _V("component_frequency_x", "component", "1/pixel", "spatial frequency along x, aliased "
                                                                           "into [-1/2, 1/2), f_x >= 0"),
                       _V("component_frequency_y", "component", "1/pixel", "spatial frequency along y"),
                       _V("component_chirp", "component", "1/pixel2", "chirp g"),
                       _V("component_amplitude", "component", "pixel", "amplitude in the projected offsets"),
                       _V("component_phase", "component", "rad", "phase at the reference pixel"),
                       _V("component_frequency_x_error", "component", "1/pixel", "1-sigma error (and so for the "
                                                                                 "other component_*_error)"),
                       _V("component_significance", "component", "1", "peak power over the white level"),
                       _V("stray_mode", "stray_mode row col", "1", "the offsets' directions that removing the "
                                                                   "components takes (5 a component: amplitude, "
                                                                   "phase, frequency x, y, chirp)"),
                       _V("phase_error", RC, "rad", "phase error the components make, in the fitted phase's "
                                                    "sense (NaN outside the fit)"),
                       _V("offset_error", RC, "pixel", "the components' sum in the projected offsets"))),
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
            stage="metrology",
            meaning="a pair's offsets minus the reference pair's (the manifest's first at the pair's wavelength); "
                    "unless metrology.stray_light is off, each difference's stray-light diagnosis, the variables of "
                    "calibration/stray_light_<baseline>.nc prefixed ddx_ and ddy_ (dims too: ddx_component...)",
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
                    "mode (the width mode shares flat and metrology with flat+metrology); grouping: position, "
                    "the (p) accuracy over positions, or group, the (g) one over group means; n the positions "
                    "or groups; accuracy, error and rms_residual in the unit the column unit names (pixel); "
                    "factor the global correction factor (the accuracy corrects each star by its own, so it "
                    "is not rms_residual x factor: docs/astrometry.md); n and factor are pure numbers",
            columns=("flat", "metrology", "grouping", "accuracy", "error", "mode", "method", "n", "rms_residual",
                     "factor", "superimposition", "unit")),
    Product("accuracy_latex", "tables/accuracy.tex", "accuracy_table", "tex", stage="astrometry",
            meaning="the accuracy table as the paper prints it"),
    Product("procrustes_residuals", "tables/procrustes_residuals.nc", "accuracy_table", "netcdf", stage="astrometry",
            meaning="the Procrustes residuals of every calibration mode, of the centroid method its attribute "
                    "centroid_method names",
            variables=(_V("residual", "mode position star axis", "pixel", "residual after the superimposition"),
                       _V("accuracy", "mode", "pixel", "accuracy over positions"))),
    Product("model_residuals", "tables/{model}_residuals.nc", "accuracy_table", "netcdf", stage="astrometry",
            meaning="the residuals of another superimposition of astrometry.superimposition (projective, pose: "
                    "with the pose's tip and tilt where the data identify them, and what it removes of "
                    "Procrustes's tip-tilt excess beside the noise-limited bound)",
            variables=(_V("residual", "mode position star axis", "pixel", "residual after the superimposition"),
                       _V("removal_measured", "mode", "1", "pose: share of Procrustes's tip-tilt excess its accuracy "
                                                          "removes", optional=True),
                       _V("removal_bound", "mode", "1", "pose: the noise-limited share its Fisher information allows",
                          optional=True),
                       _V("tip_tilt_excess", "mode", "pixel", "pose: Procrustes's tip-tilt excess from the fitted tip "
                                                            "and tilt", optional=True))),
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
    ("figure_stray_light", "figures/stray_light_{baseline}", "plot_stray_light",
     "a baseline's offset spectrum with the stray-light components found, and the phase-error map they make",
     "metrology"),
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
    ("figure_stray_light_study", "figures/stray_light_study", "plot_stray_light_study",
     "a pair's offset error under coherent stray light, left in and removed, against the field ratio (beside the "
     "paper's 4e-4 pixel), the coherence length and the fiber-tip positions averaged", "paper"),
    ("figure_paper_comparison", "figures/paper_comparison", "paper_comparison", "every regenerated number beside "
                                                                                "the paper's", "paper"),
]
_PRODUCTS += [Product(key, path, step, "figure", meaning=meaning, stage=stage)
              for key, path, step, meaning, stage in _FIGURES]

#: Every product by its key.
CATALOGUE: dict[str, Product] = {p.key: p for p in _PRODUCTS}

#: Units and long names of the coordinates the products share, set where the step that writes a product sets
#: none (:func:`dice_core.io.write_product`, which refuses a coordinate left without a long name, or numeric
#: without units). CF has no standard_name for a detector's pixel grid, a frame index or a star; none is set.
#: A label coordinate (strings: baseline, axis, mode...) has a long name and no units.
COORDINATE_ATTRS = {
    "row": {"units": "pixel", "long_name": "detector row (pixel centres at integers, counted from 0)", "axis": "Y"},
    "col": {"units": "pixel", "long_name": "detector column (pixel centres at integers, counted from 0)",
            "axis": "X"},
    "frame": {"units": "1", "long_name": "frame index in the acquisition, counted from 0"},
    "position": {"units": "1", "long_name": "star position index of the dataset's manifest"},
    "star": {"units": "1", "long_name": "pseudo-star index in the star pattern, counted from 0"},
    "batch": {"units": "1", "long_name": "batch of consecutive frames, counted from 0"},
    "iteration": {"units": "1", "long_name": "pass of the iterative solution, counted from 1"},
    # the coordinates that are not indices of the data: their attributes alone, where the step sets none
    "all_position": {"units": "1", "long_name": "star position index of the dataset's manifest, every position"},
    "window_row": {"units": "pixel", "long_name": "row within the star window, counted from its first row"},
    "window_col": {"units": "pixel", "long_name": "column within the star window, counted from its first column"},
    "axis": {"long_name": "axis of the detector frame: x along columns, y along rows, z along the detector's normal "
                          "towards the fibers"},
    "xyz": {"long_name": "component of a position in the detector frame: x along columns, y along rows, z along the "
                         "detector's normal towards the fibers"},
    "angle": {"long_name": "rotation of the star stage's pose: tip, tilt (about x, y) and roll (about z)"},
    "baseline": {"long_name": "metrology baseline, named as in the dataset's manifest"},
    "flat": {"long_name": "flat-field acquisition, named as in the dataset's manifest"},
    "fiber": {"long_name": "metrology fiber tip, named as in the dataset's manifest (metrology.geometry.fibers)"},
    "tip_mode": {"units": "1", "long_name": "eigenvector of the fiber tips' information matrix, counted from 0"},
    "kernel": {"units": "1", "long_name": "member of the PRF kernel family (kernel_order, kernel_sigma, "
                                          "kernel_half_width), counted from 0"},
    "mode": {"long_name": "calibration mode of the centroids (docs/products.md, \"Calibration modes and centroid "
                          "methods\")"},
    "model": {"long_name": "superimposition of the star pattern: procrustes, projective or pose"},
    "wavelength": {"units": "m", "long_name": "wavelength in vacuum"},
    "wavelengths": {"units": "1", "long_name": "number of calibration wavelengths of the chromatic mode (their set: "
                                              "dice_core.studies.CALIBRATION_WAVELENGTHS)"},
}
#: The dimensions that get an index coordinate (0, 1, ...) where the dataset has none.
INDEX_DIMS = ("row", "col", "frame", "position", "star", "batch", "iteration")


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


def _regex(product: Product, file_template: str, anchored: bool) -> re.Pattern:
    parts = re.split(r"({\w+})", file_template)
    body = "".join((r"(?P<%s>.+)" % p[1:-1]) if p.startswith("{") and p[1:-1] in ("point", "relpath")
                   else (r"(?P<%s>[^/]+)" % p[1:-1]) if p.startswith("{") else re.escape(p) for p in parts)
    base = "" if product.base == "dataset" else re.escape(SWEEPS_FOLDER) + "/"
    return re.compile(("^" if anchored else r"(?:^|.*/)") + base + body + "$")


def match(path, *, root=None) -> tuple[Product, dict] | None:
    """(entry, wildcards) of the product a file path is an instance of, or None.

    With ``root``, the dataset's results folder, the path relative to it must be the template's whole
    (a path outside the folder is no product); without, the template must end the path. Among the entries
    that fit, the one with the fewest wildcards, then the most literal text (``tables/procrustes_residuals.nc``
    is the Procrustes entry, not ``tables/{model}_residuals.nc``; ``offsets_difference_P24.nc`` a difference,
    which :meth:`dice_core.planning.Plan.check_names` makes sure no manifest name contradicts).
    """
    text = str(path).replace("\\", "/")
    if root is not None:
        text = os.path.relpath(os.path.abspath(text), os.path.abspath(root)).replace("\\", "/")
        if text.startswith("../") or text == "..":
            return None
    found = []
    for product in CATALOGUE.values():
        if root is not None and product.base != "dataset":
            continue
        for template in product.files():
            hit = _regex(product, template, root is not None).match(text)
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
