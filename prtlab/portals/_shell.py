"""Portals and shells (Yue et al. 2009, Section 3.1) and the shell's light (Sections 3.3, 5).

A *portal* is a set of triangles (one or more ``portal: true`` scene objects)
through which light from outside enters the interior. Its *shell* is a sphere
centred on the portal centre ``c`` (area-weighted centroid) that acts as an
environment light ``L_s(w)``: the radiance arriving at ``c`` *from* world
direction ``w``. For a distant environment (a map, an analytic sky, a
constant) ``L_s`` is the environment itself; for a dynamic exterior it is a
cubemap rendered from ``c`` (pass it as a ``(6, r, r, 3)`` array).

Portal orientation: the interior is on the side of the portal's face normals.
:func:`find_portals` turns each portal object to face the interior, whatever the
winding of its faces: toward the side of its plane where most vertices of the
scene's other (non-portal) objects lie (the built-in windows of
:func:`prtlab.geometry.window_quad` already face into the room).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from prtlab._validate import check_order
from prtlab.geometry import cubemap_directions, cubemap_solid_angles, equirect_taps
from prtlab.scene import EnvironmentLight, Scene, equirect_to_cubemap

from . import _kernels

__all__ = ["Portal", "find_portals", "shell_light", "shell_sh", "tint", "frosted"]


@dataclass(frozen=True, eq=False)
class Portal:
    """One portal: world triangles of one or more portal objects, and its shell.

    Attributes
    ----------
    names : tuple of str
        The portal objects it gathers.
    vertices : (P, 3) float64
        World vertices.
    faces : (F, 3) int64
    center : (3,) float64
        Area-weighted centroid: the shell's centre ``c``.
    normal : (3,) float64
        Area-weighted mean unit face normal (toward the interior).
    area : float
        Total area ``A``.
    size : float
        Largest distance between two portal vertices (``l`` of Section 6).
    """

    names: tuple
    vertices: np.ndarray
    faces: np.ndarray
    center: np.ndarray
    normal: np.ndarray
    area: float
    size: float

    @property
    def face_normals(self) -> np.ndarray:
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        return n / np.linalg.norm(n, axis=1, keepdims=True)


def _make_portal(names, meshes) -> Portal:
    verts, faces, offset = [], [], 0
    for v, f in meshes:
        verts.append(np.asarray(v, dtype=np.float64))
        faces.append(np.asarray(f, dtype=np.int64) + offset)
        offset += len(v)
    v = np.concatenate(verts)
    f = np.concatenate(faces)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    areas = 0.5 * np.linalg.norm(cross, axis=1)
    area = float(areas.sum())
    if not area > 0:
        raise ValueError(f"portal {names} has no area (no faces, or only degenerate ones)")
    center = (areas[:, None] * (a + b + c) / 3.0).sum(axis=0) / area
    normal = cross.sum(axis=0)
    norm = np.linalg.norm(normal)
    normal = normal / norm if norm > 0 else np.zeros(3)
    diff = v[:, None, :] - v[None, :, :]
    size = float(np.sqrt((diff**2).sum(-1)).max()) if len(v) <= 4096 else float(np.ptp(v, axis=0).max())
    return Portal(tuple(names), v, f, center, normal, area, size)


def find_portals(scene: Scene, groups=None) -> list[Portal]:
    """The portals of a scene: by default every ``portal: true`` object is its own portal.

    Parameters
    ----------
    scene : prtlab.Scene
    groups : list of list of str, optional
        Portal object names gathered into one portal each (Section 3.1: several
        windows with the same material under a distant environment may form one
        portal). Every portal object must appear exactly once.

    Returns
    -------
    list of Portal
        In scene order (or in the order of ``groups``), world space.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a prtlab.Scene, got {type(scene).__name__}")
    objs = {o.name: o for o in scene.objects if o.portal}
    if groups is None:
        groups = [[name] for name in objs]
    else:
        if isinstance(groups, (str, bytes)) or not all(isinstance(g, (list, tuple)) for g in groups):
            raise TypeError("groups must be a list of lists of portal object names, e.g. [['window1', 'window2']]")
        seen = [n for g in groups for n in g]
        if sorted(seen) != sorted(objs) or len(set(seen)) != len(seen):
            raise ValueError(
                f"groups must name every portal object exactly once: portals {sorted(objs)}, groups {groups}"
            )
    interior = [o.world_vertices() for o in scene.objects if not o.portal]
    interior = np.concatenate(interior) if interior else np.zeros((0, 3))
    meshes = {n: _facing_interior(objs[n].world_vertices(), np.asarray(objs[n].mesh.faces), interior) for n in objs}
    return [_make_portal(g, [meshes[n] for n in g]) for g in groups]


