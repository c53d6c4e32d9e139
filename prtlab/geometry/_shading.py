"""Where a vertex is shaded: a point a hair inside the vertex's own faces.

A vertex that lies on *another* surface (a floor vertex at a room corner lies
in the wall's plane; the bottom vertices of an object resting on a floor lie
in the floor) has no well-defined radiance: rays leaving it start exactly in
that other surface, and whether they pass is decided by rounding. Let alone,
such vertices leak light through the corner (rays toward the wall start on
it and miss it) or are wrongly black.

Every method and both references therefore shade a vertex at

.. math::

    p' = p + \\alpha \\, \\Pi_n (\\bar c - p),

with :math:`\\bar c` the area-weighted mean of the centroids of the triangles
around the vertex, :math:`\\Pi_n` the projection onto the tangent plane of the
vertex normal and :math:`\\alpha` = :data:`SHADING_POINT_FRACTION`. For a
vertex inside a regular patch of surface, :math:`\\bar c \\approx p` and the
point does not move; for a vertex on a mesh boundary or an edge where the
mesh meets another surface, it moves about ``alpha / 3`` of an edge length
into its own faces, away from the other surface. The move stays in the
tangent plane, so a vertex of a closed mesh never moves inside the mesh.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SHADING_POINT_FRACTION", "shading_points"]

#: How far toward the mean centroid of its faces a vertex is shaded (fraction).
SHADING_POINT_FRACTION = 1e-2


def shading_points(vertices, faces, normals, fraction: float = SHADING_POINT_FRACTION) -> np.ndarray:
    """The points at which per-vertex radiance is estimated.

    Parameters
    ----------
    vertices : (V, 3) float
        World-space vertex positions.
    faces : (F, 3) int
        Triangles.
    normals : (V, 3) float
        Unit vertex normals.
    fraction : float
        ``alpha`` of the module docstring, in [0, 1/3).

    Returns
    -------
    points : (V, 3) float64
        Vertex positions moved in their tangent planes toward their faces;
        a vertex used by no face stays where it is.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    normals = np.asarray(normals, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or normals.shape != vertices.shape:
        raise ValueError(
            f"vertices and normals must both be (V, 3) arrays, got {vertices.shape} and {normals.shape}"
        )
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must be an (F, 3) integer array, got shape {faces.shape}")
    if not 0.0 <= fraction < 1.0 / 3.0:
        raise ValueError(f"fraction must be in [0, 1/3), got {fraction}")
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    centroid = tri.mean(axis=1)
    n = len(vertices)
    corners = faces.ravel()  # each face once per corner
    weight = np.bincount(corners, weights=np.repeat(area, 3), minlength=n)
    weighted = np.stack(
        [np.bincount(corners, weights=np.repeat(area * centroid[:, k], 3), minlength=n) for k in range(3)], axis=1
    )
    used = weight > 0.0
    delta = np.zeros_like(vertices)
    delta[used] = weighted[used] / weight[used, None] - vertices[used]
    delta -= np.sum(delta * normals, axis=1, keepdims=True) * normals
    return vertices + fraction * delta
