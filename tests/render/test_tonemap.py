"""Tone curves: sRGB known values and inverse, monotonicity, files."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.render import (
    aces_narkowicz,
    load_exr,
    reinhard,
    save_exr,
    save_png,
    srgb_decode,
    srgb_encode,
    tonemap,
)


def test_srgb_known_values():
    x = np.array([0.0, 0.0031308, 0.18, 0.5, 1.0])
    expect = np.array([0.0, 0.040449936, 0.46135612950044164, 0.7353569830524495, 1.0])
    np.testing.assert_allclose(srgb_encode(x), expect, rtol=1e-8, atol=1e-9)
    assert np.isclose(srgb_encode(0.001), 0.01292)  # linear segment
    assert np.isclose(srgb_decode(0.04045), 0.04045 / 12.92)


def test_srgb_decode_inverts_encode():
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(srgb_decode(srgb_encode(x)), x, atol=1e-12)


def test_known_curve_values():
    assert np.isclose(reinhard(1.0), 0.5)
    assert aces_narkowicz(0.0) == 0.0
    assert np.isclose(aces_narkowicz(1.0), (2.51 + 0.03) / (2.43 + 0.59 + 0.14))
    assert aces_narkowicz(1e6) == 1.0
    # exposure in stops
    np.testing.assert_allclose(tonemap(np.full(3, 0.25), exposure=1.0, srgb=False), 0.5)


@pytest.mark.parametrize("curve", ["clip", "reinhard", "aces"])
@pytest.mark.parametrize("srgb", [True, False])
def test_curves_are_monotone_and_bounded(curve, srgb):
    x = np.concatenate([np.linspace(0, 1, 500), np.geomspace(1, 1e4, 500)])
    y = tonemap(x[:, None] * np.ones(3), curve=curve, srgb=srgb)[:, 0]
    assert np.all(np.diff(y) >= 0)
    assert y.min() >= 0 and y.max() <= 1


@given(st.floats(0, 1e3), st.floats(0, 1e3))
def test_curves_preserve_order(a, b):
    lo, hi = min(a, b), max(a, b)
    for f in (reinhard, aces_narkowicz, srgb_encode):
        assert f(lo) <= f(hi)


def test_png_and_exr_files(tmp_path, rng):
    import imageio.v3 as iio

    img = rng.uniform(0, 2, size=(5, 7, 3))
    png = save_png(tmp_path / "a" / "img.png", img, exposure=-1.0, tonemap="aces")
    back = iio.imread(png)
    assert back.shape == (5, 7, 3) and back.dtype == np.uint8
    np.testing.assert_array_equal(back, np.round(tonemap(img, -1.0, "aces") * 255).astype(np.uint8))
    exr = save_exr(tmp_path / "img.exr", img)
    np.testing.assert_allclose(load_exr(exr), img.astype(np.float32))


def test_tonemap_errors(tmp_path):
    with pytest.raises(ValueError, match="curve must be one of"):
        tonemap(np.ones(3), curve="filmic")
    with pytest.raises(ValueError, match="exposure must be a finite"):
        tonemap(np.ones(3), exposure=np.inf)
    with pytest.raises(ValueError, match="img contains NaN"):
        tonemap(np.array([np.nan, 0, 0]))
    with pytest.raises(TypeError, match="img must be a numeric array"):
        tonemap(np.array(["a"]))
    with pytest.raises(ValueError, match=r"img must be an \(h, w, 3\)"):
        save_png(tmp_path / "x.png", np.ones((4, 4)))
    with pytest.raises(ValueError, match=r"img must be an \(h, w, 3\)"):
        save_exr(tmp_path / "x.exr", np.ones((4, 4, 4)))


def test_load_exr_without_rgb_channels(tmp_path):
    import OpenEXR

    path = tmp_path / "grey.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.ones((2, 3), np.float32)}) as exr:
        exr.write(str(path))
    with pytest.raises(ValueError, match="no RGB channels"):
        load_exr(path)
