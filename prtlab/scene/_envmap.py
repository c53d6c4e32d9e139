"""Environment maps: EXR / Radiance HDR files, the Preetham sky, constant maps,
equirect <-> cubemap resampling and SH projection.

Every map is an equirectangular ``(H, W, 3)`` float64 image of linear RGB
radiance in the convention of :mod:`prtlab.geometry` (exactly Mitsuba 3's
``envmap``): ``u = atan2(x, -z) / (2 pi)``, ``v = acos(y) / pi``, column ``j``
at ``u = (j + 0.5) / W``, row ``i`` at ``v = i / (H - 1)``. Pixel <-> direction
maps come only from :mod:`prtlab.geometry`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from prtlab.data import path as data_path
from prtlab._validate import check_int, check_order
from prtlab.geometry import (
    cubemap_directions,
    cubemap_lookup,
    cubemap_solid_angles,
    equirect_directions,
    equirect_lookup,
    equirect_solid_angles,
)
from prtlab.geometry._spheremaps import _angles_to_directions

__all__ = [
    "read_envmap",
    "read_exr",
    "write_exr",
    "read_hdr",
    "write_hdr",
    "sun_direction",
    "preetham_zenith_xyY",
    "preetham_sky_xyY",
    "preetham_sky_radiance",
    "preetham_sun_radiance",
    "preetham_sky",
    "constant_envmap",
    "xyY_to_linear_srgb",
    "equirect_to_cubemap",
    "cubemap_to_equirect",
    "environment_sh",
    "SUN_ANGULAR_RADIUS_DEG",
]

# --------------------------------------------------------------------------- helpers


def _as_image(image, name: str = "image") -> np.ndarray:
    image = np.asarray(image)
    if image.dtype.kind not in "fiu":
        raise TypeError(f"{name} must be a real array, got dtype {image.dtype}")
    image = image.astype(np.float64, copy=False)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"{name} must be an (H, W, 3) RGB image, got shape {image.shape}")
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{name} contains NaN or inf; radiance must be finite")
    return image


# --------------------------------------------------------------------------- files


#: 8-bit image formats, refused as environment maps: they hold display values, not radiance.
_LDR_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".gif", ".webp", ".tga", ".ppm")
#: Largest map read, in pixels (16384 x 8192; 3.2 GB as float64 RGB).
MAX_MAP_PIXELS = 16384 * 8192


def read_envmap(path) -> np.ndarray:
    """Read an environment map file (``.exr`` or Radiance ``.hdr`` / ``.pic``).

    8-bit images (PNG, JPEG, ...) are refused: they store display values
    (gamma-encoded, clipped), from which radiance cannot be recovered.

    Returns
    -------
    image : (H, W, 3) float64
        Linear RGB, rows and columns as stored (the file must already be in
        the equirect convention of this module).
    """
    path = Path(os.fspath(path))
    suffix = path.suffix.lower()
    if suffix == ".exr":
        return read_exr(path)
    if suffix in (".hdr", ".pic", ".rgbe"):
        return read_hdr(path)
    if suffix in _LDR_SUFFIXES:
        raise ValueError(
            f"cannot use {str(path)!r} as an environment map: {suffix} images hold 8-bit display values "
            "(gamma-encoded, clipped at white), not linear radiance; convert the HDR original to OpenEXR (.exr) "
            "or Radiance RGBE (.hdr)"
        )
    raise ValueError(
        f"cannot read environment map {str(path)!r}: unknown extension {suffix!r}; "
        "use an OpenEXR (.exr) or Radiance RGBE (.hdr) file"
    )


def _existing_file(path, kind: str) -> Path:
    """``path`` as a Path; FileNotFoundError naming ``kind`` if it is not a file."""
    path = Path(os.fspath(path))
    if not path.is_file():
        raise FileNotFoundError(f"{kind} file not found: {str(path)!r}")
    return path


def read_exr(path) -> np.ndarray:
    """Read the R, G, B (or Y) channels of an OpenEXR file.

    Returns
    -------
    image : (H, W, 3) float64
    """
    import OpenEXR

    path = _existing_file(path, "EXR")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as err:  # OpenEXR raises RuntimeError and others for truncated or foreign files
        raise ValueError(f"cannot read EXR file {str(path)!r} (truncated, or not OpenEXR?): {err}") from err
    if all(c in channels for c in "RGB"):
        image = np.stack([channels[c] for c in "RGB"], axis=-1)
    elif "Y" in channels:
        image = np.repeat(channels["Y"][..., None], 3, axis=-1)
    else:
        raise ValueError(
            f"EXR file {str(path)!r} has channels {sorted(channels)}; need R, G, B (or Y)"
        )
    return image.astype(np.float64)


def write_exr(path, image, half: bool = False) -> Path:
    """Write an ``(H, W, 3)`` image as a ZIP-compressed scanline OpenEXR file.

    Parameters
    ----------
    path : str or path-like
    image : (H, W, 3) float
        Linear RGB; stored as float32 (or float16 if ``half``), so float64 input
        is rounded to float32 (relative error <= 2**-24).
    half : bool
        Store 16-bit half floats.
    """
    import OpenEXR

    image = _as_image(image)
    pixels = np.ascontiguousarray(image.astype(np.float16 if half else np.float32))
    path = Path(os.fspath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": pixels}).write(str(path))
    return path


# Radiance RGBE. imageio cannot read .hdr without downloading the FreeImage
# binary at run time (its own plugins do not handle RGBE), and prtlab must not
# download anything, so this is a small reader/writer of the format described
# in G. Ward, "Real Pixels", Graphics Gems II (1991), and Radiance's color.c.


def _rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """(..., 4) uint8 RGBE -> (..., 3) float64: ``m * 2^(e - 136)``, 0 if ``e = 0``."""
    e = rgbe[..., 3].astype(np.int64)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return rgbe[..., :3].astype(np.float64) * scale[..., None]


def _float_to_rgbe(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) non-negative float -> (..., 4) uint8 RGBE (values below 1e-32 become 0)."""
    v = rgb.max(axis=-1)
    mant, exp = np.frexp(v)
    out = np.zeros(rgb.shape[:-1] + (4,), dtype=np.uint8)
    ok = v >= 1e-32
    scale = np.where(ok, mant * 256.0 / np.where(ok, v, 1.0), 0.0)
    out[..., :3] = np.where(ok[..., None], np.floor(rgb * scale[..., None]), 0).astype(np.uint8)
    out[..., 3] = np.where(ok, exp + 128, 0).astype(np.uint8)
    return out


