"""Error-propagation coefficients of the pseudo-star centroids: Monte Carlo and linear propagation.

Paper: table "Pseudo stars simulation results". Each error source is
injected alone into simulated star windows, the windows are fitted with the
pipeline's Gaussian centroid fit (:func:`dice_core.centroids.gaussian_fit`,
weighted as ``measure_positions`` weights it), and the centroid is compared
with the true position (no Procrustes). The coefficient is the centroid
error per unit of the source, in the source's normalisation:

========  =====================================================================
source    amplitude (what one unit of the source is)
========  =====================================================================
prnu      rms relative pixel sensitivity: pixel p responds 1 + a n_p (mean 1)
photon    relative photon noise of the brightest pixel, a = 1 / sqrt(peak e-);
          every pixel Gaussian with variance a^2 I_peak I_p (Poisson-like)
offsets   pixel: each pixel's true centre displaced by (dx, dy), each N(0, a^2)
read      read noise relative to the brightest pixel: additive Gaussian of
          sd a I_peak, the same for all pixels
========  =====================================================================

(n_p standard normal, independent between pixels.) Units: pixel for
positions and offsets; signals in electrons (equivalently adu at unit gain).
Only the pipeline weights depend on the star's flux, background and read
noise (:class:`Star`, in electrons); with ``weighting="uniform"`` every
coefficient is independent of the flux.

Axis convention: the *per-axis* coefficient is the rms of one coordinate's
error, sqrt(mean(ex^2 + ey^2) / 2) / a; the *2-D* coefficient is the rms of
the error's length, sqrt(mean(ex^2 + ey^2)) / a, sqrt(2) larger for an
isotropic error. Both are reported, with which of them (if either) matches
the paper's value.

- :func:`render_window`: a pixel-integrated Gaussian PSF (erf differences over
  each pixel's, possibly displaced, area) times per-pixel sensitivities, plus
  a background.
- :func:`monte_carlo`: seeded trials at one amplitude, random sub-pixel truth.
- :func:`analytic`: linear propagation through the least-squares fit,
  averaged over sub-pixel positions; :func:`cramer_rao_coefficient`: the
  Fisher bound of the same model, for comparison.
- :func:`sweep`, :func:`error_propagation_table`, :func:`error_propagation_csv`: the
  paper's table (its figure is :func:`dice_core.plotting.error_propagation_figure`).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dice_core import centroids

__all__ = [
    "SOURCES",
    "WEIGHTINGS",
    "NORMALISATIONS",
    "SOURCE_UNITS",
    "PAPER_COEFFICIENTS",
    "PAPER_REQUIREMENTS",
    "REQUIRED_ERROR",
    "DEFAULT_AMPLITUDES",
    "CSV_COLUMNS",
    "Star",
    "star_grid",
    "render_window",
    "pixel_gradient",
    "fit_weights",
    "MonteCarlo",
    "monte_carlo",
    "Analytic",
    "analytic",
    "cramer_rao_coefficient",
    "Sweep",
    "sweep",
    "error_propagation_table",
    "combined_table",
    "error_propagation_csv",
    "write_error_propagation_csv",
]

SOURCES = ("prnu", "photon", "offsets", "read")
WEIGHTINGS = ("pipeline", "uniform")
NORMALISATIONS = {
    "prnu": "rms relative pixel sensitivity; mean sensitivity 1 (pixel p responds 1 + sigma n_p)",
    "photon": "relative photon noise of the brightest pixel, 1/sqrt(peak electrons); variance of pixel p "
              "sigma^2 I_peak I_p",
    "offsets": "rms of each pixel's centre displacement dx and dy (each N(0, sigma^2)), pixel",
    "read": "read noise relative to the brightest pixel's value; additive, sd sigma I_peak for every pixel",
}
SOURCE_UNITS = {"prnu": "1", "photon": "1", "offsets": "pixel", "read": "1"}
PAPER_COEFFICIENTS = {"prnu": 0.40, "photon": 0.55, "offsets": 0.25, "read": 1.8}
PAPER_REQUIREMENTS = {"prnu": 1.2e-5, "offsets": 2e-5}  # for a 5e-6 pixel centroid error
REQUIRED_ERROR = 5e-6  # pixel, the paper's centroid error budget
# Decades of the linear regime: the smallest errors (~1e-5 pixel) well above the fit's own bias on a
# perfect star (~3e-7 pixel weighted, ~2e-8 unweighted), the largest still linear to 1e-3.
DEFAULT_AMPLITUDES = {"prnu": (1e-4, 1e-3, 1e-2), "photon": (1e-4, 1e-3, 1e-2),
                      "offsets": (1e-4, 1e-3, 1e-2), "read": (1e-5, 1e-4, 1e-3)}
CSV_COLUMNS = ("source", "normalisation", "coefficient", "error", "paper_coefficient", "coefficient_2d",
               "error_2d", "coefficient_x", "coefficient_y", "analytic", "analytic_2d", "cramer_rao",
               "convention_matching_paper", "paper_ratio_per_axis", "paper_ratio_2d", "requirement_for_5e-6",
               "paper_requirement", "source_units", "coefficient_units", "weighting", "amplitudes", "coefficient_by_amplitude",
               "trials")
#: The columns a second weighting adds to a row of :func:`combined_table` (suffixed by its name).
SECOND_WEIGHTING_COLUMNS = ("coefficient", "error", "coefficient_2d", "analytic", "convention_matching_paper",
                            "requirement_for_5e-6")


def _check(source, weighting="pipeline"):
    if source not in SOURCES:
        raise ValueError(f"unknown error source {source!r}; sources are {', '.join(SOURCES)}")
    if weighting not in WEIGHTINGS:
        raise ValueError(f"unknown weighting {weighting!r}; weightings are {', '.join(WEIGHTINGS)}")


@dataclass(frozen=True)
class Star:
    """The pseudo star of the error budget: PSF and window of the workflow, photometry in electrons.

    ``psf_sigma`` (pixel, the simulator's ``stars.psf_sigma``) and
    ``half_size`` (windows of 2 half_size + 1 pixels, the workflow's
    ``centroids.half_size``) fix the geometry. ``flux`` (total electrons of
    the star at sensitivity 1), ``background`` (electrons per pixel, added
    after the sensitivities, as the simulator adds it) and ``read_noise``
    (electrons) are the simulator's defaults (2.5e5 adu, 10 adu and 4 adu at
    10 e-/adu); they set the pipeline's fit weights
    1 / sqrt(I_p + read_noise^2) and the background level, not the injected
    noise, whose size is the source's amplitude.
    """

    psf_sigma: float = 1.3
    half_size: int = 7
    flux: float = 2.5e6
    background: float = 100.0
    read_noise: float = 40.0

    @property
    def size(self) -> int:
        return 2 * self.half_size + 1

    @property
    def centre(self) -> int:
        """The (integer) pixel the windows sit on: true positions are within half a pixel of it."""
        return self.half_size + 1

    @property
    def shape(self) -> tuple[int, int]:
        """A detector just large enough for the windows, rows and cols."""
        return (2 * self.centre + 1,) * 2

    def window(self, x0: float, y0: float) -> centroids.Window:
        """The pipeline's window for a star at (x0, y0) pixel (:func:`dice_core.centroids.star_window`)."""
        return centroids.star_window(y0, x0, half_size=self.half_size, shape=self.shape, label="error-budget star")


