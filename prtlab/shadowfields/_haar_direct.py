"""All-frequency direct light per vertex: lights as cubemap pieces, visibility products, BRDF terms.

For a receiver vertex ``x`` with normal ``n`` and a separable BRDF
``f ~ sum_k colour_k g_k(wi) h_k(wo)`` the direct light of term ``k`` is
(Iwasaki et al. 2007 Eq. 7-8, Zhou et al. 2005 Sec. 5)::

    L_k(x) = int_S2 L(x, w) V(x, w) g_k(w) max(0, n . w) dw,     B(x, wo) = sum_k h_k(wo) colour_k L_k(x)

with ``V = V_self * prod_o V_o`` the product of the vertex's self-visibility and
the other objects' occlusion fields (:mod:`._haar`), all as cubemaps of
``r x r`` texels per face. Visibility is the pulse (texel) function of the
cubemaps; the light and the BRDF-cosine are integrated over the texels as
exactly as they allow:

* **area lights** (parallelograms): the light's quad, seen from ``x`` and
  clipped to the upper hemisphere of ``n``, is clipped against the pyramid of
  every texel it meets; each piece's solid angle ``omega_p`` and moment
  ``m_p = int_piece w dw`` are exact (spherical polygon, Lambert's edge
  formula), and ``int_piece g_k cos = g_k(m_p / |m_p|) (n . m_p)`` — exact for a
  Lambertian term (``g`` constant), a midpoint rule in ``g_k`` for glossy terms;
* **point lights**: an exact delta, ``I / r^2 g_k(d) max(0, n . d)`` times the
  visibility in the light's direction ``d``, read bilinearly between the 4 texel
  centres around ``d`` on its face (the texels are samples at their centres, so
  this places a hard shadow edge to a fraction of a texel instead of snapping it
  to texel borders: measured on a ball's shadow, relative RMS error 0.38 with
  the nearest texel);
* **environment maps**: the texel-average cubemap of the map
  (:func:`prtlab.scene.equirect_to_cubemap`), ``g_k cos`` at the texel centres
  times the texel solid angle.

So ``L_k = sum_pieces radiance_p V(texel_p) G_pk``: the visibility product is
only needed at the texels the lights cover (for an area light a few dozen, for a
point light one), evaluated straight from the Haar coefficients
(``1 + 3 log2 r`` coefficients per texel); an environment needs every texel,
then each factor is synthesised whole (one inverse Haar transform).

Visibility product: texel by texel, exact in the pulse basis, with no
truncation after each factor (so the order of the occluders does not matter,
unlike the truncated SH products of :func:`visibility_pass`). A product in the
Haar domain (:func:`prtlab.wavelet.product`) would be equally exact before
re-truncation but costs ``O(6 r^2)`` per factor and vertex however small the
light, against ``O(texels lit * log r)`` here (measured: 266 us per pair of
32-cubemaps for :func:`prtlab.wavelet.product`, against about 25 us per factor
and vertex for the blend, scatter and point evaluation here under the Fig. 9 light).

Error bound (the cubemap resolution): the pieces are exact, so the only
discretisation is ``V`` being constant per texel. At a texel where the true
visibility is not constant (a shadow edge crosses it) the error is at most that
texel's whole contribution, so ``|L_k - L_k,true| <= sum_{edge texels p}
radiance_p |G_pk|`` (:func:`edge_bound`, with edge texels those whose
visibility differs from one of their 4 neighbours on the face, or is
fractional), plus the Haar truncation, bounded by Cauchy-Schwarz with the
stored ``energy_lost`` (exact storage gives 0).

Cost (``benchmarks/bench_shadowfields.py``, one thread of a shared machine): about 130-150 us per
vertex under the Fig. 9 light with 1-3 occluders (the SH path: 30), 60 % in the exact clipping of
the light's pieces and 35 % in the visibility products; 0.5 ms per vertex under an environment
(every texel lit: one synthesis per factor and vertex).

Measured figures: ``docs/notes/shadowfields.md``.

References
----------
K. Zhou et al., "Precomputed shadow fields for dynamic scenes", SIGGRAPH 2005, Sec. 5.
R. Ng, R. Ramamoorthi, P. Hanrahan, SIGGRAPH 2003 (Haar cubemaps) and 2004 (triple products).
K. Iwasaki et al., EGSR 2007, Eq. (7)-(8).
"""

