"""Built-in meshes, the committed assets and mesh loading.

Every builder returns a :class:`trimesh.Trimesh` in object space (+Y up),
created with ``process=False`` so that the vertex order written here is the
order the pipelines shade in (meshes are shaded at their own vertices, in
input order).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from .. import data as _data
from . import _room as _room_module

__all__ = [
    "BUILTIN_MESHES",
    "CORNELL_BOX_PARTS",
    "cornell_box_light",
    "cornell_box_objects",
    "DATA_DIR",
    "builtin_mesh",
    "load_mesh",
    "normalize_mesh",
    "subdivide",
]

#: Root of the assets shipped with prtlab (``prtlab/data/``, :func:`prtlab.data.root`).
DATA_DIR = _data.root()

# Rotation taking the +Z axis of trimesh's primitives to the +Y axis of prtlab
# (a proper rotation about +X by -90 degrees: (x, y, z) -> (x, z, -y)).
_Z_TO_Y = np.array(
    [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)


# --------------------------------------------------------------------------- validation


def _short(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters (a message never prints a huge value whole)."""
    if isinstance(value, np.ndarray) and value.size > limit:
        return f"<array of shape {value.shape}>"
    if isinstance(value, (list, tuple)) and len(value) > limit:
        return f"<{type(value).__name__} of {len(value)} items>"
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _is_real(value: Any) -> bool:
    """A real number that is not a bool (``True`` is not a number here)."""
    return not isinstance(value, (bool, np.bool_)) and isinstance(value, (int, float, np.integer, np.floating))


def _finite_float(name: str, value: Any, *, positive: bool = False, context: str = "") -> float:
    where = f"{context}: " if context else ""
    if not _is_real(value):
        raise TypeError(f"{where}{name} must be a number, got {_short(value)}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{where}{name} must be finite, got {_short(value)}")
    if positive and v <= 0.0:
        raise ValueError(f"{where}{name} must be > 0, got {_short(value)}")
    return v


def _int(name: str, value: Any, *, minimum: int, context: str = "") -> int:
    """An integer >= ``minimum``; floats are not ints (``4.0`` is refused, as ``True`` is)."""
    where = f"{context}: " if context else ""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{where}{name} must be an integer >= {minimum}, got {_short(value)}")
    if int(value) < minimum:
        raise ValueError(f"{where}{name} must be an integer >= {minimum}, got {_short(value)}")
    return int(value)


def _vector(
    name: str, value: Any, n: int, *, positive: bool = False, context: str = ""
) -> np.ndarray:
    where = f"{context}: " if context else ""
    if np.isscalar(value) or not isinstance(value, (list, tuple, np.ndarray)):
        raise ValueError(f"{where}{name} must be a list of {n} numbers, got {_short(value)}")
    if len(value) != n:
        raise ValueError(f"{where}{name} must be a list of {n} numbers, got {_short(value)}")
    if not all(_is_real(x) for x in np.asarray(value, dtype=object).reshape(-1)):
        raise TypeError(f"{where}{name} must be a list of {n} numbers, got {_short(value)}")
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (n,):
        raise ValueError(f"{where}{name} must be a list of {n} numbers, got {_short(value)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}{name} must be finite, got {_short(value)}")
    if positive and np.any(arr <= 0.0):
        raise ValueError(f"{where}{name} must be > 0 in every component, got {_short(value)}")
    return arr


def _int_pair(name: str, value: Any, *, minimum: int, context: str = "") -> tuple[int, int]:
    where = f"{context}: " if context else ""
    if np.isscalar(value):
        value = (value, value)
    if not isinstance(value, (list, tuple, np.ndarray)) or len(value) != 2:
        raise ValueError(f"{where}{name} must be one integer or a list of 2 integers, got {_short(value)}")
    a, b = (_int(name, v, minimum=minimum, context=context) for v in value)
    return a, b


#: Most vertices a generated builtin may have (a plane of 2000 x 2000 cells has 4,004,001).
MAX_BUILTIN_VERTICES = 4_100_000


def _check_size(builtin: str, what: str, n_vertices: float) -> None:
    """Refuse a builtin whose parameters would make more than :data:`MAX_BUILTIN_VERTICES` vertices."""
    if not n_vertices <= MAX_BUILTIN_VERTICES:
        raise ValueError(
            f"builtin {builtin!r}: {what} makes about {n_vertices:,.0f} vertices, above the "
            f"{MAX_BUILTIN_VERTICES:,} limit of a builtin mesh; use a coarser resolution"
        )


def _mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """A Trimesh owning fresh copies of the arrays, vertex order as given."""
    return trimesh.Trimesh(
        vertices=np.array(vertices, dtype=np.float64, order="C"),
        faces=np.array(faces, dtype=np.int64, order="C"),
        process=False,
    )