def star_grid(n: int, star: Star = Star()) -> np.ndarray:
    """n x n true positions (x, y), pixel, at the midpoints of a grid over the centre pixel: (n^2, 2)."""
    phase = (np.arange(n) + 0.5) / n - 0.5
    u, v = np.meshgrid(phase, phase)
    return star.centre + np.column_stack([u.ravel(), v.ravel()])


def _interval(a, b):
    """Standard normal probability of [a, b], accurate in both tails (a < b)."""
    from scipy.special import ndtr

    return np.where(a > 0, ndtr(-a) - ndtr(-b), ndtr(b) - ndtr(a))


def render_window(x0: float, y0: float, *, window: centroids.Window, star: Star = Star(), sensitivity=None,
                  dx=None, dy=None) -> np.ndarray:
    """A star window: pixel-integrated Gaussian PSF x sensitivities + background, electrons.

    Pixel (row, col) has its nominal centre at (col, row) (the window's
    :meth:`~dice_core.centroids.Window.grid`) and, displaced by its offset,
    integrates the PSF over the unit square centred on (col + dx, row + dy):
    flux x [Phi((x + dx + 1/2 - x0)/s) - Phi((x + dx - 1/2 - x0)/s)] x [the same
    along y], s = ``star.psf_sigma``, times its sensitivity; then the
    background (electrons per pixel) is added.

    Parameters
    ----------
    x0, y0 : float
        True position, pixel (detector coordinates).
    window : Window
    star : Star
    sensitivity, dx, dy : ndarray (size, size), optional
        Relative sensitivities (1 if omitted) and pixel offsets (pixel, 0 if omitted).

    Returns
    -------
    ndarray (size, size), electrons
    """
    xg, yg = window.grid()
    if dx is not None:
        xg = xg + dx
    if dy is not None:
        yg = yg + dy
    s = star.psf_sigma
    signal = star.flux * _interval((xg - 0.5 - x0) / s, (xg + 0.5 - x0) / s) * _interval(
        (yg - 0.5 - y0) / s, (yg + 0.5 - y0) / s)
    if sensitivity is not None:
        signal = signal * sensitivity
    return signal + star.background


