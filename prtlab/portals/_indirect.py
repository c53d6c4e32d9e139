"""Indirect component of the portal transfer (Yue et al. 2009, Section 4.1.1).

Photons leave the portal and carry, instead of an energy, the *light
transport response* of every SH basis function at once (one trace for all
bases): a photon emitted from portal point ``p`` into the interior along
``d`` brings the shell light arriving at ``p`` from ``omega = -d``, so its
response to basis ``Y_lm`` is

.. math::

    \\Phi_{lm} = Y_{lm}(-d) \\, \\frac{A \\pi}{N} \\, \\beta,

with ``A`` the portal area, ``N`` the photons emitted (uniform by area,
cosine-weighted direction: pdf ``cos / (pi A)``) and ``beta`` (RGB) the
product of the reflection weights met so far (``kd``, or the Phong lobe's
weight on a glossy object: :func:`trace_photons`). A photon whose backward ray (from ``p``
along ``-d``) hits the scene is discarded (backward occlusion, Fig. 4(b)).
Photons are stored at every diffuse hit up to depth ``B - 1`` (``B``
indirect bounces); records keep the emission direction and ``beta`` only,
and ``Y_lm(-d)`` is evaluated when estimating.

Radiance estimates at the vertices (Christensen 1999): among the nearest
photons, those whose surface normal agrees with the vertex normal (``n_p . n_v >
cos 45 deg``) and that lie near the vertex's tangent plane; with ``r`` the
distance of the ``k``-th of them, the ``k - 1`` nearer ones give the irradiance
response ``E_lm(v) = sum Phi_lm / (f pi r^2)`` and the exitance ``B_lm(v) =
rho_v / pi E_lm(v)``. ``f`` is the part of the disc that lies on the vertex's
own surface (probe rays, :func:`disc_coverage`): on a wall's edge photons come
from half the disc, in a corner from a quarter. Dividing by the whole disc (and
counting the ``k``-th photon, an excess ``k / (k - 1)``) made the tiny room's
indirect light 10-15% too dark (``docs/notes/portals.md``).

Final gathering at vertex ``v`` casts ``M`` cosine-weighted rays;
a ray hitting the front side of a triangle reads ``B`` interpolated
(barycentrically) from the triangle's vertices; the transfer vector is

.. math::

    t_{lm}(v) = \\rho_v \\frac{1}{M} \\sum_{j=1}^{M} B_{lm}(h_j),
    \\qquad L_{ind}(v) = \\sum_{lm} t_{lm}(v) \\, c_{lm},

with ``c_lm`` the shell light's SH coefficients (:func:`prtlab.portals.shell_sh`).

Glossy (Phong) objects: photons reflect by the Phong lobe as well, and a
glossy vertex also gets a specular exitance response ``S_ji`` (SH over the
outgoing direction ``j`` times SH of the light ``i``) from the same photons;
a gather ray reaching it reads ``B + sum_j Y_j(-d) S_j`` (its radiance
toward the gathering point). Leaving both out (a Lambertian photon map with
``kd``) loses the glossy objects' specular light reflected back onto them and
via the walls (measured: ``docs/notes/portals.md``).

Errors: the SH truncation of the shell light (Section 4.2), Monte Carlo noise
of the gather (``M`` rays) and of the photons, and the bias of density
estimation: the estimate is the irradiance averaged over a disc of radius
``r`` (``O(r^2 |Laplacian E|)``), plus the linear interpolation of ``B`` between
vertices. The gather averages these over the hemisphere, so they shrink in
the result; the bias we measured on the unit-test box is stated in
``tests/portals/test_indirect.py``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from prtlab._validate import check_int
from prtlab.geometry import RayCaster, cosine_hemisphere, sample_mesh_area

from ._shell import Portal

__all__ = ["trace_photons", "PhotonMap", "radiance_estimate", "disc_coverage", "final_gather",
           "phong_lobe_sample"]

_NORMAL_AGREEMENT = np.cos(np.radians(45.0))

#: a photon whose height over a vertex's tangent plane exceeds this times its distance is not on its surface
_PLANE_TOLERANCE = 0.25

#: probe rays of :func:`disc_coverage`
N_PROBES = 64


def _sunflower(n: int) -> np.ndarray:
    """``n`` points spread evenly over the unit disc (Vogel's spiral), ``(n, 2)``."""
    i = np.arange(n) + 0.5
    r, a = np.sqrt(i / n), i * np.pi * (3 - np.sqrt(5))
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def disc_coverage(caster: RayCaster, objects, points, normals, radius, n_probes: int = N_PROBES) -> np.ndarray:
    """The fraction of each vertex's estimate disc that lies on its own surface, ``(V,)`` in ``[0, 1]``.

    The disc of radius ``radius[v]`` about ``points[v]`` in its tangent plane is probed at ``n_probes`` evenly
    spread points (a sunflower pattern): a ray from ``0.25 r`` above a probe point along ``-normal`` must meet
    object ``objects[v]`` within ``0.5 r`` on a face whose normal agrees with the vertex's (``|n_f . n_v| > cos
    45 deg``). Past a wall's edge, in a window opening or under an object standing on the surface the probe
    misses (or meets another object), so an edge vertex gets about 1/2 and a corner about 1/4. A curved surface
    counts where it stays within ``0.25 r`` of the plane. A vertex whose probes all miss gets 1 (no correction).
    """
    from prtlab.geometry import tangent_frame

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    radius = np.asarray(radius, dtype=np.float64).reshape(-1)
    objects = np.asarray(objects, dtype=np.int64).reshape(-1)
    if len(points) == 0:
        return np.ones(0)
    t1, t2 = tangent_frame(normals)
    d = _sunflower(int(n_probes))
    r = np.where(np.isfinite(radius) & (radius > 0), radius, 0.0)[:, None, None]
    probe = points[:, None] + r * (d[None, :, :1] * t1[:, None] + d[None, :, 1:] * t2[:, None])
    origin = probe + 0.25 * r * normals[:, None]
    dirs = np.broadcast_to(-normals[:, None], origin.shape)
    hits = caster.closest_hit(origin.reshape(-1, 3), dirs.reshape(-1, 3),
                              np.repeat(0.5 * r[:, 0, 0], len(d)) + caster.epsilon)
    agree = np.abs(np.einsum("vpk,vk->vp", hits.normal.reshape(origin.shape), normals)) > _NORMAL_AGREEMENT
    on = hits.hit.reshape(len(points), -1) & (hits.object.reshape(len(points), -1) == objects[:, None]) & agree
    f = on.mean(axis=1)
    return np.where((f > 0) & (r[:, 0, 0] > 0), f, 1.0)

#: bytes of the per-chunk work arrays of :func:`radiance_estimate` and :func:`final_gather`: their vertex
#: chunks shrink (to one vertex at least) so that many bounces and SH bands stream instead of piling up
CHUNK_BYTES = 1 << 28


def _fit_chunk(chunk: int, bytes_per_point: float) -> int:
    """``chunk`` reduced so that ``chunk * bytes_per_point <= CHUNK_BYTES`` (at least 1)."""
    return int(max(1, min(int(chunk), CHUNK_BYTES // max(int(bytes_per_point), 1))))


class PhotonMap:
    """Stored photons: ``position (P, 3)``, ``normal (P, 3)`` (the side hit),
    ``throughput (P, 3)`` (``A pi / N`` times the albedos met, RGB),
    ``emit_dir (P, 3)`` (the direction the shell light came *from*, ``-d``),
    ``depth (P,)`` (0 = first hit), ``direction (P, 3)`` (the photon's travel direction at the hit)."""

    def __init__(self, position, normal, throughput, emit_dir, depth, n_emitted, direction=None):
        self.direction = direction  # (P, 3) the photon's travel direction at the hit (None: not recorded)
        self.position = position
        self.normal = normal
        self.throughput = throughput
        self.emit_dir = emit_dir
        self.depth = depth
        self.n_emitted = n_emitted

    def __len__(self):
        return len(self.position)


def trace_photons(
    caster: RayCaster,
    albedo,
    portal: Portal,
    n_photons: int,
    bounces: int,
    rng: np.random.Generator,
    batch: int = 1 << 17,
    ks=None,
    exponent=None,
) -> PhotonMap:
    """Trace photons from a portal (Section 4.1.1, step 1a) for all SH bases at once.

    (Long for its documentation and signature; the code, 55 lines, is the bounce loop.)

    Parameters
    ----------
    caster : RayCaster
        The interior geometry (portals left out).
    albedo : (n_objects, 3) float
        Diffuse albedo of each caster object.
    portal : Portal
    n_photons : int
        Photons emitted (the paper: 2M per basis; here one set serves every basis).
    bounces : int >= 1
        Indirect bounces ``B``: photons are stored at depths ``0 .. B-1``.
    rng : numpy.random.Generator
    ks : (n_objects, 3) float, optional
        Specular albedo of each caster object (normalised Phong, :class:`prtlab.scene.Material`); default 0.
    exponent : (n_objects,) float, optional
        Phong exponent of each caster object (used where ``ks > 0``).

    Returns
    -------
    PhotonMap

    Notes
    -----
    At a hit on a Phong object (``kd + ks``) the photon continues by the
    specular lobe with probability ``p_s = sum(ks) / (sum(kd) + sum(ks))``,
    sampled about the mirror ``r`` of its direction with pdf
    ``(e + 1) / (2 pi) (r . w)^e``, its weight multiplied by
    ``f_s cos / (p_s pdf) = ks (e + 2) / (e + 1) max(0, n . w) / p_s``;
    otherwise by the cosine lobe, weight ``kd / (1 - p_s)``. (Without the
    specular lobe, light a glossy object reflects onto the walls is lost.) Photons are
    stored at every hit, as diffuse flux (the radiance estimate is Lambertian).
    """
    check_int(n_photons, "n_photons", 1)
    check_int(bounces, "bounces", 1, meaning="photon tracing needs one")
    albedo = np.asarray(albedo, dtype=np.float64).reshape(-1, 3)
    ks = np.zeros_like(albedo) if ks is None else np.asarray(ks, dtype=np.float64).reshape(-1, 3)
    exponent = np.zeros(len(albedo)) if exponent is None else np.asarray(exponent, dtype=np.float64).reshape(-1)
    if ks.shape != albedo.shape or exponent.shape != (len(albedo),):
        raise ValueError(f"ks must have shape {albedo.shape} and exponent ({len(albedo)},) (one per caster object), "
                         f"got {ks.shape} and {exponent.shape}")
    if np.any(ks < 0) or not np.all(np.isfinite(exponent)) or np.any(exponent < 0):
        raise ValueError("ks must be >= 0 and exponent finite and >= 0")
    total = albedo.sum(axis=1) + ks.sum(axis=1)
    p_spec = np.divide(ks.sum(axis=1), total, out=np.zeros(len(albedo)), where=total > 0)
    records = {k: [] for k in ("position", "normal", "throughput", "emit_dir", "depth", "direction")}
    w0 = portal.area * np.pi / n_photons
    mesh = (portal.vertices, portal.faces)
    for start in range(0, n_photons, batch):
        m = min(batch, n_photons - start)
        s = sample_mesh_area(mesh, m, rng)
        d = cosine_hemisphere(1, rng, s.normals)[0][:, 0, :]
        keep = ~caster.occluded(s.points, -d, normals=s.normals)  # backward occlusion
        o, d, n_o, emit = s.points[keep], d[keep], s.normals[keep], -d[keep]
        beta = np.full((len(o), 3), w0)
        for depth in range(int(bounces)):
            if len(o) == 0:
                break
            hits = caster.closest_hit(o, d, normals=n_o)
            h = hits.hit
            o, d, beta, emit = hits.point[h], d[h], beta[h], emit[h]
            n = hits.normal[h]
            n = np.where((np.sum(n * d, axis=-1) > 0)[:, None], -n, n)  # the side facing the photon
            records["position"].append(o)
            records["normal"].append(n)
            records["throughput"].append(beta)
            records["emit_dir"].append(emit)
            records["depth"].append(np.full(len(o), depth, dtype=np.int64))
            records["direction"].append(d)
            obj = hits.object[h]
            d_in = d
            d = cosine_hemisphere(1, rng, n)[0][:, 0, :]
            spec = rng.random(len(o)) < p_spec[obj]
            with np.errstate(divide="ignore", invalid="ignore"):
                weight = albedo[obj] / (1.0 - p_spec[obj])[:, None]
            if np.any(spec):
                s_obj = obj[spec]
                mirror = d_in[spec] - 2.0 * np.sum(d_in[spec] * n[spec], axis=-1, keepdims=True) * n[spec]
                w = phong_lobe_sample(mirror, exponent[s_obj], rng)
                cos = np.sum(w * n[spec], axis=-1)
                d[spec] = w
                weight[spec] = (ks[s_obj] * ((exponent[s_obj] + 2.0) / (exponent[s_obj] + 1.0) / p_spec[s_obj]
                                             * np.maximum(cos, 0.0))[:, None])
            beta = beta * weight
            alive = np.any(beta > 0, axis=1)
            o, d, beta, emit, n_o = o[alive], d[alive], beta[alive], emit[alive], n[alive]
    cat = {k: (np.concatenate(v) if v else np.zeros((0,) if k == "depth" else (0, 3))) for k, v in records.items()}
    return PhotonMap(cat["position"], cat["normal"], cat["throughput"], cat["emit_dir"],
                     cat["depth"].astype(np.int64), int(n_photons), cat["direction"])


def phong_lobe_sample(axis, exponent, rng: np.random.Generator) -> np.ndarray:
    """Directions about unit ``axis (N, 3)`` with pdf ``(e + 1) / (2 pi) (axis . w)^e`` (``exponent (N,)``).

    ``cos alpha = u^(1 / (e + 1))``, ``phi = 2 pi v`` in an orthonormal frame of the axis (Duff et al. 2017).

    Returns
    -------
    (N, 3) float64
    """
    axis = np.asarray(axis, dtype=np.float64).reshape(-1, 3)
    u = rng.random((len(axis), 2))
    cos_a = u[:, 0] ** (1.0 / (np.asarray(exponent, dtype=np.float64) + 1.0))
    sin_a = np.sqrt(np.maximum(0.0, 1.0 - cos_a**2))
    phi = 2.0 * np.pi * u[:, 1]
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    sign = np.where(z >= 0, 1.0, -1.0)
    a = -1.0 / (sign + z)
    b = x * y * a
    t = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)
    bt = np.stack([b, sign + y * y * a, -y], axis=-1)
    return (sin_a * np.cos(phi))[:, None] * t + (sin_a * np.sin(phi))[:, None] * bt + cos_a[:, None] * axis


def radiance_estimate(photons: PhotonMap, points, normals, albedo, order: int, k: int = 32,
                      chunk: int = 4096, depths: int | None = None, glossy=None, surface=None,
                      halves: bool = False):
    """Exitance response ``B_lm(v) = rho_v / pi * E_lm(v)`` at points (Christensen 1999).

    (Long for its documentation; the code, 76 lines, is the chunk loop: neighbours, disc coverage, sums.)

    Parameters
    ----------
    photons : PhotonMap
    points, normals : (V, 3) float
    albedo : (V, 3) float
    order : int
        SH order ``n`` (``n*n`` coefficients).
    k : int
        Photons per estimate: the radius is the distance of the ``k``-th agreeing photon and the ``k - 1``
        nearer ones are summed (unbiased for a uniform density; with fewer found, the last found sets the
        radius).
    surface : tuple (caster RayCaster, objects (V,) int), optional
        The scene and each point's object in it: the disc area is scaled by the part of it on the point's
        surface (:func:`disc_coverage`). Without it the whole disc is used (too dark at edges and corners).
    depths : int, optional
        Split the estimate by photon depth ``0 .. depths-1`` (the same ``k``
        nearest photons and radius; each photon counts toward its own depth), so
        the depths sum to the undivided estimate: light that has bounced
        ``d + 1`` times when it leaves the point.
    glossy : tuple (index (V_g,) int, ks (V_g, 3), exponent (V_g,), order_out), optional
        Points ``index`` are Phong: also return their specular exitance response
        ``S_{j i}(v) = ks sum_p Phi_i(p) sqrt(4 pi / (2l+1)) z_l Y_j(r_p) / (pi r^2)`` with ``r_p`` the mirror of
        photon ``p``'s direction about its normal and ``z`` the lobe's ZH (:func:`phong_lobe_zh`): the
        radiance leaving ``v`` toward ``w`` is ``sum_j Y_j(w) sum_i S_ji c_i`` (the photon estimate
        ``L(w) = sum_p f_s(w_p, w) Phi_p / (pi r^2)`` projected over ``w``). A gather ray reaching a glossy
        object reads it (:func:`final_gather`), so light a glossy object reflects specularly onto another
        point (the bunny onto itself) is kept.
    halves : bool
        Also return ``E_a - E_b`` (the main result's shape, last): the estimate's sum split between two halves
        of the photon paths (same neighbours and radius; a path's half is a low mantissa bit of its emission
        direction, shared by its photons at every depth), a one-sample standard error of the estimate for
        independent paths (their variances add, so the difference's equals the sum's).

    Returns
    -------
    (V, n*n, 3) float64, or (V, depths, n*n, 3) with ``depths``;
    with ``glossy`` also ``(V_g, n_out^2, n*n, 3)`` (or ``(V_g, depths, n_out^2, n*n, 3)``); with ``halves``
    then the difference
    """
    import prtlab.sh as sh

    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    n_coeffs = order * order
    n_depths = 1 if depths is None else int(depths)
    out = np.zeros((len(points), n_depths, n_coeffs, 3))
    if glossy is not None:
        g_index, g_ks, g_exponent, order_out = glossy
        g_index = np.asarray(g_index, dtype=np.int64).reshape(-1)
        g_ks = np.asarray(g_ks, dtype=np.float64).reshape(len(g_index), 3)
        g_exponent = np.broadcast_to(np.asarray(g_exponent, dtype=np.float64), (len(g_index),))
        spec = np.zeros((len(g_index), n_depths, order_out * order_out, n_coeffs, 3))
        lobes: dict = {}
        if len(g_index) and photons.direction is None:
            raise ValueError("the photon map has no photon directions; trace it with trace_photons")

    diff = np.zeros_like(out) if halves else None

    def result():
        main = out if depths is not None else out[:, 0]
        parts = (main,) + (() if glossy is None else ((spec if depths is not None else spec[:, 0]),))
        if halves:
            parts += (diff if depths is not None else diff[:, 0],)
        return parts[0] if len(parts) == 1 else parts

    if len(photons) == 0 or len(points) == 0:
        return result()
    onehot = np.zeros((len(photons), n_depths))
    if depths is None:
        onehot[:, 0] = 1.0
    else:
        keep = photons.depth < n_depths
        onehot[np.nonzero(keep)[0], photons.depth[keep]] = 1.0
    tree = cKDTree(photons.position)
    if halves:
        bits = np.ascontiguousarray(photons.emit_dir[:, 0], dtype=np.float64).view(np.uint64)
        path_sign = np.where((bits >> np.uint64(4)) & np.uint64(1), -1.0, 1.0)
    y = sh.basis(photons.emit_dir, order)
    q = min(len(photons), 4 * k)
    chunk = _fit_chunk(chunk, 2 * q * n_depths * n_coeffs * 3 * 8)
    for start in range(0, len(points), chunk):
        x = points[start : start + chunk]
        nv = normals[start : start + chunk]
        dist, idx = tree.query(x, q)
        dist = dist.reshape(len(x), q)
        idx = idx.reshape(len(x), q)
        ok = np.einsum("vqk,vk->vq", photons.normal[idx], nv) > _NORMAL_AGREEMENT
        # radius: distance of the k-th agreeing photon near the tangent plane (or of the last one found)
        height = np.abs(np.einsum("vqk,vk->vq", photons.position[idx] - x[:, None], nv))
        ok &= height <= _PLANE_TOLERANCE * dist  # within ~14 degrees of the tangent plane
        rank = np.cumsum(ok, axis=1)
        have = rank[:, -1]
        m = np.minimum(k, np.maximum(have, 1))
        kth = np.argmax(rank >= m[:, None], axis=1)
        radius = dist[np.arange(len(x)), kth]
        use = ok & (rank <= np.maximum(m - 1, 1)[:, None]) & (have[:, None] > 0)
        cover = 1.0 if surface is None else disc_coverage(surface[0], np.asarray(surface[1])[start : start + chunk],
                                                          x, nv, radius)
        with np.errstate(divide="ignore", invalid="ignore"):
            area = np.where(radius > 0, cover * np.pi * radius**2, np.inf)
        w = use / area[:, None]  # (v, q)
        e = np.einsum("vq,vqd,vqc,vqi->vdic", w, onehot[idx], photons.throughput[idx], y[idx], optimize=True)
        out[start : start + chunk] = e * (np.asarray(albedo[start : start + chunk]) / np.pi)[:, None, None, :]
        if halves:
            sign = path_sign[idx]
            d = np.einsum("vq,vqd,vqc,vqi->vdic", w * sign, onehot[idx], photons.throughput[idx], y[idx],
                          optimize=True)
            diff[start : start + chunk] = d * (np.asarray(albedo[start : start + chunk]) / np.pi)[:, None, None, :]
        if glossy is not None:
            rows_all = np.nonzero((g_index >= start) & (g_index < start + len(x)))[0]
            for b0 in range(0, len(rows_all), 128):  # bounds the (vertices, q, n_out^2) lobe array
                rows = rows_all[b0 : b0 + 128]
                loc = g_index[rows] - start
                sel = idx[loc]  # (b, q); unused neighbours carry w = 0
                dp, npn = photons.direction[sel], photons.normal[sel]
                mirror = dp - 2.0 * np.sum(dp * npn, axis=-1, keepdims=True) * npn
                zh = np.stack([lobes.setdefault(float(e), phong_lobe_zh(float(e), order_out))
                               for e in g_exponent[rows]])
                lobe = sh.zh_rotate(zh[:, None, :], mirror)  # (b, q, n_out^2)
                resp = np.einsum("vq,vqd,vqc,vqi->vqdic", w[loc], onehot[sel], photons.throughput[sel], y[sel],
                                 optimize=True)
                spec[rows] = np.einsum("vqj,vqdic->vdjic", lobe, resp, optimize=True) \
                    * g_ks[rows][:, None, None, None, :]
    return result()


def phong_lobe_zh(exponent: float, order: int) -> np.ndarray:
    """ZH coefficients of the normalised Phong lobe ``g(mu) = (e + 2) / (2 pi) max(0, mu)^e`` about its axis.

    ``z_l = 2 pi int_0^1 g(mu) sqrt((2l+1)/(4 pi)) P_l(mu) dmu`` by Gauss-Legendre on ``[0, 1]`` (exact for an
    integer ``e``: a polynomial there). Rotated to the mirror direction ``r`` (:func:`prtlab.sh.zh_rotate`) it is
    the SH projection over ``w_o`` of ``g(r . w_o)``.

    Returns
    -------
    (order,) float64
    """
    if not (np.isfinite(exponent) and exponent >= 0):
        raise ValueError(f"exponent must be a finite number >= 0, got {exponent!r}")
    n_nodes = int(order + np.ceil(exponent) // 2 + 16)
    t, w = np.polynomial.legendre.leggauss(n_nodes)
    mu, w = 0.5 * (t + 1.0), 0.5 * w
    legendre = np.polynomial.legendre.legvander(mu, order - 1) * np.sqrt((2.0 * np.arange(order) + 1) / (4 * np.pi))
    g = (exponent + 2.0) / (2.0 * np.pi) * mu**exponent
    return 2.0 * np.pi * (legendre * (w * g)[:, None]).sum(axis=0)


def front_hit_corners(hits, dirs, faces_all, vertex_offset, vertex_normals):
    """``(sel, vid, bw)`` of the rays that hit: their indices ``sel``, the hit triangles' global vertex ids ``vid
    (R, 3)`` and barycentric weights ``bw (R, 3)``, zero where the ray meets the back of the surface (by the
    interpolated vertex normal). ``dirs (N, 3)``: the rays' directions."""
    sel = np.nonzero(hits.hit)[0]
    obj, tri = hits.object[sel], hits.triangle[sel]
    u, v = hits.barycentric[sel, 0], hits.barycentric[sel, 1]
    vid = np.empty((len(sel), 3), dtype=np.int64)
    for i in np.unique(obj):
        m = obj == i
        vid[m] = faces_all[i][tri[m]] + vertex_offset[i]
    bw = np.stack([1.0 - u - v, u, v], axis=-1)
    n_hit = np.einsum("rk,rkc->rc", bw, vertex_normals[vid])
    bw *= (np.einsum("rc,rc->r", n_hit, dirs[sel]) < 0)[:, None]
    return sel, vid, bw


def final_gather(caster: RayCaster, points, normals, albedo, exitance, vertex_offset, vertex_normals,
                 n_rays: int, rng: np.random.Generator, chunk: int = 512, glossy=None, glossy_exitance=None):
    """Transfer vectors ``t(v) = rho_v mean_j B(h_j)`` by final gathering (Section 4.1.1, step 2).

    (Long for its documentation; the code, 76 lines, is the chunk loop: cast, read the exitance, average.)

    Parameters
    ----------
    caster : RayCaster
    points, normals : (V, 3) float
        Gather points and their shaded-side normals.
    albedo : (V, 3) float
        Lambertian albedo (``kd`` of a Phong vertex).
    exitance : (N, ..., 3) float
        ``B`` at every vertex of every caster object, concatenated in caster order
        (``(N, n*n, 3)``, or ``(N, depths, n*n, 3)`` split by bounce).
    vertex_offset : (n_objects + 1,) int
        Start of each caster object's vertices in ``exitance``.
    vertex_normals : (N, 3) float
        World vertex normals in the same order (the side ``B`` was estimated for).
    n_rays : int
        Gather rays per vertex (the paper: 4096).
    glossy : tuple (ks (V, 3), exponent (V,), order_out), optional
        Every point is a Phong vertex: also return its specular transfer *matrix*
        (Appendix, non-diffuse vertices), from the same gather rays.

    Returns
    -------
    transfer : (V, ..., 3) float64
        The trailing axes of ``exitance``.
    matrix : (V, ..., n_out^2, n*n, 3) float64, only with ``glossy``
        ``M_{j i}(v) = ks (pi / M) sum_r sqrt(4 pi / (2l+1)) z_l Y_j(r_r) B_i(h_r)`` with ``r_r = 2 (n . d_r) n - d_r``
        the mirror of gather ray ``d_r`` and ``z`` the Phong lobe's ZH (:func:`phong_lobe_zh`), ``l`` the band of
        ``j``: the SH projection over ``w_o`` of ``L_o(w_o) = int ks g(r(w_i) . w_o) L_i(w_i) cos dw_i`` (cosine
        sampling, pdf ``cos / pi``). Run time: ``L_o(w_o) = sum_j Y_j(w_o) sum_i M_ji c_i`` (Eq. 6).
    glossy_exitance : tuple (row (N,) int, S (N_g, ..., n_s^2, n*n, 3)), optional
        The specular exitance response of the glossy caster vertices (:func:`radiance_estimate` with
        ``glossy``; ``row[i]`` its row for caster vertex ``i``, ``-1`` for a diffuse one): a ray reaching a
        glossy vertex ``h`` along ``d`` reads ``B(h) + sum_j Y_j(-d) S_j(h)`` (the view-dependent radiance
        toward the gathering point) instead of ``B(h)`` alone.
    """
    import prtlab.sh as sh

    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    trailing = exitance.shape[1:]
    exitance = exitance.reshape(len(exitance), -1)
    out = np.zeros((len(points),) + trailing)
    if glossy is not None:
        ks, exponent, order_out = glossy
        ks = np.asarray(ks, dtype=np.float64).reshape(len(points), 3)
        exponent = np.broadcast_to(np.asarray(exponent, dtype=np.float64), (len(points),))
        lobes = {float(e): phong_lobe_zh(float(e), order_out) for e in np.unique(exponent)}
        n_out = order_out * order_out
        matrix = np.zeros((len(points), n_out, exitance.shape[1]))
    faces_all = [caster.faces(i) for i in range(caster.n_objects)]
    chunk = _fit_chunk(chunk, 4 * n_rays * exitance.shape[1] * 8)  # gathered and the 3 corners' exitance
    for start in range(0, len(points), chunk):
        x = points[start : start + chunk]
        nv = normals[start : start + chunk]
        nc = len(x)
        dirs, _ = cosine_hemisphere(n_rays, rng, nv)  # (nc, M, 3)
        org = np.broadcast_to(x[:, None, :], dirs.shape)
        nrm = np.broadcast_to(nv[:, None, :], dirs.shape)
        hits = caster.closest_hit(org.reshape(-1, 3), dirs.reshape(-1, 3), normals=nrm.reshape(-1, 3))
        sel, vid, bw = front_hit_corners(hits, dirs.reshape(-1, 3), faces_all, vertex_offset, vertex_normals)
        gathered = np.einsum("rk,rkx->rx", bw, exitance[vid])
        if glossy_exitance is not None:
            g_rows = glossy_exitance[0][vid]  # (R, 3): a triangle's vertices are all glossy or all not
            on = np.nonzero(np.all(g_rows >= 0, axis=1))[0]
            if len(on):
                s_all = glossy_exitance[1]
                s_trail = s_all.shape[1:]  # (..., n_s^2, n*n, 3)
                n_s2 = s_trail[-3]
                s_flat = np.moveaxis(s_all, -3, 1).reshape(len(s_all), n_s2, -1)  # (N_g, n_s^2, ... n*n 3)
                y_out = sh.basis(-dirs.reshape(-1, 3)[sel[on]], int(round(np.sqrt(n_s2))))  # (R_on, n_s^2)
                for b0 in range(0, len(on), 1024):  # bounds the (rays, n_s^2, ...) gather of S
                    b = slice(b0, b0 + 1024)
                    for c in range(3):
                        gathered[on[b]] += bw[on[b], c][:, None] * np.einsum(
                            "rj,rjx->rx", y_out[b], s_flat[g_rows[on[b], c]])
        owner = sel // n_rays
        acc = np.zeros((nc, exitance.shape[1]))
        if len(owner):  # owner is sorted (rays are in vertex order): sum runs of equal owners
            first_vertex, first = np.unique(owner, return_index=True)
            acc[first_vertex] = np.add.reduceat(gathered, first, axis=0)
        rho = np.asarray(albedo[start : start + nc]).reshape((nc,) + (1,) * (len(trailing) - 1) + (3,))
        out[start : start + nc] = acc.reshape((nc,) + trailing) / n_rays * rho
        if glossy is not None and len(owner):
            d = dirs.reshape(-1, 3)[sel]
            nr = nv[owner]
            mirror = 2.0 * np.sum(d * nr, axis=-1, keepdims=True) * nr - d
            zh = np.stack([lobes[float(e)] for e in exponent[start + owner]]) if len(lobes) > 1 else \
                next(iter(lobes.values()))
            a = sh.zh_rotate(zh, mirror)  # (R, n_out)
            bounds = np.append(first, len(owner))
            for vtx, lo, hi in zip(first_vertex, bounds[:-1], bounds[1:]):
                matrix[start + vtx] = a[lo:hi].T @ gathered[lo:hi]
    if glossy is None:
        return out
    # (V, n_out, D * n*n * 3) -> (V, ..., n_out, n*n, 3), ks and pi / M folded in
    matrix = matrix.reshape((len(points), n_out) + trailing) * (np.pi / n_rays)
    matrix = np.moveaxis(matrix, 1, -3) * ks.reshape((len(points),) + (1,) * len(trailing) + (3,))
    return out, matrix
