"""FITS streaming and netCDF products: round trips, chunking, and every kind of bad input."""

from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from astropy.io import fits

from dice_core import DatasetError
from dice_core.calibration import dark_maps
from dice_core.io import (CHUNK_BYTES, FrameStream, auto_chunk_frames, open_cube, read_product, write_cube,
                          write_product)
from dice_core.manifest import Acquisition, Detector

REPO = Path(__file__).resolve().parents[1]

DETECTOR = Detector(shape=(6, 7), science_rows=(0, 6), science_cols=(0, 7), gain=2.0, saturation=60000.0)


def cube(n, rng, low=100, high=50000):
    return rng.integers(low, high, size=(n, 6, 7)).astype(float)


def stream(paths, **kwargs):
    return FrameStream(Acquisition("test acquisition", tuple(paths)), DETECTOR, **kwargs)


def collect(frame_stream):
    chunks = list(frame_stream)
    return np.concatenate([c.frames for c in chunks]), chunks


@pytest.mark.parametrize("dtype", ["uint16", "int32", "float32"])
def test_write_then_stream_round_trip(tmp_path, rng, dtype):
    data = cube(23, rng)
    path = tmp_path / "c.fits"
    write_cube(path, [data[:10], data[10:]], shape=(6, 7), n_frames=23, dtype=dtype)
    # astropy reads what we wrote, as (frame, row, col)
    np.testing.assert_array_equal(fits.getdata(path), data)
    frames, chunks = collect(stream([path], chunk_frames=5))
    np.testing.assert_array_equal(frames, data)
    assert [c.start for c in chunks] == [0, 5, 10, 15, 20]


def test_a_stream_keeps_no_chunk_it_has_given(tmp_path, rng):
    """A consumer that lets go of each chunk holds one chunk at a time: the stream keeps no name on the chunk
    it gave while it reads the next (six chunks of 16 frames of 128x128, 2 MiB of float64 each; traced peak
    measured 2.5 MiB, 4.5 before: two chunks, the one given and the one being read)."""
    import tracemalloc

    detector = Detector(shape=(128, 128), science_rows=(0, 128), science_cols=(0, 128), gain=2.0,
                        saturation=60000.0)
    data = rng.integers(100, 50000, size=(96, 128, 128)).astype(float)
    write_cube(tmp_path / "c.fits", [data], shape=(128, 128), n_frames=96)
    frames = FrameStream(Acquisition("test acquisition", (tmp_path / "c.fits",)), detector, chunk_frames=16)
    chunk_bytes = 16 * 128 * 128 * 8
    tracemalloc.start()
    try:
        total = 0.0
        for chunk in frames:
            total += float(chunk.frames[0, 0, 0])
            del chunk
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert total == data[::16, 0, 0].sum()
    assert peak < 1.5 * chunk_bytes, peak / chunk_bytes


def test_files_concatenate_in_order_and_chunks_do_not_span_files(tmp_path, rng):
    a, b = cube(7, rng), cube(4, rng)
    write_cube(tmp_path / "a.fits", [a], shape=(6, 7), n_frames=7)
    write_cube(tmp_path / "b.fits", [b], shape=(6, 7), n_frames=4)
    fs = stream([tmp_path / "a.fits", tmp_path / "b.fits"], chunk_frames=3)
    frames, chunks = collect(fs)
    assert fs.n_frames == 11 and fs.shape == (11, 6, 7)
    np.testing.assert_array_equal(frames, np.concatenate([a, b]))
    assert [c.start for c in chunks] == [0, 3, 6, 7, 10]
    # a stream can be iterated again
    np.testing.assert_array_equal(collect(fs)[0], frames)


def test_astropy_unsigned_and_2d_frame(tmp_path, rng):
    frame = rng.integers(0, 65535, size=(6, 7)).astype(np.uint16)
    fits.PrimaryHDU(frame).writeto(tmp_path / "one.fits")  # astropy writes BZERO 32768
    frames, _ = collect(stream([tmp_path / "one.fits"]))
    np.testing.assert_array_equal(frames, frame[None].astype(float))


def test_saturated_samples_are_flagged_masked_and_counted(tmp_path, rng):
    data = cube(20, rng, 1000, 2000)
    data[3, 2, 2] = data[7, 2, 2] = 65535
    path = tmp_path / "d.fits"
    write_cube(path, [data], shape=(6, 7), n_frames=20)
    _, chunks = collect(stream([path], chunk_frames=8))
    assert sum(int(c.saturated.sum()) for c in chunks) == 2
    maps = dark_maps(stream([path], chunk_frames=8), DETECTOR)
    assert maps["saturated_count"].values[2, 2] == 2 and maps["saturated_count"].values.sum() == 2
    # the saturated samples are left out of the mean, not averaged in
    expected = np.delete(data[:, 2, 2], [3, 7]).mean()
    assert maps["dark"].values[2, 2] == pytest.approx(expected, rel=1e-12)


def test_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="file not found") as info:
        stream([tmp_path / "absent.fits"])
    assert "absent.fits" in str(info.value)


