"""Tests of prtlab/shadowfields/_haar.py: sparse Haar visibility cubemaps, occlusion fields, rotation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import (
    RayCaster,
    builtin_mesh,
    cubemap_directions,
    direction_to_cubemap,
)
from prtlab.scene import Transform
from prtlab.shadowfields import (
    HaarOcclusionField,
    SparseCubemaps,
    cubemap_frames,
    encode_sparse,
    haar_occlusion_field,
    haar_self_visibility,
    interpolate_field,
    rotation_texel_map,
    visibility_cubemaps,
)
from prtlab.shadowfields._haar_kernels import haar_point_value, haar_synthesis
from prtlab.wavelet import haar2d, keep_largest
from tests.conftest import FLOAT_TOLERANCE

RES = 8
SMALL = dict(resolution=RES, keep=96, n_radii=3, grid_resolution=2)


@pytest.fixture(scope="module")
def ball():
    return builtin_mesh("icosphere", radius=0.5, subdivisions=2)


@pytest.fixture(scope="module")
def ball_field(ball):
    return haar_occlusion_field(ball, **SMALL)


# --------------------------------------------------------------------------- Haar synthesis


@given(seed=st.integers(0, 2**31 - 1), res=st.sampled_from([1, 2, 4, 8]))
def test_point_value_and_synthesis_invert_haar2d(seed, res):
    x = np.random.default_rng(seed).normal(size=(6, res, res))
    c = haar2d(x).reshape(-1)
    values = np.array([haar_point_value(c, t, res) for t in range(6 * res * res)])
    np.testing.assert_allclose(values, x.reshape(-1), atol=FLOAT_TOLERANCE[np.float64])
    out, work = np.empty(6 * res * res), np.empty(res * res)
    haar_synthesis(c, res, out, work)
    np.testing.assert_allclose(out, x.reshape(-1), atol=FLOAT_TOLERANCE[np.float64])


def test_face_frames_follow_the_cubemap_convention(rng):
    d = rng.normal(size=(200, 3))
    face, s, t = direction_to_cubemap(d)
    frames = cubemap_frames()
    A, S, T = frames[face, 0], frames[face, 1], frames[face, 2]
    depth = np.sum(d * A, axis=1)
    np.testing.assert_allclose(np.sum(d * S, axis=1) / depth, 2 * s - 1, atol=1e-12)
    np.testing.assert_allclose(np.sum(d * T, axis=1) / depth, 2 * t - 1, atol=1e-12)


# --------------------------------------------------------------------------- sparse storage


@given(seed=st.integers(0, 2**31 - 1), keep=st.integers(1, 400))
def test_encode_sparse_keeps_the_largest_coefficients(seed, keep):
    rng = np.random.default_rng(seed)
    cubes = (rng.random((3, 6, RES, RES)) > 0.3).astype(float)
    sparse = encode_sparse(cubes, keep)
    dense, _ = keep_largest(haar2d(cubes), keep)
    np.testing.assert_allclose(np.sort(np.abs(sparse.coefficients()).reshape(3, -1), axis=1),
                               np.sort(np.abs(dense).reshape(3, -1), axis=1), atol=1e-12)
    err = np.sum((sparse.dense() - cubes) ** 2, axis=(1, 2, 3))
    np.testing.assert_allclose(sparse.energy_lost, err, atol=1e-9)  # Parseval


def test_encode_sparse_is_exact_with_enough_coefficients_and_round_trips():
    cubes = np.ones((2, 6, RES, RES))
    cubes[0, 2, :3, 1:5] = 0.0
    sparse = encode_sparse(cubes, 6 * RES * RES + 5)  # more than there are: padded
    assert sparse.indices.shape == (2, 6 * RES * RES + 5) and sparse.indices.dtype == np.int32
    np.testing.assert_allclose(sparse.dense(), cubes, atol=1e-12)
    np.testing.assert_array_equal(sparse.energy_lost, 0.0)
    back = SparseCubemaps.from_arrays(sparse.to_arrays())
    np.testing.assert_array_equal(back.values, sparse.values)
    assert encode_sparse(np.zeros((0, 6, 4, 4)), 3).indices.shape == (0, 3)


# --------------------------------------------------------------------------- occlusion fields


def test_field_at_its_sample_points_is_the_ray_cast_visibility(ball, ball_field):
    pts = ball_field.grid.points().reshape(-1, 3)
    want = visibility_cubemaps(RayCaster([(ball.vertices, ball.faces)]), pts, RES)
    assert np.all(ball_field.visibility.energy_lost == 0)  # keep=96 holds these exactly
    got = ball_field.lookup(pts)
    np.testing.assert_allclose(got.reshape(want.shape), want, atol=1e-12)
    assert 0 < want.mean() < 1


def test_field_lookup_under_a_pose_is_the_visibility_of_the_moved_object(ball, ball_field):
    """A quarter turn about y permutes the cube's texels: the resampling is exact (up to rays that graze
    the mesh, which may flip between the two floating-point versions of it: at most 1 texel in 500)."""
    T = Transform(translate=np.array([0.3, -1.0, 2.0]), rotate_deg=np.array([0.0, 90.0, 0.0]), scale=1.5)
    local = ball_field.grid.points()[:-1].reshape(-1, 3)[::3]  # the outermost sphere may round to beyond
    world = T.apply_points(local)
    got = ball_field.lookup(world, T)
    turned = ball_field.lookup(local).reshape(len(local), -1)[:, rotation_texel_map(T.rotation, RES)]
    np.testing.assert_allclose(got.reshape(len(local), -1), turned, atol=1e-12)
    caster = RayCaster([(T.apply_points(ball.vertices), ball.faces)])
    assert np.mean(np.abs(got - visibility_cubemaps(caster, world, RES)) > 1e-9) < 1 / 500
    np.testing.assert_allclose(ball_field.lookup(world, T, method="reference"), ball_field.lookup(world, T),
                               atol=1e-12)


def test_far_points_are_unoccluded_and_batches_keep_their_shape(ball_field):
    far = np.array([[[100.0, 0, 0], [0, 0, -50.0]]])
    np.testing.assert_array_equal(ball_field.lookup(far), 1.0)
    assert ball_field.lookup(far).shape == (1, 2, 6, RES, RES)
    assert ball_field.lookup(np.zeros((0, 3))).shape == (0, 6, RES, RES)


def test_trilinear_weights_are_those_of_the_sh_grid(ball_field, rng):
    grid = ball_field.grid
    field = rng.normal(size=grid.shape)
    q = rng.normal(size=(50, 3)) * grid.radius * 2
    corners, weights = ball_field.corners(q)
    want, beyond = interpolate_field(grid, field, q)
    np.testing.assert_allclose(np.sum(field.reshape(-1)[corners] * weights, axis=1)[~beyond], want[~beyond],
                               atol=1e-12)
    _, wn = ball_field.corners(q, interpolation="nearest")
    assert np.all(np.isin(wn.sum(axis=1), [0.0, 1.0]))


def test_trilinear_lookup_is_a_convex_blend_of_the_samples(ball_field, rng):
    q = rng.normal(size=(20, 3)) * 0.8
    v = ball_field.lookup(q)
    assert np.all(v >= -1e-12) and np.all(v <= 1 + 1e-12)


def test_rotation_texel_map(rng):
    assert np.array_equal(rotation_texel_map(np.eye(3), 4), np.arange(96))
    Ry = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    m = rotation_texel_map(Ry, 4)
    assert np.array_equal(np.sort(m), np.arange(96))  # a quarter turn permutes the texels
    d = cubemap_directions(4).reshape(-1, 3)
    np.testing.assert_allclose(d[m], d @ Ry, atol=1e-12)  # texel t reads the object texel of R^T d_t


def test_self_visibility_is_ray_cast_from_the_offset_vertices():
    torus = builtin_mesh("torus", sections=[16, 8])
    sv = haar_self_visibility(torus, resolution=4, keep=96)
    assert sv.shape == (len(torus.vertices),)
    caster = RayCaster([(torus.vertices, torus.faces)])
    want = visibility_cubemaps(caster, torus.vertices, 4, normals=torus.vertex_normals)
    np.testing.assert_allclose(sv.dense(), want, atol=1e-12)
    outer = np.argmax(torus.vertices[:, 0])  # faces away from the hole: its upper hemisphere is free
    up = cubemap_directions(4) @ torus.vertex_normals[outer] > 0.1
    assert np.all(sv.dense()[outer][up] == 1.0)
    inner = np.argmin(np.abs(torus.vertices[:, 0]) + np.abs(torus.vertices[:, 2]) + np.abs(torus.vertices[:, 1]))
    assert sv.dense()[inner][cubemap_directions(4) @ torus.vertex_normals[inner] > 0.1].mean() < 0.9


def test_supersampled_visibility_is_a_texel_average(ball):
    caster = RayCaster([(ball.vertices + [0, 2.0, 0], ball.faces)])
    v1 = visibility_cubemaps(caster, np.zeros((1, 3)), 4, supersample=1)
    v4 = visibility_cubemaps(caster, np.zeros((1, 3)), 4, supersample=4)
    assert np.all((v4 >= 0) & (v4 <= 1)) and np.any((v4 > 0) & (v4 < 1))
    # the contract: each texel is the solid-angle average of its 4 x 4 texels of the 16^2 cubemap
    from prtlab.geometry import cubemap_solid_angles

    v16 = visibility_cubemaps(caster, np.zeros((1, 3)), 16, supersample=1).reshape(6, 4, 4, 4, 4)
    w16 = cubemap_solid_angles(16).reshape(6, 4, 4, 4, 4)
    want = (v16 * w16).sum(axis=(2, 4)) / w16.sum(axis=(2, 4))
    np.testing.assert_allclose(v4.reshape(6, 4, 4), want, atol=1e-12)
    np.testing.assert_array_equal(v1, np.round(v1))  # one ray per texel: 0 or 1


def test_errors(ball, ball_field):
    with pytest.raises(ValueError, match="power of two"):
        haar_occlusion_field(ball, resolution=12)
    with pytest.raises(TypeError, match="keep must be an int"):
        encode_sparse(np.ones((6, 4, 4)), 2.5)
    with pytest.raises(ValueError, match="keep must be an int >= 1"):
        encode_sparse(np.ones((6, 4, 4)), 0)
    with pytest.raises(ValueError, match="cubemaps must be"):
        encode_sparse(np.ones((5, 4, 4)), 3)
    with pytest.raises(ValueError, match="NaN or inf"):
        encode_sparse(np.full((6, 4, 4), np.nan), 3)
    with pytest.raises(ValueError, match="interpolation must be"):
        ball_field.lookup(np.zeros(3), interpolation="cubic")
    with pytest.raises(ValueError, match="points must be"):
        ball_field.lookup(np.zeros(2))
    with pytest.raises(ValueError, match="points contain NaN"):
        ball_field.lookup([np.nan, 0, 0])
    with pytest.raises(ValueError, match="R must be a finite"):
        rotation_texel_map(np.eye(2), 4)
    with pytest.raises(ValueError, match="origins must be"):
        visibility_cubemaps(RayCaster([(ball.vertices, ball.faces)]), np.zeros(2), 4)
    with pytest.raises(TypeError, match="supersample must be an int"):
        visibility_cubemaps(RayCaster([(ball.vertices, ball.faces)]), np.zeros(3), 4, supersample=1.5)
    with pytest.raises(ValueError, match="normals are required"):
        haar_self_visibility((ball.vertices, ball.faces))
    with pytest.raises(ValueError, match=r"normals must be .* \(one per vertex\)"):
        haar_self_visibility(ball, normals=np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"points must be .* \(one per vertex\)"):
        haar_self_visibility(ball, points=np.zeros((2, 3)))
    assert isinstance(HaarOcclusionField.from_arrays(ball_field.to_arrays()), HaarOcclusionField)


def test_field_survives_the_hdf5_cache(ball_field, tmp_path):
    from prtlab.cache import Cache, cache_key

    cache = Cache(tmp_path, progress=False)
    key = cache_key("haar field test")
    cache.store(key, {"oof": ball_field.to_arrays()})
    back = HaarOcclusionField.from_arrays(cache.load(key)["oof"])
    np.testing.assert_array_equal(back.visibility.indices, ball_field.visibility.indices)
    np.testing.assert_array_equal(back.visibility.values, ball_field.visibility.values)
    q = np.array([[0.3, 0.7, -0.2], [2.0, 0.1, 0.0]])
    np.testing.assert_array_equal(back.lookup(q), ball_field.lookup(q))
