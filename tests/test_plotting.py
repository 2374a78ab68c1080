"""The paper's experimental figures, built from small synthetic products: what each draws."""

import re

import matplotlib.colors
import matplotlib.container
import matplotlib.lines
import matplotlib.text
import numpy as np
import pytest
import xarray as xr

from dice_core import accuracies, allan, plotting
from dice_core.manifest import Detector
from test_allan import allan_inputs
from test_accuracies import centroid_datasets

USED = (3, 9)


@pytest.fixture
def residuals_product(rng):
    """A residuals product of 12 positions, 3-9 used, for two modes; and its centroid datasets."""
    datasets = centroid_datasets(rng)
    rows, residuals = accuracies.mode_accuracies(datasets, positions=USED, trials=50)
    return accuracies.residuals_dataset(datasets, rows, residuals=residuals), datasets


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
    product, datasets = residuals_product
    fig = plotting.procrustes_figure(product)
    # the centroid method the residuals are of, recorded and said: the accuracy table has every method's rows
    method = {ds.attrs["method"] for ds in datasets.values()}
    assert {product.attrs["centroid_method"]} == method
    assert f"({product.attrs['centroid_method']} centroids)" in fig._suptitle.get_text()
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
# a PRNU level is relative
DIMENSIONLESS = re.compile(r"(slope|ratio|layout x|PRNU|chi2/dof between baselines)\s*[-+]?$")


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
    fig.canvas.draw()  # constrained layout places the panels and legends at draw time
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


def test_centroids_window_titles_stay_apart(rng):
    """Each star window's title (its centroid at the first position) stays clear of its neighbours' and of
    the colour bar: a newcomer found the titles of "at position 1: x ... pixel, y ... pixel" running into
    each other, unreadable; the position is said once, on the colour bar."""
    ds = central_centroids(rng)
    fig = plotting.centroids_figure(ds, title="test", positions=USED)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    windows = sorted((ax for ax in fig.axes if ax.get_images()), key=lambda ax: ax.get_position().x0)
    boxes = [ax.title.get_window_extent(renderer) for ax in windows]
    (bar,) = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(boxes) == 5 and all(left.x1 < right.x0 for left, right in zip(boxes, boxes[1:]))
    assert boxes[-1].x1 < bar.get_window_extent(renderer).x0
    assert f"position {int(ds['position'].values[0])}" in bar.get_ylabel()
    plotting.save(fig, None)


def test_allan_figure_numbers_carry_units_and_the_legend_leaves_the_curves(rng):
    args, keywords = allan_inputs(rng)
    ds = allan.allan_dataset(*args, **keywords, first_frame=rng.uniform(500, 3000, args[3].size))
    fig = plotting.allan_figure(ds, title="test")
    fig.canvas.draw()
    (ax,) = fig.axes
    assert ax.get_legend() is None and len(fig.legends) == 1
    fig.canvas.draw()  # constrained layout places the panels and legends at draw time
    renderer = fig.canvas.get_renderer()
    assert not fig.legends[0].get_window_extent(renderer).overlaps(ax.get_window_extent(renderer))
    assert not overlapping_labels(fig, ax.xaxis)
    assert {text: numbers_without_unit(text) for text in texts(fig) if numbers_without_unit(text)} == {}
    plotting.save(fig, None)


# What a reader of the printed figure sees: no text cut at the figure's edge, legends off the data, labelled
# ticks across every axis, points inside the labelled range.

def drawn_texts(fig):
    """Every visible, non-empty text artist of ``fig``: titles, labels, legends, annotations, figure texts,
    and the tick labels of the ticks within each axis's view (those outside are not drawn)."""
    tick_labels, found = set(), []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            low, high = sorted(axis.get_view_interval())
            slack = 1e-9 * (high - low)
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                tick_labels |= {id(tick.label1), id(tick.label2)}
                if low - slack <= tick.get_loc() <= high + slack:
                    found += [tick.label1, tick.label2]
    found += [text for text in fig.findobj(matplotlib.text.Text) if id(text) not in tick_labels]
    return [text for text in found if text.get_visible() and text.get_text()]


def texts_outside(fig):
    """The texts of ``fig``, drawn, whose box leaves the figure (by more than a pixel): cut in the PNG."""
    fig.canvas.draw()
    renderer, box = fig.canvas.get_renderer(), fig.bbox
    return [text.get_text() for text in drawn_texts(fig)
            if not box.padded(1).contains(*text.get_window_extent(renderer).p0)
            or not box.padded(1).contains(*text.get_window_extent(renderer).p1)]


def points_under_legends(fig):
    """(legend texts, number of points) for each legend of ``fig`` whose box holds data points (the vertices of
    the lines drawn in any axes, markers or not)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None] + list(fig.legends)
    covered = []
    for legend in legends:
        box = legend.get_window_extent(renderer)
        inside = 0
        for ax in fig.axes:
            for line in ax.get_lines():
                xy = line.get_xydata()
                xy = xy[np.all(np.isfinite(xy), axis=1)]
                if line.get_visible() and xy.size:
                    shown = ax.transData.transform(xy)
                    inside += int(np.sum((shown[:, 0] > box.x0) & (shown[:, 0] < box.x1) & (shown[:, 1] > box.y0)
                                         & (shown[:, 1] < box.y1)))
        if inside:
            covered.append(([t.get_text() for t in legend.get_texts()], inside))
    return covered


def labelled_ticks(fig, axis):
    """The labels of ``axis``'s ticks (major and minor) within its view, as drawn."""
    fig.canvas.draw()
    low, high = sorted(axis.get_view_interval())
    return [tick.label1.get_text() for tick in axis.get_major_ticks() + axis.get_minor_ticks()
            if low * (1 - 1e-9) <= tick.get_loc() <= high * (1 + 1e-9) and tick.label1.get_visible()
            and tick.label1.get_text()]


