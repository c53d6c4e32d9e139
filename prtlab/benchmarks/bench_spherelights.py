"""Benchmarks of the spherical-lights pipeline at the paper's squirrel scale (Guerrero et al. 2008, Sec. 8.5).

The squirrel scene: about 21k receiver vertices, 14 leaf spherical lights,
order 4. Here: a squirrel-like object of 8 lights plus 6 balls of one
light each (7 objects), 92 surface samples per light, receivers on a
ground grid and around the objects (synthetic arrays, no precomputation).
Cases: a whole frame (first pass + second pass) with per-object and per-sphere blocking, shadows only, the
per-object frame with the ground's terms (issue 16), the frame of the pipeline's default options with the ground
(``per_object_ground_near``: the ground's rays against meshes through the objects' receivers, near blockers,
emission order 6; every ray cast each frame, as when the geometry changes), the same frame when only the environment
changes (``per_object_ground_near_relit``: the geometry-only results reused), the same frame when one object moves
(``per_object_ground_near_move_one``: the ground's rays that cannot meet it kept), a frame of a real scene with the
objects' direct light against the meshes (``mesh_blockers``), and the precomputation of a real scene
(``data/scenes/bunny_spheres_env.yaml``, 16 lights on the bunny) with its precomputed memory per object in ``info``
(the paper: 32-150 KB per object).
"""

from __future__ import annotations

import functools
import math
from concurrent.futures import wait as futures_wait

import numpy as np

import prtlab.data
from prtlab.bench import case, floor
from prtlab.geometry import geodesic_directions
from prtlab.spherelights import SphereLightOptions, first_pass, second_pass, voronoi_cell_sums

ORDER = 4
#: the lights' emission order of the pipeline's defaults (``emission_order``; the paper's: ``ORDER``)
EMISSION_ORDER = SphereLightOptions().light_order
N_LIGHTS = 14
N_RECEIVERS = 21_000
SCENE = prtlab.data.scene_path("bunny_spheres_env")
# the precomputed arrays each kind of frame reads (``SphereLights.data["objects"][name]``): the second pass reads
# the sphere set, the first pass (indirect light) also the surface samples and the albedo SH; the rest of what is
# stored is the per-vertex light index (soft deformations, Sec. 7.1) and the fit's figures
SHADOW_ARRAYS = ("centres", "radii", "intersect")
FRAME_ARRAYS = SHADOW_ARRAYS + ("sample_points", "sample_normals", "sample_valid", "albedo_sh")