def test_not_a_fits_file(tmp_path):
    path = tmp_path / "junk.fits"
    path.write_bytes(b"this is not FITS" * 200)
    with pytest.raises(DatasetError, match="not a readable FITS file") as info:
        stream([path])
    assert "junk.fits" in str(info.value)


def test_cube_shape_differs_from_detector(tmp_path, rng):
    path = tmp_path / "wrong.fits"
    write_cube(path, [rng.normal(size=(2, 6, 8))], shape=(6, 8), n_frames=2, dtype="float32")
    with pytest.raises(DatasetError, match=r"frames are 6x8 .* detector is 6x7") as info:
        stream([path])
    assert "wrong.fits" in str(info.value)


@pytest.mark.parametrize("array", [np.zeros((2, 6, 7), np.uint8), np.zeros((2, 6, 7), np.float64),
                                   np.zeros((2, 6, 7), np.int16), np.zeros((2, 6, 7), np.int64)])
def test_unsupported_data_type(tmp_path, array):
    path = tmp_path / "type.fits"
    fits.PrimaryHDU(array).writeto(path)
    with pytest.raises(DatasetError, match="unsupported data type") as info:
        stream([path])
    assert "type.fits" in str(info.value)


def test_truncated_file(tmp_path, rng):
    path = tmp_path / "cut.fits"
    write_cube(path, [cube(10, rng)], shape=(6, 7), n_frames=10)
    path.write_bytes(path.read_bytes()[:2880 + 200])
    with pytest.raises(DatasetError, match="truncated"):
        stream([path])


def test_checksum_verifies_when_intact(tmp_path, rng):
    path = tmp_path / "sum.fits"
    fits.PrimaryHDU(cube(9, rng).astype(np.float32)).writeto(path, checksum=True)
    frames, _ = collect(stream([path], chunk_frames=4))
    assert frames.shape == (9, 6, 7)


@pytest.mark.parametrize("where, expected", [("data", "DATASUM does not verify"),
                                             ("header", "CHECKSUM does not verify")])
def test_checksum_that_does_not_verify(tmp_path, rng, where, expected):
    path = tmp_path / "sum.fits"
    fits.PrimaryHDU(cube(9, rng).astype(np.float32)).writeto(path, checksum=True)
    raw = bytearray(path.read_bytes())
    if where == "data":
        raw[2880 + 101] ^= 0x10
    else:
        at = raw.index(b"EXPTIME") if b"EXPTIME" in raw else raw.index(b"NAXIS3")
        raw[at + 40:at + 41] = b"/"  # edit the comment field: header still parses
    path.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match=expected) as info:
        collect(stream([path]))
    assert "sum.fits" in str(info.value)


def test_non_finite_samples(tmp_path, rng):
    data = cube(12, rng).astype(np.float32)
    data[9, 1, 4] = np.nan
    path = tmp_path / "nan.fits"
    write_cube(path, [data], shape=(6, 7), n_frames=12, dtype="float32")
    with pytest.raises(DatasetError, match=r"1 non-finite sample.*frame 9, row 1, col 4") as info:
        collect(stream([path], chunk_frames=5))
    assert "nan.fits" in str(info.value)


def test_non_finite_samples_are_counted_over_the_file_from_the_first_bad_frame(tmp_path, rng):
    """The message gives the first bad frame and how many samples and frames are bad, not a chunk's range."""
    data = cube(12, rng).astype(np.float32)
    data[6, 2, 3] = np.inf
    data[6, 0, 0] = -np.inf
    data[11, 5, 6] = np.nan
    path = tmp_path / "bad.fits"
    write_cube(path, [data], shape=(6, 7), n_frames=12, dtype="float32")
    with pytest.raises(DatasetError) as info:
        collect(stream([path], chunk_frames=5))
    message = str(info.value)
    assert "3 non-finite sample(s) (NaN or infinite) in 2 of its 12 frames" in message
    assert "the first in frame 6, row 0, col 0" in message and "5..9" not in message


def test_too_few_frames(tmp_path, rng):
    path = tmp_path / "short.fits"
    write_cube(path, [cube(1, rng)], shape=(6, 7), n_frames=1)
    with pytest.raises(DatasetError, match="test acquisition has 1 frame.*at least 2.*for a noise map") as info:
        stream([path], min_frames=2, purpose="a noise map")
    assert "short.fits" in str(info.value)


def test_open_cube_reads_layout_only(tmp_path, rng):
    path = tmp_path / "c.fits"
    write_cube(path, [cube(3, rng)], shape=(6, 7), n_frames=3, header={"FRAMERAT": 108.0})
    info = open_cube(path, DETECTOR)
    assert (info.n_frames, info.shape, info.bzero) == (3, (6, 7), 32768.0)
    assert info.header["FRAMERAT"] == 108.0


def test_write_cube_failure_leaves_nothing_half_written(tmp_path, rng):
    path = tmp_path / "c.fits"
    write_cube(path, [cube(3, rng)], shape=(6, 7), n_frames=3)
    before = path.read_bytes()

    def failing():
        yield cube(2, rng)
        raise RuntimeError("simulated crash")

    with pytest.raises(RuntimeError):
        write_cube(path, failing(), shape=(6, 7), n_frames=3)
    assert path.read_bytes() == before
    assert list(tmp_path.iterdir()) == [path]


