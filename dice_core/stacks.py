"""Star positions read once: each position's mean frame and batch means (the ``stars/<index>.nc`` product).

The pseudo-star centroids (:mod:`dice_core.centroids`) of every calibration
mode and method are measured from these, so that each position's cube is read
once whatever the number of modes and methods. A module of its own, with
numpy and xarray only, so that the one workflow step per position starts
fast. Units: adu for frames, frames for counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dice_core import lazy

xr = lazy.module("xarray")

__all__ = ["PositionStack", "batch_edges", "stack_position"]


@dataclass(frozen=True)
class PositionStack:
    """One detector position's frames reduced to what the centroids need: the ``stars/<index>.nc`` product.

    Attributes
    ----------
    mean : ndarray (row, col)
        Mean of all the position's frames, adu (dark not subtracted).
    batch_means : ndarray (batch, row, col)
        Means of consecutive batches of its frames, adu (see :func:`stack_position`).
    n_saturated : ndarray (row, col) of int
        Saturated samples of each pixel over all the frames.
    n_frames : int
        Frames averaged.
    position : int, optional
        The position's index, checked by :func:`dice_core.centroids.measure_positions`.
    """

    mean: np.ndarray
    batch_means: np.ndarray
    n_saturated: np.ndarray
    n_frames: int
    position: int | None = None

    @property
    def n_batches(self) -> int:
        return self.batch_means.shape[0]

    def to_dataset(self) -> xr.Dataset:
        """The ``stars/<index>.nc`` product of this stack."""
        rc = ("row", "col")
        edges = batch_edges(self.n_frames, self.n_batches)
        return xr.Dataset(
            {
                "mean": (rc, self.mean, {"units": "adu", "long_name": "mean of the position's frames"}),
                "batch_mean": (("batch", *rc), self.batch_means,
                               {"units": "adu", "long_name": "mean of each batch of consecutive frames"}),
                "n_saturated": (rc, self.n_saturated, {"units": "1", "long_name": "saturated samples of the pixel"}),
                "batch_frames": (("batch",), np.diff(edges), {"units": "1", "long_name": "frames in the batch"}),
                "n_frames": ((), self.n_frames, {"units": "1", "long_name": "frames averaged"}),
            },
            coords={"row": np.arange(self.mean.shape[0]), "col": np.arange(self.mean.shape[1]),
                    "batch": np.arange(self.n_batches)},
            attrs={} if self.position is None else {"position": int(self.position)},
        )

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> "PositionStack":
        """The stack held by a ``stars/<index>.nc`` product."""
        return cls(ds["mean"].values, ds["batch_mean"].values, ds["n_saturated"].values.astype(np.int64),
                   int(ds["n_frames"]), ds.attrs.get("position"))


def batch_edges(n_frames: int, n_batches: int) -> np.ndarray:
    """Frame indices [edge_b, edge_b+1) of ``n_batches`` consecutive batches splitting ``n_frames`` evenly."""
    return np.linspace(0, n_frames, n_batches + 1).round().astype(int)


def stack_position(chunks, n_frames: int, *, n_batches: int, position: int | None = None,
                   label: str = "position") -> PositionStack:
    """Mean frame, the mean frames of ``n_batches`` consecutive batches, and saturated-sample counts.

    One pass over a position's frames (``chunks``: :class:`dice_core.io.Chunk`
    in order, ``n_frames`` in all); memory is a few frames whatever their
    number. Batches split the frames as evenly as possible (:func:`batch_edges`).

    Raises
    ------
    ValueError
        Fewer frames than batches; chunks that do not hold ``n_frames`` frames.
    """
    if n_frames < n_batches:
        raise ValueError(f"{label}: {n_frames} frame(s) for {n_batches} batches; each batch needs one at least")
    edges = batch_edges(n_frames, n_batches)
    sums = saturated = None
    seen = 0
    for chunk in chunks:
        frames = np.asarray(chunk.frames, dtype=np.float64)
        if chunk.start + frames.shape[0] > n_frames:
            raise ValueError(f"{label}: frames beyond the {n_frames} announced (chunk at frame {chunk.start})")
        if sums is None:
            sums = np.zeros((n_batches, *frames.shape[1:]))
            saturated = np.zeros(frames.shape[1:], dtype=np.int64)
        batch = np.searchsorted(edges, chunk.start + np.arange(frames.shape[0]), side="right") - 1
        for b in np.unique(batch):
            sums[b] += frames[batch == b].sum(axis=0)
        if chunk.any_saturated:
            saturated += chunk.saturated.sum(axis=0)
        seen += frames.shape[0]
    if seen != n_frames:
        raise ValueError(f"{label}: {seen} frame(s) read, {n_frames} announced")
    counts = np.diff(edges).astype(float)
    return PositionStack(sums.sum(axis=0) / n_frames, sums / counts[:, None, None], saturated, int(n_frames),
                         position)
