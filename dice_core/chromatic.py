"""Chromatic pixels: silicon's absorption depth, the detector's response across wavelength, the stars' spectra.

A photon of wavelength lambda entering a back-illuminated CCD is absorbed at
depth z below the surface it enters with probability density
``exp(-z / L) / L``, L = 1 / alpha(lambda) the absorption length: about
0.1 um at 400 nm, 3 um at 633 nm and 12 um at 800 nm in silicon at room
temperature (:func:`absorption_length`, from the extinction coefficients of
Schinke et al. 2015). The charge it makes drifts and diffuses towards the
potential wells at the far side, a thickness T away. Where in depth it was
made sets how far it travels before it is collected: charge made far from
the wells (blue light) spreads more and is pushed further by lateral fields
(a wider PRF, a displaced centre), and charge made in the first tenths of a
um behind the surface meets the back surface's passivation, whose
pixel-to-pixel pattern shows in blue flat fields only (Janesick 2001,
"Scientific Charge-Coupled Devices", SPIE Press, on quantum efficiency and
charge diffusion; Holland et al. 2003, IEEE Trans. Electron Devices 50, 225,
on diffusion against depth; Plazas, Bernstein & Sheldon 2014, PASP 126, 750,
on lateral fields displacing charge; the paper's own reference for CCDs'
spectral dependency is 1995PASP..107.1094R). A pixel's response at lambda is the absorption-weighted mean of
its response to charge made at each depth; the simulator models each
pixel property (sensitivity, PRF centre, PRF width) as a constant plus two
depth profiles (:func:`depth_kernels`):

- ``drift``: proportional to the distance to the wells, (T - z) / T. Its
  mean over the absorption profile falls from about 1 (blue) to about 0.5
  (light absorbed evenly through the thickness);
- ``surface``: ``exp(-z / d_s)``, a layer of depth d_s behind the entrance
  surface. Its mean, about d_s / (d_s + L), is large in the blue only.

What a polychromatic source sees is linear in its spectrum: each pixel's
signal is the photon-weighted sum of its monochromatic responses, so its
effective sensitivity is the spectrum-weighted sensitivity, its effective
PRF centre the sensitivity-and-spectrum-weighted centre, and so on.

The named spectra (:data:`SPECTRA`) are the detected photon spectra of the
simulator's pseudo stars and flat lamps over the paper's 400-800 nm band:
``flat`` (uniform), ``warm`` (a 3500 K black body's photon flux, red-heavy)
and ``cool`` (10000 K, blue-heavy).

Units: m for wavelengths and depths (the manifest's), 1 for kernels and weights.
"""

from __future__ import annotations

import numpy as np

from dice_core import lazy

xr = lazy.module("xarray")

__all__ = [
    "EXTINCTION",
    "absorption_length",
    "depth_kernels",
    "SPECTRA",
    "BAND",
    "named_spectrum",
    "spectrum_density",
    "quadrature_weights",
    "CHANGE_WAVELENGTH",
    "change_coefficients",
    "chromatic_response",
    "MAX_DEGREE",
    "MODEL",
    "depth_coordinate",
    "model_weights",
    "spectrum_grid",
    "EffectiveResponse",
    "effective_response",
    "chromatic_dataset",
    "star_calibration",
    "calibration_from_products",
    "stars_spectrum",
]

#: Extinction coefficient k of crystalline silicon at 295 K against wavelength (m): Schinke et al. 2015,
#: "Uncertainty analysis for the coefficient of band-to-band absorption of crystalline silicon", AIP Advances 5,
#: 067168 (the refractiveindex.info database's Si/Schinke, public domain), every 10 nm from 380 to 1000 nm. The
#: absorption coefficient is 4 pi k / lambda. Its stated uncertainty is about 11% at 600 nm. A CCD operated cold
#: (-100 C) absorbs red light less (a longer absorption length beyond 700 nm); the model's shape, not its exact
#: numbers, is what the reduction relies on.
EXTINCTION = dict(zip(np.round(np.arange(380, 1001, 10) * 1e-9, 12), (
    9.8399e-01, 5.0308e-01, 3.2627e-01, 2.4127e-01, 1.7694e-01, 1.3766e-01, 1.1201e-01, 9.5362e-02, 7.9105e-02,
    7.0240e-02, 5.9817e-02, 5.3810e-02, 4.8542e-02, 4.3831e-02, 3.9531e-02, 3.4804e-02, 2.9896e-02, 2.8038e-02,
    2.6551e-02, 2.3746e-02, 2.1896e-02, 2.0076e-02, 1.8521e-02, 1.7257e-02, 1.6809e-02, 1.6268e-02, 1.4693e-02,
    1.4447e-02, 1.3608e-02, 1.2807e-02, 1.2045e-02, 1.1317e-02, 1.0623e-02, 9.9610e-03, 9.3335e-03, 8.7312e-03,
    8.1618e-03, 7.6156e-03, 7.0942e-03, 6.6054e-03, 6.1338e-03, 5.6888e-03, 5.2655e-03, 4.8640e-03, 4.4836e-03,
    4.1235e-03, 3.7828e-03, 3.4605e-03, 3.1563e-03, 2.8697e-03, 2.6001e-03, 2.3464e-03, 2.1092e-03, 1.8864e-03,
    1.6787e-03, 1.4757e-03, 1.3061e-03, 1.1393e-03, 9.8243e-04, 8.4060e-04, 7.1334e-04, 5.9638e-04, 4.9020e-04)))

