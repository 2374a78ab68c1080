"""Beyond Procrustes: the projective superimposition, the detector pose's inversion and its identifiability.

Star positions come from the simulator's own projection (dice_core.simulation.project_stars), the truth
the astrometry module's independent projection is tested against.
"""

import dataclasses

import numpy as np
import pytest

from dice_core import accuracies, simulation, superimposition

PAPER = simulation.load_preset("config/presets/paper.yaml")


def stage(n_positions, tip_tilt_pv, *, seed=3, constant=False):
    """Simulated star positions (position, star, 2), the true poses and the geometry labelling them."""
    cfg = dataclasses.replace(PAPER, stars=dataclasses.replace(PAPER.stars, positions=n_positions,
                                                               tip_tilt_pv=tip_tilt_pv))
    rng = np.random.default_rng(seed)
    poses = simulation._nominal_poses(cfg.stars)
    poses[:, :2] += 0.01 * rng.standard_normal((n_positions, 2))
    for axis in (3, 4):  # the simulator's random walks, of zero mean
        walk = np.cumsum(rng.standard_normal(n_positions))
        poses[:, axis] = 0.0 if constant else (walk - walk.mean()) * tip_tilt_pv / np.ptp(walk)
    poses[:, 5] = 1e-4 * rng.standard_normal(n_positions)
    pattern = simulation._nominal_pattern(cfg.stars)
    rows, cols = cfg.detector.shape
    geometry = superimposition.PoseGeometry(distance=cfg.stars.distance, off_axis=np.radians(cfg.stars.off_axis_deg),
                                            centre=((cols - 1) / 2, (rows - 1) / 2))
    directions = np.column_stack([(pattern[:, 0] - geometry.centre[0]) / geometry.distance
                                  + np.tan(geometry.off_axis), (pattern[:, 1] - geometry.centre[1]) / geometry.distance])
    return simulation.project_stars(pattern, poses, cfg=cfg), poses, directions, geometry


def test_the_projection_is_the_simulators_and_its_jacobian_the_derivative():
    positions, poses, directions, geometry = stage(6, 5e-3)
    np.testing.assert_allclose(superimposition.pose_project(directions, poses, geometry), positions, rtol=0, atol=1e-9)
    _, jacobian = superimposition.pose_project(directions, poses, geometry, jacobian=True)
    x0 = np.concatenate([directions.ravel(), poses.ravel()])

    def model(x):
        return superimposition.pose_project(x[:10].reshape(5, 2), x[10:].reshape(-1, 6), geometry).ravel()

    for k in range(x0.size):
        step = 1e-3 if k >= 10 and (k - 10) % 6 < 3 else 1e-7  # pixel, or rad and tangents
        up, down = x0.copy(), x0.copy()
        up[k] += step
        down[k] -= step
        numeric = (model(up) - model(down)) / (2 * step)
        assert np.max(np.abs(numeric - jacobian[:, k])) <= 1e-5 * np.max(np.abs(jacobian[:, k])) + 1e-9


def test_the_gauge_is_a_turn_of_the_bench_about_the_pinhole_and_the_constraints_fix_it():
    """Exactly 3 null directions (a rotation about the pinhole), and the fit's rows remove them."""
    _, poses, directions, geometry = stage(12, 5e-3)
    _, jacobian = superimposition.pose_project(directions, poses, geometry, jacobian=True)
    scaled = jacobian / np.linalg.norm(jacobian, axis=0)
    singular = np.linalg.svd(scaled, compute_uv=False)
    assert np.sum(singular < 1e-12 * singular[0]) == 3
    assert singular[-4] > 1e-11 * singular[0]  # the distance's near-gauge is not exact
    # a rotation of the whole bench about the pinhole leaves every position in place
    rotation, _ = superimposition._axis_rotations(np.array([[2e-3, -1e-3, 5e-3]]))
    rotation = rotation[0]
    origin = np.array([geometry.distance * np.tan(geometry.off_axis), 0, geometry.distance]) + poses[:, :3]
    turned_d = np.column_stack([directions, np.ones(5)]) @ rotation.T
    turned_r, _ = superimposition._axis_rotations(poses[:, 3:])
    turned_r = rotation @ turned_r
    moved = poses.copy()
    moved[:, :3] = origin @ rotation.T - (origin - poses[:, :3])  # the detector's centre turned too
    # the turned orientations back to angles R = Rz Ry Rx
    moved[:, 4] = -np.arcsin(turned_r[:, 2, 0])
    moved[:, 3] = np.arctan2(turned_r[:, 2, 1], turned_r[:, 2, 2])
    moved[:, 5] = np.arctan2(turned_r[:, 1, 0], turned_r[:, 0, 0])
    np.testing.assert_allclose(superimposition.pose_project(turned_d[:, :2] / turned_d[:, 2:], moved, geometry),
                               superimposition.pose_project(directions, poses, geometry), rtol=0, atol=1e-8)
    constraints, _ = superimposition._pose_constraints(5, 12)
    stacked = np.vstack([scaled, constraints / np.linalg.norm(jacobian, axis=0)])
    assert np.linalg.matrix_rank(stacked, tol=1e-12 * np.linalg.norm(stacked, 2)) == stacked.shape[1]


