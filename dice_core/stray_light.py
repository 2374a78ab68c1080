"""Coherent stray light: its model on the bench, its signature in the pixel offsets, its diagnosis and removal.

Physics (paper, appendix C and section "Bias on pixel offsets"; docs/metrology.md, "Coherent stray light").
A stray source s (a baffle vane's edge) at S re-emits a copy of fiber f's wave
with field ratio eps (its field over the direct wave's, sqrt(I1 / I0)) and an
optical path P_s(r) = |S - T_f| + |r - S| + e_s from f's tip T_f to detector
point r (e_s: the path the re-emission adds, a reflection's). Beside the direct
fringe of a baseline's two fibers a and b, Phi(r) = k (|r - a| - |r - b|), it makes

- with the *other* fiber's wave a parasitic fringe, modulated by the fringe
  sweep like the real one: Phi'_s = k (P_s - |r - b|) for a copy of a,
  k (|r - a| - P_s) for a copy of b. Each pixel then sees
  R + eps gamma R'_s, R the pixel's response to the direct fringe, R'_s to the
  parasitic one, so its fitted phase is off by
  arg(1 + eps gamma (h(K'_s) / h(K)) exp(i Delta_s)) ~ eps gamma (h(K'_s) / h(K)) sin Delta_s,
  Delta_s = Phi'_s - Phi = k (P_s - |r - f|) up to the sign of b's copy:
  a ripple at the spatial frequency of the stray and the direct wave's
  difference, weakened by the pixel's response h at the parasitic fringe's
  own frequency K'_s (only waves within about wavelength / pixel pitch of the
  fibers' directions survive the pixel's integration), sampled (aliased) by
  the pixel grid;
- with its *own* fiber's wave a static pattern, eps gamma B cos Delta_s, which
  only changes the level B (relative contrast 2 eps gamma in a flat lit by that
  fiber alone: speckle).

gamma = |gamma(OPD)| is the laser's coherence at the two waves' optical path
difference; with a coherence length Lc, gamma = exp(-(OPD / Lc)^2) (Lc the 1/e
OPD), 1 for a fully coherent laser. The direct fringe itself has
gamma(|a - r| - |b - r|), under 0.2 mm.

A ripple Delta_s is a chirped sinusoid: the difference of two spherical waves from
different distances has a quadratic phase about any point. Over a detector it is
described by a *component* of the projected offsets (pixel, at nominal pixel
centres r = (col, row), about a reference pixel r0)::

    a cos(2 pi (f . (r - r0) + g |r - r0|^2 / 2) + phi)

with spatial frequency f (cycles/pixel, aliased into [-1/2, 1/2), sign such that
f_x > 0 or f_x = 0 and f_y > 0), chirp g (cycles/pixel^2), amplitude a (pixel)
and phase phi (rad). A source at distance d_s gives g ~ pitch^2 / wavelength
(1 / d_s - 1 / d_f): about 1.5e-3 cycles/pixel^2 for a vane halfway to the
fibers, 6 frequency bins across an 80-pixel detector.

Units: m for positions and paths, pixel for offsets and pixel coordinates,
rad for phases, cycles/pixel for spatial frequencies.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

__all__ = ["StraySource", "coherence", "place_sources", "fringe_terms", "component_phase", "component_design",
           "fit_amplitudes", "quadratic_frequency", "canonical", "reference_pixel", "FALSE_ALARM", "MAX_CHIRP",
           "Component", "Diagnosis", "diagnose", "component_model", "tangent_modes", "diagnose_map",
           "diagnosis_variables", "stray_light_dataset", "summary_line", "fringe_harmonics", "EXCLUDE_BINS"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StraySource:
    """One stray source on the bench: the fiber whose wave it re-emits, its position ``point`` S (m, detector
    frame), its field ratio, and ``reemission`` e, m: the wave's optical path to detector point r from the
    fiber's tip T is P_s(r) = |S - T| + |r - S| + e (the tip may move, the source stays); ``extra_path`` is
    P_s - |r - T| at the detector centre for the tips it was placed with."""

    fiber: str
    point: np.ndarray
    field_ratio: float
    reemission: float
    extra_path: float


def coherence(opd, coherence_length):
    """|gamma| of the laser at optical path difference ``opd`` (m): exp(-(opd / Lc)^2), 1 without a
    coherence length (None: fully coherent)."""
    if coherence_length is None:
        return np.ones_like(np.asarray(opd, float)) if np.ndim(opd) else 1.0
    return np.exp(-(np.asarray(opd, float) / coherence_length) ** 2)


def _distance(x, y, point, pitch):
    """|r - point| (m) and its gradient along x, y (m/pixel) at pixel coordinates x, y (detector plane z = 0)."""
    dx, dy = np.asarray(x, float) * pitch - point[0], np.asarray(y, float) * pitch - point[1]
    d = np.sqrt(dx**2 + dy**2 + point[2] ** 2)
    return d, dx / d * pitch, dy / d * pitch


def place_sources(specs, tips: dict, *, centre, pitch, default_ratio: float):
    """Stray sources from their specifications, fixed in space by the fibers' *unshifted* tips.

    Parameters
    ----------
    specs : sequence of mappings
        ``fiber``; ``offset_mrad`` (x, y): the source's direction seen from the
        detector centre minus its fiber tip's, mrad; ``distance``: its height
        above the detector plane, m; ``extra_path``: its optical path to the
        detector centre minus the fiber's direct path, m; ``field_ratio``
        (optional, else ``default_ratio``).
    tips : dict
        Fiber name -> tip (x, y, z), m.
    centre : (float, float)
        The detector centre, pixel (x, y).
    pitch : float
        Pixel pitch, m.

    Returns
    -------
    list of StraySource
    """
    centre_m = np.array([centre[0] * pitch, centre[1] * pitch, 0.0])
    out = []
    for spec in specs:
        tip = np.asarray(tips[spec["fiber"]], float)
        d = float(spec["distance"])
        lateral = centre_m[:2] + (tip[:2] - centre_m[:2]) * d / tip[2] + d * 1e-3 * np.asarray(spec["offset_mrad"])
        point = np.array([*lateral, d])
        extra = float(spec["extra_path"])
        ratio = default_ratio if spec.get("field_ratio") is None else float(spec["field_ratio"])
        reemission = extra + np.linalg.norm(centre_m - tip) - np.linalg.norm(centre_m - point) - np.linalg.norm(
            point - tip)
        out.append(StraySource(spec["fiber"], point, ratio, reemission, extra))
    return out


def fringe_terms(x, y, tip_a, tip_b, sources, *, fibers, wavelength, pitch, coherence_length, centre):
    """The stray waves' terms in one baseline's frames, at pixel coordinates x, y.

    Returns
    -------
    modulated : list of (weight, gx, gy, phase, index)
        Parasitic fringes Phi'_s (rad; its gradient rad/pixel), each to be
        added to the direct fringe's response with ``weight`` = eps gamma.
    static : list of (weight, gx, gy, phase, index)
        Delta_s patterns of the level, weight eps gamma (relative to B).
    direct_coherence : float
        gamma of the direct fringe.
    Sources of fibers other than ``fibers`` (a, b) are left out; ``index``
    is the source's place in ``sources``.
    """
    k = 2 * np.pi / wavelength
    da, ax, ay = _distance(x, y, tip_a, pitch)
    db, bx, by = _distance(x, y, tip_b, pitch)
    centre_m = np.array([centre[0] * pitch, centre[1] * pitch, 0.0])
    to_a, to_b = np.linalg.norm(centre_m - tip_a), np.linalg.norm(centre_m - tip_b)
    modulated, static = [], []
    for index, s in enumerate(sources):
        if s.fiber not in fibers or s.field_ratio == 0:
            continue
        ds, sx, sy = _distance(x, y, s.point, pitch)
        tip = tip_a if s.fiber == fibers[0] else tip_b
        constant = np.linalg.norm(s.point - tip) + s.reemission
        path = ds + constant
        centre_path = np.linalg.norm(centre_m - s.point) + constant  # the OPDs, at the detector centre
        if s.fiber == fibers[0]:  # a copy of a, beating with b's wave
            phase, gx, gy, opd = k * (path - db), k * (sx - bx), k * (sy - by), centre_path - to_b
            own, ox, oy, own_opd = k * (path - da), k * (sx - ax), k * (sy - ay), centre_path - to_a
        else:  # a copy of b, beating with a's
            phase, gx, gy, opd = k * (da - path), k * (ax - sx), k * (ay - sy), centre_path - to_a
            own, ox, oy, own_opd = k * (path - db), k * (sx - bx), k * (sy - by), centre_path - to_b
        modulated.append((s.field_ratio * coherence(abs(opd), coherence_length), gx, gy, phase, index))
        static.append((s.field_ratio * coherence(abs(own_opd), coherence_length), ox, oy, own, index))
    return modulated, static, float(coherence(abs(to_a - to_b), coherence_length))


# --------------------------------------------------------------------------- components

def reference_pixel(x, y) -> tuple[int, int]:
    """The reference pixel r0 (x, y) of the components' phases: the integer pixel at the middle of the pixels'
    bounding box (an integer, so that a frequency aliased by whole cycles per pixel keeps its phase)."""
    return int((np.min(x) + np.max(x)) // 2), int((np.min(y) + np.max(y)) // 2)


def component_phase(x, y, frequency, chirp, reference):
    """2 pi (f . (r - r0) + g |r - r0|^2 / 2), rad, at pixel coordinates x, y; f (cycles/pixel), g
    (cycles/pixel^2), r0 = ``reference`` (x, y), pixel."""
    u, v = np.asarray(x, float) - reference[0], np.asarray(y, float) - reference[1]
    return 2 * np.pi * (frequency[0] * u + frequency[1] * v + 0.5 * chirp * (u * u + v * v))


def component_design(x, y, frequencies, chirps, reference) -> np.ndarray:
    """(2 n, pixel): cos and sin of each component's phase, the linear part of the component model."""
    rows = []
    for f, g in zip(frequencies, chirps):
        phase = component_phase(x, y, f, g, reference)
        rows += [np.cos(phase), -np.sin(phase)]
    return np.array(rows).reshape(2 * len(frequencies), np.size(x))


