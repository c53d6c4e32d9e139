"""Tests of prtlab/shadowfields/_haar_direct.py: light pieces, visibility and direct passes, haar_direct."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab import brdf
from prtlab.geometry import (
    builtin_mesh,
    cubemap_directions,
    cubemap_solid_angles,
    direction_to_cubemap,
)
from prtlab.scene import AreaLight, EnvironmentLight, PointLight, Transform
from prtlab.shadowfields import (
    area_light_sh,
    encode_sparse,
    haar_direct,
    haar_direct_pass,
    haar_occlusion_field,
    haar_visibility_pass,
    light_pieces,
    texel_moments,
)
from tests.conftest import FLOAT_TOLERANCE

LIGHT = AreaLight(center=np.array([0.0, 2.0, 0.0]), u=np.array([0.3, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.2]),
                  radiance=np.array([1.0, 2.0, 3.0]))  # cross(u, v) = -y: emits downward
LAMBERT = brdf.separable(brdf.lambert(1.0), 1)
PHONG = brdf.separable(brdf.phong(0.3, 0.5, 8.0), 3, resolution=(16, 32))


def corner_form_factor(x, y):
    """Differential area to a parallel rectangle with one corner above it (sides x, y in heights)."""
    ax, ay = x / np.sqrt(1 + x * x), y / np.sqrt(1 + y * y)
    return (ax * np.arctan(y / np.sqrt(1 + x * x)) + ay * np.arctan(x / np.sqrt(1 + y * y))) / (2 * np.pi)


# --------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("res", [1, 4, 32])
def test_area_light_pieces_give_the_closed_form_irradiance(res):
    """Exact partial coverage: the pieces' solid angles sum to the rectangle's, their cosines to pi F."""
    h, a, b = 2.0, 0.3, 0.2
    texel, gw, _, _ = light_pieces([LIGHT], np.zeros((1, 3)), [[0.0, 1, 0]], LAMBERT, res)
    form = 4 * corner_form_factor(a / h, b / h)
    np.testing.assert_allclose(np.pi * gw[0, :, 0].sum(), np.pi * form, rtol=1e-12)  # g = 1 / pi
    lk = haar_direct(np.zeros((1, 3)), [[0.0, 1, 0]], [LIGHT], LAMBERT, resolution=res)
    np.testing.assert_allclose(np.pi * lk[0, 0], LIGHT.radiance * np.pi * form, rtol=1e-12)
    assert np.all(texel[0, gw[0, :, 0] > 0] < 6 * res * res)


def test_area_light_moments_match_the_sh_of_the_light(rng):
    """sum over pieces of int w dw = the l = 1 SH coefficients of the light / sqrt(3 / 4 pi) (light above the
    horizon); a tilted normal clips nothing here. Independent: area_light_sh integrates over the light's area."""
    pts = rng.uniform(-0.5, 0.5, size=(6, 3)) * [1, 0.2, 1]
    normals = np.tile([0.0, 1.0, 0.0], (6, 1))
    sh = area_light_sh(LIGHT, pts, 2, n_nodes=64)[..., 0] / LIGHT.radiance[0]
    for res in (2, 16):
        _, gw, _, _ = light_pieces([LIGHT], pts, normals, LAMBERT, res)
        # moments are recovered from the Lambert weights only along n; use the y component of the SH
        np.testing.assert_allclose(np.pi * gw[:, :, 0].sum(axis=1), sh[:, 1] / np.sqrt(3 / (4 * np.pi)), rtol=1e-9)


