"""Pixel <-> direction maps of the two sphere images prtlab uses.

Everything in prtlab that reads or writes an equirectangular map or a cubemap
goes through these functions, so the conventions live in exactly one place.

Equirectangular (exactly Mitsuba 3's ``envmap``)
    ``u = atan2(x, -z) / (2 pi)`` wrapped to [0, 1), ``v = acos(y) / pi``.
    Pixels are *samples* of a bilinear function: column ``j`` sits at
    ``u = (j + 0.5) / W`` (wrapping in u), row ``i`` at ``v = i / (H - 1)``;
    row 0 is the +Y pole, row ``H - 1`` the -Y pole.

Cubemap (OpenGL face orientation)
    Faces in the order +X, -X, +Y, -Y, +Z, -Z, each ``(res, res)`` indexed
    ``[i, j]`` with ``i`` the row (the GL ``t`` coordinate) and ``j`` the column
    (the GL ``s`` coordinate); texel centres at ``s = (j + 0.5) / res``,
    ``t = (i + 0.5) / res``. With ``sc = 2 s - 1`` and ``tc = 2 t - 1`` the
    face directions (before normalisation) are::

        +X: ( 1, -tc, -sc)   -X: (-1, -tc,  sc)
        +Y: (sc,   1,  tc)   -Y: (sc,  -1, -tc)
        +Z: (sc, -tc,   1)   -Z: (-sc, -tc, -1)
"""

from __future__ import annotations

import numpy as np

from prtlab._validate import as_directions

__all__ = [
    "equirect_directions",
    "equirect_solid_angles",
    "direction_to_equirect",
    "equirect_lookup",
    "equirect_taps",
    "cubemap_directions",
    "cubemap_solid_angles",
    "direction_to_cubemap",
    "cubemap_lookup",
    "CUBE_FACES",
]

CUBE_FACES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


def _check_equirect_shape(height: int, width: int) -> None:
    if int(height) < 2 or int(width) < 1:
        raise ValueError(f"an equirectangular map needs height >= 2 and width >= 1, got ({height}, {width})")


# --------------------------------------------------------------------------- equirect