from __future__ import annotations

import functools

import numba
import numpy as np

from prtlab._validate import as_points, check_choice
from prtlab.geometry import direction_to_cubemap
from prtlab.scene import AreaLight, EnvironmentLight, PointLight

from . import _haar_kernels as hk
from ._haar import (
    HaarOcclusionField,
    SparseCubemaps,
    _check_resolution,
    cubemap_frames,
    rotation_texel_map,
)

__all__ = [
    "edge_bound",
    "environment_cubemap",
    "haar_direct",
    "haar_direct_pass",
    "haar_visibility_pass",
    "light_pieces",
    "texel_moments",
]

_METHODS = ("numba", "reference")
#: Pieces (vertex x texel) handled per chunk of vertices.
_PIECES_PER_CHUNK = 1 << 21


def environment_cubemap(light: EnvironmentLight, resolution: int) -> np.ndarray:
    """(6, r, r, 3) texel-average radiance of an environment light (:func:`prtlab.scene.equirect_to_cubemap`)."""
    res = _check_resolution(resolution)
    if light.constant is not None:
        return np.broadcast_to(np.asarray(light.constant, float), (6, res, res, 3)).copy()
    from prtlab.scene import equirect_to_cubemap

    return equirect_to_cubemap(light.image, res)


@functools.lru_cache(maxsize=4)
def _texel_moments(res: int) -> np.ndarray:
    edges = 2.0 * np.arange(res + 1) / res - 1.0
    frames = cubemap_frames()
    out = np.empty((6, res, res, 3))
    for f in range(6):
        A, S, T = frames[f]
        corner = A + edges[None, :, None] * S + edges[:, None, None] * T  # [i, j] at (tc_i, sc_j)
        quad = [corner[:-1, :-1], corner[:-1, 1:], corner[1:, 1:], corner[1:, :-1]]
        m = np.zeros((res, res, 3))
        for k in range(4):
            x0, x1 = quad[k], quad[(k + 1) % 4]
            c = np.cross(x0, x1)
            lc = np.linalg.norm(c, axis=-1, keepdims=True)
            theta = np.arctan2(lc, np.sum(x0 * x1, axis=-1, keepdims=True))
            m += 0.5 * theta * c / lc
        out[f] = m * np.sign(np.sum(m * A, axis=-1, keepdims=True))
    out = out.reshape(-1, 3)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=4)
def _texel_omega(res: int) -> np.ndarray:
    from prtlab.geometry import cubemap_solid_angles

    out = np.ascontiguousarray(cubemap_solid_angles(res).reshape(-1))
    out.setflags(write=False)
    return out


def texel_moments(resolution: int) -> np.ndarray:
    """(6 r^2, 3) exact moments ``int_texel w dw`` of the cubemap texels (Lambert's edge formula).

    ``|m_t|`` is at most the texel's solid angle, and ``n . m_t`` its exact cosine integral
    when the texel lies above the horizon of ``n``.
    """
    return _texel_moments(_check_resolution(resolution))


def _lambert_g(sep):
    """The constant ``g`` of a one-term Lambertian ``sep`` (constant to rounding), else None."""
    if sep.K == 1 and int(sep.freq[0]) == 0 and np.ptp(sep.g_radial) <= 1e-12 * np.abs(sep.g_radial).max():
        return float(np.mean(sep.g_radial))
    return None