def pixel_gradient(x0: float, y0: float, *, window: centroids.Window, star: Star = Star()):
    """d(value)/d(dx) and d(value)/d(dy) of each pixel of :func:`render_window`, electrons per pixel of offset."""
    xg, yg = window.grid()
    s = star.psf_sigma
    phi = lambda t: np.exp(-0.5 * t * t) / np.sqrt(2 * np.pi)  # noqa: E731
    ix = _interval((xg - 0.5 - x0) / s, (xg + 0.5 - x0) / s)
    iy = _interval((yg - 0.5 - y0) / s, (yg + 0.5 - y0) / s)
    dix = (phi((xg + 0.5 - x0) / s) - phi((xg - 0.5 - x0) / s)) / s
    diy = (phi((yg + 0.5 - y0) / s) - phi((yg - 0.5 - y0) / s)) / s
    return star.flux * dix * iy, star.flux * ix * diy


def fit_weights(image: np.ndarray, star: Star = Star(), *, weighting: str = "pipeline"):
    """The weights (1 / sigma per pixel) the fit is given, or None for an unweighted fit.

    ``"pipeline"``: the Gaussian method's weights in ``measure_positions``,
    photon plus read noise of the window itself (the pipeline's own
    ``_noise_variance``, at unit gain, electrons); ``"uniform"``: none.
    """
    _check(SOURCES[0], weighting)
    if weighting == "uniform":
        return None
    return 1.0 / np.sqrt(centroids._noise_variance(image, 1, 1.0, star.read_noise))


def _perturbed(source, amplitude, x0, y0, window, star, normals):
    """The window with the source injected at ``amplitude``; ``normals`` (2, size, size) standard normal."""
    if source == "prnu":
        return render_window(x0, y0, window=window, star=star, sensitivity=1 + amplitude * normals[0])
    if source == "offsets":
        return render_window(x0, y0, window=window, star=star, dx=amplitude * normals[0], dy=amplitude * normals[1])
    image = render_window(x0, y0, window=window, star=star)
    peak = image.max()
    if source == "photon":
        return image + amplitude * np.sqrt(peak * np.clip(image, 0, None)) * normals[0]
    return image + amplitude * peak * normals[0]  # read


