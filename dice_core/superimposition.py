"""Superimpositions of star configurations: Procrustes, projective and pose, and what the data identify of a pose.

Paper: section "Differential astrometry dispersion metrics" and appendix D
(tip-tilt). Units: pixel; rad for angles and star directions.

Configurations are arrays (position, star, 2) of (x, y) centroids. A
superimposition fits one shape of the star pattern and a transform per
position, and leaves residuals:

- :func:`procrustes`: generalised Procrustes superimposition with 5
  parameters per position (translation x and y, scale x and y, rotation):
  each position is modelled as X_p = S_p R_p M + t_p, with S_p = diag(sx, sy)
  along the detector axes (tip-tilt of the stage changes the plate scale per
  axis), R_p a rotation (roll), M the mean configuration; M and the
  transforms are fitted together (Levenberg-Marquardt on the Schur complement
  of the transforms), M's gauge fixed by zero mean translation, rotation and
  isotropic scale. Residuals are in detector
  pixels.
- :func:`projective`: a homography per position (8 parameters), which takes
  up tip-tilt's non-homogeneous scale without a 3-D model.
- :func:`pose`: the detector's 3-D pose per position (6 parameters), the
  stars' directions shared, through the exact projection
  (:func:`pose_project`); :func:`pose_identifiability` says what the data
  constrain of it.

:func:`superimpose` fits one by name (:data:`SUPERIMPOSITIONS`) and
:func:`tangent_space` is what a fitted one can absorb. How much of a random
error that is, the accuracies and their tables, are
:mod:`dice_core.accuracies`'.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from dice_core.parallel import one_blas_thread

__all__ = [
    "AstrometryError",
    "check_configurations",
    "ProcrustesResult",
    "procrustes",
    "tangent_space",
    "SUPERIMPOSITIONS",
    "superimpose",
    "configured_superimpositions",
    "ProjectiveResult",
    "projective",
    "PoseGeometry",
    "pose_project",
    "POSE_CONSTRAINTS",
    "POSE_PARAMETERS",
    "PoseResult",
    "pose",
    "PoseUnidentifiable",
    "PoseIdentifiability",
    "pose_identifiability",
    "tip_tilt_signature",
    "TipTiltRemoval",
    "tip_tilt_removal",
]


log = logging.getLogger(__name__)


class AstrometryError(ValueError):
    """Centroids that cannot give an accuracy (too few stars or positions...)."""


def check_configurations(configurations, *, min_positions=2) -> np.ndarray:
    """The configurations as a float array (position, star, 2), refused (:class:`AstrometryError`) with fewer than
    3 stars or ``min_positions`` positions, or a NaN centroid."""
    configurations = np.asarray(configurations, dtype=float)
    if configurations.ndim != 3 or configurations.shape[2] != 2:
        raise AstrometryError(f"configurations must be (position, star, 2), got shape {configurations.shape}")
    if configurations.shape[1] < 3:
        raise AstrometryError(f"{configurations.shape[1]} star(s): at least 3 are needed (5 parameters are fitted "
                              "to 2 coordinates per star)")
    if configurations.shape[0] < min_positions:
        raise AstrometryError(f"{configurations.shape[0]} position(s): at least {min_positions} are needed")
    if not np.all(np.isfinite(configurations)):
        raise AstrometryError("configurations hold NaN (an unmeasured star): select positions where all are measured")
    return configurations


def _rotation(theta):
    cos, sin = np.cos(theta), np.sin(theta)
    return np.array([[cos, -sin], [sin, cos]])


def _transform(params, mean):
    """S R M + t for params (tx, ty, log sx, log sy, theta); mean (star, 2)."""
    tx, ty, lsx, lsy, theta = params
    return (mean @ _rotation(theta).T) * np.exp([lsx, lsy]) + [tx, ty]


@dataclass
class ProcrustesResult:
    """Result of :func:`procrustes`.

    Attributes
    ----------
    mean : ndarray (star, 2)
        Mean configuration, pixel.
    params : ndarray (position, 5)
        tx, ty (pixel), log sx, log sy (1), rotation (rad) of each position.
    residuals : ndarray (position, star, 2)
        Configuration minus its fitted transform of the mean, pixel.
    """

    mean: np.ndarray
    params: np.ndarray
    residuals: np.ndarray

    @property
    def rms(self) -> float:
        """rms of the residuals over positions, stars and both axes, pixel."""
        return float(np.sqrt(np.mean(self.residuals**2)))


def _rotations(theta):
    """Rotation matrices (position, 2, 2) and their derivatives d/dtheta, for angles ``theta`` (position,), rad."""
    cos, sin = np.cos(theta), np.sin(theta)
    rotation = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
    derivative = np.stack([np.stack([-sin, -cos], -1), np.stack([cos, -sin], -1)], -2)
    return rotation, derivative


def _model(mean, params):
    """Configurations (position, star, 2) of the transforms ``params`` (position, 5) of ``mean`` (star, 2)."""
    rotation, _ = _rotations(params[:, 4])
    return np.exp(params[:, None, 2:4]) * np.einsum("pij,sj->psi", rotation, mean) + params[:, None, :2]


def _jacobian(mean, params) -> np.ndarray:
    """d(model coordinates) / d(mean configuration, every position's 5 parameters): (2 S N, 2 S + 5 N)."""
    n_pos, n_star = params.shape[0], mean.shape[0]
    jac = np.zeros((n_pos, n_star, 2, 2 * n_star + 5 * n_pos))
    for p, (_, _, lsx, lsy, theta) in enumerate(params):
        scale, rotation = np.exp([lsx, lsy]), _rotation(theta)
        d_rotation = np.array([[-np.sin(theta), -np.cos(theta)], [np.cos(theta), -np.sin(theta)]])
        rotated = mean @ rotation.T
        for s in range(n_star):
            jac[p, s, :, 2 * s:2 * s + 2] = scale[:, None] * rotation
        k = 2 * n_star + 5 * p
        jac[p, :, 0, k], jac[p, :, 1, k + 1] = 1.0, 1.0
        jac[p, :, 0, k + 2] = scale[0] * rotated[:, 0]
        jac[p, :, 1, k + 3] = scale[1] * rotated[:, 1]
        jac[p, :, :, k + 4] = (mean @ d_rotation.T) * scale
    return jac.reshape(n_pos * n_star * 2, -1)


def _normal_equations(c, mean, params):
    """Residuals and the Gauss-Newton blocks of the Procrustes model at (mean, params).

    Returns r (position, star, 2) = model - c; per position the 5x5 blocks
    B_p = J_qp'J_qp and g_qp = J_qp'r_p of its transform; the mean shape's
    block A (2, 2), the same for every star, and g_m (star, 2); and the
    couplings C (position, 2 star, 5) between the mean shape and each
    transform.
    """
    n_pos, n_star = c.shape[:2]
    rotation, d_rotation = _rotations(params[:, 4])  # (P, 2, 2)
    scale = np.exp(params[:, 2:4])  # (P, 2)
    rotated = np.einsum("pij,sj->psi", rotation, mean)  # R_p m_s
    r = scale[:, None, :] * rotated + params[:, None, :2] - c
    jq = np.zeros((n_pos, n_star, 2, 5))  # d model / d (tx, ty, log sx, log sy, theta)
    jq[:, :, 0, 0] = jq[:, :, 1, 1] = 1.0
    jq[:, :, 0, 2] = scale[:, None, 0] * rotated[..., 0]
    jq[:, :, 1, 3] = scale[:, None, 1] * rotated[..., 1]
    jq[:, :, :, 4] = scale[:, None, :] * np.einsum("pij,sj->psi", d_rotation, mean)
    jm = scale[:, :, None] * rotation  # d model / d m_s = S_p R_p, the same for every star
    B = np.einsum("psik,psil->pkl", jq, jq)
    g_q = np.einsum("psik,psi->pk", jq, r)
    A = np.einsum("pik,pil->kl", jm, jm)
    g_m = np.einsum("pik,psi->sk", jm, r)
    C = np.einsum("pik,psil->pskl", jm, jq).reshape(n_pos, 2 * n_star, 5)
    return r, B, g_q, A, g_m, C


def _fix_procrustes_gauge(mean, params):
    """The same model with zero mean rotation, isotropic log-scale and translation of the transforms.

    The mean shape M' = l R(phi) M + tau and transforms theta - phi,
    log s - log l, t - (S_p / l) R(theta_p - phi) tau give every position the
    same model: the gauge, fixed exactly.
    """
    phi = params[:, 4].mean()
    log_l = params[:, 2:4].mean()
    params = params.copy()
    params[:, 4] -= phi
    params[:, 2:4] -= log_l
    rotation, _ = _rotations(params[:, 4])
    maps = np.exp(params[:, 2:4])[:, :, None] * rotation  # (S_p / l) R(theta_p - phi)
    tau = np.linalg.solve(maps.mean(axis=0), params[:, :2].mean(axis=0))
    params[:, :2] -= maps @ tau
    mean = np.exp(log_l) * mean @ _rotation(phi).T + tau
    return mean, params


def procrustes(configurations, *, max_iterations: int = 200) -> ProcrustesResult:
    """Generalised Procrustes superimposition with translation, two scales and a rotation per position.

    All transforms and the mean configuration are fitted together by
    Levenberg-Marquardt, the way bundle adjustments are solved: each
    iteration eliminates every position's 5 parameters from the normal
    equations (a 5x5 block each) and solves the mean configuration's
    2S-dimensional Schur complement, so an iteration costs
    O(positions x stars) instead of a dense (2SN x (2S + 5N)) factorisation. The model is
    unchanged if the mean configuration is translated, rotated or scaled
    isotropically and every transform compensates: that gauge (the Schur
    complement's 4-dimensional null space) is fixed after each step, exactly,
    by zero mean translation, rotation and isotropic log-scale of the
    transforms, so that the mean configuration lies where the data are.

    A stretch of the mean configuration along x against y, with every
    transform's scales compensating, changes the model only through the
    spread of the rolls: with few positions (a few group means) the data
    barely constrain it, the cost keeps falling slowly along it, and the fit
    ends where MINPACK's Levenberg-Marquardt tolerances stop it (after
    ``max_iterations`` of the fast solver, logged), as it always did; the
    stretch it stops at, and the residual there (0.2-0.8% in rms on 3 group
    means), depend on where that is.

    Parameters
    ----------
    configurations : ndarray (position, star, 2)
        (x, y) of every star at every position, pixel.
    max_iterations : int
        Of the fast solver, before the dense fit takes over.

    Raises
    ------
    AstrometryError
        Fewer than 3 stars or 2 positions, NaN centroids.
    """
    c = check_configurations(configurations)
    n_pos, n_star = c.shape[:2]
    centres = c.mean(axis=1)
    mean = (c - centres[:, None, :]).mean(axis=0) + centres.mean(axis=0)
    params = np.column_stack([centres - centres.mean(axis=0), np.zeros((n_pos, 3))])
    cost = float(np.sum((_model(mean, params) - c) ** 2))
    damping = 1e-3
    for _ in range(max_iterations):
        r, B, g_q, A, g_m, C = _normal_equations(c, mean, params)
        # The mean configuration's step is (dM, du): M -> exp(du) (M + dM), du a log-stretch along x and
        # y. A stretch of M with every transform's scale compensating changes the model only through
        # the rolls' spread: a long, curved valley of the cost, straight in these coordinates, where a
        # step in M itself would overshoot at every iteration.
        stretch = np.zeros((2 * n_star, 2))
        stretch[0::2, 0], stretch[1::2, 1] = mean[:, 0], mean[:, 1]
        T = np.hstack([np.eye(2 * n_star), stretch])  # d M / d (dM, du) at zero
        A_z = T.T @ np.kron(np.eye(n_star), A) @ T
        while True:
            # Levenberg-Marquardt: each block's diagonal raised by the damping (Marquardt's scaling),
            # then the transforms eliminated
            B_inv = np.linalg.inv(B + damping * np.einsum("pkk->pk", B)[:, :, None] * np.eye(5))
            CB = np.einsum("pak,pkl->pal", C, B_inv)
            schur = A_z + damping * np.diag(np.diag(A_z)) - T.T @ np.einsum("pal,pbl->ab", CB, C) @ T
            rhs = T.T @ (-g_m.ravel() + np.einsum("pal,pl->a", CB, g_q))
            step = np.linalg.lstsq(schur, rhs, rcond=1e-14)[0]
            d_params = -np.einsum("pkl,pl->pk", B_inv, g_q + np.einsum("pak,a->pk", C, T @ step))
            trial_mean = np.exp(step[-2:]) * (mean + step[:-2].reshape(n_star, 2))
            trial_mean, trial_params = _fix_procrustes_gauge(trial_mean, params + d_params)
            trial_cost = float(np.sum((_model(trial_mean, trial_params) - c) ** 2))
            if trial_cost <= cost or damping > 1e12:
                break
            damping *= 10
        if trial_cost > cost:  # no step lowers the cost: at the minimum, to rounding
            break
        converged = cost - trial_cost <= 1e-14 * cost
        mean, params, cost = trial_mean, trial_params, trial_cost
        damping = max(damping / 10, 1e-12)
        if converged:
            break
    else:
        # Still creeping along the stretch valley: few positions, or rolls too alike, leave the mean
        # shape's anisotropic stretch barely constrained. MINPACK's dense Levenberg-Marquardt, from here,
        # ends the fit with its own tolerances, as this function always did before the fast solver.
        log.warning("Procrustes: the mean shape's x/y stretch is barely constrained by these %d configurations "
                    "(alike rolls); dense Levenberg-Marquardt ends the fit", n_pos)
        mean, params = _dense_procrustes(c, mean, params)
    return ProcrustesResult(mean, params, c - _model(mean, params))


def _dense_procrustes(c, mean, params):
    """The whole superimposition by MINPACK's Levenberg-Marquardt, the gauge as 4 penalty rows (slow, robust)."""
    n_pos, n_star = c.shape[:2]
    offset = 2 * n_star
    x0 = np.concatenate([mean.ravel(), params.ravel()])
    gauge = np.zeros((4, x0.size))
    gauge[0, offset + 0::5] = gauge[1, offset + 1::5] = gauge[2, offset + 4::5] = 1.0 / n_pos
    gauge[3, offset + 2::5] = gauge[3, offset + 3::5] = 0.5 / n_pos

    def unpack(x):
        return x[:offset].reshape(n_star, 2), x[offset:].reshape(n_pos, 5)

    def residual(x):
        return np.concatenate([(_model(*unpack(x)) - c).ravel(), gauge @ x])

    def jacobian(x):
        return np.vstack([_jacobian(*unpack(x)), gauge])

    from scipy.optimize import least_squares

    fit = least_squares(residual, x0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        max_nfev=200 * x0.size)
    return unpack(fit.x)


def _tangent_basis(mean, params) -> np.ndarray:
    """Orthonormal basis (observation, k) of what the superimposition can absorb at (mean, params).

    The columns of the model's Jacobian with respect to the mean configuration
    and every position's 5 parameters; the residuals of small errors e are
    e - Q Q'e (the model is linear to first order in errors of 1e-4 pixel).
    """
    u, singular, _ = np.linalg.svd(_jacobian(mean, params), full_matrices=False)
    return u[:, singular > singular[0] * 1e-10]  # the gauge freedoms are null directions


def tangent_space(result) -> np.ndarray:
    """Orthonormal basis (observation, k) of what a superimposition's result can absorb: its tangent space at the
    solution, the observations its residuals' coordinates (position, star, axis) in order."""
    if isinstance(result, ProcrustesResult):
        return _tangent_basis(result.mean, result.params)
    if isinstance(result, PoseResult):  # the fit moves only within its constraints
        from scipy.linalg import null_space

        n_pos, n_star = result.residuals.shape[:2]
        return _column_basis(result.jacobian() @ null_space(_pose_constraints(n_star, n_pos)[0]))
    return _column_basis(result.jacobian())



#: The superimpositions :func:`superimpose` fits (and :func:`dice_core.accuracies.accuracy` offers): Procrustes
#: (5 parameters per position), projective (a homography, 8) and pose (the detector's 3-D pose, 6, with the star
#: directions shared).
SUPERIMPOSITIONS = ("procrustes", "projective", "pose")


def configured_superimpositions(value) -> list:
    """The superimpositions a configuration asks for, Procrustes first and always (its rows and residuals are
    the products contract's), then the others in their configured order without repeats.

    ``value`` is one name of :data:`SUPERIMPOSITIONS` or a list of them.
    """
    names = [value] if isinstance(value, str) else list(value)
    unknown = [name for name in names if name not in SUPERIMPOSITIONS]
    if unknown:
        raise AstrometryError(f"unknown superimposition {unknown[0]!r}: one of {', '.join(SUPERIMPOSITIONS)}")
    return ["procrustes", *(name for name in dict.fromkeys(names) if name != "procrustes")]


def superimpose(configurations, model: str = "procrustes", *, geometry=None):
    """Fit the superimposition ``model`` (:data:`SUPERIMPOSITIONS`); ``geometry`` (:class:`PoseGeometry`) for pose.

    Raises
    ------
    AstrometryError
        An unknown model, or what the model's fit raises.
    """
    if model == "procrustes":
        return procrustes(configurations)
    if model == "projective":
        return projective(configurations)
    if model == "pose":
        return pose(configurations, geometry=geometry or PoseGeometry())
    raise AstrometryError(f"unknown superimposition {model!r}: one of {', '.join(SUPERIMPOSITIONS)}")



# --------------------------------------------------------------------------- models beyond Procrustes

def _column_basis(jacobian) -> np.ndarray:
    """Orthonormal basis (observation, k) of the column space of ``jacobian`` (observation, parameter).

    Columns are normalised first, so that parameters of very different units
    (pixel, rad, a star's direction) weigh alike; directions with a singular
    value below 1e-10 of the largest are the model's gauge freedoms (null).
    """
    norms = np.linalg.norm(jacobian, axis=0)
    u, singular, _ = np.linalg.svd(jacobian / np.where(norms > 0, norms, 1.0), full_matrices=False)
    return u[:, singular > singular[0] * 1e-10]


# ----- projective superimposition: a homography per position

@dataclass
class ProjectiveResult:
    """Result of :func:`projective`.

    Attributes
    ----------
    mean : ndarray (star, 2)
        Mean configuration, pixel; 4 reference stars (``reference``) fix the
        projective gauge at their Procrustes mean positions.
    homographies : ndarray (position, 3, 3)
        H_p, with H_p[2, 2] = 1, mapping the mean configuration's normalised
        coordinates ``(mean - centre) / scale`` to detector pixels.
    centre, scale : ndarray (2,), float
        The normalisation of the mean configuration (pixel).
    reference : ndarray (4,)
        The stars held fixed.
    residuals : ndarray (position, star, 2)
        Configuration minus the model, pixel.
    """

    mean: np.ndarray
    homographies: np.ndarray
    centre: np.ndarray
    scale: float
    reference: np.ndarray
    residuals: np.ndarray

    @property
    def rms(self) -> float:
        """rms of the residuals over positions, stars and both axes, pixel."""
        return float(np.sqrt(np.mean(self.residuals**2)))

    def jacobian(self) -> np.ndarray:
        """d(model coordinates) / d(free mean coordinates, every position's 8 entries of H)."""
        free = np.setdiff1d(np.arange(self.mean.shape[0]), self.reference)
        h = self.homographies.reshape(-1, 9)[:, :8]
        return _homography_jacobian((self.mean - self.centre) / self.scale, h, free)[1]


def _homography_apply(points, h):
    """Pixels (position, star, 2) of normalised points (star, 2) through homographies h (position, 8)."""
    x, y = points[:, 0], points[:, 1]
    w = h[:, 6, None] * x + h[:, 7, None] * y + 1.0
    u = (h[:, 0, None] * x + h[:, 1, None] * y + h[:, 2, None]) / w
    v = (h[:, 3, None] * x + h[:, 4, None] * y + h[:, 5, None]) / w
    return np.stack([u, v], axis=-1), w


def _homography_jacobian(points, h, free):
    """Model (position, star, 2) and its Jacobian (2 S N, 2 len(free) + 8 N) in (free stars' points, h)."""
    n_pos, n_star = h.shape[0], points.shape[0]
    model, w = _homography_apply(points, h)
    u, v = model[..., 0], model[..., 1]
    x, y = points[None, :, 0], points[None, :, 1]
    jac = np.zeros((n_pos, n_star, 2, 2 * len(free) + 8 * n_pos))
    for k, s in enumerate(free):
        jac[:, s, 0, 2 * k] = (h[:, 0] - h[:, 6] * u[:, s]) / w[:, s]
        jac[:, s, 0, 2 * k + 1] = (h[:, 1] - h[:, 7] * u[:, s]) / w[:, s]
        jac[:, s, 1, 2 * k] = (h[:, 3] - h[:, 6] * v[:, s]) / w[:, s]
        jac[:, s, 1, 2 * k + 1] = (h[:, 4] - h[:, 7] * v[:, s]) / w[:, s]
    one = np.ones_like(u)
    for p in range(n_pos):
        k = 2 * len(free) + 8 * p
        jac[p, :, 0, k:k + 3] = np.stack([x[0], y[0], one[p]], -1) / w[p, :, None]
        jac[p, :, 1, k + 3:k + 6] = np.stack([x[0], y[0], one[p]], -1) / w[p, :, None]
        jac[p, :, 0, k + 6] = -x[0] * u[p] / w[p]
        jac[p, :, 0, k + 7] = -y[0] * u[p] / w[p]
        jac[p, :, 1, k + 6] = -x[0] * v[p] / w[p]
        jac[p, :, 1, k + 7] = -y[0] * v[p] / w[p]
    return model, jac.reshape(n_pos * n_star * 2, -1)


def _projective_reference(points) -> np.ndarray:
    """The 4 stars whose smallest triangle is the largest: a well-conditioned projective basis."""
    from itertools import combinations

    def area(a, b, c):
        return abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])) / 2

    best = max(combinations(range(len(points)), 4),
               key=lambda q: min(area(*points[list(t)]) for t in combinations(q, 3)))
    return np.array(best)


