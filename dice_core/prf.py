"""PRF width maps from the fringe contrast of baselines at different periods (issue 14; beyond the paper).

A pixel's response to the fringe ``1 + V sin(K.r + phi)`` is its sensitivity
times ``V H(K)``, with H the characteristic function of its normalised PRF
(:meth:`dice_core.detector.PixelResponse.fringe_response`). The metrology's
contrast ``alpha / iota`` (:mod:`dice_core.fringes`) therefore is, up to the
product's normalisations,

.. math::

    \\ln(\\alpha_p / \\iota_p) = \\ln V_b(r_p) + \\ln|h_x(k_x; w_{x,p})| + \\ln|h_y(k_y; w_{y,p})|

for baseline b of wavevector (k_x, k_y): the sensitivity, the illumination
and the envelope cancel. ``V_b`` (the fringe visibility, the beams' balance)
is smooth across the detector; the pixel-to-pixel part is the transfer of
the pixels' PRFs. To first order in the PRF's variance ``v = w^2``,
``ln h(k; v) = ln h(k; v0) + a(k) (v - v0)`` with ``a(k) = -k^2 / 2`` for
any symmetric PRF, corrected at order ``k^4`` by the kernel's fourth moment:
``a`` is computed for each kernel (:func:`log_transfer_slope`).

:func:`width_maps` separates the two like the gauge fixing does (smooth
against pixel-scale): each baseline's log-contrast is projected off the
polynomials of degree ``smooth_degree`` over the pixels fitted; the
pixel-scale rests of all baselines are then solved, pixel by pixel, for the
deviations of the variance along x and along y, weighted by their photon
noise (:func:`log_contrast_variance`, propagated from the fits' frame
factors as the offsets' photon floor is). Two periods along a direction
measure the same deviation twice, with slopes in the ratio of about
``(K1 / K2)^2`` (2.8 for 2.4 and 4 pixels) times a factor of 1.02-1.09 set
by the kernel's shape (its fourth moment): their agreement weighs each
kernel of a :class:`PrfFamily` (issue 27), and the maps are the posterior's
means, the shape's spread in their errors.

What the contrast cannot give:

- any smooth variation of the widths over the detector: it is the
  visibility's. The maps are each direction's mean width plus each pixel's
  deviation, orthogonal to the smooth polynomials over the fitted pixels.
  A truth is compared after the same projection (:func:`pixel_scale`), as
  offsets are after their affine part;
- the mean width and the deviations' scale beyond what the two periods'
  ratio allows: the kernels of the family with the same ratio have widths
  within 0.002-0.009 pixel of each other (``error_mean_width``); with one
  period per direction, the whole family's spread;
- symmetry. An asymmetric PRF (the simulator's ``prf_slope_rms``, the
  kernel times 1 + s u) has ``|h|^2 = h_r^2 + s^2 h_i^2``: its modulus, and
  so its measured width, moves at second order in s (``s^2 k^2 w^4 / 2`` in
  the log-contrast, 2e-5 for s = 0.05 per pixel at 2.4 pixels against a
  photon noise of about 1.5e-4 at 4000 frames); its phase, the first order,
  is the metrology's (docs/metrology.md).

Units: pixel, rad/pixel; variances pixel^2.
"""

from __future__ import annotations

import json

import numpy as np

from dice_core import lazy
from dice_core.detector import _kernel, _quadrature, hyper_gaussian_std
from dice_core.fringes import frame_moments
from dice_core.parallel import one_blas_thread
from dice_core.polynomials import polynomial_design

xr = lazy.module("xarray")

__all__ = [
    "PrfShape",
    "PrfFamily",
    "log_transfer",
    "log_transfer_slope",
    "log_contrast_variance",
    "pixel_scale",
    "WidthMaps",
    "width_maps",
    "prf_dataset",
    "variance_deviations",
]


