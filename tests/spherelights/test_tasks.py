"""The frame's work as tasks on numba's threads (``prtlab._tasks``): the same results bit for bit."""

import threading
import time

import numba
import numpy as np
import pytest

from prtlab import _tasks


@numba.njit(parallel=True)
def _count(x):
    for i in numba.prange(x.shape[0]):
        x[i] = i


def _two_numba_threads():
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs 2 numba threads (one core here)")
    numba.set_num_threads(2)
    _count(np.zeros(4))  # a parallel kernel chooses numba's threading layer
    if numba.threading_layer() == "workqueue":
        pytest.skip("numba's workqueue layer: no tasks")


def test_run_tasks_runs_large_jobs_here_and_the_others_on_one_numba_thread_each(monkeypatch):
    """``run_tasks``: the results in list order; a job with more than half the sizes runs on the caller's thread
    with every numba thread, the others on the pool with one (a job's own ``run_tasks`` one after another on its
    thread, even given ``threads``);
    an error is raised once every job ended; without ``TASKS`` or on numba's workqueue layer every job runs here."""
    _two_numba_threads()
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


def test_task_frames_equal_serial_frames(monkeypatch):
    """The benchmark's frame of the pipeline's defaults with the ground (``_default_frame``: the ground's rays in
    chunks, the objects' direct light against the other objects' meshes, the first pass's ground transfer) at 4,000
    receivers, with ``TASKS`` (each chunk, occluder or block a task on one numba thread) and without: every
    object's direct and indirect light and the ground's equal bit for bit, and the frame ran tasks."""
    from prtlab import bench
    from prtlab.benchmarks import bench_spherelights  # noqa: F401  (registers the cases)
    from prtlab.spherelights import _ground, _groundrays, _meshdirect, _passes

    _two_numba_threads()
    spec = bench._CASES["spherelights.frame.per_object_ground_near.21k"](True)
    calls = []
    run_tasks = _tasks.run_tasks

    def counted(jobs, sizes=None, threads=None):
        if _tasks.TASKS:
            calls.append(len(jobs))
        return run_tasks(jobs, sizes, threads)

    for module in (_ground, _groundrays, _meshdirect, _passes):
        monkeypatch.setattr(module, "run_tasks", counted)
    frames = {}
    for tasks in (False, True, False, True):
        monkeypatch.setattr(_tasks, "TASKS", tasks)
        frames.setdefault(tasks, []).append(spec["run"]())
    assert len(calls) >= 4 and min(calls) > 1  # chunks, occluders, blocks of the ground's transfer, receivers
    serial, tasks = frames[False], frames[True]
    assert len(serial[0]) == 8  # the ground and 7 objects
    for a, b in zip(serial + serial, tasks + tasks[::-1]):
        for (direct_a, indirect_a), (direct_b, indirect_b) in zip(a, b, strict=True):
            assert np.array_equal(direct_a, direct_b)
            assert np.array_equal(indirect_a, indirect_b)


def test_task_pipeline_frames_equal_serial_frames(monkeypatch):
    """``SphereLights.shade`` (the defaults: the ground's rays, the objects against the others' meshes) of a ground
    with three objects, one and two bounces and an object moved: the same results with ``TASKS`` and without."""
    from prtlab.pipeline import FrameState
    from prtlab.scene import Scene, Transform
    from prtlab.spherelights import SphereLights

    _two_numba_threads()

    def thing(name, mesh, translate, albedo):
        return {"name": name, "mesh": mesh, "transform": {"translate": translate},
                "material": {"type": "diffuse", "albedo": albedo}, "dynamic": True}

    scene = Scene.from_dict({
        "objects": [
            {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [40, 40]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            thing("ball", {"builtin": "icosphere", "radius": 0.5, "subdivisions": 3}, [0.3, 0.5, -0.2], [0.8, 0.3, 0.2]),
            thing("box", {"builtin": "box", "size": [0.6, 0.6, 0.6], "subdivisions": 2}, [-0.9, 0.3, 0.4],
                  [0.3, 0.6, 0.8]),
            thing("small", {"builtin": "icosphere", "radius": 0.3, "subdivisions": 2}, [0.8, 0.3, 0.9], [0.5, 0.5, 0.2]),
        ],
        "lights": [{"type": "environment", "constant": [1.0, 0.9, 0.8]}],
    })
    pre = SphereLights.precompute(scene, {"n_spheres": 2, "fit_resolution": 16}, cache=False, progress=False)
    frames = {}
    for tasks in (False, True):
        monkeypatch.setattr(_tasks, "TASKS", tasks)
        state = FrameState.from_scene(scene)
        out = [pre.shade(state, bounces=1), pre.shade(state, bounces=2)]
        state.transforms["ball"] = Transform(translate=[0.1, 0.5, 0.0])
        out.append(pre.shade(state, bounces=1))
        frames[tasks] = out
    for a, b in zip(frames[False], frames[True], strict=True):
        for name in a.total:
            for part in ("direct", "indirect", "total"):
                assert np.array_equal(getattr(a, part)[name], getattr(b, part)[name]), (name, part)
