"""Procrustes superimposition, its Monte Carlo correction factor and error bars, barycentre residuals."""

import numpy as np
import pytest

from dice_core import astrometry

# the simulator's layout: a central star and the corners of a 40-pixel square (x, y)
LAYOUT = np.array([[46.0, 40.0], [26.0, 20.0], [66.0, 20.0], [26.0, 60.0], [66.0, 60.0]])


def transformed(rng, n_positions, layout=LAYOUT):
    """Positions that differ by translation, anisotropic scale and rotation only (stage-like sizes)."""
    params = np.column_stack([rng.normal(0, 1, n_positions), rng.normal(0, 1, n_positions),
                              rng.normal(0, 2e-4, n_positions), rng.normal(0, 2e-4, n_positions),
                              rng.normal(0, 2e-3, n_positions)])
    return np.array([astrometry._transform(q, layout) for q in params])


def test_translation_anisotropic_scale_and_rotation_leave_zero_residual(rng):
    result = astrometry.procrustes(transformed(rng, 33))
    assert result.rms < 1e-12
    # the residuals of the barycentre method are not zero: it cannot absorb scale or rotation
    assert np.sqrt(np.mean(astrometry.barycentre_residuals(transformed(rng, 33)) ** 2)) > 1e-3


def test_correction_factor_for_five_stars_is_the_papers_1_4(rng):
    """10 coordinates per position, 5 absorbed by its transform, and the mean shape fitted too (10
    numbers less 4 gauge freedoms): the residuals keep (10 N - 5 N - 6) / 10 N of a white jitter's
    variance, so the factor is about sqrt(2), 1.41 for many positions; the paper found 1.4."""
    n = 33
    result = astrometry.procrustes(transformed(rng, n))
    factor, error = astrometry.correction_factor(result)
    assert error < 0.005
    assert factor == pytest.approx(np.sqrt(2 * 5 * n / (2 * 5 * n - 5 * n - 2 * 5 + 4)), rel=0.02)
    assert 1.38 < factor < 1.5
    # the first-order Monte Carlo agrees with full nonlinear superimpositions of jittered data
    configurations = astrometry._model(result.mean, result.params)
    ratios = [1e-4 / astrometry.procrustes(configurations + 1e-4 * rng.standard_normal(configurations.shape)).rms
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
        result = astrometry.accuracy(configurations, trials=500)
        deviations.append((result.accuracy - jitter) / result.error)
        inside += abs(result.accuracy - jitter) < result.error
    assert 0.5 <= inside / 40 <= 0.9  # 68% expected
    assert np.max(np.abs(deviations)) < 3.5
    assert abs(np.mean(deviations)) < 0.5  # unbiased


def test_groups_of_contiguous_positions(rng):
    configurations = transformed(rng, 33)
    groups = astrometry.group_means(configurations, 3)
    assert groups.shape == (3, 5, 2)
    np.testing.assert_allclose(groups[1], configurations[11:22].mean(axis=0))
    with pytest.raises(astrometry.AstrometryError, match="2 position\\(s\\) for 3 groups"):
        astrometry.group_means(configurations[:2], 3)


def test_bad_input(rng):
    configurations = transformed(rng, 10)
    with pytest.raises(astrometry.AstrometryError, match="2 star\\(s\\): at least 3"):
        astrometry.procrustes(configurations[:, :2])
    configurations[4, 2, 0] = np.nan
    with pytest.raises(astrometry.AstrometryError, match="NaN"):
        astrometry.accuracy(configurations)


def test_the_central_star_is_barely_absorbed_the_corners_much(rng):
    """Per-star factors (docs/astrometry.md): the transforms have little leverage on the centre."""
    factors = astrometry.star_factors(astrometry.procrustes(transformed(rng, 33)))
    assert factors[0] < 1.25 and np.all(factors[1:] > 1.45)


def test_the_fast_superimposition_agrees_with_the_dense_fit(rng):
    """The Schur-complement Levenberg-Marquardt against MINPACK's dense one on the same jittered data."""
    configurations = transformed(rng, 33) + 1e-4 * rng.standard_normal((33, 5, 2))
    fast = astrometry.procrustes(configurations)
    c = astrometry._check(configurations)
    centres = c.mean(axis=1)
    start = ((c - centres[:, None, :]).mean(axis=0) + centres.mean(axis=0),
             np.column_stack([centres - centres.mean(axis=0), np.zeros((33, 3))]))
    dense_mean, dense_params = astrometry._dense_procrustes(c, *start)
    dense = c - astrometry._model(dense_mean, dense_params)
    np.testing.assert_allclose(fast.residuals, dense, rtol=0, atol=1e-9)
    # the gauge: zero mean translation, rotation and isotropic log-scale of the transforms
    np.testing.assert_allclose(fast.params[:, [0, 1, 4]].mean(axis=0), 0, atol=1e-12)
    assert abs(fast.params[:, 2:4].mean()) < 1e-12


def test_a_barely_constrained_stretch_ends_with_the_dense_fit_logged(rng, caplog):
    """Three configurations whose rolls differ by 1e-6 rad: the x/y stretch of the mean shape is nearly free,
    and where the fit stops along it moves the residuals only a little (docs/astrometry.md)."""
    params = np.column_stack([rng.normal(0, 1, 3), rng.normal(0, 1, 3), rng.normal(0, 2e-4, 3),
                              rng.normal(0, 2e-4, 3), 1e-6 * rng.standard_normal(3)])
    configurations = np.array([astrometry._transform(q, LAYOUT) for q in params])
    configurations += 1e-4 * rng.standard_normal(configurations.shape)
    with caplog.at_level("WARNING", logger="dice_core.astrometry"):
        result = astrometry.procrustes(configurations, max_iterations=20)
    assert "dense Levenberg-Marquardt ends the fit" in caplog.text
    c = astrometry._check(configurations)
    centres = c.mean(axis=1)
    start = ((c - centres[:, None, :]).mean(axis=0) + centres.mean(axis=0),
             np.column_stack([centres - centres.mean(axis=0), np.zeros((3, 3))]))
    dense = np.sqrt(np.mean((c - astrometry._model(*astrometry._dense_procrustes(c, *start))) ** 2))
    assert result.rms == pytest.approx(dense, rel=0.02)


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
    rows, residuals = astrometry.mode_accuracies(datasets, positions=(3, 9), trials=50)
    product = astrometry.residuals_dataset(datasets, rows, residuals=residuals)
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
    rigid = np.array([astrometry._transform(q, LAYOUT) for q in params]) + 2e-4 * rng.standard_normal((12, 5, 2))
    gaussian["raw"]["x"].values[:], gaussian["raw"]["y"].values[:] = rigid[..., 0], rigid[..., 1]
    tables = astrometry.accuracy_tables([*fourier.values(), *gaussian.values()], ["gaussian", "fourier", "none"],
                                        models=["procrustes", "pose"], trials=50,
                                        geometry=astrometry.PoseGeometry(centre=None))
    keys = [(r["method"], r["mode"], r["superimposition"], r["grouping"]) for r in tables.rows]
    assert len(keys) == len(set(keys)) == (1 + 2) * 2 * 2
    assert keys[0] == ("gaussian", "raw", "procrustes", "position")
    assert set(tables.residuals) == {"procrustes", "pose"}
    assert tables.residuals["pose"].attrs["superimposition"] == "pose"
    assert list(tables.residuals["pose"]["mode"].values) == ["raw"]  # the first method's
    # no tip-tilt to detect, so no pose accuracy is claimed
    assert np.all(np.isnan(tables.residuals["pose"]["tip_crlb"].values))
    assert "NOT identifiable" in tables.reports["gaussian raw"]
    assert tables.latex.count(r"\begin{tabular}") == 4
    csv = astrometry.accuracy_csv(tables.rows).splitlines()
    assert csv[0].endswith(",superimposition") and csv[1].endswith(",procrustes")
    # Procrustes rows and residuals are those of the single-model call
    rows, residuals = astrometry.mode_accuracies(gaussian, trials=50)
    assert rows[0]["accuracy"] == tables.rows[0]["accuracy"]
    with pytest.raises(astrometry.AstrometryError, match="no centroid product of the configured methods"):
        astrometry.accuracy_tables(gaussian.values(), ["fourier"])
    with pytest.raises(astrometry.AstrometryError, match="unknown superimposition 'affine'"):
        astrometry.accuracy_tables(gaussian.values(), ["gaussian"], models=["affine"])


def test_the_paper_comparison_reads_only_the_procrustes_rows():
    from dice_core import reproduction

    records = [{"mode": "raw", "grouping": "position", "accuracy": "2e-4", "error": "1e-5"},
               {"mode": "raw", "grouping": "position", "accuracy": "1e-4", "error": "1e-5", "superimposition": "pose"}]
    rows = reproduction.accuracy_rows(records, dataset="d", note="n")
    assert [(row.key, row.ours) for row in rows] == [("accuracy_raw_position", 2e-4)]


def test_configured_superimpositions_put_procrustes_first_once_and_refuse_unknown_names():
    assert astrometry.configured_superimpositions("procrustes") == ["procrustes"]
    assert astrometry.configured_superimpositions("pose") == ["procrustes", "pose"]
    assert astrometry.configured_superimpositions(["pose", "procrustes", "pose", "projective"]) == [
        "procrustes", "pose", "projective"]
    with pytest.raises(astrometry.AstrometryError, match="unknown superimposition 'affine'"):
        astrometry.configured_superimpositions(["pose", "affine"])