def _g_cos(sep, dirs, normals, lengths=None) -> np.ndarray:
    """``g_k(local(d)) max(0, n . d)`` (times ``lengths``: |m| for moments) for dirs (V, P, 3) -> (V, P, K)."""
    from prtlab.brdf import local_frame

    norm = np.linalg.norm(dirs, axis=-1, keepdims=True)
    unit = np.where(norm > 0, dirs / np.where(norm > 0, norm, 1.0), np.array([0.0, 0.0, 1.0]))
    cos = np.maximum(np.einsum("vpi,vi->vp", unit, normals), 0.0)
    if lengths is not None:
        cos = cos * lengths
    g0 = _lambert_g(sep)
    if g0 is not None:
        return (cos * g0)[..., None]
    R = local_frame(normals)  # world = R local
    local = np.einsum("vji,vpj->vpi", R, unit)
    return sep.g(local) * cos[..., None]


def _bilinear_texels(dirs, res: int):
    """The 4 texels around each direction on its face and their bilinear weights (clamped at face borders,
    as the sample-sphere lookups): (V, 4) int64, (V, 4) float64."""
    face, s, t = direction_to_cubemap(dirs)
    x = np.clip(s * res - 0.5, 0.0, res - 1.0)
    y = np.clip(t * res - 0.5, 0.0, res - 1.0)
    j0 = np.minimum(np.floor(x).astype(np.int64), res - 1)
    i0 = np.minimum(np.floor(y).astype(np.int64), res - 1)
    fj, fi = x - j0, y - i0
    j1, i1 = np.minimum(j0 + 1, res - 1), np.minimum(i0 + 1, res - 1)
    base = face * res * res
    texel = np.stack([base + i0 * res + j0, base + i0 * res + j1, base + i1 * res + j0, base + i1 * res + j1], 1)
    weight = np.stack([(1 - fi) * (1 - fj), (1 - fi) * fj, fi * (1 - fj), fi * fj], axis=1)
    return texel, weight


def light_pieces(lights, points, normals, sep, resolution: int):
    """The lights at each vertex as weighted cubemap texels: ``L_k = sum_p V(texel_p) G_pk radiance_p``.

    Parameters
    ----------
    lights : sequence of EnvironmentLight, AreaLight, PointLight
    points, normals : (V, 3) float
        World positions and unit normals of the receivers.
    sep : prtlab.brdf.SeparableBRDF
        The receiver's separable BRDF (``"plain"``).
    resolution : int
        Cubemap texels per face edge.

    Returns
    -------
    texel : (V, T) int64
        World texels ``f r^2 + i r + j``.
    g_weight : (V, T, K) float64
        ``int_piece g_k(w) max(0, n . w) dw`` (point lights: ``g_k(d) max(0, n . d) / r^2`` times the
        bilinear weight of each of the 4 texels around ``d``).
    radiance : (V, T, C) float64
        The piece's radiance (point lights: the intensity).
    count : (V,) int64
        Used pieces per vertex (the rest have zero weight).
    """
    res = _check_resolution(resolution)
    points = as_points(points, "points", flat=True)
    normals = as_points(normals, "normals", flat=True)
    nv = len(points)
    n = 6 * res * res
    frames = cubemap_frames()
    texels, gws, rads = [], [], []
    for light in lights:
        if isinstance(light, PointLight):
            d = np.asarray(light.position, float) - points
            r2 = np.einsum("vi,vi->v", d, d)
            safe = np.where(r2 > 0, r2, 1.0)
            dd = np.where(r2[:, None] > 0, d, normals)
            texel, weight = _bilinear_texels(dd, res)  # (V, 4)
            delta = _g_cos(sep, dd[:, None, :], normals) * np.where(r2 > 0, 1.0 / safe, 0.0)[:, None, None]
            texels.append(texel)
            gws.append(weight[:, :, None] * delta)
            rads.append(np.broadcast_to(np.asarray(light.intensity, float), (nv, 4, 3)))
        elif isinstance(light, AreaLight):
            c, u, v = (np.asarray(a, float) for a in (light.center, light.u, light.v))
            corners = np.ascontiguousarray([c - u - v, c + u - v, c + u + v, c - u + v])
            ln = np.asarray(light.normal, float)
            count = np.zeros(nv, dtype=np.int64)
            if nv:
                hk.area_light_count_kernel(points, normals, corners, ln, frames, res, count)
            tmax = max(int(count.max()) if nv else 0, 1)
            texel = np.zeros((nv, tmax), dtype=np.int64)
            omega = np.zeros((nv, tmax))
            moment = np.zeros((nv, tmax, 3))
            if nv:
                hk.area_light_pieces_kernel(points, normals, corners, ln, frames, res, _texel_omega(res),
                                            texel_moments(res), texel, omega, moment, count)
            length = np.linalg.norm(moment, axis=-1)
            texels.append(texel)
            gws.append(_g_cos(sep, moment, normals, length))
            rads.append(np.broadcast_to(np.asarray(light.radiance, float), (nv, tmax, 3)))
        elif isinstance(light, EnvironmentLight):
            cube = environment_cubemap(light, res).reshape(n, 3)
            moment = texel_moments(res)
            texels.append(np.broadcast_to(np.arange(n), (nv, n)))
            gws.append(_g_cos(sep, np.broadcast_to(moment, (nv, n, 3)), normals,
                              np.linalg.norm(moment, axis=1)[None, :]))
            rads.append(np.broadcast_to(cube, (nv, n, 3)))
        else:
            raise TypeError(f"lights must be EnvironmentLight, AreaLight or PointLight, got {type(light).__name__}")
    if not texels:
        return (np.zeros((nv, 0), np.int64), np.zeros((nv, 0, sep.K)), np.zeros((nv, 0, 3)), np.zeros(nv, np.int64))
    texel = np.ascontiguousarray(np.concatenate(texels, axis=1), dtype=np.int64)
    gw = np.ascontiguousarray(np.concatenate(gws, axis=1))
    rad = np.ascontiguousarray(np.concatenate(rads, axis=1))
    return texel, gw, rad, np.full(nv, texel.shape[1], dtype=np.int64)


