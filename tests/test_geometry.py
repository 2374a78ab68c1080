"""Spherical-wave reduction against known truth: tip refinement, local-wavevector offsets, unobservable modes."""

import numpy as np
import pytest

from dice_core import deprojection, fringes, geometry, simulation, studies
from dice_core.geometry import fit_two_source, remove_modes, two_source_phase

PITCH, WAVELENGTH, DISTANCE = 24e-6, 633e-9, 0.6
ROWS, COLS = np.mgrid[2:79, 10:83]
X, Y = COLS.ravel().astype(float), ROWS.ravel().astype(float)
AFFINE = np.array([np.ones_like(X), X, Y])


def rms(values):
    return float(np.sqrt(np.nanmean(np.square(values))))


def assert_pinned_tips_refined(fit, true_tips):
    """Along each tip mode the data pin (the declared ones), the refined tips are within 4 sigma of the true
    ones; along the best pinned one, the defocus, the nominal tips were not: the refinement did the work."""
    error, start = (np.ravel(t) - np.ravel(true_tips) for t in (fit.tips, fit.nominal))
    for k in np.flatnonzero(fit.information > geometry.MODE_INFORMATION_THRESHOLD):
        v = fit.tip_modes[:, k]
        sigma = np.sqrt(v @ fit.tip_covariance @ v)
        assert abs(v @ error) < 4 * sigma, k
    v = fit.tip_modes[:, 0]
    assert abs(v @ start) > 4 * np.sqrt(v @ fit.tip_covariance @ v)


def bench_tips(period, midpoint, angle):
    """Two tips 600 mm away about ``midpoint`` (m, from the detector centre), spaced for ``period`` pixel."""
    length = WAVELENGTH * DISTANCE / (period * PITCH)
    direction = np.array([np.cos(angle), np.sin(angle)])
    mid = np.array([41.5, 39.5]) * PITCH + np.asarray(midpoint)
    return (np.array([*(mid - 0.5 * length * direction), DISTANCE]),
            np.array([*(mid + 0.5 * length * direction), DISTANCE]))


def off_by(tip, length, rng):
    error = rng.standard_normal(3)
    return tip + length * error / np.linalg.norm(error)