def _equirect_angles(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The polar angle ``theta`` (height,) of each row and the azimuth ``phi`` (width,) of each column."""
    return np.pi * np.arange(height) / (height - 1), 2.0 * np.pi * (np.arange(width) + 0.5) / width


def _angles_to_directions(theta, phi) -> np.ndarray:
    """Unit directions ``(sin t sin phi, cos t, -sin t cos phi)`` (..., 3) of the equirect convention at polar
    angles ``theta`` and azimuths ``phi``, broadcast against each other."""
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(st * np.sin(phi), np.cos(theta), -st * np.cos(phi)), axis=-1)


def equirect_directions(height: int, width: int) -> np.ndarray:
    """Directions of the pixel samples of an equirectangular map.

    Returns
    -------
    dirs : (height, width, 3) float64
    """
    _check_equirect_shape(height, width)
    theta, phi = _equirect_angles(height, width)
    return _angles_to_directions(theta[:, None], phi[None, :])


def equirect_solid_angles(height: int, width: int) -> np.ndarray:
    """Quadrature weights (steradians) of the pixels of an equirectangular map.

    The map is the bilinear interpolant of its pixel samples, so the weight of
    row ``i`` is ``(2 pi / W) * int hat_i(theta) sin(theta) dtheta`` with
    ``hat_i`` the tent function of the row. In closed form, with
    ``h = pi / (H - 1)``::

        w_i = (2 pi / W) (2 sin t_i - sin t_(i-1) - sin t_(i+1)) / h   (interior rows)
        w_0 = w_(H-1) = (2 pi / W) (1 - sin(h) / h)                    (pole rows)

    The weights sum to ``4 pi`` exactly, and integrate the bilinear interpolant
    of a function that is constant along rows exactly.

    Returns
    -------
    weights : (height, width) float64
    """
    _check_equirect_shape(height, width)
    h = np.pi / (height - 1)
    theta = h * np.arange(height)
    s = np.sin(theta)
    row = np.empty(height)
    row[0] = row[-1] = 1.0 - np.sin(h) / h
    if height > 2:
        row[1:-1] = (2.0 * s[1:-1] - s[:-2] - s[2:]) / h
    return np.repeat((2.0 * np.pi / width * row)[:, None], width, axis=1)


def direction_to_equirect(dirs) -> tuple[np.ndarray, np.ndarray]:
    """Map directions to equirectangular texture coordinates.

    Parameters
    ----------
    dirs : (..., 3) float
        Unit directions.

    Returns
    -------
    u : (...) float64 in [0, 1)
    v : (...) float64 in [0, 1]
    """
    dirs = as_directions(dirs, normalize=False)
    u = np.arctan2(dirs[..., 0], -dirs[..., 2]) / (2.0 * np.pi)
    u = u - np.floor(u)
    u = np.where(u >= 1.0, 0.0, u)
    v = np.arccos(np.clip(dirs[..., 1], -1.0, 1.0)) / np.pi
    return u, v


def equirect_taps(dirs, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The four texels and bilinear weights of :func:`equirect_lookup` in the given directions.

    Parameters
    ----------
    dirs : (..., 3) float
    height, width : int
        Size of the equirectangular map.

    Returns
    -------
    index : (..., 4) int64
        Flat texel indices ``y W + x`` (the map's rows wrap in ``x``; ``y`` is clamped).
    weight : (..., 4) float64
        Bilinear weights, summing to 1.
    """
    _check_equirect_shape(height, width)
    u, v = direction_to_equirect(dirs)
    fx = u * width - 0.5
    fy = v * (height - 1)
    x0 = np.floor(fx)
    y0 = np.clip(np.floor(fy), 0, height - 2)
    ax, ay = fx - x0, fy - y0
    x0 = x0.astype(np.int64) % width
    x1 = (x0 + 1) % width
    y0 = y0.astype(np.int64)
    y1 = y0 + 1
    index = np.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], axis=-1)
    weight = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], axis=-1)
    return index, weight


def equirect_lookup(image, dirs) -> np.ndarray:
    """Bilinear lookup of an equirectangular map in the given directions.

    Parameters
    ----------
    image : (H, W) or (H, W, C) float
    dirs : (..., 3) float

    Returns
    -------
    values : (...) or (..., C) float64
    """
    image = np.asarray(image, dtype=np.float64)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {image.shape}")
    height, width = image.shape[:2]
    index, weight = equirect_taps(dirs, height, width)
    texels = image.reshape((height * width,) + image.shape[2:])[index]  # (..., 4) or (..., 4, C)
    if image.ndim == 3:
        weight = weight[..., None]
    return np.sum(weight * texels, axis=-2 if image.ndim == 3 else -1)


# --------------------------------------------------------------------------- cubemap


def _face_directions(face: int, sc: np.ndarray, tc: np.ndarray) -> np.ndarray:
    one = np.ones_like(sc)
    table = {
        0: (one, -tc, -sc),
        1: (-one, -tc, sc),
        2: (sc, one, tc),
        3: (sc, -one, -tc),
        4: (sc, -tc, one),
        5: (-sc, -tc, -one),
    }
    return np.stack(table[face], axis=-1)


def cubemap_directions(res: int, normalize: bool = True) -> np.ndarray:
    """Directions through the texel centres of a cubemap.

    Returns
    -------
    dirs : (6, res, res, 3) float64
        Unit vectors (or points on the cube ``max(|x|,|y|,|z|) = 1`` if
        ``normalize=False``).
    """
    res = int(res)
    if res < 1:
        raise ValueError(f"cubemap resolution must be >= 1, got {res}")
    c = 2.0 * (np.arange(res) + 0.5) / res - 1.0
    tc, sc = np.meshgrid(c, c, indexing="ij")
    dirs = np.stack([_face_directions(f, sc, tc) for f in range(6)])
    if normalize:
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    return dirs