def _dlt(points, targets):
    """Least-squares homography (8,) with H[2, 2] = 1 mapping points (star, 2) to targets (star, 2)."""
    x, y = points[:, 0], points[:, 1]
    u, v = targets[:, 0], targets[:, 1]
    zero, one = np.zeros_like(x), np.ones_like(x)
    rows = np.concatenate([np.column_stack([x, y, one, zero, zero, zero, -x * u, -y * u]),
                           np.column_stack([zero, zero, zero, x, y, one, -x * v, -y * v])])
    return np.linalg.lstsq(rows, np.concatenate([u, v]), rcond=None)[0]


def projective(configurations) -> ProjectiveResult:
    """Generalised projective superimposition: a homography (8 parameters) per position.

    Each position is modelled as X_p = H_p(M): the mean configuration M
    mapped by a plane-to-plane projective transform, which holds, besides
    Procrustes's translation, scales and rotation, a shear and the two
    projective terms: a tilted detector seeing star directions through a
    pinhole maps their tangent plane to the detector by exactly such a
    homography, so H_p absorbs tip-tilt's non-homogeneous scale (the paper's
    appendix D) without a 3-D model. The model is unchanged if M is mapped
    by any homography G and every H_p by H_p G^-1: that 8-dimensional
    gauge is fixed by holding 4 stars of M (the best-conditioned projective
    basis) at their Procrustes mean positions. With S stars the data keep
    2SN - 8N - 2(S - 4) degrees of freedom: 2N - 2 for 5 stars (a
    deflation factor near sqrt(5)).

    Fitted by Levenberg-Marquardt (MINPACK) with an analytic Jacobian, from
    each position's linear (DLT) homography onto the Procrustes mean.

    Parameters
    ----------
    configurations : ndarray (position, star, 2)
        (x, y) of every star at every position, pixel.

    Raises
    ------
    AstrometryError
        Fewer than 5 stars (4 fix the gauge and leave nothing to compare) or
        2 positions, NaN centroids.
    """
    c = check_configurations(configurations)
    n_pos, n_star = c.shape[:2]
    if n_star < 5:
        raise AstrometryError(f"{n_star} star(s): the projective superimposition needs at least 5 (a homography "
                              "maps any 4 points onto any 4 others)")
    start = procrustes(c)
    centre = start.mean.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((start.mean - centre) ** 2, axis=1))))
    points = (start.mean - centre) / scale
    reference = _projective_reference(points)
    free = np.setdiff1d(np.arange(n_star), reference)
    h0 = np.array([_dlt(points, c[p]) for p in range(n_pos)])
    x0 = np.concatenate([points[free].ravel(), h0.ravel()])

    def unpack(x):
        p = points.copy()
        p[free] = x[:2 * len(free)].reshape(-1, 2)
        return p, x[2 * len(free):].reshape(n_pos, 8)

    def residual(x):
        return (_homography_apply(*unpack(x))[0] - c).ravel()

    def jacobian(x):
        p, h = unpack(x)
        return _homography_jacobian(p, h, free)[1]

    from scipy.optimize import least_squares

    fit = least_squares(residual, x0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        x_scale="jac", max_nfev=100 * x0.size)
    p, h = unpack(fit.x)
    model = _homography_apply(p, h)[0]
    homographies = np.concatenate([h, np.ones((n_pos, 1))], axis=1).reshape(n_pos, 3, 3)
    return ProjectiveResult(p * scale + centre, homographies, centre, scale, reference, c - model)


