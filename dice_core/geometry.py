"""Spherical-wave fringes of two fiber tips: the phase surface, its refinement, and what it absorbs.

On a real DICE bench each baseline's fringes come from two fiber tips, point
sources at s1 and s2 about 600 mm from the detector. Their phase at detector
point r (dataset format, "Coordinates")::

    Phi(r) = (2 pi / wavelength) (|r - s1| - |r - s2|),   r = (x, y, 0) pixel_pitch,

a hyperboloid, not a plane: fitted with a plane over an 80x84 detector it
leaves up to 1e-3 pixel of smooth pattern in the offsets once the baseline's
midpoint is 10-20 mm off the detector normal. :func:`fit_two_source`
measures each pixel's offset against this surface instead, along the pixel's
local wavevector grad Phi, after refining the tips from the pixel phases.

Refinement and what it absorbs (docs/metrology.md, "Spherical waves"). The
pixel phases are theta_p = sign Phi(r_p + delta_p) + c + a.r_p: the sign
and constant c are the fringe solution's gauge, the plane a.r_p carries the
affine part of the offsets, which metrology never sees (dataset format). The
tips are refined by a maximum a posteriori fit: the nominal tips, known to
``tip_sigma`` (about 1 mm on a bench), are the prior, and the unknown pixel
offsets, rms s_delta, are the noise the tips are fitted against. Moving the
tips changes the surface along six patterns, the columns of d Phi / d s; with
the plane free, only their non-affine parts matter. Every mode whose
information ratio, data over prior,

    r_k = tip_sigma^2 lambda_k / (s_delta |K|)^2 > MODE_INFORMATION_THRESHOLD (0.01),

lambda_k the eigenvalues of J'J (J the non-affine parts of d Phi / d s), is
declared: the fit absorbs a fraction r_k / (1 + r_k) of the offsets'
component along it into the tips (all of it for r_k >> 1, part of it for
0.01 < r_k < 1, where the prior still dominates). They are the unobservable
modes the offsets product declares, and the offsets are reported orthogonal
to them. The other modes stay at the prior. For offsets that are white, with
rms s_delta over N pixels, what such a mode can leave in the offsets is at
most about sqrt(r_k) s_delta / sqrt(N), a tenth of s_delta / sqrt(N) at the
threshold. Offsets with a smooth component c along an undeclared mode lose
r_k / (1 + r_k) of it, up to 1 % of c.

The refinement fits wrapped phase residuals, which see the truth only while
the surface is within about a radian of it everywhere: on a detector wider
than about 1000 pixels at 600 mm it runs in stages, over discs from the
centre out (:func:`fit_two_source`, ``STAGE_PHASE_LIMIT``), each from the
plane its residual's periodogram peaks at within the plane's 3-sigma error.

Units: m for positions, pixel for x, y and offsets, rad for phases,
rad/pixel for wavevectors.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np

from dice_core.pixel_blocks import pixel_blocks, stacked_r

__all__ = [
    "UNOBSERVABLE_MODE",
    "MODE_INFORMATION_THRESHOLD",
    "MAX_TIP_SHIFT_SIGMA",
    "GeometryError",
    "BaselineGeometry",
    "TwoSourceFit",
    "two_source_phase",
    "tip_jacobian",
    "fit_two_source",
    "wrapped_about_mean",
    "affine_basis",
    "orthonormal_modes",
    "remove_modes",
]

log = logging.getLogger(__name__)

#: Largest move of a refined tip coordinate from its nominal value accepted, in units of tip_sigma.
MAX_TIP_SHIFT_SIGMA = 5.0
#: Attributes of the ``mode`` coordinate of the products that hold unobservable offset modes (a baseline's
#: ``unobservable_offset``, a pair's ``unobservable_dx``, ``unobservable_dy``).
UNOBSERVABLE_MODE = {"units": "1", "long_name": "unobservable offset mode beyond the affine part, counted from 0"}

#: Largest phase (rad) that the tips' uncertainty may put, at 3 sigma, on a pixel of a stage of the tips'
#: refinement beyond the affine part. The refinement fits wrapped phase residuals: where they pass +-pi its
#: Gauss-Newton steps wander (a 2048x2048 detector at 600 mm, tips 1 mm off: up to 12 rad), so a large detector
#: is refined from its centre out, over discs it can trust (:func:`fit_two_source`).
STAGE_PHASE_LIMIT = 1.0
#: Fewest pixels of the first stage of a refinement in stages.
STAGE_MIN_PIXELS = 200
#: Pixels over which a stage's phase bound is evaluated (evenly picked; the bound is smooth), and over which
#: the periodogram that finds the plane a stage starts from is summed (picked at random).
STAGE_BOUND_SAMPLES = 20000
#: Largest phase (rad) at a stage's edge between the plane a stage starts from, searched for on a grid, and the
#: periodogram's peak: sets the grid's step. The first stage's affine fits of the wrapped residual, or a later
#: stage's Gauss-Newton steps, then take the plane the rest of the way.
STAGE_PLANE_STEP = 0.25
#: Most steps of that grid each way from the plane carried into a stage, per axis.
STAGE_PLANE_POINTS = 128

#: Information ratio (data over prior) above which a tip mode counts as refined from the data,
#: and its offset pattern as unobservable (module docstring).
MODE_INFORMATION_THRESHOLD = 0.01


class GeometryError(ValueError):
    """Pixel phases that the two-source surface of the given tips does not fit."""


@dataclass(frozen=True)
class BaselineGeometry:
    """One baseline's bench: its two fibers (phase order) and their nominal tips, m, detector frame.

    ``tip_sigma`` is the 1-sigma error of each nominal coordinate, m (the
    prior of the refinement); ``wavelength`` and ``pixel_pitch`` are in m.
    """

    fibers: tuple[str, str]
    nominal: tuple[tuple[float, float, float], tuple[float, float, float]]
    wavelength: float
    pixel_pitch: float
    tip_sigma: float = 1e-3

    @classmethod
    def of_baseline(cls, bench, baseline: str, *, tip_sigma: float = 1e-3,
                    wavelength: float | None = None) -> "BaselineGeometry":
        """From a manifest's :class:`dice_core.manifest.BenchGeometry`; ``wavelength`` (m), the baseline's own
        (format 1.2: ``Manifest.baseline_wavelength``), replaces the bench's in its phase surface."""
        fibers = tuple(bench.baseline_fibers[baseline])
        return cls(fibers, tuple(tuple(bench.fibers[f]) for f in fibers),
                   bench.wavelength if wavelength is None else wavelength, bench.pixel_pitch, tip_sigma)


