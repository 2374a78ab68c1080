"""2-D polynomial surfaces: the design matrix shared by gradient removal, gauge fixing and affine removal."""

from __future__ import annotations

import numpy as np

__all__ = ["polynomial_design"]


def polynomial_design(x, y, *, degree: int) -> np.ndarray:
    """Design matrix (point, term) of the 2-D polynomial terms x^i y^j, i + j <= degree.

    Coordinates are centred and scaled to about [-1, 1] first, which keeps
    high degrees well conditioned; fits are the same in any such basis.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    xs = (x - (x.max() + x.min()) / 2) / max(np.ptp(x) / 2, 1)
    ys = (y - (y.max() + y.min()) / 2) / max(np.ptp(y) / 2, 1)
    return np.column_stack([xs**i * ys**(total - i) for total in range(degree + 1) for i in range(total, -1, -1)])
