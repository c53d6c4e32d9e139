"""The residual gather: the part of a source's radiance that its PCA basis misses, gathered by ray casting.

An extension of Iwasaki et al. 2007 (issue 18). A source's outgoing radiance ``colour_k L_k`` reaches the
receivers through its basis radiance fields only as its projection ``P`` on the ``N`` PCA functions
(Eq. 14); what the basis cannot hold (the shadow of an object that moved since the basis was trained, a
light in a pose the training never saw) is lost. Per frame and bounce the residual
``r_k = colour_k L_k - P(colour_k L_k)`` at the sources' vertices is gathered instead, as a one-bounce
final gather of that residual alone:

* every receiver point casts ``n`` rays per source (stratified: a jittered grid whose random numbers are a
  hash of ``(seed, source, point, ray)``, so one ray can be made again alone) into the scene at the
  frame's poses: uniform in the cone of the source's bounding sphere, or cosine-weighted over the
  hemisphere from a point inside that sphere; a ray whose first hit is the front of the source carries
  the residual interpolated at the hit (barycentrically, as the basis radiance fields interpolate ``Psi``);
  with ``full`` a point that sees the sphere's cone small casts fewer of the ``n`` rays (a grid of its own);
* ``L_k'(x) += sum_rays g_k'(w) (n . w)+ / (n pdf(w)) sum_k h_k(-w) r_k(hit)``: unbiased for the
  residual with exact visibility, near or far (a source 3 cm away as well as a small one far off).

The hits (:class:`ResidualHits`) depend on the poses only and are reused while they stand; when objects
move, only the rays whose first hit they may change are cast again (``previous=`` of
:func:`residual_hits`). Per bounce the gather is a fixed sparse linear map of the residual
(:func:`gather_operator`, its hits in compact form, applied by :func:`apply_gather`); :func:`gather_residual` is its float64
specification. The noise of ``n`` rays falls on the residual alone, which is small where the basis holds
the radiance.

Near hits: a source's radiance is held per vertex, so a receiver a few centimetres above it (the torus over
its own shadow on the floor) gathers the radiance interpolated between vertices coarser than that shadow.
:func:`near_hits` picks the hits nearer their receiver point than a multiple of the hit triangle's longest
edge, and :func:`near_hit_correction` adds over those rays ``factor (e - interp(v))``: the source's radiance
``e`` evaluated at the hit point less the vertex-interpolated ``v`` that the basis and the residual together
carry there, so that each such ray carries ``e``, counted once.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from prtlab import brdf
from prtlab._validate import check_choice, check_float
from prtlab.brdf._kernels import factor_at, tangent_frame_at
from prtlab.geometry import _embree

from ._kernels import SERIAL_ITEMS

__all__ = ["ResidualHits", "GatherOperator", "cosine_directions", "residual_hits", "gather_residual",
           "gather_operator", "apply_gather", "pack_operators", "PackedGather", "bounce_rgb", "near_hits",
           "near_hit_correction"]


@dataclass(frozen=True)
class ResidualHits:
    """Rays of one receiver that hit the front of one source, in the order of their ``rays`` ids
    (``point * m + j``, ``m`` rays a point): ``rows`` (H,) receiver points, ``factor`` (H, K', K)
    ``g_k'(w) h_k(-w)`` times the ray's weight ``(n . w)+ / (m pdf)``, the hit ``triangles`` (H,) of the source's
    ``faces`` (F, 3) and their ``uv`` (H, 2) (the caster's barycentrics); ``vertices`` (H, 3) and ``bary``
    (H, 3) of the hits follow."""

    rows: np.ndarray
    factor: np.ndarray
    rays: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    faces: np.ndarray

    @property
    def vertices(self) -> np.ndarray:
        return np.asarray(self.faces, np.int64)[self.triangles]

    @property
    def bary(self) -> np.ndarray:
        return np.stack([1.0 - self.uv[:, 0] - self.uv[:, 1], self.uv[:, 0], self.uv[:, 1]], axis=1)

    def arrays(self) -> tuple:
        """The per-hit arrays (``faces`` is the source's)."""
        return self.rows, self.factor, self.rays, self.triangles, self.uv


@dataclass(frozen=True)
class GatherOperator:
    """The gather of one source on one receiver in compact form: the hits of each receiver point ``v`` are
    ``starts[v]:starts[v + 1]``, each a ``triangle`` of ``faces`` (int32), its ``uv`` (float32 when the caster's
    barycentrics are float32 values, as Embree's are, else float64) and ``factor`` (H, K', K); 20 bytes a hit
    for K = K' = 1. ``L[v, k', c] = sum_h factor[h, k', k] sum_j bary_j(h) r[faces[triangle[h], j], k, c]``."""

    starts: np.ndarray
    faces: np.ndarray
    triangles: np.ndarray
    uv: np.ndarray
    factor: np.ndarray


# ------------------------------------------------------------------ kernels (counter-based rays)


@numba.njit(cache=True, inline="always")
def _mix(z):
    """SplitMix64's finaliser (uint64 -> uint64)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True, inline="always")
def _uniform(key, counter):
    """A uniform double in [0, 1) of stream ``key`` at ``counter`` (SplitMix64)."""
    z = _mix(key + (counter + np.uint64(1)) * np.uint64(0x9E3779B97F4A7C15))
    return float(z >> np.uint64(11)) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True, inline="always")
def _frame(nx, ny, nz):
    """Tangents ``(t, b)`` of a unit normal (Duff et al. 2017)."""
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    return 1.0 + sign * nx * nx * a, sign * b, -sign * nx, b, sign + ny * ny * a, -ny


#: Fewest rays a receiver point casts toward a source with ``full > 0`` (a 2 x 2 grid).
MIN_RAYS = 4

#: A ray with ``facing . w`` above this never meets the front of a flat source of normal ``facing``
#: (:func:`_facing`: the vertex normals agree within ``1e-12``, so the interpolated shading normal's product
#: with ``w`` stays positive).
FACING_MARGIN = 1e-9


@numba.njit(cache=True, inline="always")
def _point_grid(rows, side, cos_c, cos_max, q, full):
    """``(rows, side)`` of one point's grid toward a source whose bounding cone (half-angle ``asin q``, cosine
    ``cos_max``) is seen at ``cos_c`` from the normal: ``rows side`` rays times ``omega / full`` (``omega`` the
    cone's solid angle times the largest cosine to the normal inside it), at least ``MIN_RAYS``, at most
    ``rows side``; ``(rows, side)`` itself if ``full`` is 0."""
    m = rows * side
    if not full > 0.0:
        return rows, side
    sin_c = math.sqrt(max(1.0 - cos_c * cos_c, 0.0))
    top = 1.0 if cos_c >= cos_max else max(cos_c * cos_max + sin_c * q, 0.0)
    want = m * 2.0 * math.pi * (1.0 - cos_max) * top / full
    if want >= m:
        return rows, side
    n = max(MIN_RAYS, min(m, int(math.ceil(want))))
    s = max(1, int(math.sqrt(n)))
    while s * s > n:
        s -= 1
    while (s + 1) * (s + 1) <= n:
        s += 1
    return max(1, n // s), s


@numba.njit(cache=True, inline="always")
def _cone(points, normals, p, centre, radius, rows, side, full):
    """Point ``p``'s view of a source's bounding sphere ``(centre, radius)`` as ``_ray`` takes it: ``(rows', side',
    inside, q, cos_max, d0, d1, d2, dist)``, its grid (``_point_grid`` with ``full > 0`` outside the sphere, else
    ``(rows, side)``: only its rays ``j < rows' side'`` may be cast), whether it lies inside the sphere, the cone's
    sine and cosine, the vector to the centre and its length."""
    x0, x1, x2 = points[p, 0], points[p, 1], points[p, 2]
    d0, d1, d2 = centre[0] - x0, centre[1] - x1, centre[2] - x2
    dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    inside = dist <= 1.0001 * radius
    q = radius / max(dist, radius)
    cos_max = math.sqrt(max(1.0 - q * q, 0.0))
    if full > 0.0 and not inside:
        n0, n1, n2 = normals[p, 0], normals[p, 1], normals[p, 2]
        rows, side = _point_grid(rows, side, (d0 * n0 + d1 * n1 + d2 * n2) / dist, cos_max, q, full)
    return rows, side, inside, q, cos_max, d0, d1, d2, dist


@numba.njit(cache=True, inline="always")
def _point_cone(points, normals, p, centre, radius, rows, side, full, key):
    """What every ray of point ``p`` toward a source shares (``_ray``'s per-point work, done once a point by a
    kernel that casts all of a point's rays): ``(rows', side', inside, cos_max, weight, t0, t1, t2, b0, b1, b2,
    a0, a1, a2, stream)``, its grid and the side of the sphere (``_cone``), the weight of a ray before its cosine,
    the frame ``(t, b, a)`` about the sampling axis and the point's random stream."""
    rows, side, inside, q, cos_max, d0, d1, d2, dist = _cone(points, normals, p, centre, radius, rows, side, full)
    m = rows * side
    if inside:  # inside the sphere: cosine-weighted about the normal
        a0, a1, a2 = normals[p, 0], normals[p, 1], normals[p, 2]
        weight = math.pi / m
    else:
        a0, a1, a2 = d0 / dist, d1 / dist, d2 / dist
        weight = 2.0 * math.pi * (1.0 - cos_max) / m
    t0, t1, t2, b0, b1, b2 = _frame(a0, a1, a2)
    return (rows, side, inside, cos_max, weight, t0, t1, t2, b0, b1, b2, a0, a1, a2,
            _mix(key ^ _mix(np.uint64(p))))


#: ``box`` of a source whose box is not known (every ray meets it).
NO_BOX = np.array([-np.inf, -np.inf, -np.inf, np.inf, np.inf, np.inf])


@numba.njit(cache=True, inline="always")
def _clip_to_box(o0, o1, o2, w0, w1, w2, tmax, box):
    """The segment ``o + t w``, ``0 <= t <= tmax``, clipped to the box ``box`` (6,: lowest then highest corner): the
    ``t`` at which it leaves the box, or 0 if it misses the box (slab test)."""
    enter, leave = 0.0, tmax
    for axis in range(3):
        start, step = (o0, o1, o2)[axis], (w0, w1, w2)[axis]
        lo, hi = box[axis], box[3 + axis]
        if step == 0.0:
            if start < lo or start > hi:
                return 0.0
        else:
            t1, t2 = (lo - start) / step, (hi - start) / step
            enter, leave = max(enter, min(t1, t2)), min(leave, max(t1, t2))
    return leave if enter <= leave else 0.0


@numba.njit(cache=True, inline="always")
def _ray(points, normals, p, j, centre, radius, bound, key, rows, side, eps, full, facing, box, out):
    """Ray ``j`` of point ``p`` toward a source: ``out`` = (origin xyz, direction xyz, weight, tmax).

    Uniform in the cone of the sphere ``(centre, radius)``, cosine-weighted on the hemisphere from inside it;
    the origin is moved ``eps`` off the surface on the ray's side (:func:`prtlab.geometry.offset_origins`);
    ``tmax`` is where the ray leaves the sphere ``(centre, bound)`` (0: it misses it, or weight 0). With
    ``full > 0`` a point outside the sphere casts only the rays ``j`` of its own grid (``_point_grid``), each
    weighted by that grid's size; the others get weight and ``tmax`` 0. ``facing`` (3,): the unit normal shared
    by every vertex of a flat source (:func:`_facing`), or zeros: a ray with ``facing . w > FACING_MARGIN``
    cannot meet the source's front, so its ``tmax`` is 0 (its weight stands). ``box`` (6,): the lowest then the
    highest corner of a box holding the source's triangles (:func:`_source_box`, or :data:`NO_BOX`): ``tmax`` is
    cut to where the ray leaves it, 0 if it misses it (no hit of the source lies beyond).
    """
    _ray_at(points, normals, p, j, _point_cone(points, normals, p, centre, radius, rows, side, full, key), centre,
            bound, eps, facing, box, out)


@numba.njit(cache=True, inline="always")
def _ray_at(points, normals, p, j, cone, centre, bound, eps, facing, box, out):
    """``_ray`` from point ``p``'s ``_point_cone`` tuple ``cone``."""
    rows, side, inside, cos_max, weight, t0, t1, t2, b0, b1, b2, a0, a1, a2, stream = cone
    x0, x1, x2 = points[p, 0], points[p, 1], points[p, 2]
    n0, n1, n2 = normals[p, 0], normals[p, 1], normals[p, 2]
    if j >= rows * side:
        out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7] = x0, x1, x2, n0, n1, n2, 0.0, 0.0
        return
    u1 = ((j // side) + _uniform(stream, np.uint64(2 * j))) / rows
    u2 = ((j % side) + _uniform(stream, np.uint64(2 * j + 1))) / side
    phi = 2.0 * math.pi * u2
    if inside:
        r = math.sqrt(u1)
        l0, l1, l2 = r * math.cos(phi), r * math.sin(phi), math.sqrt(max(1.0 - u1, 0.0))
    else:
        cos_t = 1.0 - u1 * (1.0 - cos_max)
        sin_t = math.sqrt(max(1.0 - cos_t * cos_t, 0.0))
        l0, l1, l2 = sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t
    w0 = t0 * l0 + b0 * l1 + a0 * l2
    w1 = t1 * l0 + b1 * l1 + a1 * l2
    w2 = t2 * l0 + b2 * l1 + a2 * l2
    cos_n = w0 * n0 + w1 * n1 + w2 * n2
    weight = weight * max(cos_n, 0.0) if not inside else weight
    s = -1.0 if cos_n < 0.0 else 1.0
    o0, o1, o2 = x0 + eps * s * n0, x1 + eps * s * n1, x2 + eps * s * n2
    # leaving the bounding sphere: t = -b + sqrt(b^2 - c)
    e0, e1, e2 = o0 - centre[0], o1 - centre[1], o2 - centre[2]
    bb = e0 * w0 + e1 * w1 + e2 * w2
    disc = bb * bb - (e0 * e0 + e1 * e1 + e2 * e2 - bound * bound)
    tmax = -bb + math.sqrt(disc) if disc >= 0.0 and weight > 0.0 else 0.0
    if facing[0] * w0 + facing[1] * w1 + facing[2] * w2 > FACING_MARGIN:
        tmax = 0.0  # away from a flat source's front: no hit of it can count
    if tmax > 0.0:  # the source's hits lie in its box: past it (or missing it) the ray cannot hit the source
        tmax = _clip_to_box(o0, o1, o2, w0, w1, w2, tmax, box)
    out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7] = o0, o1, o2, w0, w1, w2, weight, max(tmax, 0.0)


@numba.njit(cache=True, parallel=True)
def _rays_kernel(points, normals, point, ray, centre, radius, bound, key, rows, side, eps, full, facing, box,
                 out):
    """``_ray`` for each ``(point[i], ray[i])``: ``out`` (Q, 8)."""
    for i in numba.prange(point.shape[0]):
        _ray(points, normals, point[i], ray[i], centre, radius, bound, key, rows, side, eps, full, facing, box,
             out[i])


_FLOAT32_MAX = float(np.finfo(np.float32).max)

#: ``_cast_kernel``'s per-ray state: not cast (``tmax`` 0), cast without hitting the source's front, hit it.
_NOT_LIVE, _CAST, _HIT = 0, 1, 2


@numba.njit(cache=True, inline="always")
def _stage(buf, tnear):
    """The ray ``buf`` (``_ray``'s output, ``tmax > 0``) staged from ``tnear`` on as ``_stage_ray`` stages it:
    ``(cast, ox, oy, oz, dx, dy, dz, tfar)``, ``cast`` False if its float32 ``tfar`` is not positive."""
    dx, dy, dz = buf[3], buf[4], buf[5]
    length = np.sqrt(dx * dx + dy * dy + dz * dz)
    dx /= length
    dy /= length
    dz /= length
    tfar = buf[7] - tnear
    if tfar > _FLOAT32_MAX:
        tfar = np.inf
    cast = np.float32(tfar) > 0.0
    return cast, buf[0] + tnear * dx, buf[1] + tnear * dy, buf[2] + tnear * dz, dx, dy, dz, tfar


@numba.njit(cache=True, inline="always")
def _hits_source(buf, tnear, source, function, scene, f32, u32, address):
    """Traces the ray ``buf`` (``_ray``'s output, ``tmax > 0``) from ``tnear`` on through ``rtcIntersect1``
    (``_stage``, in the ray slot ``f32``/``u32`` at ``address``): whether its first hit is object ``source`` (then
    ``u32``/``f32`` hold its triangle and barycentrics)."""
    cast, ox, oy, oz, dx, dy, dz, tfar = _stage(buf, tnear)
    if not cast:
        return False
    _embree.set_ray(f32, u32, ox, oy, oz, dx, dy, dz, tfar)
    _embree.rtc_call(function, scene, address)
    return u32[_embree.HIT_GEOM] != _embree.INVALID_ID and np.int64(u32[_embree.HIT_GEOM]) == source


@numba.njit(cache=True, inline="always")
def _add_lane(buf, tnear, f32, u32, valid, lane):
    """Stages the ray ``buf`` (``_stage``) into lane ``lane`` of a packet slot; whether it is cast (then the lane is
    valid)."""
    cast, ox, oy, oz, dx, dy, dz, tfar = _stage(buf, tnear)
    if cast:
        _embree.set_packet_ray(f32, u32, lane, ox, oy, oz, dx, dy, dz, tfar)
        valid[lane] = -1
    return cast


@numba.njit(cache=True, inline="always")
def _trace_lanes(tracer, f32, valid, n_lanes):
    """``rtcIntersect16`` of the first ``n_lanes`` lanes of a packet slot (the others invalid)."""
    for k in range(n_lanes, _embree.PACKET):
        valid[k] = 0
    _embree.rtc_call_packet(tracer.function, valid.ctypes.data, tracer.scene, f32.ctypes.data)


@numba.njit(cache=True, inline="always")
def _lane_hits(u32, lane, source):
    """Whether the first hit of packet lane ``lane`` is object ``source``."""
    g = u32[_embree.HIT_GEOM * _embree.PACKET + lane]
    return g != _embree.INVALID_ID and np.int64(g) == source


#: Receiver points a task of ``_cast_kernel`` takes when it casts every ray of every point: ray ``j`` of 16
#: neighbouring points (nearly parallel rays from nearby origins) fills a packet.
_POINTS_PER_PACKET = 16


def _cast_tasks(n_rays: int, m: int, every: bool) -> int:
    """Tasks (ray slots) of one ``_cast_kernel`` call."""
    if every:
        return -(-(n_rays // max(m, 1)) // _POINTS_PER_PACKET)
    return -(-n_rays // _embree.RAYS_PER_TASK)


@numba.njit(cache=True, parallel=True, nogil=True)
def _cast_kernel(points, normals, point, ray, n_rays, centre, radius, bound, key, rows, side, eps, full, facing,
                 box, tnear, source, tracer, weighing, state, triangle, uv, factor):
    """``_ray`` then ``RayCaster.closest_hit`` for each ray ``i < n_rays``: ``(point[i], ray[i])``, or with
    ``point`` empty ``(i // m, i % m)`` (every ray of every point), then ``_weigh_hit`` of a hit on the source.
    ``state[i]``: ``_NOT_LIVE`` (``tmax`` 0, not cast), ``_CAST`` (cast, its first hit not the source's front) or
    ``_HIT`` (the first hit is the front of object ``source``: its ``triangle[i]``, float32 ``uv[i]`` and
    ``factor[i]``; ``weighing``: ``_weighing``'s tuple).
    Each ray is staged as ``_stage_ray`` stages it (no normals: the origin is already offset) and traced through
    ``tracer`` (a ``_raycast._Tracer`` of closest hits): one ray at a time through ``rtcIntersect1``, or with
    ``tracer.packet`` the next 16 rays cast of a task at a time through ``rtcIntersect16``: the same hits.
    Threads take tasks from a shared counter (``_cast_tasks``): ``RAYS_PER_TASK`` rays of the list, or
    ``_POINTS_PER_PACKET`` points, ray ``j`` of each point after ray ``j - 1`` of all (each point's ``_point_cone``
    made once for its rays; rays past the point's own grid are not made)."""
    m = rows * side
    every = point.shape[0] == 0
    step = _embree.RAYS_PER_TASK
    w = _embree.PACKET
    group = _POINTS_PER_PACKET
    n_points = n_rays // m if every else 0
    per_task = group * m if every else step
    n_tasks = tracer.slot_f32.shape[0]
    counter = np.zeros(1, dtype=np.int64)
    for _ in numba.prange(tracer.threads):
        buf = np.empty(8)
        lanes = np.empty(w, np.int64)
        lane_rays = np.empty((w, 8))
        live = np.zeros(group, np.int64)
        cone_grid = np.zeros((group, 2), np.int64)
        cone_inside = np.zeros(group, np.bool_)
        cone_values = np.zeros((group, 11))
        cone_stream = np.zeros(group, np.uint64)
        g = np.empty(weighing[3].shape[0])
        h = np.empty(weighing[7].shape[0])
        while True:
            block = _embree.fetch_add(counter, 1)
            if block >= n_tasks:
                break
            f32, u32 = tracer.slot_f32[block], tracer.slot_u32[block]
            address = f32.ctypes.data
            valid = tracer.valid[block]
            n_lanes = 0
            if every:
                for k in range(group):
                    p = block * group + k
                    live[k] = 0
                    if p < n_points:  # the point's _point_cone, kept for its rays
                        cone = _point_cone(points, normals, p, centre, radius, rows, side, full, key)
                        cone_grid[k, 0], cone_grid[k, 1], cone_inside[k], cone_stream[k] = cone[0], cone[1], \
                            cone[2], cone[14]
                        v = cone_values[k]
                        v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8], v[9], v[10] = cone[3:14]
                        live[k] = cone[0] * cone[1]
                        for j in range(live[k], m):
                            state[p * m + j] = _NOT_LIVE
            for t in range(per_task + 1):
                if t < per_task:
                    if every:
                        k, j = t % group, t // group
                        p = block * group + k
                        if j >= live[k]:  # past the point's own grid (or no point): not cast
                            continue
                        i = p * m + j
                        v = cone_values[k]
                        _ray_at(points, normals, p, j, (cone_grid[k, 0], cone_grid[k, 1], cone_inside[k], v[0], v[1],
                                                        v[2], v[3], v[4], v[5], v[6], v[7], v[8], v[9], v[10],
                                                        cone_stream[k]), centre, bound, eps, facing, box, buf)
                    else:
                        i = block * step + t
                        if i >= n_rays:
                            continue
                        p, j = point[i], ray[i]
                        _ray(points, normals, p, j, centre, radius, bound, key, rows, side, eps, full, facing, box,
                             buf)
                    state[i] = _NOT_LIVE
                    if not buf[7] > 0.0:
                        continue
                    state[i] = _CAST
                    if not tracer.packet:
                        if _hits_source(buf, tnear, source, tracer.function, tracer.scene, f32, u32, address):
                            triangle[i] = np.int32(u32[_embree.HIT_PRIM])
                            uv[i, 0] = f32[_embree.HIT_U]
                            uv[i, 1] = f32[_embree.HIT_V]
                            if _weigh_hit(buf, normals, p, np.int64(triangle[i]), np.float64(uv[i, 0]),
                                          np.float64(uv[i, 1]), weighing, g, h, factor[i]):
                                state[i] = _HIT
                        continue
                    if _add_lane(buf, tnear, f32, u32, valid, n_lanes):
                        lanes[n_lanes] = i
                        lane_rays[n_lanes] = buf
                        n_lanes += 1
                    if n_lanes < w:
                        continue
                if n_lanes == 0:
                    continue
                _trace_lanes(tracer, f32, valid, n_lanes)
                for k in range(n_lanes):
                    if _lane_hits(u32, k, source):
                        at = lanes[k]
                        triangle[at] = np.int32(u32[_embree.HIT_PRIM * w + k])
                        uv[at, 0] = f32[_embree.HIT_U * w + k]
                        uv[at, 1] = f32[_embree.HIT_V * w + k]
                        p = at // m if every else point[at]
                        if _weigh_hit(lane_rays[k], normals, p, np.int64(triangle[at]), np.float64(uv[at, 0]),
                                      np.float64(uv[at, 1]), weighing, g, h, factor[at]):
                            state[at] = _HIT
                n_lanes = 0


@numba.njit(cache=True, inline="always")
def _local_unit(x, y, z, n0, n1, n2):
    """``(x, y, z)`` in the local frame of the normal ``n`` (``brdf.to_local``: both normalised, the tangents of
    ``tangent_frame``), normalised again, as :meth:`SeparableBRDF.g` and ``h`` take it."""
    length = np.sqrt(x * x + y * y + z * z)
    x, y, z = x / length, y / length, z / length
    n0, n1, n2, t0, t1, t2, b0, b1, b2 = tangent_frame_at(n0, n1, n2)
    lx = t0 * x + t1 * y + t2 * z
    ly = b0 * x + b1 * y + b2 * z
    lz = n0 * x + n1 * y + n2 * z
    length = np.sqrt(lx * lx + ly * ly + lz * lz)
    return lx / length, ly / length, lz / length


@numba.njit(cache=True, inline="always")
def _weigh_hit(buf, normals, p, f, u, v, weighing, g, h, factor):
    """The hit of the ray ``buf`` (``_ray``'s output) of point ``p`` on triangle ``f`` of the source at
    barycentrics ``(u, v)``: whether it meets the front of the interpolated shading normal, and then ``factor[k', k]
    = weight g_k'(w) h_k(-w)`` in the receiver's and the source's local frames (``_cast``'s numpy weighing, by
    :func:`prtlab.brdf._kernels.factor_at`). ``weighing``: ``_weighing``'s tuple; ``g``, ``h``: scratch."""
    faces, vertex_normals, g_nodes, g_values, g_freq, g_parity, h_nodes, h_values, h_freq, h_parity, level = weighing
    i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
    b0 = 1.0 - u - v
    s0 = b0 * vertex_normals[i0, 0] + u * vertex_normals[i1, 0] + v * vertex_normals[i2, 0]
    s1 = b0 * vertex_normals[i0, 1] + u * vertex_normals[i1, 1] + v * vertex_normals[i2, 1]
    s2 = b0 * vertex_normals[i0, 2] + u * vertex_normals[i1, 2] + v * vertex_normals[i2, 2]
    length = max(np.sqrt(s0 * s0 + s1 * s1 + s2 * s2), 1e-300)
    s0, s1, s2 = s0 / length, s1 / length, s2 / length
    w0, w1, w2 = buf[3], buf[4], buf[5]
    if not s0 * w0 + s1 * w1 + s2 * w2 < 0.0:  # the back of a surface emits nothing
        return False
    if level:  # factor_at gives every direction the tables' one value: no local frames, no angles
        for kp in range(g.shape[0]):
            for k in range(h.shape[0]):
                factor[kp, k] = buf[6] * g_values[kp, 0] * h_values[k, 0]
        return True
    x, y, z = _local_unit(w0, w1, w2, normals[p, 0], normals[p, 1], normals[p, 2])
    factor_at(g_nodes, g_values, g_freq, g_parity, x, y, z, g)
    x, y, z = _local_unit(-w0, -w1, -w2, s0, s1, s2)
    factor_at(h_nodes, h_values, h_freq, h_parity, x, y, z, h)
    for kp in range(g.shape[0]):
        for k in range(h.shape[0]):
            factor[kp, k] = buf[6] * g[kp] * h[k]
    return True


def _weighing(receiver_sep, source) -> tuple:
    """What ``_weigh_hit`` reads of a (receiver, source) pair: the source's faces (int64) and world vertex normals,
    then the receiver's ``g`` and the source's ``h`` tables (nodes, values, frequencies, parities), and whether
    both are level (:func:`_level_tables`: a Lambertian pair)."""
    faces, vertex_normals, sep = source[:3]
    g_nodes, g_values = receiver_sep._ext(receiver_sep.theta_in, receiver_sep.g_radial, 0.5 * np.pi)
    h_max = 0.5 * np.pi if sep.parameterisation == "plain" else np.pi
    h_nodes, h_values = sep._ext(sep.theta_out, sep.h_radial, h_max)
    level = _level_tables(g_values, receiver_sep.freq, receiver_sep.parity) and _level_tables(h_values, sep.freq,
                                                                                            sep.parity)
    return (np.ascontiguousarray(faces, np.int64), np.ascontiguousarray(vertex_normals, np.float64), g_nodes,
            g_values, np.ascontiguousarray(receiver_sep.freq, np.int64),
            np.ascontiguousarray(receiver_sep.parity, np.int64), h_nodes, h_values,
            np.ascontiguousarray(sep.freq, np.int64), np.ascontiguousarray(sep.parity, np.int64), level)


def _level_tables(values, freq, parity) -> bool:
    """Whether :func:`prtlab.brdf._kernels.factor_at` gives every direction the same factors, each row's one value:
    every term a cosine of frequency 0 and each row of ``values`` one value at every node (then it returns that
    value exactly)."""
    return bool(np.all(np.asarray(freq) == 0) and np.all(np.asarray(parity) == 0) and np.all(values == values[:, :1]))


#: ``_recast_kernel``'s per-ray state: not flagged, flagged and not cast (``tmax`` 0), cast, hit the source.
_UNFLAGGED, _FLAGGED, _FLAGGED_CAST, _FLAGGED_HIT = 0, 1, 2, 3

#: Candidate points a thread takes at a time in ``_recast_kernel`` (one ray slot each).
_POINTS_PER_TASK = 4


@numba.njit(cache=True, inline="always")
def _meets(buf, spheres):
    """Whether the ray ``buf`` (``_ray``'s output), up to its ``tmax``, meets any of ``spheres`` (S, 4)."""
    if buf[7] > 0.0:
        for k in range(spheres.shape[0]):
            c0, c1, c2 = spheres[k, 0] - buf[0], spheres[k, 1] - buf[1], spheres[k, 2] - buf[2]
            t = min(max(c0 * buf[3] + c1 * buf[4] + c2 * buf[5], 0.0), buf[7])
            g0, g1, g2 = c0 - t * buf[3], c1 - t * buf[4], c2 - t * buf[5]
            if g0 * g0 + g1 * g1 + g2 * g2 <= spheres[k, 3] * spheres[k, 3]:
                return True
    return False


#: Widening (radians) of the angular tests of ``_cells_meeting``: far above the rounding of a ray's direction.
_ROW_MARGIN = 1e-6

#: Least angle (radians) between a moved sphere's cone and the grid's axis (either way) for which
#: ``_cells_meeting`` tests the columns (azimuths) too; nearer the axis every column is kept.
_AXIS_GAP = 1e-3


@numba.njit(cache=True, inline="always")
def _cells_meeting(points, normals, p, centre, radius, rows, side, eps, full, spheres, need, band):
    """The cells of point ``p``'s grid (``_ray``'s ``(u1, u2)`` strata, ray ``j`` in row ``j // side'`` and column
    ``j % side'``) that hold a ray which may meet one of ``spheres``: ``need[j]`` for the point's ``rows' side'``
    rays (``_point_grid``); returns ``(rows', side')``. ``band`` (at least ``rows side + 1``): scratch.

    Conservative: a ray meets a sphere ``(c, R)`` only if its angle to the direction ``e`` of ``c`` from the point
    is at most ``alpha = asin((R + eps |n|) / |c - x|)`` (its origin lies ``eps |n|`` off the point). A ray's angle
    to its axis (the normal, or the source's centre) lies in its row's band, so by the triangle inequality a row
    whose band is farther than ``alpha`` from ``e``'s angle ``theta`` holds none; and its azimuth about the axis
    (``2 pi u2`` in ``_frame``'s tangents) lies in its column's, while the cap of radius ``alpha`` about ``e``
    (when it holds neither end of the axis) spans the azimuths within ``asin(sin alpha / sin theta)`` of ``e``'s,
    so a column farther than that holds none. Both tests are widened by ``_ROW_MARGIN``; the columns are tested
    only where the cap is at least ``_AXIS_GAP`` from the axis and the normal is of unit length within ``1e-12``.
    Every ray is needed from inside a sphere or with a normal not of unit length within ``1e-6``."""
    x0, x1, x2 = points[p, 0], points[p, 1], points[p, 2]
    n0, n1, n2 = normals[p, 0], normals[p, 1], normals[p, 2]
    d0, d1, d2 = centre[0] - x0, centre[1] - x1, centre[2] - x2
    dist = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    inside = dist <= 1.0001 * radius
    q = radius / max(dist, radius)
    cos_max = math.sqrt(max(1.0 - q * q, 0.0))
    rp, sp = rows, side
    if full > 0.0 and not inside:
        rp, sp = _point_grid(rows, side, (d0 * n0 + d1 * n1 + d2 * n2) / dist, cos_max, q, full)
    length = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    every = not abs(length - 1.0) <= 1e-6
    azimuths = abs(length - 1.0) <= 1e-12
    if inside:
        a0, a1, a2 = n0 / length, n1 / length, n2 / length
        t0, t1, t2, b0, b1, b2 = _frame(n0, n1, n2)  # the tangents _ray samples about
    else:
        a0, a1, a2 = d0 / dist, d1 / dist, d2 / dist
        t0, t1, t2, b0, b1, b2 = _frame(a0, a1, a2)
    offset = eps * length * (1.0 + 1e-9) + 1e-300
    for j in range(rp * sp):
        need[j] = every
    if every:
        return rp, sp
    banded = False
    for k in range(spheres.shape[0]):
        e0, e1, e2 = spheres[k, 0] - x0, spheres[k, 1] - x1, spheres[k, 2] - x2
        de = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        reach = spheres[k, 3] + offset
        if not de > reach * (1.0 + 1e-9):  # from inside (or NaN): any ray
            for j in range(rp * sp):
                need[j] = True
            return rp, sp
        if not banded:  # row i's angles to the axis: [band[i], band[i + 1]]
            for i in range(rp + 1):
                u = i / rp
                if inside:  # cos t = sqrt(1 - u1)
                    band[i] = math.acos(min(math.sqrt(max(1.0 - u, 0.0)), 1.0))
                else:  # cos t = 1 - u1 (1 - cos_max)
                    band[i] = math.acos(min(max(1.0 - u * (1.0 - cos_max), -1.0), 1.0))
            banded = True
        alpha = math.asin(reach / de) + _ROW_MARGIN
        theta = math.acos(min(max((a0 * e0 + a1 * e1 + a2 * e2) / de, -1.0), 1.0))
        spread, azimuth = 4.0, 0.0  # the half-width of the azimuths the cap spans (beyond pi: every column)
        if azimuths and theta - alpha >= _AXIS_GAP and theta + alpha <= math.pi - _AXIS_GAP:
            spread = math.asin(min(math.sin(alpha) / math.sin(theta), 1.0)) + _ROW_MARGIN
            azimuth = math.atan2(b0 * e0 + b1 * e1 + b2 * e2, t0 * e0 + t1 * e1 + t2 * e2)
        for i in range(rp):
            if not (band[i] - _ROW_MARGIN <= theta + alpha and band[i + 1] + _ROW_MARGIN >= theta - alpha):
                continue
            for c in range(sp):
                j = i * sp + c
                if need[j]:
                    continue
                if spread < math.pi:
                    lo, hi = 2.0 * math.pi * c / sp, 2.0 * math.pi * (c + 1) / sp
                    gap = abs(azimuth - 0.5 * (lo + hi)) % (2.0 * math.pi)  # to the column's middle, in [0, 2 pi)
                    gap = min(gap, 2.0 * math.pi - gap)
                    if gap > 0.5 * (hi - lo) + spread:
                        continue
                need[j] = True
    return rp, sp


@numba.njit(cache=True, parallel=True)
def _flag_rows_kernel(points, normals, candidates, centre, radius, bound, key, rows, side, eps, full, facing, box,
                      spheres, flags):
    """``_flag_kernel`` by ``_recast_kernel``'s way: rays of the cells ``_cells_meeting`` leaves out are not made
    (unflagged); the same flags."""
    m = rows * side
    for i in numba.prange(candidates.shape[0]):
        buf = np.empty(8)
        need = np.empty(m, np.bool_)
        band = np.empty(m + 1)
        rp, sp = _cells_meeting(points, normals, candidates[i], centre, radius, rows, side, eps, full, spheres, need,
                                band)
        for j in range(m):
            flags[i, j] = False
            if j >= rp * sp or not need[j]:  # not cast (tmax 0), or in a cell no ray of which meets them
                continue
            _ray(points, normals, candidates[i], j, centre, radius, bound, key, rows, side, eps, full, facing, box,
                 buf)
            flags[i, j] = _meets(buf, spheres)


@numba.njit(cache=True, parallel=True, nogil=True)
def _recast_kernel(points, normals, candidates, centre, radius, bound, key, rows, side, eps, full, facing, box,
                   tnear, source, spheres, tracer, weighing, state, triangle, uv, factor):
    """``_flag_kernel`` and ``_cast_kernel`` in one pass: each ray ``j`` of point ``candidates[i]`` that
    ``_flag_kernel`` flags is traced (rays are made only in the cells ``_cells_meeting`` keeps, as
    ``_flag_rows_kernel``), one at a time or, with ``tracer.packet``, 16 flagged rays of a block of points at a
    time, and a hit on the source weighed (``_weigh_hit``); ``state[i, j]``: ``_UNFLAGGED``, ``_FLAGGED`` (not
    cast: ``tmax`` 0), ``_FLAGGED_CAST`` (cast, its first hit not the source's front) or ``_FLAGGED_HIT`` (its
    first hit is the front of ``source``: ``triangle[i, j]``, ``uv[i, j]``, ``factor[i, j]``)."""
    m = rows * side
    w = _embree.PACKET
    n = candidates.shape[0]
    n_blocks = (n + _POINTS_PER_TASK - 1) // _POINTS_PER_TASK
    counter = np.zeros(1, dtype=np.int64)
    for _ in numba.prange(tracer.threads):
        buf = np.empty(8)
        need = np.empty(m, np.bool_)
        band = np.empty(m + 1)
        lane_i = np.empty(w, np.int64)
        lane_j = np.empty(w, np.int64)
        lane_rays = np.empty((w, 8))
        g = np.empty(weighing[3].shape[0])
        h = np.empty(weighing[7].shape[0])
        while True:
            block = _embree.fetch_add(counter, 1)
            if block >= n_blocks:
                break
            f32, u32 = tracer.slot_f32[block], tracer.slot_u32[block]
            address = f32.ctypes.data
            valid = tracer.valid[block]
            n_lanes = 0
            rp, sp = 0, 1
            end = min(n, (block + 1) * _POINTS_PER_TASK)
            for i in range(block * _POINTS_PER_TASK, end + 1):
                if i < end:
                    rp, sp = _cells_meeting(points, normals, candidates[i], centre, radius, rows, side, eps, full,
                                            spheres, need, band)
                for j in range(m if i < end else 1):
                    if i < end:
                        state[i, j] = _UNFLAGGED
                        if j >= rp * sp or not need[j]:  # as _flag_rows_kernel: no ray of the cell is flagged
                            continue
                        _ray(points, normals, candidates[i], j, centre, radius, bound, key, rows, side, eps, full,
                             facing, box, buf)
                        if not _meets(buf, spheres):
                            continue
                        state[i, j] = _FLAGGED
                        if not buf[7] > 0.0:
                            continue
                        state[i, j] = _FLAGGED_CAST
                        if not tracer.packet:
                            if _hits_source(buf, tnear, source, tracer.function, tracer.scene, f32, u32, address):
                                triangle[i, j] = np.int32(u32[_embree.HIT_PRIM])
                                uv[i, j, 0] = f32[_embree.HIT_U]
                                uv[i, j, 1] = f32[_embree.HIT_V]
                                if _weigh_hit(buf, normals, candidates[i], np.int64(triangle[i, j]),
                                              np.float64(uv[i, j, 0]), np.float64(uv[i, j, 1]), weighing, g, h,
                                              factor[i, j]):
                                    state[i, j] = _FLAGGED_HIT
                            continue
                        if _add_lane(buf, tnear, f32, u32, valid, n_lanes):
                            lane_i[n_lanes], lane_j[n_lanes] = i, j
                            lane_rays[n_lanes] = buf
                            n_lanes += 1
                        if n_lanes < w:
                            continue
                    if n_lanes == 0:
                        continue
                    _trace_lanes(tracer, f32, valid, n_lanes)
                    for k in range(n_lanes):
                        if _lane_hits(u32, k, source):
                            a, c = lane_i[k], lane_j[k]
                            triangle[a, c] = np.int32(u32[_embree.HIT_PRIM * w + k])
                            uv[a, c, 0] = f32[_embree.HIT_U * w + k]
                            uv[a, c, 1] = f32[_embree.HIT_V * w + k]
                            if _weigh_hit(lane_rays[k], normals, candidates[a], np.int64(triangle[a, c]),
                                          np.float64(uv[a, c, 0]), np.float64(uv[a, c, 1]), weighing, g, h,
                                          factor[a, c]):
                                state[a, c] = _FLAGGED_HIT
                    n_lanes = 0


@numba.njit(cache=True, parallel=True, nogil=True)
def _flag_kernel(points, normals, candidates, centre, radius, bound, key, rows, side, eps, full, facing, box, spheres,
                 flags):
    """``flags[i, j]``: whether ray ``j`` of point ``candidates[i]``, up to its ``tmax``, meets any of ``spheres``
    (S, 4: centre, radius)."""
    m = rows * side
    for i in numba.prange(candidates.shape[0]):
        buf = np.empty(8)
        for j in range(m):
            _ray(points, normals, candidates[i], j, centre, radius, bound, key, rows, side, eps, full, facing, box,
                 buf)
            flags[i, j] = _meets(buf, spheres)


@numba.njit(cache=True, parallel=True)
def _apply_kernel(starts, faces, triangles, uv, factor, x, out):
    """``out[v, k', c] += sum_h factor[h, k', k] (b0 x[a, k, c] + u x[b, k, c] + w x[c, k, c])`` over the hits
    ``h`` of each receiver point ``v`` (``b0 = 1 - u - w``, the triangle's vertices ``a, b, c``)."""
    n_kp, n_k, n_c = factor.shape[1], factor.shape[2], x.shape[2]
    for v in numba.prange(starts.shape[0] - 1):
        for h in range(starts[v], starts[v + 1]):
            f = triangles[h]
            i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
            u, w = float(uv[h, 0]), float(uv[h, 1])
            b0 = 1.0 - u - w
            for k in range(n_k):
                for c in range(n_c):
                    at = b0 * x[i0, k, c] + u * x[i1, k, c] + w * x[i2, k, c]
                    for kp in range(n_kp):
                        out[v, kp, c] += factor[h, kp, k] * at


# ------------------------------------------------------------------ rays


def _grid(n: int) -> tuple[int, int]:
    """``(rows, side)`` of the jittered grid of ``n`` rays (``rows side <= n``)."""
    side = max(1, int(np.sqrt(n)))
    return max(1, n // side), side


def _mix_int(z: int) -> int:
    """SplitMix64's finaliser on a Python int (as ``_mix``)."""
    mask = 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
    return z ^ (z >> 31)


def _key(seed: int, source: int) -> np.uint64:
    """The stream key of one source's rays."""
    mask = 0xFFFFFFFFFFFFFFFF
    return np.uint64(_mix_int((int(seed) & mask) ^ _mix_int(((int(source) + 1) * 0x9E3779B97F4A7C15) & mask)))


def cosine_directions(normals, n: int, seed: int = 0) -> np.ndarray:
    """(V, m, 3) cosine-weighted directions about each unit normal: a jittered ``rows x side`` grid of the
    unit square (``m = rows side <= n``) lifted to the hemisphere (Malley), as the gather's rays from a
    point inside a source's bounding sphere."""
    normals = np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    rows, side = _grid(n)
    m = rows * side
    point, ray = np.repeat(np.arange(len(normals)), m), np.tile(np.arange(m), len(normals))
    out = np.empty((len(point), 8))
    inside = np.zeros(3)  # a point at the sphere's centre
    _rays_kernel(np.zeros_like(normals), normals, point, ray, inside, 1.0, 1.0, _key(seed, 0), rows, side, 0.0, 0.0,
                 np.zeros(3), NO_BOX, out)
    return out[:, 3:6].reshape(len(normals), m, 3)


def _bounding_radius(vertices, centre) -> float:
    """Radius about ``centre`` of the sphere through the farthest vertex."""
    v = np.asarray(vertices, float)
    return float(np.sqrt(np.max(np.sum((v - centre) ** 2, axis=1)))) if len(v) else 0.0


def _facing(vertex_normals) -> np.ndarray:
    """(3,) the unit normal of a flat source whose vertex normals all agree within ``1e-12`` (a ray along which
    it rises cannot meet its front, ``_ray``), else zeros."""
    n = np.asarray(vertex_normals, float).reshape(-1, 3)
    if not len(n):
        return np.zeros(3)
    length = float(np.linalg.norm(n[0]))
    if not (0.5 < length < 2.0) or float(np.max(np.abs(n - n[0]))) > 1e-12:
        return np.zeros(3)
    return n[0] / length


def _source_bound(caster, s, source) -> float:
    """The radius about the source's centre through its farthest world vertex: ``source[5]`` when the caller
    keeps it (the same :func:`_bounding_radius`), else computed."""
    if len(source) > 5:
        return float(source[5])
    return _bounding_radius(caster.world_vertices(s), np.asarray(source[3], float))


def _source_facing(source) -> np.ndarray:
    """:func:`_facing` of the source's vertex normals: ``source[6]`` when the caller keeps it, else computed."""
    return source[6] if len(source) > 6 else _facing(source[1])


def _source_box(caster, s, source, margin: float) -> np.ndarray:
    """(6,) the lowest then the highest corner of the source's world vertices (``source[7]``, a ``(2, 3)`` array, when
    the caller keeps it, else computed) widened by ``margin`` (:func:`_margin`: far above the float32 rounding of
    Embree's vertices and hits): a ray that misses it cannot hit the source."""
    lo, hi = (np.asarray(source[7], float) if len(source) > 7 else _points_box(caster.world_vertices(s)))
    return np.concatenate([lo - margin, hi + margin])


def _points_box(points) -> np.ndarray:
    """(2, 3) the lowest and the highest corner of ``points`` (``+inf`` and ``-inf`` when there are none)."""
    points = np.asarray(points, float).reshape(-1, 3)
    if not len(points):
        return np.array([[np.inf] * 3, [-np.inf] * 3])
    return np.stack([points.min(axis=0), points.max(axis=0)])


def _tracer(caster, n_blocks: int):
    """A closest-hit query of ``caster``'s Embree scene for ``n_blocks`` blocks of rays (``_raycast._Tracer``): packets
    of 16 (``rtcIntersect16``) when ``prtlab.geometry._raycast.PACKETS`` is set, else one ray at a time; one slot and
    one ``valid`` mask per block either way."""
    from prtlab.geometry import _raycast

    scene, n_blocks = caster._scene, max(1, int(n_blocks))
    slot_f32, slot_u32, valid = _embree.packet_slots(n_blocks)
    if not _raycast.PACKETS:
        slot_f32, slot_u32 = _embree.ray_slots(n_blocks * _embree.RAYS_PER_TASK)
    return _raycast._Tracer(scene.intersect16_fn if _raycast.PACKETS else scene.intersect_fn, scene.handle, slot_f32,
                            slot_u32, numba.get_num_threads(), False, bool(_raycast.PACKETS), valid)


def _margin(caster, centre, radius) -> float:
    """Widening of a bounding sphere for float32 hits and origin offsets."""
    return 2.0 * caster.epsilon + 1e-5 * (float(np.max(np.abs(centre))) + radius) + 1e-12


def _source_limits(caster, s, source) -> tuple:
    """``(centre, bound, box)`` of source ``s`` as the ray kernels take them: its bounding-sphere centre, the radius
    through its farthest vertex (:func:`_source_bound`) and its box (:func:`_source_box`), both widened by
    :func:`_margin`."""
    centre = np.asarray(source[3], float)
    bound = _source_bound(caster, s, source)
    margin = _margin(caster, centre, bound)
    return centre, bound + margin, _source_box(caster, s, source, margin)


def _cast(points, normals, receiver_sep, caster, s, source, point, ray, key, grid, ids, stats,
          method: str = "numba") -> ResidualHits | None:
    """The hits on the front of source ``s`` of the rays ``(point, ray)`` (ids ``ids``; ``point`` None: every ray
    of every point, ids ``point * m + ray``), ids ascending. ``method="numba"`` (with Embree) makes and traces
    the rays and weighs their hits in one kernel (:func:`_cast_kernel`);
    ``"reference"`` makes them (``_rays_kernel``), traces them through ``RayCaster.closest_hit`` and weighs the
    hits with numpy and :class:`prtlab.brdf.SeparableBRDF`, the specification: the same hits, factors within
    float64 rounding."""
    faces, vertex_normals, sep, centre, radius = source[:5]
    centre, bound, box = _source_limits(caster, s, source)
    m = grid[0] * grid[1]
    if method == "numba" and getattr(caster, "_scene", None) is not None:
        return _cast_numba(points, normals, receiver_sep, caster, s, source, point, ray, key, grid, ids, stats,
                           centre, bound, box)
    if point is None:
        point, ray = np.repeat(np.arange(len(points)), m), np.tile(np.arange(m), len(points))
        ids = np.arange(len(points) * m, dtype=np.int64)
    buf = np.empty((len(point), 8))
    if len(point):
        _rays_kernel(points, normals, point, ray, centre, float(radius), bound, key, grid[0], grid[1],
                     float(caster.epsilon), grid[2], _source_facing(source), box, buf)
    live = np.flatnonzero(buf[:, 7] > 0.0)
    if not len(live):
        return None
    buf = buf[live]
    stats["rays_cast"] += len(live)
    hits = caster.closest_hit(buf[:, :3], buf[:, 3:6], tmax=buf[:, 7])
    sel = np.flatnonzero(hits.hit & (hits.object == s))
    if not len(sel):
        return None
    triangles = hits.triangle[sel]
    tri = np.asarray(faces, np.int64)[triangles]
    uv = hits.barycentric[sel]
    bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
    shading = np.einsum("hc,hcx->hx", bary, np.asarray(vertex_normals, float)[tri])
    shading /= np.maximum(np.linalg.norm(shading, axis=1, keepdims=True), 1e-300)
    w = buf[sel, 3:6]
    front = np.einsum("hx,hx->h", shading, w) < 0.0  # the back of a surface emits nothing
    if not np.any(front):
        return None
    sel, w, shading = sel[front], w[front], shading[front]
    triangles, uv = triangles[front], uv[front]
    rows = point[live[sel]]
    g = receiver_sep.g(brdf.to_local(w, normals[rows]))  # (H, K')
    h = sep.h(brdf.to_local(-w, shading))  # (H, K)
    factor = buf[sel, 6][:, None, None] * g[:, :, None] * h[:, None, :]
    return ResidualHits(rows, factor, ids[live[sel]], triangles, uv, faces)


_SCRATCH = threading.local()


def _scratch(n: int, k_receiver: int, k_source: int) -> tuple:
    """``(state (n,) int8, triangle (n,) int32, uv (n, 2) float32, factor (n, K', K))``: uninitialised output arrays
    of the ray kernels, views of buffers kept per Python thread and grown as needed (the pages of a fresh array of
    a full cast, tens of MB a frame, are otherwise faulted in and cleared on every call). A caller copies what it
    keeps before its thread's next call."""
    held = getattr(_SCRATCH, "arrays", None)
    need = n * k_receiver * k_source
    if held is None or len(held[0]) < n or len(held[3]) < need:
        size = max(n, 1 if held is None else len(held[0]))
        held = _SCRATCH.arrays = (np.empty(size, np.int8), np.empty(size, np.int32), np.empty((size, 2), np.float32),
                                  np.empty(max(size * k_receiver * k_source, need), np.float64))
    return held[0][:n], held[1][:n], held[2][:n], held[3][:need].reshape(n, k_receiver, k_source)


def _cast_numba(points, normals, receiver_sep, caster, s, source, point, ray, key, grid, ids, stats, centre, bound,
                box):
    """``_cast`` by :func:`_cast_kernel`, which weighs the hits as it finds them."""
    m = grid[0] * grid[1]
    n_rays = len(points) * m if point is None else len(point)
    state, triangle, uv32, factor = _scratch(n_rays, receiver_sep.K, source[2].K)
    empty = np.zeros(0, np.int64)
    _cast_kernel(points, normals, empty if point is None else point, empty if ray is None else ray, n_rays, centre,
                 float(source[4]), bound, key, grid[0], grid[1], float(caster.epsilon), grid[2], _source_facing(source),
                 box, float(caster.tnear), s, _tracer(caster, _cast_tasks(n_rays, m, point is None)),
                 _weighing(receiver_sep, source), state, triangle, uv32, factor)
    stats["rays_cast"] += int(np.count_nonzero(state))
    at = np.flatnonzero(state == _HIT)
    if not len(at):
        return None
    rows = at // m if point is None else point[at]
    return ResidualHits(rows, factor[at], at if point is None else ids[at].astype(np.int64),
                        triangle[at].astype(np.int64), uv32[at].astype(np.float64), source[0])


def _merge(old: ResidualHits | None, recast: np.ndarray, new: ResidualHits | None) -> ResidualHits | None:
    """``old`` without the rays ``recast`` (sorted ids), with ``new`` (their hits now), in the order of the ids."""
    parts = []
    if old is not None:
        keep = ~np.isin(old.rays, recast, assume_unique=False)
        if np.all(keep) and new is None:
            return old
        parts.append(tuple(a[keep] for a in old.arrays()))
    if new is not None:
        parts.append(new.arrays())
    parts = [p for p in parts if len(p[0])]
    if not parts:
        return None
    joined = [np.concatenate([p[i] for p in parts]) for i in range(len(parts[0]))]
    order = np.argsort(joined[2], kind="stable")
    return ResidualHits(*(a[order] for a in joined), (old or new).faces)


def _update(old: ResidualHits | None, recast: np.ndarray, new: ResidualHits | None) -> ResidualHits | None:
    """``old`` itself if the rays ``recast`` (sorted ids) hit now as they did (``new``: their hits now, ids
    ascending), else ``_merge(old, recast, new)``: what ``_merge`` then ``_same`` give, comparing only the recast
    rays' entries (found by ``searchsorted`` in ``old``'s sorted ids) instead of every hit, and merging by
    insertion at sorted positions instead of a sort."""
    if old is None:
        return new
    at = np.searchsorted(old.rays, recast)
    found = at < len(old.rays)
    found[found] = old.rays[at[found]] == recast[found]
    at = at[found]  # old's entries of the recast rays
    if new is None and not len(at):
        return old
    if new is not None and len(at) == len(new.rays) and all(np.array_equal(a[at], b)
                                                            for a, b in zip(old.arrays(), new.arrays())):
        return old
    keep = np.ones(len(old.rays), bool)
    keep[at] = False
    kept = [a[keep] for a in old.arrays()]
    if new is not None:
        where = np.searchsorted(kept[2], new.rays)
        kept = [np.insert(a, where, b.astype(a.dtype, copy=False), axis=0) for a, b in zip(kept, new.arrays())]
    return ResidualHits(*kept, old.faces) if len(kept[0]) else None


def _same(a: ResidualHits | None, b: ResidualHits | None) -> bool:
    if a is None or b is None:
        return a is b
    return all(np.array_equal(x, y) for x, y in zip(a.arrays(), b.arrays()))


def residual_hits(points, normals, receiver_sep, caster, sources: dict, n_rays: int, seed: int = 0, *,
                  previous: dict | None = None, moved: dict | None = None, stats: dict | None = None,
                  method: str = "numba", full: float = 0.0) -> dict:
    """``{source index: ResidualHits}`` of ``n_rays`` rays per receiver point and source.

    ``caster`` holds every object at its pose (its object index is the key); ``sources`` maps the indices
    that are sources of this receiver to ``(faces, world vertex normals, separable BRDF, bounding-sphere
    centre, radius)``, optionally followed by the radius about that centre through the farthest world vertex,
    :func:`_facing` of the normals and the box of the world vertices (:func:`_points_box`) (kept by callers across
    calls; computed when absent). Rays go uniformly into the cone of the source's bounding sphere (cosine-weighted
    over the hemisphere from a point inside it), so a small far source gets all of them; a ray counts
    when its first hit is the front of that source. With ``full > 0`` (steradians) a point outside the
    sphere casts ``n_rays`` times ``omega / full`` rays (a grid of its own, each ray weighted by its size; at
    least ``MIN_RAYS``, at most ``n_rays``), ``omega`` the cone's solid angle times the largest cosine to the
    point's normal inside it: still unbiased, with fewer rays toward sources that subtend little.

    With ``previous`` (this function's result for the same receiver points, sources' geometry, seed and
    caster epsilon, at earlier poses) and ``moved`` (``{object index: (S, 4) array}``: the old and new
    bounding spheres, centre and radius, of every object whose pose changed since; the receiver not among
    them) only the rays whose first hit may have changed are cast again: every ray toward a moved source,
    and the rays of the other sources whose path up to the source meets a moved object's old or new
    bounding sphere. The result equals a full cast (the same rays, the same hits) but for float32 ties
    between triangles at one distance. An unchanged source keeps its ``ResidualHits`` object. ``stats``
    (a dict) gets ``rays_cast`` added; ``previous`` must come from the same ``full``. ``method="numba"`` makes
    and traces the rays in one kernel (with Embree; else as ``"reference"``), ``"reference"`` makes them apart
    and traces them through ``RayCaster.closest_hit``: the same hits.
    """
    check_choice(method, "method", ("numba", "reference"))
    points = np.ascontiguousarray(points, dtype=np.float64)
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    check_float(full, "full", 0.0, meaning="in steradians, 0: every point casts n_rays")
    grid = (*_grid(n_rays), float(full))
    out = {}
    if len(points) == 0:
        return out
    stats = {} if stats is None else stats
    stats.setdefault("rays_cast", 0)
    incremental = previous is not None and moved is not None
    spheres = np.concatenate(list(moved.values())) if incremental and moved else np.zeros((0, 4))
    for s, source in sources.items():
        key = _key(seed, s)
        if not incremental or s in moved:
            hits = _cast(points, normals, receiver_sep, caster, s, source, None, None, key, grid, None, stats,
                         method)
        elif not len(spheres):
            hits = previous.get(s)
        else:
            hits = _recast(points, normals, receiver_sep, caster, s, source, key, grid, spheres, previous.get(s),
                           stats, method)
        if hits is not None:
            out[s] = hits
    return out


@numba.njit(cache=True, inline="always")
def _capsule_at(points, v, centre, spheres, bound, eps):
    """:func:`_capsule_kernel`'s test of point ``v``."""
    x0, x1, x2 = points[v, 0], points[v, 1], points[v, 2]
    d0, d1, d2 = centre[0] - x0, centre[1] - x1, centre[2] - x2
    dd = max(d0 * d0 + d1 * d1 + d2 * d2, 1e-300)
    for k in range(spheres.shape[0]):
        t = min(max(((spheres[k, 0] - x0) * d0 + (spheres[k, 1] - x1) * d1 + (spheres[k, 2] - x2) * d2) / dd,
                    0.0), 1.0)
        g0, g1, g2 = x0 + t * d0 - spheres[k, 0], x1 + t * d1 - spheres[k, 1], x2 + t * d2 - spheres[k, 2]
        if g0 * g0 + g1 * g1 + g2 * g2 <= (bound + spheres[k, 3] + eps) ** 2:
            return True
    return False


@numba.njit(cache=True, parallel=True, nogil=True)
def _capsule_kernel(points, centre, spheres, bound, eps, near):
    """``near[v]``: the segment from ``points[v]`` to ``centre`` passes within ``bound + R + eps`` of a sphere ``(c, R)`` of
    ``spheres`` (S, 4). Every ray of a point lies, up to its ``tmax``, in the capsule of radius ``bound`` about that
    segment, so only such points can hold a ray that meets a sphere."""
    for v in numba.prange(points.shape[0]):
        near[v] = _capsule_at(points, v, centre, spheres, bound, eps)


@numba.njit(cache=True, nogil=True)
def _capsule_serial(points, centre, spheres, bound, eps, near):
    """:func:`_capsule_kernel` on one thread (no parallel region)."""
    for v in range(points.shape[0]):
        near[v] = _capsule_at(points, v, centre, spheres, bound, eps)


@numba.njit(cache=True, nogil=True)
def _flagged(state):
    """``np.nonzero(state)`` of a (C, m) state array, in the same (row-major) order: the rows and columns of its
    nonzero entries (counted, then written: two compiled scans, faster than numpy's on these mostly zero states)."""
    rows, cols = state.shape
    count = 0
    for i in range(rows):
        for j in range(cols):
            if state[i, j] != 0:
                count += 1
    at_i, at_j = np.empty(count, np.int64), np.empty(count, np.int64)
    count = 0
    for i in range(rows):
        for j in range(cols):
            if state[i, j] != 0:
                at_i[count], at_j[count] = i, j
                count += 1
    return at_i, at_j


def _recast(points, normals, receiver_sep, caster, s, source, key, grid, spheres, old, stats, method):
    """The hits of source ``s`` after the objects of ``spheres`` (old and new bounding spheres) moved."""
    radius = float(source[4])
    centre, bound, box = _source_limits(caster, s, source)
    m = grid[0] * grid[1]
    widened = spheres.copy()
    widened[:, 3] += np.array([_margin(caster, c[:3], c[3]) for c in spheres])
    near = np.empty(len(points), np.bool_)
    capsule = _capsule_kernel if len(points) >= SERIAL_ITEMS else _capsule_serial
    capsule(points, centre, widened, bound, float(caster.epsilon), near)
    candidates = np.flatnonzero(near)
    if not len(candidates):
        return old
    if method == "numba" and getattr(caster, "_scene", None) is not None:
        state, triangle, uv32, factor = _scratch(len(candidates) * m, receiver_sep.K, source[2].K)
        state, triangle = state.reshape(len(candidates), m), triangle.reshape(len(candidates), m)
        uv32, factor = uv32.reshape(len(candidates), m, 2), factor.reshape(len(candidates), m, *factor.shape[1:])
        n_blocks = -(-len(candidates) // _POINTS_PER_TASK)
        _recast_kernel(points, normals, candidates, centre, radius, bound, key, grid[0], grid[1],
                       float(caster.epsilon), grid[2], _source_facing(source), box, float(caster.tnear), s, widened,
                       _tracer(caster, n_blocks), _weighing(receiver_sep, source), state, triangle, uv32, factor)
        i, j = _flagged(state)
        if not len(i):
            return old
        stats["rays_cast"] += int(np.count_nonzero(state >= _FLAGGED_CAST))
        ids = candidates[i] * m + j
        hit = np.flatnonzero(state[i, j] == _FLAGGED_HIT)
        new = None
        if len(hit):
            a, c = i[hit], j[hit]
            new = ResidualHits(candidates[a], factor[a, c], ids[hit].astype(np.int64),
                               triangle[a, c].astype(np.int64), uv32[a, c].astype(np.float64), source[0])
        return _update(old, ids, new)
    flags = np.empty((len(candidates), m), np.bool_)
    _flag_kernel(points, normals, candidates, centre, radius, bound, key, grid[0], grid[1], float(caster.epsilon),
                 grid[2], _source_facing(source), box, widened, flags)
    i, j = np.nonzero(flags)
    if not len(i):
        return old
    point, ray = candidates[i], j.astype(np.int64)
    ids = point * m + ray
    new = _cast(points, normals, receiver_sep, caster, s, source, point, ray, key, grid, ids, stats, method)
    merged = _merge(old, ids, new)
    return old if _same(merged, old) else merged


# ------------------------------------------------------------------ the gather


def gather_residual(hits: ResidualHits, residual, n_points: int) -> np.ndarray:
    """``L_k',c`` (n_points, K', C) gathered from a source's per-vertex ``residual`` (V_s, K, C): the float64
    specification of :func:`apply_gather`."""
    residual = np.asarray(residual, float)
    at_hit = np.einsum("hv,hvkc->hkc", hits.bary, residual[hits.vertices])
    per_ray = np.einsum("hqk,hkc->hqc", hits.factor, at_hit)
    out = np.zeros((n_points,) + per_ray.shape[1:])
    np.add.at(out, hits.rows, per_ray)
    return out


def gather_operator(hits: ResidualHits, n_points: int) -> GatherOperator:
    """The compact form of ``hits`` (:class:`GatherOperator`) on ``n_points`` receiver points."""
    uv = np.asarray(hits.uv)
    uv32 = uv.astype(np.float32)
    exact = np.array_equal(uv32.astype(np.float64), uv)
    return GatherOperator(np.searchsorted(hits.rows, np.arange(n_points + 1)).astype(np.int64),
                          np.ascontiguousarray(hits.faces, np.int32), np.ascontiguousarray(hits.triangles, np.int32),
                          np.ascontiguousarray(uv32 if exact else uv), np.ascontiguousarray(hits.factor, np.float64))


def apply_gather(op: GatherOperator, residual, out) -> np.ndarray:
    """``out`` (V_r, K', C) += the gather of ``residual`` (V_s, K, C) through ``op``; returns ``out``."""
    residual = np.ascontiguousarray(residual, dtype=np.float64)
    if op.factor.shape[1:] == (1, 1) and residual.shape[1:] == (1, 3) and out.flags.c_contiguous:
        _gather_rows(op.starts, op.faces, op.triangles, op.uv, op.factor.reshape(-1), 0, residual.reshape(-1, 3),
                     out.reshape(-1, 3))
    else:
        _apply_kernel(op.starts, op.faces, op.triangles, op.uv, op.factor, residual, out)
    return out


def _rgb_ready(operators) -> bool:
    """Whether :func:`bounce_rgb` takes ``operators``: ``K = K' = 1`` factors and float32 barycentrics in all."""
    return all(op.factor.shape[1:] == (1, 1) and op.uv.dtype == np.float32 for op in operators)


#: Type of the packed gather weights (:func:`pack_operators`) and of the residual rows :func:`bounce_rgb` reads
#: with them: float32 halves the bytes a bounce reads, and rounding each weight and each residual value once
#: (relative ``2**-24``) bounds the change of a gather by ``2 * 2**-24`` (and ``2**-48``) times the sum of its
#: terms' magnitudes (``test_packed_float32_gather_within_its_rounding_bound``).
PACKED_WEIGHTS = np.float32


def pack_operators(operators, sources, offsets, dtype=None) -> tuple:
    """The gathers of ``operators`` (:class:`GatherOperator`, :func:`_rgb_ready`) on one receiver merged into
    one list of terms per receiver point, the form :func:`bounce_rgb` reads: ``(starts (V + 1,) int64, rows
    (T, 3) int32, weights (T, 3))``. Point ``v``'s terms ``starts[v]:starts[v + 1]`` are its hits of every
    source in the order of ``operators``, each the rows of the hit triangle's vertices in the stacked residual
    (``offsets[sources[j]]`` plus the vertex) and ``factor * (1 - u - v, u, v)`` rounded to ``dtype``
    (default :data:`PACKED_WEIGHTS`). Made once per set of operators by callers that apply them every bounce:
    24 bytes a hit in float32."""
    dtype = PACKED_WEIGHTS if dtype is None else dtype
    n_points = len(operators[0].starts) - 1 if operators else 0
    counts = np.zeros(n_points, np.int64)
    for op in operators:
        counts += np.diff(op.starts)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    rows = np.empty((starts[-1], 3), np.int32)
    weights = np.empty((starts[-1], 3), dtype)
    fill = starts[:-1].copy()
    for op, j in zip(operators, sources):
        _pack_kernel(op.starts, op.faces, op.triangles, op.uv, op.factor.reshape(-1), int(offsets[j]),
                     np.zeros(0, np.int32), fill, rows, weights)
    return starts, rows, weights


def _room(n: int) -> int:
    """Terms a segment of ``n`` terms is given in :class:`PackedGather`'s arrays: room to grow by an eighth in place."""
    return n + n // 8 + 64


#: Most rows :class:`PackedGather`'s compact residual holds with uint16 row numbers (above: int32).
SHORT_ROWS = 1 << 16

#: :class:`PackedGather` packs every operator again when its compact residual has grown past
#: ``COMPACT_GROWTH`` times the rows it held when last packed whole plus ``COMPACT_SLACK`` (rows no term reads
#: any more are dropped only then).
COMPACT_GROWTH, COMPACT_SLACK = 1.5, 1024


class PackedGather:
    """The gathers of one receiver's operators packed for :func:`bounce_rgb` in segments, re-packed segment by
    segment, over a compact copy of the residual rows they read.

    Segment ``s`` holds :func:`pack_operators`'s terms of a run of consecutive operators: point ``v``'s terms are
    ``starts[s, v]:starts[s, v + 1]`` of ``rows`` (C, 3) and ``weights`` (C, 3) ``dtype`` (default
    :data:`PACKED_WEIGHTS`), so that reading the segments in order for each point sums its terms in the order of
    :func:`pack_operators`. ``rows`` number rows of the compact residual: compact row ``k`` is row
    ``residual_rows[k]`` of the stacked residual (each row at most once; uint16 while there are at most
    :data:`SHORT_ROWS`, else int32), so that a bounce copies the rows its terms read together (about half the
    stacked residual a receiver, small enough to stay in a core's cache) and reads 18 bytes a term.
    :meth:`update` re-packs only the segments holding an operator that is not the object it last packed there
    (or whose source's rows moved in the stacked residual), split into runs of changed and unchanged operators:
    an operator that changes every frame gets a segment of its own, the others stay merged. Segments are never
    merged again, so ``B`` operators changing in turn leave up to ``B`` segments (a slower bounce). A segment is
    re-packed in its place when it fits, else after the others; the arrays are made again, live segments only,
    when that runs out of room. Rows a re-packed segment reads anew join the compact residual; every operator is
    packed again, in one segment over only the rows read, when the compact residual has grown past
    :data:`COMPACT_GROWTH` times its size when last packed whole and :data:`COMPACT_SLACK` rows (or past
    :data:`SHORT_ROWS` with uint16 rows).
    Updated in place: the arrays of :meth:`arrays` hold until the next :meth:`update`."""

    def __init__(self, dtype=None):
        self.dtype = PACKED_WEIGHTS if dtype is None else dtype
        self.starts = np.zeros((0, 1), np.int64)
        self._reset(0)

    def _reset(self, n_operators: int):
        """No segment, no compact row: every one of ``n_operators`` operators is packed anew."""
        self.rows = np.zeros((0, 3), np.uint16)
        self.weights = np.zeros((0, 3), self.dtype)
        self.residual_rows = np.zeros(0, np.int64)
        self._compact = np.zeros(0, np.int32)  # per stacked residual row: its compact row, or -1
        self._compacted = 0  # compact rows when last packed whole
        self._keys = [None] * n_operators  # per operator: (operator, its source's first row) last packed
        self._segments = []  # [first operator, last operator + 1, first term, room, starts (V + 1,)]
        self._used = 0  # terms of the arrays given to segments

    def arrays(self) -> tuple:
        """``(starts (S, V + 1) int64, rows (C, 3) uint16 or int32, weights (C, 3), residual_rows (R,) int64)``,
        the form :func:`_bounce_kernel` reads."""
        return self.starts, self.rows, self.weights, self.residual_rows

    def update(self, operators, sources, offsets) -> PackedGather:
        """Packs ``operators`` (:class:`GatherOperator`, :func:`_rgb_ready`) of the objects ``sources`` whose rows
        in the stacked residual start at ``offsets[sources[b]]``, re-packing only the segments that changed;
        returns ``self``."""
        keys = [(op, int(offsets[j])) for op, j in zip(operators, sources)]
        n_points = len(operators[0].starts) - 1 if operators else 0
        if len(keys) != len(self._keys) or self.starts.shape[1] != n_points + 1:
            self._reset(len(keys))
        stale = [self._keys[b] is None or self._keys[b][0] is not key[0] or self._keys[b][1] != key[1]
                 for b, key in enumerate(keys)]
        if self._segments and not any(stale):
            return self
        if not self._add_rows([key for key, changed in zip(keys, stale) if changed]):
            self._reset(len(keys))  # grown too far: every operator packed again, over the rows read only
            stale = [True] * len(keys)
            self._add_rows(keys)
        kept, fresh = [], []  # fresh: [first operator, last + 1, its terms, (first term, room) it may reuse]
        for seg in self._segments or [[0, len(keys), 0, 0, None]]:
            lo, hi = seg[0], seg[1]
            if not any(stale[lo:hi]) and seg[4] is not None:
                kept.append(seg)
                continue
            span = (seg[2], seg[3])
            for b in range(lo, hi):
                if not (fresh and fresh[-1][1] == b and stale[b] == stale[b - 1]):  # else b joins the run before
                    fresh.append([b, b + 1, 0, span])
                    span = (0, 0)
                else:
                    fresh[-1][1] = b + 1
        for run in fresh:
            run[2] = sum(len(keys[b][0].triangles) for b in range(run[0], run[1]))
        grown = [run for run in fresh if run[2] > run[3][1]]
        if self._used + sum(_room(run[2]) for run in grown) > len(self.rows):
            self._rebuild(kept, fresh)
        else:
            for run in grown:
                run[3] = (self._used, _room(run[2]))
                self._used += run[3][1]
        for lo, hi, _, (first, room) in fresh:
            counts = np.zeros(n_points, np.int64)
            for b in range(lo, hi):
                counts += np.diff(keys[b][0].starts)
            starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64) + first
            fill = starts[:-1].copy()
            for b in range(lo, hi):
                op, offset = keys[b]
                _pack_kernel(op.starts, op.faces, op.triangles, op.uv, op.factor.reshape(-1), offset, self._compact,
                             fill, self.rows, self.weights)
            kept.append([lo, hi, first, room, starts])
        self._segments = sorted(kept, key=lambda seg: seg[0])
        self._keys = keys
        self.starts = np.stack([seg[4] for seg in self._segments]) if self._segments \
            else np.zeros((0, n_points + 1), np.int64)
        return self

    def _add_rows(self, keys) -> bool:
        """Gives every stacked residual row that the hits of ``keys`` (``(operator, first row)``) read a compact
        row; False, changing nothing, if that grows a compact residual already packed past its bounds
        (:data:`COMPACT_GROWTH`, :data:`COMPACT_SLACK`, :data:`SHORT_ROWS`)."""
        n_rows = max([offset + int(op.faces.max()) + 1 for op, offset in keys if len(op.faces)], default=0)
        read = np.zeros(max(n_rows, len(self._compact)), np.bool_)
        for op, offset in keys:
            _mark_rows(op.faces, op.triangles, offset, read)
        compact = np.full(len(read), -1, np.int32)
        compact[:len(self._compact)] = self._compact
        new = np.flatnonzero(read & (compact < 0))
        total = len(self.residual_rows) + len(new)
        short = self.rows.dtype == np.uint16
        grown = total > COMPACT_GROWTH * self._compacted + COMPACT_SLACK
        if self._segments and (grown or (short and total > SHORT_ROWS)):
            return False
        if short and total > SHORT_ROWS:  # packed whole: int32 rows (the arrays made again)
            self.rows, self.weights, self._used = np.zeros((0, 3), np.int32), np.zeros((0, 3), self.dtype), 0
        compact[new] = np.arange(len(self.residual_rows), total, dtype=np.int32)
        self._compact = compact
        self.residual_rows = np.concatenate([self.residual_rows, new]).astype(np.int64)
        if not self._segments:
            self._compacted = total
        return True

    def _rebuild(self, kept, fresh):
        """New arrays with each segment's room (:func:`_room`) and an eighth more: the ``kept`` segments copied
        into theirs, the ``fresh`` runs' rooms left for :meth:`update` to pack."""
        rooms = [_room(int(seg[4][-1] - seg[4][0])) for seg in kept] + [_room(run[2]) for run in fresh]
        rows = np.empty((sum(rooms) + sum(rooms) // 8, 3), self.rows.dtype)
        weights = np.empty((len(rows), 3), self.dtype)
        first = 0
        for seg, room in zip(kept, rooms):
            lo, hi = seg[4][0], seg[4][-1]
            rows[first:first + hi - lo] = self.rows[lo:hi]
            weights[first:first + hi - lo] = self.weights[lo:hi]
            seg[2], seg[3], seg[4] = first, room, seg[4] + (first - lo)
            first += room
        for run, room in zip(fresh, rooms[len(kept):]):
            run[3] = (first, room)
            first += room
        self.rows, self.weights, self._used = rows, weights, first


@numba.njit(cache=True, nogil=True)
def _mark_rows(fc, tr, o, read):
    """``read[o + fc[tr[h], j]] = True`` for every hit ``h`` and vertex ``j``."""
    for h in range(tr.shape[0]):
        f = tr[h]
        read[o + fc[f, 0]] = True
        read[o + fc[f, 1]] = True
        read[o + fc[f, 2]] = True


@numba.njit(cache=True, parallel=True, nogil=True)
def _pack_kernel(st, fc, tr, bc, fa, o, compact, fill, rows, weights):
    """One source's hits appended to each point's terms at ``fill[v]`` (advanced past them); each term's rows
    ``compact[o + vertex]``, or ``o + vertex`` itself if ``compact`` is empty."""
    direct = compact.shape[0] == 0
    for v in numba.prange(st.shape[0] - 1):
        t = fill[v]
        for h in range(st[v], st[v + 1]):
            f = tr[h]
            u, w = np.float64(bc[h, 0]), np.float64(bc[h, 1])
            c = fa[h]
            for j in range(3):
                rows[t, j] = o + fc[f, j] if direct else compact[o + fc[f, j]]
            weights[t, 0], weights[t, 1], weights[t, 2] = c * (1.0 - u - w), c * u, c * w
            t += 1
        fill[v] = t


def bounce_rgb(stacked, w, operators, sources, residual, offsets, extra=None, packed=None) -> np.ndarray:
    """One bounce's ``L`` (V, 3) of a receiver with ``K' = 1`` in one pass: ``stacked @ w`` (its basis
    irradiance, Eq. 12 before ``h``) plus the residual gather of every source (:func:`apply_gather`) plus
    ``extra`` (V, 3) if given.

    ``stacked`` (V, M) float64 or float32 (each value read as float64), ``w`` (M, 3); ``operators``: the sources' :class:`GatherOperator` (``K = K' = 1``,
    float32 barycentrics, :func:`_rgb_ready`), ``sources`` their object numbers, ``residual`` (V_all, 3) every
    object's residual stacked by object and ``offsets`` (n_objects,) where each object's rows start;
    ``packed``: a :class:`PackedGather` updated to ``operators`` or their :func:`pack_operators` (one segment) if the
    caller keeps it (else it is made here). Per point the sum is ``dot + gather + extra``, in that order, the
    gather's terms in the order of the numpy path
    (:func:`apply_gather` per source), which holds it to ``1e-12`` with float64 weights and to its rounding
    bound with float32 ones (``tests/interreflection/test_residual.py``); the dot product's summation order
    differs from BLAS's. The residual rows the terms read are copied first into a table of the weights' type:
    with float32 weights each residual value is rounded once too.
    """
    stacked = np.ascontiguousarray(stacked, np.float32 if stacked.dtype == np.float32 else np.float64)
    out = np.empty((stacked.shape[0], 3))
    if not len(out):
        return out
    extra = np.zeros((0, 3)) if extra is None else np.ascontiguousarray(extra, np.float64)
    if operators:
        packed = PackedGather().update(operators, sources, offsets) if packed is None else packed
        if isinstance(packed, PackedGather):
            starts, rows, weights, residual_rows = packed.arrays()
        else:  # pack_operators' terms number the stacked residual's rows: the table holds them all
            starts, rows, weights = packed
            residual_rows = np.arange(len(residual), dtype=np.int64)
        starts = starts.reshape(-1, len(out) + 1)  # pack_operators' list is one segment
        residual = np.ascontiguousarray(residual, np.float64)
    else:
        starts, rows, weights = np.zeros((0, len(out) + 1), np.int64), np.zeros((0, 3), np.int32), np.zeros((0, 3))
        residual, residual_rows = np.zeros((0, 3)), np.zeros(0, np.int64)
    _bounce_kernel(stacked, np.ascontiguousarray(np.transpose(w), np.float64), starts, rows, weights, residual,
                   residual_rows, np.empty((len(residual_rows), 4), weights.dtype), extra, out)
    return out


@numba.njit(cache=True, parallel=True, nogil=True)
def _gather_rows(st, fc, tr, bc, fa, o, x, g):
    """``_apply_kernel`` for ``K = K' = 1`` and 3 colours: ``g`` (V, 3) += ``sum_h fa[h] (b0 x[a] + u x[b] + w x[c])``
    over the hits of each receiver point, the source's vertices from row ``o`` of ``x`` (V_s, 3)."""
    for v in numba.prange(g.shape[0]):
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        for h in range(st[v], st[v + 1]):
            f = tr[h]
            i0, i1, i2 = o + fc[f, 0], o + fc[f, 1], o + fc[f, 2]
            u, t = float(bc[h, 0]), float(bc[h, 1])
            b0 = 1.0 - u - t
            c = fa[h]
            a0 += c * (b0 * x[i0, 0] + u * x[i1, 0] + t * x[i2, 0])
            a1 += c * (b0 * x[i0, 1] + u * x[i1, 1] + t * x[i2, 1])
            a2 += c * (b0 * x[i0, 2] + u * x[i1, 2] + t * x[i2, 2])
        g[v, 0] += a0
        g[v, 1] += a1
        g[v, 2] += a2


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _dot_rgb(stacked, wt, v):
    """``stacked[v] @ wt.T`` (``wt`` (3, M)), each value read as float64, summed in any order (``reassoc``: the
    compiler vectorises the sums; any order's rounding is within ``(M - 1) 2**-53 sum_m |a_m w_m|``)."""
    d0 = 0.0
    d1 = 0.0
    d2 = 0.0
    for m in range(stacked.shape[1]):
        a = np.float64(stacked[v, m])
        d0 += a * wt[0, m]
        d1 += a * wt[1, m]
        d2 += a * wt[2, m]
    return d0, d1, d2


_LANES = ir.VectorType(ir.DoubleType(), 4)


@intrinsic
def _gather_terms(typingctx, acc, table, rows, weights, start, stop):
    """``acc`` (3 float64) plus ``sum_t sum_j weights[t, j] table[rows[t, j], :3]`` over ``start <= t < stop``, the
    terms in order: each row read as one 4-lane vector (``table`` (R, 4), lane 3 unused), multiplied and added
    lane by lane, so each colour's sum is rounded exactly as the scalar ``a += c * table[i, colour]`` in float64.
    ``table`` float32 or float64, ``rows`` (T, 3) uint16 or int32, ``weights`` (T, 3) float32 or float64, all
    C-contiguous. (numba vectorises the three colours of a row only with its process-wide SLP option.)"""
    arrays = (table, rows, weights)
    if not (isinstance(acc, types.UniTuple) and acc.count == 3 and acc.dtype == types.float64
            and all(isinstance(a, types.Array) and a.ndim == 2 and a.layout == "C" for a in arrays)
            and table.dtype in (types.float32, types.float64) and rows.dtype in (types.uint16, types.int32)
            and weights.dtype in (types.float32, types.float64)
            and isinstance(start, types.Integer) and isinstance(stop, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        i32, i64 = ir.IntType(32), ir.IntType(64)
        table_t, rows_t, weights_t = sig.args[1:4]
        row_type = ir.VectorType(context.get_value_type(table_t.dtype), 4)
        tab, rws, wts = (context.make_array(t)(context, builder, a).data for t, a in zip(sig.args[1:4], args[1:4]))
        tab = builder.bitcast(tab, row_type.as_pointer())
        start, stop = (context.cast(builder, a, t, types.int64) for a, t in zip(args[4:], sig.args[4:]))
        total = ir.Constant(_LANES, [0.0] * 4)
        for lane in range(3):
            total = builder.insert_element(total, builder.extract_value(args[0], lane), ir.Constant(i32, lane))
        slot = cgutils.alloca_once(builder, _LANES)  # promoted to a register by LLVM
        builder.store(total, slot)
        broadcast = ir.Constant(ir.VectorType(i32, 4), [0] * 4)
        with cgutils.for_range(builder, builder.sub(stop, start)) as loop:
            first = builder.mul(builder.add(start, loop.index), ir.Constant(i64, 3))
            total = builder.load(slot)
            for j in range(3):
                at = builder.add(first, ir.Constant(i64, j))
                row = builder.load(builder.gep(rws, [at]))
                row = builder.zext(row, i64) if rows_t.dtype == types.uint16 else builder.sext(row, i64)
                c = builder.load(builder.gep(wts, [at]))
                if weights_t.dtype == types.float32:
                    c = builder.fpext(c, ir.DoubleType())
                x = builder.load(builder.gep(tab, [row]), align=table_t.dtype.bitwidth // 8)
                if table_t.dtype == types.float32:
                    x = builder.fpext(x, _LANES)
                c = builder.shuffle_vector(builder.insert_element(ir.Constant(_LANES, ir.Undefined), c,
                                                                  ir.Constant(i32, 0)),
                                           ir.Constant(_LANES, ir.Undefined), broadcast)
                total = builder.fadd(total, builder.fmul(c, x))
            builder.store(total, slot)
        total = builder.load(slot)
        out = cgutils.get_null_value(context.get_value_type(sig.return_type))
        for lane in range(3):
            out = builder.insert_value(out, builder.extract_element(total, ir.Constant(i32, lane)), lane)
        return out

    return types.UniTuple(types.float64, 3)(acc, table, rows, weights, start, stop), codegen


@numba.njit(cache=True, parallel=True, nogil=True)
def _bounce_kernel(stacked, wt, starts, rows, weights, x, x_rows, table, extra, out):
    """:func:`bounce_rgb` in one parallel pass over the points: the dot product with ``wt`` (3, M) (:func:`_dot_rgb`),
    the packed gather's terms (``starts`` (S, V + 1), :class:`PackedGather`; S = 0 for none) segment after
    segment, each in order (:func:`_gather_terms`), and ``extra`` ((V, 3) or (0, 3)). The terms' ``rows`` number
    rows of ``table`` (R, 4), filled first with the rows ``x_rows`` (R,) of ``x`` (V_all, 3), each rounded to the
    table's type, lane 3 zero."""
    for k in numba.prange(x_rows.shape[0]):
        i = x_rows[k]
        table[k, 0] = x[i, 0]
        table[k, 1] = x[i, 1]
        table[k, 2] = x[i, 2]
        table[k, 3] = 0.0
    add = extra.shape[0] > 0
    for v in numba.prange(stacked.shape[0]):
        d0, d1, d2 = _dot_rgb(stacked, wt, v)
        g = (0.0, 0.0, 0.0)
        for s in range(starts.shape[0]):
            g = _gather_terms(g, table, rows, weights, starts[s, v], starts[s, v + 1])
        out[v, 0] = d0 + g[0]
        out[v, 1] = d1 + g[1]
        out[v, 2] = d2 + g[2]
        if add:
            out[v, 0] += extra[v, 0]
            out[v, 1] += extra[v, 1]
            out[v, 2] += extra[v, 2]


# ------------------------------------------------------------------ near hits


def near_hits(hits: ResidualHits, points, source_vertices, source_normals, near: float, method: str = "numba"):
    """``(index (Q,), positions (Q, 3), normals (Q, 3))`` of the hits nearer their receiver point
    (``points[rows]``) than ``near`` times the longest edge of the hit triangle: indices into ``hits``, the hit
    points on the source's triangles (world ``source_vertices`` (V_s, 3)) and the unit shading normals there
    (``source_normals`` (V_s, 3) interpolated). ``method="numba"`` runs :func:`_near_kernel`, ``"reference"`` numpy
    (the specification; the same arrays)."""
    if not near > 0.0:
        raise ValueError(f"near must be a positive multiple of the edge length, got {near!r}")
    check_choice(method, "method", ("numba", "reference"))
    if method == "numba":
        vertices = np.ascontiguousarray(source_vertices, np.float64)
        vertex_normals = np.ascontiguousarray(source_normals, np.float64)
        faces = np.ascontiguousarray(hits.faces, np.int64)
        points = np.ascontiguousarray(points, np.float64)
        rows, triangles = np.ascontiguousarray(hits.rows, np.int64), np.ascontiguousarray(hits.triangles, np.int64)
        uv = np.ascontiguousarray(hits.uv, np.float64)
        flags = np.empty(len(rows), np.bool_)
        _near_kernel(points, vertices, faces, rows, triangles, uv, float(near), flags)
        index = np.flatnonzero(flags)
        at, normals = np.empty((len(index), 3)), np.empty((len(index), 3))
        _near_points_kernel(vertices, vertex_normals, faces, triangles, uv, index, at, normals)
        return index, at, normals
    tri = np.asarray(source_vertices, float)[hits.vertices]  # (H, 3, 3)
    edge2 = np.max(np.stack([np.sum((tri[:, (i + 1) % 3] - tri[:, i]) ** 2, axis=1) for i in range(3)]), axis=0)
    bary = hits.bary
    at = np.einsum("hc,hcx->hx", bary, tri)
    gap2 = np.sum((at - np.asarray(points, float)[hits.rows]) ** 2, axis=1)
    index = np.flatnonzero(gap2 < near * near * edge2)
    normals = np.einsum("hc,hcx->hx", bary[index], np.asarray(source_normals, float)[hits.vertices[index]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return index, at[index], normals


@numba.njit(cache=True, inline="always")
def _barycentric_point(vertices, i0, i1, i2, b0, u, v, x):
    """Coordinate ``x`` of ``b0 p[i0] + u p[i1] + v p[i2]``."""
    return b0 * vertices[i0, x] + u * vertices[i1, x] + v * vertices[i2, x]


@numba.njit(cache=True, parallel=True, nogil=True)
def _near_kernel(points, vertices, faces, rows, triangles, uv, near, flags):
    """``flags[h]``: hit ``h`` lies nearer its receiver point than ``near`` times its triangle's longest edge
    (``near_hits``'s numpy test)."""
    for h in numba.prange(rows.shape[0]):
        f = triangles[h]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        edge2 = 0.0
        for a, b in ((i0, i1), (i1, i2), (i2, i0)):
            e0 = vertices[b, 0] - vertices[a, 0]
            e1 = vertices[b, 1] - vertices[a, 1]
            e2 = vertices[b, 2] - vertices[a, 2]
            edge2 = max(edge2, e0 ** 2 + e1 ** 2 + e2 ** 2)
        u, v = uv[h, 0], uv[h, 1]
        b0 = 1.0 - u - v
        p = rows[h]
        g0 = _barycentric_point(vertices, i0, i1, i2, b0, u, v, 0) - points[p, 0]
        g1 = _barycentric_point(vertices, i0, i1, i2, b0, u, v, 1) - points[p, 1]
        g2 = _barycentric_point(vertices, i0, i1, i2, b0, u, v, 2) - points[p, 2]
        flags[h] = g0 ** 2 + g1 ** 2 + g2 ** 2 < near * near * edge2


@numba.njit(cache=True, inline="always")
def _hit_corners(h, triangles, uv, faces):
    """Hit ``h``'s triangle's vertices and barycentric weights: ``(i0, i1, i2, 1 - u - v, u, v)``."""
    f = triangles[h]
    u, v = uv[h, 0], uv[h, 1]
    return faces[f, 0], faces[f, 1], faces[f, 2], 1.0 - u - v, u, v


@numba.njit(cache=True, parallel=True, nogil=True)
def _near_points_kernel(vertices, vertex_normals, faces, triangles, uv, index, at, normals):
    """The hit points ``at`` and unit interpolated normals of the hits ``index`` (``near_hits``)."""
    for q in numba.prange(index.shape[0]):
        h = index[q]
        i0, i1, i2, b0, u, v = _hit_corners(h, triangles, uv, faces)
        for x in range(3):
            at[q, x] = _barycentric_point(vertices, i0, i1, i2, b0, u, v, x)
            normals[q, x] = _barycentric_point(vertex_normals, i0, i1, i2, b0, u, v, x)
        length = max(np.sqrt(normals[q, 0] ** 2 + normals[q, 1] ** 2 + normals[q, 2] ** 2), 1e-300)
        for x in range(3):
            normals[q, x] /= length


@numba.njit(cache=True, nogil=True, parallel=True)
def _near_correction_kernel(rows, factor, triangles, uv, faces, index, exact, values, starts, out):
    """``near_hit_correction``'s sum, hit after hit in the order of ``index`` (as ``np.add.at``); the runs
    ``index[starts[c]:starts[c + 1]]`` in parallel (no two runs add to one row)."""
    rgb = factor.shape[1] == 1 and factor.shape[2] == 1 and exact.shape[2] == 3
    for c in numba.prange(starts.shape[0] - 1):
        if rgb:
            _near_correction_run_rgb(rows, factor, triangles, uv, faces, index, exact, values, starts[c],
                                     starts[c + 1], out)
        else:
            _near_correction_run(rows, factor, triangles, uv, faces, index, exact, values, starts[c], starts[c + 1],
                                 out)


@numba.njit(cache=True, nogil=True)
def _near_correction_run(rows, factor, triangles, uv, faces, index, exact, values, first, last, out):
    """The hits ``index[first:last]`` of :func:`_near_correction_kernel`, in order."""
    n_kp, n_k, n_c = factor.shape[1], factor.shape[2], exact.shape[2]
    diff = np.empty((n_k, n_c))
    for q in range(first, last):
        h = index[q]
        i0, i1, i2, b0, u, v = _hit_corners(h, triangles, uv, faces)
        for k in range(n_k):
            for c in range(n_c):
                diff[k, c] = exact[q, k, c] - (b0 * values[i0, k, c] + u * values[i1, k, c] + v * values[i2, k, c])
        p = rows[h]
        for kp in range(n_kp):
            for c in range(n_c):
                total = 0.0
                for k in range(n_k):
                    total += factor[h, kp, k] * diff[k, c]
                out[p, kp, c] += total


@numba.njit(cache=True, nogil=True)
def _near_correction_run_rgb(rows, factor, triangles, uv, faces, index, exact, values, first, last, out):
    """:func:`_near_correction_run` for ``K' = K = 1`` and 3 colours, unrolled: the same operations in the same
    order (``0.0 +`` the one product, as the general sum starts from 0.0), so the same values bit for bit."""
    for q in range(first, last):
        h = index[q]
        i0, i1, i2, b0, u, v = _hit_corners(h, triangles, uv, faces)
        weight = factor[h, 0, 0]
        p = rows[h]
        for c in range(3):
            diff = exact[q, 0, c] - (b0 * values[i0, 0, c] + u * values[i1, 0, c] + v * values[i2, 0, c])
            out[p, 0, c] += 0.0 + weight * diff


@numba.njit(cache=True, nogil=True, parallel=True)
def light_outer_kernel(terms, radiance, out, add):
    """``out[q, k, c] = terms[q, k] radiance[c]`` (``np.multiply.outer``), or with ``add`` that added to ``out``
    (``out + outer``): the same roundings, element by element, as numpy's two operations."""
    for q in numba.prange(terms.shape[0]):
        for k in range(terms.shape[1]):
            for c in range(radiance.shape[0]):
                part = terms[q, k] * radiance[c]
                out[q, k, c] = out[q, k, c] + part if add else part


#: hits per run of :func:`_near_correction_kernel` (at least; a run ends where its receiver point does)
_CORRECTION_RUN = 4096


def _row_runs(rows) -> np.ndarray:
    """(R + 1,) bounds of runs of ``rows`` (the hits' receiver points in their order) of about
    :data:`_CORRECTION_RUN` hits, each run's rows apart from every other's: the whole when ``rows`` is not
    sorted."""
    rows = np.asarray(rows)
    if len(rows) <= _CORRECTION_RUN or np.any(rows[1:] < rows[:-1]):
        return np.array([0, len(rows)], np.int64)
    cuts = np.searchsorted(rows, rows[np.arange(_CORRECTION_RUN, len(rows), _CORRECTION_RUN)], side="left")
    return np.unique(np.concatenate([[0], cuts, [len(rows)]])).astype(np.int64)


def near_hit_correction(hits: ResidualHits, index, exact, vertex_values, n_points: int,
                        method: str = "numba") -> np.ndarray:
    """``L_k',c`` (n_points, K', C): over the hits ``index`` of ``hits``, ``factor (exact - interp)``, with
    ``exact`` (Q, K, C) a source's radiance term ``colour_k L_k`` evaluated at those hits and ``interp`` the
    barycentric interpolation of ``vertex_values`` (V_s, K, C), the same term at its vertices.
    ``method="numba"``: one serial pass over the hits; ``"reference"``: numpy, the specification (within float64
    rounding: the sums' order differs)."""
    check_choice(method, "method", ("numba", "reference"))
    index = np.asarray(index, np.int64)
    values = np.asarray(vertex_values, float)
    if method == "numba":
        exact = np.ascontiguousarray(exact, np.float64)
        out = np.zeros((n_points, hits.factor.shape[1], exact.shape[2]))
        _near_correction_kernel(*(np.ascontiguousarray(a, t) for a, t in (
            (hits.rows, np.int64), (hits.factor, np.float64), (hits.triangles, np.int64), (hits.uv, np.float64),
            (hits.faces, np.int64))), index, exact, np.ascontiguousarray(values), _row_runs(hits.rows[index]), out)
        return out
    at = np.einsum("hv,hvkc->hkc", hits.bary[index], values[hits.vertices[index]])
    per_ray = np.einsum("hqk,hkc->hqc", hits.factor[index], np.asarray(exact, float) - at)
    out = np.zeros((n_points,) + per_ray.shape[1:])
    np.add.at(out, hits.rows[index], per_ray)
    return out
