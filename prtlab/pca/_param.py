"""(u, v) parameterisations of a surface for the journal paper's basis comparison.

The comparison bases (SH, Haar, Fourier cosine) are functions of ``(u, v) in
[0, 1]^2``; the surface intensity ``L(x)`` becomes ``L(u, v)`` through a
parameterisation ``x(u, v)`` (Iwasaki et al. 2007, journal version, Sec. 5.1).

Meshes
    ``xatlas`` (the parameterisation library of Blender and Godot) cuts the
    mesh into charts, flattens each with least-squares conformal maps and packs
    them into the unit square. The paper uses a geometry image (Gu, Gortler,
    Hoppe 2002: one cut, one disk mapped to the whole square) with a
    stretch-minimising parameterisation; xatlas gives several charts (about
    20 for the bunny) and leaves part of the square empty. A vertex on a chart
    seam appears once per chart, with one ``(u, v)`` each
    (:attr:`SurfaceParam.vertex` maps them back).

Planes
    A plane uses its own coordinates: the vertex positions in the plane's two
    tangent axes, scaled to ``[0, 1]^2`` (the floor of the paper).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prtlab._validate import check_int

__all__ = ["SurfaceParam", "surface_uv"]


@dataclass(frozen=True, eq=False)
class SurfaceParam:
    """A (u, v) parameterisation of a mesh, possibly with seams.

    Attributes
    ----------
    uv : (n_param, 2) float64
        Parameter coordinates in ``[0, 1]^2`` of each parameterisation vertex.
    vertex : (n_param,) int
        Original mesh vertex of each parameterisation vertex (seam vertices repeat).
    faces : (n_faces, 3) int
        Faces over the parameterisation vertices (same order as the mesh's faces).
    n_vertices : int
        Vertices of the original mesh.
    n_charts : int
        Charts of the atlas (1 for a plane).
    """

    uv: np.ndarray
    vertex: np.ndarray
    faces: np.ndarray
    n_vertices: int
    n_charts: int

    def to_param(self, values) -> np.ndarray:
        """Per-vertex values ``(..., n_vertices[, C])`` -> per-parameterisation-vertex ``(..., n_param[, C])``.

        The point axis is the last axis if its length is ``n_vertices``, else the second to last.
        """
        v = np.asarray(values, dtype=np.float64)
        if v.ndim >= 1 and v.shape[-1] == self.n_vertices:
            return v[..., self.vertex]
        if v.ndim >= 2 and v.shape[-2] == self.n_vertices:
            return v[..., self.vertex, :]
        raise ValueError(f"values must have shape (..., {self.n_vertices}[, C]), got {v.shape}")

    def to_vertices(self, values, colour: bool = False) -> np.ndarray:
        """Per-parameterisation-vertex values -> per-vertex, averaging the copies of seam vertices."""
        v = np.asarray(values, dtype=np.float64)
        if colour:
            v = np.moveaxis(v, -1, 0)
        counts = np.bincount(self.vertex, minlength=self.n_vertices).astype(np.float64)
        flat = v.reshape(-1, v.shape[-1])
        out = np.zeros((flat.shape[0], self.n_vertices))
        for k in range(flat.shape[0]):
            out[k] = np.bincount(self.vertex, weights=flat[k], minlength=self.n_vertices)
        out = (out / np.maximum(counts, 1.0)).reshape(v.shape[:-1] + (self.n_vertices,))
        return np.moveaxis(out, 0, -1) if colour else out


def _plane_uv(mesh) -> SurfaceParam:
    v = np.asarray(mesh.vertices, dtype=np.float64)
    normal = np.asarray(mesh.vertex_normals, dtype=np.float64).mean(axis=0)
    if not np.linalg.norm(normal) > 0:
        raise ValueError("plane=True needs a mesh whose vertex normals agree on a side")
    normal /= np.linalg.norm(normal)
    # the plane's own axes: the two world axes closest to its tangent plane
    axes = np.argsort(np.abs(normal))[:2]
    axes.sort()
    coords = v[:, axes]
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    uv = (coords - lo) / span
    return SurfaceParam(uv, np.arange(len(v)), np.asarray(mesh.faces, dtype=np.int64), len(v), 1)


def surface_uv(mesh, *, plane: bool = False, resolution: int = 512) -> SurfaceParam:
    """A (u, v) parameterisation of ``mesh`` (xatlas atlas, or a plane's own coordinates).

    Parameters
    ----------
    mesh : trimesh.Trimesh or SceneObject
        Object-space mesh.
    plane : bool
        Use the plane's own coordinates (the two world axes spanning it, scaled to ``[0, 1]``).
    resolution : int
        Packing resolution of the xatlas atlas (texels per side); it sets the
        gutter between charts, not the accuracy of the map.

    Returns
    -------
    SurfaceParam
        The charts' coordinates in ``[0, 1]^2``; seam vertices repeat.

    Examples
    --------
    >>> from prtlab.geometry import builtin_mesh
    >>> p = surface_uv(builtin_mesh("plane", resolution=[2, 2]), plane=True)
    >>> float(p.uv.min()), float(p.uv.max()), p.n_charts
    (0.0, 1.0, 1)
    """
    mesh = getattr(mesh, "mesh", mesh)
    if not (hasattr(mesh, "vertices") and hasattr(mesh, "faces")):
        raise TypeError(f"mesh must be a trimesh.Trimesh or a SceneObject, got {type(mesh).__name__}")
    if len(mesh.faces) == 0:
        raise ValueError("mesh has no faces; a parameterisation needs a surface")
    if plane:
        return _plane_uv(mesh)
    check_int(resolution, "resolution", 16)
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.asarray(mesh.vertices, dtype=np.float32), np.asarray(mesh.faces, dtype=np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = 1
    atlas.generate(xatlas.ChartOptions(), pack)
    vmapping, indices, uvs = atlas[0]
    return SurfaceParam(
        np.clip(np.asarray(uvs, dtype=np.float64), 0.0, 1.0),
        np.asarray(vmapping, dtype=np.int64),
        np.asarray(indices, dtype=np.int64),
        len(mesh.vertices),
        int(atlas.chart_count),
    )
