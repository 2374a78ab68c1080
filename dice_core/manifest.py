"""Read and validate a DICE raw dataset manifest (``dataset.yaml``, format dice-dataset/1).

The format is the contract of ``docs/dataset-format.md``. Validation is
in two layers: the JSON schema ``schemas/dataset.schema.yaml`` checks types and
keys, then :func:`load_manifest` checks what a schema cannot (science area
inside the detector, pairs naming known baselines, distinct star positions,
files present and readable). Every failure raises :class:`dice_core.DatasetError`
naming the manifest (or the missing file) and the problem.

Format 1.2 (several wavelengths) adds a ``wavelength`` (m) to a baseline or a
flat and the pseudo stars' detected ``stars.spectrum``; a baseline without one
takes ``metrology.geometry.wavelength`` when the manifest has a geometry. Both
baselines of a pair must share one wavelength.
"""

from __future__ import annotations

import difflib
import math
import os
import re
import shlex
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import yaml

from dice_core import DatasetError, lazy, yamlfile

jsonschema = lazy.module("jsonschema")  # used when a manifest is checked

__all__ = [
    "Acquisition",
    "BenchGeometry",
    "Detector",
    "Manifest",
    "StarPosition",
    "Spectrum",
    "load_manifest",
    "ManifestError",
    "schema_problems",
    "same_wavelength",
    "parse_manifest",
    "FORMAT",
    "NAME_PATTERN",
    "name_problem",
]

FORMAT = "dice-dataset/1"


@dataclass(frozen=True)
class Detector:
    """Detector description of a manifest.

    Attributes
    ----------
    shape : (int, int)
        (rows, cols) of every frame.
    science_rows, science_cols : (int, int)
        0-based half-open ranges of the science area.
    gain : float
        Electrons per ADU.
    saturation : float
        ADU; a sample at or above it is saturated.
    read_noise : float or None
        ADU rms, when the manifest gives it.
    frame_rate : float or None
        Hz, when the manifest gives it.
    """

    shape: tuple[int, int]
    science_rows: tuple[int, int]
    science_cols: tuple[int, int]
    gain: float
    saturation: float
    read_noise: float | None = None
    frame_rate: float | None = None

    @property
    def science_slices(self) -> tuple[slice, slice]:
        """(row slice, col slice) of the science area, for indexing a (row, col) map."""
        return slice(*self.science_rows), slice(*self.science_cols)

    def science_mask(self):
        """Boolean (row, col) map, True inside the science area."""
        mask = np.zeros(self.shape, dtype=bool)
        mask[self.science_slices] = True
        return mask


@dataclass(frozen=True)
class Acquisition:
    """One acquisition: its files, concatenated in time in the order listed.

    ``label`` says what it is ("dark", "flat fiber_a", "baseline H1H4",
    "position 3") so that errors can name it. ``wavelength`` (m) is the one a
    flat or a baseline states (format 1.2), None where it states none (a
    broadband flat; a baseline of format 1 or 1.1).
    """

    label: str
    files: tuple[Path, ...]
    wavelength: float | None = None


@dataclass(frozen=True)
class Spectrum:
    """The pseudo stars' spectrum as detected (``stars.spectrum``, format 1.2).

    Attributes
    ----------
    wavelength : tuple of float
        Sample wavelengths, m, increasing.
    weight : tuple of float
        Relative photons per unit wavelength at each sample (the source times
        the detector's mean quantum efficiency), >= 0, not all 0.
    """

    wavelength: tuple[float, ...]
    weight: tuple[float, ...]


@dataclass(frozen=True)
class StarPosition:
    """One detector position of the pseudo-star sequence."""

    index: int
    acquisition: Acquisition


@dataclass(frozen=True)
class BenchGeometry:
    """The metrology bench of a format-1.1 manifest (``metrology.geometry``), for spherical-wave fringes.

    Attributes
    ----------
    wavelength : float
        Of the metrology laser, m; in format 1.2 the default of the baselines that state none.
    pixel_pitch : float
        m.
    fibers : dict of str to (float, float, float)
        Nominal fiber-tip positions, m, in the detector frame: origin at the
        nominal centre of pixel (row 0, col 0), x along cols, y along rows, z
        along the normal towards the fibers.
    baseline_fibers : dict of str to (str, str)
        The two fibers of each baseline, in phase order.
    """

    wavelength: float
    pixel_pitch: float
    fibers: dict[str, tuple[float, float, float]]
    baseline_fibers: dict[str, tuple[str, str]]


