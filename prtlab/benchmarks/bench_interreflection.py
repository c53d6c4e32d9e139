"""Benchmarks of prtlab.interreflection: per-frame times (relighting, a moving object) and the Eq. 13 kernel.

Full mode is the paper's room scale (Sec. 6: about 50k vertices, 12 objects): a floor, two walls and
nine objects (teapots, bunnies, balls, a box), 46.8k vertices, with the paper's sample spheres
(16 x 6 x 16 x 16), N = 16 and 3 bounces; quick mode a ball over a floor (~800 vertices) with quick
fields. The precomputation is cached (``$PRTLAB_CACHE``) and done outside the timers; every timed frame
gets a new ``FrameState`` (``setup``) with a light position or pose no earlier frame had, and its pair counts
(``info``: computed, updated, reused) say which work it did and which it reused.
"""

from __future__ import annotations

import numpy as np

from prtlab.bench import case
from prtlab.pipeline import FrameState
from prtlab.scene import Scene, Transform

_PRE: dict = {}


def _room_objects() -> list:
    """The paper's room scale (Sec. 6): 12 objects, about 47k vertices (floor, two walls, 9 objects)."""
    objects = [
        {"name": "floor", "mesh": {"builtin": "plane", "size": [5, 5], "resolution": [90, 90]},
         "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
        {"name": "wall_back", "mesh": {"builtin": "plane", "size": [5, 2.5], "resolution": [80, 40]},
         "transform": {"translate": [0, 1.25, -2.5], "rotate_deg": [90, 0, 0]},
         "material": {"type": "diffuse", "albedo": [0.3, 0.7, 0.3]}},
        {"name": "wall_left", "mesh": {"builtin": "plane", "size": [2.5, 5], "resolution": [40, 80]},
         "transform": {"translate": [-2.5, 1.25, 0], "rotate_deg": [0, 0, -90]},
         "material": {"type": "diffuse", "albedo": [0.75, 0.25, 0.2]}},
    ]
    things = [("teapot", {"builtin": "teapot", "resolution": 12}, 0.45, 0.0),
              ("bunny", {"builtin": "bunny"}, 0.7, 0.0),
              ("ball", {"builtin": "icosphere", "radius": 0.35, "subdivisions": 4}, 1.0, 0.35),
              ("teapot", {"builtin": "teapot", "resolution": 12}, 0.45, 0.0),
              ("box", {"builtin": "box", "size": [0.6, 0.6, 0.6], "subdivisions": 5}, 1.0, 0.3),
              ("ball", {"builtin": "icosphere", "radius": 0.35, "subdivisions": 4}, 1.0, 0.35),
              ("bunny", {"builtin": "bunny"}, 0.7, 0.0),
              ("teapot", {"builtin": "teapot", "resolution": 12}, 0.45, 0.0),
              ("ball", {"builtin": "icosphere", "radius": 0.35, "subdivisions": 4}, 1.0, 0.35)]
    for i, (kind, mesh, scale, lift) in enumerate(things):
        x, z = -1.4 + 1.4 * (i % 3), -1.4 + 1.4 * (i // 3)
        objects.append({"name": f"{kind}{i}", "mesh": mesh, "dynamic": True,
                        "transform": {"translate": [x, lift, z], "rotate_deg": [0, 40 * i, 0], "scale": scale},
                        "material": {"type": "diffuse", "albedo": [0.3 + 0.05 * i, 0.7, 0.8 - 0.05 * i]}})
    return objects


def _scene(quick: bool) -> Scene:
    if quick:
        objects = [{"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [12, 12]},
                    "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.3]}},
                   {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 3},
                    "transform": {"translate": [0, 0.7, 0]}, "material": {"type": "diffuse", "albedo": [0.7] * 3}}]
    else:
        objects = _room_objects()
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


def _product_flop(order: int) -> int:
    """One order-n SH product truncated to order n: ``a_i b_j G_ijk`` summed, 3 flops a Gaunt non-zero."""
    from prtlab.sh import gaunt_tensor

    return 3 * len(gaunt_tensor(order).value)


def _bounce_gflop(pre, bounces: int) -> float:
    """Weights (Eq. 14: ``A^-1 Psi`` at the samples) and bounces (Eq. 12: ``(V K', M) x (M, 3)`` per receiver,
    radiance by ``h``) of ``bounces`` bounces, from the shapes of the stacked basis irradiance."""
    flop = 0.0
    for o in pre.objects:
        n_k, n_b = pre.seps[o.name].K, pre.bases[o.name].n_basis
        n_s = len(pre.bases[o.name].samples)
        flop += n_k * 3 * (2 * n_b * n_s + 2 * n_b * n_b)  # weights
        stacked = pre.reuse.stacked.get(o.name)
        if stacked is not None:
            v, kp, m = stacked[1].shape
            flop += 2 * v * kp * m * 3 + 2 * v * kp * 3  # Eq. 12, then sum_k' h_k' colour L_k'
    return bounces * flop / 1e9


def _direct_gflop(pre) -> float:
    """Step 1 with the transfer kept: ``< L_env, P_n(V G_k) >`` per vertex, term and colour."""
    n2 = pre.options.order ** 2
    return sum(2 * o.n_vertices * pre.seps[o.name].K * n2 * 3 for o in pre.objects) / 1e9


def _pose_gflop(pre, recomputed) -> float:
    """A pose change: every occlusion-field lookup (8 corners), every receiver's visibility and transfer
    products (step 1), and for the recomputed pairs their visibility, transfer and Eq. 13 (8 corners of
    ``K' x K N`` coefficient vectors). SH rotations and ray casting (``near_field``) are not counted."""
    n2, prod = pre.options.order ** 2, _product_flop(pre.options.order)
    n_obj = len(pre.objects)
    flop = 0.0
    for r in pre.objects:
        v, kp = r.n_vertices, pre.seps[r.name].K
        flop += v * (n_obj - 1) * 8 * n2 * 2  # lookups
        flop += v * ((n_obj - 1) + kp) * prod  # step 1: visibility and transfer
    for r_name, s_name in recomputed:
        r = next(o for o in pre.objects if o.name == r_name)
        v, kp = r.n_vertices, pre.seps[r_name].K
        m = pre.seps[s_name].K * pre.bases[s_name].n_basis
        flop += v * ((n_obj - 2) + kp) * prod + v * kp * m * n2 * 8 * 2
    return flop / 1e9


def _frame_info(info: dict, result) -> None:
    """Keep the pair counts of the last timed frame (``computed_pairs``, ``updated_pairs``, ``reused_pairs``):
    they say which work a frame did and which it reused."""
    for k in ("computed_pairs", "updated_pairs", "reused_pairs", "skipped_pairs"):
        info[k] = int(result.info.get(k, 0))


def _frames(pre, next_state):
    """``setup`` (the ``FrameState`` of the next frame, ``next_state()``, made before every call, untimed),
    ``run`` (shade it with 3 bounces, recording the frame's pair counts) and the ``info`` dict they fill."""
    frame: dict = {}
    info: dict = {}

    def setup():
        frame["state"] = next_state()

    def run():
        result = pre.shade(frame["state"], bounces=3)
        _frame_info(info, result)
        return result

    return setup, run, info


def _relight(pre, env_only: bool):
    """``setup`` and ``run`` of a relighting frame: poses stay, so every pair's basis irradiance is reused (the
    paper's relighting); the environment's scale changes every frame and, unless ``env_only``, the area light
    moves to a position no earlier frame had (its SH at every vertex and the direct light are recomputed).
    ``env_only`` shades the environment alone. Each repeat gets a new ``FrameState``."""
    env, area = pre.scene.lights[0], pre.scene.lights[1]
    steps = iter(range(1, 1_000_000))

    def next_state():
        k = next(steps)
        state = FrameState.from_scene(pre.scene)
        lights = [type(env)(image=env.image * (1.0 + 0.5 * (k % 2)))]
        if not env_only:
            lights.append(type(area)(center=area.center + [0.5 * k / 1_000_000 + 1e-3 * k, 0.0, 0.0], u=area.u,
                                     v=area.v, radiance=area.radiance))
        state.lights = lights
        return state

    setup, run, info = _frames(pre, next_state)
    setup()
    run()  # the pairs at the scene's poses: computed once, reused by every relighting frame
    return setup, run, info


def _relight_case(quick: bool, env_only: bool) -> dict:
    pre = _precomputed(quick)
    setup, run, info = _relight(pre, env_only)
    return {"run": run, "setup": setup, "gflop": _direct_gflop(pre) + _bounce_gflop(pre, 3),
            "items": _vertices(pre), "peer": None, "info": info}


@case("interreflection.frame.relight")
def relight_frame(quick: bool) -> dict:
    """Light changes, poses do not: the area light moves (exact SH at every vertex, the default) and the
    environment changes, then weights and 3 bounces; every pair's basis irradiance reused (``reused_pairs``)."""
    return _relight_case(quick, env_only=False)


@case("interreflection.frame.relight_env_only")
def relight_env_frame(quick: bool) -> dict:
    """The environment changes, no area light in the frame, poses do not: direct, weights and 3 bounces, every
    pair's basis irradiance reused."""
    return _relight_case(quick, env_only=True)


def _moving(pre):
    """``setup``, ``run`` moving the last object (a ball) to a new pose each call, the work of one call in GFLOP,
    and the pair counts of the last frame."""
    mover = pre.objects[-1]
    poses = iter([Transform(translate=mover.transform.translate + [dx, 0, 0], rotate_deg=mover.transform.rotate_deg,
                            scale=mover.transform.scale) for dx in np.linspace(0.0, 0.1, 10_000)])

    def next_state():
        state = FrameState.from_scene(pre.scene)
        state.transforms[mover.name] = next(poses)
        return state

    setup, run, info = _frames(pre, next_state)
    setup()
    run()
    before = {k: v[1] for k, v in pre.reuse.pair_irradiance.items()}
    setup()
    run()
    recomputed = [k for k, v in pre.reuse.pair_irradiance.items() if before.get(k) is not v[1]]
    return setup, run, _pose_gflop(pre, recomputed) + _direct_gflop(pre) + _bounce_gflop(pre, 3), info


@case("interreflection.frame.move_one")
def move_frame(quick: bool) -> dict:
    """One object moves: the pairs it touches are recomputed (visibility, transfer, Eq. 13; receivers near a
    source's surface by ray casting, ``near_field``), the others reused, then 3 bounces. Every frame is a new
    pose."""
    setup, run, gflop, info = _moving(_precomputed(quick))
    return {"run": run, "setup": setup, "gflop": gflop, "items": _vertices(_precomputed(quick)), "peer": None,
            "info": info}


@case("interreflection.frame.move_one.paper")
def move_frame_paper(quick: bool) -> dict:
    """As ``frame.move_one`` with ``near_field=0`` (every basis radiance interpolated, as the paper)."""
    import dataclasses

    from prtlab.interreflection import Interreflection

    base = _precomputed(quick)
    pre = Interreflection(base.scene, dataclasses.replace(base.options, near_field=0.0), base.data)
    setup, run, gflop, info = _moving(pre)
    return {"run": run, "setup": setup, "gflop": gflop, "items": _vertices(pre), "peer": None, "info": info}


@case("interreflection.frame.move_light")
def move_light_frame(quick: bool) -> dict:
    """The area light moves (poses do not) with ``area_lights="field"``: its SH radiance at every vertex from
    its source radiance field, then 3 bounces; peer: the exact per-vertex projection (the default). Each frame
    a new light position and a new ``FrameState``."""
    import dataclasses

    from prtlab.interreflection import Interreflection

    base = _precomputed(quick)
    frames = {}

    def mover(area_lights):
        pre = Interreflection(base.scene, dataclasses.replace(base.options, area_lights=area_lights), base.data)
        light = base.scene.lights[1]
        centres = iter([light.center + [dx, 0.0, 0.0] for dx in np.linspace(0.0, 0.5, 10_000)])

        def setup():
            state = FrameState.from_scene(pre.scene)
            state.lights[1] = type(light)(center=next(centres), u=light.u, v=light.v, radiance=light.radiance)
            frames[area_lights] = state

        def run():
            return pre.shade(frames[area_lights], bounces=3)

        return setup, run

    setup_field, run_field = mover("field")
    setup_exact, run_exact = mover("exact")

    def setup():
        setup_field()
        setup_exact()

    return {"run": run_field, "setup": setup, "gflop": None, "items": _vertices(base),
            "peer": ("exact area_light_sh", run_exact)}


@case("interreflection.precompute")
def precompute_scene(quick: bool) -> dict:
    """The whole precomputation of the scene (fields, PCA bases, basis radiance fields, self terms), uncached,
    written to a fresh HDF5 cache; ``info``: the file's size (the paper: 66.3 MB for its 50k-vertex room).
    One run, no warm-up: the kernels were compiled by the cases before it (and the cache of the frame
    cases is not touched)."""
    import tempfile
    from pathlib import Path

    from prtlab.cache import Cache
    from prtlab.interreflection import Interreflection

    scene = _scene(quick)
    info: dict = {}

    def run():
        with tempfile.TemporaryDirectory() as root:
            Interreflection.precompute(scene, _options(quick), cache=Cache(root, progress=False), progress=False)
            info["hdf5_mb"] = sum(f.stat().st_size for f in Path(root).rglob("*.h5")) / 1e6

    return {"run": run, "gflop": None, "items": _vertices(_precomputed(quick)), "peer": None, "repeats": 1,
            "warmup": False, "info": info}


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