def fit_amplitudes(values, x, y, frequencies, chirps, reference, *, against=None):
    """Amplitudes (pixel) and phases (rad) of components of known frequencies and chirps in ``values``, fitted
    jointly by linear least squares (with the fields ``against``, (mode, pixel), e.g. the affine part, fitted
    beside them and discarded)."""
    design = component_design(x, y, frequencies, chirps, reference)
    extra = np.zeros((0, np.size(x))) if against is None else np.asarray(against, float)
    coef, *_ = np.linalg.lstsq(np.vstack([design, extra]).T, np.asarray(values, float), rcond=None)
    c, s = coef[0:2 * len(frequencies):2], coef[1:2 * len(frequencies):2]
    return np.hypot(c, s), np.arctan2(s, c)


def quadratic_frequency(phase, x, y, reference):
    """Frequency f (cycles/pixel) and isotropic chirp g (cycles/pixel^2) of a smooth phase map (rad) at pixel
    coordinates x, y: the least-squares quadratic c + 2 pi (f . u + g |u|^2 / 2 + anisotropic terms), u = r - r0."""
    u, v = np.asarray(x, float) - reference[0], np.asarray(y, float) - reference[1]
    design = np.column_stack([np.ones_like(u), u, v, 0.5 * (u * u + v * v), 0.5 * (u * u - v * v), u * v])
    coef, *_ = np.linalg.lstsq(design, np.asarray(phase, float), rcond=None)
    return coef[1:3] / (2 * np.pi), coef[3] / (2 * np.pi)


