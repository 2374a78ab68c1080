"""Memory and wall time a workflow step needs, from the dataset's size.

A cluster scheduler (SLURM, through Snakemake's executor plugin) needs each
job's memory and time limit before it runs. Both follow from the data a step
reads: its pixels, its frames and, for the pseudo-star steps, its positions.
Each step's cost is a linear model of those,

    memory (MB)  = base_mb + mb_per_mpixel * pixels / 1e6 + mb_per_mframe * frames / 1e6
                   + mb_per_gsample * pixels * frames / 1e9 + mb_per_mchunk * pixels * chunk / 1e6
                   + workers * (worker_mb + worker_mb_per_mpixel * pixels / 1e6
                                + mb_per_mchunk * pixels * chunk / 1e6)                 (workers > 1)
    time (s)     = start_s + s_per_mpixel * pixels / 1e6 + s_per_gsample * pixels * frames / 1e9
                   + s_per_position * positions
                   + s_per_gstatistic * pixels * batches * group sizes / 1e9   (the Allan statistics)

whose coefficients come from the workflow's own ``benchmark:`` files (max_rss
and wall time of each job) on the ``ci`` preset, on the ``ci`` preset with a
detector 8 times larger on a side, on the default and paper presets, and on
the ``large`` preset's detector from 256x256 to 1024x1024 pixels
(BENCHMARKS.md, "Job resources" and "A large detector"). Memory does not grow with frames for the
streaming steps (the cubes are read in chunks) but for per-frame series (the
fit's frame factors: tens of bytes a frame); it grows with pixels (the
per-pixel maps and accumulators) and, for the Allan deviations, with the
number of batches times the pixels (each batch's offset map), so with pixels
x frames; and, for the calibration steps, with the samples of a chunk (``chunk``: its frames, the
configuration's ``chunk_frames`` or the reader's automatic choice, at most the job's frames), which they hold
as read and converted while they work on it a band of rows at a time. A job that reads its frames in worker
processes (its threads) adds each worker's memory, ``worker_mb`` and ``worker_mb_per_mpixel`` a worker, and
a chunk's (``mb_per_mchunk``) a worker: each worker reads its chunks as the job would.

The request adds margins to the measured cost, because a job that runs out
of memory or time on a cluster is killed: :data:`MEMORY_MARGIN` on memory,
the Snakemake process that runs the job on the node (:data:`EXECUTOR_MB`),
:data:`TIME_MARGIN` on time (the benchmarks' jobs took up to 5.4 times their
quiet-machine time with other jobs on the cores) and at least
:data:`MIN_RUNTIME` minutes. A retried job (Snakemake's ``attempt``) asks for
``attempt`` times as much.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

__all__ = ["StepCost", "COSTS", "MEMORY_MARGIN", "EXECUTOR_MB", "TIME_MARGIN", "MIN_RUNTIME", "job_resources",
           "modelled_cost", "chunk_frames_of",
           "step_cost", "job_data", "part_files", "sample_groups", "position_groups", "simulation_groups",
           "group_files", "FileFrames", "ALLAN_BATCH_FRAMES", "allan_statistics_size", "allan_batches"]

#: Factor on the modelled memory: the spread of repeated runs (383-419 MB for one fit) and of library versions.
MEMORY_MARGIN = 1.5
#: MB for the Snakemake process that runs a job on a cluster node (it parses the workflow, then starts the
#: step's script; the ``benchmark:`` files measure the script only).
EXECUTOR_MB = 400
#: Factor on the modelled wall time: the benchmarks' fits took 5-19 s on shared cores against 3.3-3.5 s alone.
TIME_MARGIN = 6.0
#: Minutes: the least wall time asked for, which covers Python's start on a busy node.
MIN_RUNTIME = 5


@dataclass(frozen=True)
class StepCost:
    """Measured cost of one workflow step, linear in the data it reads.

    Attributes
    ----------
    base_mb : float
        Peak resident memory, MB, of the step on a vanishing dataset (the
        interpreter and its imports).
    mb_per_mpixel : float
        MB per million detector pixels (maps and accumulators).
    mb_per_mframe : float
        MB per million frames, whatever the pixels (per-frame series).
    mb_per_gsample : float
        MB per 1e9 samples read (pixels x frames): per-pixel maps kept for each part of the frames.
    worker_mb, worker_mb_per_mpixel : float
        MB that each worker process adds, and MB per million pixels, for a job
        that reads its frames in worker processes (``workers`` > 1: they are
        forked, what they share with the job counted once): what it makes of
        its own (its batches' sums), its chunk counted apart (``mb_per_mchunk``).
    mb_per_mchunk : float
        MB per million samples of a chunk (its frames x pixels): the chunk as read and converted.
    start_s : float
        Wall time, s, of the step on a vanishing dataset.
    s_per_mpixel : float
        s per million pixels (per-pixel solutions, figures).
    s_per_gsample : float
        s per 1e9 samples read or written.
    s_per_position : float
        s per star position.
    s_per_gstatistic : float
        s per 1e9 pixel x batch x group size of the Allan statistics
        (:func:`allan_statistics_size`: the groups' fits sum every batch
        of every group of every size, over every pixel).
    """

    base_mb: float
    mb_per_mpixel: float = 0.0
    mb_per_mframe: float = 0.0
    mb_per_gsample: float = 0.0
    worker_mb: float = 0.0
    worker_mb_per_mpixel: float = 0.0
    mb_per_mchunk: float = 0.0
    start_s: float = 5.0
    s_per_mpixel: float = 0.0
    s_per_gsample: float = 0.0
    s_per_position: float = 0.0
    s_per_gstatistic: float = 0.0


#: Frames of the shortest batch the Allan job's requests are sized for. A batch is the shortest run of frames
#: that sweeps a fringe period (dice_core.allan.fringe_batches), known once the fit has run, not when the job is
#: planned; a faster sweep makes shorter batches, so more of them, and the statistics' time grows with them
#: (:func:`allan_statistics_size`). The benchmarks' fastest sweep made batches of 42 frames; the presets' 71
#: (ci) to about 700 (paper). A baseline of shorter batches may outrun its request (its retry asks for twice).
ALLAN_BATCH_FRAMES = 40


def allan_statistics_size(frames: int, batches: int | None = None) -> int:
    """Batches x group sizes (:func:`dice_core.allan.group_sizes`) of an Allan job: the statistics' work per
    pixel. ``batches`` where known (:func:`allan_batches`), else ``frames`` in batches of
    :data:`ALLAN_BATCH_FRAMES`. 0 under two batches."""
    from dice_core.allan import group_sizes  # here: the workflow's start-up does not import the Allan code

    batches = int(frames) // ALLAN_BATCH_FRAMES if batches is None else int(batches)
    return batches * len(group_sizes(batches)) if batches >= 2 else 0


def allan_batches(metrology_path) -> int | None:
    """The batches the Allan job of a baseline will make (:func:`dice_core.allan.fringe_batches` of the fringe
    phase of its ``metrology`` product), or None where the product is not written yet or has too few frames
    (the job says why), or where it cannot be read (a file that is not a product, or one without ``phase``:
    the job, not the workflow's planning, then fails with a one-line error naming it). Snakemake evaluates a
    job's resources again when it is about to run, its inputs written: the request then follows the baseline's
    own batches, not :data:`ALLAN_BATCH_FRAMES`.

    Read once a version of the file (its path, size, modification and change times and inode): Snakemake
    evaluates each of a job's resources, and each time it plans, in the workflow's one process."""
    path = Path(metrology_path)
    if not path.is_file():
        return None
    from dice_core.io import _digest_key  # the key of a file's version the digests' cache uses too

    return _batches_of(*_digest_key(path))


@functools.lru_cache(maxsize=1024)
def _batches_of(path: str, *version: int) -> int | None:
    """:func:`allan_batches` of one version of a file (``version``, its stat's numbers, keys the cache: a file
    replaced keeps no size, times and inode all alike, ctime being the system's own)."""
    from dice_core import allan, io

    try:
        with io.open_product(path) as product:
            phase = product["phase"].values
        return len(allan.fringe_batches(phase))
    except (OSError, KeyError, ValueError, allan.AllanError):  # netCDF's errors are OSError; a bad phase ValueError
        return None


#: Cost of each step of :data:`dice_core.steps.STEPS` (BENCHMARKS.md, "Job resources"). Steps not listed here
#: cost :data:`LIGHT`.
COSTS: dict[str, StepCost] = {
    # 2.3-2.4 GB for a metrology file of 1024x1024 pixels (its truth maps and the spherical fringes'
    # per-pixel response); 48-66 s per 1e9 samples at every size (BENCHMARKS.md, "A large detector")
    "simulate_file": StepCost(base_mb=230.0, mb_per_mpixel=2200.0, start_s=3.0, s_per_gsample=60.0),
    # the interpreter (210 MB through the workflow), then measured above it (library, benchmarks/
    # calibration_memory.py, 1024x1024 to 4096x4096, chunks of 4 to 48 frames; BENCHMARKS.md, "The calibration
    # jobs at 4096x4096"): the maps, 36 (dark) and 112 (PRNU: its illumination fit's design) bytes a pixel,
    # and one chunk as read and converted, 11 bytes a sample of it (its arithmetic a band of rows at a time):
    # the sum overstates a little, the PRNU's peak being the larger of its pass and its finish. 1389 and 2427
    # MiB at 4096x4096 in 4-frame chunks (before the bands, 3581 and 4687: 94 and 136 bytes a pixel and 31
    # and 37 a chunk's sample). 18.7 and 32.6 s at 4096x4096 x 12 frames (library, calibration_memory.py,
    # load 3.7: BENCHMARKS.md, "The calibration jobs at 4096x4096"), most of it the per-pixel finish and the
    # product's write.
    "measure_dark": StepCost(base_mb=210.0, mb_per_mpixel=40.0, mb_per_mchunk=11.0, start_s=3.0, s_per_mpixel=4.0,
                             s_per_gsample=10.0),
    "measure_prnu": StepCost(base_mb=210.0, mb_per_mpixel=115.0, mb_per_mchunk=11.0, start_s=3.0,
                             s_per_mpixel=5.0, s_per_gsample=10.0),
    # The calibration steps that read maps only (library, benchmarks/calibration_memory.py --bad-pixels at
    # 2048x2048 and 4096x4096; BENCHMARKS.md, "The calibration jobs at 4096x4096"): above the interpreter, 40
    # (select_reference_prnu), 114 (compare_prnu) and 88 (find_bad_pixels) bytes a pixel; 752, 1933 and 1518
    # MiB at 4096x4096, the bad pixels in 33.5 s (its local medians vectorised; 1502 s before). LIGHT's 300
    # MB a million pixels asked more than 8 GB for each at that size.
    "select_reference_prnu": StepCost(base_mb=210.0, mb_per_mpixel=45.0, start_s=3.0, s_per_mpixel=1.0),
    "compare_prnu": StepCost(base_mb=210.0, mb_per_mpixel=120.0, start_s=3.0, s_per_mpixel=1.0),
    "find_bad_pixels": StepCost(base_mb=210.0, mb_per_mpixel=95.0, start_s=3.0, s_per_mpixel=3.0),
    # Through the workflow (Snakemake's benchmark files: the RSS of the job and its two reading workers summed,
    # so its worker_mb is 0), 481 and 727 MB at 256x256 and 512x512 x 4000 frames (BENCHMARKS.md, "The single
    # fit's memory through the workflow"): 1250 bytes a pixel above about 400 MB, asked as 1400. 1961 MB and
    # 180 s for 1024x1024 x 5000 frames with older code (three passes and the cubes' checksums in reads of their own).
    "fit_fringes": StepCost(base_mb=400.0, mb_per_mpixel=1400.0, mb_per_mframe=170.0, start_s=3.0,
                            s_per_gsample=35.0, s_per_mpixel=80.0),
    # A split fit's jobs (docs/metrology.md), measured on 256x256 to 1024x1024 detectors (BENCHMARKS.md, "A
    # large detector"). A part holds the projector, F'X and a chunk per pixel and its own frames' products
    # (frames: its files' frames): 438 MB at 1024x1024 whether its files hold 2000 or 10,000 frames; pass 1
    # read its files twice then (their checksums, then the pass): 14.5 s per 1e9 samples from the disk, 8 for
    # a later pass (pass 1 now hashes what it streams: kept at 15 until measured from a disk again). The
    # start forms pass 1's 7-column design and projector: 536 MB at 1024x1024. The sum of
    # a pass (11 s) and the product (74-78 s: the pixel solution and the tips' refinement) hold all frames'
    # factors (frames: the baseline's) and per-pixel arrays, above the interpreter (about 115 MB): the sum
    # 270 bytes a pixel at 1024x1024 and the product 397-420 (447 at 512x512), both swept over blocks of
    # pixels and the state spent as used (library, benchmarks/fit_memory.py: BENCHMARKS.md, "Memory of a split
    # fit's reduction and product"; before, 315-333 and 579, and 1.5-1.6 and 1.85 GB at first); through the
    # workflow at 2048x2048, 229 and 312 ("A 2048x2048 x 2,000-frame baseline through the split fit").
    "fit_start": StepCost(base_mb=400.0, mb_per_mpixel=2500.0, start_s=3.0, s_per_mpixel=60.0),
    "fit_part": StepCost(base_mb=400.0, mb_per_mpixel=600.0, mb_per_mframe=170.0, start_s=3.0,
                         s_per_gsample=15.0),
    "fit_reduce": StepCost(base_mb=400.0, mb_per_mpixel=400.0, mb_per_mframe=170.0, start_s=3.0,
                           s_per_mpixel=30.0),
    "fit_finish": StepCost(base_mb=400.0, mb_per_mpixel=500.0, mb_per_mframe=170.0, start_s=3.0,
                           s_per_mpixel=80.0),  # reads the state and the parts' digests, no cube
    # what grows with pixels times batches on disk (docs/metrology.md, "The Allan job, on disk and in bands of
    # pixels"); each band of pixels about 8 bytes a batch-pixel number, at least one row of 10x10-pixel blocks:
    # 10 x 4096 pixels x 160 batches at 4096x4096 (50 MB), which the per-sample term covers for batches of 40
    # frames or more (0.5 MB per 1e9 samples). Measured (library, benchmarks/allan_memory.py, 47 batches of 42
    # frames; in MiB, 2^20 bytes, as the script reports them, where this model is in MB, 1e6 bytes; BENCHMARKS.md,
    # "The Allan job's memory cut"), the job's process tree (the peak of its processes' summed PSS: what they take
    # together, forked workers sharing the job's pages; and of their summed RSS): one worker, the job alone, peak
    # RSS 247 and 527 MiB at 512x512 and 1024x1024 (372 bytes a pixel, 355 MiB a million pixels; 491 bytes
    # before the cut), of which the chunks it reads: 16 frames at these sizes (io.auto_chunk_frames), two
    # float32 chunks and a raw one held at once, 10 bytes a sample (tracemalloc), 4 frames at 4096x4096; the
    # rest 212 bytes a pixel (written 195 until 2026-12-05: 355 MiB a million pixels less 160 bytes). With two
    # workers the tree's PSS 329 and 775 MiB: each worker its chunks and about 28 bytes a pixel more (27 MiB a
    # million pixels; its batches' sums); the batches' fit reaches it through the fork, shared (it was sent a
    # pickled copy: 257 MiB a million pixels a worker). The job's chunk is counted with workers too (it reads
    # none then but the first). Measured again with 4-frame chunks (as 4096x4096 reads them; BENCHMARKS.md, "The
    # Allan job's chunk term, measured"): the tree's PSS with two workers 233 and 587 MiB at 512x512 and
    # 1024x1024 (and 333 with 16-frame chunks at 512x512: 11.1 bytes a chunk sample in each of the three
    # processes, written 10.6 there), 471 bytes a pixel (450 MiB a million pixels), of which about 338 besides
    # the chunks (written 324: MiB a million pixels less bytes): the job's term was raised from 200 to 265 to
    # cover it, which like with like it does not quite (265 + 2 x 30 = 325): the model's 7.9 GB at 4096x4096
    # with two workers (5.5 with one) is under that straight line's 7667 MiB, 8.0 GB (once written 7.7 GB).
    # Measured at 2048x2048 since ("The Allan job at 2048x2048, measured"): the tree's PSS 1699-1704 MiB
    # (1782-1787 MB) with two workers and 4-frame chunks (RSS 2813 MiB, 2950 MB), under the model's 2271 MB; at
    # 4096x4096, by the lines through today's 1024x1024 and 2048x2048, 6.7-6.9 GB (the larger, the job's own
    # peak RSS, VmHWM; the tree's PSS, sampled every 20 ms, a lower bound): under the model's 7.9 GB.
    # Time: the reading pass, 1-3.5 plain read passes (17 s per 1e9 samples, from the workflow's runs), then the
    # statistics, which grow with pixels x batches x group sizes: 44-76 plain read passes' time per sample in
    # five of six runs at 256x256 to 1024x1024 and 47 or 190 batches (pixels x groups fitted varied 178-446),
    # 0.24-0.97 us a pixel x batch x group size on shared cores (load 4-13: BENCHMARKS.md, "The Allan job's
    # inputs, workers and time"); asked as the two fastest runs' 0.25 us, TIME_MARGIN (6) covering the slowest
    # (request over measured 2.0-7.6 in those runs); before, the request grew with samples alone and missed
    # them for short batches.
    "allan_deviation": StepCost(base_mb=350.0, mb_per_mpixel=265.0, mb_per_gsample=0.5, mb_per_mchunk=10.0,
                                worker_mb=25.0, worker_mb_per_mpixel=30.0, start_s=3.0, s_per_gsample=17.0,
                                s_per_gstatistic=250.0),
    "stack_position": StepCost(base_mb=200.0, mb_per_mpixel=1000.0, start_s=3.0, s_per_gsample=20.0),
    "measure_centroids": StepCost(base_mb=170.0, start_s=5.0, s_per_position=0.1),
    # every wavelength's products read and its width maps made, one wavelength at a time: linear in the
    # wavelengths; sized for 5, measured 754 MB and 52.6 s on 512x512 (BENCHMARKS.md, "Several wavelengths")
    "chromatic_calibration": StepCost(base_mb=250.0, mb_per_mpixel=2000.0, start_s=5.0, s_per_mpixel=200.0),
    # the stray-light search (dice_core.stray_light.diagnose): a white 512x512 map's one pass took 4.5 s and
    # 86 MB above the interpreter on 2 shared cores (load 8); a pass more for each component found, 7 at most;
    # the metrology product read beside it. compare_pairs searches both differences, ddx and ddy.
    "find_stray_light": StepCost(base_mb=250.0, mb_per_mpixel=500.0, start_s=5.0, s_per_mpixel=150.0),
    "compare_pairs": StepCost(base_mb=250.0, mb_per_mpixel=700.0, start_s=5.0, s_per_mpixel=300.0),
    # the studies' own benches, whatever the dataset: the largest point measured (a chromatic point: 58-105 s and
    # 189 MB on 2 shared cores, two at a time; an offset-bias point 22 s)
    "sweep_point": StepCost(base_mb=240.0, start_s=110.0),
}

#: A step that reads products only (figures, tables, comparisons): the interpreter with matplotlib and xarray.
LIGHT = StepCost(base_mb=250.0, mb_per_mpixel=300.0, start_s=10.0, s_per_mpixel=30.0)


def step_cost(step: str) -> StepCost:
    """The measured cost of a step (a rule name); :data:`LIGHT` for a step that reads products only."""
    return COSTS.get(step, LIGHT)


def chunk_frames_of(setting, *, pixels: int, frames: int) -> int:
    """Frames of the largest chunk a job reads: the configuration's ``chunk_frames`` (an integer, or "auto"
    or None for :func:`dice_core.io.auto_chunk_frames` of frames of ``pixels`` pixels), at most the job's
    ``frames`` (a chunk never spans two files: an upper bound)."""
    from dice_core.io import auto_chunk_frames

    per_chunk = auto_chunk_frames((1, pixels)) if setting in (None, "auto") else int(setting)
    if per_chunk < 1:
        raise ValueError(f'chunk_frames must be "auto" or an integer >= 1, got {setting!r}')
    return min(per_chunk, frames)


def job_resources(step: str, *, pixels: int, frames: int = 0, positions: int = 0, chunk_frames="auto",
                  workers: int = 1, batches: int | None = None, attempt: int = 1) -> dict:
    """Memory and wall time to ask a scheduler for, for one job of a step.

    Parameters
    ----------
    step : str
        The rule's name (``fit_fringes``, ``measure_dark``...).
    pixels : int
        Detector pixels, rows x cols.
    frames : int
        Frames the job reads (or writes, for a simulation), over all its files.
    positions : int
        Star positions the job handles.
    chunk_frames : int or "auto"
        The configuration's ``chunk_frames``, for a step whose memory grows with a chunk's samples.
    workers : int
        Worker processes the job reads its frames in (its threads, :func:`reading_workers`); one: none, the
        job reads them itself.
    batches : int, optional
        The Allan job's batches where known (:func:`allan_batches`); None: ``frames`` in batches of
        :data:`ALLAN_BATCH_FRAMES`.
    attempt : int
        Snakemake's attempt number, 1 for the first: a retried job asks for that many times more.

    Returns
    -------
    dict
        ``mem_mb`` (int, MB) and ``runtime`` (int, minutes), Snakemake's standard resource names.
    """
    if attempt < 1:
        raise ValueError(f"job_resources({step!r}): attempt {attempt} must be at least 1")
    memory, seconds = modelled_cost(step, pixels=pixels, frames=frames, positions=positions,
                                    chunk_frames=chunk_frames, workers=workers, batches=batches)
    mem_mb = math.ceil(MEMORY_MARGIN * memory + EXECUTOR_MB) * attempt
    runtime = max(MIN_RUNTIME, math.ceil(TIME_MARGIN * seconds / 60)) * attempt
    return {"mem_mb": int(mem_mb), "runtime": int(runtime)}


def modelled_cost(step: str, *, pixels: int, frames: int = 0, positions: int = 0, chunk_frames="auto",
                  workers: int = 1, batches: int | None = None) -> tuple[float, float]:
    """The module's linear model of one job of ``step``: its memory (MB) and wall time (s), before the margins
    and the executor's memory that :func:`job_resources` adds. Parameters as there."""
    if pixels <= 0 or frames < 0 or positions < 0 or workers < 1:
        raise ValueError(f"job_resources({step!r}): pixels {pixels} must be positive, frames {frames} and "
                         f"positions {positions} non-negative, workers {workers} at least 1")
    cost = step_cost(step)
    samples = float(pixels) * float(frames)
    chunk = chunk_frames_of(chunk_frames, pixels=pixels, frames=frames) if cost.mb_per_mchunk else 0
    memory = (cost.base_mb + cost.mb_per_mpixel * pixels / 1e6 + cost.mb_per_mframe * frames / 1e6
              + cost.mb_per_gsample * samples / 1e9 + cost.mb_per_mchunk * pixels * chunk / 1e6
              + (workers if workers > 1 else 0) * (cost.worker_mb + cost.worker_mb_per_mpixel * pixels / 1e6
                                                   + cost.mb_per_mchunk * pixels * chunk / 1e6))
    seconds = (cost.start_s + cost.s_per_mpixel * pixels / 1e6 + cost.s_per_gsample * samples / 1e9
               + cost.s_per_position * positions)
    if cost.s_per_gstatistic:
        seconds += cost.s_per_gstatistic * pixels * allan_statistics_size(frames, batches) / 1e9
    return memory, seconds


def part_files(files, frames_of, *, parts: int, part: int) -> list:
    """The files of part ``part`` of a split fit over ``files`` (its baseline's, in order): the group of whole
    files :meth:`dice_core.io.FrameStream.split` gives that part; none for a part beyond the groups.
    ``frames_of(file)`` gives a file's frames."""
    from dice_core.io import file_groups

    groups = file_groups([frames_of(f) for f in files], parts)
    return list(files[slice(*groups[part])]) if part < len(groups) else []


#: Samples of a baseline from which its fit and Allan jobs read it in worker processes, one per part of its
#: files: below it a second worker's fork and pool cost more than the half of the reading it saves, and its
#: core is held from every other job for the whole job, most of which (start, imports, the solve, the product)
#: is serial. A judgement between two measurements (BENCHMARKS.md, "One worker or two"): on shared cores one
#: worker was faster in the median at 2.7e7, 1e8 and 1e9 samples (a second worker had no idle core); on idle
#: cores two workers read 1.3e9 samples 1.7-1.9x faster than one (issue 10's measurement). Not measured on
#: idle cores between them.
PARALLEL_READ_SAMPLES = 2e8


def reading_workers(files, frames_of, *, pixels: int, parts: int, cores: int | None = None,
                    baselines: int = 1) -> int:
    """Worker processes, a job's threads, for a job that streams a baseline of ``files`` (``frames_of(path)``
    its frames, ``pixels`` a frame's) in ``parts`` parts of whole files (the fit's ``metrology.parts``, the
    Allan step's :data:`dice_core.parallel.LANES`): one per part, a part one file at least, from
    ``PARALLEL_READ_SAMPLES`` samples; else one. The product does not depend on it.

    ``cores`` are the run's (Snakemake's ``--cores``; None where a job has a slot of its own, as on a cluster) and
    ``baselines`` the dataset's (a run that makes one baseline's products alone shares the cores as if it made all:
    it leaves a core idle where it could read in two): a job takes at most ``cores // baselines`` workers, so that
    the baselines' jobs, side by side, fill the cores with one process each before any takes two. A second worker
    reads its part about 1.5x faster but holds a core for the whole job, most of which is serial: on 2 cores the
    paper preset's reduction (four baselines) took 77-80 s with one worker a job against 97 s with two
    (BENCHMARKS.md, "The README's commands on idle cores").
    """
    samples = pixels * sum(frames_of(f) for f in files)
    workers = max(1, min(parts, len(files))) if samples >= PARALLEL_READ_SAMPLES else 1
    if cores is not None:
        workers = min(workers, max(1, cores // max(1, baselines)))
    return workers


def sample_groups(sizes, *, samples: float) -> list[tuple[int, ...]]:
    """Consecutive items in groups, one workflow job a group (config ``job_samples``): each group takes items
    in order while its samples stay within ``samples``; an item of more is a group of its own.

    ``sizes`` are the items' samples (pixels x frames), in order. Returns tuples of the items' numbers, from 1,
    every item once, in order.
    """
    groups, group, group_samples = [], [], 0.0
    for number, size in enumerate(sizes, start=1):
        if group and group_samples + size > samples:
            groups.append(tuple(group))
            group, group_samples = [], 0.0
        group.append(number)
        group_samples += size
    return groups + [tuple(group)] if group else groups


def position_groups(positions, frames_of, *, pixels: int, samples: float) -> list[tuple]:
    """The star positions in groups of consecutive positions by their samples (:func:`sample_groups`): tuples
    of the positions' indices. ``positions`` are the manifest's (``.index``, ``.acquisition``);
    ``frames_of(file)`` gives a raw file's frames."""
    positions = list(positions)
    sizes = [pixels * sum(frames_of(f) for f in p.acquisition.files) for p in positions]
    return [tuple(positions[n - 1].index for n in group) for group in sample_groups(sizes, samples=samples)]


def simulation_groups(manifest, frames_of, *, pixels: int, samples: float) -> list[tuple[int, ...]]:
    """The dataset's files, numbered from 1 in the manifest's order (``manifest.all_files()``), in groups of one
    simulation job each (:func:`sample_groups`, ``samples`` a job): the files of one acquisition (the dark, a
    flat, a baseline) among themselves, the star positions' files among theirs. A group never holds two of the
    other acquisitions' files, so that making one file again (Snakemake re-makes a job's every output) rewrites
    no other acquisition's, whose reductions would then run again."""
    positions = [p.acquisition for p in manifest.positions]
    acquisitions = manifest.acquisitions()
    others = acquisitions[:len(acquisitions) - len(positions)]  # positions come last
    segments = [list(a.files) for a in others] + [[f for a in positions for f in a.files]]
    number = 1
    groups = []
    for files in segments:
        groups += [tuple(number - 1 + n for n in group)
                   for group in sample_groups([pixels * frames_of(f) for f in files], samples=samples)]
        number += len(files)
    return groups


def group_files(manifest, group: tuple[str, int, int]) -> list:
    """The raw files of a group's job, ``group`` its (step, first, last) (:func:`dice_core.steps.rule_group`):
    the manifest's files ``first`` to ``last`` (numbered from 1) of ``simulate_file``, or the files of the star
    positions of index ``first`` to ``last`` of ``stack_position``."""
    step, first, last = group
    if step == "simulate_file":
        return list(manifest.all_files()[first - 1:last])
    indices = [p.index for p in manifest.positions]
    return [f for p in manifest.positions[indices.index(first):indices.index(last) + 1] for f in p.acquisition.files]


def job_data(step: str, wildcards: dict, *, manifest, frames_of, parts: int = 1, inputs=None,
             workers: int | None = None) -> dict:
    """What one job of ``step`` reads (or writes, for the simulation), for :func:`job_resources`:
    ``frames`` over all its files and ``positions``.

    ``wildcards`` are the job's; ``frames_of(path)`` gives a raw file's frames (planned or from its header);
    ``parts`` the split fit's number of parts (``metrology.parts``, the parts a single fit reads in too). For a
    baseline's fit and Allan jobs, also their ``workers``: ``workers`` where given (the job's threads, as
    Snakemake gives them), else :func:`reading_workers` of the baseline with no limit of cores; no more than
    the parts it reads (a worker a part, :func:`dice_core.parallel.lane_workers`);
    for an Allan job whose ``inputs`` (name -> path) hold a written ``metrology`` product, its ``batches``.
    """
    def acquisition(acq):
        return sum(frames_of(f) for f in acq.files)

    positions = len(manifest.positions)
    if step == "simulate_file":  # a group of files (sample_groups), their paths as the job's "files"
        return {"frames": sum(frames_of(f) for f in wildcards["files"])}
    if step == "simulate_truth":
        return {"frames": sum(frames_of(f) for f in manifest.all_files()), "positions": positions}
    if step == "measure_dark":
        return {"frames": acquisition(manifest.dark) if manifest.dark else 0}
    if step == "measure_prnu":
        return {"frames": acquisition(manifest.flats[wildcards["flat"]])}
    if step in ("fit_fringes", "allan_deviation"):  # their worker processes too, the rules' threads
        from dice_core.parallel import LANES, lane_workers

        files = manifest.baselines[wildcards["baseline"]].files
        lanes = max(1, min(parts if step == "fit_fringes" else LANES, len(files)))  # a part a worker at most
        if workers is None:
            workers = reading_workers(files, frames_of, pixels=manifest.detector.shape[0] * manifest.detector.shape[1],
                                      parts=lanes)
        data = {"frames": acquisition(manifest.baselines[wildcards["baseline"]]),
                "workers": lane_workers(workers, lanes)}
        if step == "allan_deviation" and inputs and "metrology" in inputs:
            if (batches := allan_batches(inputs["metrology"])) is not None:
                data["batches"] = batches
        return data
    if step in ("fit_reduce", "fit_finish"):
        return {"frames": acquisition(manifest.baselines[wildcards["baseline"]])}
    if step == "fit_part":  # its own files' frames only (none for a part beyond the groups of files)
        files = manifest.baselines[wildcards["baseline"]].files
        return {"frames": sum(frames_of(f) for f in part_files(files, frames_of, parts=parts,
                                                                  part=int(wildcards["part"])))}
    if step == "fit_start":  # the first chunk only
        return {"frames": 0}
    if step == "stack_position":  # a group of positions (position_groups), its indices as the job's "positions"
        group = ("stack_position", wildcards["positions"][0], wildcards["positions"][-1])
        return {"frames": sum(frames_of(f) for f in group_files(manifest, group))}
    return {"positions": positions}


class FileFrames:
    """Frames of a dataset's raw files: the simulation's plan (``planned``: path relative to the manifest's
    folder -> frames) where it simulates a file, which may not exist yet, else NAXIS3 of the file's header,
    read once (``cache``: resolved path -> frames, which may be shared)."""

    def __init__(self, manifest, planned=None, cache=None):
        self.manifest, self.planned = manifest, planned or {}
        self.cache = {} if cache is None else cache

    def __call__(self, path) -> int:
        """The file's frames.

        Raises
        ------
        DatasetError
            A file that is not a readable FITS file, naming the acquisition and the manifest that name it.
        """
        from astropy.io import fits

        from dice_core import DatasetError

        path = Path(path).resolve()
        folder = self.manifest.path.parent.resolve()
        relative = path.relative_to(folder).as_posix() if path.is_relative_to(folder) else None
        if relative in self.planned:
            return self.planned[relative]
        if path not in self.cache:
            try:
                self.cache[path] = int(fits.getheader(path).get("NAXIS3", 1))
            except (OSError, ValueError, IndexError) as exc:  # astropy's errors of a file that is not FITS
                named_by = next((a.label for a in self.manifest.acquisitions() if path in a.files), "an acquisition")
                raise DatasetError(path, f"not a readable FITS file ({' '.join(str(exc).split())}); named by "
                                         f"{named_by} in {self.manifest.path}") from None
        return self.cache[path]
