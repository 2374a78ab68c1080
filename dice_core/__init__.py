"""dice_core: the numerics of the DICE detector-calibration pipeline.

One module per concern; none of them knows about Snakemake:

- :mod:`dice_core.manifest` -- read and validate a raw dataset manifest;
- :mod:`dice_core.io` -- stream FITS cubes in chunks of frames, write netCDF products;
- :mod:`dice_core.calibration` -- dark and PRNU (flat-field) maps;
- :mod:`dice_core.fringes` -- global fringe solution of a metrology baseline;
- :mod:`dice_core.allan` -- Allan deviations of the pixel offsets;
- :mod:`dice_core.stacks` -- each star position's frames read once into a mean and batch means;
- :mod:`dice_core.centroids` -- pseudo-star windows, Gaussian fit, Fourier resampling, offset correction;
- :mod:`dice_core.astrometry` -- barycentre residuals, Procrustes superimposition, accuracies;
- :mod:`dice_core.deprojection` -- x and y offsets from a pair of baselines;
- :mod:`dice_core.detector` -- the pixel-response model (truncated hyper-Gaussian PRFs);
- :mod:`dice_core.simulation` -- the simulated DICE testbed;
- :mod:`dice_core.polynomials` -- 2-D polynomial surfaces shared by the fits;
- :mod:`dice_core.parallel` -- worker processes and BLAS threads of the streaming reductions;
- :mod:`dice_core.plotting` -- the paper's figures;
- :mod:`dice_core.paper_method` -- the paper's own fringe reduction as its text describes it, for comparison;
- :mod:`dice_core.error_budget` -- error-propagation coefficients of the centroids, Monte Carlo and analytic;
- :mod:`dice_core.studies` -- the simulation studies that sweep points run;
- :mod:`dice_core.reproduction` -- the paper's numbers beside ours;
- :mod:`dice_core.overrides` -- dotted-key overrides of nested configurations (sweeps, benches, presets).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dice-core")
except PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0+unknown"


class DatasetError(ValueError):
    """A raw dataset that cannot be reduced: the message names the file and the problem."""

    def __init__(self, path, problem):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):  # so that the error crosses from a worker process intact
        return type(self), (self.path, self.problem)


__all__ = ["DatasetError", "__version__", "run_logged"]


def run_logged(log_path, step, /, *args, **kwargs):
    """Run ``step(*args, **kwargs)`` with this process's log records sent to ``log_path``.

    For workflow steps: each writes its own log, with timestamps; an exception
    is written to the log with its traceback, then raised again so the caller
    (and Snakemake) sees the step fail.
    """
    import logging
    import os

    handler = logging.FileHandler(log_path, mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.INFO)
    logging.captureWarnings(True)
    log = logging.getLogger("dice")
    log.info("dice_core %s: %s", __version__, getattr(step, "__name__", step))
    # What the environment asks of thread pools; the reductions set their own (dice_core.parallel).
    threads = [f"{name}={os.environ[name]}" for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                          "MKL_NUM_THREADS") if name in os.environ]
    log.info("thread variables in the environment: %s", ", ".join(threads) or "none")
    try:
        result = step(*args, **kwargs)
    except Exception:
        log.exception("step failed")
        raise
    log.info("done")
    return result