def canonical(frequency, chirp, phase):
    """(f, g, phi) aliased by the pixel grid into [-1/2, 1/2) cycles/pixel and signed so that f_x > 0 (or
    f_x = 0, f_y > 0): the same component, since a cos(x) = a cos(-x) at integer pixel offsets from r0."""
    f = np.asarray(frequency, float) - np.round(np.asarray(frequency, float))
    f = np.where(f >= 0.5, f - 1.0, f)
    if f[0] < 0 or (f[0] == 0 and f[1] < 0):
        return -f, -chirp, float(np.angle(np.exp(-1j * phase)))
    return f, chirp, float(np.angle(np.exp(1j * phase)))


# --------------------------------------------------------------------------- diagnosis

#: False-alarm probability per map of the detection threshold: the chance that a map without stray light
#: (white offsets and photon noise) shows a component.
FALSE_ALARM = 1e-3

#: Largest |chirp| searched, cycles/pixel^2: a vane edge 0.2 m above the detector, the fibers 0.6 m away
#: (pitch^2 / wavelength (1/0.2 - 1/0.6) = 3.0e-3 for 24 um pixels at 633 nm).
MAX_CHIRP = 3.0e-3

#: Most chirps searched (a map's spectrum is computed once for each, per component found).
MAX_CHIRPS = 61

#: Zero-padding of the spectrum along each axis (the power between Fourier bins, a quarter bin apart at most).
PAD = 2

#: Half-width, in Fourier bins along each axis, of the spectral cells left out about each excluded frequency
#: (a baseline's fringe frequency K / 2 pi and its harmonic 2K, where the gauge's residual mixing puts a ripple
#: of the fit's own: docs/metrology.md).
EXCLUDE_BINS = 2.0


