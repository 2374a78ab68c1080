"""Error-propagation coefficients: Monte Carlo against linear propagation, linearity, axis conventions,
the fit on perfect stars, the table, its CSV and its figure (dice_core.error_budget)."""

import csv
import io

import numpy as np
import pytest

from dice_core import centroids, plotting
from dice_core import error_budget as eb

STAR = eb.Star()  # the simulator's star in electrons, the workflow's 15x15 windows
TRIALS = 400  # per-axis MC errors of 1.4-1.6% relative


@pytest.fixture(scope="module")
def runs():
    """One Monte Carlo per (source, weighting) at a mid-decade amplitude, fixed seeds."""
    amplitude = {"prnu": 1e-3, "photon": 1e-3, "offsets": 1e-3, "read": 1e-4}
    return {(s, w): eb.monte_carlo(s, amplitude[s], trials=TRIALS, seed=[7, i], weighting=w)
            for i, s in enumerate(eb.SOURCES) for w in eb.WEIGHTINGS}


@pytest.fixture(scope="module")
def sweeps():
    """Small sweeps (two amplitudes a decade apart, 40 trials) for the table and the figure."""
    amplitudes = {"prnu": (1e-4, 1e-3), "photon": (1e-4, 1e-3), "offsets": (1e-4, 1e-3), "read": (1e-5, 1e-4)}
    return [eb.sweep(s, amplitudes[s], trials=40, seed=3, grid=4) for s in eb.SOURCES]


def test_render_window_integrates_the_psf_over_each_pixels_displaced_area():
    x0, y0 = STAR.centre + 0.31, STAR.centre - 0.22
    window = STAR.window(x0, y0)
    image = eb.render_window(x0, y0, window=window, star=STAR)
    # the 15x15 window holds all but ~1e-7 of the flux (5.4 sigma each side at least)
    assert (image - STAR.background).sum() == pytest.approx(STAR.flux, rel=1e-6)
    # every pixel displaced by (d, e) records what the star moved by (-d, -e) gives the nominal pixel
    moved = eb.render_window(x0 - 0.2, y0 + 0.1, window=window, star=STAR)
    shifted = eb.render_window(x0, y0, window=window, star=STAR, dx=np.full(image.shape, 0.2),
                               dy=np.full(image.shape, -0.1))
    np.testing.assert_allclose(shifted, moved, rtol=1e-12, atol=1e-9)
    # sensitivities multiply the star's signal, not the background
    halved = eb.render_window(x0, y0, window=window, star=STAR, sensitivity=np.full(image.shape, 0.5))
    np.testing.assert_allclose(halved - STAR.background, 0.5 * (image - STAR.background), rtol=1e-12, atol=1e-9)
    # the analytic gradient against a centred finite difference of one pixel's offset
    gx, gy = eb.pixel_gradient(x0, y0, window=window, star=STAR)
    h, zero = 1e-6, np.zeros(image.shape)
    fd_x = (eb.render_window(x0, y0, window=window, star=STAR, dx=zero + h)
            - eb.render_window(x0, y0, window=window, star=STAR, dx=zero - h))
    fd_y = (eb.render_window(x0, y0, window=window, star=STAR, dy=zero + h)
            - eb.render_window(x0, y0, window=window, star=STAR, dy=zero - h))
    np.testing.assert_allclose(gx, fd_x / (2 * h), rtol=1e-5, atol=1e-6 * np.abs(gx).max())
    np.testing.assert_allclose(gy, fd_y / (2 * h), rtol=1e-5, atol=1e-6 * np.abs(gy).max())


@pytest.mark.parametrize("weighting", eb.WEIGHTINGS)
@pytest.mark.parametrize("source", eb.SOURCES)
def test_monte_carlo_agrees_with_the_linear_propagation(runs, source, weighting):
    run = runs[source, weighting]
    assert run.error / run.coefficient < 0.03  # a few percent
    predicted = eb.analytic(source, weighting=weighting)
    assert abs(run.coefficient - predicted.coefficient) < 3 * run.error
    assert abs(run.coefficient_2d - predicted.coefficient_2d) < 3 * run.error_2d


