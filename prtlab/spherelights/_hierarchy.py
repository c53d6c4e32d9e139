"""Hierarchies of spherical lights and receiver clusters with the reflection ratio (Guerrero et al. 2008, Sec. 7.3).

Hierarchy (as Ren et al. 2006, Sec. 6, build their sphere hierarchies): the
leaves are an object's fitted spheres; starting from them, each level
groups ``n_children`` nodes (the node farthest from the level's centroid
with its ``n_children - 1`` nearest ungrouped neighbours) under a parent
sphere that bounds the children's spheres, until one root is left.

A parent's light (``emission``) is the sum of its leaves' radiant
intensities: a sphere of radius ``r`` and radiance distribution ``L(w)``
seen from far away has the intensity ``pi r^2 L(w)``, so

``L_P(w) = sum_{j in leaves(P)} (r_j / r_P)^2 L_j(w)``

(the ``weights`` of :class:`LightHierarchy`). This is exact in the far
field, where a cut uses the parent, is linear (a parent's light follows its
leaves' every frame at the cost of one small matrix product) and needs no
surface samples of its own: the leaves' samples already leave out the
directions in which another segment of the object hides them (Sec. 4.2,
rule 2). Its error near the object is what the reflection ratio corrects.

Cut (once per frame per receiver cluster): from each root down, a node is
taken when it is a leaf or when its angular size from anywhere in the
cluster is below the user threshold,
``r_P / (|c_P - x_C| - R_C) < threshold`` (``x_C`` the cluster centre,
``R_C`` the cluster radius), else its children are visited. Threshold 0
selects the leaves everywhere (the flat pipeline).

Reflection ratio (Eqs. 25-26): at the cluster centre ``x_C`` (the cluster's
medoid receiver, so the centre has a normal), per node ``P`` of the cut and
colour channel,

``t_P = sum_{j in leaves(P)} L~_j V~_j (x_C) / (L~_P V~_P (x_C))``

where the numerator is evaluated with the leaves (the flat pipeline's
per-light values) and the denominator with the cut. All receivers of the
cluster scale the node's diffuse reflection by ``t_P`` (Eq. 26), which the
second pass does exactly by scaling the node's emission (the indirect term
is linear in it). The ratio is applied to every node of the cut, leaves
included: a leaf in a cut is blocked by coarser blockers than in the flat
pass, and its ratio corrects that too, so the cluster centre's indirect
equals the flat value exactly (up to the clipping of ``t`` to
``[0, max_ratio]`` where a node's value at the centre vanishes). With several
ratio points per cluster (option ``ratio_samples``) ``t`` is the
least-squares best scaling over them, steadier on curved receivers.

The per-light values at the ratio points come from :func:`per_light_indirect`
(the numpy form of the second pass keeping the lights apart); the receivers
themselves are shaded by the fused second pass, one call per coarse cluster
(its emission scaled by ``t``), or per distinct cut without the ratio.

Measured figures: ``docs/notes/spherelights.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["LightHierarchy", "bounding_sphere", "build_hierarchy", "cluster_samples", "per_light_indirect",
           "receiver_clusters", "reflection_ratio", "select_cut"]


def bounding_sphere(centres, radii, iterations: int = 200) -> tuple[np.ndarray, float]:
    """A small sphere bounding spheres (Badoiu-Clarkson iterations, then the exact bounding radius).

    Parameters
    ----------
    centres : (K, 3) float
    radii : (K,) float

    Returns
    -------
    centre : (3,) float64
    radius : float
        ``max_j |c_j - centre| + r_j``: every input sphere lies inside, whatever the iterations.
    """
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if c.shape[0] == 0:
        raise ValueError("bounding_sphere needs at least one sphere, got centres of shape (0, 3)")
    x = np.average(c, axis=0, weights=r**3 + 1e-300)
    for k in range(iterations):
        d = np.linalg.norm(c - x, axis=1)
        far = int(np.argmax(d + r))
        u = (c[far] - x) / d[far] if d[far] > 0 else np.zeros(3)
        x = x + (c[far] + r[far] * u - x) / (k + 2)
    return x, float(np.max(np.linalg.norm(c - x, axis=1) + r))


@dataclass(frozen=True)
class LightHierarchy:
    """A sphere hierarchy over one object's lights (object space).

    Attributes
    ----------
    centres : (N, 3) float64
        Node spheres: the ``S`` leaves first (the fitted lights, in order), then the parents level by level.
    radii : (N,) float64
    children : tuple of tuple of int
        Children of each node (empty for a leaf).
    weights : (N, S) float64
        ``L_P = sum_j weights[P, j] L_j``: ``(r_j / r_P)^2`` for the leaves ``j`` under ``P`` (identity on the
        leaves).
    roots : tuple of int
    """

    centres: np.ndarray
    radii: np.ndarray
    children: tuple
    weights: np.ndarray
    roots: tuple

    @property
    def n_leaves(self) -> int:
        return self.weights.shape[1]

    def leaves_under(self, node: int) -> np.ndarray:
        return np.nonzero(self.weights[node] > 0)[0]


def build_hierarchy(centres, radii, n_children: int) -> LightHierarchy:
    """Sphere hierarchy of one object's lights: parents bounding ``n_children`` children (Sec. 7.3).

    Parameters
    ----------
    centres : (S, 3) float
    radii : (S,) float
        The leaf lights (the object's fitted spheres).
    n_children : int
        Children per parent (>= 2); the last group of a level may be smaller.

    Returns
    -------
    LightHierarchy

    References
    ----------
    Guerrero et al. 2008, Sec. 7.3; Ren et al. 2006, Sec. 6 (sphere hierarchies).
    """
    if isinstance(n_children, bool) or not isinstance(n_children, (int, np.integer)) or n_children < 2:
        raise ValueError(f"n_children must be an int >= 2 (children per parent), got {n_children!r}")
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if r.shape[0] != c.shape[0] or not np.all(np.isfinite(c)) or not np.all(np.isfinite(r)) or np.any(r <= 0):
        raise ValueError(f"centres (S, 3) and radii (S,) must be finite with radii > 0, got shapes {c.shape}, "
                         f"{r.shape}")
    S = c.shape[0]
    node_c, node_r = list(c), list(r)
    children: list[tuple] = [() for _ in range(S)]
    weights = [np.eye(S)[j] for j in range(S)]
    level = list(range(S))
    while len(level) > 1:
        pos = np.array([node_c[i] for i in level])
        free = list(range(len(level)))
        nxt = []
        while free:
            centroid = pos[free].mean(axis=0)
            seed = max(free, key=lambda i: (np.linalg.norm(pos[i] - centroid), -i))
            group = sorted(free, key=lambda i: (np.linalg.norm(pos[i] - pos[seed]), i))[:n_children]
            free = [i for i in free if i not in group]
            kids = tuple(level[i] for i in group)
            if len(kids) == 1:  # a lone node goes up a level as it is
                nxt.append(kids[0])
                continue
            x, rad = bounding_sphere([node_c[k] for k in kids], [node_r[k] for k in kids])
            node_c.append(x)
            node_r.append(rad)
            children.append(kids)
            w = sum(weights[k] for k in kids)
            weights.append(np.where(w > 0, (r / rad) ** 2, 0.0))
            nxt.append(len(node_c) - 1)
        level = nxt
    return LightHierarchy(np.array(node_c).reshape(-1, 3), np.array(node_r), tuple(children), np.array(weights),
                          tuple(level))


def receiver_clusters(points, n_clusters: int, normals=None, iterations: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """Receiver clusters by k-means on positions (farthest-point start, deterministic).

    Parameters
    ----------
    points : (V, 3) float
    n_clusters : int
        At most this many clusters (fewer for fewer distinct points; empty clusters are dropped).
    normals : (V, 3) float, optional
        Unit normals: then the features are ``(p, s n)`` with ``s`` a quarter of the points' bounding-box
        diagonal, so that a cluster's receivers also face alike (the ratio taken at the centre scales a
        cosine-weighted quantity; on a curved receiver a position-only cluster mixes facing and grazing
        receivers).

    Returns
    -------
    labels : (V,) int64
        Cluster of each receiver, ``0..C-1``.
    medoid : (C,) int64
        The receiver nearest each cluster's mean: the cluster centre ``x_C`` (it has a normal).
    """
    if isinstance(n_clusters, bool) or not isinstance(n_clusters, (int, np.integer)) or n_clusters < 1:
        raise ValueError(f"n_clusters must be an int >= 1, got {n_clusters!r}")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    V = p.shape[0]
    if V == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if n.shape != p.shape:
            raise ValueError(f"normals must have the shape of points {p.shape}, got {n.shape}")
        scale = 0.25 * float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
        p = np.concatenate([p, scale * n / np.linalg.norm(n, axis=1, keepdims=True)], axis=1)
    seeds = [int(np.argmin(np.linalg.norm(p - p.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(p - p[seeds[0]], axis=1)
    while len(seeds) < min(n_clusters, V) and dist.max() > 0:
        seeds.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(p - p[seeds[-1]], axis=1))
    means = p[seeds]
    for _ in range(iterations):
        labels = np.argmin(np.linalg.norm(p[:, None] - means[None], axis=2), axis=1)
        used = np.unique(labels)
        means = np.array([p[labels == k].mean(axis=0) for k in used])
    labels = np.argmin(np.linalg.norm(p[:, None] - means[None], axis=2), axis=1)
    used, labels = np.unique(labels, return_inverse=True)
    medoid = np.array([np.flatnonzero(labels == k)[np.argmin(np.linalg.norm(p[labels == k] - p[labels == k].mean(
        axis=0), axis=1))] for k in range(len(used))], dtype=np.int64)
    return labels.astype(np.int64), medoid


def cluster_samples(points, labels, medoid, n_samples: int) -> np.ndarray:
    """(C, n_samples) receivers of each cluster where the reflection ratio is fitted: the centre (medoid) first,
    then farthest-point picks among the cluster's receivers (the centre repeated for a small cluster)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.empty((len(medoid), n_samples), dtype=np.int64)
    for k, m in enumerate(medoid):
        members = np.flatnonzero(labels == k)
        picks = [int(m)]
        dist = np.linalg.norm(p[members] - p[m], axis=1)
        while len(picks) < n_samples:
            j = int(np.argmax(dist))
            if dist[j] <= 0:
                picks.append(int(m))
                continue
            picks.append(int(members[j]))
            dist = np.minimum(dist, np.linalg.norm(p[members] - p[members[j]], axis=1))
        out[k] = picks
    return out