# ----- pose: the detector's 3-D position and orientation per position, star directions shared

@dataclass(frozen=True)
class PoseGeometry:
    """The nominal bench that labels the pose parameters (not fitted).

    The pinhole (the mirror) is the origin; the detector's centre ``centre``
    (pixel coordinates x, y) sits at the reference pose at
    ``(distance tan(off_axis), 0, distance)``, its x, y axes along the
    frame's. These only label the parameters (a translation, the rotation
    centre, the directions' zero): the fitted model, its residuals and its
    accuracy do not depend on them, its start does.

    Attributes
    ----------
    distance : float
        Mirror to detector, pixel.
    off_axis : float
        Off-axis angle of the field along x, rad.
    centre : (float, float)
        Detector pixel (x, y) about which tip, tilt and roll turn.
    """

    distance: float = 25000.0
    off_axis: float = 0.0
    centre: tuple = (0.0, 0.0)


def _axis_rotations(angles):
    """R = Rz(roll) Ry(tilt) Rx(tip) (position, 3, 3) and dR/d(tip, tilt, roll) (3, position, 3, 3)."""
    def parts(angle):
        c, s = np.cos(angle), np.sin(angle)
        return c, s

    (c1, s1), (c2, s2), (c3, s3) = parts(angles[:, 0]), parts(angles[:, 1]), parts(angles[:, 2])
    n = len(angles)
    rx, ry, rz = (np.zeros((n, 3, 3)) for _ in range(3))
    drx, dry, drz = (np.zeros((n, 3, 3)) for _ in range(3))
    rx[:, 0, 0] = 1
    rx[:, 1, 1], rx[:, 1, 2], rx[:, 2, 1], rx[:, 2, 2] = c1, -s1, s1, c1
    drx[:, 1, 1], drx[:, 1, 2], drx[:, 2, 1], drx[:, 2, 2] = -s1, -c1, c1, -s1
    ry[:, 1, 1] = 1
    ry[:, 0, 0], ry[:, 0, 2], ry[:, 2, 0], ry[:, 2, 2] = c2, s2, -s2, c2
    dry[:, 0, 0], dry[:, 0, 2], dry[:, 2, 0], dry[:, 2, 2] = -s2, c2, -c2, -s2
    rz[:, 2, 2] = 1
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1] = c3, -s3, s3, c3
    drz[:, 0, 0], drz[:, 0, 1], drz[:, 1, 0], drz[:, 1, 1] = -s3, -c3, c3, -s3
    rotation = rz @ ry @ rx
    return rotation, np.stack([rz @ ry @ drx, rz @ dry @ rx, drz @ ry @ rx])