def _check_geometry(path, g, baselines) -> BenchGeometry:
    """The manifest's ``metrology.geometry``, its values checked beyond what the schema can."""
    for key, low, high in (("wavelength", 1e-7, 1e-5), ("pixel_pitch", 1e-6, 1e-4)):
        if not low < g[key] < high:
            _fail(path, f"metrology.geometry.{key} {g[key]!r} is not in metres ({low:g} to {high:g} m expected)")
    fibers = {}
    for name, xyz in g["fibers"].items():
        if not all(np.isfinite(xyz)) or not xyz[2] > 0:
            _fail(path, f"metrology.geometry.fibers.{name} {xyz} is not a finite position with z > 0 "
                        "(z runs from the detector towards the fibers)")
        fibers[name] = tuple(float(v) for v in xyz)
    for baseline, members in g["baseline_fibers"].items():
        if baseline not in baselines:
            _fail(path, f"metrology.geometry.baseline_fibers names unknown baseline {baseline}")
        unknown = [f for f in members if f not in fibers]
        if unknown:
            _fail(path, f"metrology.geometry.baseline_fibers.{baseline} names unknown fiber(s) {unknown}")
        if fibers[members[0]] == fibers[members[1]]:
            _fail(path, f"metrology.geometry.baseline_fibers.{baseline}: its two fibers are at one position")
    missing = [b for b in baselines if b not in g["baseline_fibers"]]
    if missing:
        # a baseline without its fibers would have to be reduced as plane waves, which the
        # geometry says it is not
        _fail(path, f"metrology.geometry gives no fibers for baseline(s) {missing}")
    return BenchGeometry(float(g["wavelength"]), float(g["pixel_pitch"]), fibers,
                         {b: tuple(m) for b, m in g["baseline_fibers"].items()})


@dataclass(frozen=True)
class Manifest:
    """A validated raw dataset. Paths are absolute (resolved from the manifest's folder)."""

    path: Path
    name: str
    detector: Detector
    dark: Acquisition | None = None
    flats: dict[str, Acquisition] = field(default_factory=dict)
    baselines: dict[str, Acquisition] = field(default_factory=dict)
    pairs: dict[str, tuple[str, str]] = field(default_factory=dict)
    star_approx: tuple[tuple[float, float], ...] = ()
    positions: tuple[StarPosition, ...] = ()
    geometry: BenchGeometry | None = None
    spectrum: Spectrum | None = None

    @property
    def reference_flat(self) -> str | None:
        """Name of the reference flat (the first one listed), or None without flats."""
        return next(iter(self.flats), None)

    @property
    def reference_pair(self) -> str | None:
        """Name of the reference metrology pair (the first one listed), or None."""
        return next(iter(self.pairs), None)

    def baseline_wavelength(self, baseline: str) -> float | None:
        """A baseline's wavelength, m: its own, else ``metrology.geometry.wavelength``, else None (unstated)."""
        own = self.baselines[baseline].wavelength
        if own is not None:
            return own
        return None if self.geometry is None else self.geometry.wavelength

    def pair_wavelength(self, pair: str) -> float | None:
        """The wavelength (m) both baselines of a pair share, or None where they state none."""
        return self.baseline_wavelength(self.pairs[pair][0])

    @property
    def wavelengths(self) -> tuple[float, ...]:
        """The distinct wavelengths of the pairs (to the picometre: :func:`same_wavelength`), m, in the order
        their first pair is listed; empty where no pair states one (formats 1 and 1.1)."""
        found = {}
        for w in (self.pair_wavelength(p) for p in self.pairs):
            if w is not None:
                found.setdefault(_picometres(w), w)
        return tuple(found.values())

    def pairs_at(self, wavelength: float) -> list[str]:
        """The pairs at ``wavelength`` (m), in manifest order (the first is that wavelength's reference)."""
        return [p for p in self.pairs if same_wavelength(self.pair_wavelength(p), wavelength)]

    def flats_at(self, wavelength: float) -> list[str]:
        """The flats that state ``wavelength`` (m), in manifest order."""
        return [f for f, acquisition in self.flats.items() if same_wavelength(acquisition.wavelength, wavelength)]

    def acquisitions(self) -> list[Acquisition]:
        """Every acquisition (dark, flats, baselines, star positions), in manifest order."""
        acquisitions = [self.dark] if self.dark else []
        acquisitions += list(self.flats.values()) + list(self.baselines.values())
        return acquisitions + [p.acquisition for p in self.positions]

    def all_files(self) -> list[Path]:
        """Every FITS file the manifest names, in manifest order."""
        return [f for acq in self.acquisitions() for f in acq.files]