def offset_bias_datasets(rng, side=12):
    """Two points of the offset_bias study: photon-noise errors of 3e-5 pixel, the paper's noiseless bias
    1e-6 and 3e-5 pixel, ours 1e-9 pixel (as measured: four decades under the others)."""
    out = []
    for prnu, paper_bias in ((5e-5, 1e-6), (2e-3, 3e-5)):
        maps = {}
        for name, rms in (("error_paper", 3e-5), ("error_ours", 2.9e-5), ("bias_paper", paper_bias),
                          ("bias_ours", 9e-10)):
            values = np.full((side, side), np.nan)
            values[1:-1, 1:-1] = rms * rng.standard_normal((side - 2, side - 2))
            maps[name] = (("row", "col"), values)
        out.append(xr.Dataset({**maps, "rms_photon_floor": ((), 2.9e-5), "rms_bias_paper": ((), paper_bias),
                               "rms_bias_ours": ((), 1e-9)},
                              attrs={"prnu_rms": prnu, "baseline": "H1H4", "frames": 2000, "noiseless_frames": 400,
                                     "noiseless_draws": 8}))
    return out


def prf_product(rng, detector, side=12):
    """A calibration/prf.nc-like dataset: widths of 0.2064 +- 2e-3 pixel (mean known to 4e-3) with pixel-scale
    errors of 3e-4 pixel."""
    maps = {f"{kind}_{axis}": (("row", "col"), scale * rng.standard_normal((side, side)) + offset)
            for axis in "xy" for kind, scale, offset in (("width", 2e-3, 0.2064), ("error_width", 1e-5, 4e-3),
                                                         ("error_width_pixel", 1e-5, 3e-4))}
    means = {f"{name}_{axis}": ((), value) for axis in "xy" for name, value in (("mean_width", 0.2064),
                                                                               ("error_mean_width", 4e-3))}
    return xr.Dataset({**maps, **means, "chi2": ((), 0.99)}, coords={"baseline": ["H1H4", "V2V4"]})


def test_prf_and_offset_bias_numbers_carry_their_units(rng):
    _, detector = metrology_product(rng)
    for fig in (plotting.prf_widths_figure(prf_product(rng, detector), detector),
                plotting.offset_bias_figure(offset_bias_datasets(rng))):
        assert {text: numbers_without_unit(text) for text in texts(fig) if numbers_without_unit(text)} == {}
        plotting.save(fig, None)


MODES = ("raw", "flat+metrology+width")  # the longest mode name of the configuration


def every_figure(rng):
    """(name, figure) of each figure function that draws data, from small synthetic products."""
    datasets = centroid_datasets(rng, modes=MODES)
    rows, residuals = accuracies.mode_accuracies(datasets, positions=USED, trials=20)
    product = accuracies.residuals_dataset(datasets, rows, residuals=residuals)
    args, keywords = allan_inputs(rng)
    allan_ds = allan.allan_dataset(*args, **keywords, first_frame=rng.uniform(500, 3000, args[3].size))
    metrology, detector = metrology_product(rng)
    image = rng.standard_normal((12, 12))
    yield "procrustes", plotting.procrustes_figure(product)
    yield "barycentre", plotting.barycentre_figure(product)
    yield "centroids", plotting.centroids_figure(central_centroids(rng), title="test", positions=USED)
    yield "metrology", plotting.metrology_figure(metrology, detector, title="test")
    yield "allan", plotting.allan_figure(allan_ds, title="test")
    yield "offset_bias", plotting.offset_bias_figure(offset_bias_datasets(rng))
    yield "map", plotting.map_figure(image, detector, title="PRNU, flat F1", units="PRNU - 1 [1e-3]", scale=1e3,
                                     note="rms 3.29e-03, photon-noise limit 2.5e-04, relative to the mean "
                                          "response (80 frames)")  # the PRNU map's note, once cut
    yield "prf", plotting.prf_widths_figure(prf_product(rng, detector), detector)
    yield "maps", plotting.maps_figure([image, image], detector, titles=["dx", "dy"], units="1e-3 pixel",
                                       scale=1e3, suptitle="offsets")


def test_a_map_whose_colours_are_clipped_says_so_with_the_values_span(rng):
    """A PRNU map with a dust spot far below the rest: the colours span the 0.5-99.5 percentiles (the spot would
    flatten the rest), and the colour bar says it with arrows and in its label; a map within its colour limits
    (clip_percentile 0) says nothing of the kind."""
    detector = Detector(shape=(40, 40), science_rows=(0, 40), science_cols=(0, 40), gain=2.0, saturation=6e4)
    image = 1 + 3e-3 * rng.standard_normal((40, 40))
    image[20:22, 20:22] = 0.95  # dust: -50e-3, 4 pixels of 1600 (under the 0.5 percentile's 8)
    fig = plotting.map_figure(image - 1, detector, title="PRNU", units="PRNU - 1 [1e-3]", scale=1e3)
    assert fig.axes[-1].get_ylabel() == "PRNU - 1 [1e-3]; colours clipped (arrows)"
    assert fig.axes[0].images[0].colorbar.extend == "both"
    lo, hi = fig.axes[0].images[0].get_clim()
    assert -15 < lo < -5 and 5 < hi < 15  # the rest's spread, not the spot's
    whole = plotting.map_figure(image - 1, detector, title="PRNU", units="PRNU - 1 [1e-3]", scale=1e3,
                                clip_percentile=0.0)
    assert whole.axes[-1].get_ylabel() == "PRNU - 1 [1e-3]"
    assert whole.axes[0].images[0].colorbar.extend == "neither"


