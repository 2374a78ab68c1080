"""What a workflow run checks once its jobs are planned and before any of them runs.

A job's output is deleted by the workflow engine before the job runs and then
written, so a path that leaves the run's results folder is a file destroyed
wherever it is: :func:`paths_outside` finds them. Names from a dataset's
manifest are already restricted (:data:`dice_core.manifest.NAME_PATTERN`);
this is the one check over every path actually planned, whatever put it there.
:func:`unwritable_folders` and :func:`disk_shortfall` turn what would be a
traceback in the middle of a run (a read-only results folder, a disk too small
for the simulated cubes) into one line before it starts.

Nothing here knows the workflow engine: the caller passes plain paths.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

__all__ = ["normalised", "paths_outside", "unwritable_folders", "disk_shortfall", "nearest_existing", "size_text"]


def normalised(path) -> str:
    """``path`` absolute and with ``.`` and ``..`` resolved lexically (symbolic links are not followed:
    a results folder the user links to another disk stays the results folder)."""
    return os.path.normpath(os.path.abspath(os.fspath(path)))


def paths_outside(paths, roots) -> list[str]:
    """The paths (as given, in their order, once each) that do not lie inside any of the folders ``roots``."""
    folders = [normalised(root) for root in roots]
    outside = []
    for path in dict.fromkeys(map(os.fspath, paths)):
        where = normalised(path)
        if not any(where.startswith(folder + os.sep) for folder in folders):
            outside.append(path)
    return outside


def nearest_existing(path) -> Path:
    """``path`` itself if it exists, else its nearest existing ancestor (the folder a new file lands in)."""
    path = Path(normalised(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def unwritable_folders(folders) -> dict[str, tuple[str, list[str]]]:
    """The folders that a file cannot be created in: {existing folder: (why, [the folders asked for that
    land there])}. Tried for real, by creating and removing a file in each folder or, where it does not
    exist yet, in its nearest existing ancestor (where the workflow would create it): a permission check
    alone would pass for root, and on a read-only filesystem or an immutable folder."""
    problems, tried = {}, {}
    for folder in dict.fromkeys(map(os.fspath, folders)):
        existing = nearest_existing(folder)
        if existing not in tried:
            tried[existing] = _write_problem(existing)
        if tried[existing] is not None:
            problems.setdefault(str(existing), (tried[existing], []))[1].append(folder)
    return problems


def _write_problem(folder: Path) -> str | None:
    """Why no file can be created in ``folder``, or None."""
    if not folder.is_dir():
        return "a file, not a folder"
    try:
        with tempfile.TemporaryFile(dir=folder):  # gone when closed, whatever happens
            pass
    except OSError as exc:
        return exc.strerror or str(exc)
    return None


def disk_shortfall(folder, needed_bytes: int) -> int:
    """Bytes missing on the filesystem that will hold ``folder`` for ``needed_bytes`` more (0 if they fit)."""
    free = shutil.disk_usage(nearest_existing(folder)).free
    return max(0, int(needed_bytes) - free)


def size_text(n_bytes: float) -> str:
    """A number of bytes in the unit that reads best: kB, MB, GB or TB (powers of 1000), 3 digits."""
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if abs(n_bytes) >= scale:
            return f"{n_bytes / scale:.3g} {unit}"
    return f"{n_bytes / 1e3:.3g} kB"