def _schema() -> dict:
    text = resources.files("dice_core").joinpath("schemas/dataset.schema.yaml").read_text()
    return yaml.safe_load(text)


#: What a name that becomes part of a file path may be (the schema's ``$defs.name``): the dataset's name
#: (its results folder) and the keys of flats, baselines and pairs (products such as
#: ``metrology/<baseline>.nc``). Letters, digits, ``_``, ``-`` and ``.``, not starting with ``.`` (so no
#: ``.``, ``..`` nor hidden file), at most 64 characters: the products add their own prefixes, and the
#: temporary files 20 more characters, to a file name that most filesystems cap at 255 bytes.
NAME_PATTERN = _schema()["$defs"]["name"]["pattern"]


def name_problem(value) -> str | None:
    """Why ``value`` cannot be a name that becomes part of a path, or None if it can."""
    if isinstance(value, str) and re.fullmatch(NAME_PATTERN, value):
        return None
    return (f"{value!r} is not a valid name: names become parts of file paths, so they hold only letters, "
            "digits, '_', '-' and '.', do not start with '.', and have at most 64 characters")


def _fail(path, problem):
    raise DatasetError(path, problem)


#: What a wavelength in metres may be, m: the manifest's wavelengths are checked to lie between them, so that one
#: given in nm or um is refused rather than read as a far-infrared or X-ray wavelength.
WAVELENGTH_RANGE = (1e-7, 1e-5)


def _check_wavelength(path, key, value):
    low, high = WAVELENGTH_RANGE
    if not low < value < high:
        _fail(path, f"{key} {value!r} is not in metres ({low:g} to {high:g} m expected)")
    return float(value)


def _picometres(wavelength: float) -> int:
    return round(wavelength * 1e12)


def same_wavelength(a: float | None, b: float | None) -> bool:
    """Whether two wavelengths (m; None: unstated) are the same laser's: equal to the picometre (a manifest
    written by another program may give 633e-9 as 6.330000000001e-07), or both unstated."""
    if a is None or b is None:
        return a is None and b is None
    return _picometres(a) == _picometres(b)


def _nm(wavelength) -> str:
    return "no stated wavelength" if wavelength is None else f"{wavelength * 1e9:.12g} nm"


def _check_pair_wavelengths(path, manifest) -> None:
    """Refuse a pair whose two baselines differ in wavelength (one stated and one not included)."""
    for pair, (first, second) in manifest.pairs.items():
        w1, w2 = manifest.baseline_wavelength(first), manifest.baseline_wavelength(second)
        if not same_wavelength(w1, w2):
            _fail(path, f"metrology.pairs.{pair} mixes wavelengths: {first} at {_nm(w1)}, {second} at {_nm(w2)}; "
                        "both baselines of a pair must share one")


def _spectrum(path, entry) -> Spectrum:
    """The manifest's ``stars.spectrum``, checked beyond what the schema can."""
    wavelength, weight = entry["wavelength"], entry["weight"]
    if len(wavelength) != len(weight):
        _fail(path, f"stars.spectrum gives {len(wavelength)} wavelength(s) and {len(weight)} weight(s); one weight "
                    "per wavelength")
    values = [_check_wavelength(path, "stars.spectrum.wavelength", w) for w in wavelength]
    if any(b <= a for a, b in zip(values, values[1:])):
        _fail(path, "stars.spectrum.wavelength is not strictly increasing")
    if not all(math.isfinite(w) and w >= 0 for w in weight):
        _fail(path, f"stars.spectrum.weight holds a value that is not finite and non-negative: {_shown(weight)}")
    if not sum(weight) > 0:
        _fail(path, "stars.spectrum.weight is zero everywhere: no light")
    return Spectrum(tuple(values), tuple(float(w) for w in weight))


def _shown(value, limit: int = 60) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= limit else f"{text[:limit]}..."


def _is_name_error(error) -> bool:
    """Whether a schema error is a name that fails :data:`NAME_PATTERN` (the dataset's, or a key's)."""
    return error.validator == "pattern" and error.validator_value == NAME_PATTERN and (
        "propertyNames" in error.schema_path or list(error.absolute_path) == ["name"])