def _facing_interior(vertices, faces, interior) -> tuple[np.ndarray, np.ndarray]:
    """A portal object's world ``(vertices, faces)`` wound so that its mean normal faces the interior: the side of
    its plane holding more of the ``interior`` points (those off the plane by more than ``1e-6`` of the scene's
    size); unchanged when the points do not decide (none off the plane, or as many on each side)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0 or len(interior) == 0:
        return v, f
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    normal = cross.sum(axis=0)
    norm = np.linalg.norm(normal)
    if not norm > 0:
        return v, f
    normal /= norm
    areas = np.linalg.norm(cross, axis=1)
    centre = ((a + b + c) / 3.0 * areas[:, None]).sum(axis=0) / areas.sum()
    everything = np.concatenate([interior, v])
    eps = 1e-6 * max(float(np.ptp(everything, axis=0).max()), 1e-300)
    side = (interior - centre) @ normal
    ahead, behind = int(np.sum(side > eps)), int(np.sum(side < -eps))
    return (v, f[:, ::-1].copy()) if behind > ahead else (v, f)


def shell_light(source, res: int = 32, method: str = "numba") -> np.ndarray:
    """The shell's light ``L_s`` as a cubemap of texel-average radiance.

    Parameters
    ----------
    source : EnvironmentLight, (H, W, 3) equirect image, (6, r, r, 3) cubemap, or (3,) constant RGB
        A cubemap must already have ``r = res`` (e.g. one rendered from the
        portal centre of a dynamic exterior).
    res : int
        Face resolution (32 in the paper).
    method : {"numba", "reference"}
        For an equirect source: ``"reference"`` is
        :func:`prtlab.scene.equirect_to_cubemap`; ``"numba"`` applies the same
        linear map as a table of taps (equirect pixel index and weight, built once
        per image size and ``res``) in a parallel kernel: the per-frame path.

    Returns
    -------
    (6, res, res, 3) float64
        ``L_s`` averaged over each texel's solid angle (faces +X, -X, +Y, -Y, +Z, -Z).

    Notes
    -----
    With ``s x s`` sub-texels ``d_q`` of solid angle ``w_q`` per texel and the
    bilinear interpolant ``L(d) = sum_p b_p(d) I_p`` of the equirect pixels,
    ``C_t = sum_q w_q L(d_q) / sum_q w_q = sum_p (sum_q w_q b_p(d_q) / sum_q w_q) I_p``:
    the taps are the pixels ``p`` and their bracketed weights.
    """
    if method not in ("numba", "reference"):
        raise ValueError(f"method must be 'numba' or 'reference', got {method!r}")
    if isinstance(res, bool) or not isinstance(res, (int, np.integer)) or res < 1 or (res & (res - 1)):
        raise ValueError(f"res must be a power of two >= 1 (Haar on the faces), got {res!r}")
    res = int(res)
    if isinstance(source, EnvironmentLight):
        if source.constant is not None:
            source = np.asarray(source.constant, dtype=np.float64)
        else:
            source = source.image
    arr = np.asarray(source, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError("shell light source has NaN or infinite values; clean the environment first")
    if arr.shape == (3,):
        return np.broadcast_to(arr, (6, res, res, 3)).copy()
    if arr.ndim == 4 and arr.shape[0] == 6 and arr.shape[-1] == 3:
        if arr.shape[1:3] != (res, res):
            raise ValueError(f"a cubemap source must have shape (6, {res}, {res}, 3), got {arr.shape}")
        return arr.copy()
    if arr.ndim == 3 and arr.shape[-1] == 3:
        if method == "reference" or arr.shape[0] < 2:
            return equirect_to_cubemap(arr, res)
        taps, weights = _resampling_taps(arr.shape[0], arr.shape[1], res)
        out = np.empty((6 * res * res, 3))
        _kernels.shell_resample_kernel(np.ascontiguousarray(arr.reshape(-1, 3)), taps, weights, out)
        return out.reshape(6, res, res, 3)
    raise ValueError(
        "source must be an EnvironmentLight, an (H, W, 3) equirect image, a (6, r, r, 3) cubemap or a (3,) "
        f"constant, got shape {arr.shape}"
    )


@lru_cache(maxsize=8)
def _resampling_taps(height: int, width: int, res: int) -> tuple[np.ndarray, np.ndarray]:
    """Taps ``(6 res^2, 4 s^2)`` (flat pixel indices, weights) of :func:`prtlab.scene.equirect_to_cubemap`.

    The sub-texel count ``s = max(2, ceil(W / (4 res)))`` and the bilinear rule
    are those of :func:`prtlab.scene.equirect_to_cubemap` and
    :func:`prtlab.geometry.equirect_lookup` (held to them by the tests).
    """
    s = max(2, -(-width // (4 * res)))
    fine = res * s
    idx, bil = equirect_taps(cubemap_directions(fine), height, width)
    w = cubemap_solid_angles(fine)
    bil = bil * w[..., None]

    def per_texel(a):  # (6, fine, fine, 4) -> (6 res^2, 4 s^2), sub-texels of one texel together
        return np.ascontiguousarray(a.reshape(6, res, s, res, s, 4).transpose(0, 1, 3, 2, 4, 5).reshape(6 * res * res, -1))

    taps = per_texel(idx)
    weights = per_texel(bil)
    weights /= per_texel(np.broadcast_to(w[..., None], idx.shape)).sum(axis=1, keepdims=True) / 4.0
    for a in (taps, weights):
        a.setflags(write=False)
    return taps, weights


def shell_sh(cube, order: int) -> np.ndarray:
    """SH coefficients ``c_lm = int L_s(w) Y_lm(w) dw`` of a shell cubemap, ``(order**2, 3)``.

    Quadrature over the texel centres with their exact solid angles (texel
    averages times the basis at the centre: exact for a light constant per texel
    up to the basis variation within a texel).
    """
    cube = np.asarray(cube, dtype=np.float64)
    if cube.ndim != 4 or cube.shape[0] != 6 or cube.shape[-1] != 3 or cube.shape[1] != cube.shape[2]:
        raise ValueError(f"cube must have shape (6, r, r, 3), got {cube.shape}; build it with shell_light")
    return _projection(cube.shape[1], check_order(order)) @ cube.reshape(-1, 3)


@lru_cache(maxsize=16)
def _projection(res: int, order: int) -> np.ndarray:
    """(order**2, 6 res**2) quadrature matrix ``Y_lm(w_k) dw_k`` over texel centres (cached per frame size)."""
    import prtlab.sh as sh

    dirs = cubemap_directions(res).reshape(-1, 3)
    w = cubemap_solid_angles(res).reshape(-1)
    out = np.ascontiguousarray(sh.basis(dirs, order).T * w[None, :])
    out.setflags(write=False)
    return out


def tint(cube, colour) -> np.ndarray:
    """A coloured glass: ``L_s' = colour * L_s`` (Section 3.3)."""
    colour = np.asarray(colour, dtype=np.float64)
    if colour.shape != (3,) or np.any(colour < 0) or not np.all(np.isfinite(colour)):
        raise ValueError(f"colour must be a finite non-negative (3,) RGB factor, got {colour!r}")
    return np.asarray(cube, dtype=np.float64) * colour


