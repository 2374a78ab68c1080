"""BLAS threads and worker processes: the reductions set their own, whatever the environment says."""

import multiprocessing
import os
import subprocess
import sys

import numpy as np
import pytest
import threadpoolctl

from dice_core import parallel


def two_blas_threads():
    """BLAS at two threads, or a skip where the library runs one only (a single-core machine)."""
    limits = threadpoolctl.threadpool_limits(limits=2, user_api="blas")
    if parallel.blas_threads() < 2:
        limits.restore_original_limits()
        pytest.skip("BLAS cannot run two threads here")
    return limits


def test_one_blas_thread_inside_and_the_setting_restored_after():
    with two_blas_threads():
        before = parallel.blas_threads()
        assert before == 2
        inside = parallel.one_blas_thread(parallel.blas_threads)()
        assert inside == 1
        assert parallel.blas_threads() == before


def _worker_threads(_):
    return parallel.blas_threads()


@pytest.mark.skipif(parallel.lane_workers(2, 2) < 2, reason="processes cannot be forked here")
def test_worker_processes_run_one_blas_thread_when_the_parent_runs_two():
    with two_blas_threads():
        with parallel.lane_executor(2, parallel.LANES) as executor:
            assert list(executor.map(_worker_threads, range(4))) == [1, 1, 1, 1]


def test_lane_workers_never_exceed_lanes():
    assert parallel.lane_workers(8, 2) <= 2
    assert parallel.lane_workers(1, 2) == 1
    assert parallel.lane_workers(0, 2) == 1
    with parallel.lane_executor(1, 2) as executor:
        assert executor is None


def test_the_environment_does_not_set_the_threads_of_a_fit():
    """As under Snakemake: OPENBLAS_NUM_THREADS=2 set before numpy loads; the decorated step runs one."""
    code = ("import numpy, dice_core.parallel as p; "
            "print(p.blas_threads(), p.one_blas_thread(p.blas_threads)())")
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2", "OMP_NUM_THREADS": "2", "MKL_NUM_THREADS": "2"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    environment_threads, step_threads = out.split()
    if environment_threads != "2":
        pytest.skip("BLAS cannot run two threads here")
    assert step_threads == "1"


def _lane_plus_sum(lane, values):
    return lane + int(values.sum())


def test_an_inherited_value_reaches_forked_workers_without_a_pickle():
    """parallel.inherited: map_lanes sends a worker a handle of a few bytes, and the function gets the value, in
    the pool's forked processes as in this one; a pool forked before the value was handed is an error that says
    so, not a wrong value."""
    import pickle

    values = np.arange(100_000.0)
    with parallel.inherited(values) as handle, parallel.lane_executor(2, 2) as executor:
        assert len(pickle.dumps(handle)) < 100 < values.nbytes
        expected = [lane + int(values.sum()) for lane in (1, 2)]
        assert parallel.map_lanes(executor, _lane_plus_sum, [1, 2], handle) == expected
        assert parallel.map_lanes(None, _lane_plus_sum, [1, 2], handle) == expected
    if "fork" not in multiprocessing.get_all_start_methods():
        return
    with parallel.lane_executor(2, 2) as executor:
        parallel.map_lanes(executor, _lane_plus_sum, [1, 2], values)  # its workers forked now
        with parallel.inherited(values) as late, pytest.raises(RuntimeError, match="forked before"):
            parallel.map_lanes(executor, _lane_plus_sum, [1, 2], late)


def _killed(lane):
    """A lane whose worker is killed outright (as by the out-of-memory killer)."""
    import os
    import signal

    if lane == 1:
        os.kill(os.getpid(), signal.SIGKILL)
    return lane


def test_a_worker_killed_outright_is_one_line_naming_the_likely_cause():
    """A worker killed by the system (SIGKILL: the out-of-memory killer) gave a bare BrokenProcessPool and its
    traceback; it is now a WorkerDied, a known error (one line from run_logged) saying what to do."""
    import dice_core

    with parallel.lane_executor(2, 2) as executor:
        with pytest.raises(parallel.WorkerDied) as info:
            parallel.map_lanes(executor, _killed, [0, 1])
    assert dice_core.known_error(info.value)
    line = dice_core.error_line(info.value)
    assert "worker process ended abruptly" in line and "lack of memory" in line and "--set-threads" in line
