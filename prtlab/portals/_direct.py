"""Direct component of the portal transfer (Yue et al. 2009, Section 4.1.2).

For a vertex ``x`` with normal ``n`` (shaded side) and a portal of area ``A``,
the direct radiance is (Lambertian, albedo ``rho``)

.. math::

    L_d(x) = \\frac{\\rho}{\\pi} \\int_{S^2} L_s(\\omega) V(x, \\omega) \\max(0, n \\cdot \\omega)\\, d\\omega
           = \\rho \\sum_k T_k \\bar L_{s,k},

where ``omega`` is the direction **from the vertex through the portal point
toward the shell** (the direction the light comes from, in world
coordinates, so ``L_s(omega)`` is read in the same convention as
:meth:`prtlab.scene.EnvironmentLight.radiance`), ``V`` is the visibility
from ``x`` to the portal point *and* the backward visibility from the portal
point to the shell (Fig. 4(b)), and ``k`` runs over the texels of a cubemap
(``r x r`` per face). The transfer texel

.. math::

    T_k = \\frac{1}{\\pi} \\int_{\\Omega_k} V \\max(0, n \\cdot \\omega)\\, d\\omega

already contains the texel's solid angle, so the run-time pass is a plain sum
of products with the texel *averages* ``bar L_{s,k}`` of the shell light
(:func:`prtlab.portals.shell_light`). ``T_k`` is estimated by sampling the
portal by area (pdf ``1/A``) and converting to solid angle:
``d omega = cos_p dA / d^2`` with ``cos_p`` the cosine at the portal.

Errors against the exact integral: (i) Monte Carlo noise of ``T``; (ii) the
cubemap resolution: ``|sum_k int_{Omega_k} (L - bar L_k) ...| <= sum_k T_k
(max_{Omega_k} L - min_{Omega_k} L)``, zero for a light constant per texel;
(iii) 8-bit quantisation (:func:`prtlab.wavelet.quantize8`): every stored
coefficient is off by at most ``scale / 510``, so ``|Delta L_d| <= rho
scale / 510 * sum_k |L_k|`` over the coefficients of the chosen basis that the
vertex's transfer support can touch (bounded by the whole light's L1 norm in
that basis).
"""

from __future__ import annotations

import numpy as np

from prtlab._validate import check_int
from prtlab.geometry import RayCaster, direction_to_cubemap

from ._shell import Portal

__all__ = ["direct_transfer", "glossy_direct_transfer", "view_interpolation", "phong_lipschitz", "strip_frame",
           "strip_weights"]


def _check_points(points, normals):
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (V, 3), got {points.shape}")
    if normals.shape != points.shape:
        raise ValueError(f"normals must have the shape of points {points.shape}, got {normals.shape}")
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(normals))):
        raise ValueError("points and normals must be finite (NaN or inf found)")
    return points, normals


#: the portal samplers of :func:`direct_transfer` (``sampler``)
PORTAL_SAMPLERS = ("sobol", "jittered", "random")


def _parallelogram(portal):
    """``(corner, edge1, edge2)`` when the portal is one planar parallelogram (two triangles sharing a diagonal,
    the same facing), else ``None``."""
    f = np.asarray(portal.faces, dtype=np.int64)
    if len(f) != 2:
        return None
    shared = np.intersect1d(f[0], f[1])
    if len(shared) != 2 or len(np.unique(f)) != 4:
        return None
    v = np.asarray(portal.vertices, dtype=np.float64)
    a, b = v[np.setdiff1d(f[0], shared)[0]], v[np.setdiff1d(f[1], shared)[0]]
    s0, s1 = v[shared[0]], v[shared[1]]
    normals = portal.face_normals
    if np.linalg.norm(a + b - s0 - s1) > 1e-9 * portal.size or normals[0] @ normals[1] < 1.0 - 1e-9:
        return None
    return a, s0 - a, s1 - a


