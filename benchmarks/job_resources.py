"""Fit each step's cost (dice_core.resources) to the workflow's benchmark files, and check the requests.

    python benchmarks/job_resources.py results/sim-ci /tmp/big/results/sim-ci ...

Each argument is a results folder of one run (results/<name>/, with raw/dataset.yaml and benchmarks/), or the
<name>.json record of a run of benchmarks/large_detector.py (the same rows, taken before it removed the raw
files). Every
``benchmark:`` file of the runs (max_rss in MB, wall time s) is matched with its job's data: the detector's
pixels, the frames it read (its files' NAXIS3) and the positions. For each step the script prints

- the non-negative least-squares fit of memory on (1, Mpixels, Mframes, Gsamples) and of time on (1,
  Mpixels, Gsamples, positions), the coefficients of dice_core.resources.StepCost (not the calibration
  steps' per-chunk term, mb_per_mchunk: the runs' chunks are "auto"; benchmarks/calibration_memory.py
  varies them);
- each job's measurement beside dice_core.resources' model and its request (mem_mb, runtime), and the
  largest measured / requested ratio, which must stay below 1.

The runs should differ in pixels and in frames (the ci preset, the same with a larger detector, the same
with more frames), or the fit cannot tell the per-pixel cost from the per-sample one.
"""

import argparse
import csv
import json
import re
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
from astropy.io import fits
from scipy.optimize import nnls

from dice_core import resources, steps
from dice_core.io import file_groups
from dice_core.manifest import load_manifest


def file_frames(acquisition):
    return [int(fits.getheader(f)["NAXIS3"]) for f in acquisition.files]


def frames(acquisition):
    return sum(file_frames(acquisition))


def part_frames(results, manifest, baseline, npass, part, parts):
    """Frames a split fit's part job read: its group of files' (the workflow's grouping), none once converged."""
    if "nothing to read" in (results / "logs" / f"fit_part_{baseline}_{npass}_{part}.log").read_text():
        return 0
    counts = file_frames(manifest.baselines[baseline])
    groups = file_groups(counts, parts)
    return sum(counts[slice(*groups[part])]) if part < len(groups) else 0


def jobs(results, *, parts=None, since=0.0):
    """(step, pixels, frames, positions, max_rss MB, wall s, benchmark file) of each benchmark of a run.

    ``parts``: the split fit's metrology.parts (default: the pass-1 part jobs' benchmark files); ``since``: a
    time.time() before which a benchmark file is an earlier run's and left out.
    """
    results = Path(results)
    manifest = load_manifest(results / "raw" / "dataset.yaml")
    pixels = manifest.detector.shape[0] * manifest.detector.shape[1]
    positions = len(manifest.positions)
    for tsv in sorted((results / "benchmarks").rglob("*.tsv")):
        if tsv.stat().st_mtime < since:
            continue
        rel = tsv.relative_to(results / "benchmarks").with_suffix("").as_posix()
        name = rel.split("/")[-1]
        if group := steps.rule_group(name):  # a group's job (dice_core.steps.group_rule): its inputs' frames
            files = resources.group_files(manifest, group)
            step, n, k = group[0], sum(int(fits.getheader(f)["NAXIS3"]) for f in files), 0
        elif name == "measure_dark":
            step, n, k = name, frames(manifest.dark), 0
        elif name.startswith("measure_prnu_"):
            step, n, k = "measure_prnu", frames(manifest.flats[name[len("measure_prnu_"):]]), 0
        elif m := re.fullmatch(r"fit_part_(.+)_(\d+)_(\d+)", name):
            baseline = m.group(1)
            n_parts = parts or len(list((results / "benchmarks").glob(f"fit_part_{baseline}_1_*.tsv")))
            step, n, k = "fit_part", part_frames(results, manifest, baseline, m.group(2), int(m.group(3)), n_parts), 0
        elif m := re.fullmatch(r"fit_reduce_(.+)_\d+", name):
            step, n, k = "fit_reduce", frames(manifest.baselines[m.group(1)]), 0
        elif m := re.fullmatch(r"fit_start_(.+)", name):  # reads the first chunk only (the workflow's job_data)
            step, n, k = "fit_start", 0, 0
        elif m := re.fullmatch(r"(fit_fringes|allan_deviation|fit_finish)_(.+)", name):
            step, n, k = m.group(1), frames(manifest.baselines[m.group(2)]), 0
        elif name.startswith("measure_centroids_"):
            step, n, k = "measure_centroids", 0, positions
        else:
            print(f"skipped {tsv}: no step known", file=sys.stderr)
            continue
        with open(tsv) as handle:
            row = next(csv.DictReader(handle, delimiter="\t"))
        yield step, pixels, n, k, float(row["max_rss"]), float(row["s"]), tsv


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", help="results/<name>/ folders of workflow runs, or the <name>.json "
                                                   "records of benchmarks/large_detector.py")
    args = parser.parse_args(argv)
    by_step = defaultdict(list)
    for folder in args.results:
        if folder.endswith(".json"):  # benchmarks/large_detector.py's record of a run whose raw files are gone
            recorded = json.loads(Path(folder).read_text())["resources"]
            rows = [(*row[:6], Path(row[6])) for row in recorded]
        else:
            rows = jobs(folder)
        for job in rows:
            by_step[job[0]].append(job[1:])
    worst = 0.0
    for step, rows in sorted(by_step.items()):
        pixels, n, k, rss, wall, _ = map(np.array, zip(*rows))
        mpix, gsamples = pixels / 1e6, pixels * n / 1e9
        memory, _ = nnls(np.column_stack([np.ones_like(mpix), mpix, n / 1e6, gsamples]), rss)
        times, _ = nnls(np.column_stack([np.ones_like(mpix), mpix, gsamples, k]), wall)
        print(f"\n{step}: {len(rows)} jobs; fit: base_mb={memory[0]:.0f}, mb_per_mpixel={memory[1]:.0f}, "
              f"mb_per_mframe={memory[2]:.0f}, mb_per_gsample={memory[3]:.0f}; start_s={times[0]:.1f}, s_per_mpixel={times[1]:.1f}, "
              f"s_per_gsample={times[2]:.1f}, s_per_position={times[3]:.3f}")
        print(f"  {'pixels':>8} {'frames':>7} {'pos':>4} {'max_rss':>8} {'model':>7} {'mem_mb':>7} "
              f"{'wall s':>7} {'model':>7} {'runtime s':>9}")
        for p, f, q, r, w in zip(pixels, n, k, rss, wall):
            # the model as the workflow asks it (one worker, planned batches: what these records hold)
            model_mb, model_s = resources.modelled_cost(step, pixels=int(p), frames=int(f), positions=int(q))
            asked = resources.job_resources(step, pixels=int(p), frames=int(f), positions=int(q))
            worst = max(worst, r / (asked["mem_mb"] - resources.EXECUTOR_MB), w / (60 * asked["runtime"]))
            print(f"  {p:8d} {f:7d} {q:4d} {r:8.0f} {model_mb:7.0f} {asked['mem_mb']:7d} {w:7.1f} {model_s:7.1f} "
                  f"{60 * asked['runtime']:9d}")
    print(f"\nlargest measured / requested (memory less the executor's {resources.EXECUTOR_MB} MB, or time): "
          f"{worst:.2f}")
    return 0 if worst < 1 else 1


if __name__ == "__main__":
    sys.exit(main())
