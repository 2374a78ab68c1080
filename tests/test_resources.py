"""Job resources from the dataset's size: the requests cover the measured jobs, and scale with the data."""

import pytest

from dice_core import resources
from dice_core.resources import job_resources

PAPER_PIXELS = 80 * 84
#: MB (1e6 bytes, the model's and the requests' unit) in a MiB (2^20 bytes): benchmarks/allan_memory.py and
#: Snakemake's benchmark files (max_rss, max_pss) report MiB.
MB_PER_MIB = 2**20 / 1e6


@pytest.mark.parametrize("step, frames, max_rss_mib, seconds, pixels", [
    # MiB, as measured (converted to MB below). BENCHMARKS.md, the paper preset (80x84 pixels, 200,000-frame
    # baselines): the benchmark files' max_rss and wall time with other jobs on the cores
    ("fit_fringes", 200_000, 411, 19, PAPER_PIXELS),
    ("allan_deviation", 200_000, 491, 14, PAPER_PIXELS),
    # BENCHMARKS.md, one 20,000-frame metrology file simulated (3.4 s alone), memory_streaming.py's 221 MiB
    ("simulate_file", 20_000, 221, 3.4, PAPER_PIXELS),
    # BENCHMARKS.md, "The Allan job on disk" (library, benchmarks/allan_memory.py: the script's calls in a
    # fresh process, one worker, not through Snakemake): the Allan step's peak (VmHWM) at 190 batches of 42
    # frames on 256x256 and 512x512 pixels, its batches' arrays on disk (before, 2353 MiB at 512x512: 47 bytes
    # a pixel and batch, "Reads and memory of one baseline")
    ("allan_deviation", 8_000, 226, 45.0, 256 * 256),
    ("allan_deviation", 8_000, 273, 195.3, 512 * 512),
    # BENCHMARKS.md, "The single fit's memory through the workflow": fit_fringes jobs (benchmark files, the
    # job with its two reading workers) on the large preset scaled to 256x256 and 512x512, 4000 frames
    ("fit_fringes", 4_000, 481, 13.1, 256 * 256),
    ("fit_fringes", 4_000, 727, 42.0, 512 * 512),
])
def test_requests_cover_the_paper_scale_measurements(step, frames, max_rss_mib, seconds, pixels):
    asked = job_resources(step, pixels=pixels, frames=frames)
    max_rss_mb = max_rss_mib * MB_PER_MIB
    assert asked["mem_mb"] - resources.EXECUTOR_MB >= max_rss_mb
    assert asked["mem_mb"] <= 4 * max_rss_mb + resources.EXECUTOR_MB  # a request, not the whole node
    assert asked["runtime"] * 60 >= seconds


