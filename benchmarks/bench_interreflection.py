"""Benchmarks of prtlab.interreflection: per-frame times (relighting, a moving object) and the Eq. 13 kernel.

The scenes are smaller than the paper's room (50k vertices, 12 objects): quick mode a ball over a floor
(~800 vertices) with quick fields; full mode four objects on a floor (~8k vertices) with the paper's
sample spheres (16 x 6 x 16 x 16) and N = 16. The precomputation is cached (``$PRTLAB_CACHE``), so only
the first run pays for it.
"""

from __future__ import annotations

import numpy as np

from prtlab.bench import case
from prtlab.pipeline import FrameState
from prtlab.scene import Scene, Transform

_PRE: dict = {}


def _scene(quick: bool) -> Scene:
    floor = {"builtin": "plane", "size": [4, 4], "resolution": [12, 12] if quick else [40, 40]}
    objects = [{"name": "floor", "mesh": floor,
                "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.3]}}]
    if quick:
        objects.append({"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 3},
                        "transform": {"translate": [0, 0.7, 0]}, "material": {"type": "diffuse", "albedo": [0.7] * 3}})
    else:
        for i, (x, z) in enumerate([(-1, -1), (1, -1), (-1, 1), (1, 1)]):
            objects.append({"name": f"ball{i}", "mesh": {"builtin": "icosphere", "radius": 0.45, "subdivisions": 4},
                            "transform": {"translate": [x, 0.6, z]},
                            "material": {"type": "diffuse", "albedo": [0.2 + 0.2 * i, 0.7, 0.9 - 0.2 * i]}})
    return Scene.from_dict({
        "objects": objects,
        "lights": [{"type": "environment", "sky": {"sun_elevation_deg": 40, "sun_azimuth_deg": 30, "turbidity": 3},
                    "scale": 0.1},
                   {"type": "area", "center": [0, 3, 0], "u": [0.4, 0, 0], "v": [0, 0, 0.4],
                    "radiance": [10.0, 10.0, 10.0]}],
        "camera": {"position": [0, 3, 6], "look_at": [0, 0, 0]},
    })


def _options(quick: bool) -> dict:
    return dict(n_radii=8, resolution=8, degree=31, n_lights=64, n_basis=8) if quick else dict(n_basis=16)


def _precomputed(quick: bool):
    if quick not in _PRE:
        from prtlab.interreflection import Interreflection

        scene = _scene(quick)
        _PRE[quick] = Interreflection.precompute(scene, _options(quick), progress=False)
    return _PRE[quick]


def _vertices(pre) -> int:
    return sum(o.n_vertices for o in pre.objects)


@case("interreflection.frame.relight")
def relight_frame(quick: bool) -> dict:
    """Light changes, poses do not: direct + weights + 3 bounces (basis irradiance reused)."""
    pre = _precomputed(quick)
    state = FrameState.from_scene(pre.scene)
    pre.shade(state, bounces=3)  # fills the pair cache
    env = state.lights[0]
    scales = iter(np.tile([1.0, 1.5], 10_000))

    def run():
        state.lights = [type(env)(image=env.image * next(scales)), *state.lights[1:]]
        return pre.shade(state, bounces=3)

    return {"run": run, "gflop": None, "items": _vertices(pre), "peer": None}


@case("interreflection.frame.move_one")
def move_frame(quick: bool) -> dict:
    """One object moves: the pairs it touches are recomputed (visibility, transfer, Eq. 13; receivers near a
    source's surface by ray casting, ``near_field``), then 3 bounces. Every frame is a new pose."""
    pre = _precomputed(quick)
    state = FrameState.from_scene(pre.scene)
    mover = pre.objects[1]
    base = mover.transform
    poses = iter([Transform(translate=base.translate + [dx, 0, 0]) for dx in np.linspace(0.0, 0.1, 10_000)])

    def run():
        state.transforms[mover.name] = next(poses)
        return pre.shade(state, bounces=3)

    return {"run": run, "gflop": None, "items": _vertices(pre), "peer": None}


@case("interreflection.frame.move_one.paper")
def move_frame_paper(quick: bool) -> dict:
    """As ``frame.move_one`` with ``near_field=0`` (every basis radiance interpolated, as the paper)."""
    import dataclasses

    from prtlab.interreflection import Interreflection

    base = _precomputed(quick)
    pre = Interreflection(base.scene, dataclasses.replace(base.options, near_field=0.0), base.data)
    state = FrameState.from_scene(pre.scene)
    mover = pre.objects[1]
    poses = iter([Transform(translate=mover.transform.translate + [dx, 0, 0]) for dx in np.linspace(0.0, 0.1, 10_000)])

    def run():
        state.transforms[mover.name] = next(poses)
        return pre.shade(state, bounces=3)

    return {"run": run, "gflop": None, "items": _vertices(pre), "peer": None}


@case("interreflection.basis_irradiance.kernel")
def basis_irradiance_kernel(quick: bool) -> dict:
    """Eq. 13 at receiver vertices: trilinear S (8 corners) dotted with P_n(V G) for K' x K N vectors."""
    from prtlab.geometry import builtin_mesh
    from prtlab.interreflection import basis_irradiance
    from prtlab.shadowfields import sphere_grid

    rng = np.random.default_rng(0)
    grid = sphere_grid(builtin_mesh("icosphere", subdivisions=2), n_radii=16, resolution=16)
    n_k, n_b, n2 = 1, 16, 16
    field = rng.normal(size=grid.shape + (n_k, n_b, n2))
    v = 20_000 if quick else 100_000
    pts = rng.normal(size=(v, 3)) * 3.0
    transfer = rng.normal(size=(v, 1, n2))
    flop = v * 8 * n_k * n_b * n2 * 2
    return {
        "run": lambda: basis_irradiance(field, grid, pts, transfer),
        "gflop": flop / 1e9,
        "items": v,
        "peer": ("numpy float64 tier", lambda: basis_irradiance(field, grid, pts, transfer, method="reference")),
    }
