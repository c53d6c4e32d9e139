"""The frame's work as tasks on numba's threads (``prtlab._tasks``): the same results bit for bit."""

import numpy as np

from prtlab import _tasks
from tests.conftest import two_numba_threads


def test_task_frames_equal_serial_frames(monkeypatch):
    """The benchmark's frame of the pipeline's defaults with the ground (``_default_frame``: the ground's rays in
    chunks, the objects' direct light against the other objects' meshes, the first pass's ground transfer) at 4,000
    receivers, with ``TASKS`` (each chunk, occluder or block a task on one numba thread) and without: every
    object's direct and indirect light and the ground's equal bit for bit, and the frame ran tasks."""
    from prtlab import bench
    from prtlab.spherelights import _ground, _groundrays, _meshdirect, _passes

    two_numba_threads()
    bench._discover()  # registers the cases, as prtlab bench does
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

    two_numba_threads()

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
        pre.frame_reuse.clear()  # every ray cast again under this setting (not the other setting's kept results)
        state = FrameState.from_scene(scene)
        out = [pre.shade(state, bounces=1), pre.shade(state, bounces=2)]
        state.transforms["ball"] = Transform(translate=[0.1, 0.5, 0.0])
        out.append(pre.shade(state, bounces=1))
        frames[tasks] = out
    for a, b in zip(frames[False], frames[True], strict=True):
        for name in a.total:
            for part in ("direct", "indirect", "total"):
                assert np.array_equal(getattr(a, part)[name], getattr(b, part)[name]), (name, part)
