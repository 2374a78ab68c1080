"""The dataset checker, ``python -m dice_core check PATH/dataset.yaml [--data]``, run as a user runs it: on the
default preset's layout (its manifest and its 23 files, 17,392 frames of 80x84 pixels, written here with
astropy), on defects of one file or one key each, and on a folder of one-frame FITS files written by another
program, made a dataset by the script of docs/own-data.md."""

import copy
import os
import re
import resource
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml
from astropy.io import fits

from dice_core import io, simulation
from dice_core.manifest import load_manifest

from conftest import REPO, small_config

#: What the checker may take on the default preset, s of CPU time (the issue's "in seconds"): CPU time rather than
#: wall time, which a machine shared by other jobs stretches without bound.
SECONDS = 5.0


def run_check(*args):
    """``python -m dice_core check *args`` from the repository, as the README says: (exit status, stdout lines,
    stderr, CPU seconds the checker took)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    result = subprocess.run([sys.executable, "-m", "dice_core", "check", *map(str, args)], cwd=REPO,
                            env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=300)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return result.returncode, result.stdout.splitlines(), result.stderr, cpu


def problems(lines):
    return [line for line in lines if line.startswith("problem: ")]


def write_frames(path, frames, *, checksum=False):
    """Unsigned 16-bit samples as another program writes them with astropy: BITPIX 16, BZERO 32768."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fits.PrimaryHDU(np.asarray(frames, dtype=np.uint16)).writeto(path, checksum=checksum)
    return path


@pytest.fixture(scope="module")
def default_dataset(tmp_path_factory):
    """The default preset's manifest with files of its layout (each of its frames, at a constant 1000 adu)."""
    cfg = simulation.load_preset(REPO / "config" / "presets" / "default.yaml")
    folder = tmp_path_factory.mktemp("default") / "raw"
    shape = cfg.detector.shape
    for relpath, (_, _, start, stop) in simulation.file_jobs(cfg).items():
        write_frames(folder / relpath, np.full((stop - start, *shape), 1000))
    layout = simulation.dataset_layout(cfg)
    (folder / "dataset.yaml").write_text(yaml.safe_dump(layout, sort_keys=False))
    return folder, layout


def variant(dataset, name, edit):
    """A manifest beside the dataset's, with ``edit`` applied to its layout (files stay those of the dataset)."""
    folder, layout = dataset
    document = copy.deepcopy(layout)
    edit(document)
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False))
    return path


def use_file(document, relpath):
    """Replace the second file of baseline H1H4 by ``relpath``."""
    document["metrology"]["baselines"]["H1H4"]["files"][1] = relpath


def test_a_good_dataset_says_what_the_workflow_makes_and_skips_and_exits_0(default_dataset):
    folder, _ = default_dataset
    status, lines, stderr, cpu = run_check(folder / "dataset.yaml")
    assert status == 0 and not problems(lines) and not stderr, (lines, stderr)
    assert "baseline H1H4: 2 readable file(s), 4000 frames of 80x84 pixels" in lines
    assert "star positions: 12 positions, 12 readable file(s), 192 frames of 80x84 pixels" in lines
    written = next(line for line in lines if line.startswith("the workflow would write"))
    assert "results/sim-default/" in written
    assert any(line.strip().startswith("astrometry: tables/accuracy.csv") for line in lines)
    # one wavelength and every mode configured: the chromatic mode left out unsaid, as the workflow does
    assert not any("chromatic" in line for line in lines if line.startswith("skipping"))
    assert lines[-1].startswith("no problem: 23 file(s), 17392 frames checked (headers)")
    assert cpu < SECONDS
    status, lines, _, cpu = run_check(folder / "dataset.yaml", "--data")
    assert status == 0 and not problems(lines), lines
    assert "saturated samples (masked by the steps): 0" in lines
    assert lines[-1].startswith("no problem: 23 file(s), 17392 frames checked (headers, samples and checksums)")
    assert cpu < SECONDS