# --------------------------------------------------------------------------- primitives


def _plane(size=(1.0, 1.0), resolution=(1, 1)) -> trimesh.Trimesh:
    w, d = _vector("size", size, 2, positive=True, context="builtin 'plane'")
    nx, nz = _int_pair("resolution", resolution, minimum=1, context="builtin 'plane'")
    _check_size("plane", f"resolution [{nx}, {nz}]", (nx + 1) * (nz + 1))
    xs = np.linspace(-0.5 * w, 0.5 * w, nx + 1)
    zs = np.linspace(-0.5 * d, 0.5 * d, nz + 1)
    # vertex (i, k) at index i * (nz + 1) + k: x varies slowest
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    vertices = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)
    i, k = np.meshgrid(np.arange(nx), np.arange(nz), indexing="ij")
    a = (i * (nz + 1) + k).ravel()  # (x_i, z_k)
    b = a + 1  # (x_i, z_k+1)
    c = a + (nz + 1)  # (x_i+1, z_k)
    e = c + 1  # (x_i+1, z_k+1)
    # a -> b -> c turns counter-clockwise seen from +Y: cross(+z, +x) = +y
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, e], 1)])
    return _mesh(vertices, faces)


def _box(size=(1.0, 1.0, 1.0), subdivisions=0) -> trimesh.Trimesh:
    """Axis-aligned box centred at the origin; each side a (2^k x 2^k)-cell grid.

    The six sides do not share vertices: every vertex has the normal of its
    side, so per-vertex shading keeps the box's sharp edges (shared corners
    would get the averaged, diagonal normal). The box is closed geometrically
    (coincident edge vertices), not topologically.
    """
    extents = _vector("size", size, 3, positive=True, context="builtin 'box'")
    levels = _int("subdivisions", subdivisions, minimum=0, context="builtin 'box'")
    _check_size("box", f"subdivisions {levels}", 6 * (2 ** min(levels, 64) + 1) ** 2)
    n = 2**levels
    half = 0.5 * np.asarray(extents)
    grid = np.linspace(-1.0, 1.0, n + 1)
    gs, gt = np.meshgrid(grid, grid, indexing="ij")
    i, k = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = (i * (n + 1) + k).ravel()
    quads = np.concatenate([np.stack([a, a + n + 1, a + 1], 1), np.stack([a + 1, a + n + 1, a + n + 2], 1)])
    vertices, faces = [], []
    for axis in range(3):
        s_axis, t_axis = (axis + 1) % 3, (axis + 2) % 3  # (s, t, axis) is a right-handed frame
        for sign in (1.0, -1.0):
            v = np.zeros(((n + 1) ** 2, 3))
            v[:, axis] = sign
            v[:, s_axis] = gs.ravel()
            v[:, t_axis] = gt.ravel() * sign  # mirror t on the negative side to keep normals outward
            faces.append(quads + sum(len(p) for p in vertices))
            vertices.append(v * half)
    return _mesh(np.concatenate(vertices), np.concatenate(faces))


def _icosphere(radius=1.0, subdivisions=3) -> trimesh.Trimesh:
    r = _finite_float("radius", radius, positive=True, context="builtin 'icosphere'")
    levels = _int("subdivisions", subdivisions, minimum=0, context="builtin 'icosphere'")
    if levels > 7:
        raise ValueError(
            f"builtin 'icosphere': subdivisions must be <= 7 (163,842 vertices), got {subdivisions!r}"
        )
    mesh = trimesh.creation.icosphere(subdivisions=levels, radius=r)
    return _mesh(mesh.vertices, mesh.faces)


def _uv_sphere(radius=1.0, count=(32, 32)) -> trimesh.Trimesh:
    r = _finite_float("radius", radius, positive=True, context="builtin 'uv_sphere'")
    lat, lon = _int_pair("count", count, minimum=3, context="builtin 'uv_sphere'")
    _check_size("uv_sphere", f"count [{lat}, {lon}]", lat * lon)
    mesh = trimesh.creation.uv_sphere(radius=r, count=[lat, lon])
    return _mesh(trimesh.transform_points(mesh.vertices, _Z_TO_Y), mesh.faces)


def _torus(major_radius=1.0, minor_radius=0.25, sections=(32, 16)) -> trimesh.Trimesh:
    big = _finite_float("major_radius", major_radius, positive=True, context="builtin 'torus'")
    small = _finite_float("minor_radius", minor_radius, positive=True, context="builtin 'torus'")
    if small >= big:
        raise ValueError(
            f"builtin 'torus': minor_radius must be < major_radius, got {minor_radius!r} "
            f">= {major_radius!r}"
        )
    n_major, n_minor = _int_pair("sections", sections, minimum=3, context="builtin 'torus'")
    _check_size("torus", f"sections [{n_major}, {n_minor}]", n_major * n_minor)
    mesh = trimesh.creation.torus(big, small, major_sections=n_major, minor_sections=n_minor)
    return _mesh(trimesh.transform_points(mesh.vertices, _Z_TO_Y), mesh.faces)