class PrfShape:
    """The assumed PRF kernel: a truncated hyper-Gaussian of ``order``, ``half_width`` (pixel) and scale ``sigma``.

    ``width`` (pixel) is its standard deviation; a member of a :class:`PrfFamily`, or a family of one.
    """

    def __init__(self, *, order: float = 4.0, half_width: float = 0.5, sigma: float = 0.3):
        if not (order > 0 and half_width > 0 and sigma > 0):
            raise ValueError(f"PRF shape: order, half_width and sigma must be > 0, got {order}, {half_width}, {sigma}")
        self.order, self.half_width, self.sigma = float(order), float(half_width), float(sigma)

    @property
    def width(self) -> float:
        return float(hyper_gaussian_std(self.sigma, order=self.order, half_width=self.half_width))

    def as_dict(self):
        return {"order": self.order, "half_width": self.half_width, "sigma": self.sigma}


def _span(value):
    """A setting's (low, high): a number is a span of one value."""
    low, high = (value, value) if np.ndim(value) == 0 else value
    if not (0 < float(low) <= float(high)):
        raise ValueError(f"PRF family: a span must be 0 < low <= high, got {value!r}")
    return float(low), float(high)


class PrfFamily:
    """The PRF kernels a detector may have: truncated hyper-Gaussians whose order, scale ``sigma`` (pixel) and
    truncation ``half_width`` (pixel) each lie in a span (low, high), a number being a span of one.

    The default is the family of issue 27: orders 2 to 6, sigmas 0.25 to 0.45 pixel, truncated at half a
    pixel (widths 0.158 to 0.266 pixel). Its ``members`` are a grid over the spans (9 orders, 17 sigmas, 3
    half-widths where a span is not one value), the prior :func:`width_maps` weighs by the data.
    """

    def __init__(self, *, order=(2.0, 6.0), sigma=(0.25, 0.45), half_width=0.5):
        self.order, self.sigma, self.half_width = _span(order), _span(sigma), _span(half_width)

    @classmethod
    def of(cls, shape: "PrfShape") -> "PrfFamily":
        """The family of one kernel."""
        return cls(order=shape.order, sigma=shape.sigma, half_width=shape.half_width)

    @property
    def members(self) -> list:
        def grid(span, n):
            return np.linspace(*span, n if span[1] > span[0] else 1)
        return [PrfShape(order=n, sigma=s, half_width=a) for n in grid(self.order, 9) for s in grid(self.sigma, 17)
                for a in grid(self.half_width, 3)]

    def as_dict(self):
        return {"order": list(self.order), "sigma": list(self.sigma), "half_width": list(self.half_width)}


def log_transfer(k, sigma, shape: PrfShape):
    """ln h(k) of the kernel of scale ``sigma`` (pixel; scalar or array) at wavenumber ``k`` (rad/pixel)."""
    u, w = _quadrature(shape.half_width)
    kern = _kernel(u, np.asarray(sigma, float)[..., None], shape.order)
    return np.log(np.abs((w * kern * np.cos(k * u)).sum(-1) / (w * kern).sum(-1)))


def log_transfer_slope(k, shape: PrfShape, *, relative_step: float = 1e-4) -> float:
    """a(k) = d ln h(k) / d(w^2) at the shape's width, pixel^-2 (central difference along the kernel's scale)."""
    s = shape.sigma * np.array([1 - relative_step, 1 + relative_step])
    v = hyper_gaussian_std(s, order=shape.order, half_width=shape.half_width) ** 2
    lnh = log_transfer(float(k), s, shape)
    return float((lnh[1] - lnh[0]) / (v[1] - v[0]))


def _frame_factors(product: xr.Dataset) -> np.ndarray:
    """(B, A cos phi, A sin phi) (frame, 3), adu, in the normalisation of the product's iota and alpha."""
    level, amplitude, phase = (product[v].values for v in ("level", "amplitude", "phase"))
    return np.column_stack([level, amplitude * np.cos(phase), amplitude * np.sin(phase)])


