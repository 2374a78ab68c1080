"""Simulated DICE testbed: writes a raw dataset in the dice-dataset/1 format plus ``truth.nc``.

The numerical model follows the paper's section "Numerical simulations":

- **Detector**: one truncated hyper-Gaussian PRF per pixel
  (:class:`dice_core.detector.PixelResponse`) with per-pixel sensitivity
  (white PRNU plus dust pixels and bright row bands), offsets and widths; a
  bias pattern and per-pixel read noise; photon noise through the gain.
- **Dark**: bias plus read noise.
- **Flats**: a broad illumination with a gradient, different for each fiber,
  times the pixel sensitivities, with source flux fluctuations.
- **Metrology**: moving Young fringes ``B(t) E(r) [1 + V(r)/V0 (A(t)/B(t)) sin(K.r + phi(t))]``
  integrated against each PRF; laser intensity noise scales B and A together, a
  much smaller noise scales A alone; the phase is swept back and forth over
  several 2 pi in piecewise-exponential segments, with white jitter and an
  optional random walk.
- **Pseudo stars**: five Gaussian PSFs (centre and corners of a square) whose
  centres at each detector position come from an exact 3-D projection of fixed
  star directions through the detector pose (translation, tip, tilt, roll), so
  tip-tilt produces the paper's non-homogeneous scale (appendix D).
- **Chromatic pixels** (off by default; docs/simulation.md, "Chromatic pixels"):
  each pixel's sensitivity, offsets and PRF widths change with wavelength
  (:mod:`dice_core.chromatic`); lasers at several wavelengths, laser flats and
  broadband stars, summed over their spectrum (format 1.2).

Every random quantity comes from a generator seeded by ``(seed, name)``, so a
configuration always gives the same dataset. Frames are generated and written
in chunks: memory does not grow with the number of frames.

Units: pixel for positions, rad for angles and phases, adu for signals,
electrons per adu for the gain.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from dice_core import DatasetError, lazy, stray_light, yamlfile
from dice_core.detector import PixelResponse
from dice_core.geometry import affine_basis as geometry_affine
from dice_core.geometry import two_source_phase
from dice_core.io import write_cube, write_product, write_text
from dice_core.polynomials import polynomial_design
from dice_core.manifest import FORMAT
from dice_core.overrides import apply_dotted, typed_value

xr = lazy.module("xarray")

__all__ = [
    "SimulationConfig",
    "load_preset",
    "dataset_layout",
    "make_truth",
    "pixel_response",
    "acquisition_chunks",
    "file_jobs",
    "write_file",
    "write_manifest",
    "simulate_dataset",
    "project_stars",
    "fiber_tips",
    "two_source_phase",
    "metrology_baselines",
    "metrology_pairs",
    "flat_acquisitions",
    "is_chromatic",
    "wavelength_grid",
    "wavelength_tag",
]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- configuration

def _build(cls, values, where):
    """Instantiate a config dataclass from a dict, refusing unknown keys with a clear message."""
    values = dict(values or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ValueError(f"simulation config {where}: unknown key(s) {unknown}; known: {sorted(names)}")
    for f in dataclasses.fields(cls):
        if f.name in values and isinstance(values[f.name], list):
            values[f.name] = tuple(values[f.name])
    return cls(**values)


@dataclass(frozen=True)
class DetectorConfig:
    """Detector model. Lengths in pixel, signals in adu."""

    shape: tuple = (80, 84)              # rows, cols
    science_rows: tuple = (2, 79)        # half-open
    science_cols: tuple = (10, 83)
    gain: float = 10.0                   # electrons per adu
    saturation: float = 65535.0          # adu
    bias: float = 500.0                  # adu, mean bias level
    bias_column_rms: float = 2.0         # adu, column-to-column bias structure
    bias_row_slope: float = 3.0          # adu, bias ramp from first to last row
    read_noise: float = 4.0              # adu rms (median over pixels)
    read_noise_spread: float = 0.03      # relative pixel-to-pixel spread of the read noise
    prnu_rms: float = 2e-3               # white PRNU, relative
    dust_pixels: int = 6                 # pixels darkened by dust
    dust_depth: float = 0.05             # deepest dust loss, relative
    # Defects (none by default, the idealisation of the paper's simulations): dead pixels and
    # columns (no response), hot pixels (a dark signal of hot_level adu per frame, with its shot noise)
    dead_pixels: int = 0
    dead_columns: int = 0
    hot_pixels: int = 0
    hot_level: float = 2000.0            # adu per frame
    bright_bands: int = 2                # bright horizontal bands
    bright_band_amplitude: float = 3e-3  # relative excess sensitivity in a band
    offset_rms: float = 1e-3             # pixel, rms of dx and dy
    prf_order: float = 4.0               # hyper-Gaussian order n
    prf_sigma: float = 0.3               # pixel, hyper-Gaussian scale parameter
    prf_width_spread: float = 0.01       # relative pixel-to-pixel spread of the PRF scale
    prf_half_width: float = 0.5          # pixel, truncation half-width
    # Asymmetric pixel responses: each PRF times (1 + sx u)(1 + sy v), slopes drawn with this rms,
    # 1/pixel. 0 (the default) keeps them symmetric, the idealisation of the paper's simulations.
    prf_slope_rms: float = 0.0
    frame_rate: float = 108.0            # Hz
    dtype: str = "uint16"                # storage type of the cubes (float32 avoids quantisation)
    photon_noise: bool = True            # False gives noiseless frames (with read_noise 0, float32)
    # A sample whose mean holds at least this many electrons gets its photon noise from the normal
    # law of the Poisson mean and variance (drawn with the read noise, several times faster than
    # Poisson draws); a fainter one from Poisson. The normal law misses only the Poisson skewness
    # 1/sqrt(N): 3.2% at 1000 e-, 0.5% or less for the metrology's 4e4-1.6e5 e-. None: Poisson for
    # all (docs/simulation.md).
    gaussian_photons_above: float | None = 1000.0

    def __post_init__(self):
        rows, cols = self.shape
        if not (0 <= self.science_rows[0] < self.science_rows[1] <= rows
                and 0 <= self.science_cols[0] < self.science_cols[1] <= cols):
            raise ValueError(f"simulation config detector: science area {self.science_rows}, "
                             f"{self.science_cols} does not fit in {self.shape}")
        science = (self.science_rows[1] - self.science_rows[0]) * (self.science_cols[1] - self.science_cols[0])
        for key in ("dead_pixels", "dead_columns", "hot_pixels", "hot_level"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"simulation config detector: {key} must be >= 0, got {getattr(self, key)!r}")
        if self.dead_columns > self.science_cols[1] - self.science_cols[0] or (
                self.dead_pixels + self.hot_pixels > science // 2):
            raise ValueError("simulation config detector: more defects than the science area holds "
                             f"({self.dead_columns} dead columns, {self.dead_pixels + self.hot_pixels} pixels)")
        if not self.prf_slope_rms >= 0:
            raise ValueError(f"simulation config detector: prf_slope_rms must be >= 0, got {self.prf_slope_rms!r}")
        if self.gaussian_photons_above is not None and not self.gaussian_photons_above >= 0:
            raise ValueError("simulation config detector: gaussian_photons_above must be >= 0 (electrons) or null, "
                             f"got {self.gaussian_photons_above!r}")
        if self.dtype not in ("uint16", "int32", "float32"):
            raise ValueError(f"simulation config detector: dtype {self.dtype!r} is not uint16, int32 or float32")


@dataclass(frozen=True)
class DarkConfig:
    frames: int = 200


@dataclass(frozen=True)
class FiberConfig:
    """Flat-field illumination of one fiber: relative change across the detector."""

    gradient: tuple = (0.0, 0.0)   # relative change from the first to the last col (x) and row (y)
    curvature: float = 0.0         # relative change from the centre to a corner


@dataclass(frozen=True)
class FlatConfig:
    frames: int = 400
    level: float = 20000.0         # adu for a pixel of sensitivity 1 at the detector centre
    flux_rsd: float = 5e-4         # source flux fluctuation from frame to frame, relative
    fibers: dict = field(default_factory=lambda: {
        "fiber_a": {"gradient": [0.015, -0.008]},
        "fiber_b": {"gradient": [-0.010, 0.012]},
    })
    # A chromatic detector (section chromatic): the fibers' flats are white light of this detected spectrum
    # (dice_core.chromatic.SPECTRA), and each of these wavelengths (m) adds a laser flat, laser_<nm>, under the
    # first fiber's illumination (format 1.2: the flat states its wavelength)
    spectrum: str = "flat"
    wavelengths: tuple = ()


@dataclass(frozen=True)
class BaselineConfig:
    period: float        # fringe period, pixel
    angle_deg: float     # direction of the wavevector from +x towards +y, degrees
    # With metrology.spherical: the midpoint of the baseline's two fiber tips, m, in the detector
    # plane from the detector centre (its offset from the detector normal)
    midpoint: tuple = (0.0, 0.0)


@dataclass(frozen=True)
class MetrologyConfig:
    frames: int = 4000                 # per baseline
    mean_level: float = 10000.0        # B, adu
    amplitude: float = 6000.0          # A, adu
    laser_rsd: float = 1e-2            # laser intensity noise (scales B and A), relative
    amplitude_rsd: float = 1e-3        # amplitude-only noise, relative
    phase_jitter: float = 1e-2         # rad rms, white
    phase_random_walk: float = 0.0     # rad per sqrt(frame)
    intensity_random_walk: float = 0.0  # relative per sqrt(frame), scales B and A
    # Stray light: a parasitic fringe from the same laser (its phase follows the sweep) with its
    # own wavevector, amplitude relative to A, and an extra path that random-walks (a drift).
    # Unlike the walks above, common to all pixels and absorbed by the per-frame phase and
    # level, it moves each pixel's apparent phase differently: correlated noise in the offsets.
    stray_light: float = 0.0           # relative to A
    stray_light_period: float = 7.0    # pixel
    stray_light_angle_deg: float = 40.0
    stray_light_phase_walk: float = 0.0  # rad per sqrt(frame), of the extra path
    # The flat is a white LED's, the metrology a 633 nm laser's: the pixels' sensitivities differ
    # between the two by a chromatic PRNU of this rms (a real bench's: about 5e-4), relative.
    chromatic_prnu_rms: float = 0.0
    # Speckle in the laser illumination: a random multiplicative pattern of this rms contrast, white
    # noise smoothed by a Gaussian of standard deviation speckle_grain (pixel), one per baseline,
    # common to the fringe level and amplitude (intensity speckle only: no phase or visibility speckle).
    speckle_rms: float = 0.0
    speckle_grain: float = 3.0
    sweep_cycles: float = 4.0          # fringe periods swept in one direction
    sweep_frames: int = 500            # frames of one one-way sweep
    sweep_time_constant: float = 0.3   # of the exponential segments, in sweeps
    envelope_sigma: float = 300.0      # pixel, Gaussian beam radius of the fringe envelope
    envelope_centre: tuple = (25.0, -15.0)  # pixel, beam centre from the detector centre (x, y)
    visibility_gradient: tuple = (0.03, -0.02)  # relative change of visibility across x and y
    # Spherical-wave fringes from two fiber tips (point sources) per baseline, fiber_distance from
    # the detector, baselines of the length that gives each baseline's period at the centre. False:
    # plane waves, the fibers at infinity (the idealisation of the paper's simulations).
    spherical: bool = False
    fiber_distance: float = 0.6        # m, tips to detector (the paper's design: 600 mm)
    wavelength: float = 633.0e-9       # m, of the metrology laser
    pixel_pitch: float = 24.0e-6       # m
    # The manifest's nominal tips are off the true ones by a random vector of this length range, m
    # (a bench measures them to about 1 mm); the truth holds the true ones.
    tip_error: tuple = (0.5e-3, 1.0e-3)
    # Every fiber tip (true and nominal) moved by this vector, m, the stray sources staying where the unmoved
    # tips put them (stray_light): the paper's fiber-tip positions. Omitted from to_dict() when zero.
    tip_shift: tuple = (0.0, 0.0, 0.0)
    # Which acquisition of the bench: another draw of the metrology frames' noise (photon, read, laser,
    # phase), the detector and the fringe sweep's shape kept. Omitted from to_dict() when zero.
    acquisition: int = 0
    baselines: dict = field(default_factory=lambda: {
        "H1H4": {"period": 2.4, "angle_deg": 2.0},
        "V1V4": {"period": 2.4, "angle_deg": 93.0},
        "H2H4": {"period": 4.0, "angle_deg": -3.0},
        "V2V4": {"period": 4.0, "angle_deg": 88.5},
    })
    pairs: dict = field(default_factory=lambda: {"P14": ["H1H4", "V1V4"], "P24": ["H2H4", "V2V4"]})
    # Lasers of several wavelengths (m; format 1.2): every baseline and pair above at each, those at `wavelength`
    # under their own names, the others as <name>_<nm> (H1H4_450, P14_450), each of the configured period (a
    # bench sets each laser's fiber tips for it); empty: the one laser at `wavelength`, no wavelength stated
    wavelengths: tuple = ()


@dataclass(frozen=True)
class StarsConfig:
    positions: int = 12
    frames: int = 16                   # per position
    flux: float = 2.5e5                # adu per star per frame, sensitivity 1
    flux_rsd: float = 1e-3             # source fluctuation from frame to frame
    background: float = 10.0           # adu per pixel
    psf_sigma: float = 1.3             # pixel
    pattern_centre: tuple = (46.0, 40.0)  # pixel (x, y), central star at the mid position
    pattern_side: float = 40.0         # pixel, side of the square of corner stars
    step: tuple = (0.0, 0.17)          # pixel per position (x, y) of the stage
    step_jitter: float = 0.01          # pixel rms, irregularity of each step
    tip_tilt_pv: float = 2e-3          # rad, peak-to-valley of the tip and tilt random walks
    roll_rms: float = 1e-4             # rad
    distance: float = 25000.0          # pixel, mirror to detector (600 mm / 24 um)
    off_axis_deg: float = 2.0          # degrees, off-axis angle of the star field
    # The pseudo stars' detected spectrum (dice_core.chromatic.SPECTRA: flat, warm, cool), over the paper's
    # 400-800 nm band, each star the sum of its monochromatic images on a chromatic detector (section
    # chromatic); written to the manifest (format 1.2). None: the stars see the detector at metrology.wavelength
    spectrum: str | None = None


@dataclass(frozen=True)
class ChromaticConfig:
    """The detector's response against wavelength (docs/simulation.md, "Chromatic pixels"; :mod:`dice_core.chromatic`).

    Each pixel's sensitivity, PRF centre and PRF scale are their values at ``metrology.wavelength`` plus two
    depth profiles' changes (the drift and surface kernels), each a white pixel-to-pixel field. ``amplitude``
    scales them all; the rms values are the changes from metrology.wavelength to 400 nm at amplitude 1 (the
    default bench's PRNU, offsets and width spread). 0 (the default): an achromatic detector, today's.
    """

    amplitude: float = 0.0
    sensitivity_rms: float = 2e-3      # relative
    offset_rms: float = 1e-3           # pixel, each axis
    width_rms: float = 0.01            # relative, of each PRF scale
    width_trend: float = 0.05          # relative: every PRF's scale wider at 400 nm by this much (drift kernel)
    surface_share: float = 0.5         # of each change's variance at 400 nm, from the surface kernel
    thickness: float = 16.0e-6         # m, the silicon from the entrance surface to the wells
    surface_depth: float = 0.3e-6      # m, of the entrance surface's layer

    def __post_init__(self):
        for key in ("amplitude", "sensitivity_rms", "offset_rms", "width_rms"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"simulation config chromatic: {key} must be >= 0, got {getattr(self, key)!r}")
        if not 0 <= self.surface_share <= 1:
            raise ValueError(f"simulation config chromatic: surface_share must be in [0, 1], got {self.surface_share!r}")
        if not (1e-6 <= self.thickness <= 1e-3 and 1e-9 <= self.surface_depth <= self.thickness):
            raise ValueError("simulation config chromatic: thickness and surface_depth are in metres (thickness "
                             f"1e-6 to 1e-3, surface_depth below it), got {self.thickness!r}, {self.surface_depth!r}")


@dataclass(frozen=True)
class StraySourceConfig:
    """A stray source (a baffle vane's edge) re-emitting a copy of one metrology fiber's wave
    (:mod:`dice_core.stray_light`)."""

    fiber: str                         # the fiber whose wave it re-emits, e.g. H1H4a (b + "a" or b + "b")
    offset_mrad: tuple = (0.0, 0.0)    # its direction from the detector centre minus the fiber tip's, mrad (x, y)
    distance: float = 0.3              # m, its height above the detector plane (the tips are at fiber_distance)
    extra_path: float = 0.01           # m, its optical path to the detector centre minus the fiber's direct one
    field_ratio: float | None = None   # its field over the direct wave's; None: stray_light.field_ratio


@dataclass(frozen=True)
class StrayLightConfig:
    """Coherent stray light of the metrology laser (:mod:`dice_core.stray_light`); off by default (no sources,
    and omitted from to_dict(), so that the presets' datasets are those of before it existed, bit for bit)."""

    field_ratio: float = 1e-3          # sqrt(I1 / I0) of every source that does not set its own
    coherence_length: float | None = None  # m, the OPD at which the laser's coherence falls to 1/e; None: coherent
    sources: tuple = ()                # StraySourceConfig mappings
    # flat -> metrology fiber: that flat is lit coherently by the laser through that fiber, so it carries the
    # fiber's stray sources' static pattern (speckle of contrast 2 eps gamma); the others stay incoherent (LED)
    coherent_flats: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SimulationConfig:
    """A whole simulated testbed. See ``config/presets/*.yaml`` for annotated presets."""

    name: str = "sim-default"
    seed: int = 20150926
    frames_per_file: int = 5000
    chunk_frames: int = 256            # at most; fewer on a large detector (simulation_chunk_frames)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    dark: DarkConfig = field(default_factory=DarkConfig)
    flats: FlatConfig = field(default_factory=FlatConfig)
    metrology: MetrologyConfig = field(default_factory=MetrologyConfig)
    stars: StarsConfig = field(default_factory=StarsConfig)
    stray_light: StrayLightConfig = field(default_factory=StrayLightConfig)
    chromatic: ChromaticConfig = field(default_factory=ChromaticConfig)

    @classmethod
    def from_dict(cls, values: dict) -> "SimulationConfig":
        values = dict(values or {})
        sections = {"detector": DetectorConfig, "dark": DarkConfig, "flats": FlatConfig,
                    "metrology": MetrologyConfig, "stars": StarsConfig, "stray_light": StrayLightConfig,
                    "chromatic": ChromaticConfig}
        built = {key: _build(sub, values.pop(key, {}), key) for key, sub in sections.items()}
        top = _build(cls, values, "(top level)")
        cfg = dataclasses.replace(top, **built)
        for name, b in cfg.metrology.baselines.items():
            baseline = _build(BaselineConfig, b, f"metrology.baselines.{name}")
            if any(baseline.midpoint) and not cfg.metrology.spherical:
                raise ValueError(f"simulation config metrology.baselines.{name}: a midpoint places fiber tips, "
                                 "which only spherical-wave fringes have (metrology.spherical: true)")
        for name, f in cfg.flats.fibers.items():
            _build(FiberConfig, f, f"flats.fibers.{name}")
        for pair, members in cfg.metrology.pairs.items():
            unknown = [m for m in members if m not in cfg.metrology.baselines]
            if unknown:
                raise ValueError(f"simulation config metrology.pairs.{pair}: unknown baseline(s) {unknown}")
        _check_stray_light(cfg)
        _check_wavelengths(cfg)
        return cfg

    @property
    def has_stray_light(self) -> bool:
        """Whether any stray source has a field: the frames and the truth then carry it."""
        s = self.stray_light
        return any((s.field_ratio if src.get("field_ratio") is None else src["field_ratio"]) != 0
                   for src in s.sources)

    def to_dict(self) -> dict:
        """The configuration as plain JSON types; the keys added after the presets (:data:`_LATER_KEYS`) only
        where they differ from their defaults, so that a preset's truth and records stay as they were."""
        values = json.loads(json.dumps(dataclasses.asdict(self)))
        defaults = json.loads(json.dumps(dataclasses.asdict(SimulationConfig())))
        for *sections, key in _LATER_KEYS:
            here, default = values, defaults
            for section in sections:
                here, default = here[section], default[section]
            if here[key] == default[key]:
                del here[key]
        return values


#: The configuration's keys added after the first presets (stray light, fiber-tip shifts, acquisitions,
#: wavelengths, the chromatic detector), as paths of sections.
_LATER_KEYS = (("stray_light",), ("metrology", "tip_shift"), ("metrology", "acquisition"), ("chromatic",),
               ("metrology", "wavelengths"), ("flats", "wavelengths"), ("flats", "spectrum"), ("stars", "spectrum"))


def _check_stray_light(cfg: SimulationConfig) -> None:
    """Refuse stray sources that name no fiber of the bench, or a bench without fiber tips (plane waves)."""
    s = cfg.stray_light
    fibers = [b + suffix for b in cfg.metrology.baselines for suffix in "ab"]
    for i, spec in enumerate(s.sources):
        src = _build(StraySourceConfig, spec, f"stray_light.sources[{i}]")
        if not cfg.metrology.spherical:
            raise ValueError("simulation config stray_light.sources: stray sources re-emit a fiber's wave, which "
                             "only spherical-wave fringes have (metrology.spherical: true)")
        if src.fiber not in fibers:
            raise ValueError(f"simulation config stray_light.sources[{i}]: fiber {src.fiber!r} is not a fiber of "
                             f"the bench ({', '.join(fibers)})")
        if not 0 < src.distance < cfg.metrology.fiber_distance:
            raise ValueError(f"simulation config stray_light.sources[{i}]: distance {src.distance!r} m is not "
                             f"between the detector and the fibers (0 to {cfg.metrology.fiber_distance} m)")
    for flat, fiber in s.coherent_flats.items():
        if flat not in cfg.flats.fibers or fiber not in fibers:
            raise ValueError(f"simulation config stray_light.coherent_flats: {flat!r}: {fiber!r} must map a flat "
                             f"({', '.join(cfg.flats.fibers)}) to a metrology fiber ({', '.join(fibers)})")
    if s.coherence_length is not None and not s.coherence_length > 0:
        raise ValueError(f"simulation config stray_light.coherence_length must be > 0 (m) or null, got "
                         f"{s.coherence_length!r}")
    if cfg.metrology.wavelengths and (cfg.has_stray_light or s.coherence_length is not None):
        # the stray waves' fringes are drawn at metrology.wavelength, for the baselines of one laser
        raise ValueError("simulation config stray_light: stray light and a finite coherence length are simulated "
                         "for one laser wavelength; metrology.wavelengths lists several (not simulated together)")


def load_preset(path, overrides: dict | None = None) -> SimulationConfig:
    """Read a simulation preset (YAML of :class:`SimulationConfig` keys; missing keys take defaults).

    ``overrides`` sets dotted keys on top of the file's (``{"detector.prf_width_spread": 0.02}``;
    :func:`dice_core.overrides.apply_dotted`). Overrides make another dataset: unless they set ``name``,
    its name is the preset's followed by a short hash of them (``sim-default-1a2b3c4d``), so that its
    products never overwrite the preset's own.
    """
    path = Path(path)
    try:
        values = yamlfile.read(path) or {}
    except DatasetError as exc:
        raise ValueError(f"{path}: cannot read simulation preset ({exc.problem})") from None
    if overrides:
        try:
            changed = apply_dotted(values, overrides, what="simulation preset")
        except (KeyError, ValueError) as exc:
            raise ValueError(f"{path}: override {exc.args[0]}") from None
        if "name" not in overrides:
            typed = {k: typed_value(k, v, None) for k, v in overrides.items()}
            digest = hashlib.sha256(json.dumps(typed, sort_keys=True).encode()).hexdigest()[:8]
            changed["name"] = f"{values.get('name', SimulationConfig.name)}-{digest}"
        values = changed
    try:
        return SimulationConfig.from_dict(values)
    except (TypeError, ValueError) as exc:
        where = f" with overrides {overrides}" if overrides else ""
        raise ValueError(f"{path}{where}: {exc}") from None


# --------------------------------------------------------------------------- wavelengths (format 1.2)

def _check_wavelengths(cfg: SimulationConfig) -> None:
    """Refuse wavelengths that are not metres in the silicon table, a repeated one, or unknown spectra."""
    from dice_core.chromatic import SPECTRA, absorption_length

    lists = {"metrology.wavelengths": cfg.metrology.wavelengths, "flats.wavelengths": cfg.flats.wavelengths,
             "metrology.wavelength": (cfg.metrology.wavelength,)}
    for key, values in lists.items():
        for value in values:
            try:
                absorption_length(value)
            except (TypeError, ValueError):
                raise ValueError(f"simulation config {key}: {value!r} is not a wavelength in metres within 380-1000 "
                                 "nm (the silicon absorption table)") from None
        if len({wavelength_tag(v) for v in values}) != len(values):
            raise ValueError(f"simulation config {key}: a wavelength is listed twice (to the nm): {list(values)}")
    for key, name in (("stars.spectrum", cfg.stars.spectrum), ("flats.spectrum", cfg.flats.spectrum)):
        if name is not None and name not in SPECTRA:
            raise ValueError(f"simulation config {key}: unknown spectrum {name!r}; spectra are {', '.join(SPECTRA)}")


def wavelength_tag(wavelength: float) -> str:
    """A wavelength (m) as the names of its acquisitions spell it: nanometres, rounded (``450``)."""
    return f"{round(wavelength * 1e9):d}"


def _laser_order(cfg: SimulationConfig) -> list[float]:
    """The lasers' wavelengths (m): metrology.wavelength first where listed, so that its pairs come first
    (the manifest's first pair is the reference), then the others in the configured order."""
    m = cfg.metrology
    listed = list(m.wavelengths)
    return sorted(listed, key=lambda w: wavelength_tag(w) != wavelength_tag(m.wavelength))


def _at(name: str, wavelength: float, cfg: SimulationConfig) -> str:
    same = wavelength_tag(wavelength) == wavelength_tag(cfg.metrology.wavelength)
    return name if same else f"{name}_{wavelength_tag(wavelength)}"


def metrology_baselines(cfg: SimulationConfig) -> dict:
    """Every simulated baseline: name -> (its entry of metrology.baselines, its wavelength in m or None).

    Without metrology.wavelengths, the configured baselines with no stated wavelength; with them, every
    configured baseline at each wavelength (:class:`MetrologyConfig`), metrology.wavelength's first.
    """
    m = cfg.metrology
    if not m.wavelengths:
        return {name: (b, None) for name, b in m.baselines.items()}
    return {_at(name, w, cfg): (b, float(w)) for w in _laser_order(cfg) for name, b in m.baselines.items()}


def metrology_pairs(cfg: SimulationConfig) -> dict:
    """Every simulated pair: name -> its two baselines, each configured pair at each wavelength."""
    m = cfg.metrology
    if not m.wavelengths:
        return {pair: list(members) for pair, members in m.pairs.items()}
    return {_at(pair, w, cfg): [_at(b, w, cfg) for b in members] for w in _laser_order(cfg)
            for pair, members in m.pairs.items()}


def flat_acquisitions(cfg: SimulationConfig) -> dict:
    """Every simulated flat: name -> (its fiber's illumination entry, its wavelength in m or None): the fibers'
    white-light flats, then a laser flat ``laser_<nm>`` per flats.wavelengths under the first fiber's light."""
    out = {name: (fiber, None) for name, fiber in cfg.flats.fibers.items()}
    first = next(iter(cfg.flats.fibers.values()), {})
    out.update({f"laser_{wavelength_tag(w)}": (first, float(w)) for w in cfg.flats.wavelengths})
    return out


def is_chromatic(cfg: SimulationConfig) -> bool:
    """Whether the simulation involves wavelengths beyond today's single one: a chromatic detector, several
    lasers, laser flats or broadband stars. Its truth then holds the response at each wavelength."""
    return bool(cfg.chromatic.amplitude or cfg.metrology.wavelengths or cfg.flats.wavelengths
                or cfg.stars.spectrum is not None)


def wavelength_grid(cfg: SimulationConfig) -> np.ndarray:
    """The wavelengths (m, increasing) the truth holds the response at: metrology.wavelength, every laser's and
    laser flat's, and the samples of the stars' and the white flats' spectra (dice_core.chromatic)."""
    from dice_core.chromatic import named_spectrum

    values = [cfg.metrology.wavelength, *cfg.metrology.wavelengths, *cfg.flats.wavelengths]
    if _broadband(cfg):
        for name in {cfg.stars.spectrum, cfg.flats.spectrum} - {None}:
            values += list(named_spectrum(name)[0])
    return np.array(sorted({round(float(v) * 1e9, 6): float(v) for v in values}.values()))


def _broadband(cfg: SimulationConfig) -> bool:
    """Whether the simulation integrates over spectra: broadband stars, or a chromatic detector (whose white
    flats then see the lamp's spectrum)."""
    return bool(cfg.chromatic.amplitude) or cfg.stars.spectrum is not None


# --------------------------------------------------------------------------- layout

def _n_files(frames: int, per_file: int) -> int:
    return max(1, math.ceil(frames / per_file))


def _file_frames(frames: int, per_file: int) -> list[tuple[int, int]]:
    return [(i * per_file, min(frames, (i + 1) * per_file)) for i in range(_n_files(frames, per_file))]


def _acquisitions(cfg: SimulationConfig):
    """(kind, name, frames, relative file stem) of every acquisition, in manifest order."""
    out = [("dark", "dark", cfg.dark.frames, "dark/dark")]
    out += [("flat", f, cfg.flats.frames, f"flat/{f}") for f in flat_acquisitions(cfg)]
    out += [("baseline", b, cfg.metrology.frames, f"metrology/{b}") for b in metrology_baselines(cfg)]
    return out


def acquisition_files(cfg: SimulationConfig, kind: str, *, name: str) -> list[str]:
    """Relative paths of the files of one acquisition (kind: dark, flat, baseline or position)."""
    if kind == "position":
        return [f"stars/pos_{int(name):03d}.fits"]
    for k, n, frames, stem in _acquisitions(cfg):
        if (k, n) == (kind, name):
            return [f"{stem}_{i:03d}.fits" for i in range(_n_files(frames, cfg.frames_per_file))]
    raise KeyError(f"no {kind} acquisition named {name!r} in this simulation")


def file_jobs(cfg: SimulationConfig) -> dict[str, tuple[str, object, int, int]]:
    """Every file the simulator writes: relative path -> (kind, name, first frame, end frame).

    Each file can be simulated on its own (by :func:`write_file`), so a
    workflow can spread them over jobs.
    """
    jobs = {}
    for kind, name, frames, _ in _acquisitions(cfg):
        for rel, (start, stop) in zip(acquisition_files(cfg, kind, name=name),
                                      _file_frames(frames, cfg.frames_per_file)):
            jobs[rel] = (kind, name, start, stop)
    for index in range(1, cfg.stars.positions + 1):
        jobs[acquisition_files(cfg, "position", name=index)[0]] = ("position", index, 0, cfg.stars.frames)
    return jobs


def _manifest_geometry(cfg: SimulationConfig) -> dict:
    """The manifest's ``metrology.geometry`` (format 1.1): the nominal tips, as measured on a bench."""
    _, nominal = fiber_tips(cfg)
    return {"wavelength": cfg.metrology.wavelength, "pixel_pitch": cfg.metrology.pixel_pitch,
            "fibers": {f: [float(v) for v in xyz] for f, xyz in nominal.items()},
            "baseline_fibers": {b: [b + "a", b + "b"] for b in metrology_baselines(cfg)}}


def dataset_layout(cfg: SimulationConfig) -> dict:
    """The manifest the simulator writes for ``cfg`` (a dict in the dice-dataset/1 format).

    Known without simulating anything, so that a workflow can plan its jobs.
    """
    d = cfg.detector
    nominal = _nominal_pattern(cfg.stars)
    first = project_stars(nominal, _nominal_poses(cfg.stars)[:1], cfg=cfg)[0]
    return {
        "format": FORMAT,
        "name": cfg.name,
        "detector": {
            "shape": list(d.shape),
            "science_area": {"rows": list(d.science_rows), "cols": list(d.science_cols)},
            "gain": d.gain,
            "saturation": d.saturation,
            "read_noise": d.read_noise,
            "frame_rate": d.frame_rate,
        },
        "dark": {"files": acquisition_files(cfg, "dark", name="dark")},
        "flats": {f: {"files": acquisition_files(cfg, "flat", name=f), **_stated(w)}
                  for f, (_, w) in flat_acquisitions(cfg).items()},
        "metrology": {
            # broadband stars' spectrum goes with the lasers' wavelength (format 1.2): stated even for one laser
            "baselines": {b: {"files": acquisition_files(cfg, "baseline", name=b),
                              **_stated(cfg.metrology.wavelength if w is None and cfg.stars.spectrum else w)}
                          for b, (_, w) in metrology_baselines(cfg).items()},
            "pairs": metrology_pairs(cfg),
            **({} if not cfg.metrology.spherical else {"geometry": _manifest_geometry(cfg)}),
        },
        "stars": {
            "approx": [[round(float(y), 1), round(float(x), 1)] for x, y in first],
            "positions": [{"index": i + 1, "files": acquisition_files(cfg, "position", name=i + 1)}
                          for i in range(cfg.stars.positions)],
            **_manifest_spectrum(cfg),
        },
    }


def _stated(wavelength) -> dict:
    """An acquisition's ``wavelength`` key (format 1.2), where it states one."""
    return {} if wavelength is None else {"wavelength": wavelength}


def _manifest_spectrum(cfg: SimulationConfig) -> dict:
    """The manifest's ``stars.spectrum`` (format 1.2), where the stars are broadband."""
    if cfg.stars.spectrum is None:
        return {}
    from dice_core.chromatic import named_spectrum

    wavelength, weight = named_spectrum(cfg.stars.spectrum)
    return {"spectrum": {"wavelength": [float(w) for w in wavelength], "weight": [round(float(w), 6) for w in weight]}}


# --------------------------------------------------------------------------- geometry of the stars

def _nominal_pattern(stars: StarsConfig) -> np.ndarray:
    """(star, xy) nominal positions at the mid position: centre, then the four corners."""
    cx, cy = stars.pattern_centre
    h = stars.pattern_side / 2
    return np.array([[cx, cy], [cx - h, cy - h], [cx + h, cy - h], [cx - h, cy + h], [cx + h, cy + h]])


def _nominal_poses(stars: StarsConfig) -> np.ndarray:
    """(position, 6) poses without irregularities: translation (x, y, z) pixel, tip, tilt, roll rad."""
    p = np.arange(stars.positions) - (stars.positions - 1) / 2
    poses = np.zeros((stars.positions, 6))
    poses[:, 0] = p * stars.step[0]
    poses[:, 1] = p * stars.step[1]
    return poses


def _rotation(tip, tilt, roll):
    """Rotation matrices (..., 3, 3) = Rz(roll) Ry(tilt) Rx(tip)."""
    c1, s1, c2, s2, c3, s3 = np.cos(tip), np.sin(tip), np.cos(tilt), np.sin(tilt), np.cos(roll), np.sin(roll)
    one, zero = np.ones_like(tip), np.zeros_like(tip)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, c1, -s1], -1), np.stack([zero, s1, c1], -1)], -2)
    ry = np.stack([np.stack([c2, zero, s2], -1), np.stack([zero, one, zero], -1), np.stack([-s2, zero, c2], -1)], -2)
    rz = np.stack([np.stack([c3, -s3, zero], -1), np.stack([s3, c3, zero], -1), np.stack([zero, zero, one], -1)], -2)
    return rz @ ry @ rx


