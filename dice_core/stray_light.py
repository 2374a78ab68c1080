"""Coherent stray light: its model on the bench, its signature in the pixel offsets, its diagnosis and removal.

Physics (paper, appendix C and section "Bias on pixel offsets"; docs/metrology.md, "Coherent stray light").
A stray source s (a baffle vane's edge) re-emits a copy of fiber f's wave with
field ratio eps (its field over the direct wave's, sqrt(I1 / I0)) and an optical
path P_s(r) = |r - S| + c_s to detector point r, S its position. Beside the direct
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
           "fit_amplitudes", "quadratic_frequency", "canonical", "reference_pixel"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StraySource:
    """One stray source on the bench: the fiber whose wave it re-emits, its position ``point`` (m, detector
    frame), its field ratio, and the constant ``path_constant`` c_s of its path P_s(r) = |r - S| + c_s, m."""

    fiber: str
    point: np.ndarray
    field_ratio: float
    path_constant: float
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
        constant = extra + np.linalg.norm(centre_m - tip) - np.linalg.norm(centre_m - point)
        out.append(StraySource(spec["fiber"], point, ratio, constant, extra))
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
    opd_ab = np.linalg.norm(centre_m - tip_a) - np.linalg.norm(centre_m - tip_b)
    modulated, static = [], []
    for index, s in enumerate(sources):
        if s.fiber not in fibers or s.field_ratio == 0:
            continue
        ds, sx, sy = _distance(x, y, s.point, pitch)
        path = ds + s.path_constant
        if s.fiber == fibers[0]:  # a copy of a, beating with b's wave
            phase, gx, gy, opd = k * (path - db), k * (sx - bx), k * (sy - by), s.extra_path + opd_ab
            own, ox, oy = k * (path - da), k * (sx - ax), k * (sy - ay)
        else:  # a copy of b, beating with a's
            phase, gx, gy, opd = k * (da - path), k * (ax - sx), k * (ay - sy), s.extra_path - opd_ab
            own, ox, oy = k * (path - db), k * (sx - bx), k * (sy - by)
        modulated.append((s.field_ratio * coherence(abs(opd), coherence_length), gx, gy, phase, index))
        static.append((s.field_ratio * coherence(abs(s.extra_path), coherence_length), ox, oy, own, index))
    return modulated, static, float(coherence(abs(opd_ab), coherence_length))


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