@dataclass
class Component:
    """One stray-light component of a map (module docstring's model), with its 1-sigma errors."""

    frequency: np.ndarray        # (2,) cycles/pixel, x then y
    chirp: float                 # cycles/pixel^2
    amplitude: float             # pixel (the map's units)
    phase: float                 # rad, at the reference pixel
    frequency_error: np.ndarray  # (2,)
    chirp_error: float
    amplitude_error: float
    phase_error: float
    significance: float          # peak power of its dechirped spectrum over the white level, when found


@dataclass
class Diagnosis:
    """Result of :func:`diagnose`. Pixel arrays run over the pixels given to it."""

    reference: tuple             # r0 (x, y), pixel
    frequency_x: np.ndarray      # (nx,) cycles/pixel, increasing
    frequency_y: np.ndarray      # (ny,)
    power: np.ndarray            # (ny, nx): the map's power spectrum over the white level
    white_level: float           # variance per pixel of the map without its components (units^2)
    threshold: float             # detection threshold, in units of the white level
    false_alarm: float           # its false-alarm probability per map
    trials: int                  # independent spectral cells and chirps the threshold counts
    components: list             # Component, strongest first
    model: np.ndarray            # (pixel,) the components' sum
    modes: np.ndarray            # (mode, pixel): what fitting them takes from a map, 5 a component, unit rms
    excluded: list               # the frequencies left out (cycles/pixel)


def _spectrum(values, x, y, shape, chirp, reference):
    """|FFT|^2 / N (zero-padded PAD times) of ``values`` at pixels x, y of a (rows, cols) box, dechirped by
    ``chirp``: each spectral cell's power is that of the best sinusoid of its frequency with that chirp."""
    grid = np.zeros((PAD * shape[0], PAD * shape[1]), complex)
    u, v = x - reference[0], y - reference[1]
    grid[(y - y.min()).astype(int), (x - x.min()).astype(int)] = values * np.exp(-1j * np.pi * chirp * (u * u + v * v))
    return np.abs(np.fft.fft2(grid)) ** 2 / values.size


def _half_plane(ny, nx):
    """Cells of a (ny, nx) FFT grid with f_x > 0, or f_x = 0 and f_y > 0 (one of each conjugate pair, no zero)."""
    fy, fx = np.fft.fftfreq(ny)[:, None], np.fft.fftfreq(nx)[None, :]
    return (fx > 0) | ((fx == 0) & (fy > 0))


def _residual(values, x, y, components, reference, basis):
    """``values`` minus their least-squares fit by the components' sinusoids (amplitudes free) and ``basis``
    ((mode, pixel), orthonormal rows of unit norm); and the components' fitted (cos, -sin) coefficients."""
    design = component_design(x, y, [c[0] for c in components], [c[1] for c in components], reference)
    values = values - basis.T @ (basis @ values)
    design = design - (design @ basis.T) @ basis
    if not len(design):
        return values, np.zeros(0)
    coef = np.linalg.lstsq(design @ design.T, design @ values, rcond=None)[0]
    return values - design.T @ coef, coef


def _refine(values, x, y, found, reference, basis, iterations: int = 20):
    """Frequencies and chirps of ``found`` [(f, g)] refined jointly by damped Gauss-Newton on the full model,
    the amplitudes and ``basis`` solved linearly at every step (variable projection, Kaufman's Jacobian)."""
    params = np.array([[*f, g] for f, g in found], float)
    u, v = x - reference[0], y - reference[1]
    r2 = 0.5 * (u * u + v * v)

    def evaluate(p):
        return _residual(values, x, y, [(q[:2], q[2]) for q in p], reference, basis)

    residual, coef = evaluate(params)
    cost, damping = float(residual @ residual), 1e-3
    for _ in range(iterations):
        columns = []
        for i, (fx, fy, g) in enumerate(params):
            phase = component_phase(x, y, (fx, fy), g, reference)
            # d/dtheta of c cos(theta) - s sin(theta) is -(c sin(theta) + s cos(theta))
            d = -(coef[2 * i] * np.sin(phase) + coef[2 * i + 1] * np.cos(phase)) * 2 * np.pi
            columns += [d * u, d * v, d * r2]
        jac = np.array(columns)
        linear = component_design(x, y, [q[:2] for q in params], params[:, 2], reference)
        linear = linear - (linear @ basis.T) @ basis  # basis: orthonormal rows
        jac = jac - (jac @ basis.T) @ basis
        jac = jac - np.linalg.solve(linear @ linear.T, linear @ jac.T).T @ linear
        normal, rhs = jac @ jac.T, jac @ residual
        while True:
            step = np.linalg.solve(normal + damping * np.diag(np.diag(normal)), rhs)
            trial = params + step.reshape(params.shape)
            new_residual, new_coef = evaluate(trial)
            new_cost = float(new_residual @ new_residual)
            if new_cost <= cost or damping > 1e6:
                break
            damping *= 10
        if new_cost > cost:
            break
        params, residual, coef, damping = trial, new_residual, new_coef, max(damping / 10, 1e-6)
        converged = cost - new_cost < 1e-10 * cost
        cost = new_cost
        if converged:
            break
    return [(q[:2].copy(), float(q[2])) for q in params]