def _cylinder(radius=0.5, height=1.0, sections=32) -> trimesh.Trimesh:
    """Cylinder about +Y, centred at the origin; side and caps do not share vertices.

    Split rims keep the sharp edge under per-vertex shading: side vertices
    carry radial normals, cap vertices carry +-Y (as the box's sides do).
    """
    r = _finite_float("radius", radius, positive=True, context="builtin 'cylinder'")
    h = _finite_float("height", height, positive=True, context="builtin 'cylinder'")
    n = _int("sections", sections, minimum=3, context="builtin 'cylinder'")
    _check_size("cylinder", f"sections {n}", 4 * n + 2)
    angle = 2.0 * np.pi * np.arange(n) / n
    ring = np.stack([r * np.sin(angle), np.zeros(n), r * np.cos(angle)], axis=1)
    low, high = ring + [0.0, -0.5 * h, 0.0], ring + [0.0, 0.5 * h, 0.0]
    j, j1 = np.arange(n), (np.arange(n) + 1) % n
    # side: low ring 0..n-1, high ring n..2n-1; counter-clockwise seen from outside
    side = np.concatenate([np.stack([j, j1, n + j], 1), np.stack([j1, n + j1, n + j], 1)])
    # caps: centre then rim, fans oriented along -Y (bottom) and +Y (top)
    base = 2 * n
    bottom = np.stack([np.full(n, base), base + 1 + j1, base + 1 + j], 1)
    top = np.stack([np.full(n, base + n + 1), base + n + 2 + j, base + n + 2 + j1], 1)
    vertices = np.concatenate([low, high, [[0.0, -0.5 * h, 0.0]], low, [[0.0, 0.5 * h, 0.0]], high])
    return _mesh(vertices, np.concatenate([side, bottom, top]))


# --------------------------------------------------------------------------- assets