def _rms_coefficient(q, amplitude):
    """(rms, its 1-sigma error), from the per-trial squared errors q (pixel^2), as coefficients if amplitude > 0.

    The error is the delta method's, 0.5 sd(q) / (sqrt(n) mean(q)) relative:
    it allows for the error's variance changing with sub-pixel phase (a
    kurtosis above the normal's) and for correlated x and y, and is
    1 / sqrt(2 n) for n independent normal errors.
    """
    q = np.asarray(q, float)
    mean = q.mean()
    rms = np.sqrt(mean)
    relative = 0.5 * q.std(ddof=1) / np.sqrt(q.size) / mean if mean > 0 else np.nan
    scale = amplitude if amplitude > 0 else 1.0
    return rms / scale, rms * relative / scale


@dataclass(frozen=True)
class MonteCarlo:
    """Centroid errors of :func:`monte_carlo`: truth and errors (trials,), pixel.

    Coefficients are rms error / amplitude (pixel per unit of the source);
    ``error*`` their 1-sigma Monte Carlo errors. At zero amplitude they are
    NaN, and ``rms`` (pixel) is the fit's own error on perfect stars.
    """

    source: str
    amplitude: float
    weighting: str
    x: np.ndarray
    y: np.ndarray
    ex: np.ndarray
    ey: np.ndarray

    @property
    def trials(self) -> int:
        return self.ex.size

    def _coefficient(self, q):
        value, error = _rms_coefficient(q, self.amplitude)
        return (value, error) if self.amplitude > 0 else (np.nan, np.nan)

    @property
    def rms(self) -> float:
        """Per-axis rms error, pixel: sqrt(mean(ex^2 + ey^2) / 2)."""
        return float(np.sqrt(np.mean((self.ex**2 + self.ey**2) / 2)))

    @property
    def rms_2d(self) -> float:
        """rms of the error's length, pixel: sqrt(mean(ex^2 + ey^2))."""
        return float(np.sqrt(np.mean(self.ex**2 + self.ey**2)))

    @property
    def coefficient(self) -> float:
        """Per-axis coefficient, sqrt(mean(ex^2 + ey^2) / 2) / amplitude."""
        return self._coefficient((self.ex**2 + self.ey**2) / 2)[0]

    @property
    def error(self) -> float:
        return self._coefficient((self.ex**2 + self.ey**2) / 2)[1]

    @property
    def coefficient_x(self) -> float:
        return self._coefficient(self.ex**2)[0]

    @property
    def error_x(self) -> float:
        return self._coefficient(self.ex**2)[1]

    @property
    def coefficient_y(self) -> float:
        return self._coefficient(self.ey**2)[0]

    @property
    def error_y(self) -> float:
        return self._coefficient(self.ey**2)[1]

    @property
    def coefficient_2d(self) -> float:
        """rms of sqrt(ex^2 + ey^2) / amplitude."""
        return self._coefficient(self.ex**2 + self.ey**2)[0]

    @property
    def error_2d(self) -> float:
        return self._coefficient(self.ex**2 + self.ey**2)[1]


