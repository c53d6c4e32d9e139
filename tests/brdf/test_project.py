"""Tests of prtlab.brdf._project: SH vectors of g_k cos per normal, h_k per view."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import sh
from prtlab.brdf import lambert, phong, project_g_cos, project_h, separable, to_local, to_world, transfer_error
from tests.conftest import FLOAT_TOLERANCE, random_directions, random_rotation

TOL = FLOAT_TOLERANCE[np.float64]
POLES = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 1.0, 0], [0, -1.0, 0], [1.0, 0, 0]])


def _normals(rng, n=8):
    return np.concatenate([POLES, random_directions(rng, n)])


def _isotropic_K(sep_full, index):
    s = sep_full.singular_values
    return [k for k in range(1, len(s)) if s[k - 1] - s[k] > 1e-9 * s[0]][index]


# --------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("order", [1, 2, 4, 6])
def test_lambert_is_the_clamped_cosine_zh(rng, order):
    sep = separable(lambert([0.4, 0.8]), 1)
    n = _normals(rng)
    c = project_g_cos(sep, n, order)
    assert c.shape == (len(n), 1, order * order)
    np.testing.assert_allclose(c[:, 0], sh.zh_rotate(sh.clamped_cosine_zh(order), n) / np.pi, rtol=0, atol=TOL)


def test_lambert_reflected_radiance_is_albedo_times_irradiance(rng):
    albedo = np.array([0.4, 0.8, 0.1])
    sep = separable(lambert(albedo), 1)
    order = 4
    L = rng.normal(size=(order * order, 3))  # coloured SH radiance
    n = _normals(rng)
    wo = random_directions(rng, len(n))
    c = project_g_cos(sep, n, order)  # (V, K, n^2)
    h = project_h(sep, wo, n)  # (V, K)
    radiance = np.einsum("vk,kc,vkl,lc->vc", h, sep.colour, c, L)
    expected = albedo / np.pi * sh.evaluate(sh.irradiance(L), n)
    np.testing.assert_allclose(radiance, expected, atol=TOL)


# --------------------------------------------------------------------------- tiers and outside references


def test_rotation_tier_matches_world_quadrature_tier(rng):
    sep = separable(phong([0.1, 0.3], [0.6, 0.5], 12.0), 5, resolution=(16, 32))
    n = _normals(rng, 6)
    np.testing.assert_allclose(project_g_cos(sep, n, 5), project_g_cos(sep, n, 5, method="reference"), atol=TOL)


def test_matches_independent_hemisphere_quadrature(rng):
    """sh.project of w -> g_k(local(w)) max(0, n.w) on a finer hemisphere grid about each normal.

    The two differ only by the linear interpolation of the radial profiles
    (the independent grid samples between the nodes); the tolerance is the
    interpolation error bound ``h^2 / 8 max|u''|`` (divided differences),
    times ``int cos |Y_lm| <= sqrt(2 pi / 3)`` (Cauchy-Schwarz), doubled.
    """
    sep = separable(phong(0.0, 1.0, 10.0), 4, resolution=(32, 64))
    order = 4
    theta = sep.theta_in
    h = np.diff(theta)
    second = np.abs(np.diff(np.diff(sep.g_radial, axis=1) / h, axis=1)) / (0.5 * (h[1:] + h[:-1]))
    bound = np.max(h) ** 2 / 8.0 * second.max(axis=1)  # (K,)
    tol = 2.0 * bound * np.sqrt(2.0 * np.pi / 3.0)
    t, w = np.polynomial.legendre.leggauss(97)
    th = 0.25 * np.pi * (t + 1.0)
    n_phi = 96
    phi = 2.0 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    local = np.stack(np.broadcast_arrays(np.sin(th)[:, None] * np.cos(phi), np.sin(th)[:, None] * np.sin(phi),
                                         np.cos(th)[:, None]), axis=-1).reshape(-1, 3)
    weights = np.repeat(0.25 * np.pi * w * np.sin(th) * 2.0 * np.pi / n_phi, n_phi)
    for normal in _normals(rng, 3):
        world = to_world(local, normal)
        values = sep.g(to_local(world, normal)) * local[:, 2:3]
        direct = sh.project(values, world, weights, order)  # (n^2, K)
        got = project_g_cos(sep, normal, order)  # (K, n^2)
        assert np.all(np.abs(got - direct.T) <= tol[:, None])


def test_radiance_is_frame_independent_for_isotropic_K(rng):
    b = phong(0.2, 0.7, 10.0)
    K = _isotropic_K(separable(b, 40, resolution=(16, 32)), 2)
    sep = separable(b, K, resolution=(16, 32))
    assert sep.isotropic
    order = 4
    L = rng.normal(size=order * order)
    n = random_directions(rng, 6)
    wo = random_directions(rng, 6)
    wo *= np.sign(np.sum(wo * n, axis=1, keepdims=True))
    R = random_rotation(rng)

    def radiance(normals, views, coeffs):
        return np.einsum("vk,k,vkl,l->v", project_h(sep, views, normals), sep.colour[:, 0],
                         project_g_cos(sep, normals, order), coeffs)

    np.testing.assert_allclose(radiance(n @ R.T, wo @ R.T, sh.rotate(L, R)), radiance(n, wo, L), atol=TOL)


def test_project_h(rng):
    sep = separable(phong(0.2, 0.7, 10.0), 4, resolution=(16, 32))
    n = random_directions(rng, 12).reshape(3, 4, 3)
    wo = random_directions(rng, 12).reshape(3, 4, 3)
    h = project_h(sep, wo, n)
    assert h.shape == (3, 4, 4)
    np.testing.assert_allclose(h, sep.h(to_local(wo, n)), atol=TOL)
    np.testing.assert_allclose(project_h(sep, wo[0]), sep.h(wo[0]), atol=TOL)
    np.testing.assert_allclose(project_h(sep, wo, n, method="reference"), h, atol=1e-12)
    assert project_h(sep, np.zeros((0, 3))).shape == (0, 4)


# --------------------------------------------------------------------------- transfer error


def test_transfer_error():
    b = phong([0.2, 0.1, 0.3], [0.5, 0.6, 0.2], 12.0)
    probe = separable(b, 1, resolution=(8, 11))
    full = separable(b, len(probe.singular_values) + 1, resolution=(8, 11))
    assert np.all(transfer_error(full, 4) < 1e-10)
    assert np.all(transfer_error(separable(lambert([0.3, 0.6]), 1, resolution=(8, 11)), 3) < 1e-10)
    grey = phong(0.0, 1.0, 16.0)
    full_grey = separable(grey, 60, resolution=(12, 24))
    ks = [_isotropic_K(full_grey, i) for i in range(6)]
    errs = [transfer_error(separable(grey, k, resolution=(12, 24)), 4)[0] for k in ks]
    assert np.all(np.diff(errs) <= 1e-12)


# --------------------------------------------------------------------------- shapes and errors


def test_shapes():
    sep = separable(phong(0.2, 0.7, 10.0), 3, resolution=(8, 11))
    assert project_g_cos(sep, np.zeros((0, 3)), 3).shape == (0, 3, 9)
    assert project_g_cos(sep, np.ones((2, 5, 3)), 2).shape == (2, 5, 3, 4)
    assert project_g_cos(sep, [0, 1, 0], 3).shape == (3, 9)


def test_errors():
    sep = separable(phong(0.2, 0.7, 10.0), 3, resolution=(8, 11))
    refl = separable(phong(0.2, 0.7, 10.0), 2, resolution=(8, 11), parameterisation="reflection")
    with pytest.raises(ValueError, match="reflection' parameterisation"):
        project_g_cos(refl, [0, 0, 1], 3)
    with pytest.raises(ValueError, match="reflection' parameterisation"):
        project_h(refl, [0, 0, 1])
    with pytest.raises(TypeError, match="sep must be a SeparableBRDF"):
        project_g_cos(phong(0.2, 0.7, 10.0), [0, 0, 1], 3)
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        project_g_cos(sep, [0, 0, 1], 0)
    with pytest.raises(TypeError, match="order must be an int"):
        project_g_cos(sep, [0, 0, 1], 2.5)
    with pytest.raises(ValueError, match=r"normals must be a \(\.\.\., 3\) array"):
        project_g_cos(sep, np.ones((3, 4)), 3)
    with pytest.raises(ValueError, match="normals contains NaN or inf"):
        project_g_cos(sep, [np.nan, 0, 1], 3)
    with pytest.raises(ValueError, match="method must be one of"):
        project_g_cos(sep, [0, 0, 1], 3, method="fast")
    with pytest.raises(ValueError, match="wo_dirs contains a zero vector"):
        project_h(sep, [0, 0, 0])
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        transfer_error(sep, 0)