def log_contrast_variance(product: xr.Dataset, *, gain: float, read_noise=None) -> np.ndarray:
    """Variance of ln(alpha / iota) per pixel (row, col) from photon and read noise, for the temporal fit used.

    Pixel factors G = (iota, alpha sin theta, alpha cos theta) and frame factors
    F = (B, A cos phi, A sin phi) from a ``metrology/<baseline>.nc`` product;
    sample variance F_t.G_p / g + sigma_r^2 (adu^2), so that
    cov(G_p) = (F'F)^-1 [sum_k G_pk M_k / g + sigma_r^2 F'F] (F'F)^-1 (the
    offsets' photon floor, :func:`dice_core.fringes.photon_floor`), and
    ln c = ln|(g2, g3)| - ln g1 propagates it linearly. NaN where the product
    has no fit. ``read_noise``: adu, scalar or (row, col); none if omitted.
    """
    F = _frame_factors(product)
    FtF, third = frame_moments(F)
    inv = np.linalg.inv(FtF)
    iota, alpha, theta = (product[v].values for v in ("iota", "alpha", "pixel_phase"))
    G = np.stack([iota, alpha * np.sin(theta), alpha * np.cos(theta)], axis=-1)  # (row, col, 3)
    r2 = alpha**2
    gradient = np.stack([-1.0 / iota, G[..., 1] / r2, G[..., 2] / r2], axis=-1)
    u = gradient @ inv
    outer = (u[..., :, None] * u[..., None, :]).reshape(*u.shape[:-1], 9)
    photon = np.sum(G / gain * (outer @ third.reshape(3, 9).T), axis=-1)
    noise = 0.0 if read_noise is None else np.asarray(read_noise, float) ** 2
    return photon + noise * (outer @ FtF.ravel())


def pixel_scale(values, x, y, *, degree: int):
    """``values`` (pixel,) minus their least-squares polynomial of ``degree`` in (x, y): the pixel-scale part."""
    design = polynomial_design(x, y, degree=degree)
    q, _ = np.linalg.qr(design)
    values = np.asarray(values, float)
    return values - q @ (q.T @ values)


def variance_deviations(width, shape_width):
    """w^2 - w0^2 (pixel^2): a width map's PRF variance relative to the mean kernel's, NaN kept."""
    return np.asarray(width, float) ** 2 - float(shape_width) ** 2


class WidthMaps:
    """Result of :func:`width_maps`: maps (row, col) in pixel; NaN where not measured.

    Attributes
    ----------
    width_x, width_y : ndarray
        Each pixel's PRF standard deviation along x and y: the direction's mean width plus the pixel's
        pixel-scale deviation (the smooth variations over the detector are the visibility's: not measured).
    error_width_x, error_width_y : ndarray
        1-sigma error of the width: photon noise and the kernel shape's uncertainty (which scales the
        deviations and sets the mean).
    error_width_pixel_x, error_width_pixel_y : ndarray
        1-sigma error of the width minus the map's mean: photon noise and the shape's uncertainty in the
        scale of the deviations only (the mean's error is common to every pixel).
    photon_error_width_x, photon_error_width_y : ndarray
        The photon-noise part of those errors.
    variance_x, variance_y : ndarray
        Each pixel's PRF variance minus the mean one, pixel^2 (what the contrast measures, and what the
        centroid correction uses), pixel-scale part.
    mean_width, error_mean_width : dict
        Axis -> the mean width (pixel) and its 1-sigma error, over the family's kernels the data allow.
    error_scale : dict
        Axis -> the relative 1-sigma error of the deviations' scale (width minus mean), from the shape.
    family : PrfFamily
        The kernels assumed possible.
    posterior : dict
        Axis -> {"weights": (member,) posterior weights over ``family.members``, "chi2": (member,)}.
    baselines : dict
        Baseline name -> (kx, ky, a_x, a_y): mean wavevector (rad/pixel) and the log-contrast's slopes per
        unit variance along x and y (pixel^-2), the posterior's mean.
    chi2 : float
        Mean chi^2 per degree of freedom of the per-pixel fits with the most likely kernels (NaN with no
        redundant baseline): about 1 when the periods agree within their noise.
    residual_rms : dict
        Baseline name -> rms of its pixel-scale log-contrast (1).
    """

    def __init__(self, **fields):
        self.__dict__.update(fields)