def test_area_light_coverage_per_texel_against_sampling():
    """Each piece's solid angle against the fraction of a texel's sub-directions that hit the light."""
    res, sub = 4, 64
    point = np.array([[0.1, 0.2, -0.1]])
    texel, gw, _, _ = light_pieces([LIGHT], point, [[0.0, 1, 0]], LAMBERT, res)
    fine = cubemap_directions(res * sub).reshape(-1, 3)
    w = cubemap_solid_angles(res * sub).reshape(-1)
    # ray / parallelogram intersection
    n = LIGHT.normal
    t = ((LIGHT.center - point[0]) @ n) / (fine @ n)
    hit = point[0] + t[:, None] * fine - LIGHT.center
    s_ = hit @ LIGHT.u / (LIGHT.u @ LIGHT.u)
    t_ = hit @ LIGHT.v / (LIGHT.v @ LIGHT.v)
    inside = (t > 0) & (np.abs(s_) <= 1) & (np.abs(t_) <= 1)
    face, _, _, i, j = direction_to_cubemap(fine, res)
    coarse = face * res * res + i * res + j
    covered = np.bincount(coarse, weights=w * inside, minlength=6 * res * res)
    cos = np.maximum(fine[:, 1], 0) / np.pi
    want = np.bincount(coarse, weights=w * inside * cos, minlength=6 * res * res)
    got = np.bincount(texel[0], weights=gw[0, :, 0], minlength=6 * res * res)
    # sampling error: at most the sub-texels along the light's outline, (4 edges) x sub per texel
    tol = 4 * sub * w.max() / np.pi
    np.testing.assert_allclose(got, want, atol=tol)
    assert covered.sum() > 0


def test_point_light_is_an_exact_delta():
    light = PointLight(np.array([1.0, 2.0, 0.5]), np.array([2.0, 3.0, 4.0]))
    x = np.array([[0.0, 0, 0], [0.5, 0.1, 0.2]])
    n = np.array([[0.0, 1, 0], [0.6, 0.8, 0.0]])
    d = light.position - x
    r2 = np.sum(d * d, axis=1)
    cos = np.sum(d * n, axis=1) / np.sqrt(r2)
    lk = haar_direct(x, n, [light], LAMBERT, resolution=8)
    np.testing.assert_allclose(lk[:, 0], (cos / r2 / np.pi)[:, None] * light.intensity, rtol=1e-12)
    lk = haar_direct(x, n, [light], PHONG, resolution=8)
    g = PHONG.g(brdf.to_local(d / np.sqrt(r2)[:, None], n))
    np.testing.assert_allclose(lk, (g * (cos / r2)[:, None])[..., None] * light.intensity, rtol=1e-12)


def test_constant_environment_is_exact_for_axis_normals():
    env = EnvironmentLight(constant=np.array([1.0, 2.0, 3.0]))
    n = np.array([[0.0, 1, 0], [-1.0, 0, 0], [0.0, 0, 1]])
    lk = haar_direct(np.zeros((3, 3)), n, [env], LAMBERT, resolution=8)
    np.testing.assert_allclose(lk[:, 0], np.tile(env.constant, (3, 1)), rtol=1e-12)
    m = texel_moments(8)
    assert np.all(np.linalg.norm(m, axis=1) <= cubemap_solid_angles(8).reshape(-1))


def test_glossy_terms_match_the_projected_g_cos_under_a_constant_environment():
    """int g_k cos over the sphere = sqrt(4 pi) * c_00 of project_g_cos (an independent quadrature)."""
    env = EnvironmentLight(constant=np.ones(3))
    n = np.array([[0.0, 1, 0], [0.0, 0, -1]])
    lk = haar_direct(np.zeros((2, 3)), n, [env], PHONG, resolution=16)
    want = brdf.project_g_cos(PHONG, n, 2)[:, :, 0] * np.sqrt(4 * np.pi)
    np.testing.assert_allclose(lk[..., 0], want, rtol=0.01, atol=1e-3 * np.abs(want).max())


# --------------------------------------------------------------------------- tiers


@given(seed=st.integers(0, 2**31 - 1), full=st.booleans())
def test_visibility_pass_tiers_agree(seed, full):
    """Point evaluation (few texels) and whole synthesis (all texels) against dense numpy reconstruction."""
    rng = np.random.default_rng(seed)
    res, nv, npts = 4, 5, 7
    n = 6 * res * res
    factors = []
    for _ in range(2):
        table = encode_sparse(rng.random((npts, 6, res, res)), int(rng.integers(1, n)))
        corners = rng.integers(0, npts, size=(nv, 8))
        weights = rng.random((nv, 8))
        weights[0] = 0.0  # beyond the outermost sphere: factor 1
        factors.append((table, corners, weights, rng.permutation(n)))
    query = np.tile(np.arange(n), (nv, 1)) if full else rng.integers(0, n, size=(nv, 5))
    fast = haar_visibility_pass(query, factors, res)
    np.testing.assert_allclose(fast, haar_visibility_pass(query, factors, res, method="reference"),
                               atol=FLOAT_TOLERANCE[np.float64] * 100)