def monte_carlo(source: str, amplitude: float, *, trials: int = 400, seed=0, star: Star = Star(),
                weighting: str = "pipeline") -> MonteCarlo:
    """Centroid errors with one error source injected at ``amplitude``, against the true positions.

    Each trial draws a true position uniform over the centre pixel, and two
    standard-normal fields over the window (the offsets use both, dx and
    dy; the other sources the first), scales them by ``amplitude`` in the
    source's normalisation (module docstring; photon noise is its Gaussian
    limit), renders the window (:func:`render_window`, electrons), and fits
    it with :func:`dice_core.centroids.gaussian_fit` in the pipeline's
    window (:func:`dice_core.centroids.star_window`), weighted as
    ``weighting`` says (:func:`fit_weights`, computed from the perturbed
    window as the pipeline computes them).

    The draws depend only on ``seed`` and ``trials`` (a
    ``numpy.random.default_rng(seed)``), not on the source or amplitude:
    the same seed at two amplitudes gives common random numbers, so that
    their ratio isolates the nonlinearity.

    Parameters
    ----------
    source : {"prnu", "photon", "offsets", "read"}
    amplitude : float
        In the source's normalisation (pixel for offsets, relative otherwise); 0 for the fit's own error.
    trials : int
    seed : int or sequence of int
    star : Star
    weighting : {"pipeline", "uniform"}

    Returns
    -------
    MonteCarlo
    """
    _check(source, weighting)
    rng = np.random.default_rng(seed)
    phases = rng.uniform(-0.5, 0.5, size=(trials, 2))
    normals = rng.standard_normal((trials, 2, star.size, star.size))
    truth = star.centre + phases
    windows = [star.window(x0, y0) for x0, y0 in truth]
    images = np.array([_perturbed(source, amplitude, x0, y0, window, star, normals[k])
                       for k, ((x0, y0), window) in enumerate(zip(truth, windows))])
    weights = None if weighting == "uniform" else np.array([fit_weights(image, star, weighting=weighting)
                                                              for image in images])
    fits = centroids.gaussian_fits(images, windows, weights=weights)  # all trials in one fit: its overhead once
    errors = np.array([[fit.x, fit.y] for fit in fits]) - truth
    return MonteCarlo(source, float(amplitude), weighting, truth[:, 0], truth[:, 1], errors[:, 0], errors[:, 1])


def _propagation(x0, y0, star, weighting):
    """Rows x, y of (J^T W J)^-1 J^T W at the best fit of the perfect window, each (pixel,), and that window."""
    window = star.window(x0, y0)
    image = render_window(x0, y0, window=window, star=star)
    weights = fit_weights(image, star, weighting=weighting)
    fit = centroids.gaussian_fit(image, window, weights=weights)
    xg, yg = window.grid()
    jacobian = centroids._gaussian_model(fit.params, xg.ravel(), yg.ravel())[1]  # the fit's own model
    w2 = np.ones(image.size) if weights is None else weights.ravel() ** 2
    gain = np.linalg.solve(jacobian.T @ (w2[:, None] * jacobian), jacobian.T * w2)
    return gain[2], gain[3], window, image


def _pixel_variance(source, x0, y0, window, image, star):
    """Each pixel's variance per unit amplitude^2 (electrons^2; independent pixels), (pixel,)."""
    if source == "prnu":
        return ((image - star.background) ** 2).ravel()
    if source == "photon":
        return (image.max() * np.clip(image, 0, None)).ravel()
    if source == "read":
        return np.full(image.size, image.max() ** 2)
    gx, gy = pixel_gradient(x0, y0, window=window, star=star)
    return (gx**2 + gy**2).ravel()


@dataclass(frozen=True)
class Analytic:
    """Predicted coefficients (pixel per unit of the source), averaged over the sub-pixel grid."""

    source: str
    weighting: str
    coefficient_x: float
    coefficient_y: float

    @property
    def coefficient(self) -> float:
        """Per axis: sqrt((var_x + var_y) / 2) per unit amplitude."""
        return float(np.sqrt((self.coefficient_x**2 + self.coefficient_y**2) / 2))

    @property
    def coefficient_2d(self) -> float:
        """Of the error's length: sqrt(var_x + var_y) per unit amplitude."""
        return float(np.hypot(self.coefficient_x, self.coefficient_y))