def test_the_pose_fit_recovers_the_simulators_poses_without_noise():
    positions, poses, directions, geometry = stage(33, 5e-3)
    result = superimposition.pose(positions, geometry=geometry)
    assert result.rms < 1e-9
    # the field's direction is held where the stars' mean position points, off the truth by the stage's
    # mean translation (1.3e-3 pixel, 5e-8 in tangent here): tip and tilt follow it by 2e-8 rad
    np.testing.assert_allclose(result.field, directions.mean(axis=0), rtol=0, atol=1e-7)
    np.testing.assert_allclose(result.poses[:, 3:5], poses[:, 3:5], rtol=0, atol=1e-7)
    # the gauge: the roll's mean is the bench's turn about z
    np.testing.assert_allclose(result.poses[:, 5], poses[:, 5] - poses[:, 5].mean(), rtol=0, atol=1e-8)
    np.testing.assert_allclose(result.directions, directions, rtol=0, atol=1e-7)
    # Procrustes cannot absorb the tip-tilt's shear and projective terms; the homography nearly can
    assert superimposition.procrustes(positions).rms > 1e-4
    assert superimposition.projective(positions).rms < 0.1 * superimposition.procrustes(positions).rms


def test_holding_the_near_gauges_at_a_wrong_bench_costs_only_second_order():
    """A nominal off-axis angle 10% off and a distance 2% off leave 2.3e-6 pixel rms: 1/2000 of the variance
    of centroid errors of 1e-4 pixel."""
    positions, _, _, geometry = stage(33, 5e-3)
    wrong = dataclasses.replace(geometry, off_axis=geometry.off_axis * 1.1, distance=geometry.distance * 1.02)
    assert superimposition.pose(positions, geometry=wrong).rms < 5e-6


def test_recovered_tip_and_tilt_agree_with_truth_within_their_bound_where_identifiable(rng):
    positions, poses, _, geometry = stage(33, 2e-2)
    positions = positions + 1e-4 * rng.standard_normal(positions.shape)
    result = superimposition.pose(positions, geometry=geometry)
    report = superimposition.pose_identifiability(result)
    assert report.all_identifiable, report.summary()
    tip, tilt, tip_bound, tilt_bound = report.tip_tilt()
    for fitted, true, bound in ((tip, poses[:, 3], tip_bound), (tilt, poses[:, 4], tilt_bound)):
        normalised = (fitted - true) / bound
        assert np.sqrt(np.mean(normalised**2)) < 1.5
        assert np.max(np.abs(normalised)) < 4
    # with the field's direction known (the simulation's), the bound is the fit's own scatter
    for k in (3, 4):
        normalised = (result.poses[:, k] - poses[:, k]) / report.crlb_nominal_field[:, k]
        assert 0.6 < np.sqrt(np.mean(normalised**2)) < 1.5
    assert report.sigma == pytest.approx(1e-4, rel=0.15)


@pytest.mark.parametrize("case", ["constant tip-tilt", "3 positions"])
def test_an_unidentifiable_pose_is_said_and_no_accuracy_claimed(rng, case):
    positions, *_, geometry = (stage(33, 5e-3, constant=True) if case == "constant tip-tilt" else stage(3, 5e-3))
    positions = positions + 1e-4 * rng.standard_normal(positions.shape)
    report = superimposition.pose_identifiability(superimposition.pose(positions, geometry=geometry))
    assert not report.identifiable["tip"] and not report.identifiable["tilt"]
    assert "do not sample the tip" in report.summary()
    with pytest.raises(superimposition.PoseUnidentifiable, match="no pose accuracy can be reported"):
        report.tip_tilt()


