"""Benchmarks of the spherical-lights pipeline at the paper's squirrel scale (Guerrero et al. 2008, Sec. 8.5).

The squirrel scene: about 21k receiver vertices, 14 leaf spherical lights,
order 4. Here: a squirrel-like object of 8 lights plus 6 balls of one
light each (7 objects), 92 surface samples per light, receivers on a
ground grid and around the objects. Cases: a whole frame (first pass +
second pass) with per-object and per-sphere blocking, shadows only, and
the precomputed memory per object.
"""

from __future__ import annotations

import numpy as np

from prtlab.bench import case
from prtlab.geometry import geodesic_directions
from prtlab.sh import gaunt_tensor
from prtlab.spherelights import first_pass, second_pass, voronoi_cell_sums

ORDER = 4
N_LIGHTS = 14
N_RECEIVERS = 21_000


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
    albedo = np.zeros((N_LIGHTS, ORDER * ORDER, 3))
    albedo[:, 0] = 0.7 * np.sqrt(4 * np.pi)
    env = np.zeros((ORDER * ORDER, 3))
    env[0] = [3.0, 2.8, 2.5]
    env[2] = [0.8, 0.8, 0.9]
    env[1:, :] += 0.05 * rng.normal(size=(ORDER * ORDER - 1, 3))
    return dict(points=points, normals=normals, centres=centres, radii=radii, sl_object=sl_object, inter=inter,
                rot=rot, spts=spts, snrm=snrm, valid=valid, albedo=albedo, env=env)


def _frame(a, blocking, indirect=True, exp_method="hyb"):
    emission = np.zeros((N_LIGHTS, ORDER * ORDER, 3))
    if indirect:
        emission = first_pass(a["spts"], a["snrm"], a["valid"], a["centres"], a["radii"], a["env"],
                              voronoi_cell_sums(ORDER), a["albedo"], exp_method=exp_method)
    return second_pass(a["points"], a["normals"], a["centres"], a["radii"], a["sl_object"], a["inter"], a["rot"],
                       emission, a["env"], blocking=blocking, exp_method=exp_method, indirect=indirect)


def _hyb_flops(order: int = ORDER, squarings: float = 4.0) -> float:
    """One HYB exponential: OL (~3 n2 + 35) plus the squarings (3 flops per Gaunt entry each)."""
    return 3 * order * order + 35 + squarings * 3 * gaunt_tensor(order).nnz


def _ol_flops(order: int = ORDER) -> float:
    """One OL exponential: the norm, the table lookup, the exp of the DC and one scaled copy (~3 n2 + 35)."""
    return 3 * order * order + 35


def _frame_flops(n_recv: int, blocking: str, indirect: bool, exp_method: str = "hyb") -> float:
    """Counted work of one frame (dominant terms): per receiver, S rotated blocker logs (~3 n2 + 40 each),
    the front sums (S^2 / 2 or ~S n_l / 2 vector adds of n2), 1 + 2S exponentials, dot products."""
    n2 = ORDER * ORDER
    s = N_LIGHTS
    exp_flops = _hyb_flops() if exp_method == "hyb" else _ol_flops()
    per = s * (3 * n2 + 40) + exp_flops + 2 * n2 * 3
    if indirect:
        adds = s * s / 2 if blocking == "sphere" else s * 8 / 2 + s
        per += adds * n2 + 2 * s * exp_flops + s * (2 * n2 + 3 * n2 * 2 + 40)
    samples = N_LIGHTS * 92 * (per - (0 if not indirect else 2 * s * exp_flops)) if indirect else 0
    return (n_recv * per + samples) / 1e9


def _n(quick):
    return 4_000 if quick else N_RECEIVERS


@case("spherelights.frame.per_object.21k")
def frame_per_object(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"run": lambda: _frame(a, "object"), "gflop": _frame_flops(_n(quick), "object", True),
            "items": _n(quick), "peer": ("per-sphere blocking", lambda: _frame(a, "sphere"))}


@case("spherelights.frame.per_sphere.21k")
def frame_per_sphere(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"run": lambda: _frame(a, "sphere"), "gflop": _frame_flops(_n(quick), "sphere", True),
            "items": _n(quick), "peer": None}


@case("spherelights.frame.per_object_ol.21k")
def frame_per_object_ol(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"run": lambda: _frame(a, "object", exp_method="ol"),
            "gflop": _frame_flops(_n(quick), "object", True, exp_method="ol"), "items": _n(quick),
            "peer": ("HYB exponentiation", lambda: _frame(a, "object", exp_method="hyb"))}


@case("spherelights.frame.shadows_only.21k")
def frame_shadows_only(quick: bool) -> dict:
    a = _scene_arrays(_n(quick))
    return {"run": lambda: _frame(a, "object", indirect=False), "gflop": _frame_flops(_n(quick), "object", False),
            "items": _n(quick), "peer": None}