def analytic(source: str, *, star: Star = Star(), weighting: str = "pipeline", grid: int = 8) -> Analytic:
    """Linear error propagation through the pipeline's least-squares Gaussian fit.

    At the best fit p of the perfect window (no perturbation), a small
    perturbation dI of the pixels moves the parameters by
    dp = (J^T W J)^-1 J^T W dI, J the Jacobian (pixel, 7) of the fitted
    Gaussian model wrt its parameters and W the diagonal of the squared fit
    weights (1 for ``"uniform"``, the pipeline's 1 / (I_p + read_noise^2)
    otherwise). With g_x the x row of that matrix, var(x) = sum_p g_x,p^2 C_p
    for the source's independent pixel variances C_p per unit amplitude^2:

    - prnu: S_p^2 (S_p the star's signal in the pixel, electrons);
    - photon: I_peak I_p (I_p the pixel's value);
    - offsets: |grad I_p|^2 = (dI_p/ddx)^2 + (dI_p/ddy)^2, dx and dy independent;
    - read: I_peak^2.

    The variances are averaged over a ``grid`` x ``grid`` grid of true
    positions over the centre pixel (:func:`star_grid`): the expectation the
    Monte Carlo's uniform positions estimate. Where the weights are the
    source's inverse variances (the fit is then its maximum-likelihood
    estimator: uniform weights for read noise; the pipeline's weights for
    photon noise of a star without read noise or background) this equals the
    Cramer-Rao bound of the model's Fisher matrix J^T C^-1 J
    (:func:`cramer_rao_coefficient`); otherwise it is above it. The
    Gauss-Newton form neglects the fit residual's curvature term (the
    Gaussian sampled at pixel centres against the pixel-integrated PSF, a
    few 1e-3 of the peak).

    Returns
    -------
    Analytic
        Coefficients in pixel per unit of the source's normalisation.
    """
    _check(source, weighting)
    var = np.zeros(2)
    positions = star_grid(grid, star)
    for x0, y0 in positions:
        gx, gy, window, image = _propagation(x0, y0, star, weighting)
        c = _pixel_variance(source, x0, y0, window, image, star)
        var += np.array([gx**2 @ c, gy**2 @ c])
    var /= len(positions)
    return Analytic(source, weighting, float(np.sqrt(var[0])), float(np.sqrt(var[1])))


def cramer_rao_coefficient(source: str, *, star: Star = Star(), grid: int = 8) -> float:
    """The Cramer-Rao bound per axis, pixel per unit amplitude, of the fitted 7-parameter model.

    sqrt of the mean over the sub-pixel grid of (F^-1_xx + F^-1_yy) / 2, with
    F = J^T C^-1 J the Fisher matrix of the source's pixel variances C (see
    :func:`analytic`), J at the maximum-likelihood fit of the perfect window
    (weights C^-1/2). The lowest per-axis coefficient an unbiased estimator
    of that model reaches; the pipeline's fit reaches it where its weights
    are the source's inverse variances. Photon and read noise only: the
    PRNU's variance S_p^2 and the offsets' |grad I_p|^2 vanish in the
    window's wings (and the latter at the PSF's peak), where a pixel would
    then be noiseless, and the bound degenerate.
    """
    if source not in ("photon", "read"):
        raise ValueError(f"no Fisher bound for {source!r}: its pixel variance vanishes where the star's "
                         "signal (or gradient) does; photon and read noise only")
    total = 0.0
    positions = star_grid(grid, star)
    for x0, y0 in positions:
        window = star.window(x0, y0)
        image = render_window(x0, y0, window=window, star=star)
        c = _pixel_variance(source, x0, y0, window, image, star)
        fit = centroids.gaussian_fit(image, window, weights=1 / np.sqrt(c.reshape(image.shape)))
        xg, yg = window.grid()
        jacobian = centroids._gaussian_model(fit.params, xg.ravel(), yg.ravel())[1]
        inverse = np.linalg.inv(jacobian.T @ (jacobian / c[:, None]))
        total += (inverse[2, 2] + inverse[3, 3]) / 2
    return float(np.sqrt(total / len(positions)))


@dataclass(frozen=True)
class Sweep:
    """One source's Monte Carlo at several amplitudes, with its analytic prediction."""

    source: str
    weighting: str
    runs: tuple  # of MonteCarlo, by increasing amplitude
    prediction: Analytic
    cramer_rao: float | None = None
    star: Star = field(default_factory=Star)

    @property
    def amplitudes(self) -> np.ndarray:
        return np.array([r.amplitude for r in self.runs])

    def _pooled(self, kind):
        """Coefficient and error over every run: the rms of error / amplitude over all trials."""
        q = np.concatenate([{"axis": (r.ex**2 + r.ey**2) / 2, "2d": r.ex**2 + r.ey**2, "x": r.ex**2,
                             "y": r.ey**2}[kind] / r.amplitude**2 for r in self.runs])
        return _rms_coefficient(q, 1.0)

    @property
    def coefficient(self) -> float:
        return self._pooled("axis")[0]

    @property
    def error(self) -> float:
        return self._pooled("axis")[1]

    @property
    def coefficient_2d(self) -> float:
        return self._pooled("2d")[0]

    @property
    def error_2d(self) -> float:
        return self._pooled("2d")[1]

    @property
    def coefficient_x(self) -> float:
        return self._pooled("x")[0]

    @property
    def coefficient_y(self) -> float:
        return self._pooled("y")[0]