def test_no_text_leaves_the_figure(rng):
    """Titles, labels, tick labels and legends all inside the figure: the PNG cuts what is outside."""
    for name, fig in every_figure(rng):
        assert (name, texts_outside(fig)) == (name, [])
        plotting.save(fig, None)


def test_procrustes_title_of_the_longest_mode_fits(rng):
    """The mode's title (its sigma and accuracy) is the widest text: it must fit the panel's width."""
    datasets = centroid_datasets(rng, modes=MODES)
    rows, residuals = accuracies.mode_accuracies(datasets, positions=USED, trials=20)
    fig = plotting.procrustes_figure(accuracies.residuals_dataset(datasets, rows, residuals=residuals))
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        extent = ax.title.get_window_extent(renderer)
        assert fig.bbox.x0 <= extent.x0 and extent.x1 <= fig.bbox.x1 and "flat+metrology+width" in \
            fig.axes[-1].get_title()
    plotting.save(fig, None)


@pytest.mark.parametrize("sizes", [(100, 200, 300, 400), (150, 400, 1200, 3700), (10, 100, 1000, 30000),
                                   (350, 700, 1050, 1400, 1750), (1050, 1400, 1750)])
def test_allan_axis_has_labelled_ticks_across_the_group_sizes(rng, sizes):
    """At least three labelled ticks within the group sizes (on 150-3700, not 1000 alone), none overlapping, and
    no stretch of the axis unlabelled over 0.2 decade or, on a longer axis, 30% of it (on 350-1750 frames, not
    1000 the last label)."""
    args, keywords = allan_inputs(rng, n_batches=2 * len(sizes))
    ds = allan.allan_dataset(*args, **keywords)
    ds = ds.isel(n_frames=slice(len(sizes))).assign_coords(n_frames=np.array(sizes, float))
    fig = plotting.allan_figure(ds, title="test")
    (ax,) = fig.axes
    labels = labelled_ticks(fig, ax.xaxis)
    assert len(labels) >= 3, labels
    assert not overlapping_labels(fig, ax.xaxis)
    view = np.log10(sorted(ax.get_xlim()))
    stretches = np.diff(np.sort(np.concatenate([view, np.log10([float(label) for label in labels])])))
    assert stretches.max() <= max(0.2, 0.3 * (view[1] - view[0])) + 1e-9, (labels, ax.get_xlim())
    plotting.save(fig, None)


@pytest.mark.parametrize("frames", [350, 450, 650])
def test_a_one_group_size_allan_axis_still_says_its_frames(rng, frames):
    """Two or three batches make one group size: its axis, a few percent wide, must still carry a label (450
    and 650 frames had none: no mantissa falls in so narrow a view)."""
    args, keywords = allan_inputs(rng, n_batches=3, frames=frames)
    fig = plotting.allan_figure(allan.allan_dataset(*args, **keywords), title="test")
    labels = labelled_ticks(fig, fig.axes[0].xaxis)
    assert len(labels) == 1 and abs(float(labels[0]) / frames - 1) < 0.01, labels
    plotting.save(fig, None)


@pytest.mark.parametrize("positions", [USED, (1, 12)])
def test_centroids_legends_leave_the_points_and_list_only_what_is_drawn(rng, positions):
    ds = central_centroids(rng)
    ds["precision_y"] = ds["precision_y"] * np.geomspace(0.12, 1, 12)[:, None]  # as on the ci bench: 1e-4-1e-3
    fig = plotting.centroids_figure(ds, title="test", positions=positions)
    assert points_under_legends(fig) == []
    (bound,) = [ax for ax in fig.axes if lines(ax, "Cramer-Rao x")]
    assert len(labelled_ticks(fig, bound.yaxis)) >= 3 and not overlapping_labels(fig, bound.yaxis)
    (path,) = [ax for ax in fig.axes if ax.get_xlabel() == "x [pixel]"]
    entries = [t.get_text() for t in path.get_legend().get_texts()]
    assert ("other positions" in entries) == (positions != (1, 12))
    plotting.save(fig, None)


def test_metrology_legends_leave_the_curves_and_the_convergence_points_sit_within_labelled_ticks(rng):
    ds, detector = metrology_product(rng, passes=4)
    ds["max_change"] = ds["max_change"] * 3.0  # above the decade: the autoscaled top tick was below the point
    fig = plotting.metrology_figure(ds, detector, title="test")
    (kt,) = [ax for ax in fig.axes if ax.get_ylabel().startswith("K(t)")]
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    box = kt.get_legend().get_window_extent(renderer)
    for line in kt.get_lines():
        shown = kt.transData.transform(line.get_xydata())
        assert not np.any((shown[:, 0] > box.x0) & (shown[:, 0] < box.x1) & (shown[:, 1] > box.y0)
                          & (shown[:, 1] < box.y1))
    (ax,) = [ax for ax in fig.axes if ax.get_xlabel() == "pass"]
    low, high = ax.get_ylim()
    ticks = [t for t in ax.get_yticks() if low * (1 - 1e-9) <= t <= high * (1 + 1e-9)]
    values = np.concatenate([line.get_ydata() for line in ax.get_lines()])
    assert min(ticks) <= values.min() and values.max() <= max(ticks)
    assert len(labelled_ticks(fig, ax.yaxis)) >= 2
    plotting.save(fig, None)