def _scene_arrays(n_receivers: int):
    rng = np.random.default_rng(2008)
    # squirrel: 8 overlapping spheres in a blob; balls: 6 separate spheres
    squirrel = np.array([0.0, 0.6, 0.0]) + 0.35 * rng.normal(size=(8, 3))
    balls = np.stack([np.cos(a) * 1.8 * np.array([1, 0, 0]) + np.sin(a) * 1.8 * np.array([0, 0, 1])
                      for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]) + [0.0, 0.3, 0.0]
    centres = np.concatenate([squirrel, balls])
    radii = np.concatenate([rng.uniform(0.25, 0.4, 8), np.full(6, 0.3)])
    sl_object = np.concatenate([np.zeros(8, dtype=np.int64), np.arange(1, 7)])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    inter = (d < radii[:, None] + radii[None]) & (sl_object[:, None] == sl_object[None])
    np.fill_diagonal(inter, False)
    rot = np.broadcast_to(np.eye(3), (N_LIGHTS, 3, 3))
    # receivers: a ground grid (80%) and points on the spheres' surfaces, pushed out a little (20%)
    n_ground = int(0.8 * n_receivers)
    g = rng.uniform(-3, 3, size=(n_ground, 2))
    ground = np.stack([g[:, 0], np.zeros(n_ground), g[:, 1]], -1)
    gn = np.broadcast_to([0.0, 1.0, 0.0], ground.shape)
    k = rng.integers(0, N_LIGHTS, n_receivers - n_ground)
    dirs = rng.normal(size=(k.size, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    surf = centres[k] + 1.01 * radii[k, None] * dirs
    points = np.concatenate([ground, surf])
    normals = np.concatenate([gn, dirs])
    # surface samples: on each sphere along the 92 directions
    sd = geodesic_directions(92)
    spts = centres[:, None] + 0.9 * radii[:, None, None] * sd[None]
    snrm = np.broadcast_to(sd, spts.shape).copy()
    valid = np.ones((N_LIGHTS, 92), dtype=bool)
    albedo = np.zeros((N_LIGHTS, EMISSION_ORDER**2, 3))  # uniform: the first k*k rows are the order-k albedo
    albedo[:, 0] = 0.7 * np.sqrt(4 * np.pi)
    env = np.zeros((ORDER * ORDER, 3))
    env[0] = [3.0, 2.8, 2.5]
    env[2] = [0.8, 0.8, 0.9]
    env[1:, :] += 0.05 * rng.normal(size=(ORDER * ORDER - 1, 3))
    # the receivers' objects: -1 the ground, else the object of the light they lie on
    recv_object = np.concatenate([np.full(n_ground, -1), sl_object[k]])
    recv_light = np.concatenate([np.full(n_ground, -1), k])  # the light a receiver lies on (-1: the ground)
    return dict(points=points, normals=normals, centres=centres, radii=radii, sl_object=sl_object, inter=inter,
                rot=rot, spts=spts, snrm=snrm, valid=valid, albedo=albedo, env=env, recv_object=recv_object,
                recv_light=recv_light)


def _frame(a, blocking, indirect=True, exp_method="hyb", emission_order=EMISSION_ORDER):
    """First and second pass, the visibility at ``ORDER`` and the lights' emission at ``emission_order``."""
    emission = np.zeros((N_LIGHTS, ORDER * ORDER, 3))
    if indirect:
        emission = first_pass(a["spts"], a["snrm"], a["valid"], a["centres"], a["radii"], a["env"],
                              voronoi_cell_sums(emission_order), a["albedo"][:, : emission_order**2],
                              exp_method=exp_method, order=ORDER)
    return second_pass(a["points"], a["normals"], a["centres"], a["radii"], a["sl_object"], a["inter"], a["rot"],
                       emission, a["env"], blocking=blocking, exp_method=exp_method, indirect=indirect, order=ORDER)


# Counted work (flops, an FMA = 2) of the fused second pass as it runs: blocks of receivers as SIMD lanes, so the
# per-light vector work is done for every lane of a block (culled pairs included) once any lane needs it. Per object
# with HYB, a light alone in its object is counted with its own two exponentials, which the pass reads from the
# objects' prefix chain (``_Mode.object_chain``): an overcount of a few per cent on this scene.
_BLOCKER = 130  # per receiver and light: adjustment, axis, table lookup, order-4 basis, ZH scaling, sum
_DIRECT = 2 * 31 * 48 + 150 + 30 + 90  # per receiver: T_n = cos_7(n) @ M (31 non-zero rows), order-7 basis, dots
_OL = 30  # one OL exponential given |f^| (norm counted apart): lookup, exp, scale
_OL_VISIBILITY = 15 * 9 + 2 * _OL  # per pair: norms and rho-dots of front and front + own, two OL factors
_SQUARE = 3 * 194  # one order-4 square: 194 symmetric Gaunt pairs, 3 flops each
_HYB_FIXED = 30 + 15 + 32 + 16  # per HYB exponential besides its squarings: norm, halving, OL, DC factor
_AVERAGE = {"cosine": lambda m: 15 + 15 + 60 + 50 + 2 * (m + 1) ** 2 * 9 + 2 * m * m * 3 + 60 + 40,
            "paper": lambda m: 12 + 30 + 32 + 2 * m * m * 3 + 6}  # per pair, emission order m


def _frame_flops(a, blocking: str, indirect: bool, exp_method: str = "hyb", average: str = "cosine") -> float:
    """GFLOP of one frame, counted from the scene: the lights' front lists (``_front_lists``) and, for HYB, the
    number of squarings of every exponential (``ceil(log2(|f^| / 0.125))``, from the composed tier's blocker
    logs and front sums), plus the first pass (``S`` blocker logs, one exponential, the transfer per sample)."""
    from prtlab.spherelights import accumulate_blockers
    from prtlab.spherelights._passes import _front_lists, _light_arrays

    n2 = ORDER * ORDER
    b, s = a["points"].shape[0], N_LIGHTS
    gs, gf, theta, _ = accumulate_blockers(a["points"], a["normals"], a["centres"], a["radii"], a["sl_object"],
                                           a["inter"], ORDER, blocking=blocking)

    flops = b * (s * _BLOCKER + _DIRECT)
    if exp_method == "hyb":
        flops += b * _HYB_FIXED + _SQUARE * _squarings(gs.sum(axis=1)).sum()
    else:
        flops += b * (15 * 2 + _OL)
    if indirect:
        _, _, obj, inter, obj_centres = _light_arrays(a["centres"], a["radii"], a["sl_object"], a["inter"])
        ptr, _ = _front_lists(obj, inter, blocking == "object")
        n_obj = obj_centres.shape[0]
        fronts = (n_obj * 8 + s * n2 + 2 * n_obj * n2 if blocking == "object" else 0) + (s + ptr[-1]) * n2
        flops += b * (16 + fronts + s * _AVERAGE[average](EMISSION_ORDER))
        if exp_method == "hyb":
            live = theta >= 0
            front = np.where(live, _squarings(gf), 0.0)
            own = np.where(live, _squarings(gf + gs), 0.0)
            flops += b * s * (2 * _HYB_FIXED + 3 * n2) + _SQUARE * (front.sum() + own.sum())
        else:
            flops += b * s * _OL_VISIBILITY
        flops += N_LIGHTS * 92 * (s * _BLOCKER + _DIRECT + _OL + 30)  # first pass
    return flops / 1e9


# Floors (``prtlab.bench.floor``): B receivers, S lights, n^2 = 16 SH coefficients, 3 colours, L live (receiver,
# light) pairs (the adjusted light above the receiver's horizon and not culled, ``accumulate_blockers``' theta >= 0
# for the case's blocking), every exponential at OL's cost (E = 3 n^2: the norm of f^, the scale, the DC term)
# plus, for HYB, 3 x 194 flops (an order-4 square, its symmetric Gaunt pairs) per squaring it needs (the count
# ``ceil(log2(|f^| / 0.125))`` from the logs). Per receiver: the transfer T_n = M cos_7(n) (2 x 31 x 3 n^2, the
# order-7 clamped cosine's 31 non-zero coefficients; the basis at n not counted), one exponential of the summed
# logs and the dot V . T_n (2 x 3 n^2). Per live pair: the light's log (its order-4 basis, ZH scaling and sum into
# the total: 4 n^2); with indirect light also the front sum and front + own (2 n^2), two exponentials, their
# difference dotted with rho_n (3 n^2), the average radiance (2 x 3 m^2, m the emission's order) and its
# product (6). First pass: per
# surface sample (S x 92) the receiver's per-receiver work, no blocker counted. Bytes: points and normals read,
# direct and indirect written (96 B); the lights' arrays are a few KB.
FLOOR_FORMULA = ("B (2 31 3 n^2 + E + 6 n^2) + 4 n^2 L [+ L (2 n^2 + 2 E + 3 n^2 + 6 m^2 + 6) + 92 S (2 31 3 n^2 + "
                 "E + 6 n^2) with indirect] flops, E = 3 n^2 (+ 582 a HYB squaring), m the emission's order; "
                 "96 B bytes")


def _squarings(x):
    """Squarings HYB needs for the exponential of each order-4 vector of ``x`` (``ceil(log2(|f^| / 0.125))``)."""
    from prtlab.sh._explog import _HYB_THRESHOLD

    norm = np.linalg.norm(x[..., 1:], axis=-1)
    return np.where(norm > _HYB_THRESHOLD, np.ceil(np.log2(np.maximum(norm, 1e-300) / _HYB_THRESHOLD)), 0.0)


def frame_floor(a, blocking: str, indirect: bool, exp_method: str = "hyb") -> tuple[float, float]:
    """(flop, bytes) of one frame's floor (``FLOOR_FORMULA``)."""
    from prtlab.spherelights import accumulate_blockers

    n2, b = ORDER * ORDER, a["points"].shape[0]
    gs, gf, theta, _ = accumulate_blockers(a["points"], a["normals"], a["centres"], a["radii"], a["sl_object"],
                                           a["inter"], ORDER, blocking=blocking)
    live = theta >= 0
    exp_cost, square = 3 * n2, 3 * 194
    per_receiver = 2 * 31 * 3 * n2 + exp_cost + 6 * n2
    flop = b * per_receiver + 4 * n2 * live.sum()
    if exp_method == "hyb":
        flop += square * _squarings(gs.sum(axis=1)).sum()
    if indirect:
        flop += (live.sum() * (2 * n2 + 2 * exp_cost + 3 * n2 + 6 * EMISSION_ORDER**2 + 6)
                 + N_LIGHTS * 92 * per_receiver)
        if exp_method == "hyb":
            flop += square * np.where(live, _squarings(gf) + _squarings(gf + gs), 0.0).sum()
    return float(flop), 96.0 * b


def _n(quick):
    return 4_000 if quick else N_RECEIVERS


def _new_sky_each_frame(a):
    """``setup``: each call a new environment (``a["env"]`` scaled by ``1 + 1e-9 k`` at call ``k``), as in an
    animation, so that no work is kept from the frame before by a pass that keeps what its inputs give
    (``_passes._fused_inputs``) while the work stays the same."""
    env = a["env"].copy()
    calls = iter(range(1, 1 << 62))

    def setup():
        a["env"] = env * (1.0 + 1e-9 * next(calls))

    return setup


@case("spherelights.frame.per_object.21k")
def frame_per_object(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"setup": _new_sky_each_frame(a),
            "run": lambda: _frame(a, "object"), "gflop": _frame_flops(a, "object", True),
            "items": _n(quick), "peer": ("per-sphere blocking", lambda: _frame(a, "sphere")),
            "floor": floor(*frame_floor(a, "object", True), FLOOR_FORMULA)}


@case("spherelights.frame.emission_order.21k")
def frame_emission_order(quick: bool) -> dict:
    """The per-object frame at the default emission order (``emission_order``, 6); peer: the paper's single order
    (4), the accuracy/speed trade-off of the option."""
    a = _scene_arrays(_n(quick))
    return {"setup": _new_sky_each_frame(a),
            "run": lambda: _frame(a, "object"), "gflop": _frame_flops(a, "object", True), "items": _n(quick),
            "peer": ("the paper's emission order (4)", lambda: _frame(a, "object", emission_order=ORDER)),
            "floor": floor(*frame_floor(a, "object", True), FLOOR_FORMULA)}


@case("spherelights.frame.per_sphere.21k")
def frame_per_sphere(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"setup": _new_sky_each_frame(a),
            "run": lambda: _frame(a, "sphere"), "gflop": _frame_flops(a, "sphere", True),
            "items": _n(quick), "peer": None, "floor": floor(*frame_floor(a, "sphere", True), FLOOR_FORMULA)}


@case("spherelights.frame.per_object_ol.21k")
def frame_per_object_ol(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"setup": _new_sky_each_frame(a),
            "run": lambda: _frame(a, "object", exp_method="ol"),
            "gflop": _frame_flops(a, "object", True, exp_method="ol"), "items": _n(quick),
            "peer": ("HYB exponentiation", lambda: _frame(a, "object", exp_method="hyb")),
            "floor": floor(*frame_floor(a, "object", True, "ol"), FLOOR_FORMULA)}


@case("spherelights.frame.shadows_only.21k")
def frame_shadows_only(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"setup": _new_sky_each_frame(a),
            "run": lambda: _frame(a, "object", indirect=False), "gflop": _frame_flops(a, "object", False),
            "items": _n(quick), "peer": None, "floor": floor(*frame_floor(a, "object", False), FLOOR_FORMULA)}


def _ground_texels(a):
    """The 6 x 6 ground's 64 x 64 texel centres, their normals, which receivers lie above it, its rectangle."""
    g = 3.0 * (-1.0 + (np.arange(64) + 0.5) / 32.0)
    texels = np.stack(np.broadcast_arrays(g[:, None], 0.0, g[None, :]), -1).reshape(-1, 3)
    up = np.broadcast_to([0.0, 1.0, 0.0], texels.shape)
    return texels, up, a["points"][:, 1] > 0, np.array([[0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 3.0]])


def _ground_direct(a, texels, up):
    """The ground texture's shadows-only pass at ``ORDER``, as the pipeline runs it."""
    return second_pass(texels, up, a["centres"], a["radii"], a["sl_object"], a["inter"], a["rot"],
                       np.zeros((N_LIGHTS, ORDER * ORDER, 3)), a["env"], indirect=False)[0]


@case("spherelights.frame.per_object_ground.21k")
def frame_per_object_ground(quick: bool) -> dict:
    """The per-object frame with the ground taking part (``ground="reflects"``): plus the ground's texture (a 64 x
    64 shadows-only pass over the 6 x 6 ground) and ``ground_light`` at the receivers above it; peer: without."""
    from prtlab.spherelights import ground_light

    a = _scene_arrays(_n(quick))
    texels, up, above, rect = _ground_texels(a)

    def run():
        _frame(a, "object")
        e = _ground_direct(a, texels, up)
        tex = (np.maximum(e, 0.0) * 0.7 / np.pi).reshape(1, 64, 64, 3)
        return ground_light(a["points"][above], a["normals"][above], rect, tex, a["env"], a["centres"], a["radii"])

    # gflop and floor count the per-object frame only (the ground terms' work is not counted: a lower bound)
    return {"setup": _new_sky_each_frame(a),
            "run": run, "gflop": _frame_flops(a, "object", True), "items": _n(quick),
            "peer": ("without the ground terms", lambda: _frame(a, "object")),
            "floor": floor(*frame_floor(a, "object", True), FLOOR_FORMULA)}


def _object_meshes(a):
    """Per object (the lights' objects, in order) a closed surface through its receivers: each light's receivers
    triangulated by the convex hull of their directions (faces turned outwards), at 0.99 of its radius (inside
    the light, whose sphere bounds it, as a fitted set bounds its mesh); the vertices in the order of the object's
    receivers. What the ground's rays of ``ground_shading="rays"`` meet."""
    from scipy.spatial import ConvexHull

    out = []
    for own in range(int(a["sl_object"].max()) + 1):
        rows = np.nonzero(a["recv_object"] == own)[0]
        verts, faces = np.empty((len(rows), 3)), []
        for light in np.nonzero(a["sl_object"] == own)[0]:
            local = np.nonzero(a["recv_light"][rows] == light)[0]
            dirs = a["normals"][rows[local]]
            verts[local] = a["centres"][light] + 0.99 * a["radii"][light] * dirs
            tri = ConvexHull(dirs).simplices
            d = dirs[tri]
            flip = np.einsum("fi,fi->f", np.cross(d[:, 1] - d[:, 0], d[:, 2] - d[:, 0]), d.sum(axis=1)) < 0
            tri[flip] = tri[flip][:, ::-1]
            faces.append(local[tri])
        out.append((verts, np.concatenate(faces)))
    return out


def _mesh_direct_parts(a, meshes) -> list:
    """Per object what ``SphereLights._mesh_direct`` keeps from frame to frame (``mesh_blockers=True``): its
    receivers' own-mesh bits along the 1,024 directions (``self_blocked``, cast once) and the other objects as
    occluders (their meshes' casters, their lights as bounds, the balls inside them); every pose the identity."""
    from prtlab.spherelights._meshdirect import fibonacci_directions, inner_spheres, mesh_occluder, self_blocked

    dirs = fibonacci_directions(1024)
    c, r, obj = a["centres"], a["radii"], a["sl_object"]
    bounds = [np.concatenate([c[obj == g], r[obj == g, None]], axis=1) for g in range(len(meshes))]
    occ = [mesh_occluder(v, f, bounds=bounds[g], inner=inner_spheres(v, f, c[obj == g]))
           for g, (v, f) in enumerate(meshes)]
    parts = []
    for g, (v, f) in enumerate(meshes):
        rows = a["recv_object"] == g
        bits = self_blocked(a["points"][rows], a["normals"][rows], v, f, dirs)
        parts.append((bits, [o for k, o in enumerate(occ) if k != g]))
    return parts


def _default_frame(a, texels, up, rect, meshes, near_blockers: int = 2, ground_shading: str = "rays",
                   mesh_parts=None, ground_ray_spacing: float = SphereLightOptions().ground_ray_spacing,
                   emission_coverage: bool = SphereLightOptions().emission_coverage, reuse=None, moved=None):
    """One frame as ``SphereLights.shade_frame`` runs it with the default options and the ground (``bounces=1``,
    ``ground="reflects"``, ``ground_texels=64``, ``ground_shading``, ``near_blockers``, ``emission_order``, HYB,
    per-object blocking): the near blockers' correction at the surface samples (``_near_samples``), the first pass
    with the ground hiding the environment from the samples, the ground's texture (``"rays"``: its direct light
    against the objects' meshes, ``_object_meshes``; ``"lights"``: a shadows-only pass and the near blockers at its
    texels; the texels under an object filled), then per receiving object the second pass, the near blockers (the object's own lights not eligible)
    and, above the ground, ``ground_light`` testing the eligible lights unadjusted; the ground's receivers last from
    the rays (their direct light and the light gathered from the objects' radiance; ``"lights"``: first, as any
    receiver, less ``ground_light``), cast where ``ground_ray_spacing`` (the option) says. With ``mesh_parts``
    (:func:`_mesh_direct_parts`; ``mesh_blockers=True``) the objects' direct light is ``mesh_direct`` against the
    meshes and the ground instead of the second pass's, near blockers' and hidden ground light. With
    ``emission_coverage`` the first pass also gives the emission weighted by ``coverage_weights`` (here of a
    coverage of 1: the same work as the meshes' coverage) for the other objects' receivers, the paper's for a
    light's own object. The geometry-only results (the blockers, the texels' and the ground's ray hits, the objects'
    visible rays, ``ground_light``'s samples, the near blockers' caps and the ground's hidden projection at the surface
    samples) go through ``reuse``
    (a :class:`prtlab.spherelights._reuse.FrameReuse`, as ``SphereLights`` keeps them; None: a fresh one, every ray
    cast); the objects' occluders are ``mesh_parts``'. Kept visible rays and ground rays are updated on the second
    thread while the objects are shaded (``prtlab._tasks.run_ahead``), as the pipeline does. ``moved``: ``(object,
    translation (3,))``, that object (its lights, receivers, surface samples, mesh and occluder) translated
    (:func:`_translated`)."""
    from prtlab._tasks import run_ahead
    from prtlab.spherelights._ground import (covered_texels, fill_covered, ground_hidden_projection, ground_sample_sums,
                                             ground_samples)
    from prtlab.spherelights._groundrays import (contact_radiance, ground_direct_hits, ground_direct_sums,
                                                 ground_light_hits, ground_light_sums, mesh_blockers, object_size)
    from prtlab.spherelights._meshdirect import mesh_direct_sums, mesh_direct_visible, mesh_direct_visible_update
    from prtlab.spherelights._nearcaps import (has_near_blocker, near_blocker_direct, near_blocker_sums,
                                               near_blocker_visibility)
    from prtlab.spherelights._pipeline import (_GROUND_RAYS, _TEXEL_RAYS, ground_hits_reuse, ground_samples_reuse,
                                               near_samples_reuse)
    from prtlab.spherelights._reuse import FrameReuse, same_inputs

    reuse = FrameReuse() if reuse is None else reuse
    size = max(object_size(v) for v, _ in meshes)  # before a move: the objects' own sizes (translation-free)
    if moved is not None:
        a, meshes, mesh_parts = _translated(a, meshes, mesh_parts, *moved)
    c, r, obj, env = a["centres"], a["radii"], a["sl_object"], a["env"]
    counts = np.bincount(obj)
    albedo = 0.7 / np.pi

    def eligible(own):  # SphereLights._near_eligible: one-sphere lights of the other objects
        return (obj != own) & (counts[obj] == 1)

    def near(p, n, direct, own):  # SphereLights._irradiance's near blockers
        e = eligible(own)
        sel = has_near_blocker(p, n, c, r, e)
        if near_blockers and sel.any():
            direct[sel] = near_blocker_direct(p[sel], n[sel], c, r, env, ORDER, near_blockers, eligible=e)

    rays = ground_shading == "rays"
    if rays:  # SphereLights._mesh_blocker_inputs: in the ground's frame
        inputs = (meshes, np.concatenate([c, r[:, None]], axis=1), np.zeros((0, 4)),
                  np.array([rect[0, 1], rect[0, 0], rect[0, 2]]), float(np.arctan2(rect[0, 4], rect[0, 3])),
                  float(np.hypot(*rect[0, 3:5])), size)
        blockers = reuse.get("mesh_blockers", inputs, lambda: mesh_blockers(*inputs))
    def mesh_direct(own):  # SphereLights._mesh_direct: an object's direct light through its visible rays
        rows = a["recv_object"] == own
        p, n = a["points"][rows], a["normals"][rows]
        bits, occluders = mesh_parts[own]
        key = (p, n, bits, rect, [o.translate for o in occluders])

        def update(kept_key, kept):
            if not same_inputs(kept_key[:4], key[:4]) or len(kept_key[4]) != len(key[4]):
                return None
            moved = [not same_inputs(a, b) for a, b in zip(kept_key[4], key[4])]
            visible, counts = mesh_direct_visible_update(kept[0], kept[1], p, n, np.eye(3), bits, occluders, moved,
                                                         rect)
            return (visible, occluders), counts

        visible = reuse.get(("mesh_direct", own), key,
                            lambda: (mesh_direct_visible(p, n, np.eye(3), bits, occluders, rect), occluders), update)[0]
        return mesh_direct_sums(visible, n, env, np.eye(3))

    # SphereLights.shade_frame: kept geometry (the objects' visible rays with their sums, then the ground's ray hits)
    # updated on a second thread while the first pass and the objects are shaded
    ahead = {}  # object (-1: the ground's rays) -> future
    if mesh_parts is not None:
        for own in range(len(mesh_parts)):
            if reuse.holds(("mesh_direct", own)):
                ahead[own] = run_ahead(functools.partial(mesh_direct, own))
    if rays:
        ground_pts = a["points"][a["recv_object"] == -1]
        ground_key = (inputs, ground_pts, ground_ray_spacing)

        def ground_hits():
            return reuse.get(("ground_rays", "ground"), ground_key,
                             lambda: ground_light_hits(ground_pts, blockers, _GROUND_RAYS, spacing=ground_ray_spacing),
                             ground_hits_reuse(ground_key, blockers, ground_pts, _GROUND_RAYS, ground_ray_spacing))

        if reuse.holds(("ground_rays", "ground")):
            ahead[-1] = run_ahead(ground_hits)
    try:
        extra = None
        if near_blockers:  # SphereLights._near_samples (every sample valid here)
            extra = np.zeros(a["valid"].shape + (3,))
            for own in np.unique(obj):
                rows = obj == own
                e = eligible(own)
                p = a["spts"][rows].reshape(-1, 3)
                n = a["snrm"][rows].reshape(-1, 3)
                n = n / np.linalg.norm(n, axis=1, keepdims=True)
                sel = has_near_blocker(p, n, c, r, e)
                if sel.any():
                    corr = np.zeros((len(p), 3))
                    args = (p[sel], n[sel], c, r, ORDER)
                    key = (p, n, sel, c, r, ORDER, near_blockers, e, "hyb")
                    near_vis, far_vis = reuse.get(("near_samples", int(own)), key, lambda: tuple(
                        near_blocker_visibility(*args, m, eligible=e) for m in (near_blockers, 0)),
                        near_samples_reuse(key))
                    corr[sel] = near_blocker_sums(near_vis, env) - near_blocker_sums(far_vis, env)
                    extra[rows] = corr.reshape(-1, a["valid"].shape[1], 3)
        weight = None
        if emission_coverage:  # SphereLights._emission
            from prtlab.spherelights._samples import coverage_weights

            weight = coverage_weights(np.ones(a["valid"].shape), a["valid"], geodesic_directions(a["valid"].shape[1]))
            weight = np.stack([np.ones_like(weight), weight])
        n_proj = ORDER + math.isqrt(len(env)) - 1  # SphereLights._ground_projection: per object, kept
        projection = np.zeros(a["valid"].shape + (n_proj * n_proj,))
        for own in np.unique(obj):
            p, n = a["spts"][obj == own].reshape(-1, 3), a["snrm"][obj == own].reshape(-1, 3)
            n = n / np.linalg.norm(n, axis=1, keepdims=True)
            projection[obj == own] = reuse.get(("ground_projection", int(own)), (p, n, rect, n_proj),
                                               lambda: ground_hidden_projection(p, n, rect, n_proj)).reshape(
                -1, a["valid"].shape[1], n_proj * n_proj)
        emission = first_pass(a["spts"], a["snrm"], a["valid"], c, r, env, voronoi_cell_sums(EMISSION_ORDER),
                              a["albedo"][:, : EMISSION_ORDER**2], ground=rect, extra_irradiance=extra, order=ORDER,
                              sample_weight=weight, ground_projection=projection.reshape(-1, n_proj * n_proj))
        own_emission, emission = (emission[0], emission[1]) if emission_coverage else (emission, emission)
        if rays:
            key = (inputs, texels, ground_ray_spacing)
            hits = reuse.get(("texel_rays", "ground"), key,
                             lambda: ground_direct_hits(texels, blockers, _TEXEL_RAYS, spacing=ground_ray_spacing),
                             ground_hits_reuse(key, blockers, texels, _TEXEL_RAYS, ground_ray_spacing))
            e = ground_direct_sums(hits, env, blockers)
        else:
            e = _ground_direct(a, texels, up)
            near(texels, up, e, -1)
        covered = np.zeros((64, 64), dtype=bool)  # SphereLights._covered: per object, kept while it stays
        for g, mesh in enumerate(meshes):
            covered |= reuse.get(("covered_texels", "ground", g), (rect[0], 64, mesh),
                                 lambda: covered_texels(rect[0], 64, [mesh]))
        tex = fill_covered((np.maximum(e, 0.0) * albedo).reshape(64, 64, 3), covered)[None]
        out, radiance = [], []
        for own in range(0 if rays else -1, int(obj.max()) + 1):
            rows = a["recv_object"] == own
            p, n = a["points"][rows], a["normals"][rows]
            emission_in = (np.where((obj == own)[:, None, None], own_emission, emission)  # own lights: the paper's
                           if emission_coverage and own >= 0 else emission)
            direct, indirect = second_pass(p, n, c, r, obj, a["inter"], a["rot"], emission_in, env, order=ORDER)
            exact = mesh_parts is not None and own >= 0
            if exact:
                direct = ahead[own].result() if own in ahead else mesh_direct(own)
            else:
                near(p, n, direct, own)
            if own >= 0:
                unadjusted = eligible(own) & (near_blockers > 0)
                key = (p, n, rect, c, r, None, unadjusted)
                samples = reuse.get(("ground_light", own), key, lambda: ground_samples(*key[:6], unadjusted=unadjusted),
                                    ground_samples_reuse(key))
                hidden, reflected = ground_sample_sums(samples, tex, env)
                direct, indirect = (direct if exact else direct - hidden), indirect + reflected
            out.append((np.maximum(direct, 0.0), np.maximum(indirect, 0.0)))
            if rays:  # the objects' exit radiance as the ground sees it (one bounce: their direct light)
                radiance.append(contact_radiance(p, n, out[-1][0] * albedo, rect[:, 0],
                                                blockers.caster.epsilon * blockers.scale))
        if rays:
            hits = ahead[-1].result() if -1 in ahead else ground_hits()
            direct, indirect = ground_light_sums(hits, env, blockers, radiance)
            out.insert(0, (np.maximum(direct, 0.0), np.maximum(indirect, 0.0)))
    finally:
        futures_wait(list(ahead.values()))
    return out


def _translated(a, meshes, mesh_parts, own: int, shift):
    """``a``, ``meshes`` and ``mesh_parts`` with object ``own`` translated by ``shift``: its lights, its receivers,
    its lights' surface samples, its mesh and its occluder in the other objects' parts (its own-mesh bits are
    object-space: unchanged)."""
    shift = np.asarray(shift, dtype=np.float64)
    mine = a["sl_object"] == own
    rows = a["recv_object"] == own
    centres, points, spts = a["centres"].copy(), a["points"].copy(), a["spts"].copy()
    centres[mine] += shift
    points[rows] += shift
    spts[mine] += shift
    a = {**a, "centres": centres, "points": points, "spts": spts}
    meshes = [(v + shift, f) if g == own else (v, f) for g, (v, f) in enumerate(meshes)]
    if mesh_parts is not None:
        def move(o):
            return o._replace(translate=o.translate + shift, bounds=o.bounds + np.append(shift, 0.0),
                              inner=o.inner + np.append(shift, 0.0))

        mesh_parts = [(bits, [move(o) if (k if k < g else k + 1) == own else o for k, o in enumerate(occluders)])
                      for g, (bits, occluders) in enumerate(mesh_parts)]
    return a, meshes, mesh_parts


def _pipeline_sky(env):
    """``env`` (order ``ORDER``) extended to the order ``3 ORDER - 2`` of the pipeline's sky
    (``SphereLights._environment``) by small bands of a fixed draw: the work of the terms whose cost grows with the
    sky's order (the ground's hidden transfer at the surface samples) is the pipeline's."""
    n = 3 * ORDER - 2
    out = np.zeros((n * n, 3))
    out[: len(env)] = env
    out[len(env):] = 0.01 * np.random.default_rng(2009).normal(size=(n * n - len(env), 3))
    return out


def _ground_frame_arrays(quick: bool):
    """The arrays of the frames with the ground's rays: the scene, the texels, their normal, the ground's
    rectangle, the objects' meshes and their own-mesh bits and occluders (``_mesh_direct_parts``)."""
    a = _scene_arrays(_n(quick))
    a["env"] = _pipeline_sky(a["env"])
    texels, up, _, rect = _ground_texels(a)
    meshes = _object_meshes(a)
    return a, texels, up, rect, meshes, _mesh_direct_parts(a, meshes)


@case("spherelights.frame.per_object_ground_near.21k")
def frame_per_object_ground_near(quick: bool) -> dict:
    """The frame of the pipeline's defaults with the ground (``_default_frame``: ``ground_shading="rays"`` with
    ``ground_ray_spacing=0.5``, ``mesh_blockers=True``, ``near_blockers=2``, ``emission_order=6``, HYB, per-object
    blocking, ``ground="reflects"``), the receivers shaded per object as the pipeline does (the own meshes' bits
    cast once, not timed, as the pipeline keeps them), as a frame where the geometry changes: nothing is reused
    from the frame before (a fresh ``FrameReuse`` each frame: every ray cast); peer: the ground and the objects'
    direct light through the spherical lights (``ground_shading="lights"``, ``mesh_blockers=False``)."""
    a, texels, up, rect, meshes, parts = _ground_frame_arrays(quick)
    return {"run": lambda: _default_frame(a, texels, up, rect, meshes, mesh_parts=parts),
            "gflop": _frame_flops(a, "object", True), "items": _n(quick),
            "peer": ("the ground and the objects' direct light through the lights (ground_shading='lights', "
                     "mesh_blockers=False)",
                     lambda: _default_frame(a, texels, up, rect, meshes, ground_shading="lights")),
            "floor": floor(*frame_floor(a, "object", True), FLOOR_FORMULA)}


@case("spherelights.frame.per_object_ground_near_relit.21k")
def frame_per_object_ground_near_relit(quick: bool) -> dict:
    """The frame of ``per_object_ground_near`` when only the lighting changes: nothing moves and the environment turns
    each frame by a rotation it has not had before (about a tilted axis, 0.1 rad a frame more), so the geometry-only
    results of the frame before (the blockers, the texels' and the ground's ray hits, the objects' visible rays,
    ``ground_light``'s samples, the near blockers' caps, the ground's hidden projection at the surface samples) are
    reused through one kept ``FrameReuse``, as
    ``SphereLights`` keeps them, and everything lighting-dependent is computed; peer: the same frames with nothing
    reused (every ray cast)."""
    from prtlab import sh
    from prtlab.spherelights._reuse import FrameReuse

    a, texels, up, rect, meshes, parts = _ground_frame_arrays(quick)
    reuse = FrameReuse()
    turns = [0]
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])

    def relit():  # the next environment: turned 0.1 rad further about ``axis``
        turns[0] += 1
        angle = 0.1 * turns[0]
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
        return {**a, "env": sh.rotate(a["env"], rot, channels=True)}

    return {"run": lambda: _default_frame(relit(), texels, up, rect, meshes, mesh_parts=parts, reuse=reuse),
            "gflop": _frame_flops(a, "object", True), "items": _n(quick),
            "peer": ("every ray cast (nothing reused)",
                     lambda: _default_frame(relit(), texels, up, rect, meshes, mesh_parts=parts)),
            "floor": floor(*frame_floor(a, "object", True), FLOOR_FORMULA)}


