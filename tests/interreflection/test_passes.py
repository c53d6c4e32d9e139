"""Tests of prtlab/interreflection/_passes.py: basis irradiance (Eq. 13), weights (Eq. 14), bounces (Eq. 12)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prtlab import brdf, pca, sh
from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.interreflection import basis_irradiance, basis_radiance_at, fit_weights, outgoing_radiance, reflected_light
from prtlab.reference import irradiance_at
from prtlab.scene import AreaLight, Material, Scene, SceneObject, Transform
from prtlab.shadowfields import sphere_grid
from tests.conftest import FLOAT_TOLERANCE, MC_SIGMAS

ORDER = 4
N2 = ORDER * ORDER


# --------------------------------------------------------------------------- tiers


@given(seed=st.integers(0, 2**31 - 1), turned=st.booleans())
def test_basis_irradiance_numba_tier_equals_reference(seed, turned):
    rng = np.random.default_rng(seed)
    grid = sphere_grid(builtin_mesh("icosphere", subdivisions=1), n_radii=3, resolution=3)
    field = rng.normal(size=grid.shape + (2, 3, 4))
    pts = rng.normal(size=(6, 3)) * 4.0
    transfer = rng.normal(size=(6, 2, 4))
    pose = Transform(translate=rng.normal(size=3), rotate_deg=rng.uniform(-90, 90, 3), scale=1.3) if turned else None
    a = basis_irradiance(field, grid, pts, transfer, pose)
    b = basis_irradiance(field, grid, pts, transfer, pose, method="reference")
    assert a.shape == (6, 2, 2, 3)
    np.testing.assert_allclose(a, b, atol=FLOAT_TOLERANCE[np.float64] * 100)


def test_basis_irradiance_of_a_turned_source_is_the_world_frame_integral(rng):
    """<S_world, T> computed by rotating T into the source frame equals rotating S to the world frame."""
    grid = sphere_grid(builtin_mesh("icosphere", subdivisions=1), n_radii=2, resolution=2)
    field = rng.normal(size=grid.shape + (1, 2, N2))
    pose = Transform(translate=np.array([0.5, 0, 0]), rotate_deg=np.array([30.0, -20.0, 45.0]))
    p = pose.translate + np.array([[0.0, 2.0, 0.3]])
    transfer = rng.normal(size=(1, 1, N2))
    from prtlab.shadowfields import interpolate_field

    local = ((p - pose.translate) @ pose.rotation) / pose.scale
    s_obj, _ = interpolate_field(grid, field, local, method="reference")  # (1, 1, 2, N2)
    s_world = sh.rotate(s_obj[0, 0], pose.rotation, channels=False)  # (2, N2)
    expected = s_world @ transfer[0, 0]
    np.testing.assert_allclose(basis_irradiance(field, grid, p, transfer, pose)[0, 0, 0], expected, atol=1e-12)


def test_beyond_the_outermost_sphere_falls_off_as_inverse_square():
    grid = sphere_grid(builtin_mesh("icosphere", subdivisions=1), n_radii=2, resolution=2, r_min=1, r_max=2)
    field = np.ones(grid.shape + (1, 1, 1))
    out = basis_irradiance(field, grid, np.array([[0, 0, 2.0], [0, 0, 4.0]]) * grid.radius, np.ones((2, 1, 1)))
    np.testing.assert_allclose(out[:, 0, 0, 0], [1.0, 0.25])


@given(seed=st.integers(0, 2**31 - 1))
def test_reflected_light_tiers(seed):
    rng = np.random.default_rng(seed)
    phis = [rng.normal(size=(5, 2, 1, 4)), rng.normal(size=(5, 2, 3, 2))]
    ws = [rng.normal(size=(1, 4, 3)), rng.normal(size=(3, 2, 3))]
    a = reflected_light(phis, ws)
    b = reflected_light(phis, ws, method="reference")
    np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_allclose(a, sum(np.einsum("vkm,mc->vkc", p.reshape(5, 2, -1), w.reshape(-1, 3))
                                      for p, w in zip(phis, ws)), atol=1e-12)


@given(seed=st.integers(0, 2**31 - 1), n_k=st.integers(1, 3))
def test_outgoing_radiance_tiers(seed, n_k):
    """The kernel against numpy's einsum, and against the sum written out for one vertex."""
    rng = np.random.default_rng(seed)
    light, h, colour = rng.normal(size=(7, n_k, 3)), rng.normal(size=(7, n_k)), rng.random((n_k, 3))
    a = outgoing_radiance(light, h, colour)
    np.testing.assert_allclose(a, outgoing_radiance(light, h, colour, method="reference"), rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(a[2], sum(h[2, k] * colour[k] * light[2, k] for k in range(n_k)), rtol=1e-13,
                               atol=1e-13)
    with pytest.raises(ValueError, match="do not match"):
        outgoing_radiance(light, h[:, :1] if n_k > 1 else h[:, [0, 0]], colour)


def test_weights_reproduce_a_function_in_the_span():
    mesh = builtin_mesh("icosphere", subdivisions=1)
    basis = pca.fit_pca_basis(mesh, 6, 32)
    sep = brdf.separable(brdf.lambert(np.array([0.2, 0.4, 0.6])), 1, resolution=(8, 16))
    coeff = np.array([1.0, 0.3, -0.2, 0.0, 0.1, 0.05])
    light = np.repeat((coeff @ basis.basis)[:, None, None], 3, axis=2)  # (V, 1, 3)
    w = fit_weights(basis, light, sep.colour)
    np.testing.assert_allclose(w[0], coeff[:, None] * sep.colour[0][None, :], atol=1e-10)
    np.testing.assert_allclose(outgoing_radiance(light, np.ones((len(light), 1)), sep.colour),
                               light[:, 0] * sep.colour[0], atol=1e-14)


# --------------------------------------------------------------------------- against Monte Carlo


@settings(max_examples=8, deadline=None)
@given(px=st.floats(-0.8, 0.8), py=st.floats(0.3, 1.2), pz=st.floats(-0.8, 0.8),
       tilt=st.floats(0.0, 1.0), azimuth=st.floats(0.0, 2 * np.pi))
def test_basis_irradiance_of_a_lit_floor_against_monte_carlo(px, py, pz, tilt, azimuth):
    """One source, one receiver point: a floor lit by a square area light, a point above it facing down
    (tilted from straight down by up to 1 rad), anywhere over the floor's middle.

    Ours: the floor's exact vertex radiance as weights of hat basis functions (Psi = identity, so the
    basis itself adds no error), S projected at the point (degree 127), integrated against the order-4
    SH of ``cos / pi``. Error budget: by orthogonality
    ``|int S G - <S_n, G_n>| = |<S - S_n, G - G_n>| <= ||S - S_n|| ||G - G_n||`` (the SH truncation,
    computed here from a dense quadrature of ``S``), plus the step-quadrature error of ``S``
    (``||s - S_n||``, the projection at degree 127 against the dense quadrature's) times ``||G_n||``, plus
    the Monte Carlo error.
    """
    floor = builtin_mesh("plane", size=[2.0, 2.0], resolution=[16, 16])
    albedo = 0.8
    light = AreaLight(center=np.array([0.3, 1.5, 0.0]), u=np.array([0.25, 0, 0]), v=np.array([0, 0, 0.25]),
                      radiance=np.full(3, 20.0))  # faces down
    assert light.normal[1] < 0
    # exact vertex radiance of the floor (unoccluded): albedo/pi * int over the light of cos cos / r^2
    x, wgt = np.polynomial.legendre.leggauss(24)
    ys = (light.center + x[:, None, None] * light.u + x[None, :, None] * light.v).reshape(-1, 3)
    area_w = (wgt[:, None] * wgt[None, :]).ravel() * np.linalg.norm(np.cross(light.u, light.v))
    d = ys[None] - floor.vertices[:, None]
    r2 = np.sum(d * d, -1)
    cos_x = np.maximum(d[..., 1], 0) / np.sqrt(r2)
    cos_l = np.maximum(-(d @ light.normal), 0) / np.sqrt(r2)
    radiance = albedo / np.pi * 20.0 * np.sum(area_w * cos_x * cos_l / r2, axis=1)  # (V,)

    p = np.array([[px, py, pz]])
    n = np.array([np.sin(tilt) * np.cos(azimuth), -np.cos(tilt), np.sin(tilt) * np.sin(azimuth)])
    sep = brdf.separable(brdf.lambert(np.ones(3)), 1, resolution=(8, 16))
    s = basis_radiance_at(floor, radiance[None], sep, p, ORDER, degree=127)[0, 0, 0]  # S of the lit floor
    g = brdf.project_g_cos(sep, n, ORDER)[0]
    ours = np.pi * float(s @ g)

    # dense quadrature of S (no SH): ||S||^2 and the exact integral
    dirs, w = sh.quadrature(1, 255)
    hits = RayCaster([floor]).closest_hit(np.broadcast_to(p, dirs.shape), dirs)
    tri = floor.faces[np.where(hits.hit, hits.triangle, 0)]
    uv = hits.barycentric
    bary = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
    s_dense = np.where(hits.hit, np.sum(bary * radiance[tri], 1), 0.0)
    norm_s = np.sqrt(np.sum(w * s_dense**2))
    s_n = (w * s_dense) @ sh.basis(dirs, ORDER)  # S_n by the dense quadrature
    s_trunc = np.sqrt(max(norm_s**2 - float(s_n @ s_n), 0.0))
    g_norm2 = 2 * np.pi / 3 / np.pi**2  # ||cos+ / pi||^2
    g_trunc = np.sqrt(g_norm2 - float(g @ g))
    bound = np.pi * (s_trunc * g_trunc + np.linalg.norm(s - s_n) * np.linalg.norm(g))
    exact = float(np.sum(w * s_dense * np.maximum(dirs @ n, 0)))
    assert abs(ours - exact) <= bound

    scene = Scene(objects=[SceneObject("floor", floor, material=Material("diffuse", np.full(3, albedo)))],
                  lights=[light])
    est = irradiance_at(scene, p, n, 256, np.random.default_rng(5), bounces=1)
    corners = light.center + np.array([[a, b] for a in (-1, 1) for b in (-1, 1)]) @ np.stack([light.u, light.v])
    if np.all((corners - p) @ n <= 0):  # the light below the receiver's horizon: no direct light
        assert np.all(est.direct == 0)
    mc, se = est.indirect[0, 0], est.indirect_stderr[0, 0]
    assert abs(exact - mc) <= MC_SIGMAS * se + 0.01 * exact  # piecewise-linear vertex radiance vs exact shading
    assert abs(ours - mc) <= MC_SIGMAS * se + bound + 0.01 * exact


# --------------------------------------------------------------------------- errors


def test_errors():
    grid = sphere_grid(builtin_mesh("icosphere", subdivisions=1), n_radii=2, resolution=2)
    field = np.zeros(grid.shape + (1, 2, 4))
    with pytest.raises(ValueError, match="field must be"):
        basis_irradiance(field[0], grid, np.zeros((1, 3)), np.zeros((1, 1, 4)))
    with pytest.raises(ValueError, match="points must be"):
        basis_irradiance(field, grid, np.zeros(3), np.zeros((1, 1, 4)))
    with pytest.raises(ValueError, match="transfer must be"):
        basis_irradiance(field, grid, np.zeros((1, 3)), np.zeros((1, 1, 9)))
    with pytest.raises(ValueError, match="NaN or inf"):
        basis_irradiance(field, grid, np.full((1, 3), np.nan), np.zeros((1, 1, 4)))
    with pytest.raises(ValueError, match="method must be"):
        basis_irradiance(field, grid, np.zeros((1, 3)), np.zeros((1, 1, 4)), method="gpu")
    assert basis_irradiance(field, grid, np.zeros((0, 3)), np.zeros((0, 2, 4))).shape == (0, 2, 1, 2)
    with pytest.raises(ValueError, match="one per source"):
        reflected_light([np.zeros((1, 1, 1, 1))], [])
    with pytest.raises(ValueError, match="at least one source"):
        reflected_light([], [])
    with pytest.raises(ValueError, match="do not match"):
        reflected_light([np.zeros((1, 1, 1, 2))], [np.zeros((1, 3, 3))])
    with pytest.raises(ValueError, match="light must be"):
        fit_weights(None, np.zeros((3, 2, 3)), np.zeros((1, 3)))