def pose_project(directions, poses, geometry: PoseGeometry, *, jacobian: bool = False):
    """Pixel positions of stars seen through a pinhole by a moving, tilted detector (exact, no approximation).

    Parameters
    ----------
    directions : ndarray (star, 2)
        Each star's direction as tangents (a, b): the ray (a, b, 1) from the
        pinhole, a and b in rad to first order.
    poses : ndarray (position, 6)
        Detector translation (x, y, z) from the reference pose, pixel, then
        tip (about x), tilt (about y), roll (about z), rad: orientation
        R = Rz(roll) Ry(tilt) Rx(tip) about the detector's ``centre``.
    geometry : PoseGeometry
    jacobian : bool
        Also return d(positions)/d(directions, poses), (2 S N, 2 S + 6 N),
        derived analytically.

    Returns
    -------
    ndarray (position, star, 2)
        (x, y) on the detector, pixel.

    Notes
    -----
    In the detector's frame the pinhole is at q = -R'O (O the detector
    centre's position) and a ray's direction is e = R'd; the ray meets the
    detector plane z = 0 at q + lambda e with lambda = -q_z / e_z, so
    x = xc + q_x + lambda e_x and y = yc + q_y + lambda e_y.
    """
    n_pos, n_star = poses.shape[0], directions.shape[0]
    d = np.column_stack([directions, np.ones(n_star)])
    origin = np.array([geometry.distance * np.tan(geometry.off_axis), 0.0, geometry.distance]) + poses[:, :3]
    rotation, d_rotation = _axis_rotations(poses[:, 3:6])
    q = -np.einsum("pji,pj->pi", rotation, origin)
    e = np.einsum("pji,sj->psi", rotation, d)
    lam = -q[:, None, 2] / e[..., 2]
    xy = q[:, None, :2] + lam[..., None] * e[..., :2] + np.asarray(geometry.centre, float)
    if not jacobian:
        return xy
    # d(x, y)/dq = M and d(x, y)/de = lambda M, with M = [[1, 0, -e_x/e_z], [0, 1, -e_y/e_z]]
    m = np.zeros((n_pos, n_star, 2, 3))
    m[..., 0, 0] = m[..., 1, 1] = 1.0
    m[..., :, 2] = -e[..., :2] / e[..., 2:3]
    jac = np.zeros((n_pos, n_star, 2, 2 * n_star + 6 * n_pos))
    lm_rt = lam[..., None, None] * np.einsum("psik,pjk->psij", m, rotation)  # lambda M R' (position, star, 2, 3)
    for s in range(n_star):
        jac[:, s, :, 2 * s:2 * s + 2] = lm_rt[:, s, :, :2]
    dq = -np.einsum("apji,pj->api", d_rotation, origin)  # (angle, position, 3)
    de = np.einsum("apji,sj->apsi", d_rotation, d)  # (angle, position, star, 3)
    for p in range(n_pos):
        k = 2 * n_star + 6 * p
        jac[p, :, :, k:k + 3] = -np.einsum("sik,jk->sij", m[p], rotation[p])
        for a in range(3):
            jac[p, :, :, k + 3 + a] = (np.einsum("sik,k->si", m[p], dq[a, p])
                                       + lam[p, :, None] * np.einsum("sik,sk->si", m[p], de[a, p]))
    return xy, jac.reshape(n_pos * n_star * 2, -1)