@pytest.mark.parametrize("pixels, workers, tree_pss_mib, tree_rss_mib, share_needed", [
    # BENCHMARKS.md, "The Allan job's memory cut" (library, benchmarks/allan_memory.py, 2000 frames in two
    # files, 47 batches; the batches' fit reaching the workers through their fork): the peak of the job's
    # process tree's summed PSS (its forked workers share its pages) and of their summed RSS (each shared page
    # counted in each process), MiB as the script reports them (its tables say MB). (The rows before the cut,
    # when each worker was sent a pickled copy of the fit: 220/259, 405/738, 587/627 and 1176/1806 MiB.)
    (512 * 512, 1, 232, 247, False),
    (512 * 512, 2, 329, 612, False),
    (1024 * 1024, 1, 496, 527, False),
    (1024 * 1024, 2, 775, 1289, True),
])
def test_the_allan_request_covers_its_worker_processes(pixels, workers, tree_pss_mib, tree_rss_mib, share_needed):
    """The Allan job's request covers its process tree's memory, its workers' with it (each its chunks and its
    batches' sums); without the workers' share it would not cover the two workers' job at 1024x1024 (by the
    RSS; at 512x512 the job's own request covers them now that the workers share the job's fit)."""
    tree_pss_mb, tree_rss_mb = tree_pss_mib * MB_PER_MIB, tree_rss_mib * MB_PER_MIB
    asked = job_resources("allan_deviation", pixels=pixels, frames=2000, workers=workers)
    assert asked["mem_mb"] - resources.EXECUTOR_MB >= tree_rss_mb
    assert asked["mem_mb"] <= 4 * tree_pss_mb + resources.EXECUTOR_MB
    alone = job_resources("allan_deviation", pixels=pixels, frames=2000)
    if workers == 1:
        assert asked == alone
    else:
        assert (alone["mem_mb"] - resources.EXECUTOR_MB < tree_rss_mb) == share_needed
        def memory(workers, chunk_frames="auto"):  # the model's, MB
            return resources.modelled_cost("allan_deviation", pixels=pixels, frames=2000, workers=workers,
                                           chunk_frames=chunk_frames)[0]

        # the workers' share, with the request's margin; each worker holds a chunk as the job does
        share = memory(workers) - memory(1)
        assert asked["mem_mb"] - alone["mem_mb"] == pytest.approx(resources.MEMORY_MARGIN * share, abs=1)
        chunk_grown = memory(1, 32) - memory(1, 4)
        assert chunk_grown > 0
        assert (memory(workers, 32) - memory(workers, 4)) == pytest.approx((workers + 1) * chunk_grown)


def test_the_allan_job_at_4096x4096_is_modelled_under_8_gb_with_two_workers():
    """The issue's goal, by the law fitted at 512x512 and 1024x1024 (modelled, not measured at 4096x4096): the
    Allan job's process tree at 4096x4096 (8000 frames, its chunks of 4 frames) under 8 GB with two workers and
    with one, before the request's margins (7.9 and 5.5 GB; with them, two workers ask 12.3 GB and one 8.7:
    BENCHMARKS.md, "The Allan job's chunk term, measured"). Measured since at 2048x2048 with two workers
    ("The Allan job at 2048x2048, measured"): 6.7-6.9 GB at 4096x4096 by the line through 1024x1024 and
    2048x2048 (extrapolated)."""
    for workers in (1, 2):
        asked = job_resources("allan_deviation", pixels=4096 * 4096, frames=8000, workers=workers)
        assert (asked["mem_mb"] - resources.EXECUTOR_MB) / resources.MEMORY_MARGIN < 8000, (workers, asked)


@pytest.mark.parametrize("pixels, tree_pss_mib, tree_rss_mib", [
    # BENCHMARKS.md, "The Allan job's chunk term, measured" (library, benchmarks/allan_memory.py --chunk-frames 4
    # --workers 2, 2000 frames in two files; MiB, as the script reports them): 4-frame chunks, as a 4096x4096
    # detector reads them
    (512 * 512, 233, 517),
    (1024 * 1024, 587, 1096),
    # "The Allan job at 2048x2048, measured" (the same command, --size 2048: the large preset scaled): 1704 MiB
    # (1787 MB), 2813 MiB (2950 MB)
    (2048 * 2048, 1704, 2813),
])
def test_the_allan_model_covers_its_trees_with_the_chunks_of_a_large_detector(pixels, tree_pss_mib, tree_rss_mib):
    """With 4-frame chunks the model (before margins, MB) covers the tree's measured PSS, and the request its
    RSS (both measured in MiB)."""
    memory, _ = resources.modelled_cost("allan_deviation", pixels=pixels, frames=2000, workers=2, chunk_frames=4)
    assert memory >= tree_pss_mib * MB_PER_MIB
    asked = job_resources("allan_deviation", pixels=pixels, frames=2000, workers=2, chunk_frames=4)
    assert asked["mem_mb"] - resources.EXECUTOR_MB >= tree_rss_mib * MB_PER_MIB


