"""What a workflow run makes of a dataset and a configuration: its targets, what it skips and why, its sweeps.

:class:`Plan` answers, from the manifest and the configuration alone, which
products the run makes (stage by stage, as paths from the catalogue
:mod:`dice_core.products`), which it skips and why (a dataset may lack any
section), and what each job reads. :func:`plan_sweep` turns a configured sweep
into its points and their folders. A problem is a :class:`PlanningError`, one
line naming the configuration key or the manifest. Nothing here knows the
workflow engine: ``workflow/rules/common.smk`` asks and Snakemake runs.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from dice_core import products
from dice_core.centroids import MODES, mode_needs
from dice_core.manifest import same_wavelength

__all__ = ["PlanningError", "Plan", "plan_run", "run_roots", "Sweep", "plan_sweep", "folder_value",
           "reduction_point_config", "module_name", "SWEEPS_FOLDER", "load_dataset", "point_dataset_name"]

#: The sweeps' folder beside the datasets' own, under the results folder: no dataset may be named after it.
SWEEPS_FOLDER = products.SWEEPS_FOLDER


class PlanningError(ValueError):
    """A configuration or dataset the workflow cannot plan: one line naming the key or the file."""


@dataclass
class Plan:
    """The products a run makes of ``manifest`` with ``config`` (a configuration with its defaults set).

    ``dataset_root`` is ``results/<name>`` and ``sweeps_root`` ``results/sweeps``, as the workflow spells
    them; every path this returns lies below one of them.
    """

    manifest: object
    config: dict
    dataset_root: str
    sweeps_root: str
    skipped: list = field(default_factory=list)

    def path(self, key: str, *, suffix: str = "", **wildcards) -> str:
        """The path of one instance of catalogue product ``key``."""
        return products.path_of(key, dataset_root=self.dataset_root, sweeps_root=self.sweeps_root,
                                suffix=suffix, **wildcards)

    def figure(self, key: str, **wildcards) -> list[str]:
        """A figure's PNG and PDF."""
        return [self.path(key, suffix=suffix, **wildcards) for suffix in (".png", ".pdf")]

    def skip(self, what: str, why: str) -> None:
        """Record, once, that the run does not make ``what`` and why."""
        message = f"skipping {what}: {why}"
        if message not in self.skipped:
            self.skipped.append(message)

    def check_names(self) -> None:
        """Refuse manifest names that would make a product's path read as another product's: each path of the
        catalogue's products named by one flat, baseline or pair, for every name the manifest gives, must be
        its own entry's (:func:`dice_core.products.match`). A pair ``difference_P14`` beside ``P14`` would
        make ``offsets_difference_P14.nc`` both pairs' (Snakemake's 12-line AmbiguousRuleException); alone,
        its offsets would be read, and checked, as a difference."""
        m = self.manifest
        names = {"flat": ("flats key", list(m.flats)), "baseline": ("metrology.baselines key", list(m.baselines)),
                 "pair": ("metrology.pairs key", list(m.pairs))}
        for product in products.CATALOGUE.values():
            if len(product.wildcards) != 1 or product.wildcards[0] not in names:
                continue
            key, values = names[product.wildcards[0]]
            for value, template in ((v, t) for v in values for t in product.files()):
                path = template.format(**{product.wildcards[0]: value})
                found = products.match(f"{self.dataset_root}/{path}", root=self.dataset_root)
                if found is None or found[0].key != product.key:
                    raise PlanningError(f"{m.path}: manifest {key} {value!r} would make {path} read as another "
                                        "product's path; rename it")

    # ------------------------------------------------------------------ dark and flat field

    def calibration_targets(self) -> list[str]:
        """Products and figures of the dark and PRNU stages that this dataset allows."""
        m = self.manifest
        if m.dark is None:
            self.skip("dark and PRNU", f"{m.path} has no dark section")
            return []
        targets = [self.path("dark"), *self.figure("figure_dark"), *self.figure("figure_dark_noise")]
        if not m.flats:
            self.skip("PRNU", f"{m.path} has no flats section")
            return targets
        targets += [self.path("prnu"), self.path("bad_pixels")]
        for flat in m.flats:
            targets += self.figure("figure_prnu", flat=flat)
        others = self.compared_flats()
        for flat in others:
            targets += [self.path("prnu_difference", flat=flat), *self.figure("figure_prnu_difference", flat=flat)]
        if not others:
            self.skip("PRNU difference", "the dataset has no two flats of one light (white, or one laser's)")
        return targets

    def compared_flats(self) -> dict:
        """Flat -> the flat its PRNU is compared with: the first of the same light (white flats with the first
        white one, a laser's with its wavelength's first; format 1.2), which the difference's photon-noise
        check needs (a laser flat against a white one would measure colour, not noise)."""
        flats = self.manifest.flats
        out = {}
        for flat, acquisition in flats.items():
            first = next(f for f in flats if same_wavelength(flats[f].wavelength, acquisition.wavelength))
            if first != flat:
                out[flat] = first
        return out

    def prnu_compared_with(self, flat: str) -> str:
        """The PRNU product flat ``flat``'s is compared with (:meth:`compared_flats`): the reference PRNU where
        that is the reference flat's."""
        reference = self.compared_flats()[flat]
        return self.path("prnu") if reference == self.manifest.reference_flat else self.path("flat_prnu",
                                                                                             flat=reference)

    def compared_pairs(self) -> dict:
        """Pair -> the pair its offsets are compared with: its wavelength's first pair (the reference pair for a
        single wavelength), so that the true offsets cancel in the difference."""
        m = self.manifest
        out = {}
        for pair in m.pairs:
            reference = m.pairs_at(m.pair_wavelength(pair))[0]
            if reference != pair:
                out[pair] = reference
        return out

    def prnu_for_metrology(self, baseline: str | None = None) -> list[str]:
        """The PRNU that tells a baseline's fringe solution the intensity map from the fringe, if used: a laser
        flat's at the baseline's wavelength where the dataset has one (format 1.2: what that laser sees), else the
        reference flat's."""
        if not (self.config["metrology"]["use_flat"] and self.manifest.flats):
            return []
        wavelength = None if baseline is None else self.manifest.baseline_wavelength(baseline)
        same = self.manifest.flats_at(wavelength) if wavelength is not None else []
        return [self.path("flat_prnu", flat=same[0])] if same else [self.path("prnu")]

    def bad_pixel_mask(self) -> list[str]:
        """The bad-pixel mask, which every stage that reads pixels leaves its flagged pixels out by, if the
        dataset allows one (a dark and a flat)."""
        return [self.path("bad_pixels")] if self.manifest.dark and self.manifest.flats else []

    # ------------------------------------------------------------------ metrology

    def metrology_unavailable(self) -> str | None:
        """Why this dataset's metrology cannot be reduced, or None."""
        if not self.manifest.baselines:
            return f"{self.manifest.path} has no metrology section"
        if self.manifest.dark is None:
            return f"{self.manifest.path} has no dark to subtract"
        return None

    def prf_baselines(self) -> list[str]:
        """The baselines the PRF widths (calibration/prf.nc) are measured with: all of them, or, where the
        baselines state wavelengths (format 1.2), those at the reference pair's (each wavelength's PRFs are its
        own: calibration/chromatic.nc holds them)."""
        m = self.manifest
        if not m.pairs:
            return list(m.baselines)
        reference = m.pair_wavelength(m.reference_pair)  # None: the baselines that state none
        return [b for b in m.baselines if same_wavelength(m.baseline_wavelength(b), reference)]

    def metrology_products(self) -> list[str]:
        """The metrology products the PRF widths use (:meth:`prf_baselines`)."""
        return [self.path("metrology", baseline=b) for b in self.prf_baselines()]

    def chromatic_unavailable(self) -> str | None:
        """Why this dataset has no calibration across wavelength (calibration/chromatic.nc), or None."""
        if (why := self.metrology_unavailable()) is not None:
            return why
        wavelengths = self.manifest.wavelengths
        if len(wavelengths) < 2:
            at = "one wavelength" if wavelengths else "no stated wavelength"
            return f"{self.manifest.path} has its pairs at {at} (format 1.2 gives each baseline its own)"
        from dice_core.chromatic import wavelength_problem

        for pair in self.manifest.pairs:
            if (problem := wavelength_problem(self.manifest.pair_wavelength(pair))) is not None:
                return f"{self.manifest.path}: pair {pair}'s wavelength {problem}"
        return None

    def chromatic_inputs(self) -> dict:
        """What calibration/chromatic.nc is made of: each wavelength's reference pair's offsets, the metrology of
        every baseline of its pairs (their PRF widths), and its laser flats' PRNU, in the manifest's order."""
        m = self.manifest
        pairs = [m.pairs_at(w)[0] for w in m.wavelengths]
        baselines = [b for w in m.wavelengths for p in m.pairs_at(w) for b in m.pairs[p]]
        flats = [m.flats_at(w)[0] for w in m.wavelengths if m.flats_at(w)]
        return {"offsets": [self.path("offsets", pair=p) for p in pairs],
                "metrology": [self.path("metrology", baseline=b) for b in dict.fromkeys(baselines)],
                "flats": [self.path("flat_prnu", flat=f) for f in flats]}

    def metrology_targets(self) -> list[str]:
        """Products and figures of the metrology stage that this dataset allows."""
        why = self.metrology_unavailable()
        if why is not None:
            self.skip("metrology", why)
            return []
        targets = []
        for baseline in self.manifest.baselines:
            targets += [self.path("metrology", baseline=baseline), *self.figure("figure_metrology", baseline=baseline),
                        self.path("allan", baseline=baseline), *self.figure("figure_allan", baseline=baseline)]
        targets += [self.path("prf"), *self.figure("figure_prf")]
        targets += self.stray_light_products(figures=True)
        pairs = list(self.manifest.pairs)
        for pair in pairs:
            targets += [self.path("offsets", pair=pair), *self.figure("figure_offsets", pair=pair)]
        for pair in self.compared_pairs():
            targets += [self.path("offsets_difference", pair=pair),
                        *self.figure("figure_offsets_difference", pair=pair)]
        if not pairs:
            self.skip("deprojection", "the dataset names no pair of baselines")
        if self.chromatic_unavailable() is None:
            targets += [self.path("chromatic"), *self.figure("figure_chromatic")]
        return targets

    def stray_light_products(self, *, figures: bool = False) -> list[str]:
        """Each baseline's stray-light product (and figure), unless metrology.stray_light is off."""
        if self.config["metrology"]["stray_light"] == "off":
            self.skip("stray-light diagnosis", "config metrology.stray_light is off")
            return []
        out = []
        for baseline in self.manifest.baselines:
            out += [self.path("stray_light", baseline=baseline),
                    *(self.figure("figure_stray_light", baseline=baseline) if figures else [])]
        return out

    def stray_light_removed(self, pair: str) -> list[str]:
        """The stray-light products of a pair's two baselines if their components are removed from its offsets
        (metrology.stray_light: remove), else nothing."""
        if self.config["metrology"]["stray_light"] != "remove":
            return []
        return [self.path("stray_light", baseline=b) for b in self.manifest.pairs[pair]]

    # ------------------------------------------------------------------ pseudo stars and astrometry

    def centroid_pair(self) -> str | None:
        """The metrology pair whose offsets the metrology modes use."""
        pair = self.config["centroids"]["pair"] or self.manifest.reference_pair
        if pair is not None and pair not in self.manifest.pairs:
            pairs = ", ".join(self.manifest.pairs) or "none"
            raise PlanningError(f"config centroids.pair {pair!r} is not a pair of {self.manifest.path} "
                                f"(pairs: {pairs})")
        return pair

    def other_methods(self) -> list[str]:
        """The centroid methods besides centroids.method, each under centroids/<method>/, in the order of
        centroids.methods, whose order decides nothing else."""
        method = self.config["centroids"]["method"]
        return [m for m in self.config["centroids"]["methods"] if m != method]

    def centroid_modes(self) -> list[str]:
        """The configured calibration modes that this dataset allows, saying why of the others."""
        m = self.manifest
        if not m.positions:
            self.skip("centroids", f"{m.path} has no star positions")
            return []
        if m.dark is None:
            self.skip("centroids", f"{m.path} has no dark to subtract")
            return []
        from dice_core.centroids import science_area_problem

        problem = science_area_problem(m.detector, self.config["centroids"]["half_size"])
        if problem is not None:
            raise PlanningError(f"{m.path}: {problem}")
        modes, configured = [], self.config["centroids"]["modes"]
        # every mode (the default) means every mode the dataset can have: a dataset of one wavelength is not
        # told, on every run, that it has no calibration across wavelength
        every_mode = list(configured) == list(MODES)
        for mode in configured:
            needs = mode_needs(mode)
            if "chromatic" in needs and every_mode and len(m.wavelengths) < 2:
                continue
            if "flat" in needs and not m.flats:
                self.skip(f"centroid mode {mode}", "the dataset has no flat field")
            elif "offsets" in needs and self.centroid_pair() is None:
                self.skip(f"centroid mode {mode}", "the dataset names no pair of metrology baselines")
            elif needs & {"offsets", "widths"} and self.metrology_unavailable() is not None:
                self.skip(f"centroid mode {mode}", f"the metrology is not reduced ({self.metrology_unavailable()})")
            elif "chromatic" in needs and self.chromatic_unavailable() is not None:
                self.skip(f"centroid mode {mode}", f"no calibration across wavelength: {self.chromatic_unavailable()}")
            elif "chromatic" in needs and m.spectrum is None and self.config["centroids"]["spectrum"] is None:
                self.skip(f"centroid mode {mode}", f"no spectrum of the stars ({m.path} has no stars.spectrum and "
                                                   "config centroids.spectrum is null)")
            elif "chromatic" in needs and (why := self.spectrum_problem()) is not None:
                self.skip(f"centroid mode {mode}", why)
            else:
                modes.append(mode)
        return modes

    def spectrum_problem(self) -> str | None:
        """Why the stars' spectrum cannot be used by the chromatic mode (the manifest's, where config
        centroids.spectrum does not replace it), or None. A configured one that cannot be is a configuration
        error (:class:`PlanningError`)."""
        from dice_core import chromatic

        configured = self.config["centroids"]["spectrum"]
        if configured is not None:
            try:
                chromatic.stars_spectrum(configured, None)
            except ValueError as exc:
                raise PlanningError(str(exc)) from None
            return None
        spectrum = self.manifest.spectrum
        problem = chromatic.spectrum_problem(spectrum.wavelength, spectrum.weight)
        return None if problem is None else f"{self.manifest.path}: stars.spectrum {problem}"

    def centroid_products(self) -> list[str]:
        """Every centroid product: each allowed mode with centroids.method, then with each other method."""
        modes = self.centroid_modes()
        return [*(self.path("centroids", mode=mode) for mode in modes),
                *(self.path("centroids_by_method", method=method, mode=mode)
                  for mode in modes for method in self.other_methods())]

    def centroid_targets(self) -> list[str]:
        """Centroid products and figures of the configured modes that this dataset allows."""
        targets = []
        for mode in self.centroid_modes():
            targets += [self.path("centroids", mode=mode), *self.figure("figure_centroids", mode=mode)]
            targets += [self.path("centroids_by_method", method=method, mode=mode) for method in self.other_methods()]
        return targets

    def centroid_calibrations(self, mode: str) -> dict:
        """The calibration products a mode needs (:data:`dice_core.centroids.MODES`), by input name."""
        inputs = {"bad_pixels": self.bad_pixel_mask()} if self.bad_pixel_mask() else {}
        needs = mode_needs(mode)
        if "flat" in needs:
            inputs["prnu"] = self.path("prnu")
        if "offsets" in needs:
            inputs["offsets"] = self.path("offsets", pair=self.centroid_pair())
        if "widths" in needs:
            inputs["prf"] = self.path("prf")
        if "chromatic" in needs:
            inputs["chromatic"] = self.path("chromatic")
        return inputs

    def extra_superimpositions(self) -> list[str]:
        """The superimpositions configured besides Procrustes (which always runs): projective, pose."""
        from dice_core.superimposition import configured_superimpositions

        return configured_superimpositions(self.config["astrometry"]["superimposition"])[1:]

    def astrometry_targets(self) -> list[str]:
        """The accuracy table of the centroid modes this dataset allows, and its figures."""
        if not self.centroid_modes():
            return []
        return [self.path("accuracy_table"), self.path("accuracy_latex"),
                *self.figure("figure_procrustes_residuals"), *self.figure("figure_barycentre_residuals"),
                *(f for model in self.extra_superimpositions() for f in self.figure("figure_model_residuals",
                                                                                    model=model))]

    def default_targets(self) -> list[str]:
        """Everything the default target makes of this dataset."""
        return [*self.calibration_targets(), *self.metrology_targets(), *self.centroid_targets(),
                *self.astrometry_targets()]

    # ------------------------------------------------------------------ sweeps and the paper

    @property
    def sweeps(self) -> dict:
        """Every configured sweep, planned (:func:`plan_sweep`), by name."""
        if not hasattr(self, "_sweeps"):
            self._sweeps = {name: plan_sweep(name, spec) for name, spec in self.config["sweeps"].items()}
        return self._sweeps

    def sweep_points(self, name: str) -> list[str]:
        """The point products of a configured sweep, in the configuration's order."""
        if name not in self.sweeps:
            raise PlanningError(f"no sweep named {name!r} in config sweeps (sweeps: {', '.join(self.sweeps) or 'none'})")
        return [self.path("sweep_point", sweep=name, point=folder) for folder in self.sweeps[name].folders]

    def point_parameters(self, name: str, folder: str) -> dict:
        """The parameters of a sweep's point, by its folder (dotted bench keys or option names)."""
        sweep = self.sweeps[name]
        return sweep.points[sweep.folders.index(folder)]

    def paper_sweep(self, study: str) -> str:
        """The sweep that config paper.<study> names, checked to run that study."""
        name = self.config["paper"][study]
        if name not in self.sweeps or self.sweeps[name].study != study:
            raise PlanningError(f"config paper.{study}: {name!r} is not a sweep of study {study} in config sweeps")
        return name

    def comparison_inputs(self) -> dict:
        """What the paper comparison reads: the studies, and this dataset's accuracy table and Allan products."""
        inputs = {"offset_bias": self.sweep_points(self.paper_sweep("offset_bias")),
                  "stray_light_study": self.sweep_points(self.paper_sweep("stray_light")),
                  "error_propagation": self.path("error_propagation"),
                  "deflation": self.path("procrustes_deflation"),
                  "chromatic": self.sweep_points(self.paper_sweep("chromatic"))}
        if self.astrometry_targets():
            inputs["accuracy"] = self.path("accuracy_table")
        if self.metrology_unavailable() is None:
            inputs["allan"] = [self.path("allan", baseline=baseline) for baseline in self.manifest.baselines]
            inputs["stray_light"] = self.stray_light_products()
        return inputs