def frosted(cube, sigma_deg: float) -> np.ndarray:
    """Frosted glass as a blur of the shell's light (Section 3.3).

    ``L_s'(w) = sum_k K(w . w_k) L_s(w_k) dw_k / sum_k K(w . w_k) dw_k`` with the
    spherical Gaussian ``K(mu) = exp((mu - 1) / s^2)``, ``s = sigma_deg`` in radians
    (angular standard deviation for small angles), over all texels ``w_k``.
    Energy is preserved up to the normalisation per output texel.
    """
    cube = np.asarray(cube, dtype=np.float64)
    if cube.ndim != 4 or cube.shape[0] != 6 or cube.shape[-1] != 3:
        raise ValueError(f"cube must have shape (6, r, r, 3), got {cube.shape}")
    if not (np.isfinite(sigma_deg) and sigma_deg > 0):
        raise ValueError(f"sigma_deg must be a positive angle in degrees, got {sigma_deg!r}")
    res = cube.shape[1]
    dirs = cubemap_directions(res).reshape(-1, 3)
    w = cubemap_solid_angles(res).reshape(-1)
    s2 = np.radians(sigma_deg) ** 2
    flat = cube.reshape(-1, 3)
    out = np.empty_like(flat)
    for start in range(0, len(dirs), 512):  # rows of the kernel in blocks: bounded memory
        kernel = np.exp((dirs[start : start + 512] @ dirs.T - 1.0) / s2) * w[None, :]
        out[start : start + 512] = (kernel @ flat) / kernel.sum(axis=1, keepdims=True)
    return out.reshape(cube.shape)