def project_stars(pattern: np.ndarray, poses: np.ndarray, *, cfg: SimulationConfig) -> np.ndarray:
    """Exact 3-D projection of fixed star directions onto a moving, tilting detector.

    Parameters
    ----------
    pattern : ndarray (star, 2)
        (x, y) of each star on the detector at the reference pose, pixel; fixes
        the star directions.
    poses : ndarray (position, 6)
        Detector translation (x, y, z) in pixel, then tip (about x), tilt
        (about y) and roll (about z) in rad, about the detector centre.
    cfg : SimulationConfig
        Distance mirror-detector and off-axis angle of the field.

    Returns
    -------
    ndarray (position, star, 2)
        (x, y) of each star in detector pixel coordinates.

    Notes
    -----
    The mirror is the origin; at the reference pose the detector centre
    ``(xc, yc)`` is at ``D = (L tan(theta_off), 0, L)`` and pixel (x, y) at
    ``D + (x - xc, y - yc, 0)``. A star's direction is that of its reference
    point. At pose (T, R), pixel (x, y) is at ``D + T + R (x - xc, y - yc, 0)``;
    the star lands where its ray meets that plane, a 3x3 linear solve.
    """
    st = cfg.stars
    rows, cols = cfg.detector.shape
    xc, yc = (cols - 1) / 2, (rows - 1) / 2
    centre = np.array([st.distance * math.tan(math.radians(st.off_axis_deg)), 0.0, st.distance])
    directions = np.column_stack([pattern[:, 0] - xc, pattern[:, 1] - yc, np.zeros(len(pattern))]) + centre
    rot = _rotation(poses[:, 3], poses[:, 4], poses[:, 5])                  # (P, 3, 3)
    origin = centre + poses[:, :3]                                          # (P, 3)
    n_pos, n_star = len(poses), len(pattern)
    system = np.empty((n_pos, n_star, 3, 3))
    system[..., 0] = rot[:, None, :, 0]
    system[..., 1] = rot[:, None, :, 1]
    system[..., 2] = -directions[None, :, :]
    rhs = np.broadcast_to(-origin[:, None, :], (n_pos, n_star, 3))
    solution = np.linalg.solve(system, rhs[..., None])[..., 0]
    return np.stack([solution[..., 0] + xc, solution[..., 1] + yc], axis=-1)


