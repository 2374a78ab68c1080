"""A dataset from someone else, run as a user would (the README's command, a copy of the repository): names
that would reach outside the results folder are refused before any job, with nothing created, changed or
deleted anywhere; every bad manifest, configuration or folder is said in one line naming the file or key.

The refusals before any job cost a Snakemake start each (3-5 s); the CI set runs one case per hostile name and
per key, two at a time, and the whole matrix is marked slow.
"""

import copy
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from conftest import REPO, copy_repository, renamed, snakemake
from dice_core import simulation

HOSTILE = ["..", ".", "../x", "ABSOLUTE", "a/b", "{x}"]
KEYS = {"name": "manifest name", "flat": "manifest flats key", "baseline": "manifest metrology.baselines key",
        "pair": "manifest metrology.pairs key"}
# every hostile name once and every key at least once, for the CI set
CI_CASES = [("name", ".."), ("flat", "."), ("baseline", "../x"), ("pair", "ABSOLUTE"), ("name", "a/b"),
            ("baseline", "{x}")]


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory):
    """A folder holding a copy of the repository (``repo``) and the ci preset's raw dataset (``data``): a
    hostile manifest's paths land inside it, where the test sees them."""
    root = tmp_path_factory.mktemp("sandbox")
    copy_repository(root / "repo")
    simulation.simulate_dataset(simulation.load_preset(REPO / "config" / "presets" / "ci.yaml"), root / "data")
    return root


def tree(root):
    """{path: (size, mtime, mode)} of every file under ``root``, and the folders (their mode only: a folder's
    time changes with Snakemake's state folder, .snakemake, which is left out)."""
    found = {}
    for folder, subfolders, names in os.walk(root):
        subfolders[:] = [d for d in subfolders if d not in (".snakemake", "__pycache__")]
        for name in subfolders:
            found[str((Path(folder) / name).relative_to(root))] = (Path(folder, name).lstat().st_mode,)
        for name in names:
            stat = (Path(folder) / name).lstat()
            found[str((Path(folder) / name).relative_to(root))] = (stat.st_size, stat.st_mtime_ns, stat.st_mode)
    return found


