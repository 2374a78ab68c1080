"""The paper's experimental figures, built from small synthetic products: what each draws."""

import re

import matplotlib.colors
import numpy as np
import pytest
import xarray as xr

from dice_core import allan, astrometry, plotting
from dice_core.manifest import Detector
from test_allan import allan_inputs
from test_astrometry import centroid_datasets

USED = (3, 9)


@pytest.fixture
def residuals_product(rng):
    """A residuals product of 12 positions, 3-9 used, for two modes; and its centroid datasets."""
    datasets = centroid_datasets(rng)
    rows, residuals = astrometry.mode_accuracies(datasets, positions=USED, trials=50)
    return astrometry.residuals_dataset(datasets, rows, residuals=residuals), datasets


def lines(ax, gid):
    return [line for line in ax.get_lines() if line.get_gid() == gid]


def is_red(line):
    return matplotlib.colors.same_color(line.get_color(), "red")


def test_barycentre_paths_sit_in_the_downscaled_layout(residuals_product):
    """Right panels: each star's path offset by (its mean position - the pattern's) x scale, the scale
    making the layout span 3x the paths' largest extent; the corner stars' square at those offsets;
    the used positions circled in black; the central star black."""
    product, _ = residuals_product
    fig = plotting.barycentre_figure(product)
    for row, mode in enumerate(product["mode"].values):
        ax = fig.axes[2 * row + 1]
        residual = product["barycentre_residual"].sel(mode=mode).values
        star = np.column_stack([product["star_x"].sel(mode=mode), product["star_y"].sel(mode=mode)])
        centred = star - star.mean(axis=0)
        extent = np.max(residual.max(axis=0) - residual.min(axis=0))
        scale = 3 * extent / np.max(np.ptp(centred, axis=0))
        (square,) = lines(ax, "layout square")
        corners = square.get_xydata()
        assert len(corners) == 5 and np.array_equal(corners[0], corners[-1])  # closed
        np.testing.assert_allclose(np.sort(corners[:4], axis=0), np.sort(centred[1:] * scale, axis=0), rtol=1e-12)
        # the layout, downscaled, spans 3 times the residual paths
        assert np.max(np.ptp(corners, axis=0)) == pytest.approx(3 * extent, rel=1e-12)
        # the corners in order around the square (no diagonal): every side is horizontal or vertical
        sides = np.diff(corners, axis=0)
        assert np.all(np.min(np.abs(sides), axis=1) < 0.05 * np.max(np.abs(sides)))
        circled = lines(ax, "used positions")
        assert len(circled) == 5
        for s, line in enumerate(circled):
            assert len(line.get_xdata()) == USED[1] - USED[0] + 1
            assert matplotlib.colors.same_color(line.get_markeredgecolor(), "black")
            used = (product["all_position"].values >= USED[0]) & (product["all_position"].values <= USED[1])
            np.testing.assert_allclose(line.get_xydata(), residual[used, s] + centred[s] * scale, rtol=1e-12)
        # the central star (0, in the middle of the layout) black, in both panels
        paths = [line for line in ax.get_lines() if line.get_gid() is None]
        assert matplotlib.colors.same_color(paths[0].get_color(), "black")
        assert matplotlib.colors.same_color(fig.axes[2 * row].get_lines()[0].get_color(), "black")
        # in pixel, or a power of ten of the pixel that the tick labels are in
        assert re.search(r"\[(1e-?\d+ )?pixel\]", ax.get_xlabel()) and re.search(r"\[(1e-?\d+ )?pixel\]",
                                                                                  ax.get_ylabel())
    plotting.save(fig, None)


def test_barycentre_figure_of_a_product_without_star_positions(residuals_product):
    """An older product (no star_x, star_y): the paths centred, no layout drawn."""
    product, _ = residuals_product
    fig = plotting.barycentre_figure(product.drop_vars(["star_x", "star_y"]))
    assert not lines(fig.axes[1], "layout square") and len(lines(fig.axes[1], "used positions")) == 5
    plotting.save(fig, None)


