"""Arrays on disk for a job's intermediate results that grow with pixels times batches.

A :func:`scratch_directory` is a temporary folder (beside the job's output, or in the system's temporary
folder) removed when its block ends, on an error too. A :class:`ScratchArray` is one array in a file there:
it is read and written by numpy indexing: runs along the last axis (``a[b]``, ``a[:, lo:hi]``) with
``pread``/``pwrite``, any other key through a map of the file made for it and dropped after it, so that what
the job reads or writes is in its memory only for that access (a map kept open keeps every page it touched
counted in the job's resident memory, and a map's faults bring in the neighbouring pages too). The file stays
open: an array stays readable after its folder is removed, and its disk space is freed when the array is
dropped.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import secrets
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["scratch_directory", "ScratchArray"]


@contextlib.contextmanager
def scratch_directory(near=None):
    """A temporary folder inside ``near`` (a folder; None: the system's temporary folder), removed when the
    block ends, on an error too: yields its path."""
    if near is not None:
        Path(near).mkdir(parents=True, exist_ok=True)
    # the folder may not go at once where its files are still open (NFS keeps an open file removed as a
    # .nfs file until it is closed): a warning then, not a failure of the job that made it
    folder = tempfile.TemporaryDirectory(prefix=".dice-scratch-", dir=near, ignore_cleanup_errors=True)
    try:
        yield Path(folder.name)
    finally:
        folder.cleanup()
        if Path(folder.name).exists():
            logging.getLogger("dice").warning("could not remove the scratch folder %s; remove it by hand",
                                              folder.name)


class ScratchArray:
    """An array of ``shape`` and ``dtype`` in a new file of ``folder`` (zeros until written).

    ``a[key]`` returns a copy in memory of those elements; ``a[key] = values`` writes them. Picklable: a
    worker process reopens the file by its path (while the folder exists) and writes where its parent reads.
    """

    def __init__(self, folder, shape, dtype, *, name: str = "array"):
        self.shape, self.dtype = tuple(int(n) for n in shape), np.dtype(dtype)
        self.path = Path(folder) / f"{name}-{secrets.token_hex(6)}.bin"
        self._file = open(self.path, "x+b")  # a new file: never another array's
        self._owner = True  # the owner removes the file when dropped; a worker's copy does not
        self._file.truncate(max(1, self.nbytes))  # sparse: no block written until the array is

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize

    def __len__(self) -> int:
        return self.shape[0]

    def _open(self):
        if self._file is None:
            self._file = open(self.path, "r+b")
        return self._file

    def _map(self, mode):
        return np.memmap(self._open(), dtype=self.dtype, mode=mode, shape=self.shape)

    def _runs(self, key):
        """For a key of ints or whole slices then a step-1 slice (or int) of the last axis: the leading
        indices (a list of tuples), the last axis' [lo, hi) and the result's shape; None for any other key."""
        key = key if isinstance(key, tuple) else (key,)
        if any(k is Ellipsis for k in key):
            whole = (slice(None),) * (self.ndim - len(key) + 1)
            at = next(i for i, k in enumerate(key) if k is Ellipsis)
            key = key[:at] + whole + key[at + 1:]
        key = key + (slice(None),) * (self.ndim - len(key))
        if len(key) != self.ndim:
            return None
        leading, shape = [], []
        for k, n in zip(key[:-1], self.shape[:-1]):
            if isinstance(k, (int, np.integer)):
                leading.append([range(n)[k]])
            elif isinstance(k, slice):
                leading.append(range(n)[k])
                shape.append(len(leading[-1]))
            else:
                return None
        last, n = key[-1], self.shape[-1]
        if isinstance(last, (int, np.integer)):
            lo = range(n)[last]
            return leading, (lo, lo + 1), tuple(shape)
        if not isinstance(last, slice) or last.step not in (None, 1):
            return None
        lo, hi, _ = last.indices(n)
        return leading, (lo, max(lo, hi)), (*shape, max(0, hi - lo))

    def _offsets(self, leading, lo):
        """Byte offset of each leading index's element ``lo`` of the last axis."""
        strides = np.cumprod((1, *self.shape[::-1][:-1]))[::-1]  # elements per step of each axis
        return [int(np.dot(index, strides[:-1]) + lo) * self.dtype.itemsize
                for index in itertools.product(*leading)]

    def __getitem__(self, key) -> np.ndarray:
        runs = self._runs(key)
        if runs is None:  # any other key: through a map, dropped (unmapped) once its elements are copied
            return np.zeros(self.shape, self.dtype)[key] if self.size == 0 else np.array(self._map("r")[key])
        # runs of the last axis read with pread: no map whose neighbouring pages the kernel would map too
        leading, (lo, hi), shape = runs
        out = np.empty((len(list(itertools.product(*leading))), hi - lo), self.dtype)
        fd = self._open().fileno()
        for row, offset in zip(out, self._offsets(leading, lo)):
            if row.nbytes and os.preadv(fd, [row], offset) != row.nbytes:
                raise OSError(f"{self.path}: short read")
        return out.reshape(shape)

    def __setitem__(self, key, values):
        runs = self._runs(key)
        if runs is None:
            if self.size:
                self._map("r+")[key] = values
            return
        leading, (lo, hi), shape = runs
        values = np.ascontiguousarray(np.broadcast_to(np.asarray(values, self.dtype), shape)).reshape(-1, hi - lo)
        fd = self._open().fileno()
        for row, offset in zip(values, self._offsets(leading, lo)):
            try:
                written = os.pwritev(fd, [row], offset) if row.nbytes else 0
            except OSError as exc:  # a full disk says ENOSPC without a file name: the scratch file's, in one line
                raise OSError(exc.errno, f"{exc.strerror} (writing a scratch array)",
                              str(self.path)) from None
            if written != row.nbytes:  # (a full disk may also stop a write short)
                raise OSError(f"{self.path}: short write, {written} of {row.nbytes} bytes (is the disk full?)")

    def __array__(self, dtype=None, copy=None):
        whole = self[...]
        return whole if dtype is None else whole.astype(dtype, copy=False)

    def __getstate__(self):
        return {"shape": self.shape, "dtype": self.dtype, "path": self.path, "_file": None, "_owner": False}

    def __setstate__(self, state):
        self.__dict__.update(state)

    def __del__(self):  # the disk space is freed once the file is both closed and removed
        if getattr(self, "_file", None) is not None:
            self._file.close()
        if getattr(self, "_owner", False):
            self.path.unlink(missing_ok=True)
