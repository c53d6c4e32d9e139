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

from prtlab.bench import case, floor
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


#: The peer of every frame case: the same frames shaded by the paper's method (``PAPER_OPTIONS``: no self
#: interreflection, basis radiance interpolated everywhere, the SH direct light with the area light's source
#: radiance field, no residual gather, the flat occluders' fields), on a precomputation of its own. Its ratio is
#: what the accuracy defaults cost; what they buy is in ``docs/FIDELITY.md`` (the rows of the paper's method).
PAPER_LABEL = "the paper's method (prtlab.interreflection.PAPER_OPTIONS)"


def _paper_form(quick: bool):
    """The scene precomputed and shaded with ``PAPER_OPTIONS`` (cached like ``_precomputed``)."""
    from prtlab.interreflection import PAPER_OPTIONS, Interreflection

    if ("paper", quick) not in _PRE:
        _PRE["paper", quick] = Interreflection.precompute(_scene(quick), {**_options(quick), **PAPER_OPTIONS},
                                                          progress=False)
    return _PRE["paper", quick]


def _both(*setups):
    """One ``setup`` that calls each of ``setups`` (ours and the peer's next frame)."""
    def setup():
        for s in setups:
            s()

    return setup


def _vertices(pre) -> int:
    return sum(o.n_vertices for o in pre.objects)


def _product_flop(order: int) -> int:
    """One order-n SH product truncated to order n: ``a_i b_j G_ijk`` summed, 3 flops a Gaunt non-zero."""
    from prtlab.sh import gaunt_tensor

    return 3 * len(gaunt_tensor(order).value)


def _bounce_gflop(pre, bounces: int) -> float:
    """Weights (Eq. 14: ``A^-1 Psi`` at the samples) and bounces (Eq. 12: ``(V K', M) x (M, 3)`` per receiver,
    radiance by ``h``, and the residual gather's terms) of ``bounces`` bounces, from the shapes of the stacked basis
    irradiance and the packed terms."""
    flop = 0.0
    for o in pre.objects:
        n_k, n_b = pre.seps[o.name].K, pre.bases[o.name].n_basis
        n_s = len(pre.bases[o.name].samples)
        flop += n_k * 3 * (2 * n_b * n_s + 2 * n_b * n_b)  # weights
        stacked = pre.reuse.stacked.get(o.name)
        if stacked is not None:
            v, kp, m = stacked[1].shape
            flop += 2 * v * kp * m * 3 + 2 * v * kp * 3  # Eq. 12, then sum_k' h_k' colour L_k'
        flop += 18 * _gather(pre, o)[0]  # the residual gather
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


# Floors (``prtlab.bench.floor``) of a frame, per object r: V_r vertices, K_r BRDF terms, N_r PCA functions fitted
# at S_r samples, M_r = sum over r's sources s (the other objects a pair is kept for, and r itself with
# self-interreflection) of K_s N_s columns of its stacked basis irradiance, n^2 SH coefficients, 3 colours, B
# bounces. Relighting (poses stay):
#   direct   2 V K n^2 3 per light (env, area): L_k = <P_n(V G_k), L>    bytes: the transfer V K n^2 read once
#   weights  2 N S K 3 per bounce (Eq. 14: the projector times the light at the samples)
#   bounces  2 V K M 3 per bounce (Eq. 12)                         bytes: the stacked V K M read once per bounce
#   radiance 2 V K 3 per outgoing radiance (direct, each bounce)   bytes: h read (V K 8), direct / indirect /
#            total written (72 V)
#   gather   18 H per bounce (``residual_rays``: the residual gather's H packed terms, 3 multiply-adds a colour)
#                                                                  bytes: the terms (3 rows and 3 weights each)
#            and their starts read once per bounce, with the R residual rows they name (an index and 3 float64)
# Each bounce's weights need the whole previous bounce, so a stacked matrix larger than the caches is read once
# per bounce. Not counted: the area light's SH at the vertices (its exact projection or its field's lookup), the
# environment's SH, the geometry of a pose. A pose change (one object m moves) adds, for the pairs (m, s) and
# (r, m) (which must be recomputed at every vertex; pairs whose occluders moved are not counted):
#   Eq. 13   V_r K_s N_s E(K_r): the source's field at 8 corners, interpolated then contracted with the K_r
#            transfers (n^2 (16 + 2 K_r)) or contracted at each corner then interpolated (K_r (16 n^2 + 16)),
#            the cheaper, E(K') = min of the two                  bytes: Phi written, V_r K_r K_s N_s x 8
#   transfer V_r K_r P flops (P: one order-n SH product, 3 a Gaunt non-zero) for the pair's transfer, and
#            V_r P for the visibility without s when there are other occluders
# and its lookups: each other receiver's points within the reach of the mover's occlusion field (R_r of them) look
# it up and multiply it in (R_r (16 n^2 + P)) and redo their direct transfer (R_r K_r P); the mover looks up each
# other field at its points within that field's reach (R_m of them over all fields: R_m (16 n^2 + P)) and redoes
# its direct transfer (V_m K_m P). Near-field rays (``near_field``) are not counted.
FRAME_FORMULA = ("per object: (2 V K n^2 3 lights + B (2 V K M 3 + 2 N S K 3 + 18 H) + (B+1) 2 V K 3) flops; "
                 "(V K n^2 + B V K M) x itemsize + 8 V K + 72 V + B (H term + starts + 32 R) bytes")
