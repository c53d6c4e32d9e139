"""Equirect and cubemap maps: the one place the sphere-image conventions live."""

import numpy as np
import pytest
from hypothesis import given, strategies as st

from prtlab.geometry import (
    cubemap_directions,
    cubemap_lookup,
    cubemap_solid_angles,
    direction_to_cubemap,
    direction_to_equirect,
    equirect_directions,
    equirect_lookup,
    equirect_taps,
    equirect_solid_angles,
)
from tests.conftest import random_directions


# ---------------------------------------------------------------- known answers


def test_equirect_axes_match_mitsuba_convention():
    # u = atan2(x, -z) / 2pi, v = acos(y) / pi
    u, v = direction_to_equirect(np.array([[0, 0, -1.0], [1, 0, 0], [0, 0, 1], [-1, 0, 0], [0, 1, 0], [0, -1, 0]]))
    np.testing.assert_allclose(u[:4], [0.0, 0.25, 0.5, 0.75])
    np.testing.assert_allclose(v, [0.5, 0.5, 0.5, 0.5, 0.0, 1.0])


def test_equirect_rows_are_samples_from_pole_to_pole():
    dirs = equirect_directions(5, 8)
    np.testing.assert_allclose(dirs[0, :, 1], 1.0)  # row 0 is the +Y pole
    np.testing.assert_allclose(dirs[-1, :, 1], -1.0)
    u, _ = direction_to_equirect(dirs[2])  # equator: columns at (j + 0.5) / W
    np.testing.assert_allclose(u, (np.arange(8) + 0.5) / 8)


@pytest.mark.parametrize("shape", [(2, 1), (3, 4), (33, 64), (257, 512)])
def test_equirect_weights_sum_to_sphere(shape):
    assert equirect_solid_angles(*shape).sum() == pytest.approx(4 * np.pi, rel=1e-12)


def test_equirect_weights_integrate_cos_squared():
    # int y^2 dw = 4 pi / 3; second-order accurate in the row spacing
    h, w = 513, 16
    y = equirect_directions(h, w)[..., 1]
    assert (equirect_solid_angles(h, w) * y**2).sum() == pytest.approx(4 * np.pi / 3, rel=1e-5)


@pytest.mark.parametrize("res", [1, 2, 7, 32])
def test_cubemap_solid_angles_sum_to_sphere(res):
    assert cubemap_solid_angles(res).sum() == pytest.approx(4 * np.pi, rel=1e-12)


def test_cubemap_solid_angles_match_fine_subdivision():
    # one texel per face covers 4 pi / 6; a coarse texel is the sum of the fine texels inside it
    np.testing.assert_allclose(cubemap_solid_angles(1), 4 * np.pi / 6)
    fine = cubemap_solid_angles(8).reshape(6, 2, 4, 2, 4).sum(axis=(2, 4))
    np.testing.assert_allclose(cubemap_solid_angles(2), fine, rtol=1e-12)


def test_cubemap_faces_follow_opengl_orientation():
    # face centres point along +X, -X, +Y, -Y, +Z, -Z
    centres = cubemap_directions(2).mean(axis=(1, 2))
    centres /= np.linalg.norm(centres, axis=-1, keepdims=True)
    np.testing.assert_allclose(centres, [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], atol=1e-12)
    # OpenGL: on +X, s grows toward -Z and t toward -Y; on +Y, s toward +X and t toward +Z
    d = cubemap_directions(4, normalize=False)
    assert d[0, 0, -1, 2] < d[0, 0, 0, 2] and d[0, -1, 0, 1] < d[0, 0, 0, 1]
    assert d[2, 0, -1, 0] > d[2, 0, 0, 0] and d[2, -1, 0, 2] > d[2, 0, 0, 2]


# ---------------------------------------------------------------- identities


@given(st.integers(1, 16))
def test_cubemap_texel_centres_round_trip(res):
    face, _, _, i, j = direction_to_cubemap(cubemap_directions(res), res)
    assert (face == np.arange(6)[:, None, None]).all()
    assert (i == np.arange(res)[None, :, None]).all() and (j == np.arange(res)[None, None, :]).all()


def test_cubemap_lookup_returns_texels(rng):
    faces = rng.random((6, 5, 5, 3))
    np.testing.assert_array_equal(cubemap_lookup(faces, cubemap_directions(5)), faces)


def test_equirect_lookup_interpolates_samples_exactly(rng):
    image = rng.random((9, 16, 3))
    image[0] = image[0, 0]  # a valid map is single-valued at the poles
    image[-1] = image[-1, 0]
    np.testing.assert_allclose(equirect_lookup(image, equirect_directions(9, 16)), image, atol=1e-12)


def test_equirect_taps_are_the_lookup_as_weights(rng):
    image = rng.random((7, 12, 3))
    dirs = random_directions(rng, 50)
    index, weight = equirect_taps(dirs, 7, 12)
    assert index.shape == weight.shape == (50, 4)
    np.testing.assert_allclose(weight.sum(axis=-1), 1.0, atol=1e-12)
    assert np.all((index >= 0) & (index < 7 * 12)) and np.all(weight >= -1e-15)
    np.testing.assert_allclose(np.einsum("dk,dkc->dc", weight, image.reshape(-1, 3)[index]),
                               equirect_lookup(image, dirs), atol=1e-12)


def test_equirect_lookup_is_bilinear_between_samples():
    # a map linear in the row index is reproduced exactly between rows (v is linear in theta)
    h, w = 9, 4
    image = np.repeat(np.arange(h, dtype=float)[:, None], w, axis=1)
    theta = np.array([0.1, 0.7, 2.9])
    dirs = np.stack([np.sin(theta), np.cos(theta), np.zeros(3)], axis=-1)
    np.testing.assert_allclose(equirect_lookup(image, dirs), theta / np.pi * (h - 1), atol=1e-12)


def test_direction_to_cubemap_handles_batches_and_empty(rng):
    dirs = random_directions(rng, 24).reshape(2, 4, 3, 3)
    face, s, t = direction_to_cubemap(dirs)
    assert face.shape == s.shape == t.shape == (2, 4, 3)
    assert ((s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)).all()
    face, s, t = direction_to_cubemap(np.zeros((0, 3)))
    assert face.shape == (0,)


# ---------------------------------------------------------------- errors


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError, match=r"dirs must be a \(\.\.\., 3\) array"):
        direction_to_equirect(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="an equirectangular map needs height >= 2"):
        equirect_directions(1, 4)
    with pytest.raises(ValueError, match="cubemap resolution must be >= 1"):
        cubemap_directions(0)
    with pytest.raises(ValueError, match=r"faces must be \(6, res, res\[, C\]\)"):
        cubemap_lookup(np.zeros((5, 2, 2)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"image must be \(H, W\) or \(H, W, C\)"):
        equirect_lookup(np.zeros(4), np.zeros((1, 3)))