def _tangents(x, y, comp, reference):
    """The directions a component moves a map along when its 5 parameters move: (5, pixel)."""
    f, g, a, phi = comp
    u, v = x - reference[0], y - reference[1]
    phase = component_phase(x, y, f, g, reference) + phi
    c, s = np.cos(phase), np.sin(phase)
    return np.array([c, s, u * s, v * s, 0.5 * (u * u + v * v) * s])


def _errors(values, x, y, comps, reference, basis, white_level):
    """1-sigma errors (f_x, f_y, g, a, phi per component) from the linearised least squares with the white
    level as the noise: the Jacobian of the model in these parameters, the basis fitted beside them."""
    columns = []
    for f, g, a, phi in comps:
        u, v = x - reference[0], y - reference[1]
        phase = component_phase(x, y, f, g, reference) + phi
        c, s = np.cos(phase), np.sin(phase)
        columns += [-a * 2 * np.pi * u * s, -a * 2 * np.pi * v * s, -a * np.pi * (u * u + v * v) * s, c, -a * s]
    jac = np.vstack([np.array(columns), basis]).T
    covariance = white_level * np.linalg.pinv(jac.T @ jac)
    return np.sqrt(np.diag(covariance))[:5 * len(comps)].reshape(len(comps), 5)


def fringe_harmonics(k) -> list:
    """The frequencies (cycles/pixel) a diagnosis leaves out for a fringe of wavevector ``k`` (rad/pixel):
    K / 2 pi and 2 K / 2 pi, where a wrong gauge (the residual mixing of the level with the fringe terms) puts
    first and second harmonics of the fringe phase into the offsets, and photon noise a ripple of its own."""
    f = np.asarray(k, float) / (2 * np.pi)
    return [f, 2 * f]


def _excluded(fx, fy, exclude, shape):
    """Cells (fy, fx grid) within EXCLUDE_BINS Fourier bins of +-each excluded frequency, aliased."""
    out = np.zeros((fy.size, fx.size), bool)
    for f in exclude:
        for sign in (1, -1):
            dx = (fx[None, :] - sign * f[0] + 0.5) % 1.0 - 0.5
            dy = (fy[:, None] - sign * f[1] + 0.5) % 1.0 - 0.5
            out |= (np.abs(dx) <= EXCLUDE_BINS / shape[1]) & (np.abs(dy) <= EXCLUDE_BINS / shape[0])
    return out