def test_a_baselines_jobs_ask_for_the_workers_their_threads_run():
    """job_data gives the fit and Allan jobs the workers reading_workers gives their rules' threads: two for a
    large baseline in two files, one for a small one; no workers for the other steps."""
    from types import SimpleNamespace

    from dice_core.manifest import Detector

    frames_of = {"a": 2000, "b": 2000, "big1": 200000, "big2": 200000}.get
    detector = Detector(shape=(80, 84), science_rows=(0, 80), science_cols=(0, 84), gain=2.5, saturation=6e4)
    manifest = SimpleNamespace(detector=detector, positions=[], baselines={
        "small": SimpleNamespace(files=["a", "b"]), "large": SimpleNamespace(files=["big1", "big2"])})
    for step in ("allan_deviation", "fit_fringes"):
        small = resources.job_data(step, {"baseline": "small"}, manifest=manifest, frames_of=frames_of, parts=2)
        large = resources.job_data(step, {"baseline": "large"}, manifest=manifest, frames_of=frames_of, parts=2)
        assert (small, large) == ({"frames": 4000, "workers": 1}, {"frames": 400000, "workers": 2}), step
        # the job's threads as Snakemake gives them (the run's cores shared, --set-threads) where known
        for threads in (1, 2, 4):  # a worker a part at most: 4 threads read the two files in two
            given = resources.job_data(step, {"baseline": "large"}, manifest=manifest, frames_of=frames_of,
                                       parts=2, workers=threads)
            assert given == {"frames": 400000, "workers": min(threads, 2)}, step
    assert "workers" not in resources.job_data("fit_finish", {"baseline": "large"}, manifest=manifest,
                                               frames_of=frames_of, parts=2)


@pytest.mark.parametrize("pixels, frames, batches, seconds", [
    # BENCHMARKS.md, "The Allan job's inputs, workers and time" (library, benchmarks/allan_memory.py, batches of
    # 42 frames, load 4-13): the step's wall time (the reading pass, then the statistics: 86-93% of it)
    (512 * 512, 2000, 47, 148.6),
    (1024 * 1024, 2000, 47, 311.4),
    (256 * 256, 8000, 190, 55.4),
])
def test_the_allan_runtime_covers_its_statistics(pixels, frames, batches, seconds):
    """The Allan job's runtime request covers the measured jobs, with their batches known (from the metrology
    product, when the job is about to run) and from its frames alone (batches of ALLAN_BATCH_FRAMES, when the
    workflow is planned: more batches than these, so at least as long). By samples alone (the request before)
    the 1024x1024 job's 311 s were not covered: 5 minutes."""
    known = job_resources("allan_deviation", pixels=pixels, frames=frames, batches=batches)
    planned = job_resources("allan_deviation", pixels=pixels, frames=frames)
    assert known["runtime"] * 60 >= seconds and planned["runtime"] >= known["runtime"]
    assert resources.allan_statistics_size(frames) >= resources.allan_statistics_size(frames, batches)
    cost = resources.step_cost("allan_deviation")
    by_samples = cost.start_s + cost.s_per_gsample * pixels * frames / 1e9
    statistics = cost.s_per_gstatistic * pixels * resources.allan_statistics_size(frames, batches) / 1e9
    assert statistics > by_samples  # the statistics, not the reading, set the time of short batches


def test_the_allan_statistics_grow_with_pixels_batches_and_group_sizes():
    """The statistics' term is pixels x batches x group sizes: 4x the pixels, 4x the term; 4x the batches at the
    same frames (a faster sweep), 4x the batches times their group sizes' ratio."""
    from dice_core.allan import group_sizes

    def term(pixels, batches):  # the modelled time (s) less the same job's with one batch (no statistics)
        seconds = [resources.modelled_cost("allan_deviation", pixels=pixels, frames=8000, batches=b)[1]
                   for b in (batches, 1)]
        return seconds[0] - seconds[1]

    assert term(512 * 512, 47) > 0
    assert term(4 * 512 * 512, 47) == pytest.approx(4 * term(512 * 512, 47))
    assert term(512 * 512, 188) == pytest.approx(4 * term(512 * 512, 47) * len(group_sizes(188)) / len(group_sizes(47)))
    assert resources.allan_statistics_size(8000, 1) == 0 and resources.allan_statistics_size(79) == 0


