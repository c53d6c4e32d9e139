"""Tests of prtlab/scene/_envmap.py: files, the Preetham sky, constant maps, cubemap resampling, SH."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab.geometry import (
    cubemap_directions,
    cubemap_solid_angles,
    equirect_directions,
    equirect_solid_angles,
)
from prtlab.scene import (
    SUN_ANGULAR_RADIUS_DEG,
    EnvironmentLight,
    constant_envmap,
    cubemap_to_equirect,
    environment_sh,
    equirect_to_cubemap,
    preetham_sky,
    preetham_sky_radiance,
    preetham_sky_xyY,
    preetham_sun_radiance,
    preetham_zenith_xyY,
    read_envmap,
    read_exr,
    read_hdr,
    sun_direction,
    write_exr,
    write_hdr,
    xyY_to_linear_srgb,
)
from prtlab.scene import _envmap
from tests.conftest import FLOAT_TOLERANCE, random_directions

TOL = FLOAT_TOLERANCE[np.float64]
LUMINANCE = np.array([0.2126729, 0.7151522, 0.0721750])  # Y row of linear sRGB -> XYZ


# ----------------------------------------------------------------------------- Preetham sky: known answers


def test_zenith_luminance_matches_preetham_formula():
    # Preetham et al. 1999, Appendix A.2, at turbidity T = 3 and sun elevation 30 deg (theta_s = 60 deg).
    t, theta_s = 3.0, np.radians(60.0)
    chi = (4.0 / 9.0 - t / 120.0) * (np.pi - 2.0 * theta_s)
    y_zenith = (4.0453 * t - 4.9710) * np.tan(chi) - 0.2155 * t + 2.4192
    x_zenith = (
        t * t * (0.00166 * theta_s**3 - 0.00375 * theta_s**2 + 0.00209 * theta_s)
        + t * (-0.02903 * theta_s**3 + 0.06377 * theta_s**2 - 0.03202 * theta_s + 0.00394)
        + (0.11693 * theta_s**3 - 0.21196 * theta_s**2 + 0.06052 * theta_s + 0.25886)
    )
    assert y_zenith == pytest.approx(5.1392, abs=5e-4)  # kcd/m^2, hand computation of the formula
    np.testing.assert_allclose(preetham_zenith_xyY(theta_s, t)[[0, 2]], [x_zenith, y_zenith], rtol=TOL)
    # the sky at the zenith is exactly the zenith value (F(0, theta_s) / F(0, theta_s) = 1)
    np.testing.assert_allclose(preetham_sky_xyY([0.0, 1.0, 0.0], 30.0, 123.0, 3.0), preetham_zenith_xyY(theta_s, t), rtol=TOL)


def test_sky_luminance_of_rgb_is_Y(rng):
    dirs = random_directions(rng, 500)
    dirs[:, 1] = np.abs(dirs[:, 1])
    xyY = preetham_sky_xyY(dirs, 40.0, 30.0, 4.0)
    rgb = preetham_sky_radiance(dirs, 40.0, 30.0, 4.0)
    in_gamut = np.all(xyY_to_linear_srgb(xyY) >= 0, axis=-1)
    assert in_gamut.mean() > 0.9
    np.testing.assert_allclose(rgb[in_gamut] @ LUMINANCE, xyY[in_gamut, 2], rtol=1e-6)


@pytest.mark.parametrize("azimuth", [0.0, 90.0, 217.0])
def test_sky_is_symmetric_about_the_sun_vertical_plane(rng, azimuth):
    dirs = random_directions(rng, 400)
    sun = sun_direction(35.0, azimuth)
    normal = np.cross(sun, [0.0, 1.0, 0.0])
    normal /= np.linalg.norm(normal)
    mirrored = dirs - 2.0 * (dirs @ normal)[:, None] * normal
    np.testing.assert_allclose(
        preetham_sky_radiance(dirs, 35.0, azimuth, 2.5), preetham_sky_radiance(mirrored, 35.0, azimuth, 2.5), rtol=1e-9
    )


def test_sun_direction_convention():
    np.testing.assert_allclose(sun_direction(0.0, 0.0), [0, 0, -1], atol=TOL)
    np.testing.assert_allclose(sun_direction(0.0, 90.0), [1, 0, 0], atol=TOL)
    np.testing.assert_allclose(sun_direction(90.0, 40.0), [0, 1, 0], atol=TOL)


def test_sky_map_layout():
    image = preetham_sky(20.0, 90.0, 3.0, height=65, width=128)
    assert image.shape == (65, 128, 3)
    dirs = equirect_directions(65, 128)
    assert np.all(image[dirs[..., 1] < 0] == 0.0)  # zero below the horizon
    assert np.all(image[dirs[..., 1] > 0] > 0.0)
    # the brightest sky pixel sits near the sun: u = azimuth / 360 = 0.25 -> column 31 or 32
    i, j = np.unravel_index(np.argmax(image @ LUMINANCE), image.shape[:2])
    assert j in (31, 32)
    assert dirs[i, j, 1] > 0
    np.testing.assert_allclose(image, preetham_sky_radiance(dirs, 20.0, 90.0, 3.0), rtol=TOL)


def test_circumsolar_brighter_than_antisolar():
    sun = sun_direction(30.0, 0.0)
    anti = np.array([-sun[0], sun[1], -sun[2]])
    near = sun + 0.05 * np.array([1.0, 0.0, 0.0])
    near /= np.linalg.norm(near)
    lum = preetham_sky_radiance(np.stack([near, anti]), 30.0, 0.0, 3.0) @ LUMINANCE
    assert lum[0] > 3.0 * lum[1]


def test_zenith_brightens_as_the_sun_rises():
    zenith = [preetham_zenith_xyY(np.radians(90.0 - e), 3.0)[2] for e in (5.0, 20.0, 40.0, 60.0, 80.0)]
    assert np.all(np.diff(zenith) > 0)


def test_cie_tables_give_equal_energy_white():
    xyz = np.array([_envmap._CIE_X.sum(), _envmap._CIE_Y.sum(), _envmap._CIE_Z.sum()])
    np.testing.assert_allclose(xyz[:2] / xyz.sum(), [1 / 3, 1 / 3], atol=1e-3)
    assert 10 * xyz[1] == pytest.approx(106.86, abs=0.05)  # int ybar = 106.857 nm


def test_sun_radiance():
    high, low = preetham_sun_radiance(60.0, 3.0), preetham_sun_radiance(5.0, 3.0)
    # the sun's luminance at the ground is about 1.6e9 cd/m^2 for a high sun (1e6 .. 2e6 kcd/m^2)
    assert 1e6 < high @ LUMINANCE < 2e6
    assert high @ LUMINANCE > low @ LUMINANCE
    assert low[0] / low[2] > high[0] / high[2]  # redder near the horizon
    assert preetham_sun_radiance(60.0, 8.0) @ LUMINANCE < high @ LUMINANCE  # haze dims it


def test_sun_disk_adds_its_power():
    h, w = 64, 128
    base = preetham_sky(25.0, 70.0, 3.0, h, w)
    with_sun = preetham_sky(25.0, 70.0, 3.0, h, w, sun=True)
    added = ((with_sun - base) * equirect_solid_angles(h, w)[..., None]).sum(axis=(0, 1))
    solid_angle = 2 * np.pi * (1 - np.cos(np.radians(SUN_ANGULAR_RADIUS_DEG)))
    np.testing.assert_allclose(added, preetham_sun_radiance(25.0, 3.0) * solid_angle, rtol=1e-12)
    assert np.count_nonzero(np.any(with_sun != base, axis=-1)) <= 4


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"sun_elevation_deg": -5.0}, ValueError, r"sun_elevation_deg must be in \[0, 90\]"),
        ({"sun_elevation_deg": 95.0}, ValueError, r"sun_elevation_deg must be in \[0, 90\]"),
        ({"turbidity": 1.0}, ValueError, r"turbidity must be in \[1.7, 10\]"),
        ({"sun_azimuth_deg": float("nan")}, ValueError, "sun_azimuth_deg must be finite"),
        ({"turbidity": "3"}, TypeError, "turbidity must be a number"),
        ({"height": 1}, ValueError, "height must be an int >= 2"),
        ({"width": 2.5}, TypeError, "width must be an int >= 1"),
    ],
)
def test_sky_parameter_errors(kwargs, exc, match):
    args = {"sun_elevation_deg": 30.0, "sun_azimuth_deg": 0.0, "turbidity": 3.0, "height": 8, "width": 16}
    args.update(kwargs)
    with pytest.raises(exc, match=match):
        preetham_sky(**args)


def test_sky_direction_errors():
    with pytest.raises(ValueError, match=r"dirs must be a \(\.\.\., 3\) array"):
        preetham_sky_xyY(np.zeros((4, 2)), 30.0)
    with pytest.raises(ValueError, match="dirs contains NaN or inf"):
        preetham_sky_xyY([np.nan, 1.0, 0.0], 30.0)


# ----------------------------------------------------------------------------- constant environments and SH


def test_constant_envmap():
    image = constant_envmap([1.0, 2.0, 3.0], 5, 7)
    assert image.shape == (5, 7, 3)
    np.testing.assert_array_equal(image[3, 4], [1, 2, 3])
    with pytest.raises(ValueError, match="rgb must be 3 finite numbers"):
        constant_envmap([1.0, np.nan, 0.0])


def test_environment_sh_of_constant_is_exact():
    rgb = np.array([0.5, 1.0, 2.0])
    exact = environment_sh(EnvironmentLight(constant=rgb), 3)
    assert exact.shape == (9, 3)
    np.testing.assert_allclose(exact[0], np.sqrt(4 * np.pi) * rgb, rtol=TOL)
    assert np.all(exact[1:] == 0)
    from_image = environment_sh(constant_envmap(rgb, 33, 64), 3)
    np.testing.assert_allclose(from_image[0], exact[0], rtol=1e-12)  # the tent weights sum to 4 pi exactly
    h = np.pi / 32
    np.testing.assert_allclose(from_image, exact, atol=h * h * rgb.max())  # second-order quadrature


def test_environment_sh_of_linear_map():
    # L(w) = y has c_{1,-1} = sqrt(4 pi / 3) and nothing else (Y_1,-1 = sqrt(3 / 4 pi) y)
    h, w = 129, 256
    image = np.repeat(equirect_directions(h, w)[..., 1:2], 3, axis=-1)
    coeffs = environment_sh(image, 2)
    expected = np.zeros((4, 3))
    expected[1] = np.sqrt(4 * np.pi / 3)
    np.testing.assert_allclose(coeffs, expected, atol=(np.pi / (h - 1)) ** 2)  # second-order quadrature, |L| <= 1


def test_environment_sh_order_error():
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        environment_sh(constant_envmap([1.0, 1.0, 1.0]), 0)


# ----------------------------------------------------------------------------- files


def test_exr_round_trip(tmp_path, rng):
    image = (rng.random((6, 10, 3)) * 100).astype(np.float32).astype(np.float64)
    path = write_exr(tmp_path / "sub" / "env.exr", image)
    back = read_exr(path)
    assert back.dtype == np.float64 and back.shape == (6, 10, 3)
    np.testing.assert_array_equal(back, image)  # float32-representable values are exact
    np.testing.assert_array_equal(read_envmap(path), image)
    half = read_exr(write_exr(tmp_path / "half.exr", image, half=True))
    np.testing.assert_allclose(half, image, rtol=2.0**-11)


def test_exr_luminance_only_file(tmp_path):
    import OpenEXR

    y = np.arange(12, dtype=np.float32).reshape(3, 4)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Y": y}).write(
        str(tmp_path / "y.exr")
    )
    back = read_exr(tmp_path / "y.exr")
    np.testing.assert_array_equal(back, np.repeat(y[..., None], 3, axis=-1))


def test_exr_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="EXR file not found"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="cannot read EXR file"):
        read_exr(tmp_path / "bad.exr")
    with pytest.raises(ValueError, match=r"image must be an \(H, W, 3\) RGB image"):
        write_exr(tmp_path / "x.exr", np.zeros((4, 4)))
    with pytest.raises(ValueError, match="image contains NaN or inf"):
        write_exr(tmp_path / "x.exr", np.full((2, 2, 3), np.inf))
    with pytest.raises(ValueError, match=r"\.png images hold 8-bit display values .* not linear radiance"):
        read_envmap(tmp_path / "x.png")
    with pytest.raises(ValueError, match="unknown extension '.tiff'"):
        read_envmap(tmp_path / "x.tiff")


@pytest.mark.parametrize("rle", [True, False])
def test_hdr_round_trip(tmp_path, rng, rle):
    image = rng.random((5, 40, 3)) * np.exp(rng.normal(size=(5, 40, 1)) * 4)
    image[2, 5:30] = [1.5, 0.25, 3.0]  # long runs exercise the run-length path
    image[3] = 0.0
    path = write_hdr(tmp_path / "env.hdr", image, rle=rle)
    back = read_hdr(path)
    # RGBE: every component carries the exponent of the largest one, 8-bit mantissa
    bound = image.max(axis=-1, keepdims=True) / 128.0
    assert np.all(np.abs(back - image) <= bound)
    assert np.all(back <= image)  # the mantissa is truncated
    np.testing.assert_array_equal(back[2, 5:30], np.broadcast_to([1.5, 0.25, 3.0], (25, 3)))  # exact in RGBE
    np.testing.assert_array_equal(read_envmap(path), back)


def test_hdr_old_style_run_length(tmp_path):
    # Radiance's old RLE: pixel (1, 1, 1, n) repeats the previous pixel n times
    a, b = [128, 64, 32, 129], [200, 100, 50, 130]  # 1.0, 0.5, 0.25 and 3.125, 1.5625, 0.78125
    row = bytes(a + [1, 1, 1, 3] + b + b)  # a a a a b b: 6 pixels
    header = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 2 +X 6\n"
    (tmp_path / "old.hdr").write_bytes(header + row + row)
    image = read_hdr(tmp_path / "old.hdr")
    expected = np.array([[1.0, 0.5, 0.25]] * 4 + [[3.125, 1.5625, 0.78125]] * 2)
    np.testing.assert_array_equal(image, np.stack([expected, expected]))
    (tmp_path / "bad.hdr").write_bytes(header + bytes([1, 1, 1, 3]) + row)
    with pytest.raises(ValueError, match="repeat code at the start of a scanline"):
        read_hdr(tmp_path / "bad.hdr")


def test_hdr_rle_is_smaller_for_runs(tmp_path):
    image = np.ones((4, 64, 3))
    assert write_hdr(tmp_path / "a.hdr", image).stat().st_size < write_hdr(tmp_path / "b.hdr", image, rle=False).stat().st_size


def test_hdr_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="HDR file not found"):
        read_hdr(tmp_path / "missing.hdr")
    (tmp_path / "a.hdr").write_bytes(b"P6 not radiance")
    with pytest.raises(ValueError, match="does not start with '#\\?RADIANCE'"):
        read_hdr(tmp_path / "a.hdr")
    (tmp_path / "b.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n+Y 2 +X 2\n" + bytes(16))
    with pytest.raises(ValueError, match="unsupported resolution line"):
        read_hdr(tmp_path / "b.hdr")
    (tmp_path / "c.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 2 +X 2\n" + bytes(16))
    with pytest.raises(ValueError, match="unsupported FORMAT=32-bit_rle_xyze"):
        read_hdr(tmp_path / "c.hdr")
    good = write_hdr(tmp_path / "d.hdr", np.ones((4, 16, 3))).read_bytes()
    (tmp_path / "e.hdr").write_bytes(good[:-20])
    with pytest.raises(ValueError, match="corrupt or truncated pixel data"):
        read_hdr(tmp_path / "e.hdr")
    (tmp_path / "f.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n")
    with pytest.raises(ValueError, match="header has no end"):
        read_hdr(tmp_path / "f.hdr")
    with pytest.raises(ValueError, match="negative values"):
        write_hdr(tmp_path / "g.hdr", -np.ones((2, 2, 3)))


# ----------------------------------------------------------------------------- cubemap <-> equirect


def _smooth(dirs):
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    base = 1.0 + 0.5 * x + 0.3 * y * z + 0.2 * z * z
    return np.stack([base, 2.0 * base, base + 0.1 * y], axis=-1)


# Gradient bound of _smooth on the sphere: |grad| <= 0.5 + 0.3 + 0.4 (+ 0.1) in every channel but the 2x one.
_GRAD_BOUND = 2.0 * 1.2


def test_constant_maps_resample_exactly():
    faces = equirect_to_cubemap(constant_envmap([1.0, 2.0, 3.0], 17, 32), 8)
    np.testing.assert_allclose(faces, np.broadcast_to([1.0, 2.0, 3.0], faces.shape), rtol=1e-14)
    image = cubemap_to_equirect(faces, 9, 16)
    np.testing.assert_allclose(image, np.broadcast_to([1.0, 2.0, 3.0], image.shape), rtol=1e-14)


def test_face_orientation_follows_geometry_convention():
    h, w = 65, 128
    image = np.repeat(equirect_directions(h, w)[..., :1], 3, axis=-1)  # L(w) = x
    faces = equirect_to_cubemap(image, 8)
    centres = cubemap_directions(8)
    np.testing.assert_allclose(faces[..., 0], centres[..., 0], atol=0.02)


def test_round_trip_error_is_bounded_for_smooth_maps():
    h, w, res = 64, 128, 32
    image = _smooth(equirect_directions(h, w))
    faces = equirect_to_cubemap(image, res)
    back = cubemap_to_equirect(faces, h, w)
    # nearest-texel reconstruction: error <= |grad L| * (largest texel angle, 2 / res at a face centre)
    assert np.max(np.abs(back - image)) <= _GRAD_BOUND * 2.0 / res
    # cube texels hold texel averages: close to the function at their centres
    np.testing.assert_allclose(faces, _smooth(cubemap_directions(res)), atol=_GRAD_BOUND * 2.0 / res / 4)


def test_cubemap_preserves_integrals():
    h, w = 64, 128
    image = _smooth(equirect_directions(h, w))
    faces = equirect_to_cubemap(image, 16)
    total_equirect = (image * equirect_solid_angles(h, w)[..., None]).sum(axis=(0, 1))
    total_cube = (faces * cubemap_solid_angles(16)[..., None]).sum(axis=(0, 1, 2))
    np.testing.assert_allclose(total_cube, total_equirect, rtol=1e-3)


def test_resampling_errors():
    with pytest.raises(ValueError, match=r"faces must be a \(6, res, res, 3\) cubemap"):
        cubemap_to_equirect(np.zeros((6, 4, 5, 3)), 8, 16)
    with pytest.raises(ValueError, match="faces contains NaN or inf"):
        cubemap_to_equirect(np.full((6, 2, 2, 3), np.nan), 8, 16)
    with pytest.raises(ValueError, match="res must be an int >= 1"):
        equirect_to_cubemap(np.zeros((4, 8, 3)), 0)
    with pytest.raises(ValueError, match=r"image must be an \(H, W, 3\) RGB image"):
        equirect_to_cubemap(np.zeros((4, 8)), 4)


def test_exr_without_colour_channels(tmp_path):
    import OpenEXR

    z = np.zeros((2, 3), dtype=np.float32)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Z": z}).write(
        str(tmp_path / "z.exr")
    )
    with pytest.raises(ValueError, match=r"has channels \['Z'\]; need R, G, B \(or Y\)"):
        read_exr(tmp_path / "z.exr")


def test_image_type_errors(tmp_path):
    with pytest.raises(TypeError, match="image must be a real array"):
        write_exr(tmp_path / "x.exr", np.full((2, 2, 3), "a"))