def product():
    return xr.Dataset({"m": (("row", "col"), np.ones((2, 3)), {"units": "adu"})})


def test_product_carries_units_and_provenance(tmp_path):
    path = tmp_path / "p.nc"
    write_product(product(), path, title="test", config={"a": 1}, inputs=["x.fits"])
    ds = read_product(path)
    assert ds["m"].attrs["units"] == "adu"
    for key in ("Conventions", "title", "source", "dice_core_version", "configuration", "inputs", "history"):
        assert key in ds.attrs
    assert '"a": 1' in ds.attrs["configuration"] and "x.fits" in ds.attrs["inputs"]


def test_product_without_units_is_refused(tmp_path):
    ds = product()
    ds["m"].attrs = {}
    with pytest.raises(ValueError, match="without units"):
        write_product(ds, tmp_path / "p.nc", title="t")


def test_failed_product_write_keeps_the_old_product(tmp_path):
    path = tmp_path / "p.nc"
    write_product(product(), path, title="first")
    bad = product()
    bad["m"].attrs["unwritable"] = {"nested": "dict"}  # netCDF cannot store it
    with pytest.raises(Exception):
        write_product(bad, path, title="second")
    assert read_product(path).attrs["title"] == "first"
    assert list(tmp_path.iterdir()) == [path]


def test_chunks_across_files_hold_their_own_samples_and_can_be_centred(tmp_path, rng):
    data = cube(40, rng)
    data[30, 1, 2] = 65000  # saturated, in the second file only
    write_cube(tmp_path / "a.fits", [data[:25]], shape=(6, 7), n_frames=25)
    write_cube(tmp_path / "b.fits", [data[25:]], shape=(6, 7), n_frames=15)
    paths = [tmp_path / "a.fits", tmp_path / "b.fits"]
    # every chunk is kept until the end: the reader's reused raw buffer must not show through
    frames, chunks = collect(stream(paths, chunk_frames=6))
    np.testing.assert_array_equal(frames, data)
    assert [c.start for c in chunks] == [0, 6, 12, 18, 24, 25, 31, 37]
    assert [c.any_saturated for c in chunks] == [False] * 5 + [True] + [False] * 2
    saturated = np.concatenate([c.saturated for c in chunks])
    assert saturated.sum() == 1 and saturated[30, 1, 2]
    reference = data[0]
    centred, _ = collect(stream(paths, chunk_frames=6, dtype=np.float32).centred(reference))
    np.testing.assert_allclose(centred, data - reference, atol=1e-3)


def test_split_into_consecutive_groups_of_whole_files(tmp_path, rng):
    data = cube(50, rng)
    sizes = [10, 10, 5, 25]
    paths, first = [], 0
    for i, n in enumerate(sizes):
        paths.append(tmp_path / f"{i}.fits")
        fits.PrimaryHDU(data[first:first + n].astype(np.float32)).writeto(paths[-1], checksum=True)
        first += n
    whole = stream(paths, chunk_frames=4)
    parts = whole.split(2)
    # about half the frames each: the cut falls after the third file (25 frames), not the second (20)
    assert [len(p.cubes) for p in parts] == [3, 1] and [p.n_frames for p in parts] == [25, 25]
    frames = [collect(p) for p in parts]
    np.testing.assert_array_equal(np.concatenate([f for f, _ in frames]), data)
    assert [c.start for c in frames[1][1]] == [25, 29, 33, 37, 41, 45, 49]  # indices in the whole acquisition
    assert len(whole.split(10)) == 4 and len(whole.split(1)) == 1
    raw = bytearray(paths[3].read_bytes())  # each part verifies its own files
    raw[2880 + 101] ^= 0x10
    paths[3].write_bytes(bytes(raw))
    collect(parts[0])
    with pytest.raises(DatasetError, match="3.fits: DATASUM does not verify"):
        collect(parts[1])
    with pytest.raises(ValueError, match="parts"):
        whole.split(0)


def test_chunk_size_is_chosen_for_the_cache_unless_given(tmp_path, rng):
    write_cube(tmp_path / "a.fits", [cube(3, rng)], shape=(6, 7), n_frames=3)
    assert stream([tmp_path / "a.fits"]).chunk_frames == auto_chunk_frames((6, 7)) == CHUNK_BYTES // (4 * 42)
    assert auto_chunk_frames((80, 84)) == 39 and auto_chunk_frames((40, 44)) == 148  # the presets': in the cache
    # a large detector: at least 16 frames (the projector's traffic), at most 256 MiB of float32
    assert auto_chunk_frames((512, 512)) == auto_chunk_frames((2048, 2048)) == 16
    assert auto_chunk_frames((4096, 4096)) == 4 and auto_chunk_frames((10000, 10000)) == 1
    assert stream([tmp_path / "a.fits"], chunk_frames=2).chunk_frames == 2
    for bad in (0, "fast"):
        with pytest.raises(ValueError, match="chunk_frames"):
            stream([tmp_path / "a.fits"], chunk_frames=bad)