def test_a_truncated_file_is_one_line(default_dataset):
    folder, _ = default_dataset
    bad = folder / "defects" / "truncated.fits"
    bad.parent.mkdir(exist_ok=True)
    shutil.copy(folder / "metrology" / "H1H4_001.fits", bad)
    os.truncate(bad, bad.stat().st_size - 3 * 80 * 84 * 2)
    status, lines, stderr, cpu = run_check(variant(default_dataset, "truncated",
                                                   lambda d: use_file(d, "defects/truncated.fits")))
    assert status == 1 and len(problems(lines)) == 1 and not stderr, (lines, stderr)  # not astropy's warning too
    assert re.fullmatch(rf"problem: {re.escape(str(bad))}: file is truncated: \d+ bytes where its header announces \d+",
                        problems(lines)[0])
    assert cpu < SECONDS


def test_a_wrong_bzero_is_one_line_with_the_value_found(default_dataset):
    folder, _ = default_dataset
    bad = folder / "defects" / "bzero.fits"
    bad.parent.mkdir(exist_ok=True)
    data = bytearray((folder / "metrology" / "H1H4_001.fits").read_bytes())
    card = data.index(b"BZERO   =")
    data[card:card + 80] = fits.Card("BZERO", 1000).image.encode()  # a program that stores samples offset by 1000
    bad.write_bytes(bytes(data))
    status, lines, _, cpu = run_check(variant(default_dataset, "bzero", lambda d: use_file(d, "defects/bzero.fits")))
    assert status == 1 and len(problems(lines)) == 1, lines
    assert problems(lines)[0].startswith(f"problem: {bad}: unsupported data type BITPIX=16, BZERO=1000; ")
    assert cpu < SECONDS


def test_a_missing_file_is_one_line(default_dataset):
    folder, _ = default_dataset
    status, lines, _, cpu = run_check(variant(default_dataset, "missing", lambda d: use_file(d, "defects/absent.fits")))
    assert status == 1 and problems(lines) == [f"problem: {folder / 'defects' / 'absent.fits'}: file not found"], lines
    assert cpu < SECONDS


def test_a_misspelt_manifest_key_is_one_line_with_the_nearest_key(default_dataset):
    def misspell(document):
        document["detector"]["saturaton"] = document["detector"].pop("saturation")

    path = variant(default_dataset, "typo", misspell)
    status, lines, _, cpu = run_check(path)
    assert status == 1 and len(problems(lines)) == 1 and len(lines) == 2, lines
    assert problems(lines)[0] == (f"problem: {path}: manifest violates dice-dataset/1 at detector.saturaton: unknown "
                                  "key; did you mean saturation? (a required key)"), lines
    assert lines[1].startswith("1 problem(s): "), lines
    assert cpu < SECONDS


def test_every_schema_problem_of_a_manifest_is_its_own_line_and_counted(default_dataset):
    """Two misspelt keys and a value of the wrong type: three lines, each naming the file and the key path (the
    right spelling of a misspelt key said, its being missing not said again), and the summary counts three."""
    def edit(document):
        document["detector"]["saturaton"] = document["detector"].pop("saturation")
        document["dark"]["fles"] = document["dark"].pop("files")
        document["detector"]["read_noise"] = "low"

    path = variant(default_dataset, "three", edit)
    status, lines, _, _ = run_check(path)
    at = f"problem: {path}: manifest violates dice-dataset/1 at"
    assert status == 1 and sorted(problems(lines)) == sorted([
        f"{at} dark.fles: unknown key; did you mean files? (a required key)",
        f"{at} detector.saturaton: unknown key; did you mean saturation? (a required key)",
        f"{at} detector.read_noise: 'low' is not of type 'number'"]), lines
    assert lines[-1].startswith("3 problem(s): "), lines