def test_an_allan_job_reads_its_batches_from_its_metrology_product(tmp_path):
    """job_data gives an Allan job the batches of its written metrology product (allan.fringe_batches of its
    phase), none before it is written; the request follows them."""
    import numpy as np
    import xarray as xr
    from types import SimpleNamespace

    from dice_core import allan, io
    from dice_core.manifest import Detector

    phase = np.cumsum(np.full(6000, 2 * np.pi / 90))  # a fringe period every 90 frames: batches of 91
    io.write_product(xr.Dataset({"phase": ("frame", phase, {"units": "rad"})}), tmp_path / "metrology.nc", title="t")
    detector = Detector(shape=(512, 512), science_rows=(0, 512), science_cols=(0, 512), gain=2.5, saturation=6e4)
    manifest = SimpleNamespace(detector=detector, positions=[], baselines={"b": SimpleNamespace(files=["a"])})
    frames_of = {"a": 6000}.get
    written = resources.job_data("allan_deviation", {"baseline": "b"}, manifest=manifest, frames_of=frames_of,
                                 inputs={"metrology": str(tmp_path / "metrology.nc")})
    assert written == {"frames": 6000, "workers": 1, "batches": len(allan.fringe_batches(phase))}
    assert 60 <= written["batches"] <= 70
    planned = resources.job_data("allan_deviation", {"baseline": "b"}, manifest=manifest, frames_of=frames_of,
                                 inputs={"metrology": str(tmp_path / "missing.nc")})
    assert planned == {"frames": 6000, "workers": 1}
    assert (job_resources("allan_deviation", pixels=512 * 512, **written)["runtime"]
            < job_resources("allan_deviation", pixels=512 * 512, **planned)["runtime"])


def test_an_allan_job_s_batches_are_read_once_a_version_of_its_metrology_product(tmp_path, monkeypatch):
    """Snakemake evaluates a job's resources many times: the product is read once, and again once replaced,
    even by a file of its very size and modification time."""
    import os

    import numpy as np
    import xarray as xr

    from dice_core import io

    path = tmp_path / "metrology.nc"
    io.write_product(xr.Dataset({"phase": ("frame", np.cumsum(np.full(6000, 2 * np.pi / 90)), {"units": "rad"})}),
                     path, title="t")
    opened = []
    real_open = io.open_product
    monkeypatch.setattr(io, "open_product", lambda p: opened.append(p) or real_open(p))
    first = [resources.allan_batches(path) for _ in range(5)]
    assert len(set(first)) == 1 and first[0] > 0 and len(opened) == 1
    # replaced by another of its very size and modification time (cp -p, a coarse clock): read again
    stat = path.stat()
    io.write_product(xr.Dataset({"phase": ("frame", np.cumsum(np.full(6000, 2 * np.pi / 45)), {"units": "rad"})}),
                     path, title="t")
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns
    assert resources.allan_batches(path) > first[0] and len(opened) == 2


@pytest.mark.parametrize("content", [b"not a netCDF file", "no phase"])
def test_an_unreadable_metrology_product_leaves_the_allan_request_to_its_frames(tmp_path, content):
    """A metrology product that is not one (garbage bytes, or a product without ``phase``) gives no batches:
    the request falls back on the frames, and the workflow's planning does not fail on it (the job reports
    the bad input with its own one-line error)."""
    import xarray as xr

    from dice_core import io

    path = tmp_path / "metrology.nc"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        io.write_product(xr.Dataset({"other": ("frame", [1.0, 2.0], {"units": "1"})}), path, title="t")
    assert resources.allan_batches(path) is None