@pytest.mark.parametrize("source", eb.SOURCES)
def test_coefficient_is_independent_of_the_amplitude_over_a_decade(source):
    low = {"prnu": 1e-3, "photon": 1e-3, "offsets": 1e-3, "read": 1e-4}[source]
    # independent draws: agreement within the combined Monte Carlo errors
    a, b = (eb.monte_carlo(source, amp, trials=200, seed=[11, k]) for k, amp in enumerate((low, 10 * low)))
    assert abs(a.coefficient - b.coefficient) < 3 * np.hypot(a.error, b.error)
    # common random numbers (same seed): the ratio isolates the nonlinearity, far below the MC error
    c = eb.monte_carlo(source, 10 * low, trials=200, seed=[11, 0])
    assert c.coefficient / a.coefficient == pytest.approx(1, abs=0.01)


@pytest.mark.parametrize("source", eb.SOURCES)
def test_2d_coefficient_is_sqrt2_times_each_axis(runs, source):
    run = runs[source, "pipeline"]
    # each axis alone (x, then y) times sqrt(2) against the rms length of the error vector
    for axis, error in ((run.coefficient_x, run.error_x), (run.coefficient_y, run.error_y)):
        assert abs(run.coefficient_2d - np.sqrt(2) * axis) < 3 * np.hypot(run.error_2d, np.sqrt(2) * error)
    assert run.coefficient_2d == pytest.approx(np.hypot(run.coefficient_x, run.coefficient_y), rel=1e-12)
    assert run.coefficient_2d == pytest.approx(np.sqrt(2) * run.coefficient, rel=1e-12)


@pytest.mark.parametrize("weighting, floor", [("uniform", 1e-7), ("pipeline", 1e-6)])
def test_zero_amplitude_gives_zero_error(weighting, floor):
    for source in eb.SOURCES:
        run = eb.monte_carlo(source, 0.0, trials=20, seed=5, weighting=weighting)
        # the fit on perfect stars: unbiased to 2e-8 pixel unweighted, 3e-7 pixel weighted (the sampled
        # Gaussian's mismatch with the pixel-integrated PSF, weighted in an off-centre window)
        assert run.rms < floor and np.isnan(run.coefficient)
    # while the smallest default amplitudes make errors of 1e-5 pixel at least
    assert eb.monte_carlo("read", 1e-5, trials=20, seed=5, weighting=weighting).rms > 5e-6


def test_the_propagation_is_the_fisher_bound_where_the_fit_is_maximum_likelihood():
    # read noise: uniform variance, so the unweighted fit is the ML one
    assert eb.analytic("read", weighting="uniform").coefficient == pytest.approx(
        eb.cramer_rao_coefficient("read"), rel=1e-9)
    # photon noise alone: the pipeline's weights are then 1 / sqrt(I_p), its inverse variances
    dark = eb.Star(background=0.0, read_noise=0.0)
    assert eb.analytic("photon", star=dark).coefficient == pytest.approx(
        eb.cramer_rao_coefficient("photon", star=dark), rel=1e-9)
    # and the project's own bound for the same star and noise agrees (photon noise of gain 1 / (a^2 I_peak))
    window = dark.window(dark.centre, dark.centre)
    image = eb.render_window(dark.centre, dark.centre, window=window, star=dark)
    fit = centroids.gaussian_fit(image, window, weights=1 / np.sqrt(image))
    bound = centroids.cramer_rao(fit, window, gain=1 / image.max(), read_noise=1e-3)  # > 0: no empty pixel
    assert bound == pytest.approx(eb.cramer_rao_coefficient("photon", star=dark, grid=1), rel=1e-5)
    # elsewhere the fit is above the bound: photon noise through the unweighted fit
    assert eb.analytic("photon", weighting="uniform").coefficient > 1.2 * eb.cramer_rao_coefficient("photon")
    with pytest.raises(ValueError, match="no Fisher bound"):
        eb.cramer_rao_coefficient("offsets")


def test_unweighted_prnu_coefficient_is_one_over_sqrt_2pi():
    """Well-sampled limit of sum g_p^2 S_p^2 for a Gaussian: 1 / sqrt(2 pi), whatever its width."""
    for sigma in (1.3, 2.0):
        assert eb.analytic("prnu", star=eb.Star(psf_sigma=sigma), weighting="uniform", grid=4).coefficient == \
            pytest.approx(1 / np.sqrt(2 * np.pi), rel=0.01)


