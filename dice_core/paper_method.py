"""The paper's own fringe reduction, as its text describes it: a reference to compare ours with.

Crouzier et al. (A&A), section "Metrology", "Minimization strategy":

1. iteration 1, every frame is fitted with perfect pixels (iota = alpha = 1,
   no offsets) and the wavevector free per frame;
2. every pixel's temporal sine is fitted against the frames' phases (the
   linear fit of the paper's appendix B), which gives its pixel phase;
3. iterations 2 to N (N = 4 in the paper), the wavevector is fixed at its
   mean, and each frame is fitted again with "the pixel locations projected
   onto the wavevector": pixels at their measured phases, their responses
   still perfect (iota = alpha = 1); then step 2 again. A measured phase is
   K.r + K.delta + constant with K the data's own, so the frame fits use K
   through the phases (the mean of K(t) only starts the plane of step 4);
4. the offsets are the pixel phases minus the plane of K, normalised to zero
   mean and gradient; there is no gauge constraint beyond these.

Step 3 is where it differs from :func:`dice_core.fringe_fit.fit_baseline`: the
frame fits weigh every pixel as if its sensitivity were 1. An uncalibrated
PRNU then correlates with the fringe: each frame's phase is off by a periodic
function of the fringe phase, of order (B / A) sigma_PRNU / sqrt(pixels), the
same in every pass, and each pixel's temporal fit against those phases turns
it into a phase error that depends on where the pixel sits on the fringe, a
pattern at K and 2K across the detector. It does not average down with the
frames: a bias that grows with the PRNU (the paper's "pixel offset bias"
figure). Our frame fits use the fitted pixel factors (iota, alpha sin theta,
alpha cos theta) themselves, and the gauge is fixed by physical constraints
(:func:`dice_core.fringes.fix_gauge`).

Plane waves only: the paper's simulations had no spherical fringes. Units:
pixel for positions and offsets, rad for phases, rad/pixel for K.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

# _pass is fringe_fit's private streaming pass (frame factors, then per-pixel normal equations): the paper's
# method must run the very same pass as ours, so that the comparison shows the method and not two
# implementations of the numerics; it stays private to fringe_fit because its arguments and returns are that
# module's internals, which only this sibling module, tested against fringe_fit's own results, may rely on.
from dice_core.fringe_fit import _pass
from dice_core.fringes import (FringeError, initial_wavevector, perfect_pixel_design, projected_offsets,
                               wavevector_per_frame)
from dice_core.io import first_chunk

__all__ = ["PaperSolution", "fit_baseline_paper"]

log = logging.getLogger(__name__)


@dataclass
class PaperSolution:
    """Result of :func:`fit_baseline_paper`; pixel arrays run over the science area (``rows``, ``cols``)."""

    rows: np.ndarray
    cols: np.ndarray
    offsets: np.ndarray      # projected on k, zero mean and gradient, pixel
    pixel_phase: np.ndarray  # theta, rad
    k: np.ndarray            # mean wavevector, rad/pixel
    iterations: int


def fit_baseline_paper(stream, dark, *, detector, iterations: int = 4, label: str = "baseline") -> PaperSolution:
    """The paper's alternating fringe fit (module docstring), over a re-iterable stream of chunks.

    Parameters
    ----------
    stream : re-iterable of Chunk
        Raw frames, adu; read once per iteration.
    dark : ndarray (row, col)
        Mean dark, adu.
    detector : Detector
        Science area: the pixels fitted.
    iterations : int
        Spatial-temporal iterations, the first with K free per frame (the paper: 4).

    Returns
    -------
    PaperSolution
    """
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    mask = detector.science_mask()
    dark0 = np.nan_to_num(dark)
    first = first_chunk(stream)
    reference = first.frames.mean(axis=0)
    rows, cols = np.nonzero(mask)
    idx = rows * detector.shape[1] + cols
    x, y = cols.astype(float), rows.astype(float)
    xc, yc = x - x.mean(), y - y.mean()
    k0 = initial_wavevector(first.frames[0] - dark0, mask)
    # Iteration 1: perfect pixels, K free per frame (linearised about the FFT estimate of frame 0)
    G, extra = perfect_pixel_design(k0, xc, yc)
    coef, FtI, FtF, *_ = _pass([stream], dark0, idx, G, extra=extra, reference=reference)
    k_mean = wavevector_per_frame(coef, k0).mean(axis=0)
    for iteration in range(1, iterations + 1):
        if iteration > 1:
            # the pixels at their measured phases, with perfect responses (iota = alpha = 1)
            G = np.column_stack([np.ones(idx.size), np.sin(theta), np.cos(theta)])
            coef, FtI, FtF, *_ = _pass([stream], dark0, idx, G, reference=reference)
        pixel = np.linalg.solve(FtF, FtI).T  # the temporal fit: (iota, alpha sin theta, alpha cos theta)
        if not np.all(np.isfinite(pixel)):
            raise FringeError(f"{label}: the paper's temporal fit is not finite (no fringe contrast?)")
        theta = np.arctan2(pixel[:, 1], pixel[:, 2])
        log.info("%s: paper's method, iteration %d of %d", label, iteration, iterations)
    k, offsets = projected_offsets(theta, x, y, k_mean)
    return PaperSolution(rows, cols, offsets, theta, k, iterations)
