"""File I/O: raw FITS cubes in, netCDF products out. The only module that touches files
besides the manifest reader.

Reading streams an acquisition (one or more FITS files concatenated in time) in
chunks of frames, so memory does not grow with the number of frames. Samples
are converted straight from a read-only memory map of the file (no copy of the
raw bytes), and each chunk's pages are released (madvise DONTNEED) once
converted, so that pages of a large cube do not accumulate in the process's
resident memory.

Conventions: a cube is ``(frame, row, col)``; samples are returned as float64
ADU; NAXIS1 is cols, NAXIS2 rows, NAXIS3 frames.
"""

from __future__ import annotations

import copy
import datetime as _dt
import json
import mmap
import os
import queue
import tempfile
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, NamedTuple

import numpy as np
import xarray as xr
from astropy.io import fits
from astropy.utils.exceptions import AstropyUserWarning

import dice_core
from dice_core import DatasetError
from dice_core.manifest import Acquisition, Detector

__all__ = [
    "Chunk",
    "CubeFile",
    "FrameStream",
    "open_cube",
    "write_cube",
    "write_product",
    "read_product",
    "DEFAULT_CHUNK_FRAMES",
]

#: Frames per chunk when streaming. 256 frames of 80x84 pixels are 14 MB in float64.
DEFAULT_CHUNK_FRAMES = 256

_FITS_BLOCK = 2880
_SUPPORTED = "unsigned 16-bit (BITPIX 16, BZERO 32768), 32-bit integer (BITPIX 32) or 32-bit float (BITPIX -32)"


@dataclass(frozen=True)
class CubeFile:
    """Layout of one FITS cube on disk, from its header (no data read).

    Attributes
    ----------
    path : Path
    n_frames : int
        NAXIS3, or 1 for a 2-D primary HDU.
    shape : (int, int)
        (rows, cols) = (NAXIS2, NAXIS1).
    disk_dtype : numpy.dtype
        Big-endian storage type.
    bzero : float
        Offset added to stored values (32768 for unsigned 16-bit).
    header_bytes : int
        Offset of the data unit in the file.
    """

    path: Path
    n_frames: int
    shape: tuple[int, int]
    disk_dtype: np.dtype
    bzero: float
    header_bytes: int
    header: fits.Header

    @property
    def frame_bytes(self) -> int:
        return self.shape[0] * self.shape[1] * self.disk_dtype.itemsize


class Chunk(NamedTuple):
    """Consecutive frames of an acquisition.

    ``start`` is the index of the first frame in the whole acquisition,
    ``frames`` the samples (frame, row, col) in ADU (float64 unless asked otherwise), and
    ``saturated`` a boolean array of the same shape, True where the sample is at
    or above the detector's saturation level.
    """

    start: int
    frames: np.ndarray
    saturated: np.ndarray