def _error_rank(error) -> tuple:
    """The order schema errors are reported in, the first alone: names that would become paths (what a hostile
    manifest is refused for), then the format (a manifest of another format breaks everything after it), then
    unknown keys (a misspelt key also makes its right spelling missing: the typo is the cause), then the rest."""
    kind = (0 if _is_name_error(error) else 1 if list(error.absolute_path) == ["format"] else
            2 if error.validator == "additionalProperties" else 3)
    return kind, [str(p) for p in error.absolute_path]


def _where(path) -> str:
    return ".".join(str(p) for p in path) or "(top level)"


def _error_lines(error) -> list:
    """A schema error as the user needs it, one line per problem, each naming the key path: a name with the value
    found; the format with the value found; each unknown key with the nearest valid one; else the validator's
    message."""
    where = _where(error.absolute_path)
    if _is_name_error(error):
        key = "name" if where == "name" else f"{where} key"
        return [f"manifest {key} {name_problem(error.instance)}"]
    if list(error.absolute_path) == ["format"]:
        return [f"manifest violates {FORMAT} at format: format is {_shown(error.instance)}, and this version reads "
                f"{FORMAT!r} (docs/dataset-format.md)"]
    if error.validator == "additionalProperties" and isinstance(error.instance, dict):
        known, required = list(error.schema.get("properties", {})), error.schema.get("required", [])
        lines = []
        for key in sorted(set(map(str, error.instance)) - set(known)):
            near = _nearest(key, known)
            missing = near and near[0] in required and near[0] not in error.instance  # then the typo is why
            hint = (f"did you mean {near[0]}?{' (a required key)' if missing else ''}" if near else
                    f"keys allowed: {', '.join(known)}")
            lines.append(f"manifest violates {FORMAT} at {_where([*error.absolute_path, key])}: unknown key; {hint}")
        return lines
    return [f"manifest violates {FORMAT} at {where}: {error.message}"]


def _missing_key(error):
    """The required key a ``required`` error says is missing (None for any other error)."""
    if error.validator != "required" or not isinstance(error.instance, dict):
        return None
    return next((k for k in error.validator_value if f"{k!r} is a required property" == error.message), None)


def _typo_targets(error) -> set:
    """(mapping's path, key) of the keys an unknown key is the nearest to: the typo, said once, is the cause of
    their being missing."""
    if error.validator != "additionalProperties" or not isinstance(error.instance, dict):
        return set()
    known = list(error.schema.get("properties", {}))
    where = tuple(map(str, error.absolute_path))
    return {(where, near) for key in set(map(str, error.instance)) - set(known) for near in _nearest(key, known)}


def _nearest(key: str, known) -> list:
    """The known key an unknown one is most likely a typo of, in a list (empty where none is near)."""
    return difflib.get_close_matches(key, known, n=1, cutoff=0.6)


def schema_problems(document) -> list:
    """Every way a parsed manifest violates the format's schema, one line each (without the manifest's path), in
    the order :func:`_error_rank` gives; a required key missing because a key near it is misspelt is said once,
    as the misspelt key."""
    validator = jsonschema.Draft202012Validator(_schema())
    errors = sorted(validator.iter_errors(document), key=_error_rank)
    typos = set().union(*map(_typo_targets, errors))
    return [line for error in errors
            if (tuple(map(str, error.absolute_path)), _missing_key(error)) not in typos
            for line in _error_lines(error)]


class ManifestError(DatasetError):
    """A manifest that violates the format's schema: ``problems``, one line each (without the path); the message
    is the first, with how many more and the command that says them all."""

    def __init__(self, path, problems):
        self.problems = tuple(problems)
        more = len(self.problems) - 1
        # the command as the README gives it, pasteable whatever the path holds
        tail = (f" (and {more} more problem{'s' if more > 1 else ''}: python3 -m dice_core check "
                f"{shlex.quote(str(path))} lists them all)" if more else "")
        super().__init__(path, self.problems[0] + tail)

    def __reduce__(self):
        return type(self), (self.path, self.problems)