# ---------------------------------------------------------------------- sweeps

@dataclass(frozen=True)
class Sweep:
    """A configured sweep: its spec, each point's parameters (dotted keys to values, typed as the point's
    folder spells them) and folder, in the configuration's order, and the folder column of each key."""

    name: str
    spec: dict
    points: tuple[dict, ...]
    folders: tuple[str, ...]
    columns: dict

    @property
    def study(self) -> str:
        return self.spec["study"]


def folder_value(value):
    """How a list or mapping value is spelt in a point's folder name: a list's items joined by commas, or a
    short hash where an item is not a plain word or number, so that a list is one folder of its own."""
    if not isinstance(value, (list, dict)):
        return value
    if isinstance(value, list) and all(isinstance(v, (str, int, float)) and re.fullmatch(r"[A-Za-z0-9_.+-]+", str(v))
                                       for v in value):
        return ",".join(map(str, value)) or "none"
    return f"h{hashlib.sha256(json.dumps(value, sort_keys=True).encode()).hexdigest()[:10]}"


def _column_values(values: list) -> list:
    """A column's values as a table of one type holds them (what Snakemake's Paramspace, over pandas, names
    folders by): integers and floats together become floats; anything else stays as it is."""
    numbers = [v for v in values if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if len(numbers) == len(values) and any(isinstance(v, float) for v in values):
        return [float(v) for v in values]
    return list(values)


def plan_sweep(name: str, spec: dict) -> Sweep:
    """The points of ``config sweeps.<name>``: one parameter and its values, a grid (every combination, the
    first parameter varying slowest) or a table of points. A point's folder is ``<key>~<value>`` per parameter,
    ``/``-separated in the parameters' sorted order, a key by its last part (``prnu_rms~5e-05``)."""
    if "points" in spec:
        points = [dict(p) for p in spec["points"]]
    elif "grid" in spec:
        keys = list(spec["grid"])
        points = [dict(zip(keys, combination)) for combination in itertools.product(*spec["grid"].values())]
    else:
        points = [{spec["parameter"]: value} for value in spec["values"]]
    keys = sorted({key for p in points for key in p})
    if any(set(p) != set(keys) for p in points):
        raise PlanningError(f"config sweeps.{name}.points: every point must set the same parameters {keys}")
    columns = {key.rsplit(".", 1)[-1]: key for key in keys}
    if len(columns) != len(keys):
        raise PlanningError(f"config sweeps.{name}: parameters {keys} share a last name; folders would clash")
    if spec["study"] != "reduction" and any(isinstance(v, (list, dict)) for p in points for v in p.values()):
        raise PlanningError(f"config sweeps.{name}: a parameter's value must be a number, a string or a boolean "
                            "(one folder per point; lists, e.g. of centroids.modes, only in a reduction sweep)")
    if any(p[key] is None for p in points for key in keys):
        raise PlanningError(f"config sweeps.{name}: a parameter's value is null, which names no folder")
    spelt = {key: _column_values([folder_value(p[key]) for p in points]) for key in keys}
    for key, values in spelt.items():
        bad = next((v for v in values if not re.fullmatch(r"[A-Za-z0-9_+-][A-Za-z0-9_.,+-]*", str(v))), None)
        if bad is not None:  # it names the point's folder: no '/', no leading '.', no braces
            raise PlanningError(f"config sweeps.{name}: {key} value {bad!r} cannot name a point's folder (letters, "
                                "digits, '.', '_', '+', '-' only, not starting with '.')")
    folders = tuple("/".join(f"{column}~{spelt[key][i]}" for column, key in columns.items())
                    for i in range(len(points)))
    if len(set(folders)) != len(folders):
        raise PlanningError(f"config sweeps.{name}: a point is listed twice")
    typed = tuple({key: (p[key] if isinstance(p[key], (list, dict)) else spelt[key][i]) for key in keys}
                  for i, p in enumerate(points))
    return Sweep(name, spec, typed, folders, columns)


def reduction_point_config(config: dict, sweep: Sweep, *, index: int, simulated: bool, raw: str,
                           sweeps_root: str) -> dict:
    """The workflow configuration of point ``index`` of a reduction sweep: ``config`` with the point's keys set.

    ``simulation.<key>`` sets a key of the simulation preset (the dataset is simulated again, in the point's
    folder); any other dotted key sets the reduction's config, and the point then reads the run's raw files
    (``raw``). ``simulated``: whether the run's dataset is a simulation preset.
    """
    from dice_core.overrides import apply_dotted

    name, point, folder = sweep.name, sweep.points[index], sweep.folders[index]
    reserved = [k for k in point if k.split(".")[0] in ("dataset", "raw", "results", "sweeps", "paper")]
    if reserved or sweep.spec.get("bench") or sweep.spec.get("options"):
        raise PlanningError(f"config sweeps.{name}: a reduction sweep varies the reduction's config or "
                            f"simulation.<key>, not {reserved or 'bench or options'}")
    simulation = {k.split(".", 1)[1]: v for k, v in point.items() if k.startswith("simulation.")}
    reduction = {k: v for k, v in point.items() if not k.startswith("simulation.")}
    if simulation and not simulated:
        raise PlanningError(f"config sweeps.{name}: simulation.* parameters need a simulation preset as the dataset")
    try:
        point_config = apply_dotted({k: v for k, v in config.items() if k != "sweeps"}, reduction, what="config")
    except (KeyError, ValueError) as exc:
        raise PlanningError(f"config sweeps.{name}: {exc.args[0]}") from None
    point_config["sweeps"] = {n: s for n, s in config.get("sweeps", {}).items() if s["study"] != "reduction"}
    point_config["simulation"] = {**(config.get("simulation") or {}), **simulation}
    point_config["results"] = f"{sweeps_root}/{name}/{folder}"
    point_config["raw"] = None if simulation else raw  # a simulated point's own raw files, in its folder
    return point_config


def point_dataset_name(config: dict, point_config: dict, *, manifest_name: str, presets: Path) -> str:
    """The name of a reduction point's dataset: the run's, or, where the point sets simulation.* keys, that of
    the preset with the point's overrides (:func:`dice_core.simulation.load_preset` names it by their hash)."""
    from dice_core import simulation

    if point_config["simulation"] == (config.get("simulation") or {}):
        return manifest_name
    return simulation.load_preset(Path(presets) / f"{config['dataset']}.yaml",
                                  overrides=point_config["simulation"]).name


def module_name(sweep: str, folder: str) -> str:
    """The name of a reduction sweep point's workflow module, from the point (its folder) and not its place in
    the list, so that removing a point renames no other's rules."""
    words = re.sub(r"\W+", "_", f"{sweep}_{folder}").strip("_")[:60]
    return f"sweep_{words}_{hashlib.sha256(folder.encode()).hexdigest()[:6]}"


def load_dataset(value: str, *, presets: Path, results: str, raw=None, overrides=None):
    """(manifest, simulation config or None) of the configuration's ``dataset``: a manifest's path, or the
    name of a simulation preset in the folder ``presets`` (its dataset laid out in ``raw``, by default
    ``<results>/<name>/raw``, with the preset's ``overrides``)."""
    from dice_core import DatasetError, simulation
    from dice_core.manifest import load_manifest, parse_manifest

    if value.endswith((".yaml", ".yml")) or "/" in value:
        try:
            return load_manifest(value), None
        except DatasetError as exc:
            raise PlanningError(f"config dataset: {exc}") from None
    preset = Path(presets) / f"{value}.yaml"
    if not preset.is_file():
        known = sorted(p.stem for p in Path(presets).glob("*.yaml"))
        raise PlanningError(f"config dataset={value!r} is neither a manifest path (*.yaml) nor a simulation preset "
                            f"{known}")
    try:
        sim = simulation.load_preset(preset, overrides=overrides or {})
        folder = Path(raw) if raw else Path(results) / sim.name / "raw"
        return parse_manifest(simulation.dataset_layout(sim), folder / "dataset.yaml"), sim
    except ValueError as exc:  # DatasetError included: a preset's name or keys
        raise PlanningError(str(exc)) from None


def run_roots(manifest, config: dict) -> tuple[str, str]:
    """The folders a run of ``config`` on ``manifest`` writes below: ``results/<name>`` and ``results/sweeps``."""
    return f"{config['results']}/{manifest.name}", f"{config['results']}/{SWEEPS_FOLDER}"


def plan_run(manifest, config: dict) -> tuple[Plan, list[str]]:
    """The plan of the workflow's run of ``config`` (defaults set) on ``manifest``, and its default targets, with
    every check the workflow makes of them before a job runs: the dataset's name, the names its products'
    paths are made of, and every default target planned (what is skipped recorded in ``Plan.skipped``). The
    workflow and the dataset checker (``python -m dice_core check``) both plan through this.

    Raises
    ------
    PlanningError
        The first problem, in one line.
    """
    plan = Plan(manifest, config, *run_roots(manifest, config))
    check_dataset_name(manifest)
    plan.check_names()
    return plan, plan.default_targets()


def check_dataset_name(manifest) -> None:
    """Refuse a dataset named after the results folder's sweeps folder."""
    if manifest.name == SWEEPS_FOLDER:
        raise PlanningError(f"{manifest.path}: manifest name {SWEEPS_FOLDER!r} is the results folder's sweeps "
                            "folder; rename the dataset")


def paper_pdf_pages(plan: Plan, captions: Path) -> list[tuple[str, str]]:
    """(figure, its caption file) of the PDF reproduction report: the paper's simulations, then this dataset's
    figures that the paper shows, those the dataset allows."""
    pages = [(plan.path(key, suffix=".png"), str(captions / f"{stem}.rst"))
             for key, stem in (("figure_paper_comparison", "paper_comparison"), ("figure_offset_bias", "offset_bias"),
                               ("figure_error_propagation", "error_propagation"),
                               ("figure_stray_light_study", "stray_light_study"))]
    pages.append((plan.path("chromatic_study_figure", suffix=".png", sweep=plan.paper_sweep("chromatic")),
                  str(captions / "chromatic_study.rst")))
    manifest = plan.manifest
    if plan.metrology_unavailable() is None:
        first = next(iter(manifest.baselines))
        pages += [(plan.path("figure_metrology", suffix=".png", baseline=first), str(captions / "metrology.rst")),
                  (plan.path("figure_allan", suffix=".png", baseline=first), str(captions / "allan.rst"))]
        if manifest.pairs:
            pages.append((plan.path("figure_offsets", suffix=".png", pair=next(iter(manifest.pairs))),
                          str(captions / "offsets.rst")))
    if plan.astrometry_targets():
        modes = [m for m in ("flat+metrology", "raw") if m in plan.centroid_modes()]
        pages += [(plan.path("figure_centroids", suffix=".png", mode=m), str(captions / "centroids.rst"))
                  for m in modes[:1]]
        pages += [(plan.path("figure_barycentre_residuals", suffix=".png"), str(captions / "barycentre_residuals.rst")),
                  (plan.path("figure_procrustes_residuals", suffix=".png"),
                   str(captions / "procrustes_residuals.rst"))]
    return pages
