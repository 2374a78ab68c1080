"""The paper's experimental figures, built from small synthetic products: what each draws."""

import matplotlib.colors
import numpy as np
import pytest

from dice_core import allan, astrometry, plotting
from test_allan import allan_inputs
from test_astrometry import centroid_datasets

USED = (3, 9)


@pytest.fixture
def residuals_product(rng):
    """A residuals product of 12 positions, 3-9 used, for two modes; and its centroid datasets."""
    datasets = centroid_datasets(rng)
    rows, residuals = astrometry.mode_accuracies(datasets, positions=USED, trials=50)
    return astrometry.residuals_dataset(datasets, rows, residuals), datasets


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
        assert "[pixel]" in ax.get_xlabel() and "[pixel]" in ax.get_ylabel()
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