def test_procrustes_sigma_lines_are_the_rms_of_the_residuals_shown(residuals_product):
    product, _ = residuals_product
    fig = plotting.procrustes_figure(product)
    for ax, mode in zip(fig.axes, product["mode"].values):
        sigma = np.sqrt(np.mean(product["residual"].sel(mode=mode).values ** 2))
        levels = sorted(line.get_ydata()[0] for line in lines(ax, "sigma"))
        np.testing.assert_allclose(levels, [-sigma, sigma], rtol=1e-12)
        accuracy = float(product["accuracy"].sel(mode=mode))
        assert f"{sigma:.2e}" in ax.get_title() and f"{accuracy:.2e}" in ax.get_title()
        assert len(ax.get_lines()) == 2 * 5 + 2  # x and y of each star, and the two sigma lines
    plotting.save(fig, None)


def central_centroids(rng, n_positions=12):
    """A centroids/<mode>.nc product with windows, precisions and limits."""
    ds = centroid_datasets(rng, n_positions, modes=("raw",))["raw"]
    shape = (n_positions, 5)
    ds["precision_x"] = ds["precision_y"] = (("position", "star"), np.full(shape, 1e-3))
    ds["photon_limit_x"] = ds["photon_limit_y"] = (("position", "star"), np.full(shape, 8e-4))
    ds["window"] = (("star", "window_row", "window_col"), rng.random((5, 7, 7)))
    return ds


@pytest.mark.parametrize("positions", [USED, None])
def test_centroids_figure_draws_the_used_positions_in_red(rng, positions):
    """x and y against the index and the path: as many red points as positions in the range, at the
    central star's coordinates."""
    ds = central_centroids(rng)
    fig = plotting.centroids_figure(ds, title="test", positions=positions)
    n_used = 12 if positions is None else positions[1] - positions[0] + 1
    used = slice(None) if positions is None else slice(positions[0] - 1, positions[1])
    red = [(ax, line) for ax in fig.axes for line in ax.get_lines() if is_red(line)]
    assert len(red) == 3  # x(index), y(index), the path
    x, y = ds["x"].values[:, 0], ds["y"].values[:, 0]  # star 0 is central
    for (ax, line), expected in zip(red, (x - x.mean(), y - y.mean())):
        assert line.get_gid() == "used positions" and len(line.get_xdata()) == n_used
        np.testing.assert_allclose(line.get_xdata(), ds["position"].values[used])
        np.testing.assert_allclose(line.get_ydata(), expected[used])
        assert "[pixel]" in ax.get_ylabel()
    ax, line = red[2]
    np.testing.assert_allclose(line.get_xydata(), np.column_stack([x, y])[used])
    assert ax.get_xlabel() == "x [pixel]" and ax.get_ylabel() == "y [pixel]"
    plotting.save(fig, None)


def test_allan_figure_draws_the_first_frame_limit_in_red(rng):
    args, keywords = allan_inputs(rng)
    ds = allan.allan_dataset(*args, **keywords, first_frame=rng.uniform(500, 3000, args[3].size))
    fig = plotting.allan_figure(ds, title="test")
    (ax,) = fig.axes
    (line,) = lines(ax, "first frame")
    assert is_red(line)
    np.testing.assert_allclose(line.get_xdata(), ds["n_frames"].values)
    np.testing.assert_allclose(line.get_ydata(), ds["photon_limit_pixel_first_frame"].values)
    assert "first frame" in line.get_label()
    assert [line for line in ax.get_lines() if is_red(line)] == [line]
    plotting.save(fig, None)
    # a product without it: no red line
    fig = plotting.allan_figure(ds.drop_vars(["photon_limit_pixel_first_frame", "first_frame_noise"]), title="t")
    assert not lines(fig.axes[0], "first frame")
    plotting.save(fig, None)


def test_the_reproduction_pdf_has_a_title_page_and_one_page_per_figure(tmp_path):
    import re

    from dice_core import plotting

    pngs = []
    for k in range(2):
        fig, ax = plotting.plt.subplots()
        ax.plot([0, 1], [k, 1 - k])
        pngs.append(tmp_path / f"figure_{k}.png")
        plotting.save(fig, pngs[-1])
    path = plotting.reproduction_pdf(tmp_path / "report" / "paper.pdf", [(p, "a caption " * 40) for p in pngs],
                                     title="test", summary_lines=["quantity paper ours"])
    data = path.read_bytes()
    assert data.startswith(b"%PDF") and len(re.findall(rb"/Type\s*/Page\b", data)) == 3
    assert not list((tmp_path / "report").glob(".*.part"))  # written through a temporary name