def two_source_phase(x, y, tip_a, tip_b, *, wavelength, pixel_pitch):
    """Phase (rad) and its gradient (rad/pixel) of the fringes of two point sources at pixel coordinates x, y.

    Phi = (2 pi / wavelength) (|r - a| - |r - b|) with r = (x, y, 0) pixel_pitch
    (the dataset format's definition); the gradient is taken along x and y in
    pixel units. For tips far from the detector, grad Phi is about
    2 pi (b - a)_xy pixel_pitch / (wavelength distance).

    Returns
    -------
    phase, gx, gy : ndarray (shape of x and y)
    """
    x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
    r = np.stack([x * pixel_pitch, y * pixel_pitch, np.zeros(x.shape)], axis=-1)
    to_a, to_b = r - np.asarray(tip_a, float), r - np.asarray(tip_b, float)
    del r  # (temporaries formed in place where the bits are the same: this runs over every pixel)
    da, db = np.linalg.norm(to_a, axis=-1), np.linalg.norm(to_b, axis=-1)
    wavenumber = 2 * np.pi / wavelength
    gradient = to_a[..., :2] / da[..., None]
    del to_a
    gradient -= to_b[..., :2] / db[..., None]
    del to_b
    gradient *= wavenumber * pixel_pitch
    return wavenumber * (da - db), gradient[..., 0], gradient[..., 1]


def tip_jacobian(x, y, tip_a, tip_b, *, wavelength, pixel_pitch) -> np.ndarray:
    """d Phi / d (tip_a, tip_b) at pixel coordinates x, y (1-D): (pixel, 6), rad/m.

    Columns: a_x, a_y, a_z, b_x, b_y, b_z. d|r - a| / da = -(r - a) / |r - a|.
    """
    r = np.stack([np.asarray(x, float) * pixel_pitch, np.asarray(y, float) * pixel_pitch,
                  np.zeros(np.size(x))], axis=-1)
    jacobian = np.empty((r.shape[0], 6))  # filled in place: this runs over every pixel
    for columns, tip in ((slice(0, 3), tip_a), (slice(3, 6), tip_b)):
        unit = np.subtract(r, np.asarray(tip, float), out=jacobian[:, columns])
        unit /= np.linalg.norm(unit, axis=-1, keepdims=True)
    np.negative(jacobian[:, :3], out=jacobian[:, :3])
    jacobian *= 2 * np.pi / wavelength
    return jacobian


def wrapped_about_mean(phase, *, block: int | None = None):
    """Phases (rad) wrapped to (-pi, pi] about their circular mean.

    Wrapped about zero instead, phases spread around pi (a constant the gauge
    leaves free) would split between +pi and -pi, a whole period apart.
    Formed ``block`` phases at a time: the complex exponentials never span
    every phase (32 bytes a phase each); the mean is summed block by block.
    """
    phase = np.asarray(phase, float)
    flat = phase.reshape(-1)
    total = 0j
    for s in pixel_blocks(flat.size, block):
        total += np.exp(1j * flat[s]).sum()
    centre = np.angle(total / flat.size)
    out = np.empty_like(flat)
    for s in pixel_blocks(flat.size, block):
        out[s] = _wrap(flat[s] - centre)
    return out.reshape(phase.shape)


def _wrap(phase):
    return np.angle(np.exp(1j * phase))


def affine_basis(x, y) -> np.ndarray:
    """The affine fields 1, x, y at pixel coordinates x, y (1-D): (3, pixel)."""
    x = np.asarray(x, float)
    return np.array([np.ones_like(x), x, np.asarray(y, float)])


def orthonormal_modes(fields, *, against=None):
    """Orthonormal basis of the span of ``fields`` (mode, sample), orthogonal to ``against`` (mode, sample).

    The inner product is the mean over samples, so every returned mode has
    unit rms. Directions of ``fields`` inside the span of ``against``, or
    dependent on the others, below 1e-9 of the largest field's norm, are
    dropped.
    """
    fields = np.asarray(fields, float).reshape(-1, np.shape(fields)[-1])
    n = fields.shape[1]
    if fields.shape[0] == 0:
        return np.empty((0, n))
    scale = np.max(np.linalg.norm(fields, axis=1))
    if against is not None and len(against):  # (in place where the bits are the same: fields span every pixel)
        basis = orthonormal_modes(against)
        basis /= np.sqrt(n)
        projection = (fields @ basis.T) @ basis
        fields = np.subtract(fields, projection, out=projection)
        del basis
    return _svd_modes(fields, scale)


