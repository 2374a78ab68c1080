"""Differential astrometry: barycentre residuals, Procrustes superimposition, accuracy with error bars.

Paper: sections "Differential astrometry dispersion metrics", "Pseudo stars
simulation results" and the experimental accuracy table. Units: pixel.

Configurations are arrays (position, star, 2) of (x, y) centroids.

- :func:`barycentre_residuals`: for each position, each star's (x, y) minus the
  barycentre of the other stars, minus its mean over positions.
- :func:`procrustes`: generalised Procrustes superimposition with 5
  parameters per position (translation x and y, scale x and y, rotation):
  each position is modelled as X_p = S_p R_p M + t_p, with S_p = diag(sx, sy)
  along the detector axes (tip-tilt of the stage changes the plate scale per
  axis), R_p a rotation (roll), M the mean configuration; M and the
  transforms are fitted together (Levenberg-Marquardt on the Schur complement
  of the transforms), M's gauge fixed by zero mean translation, rotation and
  isotropic scale. Residuals are in detector
  pixels.
- :func:`correction_factor`: the superimposition absorbs part of any random
  error (5 parameters per position fit 10 coordinates, and M is fitted too):
  by Monte Carlo on the actual geometry and number of positions, the ratio of
  an injected white jitter to the rms residual it leaves (about sqrt(2),
  1.4 and a little more, for 5 stars; see :func:`correction_factor`).
- :func:`accuracy`: each star's rms residual corrected by its own Monte
  Carlo factor, their rms, and its error bar by Monte Carlo with independent
  jitter per star.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import xarray as xr
from scipy.optimize import least_squares

__all__ = [
    "AstrometryError",
    "barycentre_residuals",
    "ProcrustesResult",
    "procrustes",
    "correction_factor",
    "star_factors",
    "Accuracy",
    "accuracy",
    "group_means",
    "select_positions",
    "mode_accuracies",
    "latex_table",
    "CSV_COLUMNS",
    "accuracy_csv",
    "residuals_dataset",
]


log = logging.getLogger(__name__)


class AstrometryError(ValueError):
    """Centroids that cannot give an accuracy (too few stars or positions...)."""


def _check(configurations, *, min_positions=2):
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


def barycentre_residuals(configurations) -> np.ndarray:
    """Each star's position minus the barycentre of the others, minus its mean over positions (position, star, 2)."""
    c = _check(configurations)
    n = c.shape[1]
    others = (c.sum(axis=1, keepdims=True) - c) / (n - 1)
    distance = c - others
    return distance - distance.mean(axis=0)


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
    c = _check(configurations)
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


def _residuals(basis, errors):
    """Residuals (trial, observation) of errors after the superimposition absorbs its part."""
    return errors - (errors @ basis) @ basis.T


