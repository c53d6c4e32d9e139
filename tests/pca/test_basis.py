"""Tests of prtlab.pca._basis: PCA basis functions from point-light renders (Iwasaki 2007, Sec. 4.2)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import builtin_mesh
from prtlab.pca import PCABasis, fit_pca_basis, pca_light_positions, point_light_intensity, principal_basis
from prtlab.scene import Material, SceneObject


@pytest.fixture(scope="module")
def sphere():
    return builtin_mesh("icosphere", subdivisions=2)


@pytest.fixture(scope="module")
def bunny_pca():
    return fit_pca_basis(builtin_mesh("bunny"), n_basis=16, n_lights=64)


# --------------------------------------------------------------------------- known answers


def test_point_light_on_sphere_closed_form(sphere):
    light = np.array([[0.0, 3.0, 0.0]])
    got = point_light_intensity(sphere, light, albedo=0.5)[0]
    x = np.asarray(sphere.vertices)
    n = np.asarray(sphere.vertex_normals)
    d = light[0] - x
    r2 = np.sum(d * d, 1)
    cos = np.sum(n * d, 1) / np.sqrt(r2)
    expected = np.where(cos > 0, 0.5 / np.pi * cos / r2, 0.0)
    # a convex object never shadows a vertex that faces the light
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-15)


def test_self_shadowing_on_concave_object():
    # two parallel plates: the lower one is shadowed by the upper one from a light above
    lower = trimesh.creation.box(extents=[1, 0.1, 1])
    upper = trimesh.creation.box(extents=[1, 0.1, 1])
    upper.apply_translation([0, 1, 0])
    both = trimesh.util.concatenate([lower, upper])
    light = np.array([[0.0, 5.0, 0.0]])
    lit = point_light_intensity(both, light, shadows=False)[0]
    shadowed = point_light_intensity(both, light)[0]
    top_of_lower = np.flatnonzero(np.isclose(both.vertices[:, 1], 0.05))
    assert np.all(lit[top_of_lower] > 0) and np.all(shadowed[top_of_lower] == 0)
    top_of_upper = np.flatnonzero(np.isclose(both.vertices[:, 1], 1.05))
    np.testing.assert_allclose(shadowed[top_of_upper], lit[top_of_upper])


def test_kernel_matches_reference(rng):
    mesh = builtin_mesh("bunny")
    lights = pca_light_positions(mesh, 16)
    np.testing.assert_allclose(
        point_light_intensity(mesh, lights), point_light_intensity(mesh, lights, method="reference"),
        rtol=1e-12, atol=1e-15,
    )


@given(seed=st.integers(0, 2**31), n=st.integers(0, 6))
def test_kernel_matches_reference_random_lights(seed, n):
    mesh = builtin_mesh("icosphere", subdivisions=1)
    lights = np.random.default_rng(seed).normal(size=(n, 3)) * 3.0
    fast = point_light_intensity(mesh, lights)
    assert fast.shape == (n, len(mesh.vertices))
    np.testing.assert_allclose(fast, point_light_intensity(mesh, lights, method="reference"), rtol=1e-12, atol=1e-14)


def test_light_positions_sphere_and_plane(sphere):
    p = pca_light_positions(sphere, 100)
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), 2.0, rtol=1e-9)  # twice the bounding radius 1
    np.testing.assert_allclose(np.linalg.norm(pca_light_positions(sphere, 10, 1.5), axis=1), 1.5)
    plane = builtin_mesh("plane", size=[4, 2], resolution=[4, 4])
    g = pca_light_positions(plane, 256, plane=True)
    assert g.shape == (256, 3)
    np.testing.assert_allclose(g[:, 1], 2.0)  # half the larger extent above the plane
    assert g[:, 0].min() > -2 and g[:, 0].max() < 2 and g[:, 2].min() > -1 and g[:, 2].max() < 1
    assert len(np.unique(g[:, 0])) == 16 and len(np.unique(g[:, 2])) == 16


def test_basis_structure(bunny_pca):
    pca = bunny_pca
    assert isinstance(pca, PCABasis) and pca.basis.shape == (16, 1839) and pca.n_basis == 16
    comps = pca.basis[1:]
    np.testing.assert_allclose(comps @ comps.T, np.eye(15), atol=1e-10)  # orthonormal components
    training = point_light_intensity(builtin_mesh("bunny"), pca.light_positions).T
    np.testing.assert_allclose(pca.basis[0], training.mean(axis=1), rtol=1e-12)
    # energy is Eckart-Young's captured fraction, from numpy's SVD of the centred training matrix
    sigma = np.linalg.svd(training - training.mean(axis=1, keepdims=True), compute_uv=False)
    np.testing.assert_allclose(pca.energy, np.concatenate([[0.0], np.cumsum(sigma[:15] ** 2)]) / np.sum(sigma**2),
                               rtol=1e-10, atol=1e-14)
    assert np.all(np.diff(pca.singular_values) <= 0)
    assert np.isfinite(pca.condition_number) and pca.a_inverse.shape == (16, 16)


def test_training_residual_equals_discarded_energy(bunny_pca):
    """Projecting a centred training column on the components leaves exactly the discarded singular values."""
    pca = bunny_pca
    training = point_light_intensity(builtin_mesh("bunny"), pca.light_positions).T
    centred = training - pca.basis[0][:, None]
    comps = pca.basis[1:]
    residual = centred - comps.T @ (comps @ centred)
    s = pca.singular_values
    np.testing.assert_allclose(np.sum(residual**2), np.sum(s[15:] ** 2), rtol=1e-8)
    # least squares over mean+components does at least as well as the PCA projection
    approx = pca.approximate(training.T)
    assert np.sum((approx - training.T) ** 2) <= np.sum(s[15:] ** 2) * (1 + 1e-9)


def test_weights_exact_in_span_and_subset_samples():
    mesh = builtin_mesh("icosphere", subdivisions=2)
    pca = fit_pca_basis(mesh, n_basis=6, n_lights=32, n_samples=60, seed=3)
    assert pca.samples.shape == (60,) and np.all(np.diff(pca.samples) > 0)
    w = np.random.default_rng(1).normal(size=(2, 6, 3))
    full = pca.reconstruct(w)  # (2, n_vertices, 3)
    np.testing.assert_allclose(pca.weights(full), w, atol=1e-9)  # full-vertex input picks the samples
    np.testing.assert_allclose(pca.weights(full[:, pca.samples]), w, atol=1e-9)
    np.testing.assert_allclose(pca.weights(full, method="reference"), w, atol=1e-9)
    t = pca.truncated(3)
    assert t.basis.shape == (3, len(mesh.vertices)) and t.solver.n_samples == 60


def test_reproducible_and_scene_object(sphere):
    a = fit_pca_basis(sphere, n_basis=4, n_lights=16)
    obj = SceneObject(name="s", mesh=sphere, material=Material())
    b = fit_pca_basis(obj, n_basis=4, n_lights=16)
    np.testing.assert_array_equal(a.basis, b.basis)
    c = fit_pca_basis(sphere, n_basis=4, n_lights=16, albedo=2.0)
    np.testing.assert_allclose(c.basis[0], 2 * a.basis[0])
    np.testing.assert_allclose(np.abs(c.basis[1:]), np.abs(a.basis[1:]), atol=1e-9)


def test_arrays_round_trip(sphere):
    a = fit_pca_basis(sphere, n_basis=4, n_lights=16, n_samples=50)
    b = PCABasis.from_arrays(a.to_arrays())
    for key, value in a.to_arrays().items():
        np.testing.assert_array_equal(getattr(b, key), value)
    np.testing.assert_allclose(b.a_inverse, a.a_inverse)
    with pytest.raises(ValueError, match="arrays lacks"):
        PCABasis.from_arrays({"basis": a.basis})


def test_plane_basis():
    """Plane mode: the basis spans the best rank-7 fit of the centred renders from the light grid above the
    plane, and the captured fraction ``energy[-1]`` is what that fit leaves (Eckart-Young)."""
    plane = builtin_mesh("plane", size=[2, 2], resolution=[8, 8])
    pca = fit_pca_basis(plane, n_basis=8, n_lights=64, plane=True)
    training = point_light_intensity(plane, pca_light_positions(plane, 64, plane=True)).T
    centred = training - training.mean(axis=1, keepdims=True)
    sigma = np.linalg.svd(centred, compute_uv=False)
    np.testing.assert_allclose(pca.energy[-1], np.sum(sigma[:7] ** 2) / np.sum(sigma**2), rtol=1e-10)
    comps = pca.basis[1:]
    residual = centred - comps.T @ (comps @ centred)
    np.testing.assert_allclose(np.sum(residual**2), (1 - pca.energy[-1]) * np.sum(sigma**2), rtol=1e-8)


# --------------------------------------------------------------------------- errors


def test_errors(sphere):
    with pytest.raises(TypeError, match="trimesh.Trimesh or a SceneObject"):
        fit_pca_basis(np.zeros(3))
    with pytest.raises(ValueError, match="n_basis - 1 <= min"):
        fit_pca_basis(sphere, n_basis=20, n_lights=8)
    with pytest.raises(ValueError, match="n_basis must be an int >= 1"):
        fit_pca_basis(sphere, n_basis=0)
    with pytest.raises(TypeError, match="n_lights must be an int"):
        fit_pca_basis(sphere, n_lights=2.5)
    with pytest.raises(ValueError, match="light_distance must be a finite number > 0"):
        fit_pca_basis(sphere, n_basis=2, n_lights=4, light_distance=-1)
    with pytest.raises(TypeError, match="light_distance must be a number"):
        pca_light_positions(sphere, 4, "far")
    with pytest.raises(TypeError, match="seed must be an int"):
        fit_pca_basis(sphere, n_basis=2, n_lights=4, seed=0.5)
    with pytest.raises(ValueError, match="n_samples must be <= n_vertices"):
        fit_pca_basis(sphere, n_basis=2, n_lights=4, n_samples=10_000)
    with pytest.raises(ValueError, match="n_samples must be an int >= 3"):
        fit_pca_basis(sphere, n_basis=3, n_lights=4, n_samples=2)
    with pytest.raises(ValueError, match="has no faces"):
        fit_pca_basis(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)))
    with pytest.raises(ValueError, match=r"light_positions must have shape \(n_lights, 3\)"):
        point_light_intensity(sphere, np.zeros(3))
    with pytest.raises(ValueError, match="light_positions contains NaN"):
        point_light_intensity(sphere, np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match="albedo must be"):
        point_light_intensity(sphere, np.ones((1, 3)) * 3, albedo=-1)
    with pytest.raises(ValueError, match="method must be one of"):
        point_light_intensity(sphere, np.ones((1, 3)) * 3, method="gpu")
    with pytest.raises(ValueError, match="normals summing to 0"):
        two = trimesh.util.concatenate([builtin_mesh("plane"), builtin_mesh("plane").apply_scale([1, -1, 1])])
        pca_light_positions(trimesh.Trimesh(two.vertices, two.faces, process=False), 4, plane=True)
    pca = fit_pca_basis(sphere, n_basis=4, n_lights=16)
    with pytest.raises(ValueError, match="n_basis must be <= 4"):
        pca.truncated(5)


def test_principal_basis_is_the_mean_and_the_leading_singular_vectors():
    rng = np.random.default_rng(5)
    # rank 2 after centring: the mean plus two directions, 40 vertices, 30 lights
    training = rng.random(40)[:, None] + rng.random((40, 2)) @ rng.standard_normal((2, 30))
    basis, s, energy = principal_basis(training, 3)
    assert basis.shape == (3, 40) and s.shape == (30,)
    np.testing.assert_allclose(basis[0], training.mean(axis=1), rtol=0, atol=1e-15)
    np.testing.assert_allclose(basis[1:] @ basis[1:].T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(energy[2], 1.0, rtol=1e-12)  # two components carry all the variance
    assert np.all(np.abs(basis[1:]).argmax(axis=1) == np.argmax(basis[1:], axis=1))  # largest entry positive
    # a third component would be a vector of the null space, where every singular value is 0 (equal): left out,
    # with or without the rank's cap
    for rank_tol in (None, 1e-12):
        capped, _, capped_energy = principal_basis(training, 4, rank_tol=rank_tol)
        assert capped.shape == (3, 40)
        np.testing.assert_array_equal(capped, basis)
        np.testing.assert_array_equal(capped_energy, energy)


def _with_singular_values(rng, values, n_v: int = 30, n_l: int = 20) -> np.ndarray:
    """A training matrix whose centred form has exactly the singular ``values`` (orthonormal factors orthogonal
    to the constant vector of the lights, so that centring leaves them)."""
    u, _ = np.linalg.qr(rng.standard_normal((n_v, len(values))))
    w = rng.standard_normal((n_l, len(values)))
    w -= w.mean(axis=0)
    v, _ = np.linalg.qr(w)
    return rng.random(n_v)[:, None] + (u * values) @ v.T


def test_principal_basis_leaves_equal_singular_values_at_the_cut_out_whole():
    """A cut between equal singular values would keep a vector that rounding picks from their shared subspace (a
    square floor under a square grid of lights: it changed with the BLAS threads): the whole run is left out,
    ties within ``EQUAL_SINGULAR`` of the largest value; values further apart are cut where asked."""
    from prtlab.pca._basis import EQUAL_SINGULAR, untied_count

    rng = np.random.default_rng(8)
    training = _with_singular_values(rng, np.array([4.0, 3.0, 2.0, 2.0, 2.0, 1.0]))
    kept = [len(principal_basis(training, n)[0]) - 1 for n in range(1, 8)]
    assert kept == [0, 1, 2, 2, 2, 5, 6]  # the run 2, 2, 2 (components 2-4) kept whole or not at all
    assert untied_count([4.0, 2.0, 2.0 - 0.5 * EQUAL_SINGULAR * 4.0], 2) == 1  # within the tolerance: tied
    assert untied_count([4.0, 2.0, 2.0 - 2.0 * EQUAL_SINGULAR * 4.0], 2) == 2  # beyond it: cut
    assert untied_count([4.0, 2.0], 2) == 2  # nothing left out: no cut


def test_a_square_plane_under_its_grid_of_lights_keeps_no_half_of_a_pair():
    """The paper's floor: a square plane under a square grid of lights has pairs of equal singular values (its
    symmetry). Asked for 15 functions (14 components), the cut would fall inside the pair of components 13 and 14:
    both are left out, 14 functions remain; asked for 16, the cut falls between pairs."""
    from prtlab.pca._basis import EQUAL_SINGULAR

    plane = builtin_mesh("plane", size=(2.0, 2.0), resolution=(12, 12))
    pca = fit_pca_basis(plane, n_basis=15, n_lights=64, plane=True)
    s = pca.singular_values
    assert s[13] - s[14] <= EQUAL_SINGULAR * s[0]  # the pair the cut would split
    assert pca.n_basis == 14 and s[12] - s[13] > EQUAL_SINGULAR * s[0]
    assert fit_pca_basis(plane, n_basis=16, n_lights=64, plane=True).n_basis == 16