def _svd_modes(fields, scale):
    """The left singular vectors of ``fields`` (mode, sample) whose singular value is above 1e-9 ``scale``,
    times sqrt(sample): :func:`orthonormal_modes` of fields already orthogonal to what they are made against."""
    n = fields.shape[1]
    u, s, _ = np.linalg.svd(fields.T, full_matrices=False)
    del fields
    modes = u[:, s > 1e-9 * scale].T
    modes *= np.sqrt(n)
    return modes


def remove_modes(values, modes):
    """``values`` (sample,) minus their least-squares projection on the span of ``modes`` (mode, sample).

    Dependent modes are harmless: the projection is onto an orthonormal basis
    of their span (:func:`orthonormal_modes`).
    """
    values = np.asarray(values, float)
    if len(modes) == 0:
        return values.copy()
    basis = orthonormal_modes(modes)
    basis /= np.sqrt(values.size)
    projection = basis.T @ (basis @ values)
    return np.subtract(values, projection, out=projection)


def _affine_rows(x, y, s, *columns):
    """The rows [1, x, y, columns...] of the samples ``s`` (a slice), columns given for those samples."""
    return np.column_stack([np.ones(s.stop - s.start), x[s], y[s], *columns])


def _affine_coefficients(R):
    """Least-squares coefficients (3, column) on 1, x, y of the columns after the first three, from the R of
    [1 | x | y | columns] (:func:`dice_core.pixel_blocks.stacked_r`)."""
    return np.linalg.lstsq(R[:3, :3], R[:3, 3:], rcond=None)[0]


def _without_affine(values, x, y, *, block: int | None = None):
    """``values`` (sample,) minus their least-squares fit by 1, x, y: ``remove_modes(values, affine_basis(x, y))``
    to rounding, with the fit's sums taken ``block`` samples at a time (no (3, sample) basis formed)."""
    values = np.asarray(values, float)
    n = values.size
    R = stacked_r(_affine_rows(x, y, s, values[s]) for s in pixel_blocks(n, block))
    coef = _affine_coefficients(R)[:, 0]
    out = values - coef[0]
    for s in pixel_blocks(n, block):
        out[s] -= coef[1] * x[s] + coef[2] * y[s]
    return out


def _without_orthonormal(values, modes):
    """``values`` (sample,) minus their projection on ``modes`` (mode, sample), orthonormal with unit rms (as
    :func:`orthonormal_modes` makes them), in place: :func:`remove_modes` to rounding, no basis made again."""
    if len(modes):
        values -= ((modes @ values) / values.size) @ modes
    return values


@dataclass
class TwoSourceFit:
    """Result of :func:`fit_two_source`; pixel arrays run over the pixels given to it.

    Attributes
    ----------
    tips : ndarray (2, 3)
        Refined tip positions, m, in phase order.
    tip_errors : ndarray (2, 3)
        Their 1-sigma errors, m (the prior and the data combined; the pixel
        offsets count as the noise they are fitted against).
    tip_covariance : ndarray (6, 6)
        Their covariance, m^2, coordinates in the order of ``tips.ravel()``.
    nominal : ndarray (2, 3)
        The starting tips, m.
    sign : int
        +1 if the pixel phases increase with Phi, -1 if with -Phi.
    k_local : ndarray (pixel, 2)
        Each pixel's wavevector, the gradient of the fitted phase surface
        (plane included), rad/pixel; points the way the pixel phases increase.
    offsets : ndarray (pixel,)
        Offsets projected on each pixel's local wavevector, pixel, with zero
        mean and gradient and orthogonal to ``modes``.
    modes : ndarray (mode, pixel)
        Unobservable offset modes beyond the affine part, orthonormal (unit rms
        over the pixels) and orthogonal to the affine part.
    information : ndarray (6,)
        Information ratio (data over prior) of each tip mode, descending.
    tip_modes : ndarray (6, 6)
        The tip modes, columns in the order of ``information``: unit vectors
        over the coordinates of ``tips.ravel()``.
    phase_rms : float
        Rms of the pixel phases about the fitted surface, rad (the offsets
        times |K|).
    iterations : int
        Gauss-Newton iterations run, summed over the refinement's stages.
    plane_wave_departure : ndarray (pixel,)
        The fitted surface minus its best plane, over |K|, pixel: what a
        plane-wave reduction would have put into the offsets.
    surface : ndarray (pixel,)
        The fitted phase, sign Phi + c + a.r, rad.
    x, y : ndarray (pixel,)
        The pixels' coordinates, pixel (the arrays given to :func:`fit_two_source`, not copies of them).
    """

    tips: np.ndarray
    tip_errors: np.ndarray
    tip_covariance: np.ndarray
    nominal: np.ndarray
    sign: int
    k_local: np.ndarray
    offsets: np.ndarray
    modes: np.ndarray
    information: np.ndarray
    tip_modes: np.ndarray
    phase_rms: float
    iterations: int
    plane_wave_departure: np.ndarray
    surface: np.ndarray
    x: np.ndarray
    y: np.ndarray

    def offsets_of(self, theta) -> np.ndarray:
        """Offsets (pixel) of other pixel phases (rad, same pixels) against this fit's surface and modes.

        The phases' constant is taken out (their difference from the surface
        wrapped about its circular mean: another gauge may rotate them), then
        the affine part and the modes, in offset space; the tips are this fit's.
        Its temporaries: a few arrays of one number a pixel.
        """
        psi = wrapped_about_mean(np.asarray(theta, float) - self.surface)
        psi /= np.hypot(*self.k_local.T)
        return _without_orthonormal(_without_affine(psi, self.x, self.y), self.modes)


