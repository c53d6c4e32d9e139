"""Benchmarks of prtlab.geometry.RayCaster: rays per second on a ~100k-triangle scene.

Scene: five icospheres of 20,480 triangles (102,400 in all) in a row, one
Embree geometry each; rays start in a box around them with uniform random
directions (about a quarter hit).

* ``raycast.closest_hit`` / ``raycast.occluded``: the default engine (Embree 4
  called from a numba ``prange`` kernel, the run's threads) against trimesh's own
  Embree wrapper (``trimesh.ray.ray_pyembree.RayMeshIntersector``, through
  embreex) on the same triangles merged into one mesh. It returns less per ray
  (only the triangle index for ``intersects_first``, a bool for
  ``intersects_any``); ours returns object, triangle, barycentrics, distance,
  unit normal and hit point.
* ``raycast.vs_embreex.*``: the same queries against ``method="embreex"``
  (the same library, float32 rays and outputs, traced under the GIL on one
  core): the same work exactly.
* ``raycast.threads.*``: the default engine on two threads against itself on
  one (``numba.set_num_threads``), interleaved; ``peer / ours`` is the speed-up
  of the second core. ``info`` gives both throughputs, the CPU time over the wall
  time of the two-thread calls (2 when both cores traced throughout), the share
  of that CPU time spent by the busiest thread (0.5 when the work was split
  evenly) and the CPU time per call on two threads over one (1 when the second
  thread costs nothing; the speed-up on two idle cores is then about
  ``2 / cpu_2_over_1``). On a machine shared with other sessions (Linux's
  autogroup gives each session an equal slice, however many threads it runs)
  the wall-time ratio falls toward 1 while the CPU figures still show two
  threads tracing.
"""

from __future__ import annotations

import os
import time

import numba
import numpy as np
import trimesh

from prtlab.bench import case
from prtlab.geometry import RayCaster


def _scene():
    spheres = []
    for k in range(5):
        s = trimesh.creation.icosphere(subdivisions=5)
        s.apply_translation([2.5 * (k - 2), 0.0, 0.0])
        spheres.append(s)
    return spheres


def _rays(n: int):
    rng = np.random.default_rng(7)
    origins = rng.uniform([-7.0, -2.0, -2.0], [7.0, 2.0, 2.0], size=(n, 3))
    dirs = rng.normal(size=(n, 3))
    return origins, dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def _trimesh_peer(spheres):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError:  # pragma: no cover - embreex is a dependency
        return None
    return RayMeshIntersector(trimesh.util.concatenate(spheres))


def _ray_case(quick: bool, query: str, peer_query: str | None) -> dict:
    """1M rays (quick: 100k) against the ~100k-triangle scene; the peer is trimesh's ``peer_query``, or
    ``method="embreex"`` when ``peer_query`` is None."""
    spheres = _scene()
    caster = RayCaster(spheres)
    n = 100_000 if quick else 1_000_000
    origins, dirs = _rays(n)
    fn = getattr(caster, query)
    if peer_query is None:
        peer = (f"RayCaster.{query}(method='embreex')", lambda: fn(origins, dirs, method="embreex"))
    else:
        intersector = _trimesh_peer(spheres)
        peer = None if intersector is None else (
            f"trimesh RayMeshIntersector.{peer_query}", lambda: getattr(intersector, peer_query)(origins, dirs))
    return {"run": lambda: fn(origins, dirs), "gflop": None, "items": n, "peer": peer}


@case("raycast.closest_hit.100k_tris")
def closest_hit_case(quick: bool) -> dict:
    return _ray_case(quick, "closest_hit", "intersects_first")


@case("raycast.occluded.100k_tris")
def occluded_case(quick: bool) -> dict:
    return _ray_case(quick, "occluded", "intersects_any")


@case("raycast.vs_embreex.closest_hit.100k_tris")
def closest_hit_vs_embreex_case(quick: bool) -> dict:
    return _ray_case(quick, "closest_hit", None)


@case("raycast.vs_embreex.occluded.100k_tris")
def occluded_vs_embreex_case(quick: bool) -> dict:
    return _ray_case(quick, "occluded", None)


def _thread_cpu() -> dict[str, float]:
    """CPU seconds of each thread of this process (Linux ``/proc``; empty elsewhere)."""
    ticks = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    out = {}
    try:
        tasks = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tasks:
        try:
            with open(f"/proc/self/task/{tid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[tid] = (int(fields[11]) + int(fields[12])) / ticks  # utime + stime
    return out


def _threads_case(quick: bool, query: str) -> dict:
    """The default engine on 2 threads (ours) and on 1 (peer); the info fills in while the case runs."""
    caster = RayCaster(_scene())
    n = 200_000 if quick else 1_000_000
    origins, dirs = _rays(n)
    fn = getattr(caster, query)
    two = min(2, numba.config.NUMBA_NUM_THREADS)
    info: dict = {"threads": two}
    walls = {1: [], 2: []}
    cpu_per_call = {1: [], 2: []}
    cpu = {"process": 0.0, "wall": 0.0, "threads": {}}

    def timed(threads: int):
        previous = numba.get_num_threads()
        numba.set_num_threads(min(threads, two))
        before, t0, p0 = _thread_cpu(), time.perf_counter(), time.process_time()
        try:
            fn(origins, dirs)
        finally:
            wall, spent = time.perf_counter() - t0, time.process_time() - p0
            numba.set_num_threads(previous)
        walls[threads].append(wall)
        cpu_per_call[threads].append(spent)
        if walls[1] and walls[2]:
            info["cpu_2_over_1"] = float(np.median(cpu_per_call[2]) / np.median(cpu_per_call[1]))
        if threads == 2:
            cpu["process"] += spent
            cpu["wall"] += wall
            for tid, seconds in _thread_cpu().items():
                cpu["threads"][tid] = cpu["threads"].get(tid, 0.0) + seconds - before.get(tid, 0.0)
            busy = sorted(cpu["threads"].values(), reverse=True)
            info["cpu_per_wall_2"] = cpu["process"] / cpu["wall"]
            if busy and sum(busy) > 0:
                info["busiest_thread_share_2"] = busy[0] / sum(busy)
        for k in (1, 2):
            if walls[k]:
                info[f"rays_per_s_{k}"] = n / float(np.median(walls[k]))

    return {"run": lambda: timed(2), "gflop": None, "items": n,
            "peer": (f"RayCaster.{query} on 1 thread", lambda: timed(1)), "info": info}


@case("raycast.threads.closest_hit.100k_tris")
def threads_closest_hit_case(quick: bool) -> dict:
    return _threads_case(quick, "closest_hit")


@case("raycast.threads.occluded.100k_tris")
def threads_occluded_case(quick: bool) -> dict:
    return _threads_case(quick, "occluded")