#: The pseudo stars' band, m: the paper's table gives 400 nm to 800 nm.
BAND = (400e-9, 800e-9)

#: The named detected spectra: name -> black-body temperature of its photon flux, K (None: uniform).
SPECTRA = {"flat": None, "warm": 3500.0, "cool": 10000.0}


def absorption_length(wavelength):
    """Absorption length of silicon at 295 K, m, at ``wavelength`` (m; scalar or array).

    Interpolated linearly in log(length) between the tabulated wavelengths
    (:data:`EXTINCTION`); refused outside 380-1000 nm.

    Raises
    ------
    ValueError
        A wavelength outside the table.
    """
    table = np.array(sorted(EXTINCTION))
    wavelength = np.asarray(wavelength, float)
    if np.any(wavelength < table[0] - 1e-15) or np.any(wavelength > table[-1] + 1e-15):
        raise ValueError(f"wavelength {np.min(wavelength) * 1e9:g}-{np.max(wavelength) * 1e9:g} nm is outside the "
                         f"silicon absorption table ({table[0] * 1e9:g}-{table[-1] * 1e9:g} nm)")
    lengths = table / (4 * np.pi * np.array([EXTINCTION[w] for w in table]))
    return np.exp(np.interp(wavelength, table, np.log(lengths)))


#: The wavelengths the per-pixel model across wavelength covers, m: silicon's absorption table's.
MODEL_RANGE = (min(EXTINCTION), max(EXTINCTION))


def wavelength_problem(wavelength: float) -> str | None:
    """Why the per-pixel model cannot use ``wavelength`` (m), or None."""
    low, high = MODEL_RANGE
    if not low - 1e-15 <= wavelength <= high + 1e-15:
        return (f"{wavelength:.4g} m is outside the per-pixel model's {low * 1e9:g}-{high * 1e9:g} nm (silicon's "
                "absorption table)")
    return None


def spectrum_problem(wavelength, weight) -> str | None:
    """Why a stars' spectrum (samples in m, relative photons per unit wavelength) cannot be used, or None:
    lengths that differ, wavelengths not increasing or outside :data:`MODEL_RANGE` (one in nm, say), weights
    negative, not finite or zero everywhere."""
    wavelength, weight = np.asarray(wavelength, float), np.asarray(weight, float)
    if wavelength.ndim != 1 or wavelength.shape != weight.shape or wavelength.size < 2:
        return "needs one weight per wavelength, at least two"
    if np.any(np.diff(wavelength) <= 0):
        return "its wavelengths do not increase"
    if not np.all(np.isfinite(weight)) or np.any(weight < 0) or not weight.sum() > 0:
        return "its weights must be finite, non-negative and not all zero"
    for value in (wavelength[0], wavelength[-1]):
        if (problem := wavelength_problem(float(value))) is not None:
            return f"wavelength {problem} (wavelengths are in m)"
    return None


def depth_kernels(wavelength, *, thickness: float, surface_depth: float):
    """The two depth profiles' means over the absorption profile at ``wavelength``: (drift, surface).

    Parameters
    ----------
    wavelength : float or ndarray
        m.
    thickness : float
        The silicon's thickness T, m, from the entrance surface to the wells.
    surface_depth : float
        The depth d_s of the surface layer, m.

    Returns
    -------
    drift, surface : ndarray
        ``E[(T - z) / T]`` and ``E[exp(-z / d_s)]`` over the absorption
        density exp(-z / L) / L truncated to [0, T] (light that crosses the
        thickness makes no charge), 1.

    Notes
    -----
    With a = T / L, E[z] = L - T e^-a / (1 - e^-a), so the drift kernel is
    1 - E[z] / T; with b = 1 / L + 1 / d_s the surface kernel is
    (1 / (L b)) (1 - e^(-T b)) / (1 - e^-a).
    """
    if not (thickness > 0 and surface_depth > 0):
        raise ValueError(f"thickness {thickness!r} and surface_depth {surface_depth!r} must be > 0 (m)")
    length = absorption_length(wavelength)
    a = thickness / length
    kept = -np.expm1(-a)
    drift = 1 - (length - thickness * np.exp(-a) / kept) / thickness
    b = 1 / length + 1 / surface_depth
    surface = -np.expm1(-thickness * b) / (length * b) / kept
    return drift, surface