def _unwrapped_start(theta, x, y, phase_of, k_plane, block, *, gradient=None, search=None):
    """The sign of the surface of the nominal tips (``phase_of(s)``: its phase and gradient at the pixels
    ``s``) that runs the way of ``k_plane``, and the constant and plane (rad, rad/pixel) that unwrap ``theta``
    against it; sums over the pixels taken ``block`` pixels at a time. ``gradient``: the surface's mean
    gradient over the pixels ``k_plane`` was fitted on, where those are not only these (a stage's disc).
    ``search``: the plane's 3-sigma error (rad/pixel, (2,)), where the plane is searched for first
    (:func:`_searched_plane`; None: not searched, as where every pixel is refined at once)."""
    n = x.size
    phase0, mean = np.empty(n), np.zeros(2)
    for s in pixel_blocks(n, block):
        phase0[s], gx, gy = phase_of(s)
        mean += gx.sum(), gy.sum()
    mean /= n
    gradient = mean if gradient is None else gradient
    sign = 1 if float(gradient @ np.asarray(k_plane, float)) > 0 else -1
    # Unwrap against the plane-wave solution: a tip 1 mm off changes the period by up to 15 %,
    # tens of radians across the detector, which the plane absorbs. k_plane is the plane-wave fit over
    # every pixel, so the nominal surface's gradient is its mean over every pixel too, even over a
    # stage's disc: away from the centre both surfaces' mean gradients differ from k_plane, by nearly
    # the same amount, and the plane is their difference.
    plane = np.asarray(k_plane, float) - sign * gradient
    constant, plane = _unwrapped_plane(theta, x, y, sign, phase0, 0.0, plane, block, search=search)
    return sign, constant, plane


def _unwrapped_plane(theta, x, y, sign, phase0, constant, plane, block, *, search=None):
    """The constant and plane (rad, rad/pixel) that unwrap ``theta`` against the surface ``sign`` ``phase0``
    (rad, at the pixels), from ``constant`` and ``plane``: searched for first if ``search`` (as
    :func:`_unwrapped_start` takes it) is given, then four affine fits of the wrapped residual, which take
    the plane to the residual's best while it is well within +-pi of it everywhere."""
    if search is not None:
        constant, plane = _searched_plane(theta, x, y, lambda p: sign * phase0[p], constant, plane, search)
    n = x.size
    for _ in range(4):
        R = stacked_r(_affine_rows(x, y, s, _wrap(theta[s] - sign * phase0[s] - plane[0] * x[s] - plane[1] * y[s]
                                                  - constant)) for s in pixel_blocks(n, block))
        coef = _affine_coefficients(R)[:, 0]
        constant, plane = constant + coef[0], plane + coef[1:]
    return constant, plane


def _searched_plane(theta, x, y, surface_at, constant, plane, error):
    """The constant and plane (rad, rad/pixel) of the peak of the periodogram of the wrapped residual
    theta - surface - constant - plane.r (rad, at the pixels; ``surface_at(p)``: the surface at the pixels of
    index ``p``), the plane searched for within ``error`` (rad/pixel, (2,): its 3-sigma error) of ``plane``.

    The grid's step puts at most ``STAGE_PLANE_STEP`` at the pixels' radius about their centroid between the
    peak and the nearest point of the grid. The sums are over up to ``STAGE_BOUND_SAMPLES`` of the pixels,
    picked at random with a fixed seed (evenly picked, a raster's pixels would make a lattice with aliases of
    its own), a block of them at a time (the grid's exponentials: a block's pixels by grid points a side)."""
    n = x.size
    picked = np.arange(n)
    if n > STAGE_BOUND_SAMPLES:
        picked = np.sort(np.random.default_rng(0).choice(n, STAGE_BOUND_SAMPLES, replace=False))
    centre = np.array([x[picked].mean(), y[picked].mean()])
    u, v = x[picked] - centre[0], y[picked] - centre[1]
    step = np.sqrt(2) * STAGE_PLANE_STEP / max(float(np.sqrt(np.max(u**2 + v**2))), 1.0)
    # within step / 2 of a point of the grid each way: at most STAGE_PLANE_STEP at the radius
    half = np.maximum(np.ceil(np.asarray(error, float) / step - 0.5), 0).astype(int)
    if np.any(half > STAGE_PLANE_POINTS):
        log.warning("the plane's 3-sigma error (%s rad/pixel) spans more than %d steps of its search each way: "
                    "searched over the %d nearest", np.array2string(np.asarray(error), precision=2),
                    STAGE_PLANE_POINTS, STAGE_PLANE_POINTS)
        half = np.minimum(half, STAGE_PLANE_POINTS)
    if not np.any(half):
        return constant, plane
    kx, ky = (step * np.arange(-h, h + 1) for h in half)
    power = np.zeros((kx.size, ky.size), complex)
    for s in pixel_blocks(picked.size, 2048):
        p = picked[s]
        z = np.exp(1j * (theta[p] - surface_at(p) - plane[0] * x[p] - plane[1] * y[p] - constant))
        power += (z[:, None] * np.exp(-1j * np.outer(u[s], kx))).T @ np.exp(-1j * np.outer(v[s], ky))
    i, j = np.unravel_index(np.argmax(np.abs(power)), power.shape)
    k = np.array([kx[i], ky[j]])
    return constant + float(np.angle(power[i, j])) - float(k @ centre), plane + k


