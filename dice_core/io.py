"""File I/O: raw FITS cubes in, netCDF products out. The only module that touches files
besides the manifest reader.

Reading streams an acquisition (one or more FITS files concatenated in time) in
chunks of frames, so memory does not grow with the number of frames. Each
chunk's raw bytes are read (``readinto``) into one chunk-sized buffer per file,
reused by every chunk, and converted from it, so that pages of a large cube do
not accumulate in the process's resident memory. A stream read to the end of a file also takes the file's
SHA-256 from the bytes it read, so that the products' provenance
(:func:`write_product`) reads no file only to hash it.

Conventions: a cube is ``(frame, row, col)``; samples are returned as float64
ADU; NAXIS1 is cols, NAXIS2 rows, NAXIS3 frames.
"""

from __future__ import annotations

import contextlib
import contextvars
import csv
import copy
import datetime as _dt
import errno
import fcntl
import hashlib
import json
import logging
import os
import re
import secrets
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, NamedTuple

import numpy as np

import dice_core
from dice_core import DatasetError, lazy, products
from dice_core.manifest import Acquisition, Detector

xr = lazy.module("xarray")
log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from astropy.io import fits

__all__ = [
    "Chunk",
    "CubeFile",
    "FrameStream",
    "file_groups",
    "open_cube",
    "write_cube",
    "write_product",
    "write_text",
    "atomic_write",
    "temporary_files",
    "remove_abandoned",
    "TEMPORARY_NAME",
    "provenance",
    "input_digests",
    "adopt_stored_digests",
    "DIGEST_STORE",
    "known_digests",
    "remember_digests",
    "read_product",
    "open_product",
    "product_attrs",
    "first_chunk",
    "CHUNK_BYTES",
    "auto_chunk_frames",
]

#: Size of a chunk of float32 samples when the number of frames per chunk is
#: left to the reader: a chunk that stays in a core's cache (1 MiB of L2 on the
#: development machine) is streamed about twice as fast as one of several MiB,
#: by the conversion and by the products over the chunk (BENCHMARKS.md).
CHUNK_BYTES = 1 << 20
#: Frames per chunk at least, where a frame is larger than a cache-sized chunk allows: each chunk of a
#: fringe-fit pass also reads the pass's projector (28 bytes a pixel) and updates F'X (48), which a
#: one-frame chunk of a 1024x1024 detector would do for every 4 MiB frame; 16 frames a chunk make that
#: traffic small, 3-5 times faster a sample (BENCHMARKS.md, "A large detector").
MIN_CHUNK_FRAMES = 16
#: But no chunk of more than this many bytes of float32 samples: 4 frames of 4096x4096.
MAX_CHUNK_BYTES = 256 << 20