# What a reader of the paper needs: integer ticks for integer quantities, tick labels apart, symmetric
# limits where the data are centred, a unit after every number printed.

def metrology_product(rng, *, passes=2, side=12):
    """A metrology/<baseline>.nc-like dataset of ``passes`` passes (the convergence history from pass 2)."""
    detector = Detector(shape=(side, side), science_rows=(1, side - 1), science_cols=(1, side - 1), gain=2.5,
                        saturation=6e4)
    n_frames = 50
    iteration = np.arange(2, passes + 1)
    ds = xr.Dataset({
        "projected_offset": (("row", "col"), 1e-3 * rng.standard_normal((side, side))),
        "photon_noise_floor_rms": ((), 2.9e-4),
        "kx_frame": (("frame",), 1.5686 + 2e-5 * rng.standard_normal(n_frames)),
        "ky_frame": (("frame",), -0.0822 + 3e-5 * rng.standard_normal(n_frames)),
        "level": (("frame",), 1e4 + rng.standard_normal(n_frames)),
        "amplitude": (("frame",), 5e3 + rng.standard_normal(n_frames)),
        "max_change": (("iteration",), 10.0 ** -(6.0 + iteration)),
        "rms_change": (("iteration",), 10.0 ** -(6.5 + iteration)),
        "projected_offset_prnu_free_gauge": (("row", "col"), 1e-3 * rng.standard_normal((side, side))),
        "gauge_difference_rms": ((), 7.3e-5),
        "gauge_difference_floor": ((), 2.6e-4),
    }, coords={"frame": np.arange(n_frames), "iteration": iteration})
    return ds, detector


def texts(fig):
    """Every piece of text a reader sees: titles, axis labels, legends, annotations, figure texts."""
    found = [fig._suptitle] if fig._suptitle is not None else []
    found += list(fig.texts) + [text for legend in fig.legends for text in legend.get_texts()]
    for ax in fig.axes:
        found += [ax.title, ax._left_title, ax._right_title, ax.xaxis.label, ax.yaxis.label, *ax.texts]
        if ax.get_legend() is not None:
            found += ax.get_legend().get_texts()
    return [text.get_text() for text in found if text.get_text()]


UNITS = ("pixel", "adu", "rad/pixel", "mm", "frames", "e-/adu")
#: numbers that are ratios or exponents: a slope, a scale factor (x5.2e-04), a ratio, powers of ten in units
DIMENSIONLESS = re.compile(r"(slope|ratio|layout x)\s*[-+]?$")


def numbers_without_unit(text):
    """Decimal numbers (a point or an exponent) in ``text`` followed by no unit: counts and indices,
    integers, are exempt."""
    missing = []
    for match in re.finditer(r"[-+]?\d+\.\d*(?:e[-+]?\d+)?|[-+]?\d+e[-+]?\d+", text):
        after, before = text[match.end():].lstrip(" )["), text[:match.start()]
        if after.startswith(UNITS) or after.startswith("x ") or DIMENSIONLESS.search(before.rstrip(" =:")):
            continue
        if re.match(r"\s*\((x|y)\)", text[match.end():]) and "ratio" in before:
            continue
        missing.append(match.group())
    return missing


def test_numbers_without_unit_are_found():
    assert numbers_without_unit("photon floor 9.6e-05") == ["9.6e-05"]
    assert numbers_without_unit("x 22.999, y 20.230") == ["22.999", "20.230"]
    assert numbers_without_unit("rms 1.0e-3 pixel (3 passes), slope -0.64, layout x5.2e-04") == []


def integer_ticks(axis):
    """The tick positions of ``axis`` within its view."""
    low, high = sorted(axis.get_view_interval())
    return [t for t in axis.get_ticklocs() if low - 1e-9 <= t <= high + 1e-9]


def overlapping_labels(fig, axis):
    """Pairs of the axis's visible tick labels whose drawn boxes overlap."""
    renderer = fig.canvas.get_renderer()
    boxes = [label.get_window_extent(renderer) for label in axis.get_ticklabels(which="both")
             if label.get_visible() and label.get_text()]
    return [(a, b) for i, a in enumerate(boxes) for b in boxes[i + 1:] if a.overlaps(b)]


