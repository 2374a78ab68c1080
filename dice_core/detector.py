"""Pixel response model: one truncated hyper-Gaussian PRF per pixel (paper, "Data generation").

Each pixel's response to light at detector position (x, y), in pixel units, is

.. math::

    \\mathrm{PRF}(x, y) = s \\, g_{\\sigma_x}(x - x_0) \\, g_{\\sigma_y}(y - y_0), \\qquad
    g_\\sigma(u) = \\frac{\\exp[-|u|^n / (2\\sigma^n)]}{\\int_{-a}^{a} \\exp[-|v|^n / (2\\sigma^n)]\\,dv}
    \\ \\text{for}\\ |u| \\le a,

with sensitivity :math:`s` (the PRF's integral), true centre
:math:`(x_0, y_0) = (c + dx, r + dy)` (its barycentre, as the paper defines the
pixel offset), order :math:`n` and truncation half-width :math:`a`. The
pixel's width is the standard deviation of :math:`g`, derived from
:math:`\\sigma`. Each factor is symmetric about the true centre, so a plane
fringe :math:`\\sin(K\\cdot r + \\phi)` gives a pixel signal of phase exactly
:math:`K\\cdot(r_0) + \\phi`: the simulated truth is the offset metrology sees.

With sensitivity slopes (``slope_x``, ``slope_y``) each factor is multiplied by
:math:`1 + s u`: :math:`(x_0, y_0)` is then the kernel's centre, not its
barycentre (off by :math:`s w^2`, see :meth:`PixelResponse.barycentres`), and the
fringe phase is neither.

Integrals over the PRF use Gauss-Legendre quadrature on :math:`[-a, a]`, exact
to far below 1e-9 for these smooth kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PixelResponse", "hyper_gaussian_std"]

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(64)


def _kernel(u, sigma, order):
    return np.exp(-np.abs(u) ** order / (2.0 * sigma**order))


def _quadrature(half_width):
    return _NODES * half_width, _WEIGHTS * half_width


def hyper_gaussian_std(sigma, *, order: float, half_width: float):
    """Standard deviation (pixel) of the truncated hyper-Gaussian of scale ``sigma`` (pixel)."""
    u, w = _quadrature(half_width)
    sigma = np.asarray(sigma, dtype=float)[..., None]
    k = _kernel(u, sigma, order)
    return np.sqrt((w * k * u**2).sum(-1) / (w * k).sum(-1))


@dataclass
class PixelResponse:
    """Per-pixel PRF parameters of a detector, all (row, col) arrays.

    Attributes
    ----------
    sensitivity : ndarray
        Integral of each PRF, relative (mean 1 over the science area by convention).
    dx, dy : ndarray
        Pixel offsets, pixel: true centre of pixel (r, c) is (c + dx, r + dy).
    sigma_x, sigma_y : ndarray
        Hyper-Gaussian scale parameters, pixel.
    order : float
        Hyper-Gaussian order n (2 is a Gaussian; larger is flatter-topped).
    half_width : float
        Truncation half-width a, pixel.
    slope_x, slope_y : ndarray, optional
        Linear sensitivity slope across each pixel, 1/pixel: the PRF is the
        hyper-Gaussian times (1 + slope_x u)(1 + slope_y v), u, v from its
        centre (|slope| x half_width < 1, checked). An asymmetric response: its
        barycentre is off its centre by slope x width^2, and the phase of its
        response to a fringe is not that of its barycentre (it depends on the
        period). None: symmetric.
    """

    def __post_init__(self):
        for slope in (self.slope_x, self.slope_y):
            if slope is not None and np.any(np.abs(slope) * self.half_width >= 1):
                raise ValueError(f"PRF slopes of {np.max(np.abs(slope)):.2f} per pixel make a response negative "
                                 f"within the {self.half_width} pixel half-width")

    sensitivity: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    sigma_x: np.ndarray
    sigma_y: np.ndarray
    order: float = 4.0
    half_width: float = 0.5
    slope_x: np.ndarray | None = None
    slope_y: np.ndarray | None = None

    @property
    def shape(self):
        return self.sensitivity.shape

    def centres(self):
        """True pixel centres (x0, y0), pixel, each (row, col)."""
        rows, cols = np.indices(self.shape)
        return cols + self.dx, rows + self.dy

    def width_x(self):
        """Standard deviation of each PRF along x, pixel."""
        return hyper_gaussian_std(self.sigma_x, order=self.order, half_width=self.half_width)

    def width_y(self):
        """Standard deviation of each PRF along y, pixel."""
        return hyper_gaussian_std(self.sigma_y, order=self.order, half_width=self.half_width)

    def _transfer(self, k, sigma, slope=None):
        """Characteristic function of the normalised 1-D PRF at wavenumber k (rad/pixel; scalar or map).

        Real for a symmetric PRF; with a ``slope``, the kernel times (1 + slope u)
        adds i slope int(u sin(k u) kernel) / int(kernel).
        """
        u, w = _quadrature(self.half_width)
        kern = _kernel(u, sigma[..., None], self.order)
        ku = np.asarray(k, dtype=float)[..., None] * u
        norm = (w * kern).sum(-1)
        real = (w * kern * np.cos(ku)).sum(-1) / norm
        if slope is None:
            return real
        return real + 1j * slope * (w * kern * u * np.sin(ku)).sum(-1) / norm

    def barycentres(self):
        """Barycentres (x, y) of the PRFs, pixel, each (row, col): the centres, moved by slope x width^2."""
        x0, y0 = self.centres()
        if self.slope_x is not None:
            x0 = x0 + self.slope_x * self.width_x() ** 2
        if self.slope_y is not None:
            y0 = y0 + self.slope_y * self.width_y() ** 2
        return x0, y0

    def fringe_response(self, kx, ky, phase=None) -> np.ndarray:
        """Complex response R to the fringe exp(i Phi(r)); (row, col).

        The signal of a pixel under illumination ``1 + v sin(Phi(r) + phi)`` is
        ``sensitivity + v * Im(R * exp(i phi))``, with
        ``R = s h_x(kx) h_y(ky) exp(i Phi(r0))``: over a pixel the fringe is
        the plane wave of its local wavevector (kx, ky) = grad Phi at the
        kernel's centre r0, and h is the PRF's characteristic function
        int g(u) (1 + s u) exp(i k u) du (real without a slope).

        Parameters
        ----------
        kx, ky : float or ndarray (row, col)
            Wavevector, rad/pixel: one for plane waves, or each pixel's local one.
        phase : ndarray (row, col), optional
            Phi(r0) at each pixel's true centre, rad; ``kx x0 + ky y0`` (plane
            waves) if omitted.
        """
        if phase is None and (np.ndim(kx) or np.ndim(ky)):
            raise ValueError("a map of local wavevectors needs the phase map that goes with it")
        x0, y0 = self.centres()
        gain = (self.sensitivity * self._transfer(kx, self.sigma_x, self.slope_x)
                * self._transfer(ky, self.sigma_y, self.slope_y))
        return gain * np.exp(1j * (kx * x0 + ky * y0 if phase is None else phase))

    def gaussian_response(self, x, y, sigma, *, rows=None, cols=None) -> np.ndarray:
        """Fraction of a unit-flux circular Gaussian PSF collected by each pixel.

        Parameters
        ----------
        x, y : float
            PSF centre, pixel (x along columns, y along rows).
        sigma : float
            PSF standard deviation, pixel.
        rows, cols : slice, optional
            Restrict the computation to a window of the detector.

        Returns
        -------
        ndarray (row, col) over the window, sensitivity included.
        """
        sl = (rows or slice(None), cols or slice(None))
        x0, y0 = (c[sl] for c in self.centres())
        u, w = _quadrature(self.half_width)

        def factor(centre, scale, slope, star):
            kern = _kernel(u, scale[..., None], self.order)
            norm = (w * kern).sum(-1)  # the slope's odd term integrates to zero: the sensitivity stays
            if slope is not None:
                kern = kern * (1 + slope[..., None] * u)
            psf = np.exp(-0.5 * ((centre[..., None] + u - star) / sigma) ** 2) / (np.sqrt(2 * np.pi) * sigma)
            return (w * kern * psf).sum(-1) / norm

        slope_x = None if self.slope_x is None else self.slope_x[sl]
        slope_y = None if self.slope_y is None else self.slope_y[sl]
        return (self.sensitivity[sl] * factor(x0, self.sigma_x[sl], slope_x, x)
                * factor(y0, self.sigma_y[sl], slope_y, y))