def cubemap_solid_angles(res: int) -> np.ndarray:
    """Exact solid angle of every cubemap texel.

    With ``F(x, y) = atan2(x y, sqrt(x^2 + y^2 + 1))`` the solid angle of the
    face rectangle ``[x0, x1] x [y0, y1]`` is
    ``F(x1, y1) - F(x0, y1) - F(x1, y0) + F(x0, y0)``; the texels sum to ``4 pi``.

    Returns
    -------
    omega : (6, res, res) float64
    """
    res = int(res)
    if res < 1:
        raise ValueError(f"cubemap resolution must be >= 1, got {res}")
    edges = 2.0 * np.arange(res + 1) / res - 1.0
    y, x = np.meshgrid(edges, edges, indexing="ij")
    big_f = np.arctan2(x * y, np.sqrt(x * x + y * y + 1.0))
    omega = big_f[1:, 1:] - big_f[:-1, 1:] - big_f[1:, :-1] + big_f[:-1, :-1]
    return np.broadcast_to(omega, (6, res, res)).copy()


def direction_to_cubemap(dirs, res: int | None = None):
    """Map directions to cubemap faces and face coordinates.

    Parameters
    ----------
    dirs : (..., 3) float
        Directions (need not be normalised; must be non-zero).
    res : int, optional
        If given, also return the integer texel row and column.

    Returns
    -------
    face : (...) int64 in 0..5 (order +X, -X, +Y, -Y, +Z, -Z)
    s, t : (...) float64 in [0, 1]
        Continuous face coordinates (column, row).
    i, j : (...) int64, only if ``res`` is given
        Texel row ``floor(t * res)`` and column ``floor(s * res)``, clamped.
    """
    d = as_directions(dirs, normalize=False)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    ax, ay, az = np.abs(x), np.abs(y), np.abs(z)
    xmajor = (ax >= ay) & (ax >= az)
    ymajor = ~xmajor & (ay >= az)
    face = np.where(xmajor, np.where(x >= 0, 0, 1), np.where(ymajor, np.where(y >= 0, 2, 3), np.where(z >= 0, 4, 5)))
    ma = np.where(xmajor, ax, np.where(ymajor, ay, az))
    with np.errstate(divide="ignore", invalid="ignore"):
        sc = np.select(
            [face == 0, face == 1, face == 2, face == 3, face == 4, face == 5],
            [-z, z, x, x, x, -x],
        ) / ma
        tc = np.select(
            [face == 0, face == 1, face == 2, face == 3, face == 4, face == 5],
            [-y, -y, z, -z, -y, -y],
        ) / ma
    s = np.clip(0.5 * (sc + 1.0), 0.0, 1.0)
    t = np.clip(0.5 * (tc + 1.0), 0.0, 1.0)
    face = face.astype(np.int64)
    if res is None:
        return face, s, t
    i = np.minimum((t * res).astype(np.int64), res - 1)
    j = np.minimum((s * res).astype(np.int64), res - 1)
    return face, s, t, i, j


def cubemap_lookup(faces, dirs) -> np.ndarray:
    """Nearest-texel lookup of a cubemap in the given directions.

    Parameters
    ----------
    faces : (6, res, res) or (6, res, res, C) float
    dirs : (..., 3) float

    Returns
    -------
    values : (...) or (..., C) float64
    """
    faces = np.asarray(faces, dtype=np.float64)
    if faces.ndim not in (3, 4) or faces.shape[0] != 6 or faces.shape[1] != faces.shape[2]:
        raise ValueError(f"faces must be (6, res, res[, C]), got shape {faces.shape}")
    face, _, _, i, j = direction_to_cubemap(dirs, faces.shape[1])
    return faces[face, i, j]