#: The pose fit's constraints: the gauge (mean tip, tilt and roll over positions zero), and two
#: near-gauges held at the nominal bench: the detector's mean distance (mean z zero) and the
#: field's mean direction (the stars' mean tangents where the nominal bench sees their mean position).
POSE_CONSTRAINTS = ("mean tip", "mean tilt", "mean roll", "mean z", "field direction a", "field direction b")


def _pose_constraints(n_star, n_pos, field=(0.0, 0.0)):
    """Constraint rows (6, 2 S + 6 N) and their targets (6,) (:data:`POSE_CONSTRAINTS`), ``field`` the mean tangents."""
    rows = np.zeros((6, 2 * n_star + 6 * n_pos))
    for k, column in enumerate((3, 4, 5, 2)):
        rows[k, 2 * n_star + column::6] = 1.0 / n_pos
    rows[4, 0:2 * n_star:2] = rows[5, 1:2 * n_star:2] = 1.0 / n_star
    return rows, np.array([0.0, 0.0, 0.0, 0.0, field[0], field[1]])


@dataclass
class PoseResult:
    """Result of :func:`pose`.

    Attributes
    ----------
    directions : ndarray (star, 2)
        Each star's direction tangents (a, b), rad.
    poses : ndarray (position, 6)
        Translation x, y, z (pixel), tip, tilt, roll (rad) of the detector,
        under :data:`POSE_CONSTRAINTS`.
    geometry : PoseGeometry
    residuals : ndarray (position, star, 2)
        Configuration minus the model, pixel.
    field : ndarray (2,)
        The stars' mean direction tangents the fit holds (nominal bench).
    cost_evaluations : int
    """

    directions: np.ndarray
    poses: np.ndarray
    geometry: PoseGeometry
    residuals: np.ndarray
    field: np.ndarray
    cost_evaluations: int = 0

    @property
    def rms(self) -> float:
        """rms of the residuals over positions, stars and both axes, pixel."""
        return float(np.sqrt(np.mean(self.residuals**2)))

    def jacobian(self) -> np.ndarray:
        """d(model coordinates) / d(directions, poses): (2 S N, 2 S + 6 N)."""
        return pose_project(self.directions, self.poses, self.geometry, jacobian=True)[1]