@dataclass
class _PhasePixels:
    """The pixel phases ``theta`` at ``x``, ``y`` that :func:`fit_two_source` refines the tips from, and the
    sums over them it needs, taken ``block`` pixels at a time (no array of more than one number a pixel)."""

    theta: np.ndarray
    x: np.ndarray
    y: np.ndarray
    wavelength: float
    pixel_pitch: float
    block: int | None
    sign: int = 1

    def surface(self, tips, s):
        """Phase and gradient of the tips' surface at the pixels ``s`` (:func:`two_source_phase`)."""
        return two_source_phase(self.x[s], self.y[s], *tips, wavelength=self.wavelength, pixel_pitch=self.pixel_pitch)

    @functools.cached_property
    def centre(self):
        """The pixels' bounding-box centre, ([x], [y]), pixel: found once (each block's Jacobian is taken from it)."""
        return np.array([(self.x.max() + self.x.min()) / 2]), np.array([(self.y.max() + self.y.min()) / 2])

    def _centre_jacobian(self, tips):
        return tip_jacobian(*self.centre, *tips, wavelength=self.wavelength, pixel_pitch=self.pixel_pitch)[0]

    def jacobian_centre(self, tips) -> np.ndarray:
        """d (sign Phi) / d tips (6,) at the pixels' centre, rad per mm of tip."""
        return self._centre_jacobian(tips) * (self.sign * 1e-3)

    def jacobian(self, tips, s) -> np.ndarray:
        """d (sign Phi) / d tips (pixel, 6) at the pixels ``s``, rad per mm of tip (for conditioning), minus
        its value at the pixels' centre: the affine part, which the plane takes, is 1e6 times the rest, and
        columns that large would cost the sums' QR 6 of their 16 digits; the constant leaves the affine-free
        part as it is and moves the plane's constant by ``jacobian_centre`` . step."""
        jac = tip_jacobian(self.x[s], self.y[s], *tips, wavelength=self.wavelength, pixel_pitch=self.pixel_pitch)
        jac -= self._centre_jacobian(tips)
        jac *= self.sign * 1e-3
        return jac

    def sums(self, tips, constant, plane, keep=None) -> np.ndarray:
        """R (10, 10) of [1 | x | y | J | psi] at ``tips``, psi the residual phase, continuous: wrapped about
        the surface sign Phi + ``constant`` + ``plane``.r, a fraction of a radian away. The plane takes the
        affine part: J'J and J'psi of the affine-free parts are R22' R22 and R22' r2 (R22 = R[3:9, 3:9],
        r2 = R[3:9, 9]), the affine-free residual's squared norm |R[3:, 9]|^2, the plane of psi - J step
        R11^-1 (r1 - R12 step) (:func:`_affine_coefficients`). With ``keep`` = (model, psi, k_local), the
        surface (pixel,), psi and the local wavevector (pixel, 2) are written into them."""
        x, y, sign = self.x, self.y, self.sign

        def rows(s):
            phase, gx, gy = self.surface(tips, s)
            model = sign * phase + constant + plane[0] * x[s] + plane[1] * y[s]
            psi = _wrap(self.theta[s] - model)
            if keep is not None:
                keep[0][s], keep[1][s] = model, psi
                keep[2][s, 0], keep[2][s, 1] = sign * gx + plane[0], sign * gy + plane[1]
            return _affine_rows(x, y, s, self.jacobian(tips, s), psi)

        return stacked_r(rows(s) for s in pixel_blocks(x.size, self.block))


def _noise_variance(R, n):
    """The variance (rad^2) the tips are fitted against: the residual phases' beyond the affine part
    (|R[3:, 9]|^2 over the ``n`` pixels, R as :meth:`_PhasePixels.sums` makes it).

    It is mostly the pixel offsets themselves (about 1e-3 pixel, white: docs/metrology.md); 1e-6 rad keeps
    noiseless phases (tests) from a singular system."""
    return max(float(np.sum(R[3:, 9] ** 2)) / n, 1e-12)


def _refine_tips(pixels, tips, constant, plane, *, nominal, prior, max_iterations, fibers, label, where=""):
    """Gauss-Newton refinement of the tips over ``pixels`` (a :class:`_PhasePixels`: every pixel, or a stage's
    disc), from ``tips`` (2, 3), m, and the unwrapping ``constant`` (rad) and ``plane`` (rad/pixel), with the
    prior (mm^-2) about the ``nominal`` tips. Returns the tips, constant and plane, the iterations run and the
    last normal matrix (6, 6), mm^-2 (the inverse of the tips' covariance, mm^2). ``where`` names a stage's
    pixels in the error of a refinement that does not converge."""
    n = pixels.x.size
    for iterations in range(1, max_iterations + 1):
        R = pixels.sums(tips, constant, plane)
        noise2 = _noise_variance(R, n)
        normal = R[3:9, 3:9].T @ R[3:9, 3:9] / noise2 + prior * np.eye(6)
        rhs = R[3:9, 3:9].T @ R[3:9, 9] / noise2 - prior * (tips - nominal).ravel() * 1e3
        step = np.linalg.solve(normal, rhs)  # mm
        coef = _affine_coefficients(R)
        coef = coef[:, 6] - coef[:, :6] @ step  # the plane of psi - J step
        coef[0] -= pixels.jacobian_centre(tips) @ step
        tips = tips + step.reshape(2, 3) * 1e-3
        constant, plane = constant + coef[0], plane + coef[1:]
        # 10 nm: the largest non-affine response, 2.5e-3 pixel per mm of tip (docs), makes that 2.5e-8 pixel
        if np.max(np.abs(step)) * 1e-3 < 1e-8:
            return tips, constant, plane, iterations, normal
    raise GeometryError(f"{label}: the refinement of the tips of fibers {fibers[0]} and {fibers[1]} did not "
                        f"converge in {max_iterations} iterations{where} (last step {np.max(np.abs(step)):.2e} mm)")