def _photon_flux(wavelength, temperature):
    """A black body's photon flux per unit wavelength at ``temperature`` (K), up to a constant."""
    h, c, k = 6.62607015e-34, 299792458.0, 1.380649e-23
    return wavelength**-4 / np.expm1(h * c / (wavelength * k * temperature))


def named_spectrum(name: str, *, band=BAND, step: float = 20e-9) -> tuple[np.ndarray, np.ndarray]:
    """A named detected spectrum (:data:`SPECTRA`) sampled every ``step`` (m) over ``band`` (m).

    Returns
    -------
    wavelength : ndarray
        m, increasing, both ends of the band included.
    weight : ndarray
        Relative photons per unit wavelength, mean 1 over the samples.

    Raises
    ------
    ValueError
        An unknown name, or a band outside the silicon table.
    """
    if name not in SPECTRA:
        raise ValueError(f"unknown spectrum {name!r}; spectra are {', '.join(SPECTRA)}")
    low, high = band
    if not (0 < low < high and step > 0):
        raise ValueError(f"spectrum band {band} and step {step!r} must be increasing and positive (m)")
    # in whole picometres, so that the manifest spells them as written (4.4e-07, not 4.3999999999999997e-07)
    picometres = np.round(np.linspace(low, high, int(round((high - low) / step)) + 1) * 1e12)
    wavelength = picometres / 1e12
    absorption_length(wavelength)  # inside the table
    temperature = SPECTRA[name]
    weight = np.ones_like(wavelength) if temperature is None else _photon_flux(wavelength, temperature)
    return wavelength, weight / weight.mean()


def spectrum_density(wavelength, spectrum):
    """A spectrum's density at ``wavelength`` (m): linear between its samples, zero outside them. ``spectrum``:
    (samples in m, weights)."""
    samples, weights = spectrum
    return np.interp(wavelength, samples, weights, left=0.0, right=0.0)


def quadrature_weights(grid, spectrum) -> np.ndarray:
    """Weights (sum 1) that integrate a function known on ``grid`` (m, increasing) against a spectrum.

    The spectrum (samples in m, weights) is a density linear between
    its samples and zero outside; the function is taken linear between the
    grid's points. The integral of the product of the two, each linear over
    every grid interval, is then exact; it is exact for the spectrum itself
    where its samples are grid points (the simulator's grids hold them).

    Raises
    ------
    ValueError
        A spectrum with no light on the grid.
    """
    grid = np.asarray(grid, float)
    samples = np.asarray(spectrum[0], float)
    density = spectrum_density(grid, spectrum)
    gaps = np.diff(grid)
    middle = (grid[:-1] + grid[1:]) / 2
    gaps[(middle < samples[0]) | (middle > samples[-1])] = 0.0  # no light outside the spectrum's samples
    out = np.zeros(grid.size)
    # the integral of f * density over [a, b], both linear there: h/6 [f_a (2 d_a + d_b) + f_b (d_a + 2 d_b)]
    out[:-1] += gaps * (2 * density[:-1] + density[1:]) / 6
    out[1:] += gaps * (density[:-1] + 2 * density[1:]) / 6
    total = out.sum()
    if not total > 0:
        raise ValueError("the spectrum has no light on the wavelength grid")
    return out / total


#: The wavelength (m) at which the simulator's chromatic amplitudes are stated: the change of each pixel
#: property from the reference wavelength to this one has the configured rms.
CHANGE_WAVELENGTH = 400e-9


def change_coefficients(wavelength, *, reference: float, thickness: float, surface_depth: float,
                        surface_share: float):
    """How much of each unit field a pixel property takes on at ``wavelength`` (m): (drift, surface).

    A property is its value at ``reference`` (m) plus ``rms (c_d F_d + c_s F_s)`` for two independent
    pixel-to-pixel fields F_d, F_s of unit rms; c_d is the drift kernel's change from the reference,
    scaled to sqrt(1 - surface_share) at :data:`CHANGE_WAVELENGTH`, and c_s the surface kernel's, scaled
    to sqrt(surface_share) there, so that the change to 400 nm has rms exactly ``rms``. Both are 0 at the
    reference.

    Raises
    ------
    ValueError
        A reference within 1 nm of :data:`CHANGE_WAVELENGTH` (the scale would be undefined).
    """
    if abs(reference - CHANGE_WAVELENGTH) < 1e-9:
        raise ValueError(f"the reference wavelength {reference * 1e9:g} nm is the one the amplitudes are stated at")
    kernels = depth_kernels(np.asarray(wavelength, float), thickness=thickness, surface_depth=surface_depth)
    at_reference = depth_kernels(reference, thickness=thickness, surface_depth=surface_depth)
    at_change = depth_kernels(CHANGE_WAVELENGTH, thickness=thickness, surface_depth=surface_depth)
    return tuple(np.sqrt(share) * (k - k0) / (k4 - k0)
                 for k, k0, k4, share in zip(kernels, at_reference, at_change, (1 - surface_share, surface_share)))