def read_hdr(path) -> np.ndarray:
    """Read a Radiance RGBE (``.hdr``) file: flat or new-style run-length encoded.

    Only the standard orientation ``-Y H +X W`` (rows top to bottom, columns
    left to right) is accepted.

    Returns
    -------
    image : (H, W, 3) float64
    """
    path = _existing_file(path, "HDR")
    data = path.read_bytes()
    where = f"HDR file {str(path)!r}"
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise ValueError(f"{where} does not start with '#?RADIANCE' or '#?RGBE'")
    height, width, pos = _hdr_header(data, where)
    if len(data) - pos < 4 * height:  # every scanline takes at least 4 bytes
        raise ValueError(f"{where}: truncated ({len(data) - pos} bytes of pixel data for {height} rows)")
    body = np.frombuffer(data, dtype=np.uint8, offset=pos)
    rgbe = np.empty((height, width, 4), dtype=np.uint8)
    k = 0
    try:
        for row in range(height):
            new_rle = (
                8 <= width < 32768
                and body[k] == 2
                and body[k + 1] == 2
                and (int(body[k + 2]) << 8 | int(body[k + 3])) == width
                and not body[k + 2] & 0x80
            )
            if not new_rle:  # flat scanline, possibly with old-style (1, 1, 1, n) repeat codes
                flat = body[k : k + 4 * width]
                flat = flat[: len(flat) // 4 * 4].reshape(-1, 4)
                if len(flat) == width and not np.any((flat[:, 0] == 1) & (flat[:, 1] == 1) & (flat[:, 2] == 1)):
                    rgbe[row] = flat
                    k += 4 * width
                else:
                    k = _read_old_rle(body, k, rgbe[row])
                continue
            k = _read_new_rle(body, k + 4, rgbe[row])
    except (IndexError, ValueError) as err:
        raise ValueError(f"{where}: corrupt or truncated pixel data at row {row} ({err})") from err
    return _rgbe_to_float(rgbe)


def _hdr_header(data: bytes, where: str) -> tuple[int, int, int]:
    """``(height, width, offset of the pixel data)`` from a Radiance header and its ``-Y H +X W`` line."""
    pos = 0
    fmt = None
    while True:  # header lines up to an empty line
        end = data.find(b"\n", pos)
        if end < 0:
            raise ValueError(f"{where}: header has no end (missing empty line)")
        line = data[pos:end].strip()
        pos = end + 1
        if not line:
            break
        if line.startswith(b"FORMAT="):
            fmt = line[7:].decode("ascii", "replace")
    if fmt not in (None, "32-bit_rle_rgbe"):
        raise ValueError(f"{where}: unsupported FORMAT={fmt}; only 32-bit_rle_rgbe is read")
    end = data.find(b"\n", pos)
    tokens = data[pos:end].split()
    pos = end + 1
    if len(tokens) != 4 or tokens[0] != b"-Y" or tokens[2] != b"+X":
        raise ValueError(
            f"{where}: unsupported resolution line {b' '.join(tokens)!r}; expected '-Y H +X W'"
        )
    if not (tokens[1].isdigit() and tokens[3].isdigit()):
        raise ValueError(f"{where}: unsupported resolution line {b' '.join(tokens)!r}; expected '-Y H +X W'")
    height, width = int(tokens[1]), int(tokens[3])
    if not (height >= 1 and width >= 1 and height * width <= MAX_MAP_PIXELS):
        raise ValueError(f"{where}: {width} x {height} pixels; expected 1 to {MAX_MAP_PIXELS:,} pixels")
    return height, width, pos


def _read_new_rle(body: np.ndarray, k: int, scanline: np.ndarray) -> int:
    """Decode the four run-length encoded channels of one new-style scanline (its 4-byte marker read) into
    ``scanline (W, 4)``; return the next byte offset."""
    width = scanline.shape[0]
    for c in range(4):
        x = 0
        line = scanline[:, c]
        while x < width:
            count = int(body[k])
            k += 1
            if count > 128:  # a run
                count -= 128
                line[x : x + count] = body[k]
                k += 1
            else:  # literal bytes
                if count == 0:
                    raise ValueError("zero-length literal")
                line[x : x + count] = body[k : k + count]
                k += count
            x += count
        if x != width:
            raise ValueError("scanline overrun")
    return k


def _read_old_rle(body: np.ndarray, k: int, line: np.ndarray) -> int:
    """Decode one scanline of old-style RLE into ``line`` (W, 4); return the next byte offset.

    A pixel ``(1, 1, 1, n)`` repeats the previous pixel ``n << shift`` times,
    ``shift`` growing by 8 for consecutive repeat codes (Radiance's ``oldreadcolrs``).
    """
    width = len(line)
    x = 0
    shift = 0
    while x < width:
        pixel = body[k : k + 4]
        if len(pixel) < 4:
            raise ValueError("truncated scanline")
        k += 4
        if pixel[0] == 1 and pixel[1] == 1 and pixel[2] == 1:
            if x == 0:
                raise ValueError("repeat code at the start of a scanline")
            count = int(pixel[3]) << shift
            if x + count > width:
                raise ValueError("scanline overrun")
            line[x : x + count] = line[x - 1]
            x += count
            shift += 8
        else:
            line[x] = pixel
            x += 1
            shift = 0
    return k


def write_hdr(path, image, rle: bool = True) -> Path:
    """Write an ``(H, W, 3)`` non-negative image as a Radiance RGBE file.

    RGBE keeps about 8 significant bits: each component is stored with the
    exponent of the largest one, so the absolute error of every component is
    below ``max(r, g, b) / 128``.
    """
    image = _as_image(image)
    if np.any(image < 0):
        raise ValueError("image has negative values; RGBE stores non-negative radiance only")
    height, width = image.shape[:2]
    rgbe = _float_to_rgbe(image)
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n")
    out += f"-Y {height} +X {width}\n".encode("ascii")
    use_rle = rle and 8 <= width < 32768
    for row in range(height):
        if not use_rle:
            out += rgbe[row].tobytes()
            continue
        out += bytes([2, 2, width >> 8, width & 0xFF])
        for c in range(4):
            out += _rle_encode(rgbe[row, :, c])
    path = Path(os.fspath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(bytes(out))
    return path


def _rle_encode(line: np.ndarray) -> bytes:
    """New-style Radiance run-length code of one channel of one scanline."""
    out = bytearray()
    n = len(line)
    x = 0
    literal_start = 0
    while x < n:
        run = 1
        while x + run < n and run < 127 and line[x + run] == line[x]:
            run += 1
        if run >= 4:
            while literal_start < x:  # flush pending literals
                count = min(128, x - literal_start)
                out.append(count)
                out += line[literal_start : literal_start + count].tobytes()
                literal_start += count
            out += bytes([128 + run, int(line[x])])
            x += run
            literal_start = x
        else:
            x += run
    while literal_start < n:
        count = min(128, n - literal_start)
        out.append(count)
        out += line[literal_start : literal_start + count].tobytes()
        literal_start += count
    return bytes(out)


# --------------------------------------------------------------------------- colour

# CIE XYZ -> linear sRGB (D65 white), IEC 61966-2-1.
_XYZ_TO_SRGB = np.array(
    [
        [3.2404542, -1.5371385, -0.4985314],
        [-0.9692660, 1.8760108, 0.0415560],
        [0.0556434, -0.2040259, 1.0572252],
    ]
)


def xyY_to_linear_srgb(xyY) -> np.ndarray:
    """CIE xyY (..., 3) -> linear sRGB (..., 3), D65; ``Y = 0`` gives black.

    ``X = x Y / y``, ``Z = (1 - x - y) Y / y``, then the sRGB matrix. Out of
    gamut colours can have negative components; callers clip if they need to.
    """
    xyY = np.asarray(xyY, dtype=np.float64)
    x, y, big_y = xyY[..., 0], xyY[..., 1], xyY[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(y > 0, big_y / np.where(y > 0, y, 1.0), 0.0)
    xyz = np.stack([x * ratio, big_y, (1.0 - x - y) * ratio], axis=-1)
    return xyz @ _XYZ_TO_SRGB.T


# --------------------------------------------------------------------------- Preetham sky

#: Perez coefficients ``A..E = a * T + b`` for Y, x, y (Preetham et al. 1999, Appendix A.2).
_PEREZ_Y = np.array([[0.1787, -1.4630], [-0.3554, 0.4275], [-0.0227, 5.3251], [0.1206, -2.5771], [-0.0670, 0.3703]])
_PEREZ_X = np.array([[-0.0193, -0.2592], [-0.0665, 0.0008], [-0.0004, 0.2125], [-0.0641, -0.8989], [-0.0033, 0.0452]])
_PEREZ_Y_CHROMA = np.array(
    [[-0.0167, -0.2608], [-0.0950, 0.0092], [-0.0079, 0.2102], [-0.0441, -1.6537], [-0.0109, 0.0529]]
)
#: Zenith chromaticity: ``x_z = [T^2, T, 1] M [theta_s^3, theta_s^2, theta_s, 1]^T`` (Appendix A.2).
_ZENITH_X = np.array(
    [[0.00166, -0.00375, 0.00209, 0.0], [-0.02903, 0.06377, -0.03202, 0.00394], [0.11693, -0.21196, 0.06052, 0.25886]]
)
_ZENITH_Y = np.array(
    [[0.00275, -0.00610, 0.00317, 0.0], [-0.04214, 0.08970, -0.04153, 0.00516], [0.15346, -0.26756, 0.06670, 0.26688]]
)

#: Angular radius of the sun disk added by ``sun=True`` (the sun's mean apparent radius).
SUN_ANGULAR_RADIUS_DEG = 0.2667


def _check_sky_parameters(sun_elevation_deg, sun_azimuth_deg, turbidity) -> tuple[float, float, float]:
    values = []
    for name, value in (
        ("sun_elevation_deg", sun_elevation_deg),
        ("sun_azimuth_deg", sun_azimuth_deg),
        ("turbidity", turbidity),
    ):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise TypeError(f"{name} must be a number, got {value!r}")
        if not math.isfinite(float(value)):
            raise ValueError(f"{name} must be finite, got {value!r}")
        values.append(float(value))
    elevation, azimuth, t = values
    if not 0.0 <= elevation <= 90.0:
        raise ValueError(
            f"sun_elevation_deg must be in [0, 90] (the Preetham model needs the sun above the "
            f"horizon), got {sun_elevation_deg!r}"
        )
    if not 1.7 <= t <= 10.0:
        raise ValueError(
            f"turbidity must be in [1.7, 10] (the range the Preetham model was fitted on), got {turbidity!r}"
        )
    return elevation, azimuth, t


def sun_direction(sun_elevation_deg: float, sun_azimuth_deg: float) -> np.ndarray:
    """Unit direction toward the sun, (3,).

    Azimuth 0 is -Z and 90 is +X (so the sun sits at ``u = azimuth / 360`` of
    the equirect map); elevation is measured up from the horizon (+Y up)::

        d = (cos e sin a, sin e, -cos e cos a)
    """
    e, a = np.radians(float(sun_elevation_deg)), np.radians(float(sun_azimuth_deg))
    return np.array([np.cos(e) * np.sin(a), np.sin(e), -np.cos(e) * np.cos(a)])


def _perez(coeffs: np.ndarray, cos_theta: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Perez et al. 1993 distribution ``(1 + A e^(B / cos theta)) (1 + C e^(D gamma) + E cos^2 gamma)``."""
    a, b, c, d, e = coeffs
    with np.errstate(divide="ignore", over="ignore"):
        ratio = np.where(cos_theta > 0, b / np.where(cos_theta > 0, cos_theta, 1.0), -np.inf)
    return (1.0 + a * np.exp(ratio)) * (1.0 + c * np.exp(d * gamma) + e * np.cos(gamma) ** 2)


def preetham_zenith_xyY(sun_zenith: float, turbidity: float) -> np.ndarray:
    """Zenith chromaticity and luminance of the Preetham sky, (3,) = (x, y, Y).

    ``Y_z = (4.0453 T - 4.9710) tan(chi) - 0.2155 T + 2.4192`` in kcd/m^2 with
    ``chi = (4/9 - T/120)(pi - 2 theta_s)``; ``x_z``, ``y_z`` cubic in
    ``theta_s`` and quadratic in ``T``.

    References
    ----------
    A. J. Preetham, P. Shirley, B. Smits, "A Practical Analytic Model for
    Daylight", SIGGRAPH 1999, Appendix A.2.
    """
    t, ts = float(turbidity), float(sun_zenith)
    chi = (4.0 / 9.0 - t / 120.0) * (np.pi - 2.0 * ts)
    big_y = (4.0453 * t - 4.9710) * np.tan(chi) - 0.2155 * t + 2.4192
    tv = np.array([t * t, t, 1.0])
    thv = np.array([ts**3, ts**2, ts, 1.0])
    return np.array([tv @ _ZENITH_X @ thv, tv @ _ZENITH_Y @ thv, big_y])


def preetham_sky_xyY(dirs, sun_elevation_deg: float, sun_azimuth_deg: float = 0.0, turbidity: float = 3.0):
    """Preetham sky in CIE xyY for view directions ``dirs`` (..., 3).

    ``v(theta, gamma) = v_z F(theta, gamma) / F(0, theta_s)`` for each of
    ``v = Y, x, y`` with the Perez function ``F``, ``theta`` the zenith angle of
    the view direction, ``gamma`` its angle to the sun and ``theta_s`` the
    sun's zenith angle. Directions below the horizon (``y < 0``) get zero.

    Returns
    -------
    xyY : (..., 3) float64
        Chromaticity x, y and luminance Y in kcd/m^2.
    """
    elevation, azimuth, t = _check_sky_parameters(sun_elevation_deg, sun_azimuth_deg, turbidity)
    dirs = np.asarray(dirs, dtype=np.float64)
    if dirs.ndim == 0 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs must be a (..., 3) array of directions, got shape {dirs.shape}")
    if not np.all(np.isfinite(dirs)):
        raise ValueError("dirs contains NaN or inf")
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    sun = sun_direction(elevation, azimuth)
    theta_s = np.radians(90.0 - elevation)
    cos_theta = dirs[..., 1]
    gamma = np.arccos(np.clip(dirs @ sun, -1.0, 1.0))
    zenith = preetham_zenith_xyY(theta_s, t)
    out = np.zeros(dirs.shape[:-1] + (3,))
    above = cos_theta >= 0.0
    tv = np.array([t, 1.0])
    for k, table in enumerate((_PEREZ_X, _PEREZ_Y_CHROMA, _PEREZ_Y)):
        coeffs = table @ tv
        ratio = _perez(coeffs, cos_theta, gamma) / _perez(coeffs, np.cos(0.0), theta_s)
        out[..., k] = np.where(above, zenith[k] * ratio, 0.0)
    return out


def preetham_sky_radiance(dirs, sun_elevation_deg: float, sun_azimuth_deg: float = 0.0, turbidity: float = 3.0):
    """Preetham sky as linear sRGB radiance for view directions ``dirs`` (..., 3).

    The xyY value of :func:`preetham_sky_xyY` converted to linear sRGB (so the
    luminance ``0.2126 R + 0.7152 G + 0.0722 B`` equals Y in kcd/m^2), with
    negative (out of gamut) components clipped to zero.

    Returns
    -------
    rgb : (..., 3) float64
    """
    xyY = preetham_sky_xyY(dirs, sun_elevation_deg, sun_azimuth_deg, turbidity)
    return np.maximum(xyY_to_linear_srgb(xyY), 0.0)


def preetham_sun_radiance(sun_elevation_deg: float, turbidity: float = 3.0) -> np.ndarray:
    """Radiance of the sun disk after the atmosphere, linear sRGB (3,), in kcd/m^2 luminance units.

    The extraterrestrial solar spectrum attenuated by Rayleigh scattering and
    aerosols along the air mass ``m = 1 / (cos theta_s + 0.15 (93.885 - theta_s)^-1.253)``
    (Preetham et al. 1999, Appendix A.1, Kasten's air mass), integrated
    against the CIE 1931 matching functions, then converted to sRGB. Ozone,
    water vapour and mixed-gas absorption bands are left out (they change the
    result by a few percent).
    """
    elevation, _, t = _check_sky_parameters(sun_elevation_deg, 0.0, turbidity)
    return _sun_rgb(90.0 - elevation, t)


def preetham_sky(
    sun_elevation_deg: float,
    sun_azimuth_deg: float = 0.0,
    turbidity: float = 3.0,
    height: int = 128,
    width: int = 256,
    sun: bool = False,
) -> np.ndarray:
    """Rasterise the Preetham, Shirley, Smits (1999) analytic sky to an equirect map.

    Parameters
    ----------
    sun_elevation_deg : float in [0, 90]
        Sun elevation above the horizon.
    sun_azimuth_deg : float
        Azimuth: 0 -> -Z, 90 -> +X (the sun lies at column ``u = azimuth / 360``).
    turbidity : float in [1.7, 10]
        Atmospheric turbidity (2 very clear, 3 clear, 6+ hazy).
    height, width : int
        Map size (height >= 2).
    sun : bool
        Also add the sun disk (angular radius :data:`SUN_ANGULAR_RADIUS_DEG`)
        with the radiance of :func:`preetham_sun_radiance`. It covers less
        than a pixel at the default size, so it is spread over the pixels
        whose samples are nearest to the sun with the disk's total power
        (radiance times solid angle) preserved. Off by default.

    Returns
    -------
    image : (height, width, 3) float64
        Linear sRGB radiance, luminance in kcd/m^2 (use the light's ``scale``
        to change units); zero below the horizon (scenes have floors).

    References
    ----------
    A. J. Preetham, P. Shirley, B. Smits, "A Practical Analytic Model for
    Daylight", SIGGRAPH 1999, Sec. 3 and Appendix A.2 (Perez model, zenith
    values and turbidity-dependent coefficients).
    """
    height = check_int(height, "height", 2)
    width = check_int(width, "width", 1)
    dirs = equirect_directions(height, width)
    image = preetham_sky_radiance(dirs, sun_elevation_deg, sun_azimuth_deg, turbidity)
    if sun:
        image += _sun_disk(dirs, sun_elevation_deg, sun_azimuth_deg, turbidity, height, width)
    return image


# Sun spectrum (Preetham et al. 1999, Appendix A.1, table of the extraterrestrial
# solar spectral radiance S0 in W / (m^2 sr nm), tabulated at 380..750 nm) and
# CIE 1931 2-degree matching functions at the same wavelengths (prtlab/data/tables).
_WAVELENGTHS, _SOL, _CIE_X, _CIE_Y, _CIE_Z = np.loadtxt(data_path("tables", "sun_spectrum.csv"), delimiter=",").T


def _sun_rgb(sun_zenith_deg: float, turbidity: float) -> np.ndarray:
    theta = np.radians(sun_zenith_deg)
    air_mass = 1.0 / (np.cos(theta) + 0.15 * (93.885 - sun_zenith_deg) ** -1.253)
    lam_um = _WAVELENGTHS / 1000.0
    beta = 0.04608365822050 * turbidity - 0.04586025928522  # Angstrom turbidity coefficient
    alpha = 1.3  # ratio of small to large particle sizes
    tau_rayleigh = np.exp(-air_mass * 0.008735 * lam_um**-4.08)
    tau_aerosol = np.exp(-air_mass * beta * lam_um**-alpha)
    spectrum = _SOL * tau_rayleigh * tau_aerosol  # W / (m^2 sr nm)
    # luminance: 683 lm/W * int S(l) ybar(l) dl (10 nm steps), in kcd/m^2
    xyz = 683.0 * 10.0 * np.array([spectrum @ _CIE_X, spectrum @ _CIE_Y, spectrum @ _CIE_Z]) / 1000.0
    return np.maximum(_XYZ_TO_SRGB @ xyz, 0.0)


def _sun_disk(dirs, elevation, azimuth, turbidity, height, width) -> np.ndarray:
    """The sun disk's power deposited on the equirect pixels nearest the sun (bilinear splat)."""
    from prtlab.geometry import direction_to_equirect

    elevation, azimuth, turbidity = _check_sky_parameters(elevation, azimuth, turbidity)
    sun = sun_direction(elevation, azimuth)
    radiance = _sun_rgb(90.0 - elevation, turbidity)
    r = np.radians(SUN_ANGULAR_RADIUS_DEG)
    power = radiance * 2.0 * np.pi * (1.0 - np.cos(r))  # radiance * solid angle of the disk
    u, v = direction_to_equirect(sun)
    fx, fy = float(u) * width - 0.5, float(v) * (height - 1)
    x0, y0 = int(np.floor(fx)), min(int(np.floor(fy)), height - 2)
    ax, ay = fx - x0, fy - y0
    weights = equirect_solid_angles(height, width)
    out = np.zeros((height, width, 3))
    for dy, wy in ((0, 1.0 - ay), (1, ay)):
        for dx, wx in ((0, 1.0 - ax), (1, ax)):
            i, j = y0 + dy, (x0 + dx) % width
            out[i, j] += wx * wy * power / weights[i, j]
    return out


def constant_envmap(rgb, height: int = 8, width: int = 16) -> np.ndarray:
    """An ``(height, width, 3)`` map of constant radiance ``rgb`` (3,)."""
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.shape != (3,) or not np.all(np.isfinite(rgb)):
        raise ValueError(f"rgb must be 3 finite numbers, got {rgb!r}")
    height = check_int(height, "height", 2)
    width = check_int(width, "width", 1)
    return np.broadcast_to(rgb, (height, width, 3)).copy()


# --------------------------------------------------------------------------- resampling


def equirect_to_cubemap(image, res: int, supersample: int | None = None) -> np.ndarray:
    """Resample an equirect map to a cubemap of texel averages.

    Each texel gets the solid-angle weighted mean of the map's bilinear
    interpolant over the texel::

        C[f, i, j] = sum_k w_k L(d_k) / sum_k w_k

    over an ``s x s`` grid of sub-texels ``d_k`` (the texel centres of a
    ``res * s`` cubemap) with their exact solid angles ``w_k``
    (:func:`prtlab.geometry.cubemap_solid_angles`). The default ``s`` makes a
    sub-texel no wider than an equirect pixel: ``s = max(2, ceil(W / (4 res)))``.
    Integrals are preserved: ``sum C omega = int L`` up to the quadrature error.

    Parameters
    ----------
    image : (H, W, 3) float
    res : int
        Face resolution.
    supersample : int, optional

    Returns
    -------
    faces : (6, res, res, 3) float64
        Order +X, -X, +Y, -Y, +Z, -Z, OpenGL orientation.
    """
    image = _as_image(image)
    res = check_int(res, "res", 1)
    if supersample is None:
        supersample = max(2, math.ceil(image.shape[1] / (4 * res)))
    s = check_int(supersample, "supersample", 1)
    fine = res * s
    dirs = cubemap_directions(fine)
    weights = cubemap_solid_angles(fine)[..., None]
    values = equirect_lookup(image, dirs) * weights
    values = values.reshape(6, res, s, res, s, 3).sum(axis=(2, 4))
    total = weights.reshape(6, res, s, res, s, 1).sum(axis=(2, 4))
    return values / total


def cubemap_to_equirect(faces, height: int, width: int, supersample: int | None = None) -> np.ndarray:
    """Resample a cubemap to an equirect map of the prtlab convention.

    The equirect pixels are samples of a bilinear function, so each pixel
    gets the solid-angle weighted mean of the (piecewise constant) cubemap
    over the pixel's cell ``|theta - theta_i| <= h / 2``,
    ``|phi - phi_j| <= pi / W`` (``h = pi / (H - 1)``; the pole rows take the
    half cell next to the pole), evaluated on an ``s x s`` sub-grid with
    weights ``sin theta``. This box filter of one pixel removes the
    aliasing of the cube texels. Default ``s = max(2, ceil(4 res / W))``, so
    sub-samples are no wider than a cube texel.

    Parameters
    ----------
    faces : (6, res, res, 3) float
    height, width : int

    Returns
    -------
    image : (height, width, 3) float64
    """
    faces = np.asarray(faces, dtype=np.float64)
    if faces.ndim != 4 or faces.shape[0] != 6 or faces.shape[1] != faces.shape[2] or faces.shape[3] != 3:
        raise ValueError(f"faces must be a (6, res, res, 3) cubemap, got shape {faces.shape}")
    if not np.all(np.isfinite(faces)):
        raise ValueError("faces contains NaN or inf; radiance must be finite")
    height = check_int(height, "height", 2)
    width = check_int(width, "width", 1)
    res = faces.shape[1]
    if supersample is None:
        supersample = max(2, math.ceil(4 * res / width))
    s = check_int(supersample, "supersample", 1)
    # Sub-sample offsets (in units of a cell) inside [-1/2, 1/2]: midpoints of s equal parts.
    offsets = (np.arange(s) + 0.5) / s - 0.5
    h = np.pi / (height - 1)
    theta = h * (np.arange(height)[:, None] + offsets[None, :])  # (H, s)
    theta = np.clip(theta, 0.0, np.pi)  # pole rows: the half cell beyond the pole folds back
    theta[0] = h * 0.5 * (offsets + 0.5)  # row 0: [0, h/2]
    theta[-1] = np.pi - h * 0.5 * (offsets + 0.5)  # row H-1: [pi - h/2, pi]
    phi = 2.0 * np.pi * (np.arange(width)[:, None] + 0.5 + offsets[None, :]) / width  # (W, s)
    dirs = _angles_to_directions(theta[:, :, None, None], phi[None, None, :, :])  # (H, s, W, s, 3)
    weights = np.broadcast_to(np.sin(theta)[:, :, None, None] + 1e-300, dirs.shape[:-1])[..., None]
    values = cubemap_lookup(faces, dirs) * weights
    return values.sum(axis=(1, 3)) / weights.sum(axis=(1, 3))


# --------------------------------------------------------------------------- SH projection


def environment_sh(env, order: int) -> np.ndarray:
    """SH coefficients of an environment light, ``(order**2, 3)``.

    ``c_lm = int L(w) Y_lm(w) dw``.

    Parameters
    ----------
    env : EnvironmentLight or (H, W, 3) array
        A constant environment projects exactly (only ``c_00 = sqrt(4 pi) L``).
    order : int
        Number of SH bands.

    Notes
    -----
    Uses :func:`prtlab.sh.project_equirect` when the SH package provides it;
    otherwise the quadrature ``sum_ij w_ij L_ij Y_lm(d_ij)`` with the tent
    weights of :func:`prtlab.geometry.equirect_solid_angles` (exact for
    ``c_00``, error ``O(h^2)`` with ``h = pi / (H - 1)`` otherwise) and the
    reference basis :func:`prtlab.sh.basis_reference`.
    """
    import prtlab.sh as sh

    from ._scene import EnvironmentLight

    order = check_order(order)
    if isinstance(env, EnvironmentLight):
        if env.constant is not None:
            out = np.zeros((order * order, 3))
            out[0] = np.sqrt(4.0 * np.pi) * np.asarray(env.constant, dtype=np.float64)
            return out
        image = env.image
    else:
        image = env
    image = _as_image(image, "env image")
    if hasattr(sh, "project_equirect"):
        return np.asarray(sh.project_equirect(image, order), dtype=np.float64)
    height, width = image.shape[:2]
    weights = equirect_solid_angles(height, width).reshape(-1)
    basis = sh.basis_reference(equirect_directions(height, width).reshape(-1, 3), order)
    return basis.T @ (weights[:, None] * image.reshape(-1, 3))
