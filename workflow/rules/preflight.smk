# Checks made once the jobs are planned and before any of them runs: Snakemake's
# onstart, which a dry run skips (it writes nothing), as does --no-hooks (which
# Snakemake's own cluster jobs are started with: the checks ran in the main run).
# A problem stops the run with one line; nothing has been written or deleted yet
# (Snakemake deletes a job's old outputs only when the job starts).
#
# - Every file a job writes (output, log, benchmark) lies inside this run's
#   results folders: the dataset's and the sweeps'. Names from a manifest are
#   checked when it is read (dice_core.manifest.NAME_PATTERN); this is the one
#   check over every path actually planned, whatever put it there. Paths are
#   compared lexically: a results folder, or a folder in it, that the user links
#   to another disk stays where the user put it.
# - Every folder a job writes in can be written, and the disk holds the cubes
#   the simulation is about to write.
# - The temporary files (.<name>.<hex>.part) that a killed run left beside the
#   outputs of this run's jobs are removed, when no other run of the workflow
#   can be alive here (workflow/rules/locks.smk), Snakemake has locked those
#   outputs for this run, and no live process writes in their folder
#   (dice_core.io.remove_abandoned).

import os
import sys
from pathlib import Path

import numpy as np

from dice_core import io as dice_io
from dice_core import preflight


def job_files(job):
    """The files a planned job writes: its outputs, logs and benchmark."""
    return [*job.output, *job.log, *([job.benchmark] if job.benchmark else [])]


def simulated_bytes(jobs):
    """Bytes of the FITS cubes the planned simulation jobs of this run write (headers aside; a reduction sweep
    point's own simulation, whose rules carry its module's prefix, is not counted)."""
    if SIMULATION is None:
        return 0
    sample = np.dtype(SIMULATION.detector.dtype).itemsize
    simulating = [job for job in jobs if (steps.rule_group(job.rule.name) or ("",))[0] == "simulate_file"]
    return sum(
        sample * PIXELS * SIM_FRAMES.get(str(Path(f).relative_to(RAW)), 0) for job in simulating for f in job.output
    )


def check_planned_jobs(dag):
    """Refuse the run, in one line, if a planned job would write outside the results folders or where it
    cannot; remove the temporary files of a killed run."""
    roots = [OUT, SWEEP_ROOT]
    files = [str(f) for job in dag.jobs for f in job_files(job)]
    outside = preflight.paths_outside(files, roots)
    if outside:
        more = f" (and {len(outside) - 1} more)" if len(outside) > 1 else ""
        fail(
            f"{outside[0]}{more}: a planned job would write outside this run's results folders "
            f"{' and '.join(roots)}; nothing was run"
        )
    running = list(dag.needrun_jobs())
    folders = sorted({str(Path(str(f)).parent) for job in running for f in job_files(job)})
    for existing, (why, asked) in preflight.unwritable_folders(folders).items():
        more = f" and {len(asked) - 1} other folder(s)" if len(asked) > 1 else ""
        fail(f"cannot write in {existing} ({why}), where this run writes {asked[0]}{more}; nothing was run")
    needed = simulated_bytes(running)
    short = preflight.disk_shortfall(RAW, needed) if needed else 0
    if short:
        fail(
            f"{RAW}: the simulation writes {preflight.size_text(needed)} of cubes and the disk lacks "
            f"{preflight.size_text(short)} of it; free some space or set config results to another disk; "
            "nothing was run"
        )
    if RUN_LOCK is not None and RUN_LOCK.alone:
        remove_stale_temporaries(running)


def remove_stale_temporaries(jobs):
    """Remove the temporary files that a killed run left beside the outputs of the jobs this run will run
    (Snakemake has locked those outputs for it), in folders where no process writes now."""
    targets = {}
    for job in jobs:
        for output in job.output:
            targets.setdefault(os.path.dirname(str(output)) or ".", []).append(str(output))
    removed = []
    for folder, outputs in sorted(targets.items()):
        try:
            removed += dice_io.remove_abandoned(folder, outputs)
        except OSError as exc:  # one that cannot be removed is left, and said
            print(f"dice: a temporary file of a killed run in {folder} stays: {exc.strerror or exc}", file=sys.stderr)
    if removed:
        folders = sorted({str(part.parent) for part in removed})
        print(
            f"dice: removed {len(removed)} temporary file(s) left by a run that was cut short, in {', '.join(folders)}",
            file=sys.stderr,
        )


onstart:
    check_planned_jobs(workflow.dag)
    say_skipped()
