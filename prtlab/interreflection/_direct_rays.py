"""Direct light of area and point lights by shadow rays at the frame's poses (``shadows="rays"``).

An extension of Iwasaki et al. 2007 (issue 18). The paper's direct light is the order-n SH product of the
light, the visibility and the clamped cosine (Eq. 8 with shadow fields); under a near area light that
product smears the light and its shadows (9-13 % per vertex on the open room corner at order 4, in
docs/FIDELITY.md). Here each vertex integrates the lights itself:

``L_k(x) = sum_lights integral L_e g_k(w) (n . w)+ V(x, w) dw``,

the term ``L_k`` (V, K, C) that the SH path computes as ``P_n(V G_k) . L`` (:meth:`direct_step`), with
``V`` from shadow rays against every object at the frame's poses (so self-shadows and a moved object's
shadow are exact). An area light is sampled by area, ``m`` points per vertex on a ``rows x side <= m`` grid
of the parallelogram jittered per vertex (unbiased at each vertex, stratified across the light); the
estimator is ``L_e A / m sum_j g_k cos_x cos_l V / d^2``. A point light takes one shadow ray. The same
samples give the radiance toward the camera with the material's BRDF itself, so a glossy receiver's direct
light is not limited by its K-term separable form (which still carries the light into the bounces). The
environment stays in SH (low frequency: the paper's form).

Random numbers: the jitter of sample ``j`` of vertex ``p`` for light ``i`` is a counter-based hash of
``(seed, i, p, j)`` (SplitMix64), so results do not depend on chunks, threads or which vertices a call
recomputes.

Tiers: :func:`light_terms` is one numba kernel per light (parallel over vertices: samples, weights, the
shadow rays traced in the kernel through Embree 16 at a time, ``g_k`` and the BRDF), for
:class:`prtlab.brdf.Phong` / Lambert receivers and a caster with an Embree scene; :func:`light_terms_reference`
is its float64 numpy
specification (shadow rays through :meth:`RayCaster.occluded`) and the fallback for anything else. With
``probe`` both cast a sub-grid of an area light's samples first and let their agreement decide the others (the
penumbra early-out, option ``light_probe``). Both
return the per-light terms at unit radiance, ``S`` (V, K) and ``F`` (V, C), and the per-sample shadow mask,
so a caller can rescale by a new radiance without casting (relighting), shade a new camera from the mask,
and re-cast only the samples whose segment meets a moved object's bounding sphere (``visibility``/``moved``).
"""

from __future__ import annotations

import numba
import numpy as np

from prtlab import brdf
from prtlab.brdf._kernels import tangent_frame_at
from prtlab.geometry import _embree
from prtlab.scene import AreaLight, PointLight

from ._residual import _mix, _uniform  # SplitMix64, the residual gather's counter-based streams

__all__ = ["ray_traced_direct", "ray_traced_direct_reference", "light_terms", "light_terms_reference",
           "mirror_wo", "sample_count", "widened_sphere", "blocker_bounds", "object_bound", "lit_integral"]

#: vertices per chunk of the reference tier: bounds its (chunk, m, 3) sample arrays (about 50 MB at m = 256)
_CHUNK = 8192

#: samples a thread of the kernel takes at a time (a block of whole vertices: ``max(1, 512 // m)`` of them)
_SAMPLES_PER_TASK = 512

#: Whether :func:`light_terms`' kernel traces its shadow rays 16 at a time (``rtcOccluded16``, the lanes filled with
#: a block's rays in sample order) rather than one at a time (``rtcOccluded1``); the masks are the same (tests).
PACKETS = True

#: :func:`light_terms`' kernel takes a term of ``g_k`` whose radial values agree within this fraction of their
#: largest (and has no azimuth) as constant, the middle of its values, on a receiver with ``ks = 0``: a Lambertian
#: BRDF's fitted separable form, whose values vary by about 1e-13 by the fit's rounding. Its sums then need the lit
#: samples' weights alone (no polar angle, no interpolation), within half that spread (relative) of the reference
#: tier's.
LEVEL_SPREAD = 1e-12

_FLOAT32_MAX = float(np.finfo(np.float32).max)
_GOLDEN = 0x9E3779B97F4A7C15
_MASK64 = 0xFFFFFFFFFFFFFFFF


# ------------------------------------------------------------------------------------------- sampling


def _grid_shape(m: int) -> tuple[int, int]:
    """``(rows, side)`` of the jittered grid, ``rows * side <= m``."""
    side = max(1, int(np.sqrt(m)))
    return max(1, m // side), side


def sample_count(light, samples: int) -> int:
    """Samples per vertex actually taken on ``light``: ``rows * side`` of the grid (1 for a point light)."""
    if isinstance(light, PointLight):
        return 1
    rows, side = _grid_shape(samples)
    return rows * side


def _mix_int(z: int) -> int:
    """SplitMix64's finaliser on a Python int."""
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31)


def _key(seed: int, light: int) -> int:
    """The stream key of light number ``light`` (uint64 as a Python int)."""
    return _mix_int((int(seed) & _MASK64) ^ _mix_int(((int(light) + 1) * _GOLDEN) & _MASK64))