# --------------------------------------------------------------------------- truth

def _acquisition(cfg: SimulationConfig) -> tuple:
    """The names that make another acquisition's noise its own (none for the first: the streams of before)."""
    return (f"acquisition {cfg.metrology.acquisition}",) if cfg.metrology.acquisition else ()


def _rng(cfg: SimulationConfig, *names) -> np.random.Generator:
    key = [cfg.seed] + [zlib.crc32(str(n).encode()) for n in names]
    return np.random.default_rng(key)


def _remove_affine(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Subtract the least-squares plane a + b x + c y over ``mask`` (offsets are defined up to an affine map).

    The plane fitted over the mask is subtracted from the whole detector, which
    :func:`dice_core.geometry.remove_modes` (the samples' own projection) does not do.
    """
    rows, cols = np.indices(values.shape)
    design = polynomial_design(cols.ravel(), rows.ravel(), degree=1)
    coef, *_ = np.linalg.lstsq(design[mask.ravel()], values[mask], rcond=None)
    return values - (design @ coef).reshape(values.shape)


BAD_DEAD, BAD_HOT, BAD_DUST = 1, 2, 4  # the truth's bad_pixel flags (dice_core.calibration.bad_pixel_mask's)


def _defects(cfg: SimulationConfig, mask: np.ndarray) -> np.ndarray:
    """The truth's defect flags (row, col): dead pixels and columns, hot pixels, in the science area."""
    d = cfg.detector
    flags = np.zeros(d.shape, np.int8)
    if not (d.dead_pixels or d.dead_columns or d.hot_pixels):
        return flags
    rng = _rng(cfg, "defects")
    for c in rng.choice(np.arange(*d.science_cols), d.dead_columns, replace=False):
        flags[slice(*d.science_rows), c] |= BAD_DEAD
    sr, sc = np.nonzero(mask & (flags == 0))  # single defects off the dead columns
    chosen = rng.choice(len(sr), d.dead_pixels + d.hot_pixels, replace=False)
    dead, hot = chosen[:d.dead_pixels], chosen[d.dead_pixels:]
    flags[sr[dead], sc[dead]] |= BAD_DEAD
    flags[sr[hot], sc[hot]] |= BAD_HOT
    return flags


def _sensitivity(cfg: SimulationConfig, mask: np.ndarray) -> np.ndarray:
    d = cfg.detector
    rng = _rng(cfg, "sensitivity")
    rows, cols = d.shape
    sens = 1.0 + d.prnu_rms * rng.standard_normal(d.shape)
    for _ in range(d.bright_bands):
        centre, width = rng.uniform(d.science_rows[0], d.science_rows[1]), rng.uniform(1.0, 2.5)
        profile = np.exp(-0.5 * ((np.arange(rows) - centre) / width) ** 2)
        sens *= 1.0 + d.bright_band_amplitude * profile[:, None]
    sr, sc = np.nonzero(mask)
    dust = np.zeros(d.shape, bool)
    for _ in range(d.dust_pixels):
        k = rng.integers(len(sr))
        r, c = sr[k], sc[k]
        depth = d.dust_depth * rng.uniform(0.3, 1.0)
        sens[r, c] *= 1.0 - depth
        dust[r, c] = True
        # dust shadows spill a little onto the neighbours
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            if 0 <= r + dr < rows and 0 <= c + dc < cols:
                sens[r + dr, c + dc] *= 1.0 - 0.2 * depth
    return sens / sens[mask].mean(), dust


def _phase_history(cfg: SimulationConfig, name: str, rng) -> np.ndarray:
    m = cfg.metrology
    t = np.arange(m.frames)
    segment, within = np.divmod(t, m.sweep_frames)
    tau = m.sweep_time_constant
    progress = (1 - np.exp(-(within / m.sweep_frames) / tau)) / (1 - np.exp(-1 / tau))
    forward = segment % 2 == 0
    sweep = 2 * np.pi * m.sweep_cycles * np.where(forward, progress, 1 - progress)
    phase = rng.uniform(0, 2 * np.pi) + sweep + m.phase_jitter * rng.standard_normal(m.frames)
    if m.phase_random_walk:
        phase += m.phase_random_walk * np.cumsum(rng.standard_normal(m.frames))
    return phase


def fiber_tips(cfg: SimulationConfig, *, shifted: bool = True) -> tuple[dict, dict]:
    """True and nominal fiber-tip positions (name -> (x, y, z), m, detector frame) of spherical-wave baselines.

    Two tips per baseline ``b``, named ``b + "a"`` and ``b + "b"`` in phase
    order, ``metrology.fiber_distance`` from the detector, centred on the
    baseline's ``midpoint`` (from the detector centre), along its wavevector's
    direction and as far apart as gives the baseline's period at the detector
    centre (about wavelength x distance / (period x pitch), corrected for the
    obliquity). The nominal tips, written to the manifest as a bench would
    measure them, are off by ``tip_error`` (a random direction, one stream
    per baseline). ``shifted``: with ``metrology.tip_shift`` added (the tips' position on the bench; the
    stray sources are placed from the unshifted ones).
    """
    m, (rows, cols) = cfg.metrology, cfg.detector.shape
    centre_px = np.array([(cols - 1) / 2, (rows - 1) / 2])
    centre = centre_px * m.pixel_pitch
    true, nominal = {}, {}
    for name, (b, own) in metrology_baselines(cfg).items():
        b = _build(BaselineConfig, b, f"metrology.baselines.{name}")
        wavelength = m.wavelength if own is None else own  # each laser's tips set for the configured period
        direction = np.array([math.cos(math.radians(b.angle_deg)), math.sin(math.radians(b.angle_deg))])
        mid = centre + np.asarray(b.midpoint, float)

        def tips(length):
            return [np.array([*(mid + sign * length * direction), m.fiber_distance]) for sign in (-0.5, 0.5)]

        # on the normal the period is wavelength x distance / (length x pitch); off it, the obliquity
        # shortens the projected baseline: rescale once so that the period at the centre is the asked one
        length = wavelength * m.fiber_distance / (b.period * m.pixel_pitch)
        _, kx, ky = two_source_phase(*centre_px, *tips(length), wavelength=wavelength, pixel_pitch=m.pixel_pitch)
        length *= (2 * np.pi / b.period) / float(np.hypot(kx, ky))
        rng = _rng(cfg, "fiber tips", name)
        for suffix, tip in zip("ab", tips(length)):
            error = rng.standard_normal(3)
            error *= rng.uniform(*m.tip_error) / np.linalg.norm(error)
            true[name + suffix], nominal[name + suffix] = tip, tip + error
    if shifted and any(m.tip_shift):  # only then: a zero shift adds nothing, not even a rounding
        shift = np.asarray(m.tip_shift, float)
        true = {f: tip + shift for f, tip in true.items()}
        nominal = {f: tip + shift for f, tip in nominal.items()}
    return true, nominal


def stray_sources(cfg: SimulationConfig) -> list:
    """The bench's stray sources (:class:`dice_core.stray_light.StraySource`), fixed by the unshifted tips."""
    if not cfg.has_stray_light:
        return []
    rows, cols = cfg.detector.shape
    return stray_light.place_sources(cfg.stray_light.sources, fiber_tips(cfg, shifted=False)[0],
                                     centre=((cols - 1) / 2, (rows - 1) / 2), pitch=cfg.metrology.pixel_pitch,
                                     default_ratio=cfg.stray_light.field_ratio)


def _pixel_response_truth(cfg: SimulationConfig, mask: np.ndarray) -> tuple[PixelResponse, np.ndarray]:
    """The detector's pixel response (offsets, PRF widths and slopes, sensitivity with dust and dead pixels)
    and its defect flags (row, col) of :data:`BAD_DEAD`, :data:`BAD_HOT`, :data:`BAD_DUST`."""
    d = cfg.detector
    rng = _rng(cfg, "offsets")
    dx = _remove_affine(d.offset_rms * rng.standard_normal(d.shape), mask)
    dy = _remove_affine(d.offset_rms * rng.standard_normal(d.shape), mask)
    rng = _rng(cfg, "widths")
    sigma_x = d.prf_sigma * (1 + d.prf_width_spread * rng.standard_normal(d.shape))
    sigma_y = d.prf_sigma * (1 + d.prf_width_spread * rng.standard_normal(d.shape))
    slope_x = slope_y = None
    if d.prf_slope_rms:
        rng = _rng(cfg, "prf slopes")
        slope_x, slope_y = d.prf_slope_rms * rng.standard_normal((2, *d.shape))
    defects = _defects(cfg, mask)
    sensitivity, dust = _sensitivity(cfg, mask)
    defects[dust & (defects == 0)] |= BAD_DUST
    sensitivity[(defects & BAD_DEAD) > 0] = 0.0
    prf = PixelResponse(sensitivity, dx, dy, sigma_x, sigma_y, d.prf_order, d.prf_half_width, slope_x, slope_y)
    return prf, defects


def _bias_and_read_noise(cfg: SimulationConfig, defects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bias (columns, a row slope; hot pixels' dark signal on top) and read noise maps (row, col), adu."""
    d = cfg.detector
    rows, cols = d.shape
    rng = _rng(cfg, "bias")
    bias = (d.bias + d.bias_column_rms * rng.standard_normal(cols)[None, :]
            + d.bias_row_slope * np.linspace(0, 1, rows)[:, None])
    read_noise = d.read_noise * (1 + d.read_noise_spread * rng.standard_normal(d.shape))
    hot = (defects & BAD_HOT) > 0
    bias[hot] += d.hot_level  # a hot pixel's dark signal, with its shot noise as a read noise
    read_noise[hot] = np.sqrt(read_noise[hot] ** 2 + d.hot_level / d.gain)
    return bias, read_noise


def _envelope_and_visibility(cfg: SimulationConfig, x0, y0, mask) -> tuple[np.ndarray, np.ndarray]:
    """The metrology beam's envelope (mean 1 over ``mask``) and the fringe visibility at the pixels' true
    centres ``x0``, ``y0`` (row, col)."""
    m, (rows, cols) = cfg.metrology, cfg.detector.shape
    xc, yc = (cols - 1) / 2, (rows - 1) / 2
    ex, ey = m.envelope_centre
    envelope = np.exp(-0.5 * ((x0 - xc - ex) ** 2 + (y0 - yc - ey) ** 2) / m.envelope_sigma**2)
    envelope /= envelope[mask].mean()
    visibility = 1 + m.visibility_gradient[0] * (x0 - xc) / cols + m.visibility_gradient[1] * (y0 - yc) / rows
    return envelope, visibility


def _wavevectors(cfg: SimulationConfig, centres, mask) -> tuple[np.ndarray, dict, dict]:
    """Each baseline's wavevector (baseline, 2), rad/pixel; with spherical waves also each baseline's phase
    surface at the pixels' true centres (:func:`dice_core.geometry.two_source_phase`) and the true fiber
    tips (empty dicts for plane waves). ``centres(wavelength)`` gives the pixels' true centres (x0, y0)
    (row, col) at a baseline's wavelength (None: metrology.wavelength)."""
    m = cfg.metrology
    baselines = metrology_baselines(cfg)
    kvec = np.array([[2 * np.pi / b["period"] * math.cos(math.radians(b["angle_deg"])),
                      2 * np.pi / b["period"] * math.sin(math.radians(b["angle_deg"]))]
                     for b, _ in baselines.values()]).reshape(-1, 2)
    spherical, tips = {}, {}
    if m.spherical:
        tips, _ = fiber_tips(cfg)
        for i, (name, (_, own)) in enumerate(baselines.items()):
            x0, y0 = centres(own)
            design = np.column_stack([np.ones(mask.sum()), x0[mask], y0[mask]])  # coefficients in rad/pixel
            surface = two_source_phase(x0, y0, tips[name + "a"], tips[name + "b"],
                                       wavelength=m.wavelength if own is None else own, pixel_pitch=m.pixel_pitch)
            spherical[name] = surface
            # the contract's kx, ky: the best plane of the phase over the science area
            kvec[i] = np.linalg.lstsq(design, surface[0][mask], rcond=None)[0][1:]
    return kvec, spherical, tips


def _fringe_histories(cfg: SimulationConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each baseline's fringe phase phi(t) (rad), level B(t) and amplitude A(t) (adu) and the stray-light
    fringe's phase (rad), all (baseline, frame)."""
    m = cfg.metrology
    names = list(metrology_baselines(cfg))
    phase = np.empty((len(names), m.frames))
    level = np.empty_like(phase)
    amplitude = np.empty_like(phase)
    stray_phase = np.empty_like(phase)
    for i, name in enumerate(names):
        rng = _rng(cfg, "metrology", name, *_acquisition(cfg))
        phase[i] = _phase_history(cfg, name, rng)
        laser = 1 + m.laser_rsd * rng.standard_normal(m.frames)
        if m.intensity_random_walk:
            laser *= 1 + m.intensity_random_walk * np.cumsum(rng.standard_normal(m.frames))
        level[i] = m.mean_level * laser
        amplitude[i] = m.amplitude * laser * (1 + m.amplitude_rsd * rng.standard_normal(m.frames))
        rng = _rng(cfg, "stray light", name)
        stray_phase[i] = phase[i] + rng.uniform(0, 2 * np.pi) + m.stray_light_phase_walk * np.cumsum(
            rng.standard_normal(m.frames))
    return phase, level, amplitude, stray_phase


def _laser_response(cfg: SimulationConfig) -> tuple[np.ndarray, np.ndarray]:
    """What the laser sees beyond the flat: a chromatic PRNU (row, col) and each baseline's speckle
    (baseline, row, col), relative (ones when not simulated)."""
    d, m = cfg.detector, cfg.metrology
    chromatic = np.ones(d.shape)
    if m.chromatic_prnu_rms:
        chromatic += m.chromatic_prnu_rms * _rng(cfg, "chromatic prnu").standard_normal(d.shape)
    names = list(metrology_baselines(cfg))
    speckle = np.ones((len(names), *d.shape))
    if m.speckle_rms:
        from scipy.ndimage import gaussian_filter

        for i, name in enumerate(names):
            grains = gaussian_filter(_rng(cfg, "speckle", name).standard_normal(d.shape), m.speckle_grain,
                                     mode="wrap")
            speckle[i] = 1 + m.speckle_rms * (grains - grains.mean()) / grains.std()
    return chromatic, speckle


def _flat_illuminations(cfg: SimulationConfig, x0, y0) -> np.ndarray:
    """Each flat fiber's relative illumination (flat, row, col) at the pixels' true centres ``x0``, ``y0``."""
    rows, cols = cfg.detector.shape
    xc, yc = (cols - 1) / 2, (rows - 1) / 2
    flats = flat_acquisitions(cfg)
    illumination = np.empty((len(flats), rows, cols))
    for i, (f, (fiber, _)) in enumerate(flats.items()):
        fib = _build(FiberConfig, fiber, f"flats.fibers.{f}")
        corner2 = (cols / 2) ** 2 + (rows / 2) ** 2
        illumination[i] = (1 + fib.gradient[0] * (x0 - xc) / cols + fib.gradient[1] * (y0 - yc) / rows
                           + fib.curvature * ((x0 - xc) ** 2 + (y0 - yc) ** 2) / corner2)
    return illumination


def _coherence_matters(cfg: SimulationConfig) -> bool:
    """Whether the bench has stray light or a finite coherence length (else the frames are those without)."""
    return cfg.has_stray_light or cfg.stray_light.coherence_length is not None


def _stray_fringes(cfg: SimulationConfig, prf: PixelResponse, tips: dict, name: str):
    """Baseline ``name``'s coherence of the direct fringe, the stray waves' fringe response (complex, added to
    the direct one's as :meth:`PixelResponse.fringe_response` gives it) and their pattern of the level
    (relative to B, sensitivity included), (row, col) each (:func:`dice_core.stray_light.fringe_terms`)."""
    m, (rows, cols) = cfg.metrology, cfg.detector.shape
    x0, y0 = prf.centres()
    modulated, static, direct = stray_light.fringe_terms(
        x0, y0, tips[name + "a"], tips[name + "b"], stray_sources(cfg), fibers=(name + "a", name + "b"),
        wavelength=m.wavelength, pitch=m.pixel_pitch, coherence_length=cfg.stray_light.coherence_length,
        centre=((cols - 1) / 2, (rows - 1) / 2))
    stray = sum((w * prf.fringe_response(gx, gy, phase=phase) for w, gx, gy, phase, _ in modulated),
                np.zeros(cfg.detector.shape, complex))
    level = sum((w * prf.fringe_response(gx, gy, phase=phase).real for w, gx, gy, phase, _ in static),
                np.zeros(cfg.detector.shape))
    return direct, stray, level


def _coherent_speckle(cfg: SimulationConfig, prf: PixelResponse, tips: dict, fiber: str) -> np.ndarray:
    """The relative pattern (row, col) of a flat lit coherently through metrology ``fiber``: its stray
    waves beating with its own, 2 eps gamma h cos Delta_s summed over its sources (the pixel's response h)."""
    m, (rows, cols) = cfg.metrology, cfg.detector.shape
    x0, y0 = prf.centres()
    _, static, _ = stray_light.fringe_terms(
        x0, y0, tips[fiber], tips[fiber], stray_sources(cfg), fibers=(fiber, None), wavelength=m.wavelength,
        pitch=m.pixel_pitch, coherence_length=cfg.stray_light.coherence_length, centre=((cols - 1) / 2, (rows - 1) / 2))
    pattern = sum((w * prf.fringe_response(gx, gy, phase=phase).real for w, gx, gy, phase, _ in static),
                  np.zeros(cfg.detector.shape))
    sensitivity = prf.sensitivity
    return 2 * np.divide(pattern, sensitivity, out=np.zeros_like(pattern), where=sensitivity > 0)


def _stage_poses(cfg: SimulationConfig) -> tuple[np.ndarray, np.ndarray]:
    """The detector's pose at each star position (position, 6: translation x, y, z in pixel, then tip, tilt,
    roll in rad) and the stars' true positions there (position, star, 2), pixel."""
    st = cfg.stars
    rng = _rng(cfg, "stage")
    poses = _nominal_poses(st)
    poses[:, :2] += st.step_jitter * rng.standard_normal((st.positions, 2))
    for axis in (3, 4):
        walk = np.cumsum(rng.standard_normal(st.positions))
        span = np.ptp(walk)
        poses[:, axis] = (walk - walk.mean()) * (st.tip_tilt_pv / span if span > 0 else 0.0)
    poses[:, 5] = st.roll_rms * rng.standard_normal(st.positions)
    return poses, project_stars(_nominal_pattern(st), poses, cfg=cfg)


def make_truth(cfg: SimulationConfig) -> xr.Dataset:
    """Everything the simulation knows, before any frame is drawn (the ``truth.nc`` content).

    Holds the contract's variables (dx, dy, sensitivity, kx, ky, phase,
    star_x, star_y) and the rest of the model, which the acquisitions are
    generated from: PRF scales and widths, bias and read-noise maps, fringe
    level and amplitude per frame, envelope and visibility, flat illuminations,
    detector poses.
    """
    d, m, st = cfg.detector, cfg.metrology, cfg.stars
    rows, cols = d.shape
    mask = np.zeros(d.shape, bool)
    mask[slice(*d.science_rows), slice(*d.science_cols)] = True
    # each part draws from its own named random streams (_rng): the order of the calls does not matter
    prf, defects = _pixel_response_truth(cfg, mask)
    dx, dy, sigma_x, sigma_y, slope_x, slope_y = prf.dx, prf.dy, prf.sigma_x, prf.sigma_y, prf.slope_x, prf.slope_y
    bias, read_noise = _bias_and_read_noise(cfg, defects)
    x0, y0 = prf.centres()
    envelope, visibility = _envelope_and_visibility(cfg, x0, y0, mask)
    names = list(metrology_baselines(cfg))
    response = _chromatic_truth(cfg, prf, mask) if is_chromatic(cfg) else None
    kvec, spherical, tips = _wavevectors(cfg, lambda wavelength: _centres_at(prf, response, wavelength), mask)
    phase, level, amplitude, stray_phase = _fringe_histories(cfg)
    chromatic, speckle = _laser_response(cfg)
    fibers = list(flat_acquisitions(cfg))
    illumination = _flat_illuminations(cfg, x0, y0)
    poses, stars = _stage_poses(cfg)

    rc = ("row", "col")
    ds = xr.Dataset(
        {
            "dx": (rc, dx, {"units": "pixel", "long_name": "true pixel offset along x (the PRF kernel's centre; "
                                                             "its barycentre unless prf_slope_rms)"}),
            "dy": (rc, dy, {"units": "pixel", "long_name": "true pixel offset along y (the PRF kernel's centre; "
                                                             "its barycentre unless prf_slope_rms)"}),
            "sensitivity": (rc, prf.sensitivity, {"units": "1", "long_name": "relative quantum efficiency (PRF integral)"}),
            "prf_sigma_x": (rc, sigma_x, {"units": "pixel", "long_name": "hyper-Gaussian scale of the PRF along x"}),
            "prf_sigma_y": (rc, sigma_y, {"units": "pixel", "long_name": "hyper-Gaussian scale of the PRF along y"}),
            "width_x": (rc, prf.width_x(), {"units": "pixel", "long_name": "PRF standard deviation along x"}),
            "width_y": (rc, prf.width_y(), {"units": "pixel", "long_name": "PRF standard deviation along y"}),
            "bias": (rc, bias, {"units": "adu", "long_name": "bias level (hot pixels: plus hot_level)"}),
            "bad_pixel": (rc, defects, {"units": "1", "long_name": "simulated defects (dust: its centre pixel)",
                                        "flag_masks": np.array([BAD_DEAD, BAD_HOT, BAD_DUST], np.int8),
                                        "flag_meanings": "dead hot dust"}),
            "read_noise": (rc, read_noise, {"units": "adu", "long_name": "read noise rms (hot pixels: with the "
                                                                          "dark signal's shot noise)"}),
            "envelope": (rc, envelope, {"units": "1", "long_name": "metrology fringe envelope (mean 1)"}),
            "chromatic_sensitivity": (rc, chromatic, {"units": "1", "long_name": "the laser's sensitivity over "
                                                      "the flat's (chromatic PRNU)"}),
            "speckle": (("baseline", "row", "col"), speckle,
                        {"units": "1", "long_name": "speckle of each baseline's laser illumination"}),
            "visibility": (rc, visibility, {"units": "1", "long_name": "fringe visibility relative to amplitude/level"}),
            "kx": (("baseline",), kvec[:, 0], {"units": "rad/pixel", "long_name": "fringe wavevector along x"}),
            "ky": (("baseline",), kvec[:, 1], {"units": "rad/pixel", "long_name": "fringe wavevector along y"}),
            "phase": (("baseline", "frame"), phase, {"units": "rad", "long_name": "fringe phase phi(t)"}),
            "fringe_level": (("baseline", "frame"), level, {"units": "adu", "long_name": "fringe mean level B(t)"}),
            "fringe_amplitude": (("baseline", "frame"), amplitude, {"units": "adu", "long_name": "fringe amplitude A(t)"}),
            "stray_light_phase": (("baseline", "frame"), stray_phase,
                                  {"units": "rad", "long_name": "phase of the parasitic (stray-light) fringe",
                                   "relative_amplitude": m.stray_light, "period": m.stray_light_period,
                                   "angle_deg": m.stray_light_angle_deg}),
            "flat_illumination": (("flat", "row", "col"), illumination,
                                  {"units": "1", "long_name": "relative flat-field illumination"}),
            "stage_translation": (("position", "axis"), poses[:, :3],
                                  {"units": "pixel", "long_name": "detector translation from the reference pose"}),
            "stage_rotation": (("position", "angle"), poses[:, 3:],
                               {"units": "rad", "long_name": "detector tip (about x), tilt (about y), roll (about z)"}),
            "star_x": (("position", "star"), stars[..., 0], {"units": "pixel", "long_name": "true PSF centre x"}),
            "star_y": (("position", "star"), stars[..., 1], {"units": "pixel", "long_name": "true PSF centre y"}),
            **({} if not m.spherical else {
                "fringe_phase_surface": (("baseline", "row", "col"), np.stack([spherical[b][0] for b in names]),
                                         {"units": "rad", "long_name": "fringe phase Phi_b at each pixel's true "
                                                                      "centre (two point sources)"}),
                "fiber_position": (("fiber", "xyz"), np.array([tips[f] for f in tips]),
                                   {"units": "m", "long_name": "true fiber-tip position, detector frame"}),
            }),
            **({} if slope_x is None else {
                "prf_slope_x": (rc, slope_x, {"units": "1/pixel", "long_name": "PRF sensitivity slope along x"}),
                "prf_slope_y": (rc, slope_y, {"units": "1/pixel", "long_name": "PRF sensitivity slope along y"}),
                "barycentre_dx": (rc, prf.barycentres()[0] - np.indices(d.shape)[1],
                                  {"units": "pixel", "long_name": "offset of the PRF barycentre along x"}),
                "barycentre_dy": (rc, prf.barycentres()[1] - np.indices(d.shape)[0],
                                  {"units": "pixel", "long_name": "offset of the PRF barycentre along y"}),
            }),
        },
        coords={
            "row": np.arange(rows), "col": np.arange(cols), "baseline": names, "frame": np.arange(m.frames),
            "flat": fibers, "position": np.arange(1, st.positions + 1), "star": np.arange(5),
            "axis": ["x", "y", "z"], "angle": ["tip", "tilt", "roll"],
            **({} if not m.spherical else {"fiber": list(tips), "xyz": ["x", "y", "z"]}),
        },
    )
    if cfg.has_stray_light:
        ds = _with_stray_truth(ds, cfg, prf, tips, mask)
    if response is not None:
        ds.update(response)
        ds["baseline_wavelength"] = (("baseline",), [np.nan if w is None else w for _, w in
                                                      metrology_baselines(cfg).values()],
                                     {"units": "m", "long_name": "each baseline's laser wavelength (NaN: unstated, "
                                                                 "metrology.wavelength's)"})
        ds["flat_wavelength"] = (("flat",), [np.nan if w is None else w for _, w in flat_acquisitions(cfg).values()],
                                 {"units": "m", "long_name": "each flat's laser wavelength (NaN: white light)"})
    ds.attrs.update({"prf_order": d.prf_order, "prf_half_width": d.prf_half_width,
                     "simulation": json.dumps(cfg.to_dict(), sort_keys=True)})
    return ds


def _with_stray_truth(ds: xr.Dataset, cfg: SimulationConfig, prf: PixelResponse, tips: dict,
                      mask: np.ndarray) -> xr.Dataset:
    """The truth ``ds`` with the stray light's (:func:`_stray_truth`) and, for the flats lit coherently, their
    stray patterns in the flat illumination."""
    ds = ds.assign(_stray_truth(cfg, prf, tips, mask))
    if cfg.stray_light.coherent_flats:
        flats = ds["flat"].values
        speckle = np.stack([_coherent_speckle(cfg, prf, tips, cfg.stray_light.coherent_flats[f])
                            if f in cfg.stray_light.coherent_flats else np.zeros(cfg.detector.shape) for f in flats])
        ds["flat_illumination"] = ds["flat_illumination"] * (1 + speckle)
        ds["coherent_speckle"] = (("flat", "row", "col"), speckle,
                                  {"units": "1", "long_name": "relative pattern of the stray waves in a flat lit "
                                                              "coherently (zero: an incoherent flat)"})
    return ds


def _stray_truth(cfg: SimulationConfig, prf: PixelResponse, tips: dict, mask: np.ndarray) -> dict:
    """The truth of the stray light: each baseline's phase error (baseline, row, col) and the offset error it
    makes along the baseline's local wavevector; each source's place and the component it makes in its
    baseline's projected offsets (:mod:`dice_core.stray_light`: frequency and chirp from its Delta_s at the
    nominal pixel centres, amplitude and phase fitted to the offset error jointly with the baseline's other
    sources and the affine part, all over the science area; the sign of the offsets along the true phase's
    gradient)."""
    m, (rows, cols) = cfg.metrology, cfg.detector.shape
    names, sources = list(m.baselines), stray_sources(cfg)
    x0, y0 = prf.centres()
    r, c = np.nonzero(mask)
    reference = stray_light.reference_pixel(c, r)
    phase_error, offset_error = np.zeros((2, len(names), rows, cols))
    n = len(sources)
    baseline_of = [""] * n
    frequency, chirp, amplitude, phase, gamma = np.zeros((n, 2)), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    for i, name in enumerate(names):
        direct, stray, _ = _stray_fringes(cfg, prf, tips, name)
        _, kx, ky = two_source_phase(x0, y0, tips[name + "a"], tips[name + "b"], wavelength=m.wavelength,
                                     pixel_pitch=m.pixel_pitch)
        response = prf.fringe_response(kx, ky, phase=two_source_phase(x0, y0, tips[name + "a"], tips[name + "b"],
                                                                      wavelength=m.wavelength,
                                                                      pixel_pitch=m.pixel_pitch)[0])
        phase_error[i] = np.angle((direct * response + stray) * np.conj(response))
        offset_error[i] = phase_error[i] / np.hypot(kx, ky)
        # each source's Delta_s at the nominal centres, which the reduction's components are functions of
        direct_phase = two_source_phase(c, r, tips[name + "a"], tips[name + "b"], wavelength=m.wavelength,
                                        pixel_pitch=m.pixel_pitch)[0]
        terms, _, _ = stray_light.fringe_terms(
            c, r, tips[name + "a"], tips[name + "b"], sources, fibers=(name + "a", name + "b"),
            wavelength=m.wavelength, pitch=m.pixel_pitch, coherence_length=cfg.stray_light.coherence_length,
            centre=((cols - 1) / 2, (rows - 1) / 2))
        if not terms:
            continue
        found = [stray_light.quadratic_frequency(t[3] - direct_phase, c, r, reference) for t in terms]
        a, phi = stray_light.fit_amplitudes(offset_error[i][r, c], c, r, [f for f, _ in found],
                                            [g for _, g in found], reference,
                                            against=geometry_affine(c, r))
        for (w, *_, index), (f, g), a_s, phi_s in zip(terms, found, a, phi):
            frequency[index], chirp[index], phase[index] = stray_light.canonical(f, g, phi_s)
            amplitude[index], gamma[index], baseline_of[index] = a_s, w / sources[index].field_ratio, name
    src = ("stray_source",)
    return {
        "stray_phase_error": (("baseline", "row", "col"), phase_error,
                              {"units": "rad", "long_name": "phase error of each baseline's fringe from stray light"}),
        "stray_offset_error": (("baseline", "row", "col"), offset_error,
                               {"units": "pixel", "long_name": "the phase error over the local |K|: the projected "
                                                               "offset error along the true phase's gradient"}),
        "stray_source_position": (("stray_source", "xyz"), np.array([s.point for s in sources]),
                                  {"units": "m", "long_name": "stray source position, detector frame"}),
        "stray_source_fiber": (src, [s.fiber for s in sources], {"units": "1", "long_name": "fiber whose wave it re-emits"}),
        "stray_source_baseline": (src, baseline_of, {"units": "1", "long_name": "the baseline whose fringe it disturbs"}),
        "stray_field_ratio": (src, [s.field_ratio for s in sources], {"units": "1", "long_name": "field ratio"}),
        "stray_extra_path": (src, [s.extra_path for s in sources],
                             {"units": "m", "long_name": "optical path beyond the fiber's direct path"}),
        "stray_coherence": (src, gamma, {"units": "1", "long_name": "coherence of its parasitic fringe"}),
        "stray_frequency_x": (src, frequency[:, 0], {"units": "1/pixel", "long_name": "component frequency x "
                                                                                        "(aliased, canonical sign)"}),
        "stray_frequency_y": (src, frequency[:, 1], {"units": "1/pixel", "long_name": "component frequency y"}),
        "stray_chirp": (src, chirp, {"units": "1/pixel2", "long_name": "component chirp"}),
        "stray_amplitude": (src, amplitude, {"units": "pixel", "long_name": "component amplitude in the "
                                                                           "projected offsets"}),
        "stray_phase": (src, phase, {"units": "rad", "long_name": "component phase at the reference pixel"}),
    }


_PER_WAVELENGTH = {  # truth variable -> (its chromatic_response map, units, what it is)
    "sensitivity_wavelength": ("sensitivity", "1", "relative quantum efficiency at each wavelength, mean 1 over "
                                                   "the science area"),
    "dx_wavelength": ("dx", "pixel", "true pixel offset along x at each wavelength"),
    "dy_wavelength": ("dy", "pixel", "true pixel offset along y at each wavelength"),
    "prf_sigma_x_wavelength": ("sigma_x", "pixel", "hyper-Gaussian scale of the PRF along x at each wavelength"),
    "prf_sigma_y_wavelength": ("sigma_y", "pixel", "hyper-Gaussian scale of the PRF along y at each wavelength"),
}


def _chromatic_truth(cfg: SimulationConfig, prf: PixelResponse, mask) -> xr.Dataset:
    """The pixel response at each wavelength of :func:`wavelength_grid` (dice_core.chromatic.chromatic_response)
    and the spectra's quadrature weights on that grid, as truth variables on the coordinate ``wavelength``."""
    from dice_core import chromatic
    from dice_core.detector import hyper_gaussian_std

    c, d = cfg.chromatic, cfg.detector
    grid = wavelength_grid(cfg)
    fields = {}
    if c.amplitude:
        for name in ("sensitivity", "dx", "dy", "sigma_x", "sigma_y"):
            pair = _rng(cfg, "chromatic", name).standard_normal((2, *d.shape))
            fields[name] = [_remove_affine(f, mask) for f in pair] if name in ("dx", "dy") else list(pair)
    maps = chromatic.chromatic_response(
        prf, grid, fields=fields, reference=cfg.metrology.wavelength, amplitude=c.amplitude,
        sensitivity_rms=c.sensitivity_rms, offset_rms=c.offset_rms, width_rms=c.width_rms,
        width_trend=c.width_trend, thickness=c.thickness, surface_depth=c.surface_depth,
        surface_share=c.surface_share, mask=mask)
    dims = ("wavelength", "row", "col")
    ds = xr.Dataset({name: (dims, maps[key], {"units": units, "long_name": what})
                     for name, (key, units, what) in _PER_WAVELENGTH.items()},
                    coords={"wavelength": ("wavelength", grid, {"units": "m"})})
    for axis in "xy":  # one wavelength at a time: the quadrature's temporaries are 64 maps
        ds[f"width_{axis}_wavelength"] = (dims, np.stack([
            hyper_gaussian_std(sigma, order=d.prf_order, half_width=d.prf_half_width)
            for sigma in maps[f"sigma_{axis}"]]), {"units": "pixel", "long_name": f"PRF standard deviation along "
                                                                                 f"{axis} at each wavelength"})
    spectra = {"star_spectrum_weight": cfg.stars.spectrum, "flat_spectrum_weight": cfg.flats.spectrum}
    for key, name in spectra.items() if _broadband(cfg) else ():
        if name is not None:
            weights = chromatic.quadrature_weights(grid, chromatic.named_spectrum(name))
            ds[key] = (("wavelength",), weights, {"units": "1", "long_name": f"the {name} spectrum's share of the "
                                                                            "light at each wavelength (sum 1)",
                                                  "spectrum": name})
    return ds


def _centres_at(prf: PixelResponse, response, wavelength):
    """The pixels' true centres (x0, y0) at ``wavelength`` (m; None: metrology.wavelength's, the base)."""
    if wavelength is None or response is None:
        return prf.centres()
    rows, cols = np.indices(prf.shape)
    at = response.sel(wavelength=wavelength, method="nearest")
    return cols + at["dx_wavelength"].values, rows + at["dy_wavelength"].values


def pixel_response(truth: xr.Dataset, wavelength: float | None = None) -> PixelResponse:
    """The detector's :class:`PixelResponse` from a truth dataset: at metrology.wavelength (its ``dx``...), or
    at ``wavelength`` (m), one of the truth's ``wavelength`` coordinate (its ``*_wavelength`` maps)."""
    slopes = [truth[v].values if v in truth else None for v in ("prf_slope_x", "prf_slope_y")]
    maps = [truth[v] for v in ("sensitivity", "dx", "dy", "prf_sigma_x", "prf_sigma_y")]
    if wavelength is not None:
        if "wavelength" not in truth.coords:
            raise ValueError(f"the truth holds no response at {wavelength * 1e9:g} nm: its simulation is achromatic")
        nearest = float(truth["wavelength"].sel(wavelength=wavelength, method="nearest"))
        if abs(nearest - wavelength) > 1e-12:
            raise ValueError(f"the truth holds no response at {wavelength * 1e9:g} nm (nearest {nearest * 1e9:g} nm)")
        maps = [truth[f"{v}_wavelength"].sel(wavelength=nearest) for v in
                ("sensitivity", "dx", "dy", "prf_sigma_x", "prf_sigma_y")]
    return PixelResponse(*(m.values for m in maps), float(truth.attrs["prf_order"]),
                         float(truth.attrs["prf_half_width"]), *slopes)


# --------------------------------------------------------------------------- frames

def _read_out(signal: np.ndarray, truth: xr.Dataset, cfg: SimulationConfig, photon_rngs, read_rng) -> np.ndarray:
    """Photon noise through the gain, then bias and read noise: signal (adu) -> raw samples (adu).

    A sample whose mean holds at least ``DetectorConfig.gaussian_photons_above``
    electrons gets one normal draw of the photon and read noises' summed
    variance, signal / gain + read_noise^2 (adu^2), from the first of
    ``photon_rngs``; a fainter one a Poisson draw of its electrons from the
    second, plus a normal read noise from ``read_rng``. Each generator is
    drawn strictly in frame order, so the frames do not depend on how they
    are chunked.
    """
    d = cfg.detector
    bias, read_noise = truth["bias"].values, truth["read_noise"].values
    if not d.photon_noise:
        return signal + bias + read_noise * read_rng.standard_normal(signal.shape, dtype=np.float32)
    normal_rng, poisson_rng = photon_rngs
    electrons = np.maximum(signal, 0) * d.gain
    if d.gaussian_photons_above is None:
        return (poisson_rng.poisson(electrons) / d.gain + bias
                + read_noise * read_rng.standard_normal(signal.shape, dtype=np.float32))
    # one draw for both noises: the costliest step of a simulation is drawing random numbers
    samples = electrons / d.gain**2 + read_noise**2  # variance, adu^2
    np.sqrt(samples, out=samples)
    samples *= normal_rng.standard_normal(signal.shape, dtype=np.float32)
    samples += signal
    samples += bias
    faint = electrons < d.gaussian_photons_above
    if faint.any():
        n_faint = int(np.count_nonzero(faint))
        samples[faint] = (poisson_rng.poisson(electrons[faint]) / d.gain + np.broadcast_to(bias, faint.shape)[faint]
                          + np.broadcast_to(read_noise, faint.shape)[faint]
                          * read_rng.standard_normal(n_faint, dtype=np.float32))
    return samples


#: Samples of one chunk of simulated frames: each float64 temporary of the signal and noise is 2 MiB, a few of
#: which fit the test machine's 32 MiB shared L3 cache, as a few 16 MiB ones (2**21 samples) do not. A
#: paper-preset metrology file took 0.75-0.80 of the time it took in chunks of 2**21 samples, the same file bit
#: for bit (``benchmarks/simulation_chunks.py``, BENCHMARKS.md "The simulation's chunk").
SIMULATION_CHUNK_SAMPLES = 2**18


def simulation_chunk_frames(cfg: SimulationConfig) -> int:
    """Frames simulated at once: ``cfg.chunk_frames``, fewer where they would exceed
    :data:`SIMULATION_CHUNK_SAMPLES` samples (at least one frame).

    A simulation job's memory is a few float64 temporaries of one chunk: 39
    frames of 80x84 pixels are 2 MB each, one frame of 1024x1024 pixels 8 MB.
    The frames do not depend on the chunk (every generator is drawn in frame
    order), so this changes memory and speed only.
    """
    pixels = cfg.detector.shape[0] * cfg.detector.shape[1]
    return max(1, min(cfg.chunk_frames, SIMULATION_CHUNK_SAMPLES // pixels))


def _stated_wavelength(entry: xr.Dataset, variable: str) -> float | None:
    """An acquisition's wavelength (m) from the truth's ``baseline_wavelength`` or ``flat_wavelength``; None
    where unstated (NaN) or the truth has none."""
    if variable not in entry:
        return None
    value = float(entry[variable])
    return None if np.isnan(value) else value


def _flat_sensitivity(truth: xr.Dataset, name: str, prf: PixelResponse) -> np.ndarray:
    """The sensitivities a flat sees (row, col): a laser flat's at its wavelength; a white flat's, on a chromatic
    detector, weighted by the lamp's spectrum; otherwise the detector's."""
    entry = truth.sel(flat=name)
    wavelength = _stated_wavelength(entry, "flat_wavelength")
    if wavelength is not None:
        return pixel_response(truth, wavelength).sensitivity
    if "flat_spectrum_weight" in truth:
        return np.tensordot(truth["flat_spectrum_weight"].values, truth["sensitivity_wavelength"].values, axes=1)
    return prf.sensitivity


def _broadband_stars(truth: xr.Dataset, position: xr.Dataset, stars) -> np.ndarray:
    """Every star's image at one position (row, col), adu: at each wavelength of the truth's grid, the star's
    share of light there (``star_spectrum_weight``) through the detector's response at that wavelength. Each star
    is integrated over a window reaching 8 PSF sigma (its light beyond is below 1e-13 of it)."""
    shape = truth["sensitivity"].shape
    image = np.zeros(shape)
    reach = int(np.ceil(8 * stars.psf_sigma)) + 1
    weights = truth["star_spectrum_weight"].values
    maps = [truth[f"{v}_wavelength"].values for v in ("sensitivity", "dx", "dy", "prf_sigma_x", "prf_sigma_y")]
    slopes = [truth[v].values if v in truth else None for v in ("prf_slope_x", "prf_slope_y")]
    for j, weight in enumerate(weights):
        if weight == 0:
            continue
        prf = PixelResponse(*(m[j] for m in maps), float(truth.attrs["prf_order"]),
                            float(truth.attrs["prf_half_width"]), *slopes)
        for x, y in zip(position["star_x"].values, position["star_y"].values):
            rows = slice(max(0, int(y) - reach), min(shape[0], int(y) + reach + 1))
            cols = slice(max(0, int(x) - reach), min(shape[1], int(x) + reach + 1))
            image[rows, cols] += stars.flux * weight * prf.gaussian_response(float(x), float(y), stars.psf_sigma,
                                                                           rows=rows, cols=cols)
    return image


def acquisition_chunks(cfg: SimulationConfig, truth: xr.Dataset, *, kind: str, name, start: int, stop: int):
    """Yield raw frames [start, stop) of one acquisition, in chunks of :func:`simulation_chunk_frames`.

    Parameters
    ----------
    kind : {"dark", "flat", "baseline", "position"}
    name : str or int
        Fiber, baseline, or position index (1-based).
    start, stop : int
        Frame range within the acquisition.

    Yields
    ------
    ndarray (frame, row, col), adu (not yet quantised).
    """
    again = _acquisition(cfg) if kind == "baseline" else ()
    photon_rngs = (_rng(cfg, "photons", kind, name, start, *again),
                   _rng(cfg, "poisson photons", kind, name, start, *again))
    read_rng = _rng(cfg, "read", kind, name, start, *again)
    shape = cfg.detector.shape
    prf = pixel_response(truth)
    if kind == "flat":
        signal_map = cfg.flats.level * _flat_sensitivity(truth, name, prf) * truth["flat_illumination"].sel(
            flat=name).values
        flux = 1 + cfg.flats.flux_rsd * _rng(cfg, "flat flux", name).standard_normal(cfg.flats.frames)
    elif kind == "baseline":
        b = truth.sel(baseline=name)
        wavelength = _stated_wavelength(b, "baseline_wavelength")
        if wavelength is not None:  # format 1.2: the detector as this laser sees it
            prf = pixel_response(truth, wavelength)
        envelope = truth["envelope"].values
        if "chromatic_sensitivity" in truth:  # the laser's own sensitivities, and its speckle
            envelope = envelope * truth["chromatic_sensitivity"].values * b["speckle"].values
        base = prf.sensitivity * envelope
        if cfg.metrology.spherical:  # each pixel under the plane wave of its local wavevector
            tips = dict(zip(truth["fiber"].values, truth["fiber_position"].values))
            x0, y0 = prf.centres()
            phase_map, kx_map, ky_map = two_source_phase(
                x0, y0, tips[name + "a"], tips[name + "b"], pixel_pitch=cfg.metrology.pixel_pitch,
                wavelength=cfg.metrology.wavelength if wavelength is None else wavelength)
            fringe = prf.fringe_response(kx_map, ky_map, phase=phase_map)
            if _coherence_matters(cfg):  # the stray waves' fringes beside the direct one, and their level
                direct, stray, static = _stray_fringes(cfg, prf, tips, name)
                fringe = direct * fringe + stray
                base = base + static * envelope
        else:
            fringe = prf.fringe_response(float(b["kx"]), float(b["ky"]))
        response = fringe * envelope * truth["visibility"].values
        level, amplitude, phase = (b[v].values for v in ("fringe_level", "fringe_amplitude", "phase"))
        m = cfg.metrology
        if m.stray_light:
            ks = 2 * np.pi / m.stray_light_period * np.array([math.cos(math.radians(m.stray_light_angle_deg)),
                                                               math.sin(math.radians(m.stray_light_angle_deg))])
            stray = m.stray_light * prf.fringe_response(*ks) * envelope
            stray_phase = b["stray_light_phase"].values
    elif kind == "position":
        p = truth.sel(position=int(name))
        st = cfg.stars
        if "star_spectrum_weight" in truth:  # broadband: the sum of the stars' monochromatic images
            image = st.background + _broadband_stars(truth, p, st)
        else:
            image = st.background + sum(st.flux * prf.gaussian_response(float(x), float(y), st.psf_sigma)
                                        for x, y in zip(p["star_x"].values, p["star_y"].values))
        flux = 1 + st.flux_rsd * _rng(cfg, "star flux", name).standard_normal(st.frames)
    elif kind != "dark":
        raise ValueError(f"unknown acquisition kind {kind!r}")

    step = simulation_chunk_frames(cfg)
    for first in range(start, stop, step):
        last = min(stop, first + step)
        n = last - first
        if kind == "dark":
            signal = np.zeros((n, *shape))
        elif kind == "flat":
            signal = flux[first:last, None, None] * signal_map
        elif kind == "baseline":
            t = slice(first, last)
            signal = (level[t, None, None] * base
                      + amplitude[t, None, None] * (np.sin(phase[t])[:, None, None] * response.real
                                                    + np.cos(phase[t])[:, None, None] * response.imag))
            if m.stray_light:
                signal += amplitude[t, None, None] * (np.sin(stray_phase[t])[:, None, None] * stray.real
                                                      + np.cos(stray_phase[t])[:, None, None] * stray.imag)
        else:
            signal = flux[first:last, None, None] * image
        yield _read_out(signal, truth, cfg, photon_rngs, read_rng)


def write_file(cfg: SimulationConfig, truth: xr.Dataset, *, relpath: str, outdir) -> Path:
    """Simulate one FITS file of the dataset (a path listed by :func:`file_jobs`) under ``outdir``."""
    jobs = file_jobs(cfg)
    if relpath not in jobs:
        raise KeyError(f"{relpath} is not a file of simulated dataset {cfg.name}")
    kind, name, start, stop = jobs[relpath]
    path = Path(outdir) / relpath
    log.info("simulating %s %s, frames %d..%d -> %s", kind, name, start, stop - 1, path)
    header = {"EXPTIME": 1.0 / cfg.detector.frame_rate, "FRAMERAT": cfg.detector.frame_rate}
    write_cube(path, acquisition_chunks(cfg, truth, kind=kind, name=name, start=start, stop=stop),
               shape=cfg.detector.shape, n_frames=stop - start, dtype=cfg.detector.dtype, header=header)
    return path


def write_manifest(cfg: SimulationConfig, outdir) -> Path:
    """Write ``dataset.yaml`` for the simulated dataset (atomically)."""
    path = Path(outdir) / "dataset.yaml"
    write_text(path, "# Simulated DICE testbed, written by dice_core.simulation\n"
               + yaml.safe_dump(dataset_layout(cfg), sort_keys=False))
    return path


def simulate_dataset(cfg: SimulationConfig, outdir) -> Path:
    """Simulate the whole dataset into ``outdir``: FITS cubes, ``truth.nc`` and ``dataset.yaml``."""
    outdir = Path(outdir)
    truth = make_truth(cfg)
    write_product(truth, outdir / "truth.nc", title=f"truth of simulated dataset {cfg.name}",
                  config=cfg.to_dict())
    for relpath in file_jobs(cfg):
        write_file(cfg, truth, relpath=relpath, outdir=outdir)
    return write_manifest(cfg, outdir)