def diagnose(values, x, y, *, against=None, exclude=(), false_alarm: float = FALSE_ALARM, max_components: int = 6,
             max_chirp: float = MAX_CHIRP) -> Diagnosis:
    """Coherent stray-light components of an offset map: its spectrum against the white level, those above.

    Parameters
    ----------
    values : ndarray (pixel,)
        A map of offsets (pixel; or any map), finite, at pixel coordinates ``x``, ``y`` (col, row).
    against : ndarray (mode, pixel), optional
        Fields the map was made orthogonal to (its affine part, a baseline's unobservable modes), fitted
        beside the components; the affine part is always.
    exclude : sequence of (float, float)
        Frequencies (cycles/pixel) whose cells (EXCLUDE_BINS Fourier bins about them and their opposites,
        aliased) are not searched: the fringes' own (:func:`fringe_harmonics`).
    false_alarm : float
        Probability that a map of white noise shows a component (per map).
    max_components : int
        At most this many components.
    max_chirp : float
        Largest |chirp| searched, cycles/pixel^2.

    Returns
    -------
    Diagnosis

    Notes
    -----
    Without stray light, an offset map is white: the pixels' own offsets (about 1e-3 pixel) plus photon
    noise, variance sigma^2, whose power spectrum |sum_p v_p exp(-2 pi i f.r_p)|^2 / N is exponential with
    mean sigma^2 in every Fourier cell. sigma^2 is the median of the spectrum over ln 2, robust to a few
    peaks. A component is a peak of the spectrum dechirped by one of the chirps of a grid (steps that move
    the edge's phase by 1 rad at most, up to ``max_chirp``). Over the M cells of one half-plane of the
    spectrum, zero-padded PAD times along each axis, and the C chirps, the largest of PAD^2 M C exponential
    variables exceeds t = -ln(1 - (1 - alpha)^(1 / (PAD^2 M C))) with probability alpha, the cells treated
    as independent: the padded cells and neighbouring chirps are correlated, so the false-alarm probability
    is at most ``false_alarm``. Each peak above t is fitted with its frequency and chirp refined by least
    squares, jointly with the earlier ones, the amplitudes and ``against``; the spectrum of what is left is
    searched again. The errors are those of the linearised fit with the white level as the noise.
    """
    values, x, y = (np.asarray(v, float) for v in (values, x, y))
    if values.size < 16 or not np.all(np.isfinite(values)):
        raise ValueError("diagnose needs at least 16 finite values")
    reference = reference_pixel(x, y)
    from dice_core.geometry import orthonormal_modes

    basis = orthonormal_modes(np.vstack([np.array([np.ones_like(x), x, y]), np.zeros((0, x.size)) if against is None
                                         else np.asarray(against, float)])) / np.sqrt(x.size)
    shape = (int(y.max() - y.min()) + 1, int(x.max() - x.min()) + 1)
    ny, nx = PAD * shape[0], PAD * shape[1]
    half = _half_plane(ny, nx)
    half_extent = 0.5 * np.hypot(*shape)
    # a chirp step moves the phase at the box's corner by 1 rad; on a large detector, where that would take
    # thousands of spectra, MAX_CHIRPS of them (a strongly chirped component then shows with less contrast)
    step = max(1.0 / (np.pi * half_extent**2), 2 * max_chirp / (MAX_CHIRPS - 1))
    chirps = np.arange(-np.floor(max_chirp / step), np.floor(max_chirp / step) + 1) * step
    cells = int(np.count_nonzero(_half_plane(*shape)))
    trials = PAD**2 * cells * chirps.size
    threshold = float(-np.log1p(-(1 - false_alarm) ** (1 / trials)))
    fx, fy = np.fft.fftfreq(nx), np.fft.fftfreq(ny)
    half &= ~_excluded(fx, fy, exclude, shape)
    residual, _ = _residual(values, x, y, [], reference, basis)
    plain = _spectrum(residual, x, y, shape, 0.0, reference)
    found, significance = [], []
    while len(found) < max_components:
        white = float(np.median(_spectrum(residual, x, y, shape, 0.0, reference)[::PAD, ::PAD][_half_plane(*shape)])
                      / np.log(2))
        best = (0.0, None)
        for g in chirps:
            power = np.where(half, _spectrum(residual, x, y, shape, g, reference), 0.0) / white
            i = np.unravel_index(np.argmax(power), power.shape)
            if power[i] > best[0]:
                best = (float(power[i]), (np.array([fx[i[1]], fy[i[0]]]), float(g)))
        if best[0] <= threshold:
            break
        found = _refine(values, x, y, [*found, best[1]], reference, basis)
        significance.append(best[0])
        residual, _ = _residual(values, x, y, found, reference, basis)
    residual, coef = _residual(values, x, y, found, reference, basis)
    white_level = float(np.sum(residual**2) / max(values.size - basis.shape[0] - 5 * len(found), 1))
    basis = basis * np.sqrt(x.size)  # unit rms, for the errors' Jacobian and the modes
    comps = []
    for i, (f, g) in enumerate(found):
        c, s = coef[2 * i], coef[2 * i + 1]
        f, g, phi = canonical(f, g, float(np.arctan2(s, c)))
        comps.append((f, g, float(np.hypot(c, s)), phi))
    errors = _errors(values, x, y, comps, reference, basis, white_level) if comps else np.zeros((0, 5))
    components = [Component(f, g, a, phi, e[:2], float(e[2]), float(e[3]), float(e[4]), sig)
                  for (f, g, a, phi), e, sig in zip(comps, errors, significance)]
    order = np.argsort([-c.amplitude for c in components])
    components = [components[i] for i in order]
    model = component_model(x, y, components, reference)
    modes = tangent_modes(x, y, components, reference, against=basis)
    power = np.fft.fftshift(plain / white_level)
    return Diagnosis(reference, np.fft.fftshift(fx), np.fft.fftshift(fy), power, white_level, threshold,
                     false_alarm, trials, components, model, modes, [np.asarray(f, float) for f in exclude])