def haar_visibility_pass(query, factors, resolution: int, method: str = "numba") -> np.ndarray:
    """Visibility of each vertex at its query texels: the texel-wise product of its factors.

    Parameters
    ----------
    query : (V, T) int
        World texels per vertex.
    factors : sequence of (table, corners, weights, texel_map)
        One per factor (self-visibility, each occluder): ``table`` a :class:`SparseCubemaps`
        of P samples (any batch shape, flattened), ``corners`` / ``weights`` (V, 8) the samples
        blended at each vertex (all weights 0: the factor is 1 there), ``texel_map`` (6 r^2,)
        world texel -> the factor's texel (:func:`rotation_texel_map`).
    resolution : int
    method : {"numba", "reference"}
        Point evaluation / synthesis from the coefficients in a parallel kernel, or
        dense numpy reconstruction with :func:`prtlab.wavelet.ihaar2d` (``"reference"``).

    Returns
    -------
    visibility : (V, T) float64
    """
    method = check_choice(method, "method", _METHODS)
    res = _check_resolution(resolution)
    query = np.ascontiguousarray(np.asarray(query, dtype=np.int64))
    nv, nt = query.shape
    vis = np.ones((nv, nt))
    count = np.full(nv, nt, dtype=np.int64)
    for table, corners, weights, texel_map in factors:
        if table.resolution != res:
            raise ValueError(f"every factor must have resolution {res}, got {table.resolution}")
        idx = np.ascontiguousarray(table.indices.reshape(-1, table.keep))
        val = np.ascontiguousarray(table.values.reshape(-1, table.keep))
        corners = np.ascontiguousarray(corners, dtype=np.int64)
        weights = np.ascontiguousarray(weights, dtype=np.float64)
        texel_map = np.ascontiguousarray(texel_map, dtype=np.int64)
        if method == "numba":
            if nv and nt:
                blocks = min(nv, 4 * numba.get_num_threads())
                hk.visibility_factor_kernel(idx, val, corners, weights, texel_map, query, count, res, blocks, vis)
            continue
        from prtlab.wavelet import ihaar2d

        n = 6 * res * res
        coeffs = np.zeros((nv, n))
        rows = np.arange(nv)[:, None]
        for c in range(8):
            np.add.at(coeffs, (rows, idx[corners[:, c]].astype(np.int64)), weights[:, c, None] * val[corners[:, c]])
        dense = ihaar2d(coeffs.reshape(nv, 6, res, res), method="reference").reshape(nv, n)
        dense[np.all(weights == 0, axis=1)] = 1.0
        vis *= np.take_along_axis(dense, texel_map[query], axis=1)
    return vis


