"""2-D polynomial surfaces: the design matrix shared by gradient removal, gauge fixing and affine removal."""

from __future__ import annotations

import numpy as np

__all__ = ["polynomial_design", "polynomial_scaling", "polynomial_terms"]


def polynomial_terms(degree: int) -> int:
    """Number of terms x^i y^j, i + j <= ``degree``."""
    return (degree + 1) * (degree + 2) // 2


def polynomial_scaling(x, y) -> tuple[float, float, float, float]:
    """(x centre, x half-width, y centre, y half-width) that map ``x``, ``y`` to about [-1, 1] (a half-width
    at least 1): what :func:`polynomial_design` scales every point by, for designs formed a block of points
    at a time with the scaling of the whole set."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    return ((x.max() + x.min()) / 2, max(np.ptp(x) / 2, 1), (y.max() + y.min()) / 2, max(np.ptp(y) / 2, 1))


def polynomial_design(x, y, *, degree: int, scaling=None) -> np.ndarray:
    """Design matrix (point, term) of the 2-D polynomial terms x^i y^j, i + j <= degree.

    Coordinates are centred and scaled to about [-1, 1] first, which keeps
    high degrees well conditioned; fits are the same in any such basis. The
    scaling is that of ``x``, ``y`` themselves, or ``scaling``
    (:func:`polynomial_scaling` of a larger set, of which these are a block):
    a block's rows are then those of the whole set's design, bit for bit.
    Memory: the design and two coordinate vectors.
    """
    x, y = np.asarray(x, float), np.asarray(y, float)
    x_centre, x_half, y_centre, y_half = polynomial_scaling(x, y) if scaling is None else scaling
    xs = (x - x_centre) / x_half
    ys = (y - y_centre) / y_half
    design = np.empty((x.size, polynomial_terms(degree)))
    column = 0
    for total in range(degree + 1):
        for i in range(total, -1, -1):
            np.multiply(xs**i, ys**(total - i), out=design[:, column])
            column += 1
    return design
