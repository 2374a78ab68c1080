"""Worker processes and BLAS threads of the streaming reductions.

The per-chunk products of a streaming pass are small (3 to 7 columns over a
cache-sized chunk): one BLAS thread per process is fastest, and two or more
threads per process on a machine whose cores are already busy with worker
processes slow a pass down many times (issue 10's measurement: a fringe fit
of 200,000 frames in two workers took 3.9 s with one BLAS thread each and
34.9 s with two; through Snakemake, which set two, the job took 27.5 s, and
3.3-3.5 s once the library set one: BENCHMARKS.md). The thread count cannot be left to the environment:
Snakemake sets ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` and
``MKL_NUM_THREADS`` to a rule's ``threads`` before a step starts, and a user's
shell may set anything. So the reductions set it themselves, at run time, with
threadpoolctl (:func:`one_blas_thread`), in the calling process and in every
worker; a rule's ``threads`` become worker processes instead.

A reduction's stream is always cut into the same :data:`LANES` consecutive
parts (groups of whole files) whose results are summed in lane order, so that
a product does not depend on how many processes reduced it.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import itertools
import multiprocessing

import threadpoolctl

__all__ = ["LANES", "one_blas_thread", "blas_threads", "lane_executor", "lane_workers", "map_lanes", "inherited",
           "threads_report"]

#: Consecutive parts a :class:`dice_core.io.FrameStream` is reduced in.
LANES = 2


def one_blas_thread(function):
    """Decorator: ``function`` runs with one BLAS thread, whatever the environment says.

    Applies to every BLAS library loaded in the process (numpy's and scipy's
    OpenBLAS, MKL...); the previous setting is restored when it returns.
    """
    @functools.wraps(function)
    def with_one_blas_thread(*args, **kwargs):
        with threadpoolctl.threadpool_limits(limits=1, user_api="blas"):
            return function(*args, **kwargs)

    return with_one_blas_thread


def blas_threads() -> int:
    """Largest thread count of the BLAS libraries loaded in this process now (1 if none is loaded)."""
    counts = [lib["num_threads"] for lib in threadpoolctl.threadpool_info() if lib["user_api"] == "blas"]
    return max(counts, default=1)


def lane_workers(workers: int, n_lanes: int) -> int:
    """Worker processes used for ``n_lanes`` lanes: no more than lanes, and one where processes cannot fork."""
    return max(1, min(workers, n_lanes)) if "fork" in multiprocessing.get_all_start_methods() else 1


def _start_worker():
    # A forked worker inherits its parent's BLAS setting, but set it again: the parent may
    # not be inside one_blas_thread, and the setting must not depend on the caller.
    threadpoolctl.threadpool_limits(limits=1, user_api="blas")


def lane_executor(workers: int, n_lanes: int):
    """Worker processes for the lanes of a pass, each with one BLAS thread; or a context holding None.

    Processes, not threads: the per-chunk work is a series of numpy calls too
    short for two threads to overlap under the interpreter lock (measured: two
    threads 1.0-1.1x as fast as one, two processes 1.7-1.9x; BENCHMARKS.md).
    Forked, so that the workers start in milliseconds with everything imported.
    With one worker the lanes run in the calling process (None).
    """
    n = lane_workers(workers, n_lanes)
    if n > 1:
        return concurrent.futures.ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork"),
                                                      initializer=_start_worker)
    return contextlib.nullcontext(None)


#: The values handed to forked workers through :func:`inherited`, by key: a worker forked while one is here
#: has it in its own (copy-on-write) copy of this dictionary.
_INHERITED: dict = {}
_KEYS = itertools.count()


class _Inherited:
    """A key of :data:`_INHERITED`: what :func:`map_lanes` sends a worker in place of the value (a few bytes)."""

    def __init__(self, key: int):
        self.key = key


def _resolved(value):
    """``value``, or the value an :class:`_Inherited` handle stands for in this process."""
    if not isinstance(value, _Inherited):
        return value
    try:
        return _INHERITED[value.key]
    except KeyError:
        raise RuntimeError("a worker process was forked before the value it was handed through "
                           "parallel.inherited(): make its executor inside that block") from None


@contextlib.contextmanager
def inherited(value):
    """``value`` as an argument of :func:`map_lanes` that worker processes forked inside this block read from
    their parent's memory (copy-on-write: shared pages, not one more copy a worker) instead of a pickled copy
    each; yields the handle to pass. For large read-only values (per-pixel arrays): the workers see the value
    as it was when they were forked, so it must not change inside the block. The executor must be made
    (:func:`lane_executor`) inside the block, as its workers are forked when it is first used: a pool that
    outlives one block (the fit's, reused across passes) cannot take a value this way."""
    key = next(_KEYS)
    _INHERITED[key] = value
    try:
        yield _Inherited(key)
    finally:
        del _INHERITED[key]


class WorkerDied(RuntimeError):
    """A worker process of :func:`map_lanes` ended without its result: most often killed (by the out-of-memory
    killer, a signal), which a user meets; also a crash in native code or a worker that could not start. Said
    in one line (:func:`dice_core.known_error`) with the pool's own message."""


def map_lanes(executor, function, lanes, *shared):
    """``function(lane, *shared)`` for each lane, in lane order: in the executor's processes, or here if None.
    A shared value may be an :func:`inherited` handle: the function gets the value.

    The files' SHA-256 a worker took while streaming its lane (:class:`dice_core.io.FrameStream`) come back
    to this process with the results, so that the products' provenance does not read the files again.
    """
    if executor is None:
        shared = [_resolved(value) for value in shared]
        return [function(lane, *shared) for lane in lanes]
    from dice_core import io  # here: io's imports are not this module's to pay for

    n = len(lanes)
    results = []
    try:
        for result, digests in executor.map(_lane_with_digests, [function] * n, lanes,
                                            *[[value] * n for value in shared]):
            io.remember_digests(digests)
            results.append(result)
    except concurrent.futures.BrokenExecutor as exc:  # the pool's BrokenProcessPool: it names no cause
        raise WorkerDied(
            f"a worker process ended abruptly while the job's {n} part(s) were read (most often killed by the "
            "system for lack of memory: give the job more memory, or read with one worker: --set-threads "
            f"<rule>=1): {exc}") from exc
    return results


def _lane_with_digests(function, lane, *shared):
    """In a worker process: ``function(lane, *shared)`` and the files' digests the worker knows."""
    from dice_core import io

    return function(lane, *[_resolved(value) for value in shared]), io.known_digests()


def threads_report(executor, lane_threads) -> str:
    """The log's account of the BLAS threads: this process's, and each lane process's (``lane_threads``)."""
    if executor is None:
        return f"BLAS threads: {blas_threads()} in this process, which reads the parts itself"
    return (f"BLAS threads: {blas_threads()} in this process, {', '.join(map(str, lane_threads))} "
            "in the processes that read the parts")
