"""Tests of prtlab.pca._compare and _param: the journal paper's basis comparison over a (u, v) domain."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.pca import (
    BasisComparison,
    area_light_intensity,
    compare_bases,
    fit_pca_basis,
    fourier_cosine_indices,
    surface_uv,
    uv_basis,
)
from prtlab.reference import direct
from prtlab.scene import AreaLight, Scene, SceneObject
from tests.conftest import MC_SIGMAS


def _grid(r):
    c = (np.arange(r) + 0.5) / r
    u, v = np.meshgrid(c, c, indexing="ij")
    return np.stack([u.ravel(), v.ravel()], axis=1)


@pytest.fixture(scope="module")
def floor_and_bunny():
    floor = builtin_mesh("plane", size=[3, 3], resolution=[16, 16])
    bunny = builtin_mesh("bunny")
    light = AreaLight(np.array([0.8, 2.0, 0.6]), np.array([0.25, 0, 0]), np.array([0, 0, 0.25]), np.full(3, 10.0))
    scene = Scene(objects=[SceneObject("floor", floor), SceneObject("bunny", bunny)], lights=[light])
    return scene


# --------------------------------------------------------------------------- the bases


@pytest.mark.parametrize("kind", ["haar", "fourier"])
def test_orthonormal_on_unit_square(kind):
    # midpoint rule on a 64 x 64 grid: exact for Haar up to level 5, for cosines of frequency < 64
    x = _grid(64)
    psi = uv_basis(kind, x, 16)
    np.testing.assert_allclose(psi.T @ psi / len(x), np.eye(16), atol=1e-12)


def test_sh_orthonormal_with_sphere_measure():
    """Midpoint rule on 256 x 256 with the measure 2 pi^2 sin(pi v): exact in phi (trigonometric
    polynomials); in theta Euler-Maclaurin leaves ``-h^2/24 [f']_0^pi + O(h^4)``, and ``f' = 2 pi Y_i Y_j``
    at the poles (zonal terms only), so the Gram matrix is the identity plus
    ``h^2/24 2 pi (Y_i Y_j(N) + Y_i Y_j(S))`` (4.4e-5 here) to within h^4 (2.3e-8)."""
    x = _grid(256)
    psi = uv_basis("sh", x, 16)
    w = 2 * np.pi**2 * np.sin(np.pi * x[:, 1]) / len(x)
    h = np.pi / 256
    poles = uv_basis("sh", np.array([[0.3, 0.0], [0.3, 1.0]]), 16)
    lead = h * h / 24 * 2 * np.pi * (np.outer(poles[0], poles[0]) + np.outer(poles[1], poles[1]))
    np.testing.assert_allclose((psi * w[:, None]).T @ psi - np.eye(16), lead, atol=h**4)


def test_haar_terms_are_piecewise_constant_cells(rng):
    # 4 terms span the functions constant on 2 x 2 cells, 16 terms those on 4 x 4 cells
    for cells, n in ((2, 4), (4, 16)):
        img = rng.normal(size=(cells, cells))
        x = _grid(32)
        f = img[(x[:, 0] * cells).astype(int), (x[:, 1] * cells).astype(int)]
        psi = uv_basis("haar", x, n)
        w = psi.T @ f / len(x)
        np.testing.assert_allclose(psi @ w, f, atol=1e-12)


def test_haar_matches_prtlab_wavelet_haar2d(rng):
    """Our Haar terms are prtlab.wavelet.haar2d's coefficients (u = row index, v = column index)."""
    from prtlab.wavelet import haar2d

    r = 4
    x = rng.normal(size=(r, r))  # x[i, j] on the cell u in [i/r, (i+1)/r), v in [j/r, (j+1)/r)
    faces = np.zeros((6, r, r))
    faces[0] = x
    C = haar2d(faces)[0]
    c = uv_basis("haar", _grid(r), 16).T @ x.ravel() / r**2  # L2 coefficients on [0, 1]^2
    expected = np.zeros((r, r))
    expected[0, 0] = c[0]
    expected[1, 0], expected[0, 1], expected[1, 1] = c[1], c[2], c[3]  # psi(u)phi(v), phi(u)psi(v), psi psi
    for p in range(2):
        for q in range(2):
            expected[2 + p, q] = c[4 + 2 * p + q]
            expected[p, 2 + q] = c[8 + 2 * p + q]
            expected[2 + p, 2 + q] = c[12 + 2 * p + q]
    np.testing.assert_allclose(C, r * expected, atol=1e-12)  # haar2d works in texel space: r x L2


def test_fourier_ordering():
    np.testing.assert_array_equal(fourier_cosine_indices(4), [[0, 0], [0, 1], [1, 0], [1, 1]])
    assert {tuple(a) for a in fourier_cosine_indices(16)} == {(a, b) for a in range(4) for b in range(4)}
    assert {tuple(a) for a in fourier_cosine_indices(9)} == {(a, b) for a in range(3) for b in range(3)}


@given(kind=st.sampled_from(["sh", "haar", "fourier"]), n=st.integers(1, 20), seed=st.integers(0, 2**31))
def test_nested_terms(kind, n, seed):
    x = np.random.default_rng(seed).random((7, 2))
    np.testing.assert_allclose(uv_basis(kind, x, n), uv_basis(kind, x, 20)[:, :n])


def test_empty_uv():
    assert uv_basis("fourier", np.zeros((0, 2)), 4).shape == (0, 4)


# --------------------------------------------------------------------------- parameterisation


def test_plane_uv_is_its_own_coordinates():
    plane = builtin_mesh("plane", size=[2, 4], resolution=[4, 4])
    p = surface_uv(plane, plane=True)
    v = np.asarray(plane.vertices)
    np.testing.assert_allclose(p.uv[:, 0], (v[:, 0] + 1) / 2)
    np.testing.assert_allclose(p.uv[:, 1], (v[:, 2] + 2) / 4)
    assert p.n_charts == 1 and np.array_equal(p.vertex, np.arange(len(v)))


def test_xatlas_atlas_round_trip():
    mesh = builtin_mesh("bunny")
    p = surface_uv(mesh)
    assert p.uv.min() >= 0 and p.uv.max() <= 1 and p.n_charts > 1
    assert set(np.unique(p.vertex)) == set(range(len(mesh.vertices)))
    np.testing.assert_array_equal(p.vertex[p.faces], np.asarray(mesh.faces))  # same faces, split at seams
    f = np.random.default_rng(0).normal(size=(2, len(mesh.vertices), 3))
    np.testing.assert_allclose(p.to_vertices(p.to_param(f), colour=True), f)
    np.testing.assert_allclose(p.to_vertices(p.to_param(f[..., 0])), f[..., 0])


# --------------------------------------------------------------------------- the comparison


def test_exact_when_intensity_is_in_every_span():
    plane = builtin_mesh("plane", size=[1, 1], resolution=[8, 8])
    p = surface_uv(plane, plane=True)
    L = np.full(len(plane.vertices), 0.3)  # constant: the first term of each basis (and the PCA mean span)
    pca = fit_pca_basis(plane, n_basis=4, n_lights=16, plane=True)
    c = compare_bases(L, p, pca, terms=(1, 4))
    assert isinstance(c, BasisComparison)
    np.testing.assert_allclose(c.rms[:3], 0.0, atol=1e-12)  # sh, haar, fourier contain constants
    assert c.rms[3, 1] <= c.rms[3, 0] + 1e-15
    assert "fourier" in c.table() and c.relative_rms.shape == (4, 2)


def test_more_terms_never_worse(floor_and_bunny):
    scene = floor_and_bunny
    L = area_light_intensity(RayCaster(scene), scene.lights[0], 0, n=4)
    floor = scene.objects[0].mesh
    c = compare_bases(L, surface_uv(floor, plane=True), fit_pca_basis(floor, n_lights=64, plane=True))
    assert np.all(np.diff(c.rms, axis=1) <= 1e-12)  # nested bases: least squares cannot get worse


def test_area_light_quadrature_against_reference(floor_and_bunny):
    """Midpoint rule vs prtlab.reference.direct, summed over each object's vertices.

    Per vertex, the sample standard error of the reference is unreliable at grazing
    and penumbra vertices (a handful of non-zero light samples), so the test sums
    the independent per-vertex errors: |sum (I_n - mc)| <= MC_SIGMAS sqrt(sum se^2)
    + sum |I_n - I_n/2| (the rule's own error estimate).
    """
    scene = floor_and_bunny
    caster = RayCaster(scene)
    ref = direct(scene, 64, np.random.default_rng(5))
    for index, name in enumerate(("floor", "bunny")):
        fine = area_light_intensity(caster, scene.lights[0], index, n=16, albedo=0.7)
        coarse = area_light_intensity(caster, scene.lights[0], index, n=8, albedo=0.7)
        mc, se = ref.direct[name][:, 0], ref.stderr["direct"][name][:, 0]
        if name == "bunny":  # vertices lying on the floor are ill-defined (docs/DECISIONS.md)
            keep = np.asarray(scene.objects[1].mesh.vertices)[:, 1] > 1e-3
        else:
            keep = np.ones(len(mc), bool)
        diff = np.sum((fine - mc)[keep])
        bound = MC_SIGMAS * np.sqrt(np.sum(se[keep] ** 2)) + np.sum(np.abs(fine - coarse)[keep])
        assert abs(diff) <= bound, (name, diff, bound)
        assert np.max(fine) > 10 * np.max(se)  # the test has power: the signal dwarfs the noise


def test_unshadowed_area_light_closed_form():
    """A vertex straight below a small square light: E ~ L_e A cos cos / r^2 (point-source limit)."""
    plane = builtin_mesh("plane", size=[0.01, 0.01], resolution=[1, 1])
    light = AreaLight(np.array([0.0, 10.0, 0.0]), np.array([0.01, 0, 0]), np.array([0, 0, 0.01]), np.full(3, 2.0))
    got = area_light_intensity([plane], light, 0, n=2)
    np.testing.assert_allclose(got, 1.0 / np.pi * 2.0 * 4e-4 / 100.0, rtol=1e-5)


# --------------------------------------------------------------------------- errors


def test_errors():
    plane = builtin_mesh("plane", size=[1, 1], resolution=[2, 2])
    p = surface_uv(plane, plane=True)
    L = np.zeros(9)
    with pytest.raises(ValueError, match="kind must be one of"):
        uv_basis("rbf", np.zeros((1, 2)), 4)
    with pytest.raises(ValueError, match=r"uv must have shape \(\.\.\., 2\)"):
        uv_basis("sh", np.zeros(3), 4)
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        uv_basis("sh", np.full((1, 2), 2.0), 4)
    with pytest.raises(ValueError, match="uv contains NaN"):
        uv_basis("sh", np.full((1, 2), np.nan), 4)
    with pytest.raises(TypeError, match="n_terms must be an int"):
        uv_basis("sh", np.zeros((1, 2)), 4.0)
    with pytest.raises(ValueError, match="n_terms must be an int >= 1"):
        uv_basis("sh", np.zeros((1, 2)), 0)
    with pytest.raises(TypeError, match="param must be a SurfaceParam"):
        compare_bases(L, None)
    with pytest.raises(ValueError, match=r"intensity must have shape \(9,\)"):
        compare_bases(np.zeros(8), p)
    with pytest.raises(ValueError, match="intensity contains NaN"):
        compare_bases(np.full(9, np.nan), p)
    with pytest.raises(ValueError, match="bases must be drawn from"):
        compare_bases(L, p, bases=("rbf",))
    with pytest.raises(ValueError, match="pca is required"):
        compare_bases(L, p)
    pca = fit_pca_basis(plane, n_basis=4, n_lights=8, plane=True)
    with pytest.raises(ValueError, match="fewer than the 8 that max"):
        compare_bases(L, p, pca, terms=(8,))
    with pytest.raises(ValueError, match="fit it on the same mesh"):
        compare_bases(np.zeros(4), surface_uv(builtin_mesh("plane"), plane=True), pca, terms=(1,))
    with pytest.raises(ValueError, match="scored must be a boolean mask"):
        compare_bases(L, p, bases=("sh",), terms=(1,), scored=np.ones(3, bool))
    with pytest.raises(TypeError, match="mesh must be a trimesh"):
        surface_uv(3)
    with pytest.raises(ValueError, match="resolution must be an int"):
        surface_uv(plane, resolution=4)
    with pytest.raises(ValueError, match=r"values must have shape \(\.\.\., 9"):
        p.to_param(np.zeros(5))
    light = AreaLight(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, 1.0]), np.ones(3))
    with pytest.raises(ValueError, match="n must be an int >= 1"):
        area_light_intensity([plane], light, 0, n=0)
    with pytest.raises(ValueError, match=r"receiver must be in \[0, 1\)"):
        area_light_intensity([plane], light, 1)


