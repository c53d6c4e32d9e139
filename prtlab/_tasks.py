"""Independent jobs as tasks on Python threads, each thread's numba kernels on one numba thread.

A frame's small parallel kernels leave threads idle at each region's end, and its Python between kernels runs on
one core. Run as tasks on as many Python threads as numba has threads (each with numba's thread count 1), one
job's Python overlaps the others' kernels (kernels that release the GIL: ``nogil=True``) and no region waits for
its slowest thread. Jobs must write only their own outputs (or disjoint parts of shared ones): the results are then
those of running them one after another, bit for bit.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as futures_wait

import numba

#: Whether :func:`run_tasks` runs its jobs as tasks (False: one after another on the caller's thread).
TASKS = True

_POOLS: dict = {}  # (process id, threads or "side") -> ThreadPoolExecutor
_WORKER = threading.local()  # .task: this thread is a pool's


def _start_worker() -> None:
    numba.set_num_threads(1)
    _WORKER.task = True


def concurrent_kernels() -> bool:
    """Whether numba's threading layer runs parallel kernels launched from several threads at once (OpenMP, TBB;
    its ``workqueue`` aborts the process). False before a parallel kernel has chosen the layer."""
    try:
        return numba.threading_layer() != "workqueue"
    except ValueError:  # not chosen yet
        return False


def pool(threads: int) -> ThreadPoolExecutor:
    """The kept pool of ``threads`` threads of this process (made on first use; a forked child makes its own), each
    with numba's thread count 1; a job on it that calls :func:`run_tasks` runs its jobs on its own thread."""
    key = (os.getpid(), int(threads))
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(max_workers=key[1], thread_name_prefix="prtlab-task",
                                         initializer=_start_worker)
    return _POOLS[key]


def side_worker() -> ThreadPoolExecutor:
    """The kept single thread of this process for one part of a frame that overlaps the caller's (made on first
    use; a forked child makes its own). Unlike a :func:`pool`'s threads it keeps numba's thread count as it is: a job
    sets the count it needs. Kept so that its OpenMP team is too."""
    key = (os.getpid(), "side")
    if key not in _POOLS:
        _POOLS[key] = ThreadPoolExecutor(max_workers=1, thread_name_prefix="prtlab-side")
    return _POOLS[key]


def run_ahead(job, threads: int = 1) -> Future:
    """``job()`` started on :func:`side_worker` with numba's thread count ``threads`` there, to overlap what the
    caller does next (its Python and kernels); the future of its result. Without :data:`TASKS` or concurrent kernels
    (:func:`concurrent_kernels`) the job runs here at once. The caller must wait for the future before it returns
    (also when it raises), and the job must write nothing the caller reads or writes meanwhile."""
    future = Future()
    if not (TASKS and concurrent_kernels()):
        try:
            future.set_result(job())
        except Exception as error:  # raised by future.result(), as from the side worker
            future.set_exception(error)
        return future

    def run():
        numba.set_num_threads(threads)
        return job()

    return side_worker().submit(run)


def on_pool() -> bool:
    """Whether this thread is one of a :func:`pool`'s."""
    return getattr(_WORKER, "task", False)


def task_threads() -> int:
    """The threads :func:`run_tasks` would use here: numba's thread count of the caller (1: no tasks), or 1 when
    :data:`TASKS` is off."""
    return numba.get_num_threads() if TASKS and concurrent_kernels() else 1


def run_tasks(jobs, sizes=None, threads: int | None = None) -> list:
    """``[job() for job in jobs]``. With :data:`TASKS`, more than one thread and more than one job (and numba's
    threading layer OpenMP or TBB, chosen: its ``workqueue`` aborts on concurrent kernels), a job whose
    ``size`` is more than ``1 / threads`` of their sum runs first on the caller's thread (its kernels on the caller's
    numba threads), then the others on a kept pool of ``threads`` threads (numba's thread count 1 in each): largest
    first, or in list order without ``sizes``. ``threads``: default numba's thread count of the caller (a caller
    that runs its own kernels on one thread may pass the count it had before). Every job has ended when this returns
    (the first job's error in list order is raised). A job calling this runs its jobs one after another on its own
    thread (a pool's thread waiting for the pool could leave none to run them)."""
    threads = numba.get_num_threads() if threads is None else int(threads)
    if not TASKS or threads < 2 or len(jobs) < 2 or on_pool() or not concurrent_kernels():
        return [job() for job in jobs]
    futures = [Future() for _ in jobs]
    order = list(range(len(jobs)))
    if sizes is not None:
        total = sum(sizes)
        for k in [k for k in order if sizes[k] * threads > total]:
            try:
                futures[k].set_result(jobs[k]())
            except Exception as error:  # raised below, in list order, once every job has ended
                futures[k].set_exception(error)
        order.sort(key=lambda k: -sizes[k])
    for k in order:
        if not futures[k].done():
            futures[k] = pool(threads).submit(jobs[k])
    futures_wait(futures)
    return [future.result() for future in futures]