def haar_direct_pass(visibility, g_weight, radiance, count=None, method: str = "numba") -> np.ndarray:
    """``L_k = sum_p V_p G_pk radiance_p`` per vertex (Iwasaki et al. Eq. 7-8, before ``h_k`` and colour).

    Parameters
    ----------
    visibility : (V, T) float
    g_weight : (V, T, K) float
    radiance : (V, T, C) float
    count : (V,) int, optional
        Pieces used per vertex (default all T).
    method : {"numba", "reference"}

    Returns
    -------
    light_k : (V, K, C) float64
    """
    method = check_choice(method, "method", _METHODS)
    vis = np.ascontiguousarray(visibility, dtype=np.float64)
    gw = np.ascontiguousarray(g_weight, dtype=np.float64)
    rad = np.ascontiguousarray(radiance, dtype=np.float64)
    nv, nt = vis.shape
    if gw.shape[:2] != (nv, nt) or rad.shape[:2] != (nv, nt) or gw.ndim != 3 or rad.ndim != 3:
        raise ValueError(f"g_weight and radiance must be (V, T, K) and (V, T, C) with (V, T) = {(nv, nt)}, "
                         f"got {gw.shape} and {rad.shape}")
    count = np.full(nv, nt, dtype=np.int64) if count is None else np.ascontiguousarray(count, dtype=np.int64)
    if method == "reference":
        used = np.arange(nt)[None, :] < count[:, None]
        return np.einsum("vp,vpk,vpc->vkc", np.where(used, vis, 0.0), gw, rad)
    out = np.zeros((nv, gw.shape[2], rad.shape[2]))
    if nv:
        hk.direct_kernel(vis, gw, rad, count, out)
    return out


def check_receivers(sep, points, normals):
    """The receivers of a Haar pass checked: ``sep`` a :class:`prtlab.brdf.SeparableBRDF`, ``points`` and
    ``normals`` ``(V, 3)`` finite, the normals made unit. Returns ``(points, normals)``."""
    from prtlab.brdf import SeparableBRDF

    if not isinstance(sep, SeparableBRDF):
        raise TypeError(f"sep must be a SeparableBRDF (prtlab.brdf.separable), got {type(sep).__name__}")
    points = as_points(points, "points", flat=True)
    normals = as_points(normals, "normals", flat=True)
    if normals.shape != points.shape:
        raise ValueError(f"normals must be {points.shape} like points, got {normals.shape}")
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return points, normals


