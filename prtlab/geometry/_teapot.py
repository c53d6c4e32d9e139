"""Newell's Utah teapot: Bezier patch data and its tessellation.

The 306-number patch set of Martin Newell (1975) is in the public domain. The
tables (``prtlab/data/tables/teapot_*.csv``) are the 32-patch version with Frank Crow's bottom, in Jim
Blinn's proportions (z divided by 1.3), as distributed in three.js's
``examples/jsm/geometries/TeapotGeometry.js`` (MIT licence, three.js 0.160.0;
``tools/convert_assets.py --check-teapot`` verifies that they match it).
Coordinates are the original z-up ones; the tessellation turns them to +Y up.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from prtlab.data import path as data_path

__all__: list[str] = []

# prtlab/data/tables: teapot_patches.csv has a row per patch (4 rim, 8 body, 4 handle, 4 spout,
# 8 lid, 4 bottom), a 4x4 grid of control-point indices, row-major: entry r*4 + c holds P[r][c], and
# the patch is S(s, t) = sum_{r,c} P[r][c] B_r(s) B_c(t); teapot_vertices.csv the control points x, y, z.
_PATCHES = np.loadtxt(data_path("tables", "teapot_patches.csv"), delimiter=",", dtype=np.int64)
_CONTROL_POINTS = np.loadtxt(data_path("tables", "teapot_vertices.csv"), delimiter=",", dtype=np.float64)

#: Patch ranges in ``_PATCHES``.
_LID = slice(20, 28)
_BOTTOM = slice(28, 32)

#: three.js's empirical enlargement of the lid in x and y ("fitLid") that
#: closes the visible gap between lid and rim.
_LID_FIT_SCALE = 1.077


def _bernstein(t: np.ndarray) -> np.ndarray:
    """(n,) parameters -> (n, 4) cubic Bernstein polynomials."""
    u = 1.0 - t
    return np.stack([u * u * u, 3.0 * u * u * t, 3.0 * u * t * t, t * t * t], axis=1)


def teapot_control_points(bottom: bool = True, fit_lid: bool = True) -> np.ndarray:
    """(n_patches, 4, 4, 3) control points, z-up, in the data's own units (height 3.15)."""
    points = _CONTROL_POINTS[_PATCHES].reshape(-1, 4, 4, 3).copy()
    if fit_lid:
        points[_LID, :, :, :2] *= _LID_FIT_SCALE
    if not bottom:
        points = points[: _BOTTOM.start]
    return points


def _weld(vertices: np.ndarray, faces: np.ndarray, tolerance: float):
    """Merge vertices closer than ``tolerance``; keep first occurrences in order."""
    n = len(vertices)
    pairs = cKDTree(vertices).query_pairs(tolerance, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    first = np.full(label.max() + 1, n)
    np.minimum.at(first, label, np.arange(n))  # the earliest vertex represents its group
    keep = np.zeros(n, dtype=bool)
    keep[first] = True
    new_index = np.cumsum(keep) - 1
    faces = new_index[first[label]][faces]
    degenerate = (
        (faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])
    )
    return vertices[keep], faces[~degenerate]


def tessellate_teapot(resolution: int, bottom: bool = True, fit_lid: bool = True):
    """Evaluate every patch on a ``(resolution + 1)**2`` grid and weld the seams.

    Returns
    -------
    vertices : (V, 3) float
        +Y up: the data's ``(x, y, z)`` becomes ``(x, z, -y)``; spout toward +x.
    faces : (F, 3) int
        Wound so that ``cross(b - a, c - a)`` points along ``dS/dt x dS/ds``,
        which is outward for every patch of this data set. Triangles that
        collapse at the lid and bottom cusps are removed.
    """
    points = teapot_control_points(bottom=bottom, fit_lid=fit_lid)
    n = resolution
    basis = _bernstein(np.linspace(0.0, 1.0, n + 1))
    grid = np.einsum("si,tj,pijk->pstk", basis, basis, points)  # (P, n+1, n+1, 3)
    vertices = grid.reshape(-1, 3)
    vertices = np.stack([vertices[:, 0], vertices[:, 2], -vertices[:, 1]], axis=1)

    s, t = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    v1 = (s * (n + 1) + t).ravel()
    v2 = v1 + 1
    v3 = v2 + (n + 1)
    v4 = v1 + (n + 1)
    quad = np.concatenate([np.stack([v1, v2, v3], 1), np.stack([v1, v3, v4], 1)])
    offsets = np.arange(len(points)) * (n + 1) ** 2
    faces = (quad[None, :, :] + offsets[:, None, None]).reshape(-1, 3)
    return _weld(vertices, faces, tolerance=1e-9)