def test_offset_bias_noiseless_maps_have_their_own_colour_scale(rng):
    """Ours without noise, 1e-9 pixel, on a colour scale of its own (within a factor of a few of its values),
    in its own unit, said in the title; the noisy maps share one scale."""
    datasets = offset_bias_datasets(rng)
    fig = plotting.offset_bias_figure(datasets)
    panels = [ax for ax in fig.axes if ax.get_images()]
    assert len(panels) == 4 * len(datasets)
    for ds, row in zip(datasets, np.reshape(panels, (len(datasets), 4))):
        noisy = {ax.get_images()[0].get_clim() for ax in row[:2]}
        assert len(noisy) == 1
        for ax, name in zip(row[2:], ("bias_paper", "bias_ours")):
            image = ax.get_images()[0]
            colour_bar = image.colorbar
            unit = re.fullmatch(r"1e(-?\d+) pixel", colour_bar.ax.get_ylabel())
            assert unit, colour_bar.ax.get_ylabel()
            values = ds[name].values
            spread = np.nanpercentile(np.abs(values), 99.5) / 10.0 ** int(unit.group(1))  # in the bar's unit
            low, high = image.get_clim()
            assert low == -high and spread / 3 <= high <= 3 * spread
            assert "own colour scale" in ax.get_title()
    assert texts_outside(fig) == []
    plotting.save(fig, None)


def test_residual_figures_legends_sit_outside_every_panel(residuals_product):
    """The star legend under the panels: inside one, the residual curves, which fill it, ran under it."""
    product, _ = residuals_product
    for figure in (plotting.procrustes_figure, plotting.barycentre_figure):
        fig = figure(product)
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        assert not [ax for ax in fig.axes if ax.get_legend() is not None]
        (legend,) = fig.legends
        assert [t.get_text() for t in legend.get_texts()][0] == "star 0 (central)"
        box = legend.get_window_extent(renderer)
        assert not any(box.overlaps(ax.get_window_extent(renderer)) for ax in fig.axes)
        assert texts_outside(fig) == []
        plotting.save(fig, None)


def test_paper_comparison_points_lie_within_the_labelled_ticks():
    """Every ratio and error bar between two labelled ticks, whatever the spread (0.14 to 23 on the ci run)."""
    from dice_core import reproduction

    rows = [reproduction.Row("allan_pixel", 23 * 2e-5, dataset="sim-ci H2H4"),
            reproduction.Row("bias_paper_2e-3", 0.14e-4, 0.06e-4, dataset="offset_bias study"),
            reproduction.Row("deflation", 1.44, 0.004, dataset="nominal geometry")]
    fig = plotting.paper_comparison_figure(rows)
    (ax,) = fig.axes
    fig.canvas.draw()
    low, high = ax.get_xlim()
    ticks = [t for t in ax.get_xticks() if low <= t <= high]
    ratios = [23.0, 0.14, 1.44 / 1.4]
    assert min(ticks) <= 0.14 - 0.06 and max(ratios) <= max(ticks) and len(labelled_ticks(fig, ax.xaxis)) >= 3
    assert texts_outside(fig) == [] and not overlapping_labels(fig, ax.xaxis)
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
    assert "astrometry.superimposition = projective" in fig.get_suptitle()
    assert "corrected accuracy [pixel]" in fig.get_suptitle()
    np.testing.assert_allclose(sorted(set(fig.axes[1].get_lines()[0].get_xdata())), [16, 400, 1600])


def tip_tilt_point(pv, positions, *, snr_per_rad=900.0, threshold=3.0):
    """A synthetic tip_tilt sweep point: Procrustes growing with the amplitude, the others flat."""
    snr = snr_per_rad * pv
    ds = xr.Dataset(coords={"model": ["procrustes", "projective", "pose"]})
    ds["accuracy"] = ("model", [5e-5 + 0.1 * pv, 6e-5, 5e-5])
    ds["error"] = ("model", [5e-6, 6e-6, 5e-6])
    for angle in ("tip", "tilt"):
        ds[f"pose_{angle}_snr"] = snr
        ds[f"pose_{angle}_identifiable"] = int(snr >= threshold)
        ds[f"pose_{angle}_error"] = 6e-5
        ds[f"pose_{angle}_crlb_nominal_field"] = 5e-5
    ds.attrs.update({"positions": positions, "method": "gaussian",
                     "point": f'{{"stars.positions": {positions}, "stars.tip_tilt_pv": {pv}}}'})
    return ds


def test_the_tip_tilt_sweep_figure_marks_what_the_pose_identifies():
    """Left: one line per model and number of positions; middle: filled markers exactly where the angle was
    identified, the threshold drawn; right: only identified points, in bounds; no text cut, no legend on data."""
    amplitudes = (0.0, 2.5e-3, 5e-3, 1e-2)
    fig = plotting.tip_tilt_sweep_figure([tip_tilt_point(pv, n) for n in (6, 33) for pv in amplitudes])
    accuracy, identifiability, against_truth = fig.axes[:3]
    assert len(accuracy.containers) == 3 * 2  # errorbars: models x numbers of positions
    markers = [line for line in identifiability.get_lines() if line.get_marker() not in ("None", "", None)]
    filled = sorted(float(x) for line in markers if line.get_markerfacecolor() != "none" for x in line.get_xdata())
    hollow = sorted(float(x) for line in markers if line.get_markerfacecolor() == "none" for x in line.get_xdata())
    assert filled == sorted([5e-3, 1e-2] * 4) and hollow == sorted([0.0, 2.5e-3] * 4)  # tip, tilt x 2 positions
    assert any(np.allclose(line.get_ydata(), 3.0) for line in identifiability.get_lines())
    drawn = [x for line in against_truth.get_lines() for x in line.get_xdata() if line.get_linestyle() != "--"]
    assert sorted(set(map(float, drawn))) == [5e-3, 1e-2]
    assert texts_outside(fig) == []
    assert points_under_legends(fig) == []
    plotting.save(fig, None)


# What a referee sees on each figure (issue: a newcomer's figures): no legend entry whose curve lies under
# another, one scale for the panels of one quantity, each number said with what it means, maps that say they
# show the science area alone.

