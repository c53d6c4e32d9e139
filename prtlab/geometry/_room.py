"""A box room with rectangular window openings, and the window quads (portals).

The room spans ``-w/2 <= x <= w/2``, ``0 <= y <= h``, ``-d/2 <= z <= d/2``
(floor on y = 0, centred on x = z = 0). Each surface is a flat grid whose
lines include every window edge, so an opening is a set of removed grid cells
and its window quad shares the opening's corner coordinates exactly.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import trimesh

__all__ = ["ROOM_SURFACES", "WINDOW_WALLS", "room_with_windows", "window_quad"]

#: Surfaces of the room, by the axis direction of their plane.
ROOM_SURFACES = ("-x", "+x", "-y", "+y", "-z", "+z")
#: Surfaces that may hold a window ("-y", the floor, may not).
WINDOW_WALLS = ("-x", "+x", "+y", "-z", "+z")

# surface -> (axis index of the plane, sign, axis of a, axis of b)
# a, b are the in-plane window coordinates: horizontal then vertical (height
# y) on the side walls, (x, z) on the floor and ceiling.
_FRAME = {
    "-x": (0, -1.0, 2, 1),
    "+x": (0, +1.0, 2, 1),
    "-z": (2, -1.0, 0, 1),
    "+z": (2, +1.0, 0, 1),
    "-y": (1, -1.0, 0, 2),
    "+y": (1, +1.0, 0, 2),
}

_DEFAULT_ROOM_SIZE = (4.0, 2.5, 4.0)
_DEFAULT_WINDOW = {"wall": "-z", "center": (0.0, 1.25), "size": (1.5, 1.0)}
_WINDOW_KEYS = ("wall", "center", "size")


def _room_size(size: Any, name: str = "size") -> np.ndarray:
    from ._meshes import _vector

    return _vector(name, size, 3, positive=True, context="room")


def _plane_bounds(size: np.ndarray, surface: str):
    """(plane coordinate, (a_min, a_max), (b_min, b_max)) of one surface."""
    axis, sign, ia, ib = _FRAME[surface]
    lo = np.array([-0.5 * size[0], 0.0, -0.5 * size[2]])
    hi = np.array([0.5 * size[0], size[1], 0.5 * size[2]])
    plane = hi[axis] if sign > 0 else lo[axis]
    return plane, (lo[ia], hi[ia]), (lo[ib], hi[ib])


def _point(surface: str, plane: float, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    axis, _, ia, ib = _FRAME[surface]
    out = np.empty(np.broadcast(a, b).shape + (3,))
    out[..., axis] = plane
    out[..., ia] = a
    out[..., ib] = b
    return out


def _inward_winding(surface: str) -> bool:
    """True if (a, b) -> cross(e_a, e_b) already points into the room."""
    axis, sign, ia, ib = _FRAME[surface]
    cross = np.cross(np.eye(3)[ia], np.eye(3)[ib])
    return float(cross[axis]) * -sign > 0.0


def _parse_window(window: Any, size: np.ndarray, index: int | None = None) -> dict[str, Any]:
    from ._meshes import _vector

    where = f"room: windows[{index}]" if index is not None else "window"
    if not isinstance(window, Mapping):
        raise TypeError(
            f"{where} must be a mapping with keys {', '.join(_WINDOW_KEYS)}, got {window!r}"
        )
    unknown = sorted(set(window) - set(_WINDOW_KEYS))
    missing = [k for k in _WINDOW_KEYS if k not in window]
    if unknown or missing:
        raise ValueError(
            f"{where}: unknown key(s) {unknown} / missing key(s) {missing}; "
            f"a window needs exactly: {', '.join(_WINDOW_KEYS)}"
        )
    wall = window["wall"]
    if wall not in WINDOW_WALLS:
        raise ValueError(f"{where}: wall must be one of {', '.join(WINDOW_WALLS)}, got {wall!r}")
    center = _vector("center", window["center"], 2, context=where)
    extent = _vector("size", window["size"], 2, positive=True, context=where)
    lo, hi = center - 0.5 * extent, center + 0.5 * extent
    _, (a0, a1), (b0, b1) = _plane_bounds(size, wall)
    eps = 1e-9 * float(max(size))
    if lo[0] < a0 - eps or hi[0] > a1 + eps or lo[1] < b0 - eps or hi[1] > b1 + eps:
        raise ValueError(
            f"{where}: the opening [{lo[0]:g}, {hi[0]:g}] x [{lo[1]:g}, {hi[1]:g}] does not fit "
            f"on wall {wall!r}, which spans [{a0:g}, {a1:g}] x [{b0:g}, {b1:g}] "
            "(center and size are (horizontal, height) on side walls, (x, z) on the ceiling)"
        )
    lo = np.maximum(lo, [a0, b0])
    hi = np.minimum(hi, [a1, b1])
    return {"wall": wall, "lo": lo, "hi": hi}


def _axis_lines(start: float, stop: float, cuts: Sequence[float], cell_size: float) -> np.ndarray:
    """Grid coordinates from start to stop through every cut, cells <= cell_size."""
    stops = np.unique(np.clip(np.array([start, stop, *cuts], dtype=np.float64), start, stop))
    pieces = [stops[:1]]
    for lo, hi in zip(stops[:-1], stops[1:]):
        if hi - lo <= 1e-12 * max(1.0, abs(stop - start)):
            continue
        n = max(1, math.ceil((hi - lo) / cell_size - 1e-9))
        pieces.append(np.linspace(lo, hi, n + 1)[1:])
    return np.concatenate(pieces)


def _surface_mesh(size, surface, openings, cell_size):
    plane, (a0, a1), (b0, b1) = _plane_bounds(size, surface)
    a_lines = _axis_lines(a0, a1, [v for o in openings for v in (o["lo"][0], o["hi"][0])], cell_size)
    b_lines = _axis_lines(b0, b1, [v for o in openings for v in (o["lo"][1], o["hi"][1])], cell_size)
    na, nb = len(a_lines), len(b_lines)
    ga, gb = np.meshgrid(a_lines, b_lines, indexing="ij")
    vertices = _point(surface, plane, ga.ravel(), gb.ravel())

    i, j = np.meshgrid(np.arange(na - 1), np.arange(nb - 1), indexing="ij")
    ca = 0.5 * (a_lines[i] + a_lines[i + 1])
    cb = 0.5 * (b_lines[j] + b_lines[j + 1])
    keep = np.ones(ca.shape, dtype=bool)
    for o in openings:
        keep &= ~((ca > o["lo"][0]) & (ca < o["hi"][0]) & (cb > o["lo"][1]) & (cb < o["hi"][1]))
    i, j = i[keep], j[keep]
    p00 = i * nb + j
    p10 = (i + 1) * nb + j
    p11 = p10 + 1
    p01 = p00 + 1
    if _inward_winding(surface):
        faces = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    else:
        faces = np.concatenate([np.stack([p00, p11, p10], 1), np.stack([p00, p01, p11], 1)])
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used) - 1
    return vertices[used], remap[faces]


def window_quad(
    room_size=_DEFAULT_ROOM_SIZE,
    wall=_DEFAULT_WINDOW["wall"],
    center=_DEFAULT_WINDOW["center"],
    size=_DEFAULT_WINDOW["size"],
) -> trimesh.Trimesh:
    """One window of :func:`room_with_windows` as a quad (4 vertices, 2 triangles).

    Parameters are those of one entry of ``windows`` plus the ``room_size``;
    the quad exactly fills the opening that the same entry cuts, and its
    normal faces into the room.
    """
    room = _room_size(room_size, "room_size")
    return _window_mesh(room, _parse_window({"wall": wall, "center": center, "size": size}, room))


def _window_mesh(room: np.ndarray, w: dict[str, Any]) -> trimesh.Trimesh:
    plane, _, _ = _plane_bounds(room, w["wall"])
    (a0, b0), (a1, b1) = w["lo"], w["hi"]
    corners = _point(w["wall"], plane, np.array([a0, a1, a1, a0]), np.array([b0, b0, b1, b1]))
    if _inward_winding(w["wall"]):
        faces = np.array([[0, 1, 2], [0, 2, 3]])
    else:
        faces = np.array([[0, 2, 1], [0, 3, 2]])
    return trimesh.Trimesh(vertices=corners, faces=faces, process=False)


def _parse_windows(windows, room) -> list[dict]:
    """The parsed ``windows`` of a room; openings on one wall must not overlap."""
    if isinstance(windows, Mapping) or not isinstance(windows, (list, tuple)):
        raise TypeError(f"room: windows must be a list of window mappings, got {windows!r}")
    parsed = [_parse_window(w, room, k) for k, w in enumerate(windows)]
    for k, wk in enumerate(parsed):
        for m in range(k):
            wm = parsed[m]
            if wk["wall"] == wm["wall"] and np.all(
                np.minimum(wk["hi"], wm["hi"]) > np.maximum(wk["lo"], wm["lo"])
            ):
                raise ValueError(f"room: windows[{m}] and windows[{k}] overlap on wall {wk['wall']!r}")
    return parsed


def room_with_windows(
    size=_DEFAULT_ROOM_SIZE,
    windows=(_DEFAULT_WINDOW,),
    cell_size=0.25,
    surfaces=ROOM_SURFACES,
) -> tuple[trimesh.Trimesh, list[trimesh.Trimesh]]:
    """A box room seen from inside, with rectangular openings and their windows.

    Parameters
    ----------
    size : (3,) float
        ``[w, h, d]``: the room spans ``|x| <= w/2``, ``0 <= y <= h``,
        ``|z| <= d/2``. Default ``[4, 2.5, 4]``.
    windows : sequence of mapping
        Each ``{"wall": W, "center": [a, b], "size": [sa, sb]}`` with ``W`` one of
        ``"+x", "-x", "+z", "-z"`` (side walls; ``a`` is the horizontal
        coordinate along the wall, z on the x walls and x on the z walls, and
        ``b`` the height y above the floor) or ``"+y"`` (a skylight; ``a = x``,
        ``b = z``). Coordinates are the room's object coordinates. The opening is
        ``|a - center[0]| <= sa/2``, ``|b - center[1]| <= sb/2``; it must lie on
        the wall, and openings on one wall must not overlap. Default: one
        1.5 x 1 window centred on the -z wall at height 1.25.
    cell_size : float
        Largest grid cell edge of the surfaces (they are shaded per vertex).
    surfaces : sequence of str
        Which of ``"-x", "+x", "-y"`` (floor), ``"+y"`` (ceiling), ``"-z", "+z"``
        to include in ``walls``; all by default. Listing a subset lets a
        scene give the floor and the walls different materials.

    Returns
    -------
    walls : trimesh.Trimesh
        All requested surfaces in one mesh, in the order of ``ROOM_SURFACES``,
        each a separate grid (vertices are not shared between surfaces, so each
        is flat-shaded), every normal facing into the room.
    windows : list of trimesh.Trimesh
        One quad per window, in input order, exactly filling its opening
        (its corners are vertices of the wall grid), normal facing into the
        room: the portals of Yue et al. through which outside light enters.

    References
    ----------
    Y. Yue, K. Iwasaki, B.-Y. Chen, Y. Dobashi, T. Nishita, "Interactive
    Rendering of Interior Scenes with Dynamic Environment Illumination",
    Computer Graphics Forum 28(7), 2009: portals are the openings (windows)
    through which the environment lights an interior.
    """
    from ._meshes import _finite_float

    room = _room_size(size)
    cell = _finite_float("cell_size", cell_size, positive=True, context="room")
    parsed = _parse_windows(windows, room)
    if isinstance(surfaces, str) or not isinstance(surfaces, (list, tuple)):
        raise TypeError(f"room: surfaces must be a list of {', '.join(ROOM_SURFACES)}")
    bad = [s for s in surfaces if s not in ROOM_SURFACES]
    if bad or not surfaces:
        raise ValueError(
            f"room: surfaces must be a non-empty list of {', '.join(ROOM_SURFACES)}, got {surfaces!r}"
        )
    min_cells = max(room) / cell
    if min_cells > 4096:
        raise ValueError(f"room: cell_size {cell_size!r} is too small for a room of size {list(room)}")

    vertices, faces, offset = [], [], 0
    for surface in ROOM_SURFACES:
        if surface not in surfaces:
            continue
        v, f = _surface_mesh(room, surface, [w for w in parsed if w["wall"] == surface], cell)
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    walls = trimesh.Trimesh(
        vertices=np.concatenate(vertices), faces=np.concatenate(faces), process=False
    )
    quads = [_window_mesh(room, w) for w in parsed]
    return walls, quads
