"""Tests of prtlab.brdf._models: Lambert and normalised Phong, the local frame."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.brdf import from_material, lambert, local_frame, phong, to_local, to_world
from prtlab.brdf._kernels import tangent_frame_at
from prtlab.geometry import tangent_frame
from prtlab.reference._kernels import bsdf_eval_numpy
from prtlab.scene import Material
from tests.conftest import FLOAT_TOLERANCE, random_directions

TOL = FLOAT_TOLERANCE[np.float64]


def _same_side(rng, n):
    """Random (normal, wi, wo) triples with wi and wo above the normal."""
    normal = random_directions(rng, n)
    wi = random_directions(rng, n)
    wo = random_directions(rng, n)
    wi *= np.sign(np.sum(wi * normal, axis=1, keepdims=True))
    wo *= np.sign(np.sum(wo * normal, axis=1, keepdims=True))
    return normal, wi, wo


# --------------------------------------------------------------------------- known answers


def test_lambert_is_albedo_over_pi(rng):
    b = lambert([0.2, 0.5, 0.9])
    normal, wi, wo = _same_side(rng, 50)
    np.testing.assert_allclose(b.eval(wi, wo, normal), np.broadcast_to([0.2 / np.pi, 0.5 / np.pi, 0.9 / np.pi], (50, 3)))
    assert b.channels == 3 and np.array_equal(b.albedo, [0.2, 0.5, 0.9])


def test_lambert_directional_albedo_is_albedo():
    b = lambert([0.3, 0.7])
    a = b.directional_albedo(np.array([1.0, 0.5, 0.01]))
    np.testing.assert_allclose(a, np.broadcast_to([0.3, 0.7], (3, 2)), rtol=0, atol=TOL)


@pytest.mark.parametrize("exponent", [0.0, 1.0, 10.0, 16.0, 128.0])
def test_phong_normalisation_at_normal_incidence(exponent):
    b = phong(0.25, 0.6, exponent)
    # the peak value: wi = wo = n
    np.testing.assert_allclose(b.eval([0, 0, 1], [0, 0, 1]), [0.25 / np.pi + 0.6 * (exponent + 2) / (2 * np.pi)])
    # (e + 2)/(2 pi) int cos^(e+1) = 1: the albedo at normal incidence is exactly kd + ks
    np.testing.assert_allclose(b.directional_albedo(1.0), [0.85], rtol=0, atol=1e-10)


@pytest.mark.parametrize("exponent", [1.0, 10.0, 64.0])
def test_phong_energy_never_gained(exponent):
    b = phong([0.1, 0.4], [0.9, 0.6], exponent)
    mu = np.array([1.0, 0.9, 0.7, 0.5, 0.3, 0.1, 0.02])
    a = b.directional_albedo(mu, n_nodes=192)
    assert np.all(a <= 1.0 + 1e-10)
    # normalised Phong loses energy at grazing incidence: the lobe drops below the horizon. With the mirror
    # direction at elevation d (sin d = mu), cos(theta_o) = cos(a) sin(d) + sin(a) cos(d) cos(phi) about it,
    # so the lobe's albedo is at most sin(d) + cos(d) (e + 2) / (2 pi) B((e + 1) / 2, 3 / 2)
    from scipy.special import beta

    assert np.all(np.diff(a[:, 0]) <= 1e-12)
    sin_d = mu[-1]
    lobe = sin_d + np.sqrt(1 - sin_d**2) * (exponent + 2) / (2 * np.pi) * beta((exponent + 1) / 2, 1.5)
    assert a[-1, 0] <= 0.1 + 0.9 * lobe, (a[-1, 0], 0.1 + 0.9 * lobe)


# --------------------------------------------------------------------------- identities


@given(seed=st.integers(0, 2**32 - 1), exponent=st.floats(0.0, 200.0))
def test_reciprocity(seed, exponent):
    rng = np.random.default_rng(seed)
    b = phong([0.3, 0.1, 0.0], [0.5, 0.2, 1.0], exponent)
    normal, wi, wo = (random_directions(rng, 64) for _ in range(3))
    np.testing.assert_allclose(b.eval(wi, wo, normal), b.eval(wo, wi, normal), rtol=1e-10, atol=1e-12)


@given(seed=st.integers(0, 2**32 - 1), exponent=st.floats(0.0, 200.0))
def test_numba_tier_matches_reference_tier(seed, exponent):
    rng = np.random.default_rng(seed)
    b = phong([0.3, 0.2], [0.4, 0.8], exponent)
    normal, wi, wo = (random_directions(rng, 64) for _ in range(3))
    np.testing.assert_allclose(b.eval(wi, wo, normal), b.eval(wi, wo, normal, method="reference"), rtol=1e-13, atol=1e-14)


def test_two_sided(rng):
    b = phong(0.3, 0.5, 12.0)
    normal, wi, wo = _same_side(rng, 40)
    front = b.eval(wi, wo, normal)
    np.testing.assert_array_equal(b.eval(wi, wo, -normal), front)  # the side is that of wo
    np.testing.assert_array_equal(b.eval(-wi, -wo, normal), b.eval(-wi, -wo, -normal))
    np.testing.assert_allclose(b.eval(-wi, -wo, normal), front)  # mirror image: same reflection
    opposite = b.eval(-wi, wo, normal)  # no transmission
    np.testing.assert_array_equal(opposite, np.zeros_like(opposite))


def test_local_frame_default_is_z(rng):
    b = phong(0.3, 0.5, 12.0)
    _, wi, wo = _same_side(rng, 10)
    np.testing.assert_array_equal(b.eval(wi, wo), b.eval(wi, wo, [0.0, 0.0, 1.0]))


# --------------------------------------------------------------------------- closed forms


@pytest.mark.parametrize("exponent", [0.0, 3.0, 10.0, 64.0])
def test_albedo_at_normal_incidence_is_kd_plus_ks(exponent):
    """At ``wi = n`` the mirror direction is ``n``, so the normalised lobe integrates in closed form:
    ``int (e+2)/(2 pi) cos^e(theta) cos(theta) dw = 1`` and ``int kd/pi cos dw = kd``: albedo ``kd + ks``."""
    kd, ks = np.array([0.2, 0.4, 0.1]), np.array([0.7, 0.3, 0.5])
    mu, weight = np.polynomial.legendre.leggauss(200)
    mu, weight = 0.5 * (mu + 1.0), 0.5 * weight                      # Gauss-Legendre on cos(theta) in [0, 1]
    wo = np.stack([np.sqrt(1.0 - mu**2), np.zeros_like(mu), mu], axis=1)  # the integrand does not depend on phi
    f = phong(kd, ks, exponent).eval(np.tile([0.0, 0.0, 1.0], (len(mu), 1)), wo)
    albedo = 2.0 * np.pi * np.sum(f * (mu * weight)[:, None], axis=0)
    np.testing.assert_allclose(albedo, kd + ks, rtol=1e-12)


# --------------------------------------------------------------------------- the other implementations
# The same Phong formula as written by the Monte Carlo estimator and the Mitsuba adapter (in-repo code,
# not outside references): all three must agree to rounding, so a fix in one reaches the others.


@pytest.mark.parametrize("exponent", [0.0, 3.0, 10.0, 64.0])
def test_matches_reference_estimator_bsdf(rng, exponent):
    kd, ks = np.array([0.2, 0.4, 0.1]), np.array([0.7, 0.3, 0.5])
    normal, wi, wo = _same_side(rng, 200)
    b = phong(kd, ks, exponent)
    fcos, _ = bsdf_eval_numpy(normal, wo, wi, np.tile(kd, (200, 1)), np.tile(ks, (200, 1)), np.full(200, exponent))
    expected = b.eval(wi, wo, normal) * np.sum(wi * normal, axis=1, keepdims=True)
    np.testing.assert_allclose(fcos, expected, rtol=1e-12, atol=1e-14)


def test_matches_mitsuba_adapter_brdf(rng):
    from prtlab.reference._mitsuba import _brdf_cos

    kd, ks, e = np.array([0.2, 0.4, 0.1]), np.array([0.7, 0.3, 0.5]), 20.0
    normal, wi, wo = _same_side(rng, 200)
    expected = phong(kd, ks, e).eval(wi, wo, normal) * np.sum(wi * normal, axis=1, keepdims=True)
    np.testing.assert_allclose(_brdf_cos(wi, normal, wo, kd, ks, e), expected, rtol=1e-12, atol=1e-14)


def test_from_material():
    diffuse = from_material(Material(type="diffuse", albedo=np.array([0.1, 0.2, 0.3])))
    assert np.array_equal(diffuse.kd, [0.1, 0.2, 0.3]) and not diffuse.ks.any()
    glossy = from_material(Material(type="phong", kd=np.array([0.1, 0.2, 0.3]), ks=np.array([0.5] * 3), exponent=10.0))
    assert glossy.exponent == 10.0 and np.array_equal(glossy.ks, [0.5] * 3)


# --------------------------------------------------------------------------- local frame


def test_local_frame_is_the_tangent_frame(rng):
    n = random_directions(rng, 30)
    R = local_frame(n)
    t, b = tangent_frame(n)
    np.testing.assert_allclose(R[..., 0], t, atol=TOL)
    np.testing.assert_allclose(R[..., 1], b, atol=TOL)
    np.testing.assert_allclose(R[..., 2], n, atol=TOL)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=TOL)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=TOL)


def test_kernels_frame_is_the_tangent_frame(rng):
    """``_kernels.tangent_frame_at`` (the kernels' inline frame) gives the unit normal and
    ``tangent_frame``'s tangents, unnormalised normals included, the poles too."""
    n = np.concatenate([random_directions(rng, 30) * rng.uniform(0.2, 5.0, (30, 1)), np.eye(3), -np.eye(3)])
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    t, b = tangent_frame(unit)
    got = np.array([tangent_frame_at(*row) for row in n])
    np.testing.assert_allclose(got[:, 0:3], unit, atol=TOL)
    np.testing.assert_allclose(got[:, 3:6], t, atol=TOL)
    np.testing.assert_allclose(got[:, 6:9], b, atol=TOL)


def test_to_local_and_back(rng):
    n = random_directions(rng, 30)
    d = random_directions(rng, 30)
    local = to_local(d, n)
    np.testing.assert_allclose(local[:, 2], np.sum(d * n, axis=1), atol=TOL)
    np.testing.assert_allclose(to_world(local, n), d, atol=TOL)
    np.testing.assert_allclose(to_local(n, n), np.broadcast_to([0.0, 0.0, 1.0], (30, 3)), atol=TOL)


def test_poles_of_the_frame():
    for n in ([0, 0, 1], [0, 0, -1], [0, 1, 0], [1, 0, 0], [0, -1, 0]):
        np.testing.assert_allclose(to_local(n, n), [0, 0, 1], atol=TOL)


# --------------------------------------------------------------------------- shapes


def test_shapes_and_broadcasting(rng):
    b = phong([0.1, 0.2, 0.3], 0.5, 4.0)
    wi = random_directions(rng, 12).reshape(3, 4, 3)
    assert b.eval(wi, [0.0, 0.0, 1.0]).shape == (3, 4, 3)
    assert b.eval(wi[:, :1], wi[:1], [0, 1, 0]).shape == (3, 4, 3)
    assert b.eval(np.zeros((0, 3)) + 1, np.zeros((0, 3)) + 1).shape == (0, 3)
    assert b.eval(np.ones((2, 0, 3)), [0, 0, 1], method="reference").shape == (2, 0, 3)
    assert phong(0.5, 0.5, 1).eval([0, 0, 1], [0, 0, 1]).shape == (1,)
    assert to_local(np.ones((0, 3)), [0, 0, 1]).shape == (0, 3)
    # unnormalised input is normalised
    np.testing.assert_allclose(b.eval([0, 0, 5], [0, 0, 2]), b.eval([0, 0, 1], [0, 0, 1]))


# --------------------------------------------------------------------------- errors


def test_errors():
    with pytest.raises(ValueError, match="exponent must be a finite number >= 0"):
        phong(0.5, 0.5, -1.0)
    with pytest.raises(ValueError, match="exponent must be a finite number >= 0"):
        phong(0.5, 0.5, np.inf)
    with pytest.raises(TypeError, match="exponent must be a real number"):
        phong(0.5, 0.5, "10")
    with pytest.raises(ValueError, match="energy gain"):
        phong([0.5, 0.7], [0.5, 0.4], 10.0)
    with pytest.raises(ValueError, match=r"ks must lie in \[0, 1\]"):
        phong(0.0, -0.1, 10.0)
    with pytest.raises(ValueError, match=r"albedo must lie in \[0, 1\]"):
        lambert(1.5)
    with pytest.raises(ValueError, match="albedo contains NaN"):
        lambert([0.5, np.nan])
    with pytest.raises(TypeError, match="kd must be a real scalar"):
        phong("red", 0.1, 1.0)
    with pytest.raises(ValueError, match="albedo must be a scalar or a"):
        lambert(np.ones((2, 3)) * 0.5)
    with pytest.raises(ValueError, match="kd has 3 channels and ks 2"):
        phong([0.1, 0.2, 0.3], [0.1, 0.2], 1.0)
    b = lambert(0.5)
    with pytest.raises(ValueError, match=r"wi must be a \(\.\.\., 3\) array"):
        b.eval(np.ones((4, 2)), [0, 0, 1])
    with pytest.raises(ValueError, match="wo contains NaN or inf"):
        b.eval([0, 0, 1], [0, np.nan, 1])
    with pytest.raises(ValueError, match="normal contains a zero vector"):
        b.eval([0, 0, 1], [0, 0, 1], [0, 0, 0])
    with pytest.raises(TypeError, match="wi must be a real"):
        b.eval(np.array(["a", "b", "c"]), [0, 0, 1])
    with pytest.raises(ValueError, match="do not broadcast"):
        b.eval(np.ones((4, 3)), np.ones((5, 3)))
    with pytest.raises(ValueError, match="method must be one of"):
        b.eval([0, 0, 1], [0, 0, 1], method="fast")
    with pytest.raises(ValueError, match=r"cos_theta must lie in \(0, 1\]"):
        b.directional_albedo(0.0)
    with pytest.raises(ValueError, match="n_nodes must be an int >= 2"):
        b.directional_albedo(0.5, n_nodes=1)
    with pytest.raises(ValueError, match="material must be a prtlab.scene.Material"):
        from_material(Material(type="mirror"))