@pytest.mark.parametrize("step, side, chunk_frames, max_rss_mb, seconds, frames", [
    # BENCHMARKS.md, "The calibration jobs at 4096x4096" (library: the workflow scripts' calls in a fresh process,
    # not through Snakemake; a dark and flats of 12 frames, 48 in the last rows; peak RSS, VmHWM, of 109 MiB of
    # interpreter and the step, in MB), a chunk's arithmetic in bands of rows, one chunk held; shared cores
    ("measure_dark", 1024, "auto", 315, 2.2, 12), ("measure_prnu", 1024, "auto", 370, 11.2, 12),
    ("measure_dark", 1024, 4, 233, 6.1, 12), ("measure_prnu", 1024, 4, 295, 9.5, 12),
    ("measure_dark", 2048, "auto", 828, 16.6, 12), ("measure_prnu", 2048, "auto", 1003, 41.7, 12),
    ("measure_dark", 2048, 4, 472, 9.6, 12), ("measure_prnu", 2048, 4, 757, 34.5, 12),
    ("measure_dark", 4096, "auto", 1456, 85.0, 12), ("measure_prnu", 4096, "auto", 2545, 85.0, 12),
    ("measure_dark", 1024, 48, 727, 27.4, 48), ("measure_prnu", 1024, 48, 784, 33.6, 48),
    # the same, --bad-pixels, the steps that read maps only (MiB measured, in MB here), after the bad pixels'
    # local medians were vectorised
    ("select_reference_prnu", 2048, "auto", 285, 2.4, 12), ("select_reference_prnu", 4096, "auto", 789, 2.5, 12),
    ("compare_prnu", 2048, "auto", 594, 3.1, 12), ("compare_prnu", 4096, "auto", 2027, 6.9, 12),
    ("find_bad_pixels", 2048, "auto", 486, 8.1, 12), ("find_bad_pixels", 4096, "auto", 1592, 33.5, 12),
])
def test_calibration_requests_cover_the_measured_jobs(step, side, chunk_frames, max_rss_mb, seconds, frames):
    asked = job_resources(step, pixels=side * side, frames=frames, chunk_frames=chunk_frames)
    assert asked["mem_mb"] - resources.EXECUTOR_MB >= max_rss_mb
    assert asked["mem_mb"] <= 4 * max_rss_mb + resources.EXECUTOR_MB
    assert asked["runtime"] * 60 >= seconds
    if side == 4096:  # a cluster slot of 8 GB takes every calibration job of a Theia-class detector
        assert asked["mem_mb"] <= 8000


def test_calibration_memory_follows_the_chunk_setting():
    """The calibration steps hold a chunk as read: 300-frame chunks of 4096x4096 pixels (5e9 samples) ask for
    far more than the automatic 4 frames; a chunk never holds more than the job's frames."""
    pixels = 4096 * 4096
    auto = job_resources("measure_prnu", pixels=pixels, frames=1000)
    large = job_resources("measure_prnu", pixels=pixels, frames=1000, chunk_frames=300)
    assert large["mem_mb"] > auto["mem_mb"] + 1.5 * 11 * pixels * 296 / 1e6 * 0.99
    assert job_resources("measure_dark", pixels=pixels, frames=12, chunk_frames=300) == job_resources(
        "measure_dark", pixels=pixels, frames=12, chunk_frames=12)
    assert resources.chunk_frames_of("auto", pixels=pixels, frames=1000) == 4
    assert resources.chunk_frames_of(None, pixels=80 * 84, frames=20) == 20


def test_memory_follows_pixels_and_time_follows_samples():
    small = job_resources("fit_fringes", pixels=PAPER_PIXELS, frames=200_000)
    more_frames = job_resources("fit_fringes", pixels=PAPER_PIXELS, frames=2_000_000)
    large = job_resources("fit_fringes", pixels=4096 * 4096, frames=20_000)
    # streaming: ten times the frames, less than twice the memory (the per-frame factors only)
    assert more_frames["mem_mb"] - resources.EXECUTOR_MB < 2 * (small["mem_mb"] - resources.EXECUTOR_MB)
    assert more_frames["runtime"] >= small["runtime"]
    # a 4k x 4k detector holds its per-pixel maps in memory: far more than 80x84, and more time per sample
    assert large["mem_mb"] > 4 * small["mem_mb"]
    huge = job_resources("fit_fringes", pixels=4096 * 4096, frames=200_000)
    assert huge["runtime"] > 5 * large["runtime"] or huge["runtime"] == resources.MIN_RUNTIME