def _stage_discs(x, y):
    """Each pixel's distance from the pixels' centroid, and the radii (pixel) of the discs about it a refinement
    may run over: every pixel first, then halving while a disc holds ``STAGE_MIN_PIXELS`` pixels."""
    distance = np.hypot(x - x.mean(), y - y.mean())
    radii = [float(distance.max())]
    while radii[-1] >= 2 and np.count_nonzero(distance <= radii[-1] / 2) >= STAGE_MIN_PIXELS:
        radii.append(radii[-1] / 2)  # (down to a pixel: pixels heaped on the centroid would halve forever)
    return distance, radii


def _sampled_jacobian(x, y, tips, pixels, index=None):
    """d Phi / d tips (sample, 6), rad/mm, at up to ``STAGE_BOUND_SAMPLES`` of the pixels ``index`` (None: every
    pixel), evenly picked (the surface is smooth), and its affine fit's coefficients (3, 6): constant, x, y
    slopes (rad/mm, rad/pixel/mm). ``pixels`` gives the bench (wavelength, pitch)."""
    n = x.size if index is None else index.size
    picked = np.linspace(0, n - 1, min(n, STAGE_BOUND_SAMPLES)).astype(int)
    index = picked if index is None else index[picked]
    jac = tip_jacobian(x[index], y[index], *tips, wavelength=pixels.wavelength, pixel_pitch=pixels.pixel_pitch)
    jac *= 1e-3  # rad/mm
    affine = affine_basis(x[index], y[index]).T
    coef = np.linalg.lstsq(affine, jac, rcond=None)[0]
    jac -= affine @ coef
    return jac, coef


def _stage_bound(x, y, tips, covariance, pixels, index=None):
    """3-sigma phase (rad), beyond the affine part over the pixels ``index`` (None: every pixel), that tips known
    to ``covariance`` (6, 6), mm^2, put on the worst of them; from up to ``STAGE_BOUND_SAMPLES`` of them,
    evenly picked (the surface is smooth). ``pixels`` gives the bench (wavelength, pitch).

    Returns the bound and the affine coefficients of d Phi / d tips over those pixels (3, 6), which
    :func:`_plane_error` takes for the disc chosen."""
    jac, coef = _sampled_jacobian(x, y, tips, pixels, index)
    return 3 * float(np.sqrt(np.max(np.einsum("pi,ij,pj->p", jac, covariance, jac)))), coef


def _plane_error(x, y, tips, covariance, pixels, coefficients, previous=None):
    """3-sigma error (rad/pixel, (2,)), from tips known to ``covariance`` (6, 6), mm^2, of the plane a stage over
    a disc of pixels starts from, against the best plane of its residual: the plane fitted over the
    pixels ``previous`` (the last stage's), or, for the first stage (None), the plane-wave solution's less the
    nominal surface's mean gradient over every pixel (:func:`_unwrapped_start`).

    Linear in the tips' error: the slopes of d Phi / d tips over the disc (``coefficients``, the affine
    coefficients :func:`_stage_bound` returned for it) against those over ``previous``,
    or their mean gradient over every pixel (central differences half a pixel each way), from the bound's
    evenly picked samples. For the first stage, plus how far the tips' surface's mean gradient over every
    pixel is from its best plane: a plane-wave solution may be either, or between."""
    bench = {"wavelength": pixels.wavelength, "pixel_pitch": pixels.pixel_pitch}
    if previous is not None:
        _, reference = _sampled_jacobian(x, y, tips, pixels, previous)
        ambiguity = np.zeros(2)
    else:
        picked = np.linspace(0, x.size - 1, min(x.size, STAGE_BOUND_SAMPLES)).astype(int)
        xs, ys = x[picked], y[picked]
        reference = np.zeros((3, 6))
        for row, (dx, dy) in ((1, (0.5, 0.0)), (2, (0.0, 0.5))):
            reference[row] = (tip_jacobian(xs + dx, ys + dy, *tips, **bench)
                              - tip_jacobian(xs - dx, ys - dy, *tips, **bench)).mean(axis=0) * 1e-3
        phase, gx, gy = two_source_phase(xs, ys, *tips, **bench)
        best = np.linalg.lstsq(affine_basis(xs, ys).T, phase, rcond=None)[0][1:]
        ambiguity = np.abs(best - [gx.mean(), gy.mean()])
    gain = reference[1:] - coefficients[1:]  # (2, 6): rad/pixel per mm of tip
    return 3 * np.sqrt(np.einsum("ai,ij,aj->a", gain, covariance, gain)) + ambiguity