def test_text_is_written_atomically_and_a_failure_keeps_the_old_file(tmp_path):
    from dice_core.io import write_text

    path = tmp_path / "tables" / "a.csv"
    write_text(path, "a,b\n1,2\n")
    assert path.read_text() == "a,b\n1,2\n"
    with pytest.raises(TypeError):
        write_text(path, None)  # not text: nothing is written
    assert path.read_text() == "a,b\n1,2\n" and list(path.parent.iterdir()) == [path]


def test_products_tables_and_cubes_honour_the_umask(tmp_path):
    import os

    import xarray as xr

    from dice_core.io import write_cube, write_product, write_text

    previous = os.umask(0o027)
    try:
        write_text(tmp_path / "table.csv", "a,b\n")
        write_product(xr.Dataset({"v": ((), 1.0, {"units": "1"})}), tmp_path / "product.nc", title="t")
        write_cube(tmp_path / "cube.fits", [np.zeros((2, 3, 4), np.float32)], shape=(3, 4), n_frames=2)
    finally:
        os.umask(previous)
    for name in ("table.csv", "product.nc", "cube.fits"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o640, name


def test_figures_manifests_and_reports_honour_the_umask(tmp_path):
    import os

    import matplotlib.pyplot as plt

    from dice_core import plotting, simulation

    previous = os.umask(0o027)
    try:
        fig, ax = plt.subplots()
        plotting.save(fig, tmp_path / "f.png", pdf=tmp_path / "f.pdf")
        plotting.reproduction_pdf(tmp_path / "report.pdf", [(tmp_path / "f.png", "a caption")], title="t")
        simulation.write_manifest(simulation.load_preset(REPO / "config" / "presets" / "ci.yaml"), tmp_path / "raw")
    finally:
        os.umask(previous)
    for name in ("f.png", "f.pdf", "report.pdf", "raw/dataset.yaml"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o640, name
    assert not list(tmp_path.rglob("*.part"))
    assert (tmp_path / "f.pdf").read_bytes()[:4] == b"%PDF" and (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"


def test_a_full_disk_is_reported_as_such_and_leaves_nothing_half_written(tmp_path, monkeypatch):
    """ENOSPC in the middle of a write is the error the user reads, even when the clean-up fails too."""
    import errno
    from pathlib import Path

    path = tmp_path / "p.nc"
    write_product(product(), path, title="first")

    def full(self, target, **kwargs):
        Path(target).write_bytes(b"CDF half")  # some bytes made it
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", full)
    with pytest.raises(OSError) as info:
        write_product(product(), path, title="second")
    assert info.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == [path]
    # the clean-up of the temporary file fails as well: the full disk is still what is reported
    real_unlink = Path.unlink

    def refused(self, missing_ok=False):
        if self.name.endswith(".part"):
            raise PermissionError(errno.EACCES, "Permission denied", str(self))
        return real_unlink(self, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", refused)
    with pytest.raises(OSError) as info:
        write_product(product(), path, title="third")
    assert info.value.errno == errno.ENOSPC and not isinstance(info.value, PermissionError)
    assert any("could not be removed" in note for note in info.value.__notes__)
    monkeypatch.undo()
    assert read_product(path).attrs["title"] == "first"


def test_a_library_error_on_a_full_disk_is_reported_as_no_space(tmp_path, monkeypatch):
    """The netCDF library reports ENOSPC as "NetCDF: HDF error": on a full filesystem, the OSError is raised."""
    import errno

    from dice_core import io

    def hdf_error(self, target, **kwargs):
        raise RuntimeError("NetCDF: HDF error")

    monkeypatch.setattr(xr.Dataset, "to_netcdf", hdf_error)
    with pytest.raises(RuntimeError, match="HDF error"):  # space left: the library's error stands
        write_product(product(), tmp_path / "p.nc", title="t")
    monkeypatch.setattr(io, "_disk_full", lambda folder: True)
    with pytest.raises(OSError, match="No space left on device") as info:
        write_product(product(), tmp_path / "p.nc", title="t")
    assert info.value.errno == errno.ENOSPC and "p.nc" in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_is_the_one_mechanism(tmp_path):
    """Every writer goes through io.atomic_write: no other module renames a temporary file itself."""
    from dice_core.io import atomic_write

    with atomic_write(tmp_path / "sub" / "a.txt") as tmp:
        assert tmp.parent == tmp_path / "sub" and tmp.name.endswith(".part")
        tmp.write_text("x")
        assert not (tmp_path / "sub" / "a.txt").exists()
    assert (tmp_path / "sub" / "a.txt").read_text() == "x"
    with pytest.raises(KeyError):
        with atomic_write(tmp_path / "sub" / "a.txt") as tmp:
            tmp.write_text("half")
            raise KeyError("crash")
    assert (tmp_path / "sub" / "a.txt").read_text() == "x" and len(list((tmp_path / "sub").iterdir())) == 1
    for source in [*(REPO / "dice_core").glob("*.py"), *(REPO / "workflow").rglob("*.smk"),
                   *(REPO / "workflow" / "scripts").glob("*.py")]:
        if source.name != "io.py":
            text = source.read_text()
            assert "os.replace(" not in text and ".replace(path)" not in text and "mkstemp" not in text, source


def test_provenance_appends_history_and_records_relative_inputs_with_checksums_and_the_code(tmp_path):
    import hashlib
    import json

    from dice_core.io import provenance
    from dice_core.products import COORDINATE_ATTRS

    dataset, results = tmp_path / "bench", tmp_path / "results" / "bench"
    raw = dataset / "raw" / "dark.fits"
    write_cube(raw, [np.zeros((2, 6, 7))], shape=(6, 7), n_frames=2)
    first = results / "calibration" / "maps.nc"
    with provenance(code_version="0123abcd", dataset=dataset, results=results):
        write_product(product(), first, title="dark maps", inputs=[raw])
    dark = read_product(first)
    assert dark.attrs["code_version"] == "0123abcd" and "code 0123abcd" in dark.attrs["history"]
    [record] = json.loads(dark.attrs["inputs"])
    assert record == {"path": "raw/dark.fits", "relative_to": "dataset",
                      "sha256": hashlib.sha256(raw.read_bytes()).hexdigest()}
    second = results / "calibration" / "flat.nc"
    write_product(product().assign_coords(row=[10, 11]), second, title="prnu", inputs=[first, raw],
                  code_version="4567ef", roots={"dataset": dataset, "results": results})
    prnu = read_product(second)
    history = prnu.attrs["history"].splitlines()
    assert history[:-1] == dark.attrs["history"].splitlines()  # the input's history kept, then this write's
    assert "flat.nc (prnu) written by dice_core" in history[-1] and "code 4567ef" in history[-1]
    records = json.loads(prnu.attrs["inputs"])
    assert [(r["path"], r["relative_to"]) for r in records] == [("calibration/maps.nc", "results"),
                                                                ("raw/dark.fits", "dataset")]
    assert records[0]["sha256"] == hashlib.sha256(first.read_bytes()).hexdigest()
    # an input under neither root keeps its absolute path
    write_product(product(), tmp_path / "x.nc", title="x", inputs=[second], roots={"dataset": dataset})
    assert json.loads(read_product(tmp_path / "x.nc").attrs["inputs"])[0]["path"] == str(second)
    # the shared coordinates carry units and long names, an index where the dataset had none
    for name in ("row", "col"):
        assert prnu[name].attrs["units"] == COORDINATE_ATTRS[name]["units"] == "pixel" and prnu[name].attrs["long_name"]
    assert prnu["row"].values.tolist() == [10, 11] and prnu["col"].values.tolist() == [0, 1, 2]


def test_checksums_recorded_by_one_product_are_taken_by_another_without_reading_the_file(tmp_path):
    """A split fringe fit's product records the cubes as pass 1's parts recorded them (input_digests): the
    checksum given is recorded, not the file read again; a file no product recorded is read and hashed."""
    import hashlib
    import json

    from dice_core.io import input_digests, provenance

    dataset, results = tmp_path / "bench", tmp_path / "results"
    raw, other = dataset / "raw" / "cube.fits", dataset / "raw" / "other.fits"
    for path in (raw, other):
        write_cube(path, [np.ones((2, 6, 7))], shape=(6, 7), n_frames=2)
    part = results / "part.nc"
    with provenance(dataset=dataset, results=results):
        write_product(product(), part, title="part", inputs=[raw])
        digests = input_digests(part)
        assert digests == {str(raw.resolve()): hashlib.sha256(raw.read_bytes()).hexdigest()}
        # what the part recorded is what the product records, even had the file changed since (it is not read)
        recorded = {str(raw.resolve()): "0" * 64}
        write_product(product(), results / "whole.nc", title="whole", inputs=[raw, other], digests=recorded)
    records = json.loads(read_product(results / "whole.nc").attrs["inputs"])
    assert [r["sha256"] for r in records] == ["0" * 64, hashlib.sha256(other.read_bytes()).hexdigest()]


def test_a_step_streaming_files_another_step_hashed_adopts_their_digests_only_for_the_same_version(
        tmp_path, rng, monkeypatch):
    """The fit keeps the SHA-256 it took of its files in the results' store (write_product); the Allan step,
    which streams the same files, adopts them (adopt_stored_digests) and hashes nothing, recording the same
    digests. A file replaced since, even with an older or its very modification time (cp -p, a rename onto
    it), is not adopted: hashed; a malformed entry is no entry; a raw file outside the dataset's folder is
    kept too, the results' own products not."""
    import hashlib
    import json
    import os

    from dice_core import io

    monkeypatch.setattr(io, "_DIGESTS", {})  # this process has hashed nothing yet
    detector = Detector(shape=(6, 7), science_rows=(0, 6), science_cols=(0, 7), gain=2.0, saturation=6e4)
    dataset, results = tmp_path / "bench", tmp_path / "results"
    files = [dataset / "raw" / f"m{i}.fits" for i in range(2)]
    for path in files:
        write_cube(path, [cube(5, rng)], shape=(6, 7), n_frames=5)
    sha256 = hashlib.sha256
    truth = {str(f.resolve()): sha256(f.read_bytes()).hexdigest() for f in files}
    baseline = Acquisition("baseline", tuple(files))
    with io.provenance(dataset=dataset, results=results):
        collect(FrameStream(baseline, detector, chunk_frames=2))  # the fit: hashed as read
        write_product(product(), results / "metrology.nc", title="fit", inputs=files)
        assert len(list((results / io.DIGEST_STORE).iterdir())) == 2

        monkeypatch.setattr(io, "_DIGESTS", {})  # a new process: the Allan job

        def no_hashing(*args):
            raise AssertionError("a file was hashed again")

        monkeypatch.setattr(io.hashlib, "sha256", no_hashing)
        assert io.adopt_stored_digests(files) == [str(f.resolve()) for f in files]
        kept = {entry: entry.stat().st_ino for entry in (results / io.DIGEST_STORE).iterdir()}  # a rewrite: a new inode
        collect(FrameStream(baseline, detector, chunk_frames=2))
        write_product(product(), results / "allan.nc", title="allan", inputs=[*files, results / "metrology.nc"])
        records = json.loads(read_product(results / "allan.nc").attrs["inputs"])
        assert {str((dataset / r["path"]).resolve()): r["sha256"] for r in records[:2]} == truth
        # the dataset's files only, not products; the adopted entries not written again
        assert {entry: entry.stat().st_ino for entry in (results / io.DIGEST_STORE).iterdir()} == kept

        # the second file replaced by other bytes of the same size with an older time, as cp -p leaves it; then
        # renamed onto by a copy with its very size and modification time
        monkeypatch.setattr(io.hashlib, "sha256", sha256)
        for older in (True, False):
            monkeypatch.setattr(io, "_DIGESTS", {})
            before = files[1].stat().st_mtime_ns
            copy = tmp_path / "copy.fits"
            write_cube(copy, [cube(5, rng)], shape=(6, 7), n_frames=5)
            os.utime(copy, ns=(before - 10**9 * older,) * 2)
            assert copy.stat().st_size == files[1].stat().st_size
            os.replace(copy, files[1])
            assert io.adopt_stored_digests(files) == [str(files[0].resolve())], older
            collect(FrameStream(baseline, detector, chunk_frames=2))
            assert io.known_digests()[io._digest_key(files[1])] == sha256(files[1].read_bytes()).hexdigest()
            assert io.known_digests()[io._digest_key(files[0])] == truth[str(files[0].resolve())]
            write_product(product(), results / "allan.nc", title="allan", inputs=files)  # the new version kept
            monkeypatch.setattr(io, "_DIGESTS", {})
            assert io.adopt_stored_digests(files) == [str(f.resolve()) for f in files], older  # its entry rewritten
        # an entry that is not one (a list, no digest) is no digest: the file is hashed as read, nothing fails
        monkeypatch.setattr(io, "_DIGESTS", {})
        for entry, text in zip(sorted((results / io.DIGEST_STORE).iterdir()), ("[1, 2]", '{"key": []}')):
            entry.write_text(text)
        assert io.adopt_stored_digests(files) == []
        # a raw file outside the dataset's folder (a manifest may name it by its absolute path) is kept too
        elsewhere = tmp_path / "archive" / "m9.fits"
        write_cube(elsewhere, [cube(5, rng)], shape=(6, 7), n_frames=5)
        collect(FrameStream(Acquisition("baseline", (elsewhere,)), detector, chunk_frames=2))
        write_product(product(), results / "fit2.nc", title="fit", inputs=[elsewhere])
        monkeypatch.setattr(io, "_DIGESTS", {})
        assert io.adopt_stored_digests([elsewhere]) == [str(elsewhere.resolve())]
    # a simulated dataset's raw files, in the results folder (its raw/ the dataset's folder), are kept too
    simulated = results / "raw" / "m0.fits"
    write_cube(simulated, [cube(5, rng)], shape=(6, 7), n_frames=5)
    with io.provenance(dataset=results / "raw", results=results):
        collect(FrameStream(Acquisition("baseline", (simulated,)), detector, chunk_frames=2))
        write_product(product(), results / "fit3.nc", title="fit", inputs=[simulated])
        monkeypatch.setattr(io, "_DIGESTS", {})
        assert io.adopt_stored_digests([simulated]) == [str(simulated.resolve())]
    # outside a results folder (no provenance block) nothing is kept, nothing adopted
    monkeypatch.setattr(io, "_DIGESTS", {})
    assert io.adopt_stored_digests(files) == []


@pytest.mark.parametrize("dtype", ["uint16", "float32"])
def test_a_frame_saturated_over_the_whole_science_area_names_the_file_and_the_saturation_level(tmp_path, rng, dtype):
    """A saturation level set below the data masks every sample; each step then failed on an empty frame
    ("no positive signal"), far from the cause. The stream says it at the first such frame."""
    detector = Detector(shape=(6, 7), science_rows=(1, 5), science_cols=(1, 6), gain=2.0, saturation=1.0)
    data = cube(10, rng, 500, 600)
    path = tmp_path / "f.fits"
    write_cube(path, [data], shape=(6, 7), n_frames=10, dtype=dtype)
    frames = FrameStream(Acquisition("flat a", (path,)), detector, chunk_frames=4)
    with pytest.raises(DatasetError) as info:
        collect(frames)
    median = np.median(data[0, 1:5, 1:6])
    assert str(info.value) == (f"{path}: every science-area sample of frame 0 (counted from 0 in this file) is at "
                               f"or above detector.saturation, 1 ADU (the frame's median is {median:.6g} ADU): is "
                               "the manifest's saturation level right?")
    # saturated samples in some pixels only, or outside the science area, are masked as before
    data[:, 0, :] = data[2, 2:4, 2:4] = 65535
    write_cube(path, [data], shape=(6, 7), n_frames=10, dtype=dtype)
    detector = Detector(shape=(6, 7), science_rows=(1, 5), science_cols=(1, 6), gain=2.0, saturation=60000.0)
    _, chunks = collect(FrameStream(Acquisition("flat a", (path,)), detector, chunk_frames=4))
    assert sum(int(c.saturated.sum()) for c in chunks) == 10 * 7 + 4


def test_a_write_error_that_names_no_file_names_the_file_being_written(tmp_path):
    """matplotlib's savefig on a full disk raises ENOSPC naming no file: the target is named, not the temporary."""
    import errno

    from dice_core.io import atomic_write

    target = tmp_path / "figures" / "metrology_H1H4.png"
    for filename in (None, "temporary"):
        with pytest.raises(OSError) as info:
            with atomic_write(target) as tmp:
                raise OSError(errno.ENOSPC, "No space left on device", *([str(tmp)] if filename else []))
        assert info.value.errno == errno.ENOSPC and info.value.filename == str(target)
        assert list((tmp_path / "figures").iterdir()) == []
    with pytest.raises(FileNotFoundError) as info:  # an error about another file keeps its name
        with atomic_write(target):
            open(tmp_path / "missing.txt")
    assert info.value.filename == str(tmp_path / "missing.txt")


def test_temporary_files_of_a_killed_writer_are_found_by_their_name_only(tmp_path):
    from dice_core.io import TEMPORARY_NAME, temporary_files

    (tmp_path / "figures").mkdir()
    left = [tmp_path / ".a.nc.0123456789ab.part", tmp_path / "figures" / ".m.png.abcdef012345.part"]
    for path in left:
        path.write_bytes(b"")
    for other in ("a.nc.0123456789ab.part", ".a.nc.part", ".a.nc.0123456789ab.partial", ".a.nc.XYZ456789abc.part"):
        (tmp_path / other).write_bytes(b"")
    assert temporary_files(tmp_path) == sorted(left)
    assert temporary_files(tmp_path, recursive=False) == left[:1]
    assert temporary_files(tmp_path / "nowhere") == []
    assert TEMPORARY_NAME.fullmatch(".x.fits.0123456789ab.part")


def test_a_killed_writers_temporary_file_is_removed_and_a_live_writers_kept(tmp_path):
    """The next run removes a killed writer's temporary file, never a live writer's: atomic_write holds a
    shared lock on the folder while its block runs, which the kernel drops when the process dies."""
    import signal
    import subprocess
    import sys
    import time

    from dice_core.io import remove_abandoned, temporary_files

    target = tmp_path / "figure.png"
    writer = subprocess.Popen([sys.executable, "-c", (
        "import time\n"
        "from dice_core.io import atomic_write\n"
        f"with atomic_write({str(target)!r}) as tmp:\n"
        "    tmp.write_bytes(b'half')\n"
        "    print('writing', flush=True)\n"
        "    time.sleep(60)\n")], stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout.readline() == "writing\n"
        (part,) = temporary_files(tmp_path)
        assert remove_abandoned(tmp_path, [target]) == [] and part.exists()  # a live writer's
        writer.send_signal(signal.SIGKILL)
        writer.wait()
        other = tmp_path / ".notes.txt.0123456789ab.part"  # not a target of this run
        other.write_bytes(b"")
        deadline = time.monotonic() + 10
        while not (removed := remove_abandoned(tmp_path, [target])):  # the kernel drops the lock with the process
            assert time.monotonic() < deadline
            time.sleep(0.05)
    finally:
        writer.kill()
    assert removed == [part] and not part.exists() and other.exists()
    assert remove_abandoned(tmp_path / "nowhere", [target]) == []


def test_a_streamed_file_is_hashed_from_the_bytes_the_stream_reads_not_read_again(tmp_path, rng, monkeypatch):
    """The products' checksums cost no read of their own: a stream read to its end records each file's
    SHA-256 (header, data and padding); a stream left after its first chunk records nothing, and a file
    changed since is hashed again; worker processes hand theirs to the parent."""
    import hashlib
    import json
    import os

    from dice_core import io, parallel

    paths = [tmp_path / f"c{i}.fits" for i in range(3)]
    for path, n in zip(paths, (7, 4, 5)):
        write_cube(path, [cube(n, rng)], shape=(6, 7), n_frames=n, dtype="uint16")
    truth = {str(p.resolve()): hashlib.sha256(p.read_bytes()).hexdigest() for p in paths}
    monkeypatch.setattr(io, "_DIGESTS", {})
    io.first_chunk(stream(paths, chunk_frames=3))  # a partial read proves nothing of the rest of the file
    assert io.known_digests() == {}
    collect(stream(paths, chunk_frames=3))
    assert {key[0]: value for key, value in io.known_digests().items()} == truth

    def no_read(*args, **kwargs):
        raise AssertionError("a streamed file read again to be hashed")

    monkeypatch.setattr(io.hashlib, "file_digest", no_read)
    write_product(product(), tmp_path / "p.nc", title="p", inputs=paths)
    assert [r["sha256"] for r in json.loads(read_product(tmp_path / "p.nc").attrs["inputs"])] == list(truth.values())
    # a file rewritten since it was streamed is hashed from its new bytes
    monkeypatch.undo()
    monkeypatch.setattr(io, "_DIGESTS", {})
    collect(stream(paths, chunk_frames=3))
    write_cube(paths[0], [cube(7, rng)], shape=(6, 7), n_frames=7, dtype="uint16")
    os.utime(paths[0], ns=(1, 1))
    write_product(product(), tmp_path / "q.nc", title="q", inputs=paths[:1])
    [record] = json.loads(read_product(tmp_path / "q.nc").attrs["inputs"])
    assert record["sha256"] == hashlib.sha256(paths[0].read_bytes()).hexdigest() != truth[str(paths[0].resolve())]
    # lanes read in worker processes: their digests come back with the results
    monkeypatch.setattr(io, "_DIGESTS", {})
    lanes = stream(paths[1:], chunk_frames=2).split(2)
    with parallel.lane_executor(2, len(lanes)) as executor:
        if executor is None:
            pytest.skip("no fork on this platform")
        counts = parallel.map_lanes(executor, _frames_of, lanes)
    assert counts == [4, 5]
    assert {key[0]: value for key, value in io.known_digests().items()} == {
        str(p.resolve()): truth[str(p.resolve())] for p in paths[1:]}


def _frames_of(lane):
    return sum(chunk.frames.shape[0] for chunk in lane)


class _SlicedReads:
    """A lazily read (n, m) float32 array (an xarray backend array) that counts its reads and fails on read
    ``fail_at`` if given."""

    def __init__(self, values, fail_at=None):
        self.values, self.shape, self.dtype, self.reads, self.fail_at = values, values.shape, values.dtype, [], fail_at

    def __getitem__(self, key):
        from xarray.core import indexing

        return indexing.explicit_indexing_adapter(key, self.shape, indexing.IndexingSupport.BASIC, self._read)

    def _read(self, key):
        self.reads.append(key)
        if self.fail_at is not None and len(self.reads) > self.fail_at:
            raise RuntimeError("the disk went away")
        return self.values[key]


def test_a_variable_not_in_memory_is_written_a_slice_at_a_time_and_never_half(tmp_path, monkeypatch):
    """write_product writes a lazily read floating-point variable WRITE_SLICE_BYTES at a time along its first
    dimension (NaN kept, its attributes, the fill value xarray gives): the file read back equals the in-memory
    product; a read failing midway leaves no file."""
    from xarray.backends import BackendArray
    from xarray.core import indexing

    from dice_core import io

    class Lazy(_SlicedReads, BackendArray):
        pass

    values = np.arange(7 * 12, dtype=np.float32).reshape(7, 12)
    values[2, 3] = np.nan
    monkeypatch.setattr(io, "WRITE_SLICE_BYTES", 2 * 12 * 4)  # two rows a slice
    lazy = Lazy(values)

    def product(data):
        return xr.Dataset({"maps": (("batch", "col"), data, {"units": "pixel", "long_name": "maps"}),
                           "small": (("col",), np.ones(12), {"units": "1"})},
                          coords={"batch": np.arange(7), "col": np.arange(12)})

    write_product(product(indexing.LazilyIndexedArray(lazy)), tmp_path / "lazy.nc", title="t")
    write_product(product(values), tmp_path / "whole.nc", title="t")
    assert len(lazy.reads) == 4  # rows 0-1, 2-3, 4-5, 6
    one, two = read_product(tmp_path / "lazy.nc"), read_product(tmp_path / "whole.nc")
    xr.testing.assert_identical(one.drop_attrs(), two.drop_attrs())
    assert one["maps"].attrs == two["maps"].attrs and np.isnan(one["maps"].encoding["_FillValue"])
    with pytest.raises(RuntimeError, match="the disk went away"):
        write_product(product(indexing.LazilyIndexedArray(Lazy(values, fail_at=2))), tmp_path / "failed.nc",
                      title="t")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lazy.nc", "whole.nc"]
