"""Superimpositions of the star pattern: Procrustes against exact transforms and the dense fit, bad input, the
configured models. The projective and pose models: tests/test_pose.py."""

import numpy as np
import pytest

from dice_core import accuracies, superimposition

# the simulator's layout: a central star and the corners of a 40-pixel square (x, y)
LAYOUT = np.array([[46.0, 40.0], [26.0, 20.0], [66.0, 20.0], [26.0, 60.0], [66.0, 60.0]])


def transformed(rng, n_positions, layout=LAYOUT):
    """Positions that differ by translation, anisotropic scale and rotation only (stage-like sizes)."""
    params = np.column_stack([rng.normal(0, 1, n_positions), rng.normal(0, 1, n_positions),
                              rng.normal(0, 2e-4, n_positions), rng.normal(0, 2e-4, n_positions),
                              rng.normal(0, 2e-3, n_positions)])
    return np.array([superimposition._transform(q, layout) for q in params])


def test_translation_anisotropic_scale_and_rotation_leave_zero_residual(rng):
    result = superimposition.procrustes(transformed(rng, 33))
    assert result.rms < 1e-12
    # the residuals of the barycentre method are not zero: it cannot absorb scale or rotation
    assert np.sqrt(np.mean(accuracies.barycentre_residuals(transformed(rng, 33)) ** 2)) > 1e-3


def test_bad_input(rng):
    configurations = transformed(rng, 10)
    with pytest.raises(superimposition.AstrometryError, match="2 star\\(s\\): at least 3"):
        superimposition.procrustes(configurations[:, :2])
    configurations[4, 2, 0] = np.nan
    with pytest.raises(superimposition.AstrometryError, match="NaN"):
        accuracies.accuracy(configurations)


def test_the_fast_superimposition_agrees_with_the_dense_fit(rng):
    """The Schur-complement Levenberg-Marquardt against MINPACK's dense one on the same jittered data."""
    configurations = transformed(rng, 33) + 1e-4 * rng.standard_normal((33, 5, 2))
    fast = superimposition.procrustes(configurations)
    c = superimposition.check_configurations(configurations)
    centres = c.mean(axis=1)
    start = ((c - centres[:, None, :]).mean(axis=0) + centres.mean(axis=0),
             np.column_stack([centres - centres.mean(axis=0), np.zeros((33, 3))]))
    dense_mean, dense_params = superimposition._dense_procrustes(c, *start)
    dense = c - superimposition._model(dense_mean, dense_params)
    np.testing.assert_allclose(fast.residuals, dense, rtol=0, atol=1e-9)
    # the gauge: zero mean translation, rotation and isotropic log-scale of the transforms
    np.testing.assert_allclose(fast.params[:, [0, 1, 4]].mean(axis=0), 0, atol=1e-12)
    assert abs(fast.params[:, 2:4].mean()) < 1e-12


def test_a_barely_constrained_stretch_ends_with_the_dense_fit_logged(rng, caplog):
    """Three configurations whose rolls differ by 1e-6 rad: the x/y stretch of the mean shape is nearly free,
    and where the fit stops along it moves the residuals only a little (docs/astrometry.md)."""
    params = np.column_stack([rng.normal(0, 1, 3), rng.normal(0, 1, 3), rng.normal(0, 2e-4, 3),
                              rng.normal(0, 2e-4, 3), 1e-6 * rng.standard_normal(3)])
    configurations = np.array([superimposition._transform(q, LAYOUT) for q in params])
    configurations += 1e-4 * rng.standard_normal(configurations.shape)
    with caplog.at_level("WARNING", logger="dice_core.superimposition"):
        result = superimposition.procrustes(configurations, max_iterations=20)
    assert "dense Levenberg-Marquardt ends the fit" in caplog.text
    c = superimposition.check_configurations(configurations)
    centres = c.mean(axis=1)
    start = ((c - centres[:, None, :]).mean(axis=0) + centres.mean(axis=0),
             np.column_stack([centres - centres.mean(axis=0), np.zeros((3, 3))]))
    dense = np.sqrt(np.mean((c - superimposition._model(*superimposition._dense_procrustes(c, *start))) ** 2))
    assert result.rms == pytest.approx(dense, rel=0.02)


def test_configured_superimpositions_put_procrustes_first_once_and_refuse_unknown_names():
    assert superimposition.configured_superimpositions("procrustes") == ["procrustes"]
    assert superimposition.configured_superimpositions("pose") == ["procrustes", "pose"]
    assert superimposition.configured_superimpositions(["pose", "procrustes", "pose", "projective"]) == [
        "procrustes", "pose", "projective"]
    with pytest.raises(superimposition.AstrometryError, match="unknown superimposition 'affine'"):
        superimposition.configured_superimpositions(["pose", "affine"])