def auto_chunk_frames(shape) -> int:
    """Frames per chunk for frames of ``shape`` (rows, cols): :data:`CHUNK_BYTES` of float32 (in a core's
    cache), or :data:`MIN_CHUNK_FRAMES` where that is more, within :data:`MAX_CHUNK_BYTES`; at least 1."""
    frame_bytes = 4 * int(shape[0]) * int(shape[1])
    return max(1, CHUNK_BYTES // frame_bytes, min(MIN_CHUNK_FRAMES, MAX_CHUNK_BYTES // frame_bytes))

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
    ``frames`` the samples (frame, row, col) in ADU (float64 unless asked otherwise),
    ``saturated`` a boolean array of the same shape, True where the sample is at
    or above the detector's saturation level (a read-only view when none is),
    and ``any_saturated`` whether any is, which lets a consumer skip the mask.
    """

    start: int
    frames: np.ndarray
    saturated: np.ndarray
    any_saturated: bool = True


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
    from astropy.io import fits  # here: a step that reads no cube does not pay for astropy (dice_core.lazy)
    from astropy.utils.exceptions import AstropyUserWarning

    try:
        # astropy's own truncation warning is superseded by the error raised below
        # (reading the header included: lazily loaded, it is where astropy warns of a short file)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", AstropyUserWarning)
            with fits.open(path, memmap=False, lazy_load_hdus=True) as hdul:
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


def file_groups(file_frames, parts: int) -> list[tuple[int, int]]:
    """Up to ``parts`` consecutive groups of files with about equal numbers of frames (:meth:`FrameStream.split`).

    ``file_frames`` are the files' frame counts, in order. Returns (first, end) file indices of each group,
    end excluded: each group ends after the file whose end is nearest to a multiple of 1/``parts`` of the
    frames, so there are fewer groups than ``parts`` when there are fewer files, or files of very unequal
    sizes.
    """
    if parts < 1:
        raise ValueError(f"parts must be >= 1, got {parts}")
    ends = np.cumsum(file_frames)
    n_frames, n_files = int(ends[-1]) if len(ends) else 0, len(ends)
    # cut after the file whose end is nearest to each k/parts of the frames
    cuts = sorted({int(np.argmin(np.abs(ends - n_frames * k / parts))) + 1 for k in range(1, parts)})
    bounds = [0, *[c for c in cuts if 0 < c < n_files], n_files]
    return list(zip(bounds[:-1], bounds[1:]))


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
    chunk_frames : int or "auto", keyword-only
        Frames per chunk (a chunk never spans two files, so the last chunk of
        each file may be shorter); "auto" (or None) for
        :func:`auto_chunk_frames`, 39 frames of 80x84 pixels.
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

    Raises
    ------
    DatasetError
        On construction: any header problem of :func:`open_cube`, or too few
        frames. During iteration: non-finite samples, or a CHECKSUM/DATASUM
        that does not verify (raised after the file's last chunk).
    """

    def __init__(self, acquisition: Acquisition, detector: Detector, *,
                 chunk_frames: int | str | None = "auto", min_frames: int = 1, purpose: str = "",
                 dtype=np.float64, subtract=None):
        if chunk_frames is None or chunk_frames == "auto":
            chunk_frames = auto_chunk_frames(detector.shape)
        if isinstance(chunk_frames, str) or chunk_frames < 1:
            raise ValueError(f'chunk_frames must be "auto" or an integer >= 1, got {chunk_frames!r}')
        self.acquisition = acquisition
        self.detector = detector
        self.chunk_frames = int(chunk_frames)
        self.dtype = np.dtype(dtype)
        self.subtract = None if subtract is None else np.asarray(subtract, dtype=np.float64)
        self.cubes = [open_cube(f, detector) for f in acquisition.files]
        self.n_frames = sum(c.n_frames for c in self.cubes)
        self.first_frame = 0  # index in the whole acquisition of this stream's first frame (see split)
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

    def split(self, parts: int) -> list["FrameStream"]:
        """The acquisition as up to ``parts`` consecutive streams of whole files.

        Files are grouped so that the groups hold about equal numbers of
        frames; a stream of fewer files than ``parts`` gives one stream per
        file. Chunks keep their index in the whole acquisition (``start``), and
        each part verifies the checksums of its own files. For reductions run
        on the parts in parallel (:func:`dice_core.fringe_fit.fit_baseline`).
        """
        pieces = []
        for begin, end in file_groups([c.n_frames for c in self.cubes], parts):
            piece = copy.copy(self)
            piece.cubes = self.cubes[begin:end]
            piece.first_frame = self.first_frame + sum(c.n_frames for c in self.cubes[:begin])
            piece.n_frames = sum(c.n_frames for c in piece.cubes)
            pieces.append(piece)
        return pieces

    @property
    def shape(self) -> tuple[int, int, int]:
        """(frames, rows, cols) of this stream (of the whole acquisition unless it is a part, see split)."""
        return (self.n_frames, *self.detector.shape)

    def __iter__(self) -> Iterator[Chunk]:
        return self._chunks()

    def _chunks(self) -> Iterator[Chunk]:
        start = self.first_frame
        saturation = self.detector.saturation
        frame_pixels = self.detector.shape[0] * self.detector.shape[1]
        unsaturated = None  # read-only all-False mask, shared by the chunks of one shape
        for cube in self.cubes:
            checksum = _OnesComplementSum() if ("DATASUM" in cube.header or "CHECKSUM" in cube.header) else None
            shift = cube.bzero if self.subtract is None else cube.bzero - self.subtract
            shift = np.asarray(shift, dtype=self.dtype) if np.any(shift) else None
            # Saturation is judged on the stored values: cheaper than on converted samples.
            threshold = saturation if cube.disk_dtype.kind == "f" else saturation - cube.bzero
            # One raw buffer per file, reused by every chunk: a chunk-sized buffer stays in
            # the CPU cache, where a fresh one per chunk would cost page faults at each read.
            buffer = np.empty(min(self.chunk_frames, cube.n_frames) * frame_pixels, dtype=cube.disk_dtype)
            with open(cube.path, "rb", buffering=0) as f:
                # the file's SHA-256 for the products' provenance, from the bytes this pass reads anyway
                # (a file already hashed in this process is not hashed again)
                digest = _StreamDigest.start(cube.path, f, cube.header_bytes)
                f.seek(cube.header_bytes)
                for first in range(0, cube.n_frames, self.chunk_frames):
                    n = min(self.chunk_frames, cube.n_frames - first)
                    stored = buffer[:n * frame_pixels]
                    got = f.readinto(memoryview(stored).cast("B"))
                    if got < stored.nbytes:
                        raise DatasetError(cube.path, f"file ended inside frame {first + got // cube.frame_bytes}")
                    if checksum is not None:
                        checksum.update(stored.view(np.uint8))
                    if digest is not None:
                        digest.update(stored.view(np.uint8))
                    stored = stored.reshape(n, *cube.shape)
                    frames = stored.astype(self.dtype)
                    # The stored values, converted exactly, are judged before any shift: the
                    # maximum of the converted chunk, still in the cache, is the cheapest test,
                    # and the mask is built only when something saturates.
                    any_saturated = bool(frames.max() >= threshold)
                    if any_saturated:
                        saturated = stored >= threshold
                        _check_not_all_saturated(cube, first, frames, saturated, self.detector)
                    else:
                        if unsaturated is None or unsaturated.shape != stored.shape:
                            unsaturated = np.broadcast_to(np.False_, stored.shape)
                        saturated = unsaturated
                    if shift is not None:
                        frames += shift
                    if cube.disk_dtype.kind == "f" and not (np.isfinite(frames.max()) and np.isfinite(frames.min())):
                        raise DatasetError(cube.path, _non_finite_report(cube))
                    yield Chunk(start, frames, saturated, any_saturated)
                    # the chunk is the consumer's now: while the next one is read, no name of ours keeps it
                    # (a consumer that lets go of it too holds one chunk at a time, not two)
                    del frames, saturated
                    start += n
                if digest is not None:
                    digest.finish(f)
            if checksum is not None:
                _check_checksums(cube, checksum.value())


def _check_not_all_saturated(cube: CubeFile, first: int, frames, saturated, detector: Detector):
    """Refuse a chunk with a frame saturated over the whole science area: no detector does that; a
    saturation level set below the data does (every sample would be masked, and each step would then fail
    on an empty frame, far from the cause). ``frames`` are the stored values converted, not shifted."""
    rows, cols = detector.science_slices
    whole = saturated[:, rows, cols].reshape(saturated.shape[0], -1).all(axis=1)
    if whole.any():
        k = int(np.argmax(whole))
        median = float(np.median(frames[k, rows, cols])) + cube.bzero
        raise DatasetError(cube.path, f"every science-area sample of frame {first + k} (counted from 0 in this "
                                      f"file) is at or above detector.saturation, {detector.saturation:g} ADU "
                                      f"(the frame's median is {median:.6g} ADU): is the manifest's "
                                      "saturation level right?")


def _non_finite_report(cube: CubeFile) -> str:
    """Where a float cube holds NaN or infinite samples: the first such frame and pixel, and how many.

    Run only once a chunk has shown one, so the whole file is read again (in chunks) to count them all.
    """
    data = np.memmap(cube.path, dtype=cube.disk_dtype, mode="r", offset=cube.header_bytes,
                     shape=(cube.n_frames, *cube.shape))
    step = auto_chunk_frames(cube.shape)
    first = None
    frames = samples = 0
    for start in range(0, cube.n_frames, step):
        bad = ~np.isfinite(data[start:start + step])
        if not bad.any():
            continue
        per_frame = bad.reshape(bad.shape[0], -1).sum(axis=1)
        frames += int(np.count_nonzero(per_frame))
        samples += int(per_frame.sum())
        if first is None:
            t, r, c = np.argwhere(bad)[0]
            first = (start + int(t), int(r), int(c))
    del data
    t, r, c = first
    return (f"{samples} non-finite sample(s) (NaN or infinite) in {frames} of its {cube.n_frames} frames; "
            f"the first in frame {t}, row {r}, col {c} (counted from 0)")


_TOKEN_BYTES = 6  # of randomness in a temporary file's name
#: The name of :func:`atomic_write`'s temporary files: ``.<name>.<12 hex digits>.part`` beside the file.
TEMPORARY_NAME = re.compile(r"\..+\.[0-9a-f]{%d}\.part" % (2 * _TOKEN_BYTES))


def temporary_files(root, *, recursive: bool = True) -> list[Path]:
    """The temporary files of :func:`atomic_write` in the folder ``root`` (and its subfolders if
    ``recursive``), sorted; none if ``root`` does not exist. A process killed while writing leaves
    them: no ``finally`` runs after ``kill -9``."""
    found = []
    for folder, _, names in os.walk(root):
        found += [Path(folder) / name for name in names if TEMPORARY_NAME.fullmatch(name)]
        if not recursive:
            break
    return sorted(found)


def remove_abandoned(folder, targets) -> list[Path]:
    """Remove the temporary files of :func:`atomic_write` in ``folder`` that were to become one of
    ``targets`` (paths) and that no live process is writing; return them.

    Every :func:`atomic_write` holds a shared ``flock`` on its file's folder while its block runs, which the
    kernel drops when the writer's process ends, however it ends (``kill -9`` included). This takes the
    folder's lock exclusively, without waiting: if a writer holds it, nothing in the folder is removed.
    Where the filesystem has no ``flock``, nothing is removed either.
    """
    folder = Path(folder)
    wanted = {os.path.normpath(os.path.abspath(t)) for t in targets}
    try:
        descriptor = os.open(folder, os.O_RDONLY)
    except OSError:
        return []
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # a live writer in the folder, or no flock: keep everything
        os.close(descriptor)
        return []
    removed = []
    try:
        for part in temporary_files(folder, recursive=False):
            target = part.parent / part.name[1:].rsplit(".", 2)[0]  # .<name>.<hex>.part -> <name>
            if os.path.normpath(os.path.abspath(target)) in wanted:
                part.unlink(missing_ok=True)
                removed.append(part)
    finally:
        os.close(descriptor)  # and with it the lock
    return removed


def _atomic_target(path: Path):
    """A fresh temporary file beside ``path`` (named as :data:`TEMPORARY_NAME` says), with the mode a plain
    ``open`` would give ``path``.

    Created with mode 0666 and O_EXCL, so that the kernel applies the umask (and any default ACL), as
    for the figures; mkstemp's 0600 would survive the rename and keep the products from other users.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(_TOKEN_BYTES)}.part"
        try:
            os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            continue
        return tmp


def _disk_full(folder: Path) -> bool:
    """Whether the filesystem holding ``folder`` has no block left for this user."""
    try:
        stats = os.statvfs(folder)
    except OSError:
        return False
    return stats.f_bavail * stats.f_frsize < 65536


@contextlib.contextmanager
def atomic_write(path):
    """Write a file under a temporary name beside ``path``, renamed to ``path`` once the block succeeds.

    Yields the temporary path (created empty, mode 0666 minus the umask, as a plain ``open`` would
    give ``path``). On any failure the temporary file is removed and ``path`` is left as it was: a
    new file never appears half-written, an existing one is never truncated. The error raised is the
    writer's own: a failed clean-up is added to it as a note, never raised in its place, and a
    writer that hides an ENOSPC behind a library error (the netCDF library's "HDF error") is
    reported as the :class:`OSError` "No space left on device" when the filesystem is full. An
    :class:`OSError` that names no file, or the temporary one (a failed ``write`` of matplotlib's
    ``savefig``), is raised naming ``path``, the file the user asked for.

    Examples
    --------
    >>> with atomic_write("results/table.csv") as tmp:  # doctest: +SKIP
    ...     tmp.write_text("a,b\n1,2\n")
    """
    path = Path(path)
    tmp = _atomic_target(path)
    # a shared lock on the folder while the block writes, so that remove_abandoned() never takes a live
    # writer's file (a lock on the file itself would clash with the HDF5 library's own on the files it writes)
    lock = os.open(path.parent, os.O_RDONLY)
    try:
        fcntl.flock(lock, fcntl.LOCK_SH)
    except OSError:  # no flock on this filesystem: the file is still written whole or not at all
        pass
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as exc:
        full = not isinstance(exc, OSError) and isinstance(exc, Exception) and _disk_full(path.parent)
        try:
            tmp.unlink(missing_ok=True)
        except OSError as cleanup:
            exc.add_note(f"the temporary file {tmp} could not be removed: {cleanup}")
        if full:
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} (the writer said: {exc})",
                          str(path)) from exc
        if isinstance(exc, OSError) and exc.errno and exc.filename in (None, str(tmp), tmp):
            renamed = OSError(exc.errno, exc.strerror or os.strerror(exc.errno), str(path))
            for note in getattr(exc, "__notes__", []):  # a failed clean-up, added above
                renamed.add_note(note)
            raise renamed from exc
        raise
    finally:
        os.close(lock)


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
    from astropy.io import fits

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
    written = 0
    with atomic_write(path) as tmp:
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


def _jsonable(value):
    return json.dumps(value, sort_keys=True, default=str)


def first_chunk(chunks) -> Chunk:
    """The first chunk of a re-iterable of chunks, its file released at once (e.g. for a reference frame)."""
    iterator = iter(chunks)
    try:
        return next(iterator)
    finally:
        if hasattr(iterator, "close"):  # a generator: close its file now, not at garbage collection
            iterator.close()


def _catalogued(path, roots):
    """The catalogue's entry of a file written under the results folder of ``roots`` (the step's, from
    :func:`provenance`), or None: a file written anywhere else is no product of the workflow."""
    results = roots.get("results")
    return products.match(path, root=results) if results else None


def write_text(path, text: str):
    """Write a text file (a table) atomically: under a temporary name, then renamed. A CSV table of the
    catalogue (:mod:`dice_core.products`), written under the results folder of the enclosing
    :func:`provenance`, must have the columns its entry promises."""
    if not isinstance(text, str):
        raise TypeError(f"{path}: text expected, got {type(text).__name__}")
    found = _catalogued(path, (_PROVENANCE.get() or {}).get("roots") or {})
    if found is not None and found[0].kind == "csv":
        header = next(csv.reader([text.split("\n", 1)[0]]), [])
        absent = [column for column in found[0].columns if column not in header]
        if absent:
            raise ValueError(f"{path}: not what the catalogue's table {found[0].key} promises: no column "
                             f"{', '.join(absent)}")
    with atomic_write(path) as tmp:
        with open(tmp, "w") as f:
            f.write(text)


_PROVENANCE = contextvars.ContextVar("dice_core_provenance", default=None)
_DIGESTS: dict = {}  # (path, size, mtime) -> sha256, so a file read by several products is hashed once


@contextlib.contextmanager
def provenance(*, code_version=None, **roots):
    """Record, in every product :func:`write_product` writes within the block, the code and relative inputs.

    Parameters
    ----------
    code_version : str, optional
        Hash of the code that makes the products (the workflow's ``code_version`` of the step's
        modules), recorded as the global attribute ``code_version``: ``dice_core_version`` alone does
        not change when an editable install's source does.
    **roots : str or Path
        Folders the inputs are recorded relative to, by name, tried in order (e.g.
        ``dataset=<the manifest's folder>, results=results/<name>``); an input under none of them is
        recorded with its absolute path.
    """
    token = _PROVENANCE.set({"code_version": code_version, "roots": roots})
    try:
        yield
    finally:
        _PROVENANCE.reset(token)


def _digest_key(path: Path, stat=None) -> tuple:
    """The key of a file's digest in :data:`_DIGESTS` and in the results' store: its resolved path, size,
    modification and change times (ns) and inode. A file replaced keeps not all of them, even with its old
    modification time (``cp -p``, ``rsync -a``, a rename onto it): its change time is the system's own."""
    stat = path.stat() if stat is None else stat
    return (str(path.resolve()), stat.st_size, stat.st_mtime_ns, stat.st_ctime_ns, stat.st_ino)


class _StreamDigest:
    """The SHA-256 of a file taken from the bytes a :class:`FrameStream` reads: the header (read here, a few
    kB), the data unit chunk by chunk, then what follows it (the FITS padding), recorded in
    :data:`_DIGESTS` when the whole file was streamed and it did not change meanwhile. The provenance of
    the products made from a stream then costs no read of its own (:func:`write_product`)."""

    def __init__(self, key, hasher):
        self.key, self.hasher = key, hasher

    @classmethod
    def start(cls, path: Path, f, header_bytes: int):
        """The digest to take of the open file ``f``, its first ``header_bytes`` (the bytes before the data
        unit) hashed, or None if this process has it already. Leaves ``f`` at ``header_bytes``."""
        key = _digest_key(Path(path), os.fstat(f.fileno()))
        if key in _DIGESTS:
            return None
        hasher = hashlib.sha256()
        f.seek(0)
        head = f.read(header_bytes)
        while len(head) < header_bytes and (more := f.read(header_bytes - len(head))):
            head += more
        hasher.update(head)
        return cls(key, hasher)

    def update(self, data):
        self.hasher.update(data)

    def finish(self, f):
        """Hash the rest of ``f`` after the data unit and record the digest."""
        while block := f.read(1 << 20):
            self.hasher.update(block)
        if _digest_key(Path(self.key[0]), os.fstat(f.fileno())) == self.key:  # not rewritten while it was read
            _DIGESTS[self.key] = self.hasher.hexdigest()


#: The folder, in a results folder (the ``results`` root of :func:`provenance`), where the SHA-256 its steps
#: took of the raw files they read are kept, a small JSON file a file (its key, :func:`_digest_key`, and
#: digest): what one step hashed while streaming a file, another step that streams the same version of it is
#: given (:func:`adopt_stored_digests`): the Allan step, the files the fit read; a split fit's later passes,
#: those its first read.
DIGEST_STORE = ".dice-digests"


def _store_entry(path: str) -> Path | None:
    """The store's file of input ``path`` (resolved, str) in the results folder of the enclosing
    :func:`provenance` block; None outside one, or one without a ``results`` root."""
    results = ((_PROVENANCE.get() or {}).get("roots") or {}).get("results")
    if results is None:
        return None
    return Path(results) / DIGEST_STORE / (hashlib.blake2b(path.encode(), digest_size=16).hexdigest() + ".json")


def _store_digests(paths) -> None:
    """Keep in the store the digests this process took of the raw files among ``paths`` (in the dataset's
    folder, or anywhere but the results folder: where the manifest puts them; a simulated dataset's are in the
    results folder), not the products (small, read whole), under their current key. A store that cannot be
    written is said once, in the log."""
    roots = (_PROVENANCE.get() or {}).get("roots") or {}
    if roots.get("results") is None:
        return
    results = Path(roots["results"]).resolve()
    dataset = Path(roots["dataset"]).resolve() if roots.get("dataset") is not None else None
    for path in paths:
        try:
            key = _digest_key(Path(path))
        except OSError:
            continue
        where = Path(key[0])
        raw = (dataset is not None and where.is_relative_to(dataset)) or not where.is_relative_to(results)
        if key not in _DIGESTS or not raw:
            continue
        entry = _store_entry(key[0])
        text = json.dumps({"key": list(key), "sha256": _DIGESTS[key]})
        with contextlib.suppress(OSError, UnicodeDecodeError):
            if entry.read_text() == text:  # kept already (the digest was adopted from it): not written again
                continue
        try:
            entry.parent.mkdir(parents=True, exist_ok=True)
            write_text(entry, text)
        except OSError as exc:  # a cache: without it a later step hashes the file again
            log.warning("%s: the digests of this product's inputs not kept (%s): a step reading them again "
                        "will hash them", entry.parent, exc)
            return


def adopt_stored_digests(paths) -> list[str]:
    """Take as this process's own the SHA-256 that another step of the same results folder took of ``paths``
    (its store, :data:`DIGEST_STORE`, in the ``results`` root of the enclosing :func:`provenance` block:
    nothing outside one), where the file is the very version it hashed: its key (:func:`_digest_key`:
    resolved path, size, modification and change times, inode) unchanged. A file rewritten or replaced since
    (even with its old modification time) is hashed as it is read, as is one whose entry is missing or
    unreadable. Returns the files adopted (resolved paths). The Allan step streams the files the fit has
    hashed: it hashes none again."""
    adopted = []
    for path in paths:
        try:
            key = _digest_key(Path(path))
        except OSError:  # gone: whoever reads it says so
            continue
        entry = _store_entry(key[0])
        try:
            record = json.loads(entry.read_text()) if entry is not None else None
        except (OSError, ValueError):  # none kept, or not readable: hashed as read
            continue
        if (isinstance(record, dict) and record.get("key") == list(key)
                and isinstance(digest := record.get("sha256"), str)):
            _DIGESTS[key] = digest
            adopted.append(key[0])
    return adopted


def known_digests() -> dict:
    """The SHA-256 this process has taken, by their files' keys (:func:`_digest_key`): a worker process hands its
    own to its parent (:func:`dice_core.parallel.map_lanes`), which :func:`remember_digests`."""
    return dict(_DIGESTS)


def remember_digests(digests: dict) -> None:
    """Add digests taken elsewhere (:func:`known_digests` of a worker process) to this process's."""
    _DIGESTS.update(digests)


def _sha256(path: Path) -> str | None:
    try:
        key = _digest_key(path)
    except OSError:
        return None
    if key not in _DIGESTS:
        with open(path, "rb") as f:
            _DIGESTS[key] = hashlib.file_digest(f, "sha256").hexdigest()
    return _DIGESTS[key]


def _input_record(path, roots, digests=None) -> dict:
    """One entry of ``inputs``: the path relative to the first root holding it, and its sha256 (from
    ``digests``, by resolved path, where it is known)."""
    path = Path(path)
    absolute = path.resolve()
    record = {"path": str(absolute), "relative_to": None}
    for name, root in roots.items():
        root = Path(root).resolve()
        if absolute.is_relative_to(root):
            record = {"path": absolute.relative_to(root).as_posix(), "relative_to": name}
            break
    known = (digests or {}).get(str(absolute))
    record["sha256"] = known if known is not None else _sha256(absolute)
    return record


def input_digests(path, *, roots=None) -> dict:
    """The SHA-256 of the inputs a product recorded (its ``inputs``), by resolved path.

    For a product made from files another product has read and recorded, so that the files are not read
    again only to be hashed (:func:`write_product`'s ``digests``): a split fringe fit records its cubes'
    checksums from the parts that read them. ``roots`` (default: those of the enclosing
    :func:`provenance` block) resolve the recorded relative paths; inputs under no known root are left out.
    """
    roots = roots if roots is not None else (_PROVENANCE.get() or {}).get("roots") or {}
    with xr.open_dataset(path, engine="netcdf4") as ds:
        records = json.loads(ds.attrs.get("inputs", "[]"))
    digests = {}
    for record in records:
        if record["relative_to"] is None:
            where = Path(record["path"])
        elif record["relative_to"] in roots:
            where = Path(roots[record["relative_to"]]) / record["path"]
        else:
            continue
        if record["sha256"] is not None:
            digests[str(where.resolve())] = record["sha256"]
    return digests


def _history_of(path) -> list[str]:
    """The ``history`` lines of a netCDF input ([] for other files or one without history)."""
    path = Path(path)
    if path.suffix != ".nc" or not path.is_file():
        return []
    import netCDF4

    with netCDF4.Dataset(path) as nc:
        return str(getattr(nc, "history", "")).splitlines()


def _annotate_coordinates(ds: xr.Dataset) -> xr.Dataset:
    """Index coordinates for the shared dims that have none (:data:`dice_core.products.INDEX_DIMS`), and the
    units and long names of :data:`dice_core.products.COORDINATE_ATTRS` where the step set none."""
    missing = {dim: np.arange(ds.sizes[dim]) for dim in products.INDEX_DIMS if dim in ds.dims and dim not in ds.coords}
    ds = ds.assign_coords(missing)
    for dim, attrs in products.COORDINATE_ATTRS.items():
        if dim in ds.coords:
            ds[dim].attrs = {**attrs, **ds[dim].attrs}
    return ds


def _unannotated_coordinates(ds: xr.Dataset) -> list[str]:
    """The coordinates without a long name, or numeric without units: what a reader could not interpret."""
    return [str(name) for name, coord in ds.coords.items() if "long_name" not in coord.attrs
            or (coord.dtype.kind in "iuf" and "units" not in coord.attrs)]


def write_product(ds: xr.Dataset, path, *, title: str, config=None, inputs=(), code_version=None, roots=None,
                  digests=None):
    """Write a netCDF product atomically, with units checked and provenance attached.

    Every data variable with a physical meaning must carry a ``units`` attribute
    (``"1"`` for dimensionless): a variable without one is refused. The shared
    index coordinates (:data:`dice_core.products.INDEX_DIMS`: row, col, frame, position, star,
    batch, iteration) get one where the dataset has none; every coordinate gets
    the units and long name of :data:`dice_core.products.COORDINATE_ATTRS` where the step set none,
    and a coordinate left without a long name (or, numeric, without units) is
    refused. The global attributes receive ``Conventions``,
    ``title``, ``source`` and ``dice_core_version`` (the software),
    ``code_version`` (the hash of the code that made it, when known),
    ``configuration`` (JSON of ``config``), ``inputs`` (JSON list of
    ``{"path", "relative_to", "sha256"}``: each input's path relative to the
    first of ``roots`` that holds it, whose name ``relative_to`` gives, and the
    SHA-256 of its bytes) and ``history``: the inputs' (and the dataset's own)
    history lines, once each, then this write's line, CF style. The file is written
    through :func:`atomic_write`, so an existing product is never left half-written; a floating-point
    variable not in memory (read lazily: a file's, or maps kept on disk such as the Allan step's) is written
    :data:`WRITE_SLICE_BYTES` at a time along its first dimension, after the others, never whole in memory
    (:func:`_write_slices`). A file written under
    the results folder of ``roots`` that is an instance of a product of the catalogue
    (:mod:`dice_core.products`) must hold the variables its entry promises, on its dims and in its units.

    ``code_version`` and ``roots`` default to those of the enclosing :func:`provenance` block.
    ``digests`` maps inputs (resolved paths, str) to their SHA-256 when already known
    (:func:`input_digests`): those are not read again.
    """
    path = Path(path)
    missing = [name for name, var in ds.data_vars.items() if "units" not in var.attrs]
    if missing:
        raise ValueError(f"{path}: variables without units: {missing}")
    found = _catalogued(path, roots if roots is not None else (_PROVENANCE.get() or {}).get("roots") or {})
    if found is not None and found[0].kind == "netcdf":
        problems = products.problems(ds, found[0])
        if problems:
            raise ValueError(f"{path}: not what the catalogue's product {found[0].key} promises: {'; '.join(problems)}")
    context = _PROVENANCE.get() or {}
    code_version = code_version if code_version is not None else context.get("code_version")
    roots = roots if roots is not None else context.get("roots") or {}
    inputs = [Path(p) for p in inputs]
    ds = _annotate_coordinates(ds.copy())
    unannotated = _unannotated_coordinates(ds)
    if unannotated:
        raise ValueError(f"{path}: coordinates without a long_name (and units, if numeric): {unannotated}")
    history = []
    for line in [*str(ds.attrs.get("history", "")).splitlines(), *(h for p in inputs for h in _history_of(p))]:
        if line and line not in history:
            history.append(line)
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    code = f", code {code_version}" if code_version else ""
    history.append(f"{stamp} {path.name} ({title}) written by dice_core {dice_core.__version__}{code}")
    ds.attrs.update({
        "Conventions": "CF-1.10",
        "title": title,
        "source": f"dice_core {dice_core.__version__}{code}",
        "dice_core_version": dice_core.__version__,
        "configuration": _jsonable(config if config is not None else {}),
        "inputs": json.dumps([_input_record(p, roots, digests) for p in inputs]),
        "history": "\n".join(history),
    })
    if code_version:
        ds.attrs["code_version"] = str(code_version)
    streamed = [name for name, var in ds.data_vars.items() if _streamable(var.variable)]
    with atomic_write(path) as tmp:
        ds.drop_vars(streamed).to_netcdf(tmp, engine="netcdf4")
        _write_slices(tmp, ds, streamed)
    _store_digests(str(p.resolve()) for p in inputs)


#: Bytes of a lazily held variable :func:`write_product` reads and writes at a time (at least one slice
#: along its first dimension).
WRITE_SLICE_BYTES = 2**24


def _streamable(variable) -> bool:
    """Whether :func:`write_product` writes ``variable`` a slice at a time: a floating-point array not in
    memory (read lazily, as a file's or a product's maps on disk), with no encoding of its own to honour."""
    return (not variable._in_memory and variable.ndim > 0 and np.issubdtype(variable.dtype, np.floating)
            and not variable.encoding)


def _write_slices(path, ds, names):
    """Append the variables ``names`` of ``ds`` to the netCDF file ``path`` (which holds the rest of ``ds``),
    :data:`WRITE_SLICE_BYTES` at a time along their first dimension, as xarray would have written them
    whole (NaN as the fill value, the attributes)."""
    if not names:
        return
    import netCDF4

    with netCDF4.Dataset(path, "a") as nc:
        for name in names:
            variable = ds[name].variable
            for dim, n in zip(variable.dims, variable.shape):
                if dim not in nc.dimensions:
                    nc.createDimension(dim, n)
            target = nc.createVariable(name, variable.dtype, variable.dims, fill_value=np.nan)
            target.setncatts(dict(variable.attrs))
            step = max(1, WRITE_SLICE_BYTES // max(1, variable[0].size * variable.dtype.itemsize))
            for lo in range(0, variable.shape[0], step):
                target[lo:lo + step] = variable[lo:lo + step].values


def _existing_product(path) -> Path:
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "product not found")
    return path


def read_product(path) -> xr.Dataset:
    """Load a netCDF product fully into memory (and close the file)."""
    return xr.load_dataset(_existing_product(path), engine="netcdf4")


def open_product(path) -> xr.Dataset:
    """A netCDF product opened lazily: nothing read until a variable (or a slice of one) is, and nothing kept
    once read (no cache), so that a step reads the variables it needs, and those a band at a time if it
    likes. A context manager: ``with open_product(path) as ds:`` closes the file."""
    return xr.open_dataset(_existing_product(path), engine="netcdf4", cache=False)


def product_attrs(path) -> dict:
    """The global attributes of a netCDF product, none of its variables read (the file closed)."""
    with xr.open_dataset(_existing_product(path), engine="netcdf4") as ds:
        return dict(ds.attrs)
