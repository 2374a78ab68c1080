# A run that was killed (kill -9, a closed terminal, the machine down) leaves
# Snakemake's lock behind in .snakemake/locks/, and the next run stops with
# "Directory cannot be locked" until `snakemake --unlock`. Snakemake's lock is
# a plain file: it cannot tell a dead run from a live one. The kernel can: each
# run of this workflow holds an flock on .snakemake/dice/running for its whole
# life, which the kernel releases when the process ends, however it ends. A run
# that gets that flock knows that no other run of the workflow is alive in this
# folder on this machine, so the Snakemake locks it finds are stale and it
# removes them; a run that does not get it leaves them to Snakemake, which
# refuses to start on files that the live run is making. --nolock would instead
# let two live runs write the same products. Snakemake's refusal then names the
# live run (its pid, from the guard file) and says not to --unlock. The
# temporary files a killed run left are removed in workflow/rules/preflight.smk.

import fcntl
import os
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import snakemake.exceptions


def explain_lock(message):
    """Have Snakemake's refusal to start on locked files say ``message``, in one line, instead of its own,
    which asks for ``--unlock`` whatever holds the lock (Snakemake raises
    ``snakemake.exceptions.LockException`` by that name, after this file is read). Dry runs, which Snakemake
    lets through, are not affected."""

    class RunLocked(snakemake.exceptions.LockException):
        def __init__(self):  # raised before Snakemake writes any lock: nothing to release
            print(f"dice: {message}", file=sys.stderr)
            raise SystemExit(1)

    snakemake.exceptions.LockException = RunLocked


@dataclass
class RunLock:
    """This run's hold on the working folder: ``guard``, the flocked guard file (kept open for the life of
    the run), and ``alone``, whether no other run of the workflow can be alive here: this run holds the
    flock and no lock of a run on another machine sharing the folder is left (what the removal of a killed
    run's temporary files waits for)."""

    guard: object
    alone: bool


def take_run_lock(state=".snakemake"):
    """Hold this run's flock and remove Snakemake's locks when they are stale.

    Returns a :class:`RunLock`, or None where this process is not the run itself (a job's Snakemake
    subprocess), another run of the workflow is alive, or the filesystem has no flock. The guard file
    records the machine, process and start of the run that holds it: a second run told that one is alive is
    told which, and a lock left by a run on another machine sharing this folder, whose flock this machine
    may not see, is left alone.
    """
    if not getattr(workflow, "is_main_process", True):
        return None
    state = Path(state)
    path = state / "dice" / "running"
    path.parent.mkdir(parents=True, exist_ok=True)
    guard = open(path, "a+")
    try:
        fcntl.flock(guard, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:  # held by a live run (EWOULDBLOCK), or no flock on this filesystem
        guard.seek(0)
        holder = guard.read().split()
        guard.close()
        if isinstance(exc, BlockingIOError):
            who = f"pid {holder[1]}, started {holder[2]}" if len(holder) >= 3 else "its pid is not recorded"
            explain_lock(
                f"another run of this workflow is alive in this folder ({who}) and makes some of the same "
                "files: wait for it to end, or stop it (Ctrl-C in its terminal, or kill its process group); "
                "do not use --unlock, which would let both runs write the same products"
            )
        return None
    guard.seek(0)
    last = guard.read().split()
    last_machine = last[0] if last else ""
    machine = socket.gethostname()
    locks = sorted((state / "locks").glob("*.lock"))
    if locks and last_machine != machine:
        # left by a run elsewhere (or by a version of the workflow before this guard): Snakemake
        # says whether they block this run, and --unlock removes them
        explain_lock(
            f"the files of this run are locked by a run on machine {last_machine or '(unknown)'}, which shares "
            "this folder and whose processes this machine cannot see: if no run of this workflow is alive "
            "there, remove its lock with snakemake --unlock; if one is, wait for it"
        )
        return RunLock(guard, alone=False)
    # this run's line, at once: a second run started from here on is told this run's pid
    guard.seek(0)
    guard.truncate()
    guard.write(f"{machine} {os.getpid()} {time.strftime('%Y-%m-%dT%H:%M:%S')}\n")
    guard.flush()
    for lock in locks:
        lock.unlink(missing_ok=True)
    if locks:
        print(
            "dice: removed the lock of a run that ended without releasing it (killed?); "
            "no other run of this workflow is alive here",
            file=sys.stderr,
        )
    return RunLock(guard, alone=True)


# Once per run: the modules of a reduction sweep's points read this file again with the same workflow object,
# and their second flock on the guard would fail against the run's own.
if "_dice_run_lock" not in vars(workflow):
    vars(workflow)["_dice_run_lock"] = take_run_lock()
RUN_LOCK = vars(workflow)["_dice_run_lock"]
