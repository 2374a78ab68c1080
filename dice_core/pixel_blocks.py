"""Sums over a detector's pixels taken a block of pixels at a time, so that no temporary spans every pixel.

A fit's least-squares problems over the pixels (the gauge's smooth basis, the
plane of the pixel phases, the fiber tips' refinement and its affine part)
have a few columns and millions of rows. Their R factor is taken a block of
rows at a time (:func:`stacked_r`, a sequential tall-skinny QR): the design
of each block is formed, used and dropped, and the sums the fits need
(R22' R22 for a residual's Gram matrix, R11^-1 R12 for coefficients) come
from R. It is the QR factorisation of the whole design taken in another
order: the results change at the rounding level only, whatever the block.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PIXEL_BLOCK", "pixel_blocks", "stacked_r"]

#: Pixels per block: a degree-6 smooth basis of a block (28 columns) is 7 MB, whatever the detector. Read
#: when a sweep starts: the functions that sweep take ``block=None`` for it.
PIXEL_BLOCK = 1 << 15


def pixel_blocks(n, block=None):
    """Consecutive slices of ``block`` (None: :data:`PIXEL_BLOCK`) of ``n`` pixels (the last one shorter)."""
    block = PIXEL_BLOCK if block is None else int(block)
    return (slice(start, min(start + block, n)) for start in range(0, n, block))


def stacked_r(blocks) -> np.ndarray:
    """R (column, column), square, of the QR factorisation of the rows of ``blocks`` stacked, taken a block
    at a time (a sequential tall-skinny QR: the R of [R; next block] each time), so that the stacked matrix
    is never formed; rows of zeros complete it when there are fewer rows than columns."""
    R = None
    for rows in blocks:
        R = np.linalg.qr(rows if R is None else np.vstack([R, rows]), mode="r")
    return np.vstack([R, np.zeros((R.shape[1] - R.shape[0], R.shape[1]))]) if R.shape[0] < R.shape[1] else R
