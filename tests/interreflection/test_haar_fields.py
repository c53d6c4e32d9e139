"""Tests of prtlab/interreflection/_haar_fields.py: Haar basis radiance cubemaps and their sparse field."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import brdf
from prtlab.geometry import builtin_mesh, cubemap_directions
from prtlab.interreflection import HaarBasisRadianceField, haar_basis_radiance_cubemaps, haar_basis_radiance_field
from prtlab.interreflection._haar_fields import _index_dtype
from prtlab.shadowfields import SphereGrid, sphere_grid
from prtlab.wavelet import ihaar2d

RES = 8


@pytest.fixture(scope="module")
def lambert():
    return brdf.separable(brdf.lambert(1.0), 1, resolution=(8, 16))


@pytest.fixture(scope="module")
def floor():
    return builtin_mesh("plane", size=[2.0, 2.0], resolution=[4, 4])


# --------------------------------------------------------------------------- known answers


def test_cubemap_of_a_plane_is_h_psi_where_the_texel_ray_hits_its_front(floor, lambert):
    """Above the plane: ``S = h(-d) Psi`` on the texels whose centre ray meets it, 0 elsewhere; below: 0."""
    psi = np.ones((1, len(floor.vertices)))
    above, below = np.array([0.13, 0.5, -0.21]), np.array([0.13, -0.5, -0.21])
    s = haar_basis_radiance_cubemaps(floor, psi, lambert, np.stack([above, below]), RES)
    assert s.shape == (2, 1, 1, 6, RES, RES)
    d = cubemap_directions(RES)
    t = -above[1] / np.where(d[..., 1] < 0, d[..., 1], -1.0)  # ray parameter to y = 0
    hit_xz = above[[0, 2]] + t[..., None] * d[..., [0, 2]]
    hits = (d[..., 1] < 0) & np.all(np.abs(hit_xz) < 1.0 - 1e-9, axis=-1)
    h = brdf.project_h(lambert, -d[hits], np.broadcast_to([0.0, 1.0, 0.0], d[hits].shape))[:, 0]
    np.testing.assert_allclose(s[0, 0, 0][hits], h, rtol=1e-12)
    assert np.all(s[0, 0, 0][~hits] == 0)
    assert np.all(s[1] == 0)  # the back of the plane emits nothing


def test_supersampled_cubemap_is_the_solid_angle_average_of_the_finer_one(floor, lambert, rng):
    from prtlab.geometry import cubemap_solid_angles

    basis = rng.normal(size=(2, len(floor.vertices)))
    p = np.array([[0.13, 0.5, -0.21], [0.4, 1.5, 0.3]])
    coarse = haar_basis_radiance_cubemaps(floor, basis, lambert, p, 4, supersample=2)
    fine = haar_basis_radiance_cubemaps(floor, basis, lambert, p, 8)
    w = cubemap_solid_angles(8).reshape(6, 4, 2, 4, 2)
    expected = np.einsum("pknfiajb,fiajb->pknfij", fine.reshape(2, 1, 2, 6, 4, 2, 4, 2), w) / w.sum(axis=(2, 4))
    np.testing.assert_allclose(coarse, expected, rtol=1e-12, atol=1e-15)
    assert haar_basis_radiance_field(floor, basis, lambert, sphere_grid(floor, n_radii=1, resolution=1), 4, keep=96,
                                     supersample=2).relative_truncation() < 1e-6


def test_field_at_the_sample_points_is_the_sparse_cubemap(floor, lambert, rng):
    """Every sample point holds the Haar coefficients of its cubemap (float32), the dropped energy by Parseval."""
    basis = rng.normal(size=(2, len(floor.vertices)))
    grid = sphere_grid(floor, n_radii=2, resolution=2)
    keep = 40
    field = haar_basis_radiance_field(floor, basis, lambert, grid, RES, keep=keep)
    cubes = haar_basis_radiance_cubemaps(floor, basis, lambert, grid.points(), RES)  # (2, 6, 2, 2, 1, 2, 6, r, r)
    assert field.indices.shape == grid.shape + (1, 2, keep) and field.indices.dtype == np.uint16
    assert field.values.dtype == np.float32 and field.nbytes == field.indices.size * 6
    assert field.build_seconds > 0
    n = 6 * RES * RES
    dense = np.zeros((field.values[..., 0].size, n))
    rows = np.arange(len(dense))[:, None]
    np.add.at(dense, (rows, field.indices.reshape(-1, keep).astype(np.int64)),
              field.values.reshape(-1, keep).astype(np.float64))
    approx = ihaar2d(dense.reshape(-1, 6, RES, RES)).reshape(cubes.shape)
    err2 = np.sum((approx - cubes) ** 2, axis=(-3, -2, -1))
    scale = np.sum(cubes**2, axis=(-3, -2, -1))
    np.testing.assert_allclose(field.energy, scale, rtol=1e-12)
    # Parseval: the squared reconstruction error is the dropped energy (up to the float32 rounding)
    np.testing.assert_allclose(err2, field.energy_lost, atol=1e-6 * scale.max())
    assert np.all(np.abs(field.values[..., :-1]) >= np.abs(field.values[..., 1:]))  # largest first
    assert 0 < field.relative_truncation() < 1
    exact = haar_basis_radiance_field(floor, basis, lambert, grid, RES, keep=n)
    assert exact.relative_truncation() < 1e-6  # all kept: 0 up to the rounding of sum c^2 - sum kept^2


def test_arrays_round_trip_and_truncation(floor, lambert, rng):
    basis = rng.normal(size=(3, len(floor.vertices)))
    field = haar_basis_radiance_field(floor, basis, lambert, sphere_grid(floor, n_radii=1, resolution=1), 4, keep=8)
    back = HaarBasisRadianceField.from_arrays(field.to_arrays())
    for name in ("indices", "values", "energy_lost", "energy"):
        np.testing.assert_array_equal(getattr(back, name), getattr(field, name))
        assert getattr(back, name).dtype == getattr(field, name).dtype
    assert back.build_seconds == field.build_seconds and back.grid.shape == field.grid.shape
    cut = field.truncated(2)
    assert cut.n_terms == (1, 2)
    np.testing.assert_array_equal(cut.values, field.values[..., :2, :])


def test_index_dtype_is_uint16_up_to_resolution_64():
    assert _index_dtype(64) == np.uint16 and _index_dtype(128) == np.int32


def test_empty_points_give_empty_cubemaps(floor, lambert):
    out = haar_basis_radiance_cubemaps(floor, np.ones((2, len(floor.vertices))), lambert, np.zeros((0, 3)), 4)
    assert out.shape == (0, 1, 2, 6, 4, 4)


# --------------------------------------------------------------------------- errors


def test_errors(floor, lambert):
    psi = np.ones((1, len(floor.vertices)))
    p = np.zeros((1, 3))
    with pytest.raises(ValueError, match="basis must be"):
        haar_basis_radiance_cubemaps(floor, np.ones((1, 3)), lambert, p)
    with pytest.raises(ValueError, match="basis contains NaN"):
        haar_basis_radiance_cubemaps(floor, psi * np.nan, lambert, p)
    with pytest.raises(ValueError, match="power of two"):
        haar_basis_radiance_cubemaps(floor, psi, lambert, p, 6)
    with pytest.raises(ValueError, match=r"points must be a \(\.\.\., 3\)"):
        haar_basis_radiance_cubemaps(floor, psi, lambert, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="points contain NaN"):
        haar_basis_radiance_cubemaps(floor, psi, lambert, np.full((1, 3), np.nan))
    with pytest.raises(TypeError, match="grid must be a SphereGrid"):
        haar_basis_radiance_field(floor, psi, lambert, "grid")
    grid = SphereGrid(np.zeros(3), 1.0, np.array([1.0]), 1)
    with pytest.raises(ValueError, match="supersample"):
        haar_basis_radiance_cubemaps(floor, psi, lambert, p, 4, supersample=0)
    with pytest.raises(ValueError, match="keep"):
        haar_basis_radiance_field(floor, psi, lambert, grid, 4, keep=0)
