"""Benchmarks of prtlab.geometry.RayCaster: rays per second on a ~100k-triangle scene.

Scene: five icospheres of 20,480 triangles (102,400 in all) in a row, one
Embree geometry each; rays start in a box around them with uniform random
directions (about half hit). Peer: trimesh's own Embree wrapper
(``trimesh.ray.ray_pyembree.RayMeshIntersector``) on the same triangles merged
into one mesh, in the same run. The peer returns less per ray (only the
triangle index for ``intersects_first``, a bool for ``intersects_any``);
ours returns object, triangle, barycentrics, distance, unit normal and hit point.
"""

from __future__ import annotations

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


def _peer(spheres):
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector
    except ImportError:  # pragma: no cover - embreex is a dependency
        return None
    return RayMeshIntersector(trimesh.util.concatenate(spheres))


def _ray_case(quick: bool, query: str, peer_query: str) -> dict:
    """1M rays (quick: 100k) against the ~100k-triangle scene, with trimesh's wrapper as peer."""
    spheres = _scene()
    caster = RayCaster(spheres)
    n = 100_000 if quick else 1_000_000
    origins, dirs = _rays(n)
    peer = _peer(spheres)
    return {
        "run": lambda: getattr(caster, query)(origins, dirs),
        "gflop": None,
        "items": n,
        "peer": None if peer is None else (
            f"trimesh RayMeshIntersector.{peer_query}", lambda: getattr(peer, peer_query)(origins, dirs)
        ),
    }


@case("raycast.closest_hit.100k_tris")
def closest_hit_case(quick: bool) -> dict:
    return _ray_case(quick, "closest_hit", "intersects_first")


@case("raycast.occluded.100k_tris")
def occluded_case(quick: bool) -> dict:
    return _ray_case(quick, "occluded", "intersects_any")