def _log_contrasts(products, names, valid, *, gain, read_noise):
    """Each baseline's ln(alpha / iota) and its photon-noise variance (row, col), and the pixels all hold."""
    lnc, var = {}, {}
    for name in names:
        p = products[name]
        with np.errstate(invalid="ignore", divide="ignore"):
            lnc[name] = np.log(p["alpha"].values / p["iota"].values)
        var[name] = log_contrast_variance(p, gain=gain, read_noise=read_noise)
        valid &= np.isfinite(lnc[name]) & np.isfinite(var[name]) & (var[name] > 0)
    return lnc, var, valid


def _without_gauge_ripple(products, names, valid, r, s2, a, *, smooth_degree):
    """The pixel-scale log-contrasts ``r`` (baseline, pixel) without each baseline's gauge ripple.

    Each baseline's gauge (fringes.fix_gauge) is fixed from noisy data: what is left of its mixing of iota
    with the fringe factors is a ripple in the log-contrast at the first and second harmonics of the pixel
    phase (measured: up to 0.7 sigma at 4000 frames). Those 4 patterns per baseline are fitted with the
    widths of design ``a`` (baseline, direction), jointly: a width pattern that one baseline's ripple hides
    the others still see (a Schur complement over the per-pixel unknowns).
    """
    rows, cols = np.nonzero(valid)
    x, y = cols.astype(float), rows.astype(float)
    n_b, n_h = len(names), 4
    if n_b <= a.shape[1]:
        return r
    nuisance = np.zeros((r.shape[1], n_b, n_b * n_h))
    for i, n in enumerate(names):
        theta = products[n]["pixel_phase"].values[valid]
        nuisance[:, i, i * n_h:(i + 1) * n_h] = np.stack(
            [pixel_scale(f(m * theta), x, y, degree=smooth_degree) for m in (1, 2) for f in (np.cos, np.sin)],
            axis=-1)
    weights = 1 / s2.T  # (pixel, baseline)
    cov = np.linalg.inv(np.einsum("bi,bj,pb->pij", a, a, weights))
    # per pixel, the weighted projector off the width directions: Q = W - W A (A'WA)^-1 A'W
    wa = weights[:, :, None] * a[None]  # (pixel, baseline, direction)
    q = np.einsum("pb,bc->pbc", weights, np.eye(n_b)) - np.einsum("pbi,pij,pcj->pbc", wa, cov, wa)
    reduced = np.einsum("pbm,pbc,pcn->mn", nuisance, q, nuisance)
    coef = np.linalg.lstsq(reduced, np.einsum("pbm,pbc,cp->m", nuisance, q, r), rcond=1e-10)[0]
    return r - np.einsum("pbm,m->bp", nuisance, coef)


def _joint_solve(a, r, s2):
    """Each pixel's variance deviations (pixel, direction) from its baselines' pixel-scale log-contrasts
    ``r`` (baseline, pixel) of variances ``s2``, design ``a`` (baseline, direction): their covariance
    (pixel, direction, direction) and the chi^2 per degree of freedom (NaN without one)."""
    cov = np.linalg.inv(np.einsum("bi,bj,pb->pij", a, a, 1 / s2.T))
    dv = np.einsum("pij,pj->pi", cov, np.einsum("bi,bp->pi", a, r / s2))
    dof = a.shape[0] - a.shape[1]
    chi2 = float(np.mean(np.sum((r - a @ dv.T) ** 2 / s2, axis=0)) / dof) if dof > 0 else float("nan")
    return dv, cov, chi2