#: The object of ``per_object_ground_near_move_one`` (a ball beside the squirrel) and its translations: ``x`` by
#: ``0.05 sin(0.7 n)`` at frame n.
MOVING_OBJECT = 2


def moving_translation(frame: int) -> np.ndarray:
    return np.array([0.05 * np.sin(0.7 * frame), 0.0, 0.0])


@case("spherelights.frame.per_object_ground_near_move_one.21k")
def frame_per_object_ground_near_move_one(quick: bool) -> dict:
    """The frame of ``per_object_ground_near`` when one object moves: a ball (:data:`MOVING_OBJECT`) translated each
    frame to a place it has not had before (:func:`moving_translation`), through one kept ``FrameReuse`` as
    ``SphereLights`` keeps it: the ground's and the texels' rays that cannot meet the ball in either place are kept
    (``_groundrays.ground_hits_update``), the other objects' visible rays that cannot meet it
    (``_meshdirect.mesh_direct_visible_update``), their ``ground_light`` samples whose rays it cannot change
    (``_ground.ground_samples_update``), their near blockers' caps at the surface samples it lies below
    (``_nearcaps.near_blocker_visibility_update``) and the ground's hidden projection at their surface samples; the
    rest (the ball's own receivers and samples, the blockers)
    computed; peer: the same frames with nothing reused (every ray cast)."""
    from prtlab.spherelights._reuse import FrameReuse

    a, texels, up, rect, meshes, parts = _ground_frame_arrays(quick)
    reuse = FrameReuse()
    frames = [0]

    def moved():
        frames[0] += 1
        return MOVING_OBJECT, moving_translation(frames[0])

    return {"run": lambda: _default_frame(a, texels, up, rect, meshes, mesh_parts=parts, reuse=reuse, moved=moved()),
            "gflop": _frame_flops(a, "object", True), "items": _n(quick),
            "peer": ("every ray cast (nothing reused)",
                     lambda: _default_frame(a, texels, up, rect, meshes, mesh_parts=parts, moved=moved())),
            "floor": floor(*frame_floor(a, "object", True), FLOOR_FORMULA)}