def test_a_step_with_no_data_asks_for_the_floor():
    asked = job_resources("plot_dark", pixels=40 * 44)
    assert asked["runtime"] == resources.MIN_RUNTIME
    assert resources.EXECUTOR_MB < asked["mem_mb"] < 2000


def test_a_retry_asks_for_twice_as_much():
    first = job_resources("measure_dark", pixels=PAPER_PIXELS, frames=10_000)
    second = job_resources("measure_dark", pixels=PAPER_PIXELS, frames=10_000, attempt=2)
    assert second == {"mem_mb": 2 * first["mem_mb"], "runtime": 2 * first["runtime"]}


def test_every_benchmarked_rule_has_a_measured_cost():
    for step in ("simulate_file", "measure_dark", "measure_prnu", "fit_fringes", "allan_deviation",
                 "stack_position", "measure_centroids", "sweep_point", "fit_start", "fit_part", "fit_reduce",
                 "fit_finish"):
        assert step in resources.COSTS, step


@pytest.mark.parametrize("kwargs", [{"pixels": 0}, {"pixels": 10, "frames": -1}, {"pixels": 10, "positions": -2},
                                    {"pixels": 10, "attempt": 0}, {"pixels": 10, "workers": 0}])
def test_bad_sizes_are_refused(kwargs):
    with pytest.raises(ValueError, match="job_resources"):
        job_resources("fit_fringes", **kwargs)