def open_cube(path, detector: Detector | None = None) -> CubeFile:
    """Read and check the header of one FITS cube.

    Raises
    ------
    DatasetError
        Missing, unreadable or non-FITS file; unsupported data type; a frame
        shape that differs from ``detector.shape``; a file shorter than its
        header says.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file not found")
    try:
        # astropy's own truncation warning is superseded by the error raised below
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", AstropyUserWarning)
            hdul = fits.open(path, memmap=False, lazy_load_hdus=True)
        with hdul:
            header = hdul[0].header.copy()
            header_bytes = hdul.fileinfo(0)["datLoc"]
    except (OSError, ValueError, IndexError) as exc:
        raise DatasetError(path, f"not a readable FITS file ({exc})") from None

    naxis = header.get("NAXIS", 0)
    if naxis not in (2, 3):
        raise DatasetError(path, f"primary HDU has NAXIS={naxis}; a frame (2) or cube (3) is expected")
    cols, rows = header["NAXIS1"], header["NAXIS2"]
    n_frames = header["NAXIS3"] if naxis == 3 else 1

    bitpix = header["BITPIX"]
    bzero, bscale = header.get("BZERO", 0), header.get("BSCALE", 1)
    if bscale != 1:
        raise DatasetError(path, f"BSCALE={bscale} is not supported; samples must be {_SUPPORTED}")
    if bitpix == 16 and bzero == 32768:
        disk_dtype = np.dtype(">i2")
    elif bitpix == 32 and bzero == 0:
        disk_dtype = np.dtype(">i4")
    elif bitpix == -32 and bzero == 0:
        disk_dtype = np.dtype(">f4")
    else:
        raise DatasetError(path, f"unsupported data type BITPIX={bitpix}, BZERO={bzero}; "
                                 f"samples must be {_SUPPORTED}")

    if detector is not None and (rows, cols) != tuple(detector.shape):
        raise DatasetError(path, f"frames are {rows}x{cols} (rows x cols) but the detector is "
                                 f"{detector.shape[0]}x{detector.shape[1]}")
    cube = CubeFile(path, n_frames, (rows, cols), disk_dtype, float(bzero), header_bytes, header)
    needed = header_bytes + n_frames * cube.frame_bytes
    size = path.stat().st_size
    if size < needed:
        raise DatasetError(path, f"file is truncated: {size} bytes where its header announces {needed}")
    return cube


class _OnesComplementSum:
    """Streaming 32-bit ones'-complement sum, the FITS CHECKSUM/DATASUM arithmetic."""

    def __init__(self):
        self.total = 0
        self._pending = b""

    def update(self, data):
        """Add bytes (any buffer; read without copying unless a partial word is pending)."""
        if self._pending:
            data = self._pending + bytes(data)
        usable = len(data) - len(data) % 4
        self._pending = bytes(data[usable:])
        if usable:
            words = np.frombuffer(data, dtype=">u4", count=usable // 4)
            self.total = self._fold(self.total + int(words.sum(dtype=np.uint64)))

    def value(self) -> int:
        # FITS pads every unit with zeros to a whole block, so a trailing partial
        # word is completed with zero bytes.
        if self._pending:
            tail = self._pending + b"\0" * (4 - len(self._pending))
            return self._fold(self.total + int.from_bytes(tail, "big"))
        return self.total

    @staticmethod
    def _fold(value: int) -> int:
        while value >> 32:
            value = (value & 0xFFFFFFFF) + (value >> 32)
        return value


def _check_checksums(cube: CubeFile, data_sum: int):
    """Verify DATASUM and CHECKSUM, when present, given the data unit's sum."""
    header = cube.header
    if "DATASUM" in header:
        try:
            declared = int(str(header["DATASUM"]).strip())
        except ValueError:
            raise DatasetError(cube.path, f"DATASUM {header['DATASUM']!r} is not an integer") from None
        if declared != data_sum:
            raise DatasetError(cube.path, f"DATASUM does not verify: header says {declared}, "
                                          f"data sums to {data_sum} (corrupted data)")
    if "CHECKSUM" in header:
        with open(cube.path, "rb") as f:
            head = f.read(cube.header_bytes)
        total = _OnesComplementSum()
        total.update(head)
        if _OnesComplementSum._fold(total.value() + data_sum) != 0xFFFFFFFF:
            raise DatasetError(cube.path, "CHECKSUM does not verify (corrupted header or data)")


class FrameStream:
    """Stream an acquisition's frames in chunks, across its files, in time order.

    Headers are read and checked on construction; samples when iterated. Each
    iteration is one pass over the data; the stream can be iterated again.

    Parameters
    ----------
    acquisition : Acquisition
        Its files are concatenated along frames in the order listed.
    detector : Detector
        Frame shape and saturation level.
    chunk_frames : int, keyword-only
        Frames per chunk (a chunk never spans two files, so the last chunk of
        each file may be shorter).
    min_frames : int, keyword-only
        Fewer frames than this raise :class:`DatasetError` on construction.
    purpose : str, keyword-only
        What the frames are for, quoted in the too-few-frames error.
    dtype : numpy dtype, keyword-only
        Type of the samples yielded: float64, or float32, which halves the
        memory traffic and still holds 16-bit integer samples exactly.
    subtract : ndarray (row, col), keyword-only
        A reference frame (ADU) subtracted from every frame in the same pass as
        the conversion: chunks then hold ``samples - subtract``. Saturation is
        still judged on the raw samples.
    prefetch : bool, keyword-only
        Read and convert the next chunk in a background thread while the
        consumer works on the current one (file reads and numpy conversions
        release the GIL, so on two cores they overlap with the consumer's
        arithmetic). Holds at most two chunks ahead.

    Raises
    ------
    DatasetError
        On construction: any header problem of :func:`open_cube`, or too few
        frames. During iteration: non-finite samples, or a CHECKSUM/DATASUM
        that does not verify (raised after the file's last chunk).
    """

    def __init__(self, acquisition: Acquisition, detector: Detector, *,
                 chunk_frames: int = DEFAULT_CHUNK_FRAMES, min_frames: int = 1, purpose: str = "",
                 dtype=np.float64, subtract=None, prefetch: bool = False):
        if chunk_frames < 1:
            raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
        self.acquisition = acquisition
        self.detector = detector
        self.chunk_frames = int(chunk_frames)
        self.dtype = np.dtype(dtype)
        self.subtract = None if subtract is None else np.asarray(subtract, dtype=np.float64)
        self.prefetch = bool(prefetch)
        self.cubes = [open_cube(f, detector) for f in acquisition.files]
        self.n_frames = sum(c.n_frames for c in self.cubes)
        if self.n_frames < min_frames:
            names = ", ".join(str(c.path) for c in self.cubes)
            why = f" for {purpose}" if purpose else ""
            raise DatasetError(names, f"{acquisition.label} has {self.n_frames} frame(s); "
                                      f"at least {min_frames} are needed{why}")

    def centred(self, reference) -> "FrameStream":
        """The same acquisition streamed as ``samples - reference`` (see ``subtract``)."""
        twin = copy.copy(self)
        twin.subtract = np.asarray(reference, dtype=np.float64)
        return twin

    @property
    def shape(self) -> tuple[int, int, int]:
        """(frames, rows, cols) of the whole acquisition."""
        return (self.n_frames, *self.detector.shape)

    def __iter__(self) -> Iterator[Chunk]:
        return self._read_ahead() if self.prefetch else self._chunks()

    def _read_ahead(self) -> Iterator[Chunk]:
        """:meth:`_chunks` run in a background thread, two chunks ahead; errors re-raised here."""
        chunks: queue.Queue = queue.Queue(maxsize=2)
        stop = threading.Event()
        done = object()

        def produce():
            try:
                for chunk in self._chunks():
                    while not stop.is_set():
                        try:
                            chunks.put(chunk, timeout=0.1)
                            break
                        except queue.Full:
                            continue
                    if stop.is_set():
                        return
                chunks.put(done)
            except BaseException as exc:  # handed to the consumer
                chunks.put(exc)

        worker = threading.Thread(target=produce, name="FrameStream read-ahead", daemon=True)
        worker.start()
        try:
            while True:
                item = chunks.get()
                if item is done:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            stop.set()
            while worker.is_alive():  # let a blocked put see the stop
                try:
                    chunks.get_nowait()
                except queue.Empty:
                    pass
                worker.join(timeout=0.05)

    def _chunks(self) -> Iterator[Chunk]:
        start = 0
        saturation = self.detector.saturation
        page = mmap.PAGESIZE
        for cube in self.cubes:
            checksum = _OnesComplementSum() if ("DATASUM" in cube.header or "CHECKSUM" in cube.header) else None
            shift = cube.bzero if self.subtract is None else cube.bzero - self.subtract
            shift = np.asarray(shift, dtype=self.dtype) if np.any(shift) else None
            with open(cube.path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
                view = memoryview(mapped)
                try:
                    for first in range(0, cube.n_frames, self.chunk_frames):
                        n = min(self.chunk_frames, cube.n_frames - first)
                        begin = cube.header_bytes + first * cube.frame_bytes
                        end = begin + n * cube.frame_bytes
                        if end > len(mapped):
                            raise DatasetError(cube.path, f"file ended inside frame "
                                                          f"{first + (len(mapped) - begin) // cube.frame_bytes}")
                        raw = view[begin:end]
                        if checksum is not None:
                            checksum.update(raw)
                        stored = np.frombuffer(raw, dtype=cube.disk_dtype).reshape(n, *cube.shape)
                        if cube.disk_dtype.kind == "f":
                            saturated = stored >= saturation
                        else:  # judge the stored integers: cheaper than converted samples
                            saturated = stored >= saturation - cube.bzero
                        frames = stored.astype(self.dtype)
                        del stored, raw  # no view into the map may outlive it
                        # the converted chunk is ours: give the mapped pages back
                        mapped.madvise(mmap.MADV_DONTNEED, begin - begin % page, end - (begin - begin % page))
                        if shift is not None:
                            frames += shift
                        if cube.disk_dtype.kind == "f":
                            bad = ~np.isfinite(frames)
                            if bad.any():
                                t, r, c = np.argwhere(bad)[0]
                                raise DatasetError(cube.path, f"{int(bad.sum())} non-finite sample(s) in frames "
                                                              f"{first}..{first + n - 1}, first at frame {first + t}, "
                                                              f"row {r}, col {c}")
                        yield Chunk(start, frames, saturated)
                        start += n
                finally:
                    view.release()
            if checksum is not None:
                _check_checksums(cube, checksum.value())


def _atomic_target(path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    os.close(fd)
    return Path(tmp)


def write_cube(path, chunks, *, shape, n_frames, dtype="uint16", header=None):
    """Write a FITS cube from an iterable of frame chunks, without holding the cube in memory.

    The file is written under a temporary name and renamed when complete, so a
    failure never leaves a half-written cube under ``path``.

    Parameters
    ----------
    path : str or Path
    chunks : iterable of ndarray
        Arrays (frames, rows, cols) in ADU, in time order, ``n_frames`` in all.
    shape : (int, int)
        (rows, cols).
    n_frames : int
    dtype : {"uint16", "int32", "float32"}
        Storage type. ``uint16`` samples are rounded and clipped to [0, 65535]
        (as an ADC does) and stored as BITPIX 16 with BZERO 32768.
    header : dict, optional
        Extra header keywords (e.g. EXPTIME, FRAMERAT, DATE-OBS).
    """
    path = Path(path)
    hdr = fits.Header()
    hdr["SIMPLE"] = True
    hdr["BITPIX"] = {"uint16": 16, "int32": 32, "float32": -32}[dtype]
    hdr["NAXIS"] = 3
    hdr["NAXIS1"], hdr["NAXIS2"], hdr["NAXIS3"] = shape[1], shape[0], n_frames
    if dtype == "uint16":
        hdr["BZERO"], hdr["BSCALE"] = 32768, 1
    for key, value in (header or {}).items():
        hdr[key] = value
    tmp = _atomic_target(path)
    written = 0
    try:
        with open(tmp, "wb") as f:
            f.write(hdr.tostring().encode("ascii"))
            for chunk in chunks:
                chunk = np.asarray(chunk)
                if chunk.shape[1:] != tuple(shape):
                    raise ValueError(f"chunk frames are {chunk.shape[1:]}, expected {tuple(shape)}")
                if dtype == "uint16":
                    stored = (np.clip(np.rint(chunk), 0, 65535) - 32768).astype(">i2")
                elif dtype == "int32":
                    stored = np.rint(chunk).astype(">i4")
                else:
                    stored = chunk.astype(">f4")
                f.write(stored.tobytes())
                written += chunk.shape[0]
            if written != n_frames:
                raise ValueError(f"{written} frames given for a cube of {n_frames}")
            pad = -f.tell() % _FITS_BLOCK
            f.write(b"\0" * pad)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _jsonable(value):
    return json.dumps(value, sort_keys=True, default=str)


def write_product(ds: xr.Dataset, path, *, title: str, config=None, inputs=()):
    """Write a netCDF product atomically, with units checked and provenance attached.

    Every data variable and coordinate with a physical meaning must carry a
    ``units`` attribute (``"1"`` for dimensionless): a variable without one is
    refused. The global attributes receive ``Conventions``, ``title``,
    ``source`` and ``dice_core_version`` (the software), ``configuration``
    (JSON of ``config``), ``inputs`` (JSON list of input paths) and a ``history``
    line. The file is written to a temporary name in the same folder and
    renamed, so an existing product is never left half-written.
    """
    path = Path(path)
    missing = [name for name, var in ds.data_vars.items() if "units" not in var.attrs]
    if missing:
        raise ValueError(f"{path}: variables without units: {missing}")
    ds = ds.copy()
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    ds.attrs.update({
        "Conventions": "CF-1.10",
        "title": title,
        "source": f"dice_core {dice_core.__version__}",
        "dice_core_version": dice_core.__version__,
        "configuration": _jsonable(config if config is not None else {}),
        "inputs": _jsonable([str(p) for p in inputs]),
        "history": f"{stamp} written by dice_core {dice_core.__version__}",
    })
    tmp = _atomic_target(path)
    try:
        ds.to_netcdf(tmp, engine="netcdf4")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_product(path) -> xr.Dataset:
    """Load a netCDF product fully into memory (and close the file)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "product not found")
    return xr.load_dataset(path, engine="netcdf4")