@case("spherelights.scene_frame.mesh_blockers.bunny16")
def frame_mesh_blockers(quick: bool) -> dict:
    """A frame of ``data/scenes/bunny_spheres_env.yaml`` (16 lights on the bunny, one per ball; 4,804 receivers of
    which the ground's 1,681) with the pipeline's defaults: the objects' direct light against the meshes
    (``mesh_blockers=True``, ``_meshdirect``; the rays cast at the first frame, not timed, as the poses stand), each
    frame under a sky it has not had before (the scene's, scaled by ``1 + 1e-9 k`` at call ``k``: its SH projected
    and every lighting pass run again, as when a user changes the sky); peer: the spheres' direct light
    (``mesh_blockers=False``: ``near_blockers`` and the paper's SH visibility), its own pipeline object and frames.
    Items: receivers."""
    import dataclasses

    import prtlab
    from prtlab.pipeline import FrameState
    from prtlab.spherelights import SphereLights

    scene = prtlab.load_scene(SCENE)
    pre = precompute_bunny(16, 24, scene)
    spheres = SphereLights(pre.scene, dataclasses.replace(pre.options, mesh_blockers=False), pre.data)

    def frames(p):
        calls = iter(range(1, 1 << 62))
        sky = scene.lights[0]

        def frame():
            state = FrameState.from_scene(scene)
            state.lights = [dataclasses.replace(sky, image=sky.image * (1.0 + 1e-9 * next(calls)))]
            return p.shade(state)

        frame()  # the geometry at the scene's poses (the own meshes' rays, the ground's), once
        return frame

    return {"run": frames(pre), "gflop": None, "items": sum(o.n_vertices for o in scene.objects),
            "peer": ("the spheres' direct light (mesh_blockers=False)", frames(spheres))}