POSE_FORMULA = (FRAME_FORMULA + "; plus per pair (m, s), (r, m): V_r K_s N_s E(K_r) + V_r (K_r + 1) P "
                "flops, 8 V_r K_r K_s N_s bytes; lookups R_r (16 n^2 + P) + R_m (16 n^2 + P), transfers "
                "R_r K_r P + V_m K_m P")


def _columns(pre, r) -> int:
    """M_r: the stacked basis irradiance's columns of receiver ``r`` (its sources' K_s N_s)."""
    stacked = pre.reuse.stacked.get(r.name)
    if stacked is not None:
        return int(stacked[1].shape[2])
    sources = [s for s in pre.objects if s.name != r.name or pre.options.self_interreflection]
    return sum(pre.seps[s.name].K * pre.bases[s.name].n_basis for s in sources)


def frame_floor(pre, bounces: int, lights: int) -> tuple[float, float]:
    """(flop, bytes) of a relighting frame's floor (``FRAME_FORMULA``) with ``lights`` SH lights."""
    n2 = pre.options.order ** 2
    flop = nbytes = 0.0
    for r in pre.objects:
        v, k, n = r.n_vertices, pre.seps[r.name].K, pre.bases[r.name].n_basis
        m, s = _columns(pre, r), len(pre.bases[r.name].samples)
        flop += 2 * v * k * n2 * 3 * lights + bounces * (2 * v * k * m * 3 + 2 * n * s * k * 3)
        flop += (bounces + 1) * 2 * v * k * 3
        stacked = pre.reuse.stacked.get(r.name)
        itemsize = stacked[1].itemsize if stacked is not None else 8
        nbytes += (v * k * n2 + bounces * v * k * m) * itemsize + 8 * v * k + 72 * v
        terms, gather_bytes = _gather(pre, r)
        flop += bounces * 18 * terms
        nbytes += bounces * gather_bytes
    return flop, nbytes


def _gather(pre, r) -> tuple[int, int]:
    """``(H, bytes)``: the residual gather's packed terms that a bounce of receiver ``r`` reads (the used ones, none
    before a frame or without ``residual_rays``) and the bytes it reads with them (``FRAME_FORMULA``)."""
    packed = getattr(pre.reuse, "residual_hits", {}).get(r.name, {}).get("packed")
    if packed is None:
        return 0, 0
    starts, rows, weights, residual_rows = packed.arrays()
    terms = int(np.sum(starts[:, -1] - starts[:, 0]))
    return terms, terms * (rows.itemsize + weights.itemsize) * 3 + starts.nbytes + 32 * len(residual_rows)


def eq13_flop(n_kp: int, n2: int) -> int:
    """E(K'): Eq. 13's flops a receiver point and source basis function (``K'`` transfers, ``n2`` coefficients, 8
    corners), the cheaper of interpolating first (``n2 (16 + 2 K')``) and contracting first (``K' (16 n2 + 16)``)."""
    return min(n2 * (16 + 2 * n_kp), n_kp * (16 * n2 + 16))


def pose_floor(pre, mover: str) -> tuple[float, float]:
    """(flop, bytes) that a pose change of ``mover`` adds to a frame's floor (``POSE_FORMULA``)."""
    n2, prod = pre.options.order ** 2, _product_flop(pre.options.order)
    n_obj = len(pre.objects)
    geo = {name: entry[1] for name, entry in pre.reuse.geometry.items()}  # the last frame's poses

    def within(x, o):
        d = x - geo[o]["center"]
        return int(np.count_nonzero(np.einsum("vi,vi->v", d, d) <= geo[o]["reach"] ** 2))

    flop = nbytes = 0.0
    for r in pre.objects:
        v, k = r.n_vertices, pre.seps[r.name].K
        if r.name == mover:
            reached = sum(within(geo[r.name]["x"], o.name) for o in pre.objects if o.name != mover)
            flop += reached * (16 * n2 + prod) + v * k * prod
        else:
            reached = within(geo[r.name]["x"], mover)
            flop += reached * (16 * n2 + prod + k * prod)
        for s in pre.objects:
            if s.name == r.name or mover not in (r.name, s.name):
                continue
            ksn = pre.seps[s.name].K * pre.bases[s.name].n_basis
            flop += v * ksn * eq13_flop(k, n2) + v * (k + (n_obj > 2)) * prod
            nbytes += 8 * v * k * ksn
    return flop, nbytes


