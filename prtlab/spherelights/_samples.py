"""Surface sample points and surface-albedo SH of spherical lights (Guerrero et al. 2008, Sec. 4.2).

Segments: a surface point ``p`` belongs to the segment ``P_S`` of the light
``S`` minimising ``d(p, S) = |p - x_S| / r_S`` (Eq. 2).

Sample points: from the centre of every light, one ray per direction
``w_j`` of the geodesic set (92 in the paper), all hits along it:

1. back-face hits (``n . w_j > 0``: the ray leaves the object) inside
   ``P_S`` exist: the farthest one is the sample;
2. hits exist but none is a back-face hit inside ``P_S``: no sample (the
   light emits nothing towards ``w_j``: the occlusion by the light whose
   segment was hit there is precomputed);
3. no hit at all (the centre lies outside the object): a ray along
   ``-w_j``; its closest front-face hit (``n . (-w_j) < 0``) inside ``P_S``
   is the sample, else no sample.

Albedo: per light, a cubemap seen from its centre whose texels follow the
same rules (the albedo of the surface the rule picks, 0 where it picks
none), projected to SH. Materials in prtlab scenes have one albedo per
object, so the cubemap is that albedo times the coverage of the segment;
this is the rendering of Sec. 4.2 without textures.
"""

from __future__ import annotations

import numpy as np
import trimesh

from prtlab import sh
from prtlab.geometry import cubemap_directions, cubemap_solid_angles

__all__ = ["segment_of", "surface_samples", "surface_albedo_sh", "segment_coverage", "coverage_weights"]


def segment_of(points, centres, radii) -> np.ndarray:
    """Index of the light whose segment holds each point (Eq. 2): ``argmin_i |p - x_i| / r_i``; ``(N,)``."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    c = np.asarray(centres, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    if p.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    return np.argmin(np.linalg.norm(p[:, None, :] - c[None], axis=2) / r[None], axis=1)


def _pick(mesh, centres, radii, light, dirs):
    """Apply the three rules for light ``light`` along ``dirs (m, 3)``: (points, face ids, valid)."""
    m = dirs.shape[0]
    origin = np.repeat(centres[light][None], m, axis=0)
    points = np.zeros((m, 3))
    faces = np.full(m, -1, dtype=np.int64)
    valid = np.zeros(m, dtype=bool)
    any_hit = np.zeros(m, dtype=bool)
    best_t = np.full(m, -np.inf)
    loc, ray, tri = mesh.ray.intersects_location(origin, dirs, multiple_hits=True)
    if len(ray):
        any_hit[ray] = True
        back = np.einsum("ij,ij->i", mesh.face_normals[tri], dirs[ray]) > 0
        inside = segment_of(loc, centres, radii) == light
        t = np.einsum("ij,ij->i", loc - origin[ray], dirs[ray])
        for h in np.nonzero(back & inside)[0]:
            k = ray[h]
            if t[h] > best_t[k]:
                best_t[k], points[k], faces[k], valid[k] = t[h], loc[h], tri[h], True
    miss = np.nonzero(~any_hit)[0]
    if miss.size:
        loc, ray, tri = mesh.ray.intersects_location(origin[miss], -dirs[miss], multiple_hits=True)
        if len(ray):
            front = np.einsum("ij,ij->i", mesh.face_normals[tri], -dirs[miss][ray]) < 0
            inside = segment_of(loc, centres, radii) == light
            t = np.einsum("ij,ij->i", loc - origin[miss][ray], -dirs[miss][ray])
            best = np.full(miss.size, np.inf)
            for h in np.nonzero(front & inside)[0]:
                q = ray[h]
                if t[h] < best[q]:
                    k = miss[q]
                    best[q], points[k], faces[k], valid[k] = t[h], loc[h], tri[h], True
    return points, faces, valid


def _as_mesh(mesh) -> trimesh.Trimesh:
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    return mesh


def surface_samples(mesh, centres, radii, directions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface sample points of every light along ``directions`` (the three rules of Sec. 4.2).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The closed object, in the same frame as the spheres.
    centres : (S, 3) float
    radii : (S,) float
    directions : (m, 3) float
        Unit sample directions (``geodesic_directions(92)``).

    Returns
    -------
    points : (S, m, 3) float64
    normals : (S, m, 3) float64
        Interpolated vertex normals at the samples (unit).
    valid : (S, m) bool
        False where the rules give no sample (the light emits nothing that way).

    References
    ----------
    Guerrero et al. 2008, Sec. 4.2 and Fig. 3.
    """
    mesh = _as_mesh(mesh)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    pts = np.zeros((c.shape[0], d.shape[0], 3))
    nrm = np.zeros((c.shape[0], d.shape[0], 3))
    valid = np.zeros((c.shape[0], d.shape[0]), dtype=bool)
    vn = np.asarray(mesh.vertex_normals)
    for i in range(c.shape[0]):
        p, f, v = _pick(mesh, c, r, i, d)
        pts[i], valid[i] = p, v
        if v.any():
            tri = mesh.triangles[f[v]]
            bary = trimesh.triangles.points_to_barycentric(tri, p[v])
            n = np.einsum("ij,ijk->ik", bary, vn[mesh.faces[f[v]]])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            nrm[i, v] = n
    return pts, nrm, valid