@functools.lru_cache(maxsize=None)
def _asset_arrays(relative: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of a shipped PLY under prtlab/data/, read once, read-only."""
    mesh = load_mesh(_data.path(relative))
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    vertices.setflags(write=False)
    faces.setflags(write=False)
    return vertices, faces


def _teapot(resolution=8, bottom=True, fit_lid=True) -> trimesh.Trimesh:
    from ._teapot import tessellate_teapot

    n = _int("resolution", resolution, minimum=1, context="builtin 'teapot'")
    if n > 128:
        raise ValueError(f"builtin 'teapot': resolution must be <= 128, got {resolution!r}")
    for key, value in (("bottom", bottom), ("fit_lid", fit_lid)):
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"builtin 'teapot': {key} must be true or false, got {_short(value)}")
    vertices, faces = tessellate_teapot(n, bottom=bool(bottom), fit_lid=bool(fit_lid))
    return normalize_mesh(_mesh(vertices, faces))


def _bunny(subdivisions=0) -> trimesh.Trimesh:
    levels = _int("subdivisions", subdivisions, minimum=0, context="builtin 'bunny'")
    if levels > 4:
        raise ValueError(f"builtin 'bunny': subdivisions must be <= 4 (~470k vertices), got {subdivisions!r}")
    vertices, faces = _asset_arrays("meshes/bunny.ply")
    mesh = _mesh(vertices, faces)
    if levels:  # Loop subdivision shrinks the mesh a little: normalise afterwards
        mesh = subdivide(mesh, levels, method="loop")
    return normalize_mesh(mesh)


_DRAGON_VARIANTS = {"5k": "meshes/dragon_5k.ply", "23k": "meshes/dragon_23k.ply"}


def _dragon(variant="5k") -> trimesh.Trimesh:
    if variant not in _DRAGON_VARIANTS:
        raise ValueError(
            f"builtin 'dragon': variant must be one of {', '.join(map(repr, _DRAGON_VARIANTS))}, "
            f"got {_short(variant)}"
        )
    vertices, faces = _asset_arrays(_DRAGON_VARIANTS[variant])
    return normalize_mesh(_mesh(vertices, faces))


#: The parts of the Cornell box, in the order of the source file.
CORNELL_BOX_PARTS = (
    "floor",
    "light",
    "ceiling",
    "back_wall",
    "green_wall",
    "red_wall",
    "short_block",
    "tall_block",
)
_MM = 1e-3  # the Cornell box data is in millimetres; prtlab uses metres


def _refine_quads(vertices: np.ndarray, faces: np.ndarray, resolution: int):
    """Split each quad (triangle pair (q0,q1,q2), (q0,q2,q3)) into a bilinear grid."""
    if resolution == 1:
        return vertices, faces
    n = resolution
    quads = np.concatenate([faces[0::2], faces[1::2, 2:]], axis=1)  # (Q, 4): q0 q1 q2 q3
    s = np.linspace(0.0, 1.0, n + 1)
    ss, tt = np.meshgrid(s, s, indexing="ij")  # s along q0->q1, t along q0->q3
    w = np.stack([(1 - ss) * (1 - tt), ss * (1 - tt), ss * tt, (1 - ss) * tt], -1).reshape(-1, 4)
    out_v = np.einsum("gk,qkc->qgc", w, vertices[quads]).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    p00 = (i * (n + 1) + j).ravel()
    p10 = p00 + (n + 1)
    p11 = p10 + 1
    p01 = p00 + 1
    cell = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    out_f = (cell[None] + (np.arange(len(quads)) * (n + 1) ** 2)[:, None, None]).reshape(-1, 3)
    return out_v, out_f


def cornell_box_objects(resolution: int = 1) -> dict[str, trimesh.Trimesh]:
    """The measured Cornell box, one mesh per part, in metres.

    Parameters
    ----------
    resolution : int
        Each quad of the data is split into ``resolution x resolution``
        bilinear grid cells (two triangles each), for per-vertex shading.

    Returns
    -------
    dict of str -> trimesh.Trimesh
        Keys ``CORNELL_BOX_PARTS``: ``floor``, ``light`` (the emitter's quad,
        facing down; it reflects nothing), ``ceiling``, ``back_wall``,
        ``green_wall``, ``red_wall``, ``short_block``, ``tall_block``.
        Walls are single quads whose normals face into the box; the blocks are
        closed (their footprints, which the source file lists with the floor,
        are their bottoms) with outward normals. Vertices are not shared
        between quads (flat shading).

    Notes
    -----
    The Cornell program's measured geometry (as shipped in Embree's and
    tinyobjloader's ``cornell_box.obj``) scaled from millimetres to metres:
    the box spans about ``0 <= x <= 0.556``, ``0 <= y <= 0.5488``,
    ``0 <= z <= 0.5592`` and is open toward -z, where the original camera
    stands at ``(0.278, 0.273, -0.800)`` looking along +z (the red wall at
    x = 0.556 is then on the left). Material colours of that file: white,
    red, green ``Kd`` = (1,1,1), (1,0,0), (0,1,0); the scene file chooses albedos.
    """
    n = _int("resolution", resolution, minimum=1, context="cornell_box")
    if n > 256:
        raise ValueError(f"cornell_box: resolution must be <= 256, got {resolution!r}")
    out = {}
    for part in CORNELL_BOX_PARTS:
        vertices, faces = _asset_arrays(f"meshes/cornell_box/{part}.ply")
        v, f = _refine_quads(vertices * _MM, faces, n)
        out[part] = _mesh(v, f)
    return out


#: Radiance of the Cornell box light in the source file (its ``Ka 20 20 20``).
_CORNELL_LIGHT_RADIANCE = (20.0, 20.0, 20.0)


def cornell_box_light() -> dict[str, np.ndarray]:
    """The Cornell box's ceiling light as a prtlab area light (metres).

    Returns
    -------
    dict
        ``center`` (3,), ``u`` (3,), ``v`` (3,): the parallelogram
        ``center + s u + t v``, ``s, t`` in [-1, 1] (half edges), emitting on the
        side of ``normalize(cross(u, v))``, which is ``-Y`` (down);
        ``radiance`` (3,): ``[20, 20, 20]``, the value the source file gives
        the light material (scale it to taste in the scene).

    Notes
    -----
    The light quad (130 x 105 mm at y = 548 mm, 0.8 mm below the ceiling) is
    the ``light`` part of :func:`cornell_box_objects`; its corners are
    ``center +- u +- v``.
    """
    vertices, faces = _asset_arrays("meshes/cornell_box/light.ply")
    corners = np.asarray(vertices, dtype=np.float64) * _MM
    center = corners.mean(axis=0)
    u = 0.5 * (corners[0] - corners[3])
    v = 0.5 * (corners[1] - corners[0])
    normal = np.cross(corners[faces[0, 1]] - corners[faces[0, 0]], corners[faces[0, 2]] - corners[faces[0, 0]])
    if np.dot(np.cross(u, v), normal) < 0.0:
        u, v = v, u
    return {
        "center": center,
        "u": u,
        "v": v,
        "radiance": np.array(_CORNELL_LIGHT_RADIANCE, dtype=np.float64),
    }


def _cornell_box(part=None, resolution=1) -> trimesh.Trimesh:
    if part not in CORNELL_BOX_PARTS:
        raise ValueError(
            f"builtin 'cornell_box' is not a single mesh: pass part= one of "
            f"{', '.join(CORNELL_BOX_PARTS)} (got {_short(part)}), or call cornell_box_objects()"
        )
    return cornell_box_objects(resolution)[part]


def _room(
    size=_room_module._DEFAULT_ROOM_SIZE,
    windows=(_room_module._DEFAULT_WINDOW,),
    cell_size=0.25,
    surfaces=_room_module.ROOM_SURFACES,
) -> trimesh.Trimesh:
    extent = _room_module._room_size(size)
    cell = _finite_float("cell_size", cell_size, positive=True, context="builtin 'room'")
    with np.errstate(over="ignore"):
        cells = 2.0 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[0] * extent[2]) / cell**2
    _check_size("room", f"cell_size {cell:g}", cells)
    walls, _ = _room_module.room_with_windows(
        size=size, windows=windows, cell_size=cell_size, surfaces=surfaces
    )
    return walls


# --------------------------------------------------------------------------- registry

#: name -> builder; each builder's keyword defaults are the documented defaults.
_BUILDERS: dict[str, Callable[..., trimesh.Trimesh]] = {
    "plane": _plane,
    "box": _box,
    "icosphere": _icosphere,
    "uv_sphere": _uv_sphere,
    "torus": _torus,
    "cylinder": _cylinder,
    "teapot": _teapot,
    "bunny": _bunny,
    "dragon": _dragon,
    "cornell_box": _cornell_box,
    "room": _room,
    "window": _room_module.window_quad,
}


class _BuiltinNames(Mapping):
    """Read-only view: builtin name -> dict of its parameters and their defaults."""

    def __getitem__(self, name: str) -> dict[str, Any]:
        import inspect

        sig = inspect.signature(_BUILDERS[name])
        return {k: p.default for k, p in sig.parameters.items()}

    def __iter__(self):
        return iter(sorted(_BUILDERS))

    def __len__(self) -> int:
        return len(_BUILDERS)

    def __repr__(self) -> str:
        return "BUILTIN_MESHES(" + ", ".join(sorted(_BUILDERS)) + ")"


#: Names of the built-in meshes, each mapped to its parameters and defaults.
BUILTIN_MESHES: Mapping[str, dict[str, Any]] = _BuiltinNames()


def builtin_mesh(name: str, **params: Any) -> trimesh.Trimesh:
    """Build one of prtlab's built-in meshes in object space (+Y up).

    (Long for the table of builtins and their parameters; the code is a 16-line dispatch.)

    Parameters
    ----------
    name : str
        One of the names below.
    **params
        The builtin's parameters; every one has a default.

    Returns
    -------
    trimesh.Trimesh
        A new mesh (``process=False``: its vertex order is the shading order),
        consistently wound with normals facing out of closed meshes.

    Raises
    ------
    ValueError
        For an unknown name or parameter (the message lists the valid ones)
        or an invalid parameter value.
    TypeError
        For a parameter of the wrong type.

    Notes
    -----
    ====================  ==============================================================
    ``plane``             ``size=[w, d]=[1, 1]``, ``resolution=[nx, nz]=[1, 1]`` cells;
                          the grid ``|x| <= w/2, y = 0, |z| <= d/2`` with
                          ``(nx+1)(nz+1)`` vertices, x slowest; normal +Y.
    ``box``               ``size=[x, y, z]=[1, 1, 1]`` centred at the origin;
                          ``subdivisions=0`` midpoint (1 -> 4) refinements. Each
                          side has vertices of its own (24 at level 0), so every
                          vertex normal is its side's: sharp edges stay sharp.
    ``icosphere``         ``radius=1``, ``subdivisions=3`` (642 vertices), centred.
    ``uv_sphere``         ``radius=1``, ``count=[lat, lon]=[32, 32]``, poles on +-Y.
    ``torus``             ``major_radius=1``, ``minor_radius=0.25``,
                          ``sections=[major, minor]=[32, 16]``; lies in the xz plane
                          (axis +Y), centred.
    ``cylinder``          ``radius=0.5``, ``height=1``, ``sections=32``; axis +Y,
                          centred, capped.
    ``teapot``            ``resolution=8`` segments per patch edge (2,081 vertices,
                          ``64 n^2 - 8 n`` faces), ``bottom=True`` (Crow's bottom),
                          ``fit_lid=True`` (three.js's 7.7 % wider lid): Newell's
                          teapot, seams welded, spout toward +x. Four open sheets
                          (body, lid, handle, spout), each with outward normals.
    ``bunny``             ``subdivisions=0``: the 1,839-vertex Stanford bunny
                          (watertight); Loop subdivision for paper-scale counts:
                          1 -> 7,350, 2 -> 29,394 vertices.
    ``dragon``            ``variant="5k"`` (5,203 vertices) or ``"23k"`` (22,982):
                          Stanford's decimated dragons (not watertight).
    ``cornell_box``       ``part`` (required: one of ``CORNELL_BOX_PARTS``),
                          ``resolution=1``: one part of :func:`cornell_box_objects`.
    ``room``              ``size=[4, 2.5, 4]``, ``windows=[one on -z]``,
                          ``cell_size=0.25``, ``surfaces=all``: the walls of
                          :func:`room_with_windows`, normals facing in.
    ``window``            ``room_size``, ``wall``, ``center``, ``size`` (defaults: the
                          default room's window): one window quad of
                          :func:`room_with_windows`, normal facing into the room.
    ====================  ==============================================================

    The scanned meshes and the teapot are normalised by :func:`normalize_mesh`:
    bounding box centred on ``x = z = 0``, resting on ``y = 0``, height 1
    (after subdivision, for the bunny). Primitives are centred on the origin.
    Sources and licences of the assets: ``prtlab/data/README.md``.

    Examples
    --------
    >>> floor = builtin_mesh("plane", size=[6, 6], resolution=[40, 40])
    >>> len(floor.vertices)
    1681
    >>> len(builtin_mesh("bunny").vertices)
    1839
    """
    if not isinstance(name, str):
        raise TypeError(f"builtin mesh name must be a string, got {_short(name)}")
    builder = _BUILDERS.get(name)
    if builder is None:
        raise ValueError(
            f"unknown builtin mesh {_short(name)}; valid names: {', '.join(sorted(_BUILDERS))}"
        )
    valid = BUILTIN_MESHES[name]
    unknown = sorted(set(params) - set(valid))
    if unknown:
        raise ValueError(
            f"builtin {name!r}: unknown parameter(s) {', '.join(map(_short, unknown))}; "
            f"valid parameters: {', '.join(valid) or '(none)'}"
        )
    return builder(**params)


# --------------------------------------------------------------------------- helpers


def normalize_mesh(mesh: trimesh.Trimesh, height: float = 1.0) -> trimesh.Trimesh:
    """Scale and move a mesh to stand on the floor, vertex order unchanged.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        Any mesh with a non-flat y extent.
    height : float
        The bounding-box height after scaling.

    Returns
    -------
    trimesh.Trimesh
        A new mesh: uniformly scaled so that ``max y - min y = height``, its
        bounding box centred on ``x = z = 0``, with ``min y = 0``.
    """
    h = _finite_float("height", height, positive=True)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if len(v) == 0:
        raise ValueError("normalize_mesh: the mesh has no vertices")
    lo, hi = v.min(axis=0), v.max(axis=0)
    if hi[1] - lo[1] <= 0.0:
        raise ValueError("normalize_mesh: the mesh is flat in y and cannot be scaled to a height")
    scale = h / (hi[1] - lo[1])
    centre = 0.5 * (lo + hi)
    out = (v - np.array([centre[0], lo[1], centre[2]])) * scale
    out[:, 1] = np.maximum(out[:, 1], 0.0)  # exact floor contact despite rounding
    return _mesh(out, mesh.faces)


_SUBDIVISION_METHODS = ("loop", "midpoint")


def _edge_topology(faces: np.ndarray):
    """Unique edges (E, 2), each face's edge ids (F, 3) for (v0v1, v1v2, v2v0),
    and the number of faces on each edge (E,)."""
    directed = np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2)
    edges, inverse = np.unique(np.sort(directed, axis=1), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    return edges, inverse.reshape(-1, 3), np.bincount(inverse, minlength=len(edges))


def _split_faces(faces: np.ndarray, face_edges: np.ndarray, n_vertices: int) -> np.ndarray:
    """1 -> 4 split; edge e becomes vertex n_vertices + e; winding kept."""
    a, b, c = faces.T
    ab, bc, ca = (face_edges + n_vertices).T
    return np.concatenate(
        [np.stack(t, axis=1) for t in ((a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca))]
    )


def _subdivide_once(vertices: np.ndarray, faces: np.ndarray, loop: bool):
    edges, face_edges, n_faces = _edge_topology(faces)
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    odd = 0.5 * (a + b)
    even = vertices
    if loop:
        # odd (edge) vertices: 3/8 (a + b) + 1/8 (c + d) on interior edges
        opposite = np.zeros((len(edges), 3))
        np.add.at(opposite, face_edges.ravel(), vertices[np.roll(faces, -2, axis=1)].reshape(-1, 3))
        interior = n_faces == 2
        odd[interior] = 0.375 * (a + b)[interior] + 0.125 * opposite[interior]
        # even vertices: Loop's beta rule inside, the cubic B-spline rule on boundaries
        n = len(vertices)
        valence = np.bincount(edges.ravel(), minlength=n)
        ring = np.zeros((n, 3))
        np.add.at(ring, edges[:, 0], vertices[edges[:, 1]])
        np.add.at(ring, edges[:, 1], vertices[edges[:, 0]])
        boundary = edges[n_faces == 1]
        n_boundary = np.bincount(boundary.ravel(), minlength=n)
        boundary_ring = np.zeros((n, 3))
        np.add.at(boundary_ring, boundary[:, 0], vertices[boundary[:, 1]])
        np.add.at(boundary_ring, boundary[:, 1], vertices[boundary[:, 0]])
        k = np.maximum(valence, 1).astype(np.float64)
        beta = (0.625 - (0.375 + 0.25 * np.cos(2.0 * np.pi / k)) ** 2) / k
        even = (1.0 - k * beta)[:, None] * vertices + beta[:, None] * ring
        on_boundary = n_boundary == 2
        even[on_boundary] = 0.75 * vertices[on_boundary] + 0.125 * boundary_ring[on_boundary]
        # isolated vertices, and vertices on non-manifold or several boundaries, stay put
        fixed = (valence == 0) | ((n_boundary > 0) & ~on_boundary)
        fixed[edges[n_faces > 2].ravel()] = True
        even[fixed] = vertices[fixed]
    return np.concatenate([even, odd]), _split_faces(faces, face_edges, len(vertices))


def subdivide(mesh: trimesh.Trimesh, levels: int = 1, method: str = "loop") -> trimesh.Trimesh:
    """Refine a mesh for methods that need more shading vertices.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The mesh to refine (not modified).
    levels : int
        Number of 1 -> 4 triangle splits; 0 returns a copy.
    method : {"loop", "midpoint"}
        ``"loop"``: Loop's smoothing subdivision: the surface moves toward the
        smooth limit surface (it shrinks a little; open boundaries follow the
        cubic B-spline rule, so their corners get rounded). ``"midpoint"``:
        new vertices at edge midpoints; the surface is unchanged (use it for
        flat walls and floors).

    Returns
    -------
    trimesh.Trimesh
        The refined mesh: per level, the ``V`` old vertices first, in input
        order (moved by ``"loop"``, unmoved by ``"midpoint"``), then one new
        vertex per edge, so ``V' = V + E`` and ``F' = 4 F``. Face ``f`` becomes
        faces ``f``, ``F + f``, ``2F + f``, ``3F + f``, with the same winding.

    Notes
    -----
    Loop's rules: a new edge vertex is ``3/8 (a + b) + 1/8 (c + d)`` on an
    interior edge ``ab`` with opposite vertices ``c, d`` and ``(a + b) / 2`` on
    a boundary edge; an old interior vertex of valence ``k`` becomes
    ``(1 - k beta) v + beta sum(neighbours)``, with
    ``beta = (5/8 - (3/8 + cos(2 pi / k) / 4)^2) / k``; an old boundary vertex
    becomes ``3/4 v + 1/8 (b1 + b2)`` of its two boundary neighbours. Vertices
    of non-manifold edges stay put.

    References
    ----------
    C. Loop, "Smooth Subdivision Surfaces Based on Triangles", MS thesis,
    University of Utah, 1987. H. Hoppe et al., "Piecewise Smooth Surface
    Reconstruction", SIGGRAPH 1994 (boundary rules).
    """
    if not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(f"subdivide: mesh must be a trimesh.Trimesh, got {type(mesh).__name__}")
    n = _int("levels", levels, minimum=0, context="subdivide")
    if method not in _SUBDIVISION_METHODS:
        raise ValueError(
            f"subdivide: unknown method {method!r}; valid methods: {', '.join(_SUBDIVISION_METHODS)}"
        )
    vertices = np.array(mesh.vertices, dtype=np.float64)
    faces = np.array(mesh.faces, dtype=np.int64)
    if len(faces) * 4**n > 50_000_000:
        raise ValueError(
            f"subdivide: {levels} levels would make {len(faces) * 4**n:,} faces; use fewer levels"
        )
    for _ in range(n if len(faces) else 0):
        vertices, faces = _subdivide_once(vertices, faces, loop=method == "loop")
    return _mesh(vertices, faces)


# --------------------------------------------------------------------------- loading


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions and triangulated faces of an OBJ file, vertices in file order."""
    vertices: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    text = path.read_text(encoding="utf-8", errors="replace").replace("\\\n", " ")
    for lineno, line in enumerate(text.splitlines(), start=1):
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        where = f"mesh file {str(path)!r}, line {lineno}"
        try:
            if fields[0] == "v":
                if len(fields) < 4:
                    raise ValueError("a vertex needs x y z")
                vertices.append((float(fields[1]), float(fields[2]), float(fields[3])))
            elif fields[0] == "f":
                polygon = []
                for token in fields[1:]:
                    i = int(token.split("/", 1)[0])
                    if i < 0:
                        i = len(vertices) + i + 1  # -1 = the latest vertex
                        if i < 1:
                            raise ValueError(f"relative index {token!r} reaches before the first vertex")
                    elif i == 0:
                        raise ValueError("OBJ indices start at 1, got 0")
                    polygon.append(i - 1)
                if len(polygon) < 3:
                    raise ValueError("a face needs at least 3 vertices")
                faces.extend((polygon[0], polygon[k], polygon[k + 1]) for k in range(1, len(polygon) - 1))
        except ValueError as err:
            raise ValueError(f"cannot read {where}: {err}") from None
    v = np.array(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.array(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) and f.max() >= len(v):
        raise ValueError(
            f"cannot read mesh file {str(path)!r}: face index {int(f.max()) + 1} > {len(v)} vertices"
        )
    return v, f


def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """Load any mesh file trimesh reads as one triangle mesh, vertices as stored.

    Parameters
    ----------
    path : str or path-like
        A PLY, OBJ, STL, OFF, GLB/GLTF, ... file.

    Returns
    -------
    trimesh.Trimesh
        One mesh (``process=False``): a file holding several meshes (a scene)
        is concatenated in file order. Vertices are neither merged nor
        reordered, so vertex ``i`` of the result is vertex ``i`` of the file
        (for a scene, counting through its meshes in order); unreferenced
        vertices are kept.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        If the file cannot be read or holds no triangles.

    Notes
    -----
    OBJ files are read by prtlab's own reader (positions and faces only:
    ``v`` and ``f`` records, ``v/vt/vn`` index forms, negative indices
    relative to the vertices read so far, polygons fanned into triangles
    ``(0, i, i+1)``; groups, objects and materials ignored), because trimesh
    reorders OBJ vertices and mis-reads negative indices. STL stores
    unindexed triangles, so an STL mesh has three vertices per face; merge
    them (``mesh.merge_vertices()``) if smooth per-vertex shading is wanted.
    """
    p = Path(os.fspath(path))
    if not p.is_file():
        raise FileNotFoundError(f"mesh file not found: {str(p)!r}")
    if p.suffix.lower() == ".obj":
        vertices, faces = _read_obj(p)
        return _checked_mesh(p, vertices, faces)
    try:
        loaded = trimesh.load(p, process=False)
    except Exception as err:  # trimesh raises many kinds for unreadable files
        raise ValueError(f"cannot read mesh file {str(p)!r}: {err}") from err
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)]
        if not geoms:
            raise ValueError(f"mesh file {str(p)!r} holds no triangle mesh (no faces)")
        parts = [(np.asarray(g.vertices), np.asarray(g.faces)) for g in geoms]
    elif isinstance(loaded, trimesh.Trimesh):
        parts = [(np.asarray(loaded.vertices), np.asarray(loaded.faces))]
    else:
        raise ValueError(
            f"mesh file {str(p)!r} holds no triangle mesh (no faces; trimesh read a "
            f"{type(loaded).__name__})"
        )
    offsets = np.cumsum([0] + [len(v) for v, _ in parts])
    vertices = np.concatenate([v for v, _ in parts]).reshape(-1, 3)
    faces = np.concatenate([f.reshape(-1, 3) + o for (_, f), o in zip(parts, offsets)])
    if p.suffix.lower() == ".ply":
        _check_ply_counts(p, len(vertices), len(faces))
    return _checked_mesh(p, vertices, faces)


def _check_ply_counts(path: Path, n_vertices: int, n_faces: int) -> None:
    """Refuse a PLY file holding fewer vertices or faces than its header declares (a truncated file)."""
    with open(path, "rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    if end < 0:
        return
    declared = {}
    for line in head[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == "element" and words[2].isdigit():
            declared[words[1]] = int(words[2])
    if n_vertices < declared.get("vertex", 0) or n_faces < declared.get("face", 0):
        raise ValueError(
            f"mesh file {str(path)!r} is truncated or corrupt: its header declares "
            f"{declared.get('vertex', 0):,} vertices and {declared.get('face', 0):,} faces, "
            f"but {n_vertices:,} vertices and {n_faces:,} faces were read"
        )


def _checked_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    if len(faces) == 0:
        raise ValueError(f"mesh file {str(path)!r} holds no triangle mesh (no faces)")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.flatnonzero(~np.all(np.isfinite(vertices), axis=1))[0])
        raise ValueError(
            f"mesh has NaN or inf vertex coordinates: vertex {bad} of {str(path)!r} is "
            f"{vertices[bad].tolist()}; fix or remove it"
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(
            f"mesh file {str(path)!r}: face indices must lie in [0, {len(vertices) - 1}], "
            f"found {int(faces.min())}..{int(faces.max())}"
        )
    return _mesh(vertices, faces)