def load_manifest(path, *, check_files: bool = True) -> Manifest:
    """Read, validate and resolve a dataset manifest.

    Parameters
    ----------
    path : str or Path
        The ``dataset.yaml`` file.
    check_files : bool, keyword-only
        Also check that every FITS file it names exists and is readable.

    Returns
    -------
    Manifest

    Raises
    ------
    DatasetError
        Missing or unreadable manifest, invalid YAML, a manifest that violates
        the format, or (with ``check_files``) a missing or unreadable FITS file.
    """
    path = Path(path)
    if not path.is_file():
        _fail(path, "manifest not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        _fail(path, f"manifest unreadable ({exc})")
    try:
        document = yamlfile.load(text, path)
    except DatasetError as exc:
        _fail(path, f"manifest {exc.problem}")
    manifest = parse_manifest(document, path)
    if check_files:
        for file in manifest.all_files():
            if not file.is_file():
                _fail(file, f"file named in {path} not found")
            if not os.access(file, os.R_OK):
                _fail(file, f"file named in {path} is not readable")
    return manifest


def parse_manifest(document, path) -> Manifest:
    """Validate a manifest already parsed from YAML; ``path`` locates its files and names it in errors."""
    path = Path(path).resolve()
    if document is None:
        _fail(path, f"manifest is empty (a {FORMAT} manifest is a mapping with format, name and detector)")
    if not isinstance(document, dict):
        _fail(path, f"manifest is a {type(document).__name__}, not a mapping of keys (format, name, "
                    f"detector, ...): {_shown(document)}")
    problems = schema_problems(document)
    if problems:
        raise ManifestError(path, problems)

    root = path.parent

    def acquisition(label, entry, key=None):
        wavelength = entry.get("wavelength")
        if wavelength is not None:
            wavelength = _check_wavelength(path, f"{key}.wavelength", wavelength)
        return Acquisition(label, tuple((root / f).resolve() for f in entry["files"]), wavelength)

    det = document["detector"]
    shape = tuple(det["shape"])
    rows, cols = tuple(det["science_area"]["rows"]), tuple(det["science_area"]["cols"])
    for axis, (lo, hi), size in (("rows", rows, shape[0]), ("cols", cols, shape[1])):
        if not lo < hi <= size:
            _fail(path, f"detector.science_area.{axis} {[lo, hi]} is not a non-empty range "
                        f"inside the detector's {size} {axis}")
    detector = Detector(shape, rows, cols, float(det["gain"]), float(det["saturation"]),
                        det.get("read_noise"), det.get("frame_rate"))

    dark = acquisition("dark", document["dark"]) if "dark" in document else None
    flats = {name: acquisition(f"flat {name}", e, f"flats.{name}") for name, e in document.get("flats", {}).items()}

    metrology = document.get("metrology", {})
    baselines = {name: acquisition(f"baseline {name}", e, f"metrology.baselines.{name}")
                 for name, e in metrology.get("baselines", {}).items()}
    pairs = {}
    for pair, members in metrology.get("pairs", {}).items():
        unknown = [b for b in members if b not in baselines]
        if unknown:
            _fail(path, f"metrology pair {pair} names unknown baseline(s) {unknown}")
        if members[0] == members[1]:
            _fail(path, f"metrology pair {pair} uses baseline {members[0]} twice")
        pairs[pair] = tuple(members)

    geometry = _check_geometry(path, metrology["geometry"], baselines) if "geometry" in metrology else None

    stars = document.get("stars")
    approx, positions, spectrum = (), (), None
    if stars:
        if "spectrum" in stars:
            spectrum = _spectrum(path, stars["spectrum"])
        approx = tuple(tuple(float(v) for v in rc) for rc in stars["approx"])
        indices = [p["index"] for p in stars["positions"]]
        if len(set(indices)) != len(indices):
            _fail(path, "stars.positions has repeated indices")
        positions = tuple(StarPosition(p["index"], acquisition(f"position {p['index']}", p))
                          for p in stars["positions"])
        for r, c in approx:
            if not (0 <= r < shape[0] and 0 <= c < shape[1]):
                _fail(path, f"stars.approx [{r}, {c}] lies outside the detector {list(shape)}")

    manifest = Manifest(path, document["name"], detector, dark, flats, baselines, pairs,
                        approx, positions, geometry, spectrum)
    _check_pair_wavelengths(path, manifest)
    if spectrum is not None and not any(manifest.baseline_wavelength(b) is not None for b in baselines):
        _fail(path, "stars.spectrum is given but no baseline states a wavelength (format 1.2: each baseline's "
                    "wavelength, or metrology.geometry.wavelength): the spectrum has no calibration to go with")
    return manifest