def test_homographies_leave_zero_residual_and_the_projective_factor(rng):
    layout = simulation._nominal_pattern(PAPER.stars)
    n = 20
    h = np.column_stack([1 + 1e-3 * rng.standard_normal(n), 1e-3 * rng.standard_normal(n), rng.normal(0, 1, n),
                         1e-3 * rng.standard_normal(n), 1 + 1e-3 * rng.standard_normal(n), rng.normal(0, 1, n),
                         1e-6 * rng.standard_normal(n), 1e-6 * rng.standard_normal(n)])
    configurations = superimposition._homography_apply(layout, h)[0]
    result = superimposition.projective(configurations)
    assert result.rms < 1e-10
    # 2SN coordinates, 8N homography and 2(S - 4) shape parameters: 2N - 2 degrees of freedom of 10N
    factor, error = accuracies.correction_factor(result, trials=1000)
    assert factor == pytest.approx(np.sqrt(10 * n / (2 * n - 2)), rel=0.03)
    with pytest.raises(superimposition.AstrometryError, match="at least 5"):
        superimposition.projective(configurations[:, :4])


@pytest.mark.parametrize("model", ["projective", "pose"])
def test_each_models_accuracy_recovers_injected_jitter(rng, model):
    positions, _, _, geometry = stage(12, 5e-3)
    estimates = []
    for _ in range(4):
        noisy = positions + 1e-4 * rng.standard_normal(positions.shape)
        result = accuracies.accuracy(noisy, model=model, geometry=geometry, trials=300)
        estimates.append((result.accuracy - 1e-4) / result.error)
    assert abs(np.mean(estimates)) < 1.2  # unbiased within the bars: the model absorbs the tip-tilt
    assert np.max(np.abs(estimates)) < 3.5
    with pytest.raises(superimposition.AstrometryError, match="unknown superimposition"):
        accuracies.accuracy(positions, model="affine")


def twins(*, nominal_off_axis_deg, n_positions=40, tip_tilt_pv=1.2e-2, sigma=5e-5, seed=27):
    """Twin stages, tilted and not, of a bench the presets never use: the field on the detector's axis (the
    presets: 2 degrees off), five stars on a 30-pixel square off the detector's centre, a tip-tilt walk of
    ``tip_tilt_pv`` rad peak to valley, and one draw of white centroid errors of ``sigma`` pixel that both
    share (a photon noise of the same seed). Returns the tilted and untilted centroids, the true tip and tilt
    (position, 2) and the pose geometry labelled with ``nominal_off_axis_deg``."""
    out = []
    for pv in (tip_tilt_pv, 0.0):
        cfg = simulation.SimulationConfig.from_dict({
            "seed": seed, "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]},
            "stars": {"positions": n_positions, "tip_tilt_pv": pv, "off_axis_deg": 0.0, "pattern_side": 30.0,
                      "pattern_centre": [40.0, 36.0]}})
        truth = simulation.make_truth(cfg)
        out.append((np.stack([truth["star_x"].values, truth["star_y"].values], axis=-1), truth))
    errors = sigma * np.random.default_rng(seed).standard_normal(out[0][0].shape)
    geometry = superimposition.PoseGeometry(25000.0, np.radians(nominal_off_axis_deg), (41.5, 39.5))
    return out[0][0] + errors, out[1][0] + errors, out[0][1]["stage_rotation"].values[:, :2], geometry


def removals(tilted, untilted, true_tip_tilt, geometry):
    from dice_core import studies

    pair = {model: [accuracies.accuracy(c, model=model, geometry=geometry, trials=300) for c in (tilted, untilted)]
            for model in ("procrustes", "pose")}
    found = studies.tip_tilt_removals(pair["procrustes"], pair["pose"], tilted=tilted, untilted=untilted,
                                      true_tip_tilt=true_tip_tilt, trials=300)
    return {name: value for name, (value, _) in found.items()}, pair