def _frame_info(info: dict, result) -> None:
    """Keep the pair counts of the last timed frame (``computed_pairs``, ``updated_pairs``, ``reused_pairs``) and
    the residual gather's rays cast: they say which work a frame did and which it reused."""
    for k in ("computed_pairs", "updated_pairs", "reused_pairs", "skipped_pairs", "residual_rays_cast"):
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
    moves to a position no earlier frame had (its direct light is recomputed).
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


def _stored_bytes(pre) -> int:
    """Bytes of the precomputation's arrays (``pre.data``, as held in memory): what the frames read from."""
    def walk(x):
        if isinstance(x, dict):
            return sum(walk(y) for y in x.values())
        if isinstance(x, (list, tuple)):
            return sum(walk(y) for y in x)
        return np.asarray(x).nbytes if isinstance(x, (np.ndarray, np.generic)) else 0

    return int(walk(pre.data))


def _relight_case(quick: bool, env_only: bool) -> dict:
    pre = _precomputed(quick)
    setup, run, info = _relight(pre, env_only)
    setup_paper, run_paper, _ = _relight(_paper_form(quick), env_only)
    return {"run": run, "setup": _both(setup, setup_paper), "gflop": _direct_gflop(pre) + _bounce_gflop(pre, 3),
            "items": _vertices(pre), "peer": (PAPER_LABEL, run_paper), "info": info,
            "floor": floor(*frame_floor(pre, 3, 1 if env_only else 2), FRAME_FORMULA),
            "stored_bytes": _stored_bytes(pre)}


@case("interreflection.frame.relight")
def relight_frame(quick: bool) -> dict:
    """Light changes, poses do not: the area light moves (its direct light ray-traced at every vertex, the
    default ``shadows="rays"``) and the environment changes, then weights and 3 bounces; every pair's basis
    irradiance reused (``reused_pairs``)."""
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
    (f_frame, b_frame), (f_pose, b_pose) = frame_floor(pre, 3, 1), pose_floor(pre, mover.name)
    return (setup, run, _pose_gflop(pre, recomputed) + _direct_gflop(pre) + _bounce_gflop(pre, 3), info,
            floor(f_frame + f_pose, b_frame + b_pose, POSE_FORMULA))


@case("interreflection.frame.move_one")
def move_frame(quick: bool) -> dict:
    """One object moves: the pairs it touches are recomputed (visibility, transfer, Eq. 13; receivers near a
    source's surface by ray casting, ``near_field``), the others reused, then 3 bounces. Every frame is a new
    pose; peer: the same frames by the paper's method (:data:`PAPER_LABEL`)."""
    pre = _precomputed(quick)
    setup, run, gflop, info, work = _moving(pre)
    setup_paper, run_paper, *_ = _moving(_paper_form(quick))
    return {"run": run, "setup": _both(setup, setup_paper), "gflop": gflop, "items": _vertices(pre),
            "peer": (PAPER_LABEL, run_paper), "info": info, "floor": work, "stored_bytes": _stored_bytes(pre)}