def run_together(workdir, argument_lists, at_once=2):
    """The README's command with each list of arguments, ``at_once`` at a time: [(exit status, what it said)]."""
    env = {**os.environ, "PYTHONPATH": str(workdir)}
    results, waiting = [], list(argument_lists)
    while waiting:
        batch, waiting = waiting[:at_once], waiting[at_once:]
        runs = [subprocess.Popen([sys.executable, "-m", "snakemake", "--cores", "2", *args], cwd=workdir, env=env,
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for args in batch]
        for run in runs:
            try:
                said, _ = run.communicate(timeout=300)
            finally:
                run.kill()
            results.append((run.returncode, said))
    return results


def dice_lines(said):
    return [line for line in said.splitlines() if line.startswith("dice: ")]


def assert_refused_in_one_line(status, said, *expected):
    """Exit status 1, one ``dice:`` line holding each of ``expected``, no traceback, no job planned."""
    lines = dice_lines(said)
    assert status == 1 and len(lines) == 1, said
    assert all(text in lines[0] for text in expected), (lines[0], expected)
    assert "Traceback" not in said and "Exception" not in said and "Job stats" not in said, said


def refuse_hostile_names(sandbox, cases):
    data, repo = sandbox / "data", sandbox / "repo"
    document = yaml.safe_load((data / "dataset.yaml").read_text())
    manifests = []
    for i, (key, name) in enumerate(cases):
        name = str(sandbox / "escaped") if name == "ABSOLUTE" else name
        manifest = data / f"hostile-{i}.yaml"
        manifest.write_text(yaml.safe_dump(renamed(document, key, name), sort_keys=False))
        manifests.append((manifest, key, name))
    before = tree(sandbox)
    results = run_together(repo, [["--config", f"dataset={manifest}"] for manifest, _, _ in manifests])
    for (manifest, key, name), (status, said) in zip(manifests, results):
        assert_refused_in_one_line(status, said, str(manifest), f"{KEYS[key]} {name!r} is not a valid name")
    assert tree(sandbox) == before  # nothing created, changed or deleted, inside the repository or beside it
    assert not (repo / "results").exists()


def test_hostile_names_are_refused_before_any_job_and_nothing_anywhere_changes(sandbox):
    """Each hostile name once, each key once at least: a baseline named ../../../../escaped-bl/H1H4 wrote
    outside the repository, one named after an existing file made Snakemake delete it, and name: .. wrote
    the run's products into the repository root."""
    refuse_hostile_names(sandbox, CI_CASES)


@pytest.mark.slow  # 24 refusals, 50-80 s on 2 cores; one per name and key runs in the CI set: pytest -m slow
def test_every_hostile_name_for_every_key_is_refused_and_nothing_anywhere_changes(sandbox):
    refuse_hostile_names(sandbox, [(key, name) for key in KEYS for name in HOSTILE])


def test_a_path_that_leaves_the_results_folder_is_refused_before_any_job_whatever_made_it(tmp_path):
    """Defence in depth: a rule whose output lies outside the results folder (nothing in the project makes
    one; the names that could are refused above) is refused before it runs, in one line."""
    repo = copy_repository(tmp_path / "repo")
    victim = tmp_path / "victim.nc"
    victim.write_text("a file of the user's")
    with open(repo / "Snakefile", "a") as snakefile:
        snakefile.write('\n\nrule escape:\n    output:\n        "../victim.nc",\n    shell:\n        "echo > {output}"\n')
    before = tree(tmp_path)
    result = snakemake(repo, "../victim.nc", "--forcerun", "escape", "--config", "dataset=ci", check=False)
    said = result.stdout + result.stderr
    assert result.returncode == 1 and dice_lines(said) == [
        "dice: ../victim.nc: a planned job would write outside this run's results folders results/sim-ci and "
        "results/sweeps; nothing was run"], said
    assert tree(tmp_path) == before and victim.read_text() == "a file of the user's"


def test_start_up_problems_are_one_line_naming_the_file_or_key(sandbox, tmp_path):
    """An empty manifest, a key given twice (in a manifest and in a configuration file), a science area too
    small for a star window, a file that is not FITS, a dataset named after the sweeps folder: one line each,
    before any job."""
    data, repo = sandbox / "data", sandbox / "repo"
    document = yaml.safe_load((data / "dataset.yaml").read_text())
    text = (data / "dataset.yaml").read_text()
    cases = {}

    def manifest(name, content):
        path = data / f"{name}.yaml"
        path.write_text(content if isinstance(content, str) else yaml.safe_dump(content, sort_keys=False))
        return path

    empty = manifest("empty", "")
    cases["empty"] = (["--config", f"dataset={empty}"], [f"{empty}: manifest is empty"])
    twice = manifest("twice", text.replace("    H2H4:\n", "    H1H4:\n", 1))
    cases["twice"] = (["--config", f"dataset={twice}"], [f"{twice}: manifest key metrology.baselines.H1H4 is "
                                                         "given twice (lines"])
    narrow = copy.deepcopy(document)
    narrow["detector"]["science_area"]["rows"] = [12, 14]
    narrow = manifest("narrow", narrow)
    cases["narrow"] = (["--config", f"dataset={narrow}"], [f"{narrow}: detector.science_area holds 2 row(s) x 39 "
                                                           "col(s), too few for the 15x15 star windows of "
                                                           "centroids.half_size 7"])
    not_fits = tmp_path / "hostname"
    not_fits.write_text("vm\n")
    foreign = copy.deepcopy(document)
    foreign["metrology"]["baselines"]["H1H4"]["files"] = [str(not_fits)]
    foreign = manifest("foreign", foreign)
    cases["foreign"] = (["--config", f"dataset={foreign}"], [f"{not_fits}: not a readable FITS file",
                                                             f"named by baseline H1H4 in {foreign}"])
    sweeps = copy.deepcopy(document)
    sweeps["name"] = "sweeps"
    sweeps = manifest("sweeps", sweeps)
    cases["sweeps"] = (["--config", f"dataset={sweeps}"], [f"{sweeps}: manifest name 'sweeps' is the results "
                                                           "folder's sweeps folder"])
    config = tmp_path / "twice.yaml"
    config.write_text("centroids:\n  half_size: 4\ncentroids:\n  half_size: 5\n")
    cases["config"] = (["--config", "dataset=ci", "--configfile", str(config)],
                       [f"{config}: key centroids is given twice (lines 1 and 3)"])
    results = run_together(repo, [args for args, _ in cases.values()])
    for (name, (_, expected)), (status, said) in zip(cases.items(), results):
        assert_refused_in_one_line(status, said, *expected)
    assert not (repo / "results").exists()


#: What Snakemake itself prints before the workflow is read, which the workflow cannot prevent (README and
#: docs/running.md, "When something is wrong"): the profile it read by itself, and the configuration file that --config extends.
SNAKEMAKE_OWN = (re.compile(r"Using workflow specific profile profiles/default for setting default command line "
                            r"arguments\."),
                 re.compile(r"Config file \S+/config/config\.yaml is extended by additional config specified via "
                            r"the command line\."))


def test_start_up_errors_are_the_one_line_and_nothing_else_the_workflow_prints(sandbox):
    """A bad dataset name, a misspelt configuration key, a manifest of another format (the value found said) and a
    misspelt manifest key (the nearest key said): the terminal shows Snakemake's own lines before the workflow is
    read, then the one dice: line, and nothing else (no header, no WorkflowError, no file and line of the
    workflow)."""
    data, repo = sandbox / "data", sandbox / "repo"
    document = yaml.safe_load((data / "dataset.yaml").read_text())
    other = data / "other-format.yaml"
    other.write_text(yaml.safe_dump({**document, "format": "dice-dataset/2"}, sort_keys=False))
    typo = copy.deepcopy(document)
    typo["detector"]["gian"] = typo["detector"].pop("gain")
    misspelt = data / "misspelt.yaml"
    misspelt.write_text(yaml.safe_dump(typo, sort_keys=False))
    cases = {
        "dataset": (["--config", "dataset=defualt"], "dice: config dataset='defualt' is neither a manifest path "
                                                     "(*.yaml) nor a simulation preset ['chromatic', 'ci', "
                                                     "'default', 'large', 'paper']"),
        "key": (["--config", "datset=ci"], "dice: config datset: unknown key; did you mean dataset? (keys of the "
                                            "config: "),
        "format": (["--config", f"dataset={other}"], f"dice: config dataset: {other}: manifest violates "
                                                     "dice-dataset/1 at format: format is 'dice-dataset/2', and this "
                                                     "version reads 'dice-dataset/1'"),
        "manifest key": (["--config", f"dataset={misspelt}"], f"dice: config dataset: {misspelt}: manifest violates "
                                                              "dice-dataset/1 at detector.gian: unknown key; did you "
                                                              "mean gain? (a required key)"),
    }
    results = run_together(repo, [args for args, _ in cases.values()])
    for (name, (_, expected)), (status, said) in zip(cases.items(), results):
        lines = said.splitlines()
        ours = [line for line in lines if not any(own.fullmatch(line) for own in SNAKEMAKE_OWN)]
        assert status == 1 and len(ours) == 1 and ours[0].startswith(expected), (name, said)
    assert not (repo / "results").exists()


def test_a_second_run_while_one_is_alive_is_told_which_and_not_to_unlock(tmp_path):
    """Snakemake's own message asks for --unlock, which would let both runs write the same products."""
    import fcntl

    repo = copy_repository(tmp_path / "repo")
    guard = repo / ".snakemake" / "dice" / "running"
    guard.parent.mkdir(parents=True)
    (repo / ".snakemake" / "locks").mkdir()
    (repo / ".snakemake" / "locks" / "0.output.lock").write_text("results/sim-ci/raw/truth.nc\n")
    with open(guard, "w") as held:  # the live run: its flock, and the line it records
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.write("vm 4242 2026-12-04T02:03:04\n")
        held.flush()
        result = snakemake(repo, "--config", "dataset=ci", check=False)
    said = result.stdout + result.stderr
    assert result.returncode == 1 and dice_lines(said) == [
        "dice: another run of this workflow is alive in this folder (pid 4242, started 2026-12-04T02:03:04) and "
        "makes some of the same files: wait for it to end, or stop it (Ctrl-C in its terminal, or kill its process "
        "group); do not use --unlock, which would let both runs write the same products"], said
    assert "--unlock argument" not in said and (repo / ".snakemake" / "locks" / "0.output.lock").is_file()


def test_a_results_folder_that_is_a_file_is_one_line_before_any_job(tmp_path):
    """What a folder that cannot be written gets (the write probe's failures are tested in test_preflight.py,
    an immutable folder in the slow test below)."""
    repo = copy_repository(tmp_path / "repo")
    (repo / "results").write_text("a file where the results folder should be")
    result = snakemake(repo, "--config", "dataset=ci", check=False)
    said = result.stdout + result.stderr
    lines = dice_lines(said)
    assert result.returncode == 1 and len(lines) == 1 and lines[0].startswith(
        f"dice: cannot write in {repo / 'results'} (a file, not a folder), where this run writes results/sim-ci"), said
    assert "Traceback" not in said


def unwritable_results(repo):
    """Make ``repo/results`` a folder nothing can be created in, even by root (chattr +i), or skip."""
    results = repo / "results"
    results.mkdir()
    if shutil.which("chattr") is None or subprocess.run(["chattr", "+i", str(results)]).returncode != 0:
        pytest.skip("chattr +i is not allowed here (needs CAP_LINUX_IMMUTABLE and an ext2-4 or xfs filesystem)")
    return results


@pytest.mark.slow  # 10 s: a DAG built; the write probe itself is tested in test_preflight.py: pytest -m slow
def test_a_results_folder_that_cannot_be_written_is_one_line_before_any_job(tmp_path):
    repo = copy_repository(tmp_path / "repo")
    results = unwritable_results(repo)
    try:
        result = snakemake(repo, "--config", "dataset=ci", check=False)
    finally:
        subprocess.run(["chattr", "-i", str(results)])
    said = result.stdout + result.stderr
    lines = dice_lines(said)
    assert result.returncode == 1 and len(lines) == 1 and lines[0].startswith(
        f"dice: cannot write in {results} (Operation not permitted), where this run writes results/sim-ci/"), said
    assert lines[0].endswith("; nothing was run") and "Traceback" not in said and not any(results.iterdir())


@pytest.mark.slow  # 10 s; needs a tmpfs mount (root, or a user namespace): pytest -m slow
def test_a_disk_too_small_for_the_simulation_is_one_line_before_any_job(tmp_path):
    """The ci preset writes 5.3 MB of cubes; a 3 MB filesystem holds the results folder."""
    repo = copy_repository(tmp_path / "repo")
    (repo / "results").mkdir()
    command = (f"mount -t tmpfs -o size=3m tmpfs results && exec {sys.executable} -m snakemake --cores 2 "
               "--config dataset=ci")
    unshare = ["unshare", "--mount"] if os.geteuid() == 0 else ["unshare", "--map-root-user", "--mount"]
    probe = subprocess.run([*unshare, "sh", "-c", "mount -t tmpfs -o size=1m tmpfs /mnt"], capture_output=True)
    if shutil.which("unshare") is None or probe.returncode != 0:
        pytest.skip(f"no tmpfs mount in a mount namespace here ({probe.stderr.decode().strip()})")
    result = subprocess.run([*unshare, "sh", "-c", command], cwd=repo, capture_output=True, text=True,
                            env={**os.environ, "PYTHONPATH": str(repo)}, timeout=300)
    said = result.stdout + result.stderr
    lines = dice_lines(said)
    assert result.returncode == 1 and len(lines) == 1, said
    assert lines[0].startswith("dice: results/sim-ci/raw: the simulation writes 5.") and "MB of cubes and the " \
        "disk lacks" in lines[0] and lines[0].endswith("nothing was run"), lines


def run_dataset(sandbox, tmp_path, edit, target):
    """The README's command on the ci dataset edited by ``edit``, for ``target`` only: (status, said)."""
    document = yaml.safe_load((sandbox / "data" / "dataset.yaml").read_text())
    edit(document)
    manifest = sandbox / "data" / f"{tmp_path.name}.yaml"
    manifest.write_text(yaml.safe_dump(document, sort_keys=False))
    repo = copy_repository(tmp_path / "repo")
    result = snakemake(repo, f"results/{document['name']}/{target}", "--config", f"dataset={manifest}", check=False)
    return result.returncode, result.stdout + result.stderr, manifest


@pytest.mark.slow  # 10 s: the dark step runs (2 idle cores, 2026-12-04): pytest -m slow
def test_a_saturation_level_below_the_data_names_the_file_and_the_key(sandbox, tmp_path):
    """It said "flat fiber_a: frame 0 has no positive signal": no file, and the wrong cause."""
    status, said, _ = run_dataset(sandbox, tmp_path, lambda d: d["detector"].update(saturation=1),
                                  "calibration/dark.nc")
    lines = dice_lines(said)
    assert status == 1 and len(lines) == 1, said
    assert lines[0].startswith(f"dice: measure_dark failed: {sandbox / 'data' / 'dark' / 'dark_000.fits'}: every "
                               "science-area sample of frame 0 (counted from 0 in this file) is at or above "
                               "detector.saturation, 1 ADU (the frame's median is "), lines
    assert "is the manifest's saturation level right?" in lines[0] and "Traceback" not in said


@pytest.mark.slow  # 25 s: the dark, flats and two fringe fits run (2 idle cores, 2026-12-04): pytest -m slow
def test_a_pair_of_parallel_baselines_names_the_manifest_and_the_pair(sandbox, tmp_path):
    """It said so inside a traceback."""
    status, said, manifest = run_dataset(sandbox, tmp_path,
                                         lambda d: d["metrology"]["pairs"].update(P14=["H1H4", "H2H4"]),
                                         "calibration/offsets_P14.nc")
    lines = dice_lines(said)
    assert status == 1 and len(lines) == 1, said
    assert lines[0].startswith(f"dice: deproject_offsets failed: {manifest}: metrology.pairs.P14 (H1H4 and H2H4): "
                               "wavevectors ("), lines
    assert "degrees from colinear; a pair needs at least 12 degrees to separate x from y" in lines[0]
    assert "Traceback" not in said