def surface_albedo_sh(mesh, centres, radii, albedo, order: int, resolution: int = 16) -> np.ndarray:
    """Surface-albedo SH vector ``c_S`` of every light from a cubemap seen from its centre (Sec. 4.2).

    Parameters
    ----------
    mesh : trimesh.Trimesh
    centres : (S, 3) float
    radii : (S,) float
    albedo : (3,) float
        The object's diffuse albedo.
    order : int
    resolution : int
        Cubemap face resolution.

    Returns
    -------
    c : (S, order**2, 3) float64
        ``int A_S(w) y(w) dw`` with ``A_S(w)`` the albedo of the surface the
        sampling rules pick along ``w`` (0 where none).

    References
    ----------
    Guerrero et al. 2008, Sec. 4.2 (cubemap of the segment), Eq. 11.
    """
    mesh = _as_mesh(mesh)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    a = np.asarray(albedo, dtype=np.float64).reshape(3)
    dirs = cubemap_directions(resolution).reshape(-1, 3)
    w = cubemap_solid_angles(resolution).reshape(-1)
    y = sh.basis(dirs, order)
    out = np.zeros((c.shape[0], order * order, 3))
    for i in range(c.shape[0]):
        _, _, v = _pick(mesh, c, r, i, dirs)
        out[i] = np.outer((w * v) @ y, a)
    return out


def _disc_points(n: int) -> np.ndarray:
    """``(n, 2)`` points of equal area over the unit disc (a sunflower spiral)."""
    k = np.arange(n) + 0.5
    r = np.sqrt(k / n)
    a = k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def segment_coverage(mesh, centres, radii, directions, n_rays: int = 256) -> np.ndarray:
    """Projected coverage of every light's segment: the part of its disc, seen from afar, that its segment fills.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The closed object, in the same frame as the spheres.
    centres : (S, 3) float
    radii : (S,) float
    directions : (m, 3) float
        Unit directions (the lights' sample directions).
    n_rays : int
        Parallel rays per light and direction, over the light's disc (equal areas).

    Returns
    -------
    coverage : (S, m) float64
        The fraction of the rays along ``-w_j`` through the disc of light ``S`` (radius ``r_S`` about ``x_S``,
        normal to ``w_j``) whose first hit on the mesh lies in the segment ``P_S`` (Eq. 2): the segment's
        projected area toward ``w_j`` over ``pi r_S^2``. In ``[0, 1]``; 0 where the segment is hidden or absent.

    Notes
    -----
    A light of the paper emits its segment's radiance over its whole sphere (Sec. 4.2), so seen from afar it
    sends ``pi r^2`` times that radiance where the segment sends ``pi r^2`` times its coverage: a set of
    spheres that bounds a thin object (a bunny's ears, with the outside volume of the fit) is far too bright as a
    light. :func:`coverage_weights` turns this into weights of the samples' radiance.
    """
    from prtlab.geometry import RayCaster

    mesh = _as_mesh(mesh)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    out = np.zeros((c.shape[0], d.shape[0]))
    if c.shape[0] == 0 or d.shape[0] == 0:
        return out
    caster = RayCaster([mesh])
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    far = 2.0 * float(np.linalg.norm(verts.max(axis=0) - verts.min(axis=0))) + 2.0 * float(r.max())
    disc = _disc_points(int(n_rays))
    for j, w in enumerate(d):
        a = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t = np.cross(w, a)
        t /= np.linalg.norm(t)
        b = np.cross(w, t)
        # every light's rays at once: (S, n_rays) origins far out along w, toward -w
        origins = c[:, None] + far * w + r[:, None, None] * (disc[None, :, :1] * t + disc[None, :, 1:] * b)
        hits = caster.closest_hit(origins.reshape(-1, 3), np.broadcast_to(-w, (origins.shape[0] * len(disc), 3)))
        mine = np.zeros(len(hits.hit), dtype=bool)
        owner = np.repeat(np.arange(c.shape[0]), len(disc))
        mine[hits.hit] = segment_of(hits.point[hits.hit], c, r) == owner[hits.hit]
        out[:, j] = mine.reshape(c.shape[0], len(disc)).mean(axis=1)
    return out


def coverage_weights(coverage, sample_valid, directions) -> np.ndarray:
    """Weights of the lights' sample radiance that give each light its segment's projected coverage.

    Parameters
    ----------
    coverage : (S, m) float
        :func:`segment_coverage` along the sample directions.
    sample_valid : (S, m) bool
        The samples (:func:`surface_samples`).
    directions : (m, 3) float
        The unit sample directions.

    Returns
    -------
    weight : (S, m) float64
        ``c_j / v_j`` where ``v_j = sum_i valid_i max(0, w_i . w_j) / sum_i max(0, w_i . w_j)`` is the part of
        the hemisphere about ``w_j`` (cosine-weighted) where the light emits; 0 where ``v_j = 0``. A light's
        emission (zero where it has no sample) weighted so is seen from afar along ``w`` with about ``c(w)`` of
        its disc lit: for a smooth radiance ``int_{u.w>0} L(u) valid(u) c(u) / v(u) (u.w) du ~ pi L c(w)``.
    """
    cov = np.asarray(coverage, dtype=np.float64)
    valid = np.asarray(sample_valid, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    cosw = np.maximum(d @ d.T, 0.0)
    v = valid @ cosw / cosw.sum(axis=0)
    return np.where(v > 0, cov / np.where(v > 0, v, 1.0), 0.0)
