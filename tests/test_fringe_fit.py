"""The streaming fringe fit: the same solution, bit for bit, whichever way its passes run (one process, worker
processes, or jobs that write their states and parts to netCDF products)."""

import numpy as np
import pytest

from dice_core import fringe_fit, fringes
from dice_core.io import FrameStream, read_product
from test_fringes import fit, simulate


def test_worker_processes_give_the_same_solution_bit_for_bit(tmp_path, caplog):
    """Files are reduced in fixed consecutive lanes, in worker processes or one after the other."""
    manifest, truth = simulate(tmp_path, metrology={"frames": 1200}, frames_per_file=300)
    assert len(manifest.baselines["H1H4"].files) == 4
    with caplog.at_level("INFO", logger="dice_core.fringe_fit"):
        one, two = (fit(manifest, truth, "H1H4", workers=n) for n in (1, 2))
    assert "reads 2 part(s) of the frames, in 1 process(es)" in caplog.text
    assert "reads 2 part(s) of the frames, in 2 process(es)" in caplog.text
    for name in ("offsets", "photon_floor", "iota", "alpha", "k", "k_frame", "level", "amplitude", "phase"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)
    assert one.history == two.history
    # lanes are a summation order, not a different estimate
    whole = fit(manifest, truth, "H1H4", stream=list(FrameStream(manifest.baselines["H1H4"], manifest.detector)))
    np.testing.assert_allclose(whole.offsets, one.offsets, rtol=0, atol=1e-9)


def split_fit(manifest, truth, baseline, folder, *, parts, flat=True, bad_pixels=None, **options):
    """The fit as a split workflow runs it: a start, then each pass's parts and its reduction as separate
    steps, every state and part written to netCDF in ``folder`` and read back, and the finish."""
    import xarray as xr

    from dice_core.io import write_product

    stream = FrameStream(manifest.baselines[baseline], manifest.detector)
    state = fringe_fit.start_fit(stream, truth["bias"].values, detector=manifest.detector,
                                 flat=truth["sensitivity"].values if flat else None, bad_pixels=bad_pixels,
                                 label=baseline, **options)
    path = folder / "state_0.nc"
    write_product(fringe_fit.state_dataset(state), path, title="state")
    for n_pass in range(1, state.options["max_passes"] + 1):
        paths = []
        for part in range(parts):
            with xr.open_dataset(path, engine="netcdf4") as ds:
                # a part reads its projector and reference only: nothing else of the state is needed
                needed = ds[["projector", "offset", "pixels", "centre"]] if "projector" in ds else ds
                paths.append(folder / f"part_{n_pass}_{part}.nc")
                write_product(fringe_fit.part_dataset(stream, needed, part=part, parts=parts), paths[-1], title="part")
        path = folder / f"state_{n_pass}.nc"
        write_product(fringe_fit.reduce_dataset(read_product(folder / f"state_{n_pass - 1}.nc"), paths), path,
                      title="state")
    return fringe_fit.finish_fit(fringe_fit.state_from_dataset(read_product(path)), detector=manifest.detector,
                                 read_noise=truth["read_noise"].values)


def assert_same_solution(one, two):
    for name in ("rows", "cols", "offsets", "photon_floor", "iota", "alpha", "k", "k_frame", "level", "amplitude",
                 "phase", "masked", "pixel_phase", "offsets_prnu_free"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)
    assert one.history == two.history and one.masked_by_reason == two.masked_by_reason
    assert one.gauge_difference_floor == two.gauge_difference_floor


