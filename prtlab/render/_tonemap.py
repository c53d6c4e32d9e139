"""Tone mapping and image files: linear HDR radiance -> display values, PNG and EXR.

Pipeline of :func:`tonemap`: scale by ``2**exposure``, apply a tone curve
(``"clip"``, ``"reinhard"`` or ``"aces"``), clip to [0, 1], encode with the
exact piecewise sRGB transfer function.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = [
    "TONE_CURVES",
    "srgb_encode",
    "srgb_decode",
    "reinhard",
    "aces_narkowicz",
    "tonemap",
    "save_png",
    "save_exr",
    "load_exr",
]

TONE_CURVES = ("clip", "reinhard", "aces")


def _image(name, img) -> np.ndarray:
    arr = np.asarray(img)
    if not np.issubdtype(arr.dtype, np.number):
        raise TypeError(f"{name} must be a numeric array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if np.isnan(arr).any():
        raise ValueError(f"{name} contains NaN; fix the radiance before tone mapping")
    return arr


def srgb_encode(linear) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1, exact piecewise curve).

    ``c = 12.92 x`` for ``x <= 0.0031308``, else ``1.055 x^(1/2.4) - 0.055``.
    Values outside [0, 1] are clipped first.
    """
    x = np.clip(_image("linear", linear), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def srgb_decode(encoded) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear [0, 1], the inverse of :func:`srgb_encode`.

    ``x = c / 12.92`` for ``c <= 0.04045``, else ``((c + 0.055) / 1.055)^2.4``.
    """
    c = np.clip(_image("encoded", encoded), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, np.power((c + 0.055) / 1.055, 2.4))


def reinhard(x) -> np.ndarray:
    """Reinhard's global operator per channel: ``x / (1 + x)`` (Reinhard et al. 2002, eq. 3)."""
    x = np.maximum(_image("x", x), 0.0)
    return x / (1.0 + x)


def aces_narkowicz(x) -> np.ndarray:
    """Narkowicz's (2015) fit of the ACES filmic curve.

    ``(x (2.51 x + 0.03)) / (x (2.43 x + 0.59) + 0.14)``, clipped to [0, 1].
    """
    x = np.maximum(_image("x", x), 0.0)
    return np.clip((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)


def tonemap(img, exposure: float = 0.0, curve: str = "clip", srgb: bool = True) -> np.ndarray:
    """Linear radiance to display values in [0, 1].

    Parameters
    ----------
    img : (..., 3) float
        Linear RGB radiance (negative values are treated as zero).
    exposure : float
        Stops: the image is multiplied by ``2**exposure``.
    curve : {"clip", "reinhard", "aces"}
    srgb : bool
        Apply the sRGB transfer function (else return linear display values).

    Returns
    -------
    out : (..., 3) float64 in [0, 1]
    """
    if curve not in TONE_CURVES:
        raise ValueError(f"curve must be one of {TONE_CURVES}, got {curve!r}")
    if not np.isfinite(exposure):
        raise ValueError(f"exposure must be a finite number of stops, got {exposure}")
    x = np.maximum(_image("img", img), 0.0) * 2.0 ** float(exposure)
    if curve == "reinhard":
        x = reinhard(x)
    elif curve == "aces":
        x = aces_narkowicz(x)
    x = np.clip(x, 0.0, 1.0)
    return srgb_encode(x) if srgb else x


def _rgb_image(img) -> np.ndarray:
    """``img`` checked as an ``(h, w, 3)`` linear RGB image."""
    arr = _image("img", img)
    if arr.ndim != 3 or arr.shape[-1] != 3:
        raise ValueError(f"img must be an (h, w, 3) linear RGB image, got shape {arr.shape}")
    return arr


def _output_path(path) -> Path:
    """``path`` as a Path, its folder created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def save_png(path, img, exposure: float = 0.0, tonemap: str = "clip") -> Path:
    """Write a linear HDR image as an 8-bit sRGB PNG.

    Parameters
    ----------
    path : str or Path
    img : (h, w, 3) float
        Linear RGB.
    exposure : float
        Stops.
    tonemap : {"clip", "reinhard", "aces"}

    Returns
    -------
    Path
    """
    import imageio.v3 as iio

    arr = _rgb_image(img)
    display = _tonemap(arr, exposure=exposure, curve=tonemap)
    path = _output_path(path)
    iio.imwrite(path, np.round(display * 255.0).astype(np.uint8), extension=".png")
    return path


_tonemap = tonemap


def save_exr(path, img) -> Path:
    """Write a linear RGB image as a float32 OpenEXR file (ZIP compressed).

    Parameters
    ----------
    path : str or Path
    img : (h, w, 3) float

    Returns
    -------
    Path
    """
    import OpenEXR

    arr = _rgb_image(img)
    path = _output_path(path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": np.ascontiguousarray(arr, dtype=np.float32)}) as exr:
        exr.write(str(path))
    return path


def load_exr(path) -> np.ndarray:
    """Read an RGB OpenEXR file written by :func:`save_exr` (or any RGB EXR).

    Returns
    -------
    img : (h, w, 3) float64
    """
    import OpenEXR

    with OpenEXR.File(str(path)) as exr:
        channels = exr.channels()
        if "RGB" in channels:
            return np.asarray(channels["RGB"].pixels, dtype=np.float64)
        if all(k in channels for k in "RGB"):
            return np.stack([np.asarray(channels[k].pixels, dtype=np.float64) for k in "RGB"], axis=-1)
    raise ValueError(f"{path}: no RGB channels in this EXR file (found {sorted(channels)})")
