"""Monte Carlo ground truth: per-vertex outgoing radiance with standard errors.

Small, obvious path tracers over Embree (:class:`prtlab.geometry.RayCaster`)
that every pipeline's tests compare against. They are *wavefront* style: the
rays of one bounce of every path of a chunk of vertices are cast in one
batched Embree call, and the BSDF math runs in numba kernels
(:mod:`prtlab.reference._kernels`).

Conventions
-----------
* **Shaded side.** A mesh vertex is shaded on the side its (world) vertex
  normal points to; light arriving from behind it contributes nothing. The
  outgoing direction ``wo = normalize(camera.position - x)`` enters only
  through Phong's view dependence, and is used as given even when the camera
  is behind the vertex.
* **Path vertices** (hits of sampled rays) reflect on both sides: the side
  facing the incoming ray. Their shading normal is the barycentric
  interpolation of the world vertex normals, flipped with the geometric
  normal to that side. Materials are Lambert ``albedo / pi`` or the
  normalised Phong of :class:`prtlab.scene.Material`.
* **Area lights** are parallelograms emitting ``radiance`` on the side of
  ``cross(u, v)`` only, reached only by next-event estimation (NEE). By
  default (``area_lights_block=True``) each is also an opaque black quad that
  ends any ray that hits it, as Mitsuba's ``rectangle`` emitter is, so the two
  references see the same scene (a shadow ray toward a light stops
  ``epsilon`` short of it, so a light never shadows itself). With
  ``area_lights_block=False`` lights are not geometry: they neither reflect
  nor block, and sampled rays never hit them.
* **Point lights**: exact shadow ray, irradiance ``I cos / r^2``.
* **Environment**: ``EnvironmentLight.radiance(dirs)`` for rays that escape
  the scene. For a constant environment the estimator uses BSDF sampling only;
  for an image it combines BSDF sampling with importance sampling of the map
  (piecewise constant over the map's bilinear cells, ``pdf ~ max corner
  luminance``) by multiple importance sampling with the power heuristic.
* **Portals** (``portal: true`` objects) are openings: they are neither
  shaded nor cast into the ray caster.
* **Vertices on another surface** (a floor vertex on a wall's plane at a room
  corner): their rays are not blocked by that surface at distance 0, in
  either direction (``RayCaster.tnear``); the radiance there is ill-defined
  (it jumps across the corner), so comparisons should use other vertices.
* **Vertices without a normal** (zero-length vertex normals, e.g. vertices no
  face uses) get zero radiance with a standard error of zero.
* **Bounces.** A path starts at the shaded vertex (depth 0). Light that
  reaches depth ``k`` straight from a light source (NEE or an escaping ray)
  has ``k`` indirect bounces. ``direct`` is ``k = 0``, ``indirect`` is
  ``1 <= k <= B`` for a bounce limit ``B``; rays leaving depth ``B`` only test
  for escape (any-hit). No Russian roulette: paths end at depth ``B``.
* **Standard errors.** Every vertex gets ``n_samples`` independent paths; the
  per-path values of direct, indirect and total (= direct + indirect of the
  same path) give the means and the standard errors
  ``std(ddof=1) / sqrt(n_samples)`` per colour channel. They are honest for
  independent samples; an estimator with zero variance (a diffuse plane under
  a constant sky, a point light) reports a standard error of 0. Where rare
  paths carry much of the integral (a small bright sun seen only by a few
  samples, small area lights behind occluders) the sample standard error of a
  *small* ``n_samples`` is itself noisy and tends to underestimate; use
  ``n_samples >= 64`` for comparisons (measured: ``mean z^2`` of 3.7 at 16, 1.6
  at 64 and 1.2 at 256 samples for irradiance under a one-pixel sun map, 1.0 at
  64 for a smooth sky).
* **Ray offsets**: origins move ``RayCaster.epsilon`` (``1e-4`` of the scene
  diagonal) along the normal on the side of the outgoing ray; shadow rays are
  then aimed from the moved origin at the light point and stop ``epsilon``
  before it (see :mod:`prtlab.geometry._raycast`).

References
----------
Veach, *Robust Monte Carlo Methods for Light Transport Simulation*, PhD thesis,
Stanford 1997, Sec. 9.2 (multiple importance sampling, power heuristic).
Pharr, Jakob, Humphreys, *Physically Based Rendering*, 3rd ed., Sec. 14.5 (path
tracing with next-event estimation).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from prtlab.geometry import RayCaster, direction_to_equirect, offset_origins
from prtlab.scene import Material, ShadeResult

from prtlab._validate import MemoryNeed, check_int, check_memory
from ._kernels import bsdf_eval_kernel, bsdf_sample_kernel, hit_frame_kernel

__all__ = [
    "shade_reference",
    "path_trace",
    "direct",
    "irradiance_at",
    "radiance_at",
    "Estimate",
    "PATHS_PER_CHUNK",
]

#: Paths traced together (one wavefront); vertices are chunked to about this many paths.
PATHS_PER_CHUNK = 1 << 17

#: Bytes per path of a wavefront: its state (position, normals, view, BSDF, throughput: about 25 doubles),
#: the two accumulators and the temporaries of next-event estimation and continuation.
BYTES_PER_PATH = 512


def _check_memory(n_points: int, n_samples: int) -> None:
    """Refuse ``n_samples`` whose wavefront (all samples of at least one point at once) does not fit."""
    paths = min(n_points, max(1, PATHS_PER_CHUNK // n_samples)) * n_samples
    needs = [MemoryNeed("the path wavefront", float(paths) * BYTES_PER_PATH, ("n_samples",)),
             MemoryNeed("the estimates", 18.0 * 8 * n_points, ())]
    check_memory("reference", {"n_samples": n_samples}, needs, f"{n_points:,} points")


class Estimate(NamedTuple):
    """Monte Carlo estimate at a set of points, each ``(..., 3)``."""

    total: np.ndarray
    stderr: np.ndarray
    direct: np.ndarray
    direct_stderr: np.ndarray
    indirect: np.ndarray
    indirect_stderr: np.ndarray


# ----------------------------------------------------------------- scene data


def _material_arrays(material: Material):
    if material.type == "phong":
        return (np.asarray(material.kd, float), np.asarray(material.ks, float), float(material.exponent))
    return np.asarray(material.albedo, float), np.zeros(3), 1.0


def _vertex_arrays(objects):
    """World shading points, normals and material ``(kd, ks, exponent)`` of every vertex of ``objects``."""
    if not objects:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    counts = [o.n_vertices for o in objects]
    mats = [_material_arrays(o.material) for o in objects]
    return (np.concatenate([o.world_shading_points() for o in objects]),
            np.concatenate([o.world_normals() for o in objects]),
            np.concatenate([np.tile(m[0], (c, 1)) for m, c in zip(mats, counts)]),
            np.concatenate([np.tile(m[1], (c, 1)) for m, c in zip(mats, counts)]),
            np.concatenate([np.full(c, m[2]) for m, c in zip(mats, counts)]))


class _SceneData:
    """World-space arrays of one pose of a scene: the ray caster, normals, materials, lights."""

    def __init__(self, scene, env_sampling: str = "mis", area_lights_block: bool = True):
        if env_sampling not in ("mis", "bsdf"):
            raise ValueError(
                f"env_sampling must be 'mis' (BSDF and map importance sampling) or 'bsdf', got {env_sampling!r}"
            )
        if not isinstance(area_lights_block, (bool, np.bool_)):
            raise TypeError(f"area_lights_block must be True or False, got {area_lights_block!r}")
        self.scene = scene
        objs = [o for o in scene.objects if not o.portal]
        meshes = [o.mesh for o in objs]
        transforms = [o.transform for o in objs]
        if area_lights_block:  # opaque black quads: they stop rays, reflect and transmit nothing
            for light in scene.area_lights:
                corners = light.center + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) @ np.stack([light.u, light.v])
                meshes.append((corners, np.array([[0, 1, 2], [0, 2, 3]])))
                transforms.append(None)
        self.caster = RayCaster(meshes, transforms)
        self.n_surfaces = len(objs)
        self.objects = objs
        self.vertex_normals = [np.asarray(o.world_normals(), float) for o in objs]
        for k in range(len(objs), self.caster.n_objects):  # light quads: flat
            self.vertex_normals.append(np.tile(self.caster.face_normals(k)[0], (4, 1)))
        # global face / vertex-normal tables in the caster's object order, for the hit kernel
        counts = [len(self.caster.world_vertices(k)) for k in range(self.caster.n_objects)]
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.faces = np.concatenate(
            [self.caster.faces(k) + offsets[k] for k in range(self.caster.n_objects)] + [np.zeros((0, 3), np.int64)]
        )
        self.face_offset = np.concatenate(
            [[0], np.cumsum([len(self.caster.faces(k)) for k in range(self.caster.n_objects)])]
        ).astype(np.int64)
        self.all_vertex_normals = np.concatenate(self.vertex_normals + [np.zeros((0, 3))])
        mats = [_material_arrays(o.material) for o in objs]
        mats += [(np.zeros(3), np.zeros(3), 1.0)] * (self.caster.n_objects - len(objs))  # black lights
        self.kd = np.array([m[0] for m in mats]).reshape(-1, 3)
        self.ks = np.array([m[1] for m in mats]).reshape(-1, 3)
        self.ex = np.array([m[2] for m in mats], dtype=float)
        self.area_lights = scene.area_lights
        self.point_lights = scene.point_lights
        self.env = scene.environment
        self.env_sampler = None
        if env_sampling == "mis" and self.env is not None and self.env.constant is None and self.env.image is not None:
            self.env_sampler = _EnvSampler(np.asarray(self.env.image, float))
        self.epsilon = self.caster.epsilon

    def env_radiance(self, dirs):
        if self.env is None or len(dirs) == 0:
            return np.zeros((len(dirs), 3))
        return np.asarray(self.env.radiance(dirs), float).reshape(-1, 3)


class _EnvSampler:
    """Importance sampling of an equirect map, piecewise constant in solid angle.

    Cells lie between the map's bilinear samples: row cell ``i`` spans
    ``theta`` in ``[pi i / (H-1), pi (i+1) / (H-1)]``, column cell ``j`` spans
    ``u`` in ``[(j + 1/2) / W, (j + 3/2) / W]`` (wrapping). A cell is chosen with
    probability ``P_ij ~ m_ij Omega_ij`` (``m`` the largest luminance of its four
    corner samples, ``Omega`` its solid angle), then a direction uniformly in
    solid angle inside it: ``pdf = P_ij / Omega_ij``, positive wherever the
    bilinear radiance is.
    """

    def __init__(self, image):
        h, w = image.shape[:2]
        self.h, self.w = h, w
        lum = image @ np.array([0.2126, 0.7152, 0.0722])
        lum = np.maximum(lum, 0.0)
        corners = np.maximum.reduce([lum[:-1], lum[1:], np.roll(lum[:-1], -1, axis=1), np.roll(lum[1:], -1, axis=1)])
        z = np.cos(np.pi * np.arange(h) / (h - 1))
        self.z_top, self.z_bottom = z[:-1], z[1:]
        omega = np.outer(self.z_top - self.z_bottom, np.full(w, 2.0 * np.pi / w))
        weight = corners * omega
        total = weight.sum()
        if not total > 0:
            self.cell_pdf = None
            return
        self.prob = (weight / total).reshape(-1)
        self.cdf = np.cumsum(self.prob)
        self.cdf[-1] = 1.0
        self.cell_pdf = (weight / total / omega).reshape(-1)

    def sample(self, uniforms):
        """(N, 3) uniforms -> directions (N, 3) and their pdf (N,)."""
        cell = np.minimum(np.searchsorted(self.cdf, uniforms[:, 0], side="right"), len(self.cdf) - 1)
        i, j = np.divmod(cell, self.w)
        y = self.z_top[i] + uniforms[:, 1] * (self.z_bottom[i] - self.z_top[i])
        u = (j + 0.5 + uniforms[:, 2]) / self.w
        s = np.sqrt(np.maximum(0.0, 1.0 - y * y))
        dirs = np.stack([s * np.sin(2 * np.pi * u), y, -s * np.cos(2 * np.pi * u)], axis=-1)
        return dirs, self.cell_pdf[cell]

    def pdf(self, dirs):
        """Density (per steradian) of :meth:`sample` at unit ``dirs`` (N, 3)."""
        if len(dirs) == 0:
            return np.zeros(0)
        u, v = direction_to_equirect(dirs)
        i = np.clip(np.floor(v * (self.h - 1)).astype(np.int64), 0, self.h - 2)
        j = np.mod(np.floor(u * self.w - 0.5).astype(np.int64), self.w)
        return self.cell_pdf[i * self.w + j]


# ------------------------------------------------------------------ the tracer


@dataclass
class _Paths:
    pos: np.ndarray
    ns: np.ndarray  # shading normal, on the reflecting side
    ng: np.ndarray  # normal used for the ray offset
    wo: np.ndarray
    kd: np.ndarray
    ks: np.ndarray
    ex: np.ndarray
    beta: np.ndarray
    index: np.ndarray  # path id into the accumulators

    def take(self, sel):
        return _Paths(*(getattr(self, f)[sel] for f in self.__dataclass_fields__))


def _eval_bsdf(p: _Paths, wi):
    fcos = np.empty((len(wi), 3))
    pdf = np.empty(len(wi))
    if len(wi):
        bsdf_eval_kernel(p.ns, p.wo, wi, p.kd, p.ks, p.ex, fcos, pdf)
    return fcos, pdf


def _power(a, b):
    a2, b2 = a * a, b * b
    s = a2 + b2
    return np.divide(a2, s, out=np.zeros_like(s), where=s > 0)


def _unit(v):
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(length > 0, length, 1.0)


def _shadowed(data: _SceneData, pos, ng, wi, target):
    """Shadow rays from the offset origins straight to the light points, stopping epsilon short.

    The origin moves ``epsilon`` off the surface on the side of ``wi``; the ray is then
    re-aimed at ``target`` from there (a parallel ray would reach a light lying on a
    surface up to ``epsilon / sin(elevation)`` early).
    """
    eps = data.epsilon
    origins = offset_origins(pos, ng, wi, eps)
    d = target - origins
    dist = np.linalg.norm(d, axis=1)
    return data.caster.occluded(origins, d / np.where(dist > 0, dist, 1.0)[:, None], dist - eps)


def _next_event(data: _SceneData, p: _Paths, acc, rng):
    """Area, point and (importance-sampled) environment light at every path vertex."""
    n = len(p.pos)
    for light in data.area_lights:
        st = 2.0 * rng.random((n, 2)) - 1.0
        y = light.center + st[:, :1] * light.u + st[:, 1:] * light.v
        d = y - p.pos
        dist = np.linalg.norm(d, axis=1)
        wi = d / np.where(dist > 0, dist, 1.0)[:, None]
        cos_l = -(wi @ light.normal)
        fcos, _ = _eval_bsdf(p, wi)
        g = np.where((cos_l > 0) & (dist > 0), cos_l * light.area / np.where(dist > 0, dist, 1.0) ** 2, 0.0)
        contrib = p.beta * fcos * np.asarray(light.radiance, float) * g[:, None]
        live = np.flatnonzero(np.any(contrib > 0, axis=1))
        if len(live):
            live = live[~_shadowed(data, p.pos[live], p.ng[live], wi[live], y[live])]
            acc[p.index[live]] += contrib[live]  # path ids are unique here
    for light in data.point_lights:
        d = np.asarray(light.position, float) - p.pos
        dist = np.linalg.norm(d, axis=1)
        wi = d / np.where(dist > 0, dist, 1.0)[:, None]
        fcos, _ = _eval_bsdf(p, wi)
        inv_r2 = np.where(dist > 0, 1.0 / np.where(dist > 0, dist, 1.0) ** 2, 0.0)
        contrib = p.beta * fcos * np.asarray(light.intensity, float) * inv_r2[:, None]
        live = np.flatnonzero(np.any(contrib > 0, axis=1))
        if len(live):
            target = np.broadcast_to(np.asarray(light.position, float), (len(live), 3))
            live = live[~_shadowed(data, p.pos[live], p.ng[live], wi[live], target)]
            acc[p.index[live]] += contrib[live]  # path ids are unique here
    if data.env_sampler is not None and data.env_sampler.cell_pdf is not None:
        wi, pdf_env = data.env_sampler.sample(rng.random((n, 3)))
        fcos, pdf_bsdf = _eval_bsdf(p, wi)
        live = np.flatnonzero(np.any(fcos > 0, axis=1) & (pdf_env > 0))
        if len(live):
            occ = data.caster.occluded(p.pos[live], wi[live], np.inf, normals=p.ng[live])
            live = live[~occ]
            weight = _power(pdf_env[live], pdf_bsdf[live]) / pdf_env[live]
            contrib = p.beta[live] * fcos[live] * data.env_radiance(wi[live]) * weight[:, None]
            acc[p.index[live]] += contrib


def _continue(data: _SceneData, p: _Paths, acc, rng, last: bool):
    """Sample the BSDF; escaping rays gather the environment; hits become the next vertices."""
    n = len(p.pos)
    wi = np.empty((n, 3))
    weight = np.empty((n, 3))
    pdf = np.empty(n)
    if n:
        bsdf_sample_kernel(p.ns, p.wo, p.kd, p.ks, p.ex, rng.random((n, 3)), wi, weight, pdf)
    keep = (pdf > 0) & np.any(weight > 0, axis=1)
    if not keep.all():
        live = np.flatnonzero(keep)
        p, wi, weight, pdf = p.take(live), wi[live], weight[live], pdf[live]
    if last:
        escaped = ~data.caster.occluded(p.pos, wi, np.inf, normals=p.ng)
        hits = None
    else:
        hits = data.caster.closest_hit(p.pos, wi, normals=p.ng)
        escaped = ~hits.hit
    if data.env is not None and np.any(escaped):
        w = weight[escaped]
        if data.env_sampler is not None and data.env_sampler.cell_pdf is not None:
            w = w * _power(pdf[escaped], data.env_sampler.pdf(wi[escaped]))[:, None]
        contrib = p.beta[escaped] * w * data.env_radiance(wi[escaped])
        acc[p.index[escaped]] += contrib
    if last:
        return None
    sel = np.flatnonzero(hits.hit & (hits.object < data.n_surfaces))  # a light quad ends the path
    obj = hits.object[sel]
    m = len(sel)
    ns, ng, wo = np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3))
    if m:
        hit_frame_kernel(obj, hits.triangle[sel], hits.barycentric[sel], hits.normal[sel], wi[sel],
                         data.face_offset, data.faces, data.all_vertex_normals, ns, ng, wo)
    return _Paths(
        pos=hits.point[sel],
        ns=ns,
        ng=ng,
        wo=wo,
        kd=data.kd[obj],
        ks=data.ks[obj],
        ex=data.ex[obj],
        beta=p.beta[sel] * weight[sel],
        index=p.index[sel],
    )


def _trace_chunk(data, pos, normals, wo, kd, ks, ex, bounces, n_samples, rng):
    """Per-path direct and indirect values: two (V * S, 3) arrays."""
    v = len(pos)
    rep = lambda a: np.repeat(a, n_samples, axis=0)  # noqa: E731
    n = v * n_samples
    direct_acc = np.zeros((n, 3))
    indirect_acc = np.zeros((n, 3))
    p = _Paths(
        pos=rep(pos), ns=rep(normals), ng=rep(normals), wo=rep(wo), kd=rep(kd), ks=rep(ks), ex=rep(ex),
        beta=np.ones((n, 3)), index=np.arange(n),
    )
    has_normal = np.linalg.norm(p.ns, axis=1) > 0
    if not has_normal.all():
        p = p.take(np.flatnonzero(has_normal))
    for depth in range(bounces + 1):
        acc = direct_acc if depth == 0 else indirect_acc
        _next_event(data, p, acc, rng)
        p = _continue(data, p, acc, rng, last=depth == bounces)
        if p is None or len(p.pos) == 0:
            break
    return direct_acc, indirect_acc


def _stats(values, v, s):
    x = values.reshape(v, s, 3)
    mean = x.mean(axis=1)
    err = x.std(axis=1, ddof=1) / np.sqrt(s)
    return mean, err


def _estimate(data, pos, normals, wo, kd, ks, ex, bounces, n_samples, rng, progress=False, desc="reference"):
    """Means and standard errors of direct, indirect, total at every point; each (V, 3)."""
    v = len(pos)
    out = {k: np.zeros((v, 3)) for k in ("direct", "indirect", "total", "direct_se", "indirect_se", "total_se")}
    chunk = max(1, PATHS_PER_CHUNK // n_samples)
    starts = range(0, v, chunk)
    if progress:
        from tqdm.auto import tqdm

        starts = tqdm(starts, desc=desc, unit="chunk", total=len(starts))
    for s in starts:
        e = min(v, s + chunk)
        d, ind = _trace_chunk(data, pos[s:e], normals[s:e], wo[s:e], kd[s:e], ks[s:e], ex[s:e], bounces, n_samples, rng)
        for name, vals in (("direct", d), ("indirect", ind), ("total", d + ind)):
            out[name][s:e], out[name + "_se"][s:e] = _stats(vals, e - s, n_samples)
    return out


# ------------------------------------------------------------------ validation


def _check_scene(scene):
    if not (hasattr(scene, "objects") and hasattr(scene, "lights")):
        raise TypeError(f"scene must be a prtlab.Scene, got {type(scene).__name__}")


def _check_rng(rng):
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator (e.g. numpy.random.default_rng(seed)), got {type(rng).__name__}"
        )
    return rng


def _check_points(x, name, shape=None):
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 0 or x.shape[-1] != 3:
        raise ValueError(f"{name} must be a (..., 3) array, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} contains NaN or inf; pass finite values")
    if shape is not None:
        try:
            x = np.broadcast_to(x, shape)
        except ValueError:
            raise ValueError(f"{name} of shape {x.shape} does not broadcast to the points' shape {shape}") from None
    return x


# ------------------------------------------------------------------ public API


def path_trace(
    scene,
    bounces: int,
    n_samples: int,
    rng: np.random.Generator,
    *,
    env_sampling: str = "mis",
    area_lights_block: bool = True,
    progress: bool = False,
) -> ShadeResult:
    """Per-vertex outgoing radiance toward the camera with up to ``bounces`` indirect bounces.

    Parameters
    ----------
    scene : prtlab.Scene
    bounces : int >= 0
        0: direct light only; 1: exactly one indirect bounce; ``B``: up to ``B``.
    n_samples : int >= 2
        Independent paths per vertex.
    rng : numpy.random.Generator
    env_sampling : {"mis", "bsdf"}
        How an environment *image* is sampled: BSDF sampling combined with
        importance sampling of the map by MIS (default), or BSDF sampling only.
        A constant environment always uses BSDF sampling.
    area_lights_block : bool
        True (default): each area light is also an opaque, black quad that
        stops rays, as Mitsuba's ``rectangle`` emitter does. False: area lights
        are not geometry (they neither block nor reflect).
    progress : bool
        Show a tqdm bar over vertex chunks.

    Returns
    -------
    ShadeResult
        ``direct``, ``indirect`` (light with ``1..B`` indirect bounces),
        ``total`` per object, each ``(n_vertices, 3)``, and ``stderr[part][name]``
        their standard errors from the per-path values.

    Notes
    -----
    Conventions (shaded side, two-sided path vertices, one-sided area lights,
    NEE + MIS, bounce counting) are in the module docstring. The outgoing
    radiance of a vertex ``x`` with normal ``n`` is

    .. math::

        L_o(x, \\omega_o) = \\int_{n \\cdot \\omega_i > 0} f(\\omega_i, \\omega_o)
            L_i(x, \\omega_i) \\cos\\theta_i \\, d\\omega_i,
        \\qquad \\omega_o = \\frac{c - x}{|c - x|}

    with ``c`` the camera position.
    """
    _check_scene(scene)
    bounces = check_int(bounces, "bounces", 0)
    n_samples = check_int(n_samples, "n_samples", 2)
    rng = _check_rng(rng)
    t0 = time.perf_counter()
    shaded = [o for o in scene.objects if not o.portal]
    counts = [o.n_vertices for o in shaded]
    _check_memory(sum(counts), n_samples)
    data = _SceneData(scene, env_sampling, area_lights_block)
    pos, normals, kd, ks, ex = _vertex_arrays(shaded)
    wo = _unit(np.asarray(scene.camera.position, float) - pos)
    out = _estimate(
        data, pos, normals, wo, kd, ks, ex, bounces, n_samples, rng, progress, desc=f"reference B={bounces}"
    )
    parts = ("direct", "indirect", "total")
    result = ShadeResult.from_vertex_arrays([o.name for o in shaded], counts, {p: out[p] for p in parts},
                                            {p: out[p + "_se"] for p in parts})
    result.info = {
        "method": "reference",
        "bounces": bounces,
        "n_samples": n_samples,
        "seconds": time.perf_counter() - t0,
        "ray_epsilon": data.epsilon,
        "env_importance_sampling": data.env_sampler is not None,
        "area_lights_block": bool(area_lights_block),
    }
    return result


def direct(scene, n_samples: int, rng: np.random.Generator, **options) -> ShadeResult:
    """Direct light only: :func:`path_trace` with ``bounces=0`` (``indirect`` is zero).

    Environment by BSDF (cosine / Phong) sampling, plus map importance
    sampling with MIS for an image environment; area lights by uniform area
    sampling of the parallelogram, one-sided; point lights by an exact shadow ray.
    Diffuse vertices give ``albedo / pi * E``; Phong vertices the normalised
    Phong BRDF toward the camera. ``options`` (``env_sampling``,
    ``area_lights_block``, ``progress``) are those of :func:`path_trace`.
    """
    return path_trace(scene, 0, n_samples, rng, **options)


def shade_reference(
    scene,
    bounces: int = 1,
    n_samples: int = 256,
    seed: int = 0,
    progress: bool = True,
    *,
    env_sampling: str = "mis",
    area_lights_block: bool = True,
) -> ShadeResult:
    """Entry point of ``prtlab.shade(scene, method="reference", ...)``: :func:`path_trace` seeded by ``seed``.

    ``seed`` (int) seeds ``numpy.random.default_rng``: the same seed gives the same
    result. The other parameters and the returned :class:`ShadeResult` (per object
    ``(n_vertices, 3)`` direct, indirect, total and their ``stderr``) are those of
    :func:`path_trace`; ``progress`` shows a tqdm bar over vertex chunks.
    """
    check_int(seed, "seed")
    return path_trace(
        scene, bounces, n_samples, np.random.default_rng(seed), env_sampling=env_sampling,
        area_lights_block=area_lights_block, progress=progress,
    )


def radiance_at(
    scene,
    points,
    normals,
    view_dirs,
    n_samples: int,
    rng: np.random.Generator,
    *,
    material: Material | None = None,
    bounces: int = 0,
    env_sampling: str = "mis",
    area_lights_block: bool = True,
) -> Estimate:
    """Outgoing radiance toward ``view_dirs`` at any points, with shadows and up to ``bounces`` bounces.

    Parameters
    ----------
    scene : prtlab.Scene
        Occluders, reflectors and lights (in their current transforms).
    points, normals, view_dirs : (..., 3) float
        Points, the unit normal of the side shaded, and the outgoing directions
        (toward the viewer; used by Phong only). ``normals`` and ``view_dirs``
        broadcast to ``points``.
    n_samples : int >= 2
    rng : numpy.random.Generator
    material : Material, optional
        The surface at the points; default white Lambert (albedo 1).
    bounces : int >= 0
    env_sampling : {"mis", "bsdf"}
        As in :func:`path_trace`.
    area_lights_block : bool
        As in :func:`path_trace`.

    Returns
    -------
    Estimate
        ``(..., 3)`` arrays: ``total``, ``stderr``, ``direct``, ``direct_stderr``,
        ``indirect``, ``indirect_stderr``.
    """
    _check_scene(scene)
    points = _check_points(points, "points")
    normals = _check_points(normals, "normals", points.shape)
    view_dirs = _check_points(view_dirs, "view_dirs", points.shape)
    bounces = check_int(bounces, "bounces", 0)
    n_samples = check_int(n_samples, "n_samples", 2)
    rng = _check_rng(rng)
    if material is None:
        material = Material(type="diffuse", albedo=np.ones(3))
    kd, ks, ex = _material_arrays(material)
    batch = points.shape[:-1]
    pos = points.reshape(-1, 3)
    v = len(pos)
    _check_memory(v, n_samples)
    data = _SceneData(scene, env_sampling, area_lights_block)
    out = _estimate(
        data, pos, _unit(normals.reshape(-1, 3)), _unit(view_dirs.reshape(-1, 3)),
        np.tile(kd, (v, 1)), np.tile(ks, (v, 1)), np.full(v, ex), bounces, n_samples, rng,
    )
    shape = batch + (3,)
    keys = ("total", "total_se", "direct", "direct_se", "indirect", "indirect_se")
    return Estimate(*(out[k].reshape(shape) for k in keys))


def irradiance_at(scene, points, normals, n_samples: int, rng: np.random.Generator, *, bounces: int = 0,
                  env_sampling: str = "mis", area_lights_block: bool = True) -> Estimate:
    """Irradiance ``E = int L_i cos`` at any points on the side of ``normals``, with shadows.

    The parameters are those of :func:`radiance_at` (a white Lambertian surface, no
    ``view_dirs``); ``bounces=B`` adds light reflected by the scene up to ``B`` times.

    Returns
    -------
    Estimate
        ``(..., 3)`` irradiance: ``pi`` times the radiance a white Lambertian
        surface at the points would reflect.
    """
    normals_arr = np.asarray(normals, dtype=np.float64)
    est = radiance_at(scene, points, normals_arr, normals_arr, n_samples, rng, bounces=bounces,
                      env_sampling=env_sampling, area_lights_block=area_lights_block)
    return Estimate(*(np.pi * x for x in est))