def test_a_split_fits_part_asks_for_its_own_files_only():
    """A 4k x 4k detector's 200,000-frame baseline (6.7 TB of 16-bit samples) in 64 parts: a part job asks for
    the time of its 1/64 of the samples, and for less memory than the single fit (the frame factors of its
    own frames only)."""
    pixels, frames = 4096 * 4096, 200_000
    single = job_resources("fit_fringes", pixels=pixels, frames=frames)
    part = job_resources("fit_part", pixels=pixels, frames=frames // 64)
    assert part["mem_mb"] < single["mem_mb"]
    assert part["runtime"] < single["runtime"] / 30
    assert job_resources("fit_part", pixels=pixels, frames=2 * frames // 64)["mem_mb"] > part["mem_mb"]


def test_star_positions_are_cut_into_consecutive_jobs_by_their_samples():
    """Positions of unequal sizes, indexed as another writer's manifest may index them (not 1..n): each job
    takes consecutive positions while their samples stay within the budget, and a position over it alone."""
    from types import SimpleNamespace

    frames = {"a": 100, "b": 100, "c": 100, "d1": 300, "d2": 200, "e": 50, "f": 50}
    files = {3: ["a"], 7: ["b"], 8: ["c"], 20: ["d1", "d2"], 21: ["e"], 40: ["f"]}
    positions = [SimpleNamespace(index=i, acquisition=SimpleNamespace(files=f)) for i, f in files.items()]
    groups = resources.position_groups(positions, frames.get, pixels=10, samples=2500)
    assert groups == [(3, 7), (8,), (20,), (21, 40)]
    assert resources.position_groups(positions, frames.get, pixels=10, samples=1) == [(i,) for i in files]
    assert resources.position_groups(positions, frames.get, pixels=10, samples=1e9) == [tuple(files)]
    assert resources.position_groups([], frames.get, pixels=10, samples=1e9) == []
    assert resources.sample_groups([3, 3, 9, 1, 1, 1], samples=6) == [(1, 2), (3,), (4, 5, 6)]


def test_a_simulation_job_holds_one_acquisition_s_files_or_the_positions(tmp_path):
    """The ci preset's files, numbered in the manifest's order, cut by job_samples: the dark, each flat and each
    baseline's files among themselves (two 150-frame files of 40x44 a baseline), the positions' files among
    theirs; and the files of a group's rule are the manifest's."""
    from pathlib import Path

    from dice_core import simulation
    from dice_core.manifest import parse_manifest

    cfg = simulation.load_preset(Path(__file__).parents[1] / "config" / "presets" / "ci.yaml")
    manifest = parse_manifest(simulation.dataset_layout(cfg), tmp_path / "dataset.yaml")
    planned = {tmp_path / rel: stop - start for rel, (_, _, start, stop) in simulation.file_jobs(cfg).items()}
    pixels = 40 * 44
    assert resources.simulation_groups(manifest, planned.get, pixels=pixels, samples=1e12) == [
        (1,), (2,), (3,), (4, 5), (6, 7), (8, 9), (10, 11), (12, 13, 14, 15)]
    assert resources.simulation_groups(manifest, planned.get, pixels=pixels, samples=1) == [(n,) for n in range(1, 16)]
    # a metrology file is 264,000 samples: one a job, while the four positions' 28,160 stay one job
    assert resources.simulation_groups(manifest, planned.get, pixels=pixels, samples=3e5) == [
        *[(n,) for n in range(1, 12)], (12, 13, 14, 15)]
    assert resources.group_files(manifest, ("simulate_file", 4, 5)) == list(manifest.baselines["H1H4"].files)
    assert resources.group_files(manifest, ("stack_position", 2, 3)) == [
        f for p in manifest.positions[1:3] for f in p.acquisition.files]


def test_a_baseline_is_read_by_one_worker_unless_it_is_large_and_in_several_files():
    """Two worker processes (a job's threads) only where the baseline holds PARALLEL_READ_SAMPLES samples and is
    read in two parts or more, each one file at least: a second worker cannot split one file, and on a small
    baseline costs more than it saves."""
    pixels = 80 * 84
    frames_of = {"a": 2000, "b": 2000, "big1": 200000, "big2": 200000, "big3": 200000}.get
    assert resources.reading_workers(["a", "b"], frames_of, pixels=pixels, parts=2) == 1
    assert resources.reading_workers(["big1"], frames_of, pixels=pixels, parts=2) == 1
    assert resources.reading_workers(["big1", "big2"], frames_of, pixels=pixels, parts=2) == 2
    assert resources.reading_workers(["big1", "big2", "big3"], frames_of, pixels=pixels, parts=3) == 3
    assert resources.reading_workers(["big1", "big2", "big3"], frames_of, pixels=pixels, parts=1) == 1
    # the threshold is in samples: the same frames of a detector 100 times smaller stay in one worker
    assert resources.reading_workers(["big1", "big2"], frames_of, pixels=pixels // 100, parts=2) == 1


def test_the_run_s_baselines_take_its_cores_one_worker_each_before_any_takes_two():
    """With the run's cores known (``--cores``), a large baseline's job takes at most cores // baselines
    workers: on 2 cores four baselines read side by side, one process each (the paper preset's reduction in 77-80
    s instead of 97); one baseline alone, or enough cores, gives each job one worker a part; no total (a
    cluster's slots) no limit."""
    pixels = 80 * 84
    frames_of = {"big1": 200000, "big2": 200000, "big3": 200000}.get
    large = ["big1", "big2", "big3"]

    def workers(cores, baselines, parts=3):
        return resources.reading_workers(large, frames_of, pixels=pixels, parts=parts, cores=cores,
                                         baselines=baselines)

    assert workers(2, 4) == 1
    assert workers(2, 2) == 1
    assert workers(2, 1) == 2
    assert workers(8, 4) == 2
    assert workers(12, 4) == 3
    assert workers(64, 4, parts=2) == 2  # never more than a worker a part
    assert workers(None, 4) == 3
    assert workers(1, 0) == 1  # a run with no baseline to share among does not divide by zero
    # the threshold holds first: a small baseline keeps one worker whatever the cores
    assert resources.reading_workers(["big1", "big2"], frames_of, pixels=pixels // 100, parts=2, cores=64) == 1
