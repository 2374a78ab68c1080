"""Accuracies: the Monte Carlo correction factors and error bars, groups of positions, barycentre residuals, the
accuracy tables and residual products."""

import numpy as np
import pytest

from dice_core import accuracies, superimposition
from test_superimposition import LAYOUT, transformed


def test_correction_factor_for_five_stars_is_the_papers_1_4(rng):
    """10 coordinates per position, 5 absorbed by its transform, and the mean shape fitted too (10
    numbers less 4 gauge freedoms): the residuals keep (10 N - 5 N - 6) / 10 N of a white jitter's
    variance, so the factor is about sqrt(2), 1.41 for many positions; the paper found 1.4."""
    n = 33
    result = superimposition.procrustes(transformed(rng, n))
    factor, error = accuracies.correction_factor(result)
    assert error < 0.005
    assert factor == pytest.approx(np.sqrt(2 * 5 * n / (2 * 5 * n - 5 * n - 2 * 5 + 4)), rel=0.02)
    assert 1.38 < factor < 1.5
    # the first-order Monte Carlo agrees with full nonlinear superimpositions of jittered data
    configurations = superimposition._model(result.mean, result.params)
    ratios = [1e-4 / superimposition.procrustes(configurations + 1e-4 * rng.standard_normal(configurations.shape)).rms
              for _ in range(30)]
    assert np.mean(ratios) == pytest.approx(factor, rel=0.02)


def test_corrected_accuracy_recovers_the_injected_jitter_within_its_error_bar(rng):
    """Over 40 data sets, the Monte Carlo error bar covers the injected jitter as a 1-sigma bar should.
    Each star has its own jitter; the accuracy is their rms."""
    per_star = np.array([0.5, 1.0, 1.2, 1.5, 0.8]) * 1e-4
    jitter = np.sqrt(np.mean(per_star**2))
    inside, deviations = 0, []
    for _ in range(40):
        configurations = transformed(rng, 33)
        configurations += per_star[None, :, None] * rng.standard_normal(configurations.shape)
        result = accuracies.accuracy(configurations, trials=500)
        deviations.append((result.accuracy - jitter) / result.error)
        inside += abs(result.accuracy - jitter) < result.error
    assert 0.5 <= inside / 40 <= 0.9  # 68% expected
    assert np.max(np.abs(deviations)) < 3.5
    assert abs(np.mean(deviations)) < 0.5  # unbiased


def test_groups_of_contiguous_positions(rng):
    configurations = transformed(rng, 33)
    groups = accuracies.group_means(configurations, 3)
    assert groups.shape == (3, 5, 2)
    np.testing.assert_allclose(groups[1], configurations[11:22].mean(axis=0))
    with pytest.raises(superimposition.AstrometryError, match="2 position\\(s\\) for 3 groups"):
        accuracies.group_means(configurations[:2], 3)


def test_the_central_star_is_barely_absorbed_the_corners_much(rng):
    """Per-star factors (docs/astrometry.md): the transforms have little leverage on the centre."""
    factors = accuracies.star_factors(superimposition.procrustes(transformed(rng, 33)))
    assert factors[0] < 1.25 and np.all(factors[1:] > 1.45)


def centroid_datasets(rng, n_positions=12, modes=("raw", "flat"), jitter=2e-4):
    """Centroid products (x, y per position and star) of the simulator's layout, one per mode."""
    import xarray as xr

    out = {}
    for mode in modes:
        c = transformed(rng, n_positions) + jitter * rng.standard_normal((n_positions, 5, 2))
        out[mode] = xr.Dataset({"x": (("position", "star"), c[..., 0]), "y": (("position", "star"), c[..., 1])},
                               coords={"position": np.arange(1, n_positions + 1), "star": np.arange(5)},
                               attrs={"mode": mode, "method": "fourier"})
    return out


def test_residuals_product_holds_each_stars_mean_position(rng):
    """star_x, star_y: each star's mean centroid over the positions where it was measured, per mode."""
    datasets = centroid_datasets(rng)
    datasets["flat"]["x"][10, 2] = np.nan  # star 2 unmeasured at position 11, outside the range used
    rows, residuals = accuracies.mode_accuracies(datasets, positions=(3, 9), trials=50)
    product = accuracies.residuals_dataset(datasets, rows, residuals=residuals)
    assert product["star_x"].dims == ("mode", "star") and product["star_x"].attrs["units"] == "pixel"
    assert product["star_y"].attrs["units"] == "pixel" and "mean centroid" in product["star_y"].attrs["long_name"]
    for mode, ds in datasets.items():
        for s in range(5):
            x, y = ds["x"].values[:, s], ds["y"].values[:, s]
            assert float(product["star_x"].sel(mode=mode)[s]) == pytest.approx(x[np.isfinite(x)].sum()
                                                                               / np.isfinite(x).sum(), abs=1e-12)
            assert float(product["star_y"].sel(mode=mode)[s]) == pytest.approx(y.mean(), abs=1e-12)
    # the pattern: the central star in the middle of the corners
    np.testing.assert_allclose(product["star_x"].sel(mode="raw"), LAYOUT[:, 0], atol=3)