def select_cut(hierarchy: LightHierarchy, centres, radii, cluster_centre, cluster_radius: float,
               threshold: float) -> list[int]:
    """A hierarchy cut for one receiver cluster: nodes whose angular size is below ``threshold``.

    Parameters
    ----------
    hierarchy : LightHierarchy
    centres : (N, 3) float
    radii : (N,) float
        The hierarchy's node spheres in the frame's world space.
    cluster_centre : (3,) float
    cluster_radius : float
        Every receiver of the cluster lies within this distance of the centre.
    threshold : float
        In ``[0, 1)``; a non-leaf node is used when ``r / (|c - x_C| - R_C) < threshold`` (its sine of angular
        radius seen from the nearest point of the cluster's ball), else its children are visited. 0: leaves.

    Returns
    -------
    cut : list of int
        Node indices covering every leaf exactly once, ascending (leaves first).
    """
    c = np.asarray(centres, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    x = np.asarray(cluster_centre, dtype=np.float64)
    cut, stack = [], list(hierarchy.roots)[::-1]
    while stack:
        k = stack.pop()
        kids = hierarchy.children[k]
        gap = float(np.linalg.norm(c[k] - x)) - cluster_radius
        if not kids or (gap > 0 and r[k] < threshold * gap):
            cut.append(k)
        else:
            stack.extend(kids[::-1])
    return sorted(cut)


def reflection_ratio(leaf_values, node_values, max_ratio: float = 4.0) -> np.ndarray:
    """Reflection ratio of every node of a cut (Eq. 25), per colour channel, as the best scaling over points.

    Parameters
    ----------
    leaf_values : (..., P, K, 3) float
        ``sum_{j in leaves(P)} L~_j V~_j (x)`` per node of the cut at ``P`` points ``x`` of a cluster (the flat
        pass's per-light values).
    node_values : (..., P, K, 3) float
        ``L~_P V~_P (x)`` with the cut.
    max_ratio : float
        ``t`` is clipped to ``[0, max_ratio]``; where the node's values vanish (``sum b^2`` below ``1e-24`` of the
        largest) ``t = 1``.

    Returns
    -------
    t : (..., K, 3) float64
        ``sum_x a b / sum_x b^2`` (least squares); with one point, the centre, Eq. 25: ``a / b``.
    """
    a = np.asarray(leaf_values, dtype=np.float64)
    b = np.asarray(node_values, dtype=np.float64)
    if a.shape != b.shape or a.ndim < 3 or a.shape[-1] != 3:
        raise ValueError(f"leaf_values and node_values must have one shape (..., P, K, 3), got {a.shape} and "
                         f"{b.shape}")
    num = np.einsum("...pkc,...pkc->...kc", a, b)
    den = np.einsum("...pkc,...pkc->...kc", b, b)
    tiny = 1e-24 * max(float(den.max(initial=0.0)), float(np.einsum("...pkc,...pkc->...kc", a, a).max(initial=0.0)),
                       1e-300)
    ok = den > tiny
    t = np.where(ok, num / np.where(ok, den, 1.0), 1.0)
    return np.clip(t, 0.0, max_ratio)


def per_light_indirect(points, normals, centres, radii, sl_object, intersect, sl_rotation, emission, env_sh, *,
                       blocking: str = "object", exp_method: str = "hyb", average: str = "cosine",
                       order: int | None = None) -> np.ndarray:
    """Each light's diffuse reflection ``L~_i V~_i`` at each receiver (the terms of Eq. 14).

    The batched numpy form of :func:`prtlab.spherelights.second_pass` (its ``method="numba"`` tier) that keeps
    the lights apart: the reflection ratio (Eq. 25) needs every light's value at the cluster centres, which
    the second pass only returns summed. Parameters as :func:`second_pass`.

    Returns
    -------
    values : (B, S, 3) float64
        ``values.sum(axis=1)`` is the second pass's indirect irradiance.
    """
    from ._passes import accumulate_blockers, light_terms

    if average not in ("cosine", "paper"):
        raise ValueError(f"average must be 'cosine' or 'paper', got {average!r}")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    em = np.asarray(emission, dtype=np.float64)
    order = math.isqrt(em.shape[-2]) if order is None else int(order)  # the visibility's (the emission's may be higher)
    B, S = p.shape[0], em.shape[0]
    out = np.zeros((B, S, 3))
    if B == 0 or S == 0:
        return out
    g_sphere, g_front, theta, axis = accumulate_blockers(p, n, centres, radii, sl_object, intersect, order,
                                                         blocking=blocking)
    rows_b, rows_s, terms = light_terms(n, g_sphere, g_front, theta, axis, sl_rotation, em, order,
                                        exp_method=exp_method, average=average)
    out[rows_b, rows_s] = terms  # the terms of Eq. 14
    return out