def test_monte_carlo_is_seeded_and_checks_its_arguments():
    a, b = (eb.monte_carlo("prnu", 1e-3, trials=5, seed=9) for _ in range(2))
    np.testing.assert_array_equal(a.ex, b.ex)
    assert not np.array_equal(a.ex, eb.monte_carlo("prnu", 1e-3, trials=5, seed=10).ex)
    with pytest.raises(ValueError, match="unknown error source"):
        eb.monte_carlo("dust", 1e-3, trials=2)
    with pytest.raises(ValueError, match="unknown weighting"):
        eb.analytic("prnu", weighting="optimal")


def test_table_rows_and_csv(sweeps):
    rows = eb.error_propagation_table(sweeps)
    assert [r["source"] for r in rows] == list(eb.SOURCES)
    for row, sw in zip(rows, sweeps):
        assert row["coefficient"] == sw.coefficient and row["analytic"] == sw.prediction.coefficient
        assert row["requirement_for_5e-6"] == pytest.approx(5e-6 / row["coefficient"])
        assert row["paper_coefficient"] == eb.PAPER_COEFFICIENTS[row["source"]]
        ratio = row["paper_coefficient"] / row["coefficient"]
        assert row["paper_ratio_per_axis"] == pytest.approx(ratio)
        analytic = row["paper_coefficient"] / row["analytic"]  # the label follows the noiseless analytic value
        expected = ("per-axis" if abs(analytic - 1) <= 0.1 else "2-D" if abs(analytic / np.sqrt(2) - 1) <= 0.1
                    else "neither")
        assert row["convention_matching_paper"].startswith(expected + " (analytic: ")
    assert rows[0]["paper_requirement"] == 1.2e-5 and rows[2]["paper_requirement"] == 2e-5
    assert rows[1]["paper_requirement"] is None and rows[0]["cramer_rao"] is None and rows[3]["cramer_rao"] > 0
    text = eb.error_propagation_csv(rows)
    assert text.splitlines()[0].startswith("source,normalisation,coefficient,error,paper_coefficient,")
    parsed = list(csv.DictReader(io.StringIO(text)))
    assert [r["source"] for r in parsed] == list(eb.SOURCES)
    assert parsed[1]["normalisation"] == eb.NORMALISATIONS["photon"]  # its commas quoted
    assert float(parsed[3]["coefficient"]) == pytest.approx(rows[3]["coefficient"], rel=1e-6)
    assert parsed[1]["paper_requirement"] == ""


def test_csv_writer_makes_the_tables_folder(sweeps, tmp_path):
    path = eb.write_error_propagation_csv(eb.error_propagation_table(sweeps), tmp_path / "tables" /
                                          "error_propagation.csv")
    assert path.is_file() and len(path.read_text().splitlines()) == 1 + len(eb.SOURCES)


def test_figure_plots_each_sources_points_analytic_and_paper_lines(sweeps):
    from matplotlib.container import ErrorbarContainer

    from dice_core.plotting import plt

    fig = plotting.error_propagation_figure(sweeps)
    try:
        axes = [ax for ax in fig.axes if ax.get_visible()]
        assert len(axes) == len(sweeps)
        for ax, sw in zip(axes, sweeps):
            assert ax.get_xscale() == "log" and ax.get_yscale() == "log" and ax.get_title() == sw.source
            points = [c for c in ax.containers if isinstance(c, ErrorbarContainer)]
            assert len(points) == 1 and points[0].get_label().startswith(f"{sw.weighting} fit, MC")
            x, y = points[0].lines[0].get_data()
            np.testing.assert_allclose(x, sw.amplitudes)
            np.testing.assert_allclose(y, [r.rms for r in sw.runs], rtol=1e-12)
            lines = {line.get_label().split(" (")[0]: line for line in ax.get_lines()}
            for name, coefficient, style in ((f"{sw.weighting} fit, analytic", sw.prediction.coefficient, "-"),
                                             ("paper", eb.PAPER_COEFFICIENTS[sw.source], "--")):
                xs, ys = lines[name].get_data()
                np.testing.assert_allclose(ys / xs, coefficient, rtol=1e-12)
                assert lines[name].get_linestyle() == style
            assert lines[f"{sw.weighting} fit, analytic"].get_color() == points[0].lines[0].get_color()
        assert len({ax.get_lines()[0].get_color() for ax in axes}) == len(sweeps)  # one colour per source
    finally:
        plt.close(fig)