def _shape_posterior(r, s2, k, family: PrfFamily, *, block: int = 16) -> dict:
    """The kernel shapes the pixel-scale log-contrasts along one direction allow, and the widths they give.

    ``r``, ``s2`` (baseline, pixel): the baselines measuring this direction, their log-contrasts with the
    other direction's share removed, and variances; ``k`` (baseline,): their wavenumbers along it,
    rad/pixel. Each member m of the family gives every baseline a slope a_mb = d ln h / d(w^2) at its own
    width w_m, each pixel's variance deviation dv_p(m) its weighted least squares, and a chi^2. The
    slopes' overall scale is not seen (dv absorbs it); their ratio between two periods is, through the
    kernel's fourth moment, and with it the width. The posterior weights are exp(-(chi2 - min) / 2S), the
    family's grid the prior, S = max(1, min chi2 per degree of freedom) (a misfit widens it); with one
    baseline the data say nothing and the weights are the prior's.

    Returns the posterior's means and spreads: ``weights`` and ``chi2`` (member,); ``mean_width`` and
    ``error_mean_width``; per pixel ``width``, its shape spread ``spread`` and ``spread_pixel`` (the
    map's mean removed first), the variance deviation ``variance``, the photon variance of the width
    ``photon``; ``slopes`` (baseline,), the slopes' mean; ``chi2_min`` per degree of freedom;
    ``error_scale``, the relative spread of the deviations' scale (their rms over the map) over the posterior.
    """
    members = family.members
    widths = np.array([m.width for m in members])
    slopes = np.array([[log_transfer_slope(kb, m) for kb in k] for m in members])  # (member, baseline)
    w = 1 / s2
    base = np.sum(w * r**2, axis=0)
    chi2 = np.empty(len(members))
    for lo in range(0, len(members), block):  # the (member, pixel) products a block of members at a time
        a = slopes[lo:lo + block]
        chi2[lo:lo + block] = np.sum(base - (a @ (w * r)) ** 2 / (a**2 @ w), axis=1)
    dof = r.shape[1] * (r.shape[0] - 1)
    scale = max(1.0, chi2.min() / dof) if dof else 1.0
    weights = np.exp(-(chi2 - chi2.min()) / (2 * scale)) if dof else np.ones(len(members))
    weights /= weights.sum()
    sums = {name: 0.0 for name in ("width", "width2", "pixel2", "variance", "photon")}
    scales = np.zeros(len(members))  # each member's rms deviation from the map's mean: the deviations' scale
    for m in np.flatnonzero(weights > 1e-6 * weights.max()):
        dv = (slopes[m] @ (w * r)) / (slopes[m] ** 2 @ w)
        width = np.sqrt(widths[m] ** 2 + dv)
        sums["width"] = sums["width"] + weights[m] * width
        sums["width2"] = sums["width2"] + weights[m] * width**2
        sums["pixel2"] = sums["pixel2"] + weights[m] * (width - width.mean()) ** 2
        scales[m] = np.std(width)
        sums["variance"] = sums["variance"] + weights[m] * dv
        sums["photon"] = sums["photon"] + weights[m] / (slopes[m] ** 2 @ w) / (4 * width**2)
    mean_width, scale = float(weights @ widths), float(weights @ scales)
    pixel_mean = sums["width"] - sums["width"].mean()
    return {"weights": weights, "chi2": chi2, "chi2_min": chi2.min() / dof if dof else float("nan"),
            "mean_width": mean_width, "error_mean_width": float(np.sqrt(weights @ (widths - mean_width) ** 2)),
            "width": sums["width"], "spread": np.sqrt(np.maximum(sums["width2"] - sums["width"] ** 2, 0)),
            "spread_pixel": np.sqrt(np.maximum(sums["pixel2"] - pixel_mean**2, 0)), "variance": sums["variance"],
            "photon": sums["photon"], "slopes": weights @ slopes,
            "error_scale": float(np.sqrt(weights @ (scales - scale) ** 2) / scale) if scale > 0 else float("nan")}