def _pose_start(c, geometry: PoseGeometry):
    """Directions and poses from the Procrustes solution: roll and distance from its rotation and scales."""
    start = procrustes(c)
    xc, yc = geometry.centre
    distance = geometry.distance
    directions = np.column_stack([(start.mean[:, 0] - xc) / distance + np.tan(geometry.off_axis),
                                  (start.mean[:, 1] - yc) / distance])
    poses = np.zeros((c.shape[0], 6))
    poses[:, 2] = distance * (np.exp(start.params[:, 2:4].mean(axis=1)) - 1)  # farther: larger
    poses[:, 5] = -start.params[:, 4]  # the detector turns one way, the pattern the other
    poses[:, 5] -= poses[:, 5].mean()
    poses[:, 2] -= poses[:, 2].mean()
    # then the translation in x, y that puts each position's stars where they are, on average
    model = pose_project(directions, poses, geometry)
    poses[:, :2] = (model - c).mean(axis=1)
    return directions, poses


def pose(configurations, *, geometry: PoseGeometry = PoseGeometry(), max_evaluations: int | None = None) -> PoseResult:
    """Invert the 3-D projection: each position's detector pose and each star's direction, fitted together.

    The model (:func:`pose_project`) is the exact projection of fixed star
    directions through a pinhole (the mirror) onto the detector at pose
    (x, y, z, tip, tilt, roll): 6 N + 2 S parameters for 2 S N coordinates
    (the paper's 10 + 6 N for 10 N with 5 stars).

    Gauge: turning the whole bench about the pinhole (directions, detector
    positions and orientations by the same rotation G) leaves every
    projected position unchanged: 3 freedoms, and the only exact ones (the
    Jacobian's null space has dimension 3; tested). The fit fixes them by
    three constraint rows, mean tip = mean tilt = mean roll = 0 over
    positions, appended to the residuals: since G moves along the null space,
    the constrained minimum has the same residuals as any other and the
    constraints are met exactly (the simulator's tip and tilt walks have zero
    mean too; its roll's mean is one more turn of G). Two further
    combinations are only weakly fixed, by second-order terms
    (:func:`pose_identifiability` measures them on the data): the distance
    (mean z) against the angular scale of the star pattern, and the scale of
    the tip-tilt against the field's off-axis angle (the tip-tilt's
    first-order signature on the pattern is the product of the two).

    Solved by Levenberg-Marquardt (MINPACK) with the analytic Jacobian, the
    bundle-adjustment way, from the Procrustes solution (rolls, distance
    from its scales, translations), tip and tilt zero.

    Parameters
    ----------
    configurations : ndarray (position, star, 2)
        (x, y) of every star at every position, pixel.
    geometry : PoseGeometry
        The nominal bench labelling the parameters.

    Raises
    ------
    AstrometryError
        Fewer than 3 stars or 2 positions, NaN centroids, fewer data than
        parameters.
    """
    c = check_configurations(configurations)
    n_pos, n_star = c.shape[:2]
    if 2 * n_star * n_pos < 2 * n_star + 6 * n_pos - len(POSE_CONSTRAINTS):
        raise AstrometryError(f"{n_pos} positions of {n_star} stars: {2 * n_star * n_pos} coordinates for "
                              f"{2 * n_star + 6 * n_pos - len(POSE_CONSTRAINTS)} pose parameters")
    directions, poses = _pose_start(c, geometry)
    # the field's direction: where the nominal bench sees the centre of the stars, over all positions
    field = (c.mean(axis=(0, 1)) - geometry.centre) / geometry.distance + [np.tan(geometry.off_axis), 0.0]
    gauge, target = _pose_constraints(n_star, n_pos, field)
    # each constraint row weighs about as a pixel of the data: angles times the distance, z as it is
    weight = np.array([geometry.distance] * 3 + [1.0] + [geometry.distance] * 2)
    x0 = np.concatenate([directions.ravel(), poses.ravel()])

    def unpack(x):
        return x[:2 * n_star].reshape(n_star, 2), x[2 * n_star:].reshape(n_pos, 6)

    def residual(x):
        return np.concatenate([(pose_project(*unpack(x), geometry) - c).ravel(), weight * (gauge @ x - target)])

    def jacobian(x):
        return np.vstack([pose_project(*unpack(x), geometry, jacobian=True)[1], weight[:, None] * gauge])

    from scipy.optimize import least_squares

    fit = least_squares(residual, x0, jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                        x_scale="jac", max_nfev=max_evaluations or 200 * x0.size)
    directions, poses = unpack(fit.x)
    return PoseResult(directions, poses, geometry, c - pose_project(directions, poses, geometry), field,
                      int(fit.nfev))


# ----- what the data say about the pose: Fisher information and Cramer-Rao bounds

class PoseUnidentifiable(AstrometryError):
    """The data cannot support the pose accuracy asked for (see :class:`PoseIdentifiability`)."""


#: Parameter groups of the pose model, in the order of a position's 6 parameters.
POSE_PARAMETERS = ("x", "y", "z", "tip", "tilt", "roll")