def test_the_pose_removes_what_the_data_allow_of_the_tip_tilt_where_the_bench_is_known():
    """Issue 27: on twins whose field is on the axis, the tip-tilt shows only through second-order terms
    (keystone and anisotropic scale, 4e-5 to 1e-4 pixel here). With the bench's geometry given, the pose
    removes Procrustes's excess to the noise-limited bound of its Fisher information (seeds 27-29:
    measured 0.93-0.99 against bounds of 0.94-0.96, 0.99-1.03 of them), the true tip and tilt through the
    model remove all of it, and the bound from the data alone is the one from the twins' true signature
    (within 0.01). Held at the presets' 2 degrees instead (a bench it was not tuned to), the model predicts
    for the true tip-tilt a shear the bench does not have (the true tip and tilt 'remove' -52 to -87
    times the excess), the pose falls to 0.79-0.89 of the bound, and the data say that its tip-tilt is not
    identifiable (SNR 0.2-0.5): the geometry must be the bench's (docs/astrometry.md, "Tip-tilt removal").
    Before issue 27 none of these was computed. 5 s on 2 shared cores."""
    tilted, untilted, true_tip_tilt, geometry = twins(nominal_off_axis_deg=0.0)
    found, _ = removals(tilted, untilted, true_tip_tilt, geometry)
    assert found["pose_removal_bound"] > 0.9  # the tip-tilt is well above the noise
    assert found["pose_removal"] >= 0.9 * found["pose_removal_bound"], found
    assert found["pose_removal_true_tip_tilt"] > 0.99, found
    assert found["pose_removal_bound_data"] == pytest.approx(found["pose_removal_bound"], abs=0.05)
    wrong = dataclasses.replace(geometry, off_axis=np.radians(2.0))
    found, pair = removals(tilted, untilted, true_tip_tilt, wrong)
    assert found["pose_removal_true_tip_tilt"] < 0, found
    report = superimposition.pose_identifiability(pair["pose"][0].result, sigma=pair["pose"][0].accuracy)
    assert not report.all_identifiable and "not" in report.summary().lower()


def test_near_the_noise_the_pose_removes_what_the_bound_allows_over_seeds():
    """Issue 27, part 3: near the noise (the field on the axis, the tip-tilt's signature of second order,
    a bound of 0.6-0.7), the share the pose removes scatters from one draw of the noise to the next (the
    issue's twins: 0.80 to 1.31 of the bound over nine seeds), so the claim is over seeds. On fast twins of a
    bench the presets never use (five stars on a 30-pixel square off centre, 40 positions, 6e-3 rad peak to
    valley, white errors of 5e-5 pixel; seeds 27-29) the pose removes at least 0.9 of the bound on average
    (measured 0.80 against 0.66), and the true tip and tilt remove all of it. 7 s on 2 idle cores."""
    removed, bounds = [], []
    for seed in (27, 28, 29):
        tilted, untilted, true_tip_tilt, geometry = twins(nominal_off_axis_deg=0.0, tip_tilt_pv=6e-3, seed=seed)
        found, _ = removals(tilted, untilted, true_tip_tilt, geometry)
        assert 0.5 < found["pose_removal_bound"] < 0.8, found  # the regime: near the noise
        assert found["pose_removal_true_tip_tilt"] > 0.98, found
        removed.append(found["pose_removal"])
        bounds.append(found["pose_removal_bound"])
    assert np.mean(removed) >= 0.9 * np.mean(bounds), (removed, bounds)


@pytest.mark.slow  # simulated images of 4 x 2 x 60 positions x 240 frames and their fits: 109 s on 2 idle cores
def test_on_the_issues_twins_the_pose_reaches_the_bound_over_seeds():
    """Issue 27, part 3, on simulated images: the issue's twins (the star-accuracy bench with the field on
    the axis, 60 positions of 240 frames, photon and read noise, 8e-3 rad peak to valley), seeds
    20150926-29. The first is the draw on which the pose removed 0.80 of the bound; over the four it removes
    at least 0.9 of it on average (measured 1.02: 0.79, 1.03, 1.20, 1.08 with 300 trials), the true tip and
    tilt all of it (0.98-1.01)."""
    from dice_core import studies

    ratios = []
    for seed in range(20150926, 20150930):
        centroids = {}
        for amplitude in (0.0, 8e-3):
            settings = studies.apply_overrides(studies.STAR_ACCURACY_BENCH, {
                "seed": seed, "stars.positions": 60, "stars.tip_tilt_pv": amplitude, "stars.frames": 240,
                "stars.off_axis_deg": 0.0, "detector.photon_noise": True, "detector.read_noise": 4.0})
            centroids[amplitude] = studies.flat_metrology_centroids(settings)
        (tilted, truth, geometry), (untilted, _, _) = centroids[8e-3], centroids[0.0]
        found, _ = removals(tilted, untilted, truth["stage_rotation"].values[:, :2], geometry)
        assert found["pose_removal_true_tip_tilt"] > 0.95, (seed, found)
        ratios.append(found["pose_removal_over_bound"])
    assert np.mean(ratios) >= 0.9, ratios