@one_blas_thread  # a QR of 1480x28 took 0.47 s with the default threads on 2 busy cores, 2 ms with one
def width_maps(products: dict, *, gain: float, read_noise=None, shape=None, smooth_degree: int = 6, science=None,
               log=None) -> WidthMaps:
    """PRF width maps along x and y from the metrology products of several baselines.

    Parameters
    ----------
    products : dict
        Baseline name -> its ``metrology/<baseline>.nc`` dataset (iota, alpha,
        pixel_phase, level, amplitude, phase, kx, ky).
    gain : float
        e-/adu.
    read_noise : float or ndarray (row, col), optional
        adu, as the fits were given it.
    shape : PrfFamily or PrfShape, optional
        The kernels the PRFs may have (a PrfShape: that kernel alone); default
        :class:`PrfFamily`'s (orders 2-6, sigmas 0.25-0.45 pixel).
    smooth_degree : int
        Degree of the polynomial that each baseline's visibility follows.
    science : bool ndarray (row, col), optional
        Pixels the maps may cover; all by default.

    Raises
    ------
    ValueError
        No products; a direction (x or y) that no baseline's wavevector
        mostly follows is left NaN, not an error, unless neither has one.

    Notes
    -----
    The pixel-scale log-contrasts are cleaned of the gauge ripple and solved
    jointly with the family's middle kernel; then, for each direction, with
    the other direction's small share removed, :func:`_shape_posterior`
    weighs every kernel of the family by how well its slopes fit the
    direction's baselines, and the maps are the posterior's means, their
    errors photon noise and the posterior's spread in quadrature.
    """
    if not products:
        raise ValueError("PRF widths need the metrology products of at least one baseline")
    family = shape if isinstance(shape, PrfFamily) else PrfFamily.of(shape) if shape else PrfFamily()
    reference = family.members[len(family.members) // 2]
    names = sorted(products)
    grid = products[names[0]]["iota"].shape
    valid = np.ones(grid, bool) if science is None else np.asarray(science, bool).copy()
    lnc, var, valid = _log_contrasts(products, names, valid, gain=gain, read_noise=read_noise)
    k = np.array([[float(products[n]["kx"]), float(products[n]["ky"])] for n in names])
    along = np.abs(k[:, 0]) >= np.abs(k[:, 1])  # the direction each baseline mostly measures
    observed = np.array([along.any(), (~along).any()])
    if not observed.any():
        raise ValueError("no baseline to measure PRF widths with")
    rows, cols = np.nonzero(valid)
    x, y = cols.astype(float), rows.astype(float)
    r = np.stack([pixel_scale(lnc[n][valid], x, y, degree=smooth_degree) for n in names])  # (baseline, pixel)
    s2 = np.stack([var[n][valid] for n in names])
    design = np.array([[log_transfer_slope(abs(kb), reference) for kb in kv] for kv in k])  # (baseline, 2)
    r = _without_gauge_ripple(products, names, valid, r, s2, design[:, observed], smooth_degree=smooth_degree)
    dv, _, _ = _joint_solve(design[:, observed], r, s2)
    out, slopes, chi2 = {}, design.copy(), []
    for j, axis in enumerate(("x", "y")):
        if not observed[j]:
            if log is not None:
                log.warning("no baseline measures the PRF widths along %s: width_%s left NaN", axis, axis)
            continue
        own = along if j == 0 else ~along
        other = np.zeros(len(names)) if observed.sum() == 1 else design[:, 1 - j]
        other_dv = dv[:, 1 - j] if observed.sum() == 2 else 0.0
        # the direction's baselines, the other direction's share (1e-3 of theirs on a bench near the axes) removed
        post = _shape_posterior((r - np.outer(other, other_dv))[own], s2[own], np.abs(k[own, j]), family)
        slopes[own, j] = post["slopes"]
        chi2.append((post["chi2_min"], own.sum() - 1))
        out[axis] = post
    return _assemble(out, valid, grid, x, y, names, k, slopes, r, chi2, family, smooth_degree, log)


def _assemble(posteriors, valid, grid, x, y, names, k, slopes, r, chi2, family, smooth_degree, log) -> WidthMaps:
    """The :class:`WidthMaps` of each direction's posterior (:func:`width_maps`), logged."""
    fields = {"family": family, "smooth_degree": smooth_degree, "mean_width": {}, "error_mean_width": {},
              "error_scale": {}, "posterior": {}}
    for axis in "xy":
        maps = {name: np.full(grid, np.nan) for name in ("width", "error", "pixel", "photon", "variance")}
        post = posteriors.get(axis)
        if post is not None:
            # the maps hold the pixel-scale part exactly (orthogonal to the smooth polynomials) about the mean
            maps["width"][valid] = post["mean_width"] + pixel_scale(post["width"], x, y, degree=smooth_degree)
            maps["variance"][valid] = pixel_scale(post["variance"], x, y, degree=smooth_degree)
            maps["error"][valid] = np.sqrt(post["photon"] + post["spread"] ** 2)
            maps["pixel"][valid] = np.sqrt(post["photon"] + post["spread_pixel"] ** 2)
            maps["photon"][valid] = np.sqrt(post["photon"])
            fields["mean_width"][axis], fields["error_mean_width"][axis] = post["mean_width"], post["error_mean_width"]
            fields["error_scale"][axis] = post["error_scale"]
            fields["posterior"][axis] = {"weights": post["weights"], "chi2": post["chi2"]}
        fields.update({f"width_{axis}": maps["width"], f"error_width_{axis}": maps["error"],
                       f"error_width_pixel_{axis}": maps["pixel"], f"photon_error_width_{axis}": maps["photon"],
                       f"variance_{axis}": maps["variance"]})
    redundant = [(c, n) for c, n in chi2 if n > 0]
    fields["chi2"] = (float(sum(c * n for c, n in redundant) / sum(n for _, n in redundant)) if redundant
                      else float("nan"))
    fields["baselines"] = {n: (*k[i], *slopes[i]) for i, n in enumerate(names)}
    fields["residual_rms"] = {n: float(np.sqrt(np.mean(r[i] ** 2))) for i, n in enumerate(names)}
    maps = WidthMaps(**fields)
    if log is not None:
        for n in names:
            log.info("%s: log-contrast slope per unit PRF variance %.3f along x, %.3f along y (pixel^-2); "
                     "pixel-scale rms %.2e", n, *maps.baselines[n][2:], maps.residual_rms[n])
        for axis, mean in maps.mean_width.items():
            log.info("PRF widths along %s: mean %.4f +- %.4f pixel over the family's kernels the data allow, the "
                     "deviations' scale known to %.1f%%", axis, mean, maps.error_mean_width[axis],
                     100 * maps.error_scale[axis])
        log.info("PRF widths: %d pixels, chi2 per dof %.3f between the baselines", valid.sum(), maps.chi2)
    return maps


def prf_dataset(maps: WidthMaps) -> xr.Dataset:
    """The ``calibration/prf.nc`` product: the width maps along x and y with their errors (row, col), pixel;
    the variance deviations the centroid correction uses, pixel^2; each direction's mean width with its
    error; and the family's posterior over its kernels."""
    rc = ("row", "col")
    rows, cols = maps.width_x.shape
    names = sorted(maps.baselines)
    members = maps.family.members
    data = {}
    maps_of_axis = (  # name, WidthMaps attribute, units, long_name; each with {axis}
        ("width", "width", "pixel", "PRF standard deviation along {axis}: the mean width plus the pixel's "
                                    "pixel-scale deviation (smooth variations not measured)"),
        ("error_width", "error_width", "pixel", "1-sigma error of width_{axis}: photon noise and the uncertainty of "
                                                "the kernel's shape (mean and scale)"),
        ("error_width_pixel", "error_width_pixel", "pixel", "1-sigma error of width_{axis} minus its mean over the "
                                                            "map: photon noise and the shape's uncertainty in the "
                                                            "deviations' scale"),
        ("photon_error_width", "photon_error_width", "pixel", "1-sigma photon-noise error of width_{axis} (its part "
                                                              "of the errors above)"),
        ("variance_deviation", "variance", "pixel2", "PRF variance along {axis} minus the mean one, pixel-scale part "
                                                     "(what the contrast measures; the centroid correction's)"))
    scalars_of_axis = (  # name, WidthMaps dict attribute, units, long_name
        ("mean_width", "mean_width", "pixel", "mean PRF standard deviation along {axis}, over the family's kernels "
                                              "the two periods allow"),
        ("error_mean_width", "error_mean_width", "pixel", "1-sigma error of mean_width_{axis}"),
        ("error_deviation_scale", "error_scale", "1", "relative 1-sigma error of the scale of width_{axis} minus its "
                                                      "mean, from the kernel's shape"))
    for axis in "xy":
        for name, attribute, units, what in maps_of_axis:
            data[f"{name}_{axis}"] = (rc, getattr(maps, f"{attribute}_{axis}"),
                                      {"units": units, "long_name": what.format(axis=axis)})
        for name, attribute, units, what in scalars_of_axis:
            data[f"{name}_{axis}"] = ((), getattr(maps, attribute).get(axis, np.nan),
                                      {"units": units, "long_name": what.format(axis=axis)})
        data[f"kernel_posterior_{axis}"] = (("kernel",), maps.posterior.get(axis, {}).get(
            "weights", np.full(len(members), np.nan)), {
            "units": "1", "long_name": f"posterior weight of each kernel of the family along {axis}"})
    data.update({
        "kernel_order": (("kernel",), [m.order for m in members], {"units": "1", "long_name": "kernel order"}),
        "kernel_sigma": (("kernel",), [m.sigma for m in members], {"units": "pixel", "long_name": "kernel scale"}),
        "kernel_half_width": (("kernel",), [m.half_width for m in members],
                              {"units": "pixel", "long_name": "kernel truncation half-width"}),
        "kernel_width": (("kernel",), [m.width for m in members],
                         {"units": "pixel", "long_name": "kernel standard deviation"}),
        "log_contrast_slope_x": (("baseline",), [maps.baselines[n][2] for n in names],
                                 {"units": "pixel-2", "long_name": "d ln(contrast) / d(PRF variance along x)"}),
        "log_contrast_slope_y": (("baseline",), [maps.baselines[n][3] for n in names],
                                 {"units": "pixel-2", "long_name": "d ln(contrast) / d(PRF variance along y)"}),
        "pixel_scale_rms": (("baseline",), [maps.residual_rms[n] for n in names],
                            {"units": "1", "long_name": "rms of the baseline's pixel-scale log-contrast"}),
        "chi2": ((), maps.chi2, {"units": "1", "long_name": "mean chi^2 per degree of freedom between the "
                                                           "baselines' widths, most likely kernels (NaN: none "
                                                           "redundant)"}),
    })
    return xr.Dataset(
        data, coords={"row": np.arange(rows), "col": np.arange(cols), "baseline": names,
                      "kernel": np.arange(len(members))},
        attrs={"prf_family": json.dumps(maps.family.as_dict()), "smooth_degree": maps.smooth_degree,
               "method": "pixel-scale log-contrast of each baseline, off a polynomial of smooth_degree, solved per "
                         "pixel for the PRF variance along x and y, over the family of kernels weighed by the "
                         "two periods' agreement (docs/centroids.md, PRF widths)"},
    )