def _data_artists(handle):
    """The Line2D a legend handle stands for (an errorbar's data line), or None for a patch or a key."""
    from matplotlib.container import ErrorbarContainer
    from matplotlib.lines import Line2D

    if isinstance(handle, ErrorbarContainer):
        return handle.lines[0]
    return handle if isinstance(handle, Line2D) else None


def hidden_entries(fig, tolerance=1.03):
    """Legend labels of ``fig`` whose curve is not seen: not visible, without finite points, or lying (within
    ``tolerance`` at every point) under another visible curve of its axes drawn over it (a higher zorder, or
    the same and later) at least as wide, while having no markers of its own to show."""
    hidden = []
    for ax in fig.axes:
        handles, labels = ax.get_legend_handles_labels()
        drawn = [line for line in ax.get_lines() if line.get_visible()]
        for handle, label in zip(handles, labels):
            line = _data_artists(handle)
            if line is None or line.axes is not ax:
                continue
            y = np.asarray(line.get_ydata(), float)
            markers = line.get_marker() not in ("None", "", None, " ")
            if not line.get_visible() or np.isfinite(y).sum() < (1 if markers else 2):  # one point: no line
                hidden.append(label)
                continue
            if markers:
                continue
            order = drawn.index(line)
            for k, other in enumerate(drawn):
                over = other.get_zorder() > line.get_zorder() or (other.get_zorder() == line.get_zorder() and k > order)
                oy = np.asarray(other.get_ydata(), float)
                if other is line or not over or oy.shape != y.shape or other.get_linewidth() < line.get_linewidth():
                    continue
                both = np.isfinite(y) & np.isfinite(oy)
                if both.any() and np.allclose(other.get_xdata()[both], line.get_xdata()[both]) and np.all(
                        np.abs(np.log(np.abs(oy[both]) / np.abs(y[both]))) < np.log(tolerance)):
                    hidden.append(label)
                    break
    return hidden


def legend_labels(fig):
    return [t.get_text() for legend in [ax.get_legend() for ax in fig.axes if ax.get_legend()] + list(fig.legends)
            for t in legend.get_texts()]


def same_looking_entries(fig):
    """Pairs of legend entries whose keys look alike: lines of one colour, line style and marker (and marker
    colours), or patches of one colour: the central star's black line and a black line-style key, say."""
    def look(handle):
        if isinstance(handle, matplotlib.lines.Line2D):
            style = handle.get_linestyle() if handle.get_linestyle() not in ("None", "none", "") else "none"
            colours = [handle.get_color()] if style != "none" else []
            if handle.get_marker() not in ("None", "none", "", None):
                colours += [handle.get_markerfacecolor(), handle.get_markeredgecolor()]
            return ("line", style, str(handle.get_marker()), tuple(matplotlib.colors.to_hex(c, keep_alpha=True)
                                                                   if c != "none" else c for c in colours))
        return ("patch", matplotlib.colors.to_hex(handle.get_facecolor(), keep_alpha=True))

    seen, alike = {}, []
    for legend in [ax.get_legend() for ax in fig.axes if ax.get_legend()] + list(fig.legends):
        for handle, text in zip(legend.legend_handles, legend.get_texts()):
            key = look(handle)
            if key in seen:
                alike.append((seen[key], text.get_text()))
            seen.setdefault(key, text.get_text())
    return alike


@pytest.mark.parametrize("stars", [5, 9])
def test_the_residual_figures_line_style_key_looks_like_no_star(residuals_product, stars):
    """The x and y keys in a grey no star is drawn in (the central star black, the others matplotlib's cycle
    without its grey), also with 9 stars, where star 7 would take the cycle's grey."""
    product, _ = residuals_product
    product = product.isel(star=np.arange(stars) % product.sizes["star"])
    for figure in (plotting.procrustes_figure, plotting.barycentre_figure):
        fig = figure(product)
        assert same_looking_entries(fig) == [], figure.__name__
        (legend,) = fig.legends
        hsv = {text.get_text(): matplotlib.colors.rgb_to_hsv(matplotlib.colors.to_rgb(handle.get_color()))
               for handle, text in zip(legend.legend_handles, legend.get_texts())
               if isinstance(handle, matplotlib.lines.Line2D)}
        stars_ = {label: v for label, v in hsv.items() if label.startswith("star ")}
        keys = {label: v for label, v in hsv.items() if label.startswith(("x residual", "y residual"))}
        assert len(stars_) == stars and len(keys) == 2
        # the stars: black (the central one) or a colour; the key: a grey far from black
        assert all(label.endswith("(central)") == (v[2] == 0) for label, v in stars_.items())
        assert all(v[1] >= 0.3 for label, v in stars_.items() if v[2] > 0), stars_
        assert all(v[1] == 0 and v[2] >= 0.5 for v in keys.values()), keys
        plotting.save(fig, None)


def test_hidden_entries_are_found():
    """The check itself: a thin curve under a wider one is hidden, one with markers or drawn over is not."""
    fig, ax = plotting.plt.subplots()
    x = np.arange(1.0, 5.0)
    ax.loglog(x, 1 / x, lw=0.8, label="under")
    ax.loglog(x, 1.01 / x, lw=1.5, label="over")
    ax.loglog(x, 2 / x, "o", label="markers")
    ax.loglog(x, 2 / x, lw=2, label="over the markers")
    ax.legend()
    assert hidden_entries(fig) == ["under"]
    plotting.save(fig, None)


def allan_product(rng, *, coincide=True):
    """An allan product whose paper's and first-frame pixel limits equal the fits' (as on the default preset)."""
    args, keywords = allan_inputs(rng, n_batches=16)
    ds = allan.allan_dataset(*args, **keywords, first_frame=rng.uniform(500, 3000, args[3].size))
    if coincide:
        ds["photon_limit_pixel_paper"] = ds["photon_limit_pixel"] * 1.01
        ds["photon_limit_pixel_first_frame"] = ds["photon_limit_pixel"] * 0.995
    return ds