#: Frames of the shipped animation the ``animation`` case steps through (each timed frame at poses no frame before it
#: had: three objects moving).
ANIMATION_FRAMES = 10_000


@case("spherelights.scene_frame.animation.bunny16")
def frame_animation(quick: bool) -> dict:
    """The shipped animation of ``data/scenes/bunny_spheres_env.yaml`` (the bunny turns and slides back, both balls
    roll: every object but the ground moves each frame, as in the paper's squirrel scene) shaded frame after frame at
    the defaults (16 lights on the bunny; one ``SphereLights`` keeping what a frame may reuse); each timed frame a
    time no frame before it had. Peer: the same frames by the paper's method (``prtlab.spherelights.PAPER_OPTIONS``,
    its own precomputation). Items: receivers."""
    import prtlab
    from prtlab.pipeline import FrameState
    from prtlab.spherelights import PAPER_OPTIONS, SphereLights

    scene = prtlab.load_scene(SCENE)
    options = {"n_spheres": {"bunny": 16, "sphere_green": 1, "sphere_orange": 1}, "fit_resolution": 24}
    ours = SphereLights.precompute(scene, options, cache=False, progress=False)
    paper = SphereLights.precompute(scene, {**options, **PAPER_OPTIONS}, cache=False, progress=False)

    def frames(pre):
        steps = iter(range(1, ANIMATION_FRAMES))
        pre.shade(FrameState.from_scene(scene.at_frame(0, ANIMATION_FRAMES)))  # the own meshes' rays, once
        return lambda: pre.shade(FrameState.from_scene(scene.at_frame(next(steps), ANIMATION_FRAMES)))

    return {"run": frames(ours), "gflop": None, "items": sum(o.n_vertices for o in scene.objects),
            "peer": ("the paper's method (prtlab.spherelights.PAPER_OPTIONS)", frames(paper))}


