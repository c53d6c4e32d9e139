"""``prtlab._tasks``: jobs as tasks on Python threads, one numba thread each."""

import threading
import time

import numba
import pytest

from prtlab import _tasks
from tests.conftest import two_numba_threads


def test_run_tasks_runs_large_jobs_here_and_the_others_on_one_numba_thread_each(monkeypatch):
    """``run_tasks``: the results in list order; a job with more than half the sizes runs on the caller's thread
    with every numba thread, the others on the pool with one (a job's own ``run_tasks`` one after another on its
    thread, even given ``threads``);
    an error is raised once every job ended; without ``TASKS`` or on numba's workqueue layer every job runs here."""
    two_numba_threads()
    seen = []

    def job(k, fail=False):
        seen.append((k, threading.current_thread() is threading.main_thread(), numba.get_num_threads()))
        time.sleep(0.01)
        if fail:
            raise ValueError(k)
        return k

    assert _tasks.run_tasks([lambda k=k: job(k) for k in range(4)], [10, 1, 2, 1]) == [0, 1, 2, 3]
    assert sorted(seen) == [(0, True, 2), (1, False, 1), (2, False, 1), (3, False, 1)]
    seen.clear()
    assert _tasks.run_tasks([lambda k=k: job(k) for k in range(3)]) == [0, 1, 2]
    assert sorted(seen) == [(0, False, 1), (1, False, 1), (2, False, 1)]
    nested = _tasks.run_tasks([lambda: [threading.current_thread()] + _tasks.run_tasks([threading.current_thread] * 2)
                               + _tasks.run_tasks([threading.current_thread] * 2, threads=2)] * 2)
    assert all(len(set(threads)) == 1 for threads in nested)  # the inner jobs on the outer job's thread
    ended = []

    def slow():
        time.sleep(0.05)
        ended.append(True)

    with pytest.raises(ValueError, match="1"):
        _tasks.run_tasks([lambda: job(0), lambda: job(1, fail=True), slow, lambda: job(3, fail=True)])
    assert ended == [True]
    for off in ((_tasks, "TASKS", False), (numba, "threading_layer", lambda: "workqueue")):
        monkeypatch.setattr(*off)
        seen.clear()
        assert _tasks.run_tasks([lambda k=k: job(k) for k in range(3)]) == [0, 1, 2]
        assert seen == [(0, True, 2), (1, True, 2), (2, True, 2)] and _tasks.task_threads() == 1
        monkeypatch.undo()


def test_run_ahead_runs_the_job_on_the_side_worker_on_its_thread_count(monkeypatch):
    """``run_ahead``: the job on the side worker with numba's thread count as asked, while the caller goes on; its
    error raised by the future; without ``TASKS`` or on numba's workqueue layer it runs here at once."""
    two_numba_threads()

    def job():
        return threading.current_thread() is threading.main_thread(), numba.get_num_threads()

    assert _tasks.run_ahead(job).result() == (False, 1)
    assert _tasks.run_ahead(job, threads=2).result() == (False, 2)
    assert numba.get_num_threads() == 2  # the caller's count is its own

    def fail():
        raise ValueError("inside")

    with pytest.raises(ValueError, match="inside"):
        _tasks.run_ahead(fail).result()
    for off in ((_tasks, "TASKS", False), (numba, "threading_layer", lambda: "workqueue")):
        monkeypatch.setattr(*off)
        future = _tasks.run_ahead(job)
        assert future.done() and future.result() == (True, 2)
        with pytest.raises(ValueError, match="inside"):
            _tasks.run_ahead(fail).result()
        monkeypatch.undo()