@pytest.mark.parametrize("n_batches", [2, 3, 4])
def test_an_allan_figure_of_too_few_batches_says_so_and_lists_only_what_it_draws(rng, n_batches):
    """Under 5 batches no single pixel reaches 5 groups (and under 4 there is no slope): the title says so in
    plain words, and the legend lists no curve that is not drawn (no pixels' entry, no slope of NaN)."""
    args, keywords = allan_inputs(rng, n_batches=n_batches, frames=350)
    ds = allan.allan_dataset(*args, **keywords)
    fig = plotting.allan_figure(ds, title="test")
    (ax,) = fig.axes
    assert ax.get_title() == (f"too few batches for Allan deviations: {n_batches} batches of 350 frames; at least "
                              f"{allan.MIN_BATCHES} needed")
    labels = legend_labels(fig)
    assert not [label for label in labels if "individual pixels" in label or "nan" in label], labels
    assert any(("no slope" in label) == (n_batches < 4) for label in labels if label.startswith("pixels, rms"))
    for handle, label in zip(*ax.get_legend_handles_labels()):  # the artists the legend's entries stand for
        line = handle.lines[0] if isinstance(handle, matplotlib.container.ErrorbarContainer) else handle
        if label in labels and isinstance(line, matplotlib.lines.Line2D):
            assert np.isfinite(np.asarray(line.get_ydata(), float)).any(), label
            assert len(line.get_ydata()) > 1 or line.get_marker() not in (None, "None", "", " "), label  # shows
    assert texts_outside(fig) == []  # the legend's long labels included
    plotting.save(fig, None)


def test_allan_figure_draws_every_entry_and_single_pixels_only_over_enough_groups(rng):
    """Curves within 3% drawn once, their entry naming each; no entry hidden; single pixels only where
    MIN_GROUPS_PIXEL groups or more (elsewhere a shaded band says so); the measured rms with error bars."""
    ds = allan_product(rng)
    fig = plotting.allan_figure(ds, title="test")
    (ax,) = fig.axes
    assert hidden_entries(fig) == []
    (red,) = lines(ax, "first frame")
    assert "paper's photon limit, pixels" in red.get_label() and "photon limit, pixels" in red.get_label()
    assert not [line for line in ax.get_lines() if line.get_label().startswith("paper's photon limit, pixels")]
    few = ds["n_groups"].values < plotting.MIN_GROUPS_PIXEL
    assert few.any() and not few.all()  # the case of the issue: the last sizes from a few groups
    green = [line for line in ax.get_lines() if matplotlib.colors.same_color(line.get_color(), "tab:green")
             and line.get_xdata().size]
    assert len(green) == ds.sizes["sample"]
    for line in green:
        assert np.isnan(line.get_ydata()[few]).all() and np.isfinite(line.get_ydata()[~few]).all()
    assert any(f"fewer than {plotting.MIN_GROUPS_PIXEL} groups" in label for label in legend_labels(fig))
    bars = [c for c in ax.containers if c.has_yerr]
    assert len(bars) == 2 and all(np.all(np.isfinite(c.lines[0].get_ydata())) for c in bars)
    assert texts_outside(fig) == []
    plotting.save(fig, None)
    # without the coincidences, each curve its own entry
    fig = plotting.allan_figure(allan_product(rng, coincide=False), title="test")
    assert hidden_entries(fig) == []
    plotting.save(fig, None)


def key_offsets_from_first_lines(legend, renderer):
    """(label, offset) of each entry of ``legend``: the height of its key's middle (its line, or its markers'
    line for error bars) above the middle of its text's first line, in lines of text."""
    out = []
    for column in legend._legend_handle_box.get_children():
        for entry in column.get_children():
            key, text = entry.get_children()
            lines = [a for a in key.get_children() if isinstance(a, matplotlib.lines.Line2D)]
            if not lines:  # a patch: one line of text
                continue
            box = text._text.get_window_extent(renderer)
            n = text._text.get_text().count("\n") + 1
            line_height = box.height / n
            # the mean of its lines' middles: error bars' caps lie either side of their markers
            middle = np.mean([(e.y0 + e.y1) / 2 for e in (a.get_window_extent(renderer) for a in lines)])
            out.append((text._text.get_text(), (middle - (box.y1 - line_height / 2)) / line_height))
    return out


def test_a_merged_allan_entry_has_its_key_beside_its_own_name(rng):
    """An entry naming the curves merged into it (several lines: the curve's own name, then '= ...' for each)
    has its key beside its first line, as every one-line entry has: the key centred on six lines sat beside a
    merged name, 2.5 lines down (on the default preset's figure), and the entry's own name, without a key, read
    as the end of the entry above."""
    fig = plotting.allan_figure(allan_product(rng), title="test")
    fig.canvas.draw()
    offsets = key_offsets_from_first_lines(fig.legends[0], fig.canvas.get_renderer())
    assert any(label.count("\n") >= 2 for label, _ in offsets)  # the red entry, two limits merged into it
    for label, offset in offsets:
        assert abs(offset) < 0.35, (label, offset)
    plotting.save(fig, None)


def shared_range(axes):
    """Whether the axes all show one y range."""
    return len({tuple(np.round(ax.get_ylim(), 15)) for ax in axes}) == 1


def tick_label_digits(fig, axis):
    """The longest drawn tick label's number of digits."""
    return max(len(re.sub(r"\D", "", text)) for text in labelled_ticks(fig, axis))