def visibility_factors(points, self_visibility, self_transform, occluders, interpolation, resolution):
    """The visibility factors at ``points``: ``(table, corners (V, 8), weights (V, 8), texel map)`` for the
    object's own cubemaps (rotated by ``self_transform``) and each ``(HaarOcclusionField, Transform)`` occluder."""
    factors = []
    nv = len(points)
    if self_visibility is not None:
        if not isinstance(self_visibility, SparseCubemaps):
            raise TypeError(f"self_visibility must be SparseCubemaps (haar_self_visibility), got "
                            f"{type(self_visibility).__name__}")
        if self_visibility.shape != (nv,):
            raise ValueError(f"self_visibility must hold one cubemap per point ({nv},), got {self_visibility.shape}")
        corners = np.zeros((nv, 8), dtype=np.int64)
        corners[:, 0] = np.arange(nv)
        weights = np.zeros((nv, 8))
        weights[:, 0] = 1.0
        R = np.eye(3) if self_transform is None else np.asarray(self_transform.rotation, float)
        factors.append((self_visibility, corners, weights, rotation_texel_map(R, resolution)))
    for i, item in enumerate(occluders):
        if not (isinstance(item, (tuple, list)) and len(item) == 2 and isinstance(item[0], HaarOcclusionField)):
            raise TypeError(f"occluders[{i}] must be a (HaarOcclusionField, Transform or None) pair")
        field, T = item
        corners, weights = field.corners(points, T, interpolation)
        R = np.eye(3) if T is None else np.asarray(T.rotation, float)
        factors.append((field.visibility, corners, weights, rotation_texel_map(R, resolution)))
    for table, *_ in factors:
        if table.resolution != resolution:
            raise ValueError(f"self_visibility and the occluders must share one cubemap resolution: they must "
                             f"have resolution {resolution}, got {table.resolution}")
    return factors