def correction_factor(result: ProcrustesResult, *, trials: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Ratio of a white jitter to the rms Procrustes residual it leaves, by Monte Carlo.

    For the actual geometry (``result``'s mean configuration, transforms and
    number of positions): each trial draws independent unit Gaussian errors
    on every coordinate and superimposes them (to first order, exact for
    errors this small against the star separations). Returns the mean over
    trials of jitter / rms residual, and its standard error. With S stars and
    N positions, 2SN coordinates lose 5N transform and 2S - 4 mean-shape
    degrees of freedom (4: the gauge): about sqrt(2SN / (2SN - 5N - 2S + 4)),
    sqrt(2) = 1.41 for 5 stars and many positions (the paper's 1.4).
    """
    ratios = 1.0 / np.sqrt(np.mean(_white_residuals(result, trials, seed) ** 2, axis=(1, 2, 3)))
    return float(ratios.mean()), float(ratios.std(ddof=1) / np.sqrt(trials))


def _factors(white):
    """Per-star and global correction factors from white-jitter residuals (trial, position, star, 2)."""
    # per star: the jitter over the mean rms residual (unbiased for the accuracy, which multiplies
    # a measured rms); globally, as correction_factor: the mean of jitter / rms over trials
    per_star = 1.0 / np.sqrt(np.mean(white**2, axis=(1, 3))).mean(axis=0)
    return per_star, float((1.0 / np.sqrt(np.mean(white**2, axis=(1, 2, 3)))).mean())


def _white_residuals(result: ProcrustesResult, trials: int, seed: int, basis=None) -> np.ndarray:
    """Residuals (trial, position, star, 2) that the superimposition leaves of unit white errors."""
    basis = _tangent_basis(result.mean, result.params) if basis is None else basis
    rng = np.random.default_rng(seed)
    errors = rng.standard_normal((trials, basis.shape[0]))
    return _residuals(basis, errors).reshape(trials, *result.residuals.shape)


def star_factors(result: ProcrustesResult, *, trials: int = 2000, seed: int = 0) -> np.ndarray:
    """The correction factor of each star (star,): white jitter over the mean rms of that star's residuals.

    The superimposition does not absorb all stars alike: the transforms have
    little leverage on a star near the centre of the pattern (factor about
    1.1 for the central star of 5) and much on the corners (about 1.6).
    Correcting each star by its own factor keeps the accuracy unbiased when
    the stars' errors differ, where one global factor would not (6% low for
    the spread of :func:`accuracy`'s test).
    """
    return _factors(_white_residuals(result, trials, seed))[0]


@dataclass
class Accuracy:
    """A corrected Procrustes accuracy (pixel) with its Monte Carlo error bar (pixel).

    ``factor`` is the global correction factor (rms residual to accuracy, for
    equal errors); ``star_accuracy`` each star's own corrected accuracy.
    """

    accuracy: float
    error: float
    rms_residual: float
    factor: float
    star_accuracy: np.ndarray
    result: ProcrustesResult


def _corrected(residuals, factors):
    """Accuracy from residuals (..., position, star, 2): each star's rms times its factor, rms over stars."""
    per_star = factors * np.sqrt(np.mean(residuals**2, axis=(-3, -1)))
    return np.sqrt(np.mean(per_star**2, axis=-1)), per_star


def accuracy(configurations, *, trials: int = 2000, seed: int = 0) -> Accuracy:
    """Differential astrometric accuracy of the configurations: corrected rms Procrustes residual.

    Each star's rms residual is multiplied by its Monte Carlo correction
    factor for this geometry and number of positions (:func:`star_factors`),
    and the accuracy is the rms over stars. The error bar is the scatter of
    the same estimate over Monte Carlo data sets with independent jitter per
    star, each star's jitter its own corrected accuracy (as in the paper).
    """
    c = _check(configurations)
    result = procrustes(c)
    basis = _tangent_basis(result.mean, result.params)  # one SVD for the factors and the error bar
    factors, global_factor = _factors(_white_residuals(result, trials, seed, basis))
    value, per_star = _corrected(result.residuals, factors)
    rng = np.random.default_rng(seed + 1)
    jitter = rng.standard_normal((trials, *c.shape)) * per_star[None, None, :, None]
    estimates, _ = _corrected(_residuals(basis, jitter.reshape(trials, -1)).reshape(trials, *c.shape), factors)
    return Accuracy(float(value), float(np.std(estimates, ddof=1)), result.rms, global_factor, per_star, result)


def group_means(configurations, n_groups: int) -> np.ndarray:
    """Mean configuration of each of ``n_groups`` groups of contiguous positions (equal sizes, the rest left out).

    Raises
    ------
    AstrometryError
        Fewer positions than groups.
    """
    c = np.asarray(configurations, float)
    if c.shape[0] < n_groups:
        raise AstrometryError(f"{c.shape[0]} position(s) for {n_groups} groups")
    size = c.shape[0] // n_groups
    return c[:size * n_groups].reshape(n_groups, size, *c.shape[1:]).mean(axis=1)


def select_positions(ds, positions=None):
    """The (position, star, 2) configurations of a centroids dataset, over an inclusive index range.

    Raises
    ------
    AstrometryError
        A range that selects no position, or an unmeasured (NaN) star in it.
    """
    if positions is not None:
        first, last = positions
        ds = ds.sel(position=(ds["position"] >= first) & (ds["position"] <= last))
        if ds.sizes["position"] == 0:
            raise AstrometryError(f"no position with an index in [{first}, {last}]")
    return np.stack([ds["x"].values, ds["y"].values], axis=-1), ds["position"].values


def mode_accuracies(datasets: dict, *, positions=None, groups: int = 3, trials: int = 2000, seed: int = 0):
    """Accuracies of every calibration mode, over positions (p) and over groups of positions (g).

    Parameters
    ----------
    datasets : dict
        Mode name -> its ``centroids/<mode>.nc`` dataset.
    positions : (int, int), optional
        Inclusive range of position indices.
    groups : int
        Contiguous groups of positions for (g).

    Returns
    -------
    rows : list of dict
        One per mode and grouping: mode, method, flat, metrology, grouping
        ("position" or "group"), n (positions or groups), accuracy and error
        (pixel), rms_residual (pixel), factor.
    residuals : dict
        Mode -> (position indices, Procrustes residuals (position, star, 2)) over positions.
    """
    rows, residuals = [], {}
    for mode, ds in datasets.items():
        configurations, index = select_positions(ds, positions)
        for grouping, data in (("position", configurations), ("group", group_means(configurations, groups))):
            result = accuracy(data, trials=trials, seed=seed)
            rows.append({"mode": mode, "method": ds.attrs.get("method", ""), "flat": "flat" in mode,
                         "metrology": "metrology" in mode, "grouping": grouping, "n": data.shape[0],
                         "accuracy": result.accuracy, "error": result.error, "rms_residual": result.rms_residual,
                         "factor": result.factor})
            if grouping == "position":
                residuals[mode] = (index, result.result.residuals)
    return rows, residuals


def _latex_value(value, error):
    exponent = int(np.floor(np.log10(abs(value)))) if value else 0
    return rf"${value / 10**exponent:.2f}\pm{error / 10**exponent:.2f}\e{{{exponent}}}$"


def latex_table(rows) -> str:
    """The accuracies laid out as the paper's table of calibrations: metrology in rows, flat in columns."""
    cell = {(r["metrology"], r["flat"], r["grouping"]): r for r in rows}
    lines = [r"% Accuracies (pixel) with different calibrations; (p) over positions, (g) over groups.",
             r"% \e{n} stands for x10^n and \specialcell makes a two-line cell, as in the paper.",
             r"\begin{tabular}{lcc}", r"\hline", r" & No flat & Flat \\", r"\hline"]
    for metrology in (False, True):
        entries = []
        for flat in (False, True):
            parts = [f"({g[0]}) " + _latex_value(cell[metrology, flat, g]["accuracy"], cell[metrology, flat, g]["error"])
                     for g in ("position", "group") if (metrology, flat, g) in cell]
            entries.append(r"\specialcell{" + r"\\".join(parts) + "}" if parts else "--")
        lines.append(f"{'Metrology' if metrology else 'No metrology'} & {entries[0]} & {entries[1]} " + r"\\")
    lines += [r"\hline", r"\end{tabular}", ""]
    return "\n".join(lines)


#: Columns of ``tables/accuracy.csv``: the contract's first, then what makes each row traceable.
CSV_COLUMNS = ("flat", "metrology", "grouping", "accuracy", "error", "mode", "method", "n", "rms_residual", "factor")


def accuracy_csv(rows) -> str:
    """The rows of :func:`mode_accuracies` as CSV text (booleans as true/false, floats to 7 digits)."""
    def text(value):
        if isinstance(value, (bool, np.bool_)):
            return str(bool(value)).lower()
        return f"{value:.6e}" if isinstance(value, float) else str(value)

    return "\n".join([",".join(CSV_COLUMNS), *(",".join(text(row[c]) for c in CSV_COLUMNS) for row in rows)]) + "\n"


def _complete_barycentre_residuals(configurations):
    """Barycentre residuals over the positions where every star was measured (NaN elsewhere)."""
    complete = np.isfinite(configurations).all(axis=(1, 2))
    out = np.full(configurations.shape, np.nan)
    if complete.sum() >= 2:
        out[complete] = barycentre_residuals(configurations[complete])
    return out


def residuals_dataset(datasets: dict, rows, *, residuals: dict) -> xr.Dataset:
    """Procrustes residuals over the selected positions and barycentre residuals over all, per mode.

    ``datasets``, ``rows`` and ``residuals`` are one method's: its centroid
    datasets by mode, and what :func:`mode_accuracies` returned for them.
    ``star_x`` and ``star_y`` (mode, star) are each star's mean centroid over
    the positions where it was measured: the pattern's layout, which the
    barycentre figure draws downscaled to the residuals.
    """
    modes = list(residuals)
    accuracy_p = {r["mode"]: r["accuracy"] for r in rows if r["grouping"] == "position"}
    configurations = [select_positions(datasets[m])[0] for m in modes]
    barycentre = [_complete_barycentre_residuals(c) for c in configurations]
    star_mean = np.stack([np.nanmean(c, axis=0) for c in configurations])  # (mode, star, 2)
    return xr.Dataset(
        {"residual": (("mode", "position", "star", "axis"), np.stack([residuals[m][1] for m in modes]),
                      {"units": "pixel", "long_name": "Procrustes residual of each star"}),
         "accuracy": (("mode",), [accuracy_p[m] for m in modes],
                      {"units": "pixel", "long_name": "corrected accuracy (p)"}),
         "barycentre_residual": (("mode", "all_position", "star", "axis"), np.stack(barycentre),
                                 {"units": "pixel", "long_name": "star minus the barycentre of the others, minus "
                                                                 "its mean over positions"}),
         "star_x": (("mode", "star"), star_mean[..., 0],
                    {"units": "pixel", "long_name": "mean centroid x of each star over the positions"}),
         "star_y": (("mode", "star"), star_mean[..., 1],
                    {"units": "pixel", "long_name": "mean centroid y of each star over the positions"})},
        coords={"mode": modes, "position": residuals[modes[0]][0],
                "all_position": datasets[modes[0]]["position"].values, "axis": ["x", "y"]})