def test_procrustes_panels_share_one_scaled_range_and_the_line_styles_are_in_the_legend(residuals_product):
    """Every mode on one y range, ticks in a power of ten of the pixel (no 0.00075), the y unit in the label;
    the legend has the stars and the key of x, y and sigma."""
    product, _ = residuals_product
    fig = plotting.procrustes_figure(product)
    fig.canvas.draw()
    assert shared_range(fig.axes)
    for ax in fig.axes:
        assert re.search(r"\[1e-\d+ pixel\]", ax.get_ylabel())
        assert tick_label_digits(fig, ax.yaxis) <= 3
        assert "\n" not in ax.get_title()  # one line: the key is in the legend
    (legend,) = fig.legends
    entries = [t.get_text() for t in legend.get_texts()]
    assert {"x residual: solid, in the star's colour", "y residual: dotted, in the star's colour", "±σ"} <= set(entries)
    assert texts_outside(fig) == [] and hidden_entries(fig) == [] and same_looking_entries(fig) == []
    plotting.save(fig, None)


def test_barycentre_titles_the_used_band_and_the_layout_read(residuals_product):
    """Titles of at most two lines; the used positions a band inside the axes (not lines on their edges);
    the layout's scale said in words; the left panels on one range."""
    product, _ = residuals_product
    fig = plotting.barycentre_figure(product)
    fig.canvas.draw()
    left = fig.axes[0::2]
    assert shared_range(left)
    for ax in fig.axes:
        assert ax.get_title().count("\n") <= 1 and "layout x" not in ax.get_title()
    for ax in left:
        (band,) = [p for p in ax.patches if p.get_gid() == "used span"]
        x0, x1 = band.get_x(), band.get_x() + band.get_width()
        assert (x0, x1) == (USED[0] - 0.5, USED[1] + 0.5)
        low, high = ax.get_xlim()
        assert low < x0 and x1 < high
    for row, mode in enumerate(product["mode"].values):
        residual = product["barycentre_residual"].sel(mode=mode).values
        star = np.column_stack([product["star_x"].sel(mode=mode), product["star_y"].sel(mode=mode)])
        _, scale = plotting._downscaled_layout(residual, star, 3.0)
        assert f"shrunk {1 / scale:,.0f} times" in fig.axes[2 * row + 1].get_title()
    assert f"positions {USED[0]}-{USED[1]} used" in legend_labels(fig)
    assert texts_outside(fig) == [] and hidden_entries(fig) == [] and same_looking_entries(fig) == []
    plotting.save(fig, None)


@pytest.mark.parametrize("difference, verdict", [(7.3e-5, "yes"), (2.6e-3, "no")])
def test_metrology_answers_its_questions_and_draws_kx_and_ky_apart(rng, difference, verdict):
    """The gauge panel's title answers with the difference over its floor and the chance noise gives it; the
    convergence panel has the photon floor to compare with and says the ratio; kx above ky, not on it; the
    gauge map says why it is striped."""
    ds, detector = metrology_product(rng, passes=3)
    ds["max_change"] = ("iteration", [1.2e-7, 7.1e-9])  # as on the default preset's V2V4
    ds["rms_change"] = ("iteration", [6e-8, 1.5e-9])
    ds["photon_noise_floor_rms"] = 8e-5
    ds["gauge_difference_rms"] = difference
    fig = plotting.metrology_figure(ds, detector, title="test")
    (gauge,) = [ax for ax in fig.axes if ax.get_ylabel() == "rms [pixel]"]
    ratio = difference / 2.6e-4
    assert gauge.get_title().startswith(f"do the two gauges agree? {verdict}")
    assert f"{ratio:.2g} x its noise floor" in gauge.get_title()
    chance = 1 / (1 + ratio**2)
    assert (f"{100 * chance:.0f}% of the time" if chance >= 0.1 else f"1 time in {1 / chance:.0f}") in gauge.get_title()
    (convergence,) = [ax for ax in fig.axes if ax.get_xlabel() == "pass"]
    assert any(np.allclose(line.get_ydata(), 8e-5) for line in convergence.get_lines())
    assert f"{float(ds['max_change'][-1]) / 8e-5:.1e} x their photon floor" in convergence.get_title()
    (kt,) = [ax for ax in fig.axes if ax.get_ylabel().startswith("K(t)")]
    kx, ky = [line for line in kt.get_lines() if line.get_label().startswith(("kx", "ky"))]
    assert np.min(kx.get_ydata()) > np.max(ky.get_ydata())
    assert not [entry for entry in points_under_legends(fig) if "largest change" in entry[0]]
    (difference_map,) = [ax for ax in fig.axes if ax.get_title().startswith("flat gauge minus")]
    assert "first harmonic of the fringe phase" in difference_map.get_title()
    assert texts_outside(fig) == [] and hidden_entries(fig) == []
    assert {text: numbers_without_unit(text) for text in texts(fig) if numbers_without_unit(text)} == {}
    plotting.save(fig, None)