def chromatic_response(base, wavelengths, *, fields: dict, reference: float, amplitude: float,
                       sensitivity_rms: float, offset_rms: float, width_rms: float, width_trend: float,
                       thickness: float, surface_depth: float, surface_share: float, mask):
    """A detector's pixel response at each wavelength, from its response at ``reference`` (the simulator's model).

    Parameters
    ----------
    base : dice_core.detector.PixelResponse
        The response at the reference wavelength: sensitivity (1), offsets and PRF scales (pixel).
    wavelengths : ndarray (wavelength,)
        m.
    fields : dict
        For each of ``sensitivity``, ``dx``, ``dy``, ``sigma_x``, ``sigma_y``: its two unit-rms fields
        (drift, surface), each (row, col); may be empty when ``amplitude`` is 0. The offsets' fields should
        have no affine part over the science area (the offsets' gauge).
    amplitude : float
        Scales every change; 0 gives the base response at every wavelength.
    sensitivity_rms, offset_rms, width_rms : float
        The rms over pixels of each change from the reference to 400 nm at amplitude 1: relative, pixel,
        relative (of the PRF scale).
    width_trend : float
        Every PRF's scale grows by this fraction from the reference to 400 nm at amplitude 1, with the drift
        kernel (charge made far from the wells diffuses more).
    thickness, surface_depth, surface_share : float
        :func:`change_coefficients`.
    mask : bool ndarray (row, col)
        The science area: each wavelength's sensitivity keeps the base's mean over it.

    Returns
    -------
    dict of ndarray (wavelength, row, col)
        ``sensitivity``, ``dx``, ``dy`` (pixel), ``sigma_x``, ``sigma_y`` (pixel, the PRF kernels' scales).

    Notes
    -----
    Sensitivity: s0 (1 + A r_s (c_d S_d + c_s S_s)), rescaled to the base's mean; offsets:
    d0 + A r_o (c_d X_d + c_s X_s); PRF scale: sigma0 (1 + A r_w (c_d W_d + c_s W_s)) (1 + A t c_d').
    c_d' is the drift kernel's change scaled to 1 at 400 nm. Every map is the base's, bit for bit, at
    the reference wavelength or with amplitude 0.
    """
    wavelengths = np.atleast_1d(np.asarray(wavelengths, float))
    drift, surface = change_coefficients(wavelengths, reference=reference, thickness=thickness,
                                         surface_depth=surface_depth, surface_share=surface_share)
    trend = change_coefficients(wavelengths, reference=reference, thickness=thickness, surface_depth=surface_depth,
                                surface_share=0.0)[0]  # the drift kernel's change, 1 at 400 nm
    base_maps = {"sensitivity": base.sensitivity, "dx": base.dx, "dy": base.dy, "sigma_x": base.sigma_x,
                 "sigma_y": base.sigma_y}
    rms = {"sensitivity": sensitivity_rms, "dx": offset_rms, "dy": offset_rms, "sigma_x": width_rms,
           "sigma_y": width_rms}
    out = {name: np.empty((wavelengths.size, *base.shape)) for name in base_maps}
    for i in range(wavelengths.size):
        for name, value in base_maps.items():
            if amplitude == 0 or (drift[i] == 0 and surface[i] == 0):
                out[name][i] = value
                continue
            f_drift, f_surface = fields[name]
            change = amplitude * rms[name] * (drift[i] * f_drift + surface[i] * f_surface)
            if name == "sensitivity":
                changed = value * (1 + change)
                out[name][i] = changed * (value[mask].mean() / changed[mask].mean())
            elif name in ("dx", "dy"):
                out[name][i] = value + change
            else:
                out[name][i] = value * (1 + change) * (1 + amplitude * width_trend * trend[i])
    return out


# --------------------------------------------------------------------------- the reduction's model across wavelength

#: The highest degree of the per-pixel polynomial in ln(absorption length): 2, a curvature; more wavelengths
#: than 3 are fitted by least squares, which averages their noise instead of following it.
MAX_DEGREE = 2

#: What :func:`model_weights` fits, as the product's attributes name it.
MODEL = ("each pixel property a polynomial of degree min(N - 1, 2) in ln(silicon absorption length) over the N "
         "calibration wavelengths, least squares (dice_core.chromatic.model_weights); a spectrum sees its "
         "photon-weighted mean, the offsets and the PRF variances (widths squared) weighted by the sensitivity too")


def depth_coordinate(wavelength):
    """ln(absorption length / 1 um) at ``wavelength`` (m): the coordinate the model is a polynomial in."""
    return np.log(absorption_length(wavelength) / 1e-6)


