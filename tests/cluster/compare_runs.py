"""Checks of tests/cluster/slurm.sh: every job went through sbatch; the products equal a local run's.

    python tests/cluster/compare_runs.py jobs --local-log L --slurm-log S --jobcomp J
    python tests/cluster/compare_runs.py products LOCAL_RESULTS SLURM_RESULTS

Exits 1 with the differences listed, 0 with a summary.
"""

import argparse
import collections
import json
import re
import sys
from pathlib import Path

import numpy as np
import xarray as xr
from matplotlib import image

#: Global attributes of a product that may differ between two runs of the same code: the write time.
VOLATILE_ATTRS = ("history",)
#: Folders of timings and messages, which differ between any two runs.
SKIPPED_FOLDERS = ("logs", "benchmarks")
#: Stands for each run's copy of the repository in the attributes that name files (``inputs``).
COPY = "<copy of the repository>"


def without_copy_folder(ds, folder):
    """The dataset with its copy's folder replaced by :data:`COPY` in every string attribute, and in
    ``inputs`` the SHA-256 of each input that is itself a netCDF product left out: a product's bytes hold
    its write time (``history``), so its checksum differs between any two runs. The raw files' (FITS cubes,
    the manifest) are compared."""
    ds = ds.copy()
    for attrs in [ds.attrs] + [ds[name].attrs for name in ds.variables]:
        for key, value in attrs.items():
            if isinstance(value, str):
                attrs[key] = value.replace(folder, COPY)
    if "inputs" in ds.attrs:
        records = json.loads(ds.attrs["inputs"])
        for record in records:
            if record["path"].endswith(".nc"):
                record["sha256"] = "(a product: its write time is in its bytes)"
        ds.attrs["inputs"] = json.dumps(records)
    return ds


def job_stats(log):
    """{rule: count} of the first 'Job stats' table of a Snakemake log: the jobs the run planned."""
    lines = Path(log).read_text().splitlines()
    start = lines.index("Job stats:") + 3  # the header and its rule
    counts = {}
    for line in lines[start:]:
        parts = line.split()
        if len(parts) != 2 or parts[0] == "total":
            break
        counts[parts[0]] = int(parts[1])
    return counts


def check_jobs(local_log, slurm_log, jobcomp):
    problems = []
    planned = job_stats(local_log)
    planned_slurm = job_stats(slurm_log)
    if planned != planned_slurm:
        problems.append(f"the runs planned different jobs: local {planned}, SLURM {planned_slurm}")
    text = Path(slurm_log).read_text()
    if "steps (100%) done" not in text:
        problems.append("the SLURM run did not finish all its steps")
    # rules without a job to run (the target rules) are the only ones Snakemake may handle on the spot
    local_rules = sorted(set(re.findall(r"^localrule (\w+):", text, re.M)) - {"all"})
    if local_rules:
        problems.append(f"jobs ran outside SLURM: localrule {local_rules}")
    submitted = re.findall(r"Job (\d+) has been submitted with SLURM jobid (\d+) \(log: (\S+)\)", text)
    rules = collections.Counter(re.search(r"/rule_(\w+?)/", log).group(1) for _, _, log in submitted)
    expected = collections.Counter({rule: n for rule, n in planned.items() if rule != "all"})
    if rules != expected:
        problems.append(f"submitted jobs {dict(rules)} are not the planned jobs {dict(expected)}")
    ids = [slurm_id for _, slurm_id, _ in submitted]
    if len(set(ids)) != len(ids):
        problems.append("a SLURM job id was reported twice")
    records = {}
    for line in Path(jobcomp).read_text().splitlines():
        fields = dict(f.split("=", 1) for f in line.split() if "=" in f)
        records[fields["JobId"]] = fields
    names = {records[i]["Name"] for i in ids if i in records}
    for slurm_id in ids:
        record = records.get(slurm_id)
        if record is None:
            problems.append(f"SLURM job {slurm_id} is not in the job completion log")
        elif record["JobState"] != "COMPLETED" or record["ExitCode"] != "0:0":
            problems.append(f"SLURM job {slurm_id}: {record['JobState']}, exit code {record['ExitCode']}")
    if len(names) != 1:
        problems.append(f"the SLURM jobs do not share one run name: {sorted(names)}")
    others = [i for i, r in records.items() if r["Name"] in names and i not in ids]
    if others:
        problems.append(f"SLURM jobs of the run that Snakemake did not report: {others}")
    if problems:
        print("\n".join(problems))
        return 1
    print(f"jobs: {len(ids)} jobs of {len(rules)} rules, each submitted with sbatch and COMPLETED with exit code "
          f"0:0 in the job completion log (run {names.pop()}); none ran locally")
    return 0


def product_files(root):
    return sorted(p.relative_to(root) for p in Path(root).rglob("*")
                  if p.is_file() and p.relative_to(root).parts[0] not in SKIPPED_FOLDERS)


def check_products(local, slurm):
    local, slurm = Path(local), Path(slurm)
    copies = (str(local.resolve().parents[1]), str(slurm.resolve().parents[1]))  # <copy>/results/<name>
    files = product_files(local)
    problems = []
    if files != product_files(slurm):
        problems.append(f"different files: only local {sorted(set(files) - set(product_files(slurm)))}, "
                        f"only SLURM {sorted(set(product_files(slurm)) - set(files))}")
    kinds = collections.Counter()
    volatile = collections.Counter()
    for rel in files:
        a, b = local / rel, slurm / rel
        if not b.is_file():
            continue
        if rel.suffix == ".nc":
            with xr.open_dataset(a) as x, xr.open_dataset(b) as y:
                x, y = without_copy_folder(x.load(), copies[0]), without_copy_folder(y.load(), copies[1])
            for name in VOLATILE_ATTRS:
                volatile[name] += x.attrs.get(name) != y.attrs.get(name)
                x.attrs.pop(name, None)
                y.attrs.pop(name, None)
            try:
                xr.testing.assert_identical(x, y)
            except AssertionError as exc:
                problems.append(f"{rel}: {str(exc)[:2000]}")
        elif rel.suffix == ".png":
            if not np.array_equal(image.imread(a), image.imread(b)):
                problems.append(f"{rel}: the pixels differ")
        elif rel.suffix == ".pdf":
            pass  # the same figures as the PNGs, with a creation date inside
        elif a.read_bytes() != b.read_bytes():
            problems.append(f"{rel}: the bytes differ")
        kinds[rel.suffix] += 1
    if problems:
        print("\n".join(problems))
        return 1
    print(f"products: {sum(kinds.values())} files identical to the local run's ({dict(kinds)}; netCDF by "
          f"xarray.testing.assert_identical, data, coordinates and attributes, global attributes "
          f"{list(VOLATILE_ATTRS)} left out, different in {dict(volatile)} files, each copy's folder in the "
          f"attributes naming files replaced by {COPY!r}, the SHA-256 of inputs that are products (their "
          f"bytes hold their write time) left out; FITS, CSV, TeX and YAML byte "
          f"for byte; PNG pixel for pixel; PDF files present, their bytes not compared)")
    return 0


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="what", required=True)
    jobs = sub.add_parser("jobs")
    jobs.add_argument("--local-log", required=True)
    jobs.add_argument("--slurm-log", required=True)
    jobs.add_argument("--jobcomp", required=True)
    products = sub.add_parser("products")
    products.add_argument("local")
    products.add_argument("slurm")
    args = parser.parse_args(argv)
    if args.what == "jobs":
        return check_jobs(args.local_log, args.slurm_log, args.jobcomp)
    return check_products(args.local, args.slurm)


if __name__ == "__main__":
    sys.exit(main())