@pytest.mark.parametrize("passes", [2, 3])
def test_the_convergence_panel_has_integer_passes(rng, passes):
    """One pass compared (pass 2) or two: ticks at whole passes only, and the points in the middle."""
    ds, detector = metrology_product(rng, passes=passes)
    fig = plotting.metrology_figure(ds, detector, title="test")
    fig.canvas.draw()
    ax = fig.axes[3]  # second row, right (the colour bars come after the panels)
    assert ax.get_xlabel() == "pass"
    ticks = integer_ticks(ax.xaxis)
    assert ticks and all(float(t).is_integer() for t in ticks) and 2 in ticks
    low, high = ax.get_xlim()
    assert low == pytest.approx(1.5) and high == pytest.approx(passes + 0.5)
    plotting.save(fig, None)


def test_metrology_numbers_carry_their_units(rng):
    ds, detector = metrology_product(rng)
    fig = plotting.metrology_figure(ds, detector, title="test")
    shown = texts(fig)
    assert any("rad/pixel" in text and "mean" in text for text in shown)  # the K(t) legend
    assert any(text.endswith("pixel") and "e-0" in text for text in shown)  # the gauge annotations
    assert {text: numbers_without_unit(text) for text in shown if numbers_without_unit(text)} == {}
    plotting.save(fig, None)


def test_procrustes_and_barycentre_figures_read_well(residuals_product):
    """Integer position ticks; in the right panels of the barycentre figure equal limits symmetric about 0
    and tick labels that do not overlap; a unit after every number."""
    product, _ = residuals_product
    fig = plotting.procrustes_figure(product)
    fig.canvas.draw()
    assert all(float(t).is_integer() for t in integer_ticks(fig.axes[-1].xaxis))
    assert {text: numbers_without_unit(text) for text in texts(fig) if numbers_without_unit(text)} == {}
    plotting.save(fig, None)
    fig = plotting.barycentre_figure(product)
    fig.canvas.draw()
    for row in range(product.sizes["mode"]):
        left, right = fig.axes[2 * row], fig.axes[2 * row + 1]
        assert all(float(t).is_integer() for t in integer_ticks(left.xaxis))
        x0, x1 = right.get_xlim()
        y0, y1 = right.get_ylim()
        assert x0 == pytest.approx(-x1) and y0 == pytest.approx(-y1) and x1 == pytest.approx(y1)
        for axis in (right.xaxis, right.yaxis, left.xaxis, left.yaxis):
            assert not overlapping_labels(fig, axis)
        # every path inside the limits
        for line in right.get_lines():
            assert np.all(np.abs(line.get_xydata()) <= x1)
        # the labels in the unit the axis label names
        unit = re.search(r"\[(?:1e(-?\d+) )?pixel\]", right.get_xlabel())
        exponent = int(unit.group(1) or 0)
        for tick, label in zip(right.get_xticks(), right.get_xticklabels()):
            if label.get_text():
                assert float(label.get_text().replace("\N{MINUS SIGN}", "-")) == pytest.approx(
                    tick / 10.0**exponent, abs=1e-6)
    assert {text: numbers_without_unit(text) for text in texts(fig) if numbers_without_unit(text)} == {}
    plotting.save(fig, None)


def test_centroids_figure_has_one_colour_scale_and_readable_bounds(rng):
    """One colour bar for the five windows (one scale); the central star's precision and Cramer-Rao bound
    on their own panel, on an axis spanning at most two decades around them; integer positions."""
    ds = central_centroids(rng)
    ds["photon_limit_y"] = ds["photon_limit_y"] * 1.3
    fig = plotting.centroids_figure(ds, title="test", positions=USED)
    fig.canvas.draw()
    colour_bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(colour_bars) == 1 and "adu" in colour_bars[0].get_ylabel()
    images = [image for ax in fig.axes for image in ax.get_images()]
    assert len(images) == 5 and len({image.get_clim() for image in images}) == 1
    (ax,) = [ax for ax in fig.axes if lines(ax, "Cramer-Rao x")]
    for axis in "xy":
        (bound,) = lines(ax, f"Cramer-Rao {axis}")
        (precision,) = lines(ax, f"precision {axis}")
        np.testing.assert_allclose(bound.get_ydata(), ds[f"photon_limit_{axis}"].values[:, 0])
        np.testing.assert_allclose(precision.get_ydata(), ds[f"precision_{axis}"].values[:, 0])
        low, high = ax.get_ylim()
        assert low < bound.get_ydata().min() and bound.get_ydata().max() < high
        assert low < precision.get_ydata().min() and precision.get_ydata().max() < high
    assert ax.get_yscale() == "log" and np.log10(high / low) <= 2
    assert "1.25 (x)" in ax.get_title() and "0.96 (y)" in ax.get_title()  # median precision / bound
    for axes in fig.axes:
        if axes.get_xlabel() == "position index":
            assert all(float(t).is_integer() for t in integer_ticks(axes.xaxis))
    assert {text: numbers_without_unit(text) for text in texts(fig) if numbers_without_unit(text)} == {}
    plotting.save(fig, None)