def model_weights(calibration, wavelengths, *, degree: int | None = None) -> np.ndarray:
    """The linear map from values at the calibration wavelengths to the model's values at ``wavelengths``.

    Parameters
    ----------
    calibration : sequence of float
        The N calibration wavelengths, m, distinct.
    wavelengths : sequence of float
        Where the model is evaluated, m.
    degree : int, optional
        Of the polynomial in :func:`depth_coordinate`; min(N - 1, :data:`MAX_DEGREE`) by default.

    Returns
    -------
    ndarray (len(wavelengths), N)
        Row j gives the model at wavelengths[j] as a combination of the N values; each row sums to 1 (a
        constant is reproduced).

    Notes
    -----
    The least-squares polynomial of the N values, equal weights: with N = degree + 1 it interpolates. Why ln L:
    the two depth profiles a pixel's properties follow (:func:`depth_kernels`) are an exponential and a
    logistic-like function of ln L, and a quadratic through 450, 633 and 800 nm leaves of a broadband star's
    effective maps 2-15% of the error a 633 nm calibration alone leaves on the simulator's silicon, at most 29%
    for silicon 10-40 um thick and surface layers of 0.1-1 um (docs/centroids.md, "Chromatic pixels"); a straight
    line through two wavelengths can do worse than 633 nm alone.

    Raises
    ------
    ValueError
        No calibration wavelength, a repeated one, or a degree the wavelengths cannot fit.
    """
    calibration = np.asarray(calibration, float)
    if calibration.size == 0 or len(np.unique(np.round(calibration * 1e12))) != calibration.size:
        raise ValueError(f"calibration wavelengths {list(calibration)} must be distinct and at least one")
    degree = min(calibration.size - 1, MAX_DEGREE) if degree is None else degree
    if not 0 <= degree < calibration.size:
        raise ValueError(f"a polynomial of degree {degree} needs {degree + 1} calibration wavelengths, not "
                         f"{calibration.size}")
    x_calibration = depth_coordinate(calibration)
    x = depth_coordinate(np.asarray(wavelengths, float))
    centre = x_calibration.mean()  # centred: a well-conditioned Vandermonde matrix
    design = np.vander(x_calibration - centre, degree + 1)
    return np.vander(x - centre, degree + 1) @ np.linalg.pinv(design)


def spectrum_grid(samples, *, calibration=(), step: float = 5e-9) -> np.ndarray:
    """The wavelengths (m) a spectrum is integrated on: its samples, every ``step`` between them, and the
    calibration wavelengths inside its range (so that a laser's line is evaluated exactly)."""
    samples = np.asarray(samples, float)
    low, high = samples[0], samples[-1]
    fine = np.linspace(low, high, max(2, int(np.ceil((high - low) / step)) + 1))
    inside = [w for w in calibration if low <= w <= high]
    return np.unique(np.concatenate([samples, fine, inside]))


class EffectiveResponse:
    """What a spectrum sees of each pixel (:func:`effective_response`): maps (row, col).

    Attributes
    ----------
    sensitivity : ndarray
        Spectrum-weighted relative sensitivity, mean 1 over the finite pixels (1).
    dx, dy : ndarray
        Sensitivity-and-spectrum-weighted pixel offsets, pixel.
    variance_x, variance_y : ndarray or None
        Sensitivity-and-spectrum-weighted PRF variances (widths squared), pixel^2, where the calibration
        holds widths: the variance of the pixel's effective PRF, its monochromatic PRFs' mixture (their
        centres' spread, of order the offsets' change squared, 1e-5 of it, left out).
    weights : dict
        Calibration wavelength (m) -> the share of its map in the offsets' effective map, for a pixel of
        constant sensitivity (sums to 1): how far the spectrum lies within the calibration's range.
    """

    def __init__(self, sensitivity, dx, dy, variance_x, variance_y, weights):
        self.sensitivity, self.dx, self.dy = sensitivity, dx, dy
        self.variance_x, self.variance_y, self.weights = variance_x, variance_y, weights


