"""Arrays on disk for a job's intermediate results that grow with pixels times batches.

A :func:`scratch_directory` is a temporary folder (beside the job's output, or in the system's temporary
folder) removed when its block ends, on an error too. A :class:`ScratchArray` is one array in a file there:
it is read and written by numpy indexing, each access through a map of the file made for it and dropped
after it, so that what the job reads or writes stays in the job's memory only for that access (a map kept
open would keep every page it touched counted in the job's resident memory). The file stays open: an array
stays readable after its folder is removed, and its disk space is freed when the array is dropped.
"""

from __future__ import annotations

import contextlib
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
    with tempfile.TemporaryDirectory(prefix=".dice-scratch-", dir=near) as folder:
        yield Path(folder)


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

    def __getitem__(self, key) -> np.ndarray:
        if self.size == 0:
            return np.zeros(self.shape, self.dtype)[key]
        # the map is dropped (unmapped) on return: nothing else refers to it once its elements are copied
        return np.array(self._map("r")[key])

    def __setitem__(self, key, values):
        if self.size:
            self._map("r+")[key] = values

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