def test_allan_figure_numbers_carry_units_and_the_legend_leaves_the_curves(rng):
    args, keywords = allan_inputs(rng)
    ds = allan.allan_dataset(*args, **keywords, first_frame=rng.uniform(500, 3000, args[3].size))
    fig = plotting.allan_figure(ds, title="test")
    fig.canvas.draw()
    (ax,) = fig.axes
    assert ax.get_legend() is None and len(fig.legends) == 1
    renderer = fig.canvas.get_renderer()
    assert not fig.legends[0].get_window_extent(renderer).overlaps(ax.get_window_extent(renderer))
    assert not overlapping_labels(fig, ax.xaxis)
    assert {text: numbers_without_unit(text) for text in texts(fig) if numbers_without_unit(text)} == {}
    plotting.save(fig, None)


def star_accuracy_points(spreads):
    """star_accuracy point products (only what the figure reads) at these PRF width spreads."""
    modes = ["flat+metrology", "flat+metrology+width"]
    return [xr.Dataset({name: ("mode", np.array([6e-3, 5e-4]) * w + 1e-6)
                        for name in ("truth_error", "accuracy_position", "error_position")},
                       coords={"mode": modes}, attrs={"method": "gaussian", "positions": 12}) for w in spreads]


def test_the_star_accuracy_figure_says_what_is_swept_in_its_unit_and_what_is_plotted():
    """The prf_width_spread sweep: x in % of the configured fraction, and the title names the spread, its
    unit and the plotted quantity with its unit."""
    spreads = [0.0, 0.01, 0.03]
    fig = plotting.star_accuracy_figure(star_accuracy_points(spreads),
                                        [{"detector.prf_width_spread": w} for w in spreads], title="sweep s")
    ax = fig.axes[0]
    assert "PRF width spread [%]" in ax.get_title() and "centroid error [pixel]" in ax.get_title()
    assert ax.get_xlabel() == "PRF width spread [%]"
    np.testing.assert_allclose(ax.get_lines()[0].get_xdata(), [0.0, 1.0, 3.0])


def test_the_reduction_sweep_figure_draws_each_superimposition_against_the_parameter_that_varies():
    """A grid whose second parameter is one value: frames a position on a log axis, that value in the title,
    one panel per superimposition, Procrustes first."""
    rows = [{"simulation.stars.frames": f, "astrometry.superimposition": "projective", "method": "fourier",
             "mode": mode, "grouping": grouping, "superimposition": model, "accuracy": str(1e-4 / f ** 0.5),
             "error": "1e-6"}
            for f in (16, 400, 1600) for mode in ("flat+metrology", "flat+metrology+width")
            for grouping in ("position", "group") for model in ("projective", "procrustes")]
    fig = plotting.reduction_sweep_figure(rows, ["simulation.stars.frames", "astrometry.superimposition"],
                                          title="sweep f")
    assert [ax.get_title() for ax in fig.axes] == ["procrustes", "projective"]
    assert fig.axes[0].get_xlabel() == "frames a position" and fig.axes[0].get_xscale() == "log"
    assert "astrometry.superimposition = projective" in fig._suptitle.get_text()
    assert "corrected accuracy [pixel]" in fig._suptitle.get_text()
    np.testing.assert_allclose(sorted(set(fig.axes[1].get_lines()[0].get_xdata())), [16, 400, 1600])