def effective_response(calibration, maps: dict, *, spectrum, sensitivity=None, sensitivity_wavelengths=None,
                       degree: int | None = None) -> EffectiveResponse:
    """Each pixel's response to light of ``spectrum``, from its responses at the calibration wavelengths.

    Parameters
    ----------
    calibration : sequence of float
        The calibration wavelengths of ``maps``, m.
    maps : dict
        ``dx``, ``dy`` (and optionally ``width_x``, ``width_y``): arrays (wavelength, row, col) at the calibration
        wavelengths, pixel.
    spectrum : (samples, weights)
        The detected spectrum: wavelengths (m, increasing) and relative photons per unit wavelength, linear
        between the samples and zero outside (the manifest's ``stars.spectrum``).
    sensitivity : ndarray, optional
        Relative sensitivities (wavelength, row, col) at ``sensitivity_wavelengths`` (m), e.g. laser flats'
        PRNU maps; or one map (row, col), the same at every wavelength (a white flat's). Ones if omitted.
    degree : int, optional
        Of each model (:func:`model_weights`; each set of wavelengths its own by default).

    Returns
    -------
    EffectiveResponse

    Notes
    -----
    With a(lambda) the spectrum's quadrature weights on :func:`spectrum_grid` (:func:`quadrature_weights`), s
    and q the model's sensitivity and property at lambda: S_eff = sum a s, q_eff = sum a s q / S_eff, the
    widths modelled and averaged as their squares (variances). The grid is walked one wavelength at a time:
    memory is the calibration maps and five accumulators, linear in the number of calibration wavelengths.
    """
    samples, density = (np.asarray(v, float) for v in spectrum)
    grid = spectrum_grid(samples, calibration=calibration)
    a = quadrature_weights(grid, (samples, density))
    m = model_weights(calibration, grid, degree=degree)
    names = [n for n in ("dx", "dy", "width_x", "width_y") if maps.get(n) is not None]
    # the widths enter as variances: the variance of a mixture of PRFs is the weighted mean of theirs
    stacks = {n: np.asarray(maps[n], float) ** (2 if n.startswith("width") else 1) for n in names}
    constant = s_model = s_maps = None  # one sensitivity map for every wavelength, or a model of several
    if sensitivity is None or np.ndim(sensitivity) == 2:
        constant = np.ones(stacks["dx"].shape[1:]) if sensitivity is None else np.asarray(sensitivity, float)
    else:
        s_model = model_weights(sensitivity_wavelengths, grid, degree=degree)
        s_maps = np.asarray(sensitivity, float)
    total = np.zeros(stacks["dx"].shape[1:])
    sums = {n: np.zeros_like(total) for n in names}
    for j in range(grid.size):
        if a[j] == 0:
            continue
        s = constant if s_model is None else np.tensordot(s_model[j], s_maps, axes=1)
        total += a[j] * s
        for n in names:
            sums[n] += a[j] * s * np.tensordot(m[j], stacks[n], axes=1)
    with np.errstate(invalid="ignore", divide="ignore"):  # a dead pixel: 0 / 0, NaN as its maps are
        effective = {n: sums[n] / total for n in names}
    scale = np.nanmean(total)
    share = dict(zip((float(w) for w in calibration), a @ m))
    return EffectiveResponse(total / scale, effective["dx"], effective["dy"], effective.get("width_x"),
                             effective.get("width_y"), share)


# --------------------------------------------------------------------------- the product and the stars' correction

def chromatic_dataset(wavelengths, *, offsets: dict, widths: dict, sensitivity: dict, pairs: dict, flats: dict,
                      reference: float) -> xr.Dataset:
    """The ``calibration/chromatic.nc`` product: each calibration wavelength's maps, stacked along ``wavelength``.

    Parameters
    ----------
    wavelengths : sequence of float
        The calibration wavelengths, m, in the manifest's order of their pairs.
    offsets : dict
        Wavelength -> that wavelength's reference pair's ``calibration/offsets_<pair>.nc`` (dx, dy and their
        photon-noise floors, pixel).
    widths : dict
        Wavelength -> that wavelength's width maps (:class:`dice_core.prf.WidthMaps`, or None where they could not
        be made).
    sensitivity : dict
        Wavelength -> the PRNU map (row, col) of a laser flat at that wavelength; absent where the dataset has none.
    pairs, flats : dict
        Wavelength -> the name of the pair, of the flat (absent: none) each map comes from.
    reference : float
        The reference pair's wavelength, m: the chromatic mode corrects the PRF widths' change from it.
    """
    wavelengths = [float(w) for w in wavelengths]
    first = offsets[wavelengths[0]]
    shape = first["dx"].shape
    dims = ("wavelength", "row", "col")

    def stack(get):
        return np.stack([np.full(shape, np.nan) if (value := get(w)) is None else np.asarray(value, float)
                         for w in wavelengths])

    variables = {
        "dx": (dims, stack(lambda w: offsets[w]["dx"].values), {"units": "pixel", "long_name": "pixel offset "
                                                                "along x at each wavelength (its reference pair's)"}),
        "dy": (dims, stack(lambda w: offsets[w]["dy"].values), {"units": "pixel", "long_name": "pixel offset "
                                                                "along y at each wavelength"}),
        "sensitivity": (dims, stack(lambda w: sensitivity.get(w)), {
            "units": "1", "long_name": "relative sensitivity at each wavelength (its laser flat's PRNU; NaN: no "
                                       "flat at that wavelength)"}),
        "width_x": (dims, stack(lambda w: None if widths.get(w) is None else widths[w].width_x), {
            "units": "pixel", "long_name": "PRF standard deviation along x at each wavelength (NaN: not measured)"}),
        "width_y": (dims, stack(lambda w: None if widths.get(w) is None else widths[w].width_y), {
            "units": "pixel", "long_name": "PRF standard deviation along y at each wavelength (NaN: not measured)"}),
    }
    for axis in "xy":
        name = f"d{axis}_photon_noise_floor"
        if all(name in offsets[w] for w in wavelengths):
            variables[name] = (dims, stack(lambda w, n=name: offsets[w][n].values), {
                "units": "pixel", "long_name": f"1-sigma photon-noise error of d{axis} at each wavelength"})
    rows, cols = shape
    return xr.Dataset(
        variables,
        coords={"wavelength": ("wavelength", wavelengths, {"units": "m", "long_name": "calibration wavelength"}),
                "row": np.arange(rows), "col": np.arange(cols),
                "pair": ("wavelength", [pairs[w] for w in wavelengths], {
                    "long_name": "metrology pair whose offsets are the wavelength's, named as in the manifest"}),
                "flat": ("wavelength", [flats.get(w, "") for w in wavelengths], {
                    "long_name": "laser flat of the wavelength, named as in the manifest (empty: none)"})},
        attrs={"model": MODEL, "max_degree": MAX_DEGREE, "reference_wavelength": float(reference),
               "depth_coordinate": "ln(absorption length / 1 um) of silicon at 295 K (Schinke et al. 2015)"},
    )