@dataclass
class PoseIdentifiability:
    """What the centroids constrain of the pose (:func:`pose_identifiability`).

    Attributes
    ----------
    sigma : float
        Centroid error per coordinate the Fisher information assumes, pixel.
    crlb : ndarray (position, 6)
        Cramer-Rao bound (1 sigma) of each position's x, y, z (pixel), tip,
        tilt, roll (rad), the star directions fitted, with the field's mean
        direction and the distance from the data alone (the constraints of
        the gauge and mean z only): what the data support.
    crlb_nominal_field : ndarray (position, 6)
        The same with the field's mean direction held at the nominal bench
        (all of :data:`POSE_CONSTRAINTS`, as the fit does).
    crlb_known_stars : ndarray (position, 6)
        The same were every star's direction known.
    snr : dict
        For tip and tilt, sqrt(mean over positions of (fitted / ``crlb``)^2):
        the tip-tilt variation seen over positions in units of its bound
        (about 1 for noise alone, the mean being the gauge).
    inflation : dict
        For tip and tilt, rms ``crlb`` over rms ``crlb_nominal_field``: what
        separating the tip-tilt from the star geometry costs.
    weak : list of (float, dict)
        The least constrained combinations (field direction from the data):
        the bound on each, in pixel of the coordinates it moves per unit of
        normalised amplitude, and each parameter group's share of it.
    rank_deficient : int
        Combinations the data leave unconstrained (Fisher eigenvalues below
        1e-24 of the largest, field direction from the data).
    identifiable : dict
        For tip and tilt, whether a pose accuracy may be reported.
    reasons : list of str
        Why not, in words.
    tip, tilt : ndarray (position,)
        The fitted values, rad.
    """

    sigma: float
    crlb: np.ndarray
    crlb_nominal_field: np.ndarray
    crlb_known_stars: np.ndarray
    snr: dict
    inflation: dict
    weak: list
    rank_deficient: int
    identifiable: dict
    reasons: list
    tip: np.ndarray
    tilt: np.ndarray

    @property
    def all_identifiable(self) -> bool:
        """Both tip and tilt identifiable."""
        return all(self.identifiable.values())

    def tip_tilt(self):
        """(tip, tilt, tip CRLB, tilt CRLB) per position, rad: the pose accuracy the data support.

        Raises
        ------
        PoseUnidentifiable
            Where the data cannot support it, with the reasons.
        """
        if not self.all_identifiable:
            raise PoseUnidentifiable("no pose accuracy can be reported: " + "; ".join(self.reasons))
        return self.tip, self.tilt, self.crlb[:, 3], self.crlb[:, 4]

    def summary(self) -> str:
        """The report in words: identifiability, bounds, weak combinations."""
        def rms(values):
            return np.sqrt(np.mean(np.asarray(values) ** 2))

        lines = [f"pose identifiability (centroid error {self.sigma:.2e} pixel per coordinate, "
                 f"{self.crlb.shape[0]} positions):"]
        for angle in ("tip", "tilt"):
            k = POSE_PARAMETERS.index(angle)
            lines.append(f"  {angle}: rms over positions {rms(getattr(self, angle)):.2e} rad; CRLB (rms) "
                         f"{rms(self.crlb[:, k]):.2e} rad from the data alone, {rms(self.crlb_nominal_field[:, k]):.2e}"
                         f" with the nominal field direction, {rms(self.crlb_known_stars[:, k]):.2e} with the "
                         f"stars known; SNR {self.snr[angle]:.1f}: "
                         + ("identifiable" if self.identifiable[angle] else "NOT identifiable"))
        for k, name in enumerate(POSE_PARAMETERS):
            if name not in ("tip", "tilt"):
                unit = "rad" if k >= 3 else "pixel"
                lines.append(f"  {name}: CRLB (rms over positions) {rms(self.crlb[:, k]):.2e} {unit}")
        for bound, shares in self.weak:
            parts = ", ".join(f"{g} {100 * v:.0f}%" for g, v in sorted(shares.items(), key=lambda t: -t[1])
                              if v >= 0.05)
            lines.append(f"  weak combination ({bound:.1e} pixel per unit): {parts}")
        if self.reasons:
            lines.append("  no pose accuracy reported: " + "; ".join(self.reasons))
        return "\n".join(lines)


