"""Star positions read once: means and batch means against a direct computation, the product, bad input."""

import numpy as np
import pytest

from dice_core import stacks
from dice_core.io import Chunk, read_product, write_product


def chunks_of(frames, size, saturated_at=None):
    """``frames`` (frame, row, col) as chunks of ``size`` frames; one saturated sample at ``saturated_at``."""
    out = []
    for start in range(0, frames.shape[0], size):
        block = frames[start:start + size]
        mask = np.zeros(block.shape, bool)
        if saturated_at is not None and start <= saturated_at[0] < start + block.shape[0]:
            mask[saturated_at[0] - start, saturated_at[1], saturated_at[2]] = True
        out.append(Chunk(start, block, mask, bool(mask.any())))
    return out


@pytest.fixture
def frames(rng):
    return 1000 + rng.standard_normal((11, 4, 5))


@pytest.mark.parametrize("size", [1, 3, 11])  # chunks straddling the batch edges, and one chunk
def test_means_and_batch_means_whatever_the_chunks(frames, size):
    stack = stacks.stack_position(chunks_of(frames, size, saturated_at=(7, 2, 3)), 11, n_batches=3, position=4)
    edges = stacks.batch_edges(11, 3)
    assert edges.tolist() == [0, 4, 7, 11]
    np.testing.assert_allclose(stack.mean, frames.mean(axis=0), rtol=1e-14)
    for b in range(3):
        np.testing.assert_allclose(stack.batch_means[b], frames[edges[b]:edges[b + 1]].mean(axis=0), rtol=1e-14)
    assert stack.n_saturated.sum() == 1 and stack.n_saturated[2, 3] == 1
    assert stack.n_frames == 11 and stack.n_batches == 3 and stack.position == 4


def test_a_stack_survives_its_product(frames, tmp_path):
    stack = stacks.stack_position(chunks_of(frames, 3), 11, n_batches=3, position=4)
    write_product(stack.to_dataset(), tmp_path / "4.nc", title="stack")
    ds = read_product(tmp_path / "4.nc")
    assert ds["batch_frames"].values.tolist() == [4, 3, 4] and ds.attrs["position"] == 4
    assert ds["mean"].attrs["units"] == "adu" and ds["batch_mean"].dims == ("batch", "row", "col")
    back = stacks.PositionStack.from_dataset(ds)
    for name in ("mean", "batch_means", "n_saturated"):
        np.testing.assert_array_equal(getattr(back, name), getattr(stack, name))
    assert back.n_frames == 11 and back.position == 4
    # the frame-weighted batch means are the mean
    weighted = np.tensordot(ds["batch_frames"].values, ds["batch_mean"].values, axes=1) / 11
    np.testing.assert_allclose(weighted, ds["mean"].values, rtol=1e-14)


def test_frames_that_do_not_match_their_count_are_refused(frames):
    with pytest.raises(ValueError, match="position 4: 11 frame\\(s\\) read, 12 announced"):
        stacks.stack_position(chunks_of(frames, 3), 12, n_batches=3, label="position 4")
    with pytest.raises(ValueError, match="frames beyond the 10 announced"):
        stacks.stack_position(chunks_of(frames, 3), 10, n_batches=3, label="position 4")
    with pytest.raises(ValueError, match="2 frame\\(s\\) for 3 batches"):
        stacks.stack_position(chunks_of(frames[:2], 3), 2, n_batches=3, label="position 4")