def star_calibration(product: xr.Dataset, spectrum, *, white_prnu, log=None) -> dict:
    """The chromatic mode's calibration of stars of ``spectrum``: ``measure_positions``' prnu, dx, dy, variances.

    Parameters
    ----------
    product : xarray.Dataset
        ``calibration/chromatic.nc`` (:func:`chromatic_dataset`).
    spectrum : (samples, weights)
        The stars' detected spectrum (m, relative photons per unit wavelength).
    white_prnu : ndarray (row, col)
        The reference (white) flat's PRNU: the sensitivity where fewer than two wavelengths have a laser flat.

    Returns
    -------
    dict
        ``prnu`` (the effective sensitivity), ``dx``, ``dy`` (pixel) and ``variance_x``, ``variance_y``: the
        effective PRF variances' change from the reference wavelength's (pixel^2; zero where the widths were not
        measured), for :func:`dice_core.centroids.measure_positions`.

    Notes
    -----
    On an achromatic detector every wavelength's maps are the same, up to their noise: the effective maps are
    then the reference's (the model reproduces a constant), their noise a weighted mean's, and the variances'
    change is noise about zero, so that the mode is flat+metrology's.
    """
    wavelengths = [float(w) for w in product["wavelength"].values]
    with_flat = [w for i, w in enumerate(wavelengths) if np.isfinite(product["sensitivity"].values[i]).any()]
    several = len(with_flat) >= 2
    if log is not None and not several:
        log.info("chromatic: %d wavelength(s) with a laser flat; the white flat stands for the sensitivity",
                 len(with_flat))
    maps = {name: product[name].values for name in ("dx", "dy", "width_x", "width_y")}
    effective = effective_response(
        wavelengths, maps, spectrum=spectrum,
        sensitivity=product["sensitivity"].isel(wavelength=[wavelengths.index(w) for w in with_flat]).values
        if several else white_prnu,
        sensitivity_wavelengths=with_flat if several else None)
    # the manifest's order, not sorted: the nearest wavelength by hand
    nearest = int(np.argmin(np.abs(np.array(wavelengths) - float(product.attrs["reference_wavelength"]))))
    reference = product.isel(wavelength=nearest)
    variances = {}
    for axis in "xy":
        change = getattr(effective, f"variance_{axis}") - reference[f"width_{axis}"].values ** 2
        variances[f"variance_{axis}"] = np.where(np.isfinite(change), change, 0.0)
    if log is not None:
        log.info("chromatic: the stars' effective offsets from %s",
                 ", ".join(f"{w * 1e9:g} nm x {share:.3f}" for w, share in effective.weights.items()))
        if (warning := extrapolation_warning(wavelengths, spectrum, shares=effective.weights)) is not None:
            log.warning("chromatic: %s", warning)
    return {"prnu": effective.sensitivity, "dx": effective.dx, "dy": effective.dy, **variances}


def extrapolation_warning(calibration, spectrum, *, shares: dict) -> str | None:
    """What to warn of when the model is extrapolated for a spectrum, or None: light beyond the calibration
    wavelengths (m) or, with them, shares of the calibration maps whose absolute sum passes 1.5 (the maps'
    noise then grows by that sum at the most), and a straight line from two wavelengths, which the docs find
    can do worse than one (docs/centroids.md, "Chromatic pixels")."""
    samples, density = (np.asarray(v, float) for v in spectrum)
    lit = samples[density > 0]
    low, high = min(calibration), max(calibration)
    said = []
    if lit.size and (lit[0] < low - 1e-12 or lit[-1] > high + 1e-12):
        said.append(f"the spectrum's light at {lit[0] * 1e9:g}-{lit[-1] * 1e9:g} nm reaches beyond the calibration "
                    f"wavelengths' {low * 1e9:g}-{high * 1e9:g} nm: the model is extrapolated")
    amplification = float(sum(abs(v) for v in shares.values()))
    if amplification > 1.5:
        said.append(f"the maps' shares sum to {amplification:.2f} in absolute value: their noise grows as much")
    if len(calibration) == 2:
        said.append("two calibration wavelengths make the model a straight line in ln(absorption length)")
    return "; ".join(said) or None