def test_a_fit_split_across_jobs_is_the_single_fit_bit_for_bit(tmp_path, caplog):
    """Four files, in 2 parts (the default), 3 (halves of unequal parts for the gauge floor) and 5 (a part
    without files): each pass's parts reduced separately into netCDF products, summed in part order by
    another step, the state written between passes: the single process's solution, bit for bit. Dead
    pixels (not in a mask) leave the fit at pass 1 for no contrast, hot pixels (not in a mask either) are
    saturated in some frames of some parts, two pixels are flagged in a bad-pixel mask, and a tolerance the fit
    cannot meet masks pixels at the end: all as in the single fit."""
    manifest, truth = simulate(tmp_path, metrology={"frames": 1200}, frames_per_file=300,
                               detector={"dead_pixels": 3, "hot_pixels": 2, "hot_level": 55000.0})
    assert len(manifest.baselines["H1H4"].files) == 4
    mask = np.zeros_like(truth["bad_pixel"].values)
    assert not truth["bad_pixel"].values[[40, 41], [50, 20]].any()
    mask[40, 50] = mask[41, 20] = 1  # flagged dead in the mask (working in fact): left out all the same
    for parts in (2, 3, 5):
        with caplog.at_level("INFO", logger="dice_core.fringe_fit"):
            caplog.clear()
            single = fit(manifest, truth, "H1H4", parts=parts, bad_pixels=mask)
            single_log = caplog.text
            caplog.clear()
            (tmp_path / f"split{parts}").mkdir()
            split = split_fit(manifest, truth, "H1H4", tmp_path / f"split{parts}", parts=parts, bad_pixels=mask)
        assert_same_solution(single, split)
        assert single.masked_by_reason["no_contrast"] > 0  # pixels that left during the passes
        assert single.masked_by_reason["saturated"] == 2 and single.masked_by_reason["bad_pixel"] == 2
        n_pass = single.history[-1]["pass"]
        assert f"converged to 1.0e-07 pixel at pass {n_pass}" in single_log and n_pass < 10
        assert f"converged to 1.0e-07 pixel at pass {n_pass}" in caplog.text
        assert f"done after pass {n_pass} (converged): state carried over" in caplog.text
    assert "the frames make 4 part(s): part 5 has no file" in caplog.text
    xr_single = fringes.solution_dataset(single, manifest.detector)
    xr_split = fringes.solution_dataset(split, manifest.detector)
    xr_single.attrs, xr_split.attrs = {}, {}
    assert xr_single.identical(xr_split)
    # not converged after max_passes: the same pixels masked, from the state the last reduction wrote
    tolerance = 0.9 * fit(manifest, truth, "H1H4", max_passes=2).history[-1]["max_change"]
    single = fit(manifest, truth, "H1H4", max_passes=2, tolerance=tolerance)
    (tmp_path / "unconverged").mkdir()
    split = split_fit(manifest, truth, "H1H4", tmp_path / "unconverged", parts=2, max_passes=2,
                      tolerance=tolerance)
    assert split.masked_by_reason["unconverged"] > 0
    assert_same_solution(single, split)
    # parts summed out of their order, or of another pass, or a file that is not a state: errors naming files
    folder = tmp_path / "split2"
    state_0 = read_product(folder / "state_0.nc")
    with pytest.raises(fringes.FringeError, match="out of part order: .*part_1_1.nc"):
        fringe_fit.reduce_dataset(state_0, [folder / "part_1_1.nc", folder / "part_1_0.nc"])
    with pytest.raises(fringes.FringeError, match="do not match the state after pass 0 .*part_2_0.nc"):
        fringe_fit.reduce_dataset(state_0, [folder / "part_2_0.nc", folder / "part_2_1.nc"])
    with pytest.raises(fringes.FringeError, match="part_1_0.nc: not a split fringe-fit state"):
        fringe_fit.state_from_dataset(read_product(folder / "part_1_0.nc"))
    # a state made with other options than the run's (a rerun by file times only) is refused, naming it
    made = {key: state_0.attrs[f"fit_{key}"] for key in ("tolerance", "max_passes", "smooth_degree")}
    fringe_fit.check_state_options(state_0, **made)
    with pytest.raises(fringes.FringeError, match=r"state_0.nc: made with metrology.max_passes = \d+, the run has 99"):
        fringe_fit.check_state_options(state_0, **{**made, "max_passes": 99})