def memory_per_object(objects: dict, arrays=None) -> dict:
    """Bytes of each object's precomputed arrays (``SphereLights.data["objects"]``): all of them, or the names in
    ``arrays`` (``FRAME_ARRAYS``, ``SHADOW_ARRAYS``)."""
    return {name: int(sum(np.asarray(v).nbytes for k, v in data.items() if arrays is None or k in arrays))
            for name, data in objects.items()}


def precompute_bunny(n_bunny: int = 16, grid_resolution: int = 40, scene=None):
    """``SphereLights.precompute`` of ``bunny_spheres_env`` (``n_bunny`` lights on the bunny, one per ball),
    uncached."""
    import prtlab
    from prtlab.spherelights import SphereLights

    scene = prtlab.load_scene(SCENE) if scene is None else scene
    return SphereLights.precompute(scene, {"n_spheres": {"bunny": n_bunny, "sphere_green": 1, "sphere_orange": 1},
                                           "fit_resolution": grid_resolution}, cache=False, progress=False)


@case("spherelights.precompute.bunny16")
def precompute_bunny16(quick: bool) -> dict:
    """The whole precomputation of ``bunny_spheres_env`` (sphere sets, surface samples, albedo SH), uncached, 16
    lights on the bunny; items: lights. ``info``: the precomputed KiB per object, all that is stored and what a frame
    reads (``FRAME_ARRAYS``), and the bunny's lights. Under a second (half that quick, a coarser fit
    grid): 3 repeats."""
    import prtlab

    scene = prtlab.load_scene(SCENE)
    grid = 24 if quick else 40
    info: dict = {}

    def run():
        pre = precompute_bunny(16, grid, scene)
        objects = pre.data["objects"]
        info["bunny_lights"] = len(objects["bunny"]["radii"])
        for name, nbytes in memory_per_object(objects).items():
            info[f"{name}_kib"] = nbytes / 1024
        for name, nbytes in memory_per_object(objects, FRAME_ARRAYS).items():
            info[f"{name}_frame_kib"] = nbytes / 1024
        stored[0] = sum(memory_per_object(objects).values())

    n_lights = 16 + 1 + 1  # 16 on the bunny, one per ball
    stored = [0]
    return {"run": run, "gflop": None, "items": n_lights, "peer": None, "repeats": 3, "info": info,
            "stored_bytes": lambda: stored[0]}
