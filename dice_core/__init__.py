"""dice_core: the numerics of the DICE detector-calibration pipeline.

One module per concern; none of them knows about Snakemake:

- :mod:`dice_core.manifest` -- read and validate a raw dataset manifest;
- :mod:`dice_core.io` -- stream FITS cubes in chunks of frames, write netCDF products;
- :mod:`dice_core.calibration` -- dark and PRNU (flat-field) maps;
- :mod:`dice_core.detector` -- the pixel-response model (truncated hyper-Gaussian PRFs);
- :mod:`dice_core.simulation` -- the simulated DICE testbed;
- :mod:`dice_core.plotting` -- the paper's figures.
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


__all__ = ["DatasetError", "__version__"]