def _refine_in_stages(pixels, k_plane, *, nominal, prior, max_iterations, fibers, label):
    """The tips refined over discs of ``pixels`` about their centroid, from the centre out (:func:`fit_two_source`):
    each stage the largest disc on which the tips' uncertainty (the prior's, then the last stage's posterior)
    puts at most ``STAGE_PHASE_LIMIT`` at 3 sigma beyond the affine part, or the next disc out; each from the
    last stage's tips, and from the constant and plane the disc's periodogram peaks at within the plane's
    3-sigma error (:func:`_plane_error`, :func:`_searched_plane`), the first stage's then fitted to the disc's
    wrapped residual (:func:`_unwrapped_plane`) as where every pixel is refined at once.
    Sets ``pixels.sign``; returns the tips, constant, plane and the iterations of every stage."""
    x, y, n = pixels.x, pixels.y, pixels.x.size
    gradient = np.zeros(2)  # the nominal surface's mean gradient over every pixel, the pixels of k_plane
    for s in pixel_blocks(n, pixels.block):
        gradient += [g.sum() for g in pixels.surface(nominal, s)[1:]]
    gradient /= n
    distance, radii = _stage_discs(x, y)
    covariance = np.eye(6) / prior  # mm^2
    tips, outer, stages, iterations = nominal.copy(), len(radii), 0, 0
    refine = {"nominal": nominal, "prior": prior, "max_iterations": max_iterations, "fibers": fibers, "label": label}
    while outer > 0:
        bound = None  # the last disc tried's: its bound (rad) and affine coefficients (_stage_bound)
        for j in range(1 if stages == 0 else 0, outer):
            bound, coefficients = _stage_bound(x, y, tips, covariance, pixels, np.flatnonzero(distance <= radii[j]))
            if bound <= STAGE_PHASE_LIMIT:
                disc = j
                break
        else:  # no disc the bound allows: the next one out anyway, said (it may not converge)
            disc = outer - 1  # (the last disc tried, or every pixel when there was none to try)
            if bound is None:  # (too few pixels for a smaller disc than every pixel)
                bound, coefficients = _stage_bound(x, y, tips, covariance, pixels)
            log.warning("%s: no disc of %d pixels or more keeps the tips' uncertainty within %g rad at 3 sigma "
                        "(%.2f rad on the disc within %.0f pixels of the centre, refined next); the refinement may "
                        "not converge", label, STAGE_MIN_PIXELS, STAGE_PHASE_LIMIT, bound, radii[disc])
        inside = np.flatnonzero(distance <= radii[disc])
        # the plane the stage starts from, searched for within its 3-sigma error (_searched_plane): on sparse
        # pixels, whose first disc spans hundreds of pixels, it can be radians off at the disc's edge
        error = _plane_error(x, y, tips, covariance, pixels, coefficients,
                             None if stages == 0 else np.flatnonzero(distance <= radii[outer]))
        stage = pixels if disc == 0 else _PhasePixels(pixels.theta[inside], x[inside], y[inside], pixels.wavelength,
                                                      pixels.pixel_pitch, pixels.block, sign=pixels.sign)
        del inside
        if stages == 0:
            pixels.sign, constant, plane = _unwrapped_start(
                stage.theta, stage.x, stage.y, lambda s: stage.surface(nominal, s), k_plane, pixels.block,
                gradient=gradient, search=error)
            stage.sign = pixels.sign
        else:  # the search only: a Gauss-Newton step fits the plane with the tips, from a plane this close
            constant, plane = _searched_plane(stage.theta, stage.x, stage.y,
                                              lambda p: stage.sign * stage.surface(tips, p)[0], constant, plane, error)
        where = f" over the {stage.x.size} pixels within {radii[disc]:.0f} pixels of the centre (stage {stages + 1})"
        tips, constant, plane, done, normal = _refine_tips(stage, tips, constant, plane, where=where, **refine)
        covariance = np.linalg.inv(normal)
        stages, iterations, outer = stages + 1, iterations + done, disc
        log.info("%s: tips refined over the %d pixels within %.0f pixels of the centre (stage %d, %d "
                 "iteration(s)); its start plane's 3-sigma error %.2f rad at its edge (searched for where that "
                 "exceeds half a step of the search's grid)", label,
                 stage.x.size, radii[disc], stages, done, float(np.hypot(*error)) * radii[disc])
    return tips, constant, plane, iterations


