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
``a`` is computed for the assumed kernel (:func:`log_transfer_slope`).

:func:`width_maps` separates the two like the gauge fixing does (smooth
against pixel-scale): each baseline's log-contrast is projected off the
polynomials of degree ``smooth_degree`` over the pixels fitted; the
pixel-scale rests of all baselines are then solved, pixel by pixel, for the
deviations of the variance along x and along y, weighted by their photon
noise (:func:`log_contrast_variance`, propagated from the fits' frame
factors as the offsets' photon floor is). Two periods along a direction
measure the same deviation twice, with slopes in the ratio of about
``(K1 / K2)^2`` (2.8 for 2.4 and 4 pixels); their agreement is a test of
the assumed kernel (``chi2``).

What the contrast cannot give, and what is therefore assumed:

- the mean width, and any smooth variation of the widths over the
  detector: they are the visibility's. The maps are the assumed kernel's
  width (``order``, ``half_width``, ``sigma``: the simulator's truncated
  hyper-Gaussian) plus each pixel's deviation, orthogonal to the smooth
  polynomials over the fitted pixels. A truth is compared after the same
  projection (:func:`pixel_scale`), as offsets are after their affine part;
- the kernel's shape beyond its variance: the slope ``a`` uses the assumed
  order and truncation. A Gaussian (order 2, no truncation) has
  ``a = -k^2/2`` exactly; the order-4 kernel truncated at half a pixel has
  ``a`` 8% larger at a 2.4-pixel period; a wrong order shows as a chi2
  above 1 between two periods;
- symmetry. An asymmetric PRF (the simulator's ``prf_slope_rms``, the
  kernel times 1 + s u) has ``|h|^2 = h_r^2 + s^2 h_i^2``: its modulus, and
  so its measured width, moves at second order in s (``s^2 k^2 w^4 / 2`` in
  the log-contrast, 2e-5 for s = 0.05 per pixel at 2.4 pixels against a
  photon noise of about 1.5e-4 at 4000 frames); its phase, the first order,
  is the metrology's (docs/metrology.md).

Units: pixel, rad/pixel; variances pixel^2.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from dice_core.detector import _kernel, _quadrature, hyper_gaussian_std
from dice_core.fringes import frame_moments
from dice_core.polynomials import polynomial_design

__all__ = [
    "PrfShape",
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

    ``width`` (pixel) is its standard deviation, the mean width the maps are built on.
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
    width_x, width_y, error_width_x, error_width_y : ndarray
        PRF standard deviation along x and y, and its 1-sigma photon-noise error.
    shape : PrfShape
        The kernel assumed (its width is the maps' mean).
    baselines : dict
        Baseline name -> (kx, ky, a_x, a_y): mean wavevector (rad/pixel) and
        the log-contrast's slopes per unit variance along x and y (pixel^-2).
    chi2 : float
        Mean chi^2 per degree of freedom of the per-pixel fits (NaN with no
        redundant baseline): about 1 when the periods agree within their noise.
    residual_rms : dict
        Baseline name -> rms of its pixel-scale log-contrast (1).
    """

    def __init__(self, width_x, width_y, error_width_x, error_width_y, shape, baselines, chi2, residual_rms,
                 smooth_degree):
        self.width_x, self.width_y = width_x, width_y
        self.error_width_x, self.error_width_y = error_width_x, error_width_y
        self.shape, self.baselines, self.chi2 = shape, baselines, chi2
        self.residual_rms, self.smooth_degree = residual_rms, smooth_degree


def width_maps(products: dict, *, gain: float, read_noise=None, shape: PrfShape | None = None,
               smooth_degree: int = 6, science=None, log=None) -> WidthMaps:
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
    shape : PrfShape, optional
        The assumed kernel; default the simulator's (order 4, half-width 0.5, sigma 0.3).
    smooth_degree : int
        Degree of the polynomial that each baseline's visibility follows.
    science : bool ndarray (row, col), optional
        Pixels the maps may cover; all by default.

    Raises
    ------
    ValueError
        No products; a direction (x or y) that no baseline's wavevector
        mostly follows is left NaN, not an error, unless neither has one.
    """
    if not products:
        raise ValueError("PRF widths need the metrology products of at least one baseline")
    shape = shape or PrfShape()
    names = sorted(products)
    first = products[names[0]]
    grid = first["iota"].shape
    valid = np.ones(grid, bool) if science is None else np.asarray(science, bool).copy()
    lnc, var, slopes = {}, {}, {}
    for name in names:
        p = products[name]
        with np.errstate(invalid="ignore", divide="ignore"):
            lnc[name] = np.log(p["alpha"].values / p["iota"].values)
        var[name] = log_contrast_variance(p, gain=gain, read_noise=read_noise)
        valid &= np.isfinite(lnc[name]) & np.isfinite(var[name]) & (var[name] > 0)
        kx, ky = float(p["kx"]), float(p["ky"])
        slopes[name] = (kx, ky, log_transfer_slope(abs(kx), shape), log_transfer_slope(abs(ky), shape))
    rows, cols = np.nonzero(valid)
    x, y = cols.astype(float), rows.astype(float)
    design = np.array([slopes[n][2:] for n in names])  # (baseline, 2): slopes along x, y
    along = np.array([abs(slopes[n][0]) >= abs(slopes[n][1]) for n in names])
    observed = np.array([along.any(), (~along).any()])
    if not observed.any():
        raise ValueError("no baseline to measure PRF widths with")
    r = np.stack([pixel_scale(lnc[n][valid], x, y, degree=smooth_degree) for n in names])  # (baseline, pixel)
    s2 = np.stack([var[n][valid] for n in names])
    a = design[:, observed]  # (baseline, direction)
    # Each baseline's gauge (fringes.fix_gauge) is fixed from noisy data: what is left of its mixing of
    # iota with the fringe factors is a ripple in the log-contrast at the first and second harmonics of
    # the pixel phase (measured: up to 0.7 sigma at 4000 frames). Those 4 patterns per baseline are fitted
    # with the widths, jointly: a width pattern that one baseline's ripple hides the others still see.
    harmonics = []
    for n in names:
        theta = products[n]["pixel_phase"].values[valid]
        harmonics.append(np.stack([pixel_scale(f(m * theta), x, y, degree=smooth_degree)
                                   for m in (1, 2) for f in (np.cos, np.sin)], axis=-1))  # (pixel, 4)
    n_b, n_h = len(names), 4
    nuisance = np.zeros((r.shape[1], n_b, n_b * n_h))
    for i in range(n_b):
        nuisance[:, i, i * n_h:(i + 1) * n_h] = harmonics[i]
    weights = 1 / s2.T  # (pixel, baseline)
    normal = np.einsum("bi,bj,pb->pij", a, a, weights)
    cov = np.linalg.inv(normal)
    # per pixel, the weighted projector off the width directions: Q = W - W A (A'WA)^-1 A'W
    wa = weights[:, :, None] * a[None]  # (pixel, baseline, direction)
    q = np.einsum("pb,bc->pbc", weights, np.eye(n_b)) - np.einsum("pbi,pij,pcj->pbc", wa, cov, wa)
    reduced = np.einsum("pbm,pbc,pcn->mn", nuisance, q, nuisance)
    if n_b > int(observed.sum()):
        coef = np.linalg.lstsq(reduced, np.einsum("pbm,pbc,cp->m", nuisance, q, r), rcond=1e-10)[0]
        r = r - np.einsum("pbm,m->bp", nuisance, coef)
    rhs = np.einsum("bi,bp->pi", a, r / s2)
    dv = np.einsum("pij,pj->pi", cov, rhs)
    fit = np.einsum("bi,pi->bp", a, dv)
    dof = len(names) - int(observed.sum())
    chi2 = float(np.mean(np.sum((r - fit) ** 2 / s2, axis=0)) / dof) if dof > 0 else float("nan")
    out = {}
    v0 = shape.width**2
    for j, axis in enumerate(("x", "y")):
        width, error = np.full(grid, np.nan), np.full(grid, np.nan)
        if observed[j]:
            col = int(np.sum(observed[:j]))
            deviation = pixel_scale(dv[:, col], x, y, degree=smooth_degree)  # exactly orthogonal to the smooth
            width[valid] = np.sqrt(v0 + deviation)
            error[valid] = np.sqrt(cov[:, col, col]) / (2 * width[valid])
        elif log is not None:
            log.warning("no baseline measures the PRF widths along %s: width_%s left NaN", axis, axis)
        out[axis] = (width, error)
    residual_rms = {n: float(np.sqrt(np.mean(r[i] ** 2))) for i, n in enumerate(names)}
    if log is not None:
        for n in names:
            log.info("%s: log-contrast slope per unit PRF variance %.3f along x, %.3f along y (pixel^-2); "
                     "pixel-scale rms %.2e", n, slopes[n][2], slopes[n][3], residual_rms[n])
        log.info("PRF widths: %d pixels, chi2 per dof %.3f between the baselines", valid.sum(), chi2)
    return WidthMaps(out["x"][0], out["y"][0], out["x"][1], out["y"][1], shape, slopes, chi2, residual_rms,
                     smooth_degree)


def prf_dataset(maps: WidthMaps) -> xr.Dataset:
    """The ``calibration/prf.nc`` product: width_x, width_y and their errors (row, col), pixel."""
    rc = ("row", "col")
    rows, cols = maps.width_x.shape
    names = sorted(maps.baselines)
    return xr.Dataset(
        {
            "width_x": (rc, maps.width_x, {"units": "pixel", "long_name": "PRF standard deviation along x"}),
            "width_y": (rc, maps.width_y, {"units": "pixel", "long_name": "PRF standard deviation along y"}),
            "error_width_x": (rc, maps.error_width_x,
                              {"units": "pixel", "long_name": "1-sigma photon-noise error of width_x"}),
            "error_width_y": (rc, maps.error_width_y,
                              {"units": "pixel", "long_name": "1-sigma photon-noise error of width_y"}),
            "log_contrast_slope_x": (("baseline",), [maps.baselines[n][2] for n in names],
                                     {"units": "pixel-2", "long_name": "d ln(contrast) / d(PRF variance along x)"}),
            "log_contrast_slope_y": (("baseline",), [maps.baselines[n][3] for n in names],
                                     {"units": "pixel-2", "long_name": "d ln(contrast) / d(PRF variance along y)"}),
            "pixel_scale_rms": (("baseline",), [maps.residual_rms[n] for n in names],
                                {"units": "1", "long_name": "rms of the baseline's pixel-scale log-contrast"}),
            "chi2": ((), maps.chi2, {"units": "1", "long_name": "mean chi^2 per degree of freedom between the "
                                                               "baselines' widths (NaN: none redundant)"}),
            "mean_width": ((), maps.shape.width, {"units": "pixel", "long_name": "width of the assumed kernel: the "
                                                                              "maps' mean"}),
        },
        coords={"row": np.arange(rows), "col": np.arange(cols), "baseline": names},
        attrs={"prf_order": maps.shape.order, "prf_half_width": maps.shape.half_width,
               "prf_sigma": maps.shape.sigma, "smooth_degree": maps.smooth_degree,
               "method": "pixel-scale log-contrast of each baseline, off a polynomial of smooth_degree, solved per "
                         "pixel for the PRF variance along x and y (docs/centroids.md, PRF widths)"},
    )