@case("interreflection.frame.move_light")
def move_light_frame(quick: bool) -> dict:
    """The area light moves (poses do not) at the defaults: its direct light by shadow rays at every vertex
    (``shadows="rays"``), then 3 bounces; peer: the same frames by the paper's method (:data:`PAPER_LABEL`: the SH
    direct light with the light's source radiance field). Each frame a new light position and a new
    ``FrameState``."""
    base = _precomputed(quick)

    def mover(pre):
        light = base.scene.lights[1]
        centres = iter([light.center + [dx, 0.0, 0.0] for dx in np.linspace(0.0, 0.5, 10_000)])
        frame = {}

        def setup():
            state = FrameState.from_scene(pre.scene)
            state.lights[1] = type(light)(center=next(centres), u=light.u, v=light.v, radiance=light.radiance)
            frame["state"] = state

        def run():
            return pre.shade(frame["state"], bounces=3)

        return setup, run

    setup, run = mover(base)
    setup_paper, run_paper = mover(_paper_form(quick))
    setup()
    run()  # the pairs at the scene's poses and the stacked irradiance: computed once, then reused
    return {"run": run, "setup": _both(setup, setup_paper), "gflop": None, "items": _vertices(base),
            "peer": (PAPER_LABEL, run_paper), "floor": floor(*frame_floor(base, 3, 2), FRAME_FORMULA),
            "stored_bytes": _stored_bytes(base)}


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
            pre = Interreflection.precompute(scene, _options(quick), cache=Cache(root, progress=False), progress=False)
            info["hdf5_mb"] = sum(f.stat().st_size for f in Path(root).rglob("*.h5")) / 1e6
            info["stored_bytes"] = _stored_bytes(pre)

    return {"run": run, "gflop": None, "items": _vertices(_precomputed(quick)), "peer": None, "repeats": 1,
            "warmup": False, "info": info, "stored_bytes": lambda: info.pop("stored_bytes")}


def _eq13_inputs(quick: bool):
    """The Eq. 13 cases' source field (16 spheres of 16 x 16 texels a face, K = 1, N = 16, n^2 = 16: 50 MB in
    float64) and random receiver points around it (most between the outer spheres, some beyond) with K' = 1."""
    from prtlab.geometry import builtin_mesh
    from prtlab.shadowfields import sphere_grid

    rng = np.random.default_rng(0)
    grid = sphere_grid(builtin_mesh("icosphere", subdivisions=2), n_radii=16, resolution=16)
    field = rng.normal(size=grid.shape + (1, 16, 16))
    v = 20_000 if quick else 100_000
    pts = rng.normal(size=(v, 3)) * 3.0
    transfer = rng.normal(size=(v, 1, 16))
    return grid, field, pts, transfer


def _eq13_floor(field_bytes: int, v: int, n_kp: int, n_k: int, n_b: int, n2: int) -> dict:
    """Eq. 13 at each point in the cheaper order (``eq13_flop``); the field read once, points and transfer
    read, Phi written."""
    return floor(v * n_k * n_b * eq13_flop(n_kp, n2), field_bytes + v * (24 + 8 * n_kp * n2 + 8 * n_kp * n_k * n_b),
                 "V K N E(K') flops, E(K') = min(n^2 (16 + 2 K'), K' (16 n^2 + 16)); field bytes + "
                 "V (24 + 8 K' n^2 + 8 K' K N) bytes")


@case("interreflection.basis_irradiance.kernel")
def basis_irradiance_kernel(quick: bool) -> dict:
    """Eq. 13 at receiver vertices: trilinear S (8 corners) dotted with P_n(V G) for K' x K N vectors, the field
    in float64 (larger than the caches: the vertices are taken sorted by cell)."""
    from prtlab.interreflection import basis_irradiance

    grid, field, pts, transfer = _eq13_inputs(quick)
    (v, n_kp, n2), (n_k, n_b) = transfer.shape, field.shape[4:6]
    return {
        "run": lambda: basis_irradiance(field, grid, pts, transfer),
        "gflop": v * 8 * n_k * n_b * n2 * 2 / 1e9,
        "items": v,
        "peer": ("numpy float64 tier", lambda: basis_irradiance(field, grid, pts, transfer, method="reference")),
        "floor": _eq13_floor(field.nbytes, v, n_kp, n_k, n_b, n2),
    }


@case("interreflection.basis_irradiance.stored_int16")
def basis_irradiance_stored_int16(quick: bool) -> dict:
    """Eq. 13 as the pipeline runs it every frame: the field of ``.kernel`` stored in the room's default format
    (``storage="int16"``: int16 values, a float32 scale per sample point and column), the same points; peer: the
    float64 field (``.kernel``'s run)."""
    from prtlab.interreflection import basis_irradiance
    from prtlab.interreflection._fields import store_basis_radiance

    grid, field, pts, transfer = _eq13_inputs(quick)
    stored = store_basis_radiance(field, "int16")
    (v, n_kp, n2), (n_k, n_b) = transfer.shape, field.shape[4:6]
    return {
        "run": lambda: basis_irradiance(stored, grid, pts, transfer),
        "gflop": v * 8 * n_k * n_b * n2 * 2 / 1e9,
        "items": v,
        "peer": ("the float64 field", lambda: basis_irradiance(field, grid, pts, transfer)),
        "floor": _eq13_floor(stored.nbytes, v, n_kp, n_k, n_b, n2),
        "stored_bytes": stored.nbytes,
    }