def calibration_from_products(manifest, *, offsets: dict, metrology: dict, flats: dict, read, gain: float,
                              read_noise=None, shape=None, smooth_degree: int = 6, log=None) -> xr.Dataset:
    """``calibration/chromatic.nc`` of a dataset with pairs at several wavelengths, from its products.

    Parameters
    ----------
    manifest : dice_core.manifest.Manifest
        Format 1.2: its pairs' wavelengths say which products belong together.
    offsets, metrology, flats : dict
        Pair -> its ``calibration/offsets_<pair>.nc`` (each wavelength's reference pair), baseline -> its
        ``metrology/<baseline>.nc`` (every baseline of those pairs), flat -> its
        ``calibration/flats/prnu_<flat>.nc`` (the laser flats): whatever ``read`` takes (paths).
    read : callable
        Reads one product (:func:`dice_core.io.read_product`). Each wavelength's are read when it is reached
        and let go after: memory is one wavelength's products and every wavelength's result maps.
    gain, read_noise, shape, smooth_degree :
        The PRF width maps' (:func:`dice_core.prf.width_maps`), one set per wavelength of that wavelength's
        baselines.

    Raises
    ------
    ValueError
        A wavelength whose reference pair's offsets or baselines' products are missing.
    """
    from dice_core import prf

    found = {"offsets": {}, "widths": {}, "sensitivity": {}, "pairs": {}, "flats": {}}
    for wavelength in manifest.wavelengths:
        pairs = manifest.pairs_at(wavelength)
        baselines = list(dict.fromkeys(b for p in pairs for b in manifest.pairs[p]))
        missing = [p for p in pairs[:1] if p not in offsets] + [b for b in baselines if b not in metrology]
        if missing:
            raise ValueError(f"{wavelength * 1e9:g} nm: no product for {missing}")
        pair_offsets = read(offsets[pairs[0]])
        kept = [n for n in ("dx", "dy", "dx_photon_noise_floor", "dy_photon_noise_floor") if n in pair_offsets]
        found["offsets"][wavelength] = pair_offsets[kept].load()  # the maps the product takes, the rest let go
        found["pairs"][wavelength] = pairs[0]
        found["widths"][wavelength] = prf.width_maps({b: read(metrology[b]) for b in baselines}, gain=gain,
                                                     read_noise=read_noise, shape=shape, smooth_degree=smooth_degree,
                                                     science=manifest.detector.science_mask(), log=log)
        laser = [f for f in manifest.flats_at(wavelength) if f in flats]
        if laser:
            found["sensitivity"][wavelength] = read(flats[laser[0]])["prnu"].values
            found["flats"][wavelength] = laser[0]
        if log is not None:
            log.info("%g nm: pair %s, PRF widths from %s, %s", wavelength * 1e9, pairs[0], ", ".join(baselines),
                     f"laser flat {laser[0]}" if laser else "no laser flat")
    return chromatic_dataset(manifest.wavelengths, offsets=found["offsets"], widths=found["widths"],
                             sensitivity=found["sensitivity"], pairs=found["pairs"], flats=found["flats"],
                             reference=manifest.pair_wavelength(manifest.reference_pair))


def stars_spectrum(configured, manifest_spectrum):
    """The stars' spectrum (samples in m, weights) the chromatic mode uses: ``configured`` (config
    ``centroids.spectrum``: a name of :data:`SPECTRA` or {wavelength, weight}) where set, else the manifest's
    (a :class:`dice_core.manifest.Spectrum`).

    Raises
    ------
    ValueError
        Neither gives one; a configured spectrum of unequal lengths or decreasing wavelengths.
    """
    if configured is None:
        if manifest_spectrum is None:
            raise ValueError("no spectrum of the stars: the manifest has no stars.spectrum and config "
                             "centroids.spectrum is null")
        return np.array(manifest_spectrum.wavelength), np.array(manifest_spectrum.weight)
    if isinstance(configured, str):
        return named_spectrum(configured)
    wavelength, weight = (np.asarray(configured[k], float) for k in ("wavelength", "weight"))
    if (problem := spectrum_problem(wavelength, weight)) is not None:
        raise ValueError(f"config centroids.spectrum: {problem}")
    return wavelength, weight