def test_the_finish_in_blocks_of_97_pixels_is_the_finish_in_one_block(tmp_path, monkeypatch):
    """A spherical-wave fit in two files (two halves for the gauge floor) with two pixels of a bad-pixel mask
    and a tolerance the last pass does not meet (the pixels still moving masked at the finish, so that the
    halves' pixels are not the active ones): finished with every sweep over the pixels in blocks of 97 of
    5,600-odd pixels (the gauges, the phases and pixel factors of the diagnostic, the photon floor, the
    tips' refinement, the planes and affine fits; a partial last block) and in one block, the same solution
    to rounding (the tips' refinement, whose weakest mode the prior sets, moves the offsets by up to 1e-9
    pixel). The state is spent by its finish."""
    from dice_core import pixel_blocks, simulation
    from dice_core.geometry import BaselineGeometry
    from dice_core.manifest import load_manifest

    cfg = simulation.SimulationConfig.from_dict({
        "name": "blocks-test", "frames_per_file": 500,
        "detector": {"shape": [80, 84], "science_rows": [2, 79], "science_cols": [10, 83], "prf_width_spread": 0.0},
        "dark": {"frames": 2}, "flats": {"frames": 2}, "stars": {"positions": 1, "frames": 1},
        "metrology": {"frames": 1000, "spherical": True, "tip_error": [1.0e-3, 1.0e-3], "pairs": {},
                      "baselines": {"H1H4": {"period": 2.4, "angle_deg": 2.0, "midpoint": [0.012, 0.006]}}},
    })
    manifest = load_manifest(simulation.simulate_dataset(cfg, tmp_path))
    truth = read_product(tmp_path / "truth.nc")
    mask = np.zeros(manifest.detector.shape, bool)
    mask[40, 50] = mask[41, 20] = True
    stream = FrameStream(manifest.baselines["H1H4"], manifest.detector)

    def done_state(**options):
        state = fringe_fit.start_fit(stream, truth["bias"].values, detector=manifest.detector,
                                     flat=truth["sensitivity"].values, bad_pixels=mask, label="H1H4", **options)
        lanes = fringe_fit.fit_stream(stream, state.next_pass).split(2)
        while not state.done:
            results = [fringe_fit.accumulate_part(lane, state.next_pass) for lane in lanes]
            state = fringe_fit.reduce_pass(state, results, n_lanes=len(lanes))
        return state

    tolerance = 0.3 * done_state(max_passes=2).history[-1]["max_change"]
    state = done_state(max_passes=2, tolerance=tolerance)
    saved = fringe_fit.state_dataset(state)
    geometry = BaselineGeometry.of_baseline(manifest.geometry, "H1H4",
                                            wavelength=manifest.baseline_wavelength("H1H4"))

    def finish():
        return fringe_fit.finish_fit(fringe_fit.state_from_dataset(saved), detector=manifest.detector,
                                     read_noise=truth["read_noise"].values, geometry=geometry)

    one = finish()
    assert one.masked_by_reason["bad_pixel"] == 2 and one.masked_by_reason["unconverged"] >= 1
    assert len(state.parts) == 2 and state.parts_idx.size > (~one.masked).sum()
    assert one.rows.size > 50 * 97 and (~one.masked).sum() % 97
    monkeypatch.setattr(pixel_blocks, "PIXEL_BLOCK", 97)
    blocked = finish()
    assert one.gauge_difference_floor is not None and len(one.two_source.modes) >= 1
    for name in ("offsets", "offsets_prnu_free"):
        np.testing.assert_allclose(getattr(blocked, name), getattr(one, name), rtol=0, atol=1e-9, err_msg=name)
    for name in ("iota", "alpha", "pixel_phase", "level", "amplitude", "phase"):  # before the tips
        np.testing.assert_allclose(getattr(blocked, name), getattr(one, name), rtol=1e-13, atol=0, err_msg=name)
    for name in ("photon_floor", "k"):  # over the local |K| of the refined tips
        np.testing.assert_allclose(getattr(blocked, name), getattr(one, name), rtol=1e-10, atol=0, err_msg=name)
    np.testing.assert_array_equal(blocked.masked, one.masked)
    np.testing.assert_allclose(blocked.two_source.tips, one.two_source.tips, rtol=0, atol=1e-9)
    np.testing.assert_allclose(blocked.two_source.modes, one.two_source.modes, rtol=0, atol=1e-7)
    assert blocked.gauge_difference_floor == pytest.approx(one.gauge_difference_floor, rel=1e-9)
    fringe_fit.finish_fit(state, detector=manifest.detector, read_noise=truth["read_noise"].values)
    assert state.G is None and state.parts == []  # spent
    with pytest.raises(ValueError, match="finished already"):
        fringe_fit.finish_fit(state, detector=manifest.detector)