def test_data_finds_what_headers_do_not_a_checksum_that_does_not_verify(default_dataset):
    folder, _ = default_dataset
    bad = write_frames(folder / "defects" / "checksum.fits", np.full((2000, 80, 84), 1000), checksum=True)
    with open(bad, "r+b") as f:  # one sample changed after the checksum was written
        f.seek(-4000, os.SEEK_END)
        f.write(b"\x12")
    path = variant(default_dataset, "checksum", lambda d: use_file(d, "defects/checksum.fits"))
    status, lines, _, _ = run_check(path)
    assert status == 0 and not problems(lines), lines
    status, lines, _, _ = run_check(path, "--data")
    assert status == 1 and problems(lines) == [f"problem: {bad}: DATASUM does not verify: header says "
                                               f"{fits.getheader(bad)['DATASUM']}, data sums to "
                                               f"{problems(lines)[0].split('data sums to ')[1].split(' ')[0]} "
                                               "(corrupted data)"], lines


# ------------------------------------------------------------------ docs/own-data.md: another program's files


def doc_script(name="make_dataset.py"):
    """A script of docs/own-data.md, as the page prints it."""
    page = (REPO / "docs" / "own-data.md").read_text()
    block = page.split(f"<!-- begin {name}")[1].split(f"<!-- end {name} -->")[0]
    return block.split("```python\n")[1].split("```")[0]


def test_the_worked_example_turns_another_program_s_frames_into_a_dataset_the_workflow_reads(tmp_path):
    """A simulated bench's cubes written again as another program would, by docs/own-data.md's
    make_example_folder.py (one 2-D uint16 file a frame, its own folder names, frame numbers not
    zero-padded, the bench's geometry beside them); the page's make_dataset.py makes the manifest; the
    checker passes it, samples and all; and the workflow's reader streams exactly the original frames."""
    manifest_path = simulation.simulate_dataset(small_config(metrology={"spherical": True}), tmp_path / "sim")
    original = load_manifest(manifest_path)
    bench = tmp_path / "bench-2026-11-30"
    converter = tmp_path / "make_example_folder.py"
    converter.write_text(doc_script("make_example_folder.py"))
    made = subprocess.run([sys.executable, str(converter), str(manifest_path), str(bench)], capture_output=True,
                          text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    assert "for make_dataset.py:" in made.stdout and "BASELINES = {" in made.stdout
    assert (bench / "dark" / "frame_10.fits").exists()
    header = fits.getheader(bench / "dark" / "frame_1.fits")
    assert (header["NAXIS"], header["BITPIX"], header["BZERO"]) == (2, 16, 32768)

    script = tmp_path / "make_dataset.py"
    script.write_text(doc_script())
    made = subprocess.run([sys.executable, str(script), str(bench)], capture_output=True, text=True, timeout=120)
    assert made.returncode == 0, made.stderr
    status, lines, stderr, _ = run_check(bench / "dataset.yaml", "--data")
    assert status == 0 and not problems(lines) and not stderr, (lines, stderr)
    assert "baseline H1H4: 200 readable file(s), 200 frames of 40x44 pixels" in lines

    converted = load_manifest(bench / "dataset.yaml")
    assert converted.name == "bench-2026-11-30" and converted.detector.shape == original.detector.shape
    assert original.geometry is not None and converted.geometry == original.geometry  # carried by geometry.yaml
    for name in ("H1H4", "V2V4"):
        ours = np.concatenate([c.frames for c in io.FrameStream(converted.baselines[name], converted.detector)])
        theirs = np.concatenate([c.frames for c in io.FrameStream(original.baselines[name], original.detector)])
        np.testing.assert_array_equal(ours, theirs)


def test_the_checker_merges_configuration_files_at_every_depth_as_snakemake_does(tmp_path):
    """A file that changes one value deep in a section keeps the section's other values, as Snakemake's
    --configfile does: before, the checker merged one level deep and refused a sweep that lost its study."""
    from dice_core import check

    override = tmp_path / "override.yaml"
    override.write_text("sweeps: {offset_bias: {values: [1.0e-4]}}\nastrometry: {pose: {off_axis_deg: 0.5}}\n")
    config = check.workflow_config(REPO, [override])
    sweep = config["sweeps"]["offset_bias"]
    assert (sweep["study"], sweep["parameter"], sweep["values"]) == ("offset_bias", "detector.prnu_rms", [1.0e-4])
    assert config["astrometry"]["pose"]["off_axis_deg"] == 0.5 and config["astrometry"]["pose"]["distance"] == 25000
