"""The metrology fit at scale: the ``large`` preset's baseline split across jobs, on the path users take.

For each size given (rows x cols x frames of the one baseline; the preset's own is 1024x1024x20000,
42 GB of uint16), in one run of this script:

1. ``python -m snakemake --cores 2 --configfile <size>.yaml -- <results>/<name>/raw/dataset.yaml``:
   the simulation (dark, flats, star positions, the baseline in files of 2,000 frames);
2. the same command with ``metrology.split: true`` for the baseline's product (``--target fit``:
   ``metrology/H1H4.nc``; ``metrology``, the default: and ``allan/H1H4.nc``; ``all``: the preset's whole
   default target):
   the fit as ``fit_start``, ``fit_part`` (``metrology.parts`` a pass, run side by side on the 2 cores),
   ``fit_reduce`` and ``fit_finish`` jobs;
3. one plain read pass of the baseline's files in a fresh process (float32 chunks summed over frames,
   imports excluded): what reading the cube costs on this machine, from the page cache or the disk
   (a cube larger than the memory is read from the disk by every pass, the plain one too).

Each job's wall time and peak memory are Snakemake's ``benchmark:`` files (the whole job: start, imports,
inputs, the step, the product); each command's wall time is measured around it. Printed: a Markdown
table per size (per kind of job: count, wall time, peak RSS, time per 1e9 samples of the job's files) and
one line per size for the scaling table of BENCHMARKS.md. Every size's numbers go to
``<workdir>/<name>.json``. With ``--drop-raw`` the raw files of a size are removed after it, so that the
sizes need the disk of the largest only.

    python benchmarks/large_detector.py --workdir /tmp/dice-large 256x256x20000 512x512x20000 1024x1024x5000 \\
        1024x1024x20000 --drop-raw --single

The dataset of the preset's own size is ``sim-large``; another size is ``sim-large-<hash>`` (a
``simulation:`` override). Needs about 1.1x the raw data of disk (the products are small).
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import shutil
import sys
import time
from collections import defaultdict
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
import job_resources  # noqa: E402  (scripts beside this one)
from user_path import benchmark_record, machine, plain_read, snakemake  # noqa: E402

BASELINE = "H1H4"
PRESET = REPO / "config" / "presets" / "large.yaml"


def size_overrides(rows: int, cols: int, frames: int) -> dict:
    """The preset's ``simulation:`` overrides (dotted keys) for another size ({} for its own): the science area,
    the star pattern and the beam scaled with the detector."""
    preset = yaml.safe_load(PRESET.read_text())
    if [rows, cols] == preset["detector"]["shape"] and frames == preset["metrology"]["frames"]:
        return {}
    scale = min(rows, cols) / 1024
    return {"detector.shape": [rows, cols], "detector.science_rows": [2, rows - 2],
            "detector.science_cols": [8, cols - 2], "metrology.frames": frames,
            "metrology.envelope_sigma": 1500.0 * scale, "stars.pattern_centre": [cols / 2, rows / 2],
            "stars.pattern_side": 400.0 * scale}


def dataset_name(overrides: dict) -> str:
    from dice_core import simulation

    return simulation.load_preset(PRESET, overrides=overrides).name


#: Extra Snakemake options of every run (``--keep-raw``: ``--rerun-triggers mtime``).
SNAKEMAKE_OPTIONS: list = []


def run_command(configfile: Path, *targets: str, forcerun: str | None = None) -> float:
    """Run the README's command for ``targets``; wall time, s. Exits with Snakemake's output on a failure."""
    return snakemake("--configfile", str(configfile), *SNAKEMAKE_OPTIONS,
                     *(["--forcerun", forcerun] if forcerun else []), "--", *targets, echo=True).wall_s


def benchmark_rows(out: Path, parts: int, since: float) -> list[dict]:
    """Every job's benchmark file written by this run (modified after ``since``, a time.time()): rule, its
    name's fields, wall s, max_rss MB, frames it read (its files')."""
    from astropy.io import fits

    from dice_core import resources, steps
    from dice_core.io import file_groups
    from dice_core.manifest import load_manifest

    manifest = load_manifest(out / "raw" / "dataset.yaml")
    files = manifest.baselines[BASELINE].files
    counts = [int(fits.getheader(f)["NAXIS3"]) for f in files]
    groups = file_groups(counts, parts)
    baseline_frames = sum(counts)
    rows = []
    for tsv in sorted((out / "benchmarks").rglob("*.tsv")):
        if tsv.stat().st_mtime < since:  # an earlier run's job, which this one did not run again
            continue
        name = tsv.relative_to(out / "benchmarks").with_suffix("").as_posix()
        row = benchmark_record(tsv)
        job = {"job": name, "s": row["s"], "max_rss_mb": row["max_rss"]}
        if name.startswith("simulate/"):  # a group of files' job, named by its rule
            simulated = resources.group_files(manifest, steps.rule_group(name[len("simulate/"):]))
            metrology = any(Path(f).parent.name == "metrology" for f in simulated)
            job |= {"rule": "simulate_file" + (" (metrology)" if metrology else " (other)"),
                    "frames": sum(int(fits.getheader(f)["NAXIS3"]) for f in simulated)}
        elif m := re.fullmatch(rf"fit_part_{BASELINE}_(\d+)_(\d+)", name):
            npass, part = int(m.group(1)), int(m.group(2))
            frames = sum(counts[slice(*groups[part])]) if part < len(groups) else 0
            job |= {"rule": "fit_part (pass 1)" if npass == 1 else "fit_part (later passes)", "frames": frames,
                    "pass": npass, "part": part}
        elif m := re.fullmatch(rf"fit_reduce_{BASELINE}_(\d+)", name):
            job |= {"rule": "fit_reduce", "frames": baseline_frames, "pass": int(m.group(1))}
        elif name in (f"fit_start_{BASELINE}", f"fit_finish_{BASELINE}", f"fit_fringes_{BASELINE}",
                      f"allan_deviation_{BASELINE}"):
            job |= {"rule": name[: -len(BASELINE) - 1], "frames": baseline_frames}
        else:
            job |= {"rule": re.sub(r"_\d+$", "", name.split("/")[-1]), "frames": 0}
        rows.append(job)
    return rows


def converged_at(out: Path) -> int | None:
    """The pass at which the split fit converged, from its log (None if it did not)."""
    log = (out / "logs" / f"fit_finish_{BASELINE}.log").read_text()
    found = re.search(r"converged to \S+ pixel at pass (\d+)", log)
    return int(found.group(1)) if found else None


def tag_after_convergence(jobs: list[dict], converged: int | None) -> None:
    """Name the part and reduce jobs of the passes after convergence apart: they only start and stop (a part
    reads no frame)."""
    for job in jobs:
        if converged is not None and job.get("pass", 0) > converged and job["rule"].startswith("fit_"):
            job["rule"] = job["rule"].split(" (")[0] + " (after convergence: empty)"
            if job["rule"].startswith("fit_part"):
                job["frames"] = 0


def same_product(one, two) -> bool:
    """Whether two products hold the same data variables, each identical (values, coordinates, attributes),
    and record the same inputs with the same checksums: what the workflow test compares on ``ci``."""
    return (set(one.data_vars) == set(two.data_vars) and all(one[v].identical(two[v]) for v in one.data_vars)
            and json.loads(one.attrs["inputs"]) == json.loads(two.attrs["inputs"]))


def run_size(size: str, args) -> dict:
    rows, cols, frames = (int(v) for v in size.split("x"))
    overrides = size_overrides(rows, cols, frames)
    name = dataset_name(overrides)
    results = args.workdir / "results"
    out = results / name
    configfile = args.workdir / f"{name}.yaml"
    config = {"dataset": "large", "results": str(results),
              "metrology": {"split": True, "parts": args.parts, "max_passes": args.max_passes}}
    if overrides:
        config["simulation"] = overrides
    configfile.write_text(yaml.safe_dump(config, sort_keys=False))
    print(f"\n## {rows}x{cols} pixels, {frames} frames: {name}", flush=True)
    manifest = out / "raw" / "dataset.yaml"
    started = time.time()
    simulate_s = run_command(configfile, str(manifest))
    raw_bytes = sum(f.stat().st_size for f in (out / "raw").rglob("*.fits"))
    cube_bytes = sum(f.stat().st_size for f in (out / "raw" / "metrology").rglob("*.fits"))
    targets = {"all": [], "fit": [str(out / "metrology" / f"{BASELINE}.nc")],
               "metrology": [str(out / "metrology" / f"{BASELINE}.nc"), str(out / "allan" / f"{BASELINE}.nc")]}
    targets = targets[args.target]
    reduce_s = run_command(configfile, *targets)
    plain_s = plain_read(manifest, BASELINE)["seconds"]
    jobs = benchmark_rows(out, args.parts, started)
    # each job's data as the workflow's resources see it, for job_resources.py once the raw files are gone
    requested = [[step, int(p), int(n), int(k), float(rss), float(wall), str(tsv)]
                 for step, p, n, k, rss, wall, tsv in job_resources.jobs(out, parts=args.parts, since=started)]
    converged = converged_at(out)
    tag_after_convergence(jobs, converged)
    single = None
    if args.single:  # the single fit_fringes job on the same files, and whether its product is the split one's
        from dice_core.io import read_product

        split_product = read_product(out / "metrology" / f"{BASELINE}.nc").load()
        single_config = args.workdir / f"{name}-single.yaml"
        single_config.write_text(yaml.safe_dump({**config, "metrology": {**config["metrology"], "split": False}},
                                                sort_keys=False))
        single_s = run_command(single_config, str(out / "metrology" / f"{BASELINE}.nc"), forcerun="fit_fringes")
        row = benchmark_record(out / "benchmarks" / f"fit_fringes_{BASELINE}.tsv")
        same = same_product(read_product(out / "metrology" / f"{BASELINE}.nc"), split_product)
        single = {"command_s": single_s, "s": row["s"], "max_rss_mb": row["max_rss"],
                  "bit_identical": same}
    largest_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    summary = {"size": size, "name": name, "pixels": rows * cols, "frames": frames,
               "gsamples": rows * cols * frames / 1e9, "raw_gb": raw_bytes / 1e9, "cube_gb": cube_bytes / 1e9,
               "simulate_s": simulate_s, "reduce_s": reduce_s, "plain_pass_s": plain_s,
               "converged_at": converged, "largest_process_mb_so_far": largest_mb, "single_fit": single,
               "parts": args.parts, "max_passes": args.max_passes, "target": args.target, "jobs": jobs,
               "resources": requested}
    (args.workdir / f"{name}.json").write_text(json.dumps(summary, indent=1))
    print_size(summary)
    if args.drop_raw:
        shutil.rmtree(out / "raw")
        print(f"removed {out / 'raw'}", flush=True)
    return summary


def print_size(summary: dict) -> None:
    print(f"\nsimulation {summary['simulate_s']:.0f} s, reduction {summary['reduce_s']:.0f} s "
          f"(snakemake commands); raw {summary['raw_gb']:.1f} GB, of which the baseline {summary['cube_gb']:.1f} GB; "
          f"plain float32 pass {summary['plain_pass_s']:.1f} s; the split fit converged at pass "
          f"{summary['converged_at']}")
    if summary["single_fit"]:
        single = summary["single_fit"]
        print(f"the single fit_fringes job on the same files: {single['s']:.1f} s, {single['max_rss_mb']:.0f} MB "
              f"(its command {single['command_s']:.0f} s); its product "
              f"{'is' if single['bit_identical'] else 'is NOT'} the split fit's: every data variable identical "
              f"(values, coordinates, attributes), the same inputs and checksums")
    print()
    print("| job | count | wall time (s) | peak RSS (MB) | s per 1e9 samples of its files |")
    print("|---|---:|---:|---:|---:|")
    by_rule = defaultdict(list)
    for job in summary["jobs"]:
        by_rule[job["rule"]].append(job)
    for rule, jobs in by_rule.items():
        s = [j["s"] for j in jobs]
        rss = [j["max_rss_mb"] for j in jobs]
        reading = [j for j in jobs if j["frames"] and rule in ("simulate_file (metrology)", "fit_part (pass 1)",
                                                               "fit_part (later passes)", "allan_deviation")]
        per = [j["s"] / (summary["pixels"] * j["frames"] / 1e9) for j in reading]
        print(f"| {rule} | {len(jobs)} | {span(s, '.1f')} | {span(rss, '.0f')} | "
              f"{span(per, '.1f') if per else ''} |")


def span(values, fmt):
    lo, hi = min(values), max(values)
    return f"{lo:{fmt}}" if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}-{hi:{fmt}}"


def print_scaling(summaries: list[dict]) -> None:
    print("\n| detector | frames | 1e9 samples | baseline (GB) | reduction command (s) | plain pass (s) "
          "| fit_part pass 1 (s) | fit_part later (s) | fit_part peak RSS (MB) | fit_start (s, MB) "
          "| fit_reduce (s, MB) | fit_finish (s, MB) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for summary in summaries:
        jobs = summary["jobs"]

        def pick(rule, with_frames=True):
            return [j for j in jobs if j["rule"] == rule and (j["frames"] or not with_frames)]

        first, later = pick("fit_part (pass 1)"), pick("fit_part (later passes)")
        one = {rule: pick(rule, False) for rule in ("fit_start", "fit_reduce", "fit_finish")}
        rows, cols = summary["size"].split("x")[:2]
        print(f"| {rows}x{cols} | {summary['frames']} | {summary['gsamples']:.2f} | {summary['cube_gb']:.1f} "
              f"| {summary['reduce_s']:.0f} | {summary['plain_pass_s']:.1f} | {span([j['s'] for j in first], '.1f')} "
              f"| {span([j['s'] for j in later], '.1f') if later else ''} "
              f"| {span([j['max_rss_mb'] for j in first + later], '.0f')} "
              + " ".join(f"| {span([j['s'] for j in one[r]], '.1f')}, {span([j['max_rss_mb'] for j in one[r]], '.0f')}"
                         for r in one) + " |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sizes", nargs="*", default=["1024x1024x20000"], help="ROWSxCOLSxFRAMES of the baseline")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/dice-large"))
    parser.add_argument("--parts", type=int, default=2, help="metrology.parts: part jobs a pass")
    parser.add_argument("--max-passes", type=int, default=10, help="metrology.max_passes")
    parser.add_argument("--target", choices=["fit", "metrology", "all"], default="metrology",
                        help="fit: the metrology product; metrology: and the Allan deviations; all: the preset's "
                             "default target")
    parser.add_argument("--drop-raw", action="store_true", help="remove each size's raw files after it")
    parser.add_argument("--keep-raw", action="store_true",
                        help="raw files simulated by other code are not made again, nor what their code's change "
                             "would rerun: Snakemake's --rerun-triggers mtime (for a reduction measured on raw "
                             "files simulated before)")
    parser.add_argument("--single", action="store_true",
                        help="also run the single fit_fringes job on the same files and compare the products")
    parser.add_argument("--report", action="store_true", help="print the tables of sizes already run")
    args = parser.parse_args(argv)
    if args.keep_raw:
        SNAKEMAKE_OPTIONS.extend(["--rerun-triggers", "mtime"])
    args.workdir = args.workdir.resolve()
    args.workdir.mkdir(parents=True, exist_ok=True)
    if args.report:
        summaries = []
        for size in args.sizes:
            summary = json.loads((args.workdir / f"{dataset_name(size_overrides(*map(int, size.split('x'))))}.json")
                                 .read_text())
            print(f"\n## {size}: {summary['name']}")
            print_size(summary)
            summaries.append(summary)
    else:
        print(f"machine: {machine()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
        summaries = [run_size(size, args) for size in args.sizes]
    print_scaling(summaries)


if __name__ == "__main__":
    main()