def strip_frame(portal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(corner, strip_edge, other_edge)`` of a parallelogram portal split into strips (``portal_strips``).

    A portal point is ``corner + u strip_edge + v other_edge`` with ``u, v`` in ``[0, 1]``; strip ``j`` of ``K``
    holds ``j / K <= u < (j + 1) / K``. ``strip_edge`` is the portal edge nearest the vertical (``+y``), pointing
    up (``u = 0`` at the bottom edge: a roller shutter or blind); on a horizontal portal the longer edge.
    Raises ``ValueError`` for a portal that is not one planar parallelogram (two triangles).
    """
    quad = _parallelogram(portal)
    if quad is None:
        raise ValueError(f"option portal_strips needs parallelogram portals (one planar quad of two triangles); "
                         f"portal {list(portal.names)} has {len(portal.faces)} face(s) that are not one: use "
                         "portal_strips=0 (a fixed window)")
    corner, e1, e2 = quad
    up = [abs(e[1]) / np.linalg.norm(e) for e in (e1, e2)]
    if abs(up[0] - up[1]) > 1e-9:
        pick = int(up[1] > up[0])
    else:
        pick = int(np.linalg.norm(e2) > np.linalg.norm(e1) * (1.0 + 1e-9))
    strip, other = (e1, e2) if pick == 0 else (e2, e1)
    if strip[1] < 0:
        corner, strip = corner + strip, -strip
    return corner, strip, other


def strip_weights(n_strips: int, low: float, high: float) -> np.ndarray:
    """``(K,)`` open fraction of each strip when the portal is open over ``low <= u <= high`` (:func:`strip_frame`):
    ``K |[j/K, (j+1)/K] cap [low, high]|``, 1 for a strip wholly open, 0 for a closed one."""
    edges = np.arange(n_strips + 1) / n_strips
    return np.clip(n_strips * (np.minimum(edges[1:], high) - np.maximum(edges[:-1], low)), 0.0, 1.0)


def _strip_of(points, n_strips: int, frame) -> np.ndarray:
    """Strip index (``0 .. K-1``) of portal points ``(..., 3)`` in the frame :func:`strip_frame`."""
    corner, strip, other = frame
    basis = np.column_stack([strip, other])
    u = (np.asarray(points) - corner) @ np.linalg.pinv(basis).T
    return np.clip(np.floor(u[..., 0] * n_strips), 0, n_strips - 1).astype(np.int64)


def _sobol_unit_square(n_samples, nc, rng):
    """``(nc, n_samples, 2)`` points of one scrambled Sobol' set (scipy's linear matrix scramble, seeded from
    ``rng``), each vertex's copy digitally shifted by its own random 32-bit XOR per axis and spread uniformly
    within the last bit: every point is uniform on the unit square (unbiased), and each vertex's set keeps the
    net's stratification (every dyadic box of the set's volume ``2^-m`` holds one point for ``n = 2^m``)."""
    import warnings

    from scipy.stats import qmc

    with warnings.catch_warnings():  # n not a power of two: still uniform points, fewer balanced boxes
        warnings.simplefilter("ignore", UserWarning)
        base = qmc.Sobol(2, scramble=True, seed=rng).random(n_samples)
    bits = np.floor(base * 2.0**32).astype(np.uint64)
    shift = rng.integers(0, 2**32, size=(nc, 1, 2), dtype=np.uint64)
    return ((bits[None] ^ shift) + rng.random((nc, n_samples, 2))) / 2.0**32


def _portal_points(portal, nc, n_samples, rng, sampler="sobol"):
    """``n_samples`` points on the portal for each of ``nc`` vertices, uniform by area. ``sampler``:

    - ``"sobol"``: scrambled Sobol' points (:func:`_sobol_unit_square`), mapped affinely onto a parallelogram
      portal (a window: its edges fall on the net's box edges) and otherwise like ``"jittered"``;
    - ``"jittered"``: one point in each cell of a grid on the unit square, mapped to a face by the inverse CDF of
      the face areas along its first axis and into the face by the area-preserving ``sqrt`` map (the sampler
      before the Sobol' one);
    - ``"random"``: independent uniform points by the same map (the paper's "uniformly sampled" portal points).

    Returns points and unit face normals, ``(nc, n_samples, 3)`` each. (Independent uniform points left the
    sun's texel of a sunlit floor vertex with about ten samples at 1024: a 30% noise.)"""
    from prtlab.geometry._sampling import _stratified_unit_square

    if sampler not in PORTAL_SAMPLERS:
        raise ValueError(f"sampler must be one of {PORTAL_SAMPLERS}, got {sampler!r}")
    if sampler == "sobol":
        u = _sobol_unit_square(n_samples, nc, rng)
        quad = _parallelogram(portal)
        if quad is not None:
            corner, e1, e2 = quad
            points = corner + u[..., 0:1] * e1 + u[..., 1:2] * e2
            return points, np.broadcast_to(portal.face_normals[0], points.shape)
    elif sampler == "jittered":
        u = _stratified_unit_square(n_samples, rng, (nc,))
    else:
        u = rng.random((nc, n_samples, 2))
    v = np.asarray(portal.vertices, dtype=np.float64)
    f = np.asarray(portal.faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    cdf = np.concatenate([[0.0], np.cumsum(double_area) / double_area.sum()])
    face = np.clip(np.searchsorted(cdf, u[..., 0], side="right") - 1, 0, len(f) - 1)
    r1 = np.clip((u[..., 0] - cdf[face]) / np.maximum(cdf[face + 1] - cdf[face], 1e-300), 0.0, 1.0)
    s = np.sqrt(r1)[..., None]
    r2 = u[..., 1:2]
    points = (1.0 - s) * a[face] + s * (1.0 - r2) * b[face] + s * r2 * c[face]
    return points, (cross / double_area[:, None])[face]


def _visible_portal_samples(caster, portal, x, n, n_samples, rng, sampler):
    """Sample ``n_samples`` portal points per vertex and keep the unoccluded pairs.

    A pair (vertex ``v``, portal point ``p``) counts when ``p`` is in front of the
    vertex and the vertex in front of the portal, nothing blocks the segment, and
    nothing blocks the ray from ``p`` on toward the shell (backward occlusion).

    Returns
    -------
    vi : (E,) int      vertex index within the batch
    dl : (E, 3) float  unit direction from the vertex to the portal point
    cos_v, cos_p, dist : (E,) float   cosines at vertex and portal, and distance
    points : (E, 3) float   the portal point
    """
    nc = len(x)
    p, n_p = _portal_points(portal, nc, n_samples, rng, sampler)
    d = p - x[:, None, :]
    dist = np.linalg.norm(d, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / dist[..., None]
    cos_v = np.einsum("vsk,vk->vs", d, n)
    cos_p = -np.einsum("vsk,vsk->vs", d, n_p)
    vi, si = np.nonzero((cos_v > 0) & (cos_p > 0) & (dist > 0))
    dl = d[vi, si]
    blocked = caster.occluded(x[vi], dl, dist[vi, si] - caster.epsilon, normals=n[vi])
    blocked |= caster.occluded(p[vi, si], dl, normals=n_p[vi, si])  # backward occlusion, on toward the shell
    keep = ~blocked
    vi, si = vi[keep], si[keep]
    return vi, dl[keep], cos_v[vi, si], cos_p[vi, si], dist[vi, si], p[vi, si]


def direct_transfer(
    caster: RayCaster,
    points,
    normals,
    portal: Portal,
    n_samples: int,
    res: int,
    rng: np.random.Generator,
    chunk: int = 256,
    sampler: str = "sobol",
    strips: int = 0,
    combine=None,
) -> np.ndarray:
    """Per-vertex direct transfer cubemaps ``T`` (Section 4.1.2, steps 1-3).

    Parameters
    ----------
    caster : RayCaster
        The interior geometry (portals left out: they are openings).
    points, normals : (V, 3) float
        Vertex positions and unit normals of the shaded side.
    portal : Portal
    n_samples : int
        Portal sample points per vertex (the paper: 4096).
    res : int
        Cubemap face resolution (the paper: 32).
    rng : numpy.random.Generator
    chunk : int
        Vertices per batch of rays.
    sampler : {"sobol", "jittered", "random"}
        How the portal points are drawn (:func:`_portal_points`); all are uniform by area, so ``T`` is
        unbiased with each.
    combine : scipy.sparse matrix (R, V), optional
        Return ``combine @ T`` (``(R, 6, res, res)``) instead, summed from the samples without the points' dense
        cubemaps (the hat averages of ``indirect="surface"``: many points, each in few rows); the same random
        stream, the same sums in another order.
    strips : int
        0: one transfer per vertex. ``K > 0`` (a parallelogram portal): one per strip of the portal
        (:func:`strip_frame`), each sample counted in the strip it falls in, so the strips' transfers sum to the
        whole portal's from the same samples; each is unbiased for its strip. With ``"sobol"`` and ``K`` and
        ``n_samples`` powers of two each strip holds exactly ``n_samples / K`` points (a net's elementary
        intervals).

    Returns
    -------
    T : (V, 6, res, res) float64, or (V, K, 6, res, res) with ``strips``
        ``T_k = (1/pi) int_{Omega_k} V max(0, n . omega) d omega`` (module docstring);
        the direct radiance of a Lambertian vertex is ``albedo * sum_k T_k L_k``.
    """
    points, normals = _check_points(points, normals)
    if not isinstance(caster, RayCaster):
        raise TypeError(f"caster must be a prtlab.geometry.RayCaster, got {type(caster).__name__}")
    check_int(n_samples, "n_samples", 1)
    if sampler not in PORTAL_SAMPLERS:
        raise ValueError(f"sampler must be one of {PORTAL_SAMPLERS}, got {sampler!r}")
    check_int(strips, "strips", 0)
    frame = strip_frame(portal) if strips else None
    n_strips = max(strips, 1)
    n_texels = 6 * res * res
    n_vertices = len(points)
    out = np.zeros((n_vertices, n_strips * n_texels)) if combine is None else None
    columns = None if combine is None else combine.T.tocsr()  # (V, R): the rows each point adds to
    flats, weights = [], []
    for start in range(0, n_vertices, chunk):
        x = points[start : start + chunk]
        n = normals[start : start + chunk]
        nc = len(x)
        vi, dl, cos_v, cos_p, dist, p = _visible_portal_samples(caster, portal, x, n, n_samples, rng, sampler)
        weight = cos_v * cos_p * portal.area / (np.pi * n_samples * dist**2)
        face, _, _, i, j = direction_to_cubemap(dl, res)
        texel = (_strip_of(p, strips, frame) * n_texels if strips else 0) + face * res * res + i * res + j
        if columns is None:
            flat = vi * (n_strips * n_texels) + texel
            out[start : start + nc] = np.bincount(flat, weights=weight, minlength=nc * n_strips * n_texels).reshape(
                nc, -1)
            continue
        first, count = columns.indptr[start + vi], np.diff(columns.indptr)[start + vi]
        sample = np.repeat(np.arange(len(vi)), count)
        entry = first[sample] + np.arange(len(sample)) - np.repeat(np.cumsum(count) - count, count)
        flats.append(columns.indices[entry].astype(np.int64) * (n_strips * n_texels) + texel[sample])
        weights.append(weight[sample] * columns.data[entry])
    if columns is not None:
        n_vertices = combine.shape[0]
        flat = np.concatenate(flats) if flats else np.zeros(0, np.int64)
        out = np.bincount(flat, weights=np.concatenate(weights) if weights else np.zeros(0),
                          minlength=n_vertices * n_strips * n_texels).reshape(n_vertices, -1)
    shape = (n_vertices, n_strips, 6, res, res) if strips else (n_vertices, 6, res, res)
    return out.reshape(shape)


def glossy_direct_transfer(caster: RayCaster, points, normals, portal: Portal, view_dirs, exponent: float,
                           n_samples: int, res: int, rng: np.random.Generator, chunk: int = 8,
                           sampler: str = "sobol") -> np.ndarray:
    """Specular direct transfer of Phong vertices, one cubemap per discretised view direction (Section 4.1.2).

    Parameters
    ----------
    caster, points, normals, portal, n_samples, res, rng, sampler
        As in :func:`direct_transfer`.
    view_dirs : (J, 3) float
        The discretised outgoing directions ``w_o`` (toward the viewer), e.g. the
        texel centres of a small cubemap (:func:`prtlab.geometry.cubemap_directions`).
    exponent : float
        Phong exponent ``e``.

    Returns
    -------
    S : (V, J, 6, res, res) float64
        ``S_jk = int_{Omega_k} (e + 2) / (2 pi) max(0, r(w) . w_oj)^e V max(0, n . w) dw`` with
        ``r(w) = 2 (n . w) n - w``; the specular radiance toward ``w_oj`` is ``ks sum_k S_jk L_k`` (the
        Lambertian part ``kd`` comes from :func:`direct_transfer`). At run time the view direction picks
        the nearest ``w_oj``.
    """
    points, normals = _check_points(points, normals)
    view_dirs = np.asarray(view_dirs, dtype=np.float64)
    if view_dirs.ndim != 2 or view_dirs.shape[1] != 3 or not np.all(np.isfinite(view_dirs)):
        raise ValueError(f"view_dirs must be a finite (J, 3) array of directions, got shape {view_dirs.shape}")
    view_dirs = view_dirs / np.linalg.norm(view_dirs, axis=1, keepdims=True)
    if not (np.isfinite(exponent) and exponent >= 0):
        raise ValueError(f"exponent must be a finite number >= 0, got {exponent!r}")
    check_int(n_samples, "n_samples", 1)
    if sampler not in PORTAL_SAMPLERS:
        raise ValueError(f"sampler must be one of {PORTAL_SAMPLERS}, got {sampler!r}")
    n_texels = 6 * res * res
    n_views = len(view_dirs)
    out = np.zeros((len(points), n_views * n_texels))
    norm = (exponent + 2.0) / (2.0 * np.pi)
    for start in range(0, len(points), chunk):
        x = points[start : start + chunk]
        n = normals[start : start + chunk]
        nc = len(x)
        vi, dl, cv, cos_p, dist, _ = _visible_portal_samples(caster, portal, x, n, n_samples, rng, sampler)
        weight = cv * cos_p * portal.area / (n_samples * dist**2)  # cos dw / pdf, no 1/pi
        mirror = 2.0 * cv[:, None] * n[vi] - dl
        lobe = norm * np.maximum(mirror @ view_dirs.T, 0.0) ** exponent  # (E, J)
        face, _, _, i, j = direction_to_cubemap(dl, res)
        texel = face * res * res + i * res + j
        flat = (vi[:, None] * n_views + np.arange(n_views)[None, :]) * n_texels + texel[:, None]
        out[start : start + nc] = np.bincount(flat.ravel(), weights=(weight[:, None] * lobe).ravel(),
                                              minlength=nc * n_views * n_texels).reshape(nc, -1)
    return out.reshape(len(points), n_views, 6, res, res)


def view_interpolation(view_dirs, view_res: int) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear weights over the discretised outgoing directions of glossy vertices (Section 4.1.2).

    The outgoing directions ``w_oj`` are the texel centres of a ``view_res`` cubemap
    (:func:`prtlab.geometry.cubemap_directions`, ``J = 6 view_res^2``). A direction
    picks the four texel centres around it on its face (bilinear in the face
    coordinates, clamped at the face's border texels, so near an edge it falls
    back to the nearest texel along that axis).

    Parameters
    ----------
    view_dirs : (N, 3) float
        Directions toward the viewer.
    view_res : int

    Returns
    -------
    index : (N, 4) int64
        Flat texel indices ``face * view_res^2 + i * view_res + j``.
    weight : (N, 4) float64
        Non-negative, summing to 1.

    Notes
    -----
    Error bound used by the tests: the Phong lobe ``g(r . w_o)`` moves by at most
    ``Lip(g) * angle(w_o, w_oj)`` when ``w_o`` moves to ``w_oj`` (``Lip(g) = max |dg /
    d alpha|``, :func:`phong_lipschitz`), so the interpolated specular radiance is off
    by at most ``ks Lip(g) sum_q weight_q angle_q * int L V cos dw``.
    """
    view_dirs = np.asarray(view_dirs, dtype=np.float64)
    if view_dirs.ndim != 2 or view_dirs.shape[1] != 3 or not np.all(np.isfinite(view_dirs)):
        raise ValueError(f"view_dirs must be a finite (N, 3) array of directions, got shape {view_dirs.shape}")
    r = int(view_res)
    face, s, t = direction_to_cubemap(view_dirs)
    fx = np.clip(s * r - 0.5, 0.0, r - 1.0)
    fy = np.clip(t * r - 0.5, 0.0, r - 1.0)
    j0 = np.minimum(np.floor(fx).astype(np.int64), max(r - 2, 0))
    i0 = np.minimum(np.floor(fy).astype(np.int64), max(r - 2, 0))
    ax, ay = fx - j0, fy - i0
    j1 = np.minimum(j0 + 1, r - 1)
    i1 = np.minimum(i0 + 1, r - 1)
    base = face * r * r
    index = np.stack([base + i0 * r + j0, base + i0 * r + j1, base + i1 * r + j0, base + i1 * r + j1], axis=-1)
    weight = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], axis=-1)
    return index.astype(np.int64), weight


def phong_lipschitz(exponent: float) -> float:
    """``max_alpha |d/d alpha (e + 2) / (2 pi) cos^e alpha|`` (radians), the lobe's Lipschitz constant.

    The maximum of ``cos^(e-1) sin`` is at ``tan^2 alpha = 1 / (e - 1)`` (``e > 1``); ``e = 1`` gives
    ``3 / (2 pi)`` at the horizon, and ``0 < e < 1`` an unbounded slope there (``inf``); ``e = 0`` is constant.
    """
    e = float(exponent)
    if e == 0.0:
        return 0.0
    if e < 1.0:
        return float("inf")
    if e == 1.0:
        return 3.0 / (2.0 * np.pi)
    a = np.arctan(1.0 / np.sqrt(e - 1.0))
    return (e + 2.0) / (2.0 * np.pi) * e * np.cos(a) ** (e - 1.0) * np.sin(a)