def test_accuracy_tables_gather_every_method_mode_and_superimposition(rng):
    """The accuracy table's logic (moved from the workflow step, issue 13): methods in the configured order,
    those without products left out, one row per method, mode, grouping and superimposition, the first
    method's residual product per superimposition, pose reports refusing what the data cannot support."""
    fourier = centroid_datasets(rng, modes=("raw", "flat+metrology"))
    gaussian = {m: ds.assign_attrs(method="gaussian") for m, ds in centroid_datasets(rng, modes=("raw",)).items()}
    # translations, rotations and isotropic scales only (an anisotropic scale is a tilt's signature)
    params = np.column_stack([rng.normal(0, 1, (12, 2)), np.repeat(rng.normal(0, 2e-4, (12, 1)), 2, axis=1),
                              rng.normal(0, 2e-3, 12)])
    rigid = np.array([superimposition._transform(q, LAYOUT) for q in params]) + 2e-4 * rng.standard_normal((12, 5, 2))
    gaussian["raw"]["x"].values[:], gaussian["raw"]["y"].values[:] = rigid[..., 0], rigid[..., 1]
    tables = accuracies.accuracy_tables([*fourier.values(), *gaussian.values()], ["gaussian", "fourier", "none"],
                                        models=["procrustes", "pose"], trials=50,
                                        geometry=superimposition.PoseGeometry(centre=None))
    keys = [(r["method"], r["mode"], r["superimposition"], r["grouping"]) for r in tables.rows]
    assert len(keys) == len(set(keys)) == (1 + 2) * 2 * 2
    assert keys[0] == ("gaussian", "raw", "procrustes", "position")
    assert set(tables.residuals) == {"procrustes", "pose"}
    assert tables.residuals["pose"].attrs["superimposition"] == "pose"
    assert list(tables.residuals["pose"]["mode"].values) == ["raw"]  # the first method's
    # no tip-tilt to detect, so no pose accuracy is claimed
    assert np.all(np.isnan(tables.residuals["pose"]["tip_crlb"].values))
    assert "NOT identifiable" in tables.reports["gaussian raw"]
    assert tables.latex.count(r"\begin{tabular}{lcc}") == 4
    # the file can be \input as it is: every macro beyond LaTeX's own is provided in it
    import re

    used = set(re.findall(r"\\([A-Za-z]+)", "\n".join(line for line in tables.latex.splitlines()
                                                         if not line.startswith("%"))))
    provided = set(re.findall(r"\\providecommand\{\\([A-Za-z]+)\}", tables.latex))
    latex_own = {"begin", "end", "hline", "multicolumn", "footnotesize", "pm", "times", "providecommand"}
    assert provided and used - latex_own <= provided, used - latex_own - provided
    csv = accuracies.accuracy_csv(tables.rows).splitlines()
    assert csv[0].endswith(",superimposition,unit") and csv[1].endswith(",procrustes,pixel")
    # header-compatible: the columns before the unit are those of the tables made before it, in their order
    assert csv[0] == "flat,metrology,grouping,accuracy,error,mode,method,n,rms_residual,factor,superimposition,unit"
    # Procrustes rows and residuals are those of the single-model call
    rows, residuals = accuracies.mode_accuracies(gaussian, trials=50)
    assert rows[0]["accuracy"] == tables.rows[0]["accuracy"]
    with pytest.raises(superimposition.AstrometryError, match="no centroid product of the configured methods"):
        accuracies.accuracy_tables(gaussian.values(), ["fourier"])
    with pytest.raises(superimposition.AstrometryError, match="unknown superimposition 'affine'"):
        accuracies.accuracy_tables(gaussian.values(), ["gaussian"], models=["affine"])


def test_the_paper_comparison_reads_only_the_procrustes_rows():
    from dice_core import reproduction

    records = [{"mode": "raw", "grouping": "position", "accuracy": "2e-4", "error": "1e-5"},
               {"mode": "raw", "grouping": "position", "accuracy": "1e-4", "error": "1e-5", "superimposition": "pose"}]
    rows = reproduction.accuracy_rows(records, dataset="d", note="n")
    assert [(row.key, row.ours) for row in rows] == [("accuracy_raw_position", 2e-4)]