def sweep(source: str, amplitudes=None, *, trials: int = 400, seed: int = 0, star: Star = Star(),
          weighting: str = "pipeline", grid: int = 8) -> Sweep:
    """:func:`monte_carlo` at each amplitude (independent draws: seed (seed, source, k)) and :func:`analytic`.

    ``amplitudes`` default to :data:`DEFAULT_AMPLITUDES` (two decades).
    """
    _check(source, weighting)
    amplitudes = sorted(DEFAULT_AMPLITUDES[source] if amplitudes is None else amplitudes)
    if not all(a > 0 for a in amplitudes):
        raise ValueError(f"amplitudes must be positive, got {amplitudes}")
    runs = tuple(monte_carlo(source, a, trials=trials, seed=[seed, SOURCES.index(source), k], star=star,
                             weighting=weighting) for k, a in enumerate(amplitudes))
    bound = cramer_rao_coefficient(source, star=star, grid=grid) if source in ("photon", "read") else None
    return Sweep(source, weighting, runs, analytic(source, star=star, weighting=weighting, grid=grid), bound, star)


def _convention(coefficient, paper, tolerance):
    """Which of per-axis and 2-D matches the paper's value within ``tolerance`` (relative), and the ratios.

    ``coefficient`` is the analytic per-axis coefficient: it has no Monte Carlo noise, so the label does not
    flip between runs where a ratio sits near the edge (the offsets' per-axis ratio is 1.11).
    """
    ratios = {"per-axis": paper / coefficient, "2-D": paper / (np.sqrt(2) * coefficient)}
    best = min(ratios, key=lambda k: abs(np.log(ratios[k])))
    text = "; ".join(f"paper/{k} = {v:.2f}" for k, v in ratios.items())
    return (best if abs(ratios[best] - 1) <= tolerance else "neither") + f" (analytic: {text})", ratios


