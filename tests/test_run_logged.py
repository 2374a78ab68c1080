"""dice_core.run_logged: what a workflow step's failure shows in the terminal and leaves in its log."""

import errno
import logging

import pytest

from dice_core import DatasetError, error_line, known_error, parallel, run_logged
from dice_core.centroids import WindowError
from dice_core.fringes import FringeError


@pytest.fixture(autouse=True)
def restore_logging():
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield
    for handler in root.handlers:
        if handler not in handlers:
            handler.close()
    root.handlers[:], root.level = handlers, level


def raise_in_a_worker(lane):
    raise FringeError(f"baseline H1H4: no fringe contrast in lane {lane}")


def fail_in_workers():
    with parallel.lane_executor(2, 2) as executor:
        parallel.map_lanes(executor, raise_in_a_worker, [0, 1])


def bad_file():
    raise DatasetError("raw/dark_000.fits", "frames are 40x45 (rows x cols) but the detector is 24x28")


def full_disk():
    raise OSError(errno.ENOSPC, "No space left on device", "results/sim-ci/calibration/dark.nc")


@pytest.mark.parametrize("step, line", [
    (bad_file, "dice: bad_file failed: raw/dark_000.fits: frames are 40x45 (rows x cols) but the detector is 24x28"),
    (fail_in_workers, "dice: fail_in_workers failed: baseline H1H4: no fringe contrast in lane 0"),
    (full_disk, "dice: full_disk failed: results/sim-ci/calibration/dark.nc: No space left on device"),
])
def test_a_known_error_is_one_line_on_stderr_and_its_traceback_in_the_log(tmp_path, capsys, step, line):
    log = tmp_path / "step.log"
    with pytest.raises(SystemExit) as info:
        run_logged(log, step)
    assert info.value.code == 1
    err = capsys.readouterr().err
    assert err == f"{line} (traceback in {log})\n"  # one line, once: no traceback, no worker's traceback
    text = log.read_text()
    assert "step failed" in text and "Traceback (most recent call last)" in text and line.rsplit(": ", 1)[1] in text


def test_a_bug_keeps_its_traceback(tmp_path, capsys):
    def buggy():
        return {}["missing"]

    with pytest.raises(KeyError):
        run_logged(tmp_path / "step.log", buggy)
    assert "Traceback" in (tmp_path / "step.log").read_text()


def test_known_errors_are_dice_core_s_own_and_os_errors():
    assert known_error(WindowError("star 1 at position 3: ...")) and known_error(FileNotFoundError(2, "gone", "a"))
    assert not known_error(ValueError("a bug")) and not known_error(ZeroDivisionError())
    assert error_line(DatasetError("a.fits", "two\nlines")) == "a.fits: two lines"


@pytest.mark.skipif(not __import__("os").path.exists("/dev/full"), reason="needs /dev/full")
def test_a_log_on_a_full_disk_leaves_the_error_one_line_and_says_so(capsys):
    """Writing to /dev/full fails with ENOSPC, as a log on a full disk does: logging's own traceback for
    each record it cannot write would bury the one line."""
    with pytest.raises(SystemExit):
        run_logged("/dev/full", full_disk)
    assert capsys.readouterr().err == ("dice: full_disk failed: results/sim-ci/calibration/dark.nc: No space left "
                                       "on device (its log /dev/full could not be written: No space left on device)\n")


def test_a_log_folder_that_cannot_be_written_is_one_line(tmp_path, capsys):
    (tmp_path / "logs").write_text("a file where the folder should be")
    with pytest.raises(SystemExit):
        run_logged(tmp_path / "logs" / "step.log", bad_file)
    assert capsys.readouterr().err == f"dice: bad_file failed: {tmp_path / 'logs' / 'step.log'}: Not a directory\n"