def test_tip_jacobian_is_the_derivative_of_the_phase():
    a, b = bench_tips(2.4, (0.01, 0.004), 0.03)
    jac = geometry.tip_jacobian(X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    step = 1e-7
    for j in range(6):
        tips = [a.copy(), b.copy()]
        tips[j // 3][j % 3] += step
        ahead, _, _ = two_source_phase(X, Y, *tips, wavelength=WAVELENGTH, pixel_pitch=PITCH)
        tips[j // 3][j % 3] -= 2 * step
        behind, _, _ = two_source_phase(X, Y, *tips, wavelength=WAVELENGTH, pixel_pitch=PITCH)
        numeric = (ahead - behind) / (2 * step)
        assert np.max(np.abs(jac[:, j] - numeric)) < 1e-6 * np.max(np.abs(numeric))


def test_orthonormal_modes_are_orthonormal_and_orthogonal_to_what_they_are_made_against(rng):
    fields = rng.standard_normal((3, 500)) + AFFINE[:, :500].mean(axis=1)[:, None]
    against = AFFINE[:, :500]
    modes = geometry.orthonormal_modes(np.vstack([fields, fields[0] + 2 * fields[1]]), against=against)
    assert modes.shape == (3, 500)  # the dependent fourth field adds no mode
    assert np.allclose(modes @ modes.T / 500, np.eye(3), atol=1e-12)
    assert np.allclose(modes @ against.T, 0, atol=1e-9)
    cleaned = remove_modes(fields[2], modes)
    assert np.allclose(cleaned @ modes.T, 0, atol=1e-9)


@pytest.mark.parametrize("period, midpoint, angle", [(2.4, (0.012, 0.005), 0.03), (4.0, (-0.008, 0.015), 1.55)])
def test_pixel_phases_give_offsets_at_their_noise_against_the_refined_surface(rng, period, midpoint, angle):
    """Nominal tips 1 mm off; pixel offsets of 1e-3 pixel rms and phase noise of 3e-5 pixel: the offsets
    along each local wavevector, once the affine part and the declared modes are removed from the truth
    too, are within 1.1 x the noise, where a plane-wave fit misses by more than 10 x."""
    a, b = bench_tips(period, midpoint, angle)
    dx, dy = 1e-3 * rng.standard_normal((2, X.size))
    phase, _, _ = two_source_phase(X + dx, Y + dy, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    _, gx, gy = two_source_phase(X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    k_norm = np.hypot(gx, gy)
    noise = 3e-5
    theta = np.angle(np.exp(1j * (1.3 - phase + noise * k_norm * rng.standard_normal(X.size))))  # runs along -Phi
    k_plane, plane_offsets = fringes.projected_offsets(theta, X, Y, -np.array([gx.mean(), gy.mean()]))
    nominal = (off_by(a, 1e-3, rng), off_by(b, 1e-3, rng))
    fit = fit_two_source(theta, X, Y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)
    assert fit.sign == -1
    truth = -(gx * dx + gy * dy) / k_norm
    assert np.allclose(fit.k_local, -np.column_stack([gx, gy]), rtol=0, atol=2e-5 * k_norm.mean())
    # the tips' z difference (a defocus) at least; at most 5, the sixth tip mode being an exact null
    assert 1 <= len(fit.modes) <= 5
    assert np.allclose(fit.modes @ fit.modes.T / X.size, np.eye(len(fit.modes)), atol=1e-10)
    assert np.allclose(fit.offsets @ np.vstack([AFFINE, fit.modes]).T, 0, atol=1e-9)
    expected = remove_modes(remove_modes(truth, AFFINE), fit.modes)
    assert rms(fit.offsets - expected) < 1.1 * noise
    assert rms(plane_offsets - remove_modes(truth, AFFINE)) > 10 * noise
    assert_pinned_tips_refined(fit, np.array([a, b]))


def test_tips_that_do_not_fit_the_phases_are_refused(rng):
    a, b = bench_tips(2.4, (0.01, 0.0), 0.0)
    phase, gx, gy = two_source_phase(X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    theta = np.angle(np.exp(1j * (phase + 1e-4 * np.hypot(gx, gy) * rng.standard_normal(X.size))))
    wrong = (a + [0, 0, 0.02], b - [0, 0, 0.02])  # 20 mm off along z, in opposite ways: a defocus the data see
    with pytest.raises(geometry.GeometryError, match="baseline H1H4: the pixel phases move the tip of fiber F[14] "
                                                     "by .* mm along z"):
        fit_two_source(theta, X, Y, *wrong, wavelength=WAVELENGTH, pixel_pitch=PITCH,
                       k_plane=(gx.mean(), gy.mean()), fibers=("F1", "F4"), label="baseline H1H4")
    # phases that are no fringe at all: the refinement wanders and stops, or the surface does not fit them
    with pytest.raises(geometry.GeometryError, match="tips of fibers a and b (did not converge|by .* rad rms)"):
        fit_two_source(rng.uniform(-np.pi, np.pi, X.size), X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH,
                       k_plane=(gx.mean(), gy.mean()))
    with pytest.raises(ValueError, match="max_iterations must be >= 1"):
        fit_two_source(theta, X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=(gx.mean(), gy.mean()),
                       max_iterations=0)


@pytest.mark.parametrize("side, period, midpoint, angle", [(2048, 2.4, (0.012, 0.006), 0.035),
                                                        (4096, 4.0, (-0.011, -0.010), 1.545)])
def test_a_large_detector_s_tips_are_refined_from_its_centre_out(caplog, side, period, midpoint, angle):
    """A detector 2048 or 4096 pixels wide (49 or 98 mm at 24 um), nominal tips 1 mm off: beyond the affine part
    their surface departs from the true one by radians at the edges, past the +-pi a wrapped residual shows,
    and a refinement over every pixel at once wandered for 30 iterations. Refined in stages, over discs from
    the centre out, the tips are within 4 sigma of the true ones along what the data pin and the offsets are
    at their noise; on the 80x84 bench of the other tests, one stage of every pixel (as before stages)."""
    rng = np.random.default_rng(0)  # tips off along directions that made the refinement before stages wander
    step = side // 128  # every pixel's geometry, on a 128x128 grid of them
    rows, cols = np.mgrid[0:side:step, 0:side:step]
    x, y = cols.ravel().astype(float), rows.ravel().astype(float)
    length = WAVELENGTH * DISTANCE / (period * PITCH)
    direction = np.array([np.cos(angle), np.sin(angle)])
    mid = np.full(2, (side - 1) / 2) * PITCH + np.asarray(midpoint)
    a, b = (np.array([*(mid + sign * length * direction), DISTANCE]) for sign in (-0.5, 0.5))
    dx, dy = 1e-3 * rng.standard_normal((2, x.size))
    phase, _, _ = two_source_phase(x + dx, y + dy, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    _, gx, gy = two_source_phase(x, y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    noise = 3e-5
    k_norm = np.hypot(gx, gy)
    theta = np.angle(np.exp(1j * (0.4 + phase + noise * k_norm * rng.standard_normal(x.size))))
    nominal = (off_by(a, 1e-3, rng), off_by(b, 1e-3, rng))
    with caplog.at_level("INFO", logger="dice_core.geometry"):
        fit = fit_two_source(theta, x, y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH,
                             k_plane=(gx.mean(), gy.mean()))
    assert "(stage 2," in caplog.text
    assert_pinned_tips_refined(fit, np.array([a, b]))
    assert np.all(np.abs(fit.tips - np.array([a, b])) < 4 * fit.tip_errors)
    truth = (gx * dx + gy * dy) / k_norm
    affine = np.array([np.ones(x.size), x, y])
    assert rms(fit.offsets - remove_modes(remove_modes(truth, affine), fit.modes)) < 1.1 * noise
    caplog.clear()
    a, b = bench_tips(period, midpoint, angle)
    phase, gx, gy = two_source_phase(X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    with caplog.at_level("INFO", logger="dice_core.geometry"):
        fit_two_source(np.angle(np.exp(1j * phase)), X, Y, off_by(a, 1e-3, rng), off_by(b, 1e-3, rng),
                       wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=(gx.mean(), gy.mean()))
    assert "refined in" in caplog.text and "stage" not in caplog.text


SPHERICAL_BASELINES = {  # the default preset's periods and angles, midpoints 8-20 mm off the normal
    "H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.012, 0.006]},
    "V1V4": {"period": 2.4, "angle_deg": 93.0, "midpoint": [-0.004, 0.008]},
    "H2H4": {"period": 4.0, "angle_deg": -3.0, "midpoint": [0.016, -0.009]},
    "V2V4": {"period": 4.0, "angle_deg": 88.5, "midpoint": [-0.011, -0.010]},
}


@pytest.fixture(scope="module")
def spherical(tmp_path_factory):
    """A noisy spherical-wave dataset, nominal tips 1 mm off the true ones."""
    cfg = simulation.SimulationConfig.from_dict({
        "name": "spherical-test", "frames_per_file": 100000,
        "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83]},
        "dark": {"frames": 2}, "flats": {"frames": 2}, "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": 2000, "spherical": True, "tip_error": [1.0e-3, 1.0e-3],
                      "baselines": SPHERICAL_BASELINES, "pairs": {"P14": ["H1H4", "V1V4"], "P24": ["H2H4", "V2V4"]}},
    })
    return studies.simulate_and_fit(cfg, tmp_path_factory.mktemp("spherical"))


@pytest.mark.parametrize("baseline", list(SPHERICAL_BASELINES))
def test_spherical_fringes_give_offsets_at_the_photon_floor(spherical, baseline):
    manifest, truth, products = spherical
    solution, product = products[baseline]
    fit = solution.two_source
    active = ~solution.masked
    r, c = solution.rows[active], solution.cols[active]
    tips = dict(zip(truth["fiber"].values, truth["fiber_position"].values))
    true_tips = [tips[f] for f in manifest.geometry.baseline_fibers[baseline]]
    _, gx, gy = two_source_phase(c, r, *true_tips, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    n = fit.sign * np.column_stack([gx, gy]) / np.hypot(gx, gy)[:, None]
    truth_p = n[:, 0] * truth["dx"].values[r, c] + n[:, 1] * truth["dy"].values[r, c]
    affine = np.array([np.ones(r.size), c, r])
    expected = remove_modes(remove_modes(truth_p, affine), fit.modes)
    floor = rms(solution.photon_floor)
    assert rms(solution.offsets[active] - expected) < 1.2 * floor
    # refined tips within 4 sigma of the true ones along what the data pin, from nominal ones 1 mm off
    assert_pinned_tips_refined(fit, true_tips)
    # the plane-wave fit of the same phases misses by the true surface's departure from its best plane
    k_plane, plane_offsets = fringes.projected_offsets(solution.pixel_phase[active], c.astype(float),
                                                       r.astype(float), solution.k)
    n_plane = k_plane / np.hypot(*k_plane)
    plane_truth = remove_modes(n_plane[0] * truth["dx"].values[r, c] + n_plane[1] * truth["dy"].values[r, c], affine)
    phase, _, _ = two_source_phase(c, r, *true_tips, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    departure = remove_modes(phase, affine) / np.hypot(*k_plane)
    assert rms(plane_offsets - plane_truth) == pytest.approx(rms(departure), rel=0.05)
    assert rms(departure) > 4 * floor
    # the product carries the geometry and the modes
    assert list(product["fiber"].values) == list(manifest.geometry.baseline_fibers[baseline])
    assert product["unobservable_offset"].sizes["mode"] == len(fit.modes) >= 1
    assert np.allclose(product["fiber_position"].values, fit.tips)
    assert np.isfinite(product["kx_local"].values[r, c]).all()


def test_spherical_pairs_give_dx_dy_at_the_floor_with_their_modes_declared(spherical):
    manifest, truth, products = spherical
    for pair, (first, second) in manifest.pairs.items():
        offsets = deprojection.offsets_dataset(products[first][1], products[second][1], label=pair)
        good = np.isfinite(offsets["dx"].values)
        rows, cols = np.nonzero(good)
        n = rows.size
        mode_dx, mode_dy = offsets["unobservable_dx"].values, offsets["unobservable_dy"].values
        modes = np.concatenate([mode_dx[:, good], mode_dy[:, good]], axis=1)
        assert 2 <= modes.shape[0] <= 8
        assert np.allclose(modes @ modes.T / (2 * n), np.eye(modes.shape[0]), atol=1e-10)
        one, zero, x, y = np.ones(n), np.zeros(n), cols.astype(float), rows.astype(float)
        affine = np.array([np.concatenate(p) for p in [(one, zero), (x, zero), (y, zero), (zero, one),
                                                        (zero, x), (zero, y)]])
        measured = np.concatenate([offsets["dx"].values[good], offsets["dy"].values[good]])
        assert np.allclose(np.vstack([affine, modes]) @ measured, 0, atol=1e-9)
        true = np.concatenate([truth["dx"].values[good], truth["dy"].values[good]])
        expected = remove_modes(remove_modes(true, affine), modes)
        error_dx, error_dy = (measured - expected)[:n], (measured - expected)[n:]
        assert rms(error_dx) < 1.2 * rms(offsets["dx_photon_noise_floor"].values[good])
        assert rms(error_dy) < 1.2 * rms(offsets["dy_photon_noise_floor"].values[good])


@pytest.mark.parametrize("tilt", [(1e-3, 0.0), (0.0, 1e-3), (0.7e-3, 0.7e-3)])
def test_a_tilted_detector_leaves_less_than_1e_6_pixel(rng, tilt):
    """Pixels at z = t.r (a 1 mrad tilt about the detector centre), reduced with the flat model and the true
    tips: the plane and the declared modes absorb what the tilt does to the phase (docs/metrology.md)."""
    a, b = bench_tips(2.4, (0.015, 0.0), 0.03)
    _, gx, gy = two_source_phase(X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    noise = 1e-3 * np.hypot(gx, gy) * rng.standard_normal(X.size)  # pixel offsets of 1e-3 pixel, as noise
    z = tilt[0] * (X - 41.5) + tilt[1] * (Y - 39.5)
    r = np.stack([X, Y, z], axis=-1) * PITCH
    tilted = 2 * np.pi / WAVELENGTH * (np.linalg.norm(r - a, axis=-1) - np.linalg.norm(r - b, axis=-1))
    flat, _, _ = two_source_phase(X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    fits = [fit_two_source(np.angle(np.exp(1j * (phase + noise))), X, Y, a, b, wavelength=WAVELENGTH,
                           pixel_pitch=PITCH, k_plane=(gx.mean(), gy.mean())) for phase in (tilted, flat)]
    assert rms(tilted - flat) / np.hypot(gx, gy).mean() > 3e-4  # pixel: what the tilt does to the phase
    assert rms(fits[0].offsets - fits[1].offsets) < 5e-7


def test_the_two_pairs_absorb_the_same_modes_so_a_joint_fit_would_pin_none(spherical):
    """docs/metrology.md: the cosines of the principal angles between P14's and P24's mode spaces are all
    near 1, so one offset map for all baselines would pin only their small differences."""
    manifest, truth, products = spherical
    pairs = [deprojection.offsets_dataset(products[a][1], products[b][1]) for a, b in manifest.pairs.values()]
    good = np.isfinite(pairs[0]["dx"].values) & np.isfinite(pairs[1]["dx"].values)
    spaces = [np.concatenate([p["unobservable_dx"].values[:, good], p["unobservable_dy"].values[:, good]], axis=1)
              for p in pairs]
    spaces = [np.linalg.qr(m.T)[0] for m in spaces]
    cosines = np.linalg.svd(spaces[0].T @ spaces[1], compute_uv=False)
    assert cosines.size == 6 and cosines.min() > 0.997


def test_the_pair_difference_maps_are_at_their_floor(spherical):
    """P24 minus P14, both pairs' declared modes and the affine part removed: within 1.2x the two pairs'
    floors added in quadrature (the pair-difference check of the paper, here without stray light)."""
    manifest, truth, products = spherical
    pairs = [deprojection.offsets_dataset(products[a][1], products[b][1]) for a, b in manifest.pairs.values()]
    good = np.isfinite(pairs[0]["dx"].values) & np.isfinite(pairs[1]["dx"].values)
    ddx, ddy, std_dx, std_dy = deprojection.pair_difference(
        pairs[0]["dx"].values, pairs[0]["dy"].values, pairs[1]["dx"].values, pairs[1]["dy"].values,
        modes=[(p["unobservable_dx"].values, p["unobservable_dy"].values) for p in pairs])
    n = int(good.sum())
    difference = np.concatenate([ddx[good], ddy[good]])
    basis = [np.concatenate([mx[good], my[good]]) for p in pairs
             for mx, my in zip(p["unobservable_dx"].values, p["unobservable_dy"].values)]
    assert np.allclose(np.array(basis) @ difference, 0, atol=1e-9)
    for part, name in ((difference[:n], "dx"), (difference[n:], "dy")):
        floor = np.hypot(pairs[0][f"{name}_photon_noise_floor"].values[good],
                         pairs[1][f"{name}_photon_noise_floor"].values[good])
        assert rms(part) < 1.2 * rms(floor), name