def haar_direct(points, normals, lights, sep, *, self_visibility: SparseCubemaps | None = None, self_transform=None,
                occluders=(), resolution: int | None = None, interpolation: str = "trilinear",
                method: str = "numba") -> np.ndarray:
    """All-frequency direct light ``L_k`` (V, K, C) of receiver vertices: Haar shadow fields, exact lights.

    Parameters
    ----------
    points, normals : (V, 3) float
        World positions and unit normals of the receiver vertices.
    lights : sequence of EnvironmentLight, AreaLight, PointLight
    sep : prtlab.brdf.SeparableBRDF
        The receiver's separable BRDF (``"plain"``): ``g_k`` in the local frame of
        :func:`prtlab.brdf.local_frame` (the frame of :func:`prtlab.brdf.project_g_cos`).
    self_visibility : SparseCubemaps (V,), optional
        :func:`haar_self_visibility` of the receiver (object frame); None: no self-shadowing.
    self_transform : prtlab.scene.Transform, optional
        The receiver's pose (its rotation turns the self-visibility).
    occluders : sequence of (HaarOcclusionField, Transform or None)
        The other objects and their poses (any order: the product is exact).
    resolution : int, optional
        Cubemap resolution (default: that of the visibility data, else 32).
    interpolation : {"trilinear", "nearest"}
        Occlusion-field lookup (:class:`HaarOcclusionField`).
    method : {"numba", "reference"}
        Tiers of :func:`haar_visibility_pass` and :func:`haar_direct_pass`.

    Returns
    -------
    light_k : (V, K, C) float64
        ``int L V g_k max(0, n . w) dw``; the radiance toward ``wo`` is
        ``sum_k h_k(wo) colour[k] light_k`` (:func:`prtlab.brdf.project_h`).

    Examples
    --------
    >>> import numpy as np
    >>> from prtlab import brdf
    >>> from prtlab.scene import PointLight
    >>> sep = brdf.separable(brdf.lambert(1.0), 1)
    >>> lk = haar_direct([[0.0, 0, 0]], [[0.0, 1, 0]], [PointLight(np.array([0.0, 2, 0]), np.ones(3))], sep)
    >>> np.round(lk[0, 0] * np.pi * 4, 6)  # E = I / r^2 = 1/4, g = 1/pi
    array([1., 1., 1.])
    """
    method = check_choice(method, "method", _METHODS)
    points, normals = check_receivers(sep, points, normals)
    if resolution is None:
        tables = ([self_visibility] if isinstance(self_visibility, SparseCubemaps) else []) + [
            o[0].visibility for o in occluders if isinstance(o, (tuple, list)) and len(o) == 2
            and isinstance(o[0], HaarOcclusionField)]
        resolution = tables[0].resolution if tables else 32
    res = _check_resolution(resolution)
    lights = list(lights)
    nv = len(points)
    out = np.zeros((nv, sep.K, 3))
    if nv == 0:
        return out
    factors = visibility_factors(points, self_visibility, self_transform, occluders, interpolation, res)
    # environments take a dense path (every texel lit, the light shared by all vertices) in the fast tier;
    # the reference tier runs every light through light_pieces and haar_direct_pass (the specification)
    fast_env = method == "numba"
    envs = [li for li in lights if isinstance(li, EnvironmentLight)] if fast_env else []
    local = [li for li in lights if not (fast_env and isinstance(li, EnvironmentLight))]
    n_tex = 6 * res * res
    per_vertex = 4 + 64 * len(local) + sum(n_tex for li in lights if isinstance(li, EnvironmentLight))
    step = max(1, _PIECES_PER_CHUNK // per_vertex)
    cubes = [environment_cubemap(li, res).reshape(n_tex, 3) for li in envs]
    moments = texel_moments(res) if envs else None
    for a in range(0, nv, step):
        b = min(nv, a + step)
        chunk = [(t, c[a:b], w[a:b], m) for t, c, w, m in factors]
        if local:
            texel, gw, rad, count = light_pieces(local, points[a:b], normals[a:b], sep, res)
            if texel.shape[1]:
                vis = haar_visibility_pass(texel, chunk, res, method=method)
                out[a:b] += haar_direct_pass(vis, gw, rad, count, method=method)
        if envs:
            out[a:b] += _environments_direct(sep, normals[a:b], chunk, cubes, moments, res, method)
    return out


def _environments_direct(sep, normals, factors, cubes, moments, res: int, method: str) -> np.ndarray:
    """``(v, K, 3)`` light of the environment ``cubes`` (each ``(6 r^2, 3)``) on every texel at once."""
    n_tex = 6 * res * res
    query = np.ascontiguousarray(np.broadcast_to(np.arange(n_tex), (len(normals), n_tex)))
    vis = haar_visibility_pass(query, factors, res, method=method)
    g0 = _lambert_g(sep)
    if g0 is not None:  # int_texel g cos = g max(0, n . m_t): one matrix product
        gc = (g0 * np.maximum(normals @ moments.T, 0.0))[:, :, None]
    else:
        gc = _g_cos(sep, np.broadcast_to(moments, (len(normals), n_tex, 3)), normals,
                    np.linalg.norm(moments, axis=1)[None, :])  # (v, t, K)
    out = np.zeros((len(normals), sep.K, 3))
    for cube in cubes:
        for k in range(sep.K):
            out[:, k] += (vis * gc[:, :, k]) @ cube
    return out


def edge_bound(texel, g_weight, radiance, visibility_cubemaps, resolution: int) -> np.ndarray:
    """The resolution bound of :func:`haar_direct`: the light on texels where ``V`` is not constant.

    Parameters
    ----------
    texel, g_weight, radiance
        From :func:`light_pieces` (V, T), (V, T, K), (V, T, C).
    visibility_cubemaps : (V, 6, r, r) float
        The world visibility of each vertex (e.g. products of :meth:`HaarOcclusionField.lookup`).
    resolution : int

    Returns
    -------
    bound : (V, K, C) float64
        ``sum over edge texels p of |G_pk| radiance_p``; an edge texel has a
        fractional visibility or one different from a 4-neighbour on its face.
    """
    res = _check_resolution(resolution)
    v = np.asarray(visibility_cubemaps, dtype=np.float64).reshape(-1, 6, res, res)
    edge = (v > 0) & (v < 1)
    diff_i = v[:, :, 1:, :] != v[:, :, :-1, :]
    diff_j = v[:, :, :, 1:] != v[:, :, :, :-1]
    edge[:, :, 1:, :] |= diff_i
    edge[:, :, :-1, :] |= diff_i
    edge[:, :, :, 1:] |= diff_j
    edge[:, :, :, :-1] |= diff_j
    on = np.take_along_axis(edge.reshape(len(v), -1), np.asarray(texel, np.int64), axis=1)
    return np.einsum("vp,vpk,vpc->vkc", on.astype(float), np.abs(g_weight), radiance)