def fit_two_source(theta, x, y, nominal_a, nominal_b, *, wavelength, pixel_pitch, k_plane,
                   tip_sigma: float = 1e-3, max_iterations: int = 30, fibers=("a", "b"),
                   label: str = "baseline", block: int | None = None) -> TwoSourceFit:
    """Refine a baseline's two fiber tips from its pixel phases and measure the offsets against their surface.

    The tips are refined over every pixel at once where the prior leaves their surface within
    ``STAGE_PHASE_LIMIT`` of the truth beyond the affine part (3 sigma); otherwise in stages over discs about
    the pixels' centroid, each the largest the previous stage's posterior allows, until every pixel, each from
    the plane its wrapped residual's periodogram peaks at within the plane's 3-sigma error.
    ``max_iterations`` bounds each stage; ``TwoSourceFit.iterations`` counts them all.

    Parameters
    ----------
    theta : ndarray (pixel,)
        Pixel phases of the fringe solution, rad (any constant, wrapped).
    x, y : ndarray (pixel,)
        Nominal pixel centres, pixel.
    nominal_a, nominal_b : (float, float, float)
        Nominal tip positions, m, detector frame (dataset format), phase order.
    wavelength, pixel_pitch : float
        m.
    k_plane : (float, float)
        The plane-wave wavevector of the same phases, rad/pixel (its sign the
        way ``theta`` increases): the start of the unwrapping.
    tip_sigma : float
        1-sigma error of each nominal tip coordinate, m: the prior.
    max_iterations : int
        Of the Gauss-Newton refinement, at least 1.
    fibers : (str, str)
        The two fibers' names, for messages.
    label : str
        Names the baseline in logs and errors.
    block : int
        Pixels a block (None: :data:`dice_core.pixel_blocks.PIXEL_BLOCK`): every sum over the pixels (the
        Gauss-Newton steps' J'J and J'psi, the affine fits, the modes' fields) is taken a block of
        pixels at a time, so that the Jacobian (6 numbers a pixel) is never formed over every pixel;
        the result is the same for any block, to rounding.

    Returns
    -------
    TwoSourceFit

    Raises
    ------
    GeometryError
        Pixel phases that no refinement of the tips fits (their rms about the
        surface above 0.5 rad), that move a tip coordinate by more than
        ``MAX_TIP_SHIFT_SIGMA`` x ``tip_sigma`` from its nominal value (the
        nominal tips, the wavelength or the pitch are not the bench's), or a
        refinement that does not converge.
    ValueError
        ``max_iterations`` under 1.
    """
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be >= 1, got {max_iterations}")
    theta, x, y = (np.asarray(v, float) for v in (theta, x, y))
    nominal = np.array([nominal_a, nominal_b], float)
    n = x.size
    pixels = _PhasePixels(theta, x, y, wavelength, pixel_pitch, block)
    prior = (1e-3 / tip_sigma) ** 2  # in mm^-2
    refine = {"nominal": nominal, "prior": prior, "max_iterations": max_iterations, "fibers": fibers, "label": label}
    # every pixel at once where the prior leaves the surface within +-STAGE_PHASE_LIMIT of the truth, as on
    # every 80x84 detector; else stages over discs from the centre out
    if _stage_bound(x, y, nominal, np.eye(6) / prior, pixels)[0] <= STAGE_PHASE_LIMIT:
        pixels.sign, constant, plane = _unwrapped_start(theta, x, y, lambda s: pixels.surface(nominal, s), k_plane,
                                                        block)
        tips, constant, plane, iterations, _ = _refine_tips(pixels, nominal.copy(), constant, plane, **refine)
    else:
        tips, constant, plane, iterations = _refine_in_stages(pixels, k_plane, **refine)
    model, psi, k_local = np.empty(n), np.empty(n), np.empty((n, 2))
    R = pixels.sums(tips, constant, plane, keep=(model, psi, k_local))
    phase_rms = float(np.sqrt(np.sum(R[3:, 9] ** 2) / n))
    if phase_rms > 0.5:
        raise GeometryError(f"{label}: the pixel phases depart from the two-source surface of the refined tips "
                            f"of fibers {fibers[0]} and {fibers[1]} by {phase_rms:.2f} rad rms; are the fiber tips, "
                            "wavelength and pixel pitch right?")
    shift = tips - nominal
    worst = np.unravel_index(np.argmax(np.abs(shift)), shift.shape)
    if abs(shift[worst]) > MAX_TIP_SHIFT_SIGMA * tip_sigma:
        raise GeometryError(f"{label}: the pixel phases move the tip of fiber {fibers[worst[0]]} by "
                            f"{shift[worst] * 1e3:+.3f} mm along {'xyz'[worst[1]]} from its nominal position, more "
                            f"than {MAX_TIP_SHIFT_SIGMA:g} x its {tip_sigma * 1e3:g} mm error; are the fiber tips, "
                            "wavelength and pixel pitch right?")
    k_norm = np.hypot(*k_local.T)

    data = R[3:9, 3:9].T @ R[3:9, 3:9] / _noise_variance(R, n)  # mm^-2
    covariance = np.linalg.inv(data + prior * np.eye(6)) * 1e-6  # m^2
    values, vectors = np.linalg.eigh(data / prior)
    order = np.argsort(values)[::-1]
    values, vectors = values[order], vectors[:, order]
    absorbed = values > MODE_INFORMATION_THRESHOLD
    modes = _absorbed_modes(lambda s: pixels.jacobian(tips, s), _affine_coefficients(R)[:, :6],
                            vectors[:, absorbed], x, y, k_norm, block)
    offsets = psi
    offsets /= k_norm
    offsets = _without_orthonormal(_without_affine(offsets, x, y, block=block), modes)
    del psi
    departure = _without_affine(model, x, y, block=block)
    departure /= k_norm
    log.info("%s: tips of fibers %s and %s refined in %d iteration(s), moved by %s mm; phases about the surface "
             "%.3e rad rms; %d offset mode(s) beyond the affine part absorbed (information ratios %s)", label,
             *fibers, iterations, np.array2string(shift * 1e3, precision=3), phase_rms, len(modes),
             np.array2string(values, precision=2))
    return TwoSourceFit(tips=tips, tip_errors=np.sqrt(np.diag(covariance)).reshape(2, 3), tip_covariance=covariance,
                        nominal=nominal, sign=pixels.sign, k_local=k_local, offsets=offsets, modes=modes,
                        information=values, tip_modes=vectors, phase_rms=phase_rms, iterations=iterations,
                        plane_wave_departure=departure, surface=model, x=x, y=y)


def _absorbed_modes(jacobian_of, affine_coef, vectors, x, y, k_norm, block):
    """The unobservable offset modes (:func:`fit_two_source`): the affine-free Jacobian (``jacobian_of(s)`` of
    the pixels ``s`` minus its affine fit, of coefficients ``affine_coef`` (3, 6)) along the absorbed tip modes
    ``vectors`` (6, mode), over |K| (``k_norm``), made orthonormal and orthogonal to the affine part
    (:func:`orthonormal_modes`): formed a block of pixels at a time, one field a mode over the pixels."""
    n = x.size
    fields, norm2 = np.empty((vectors.shape[1], n)), np.zeros(vectors.shape[1])
    if not vectors.shape[1]:
        return fields
    for s in pixel_blocks(n, block):
        jac = jacobian_of(s)
        jac -= _affine_rows(x, y, s) @ affine_coef
        block_fields = (jac @ vectors).T
        block_fields /= k_norm[s]
        fields[:, s] = block_fields
        norm2 += np.sum(block_fields**2, axis=1)
    # over |K| the fields are no longer exactly affine-free: their affine fit taken out, as orthonormal_modes does
    coef = _affine_coefficients(stacked_r(_affine_rows(x, y, s, fields[:, s].T) for s in pixel_blocks(n, block)))
    for s in pixel_blocks(n, block):
        fields[:, s] -= (_affine_rows(x, y, s) @ coef).T
    return _svd_modes(fields, np.sqrt(norm2.max()))
