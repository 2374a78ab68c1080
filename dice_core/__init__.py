"""dice_core: the numerics of the DICE detector-calibration pipeline.

One module per concern; none of them knows about Snakemake:

- :mod:`dice_core.manifest` -- read and validate a raw dataset manifest;
- :mod:`dice_core.io` -- stream FITS cubes in chunks of frames, write netCDF products;
- :mod:`dice_core.calibration` -- dark and PRNU (flat-field) maps;
- :mod:`dice_core.fringes` -- the fringe model of a metrology baseline: its gauge, pixel offsets, photon floor, product;
- :mod:`dice_core.fringe_fit` -- the streaming fringe fit: its passes, its state, a fit split across jobs;
- :mod:`dice_core.allan` -- Allan deviations of the pixel offsets;
- :mod:`dice_core.stacks` -- each star position's frames read once into a mean and batch means;
- :mod:`dice_core.centroids` -- pseudo-star windows, Gaussian fit, Fourier resampling, offset correction;
- :mod:`dice_core.superimposition` -- Procrustes, projective and pose superimpositions of the star pattern;
- :mod:`dice_core.accuracies` -- barycentre residuals, corrected accuracies with error bars, the tables;
- :mod:`dice_core.deprojection` -- x and y offsets from a pair of baselines;
- :mod:`dice_core.geometry` -- spherical-wave fringes: the fiber tips' phase surface, their refinement, its modes;
- :mod:`dice_core.stray_light` -- coherent stray light: its model on the bench, its diagnosis in the offsets, its removal;
- :mod:`dice_core.prf` -- each pixel's PRF width from the fringe contrast;
- :mod:`dice_core.chromatic` -- chromatic pixels: silicon's absorption depth, spectra, the response across wavelength;
- :mod:`dice_core.detector` -- the pixel-response model (truncated hyper-Gaussian PRFs);
- :mod:`dice_core.simulation` -- the simulated DICE testbed;
- :mod:`dice_core.polynomials` -- 2-D polynomial surfaces shared by the fits;
- :mod:`dice_core.pixel_blocks` -- least-squares sums over the pixels taken a block of pixels at a time;
- :mod:`dice_core.parallel` -- worker processes and BLAS threads of the streaming reductions;
- :mod:`dice_core.scratch` -- arrays on disk for what grows with pixels times batches, in a folder removed after;
- :mod:`dice_core.plotting` -- the paper's figures;
- :mod:`dice_core.paper_method` -- the paper's own fringe reduction as its text describes it, for comparison;
- :mod:`dice_core.error_budget` -- error-propagation coefficients of the centroids, Monte Carlo and analytic;
- :mod:`dice_core.studies` -- the simulation studies that sweep points run;
- :mod:`dice_core.reproduction` -- the paper's numbers beside ours;
- :mod:`dice_core.overrides` -- dotted-key overrides of nested configurations (sweeps, benches, presets);
- :mod:`dice_core.yamlfile` -- YAML files read strictly (a key given twice is an error);
- :mod:`dice_core.lazy` -- libraries imported on their first use (a step's process pays for what it reaches);
- :mod:`dice_core.settings` -- the workflow's configuration: its schema's choices, its checks, a step's share;
- :mod:`dice_core.steps` -- the table of the workflow's steps: the settings each reads, the code it runs;
- :mod:`dice_core.products` -- the catalogue of products: paths, variables with dims and units, writing steps;
- :mod:`dice_core.products_page` -- the generated part of docs/products.md, from the catalogue and the steps;
- :mod:`dice_core.planning` -- what a run makes of a dataset and a configuration: targets, skips, sweeps;
- :mod:`dice_core.resources` -- memory and time each job needs, from the dataset's size;
- :mod:`dice_core.preflight` -- what a workflow run checks before any job (paths, folders, disk);
- :mod:`dice_core.check` -- a dataset checked before a run: manifest, headers, samples, what the run would make;
- :mod:`dice_core.__main__` -- ``python -m dice_core check PATH/dataset.yaml``, the checker's command.

The seven before the checker describe the workflow (``workflow/``) without depending on it.
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


__all__ = ["DatasetError", "__version__", "error_line", "known_error", "run_logged"]


def known_error(exc: BaseException) -> bool:
    """Whether an exception is one a user meets, not a bug: an error class that dice_core defines
    (:class:`DatasetError`, ``FringeError``, ``WindowError``, ``GeometryError``, ``AllanError``,
    ``AstrometryError``...), or an :class:`OSError` (a file that cannot be read or written, a full disk)."""
    return isinstance(exc, OSError) or any(cls.__module__.split(".")[0] == __name__ for cls in type(exc).__mro__
                                           if issubclass(cls, Exception))


def error_line(exc: BaseException) -> str:
    """A known error as one line: the file or step, and the problem."""
    if isinstance(exc, OSError) and exc.strerror:
        where = f"{exc.filename}: " if exc.filename else ""
        text = f"{where}{exc.strerror}"
    else:
        text = str(exc)
    return " ".join(text.split())  # one line, whatever the message's own line breaks


def run_logged(log_path, step, /, *args, provenance=None, **kwargs):
    """Run ``step(*args, **kwargs)`` with this process's log records sent to ``log_path``.

    ``provenance``, a dict of :func:`dice_core.io.provenance`'s arguments (``code_version``, the
    folders inputs are recorded relative to), is recorded in every product the step writes.

    For workflow steps: each writes its own log, with timestamps. An exception is
    written to the log with its traceback. A known error (:func:`known_error`: bad
    input, an unreadable file, a full disk) then ends the process with one line on
    stderr, ``dice: <step> failed: <file>: <problem> (traceback in <log>)``, and exit
    status 1, so that the terminal shows the problem once, not a traceback (nor a
    worker process's traceback beside it); any other exception, a bug, is raised again
    with its traceback.
    """
    import logging
    import os
    import sys

    step_name = getattr(step, "__name__", step)

    class StepLog(logging.FileHandler):
        """The step's log file. A record it cannot write (a full disk) is remembered, not printed as a
        traceback on the terminal (logging's default), so that the step's error stays one line."""

        failure = None

        def handleError(self, record):
            self.failure = self.failure or sys.exc_info()[1]

        def flush(self):
            try:
                super().flush()
            except OSError as exc:
                self.failure = self.failure or exc

        def close(self):
            try:
                super().close()
            except OSError as exc:
                self.failure = self.failure or exc

    try:
        handler = StepLog(log_path, mode="w")
    except OSError as exc:  # the log's folder cannot be written: the first file the step writes
        print(f"dice: {step_name} failed: {error_line(exc)}", file=sys.stderr)
        raise SystemExit(1) from None
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.INFO)
    logging.captureWarnings(True)
    log = logging.getLogger("dice")
    log.info("dice_core %s: %s", __version__, step_name)
    # a job stopped politely (Snakemake, a cluster's time limit, scancel: SIGTERM) ends as an exception does, so
    # that what it cleans up on the way out goes (a product's temporary file, the Allan step's scratch folder)
    import signal

    def stopped(signum, frame):
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stopped)
    # What the environment asks of thread pools; the reductions set their own (dice_core.parallel).
    threads = [f"{name}={os.environ[name]}" for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                          "MKL_NUM_THREADS") if name in os.environ]
    log.info("thread variables in the environment: %s", ", ".join(threads) or "none")
    import contextlib

    from dice_core import io

    try:
        with io.provenance(**provenance) if provenance else contextlib.nullcontext():
            result = step(*args, **kwargs)
    except Exception as exc:
        log.exception("step failed")
        if known_error(exc):
            handler.flush()
            where = (f"traceback in {log_path}" if handler.failure is None else
                     f"its log {log_path} could not be written: {error_line(handler.failure)}")
            print(f"dice: {step_name} failed: {error_line(exc)} ({where})", file=sys.stderr)
            raise SystemExit(1) from None
        raise
    log.info("done")
    return result
