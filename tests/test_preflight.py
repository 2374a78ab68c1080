"""dice_core.preflight: what a run checks before any job (workflow/rules/preflight.smk runs it)."""

import os
import shutil
import subprocess

import pytest

from dice_core import preflight


def test_paths_that_leave_the_results_folders_lexically_are_found(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    roots = ["results/sim-ci", "results/sweeps"]
    inside = ["results/sim-ci/metrology/H1H4.nc", "results/sweeps/a/p~1/point.nc",
              "results/sim-ci/x/../calibration/dark.nc", str(tmp_path / "results/sim-ci/figures/a.png")]
    outside = ["results/sim-ci/metrology/../../../../escaped-bl/H1H4.nc", "results/H1H4.nc",
               "results/sim-ci", "results/sim-cix/a.nc", "/etc/victim.nc", "benchmarks/fit.tsv",
               "results/sweeps/../sim-other/a.nc"]
    assert preflight.paths_outside(inside + outside + outside[:1], roots) == outside


def test_a_results_folder_linked_to_another_disk_is_still_the_results_folder(tmp_path, monkeypatch):
    (tmp_path / "disk").mkdir()
    monkeypatch.chdir(tmp_path)
    os.symlink(tmp_path / "disk", "results")
    assert preflight.paths_outside(["results/sim-ci/a.nc"], ["results/sim-ci"]) == []


def test_a_folder_that_cannot_be_written_is_found_by_trying(tmp_path):
    (tmp_path / "ok").mkdir()
    (tmp_path / "file").write_text("")
    problems = preflight.unwritable_folders([tmp_path / "ok", tmp_path / "ok/new/deeper", tmp_path / "file/sub"])
    assert problems == {str(tmp_path / "file"): ("a file, not a folder", [str(tmp_path / "file/sub")])}
    assert sorted(p.name for p in (tmp_path / "ok").iterdir()) == []  # the probe left nothing


def chattr(flag, path):
    if shutil.which("chattr") is None:
        return False
    return subprocess.run(["chattr", flag, str(path)], capture_output=True).returncode == 0


def test_an_immutable_folder_is_unwritable_even_for_root(tmp_path):
    """A permission check (os.access) says yes to root; the probe creates a file for real."""
    locked = tmp_path / "results"
    locked.mkdir()
    if not chattr("+i", locked):
        pytest.skip("chattr +i is not allowed here (needs CAP_LINUX_IMMUTABLE and an ext2-4 or xfs filesystem)")
    try:
        problems = preflight.unwritable_folders([locked / "sim-ci/calibration", locked / "sim-ci/figures"])
    finally:
        chattr("-i", locked)
    assert problems == {str(locked): ("Operation not permitted",
                                      [str(locked / "sim-ci/calibration"), str(locked / "sim-ci/figures")])}


def test_disk_shortfall_and_sizes(tmp_path):
    free = shutil.disk_usage(tmp_path).free
    assert preflight.disk_shortfall(tmp_path / "not/yet", 1000) == 0
    assert preflight.disk_shortfall(tmp_path, free + 10**9) == pytest.approx(10**9, abs=10**8)
    assert [preflight.size_text(n) for n in (512, 5.3e6, 11e9, 2.5e12)] == ["0.512 kB", "5.3 MB", "11 GB", "2.5 TB"]