# --------------------------------------------------------------------------- the paper's qualitative result


def _ranking(scene, n_light_grid, n_lights):
    caster = RayCaster(scene)
    for index, name in enumerate(("floor", "bunny")):
        mesh = scene.objects[index].mesh
        plane = name == "floor"
        L = area_light_intensity(caster, scene.lights[0], index, n=n_light_grid)
        c = compare_bases(L, surface_uv(mesh, plane=plane), fit_pca_basis(mesh, n_lights=n_lights, plane=plane))
        order = np.argsort(c.rms, axis=0)  # per term count, best first
        if plane:
            for k in range(len(c.terms)):
                assert {c.bases[i] for i in order[:2, k]} == {"fourier", "pca"}, c.table()
        else:
            assert np.all(np.array(c.bases)[order[0]] == "pca"), c.table()


def test_paper_ranking_reproduced(floor_and_bunny):
    """Journal paper Fig. 8: PCA lowest on the bunny; Fourier cosine and PCA the two lowest on the floor."""
    _ranking(floor_and_bunny, 8, 64)


@pytest.mark.slow
def test_paper_ranking_reproduced_full_size():
    """As above at the paper's sizes: a 64 x 64 floor (4225 vertices), the subdivided bunny, 256 lights."""
    floor = builtin_mesh("plane", size=[3, 3], resolution=[64, 64])
    bunny = builtin_mesh("bunny", subdivisions=1)
    light = AreaLight(np.array([0.9, 2.2, 0.7]), np.array([0.25, 0, 0]), np.array([0, 0, 0.25]), np.full(3, 12.0))
    _ranking(Scene(objects=[SceneObject("floor", floor), SceneObject("bunny", bunny)], lights=[light]), 16, 256)


def test_pca_terms_stop_before_equal_singular_values():
    """A square plane under a square grid of lights has its PCA components 13 and 14 equal: 15 terms would keep one
    of the pair, chosen by rounding, so they take the 14 functions before it (the count in ``functions`` and the
    table); 16 terms take 16."""
    plane = builtin_mesh("plane", size=(2.0, 2.0), resolution=(12, 12))
    pca = fit_pca_basis(plane, n_basis=16, n_lights=64, plane=True)
    L = np.linspace(0.2, 1.0, len(plane.vertices))
    c = compare_bases(L, surface_uv(plane, plane=True), pca, terms=(14, 15, 16), bases=("pca", "fourier"))
    assert [c.functions[("pca", n)] for n in (14, 15, 16)] == [14, 14, 16]
    assert [c.functions[("fourier", n)] for n in (14, 15, 16)] == [14, 15, 16]
    np.testing.assert_array_equal(c.approximations[("pca", 15)], c.approximations[("pca", 14)])
    assert "(14)" in c.table().splitlines()[1] and "(" not in c.table().splitlines()[2]