def test_metrology_frame_ticks_stay_apart_at_the_papers_frames(rng):
    """200,000 frames: the frame axes' labels (six digits) do not run into each other."""
    ds, detector = metrology_product(rng)
    frames = 200_000
    ds = ds.isel(frame=np.arange(ds.sizes["frame"]).repeat(frames // ds.sizes["frame"])).assign_coords(
        frame=np.arange(frames))
    fig = plotting.metrology_figure(ds, detector, title="test")
    for ax in fig.axes:
        if ax.get_xlabel() == "frame":
            assert not overlapping_labels(fig, ax.xaxis) and len(labelled_ticks(fig, ax.xaxis)) >= 3
    plotting.save(fig, None)


@pytest.mark.parametrize("y_bound", [1.0, 1.3])
def test_centroids_bounds_error_bars_and_windows_are_seen(rng, y_bound):
    """Equal x and y bounds drawn once (else each); the error bars on the path panels longer than the markers,
    enlarged by a power of ten said in the title; the windows in detector pixels around each star."""
    ds = central_centroids(rng)
    ds["photon_limit_y"] = ds["photon_limit_y"] * y_bound
    fig = plotting.centroids_figure(ds, title="test", positions=USED)
    fig.canvas.draw()
    (ax,) = [ax for ax in fig.axes if lines(ax, "Cramer-Rao x")]
    assert len(lines(ax, "Cramer-Rao y")) == (0 if y_bound == 1.0 else 1)
    assert ("x and y: Cramer-Rao bound" in lines(ax, "Cramer-Rao x")[0].get_label()) == (y_bound == 1.0)
    assert hidden_entries(fig) == []
    for axis in "xy":
        (panel,) = [a for a in fig.axes if a.get_title().startswith(f"central star's {axis} against")]
        (bars,) = [c for c in panel.containers if c.has_yerr]
        segments = bars.lines[2][0].get_segments()
        lengths = [abs(np.diff(panel.transData.transform(seg)[:, 1])[0]) for seg in segments]  # display pixels
        marker = 3 * fig.dpi / 72  # the markers' size, display pixels
        assert np.median(lengths) > 2 * marker
        factor = np.median([abs(seg[1, 1] - seg[0, 1]) / 2 for seg in segments]) / 1e-3
        if round(factor) != 1:
            assert f"(error bars x{factor:g})" in panel.get_title()
    windows = [a for a in fig.axes if a.get_images() and a.get_label() != "<colorbar>"]
    for s, window in enumerate(windows):
        col = np.rint(ds["x"].values[0, s])
        low, high = window.get_xlim()
        assert low == pytest.approx(col - 3.5) and high == pytest.approx(col + 3.5)  # 7x7 windows
        assert window.get_xlabel() == "column x [pixel]" and len(labelled_ticks(fig, window.xaxis)) == 3
    assert texts_outside(fig) == []
    plotting.save(fig, None)


def test_prf_errors_are_summarised_by_their_median(rng):
    _, detector = metrology_product(rng)
    ds = prf_product(rng, detector)
    fig = plotting.prf_widths_figure(ds, detector)
    for axis, ax in zip("xy", fig.axes[2:4]):  # the bottom row
        median = np.nanmedian(ds[f"error_width_pixel_{axis}"].values[detector.science_slices])
        assert f"median {median:.2e} pixel" in ax.get_title()
    plotting.save(fig, None)


def test_every_map_says_it_shows_the_science_area_alone(rng):
    """Each panel with an image of the detector says, under it, that the science area alone is drawn."""
    for name, fig in every_figure(rng):
        if name in ("centroids",):  # star windows, not maps of the detector
            plotting.save(fig, None)
            continue
        maps = [ax for ax in fig.axes if ax.get_images() and ax.get_label() != "<colorbar>"]
        for ax in maps:
            assert "science area only" in ax.get_xlabel(), (name, ax.get_title())
        assert hidden_entries(fig) == [], name
        plotting.save(fig, None)


def test_stripe_ratios_measure_rows_and_columns_that_share_an_offset(rng):
    """Independent pixels: both ratios near 1; an offset per row of 0.5 sigma over 60 columns: the row ratio
    near 1 + 60 / 4, the columns' still near 1; the PRF figure's titles carry the two numbers."""
    detector = Detector(shape=(64, 64), science_rows=(2, 62), science_cols=(2, 62), gain=2.5, saturation=6e4)
    noise = rng.standard_normal((64, 64))
    rows, cols = plotting.stripe_ratios(noise, detector)
    assert 0.5 < rows < 1.6 and 0.5 < cols < 1.6
    striped = noise + 0.5 * rng.standard_normal((64, 1))
    rows, cols = plotting.stripe_ratios(striped, detector)
    assert rows > 8 and 0.5 < cols < 1.6
    rows, cols = plotting.stripe_ratios(striped.T, detector)
    assert cols > 8 and 0.5 < rows < 1.6
    _, small = metrology_product(rng)
    ds = prf_product(rng, small)
    fig = plotting.prf_widths_figure(ds, small)
    for ax, name in zip(fig.axes[:4], ("width_x", "width_y", "error_width_pixel_x", "error_width_pixel_y")):
        rows, cols = plotting.stripe_ratios(ds[name].values, small)
        assert f"row-mean ratio {rows:.2f}, column-mean ratio {cols:.2f}" in ax.get_title()
    assert texts_outside(fig) == []
    plotting.save(fig, None)


def test_the_pdf_keeps_the_layout_made_for_the_png(tmp_path):
    """save lays a figure out once, for the PNG, and writes the PDF with that layout: where a PDF laid out
    anew would put the axes, to 2e-3 of the figure (constrained layout, colour bars, long titles)."""
    def figure():
        fig, axes = plotting.plt.subplots(2, 3, figsize=(11, 7), layout="constrained")
        for i, ax in enumerate(axes.flat):
            image = ax.imshow(np.arange(80 * 84.0).reshape(80, 84) ** (1 + i / 3))
            fig.colorbar(image, ax=ax, label="offset (pixel)")
            ax.set_title(f"a long title of panel {i}, with units (1e-4 pixel)")
        fig.suptitle("layout")
        return fig

    kept = figure()
    plotting.save(kept, tmp_path / "kept.png", pdf=tmp_path / "kept.pdf")
    fresh = figure()
    fresh.savefig(tmp_path / "fresh.pdf")
    assert (tmp_path / "kept.pdf").read_bytes().startswith(b"%PDF") and (tmp_path / "kept.png").stat().st_size
    moved = max(np.abs(np.subtract(a.get_position().bounds, b.get_position().bounds)).max()
                for a, b in zip(kept.axes, fresh.axes))
    assert len(kept.axes) == 12 and moved < 2e-3, moved