def _constrained_covariance(jacobian, constraints, sigma):
    """Covariance of the constrained least-squares estimate and its Fisher eigenpairs.

    Parameters are scaled by the Jacobian's column norms (so that pixels,
    radians and tangents weigh alike); the estimate is confined to the
    constraints' null space Z: Cov = Z (Z'FZ)^-1 Z' with F = J'J / sigma^2,
    singular values of J Z below 1e-12 of the largest left out (counted as deficient).
    Returns the covariance in the original parameters, the eigenvalues and
    eigenvectors (normalised parameters, on Z) of Z'FZ, Z and the count of
    deficient combinations.
    """
    from scipy.linalg import null_space

    norms = np.linalg.norm(jacobian, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    z = null_space(constraints / norms)
    # the SVD of J Z, not the eigenvalues of its normal matrix, so that weak combinations down to 1e-12 of
    # the strongest (not 1e-6) keep their bounds
    _, singular, vt = np.linalg.svd((jacobian / norms) @ z / sigma, full_matrices=False)
    keep = singular > singular[0] * 1e-12
    values, vectors = singular[::-1] ** 2, vt[::-1].T
    inverse = (vt[keep].T / singular[keep] ** 2) @ vt[keep]
    covariance = (z @ inverse @ z.T) / np.outer(norms, norms)
    keep = keep[::-1]
    return covariance, values, vectors, z, int(np.sum(~keep))


@one_blas_thread  # its SVDs, like accuracies.accuracy's
def pose_identifiability(result: PoseResult, *, sigma: float | None = None, snr_min: float = 3.0,
                         weak: int = 3) -> PoseIdentifiability:
    """Fisher information of the pose fit on the actual data: what 5 stars constrain, and how well.

    The Fisher information J'J / sigma^2 at the fitted solution (J the
    analytic Jacobian of :func:`pose_project`), confined to the gauge and
    the nominal distance (the first four of :data:`POSE_CONSTRAINTS`), gives
    the Cramer-Rao bound of every parameter from the data alone; holding the
    field's mean direction too (as the fit does) or every star's direction
    shows what separating the tip-tilt from the star geometry costs. A
    position's tip and tilt show on the pattern to first order only through
    their product with the field's off-axis angle (a shear and an
    anisotropic scale), and that angle is a star-geometry parameter: only
    second-order terms, which grow with the tip-tilt's spread over
    positions, separate the two.

    The tip (tilt) is declared identifiable when the Fisher information has
    full rank under those constraints and the fitted tip (tilt) varies over
    positions by at least ``snr_min`` times its bound (rms of fitted / CRLB;
    about 1 for noise alone, so a tip-tilt constant over positions, which is
    all gauge, is refused; too few positions leave bounds as large as the
    tip-tilt itself).

    Parameters
    ----------
    result : PoseResult
    sigma : float, optional
        Centroid error per coordinate, pixel; by default the residuals' rms
        scaled by the degrees of freedom, sqrt(2SN / (2SN - 6N - 2S + 6)).
    snr_min : float
        Detection threshold of the tip-tilt's variation, in CRLB.
    weak : int
        How many of the least constrained combinations to describe.

    Raises
    ------
    AstrometryError
        No degrees of freedom left to estimate sigma from.
    """
    n_pos, n_star = result.residuals.shape[:2]
    n_data = 2 * n_pos * n_star
    dof = n_data - (2 * n_star + 6 * n_pos - len(POSE_CONSTRAINTS))
    if sigma is None:
        sigma = result.rms * np.sqrt(n_data / dof) if dof > 0 else np.nan
    if not np.isfinite(sigma) or sigma <= 0:
        raise AstrometryError(f"no centroid error to weigh the Fisher information with (sigma {sigma}): "
                              f"{dof} degrees of freedom left")
    jacobian = result.jacobian()
    constraints, _ = _pose_constraints(n_star, n_pos, result.field)

    def bounds(columns, rows):
        covariance, *rest = _constrained_covariance(jacobian[:, columns], constraints[np.ix_(rows, columns)], sigma)
        return np.sqrt(np.maximum(np.diag(covariance), 0))[-6 * n_pos:].reshape(n_pos, 6), rest

    every, poses_only = np.arange(jacobian.shape[1]), np.arange(2 * n_star, jacobian.shape[1])
    crlb, (values, vectors, z, deficient) = bounds(every, [0, 1, 2, 3])
    crlb_nominal, _ = bounds(every, [0, 1, 2, 3, 4, 5])
    crlb_known, _ = bounds(poses_only, [0, 1, 2, 3])
    groups = [f"star {'ab'[k % 2]}" for k in range(2 * n_star)] + list(POSE_PARAMETERS) * n_pos
    described = []
    for k in range(min(weak, values.size)):
        shares = {}
        for group, component in zip(groups, z @ vectors[:, k]):
            shares[group] = shares.get(group, 0.0) + component**2
        described.append((float(1 / np.sqrt(values[k])) if values[k] > 0 else np.inf, shares))
    snr, inflation, identifiable, reasons = {}, {}, {}, []
    if deficient:
        reasons.append(f"{deficient} combination(s) of the pose and star parameters are unconstrained by the data "
                       f"(the field's direction against the tip-tilt)")
    for angle in ("tip", "tilt"):
        k = POSE_PARAMETERS.index(angle)
        snr[angle] = float(np.sqrt(np.mean((result.poses[:, k] / crlb[:, k]) ** 2)))
        inflation[angle] = float(np.sqrt(np.mean(crlb[:, k] ** 2) / np.mean(crlb_nominal[:, k] ** 2)))
        identifiable[angle] = not deficient and snr[angle] >= snr_min
        if snr[angle] < snr_min:
            reasons.append(f"the {angle} varies over the {n_pos} positions by {snr[angle]:.1f} times its "
                           f"Cramer-Rao bound (rms {np.sqrt(np.mean(crlb[:, k] ** 2)):.1e} rad), less than "
                           f"{snr_min:g}: the positions do not sample the {angle} well enough to separate it from "
                           f"the star geometry (its bound is x{inflation[angle]:.1f} the one with the field's "
                           f"direction known)")
    return PoseIdentifiability(float(sigma), crlb, crlb_nominal, crlb_known, snr, inflation, described, deficient,
                               identifiable, reasons, result.poses[:, 3].copy(), result.poses[:, 4].copy())


# ----- how much of Procrustes's tip-tilt excess the data allow to remove

def tip_tilt_signature(result: PoseResult, tip_tilt=None) -> np.ndarray:
    """What the tip and tilt move the stars by: the pose model's positions with them minus without (tip and
    tilt zero, everything else as fitted), pixel (position, star, 2). ``tip_tilt`` (position, 2), rad:
    those instead of the fitted ones (e.g. a simulation's true ones, their mean removed as the fit's is)."""
    poses = result.poses.copy()
    if tip_tilt is not None:
        poses[:, 3:5] = np.asarray(tip_tilt, float) - np.mean(tip_tilt, axis=0)
    flat = poses.copy()
    flat[:, 3:5] = 0.0
    return (pose_project(result.directions, poses, result.geometry)
            - pose_project(result.directions, flat, result.geometry))


@dataclass
class TipTiltRemoval:
    """What the data allow of removing Procrustes's tip-tilt excess (:func:`tip_tilt_removal`).

    Attributes
    ----------
    signal : float
        The tip-tilt signature's part that Procrustes leaves, sum of squares over the coordinates, pixel^2
        (from the fitted tip and tilt, less its expected noise part, or from a signature given).
    noise : float
        The part of it that the tip and tilt's Fisher uncertainty makes, in expectation, pixel^2.
    bound : float
        signal / (signal + noise): the share of the excess an estimate of the tip and tilt at their
        Cramer-Rao bounds can remove, the most a superimposition can remove from these data (0 without
        signal).
    snr : float
        sqrt(signal / noise).
    excess : float
        Procrustes's tip-tilt excess the signal makes, factor sqrt(signal / coordinates), pixel: what its
        corrected accuracy carries of the tip-tilt, in quadrature.
    """

    signal: float
    noise: float
    bound: float
    snr: float
    excess: float


@one_blas_thread
def tip_tilt_removal(pose_result: PoseResult, procrustes_result: ProcrustesResult, *, sigma: float,
                     factor: float = 1.0, signature=None) -> TipTiltRemoval:
    """The noise-limited share of Procrustes's tip-tilt excess that the pose's Fisher information allows.

    The tip and tilt move the stars by a signature s (:func:`tip_tilt_signature`); Procrustes absorbs its
    part in its own tangent space P and leaves S = |(I - P) s|^2. An estimate of the tip and tilt with
    covariance C (the pose's Fisher information J'J / sigma^2 under the fit's constraints, the star
    directions and the other pose parameters fitted alongside) leaves of it, in expectation,
    N = trace((I - P) J_w C_ww J_w' (I - P)), J_w the tip and tilt columns of J. The best estimate at
    that precision (a Wiener one) removes S / (S + N) of the excess: the noise-limited bound. From the
    data alone S is the fitted tip-tilt's, less N (its expected noise part); with ``signature`` (a
    simulation's: the tilted twin minus the untilted) it is that one's.

    Parameters
    ----------
    pose_result : PoseResult
    procrustes_result : ProcrustesResult
        Procrustes on the same configurations.
    sigma : float
        Centroid error per coordinate, pixel (the pose's corrected accuracy).
    factor : float
        Procrustes's global correction factor, for ``excess``.
    signature : ndarray (position, star, 2), optional
        The true tip-tilt signature, pixel.
    """
    n_pos, n_star = pose_result.residuals.shape[:2]
    basis = tangent_space(procrustes_result)

    def outside(values):
        return values - basis @ (basis.T @ values)

    jacobian = pose_result.jacobian()
    rows, _ = _pose_constraints(n_star, n_pos, pose_result.field)
    covariance = _constrained_covariance(jacobian, rows, sigma)[0]
    angles = np.array([2 * n_star + 6 * p + k for p in range(n_pos) for k in (3, 4)])
    leaving = outside(jacobian[:, angles])
    noise = float(np.sum((leaving @ covariance[np.ix_(angles, angles)]) * leaving))
    if signature is None:
        signal = max(float(np.sum(outside(tip_tilt_signature(pose_result).ravel()) ** 2)) - noise, 0.0)
    else:
        signal = float(np.sum(outside(np.asarray(signature, float).ravel()) ** 2))
    bound = signal / (signal + noise) if signal + noise > 0 else 0.0
    snr = float(np.sqrt(signal / noise)) if noise > 0 else float("inf")
    return TipTiltRemoval(signal, noise, bound, snr, float(factor * np.sqrt(signal / pose_result.residuals.size)))