def component_model(x, y, components, reference) -> np.ndarray:
    """The sum of ``components`` (:class:`Component`) at pixel coordinates x, y."""
    out = np.zeros(np.size(x))
    for c in components:
        out += c.amplitude * np.cos(component_phase(x, y, c.frequency, c.chirp, reference) + c.phase)
    return out


def tangent_modes(x, y, components, reference, *, against=None) -> np.ndarray:
    """What fitting ``components`` takes from a map: the span of each one's 5 parameter directions (cos,
    sin, and the frequencies' and chirp's, at its fitted phase), orthonormal (unit rms) and orthogonal to
    ``against``; (mode, pixel). A map's part along them cannot be told from the components."""
    from dice_core.geometry import orthonormal_modes

    if not components:
        return np.zeros((0, np.size(x)))
    fields = np.vstack([_tangents(np.asarray(x, float), np.asarray(y, float),
                                  (c.frequency, c.chirp, c.amplitude, c.phase), reference) for c in components])
    return orthonormal_modes(fields, against=against)


# --------------------------------------------------------------------------- products

def diagnose_map(values, *, modes=None, exclude=(), false_alarm: float = FALSE_ALARM):
    """:func:`diagnose` of a (row, col) map over its finite pixels, ``modes`` (mode, row, col) the fields it
    was made orthogonal to; returns (diagnosis, rows, cols) of those pixels."""
    values = np.asarray(values, float)
    good = np.isfinite(values)
    rows, cols = np.nonzero(good)
    against = None if modes is None or not len(modes) else np.asarray(modes)[:, good]
    return diagnose(values[good], cols.astype(float), rows.astype(float), against=against, exclude=exclude,
                    false_alarm=false_alarm), rows, cols


def diagnosis_variables(diagnosis: Diagnosis, rows, cols, shape, *, prefix: str = "", k_norm=None,
                        modes: bool = True) -> dict:
    """The variables a product holds of a :class:`Diagnosis` of a map (row, col) of ``shape``: its power map,
    white level, threshold, components (dim ``<prefix>component``), their sum (``<prefix>offset_error``) and,
    given the local |K| (row, col, rad/pixel), the phase error they make (``<prefix>phase_error``); with
    ``modes``, what removing them takes (``<prefix>stray_mode``, unit rms)."""
    p, comps = prefix, diagnosis.components
    component = (f"{p}component",)

    def as_map(values):
        out = np.full(shape, np.nan)
        out[rows, cols] = values
        return out

    def column(name, units, meaning, values):
        return {f"{p}component_{name}": (component, np.array(values, float).reshape(len(comps)),
                                         {"units": units, "long_name": meaning})}

    offset = as_map(diagnosis.model)
    out = {
        f"{p}power": (("frequency_y", "frequency_x"), diagnosis.power,
                      {"units": "1", "long_name": "power spectrum of the map over its white level"}),
        f"{p}white_level": ((), diagnosis.white_level,
                            {"units": "pixel2", "long_name": "variance per pixel of the map without its components "
                                                              "(pixel offsets and photon noise)"}),
        f"{p}threshold": ((), diagnosis.threshold,
                          {"units": "1", "long_name": "detection threshold over the white level"}),
        f"{p}false_alarm": ((), diagnosis.false_alarm,
                            {"units": "1", "long_name": "probability that a map without stray light shows a "
                                                        "component (at most)"}),
        f"{p}n_components": ((), len(comps), {"units": "1", "long_name": "components found"}),
        f"{p}excluded_frequency": ((f"{p}excluded", "axis"), np.array(diagnosis.excluded, float).reshape(-1, 2),
                                   {"units": "1/pixel", "long_name": "frequencies (x, y) whose cells were not "
                                                                     "searched: the fringes' K / 2 pi and 2K / 2 pi"}),
        f"{p}offset_error": (("row", "col"), offset, {"units": "pixel", "long_name": "the components' sum"}),
        **column("frequency_x", "1/pixel", "spatial frequency along x (aliased into [-1/2, 1/2), f_x >= 0)",
                 [c.frequency[0] for c in comps]),
        **column("frequency_y", "1/pixel", "spatial frequency along y", [c.frequency[1] for c in comps]),
        **column("chirp", "1/pixel2", "chirp g: the frequency grows by g per pixel from the reference pixel",
                 [c.chirp for c in comps]),
        **column("amplitude", "pixel", "amplitude in the map", [c.amplitude for c in comps]),
        **column("phase", "rad", "phase at the reference pixel", [c.phase for c in comps]),
        **column("frequency_x_error", "1/pixel", "1-sigma error", [c.frequency_error[0] for c in comps]),
        **column("frequency_y_error", "1/pixel", "1-sigma error", [c.frequency_error[1] for c in comps]),
        **column("chirp_error", "1/pixel2", "1-sigma error", [c.chirp_error for c in comps]),
        **column("amplitude_error", "pixel", "1-sigma error", [c.amplitude_error for c in comps]),
        **column("phase_error", "rad", "1-sigma error", [c.phase_error for c in comps]),
        **column("significance", "1", "peak power of its dechirped spectrum over the white level",
                 [c.significance for c in comps]),
    }
    if k_norm is not None:
        out[f"{p}phase_error"] = (("row", "col"), offset * k_norm,
                                  {"units": "rad", "long_name": "phase error the components make (the sum times the "
                                                                "local |K|), in the fitted phase's sense"})
    if modes:
        stack = np.full((len(diagnosis.modes), *shape), np.nan)
        stack[:, rows, cols] = diagnosis.modes
        out[f"{p}stray_mode"] = ((f"{p}stray_mode", "row", "col"), stack,
                                 {"units": "1", "long_name": "what fitting the components takes from the map: 5 "
                                                             "directions each, orthonormal (unit rms), orthogonal "
                                                             "to the affine part and the map's own modes"})
    return out


