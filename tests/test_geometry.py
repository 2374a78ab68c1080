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


def large_bench(x, y, side, period, midpoint, angle, rng, tip_off=(1e-3, 1e-3)):
    """Pixel phases at ``x``, ``y`` of a detector ``side`` pixels wide (tips 600 mm away about ``midpoint``, m,
    from its centre, spaced for ``period`` pixel along ``angle``), with white offsets of 1e-3 pixel and noise of
    3e-5 pixel; nominal tips ``tip_off`` (m) off. Returns the phases, the true tips (2, 3), the nominal tips,
    k_plane (the true mean gradient) and a check of a fit: the tips within 4 sigma of the true ones (along what
    the data pin, and each coordinate) and the offsets at their noise (benchmarks/staged_tips.py's benches)."""
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
    nominal = (off_by(a, tip_off[0], rng), off_by(b, tip_off[1], rng))

    def check(fit):
        assert_pinned_tips_refined(fit, np.array([a, b]))
        assert np.all(np.abs(fit.tips - np.array([a, b])) < 4 * fit.tip_errors)
        truth = (gx * dx + gy * dy) / k_norm
        affine = np.array([np.ones(x.size), x, y])
        assert rms(fit.offsets - remove_modes(remove_modes(truth, affine), fit.modes)) < 1.1 * noise

    return theta, np.array([a, b]), nominal, (gx.mean(), gy.mean()), check


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
def test_a_large_detector_s_tips_are_refined_from_its_centre_out(caplog, monkeypatch, side, period, midpoint,
                                                                 angle):
    """A detector 2048 or 4096 pixels wide (49 or 98 mm at 24 um), nominal tips 1 mm off: beyond the affine part
    their surface departs from the true one by radians at the edges, past the +-pi a wrapped residual shows,
    and a refinement over every pixel at once wandered for 30 iterations. Refined in stages, over discs from
    the centre out, the tips are within 4 sigma of the true ones along what the data pin and the offsets are
    at their noise; on the 80x84 bench of the other tests, one stage of every pixel (as before stages)."""
    rng = np.random.default_rng(0)  # tips off along directions that made the refinement before stages wander
    step = side // 128  # every pixel's geometry, on a 128x128 grid of them
    rows, cols = np.mgrid[0:side:step, 0:side:step]
    x, y = cols.ravel().astype(float), rows.ravel().astype(float)
    theta, _, nominal, k_plane, check = large_bench(x, y, side, period, midpoint, angle, rng)
    with caplog.at_level("INFO", logger="dice_core.geometry"):
        fit = fit_two_source(theta, x, y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)
    assert "(stage 2," in caplog.text
    check(fit)
    with monkeypatch.context() as patch:  # the control: every pixel at once, as before stages, does not converge
        patch.setattr(geometry, "STAGE_PHASE_LIMIT", np.inf)
        with pytest.raises(geometry.GeometryError, match="did not converge"):
            fit_two_source(theta, x, y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)
    caplog.clear()
    a, b = bench_tips(period, midpoint, angle)
    phase, gx, gy = two_source_phase(X, Y, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    with caplog.at_level("INFO", logger="dice_core.geometry"):
        fit_two_source(np.angle(np.exp(1j * phase)), X, Y, off_by(a, 1e-3, rng), off_by(b, 1e-3, rng),
                       wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=(gx.mean(), gy.mean()))
    assert "refined in" in caplog.text and "stage" not in caplog.text


@pytest.mark.parametrize("positions, period, seed", [("regular", 2.4, 0), ("random", 4.0, 1)])
def test_sparse_pixels_of_a_very_large_detector_start_each_stage_from_their_searched_plane(caplog, monkeypatch,
                                                                                          positions, period, seed):
    """256x256 pixels of an 8192x8192 detector (197 mm at 24 um; a pixel every 32, or at random), nominal tips 1 mm
    off: the first disc of the stages spans hundreds of pixels, and across it the plane carried in (the
    plane-wave solution's less the nominal surface's mean gradient over every pixel) was radians off at its edge,
    past the +-pi a wrapped residual shows; the refinement did not converge on these seeds (benchmarks/
    staged_tips.py: 9 of 16 regular, 11 of 16 random converged). Each stage's plane is now searched for within
    its 3-sigma error (the periodogram's peak): the tips are within 4 sigma and the offsets at their noise."""
    rng = np.random.default_rng(seed)
    side = 8192
    if positions == "regular":
        rows, cols = np.mgrid[0:side:32, 0:side:32]
    else:
        rows, cols = np.divmod(rng.choice(side * side, 256 * 256, replace=False), side)
    x, y = cols.ravel().astype(float), rows.ravel().astype(float)
    theta, _, nominal, k_plane, check = large_bench(x, y, side, period, (0.012, 0.006) if period == 2.4 else
                                                 (-0.011, -0.010), 0.035 if period == 2.4 else 1.545, rng)
    with caplog.at_level("INFO", logger="dice_core.geometry"):
        fit = fit_two_source(theta, x, y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)
    assert "(stage 3," in caplog.text
    check(fit)
    with monkeypatch.context() as patch:  # the control: no search (a grid of one point), as before it
        patch.setattr(geometry, "STAGE_PLANE_POINTS", 0)
        with pytest.raises(geometry.GeometryError, match="did not converge"):
            fit_two_source(theta, x, y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)


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


def two_source_case(rng, shape=(77, 73), origin=(10, 2), dead=0.05, noise=1e-3):
    """Pixel phases of a bench (tips 600 mm away, a period of 2.4 pixel, nominal tips 1 mm off) over a
    ``shape`` (rows, cols) of pixels from ``origin`` (col, row), a fraction ``dead`` of them left out at
    random (dead pixels: the pixels are no grid), offsets of ``noise`` pixel rms: theta, x, y, the true
    tips, the nominal ones and the plane wavevector."""
    rows, cols = np.indices(shape)
    keep = rng.uniform(size=rows.size) >= dead
    x, y = cols.ravel()[keep] + float(origin[0]), rows.ravel()[keep] + float(origin[1])
    a, b = bench_tips(2.4, (0.012, 0.005), 0.03)
    shift = (np.array([origin[0] + shape[1] / 2, origin[1] + shape[0] / 2]) - [41.5, 39.5]) * PITCH
    a, b = (np.array([*(t[:2] + shift), t[2]]) for t in (a, b))
    dx, dy = noise * rng.standard_normal((2, x.size))
    phase, gx, gy = two_source_phase(x + dx, y + dy, a, b, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    theta = np.angle(np.exp(1j * (1.3 + phase)))
    return theta, x, y, (a, b), (off_by(a, 1e-3, rng), off_by(b, 1e-3, rng)), (gx.mean(), gy.mean())


def test_the_tips_refinement_in_blocks_of_pixels_is_the_whole_array_s(rng):
    """The refinement's sums over the pixels come from the R of [1 | x | y | J | psi] taken 333 pixels at a
    time (16 whole blocks and a partial one of 5,300-odd pixels with dead ones among them): J'J and J'psi of
    the affine-free parts, |psi|^2 and the plane's coefficients against the whole-array formulas (the
    Jacobian over every pixel, its affine part taken out by a least-squares fit of every pixel, in extended
    precision: the affine part is 2e6 times the rest, which float64 keeps to 1e-10 of it) to 1e-10 of their
    scale (measured 5e-12; 3e-11 for the float64 projection on an orthonormal basis of before); the fit is
    the same in blocks of 333 and in one block, and its offsets, plane-wave departure and offsets_of are
    those of the whole-array projections."""
    theta, x, y, _, nominal, k_plane = two_source_case(rng)
    assert x.size % 333 and x.size // 333 > 10
    tips, constant, plane = np.array(nominal), 0.7, np.array([0.01, -0.02])
    pixels = geometry._PhasePixels(theta, x, y, WAVELENGTH, PITCH, 333)
    R = pixels.sums(tips, constant, plane)
    # the whole-array formulas, in extended precision (an affine fit by normal equations of centred coordinates)
    jac = geometry.tip_jacobian(x, y, *tips, wavelength=WAVELENGTH, pixel_pitch=PITCH) * 1e-3
    phase, _, _ = two_source_phase(x, y, *tips, wavelength=WAVELENGTH, pixel_pitch=PITCH)
    psi = np.angle(np.exp(1j * (theta - phase - constant - plane[0] * x - plane[1] * y)))
    wide = np.longdouble
    A = np.column_stack([np.ones_like(x), x - x.mean(), y - y.mean()]).astype(wide)
    B = np.column_stack([jac, psi]).astype(wide)
    coef = np.array([[wide(v) for v in row] for row in np.linalg.solve((A.T @ A).astype(float), np.eye(3))])
    coef = coef @ (A.T @ B)
    for _ in range(2):  # refined: the float64 inverse of A'A alone leaves 1e-16 of the affine part
        coef += np.array(np.linalg.solve((A.T @ A).astype(float), (A.T @ (B - A @ coef)).astype(float)), wide)
    free = (B - A @ coef).astype(float)
    JtJ, Jtpsi = free[:, :6].T @ free[:, :6], free[:, :6].T @ free[:, 6]
    np.testing.assert_allclose(R[3:9, 3:9].T @ R[3:9, 3:9], JtJ, rtol=0, atol=1e-10 * np.abs(JtJ).max())
    np.testing.assert_allclose(R[3:9, 3:9].T @ R[3:9, 9], Jtpsi, rtol=0, atol=1e-10 * np.abs(Jtpsi).max())
    assert np.sum(R[3:, 9] ** 2) == pytest.approx(np.sum(free[:, 6] ** 2), rel=1e-10)
    # the plane of psi - J step: R's coefficients (J less its centre value) with the centre's J step
    step = rng.standard_normal(6)
    whole = np.linalg.lstsq(np.column_stack([np.ones_like(x), x, y]), psi - jac @ step, rcond=None)[0]
    found = geometry._affine_coefficients(R)
    found = found[:, 6] - found[:, :6] @ step
    found[0] -= pixels.jacobian_centre(tips) @ step
    np.testing.assert_allclose(found, whole, rtol=0, atol=1e-10 * np.abs(whole).max())

    options = dict(wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)
    blocked, one = (fit_two_source(theta, x, y, *nominal, block=block, **options) for block in (333, 10**9))
    assert blocked.iterations == one.iterations and len(blocked.modes) == len(one.modes) >= 1
    np.testing.assert_allclose(blocked.tips, one.tips, rtol=0, atol=1e-10)
    for name in ("offsets", "plane_wave_departure", "modes", "k_local"):
        np.testing.assert_allclose(getattr(blocked, name), getattr(one, name), rtol=0, atol=1e-9, err_msg=name)
    np.testing.assert_allclose(blocked.surface, one.surface, rtol=1e-11, atol=0)  # 600-800 rad
    # the offsets and departure against the whole-array projections (remove_modes: a basis by SVD each)
    affine, k_norm = geometry.affine_basis(x, y), np.hypot(*blocked.k_local.T)
    psi = np.angle(np.exp(1j * (theta - blocked.surface)))
    expected = remove_modes(remove_modes(psi / k_norm, affine), blocked.modes)
    np.testing.assert_allclose(blocked.offsets, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(blocked.plane_wave_departure, remove_modes(blocked.surface, affine) / k_norm,
                               rtol=0, atol=1e-10 * np.abs(blocked.surface).max())
    other = theta + 0.02 * np.sin(x / 7.0)  # another gauge's phases
    psi = fringes.wrapped_about_mean(other - blocked.surface, block=10**9)
    expected = remove_modes(remove_modes(psi / k_norm, affine), blocked.modes)
    np.testing.assert_allclose(blocked.offsets_of(other), expected, rtol=0, atol=1e-12)
    assert np.allclose(blocked.modes @ np.vstack([affine, blocked.modes]).T / x.size,
                       np.hstack([np.zeros((len(blocked.modes), 3)), np.eye(len(blocked.modes))]), atol=1e-10)


def test_the_plane_and_the_wrap_in_blocks_of_pixels_are_the_whole_array_s(rng):
    """projected_offsets, wrapped_about_mean and the affine removal in blocks of 7 of 5,300-odd pixels (dead
    ones among them, a partial last block) against the whole-array formulas: the complex mean of every
    phase, a least-squares plane of every pixel, a basis of the affine fields by SVD."""
    theta, x, y, _, _, k_plane = two_source_case(rng)
    phase = theta + 3.0  # spread about pi: a wrap about zero would split them
    centre = np.angle(np.mean(np.exp(1j * phase)))
    np.testing.assert_allclose(geometry.wrapped_about_mean(phase, block=7),
                               np.angle(np.exp(1j * (phase - centre))), rtol=0, atol=1e-12)
    values = np.sin(x / 9.0) + 1e-3 * x - 2e-3 * y + 5.0
    np.testing.assert_allclose(geometry._without_affine(values, x, y, block=7),
                               remove_modes(values, geometry.affine_basis(x, y)), rtol=0, atol=1e-12)
    k, offsets = fringes.projected_offsets(theta, x, y, k_plane, block=7)
    design = np.column_stack([np.ones_like(x), x, y])  # the plane of every pixel, after the same unwrapping
    psi = np.angle(np.exp(1j * (theta - k[0] * x - k[1] * y)))
    psi = np.angle(np.exp(1j * (psi - np.angle(np.mean(np.exp(1j * psi))))))
    coef = np.linalg.lstsq(design, psi, rcond=None)[0]
    assert np.hypot(*coef[1:]) < 1e-12  # k is the plane's own wavevector
    np.testing.assert_allclose(offsets, (psi - design @ coef) / np.hypot(*k), rtol=0, atol=1e-12)


def test_the_tips_refinement_never_holds_the_jacobian_over_every_pixel(rng):
    """fit_two_source's peak of traced memory on 200,000 pixels: its outputs (80 bytes a pixel) and the SVD of
    its modes' fields (80 with 5 modes), under 180 bytes a pixel (measured 162); 224 when the Jacobian and its
    affine-free copy (96 bytes a pixel) were formed over every pixel. offsets_of and projected_offsets hold
    under 48 bytes a pixel above what is held (measured 24 and 32; 96 and 80 with whole-array bases, designs
    and complex temporaries)."""
    import tracemalloc

    theta, x, y, _, nominal, k_plane = two_source_case(rng, shape=(400, 500), origin=(0, 0), dead=0.0)
    tracemalloc.start()
    try:
        fit = fit_two_source(theta, x, y, *nominal, wavelength=WAVELENGTH, pixel_pitch=PITCH, k_plane=k_plane)
        held, peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        fit.offsets_of(theta)
        after, offsets_peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        fringes.projected_offsets(theta, x, y, k_plane)
        plane_peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(fit.modes) == 5
    assert peak < 180 * x.size, peak / x.size
    assert offsets_peak - held < 48 * x.size, (offsets_peak - held) / x.size
    assert plane_peak - after < 48 * x.size, (plane_peak - after) / x.size