def error_propagation_table(sweeps=None, *, trials: int = 400, seed: int = 0, star: Star = Star(),
                            weighting: str = "pipeline", tolerance: float = 0.1) -> list[dict]:
    """The rows of the paper's table, one per source (:data:`CSV_COLUMNS`).

    ``coefficient``/``error``: per-axis Monte Carlo coefficient pooled over
    the sweep's amplitudes and its 1-sigma error; ``coefficient_2d``: the
    2-D one; ``analytic``/``analytic_2d``: :func:`analytic`; ``cramer_rao``:
    :func:`cramer_rao_coefficient` (photon and read noise; empty otherwise);
    ``convention_matching_paper``: "per-axis", "2-D" or "neither", the
    convention whose analytic coefficient is within ``tolerance``
    (relative) of the paper's, with both ratios paper / analytic (the
    analytic value, which the Monte Carlo agrees with within its error, has
    no noise to flip the label); ``paper_ratio_per_axis``,
    ``paper_ratio_2d``: paper / the Monte Carlo coefficients;
    ``requirement_for_5e-6``: the amplitude giving a 5e-6 pixel per-axis
    error (in the source's units, ``source_units``); ``paper_requirement``:
    the paper's (PRNU and offsets only). Coefficients are pixel per unit of
    the source's normalisation.

    ``sweeps`` (one :class:`Sweep` per source) are computed with the other
    arguments when omitted (4 sources x 3 amplitudes x ``trials`` fits).
    """
    if sweeps is None:
        sweeps = [sweep(s, trials=trials, seed=seed, star=star, weighting=weighting) for s in SOURCES]
    rows = []
    for sw in sweeps:
        paper = PAPER_COEFFICIENTS[sw.source]
        convention, _ = _convention(sw.prediction.coefficient, paper, tolerance)
        ratios = {"per-axis": paper / sw.coefficient, "2-D": paper / sw.coefficient_2d}
        rows.append({
            "source": sw.source,
            "normalisation": NORMALISATIONS[sw.source],
            "coefficient": sw.coefficient,
            "error": sw.error,
            "paper_coefficient": paper,
            "coefficient_2d": sw.coefficient_2d,
            "error_2d": sw.error_2d,
            "coefficient_x": sw.coefficient_x,
            "coefficient_y": sw.coefficient_y,
            "analytic": sw.prediction.coefficient,
            "analytic_2d": sw.prediction.coefficient_2d,
            "cramer_rao": sw.cramer_rao,
            "convention_matching_paper": convention,
            "paper_ratio_per_axis": ratios["per-axis"],
            "paper_ratio_2d": ratios["2-D"],
            "requirement_for_5e-6": REQUIRED_ERROR / sw.coefficient,
            "paper_requirement": PAPER_REQUIREMENTS.get(sw.source),
            "source_units": SOURCE_UNITS[sw.source],
            "coefficient_units": "pixel" if SOURCE_UNITS[sw.source] == "1" else f"pixel per {SOURCE_UNITS[sw.source]}",
            "weighting": sw.weighting,
            "amplitudes": ";".join(f"{a:g}" for a in sw.amplitudes),
            "coefficient_by_amplitude": ";".join(f"{r.coefficient:.4f}" for r in sw.runs),
            "trials": sum(r.trials for r in sw.runs),
        })
    return rows


def combined_table(sweeps, *, primary: str = "pipeline", tolerance: float = 0.1) -> list[dict]:
    """One row per source from sweeps of several weightings: the ``primary`` weighting's row
    (:func:`error_propagation_table`), with each other weighting's :data:`SECOND_WEIGHTING_COLUMNS`
    appended under ``<column>_<weighting>``."""
    sweeps = list(sweeps)
    weightings = [w for w in WEIGHTINGS if any(sw.weighting == w for sw in sweeps)]
    if primary not in weightings:
        raise ValueError(f"no sweep with the {primary!r} weighting among {weightings}")
    pairs = [(sw.source, sw.weighting) for sw in sweeps]
    if len(set(pairs)) != len(pairs):
        raise ValueError("more than one sweep for a (source, weighting): the table has one row per source, "
                         f"one value per weighting; got {pairs}")
    tables = {w: {row["source"]: row for row in error_propagation_table([sw for sw in sweeps if sw.weighting == w],
                                                                       tolerance=tolerance)}
              for w in weightings}
    rows = []
    for source, row in tables[primary].items():
        row = dict(row)
        for other in weightings:
            if other != primary and source in tables[other]:
                row.update({f"{c}_{other}": tables[other][source][c] for c in SECOND_WEIGHTING_COLUMNS})
        rows.append(row)
    return rows


def error_propagation_csv(rows) -> str:
    """Rows of :func:`error_propagation_table` or :func:`combined_table` as CSV text (:data:`CSV_COLUMNS`,
    then any further columns the rows share; floats to 7 digits, None empty)."""
    def text(value):
        if value is None:
            return ""
        return f"{value:.6e}" if isinstance(value, (float, np.floating)) else str(value)

    columns = list(CSV_COLUMNS) + [c for c in (rows[0] if rows else {}) if c not in CSV_COLUMNS]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([text(row.get(c)) for c in columns])
    return out.getvalue()


def write_error_propagation_csv(rows, path) -> Path:
    """Write :func:`error_propagation_csv` to ``path`` (e.g. ``tables/error_propagation.csv``) atomically,
    making its folder."""
    from dice_core.io import write_text

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text(path, error_propagation_csv(rows))
    return path