def stray_light_dataset(metrology, *, false_alarm: float = FALSE_ALARM, baseline: str = "baseline"):
    """The ``calibration/stray_light_<baseline>.nc`` product of a ``metrology/<baseline>.nc`` dataset: the
    diagnosis (:func:`diagnose`) of its projected offsets, fitted beside its unobservable modes."""
    import xarray as xr

    offsets = metrology["projected_offset"].values
    modes = metrology["unobservable_offset"].values if "unobservable_offset" in metrology else None
    exclude = fringe_harmonics((float(metrology["kx"]), float(metrology["ky"])))
    diagnosis, rows, cols = diagnose_map(offsets, modes=modes, exclude=exclude, false_alarm=false_alarm)
    if "kx_local" in metrology:
        k_norm = np.hypot(metrology["kx_local"].values, metrology["ky_local"].values)
    else:
        k_norm = np.full(offsets.shape, float(np.hypot(metrology["kx"], metrology["ky"])))
    variables = diagnosis_variables(diagnosis, rows, cols, offsets.shape, k_norm=k_norm)
    product = xr.Dataset(variables, coords={
        "row": metrology["row"].values, "col": metrology["col"].values,
        "frequency_x": ("frequency_x", diagnosis.frequency_x, {"units": "1/pixel", "long_name": "spatial frequency"}),
        "frequency_y": ("frequency_y", diagnosis.frequency_y, {"units": "1/pixel", "long_name": "spatial frequency"}),
        "axis": ["x", "y"],
    })
    product.attrs.update({"baseline": baseline, "reference_pixel": list(diagnosis.reference),
                          "component_model": "a cos(2 pi (f.(r - r0) + g |r - r0|^2 / 2) + phi), r = (col, row), "
                                             "r0 = reference_pixel (x, y)"})
    log.info("%s", summary_line(diagnosis, baseline))
    return product


def summary_line(diagnosis: Diagnosis, what: str) -> str:
    """One line saying what a diagnosis found in ``what``."""
    if not diagnosis.components:
        return (f"{what}: no coherent stray light (no spectral peak above {diagnosis.threshold:.1f} x the white "
                f"level, false-alarm rate {diagnosis.false_alarm:g})")
    found = "; ".join(f"f = ({c.frequency[0]:+.4f}, {c.frequency[1]:+.4f}) cycles/pixel, amplitude "
                      f"{c.amplitude:.2e} pixel ({c.significance:.0f} x white)" for c in diagnosis.components)
    return (f"{what}: coherent stray light, {len(diagnosis.components)} component(s) above {diagnosis.threshold:.1f} "
            f"x the white level (false-alarm rate {diagnosis.false_alarm:g}): {found}; their rms "
            f"{float(np.sqrt(np.mean(diagnosis.model ** 2))):.2e} pixel")