def _mix_numpy(z: np.ndarray) -> np.ndarray:
    """:func:`_mix` on uint64 arrays (wrapping arithmetic)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def jitter(seed: int, light: int, rows: np.ndarray, m: int) -> np.ndarray:
    """(len(rows), m, 2) uniforms in [0, 1) of vertices ``rows`` (their indices in the call's points):
    the numpy specification of the kernel's hash, bit for bit."""
    stream = _mix_numpy(np.uint64(_key(seed, light)) ^ _mix_numpy(np.asarray(rows, dtype=np.uint64)))
    counter = np.arange(2 * m, dtype=np.uint64)
    with np.errstate(over="ignore"):
        z = _mix_numpy(stream[:, None] + (counter[None] + np.uint64(1)) * np.uint64(_GOLDEN))
    return ((z >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)).reshape(len(stream), m, 2)


def _light_geometry(light, samples: int) -> tuple[np.ndarray, int, int, bool]:
    """``(params (13,), rows, side, area)``: centre (or position), u, v, normal and the weight scale
    ``A / m`` (1 for a point light), the grid and whether the light is an area light."""
    if isinstance(light, AreaLight):
        rows, side = _grid_shape(samples)
        params = np.concatenate([np.asarray(getattr(light, f), float) for f in ("center", "u", "v")]
                                + [np.asarray(light.normal, float), [light.area / (rows * side)]])
        return params, rows, side, True
    params = np.zeros(13)
    params[:3] = np.asarray(light.position, float)
    params[12] = 1.0
    return params, 1, 1, False


def _reach(params, area: bool) -> float:
    """The distance from an area light's centre to its farthest corner (0 for a point light), widened by 1e-9
    relative."""
    if not area:
        return 0.0
    u, v = params[3:6], params[6:9]
    return float(max(np.linalg.norm(u + v), np.linalg.norm(u - v))) * (1.0 + 1e-9)


def _emission(light) -> np.ndarray:
    return np.asarray(light.radiance if isinstance(light, AreaLight) else light.intensity, float)


def mirror_wo(wo, normals) -> np.ndarray:
    """``wo`` mirrored above the horizon of ``normals`` where it is below it (two-sided BRDFs)."""
    wo, n = np.asarray(wo, float), np.asarray(normals, float)
    below = np.minimum(np.einsum("vi,vi->v", wo, n), 0.0)
    return wo - 2.0 * below[:, None] * n


def widened_sphere(sphere, epsilon: float) -> np.ndarray:
    """A bounding sphere (centre, radius) widened for ``moved=`` of :func:`light_terms`: by twice the rays'
    origin offset ``epsilon`` and a relative ``1e-5`` of the coordinates (Embree's float32 rays)."""
    c, r = np.asarray(sphere[:3], float), float(sphere[3])
    return np.array([*c, r + 2.0 * epsilon + 1e-5 * (float(np.max(np.abs(c))) + r) + 1e-12])


def object_bound(vertices, flat: bool, epsilon: float) -> np.ndarray | None:
    """One object's bound in :func:`blocker_bounds` from its world ``vertices`` (V, 3): the slab (5,) of its plane
    (unit normal, lowest and highest ``n . p``) if ``flat``, else its sphere (4,) (centre: the bounding-box centre),
    both widened as :func:`widened_sphere` with ``epsilon``; None without vertices."""
    v = vertices
    if not len(v):
        return None
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    radius = float(np.sqrt(np.max(np.sum((v - centre) ** 2, axis=1))))
    sphere = widened_sphere([*centre, radius], epsilon)
    if not flat:
        return sphere
    _, _, vt = np.linalg.svd(v - v.mean(axis=0), full_matrices=False)
    normal = vt[-1] / np.linalg.norm(vt[-1])
    offset = v @ normal
    margin = sphere[3] - radius
    return np.array([*normal, offset.min() - margin, offset.max() + margin])


def blocker_bounds(caster, flat, exclude=None, bounds=None) -> tuple[np.ndarray, np.ndarray]:
    """``(spheres (S, 4), planes (P, 5))`` of ``blockers=`` in :func:`light_terms` for the objects of ``caster``:
    :func:`object_bound` of each, a flat object (``flat[i]``) as the slab of its plane, any other as its bounding
    sphere. ``exclude``: an object number left out (a flat receiver's own plane); ``bounds``: a function of the
    object number giving its :func:`object_bound` (a caller's cache), else computed here."""
    spheres, planes = [], []
    for i in range(len(flat)):
        if i == exclude:
            continue
        bound = bounds(i) if bounds is not None else object_bound(caster.world_vertices(i), flat[i], caster.epsilon)
        if bound is not None:
            (planes if flat[i] else spheres).append(bound)
    return np.asarray(spheres, float).reshape(-1, 4), np.asarray(planes, float).reshape(-1, 5)


def probe_mask(light, samples: int, probe: int) -> np.ndarray:
    """(m,) bool: the samples of ``light``'s grid cast first with ``probe`` (:func:`light_terms`), a
    ``prow x pside`` sub-grid (:func:`sample_count`'s shape of ``probe``) of rows and columns spread evenly over
    the grid, its first and last included; (0,) when there is nothing to probe (``probe`` 0 or at least ``m``, a
    point light)."""
    if isinstance(light, PointLight) or probe <= 0 or probe >= sample_count(light, samples):
        return np.zeros(0, dtype=np.bool_)
    rows, side = _grid_shape(samples)
    prow, pside = _grid_shape(probe)
    mask = np.zeros((rows, side), dtype=np.bool_)
    mask[np.ix_(np.unique(np.round(np.linspace(0, rows - 1, min(prow, rows))).astype(int)),
                np.unique(np.round(np.linspace(0, side - 1, min(pside, side))).astype(int)))] = True
    return mask.ravel()


def _check_probe(probe) -> int:
    if isinstance(probe, bool) or not isinstance(probe, (int, np.integer)) or probe < 0:
        raise ValueError(f"probe must be a non-negative int (the samples cast first; 0: none), got {probe!r}")
    return int(probe)


def _check(points, normals, wo):
    x, n, wo = (np.ascontiguousarray(a, dtype=np.float64) for a in (points, normals, wo))
    if x.ndim != 2 or x.shape[1] != 3 or n.shape != x.shape or wo.shape != x.shape:
        raise ValueError(f"points, normals and wo must be (V, 3) arrays of one shape, got {x.shape}, {n.shape}, "
                         f"{wo.shape}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(n)) and np.all(np.isfinite(wo))):
        raise ValueError("points, normals or wo contain NaN or inf; pass finite arrays")
    return x, n, wo


def _without_normal(normals) -> np.ndarray:
    """(V,) bool: the points without a normal, ``n . n == 0`` in float64 (a zero normal, or one whose components'
    squares all underflow, each below about 1.5e-162): the normals :func:`prtlab.brdf.local_frame` refuses."""
    return ~(np.einsum("vi,vi->v", normals, normals) > 0.0)


@numba.njit(cache=True, nogil=True)
def _first_without_wo(normals, wo) -> int:
    """The first point with a normal (``n . n > 0``) whose ``wo . wo`` is 0 (-1: none), in one pass."""
    for p in range(normals.shape[0]):
        o0, o1, o2, n0, n1, n2 = wo[p, 0], wo[p, 1], wo[p, 2], normals[p, 0], normals[p, 1], normals[p, 2]
        if not o0 * o0 + o1 * o1 + o2 * o2 > 0.0 and n0 * n0 + n1 * n1 + n2 * n2 > 0.0:
            return p
    return -1


def _check_decided(decided, decided_before, n_points: int, visibility):
    """``(decided, decided_before)`` as (V,) int8 arrays (or None) of :func:`light_terms`."""
    out = []
    for name, a in (("decided", decided), ("decided_before", decided_before)):
        if a is not None:
            a = np.asarray(a)
            if a.shape != (n_points,) or a.dtype.kind not in "iub" or np.any((a < 0) | (a > 2)):
                raise ValueError(f"{name} must be a ({n_points},) int array of 0 (cast), 1 (clear) or 2 (blocked), "
                                 f"got {a.dtype} {a.shape}")
            a = np.ascontiguousarray(a, np.int8)
        out.append(a)
    if out[1] is not None and visibility is None:
        raise ValueError("decided_before= needs the visibility= of the call it was given to")
    return out[0], out[1]


def _check_first(first) -> int:
    if isinstance(first, bool) or not isinstance(first, (int, np.integer)) or first < 0:
        raise ValueError(f"first must be a non-negative int (the first point's stream number), got {first!r}")
    return int(first)


def _check_reuse(visibility, moved, n_points: int, m: int):
    if visibility is None:
        if moved is not None:
            raise ValueError("moved= needs the previous visibility= of the same points and light")
        return None, None
    visibility = np.asarray(visibility)
    if visibility.dtype != np.bool_ or visibility.shape != (n_points, m):
        raise ValueError(f"visibility must be the ({n_points}, {m}) bool mask of an earlier call, got "
                         f"{visibility.dtype} {visibility.shape}")
    moved = np.zeros((0, 4)) if moved is None else np.ascontiguousarray(moved, dtype=np.float64).reshape(-1, 4)
    return np.ascontiguousarray(visibility), moved


# ------------------------------------------------------------------------------------------- exact unshadowed light


def lit_integral(points, normals, light) -> np.ndarray:
    """(V,) ``integral (n . w)+ dw`` over the solid angle of area ``light`` (the parallelogram ``c +- u +- v``)
    seen from ``points`` (V, 3) with unit ``normals`` (V, 3), 0 where a point is not in front of the light
    (``(c - x) . l >= 0``): the expectation of a vertex's lit weights' sum in :func:`light_terms` when no sample is
    blocked. Float64 numpy (the specification of the kernel's :func:`_lit_integral`).

    Notes
    -----
    Lambert's formula for a polygon ``y_1 .. y_k`` (Arvo 1995, Eq. 4) clipped to the horizon ``n . (y - x) >= 0``
    (one Sutherland-Hodgman pass over the corners in order): with ``a_i = y_i - x``,
    ``E = 1/2 |sum_i angle(a_i, a_{i+1}) n . (a_i x a_{i+1}) / |a_i x a_{i+1}||``, the angle as
    ``arctan2(|a x b|, a . b)``.

    References
    ----------
    J. Arvo, "Applications of irradiance tensors to the simulation of non-Lambertian phenomena", SIGGRAPH 1995.
    """
    x, n = np.asarray(points, float).reshape(-1, 3), np.asarray(normals, float).reshape(-1, 3)
    c, u, v, l = (np.asarray(getattr(light, f), float) for f in ("center", "u", "v", "normal"))
    corners = [c - u - v - x, c + u - v - x, c + u + v - x, c - u + v - x]  # each (V, 3)
    height = [np.einsum("vi,vi->v", a, n) for a in corners]
    total, count = np.zeros(len(x)), np.zeros(len(x), np.int64)
    first, previous = np.zeros((len(x), 3)), np.zeros((len(x), 3))

    def emit(a, at):
        nonlocal total
        cross = np.cross(previous, a)
        length = np.linalg.norm(cross, axis=1)
        angle = np.arctan2(length, np.einsum("vi,vi->v", previous, a))
        term = np.where(length > 0.0, angle * np.einsum("vi,vi->v", n, cross) / np.maximum(length, 1e-300), 0.0)
        total = total + np.where(at & (count > 0), term, 0.0)
        first[at & (count == 0)] = a[at & (count == 0)]
        previous[at] = a[at]
        count[at] += 1

    for i in range(4):
        a, b, ha, hb = corners[i], corners[(i + 1) % 4], height[i], height[(i + 1) % 4]
        emit(a, ha >= 0.0)
        crossing = (ha >= 0.0) != (hb >= 0.0)
        t = np.where(crossing, ha / np.where(crossing, ha - hb, 1.0), 0.0)
        emit(a + t[:, None] * (b - a), crossing)
    emit(first, count >= 2)  # the closing edge
    front = np.einsum("vi,i->v", c - x, l) < 0.0
    return np.where(front, 0.5 * np.abs(total), 0.0)


def _level_form(f, sep) -> bool:
    """Whether :func:`_terms_kernel` takes receiver ``f`` (``sep`` its separable form) as direction-independent: a
    :class:`prtlab.brdf.Phong` with ``ks = 0`` and ``g_k`` without azimuth whose radial values (as the kernel gets
    them) agree within :data:`LEVEL_SPREAD` of their largest."""
    if not (isinstance(f, brdf.Phong) and isinstance(sep, brdf.SeparableBRDF)) or np.any(np.asarray(f.ks) != 0.0):
        return False
    if np.any(np.asarray(sep.freq) != 0) or np.any(np.asarray(sep.parity) != 0):
        return False
    values = sep._ext(sep.theta_in, sep.g_radial, 0.5 * np.pi)[1]
    low, high = values.min(axis=1), values.max(axis=1)
    return bool(np.all(high - low <= LEVEL_SPREAD * np.maximum(np.abs(low), np.abs(high))))


# ------------------------------------------------------------------------------------------- reference tier


def _segments_meet(x, y, spheres) -> np.ndarray:
    """(V, m) whether the segment ``x -> y`` (x (V, 3), y (V, m, 3)) meets any sphere (S, 4) (centre, radius)."""
    out = np.zeros(y.shape[:2], dtype=bool)
    d = y - x[:, None]
    dd = np.maximum(np.einsum("vmi,vmi->vm", d, d), 1e-300)
    for c0, c1, c2, r in spheres:
        cx = np.array([c0, c1, c2]) - x  # (V, 3)
        t = np.clip(np.einsum("vmi,vi->vm", d, cx) / dd, 0.0, 1.0)
        gap = cx[:, None] - t[..., None] * d
        out |= np.einsum("vmi,vmi->vm", gap, gap) <= r * r
    return out


def _cast_stage(caster, x, normals, w, dist, stage, meets, visibility, blocked, stats):
    """Into ``blocked`` (V, m): the samples ``stage`` (V, m) by shadow rays, or where ``meets`` is False (the
    segment misses every moved sphere) the previous ``visibility``."""
    trace = stage if meets is None else stage & meets
    r_, c_ = np.nonzero(trace)
    if stats is not None:
        stats["rays_cast"] = stats.get("rays_cast", 0) + len(r_)
    if len(r_):
        blocked[r_, c_] = caster.occluded(x[r_], w[r_, c_], dist[r_, c_] - caster.epsilon, normals=normals[r_])
    if visibility is not None:
        blocked |= visibility & stage & ~trace


def light_terms_reference(points, normals, wo, f, sep, caster, light, index: int, samples: int, seed: int = 0,
                          visibility=None, moved=None, stats: dict | None = None, blockers=None, first: int = 0,
                          previous=None, probe: int = 0, decided=None, decided_before=None, exact_lit: bool = False):
    """Float64 numpy specification of :func:`light_terms` (same arguments and results; every ray is cast,
    ``blockers`` and ``previous`` are not used)."""
    x, n, wo = _check(points, normals, wo)
    bare = _without_normal(n)
    first = _check_first(first)
    params, rows, side, area = _light_geometry(light, samples)
    m = rows * side
    probe = probe_mask(light, samples, _check_probe(probe))
    visibility, moved = _check_reuse(visibility, moved, len(x), m)
    decided, decided_before = _check_decided(decided, decided_before, len(x), visibility)
    c, u, v, normal, scale = params[:3], params[3:6], params[6:9], params[9:12], params[12]
    exact = bool(exact_lit) and area and _level_form(f, sep)
    corner = np.stack([a.ravel() for a in np.meshgrid(np.arange(rows) / rows, np.arange(side) / side,
                                                       indexing="ij")], axis=1)  # (m, 2)
    cell = np.array([1.0 / rows, 1.0 / side])
    S, F = np.zeros((len(x), sep.K)), np.zeros((len(x), f.channels))
    blocked_all = np.zeros((len(x), m), dtype=bool)
    for lo in range(0, len(x), _CHUNK):
        part = slice(lo, lo + _CHUNK)
        xp, np_, wop, barep = x[part], n[part], wo[part], bare[part]
        if barep.any():  # no normal: no live sample; a placeholder frame and wo for g and f (their weights are 0)
            np_, wop = np_.copy(), wop.copy()
            np_[barep] = wop[barep] = (0.0, 0.0, 1.0)
        if area:
            st = (corner[None] + jitter(seed, index, np.arange(lo, lo + len(xp)) + first, m) * cell) * 2.0 - 1.0
            y = c + st[..., :1] * u + st[..., 1:] * v  # (V, m, 3)
        else:
            y = np.broadcast_to(c, (len(xp), 1, 3))
        d = y - xp[:, None]
        dist = np.linalg.norm(d, axis=-1)
        w = d / np.maximum(dist, 1e-300)[..., None]
        w[dist == 0.0] = (0.0, 0.0, 1.0)  # a sample at the point: dead (below), a placeholder direction for g and f
        cos_x = np.einsum("vmi,vi->vm", w, np_)
        cos_l = -w @ normal if area else np.ones_like(cos_x)
        live = (cos_x > 0.0) & (cos_l > 0.0) & (dist > 0.0) & ~barep[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):  # dist == 0 (not live): inf or NaN, discarded
            weight = np.where(live, cos_x * cos_l / np.maximum(dist, 1e-300) ** 2, 0.0) * scale
        meets = _segments_meet(xp, y, moved) if visibility is not None else None
        given = np.zeros(len(xp), np.int8) if decided is None else decided[part]
        if meets is not None and decided_before is not None:  # the previous bits given, not cast: cast them
            meets |= (decided_before[part] != 0)[:, None]
        open_ = live & (given == 0)[:, None]  # the samples not given
        blocked = live & (given == 2)[:, None]
        first_stage = open_ & probe[None] if len(probe) else open_
        _cast_stage(caster, xp, np_, w, dist, first_stage, meets, None if visibility is None else visibility[part],
                    blocked, stats)
        if len(probe):  # the others: the probes' common answer, else cast (re-cast where the old bits were agreed)
            n_lit = np.sum(first_stage & ~blocked, axis=1)
            n_blocked = np.sum(first_stage & blocked, axis=1)
            agreed = (n_lit > 0) != (n_blocked > 0)
            others = open_ & ~probe[None]
            blocked |= others & agreed[:, None] & (n_blocked > 0)[:, None]
            if visibility is not None:
                old = visibility[part]
                redo = (np.sum(first_stage & ~old, axis=1) > 0) != (np.sum(first_stage & old, axis=1) > 0)
                meets = meets | redo[:, None]
            _cast_stage(caster, xp, np_, w, dist, others & ~agreed[:, None], meets,
                        None if visibility is None else visibility[part], blocked, stats)
        weight[blocked] = 0.0
        blocked_all[part] = blocked
        g = sep.g(brdf.to_local(w, np.broadcast_to(np_[:, None], w.shape)))  # (V, m, K)
        S[part] = np.einsum("vm,vmk->vk", weight, g)
        F[part] = np.einsum("vm,vmc->vc", weight, f.eval(w, wop[:, None], np_[:, None]))
        S[part][barep], F[part][barep] = 0.0, 0.0  # +0 (a zero weight times a negative g_k is -0)
        if exact:  # some live sample and none blocked: the exact integral, g_k and f at the normal
            at = np.nonzero(np.any(live, axis=1) & ~np.any(blocked, axis=1))[0]
            if len(at):
                total = lit_integral(xp[at], np_[at], light)[:, None]
                S[lo + at] = total * sep.g(np.array([[0.0, 0.0, 1.0]]))
                F[lo + at] = total * f.eval(np_[at], wop[at], np_[at])
    return S, F, blocked_all


# ------------------------------------------------------------------------------------------- numba tier


@numba.njit(cache=True, inline="always")
def _segment_meets(x0, x1, x2, y0, y1, y2, spheres):
    """Whether the segment ``x -> y`` meets any sphere of ``spheres`` (S, 4) (as :func:`_segments_meet`)."""
    return _capsule_meets(x0, x1, x2, y0, y1, y2, 0.0, spheres)


@numba.njit(cache=True, inline="always")
def _capsule_meets(x0, x1, x2, y0, y1, y2, reach, spheres):
    """Whether any sphere of ``spheres`` (S, 4) comes within ``reach`` of the segment ``x -> y``: the segments
    from ``x`` to every point within ``reach`` of ``y`` lie in that capsule."""
    d0, d1, d2 = y0 - x0, y1 - x1, y2 - x2
    dd = max(d0 * d0 + d1 * d1 + d2 * d2, 1e-300)
    for s in range(spheres.shape[0]):
        c0, c1, c2 = spheres[s, 0] - x0, spheres[s, 1] - x1, spheres[s, 2] - x2
        t = min(max((d0 * c0 + d1 * c1 + d2 * c2) / dd, 0.0), 1.0)
        g0, g1, g2 = c0 - t * d0, c1 - t * d1, c2 - t * d2
        r = spheres[s, 3] + reach
        if g0 * g0 + g1 * g1 + g2 * g2 <= r * r:
            return True
    return False


@numba.njit(cache=True, inline="always")
def _listed_meet(x0, x1, x2, y0, y1, y2, spheres, planes, near, n_spheres, n_planes):
    """Whether the segment ``x -> y`` meets one of the spheres ``near[:n_spheres]`` (as :func:`_segment_meets`) or
    reaches one of the slabs ``near[S:S + n_planes]`` (``S``: the number of spheres; a slab is missed when both
    ends lie beyond one side of it)."""
    total = spheres.shape[0]
    d0, d1, d2 = y0 - x0, y1 - x1, y2 - x2
    dd = max(d0 * d0 + d1 * d1 + d2 * d2, 1e-300)
    for q in range(n_spheres):
        s = near[q]
        c0, c1, c2 = spheres[s, 0] - x0, spheres[s, 1] - x1, spheres[s, 2] - x2
        t = min(max((d0 * c0 + d1 * c1 + d2 * c2) / dd, 0.0), 1.0)
        g0, g1, g2 = c0 - t * d0, c1 - t * d1, c2 - t * d2
        r = spheres[s, 3]
        if g0 * g0 + g1 * g1 + g2 * g2 <= r * r:
            return True
    for q in range(n_planes):
        s = near[total + q]
        a0, a1, a2, lo, hi = planes[s, 0], planes[s, 1], planes[s, 2], planes[s, 3], planes[s, 4]
        sx, sy = a0 * x0 + a1 * x1 + a2 * x2, a0 * y0 + a1 * y1 + a2 * y2
        if not ((sx > hi and sy > hi) or (sx < lo and sy < lo)):
            return True
    return False


@numba.njit(cache=True, inline="always")
def _near_blockers(x0, x1, x2, params, reach, spheres, planes, near):
    """The blockers a segment from ``x`` to a point of the light (``params``: within ``reach`` of its centre, on the
    parallelogram ``c +- u +- v``) may meet, into ``near`` (spheres first, then slabs at ``near[S:]``): the spheres
    within ``reach`` of the segment to the centre (:func:`_capsule_meets`), the slabs that ``x`` and the whole
    parallelogram (its lowest and highest ``n . p``, widened by ``1e-9`` relative) do not both lie beyond on one
    side. Returns ``(n_spheres, n_planes)``; the others cannot meet such a segment."""
    c0, c1, c2 = params[0], params[1], params[2]
    d0, d1, d2 = c0 - x0, c1 - x1, c2 - x2  # _capsule_meets' arithmetic, the segment's terms once
    dd = max(d0 * d0 + d1 * d1 + d2 * d2, 1e-300)
    n_spheres = 0
    for s in range(spheres.shape[0]):
        e0, e1, e2 = spheres[s, 0] - x0, spheres[s, 1] - x1, spheres[s, 2] - x2
        t = min(max((d0 * e0 + d1 * e1 + d2 * e2) / dd, 0.0), 1.0)
        g0, g1, g2 = e0 - t * d0, e1 - t * d1, e2 - t * d2
        r = spheres[s, 3] + reach
        if g0 * g0 + g1 * g1 + g2 * g2 <= r * r:
            near[n_spheres] = s
            n_spheres += 1
    total = spheres.shape[0]
    n_planes = 0
    for s in range(planes.shape[0]):
        a0, a1, a2, lo, hi = planes[s, 0], planes[s, 1], planes[s, 2], planes[s, 3], planes[s, 4]
        sx = a0 * x0 + a1 * x1 + a2 * x2
        mid = a0 * c0 + a1 * c1 + a2 * c2
        half = abs(a0 * params[3] + a1 * params[4] + a2 * params[5]) + abs(a0 * params[6] + a1 * params[7]
                                                                              + a2 * params[8])
        margin = 1e-9 * (1.0 + abs(mid) + half + abs(lo) + abs(hi))
        if not ((sx > hi and mid - half > hi + margin) or (sx < lo and mid + half < lo - margin)):
            near[total + n_planes] = s
            n_planes += 1
    return n_spheres, n_planes


@numba.njit(cache=True, inline="always")
def _light_extent(x0, x1, x2, n0, n1, n2, params):
    """``((c - x) . n, |u . n|, |v . n|, (c - x) . l, |u . l|, |v . l|, tol)`` of area light ``params`` at ``x``
    (normal ``n``): the heights of its centre and half-sides over the horizon and over the light's plane, and
    :func:`_unlit`'s margin ``tol``."""
    c0, c1, c2 = params[0] - x0, params[1] - x1, params[2] - x2
    u0, u1, u2, v0, v1, v2 = params[3], params[4], params[5], params[6], params[7], params[8]
    l0, l1, l2 = params[9], params[10], params[11]
    tol = 1e-12 * ((abs(params[0]) + abs(u0) + abs(v0) + abs(x0)) * (abs(n0) + abs(l0))
                   + (abs(params[1]) + abs(u1) + abs(v1) + abs(x1)) * (abs(n1) + abs(l1))
                   + (abs(params[2]) + abs(u2) + abs(v2) + abs(x2)) * (abs(n2) + abs(l2)))
    return (c0 * n0 + c1 * n1 + c2 * n2, abs(u0 * n0 + u1 * n1 + u2 * n2), abs(v0 * n0 + v1 * n1 + v2 * n2),
            c0 * l0 + c1 * l1 + c2 * l2, abs(u0 * l0 + u1 * l1 + u2 * l2), abs(v0 * l0 + v1 * l1 + v2 * l2), tol)


@numba.njit(cache=True, inline="always")
def _no_normal(n0, n1, n2):
    """Whether ``n`` is no normal, ``n . n == 0`` (as :func:`_without_normal`; the order of the sum does not matter:
    it is 0 exactly when each square is)."""
    return not n0 * n0 + n1 * n1 + n2 * n2 > 0.0


@numba.njit(cache=True, inline="always")
def _unlit(x0, x1, x2, n0, n1, n2, params):
    """Whether no point of the light (``params``: ``c + s u + t v``, ``|s|, |t| <= 1``; a point light has ``u = v =
    0``) is above the horizon of ``x`` (normal ``n``), or ``x`` is not in front of an area light (normal ``l``):
    ``(c - x) . n + |u . n| + |v . n|`` (the largest ``(y - x) . n`` over the parallelogram, at a corner) is below
    ``-tol``, or ``(c - x) . l - |u . l| - |v . l|`` above ``tol``, with ``tol = 1e-12 sum_i (|c_i| + |u_i| + |v_i| +
    |x_i|) (|n_i| + |l_i|)``. The kernel's ``cos_x`` (``cos_l``) of a sample has the sign of that product up to
    rounding of a few units in the last place of those terms, far below ``tol``: a vertex this gives True has no
    live sample, as drawing them would find."""
    h, hu, hv, f, fu, fv, tol = _light_extent(x0, x1, x2, n0, n1, n2, params)
    return h + hu + hv < -tol or f - fu - fv > tol


@numba.njit(cache=True, inline="always")
def _wholly_above(x0, x1, x2, n0, n1, n2, params):
    """Whether every point of area light ``params`` is above the horizon of ``x`` (normal ``n``) and ``x`` in front
    of it, with :func:`_unlit`'s margin ``tol``: ``(c - x) . n - |u . n| - |v . n|`` (the smallest ``(y - x) . n``)
    above ``tol`` and ``(c - x) . l + |u . l| + |v . l|`` below ``-tol``. Then every sample the kernel draws is
    live, as drawing them would find."""
    h, hu, hv, f, fu, fv, tol = _light_extent(x0, x1, x2, n0, n1, n2, params)
    return h - hu - hv > tol and f + fu + fv < -tol


#: bins of the table that starts the search of a node interval (:func:`_interval`)
_GUIDE_BINS = 1024


def _guide(nodes) -> tuple[np.ndarray, float]:
    """``(guide (_GUIDE_BINS,), bins per radian)`` of :func:`_interval`: bin ``b`` starts at the node interval of
    the bin before it, ``searchsorted(nodes, (b - 1) h) - 1`` (at least 0), at or below that of any angle in it."""
    h = float(nodes[-1]) / _GUIDE_BINS
    lower = np.maximum(np.arange(_GUIDE_BINS) - 1, 0) * h
    return np.maximum(np.searchsorted(nodes, lower) - 1, 0).astype(np.int64), 1.0 / h


@numba.njit(cache=True, inline="always")
def _interval(nodes, guide, per_radian, theta):
    """``(j, t)`` of ``theta`` among ``nodes`` as :func:`prtlab.brdf._kernels.factor_eval_kernel` finds them
    (``j = searchsorted(nodes, theta) - 1``), the search started at ``guide``'s bin (:func:`_guide`)."""
    last = nodes.shape[0] - 1
    if theta <= nodes[0]:
        return 0, 0.0
    if theta >= nodes[last]:
        return last - 1, 1.0
    b = min(int(theta * per_radian), guide.shape[0] - 1)
    j = guide[b]
    while nodes[j + 1] < theta:
        j += 1
    return j, (theta - nodes[j]) / (nodes[j + 1] - nodes[j])


@numba.njit(cache=True, inline="always")
def _factor(values, k, j, t, phi, freq, parity):
    """``g_k`` at ``(theta, phi)``, ``theta`` in node interval ``j`` at ``t`` (:func:`_interval`;
    :func:`prtlab.brdf._kernels.factor_eval_kernel`)."""
    radial = (1.0 - t) * values[k, j] + t * values[k, j + 1]
    if parity[k] == 0:
        return radial * (1.0 if freq[k] == 0 else np.cos(freq[k] * phi))
    return radial * np.sin(freq[k] * phi)


@numba.njit(cache=True, inline="always")
def _vertex_frame(n, wo, p):
    """The unit normal ``a``, tangents ``t``, ``b`` (Duff et al. 2017, as ``brdf.local_frame``), the unit ``wo``
    and ``a . wo`` of vertex ``p``: the BRDF's frame."""
    a0, a1, a2, t0, t1, t2, b0, b1, b2 = tangent_frame_at(n[p, 0], n[p, 1], n[p, 2])
    o0, o1, o2 = wo[p, 0], wo[p, 1], wo[p, 2]
    length = np.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
    o0, o1, o2 = o0 / length, o1 / length, o2 / length
    co = a0 * o0 + a1 * o1 + a2 * o2
    return a0, a1, a2, t0, t1, t2, b0, b1, b2, o0, o1, o2, co


@numba.njit(cache=True, inline="always")
def _cos_out(n, wo, p):
    """``a . wo`` of :func:`_vertex_frame` alone (the same arithmetic, so the same bits)."""
    n0, n1, n2 = n[p, 0], n[p, 1], n[p, 2]
    length = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    a0, a1, a2 = n0 / length, n1 / length, n2 / length
    o0, o1, o2 = wo[p, 0], wo[p, 1], wo[p, 2]
    size = np.sqrt(o0 * o0 + o1 * o1 + o2 * o2)
    o0, o1, o2 = o0 / size, o1 / size, o2 / size
    return a0 * o0 + a1 * o1 + a2 * o2


#: :func:`_polar_angle`'s reduction points ``i / 6`` (i = 0..6), numpy's ``arctan`` of them, and the Taylor series
#: of ``atan`` (``(-1)^k / (2k + 1)``, k = 0..7) about 0
_ATAN_POINTS = np.arange(7) / 6.0
_ATAN_AT_POINTS = np.arctan(_ATAN_POINTS)
_ATAN_SERIES = np.array([(-1.0) ** k / (2 * k + 1) for k in range(8)])


@numba.njit(cache=True, inline="always")
def _atan_unit(x):
    """``atan(x)`` for ``0 <= x <= 1``: ``atan(t) + atan((x - t) / (1 + x t))`` at the nearest point ``t = i / 6``,
    the second by its Taylor series (argument at most 1/12: the series' remainder is below ``2e-20``)."""
    i = max(min(int(x * 6.0 + 0.5), 6), 0)
    t = _ATAN_POINTS[i]
    y = (x - t) / (1.0 + x * t)
    yy = y * y
    series = _ATAN_SERIES[7]
    for k in range(6, -1, -1):
        series = series * yy + _ATAN_SERIES[k]
    return _ATAN_AT_POINTS[i] + y * series


@numba.njit(cache=True, inline="always")
def _polar_angle(r, z):
    """``arctan2(r, z)`` for finite ``r >= 0`` (the polar angle of a direction with ``z`` along the normal and
    ``r`` its distance from it; ``(0, -0)`` gives 0), within 1e-15 relative of numpy's (test); 9.5 ns against
    libm's 17."""
    if z >= r:
        return _atan_unit(r / z) if z > 0.0 else 0.0
    if r > -z:
        x = z / r
        return 0.5 * np.pi - (_atan_unit(x) if x >= 0.0 else -_atan_unit(-x))
    return np.pi - _atan_unit(r / -z)


@numba.njit(cache=True, inline="always")
def _lambert_edge(p0, p1, p2, a0, a1, a2, n0, n1, n2):
    """``angle(p, a) n . (p x a) / |p x a|`` (0 where ``p x a`` is 0): an edge's term of :func:`lit_integral`."""
    k0, k1, k2 = p1 * a2 - p2 * a1, p2 * a0 - p0 * a2, p0 * a1 - p1 * a0
    length = np.sqrt(k0 * k0 + k1 * k1 + k2 * k2)
    if not length > 0.0:
        return 0.0
    return _polar_angle(length, p0 * a0 + p1 * a1 + p2 * a2) * (n0 * k0 + n1 * k1 + n2 * k2) / length


@numba.njit(cache=True)
def _lit_integral(x0, x1, x2, n0, n1, n2, params):
    """:func:`lit_integral` at one point (``params``: :func:`_light_geometry`'s), the clipped polygon's edges summed
    as they are emitted."""
    c0, c1, c2 = params[0] - x0, params[1] - x1, params[2] - x2
    if not c0 * params[9] + c1 * params[10] + c2 * params[11] < 0.0:
        return 0.0
    u0, u1, u2, v0, v1, v2 = params[3], params[4], params[5], params[6], params[7], params[8]
    total, count = 0.0, 0
    f0, f1, f2, p0, p1, p2 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for i in range(4):
        sa, ta = (-1.0, 1.0, 1.0, -1.0, -1.0)[i], (-1.0, -1.0, 1.0, 1.0, -1.0)[i]
        sb, tb = (-1.0, 1.0, 1.0, -1.0, -1.0)[i + 1], (-1.0, -1.0, 1.0, 1.0, -1.0)[i + 1]
        a0, a1, a2 = c0 + sa * u0 + ta * v0, c1 + sa * u1 + ta * v1, c2 + sa * u2 + ta * v2
        b0, b1, b2 = c0 + sb * u0 + tb * v0, c1 + sb * u1 + tb * v1, c2 + sb * u2 + tb * v2
        ha, hb = a0 * n0 + a1 * n1 + a2 * n2, b0 * n0 + b1 * n1 + b2 * n2
        for emit in range(2):
            if emit == 0:
                if not ha >= 0.0:
                    continue
                e0, e1, e2 = a0, a1, a2
            else:
                if (ha >= 0.0) == (hb >= 0.0):
                    continue
                t = ha / (ha - hb)
                e0, e1, e2 = a0 + t * (b0 - a0), a1 + t * (b1 - a1), a2 + t * (b2 - a2)
            if count == 0:
                f0, f1, f2 = e0, e1, e2
            else:
                total += _lambert_edge(p0, p1, p2, e0, e1, e2, n0, n1, n2)
            p0, p1, p2 = e0, e1, e2
            count += 1
    if count >= 2:
        total += _lambert_edge(p0, p1, p2, f0, f1, f2, n0, n1, n2)
    return 0.5 * abs(total)


#: states of a sample in :func:`_terms_kernel`'s scratch
_DEAD, _LIT, _BLOCKED, _PENDING = 0, 1, 2, 3


@numba.njit(cache=True, inline="always")
def _flush(tracer_fn, tracer_scene, valid, address, f32, lane_sample, filled, state, blocked, lo, m):
    """Trace the ``filled`` lanes of a packet (``rtcOccluded16``; the other lanes off) and resolve their samples
    (lane ``k``: sample ``q = lane_sample[k]`` of the block from vertex ``lo``, ``m`` a vertex)."""
    w = _embree.PACKET
    for k in range(filled, w):
        valid[k] = 0
    _embree.rtc_call_packet(tracer_fn, valid.ctypes.data, tracer_scene, address)
    for k in range(filled):
        q = lane_sample[k]
        if f32[_embree.TFAR * w + k] < 0.0:
            state[q] = _BLOCKED
            blocked[lo + q // m, q % m] = True
        else:
            state[q] = _LIT
        valid[k] = 0


@numba.njit(cache=True, parallel=True, nogil=True)
def _terms_kernel(x, n, wo, params, area, rows, side, key, first, tracer_fn, tracer_scene, packet, step, slot_f32,
                  slot_u32, slot_valid, threads, eps, tnear, visibility, moved, previous_S, previous_F, reach, cull,
                  spheres, planes, probe, decided, decided_before, nodes, guide, per_radian, values, freq, parity, kd,
                  ks, exponent, exact, S, F, blocked, cast):
    """``S``, ``F`` and ``blocked`` of one light (see :func:`light_terms`); ``visibility`` (V, m) or (0, m):
    the previous mask, re-cast only where a segment meets a sphere of ``moved``; with ``previous_S`` and
    ``previous_F`` (else (0, K), (0, C)) a vertex whose capsule toward the light (radius ``reach``, every corner
    within it of the centre) meets no sphere of ``moved`` keeps their rows and its mask; with ``cull``, a segment that
    meets none of ``spheres`` (S, 4) and no slab of ``planes`` (P, 5) is not traced (unblocked), at vertices
    outside every sphere; ``probe`` (m,) or (0,): the samples decided first, whose agreement decides the others
    (:func:`light_terms`); ``decided`` (V,) int8 or (0,): a vertex's answer for every sample given (1 clear, 2
    blocked, 0 none: traced), ``decided_before`` (V,) or (0,) that of the call that gave ``visibility`` (a vertex
    decided there is traced wholly when it is not now); a vertex without a normal (:func:`_no_normal`) draws no
    samples, as one below the light's horizon; ``cast`` (V,): the samples traced per vertex; ``exact``
    (an area light, a receiver whose ``g_k`` and BRDF do not depend on the direction): a vertex with some live
    sample and none blocked takes :func:`_lit_integral` for its lit weights' sum.

    Where every sample is live (:func:`_wholly_above`) and the answer is known before the draw (given, or every
    segment culled, or the probes agree), a vertex draws no samples: all blocked gives zero sums, all clear with
    ``exact`` the integral.

    Threads take blocks of ``step`` vertices from a shared counter; iteration ``t`` of the thread loop traces
    through slot ``t``: with ``packet``, a block's rays 16 at a time in sample order (``rtcOccluded16``, lanes
    filled with the rays to trace only), else one at a time (``rtcOccluded1``). Per block, the samples are drawn
    and their rays traced first (the probes of every vertex, then the others), then each vertex sums its lit
    samples in sample order."""
    n_points = x.shape[0]
    m = rows * side
    reuse = visibility.shape[0] > 0
    keep = reuse and previous_S.shape[0] > 0
    probing = probe.shape[0] > 0
    deciding = decided.shape[0] > 0
    was_deciding = reuse and decided_before.shape[0] > 0
    n_terms = values.shape[0]
    n_channels = kd.shape[0]
    any_phi = False
    for k in range(n_terms):
        if freq[k] != 0 or parity[k] != 0:
            any_phi = True
    n_blocks = (n_points + step - 1) // step
    c0, c1, c2 = params[0], params[1], params[2]
    u0, u1, u2, v0, v1, v2 = params[3], params[4], params[5], params[6], params[7], params[8]
    l0, l1, l2, scale = params[9], params[10], params[11], params[12]
    norm = (exponent + 2.0) * 0.5 / np.pi
    glossy = False
    for c in range(n_channels):
        if ks[c] != 0.0:
            glossy = True
    inv_pi = 1.0 / np.pi
    # g_k's radial values equal within LEVEL_SPREAD of their largest and no azimuth, ks = 0: g_k is taken as the
    # middle of its values (off by at most half their spread) and f = kd / pi
    level = not glossy and not any_phi
    exact = exact and area
    level_g = np.empty(n_terms)
    for k in range(n_terms):
        low, high = values[k, 0], values[k, 0]
        for j in range(values.shape[1]):
            low, high = min(low, values[k, j]), max(high, values[k, j])
        level_g[k] = 0.5 * (low + high)
        if not high - low <= LEVEL_SPREAD * max(abs(low), abs(high)):
            level = False
    exact = exact and level
    row_start, col_start = np.empty(m), np.empty(m)  # the grid cell's corner of sample j
    for j in range(m):
        row, col = divmod(j, side)
        row_start[j], col_start[j] = row / rows, col / side
    w = _embree.PACKET
    counter = np.zeros(1, dtype=np.int64)
    for thread in numba.prange(threads):
        f32, u32, valid = slot_f32[thread], slot_u32[thread], slot_valid[thread]
        address = f32.ctypes.data
        for k in range(w):
            valid[k] = 0
        lane_sample = np.zeros(w, dtype=np.int64)
        state = np.zeros(step * m, dtype=np.int8)
        weights = np.zeros(step * m)
        dirs = np.zeros((step * m, 3))
        kept = np.zeros(step, dtype=np.bool_)
        dark = np.zeros(step, dtype=np.bool_)  # no sample of the vertex is live (_unlit)
        culling = np.zeros(step, dtype=np.bool_)
        near = np.zeros((step, spheres.shape[0] + planes.shape[0]), dtype=np.int64)  # blockers near a vertex's rays
        n_near = np.zeros((step, 2), dtype=np.int64)
        redo = np.zeros(step, dtype=np.bool_)  # probe and reuse: the previous call's other bits were agreed, not cast
        whole = np.zeros(step, dtype=np.bool_)  # every sample of the vertex is live (_wholly_above)
        known = np.zeros(step, dtype=np.int8)  # answered without a draw: _LIT (exact), _BLOCKED (zero sums), or 0
        while True:
            block = _embree.fetch_add(counter, 1)
            if block >= n_blocks:
                break
            lo, hi = block * step, min(n_points, (block + 1) * step)
            filled = 0
            for stage in range(2 if probing else 1):
                for p in range(lo, hi):
                    i = p - lo
                    x0, x1, x2 = x[p, 0], x[p, 1], x[p, 2]
                    if stage == 0:
                        cast[p] = 0
                        given = decided[p] if deciding else 0
                        given_before = decided_before[p] if was_deciding else 0
                        # as before: no segment of the vertex meets a moved sphere, or its answer is given as it was
                        kept[i] = keep and given == given_before and (
                            given != 0 or not _capsule_meets(x0, x1, x2, c0, c1, c2, reach, moved))
                        if kept[i]:
                            for j in range(m):
                                blocked[p, j] = visibility[p, j]
                            continue
                        known[i] = 0
                        dark[i] = (_no_normal(n[p, 0], n[p, 1], n[p, 2])
                                   or _unlit(x0, x1, x2, n[p, 0], n[p, 1], n[p, 2], params))
                        if dark[i]:  # no normal, or every sample below a horizon: not drawn
                            for j in range(m):
                                blocked[p, j] = False
                                state[i * m + j] = _DEAD
                            continue
                        whole[i] = area and _wholly_above(x0, x1, x2, n[p, 0], n[p, 1], n[p, 2], params)
                        culling[i] = cull and given == 0
                        for q in range(spheres.shape[0] if culling[i] else 0):
                            e0, e1, e2 = x0 - spheres[q, 0], x1 - spheres[q, 1], x2 - spheres[q, 2]
                            if e0 * e0 + e1 * e1 + e2 * e2 <= spheres[q, 3] * spheres[q, 3]:
                                culling[i] = False  # inside a blocker's sphere: every segment meets it
                                break
                        if culling[i]:
                            n_near[i, 0], n_near[i, 1] = _near_blockers(x0, x1, x2, params, reach, spheres, planes,
                                                                        near[i])
                        redo[i] = reuse and given_before != 0  # the previous bits were given, not cast
                        if whole[i] and given == 2:
                            known[i] = _BLOCKED
                        elif whole[i] and exact and (given == 1 or (culling[i] and n_near[i, 0] == 0
                                                                    and n_near[i, 1] == 0)):
                            known[i] = _LIT  # given clear, or no blocker near any segment
                        if known[i] != 0:
                            for j in range(m):
                                blocked[p, j] = known[i] == _BLOCKED
                                state[i * m + j] = _DEAD
                            continue
                    elif kept[i] or dark[i] or known[i] != 0:
                        continue
                    agreed = _PENDING  # the given answer, or with probe, second stage: the probes' common answer
                    if deciding and decided[p] != 0:
                        agreed = _LIT if decided[p] == 1 else _BLOCKED
                    elif stage == 1:
                        n_lit, n_blocked, old_lit, old_blocked = 0, 0, 0, 0
                        for j in range(m):
                            if probe[j] and state[i * m + j] != _DEAD:
                                if state[i * m + j] == _BLOCKED:
                                    n_blocked += 1
                                else:
                                    n_lit += 1
                                if reuse:
                                    if visibility[p, j]:
                                        old_blocked += 1
                                    else:
                                        old_lit += 1
                        if n_lit > 0 and n_blocked == 0:
                            agreed = _LIT
                        elif n_blocked > 0 and n_lit == 0:
                            agreed = _BLOCKED
                        # the previous call decided its other samples by agreement too: their bits were not cast
                        redo[i] = redo[i] or (reuse and ((old_lit > 0) != (old_blocked > 0)))
                        # the others' answer known: not drawn (all clear: the probes' live samples decide the sums)
                        if (agreed == _LIT and exact) or (agreed == _BLOCKED and whole[i]):
                            for j in range(m):
                                if not probe[j]:
                                    blocked[p, j] = agreed == _BLOCKED
                                    state[i * m + j] = _DEAD
                            continue
                    n0, n1, n2 = n[p, 0], n[p, 1], n[p, 2]
                    stream = _mix(np.uint64(key) ^ _mix(np.uint64(p + first)))
                    for j in range(m):
                        q = i * m + j
                        if probing and probe[j] != (stage == 0):
                            continue
                        blocked[p, j] = False
                        state[q] = _DEAD
                        if area:
                            s = (row_start[j] + _uniform(stream, np.uint64(2 * j)) * (1.0 / rows)) * 2.0 - 1.0
                            t = (col_start[j] + _uniform(stream, np.uint64(2 * j + 1)) * (1.0 / side)) * 2.0 - 1.0
                            y0, y1, y2 = c0 + s * u0 + t * v0, c1 + s * u1 + t * v1, c2 + s * u2 + t * v2
                        else:
                            y0, y1, y2 = c0, c1, c2
                        d0, d1, d2 = y0 - x0, y1 - x1, y2 - x2
                        dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                        safe = max(dist, 1e-300)
                        w0, w1, w2 = d0 / safe, d1 / safe, d2 / safe
                        cos_x = w0 * n0 + w1 * n1 + w2 * n2
                        cos_l = -(w0 * l0 + w1 * l1 + w2 * l2) if area else 1.0
                        if not (cos_x > 0.0 and cos_l > 0.0 and dist > 0.0):
                            continue
                        weights[q] = cos_x * cos_l / max(dist, 1e-300) ** 2 * scale
                        dirs[q, 0], dirs[q, 1], dirs[q, 2] = w0, w1, w2  # the sums' direction, traced or not
                        if agreed != _PENDING:
                            state[q] = agreed
                            blocked[p, j] = agreed == _BLOCKED
                            continue
                        if reuse and not redo[i] and not _segment_meets(x0, x1, x2, y0, y1, y2, moved):
                            state[q] = _BLOCKED if visibility[p, j] else _LIT
                            blocked[p, j] = visibility[p, j]
                            continue
                        if culling[i] and not _listed_meet(x0, x1, x2, y0, y1, y2, spheres, planes, near[i],
                                                           n_near[i, 0], n_near[i, 1]):
                            state[q] = _LIT  # no blocker's triangle is near the segment: the ray would miss
                            continue
                        # RayCaster.occluded(x, w, dist - eps, normals=n): its unit direction, _stage_ray's offset
                        # and tfar
                        length = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
                        e0, e1, e2 = w0 / length, w1 / length, w2 / length
                        cast[p] += 1
                        state[q] = _LIT
                        off = eps if n0 * e0 + n1 * e1 + n2 * e2 >= 0.0 else -eps
                        tfar = dist - eps - tnear
                        if tfar > _FLOAT32_MAX:
                            tfar = np.inf
                        if not np.float32(tfar) > 0.0:
                            continue
                        ox, oy, oz = x0 + off * n0 + tnear * e0, x1 + off * n1 + tnear * e1, x2 + off * n2 + tnear * e2
                        if packet:
                            state[q] = _PENDING
                            _embree.set_packet_ray(f32, u32, filled, ox, oy, oz, e0, e1, e2, tfar)
                            valid[filled] = -1
                            lane_sample[filled] = q
                            filled += 1
                            if filled == w:
                                _flush(tracer_fn, tracer_scene, valid, address, f32, lane_sample, filled, state,
                                       blocked, lo, m)
                                filled = 0
                        else:
                            _embree.set_ray(f32, u32, ox, oy, oz, e0, e1, e2, tfar)
                            _embree.rtc_call(tracer_fn, tracer_scene, address)
                            if f32[_embree.TFAR] < 0.0:
                                state[q] = _BLOCKED
                                blocked[p, j] = True
                if filled > 0:  # the probes' answers are needed before the second stage
                    _flush(tracer_fn, tracer_scene, valid, address, f32, lane_sample, filled, state, blocked, lo, m)
                    filled = 0
            for p in range(lo, hi):  # the sums, sample by sample in order
                i = p - lo
                if kept[i]:
                    for k in range(n_terms):
                        S[p, k] = previous_S[p, k]
                    for c in range(n_channels):
                        F[p, c] = previous_F[p, c]
                    continue
                for k in range(n_terms):
                    S[p, k] = 0.0
                for c in range(n_channels):
                    F[p, c] = 0.0
                if dark[i] or known[i] == _BLOCKED:
                    continue
                if level:  # g_k and f do not depend on the direction: the lit weights' sum times them
                    co = _cos_out(n, wo, p)
                    total, n_lit, n_blocked = 0.0, 0, 0
                    for j in range(m):
                        if state[i * m + j] == _LIT:
                            total += weights[i * m + j]
                            n_lit += 1
                        elif state[i * m + j] == _BLOCKED:
                            n_blocked += 1
                    if known[i] == _LIT or (exact and n_lit > 0 and n_blocked == 0):
                        total = _lit_integral(x[p, 0], x[p, 1], x[p, 2], n[p, 0], n[p, 1], n[p, 2], params)
                    for k in range(n_terms):
                        S[p, k] = total * level_g[k]
                    if co >= 0.0:  # else a lit sample is on wo's side of the horizon only by rounding
                        for c in range(n_channels):
                            F[p, c] = total * (kd[c] * inv_pi)
                    continue
                a0, a1, a2, t0, t1, t2, b0, b1, b2, o0, o1, o2, co = _vertex_frame(n, wo, p)
                for j in range(m):
                    q = i * m + j
                    if state[q] != _LIT:
                        continue
                    weight = weights[q]
                    e0, e1, e2 = dirs[q, 0], dirs[q, 1], dirs[q, 2]
                    # the local direction (brdf.to_local) and g_k (factor_eval_kernel)
                    lx, ly, lz = t0 * e0 + t1 * e1 + t2 * e2, b0 * e0 + b1 * e1 + b2 * e2, a0 * e0 + a1 * e1 + a2 * e2
                    theta = _polar_angle(np.sqrt(lx * lx + ly * ly), lz)
                    phi = np.arctan2(ly, lx) if any_phi else 0.0
                    interval, at = _interval(nodes, guide, per_radian, theta)
                    for k in range(n_terms):
                        S[p, k] += weight * _factor(values, k, interval, at, phi, freq, parity)
                    # the Phong BRDF (phong_eval_kernel)
                    ci = a0 * e0 + a1 * e1 + a2 * e2
                    if ci * co < 0.0:
                        continue
                    rdot = (2.0 * ci * a0 - e0) * o0 + (2.0 * ci * a1 - e1) * o1 + (2.0 * ci * a2 - e2) * o2
                    lobe = norm * rdot**exponent if rdot > 0.0 and glossy else 0.0  # ks = 0: f = kd / pi exactly
                    for c in range(n_channels):
                        F[p, c] += weight * (kd[c] * inv_pi + ks[c] * lobe)


def _kernel_ready(f, sep, caster) -> bool:
    """Whether :func:`light_terms` runs the kernel (a Phong/Lambert BRDF, a separable form, Embree)."""
    return (isinstance(f, brdf.Phong) and isinstance(sep, brdf.SeparableBRDF)
            and getattr(caster, "_scene", None) is not None)


def _terms_out(out, n: int, m: int, n_k: int, n_c: int) -> tuple:
    """``(S (n, n_k), F (n, n_c), blocked (n, m))`` of :func:`light_terms`: new arrays, or ``out`` once checked."""
    shapes, types = ((n, n_k), (n, n_c), (n, m)), (np.float64, np.float64, np.bool_)
    if out is None:
        return tuple(np.empty(shape, t) for shape, t in zip(shapes, types))
    if len(out) != 3 or any(a.shape != shape or a.dtype != t or not a.flags.c_contiguous
                            for a, shape, t in zip(out, shapes, types)):
        raise ValueError(f"out must be C-contiguous arrays of shapes {shapes} (float64, float64, bool), got "
                         f"{[(np.shape(a), getattr(a, 'dtype', None)) for a in out]}")
    return tuple(out)


def light_terms(points, normals, wo, f, sep, caster, light, index: int, samples: int, seed: int = 0,
                visibility=None, moved=None, stats: dict | None = None, blockers=None, first: int = 0,
                previous=None, probe: int = 0, decided=None, decided_before=None, exact_lit: bool = False,
                out=None):
    """``(S (V, K), F (V, C), blocked (V, m))`` of one area or point light at unit emission (written into
    ``out``, three C-contiguous arrays of those shapes, float64, float64 and bool, when given).

    ``S[v, k] = sum_j W_j g_k(w_j)`` and ``F[v, c] = sum_j W_j f_c(w_j, wo_v)`` over the samples ``j`` of the
    light seen from ``points`` (``W``: the estimator's weight ``A / m cos_x cos_l / d^2``, or ``cos_x / d^2``
    for a point light, 0 where the shadow ray is blocked); times the light's radiance (intensity) they are
    the light's ``L_k`` and radiance toward ``wo`` of :func:`ray_traced_direct`. ``wo`` is used as given
    (:func:`mirror_wo` first). ``index``: the light's number in its list (its random stream), ``m``:
    :func:`sample_count`. ``blocked`` says which samples were shadowed (False where a sample is below a
    horizon). With ``visibility`` (the ``blocked`` of an earlier call at the same points, light, samples and
    seed, casters with the same offsets), only the samples whose segment meets one of the spheres ``moved``
    (S, 4: centre, radius; the moved objects' bounding spheres before and after, widened for float32 and
    the origin offset) are cast again; without ``moved`` none are (a new ``wo`` or radiance).

    ``blockers``: ``(spheres (S, 4), planes (P, 5))`` holding every triangle a shadow ray can hit
    (:func:`blocker_bounds`): bounding spheres (centre, radius) and slabs of flat objects (unit normal, lowest
    and highest ``n . p``), widened for float32 and the origin offset; the receiver's own plane may be left
    out (a ray leaves it on its normal's side). A sample whose segment meets none of them is not traced: its
    ray would be unblocked, so the results are those of casting it (``stats`` counts only traced rays). On a
    receiver with ``ks = 0`` whose ``g_k`` are level within :data:`LEVEL_SPREAD` (a Lambertian BRDF's fitted form),
    ``g_k`` is the middle of its values: within half their spread (relative) of the reference tier.
    ``previous``: the ``(S, F)`` of the call that gave ``visibility`` (same ``wo``, BRDF and ``first``): a vertex
    none of whose segments can meet a ``moved`` sphere keeps its rows (the same sums, bit for bit). The
    reference tier casts every ray and recomputes every vertex. ``first``: the number of the first point in the
    random streams (point ``p`` draws the jitter of point ``first + p``), so a call on ``points[a:]`` with
    ``first=a`` gives the rows ``a:`` of a call on ``points``.

    ``probe``: an area light's samples are first cast at a sub-grid of about ``probe`` of them
    (:func:`probe_mask`); at a vertex whose live probes all agree (all blocked or all clear) the other samples take
    that answer without rays, elsewhere they are cast. 0 (or ``probe >= m``): every sample cast, the unbiased
    estimator; otherwise biased where a shadow's edge crosses the light between the probes (the penumbra
    early-out). The masks record the answers as given; ``visibility`` from a call with the same ``probe``.

    ``decided``: (V,) int, per point the answer of all its samples given without rays: 1 every sample clear, 2 every
    live sample blocked, 0 none (cast as above; the samples' weights, ``g_k`` and BRDF are computed either way).
    With ``visibility``, ``decided_before`` is that of the call that gave it (None: all 0): a point given an answer
    there and none now is cast wholly, so the results are those of a call without ``visibility``.

    ``exact_lit``: on an area light and a receiver whose ``g_k`` and BRDF do not depend on the direction (``ks = 0``,
    ``g_k`` level as above), a point with some live sample and none blocked takes the exact unshadowed integral
    (:func:`lit_integral`) for its lit weights' sum, ``g_k`` and the BRDF at its normal (the estimator's noise
    removed where the light is wholly seen); the masks are as without it. Where the answer is known before the
    draw and every point of the light is above the horizon, the kernel draws no samples.

    A point without a normal (``n . n == 0`` in float64: a zero normal, or components each below about 1.5e-162;
    the pipeline's near hits can interpolate one between opposite vertex normals) has no live sample: zero ``S``
    and ``F`` and an all-False mask in both tiers, whatever its ``wo``. At a point with a normal, a zero ``wo``
    (``wo . wo == 0``) is refused with the reference tier's ``ValueError``.
    """
    first, probe = _check_first(first), _check_probe(probe)
    if not _kernel_ready(f, sep, caster):
        terms = light_terms_reference(points, normals, wo, f, sep, caster, light, index, samples, seed,
                                      visibility, moved, stats, first=first, probe=probe, decided=decided,
                                      decided_before=decided_before, exact_lit=exact_lit)
        if out is None:
            return terms
        for target, value in zip(_terms_out(out, *terms[2].shape, *(t.shape[1] for t in terms[:2])), terms):
            target[...] = value
        return out
    if previous is not None and visibility is not None:
        previous_S, previous_F = (np.ascontiguousarray(a, np.float64) for a in previous)
        if previous_S.shape != (len(points), sep.K) or previous_F.shape != (len(points), f.channels):
            raise ValueError(f"previous must be the (S, F) of an earlier call on the same {len(points)} points, "
                             f"got shapes {previous_S.shape}, {previous_F.shape}")
    else:
        previous_S, previous_F = np.zeros((0, sep.K)), np.zeros((0, f.channels))
    spheres, planes = (np.zeros((0, 4)), np.zeros((0, 5))) if blockers is None else (
        np.ascontiguousarray(blockers[0], np.float64).reshape(-1, 4),
        np.ascontiguousarray(blockers[1], np.float64).reshape(-1, 5))
    x, n, wo = _check(points, normals, wo)
    if _first_without_wo(n, wo) >= 0:  # as the reference tier's BRDF refuses it
        raise ValueError("wo contains a zero vector; every direction must be a unit vector")
    params, rows, side, area = _light_geometry(light, samples)
    m = rows * side
    visibility, moved = _check_reuse(visibility, moved, len(x), m)
    decided, decided_before = _check_decided(decided, decided_before, len(x), visibility)
    S, F, blocked = _terms_out(out, len(x), m, sep.K, f.channels)
    cast = np.zeros(len(x), dtype=np.int64)
    if not len(x):
        return S, F, blocked
    nodes, values = sep._ext(sep.theta_in, sep.g_radial, 0.5 * np.pi)
    threads = numba.get_num_threads()
    slot_f32, slot_u32, slot_valid = _embree.packet_slots(threads)
    scene = caster._scene
    _terms_kernel(x, n, wo, params, area, rows, side, np.uint64(_key(seed, index)), first,
                  scene.occluded16_fn if PACKETS else scene.occluded_fn, scene.handle, PACKETS,
                  max(1, _SAMPLES_PER_TASK // m), slot_f32, slot_u32, slot_valid, threads, float(caster.epsilon),
                  float(caster.tnear), np.zeros((0, m), np.bool_) if visibility is None else visibility,
                  np.zeros((0, 4)) if moved is None else moved, previous_S, previous_F, _reach(params, area),
                  blockers is not None, spheres, planes, probe_mask(light, samples, probe),
                  np.zeros(0, np.int8) if decided is None else decided,
                  np.zeros(0, np.int8) if decided_before is None else decided_before, nodes, *_guide(nodes), values,
                  np.ascontiguousarray(sep.freq, np.int64), np.ascontiguousarray(sep.parity, np.int64),
                  np.ascontiguousarray(f.kd, float), np.ascontiguousarray(f.ks, float), float(f.exponent),
                  bool(exact_lit), S, F, blocked, cast)
    if stats is not None:
        stats["rays_cast"] = stats.get("rays_cast", 0) + int(cast.sum())
    return S, F, blocked


# ------------------------------------------------------------------------------------------- the direct light


def _direct(terms, points, normals, wo, f, sep, caster, lights, samples, seed, **extra):
    x = np.asarray(points, float)
    wo = mirror_wo(wo, normals)
    light_k, radiance = np.zeros((len(x), sep.K, 3)), np.zeros((len(x), 3))
    for i, light in enumerate(lights):
        if not isinstance(light, (AreaLight, PointLight)):
            continue
        S, F, _ = terms(x, normals, wo, f, sep, caster, light, i, samples, seed, **extra)
        e = _emission(light)
        light_k += S[:, :, None] * e
        radiance += F * e
    return light_k, radiance


def ray_traced_direct(points, normals, wo, f, sep, caster, lights, samples: int, seed: int = 0, blockers=None):
    """``(L_k (V, K, C), radiance toward wo (V, C))`` at world ``points`` with unit ``normals`` from the area
    and point lights of ``lights`` (others are left out), with shadow rays against ``caster`` (every object at
    its pose).

    ``wo`` (V, 3): unit directions toward the camera, mirrored above a vertex's horizon where they are below
    it (the BRDFs are two-sided: a Lambertian vertex seen from behind keeps its radiance, as the separable
    form's horizon value does); ``f``: the receiver's BRDF (:mod:`prtlab.brdf`) and ``sep`` its separable
    form. ``samples`` points per vertex on each area light (a ``rows x side <= samples`` grid jittered per
    vertex by a hash of ``(seed, light number, vertex, sample)``, so a frame is deterministic). The sum over
    the lights of :func:`light_terms` times their radiance (a point without a normal, ``n . n == 0``, gets none).
    """
    return _direct(light_terms, points, normals, wo, f, sep, caster, lights, samples, seed)


def ray_traced_direct_reference(points, normals, wo, f, sep, caster, lights, samples: int, seed: int = 0):
    """:func:`ray_traced_direct` by :func:`light_terms_reference` (float64 numpy; the same samples)."""
    return _direct(light_terms_reference, points, normals, wo, f, sep, caster, lights, samples, seed)