@given(seed=st.integers(0, 2**31 - 1))
def test_direct_pass_tiers_agree(seed):
    rng = np.random.default_rng(seed)
    args = (rng.random((4, 9)), rng.normal(size=(4, 9, 2)), rng.random((4, 9, 3)), rng.integers(0, 10, size=4))
    np.testing.assert_allclose(haar_direct_pass(*args), haar_direct_pass(*args, method="reference"),
                               atol=FLOAT_TOLERANCE[np.float64] * 100)


def test_haar_direct_tiers_agree_with_occluders_and_rotation(rng):
    ball = builtin_mesh("icosphere", radius=0.5, subdivisions=2)
    field = haar_occlusion_field(ball, resolution=8, keep=64, n_radii=3, grid_resolution=2)
    T = Transform(translate=np.array([0.0, 1.0, 0.0]), rotate_deg=np.array([10.0, 40.0, 0.0]))
    x = rng.uniform(-1, 1, size=(9, 3)) * [1, 0, 1]
    n = np.tile([0.0, 1, 0], (9, 1))
    lights = [LIGHT, PointLight(np.array([0.2, 2.5, 0.0]), np.ones(3)), EnvironmentLight(constant=np.ones(3))]
    fast = haar_direct(x, n, lights, PHONG, occluders=[(field, T)])
    ref = haar_direct(x, n, lights, PHONG, occluders=[(field, T)], method="reference")
    np.testing.assert_allclose(fast, ref, atol=1e-10)
    free = haar_direct(x, n, lights, PHONG)
    assert np.all(fast[:, 0] <= free[:, 0] + 1e-12) and np.any(fast[:, 0] < free[:, 0] - 1e-6)
    assert haar_direct(np.zeros((0, 3)), np.zeros((0, 3)), lights, PHONG).shape == (0, 3, 3)
    assert haar_direct(x, n, [], PHONG).shape == (9, 3, 3)


def test_errors():
    x, n = np.zeros((1, 3)), np.array([[0.0, 1, 0]])
    with pytest.raises(ValueError, match="points must be a"):
        haar_direct(np.zeros(3), n, [LIGHT], LAMBERT)
    with pytest.raises(ValueError, match="points contains NaN or inf"):
        haar_direct([[np.nan, 0, 0]], n, [LIGHT], LAMBERT)
    with pytest.raises(TypeError, match="sep must be a SeparableBRDF"):
        haar_direct(x, n, [LIGHT], "lambert")
    with pytest.raises(TypeError, match="lights must be"):
        haar_direct(x, n, ["sun"], LAMBERT)
    with pytest.raises(ValueError, match="method must be"):
        haar_direct(x, n, [LIGHT], LAMBERT, method="gpu")
    with pytest.raises(TypeError, match=r"occluders\[0\] must be"):
        haar_direct(x, n, [LIGHT], LAMBERT, occluders=["ball"])
    with pytest.raises(TypeError, match="self_visibility must be SparseCubemaps"):
        haar_direct(x, n, [LIGHT], LAMBERT, self_visibility=np.ones((1, 6, 4, 4)))
    with pytest.raises(ValueError, match="one cubemap per point"):
        haar_direct(x, n, [LIGHT], LAMBERT, self_visibility=encode_sparse(np.ones((2, 6, 4, 4)), 4))
    with pytest.raises(ValueError, match="share one cubemap resolution"):
        haar_direct(x, n, [LIGHT], LAMBERT, self_visibility=encode_sparse(np.ones((1, 6, 4, 4)), 4), resolution=8)
    with pytest.raises(ValueError, match="g_weight and radiance must be"):
        haar_direct_pass(np.ones((2, 3)), np.ones((2, 4, 1)), np.ones((2, 3, 3)))
    with pytest.raises(ValueError, match="power of two"):
        light_pieces([LIGHT], x, n, LAMBERT, 6)
