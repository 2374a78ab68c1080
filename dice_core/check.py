"""Check a dataset before reducing it: ``python -m dice_core check PATH/dataset.yaml [--data]``.

Reads the manifest (:mod:`dice_core.manifest`) and every file's header (:func:`dice_core.io.open_cube`:
present, FITS, a supported sample type, the detector's frame shape, as long as its header says), and with
``--data`` every sample and checksum (:class:`dice_core.io.FrameStream`, the reader the steps use: non-finite
samples, frames saturated over the whole science area, CHECKSUM and DATASUM). It then plans the run as the
workflow would (:class:`dice_core.planning.Plan`, with the workflow's configuration) and says what the run
would reduce, what it would skip and why, and every problem as one line ``problem: <file>: <problem>``.
Exit status 0 when there is no problem, 1 otherwise.

The checks are the workflow's own, called the same way, so a dataset the checker passes is one whose files the
workflow's steps will read, and a problem it names is the one the step reading that file would stop on.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from dice_core import DatasetError, error_line

__all__ = ["Report", "check_dataset", "workflow_config", "main"]


@dataclass
class Report:
    """What :func:`check_dataset` found: ``lines`` to print in order (what would be reduced, skipped), the
    ``problems`` (one line each, without the ``problem:`` prefix), and how much was read."""

    lines: list = field(default_factory=list)
    problems: list = field(default_factory=list)
    files: int = 0
    frames: int = 0
    saturated: int = 0

    def problem(self, text: str) -> None:
        self.problems.append(" ".join(str(text).split()))


def workflow_config(root, configfiles=()) -> dict:
    """The workflow's configuration as a run from the folder ``root`` (the repository: its
    ``config/config.yaml`` and ``workflow/schemas/config.schema.yaml``) would check it, with ``configfiles``
    (a run's ``--configfile``) laid over it, section by section as Snakemake does; its defaults set.

    Raises
    ------
    dice_core.settings.SettingsError
        A configuration that the workflow would refuse (one line per problem).
    """
    from dice_core import settings, yamlfile

    root = Path(root)
    schema = settings.config_schema(root / "workflow" / "schemas" / "config.schema.yaml")
    files = [root / "config" / "config.yaml", *map(Path, configfiles)]
    values: dict = {}
    for path in files:
        _merge(values, yamlfile.read(path) or {})
    return settings.checked(values, schema, files=files)


def _merge(values: dict, overrides: dict) -> None:
    """``overrides`` into ``values`` at every depth, as Snakemake merges ``--configfile`` files."""
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(values.get(key), dict):
            _merge(values[key], value)
        else:
            values[key] = value


def _workflow_root(given) -> Path | None:
    """The repository whose configuration the run would use: ``given``, else the working folder when it
    holds a Snakefile, else the source tree this dice_core comes from (an editable install)."""
    candidates = [Path(given)] if given else [Path.cwd(), Path(__file__).resolve().parents[1]]
    for folder in candidates:
        if (folder / "Snakefile").is_file() and (folder / "config" / "config.yaml").is_file():
            return folder
    return None


def _check_file(path, manifest, report: Report, *, data: bool) -> None:
    """One file's header (and with ``data`` its samples and checksums), each problem into ``report``."""
    from dice_core import io
    from dice_core.manifest import Acquisition

    try:
        stream = io.FrameStream(Acquisition(str(path), (Path(path),)), manifest.detector, dtype="float32")
        saturated = 0
        if data:
            for chunk in stream:
                if chunk.any_saturated:
                    saturated += int(chunk.saturated.sum())
        report.files += 1  # counted once it has been read as far as asked: a bad checksum is not "readable"
        report.frames += stream.n_frames
        report.saturated += saturated
    except DatasetError as exc:
        report.problem(exc)
    except OSError as exc:  # a file that vanished or cannot be read while it is read
        report.problem(f"{path}: {error_line(exc)}")


def _read_files(manifest, report: Report, *, data: bool) -> None:
    """Every acquisition's files checked, and one line per kind of acquisition: files and frames."""
    counts: dict = {}
    for acquisition in manifest.acquisitions():
        before = report.files, report.frames
        for path in acquisition.files:
            _check_file(path, manifest, report, data=data)
        kind = "star positions" if acquisition.label.startswith("position") else acquisition.label
        files, frames, n = counts.get(kind, (0, 0, 0))
        counts[kind] = (files + report.files - before[0], frames + report.frames - before[1], n + 1)
    shape = "x".join(map(str, manifest.detector.shape))
    for kind, (files, frames, n) in counts.items():
        many = f"{n} positions, " if kind == "star positions" else ""
        report.lines.append(f"{kind}: {many}{files} readable file(s), {frames} frames of {shape} pixels")


def _plan_lines(manifest, config, report: Report) -> None:
    """What the workflow would make of the manifest (products by stage) and skip, from its own plan."""
    from dice_core import planning, products

    try:
        plan, targets = planning.plan_run(manifest, config)
    except planning.PlanningError as exc:
        report.problem(exc)
        return
    out = plan.dataset_root
    stages: dict = {}
    for target in targets:
        found = products.match(target, root=out)
        product = found[0] if found else None
        stage = product.stage if product else "other"
        stages.setdefault(stage, {}).setdefault(product.path if product else target, 0)
        stages[stage][product.path if product else target] += 1
    report.lines.append(f"the workflow would write {len(targets)} files under {out}/:")
    for stage, paths in stages.items():
        listed = ", ".join(p if n == 1 or "{" not in p else f"{p} (x{n})" for p, n in paths.items())
        report.lines.append(f"  {stage}: {listed}")
    report.lines += plan.skipped


def check_dataset(path, *, config: dict | None, data: bool = False) -> Report:
    """Check the dataset whose manifest is ``path``: its manifest, every file's header (with ``data``, every
    sample and checksum), and, given the workflow's ``config`` (:func:`workflow_config`), what a run would make
    and skip. Nothing is written. Problems are collected, not raised: every one is said."""
    from dice_core.manifest import load_manifest

    report = Report()
    try:
        manifest = load_manifest(path, check_files=False)  # each missing file is said below, not the first alone
    except DatasetError as exc:
        for problem in getattr(exc, "problems", None) or (exc.problem,):  # a ManifestError's: every one
            report.problem(f"{exc.path}: {problem}")
        return report
    rows, cols = manifest.detector.science_rows, manifest.detector.science_cols
    report.lines.append(f"dataset {manifest.name} ({manifest.path}): detector {manifest.detector.shape[0]}x"
                        f"{manifest.detector.shape[1]}, science area rows {rows[0]}-{rows[1]}, cols "
                        f"{cols[0]}-{cols[1]} (half-open)")
    _read_files(manifest, report, data=data)
    if data:
        report.lines.append(f"saturated samples (masked by the steps): {report.saturated}")
    if config is not None:
        _plan_lines(manifest, config, report)
    return report


def main(argv=None) -> int:
    """``python -m dice_core check``: print the report, return the exit status (0: no problem)."""
    parser = argparse.ArgumentParser(
        prog="python -m dice_core check",
        description="Check a dataset (its manifest, every file's header; with --data every sample and checksum) "
                    "and say what the workflow would reduce, what it would skip and why, and every problem, one "
                    "line each. Exit status 0 when there is no problem, 1 otherwise.")
    parser.add_argument("manifest", help="the dataset's manifest, PATH/dataset.yaml")
    parser.add_argument("--data", action="store_true", help="also read every sample and verify the checksums")
    parser.add_argument("--configfile", action="append", default=[], metavar="FILE",
                        help="a configuration file the run would be given (as snakemake's --configfile)")
    parser.add_argument("--workflow", metavar="DIR", help="the repository whose configuration the run uses "
                        "(default: the working folder, else the one this dice_core comes from)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    root = _workflow_root(args.workflow)
    config, report = None, Report()
    if root is None:
        report.problem(f"{args.workflow or Path.cwd()}: no workflow here (Snakefile and config/config.yaml); "
                       "run from the repository or give --workflow")
    else:
        from dice_core import settings

        try:
            config = workflow_config(root, args.configfile)
        except (settings.SettingsError, DatasetError) as exc:
            for line in str(exc).splitlines():
                report.problem(line)
    if config is not None:
        report = check_dataset(args.manifest, config=config, data=args.data)
    for line in report.lines:
        print(line)
    for line in report.problems:
        print(f"problem: {line}")
    read = "headers, samples and checksums" if args.data else "headers"
    verdict = "no problem" if not report.problems else f"{len(report.problems)} problem(s)"
    print(f"{verdict}: {report.files} file(s), {report.frames} frames checked ({read}) in "
          f"{time.perf_counter() - start:.1f} s")
    sys.stdout.flush()
    return 1 if report.problems else 0
