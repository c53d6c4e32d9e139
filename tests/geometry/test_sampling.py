"""Tests of prtlab.geometry._sampling: point sets, and chi-square tests of the samplers."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chisquare

from prtlab.geometry import (
    cosine_hemisphere,
    cosine_hemisphere_pdf,
    fibonacci_sphere,
    geodesic_directions,
    geodesic_sphere,
    sample_mesh_area,
    sample_parallelogram,
    stratified_hemisphere,
    stratified_sphere,
    tangent_frame,
    uniform_hemisphere,
    uniform_sphere,
)
from tests.conftest import random_directions, random_rotation

CHI2_SIGNIFICANCE = 1e-3  # as Mitsuba's ChiSquareTest
CHI2_SAMPLES = 100_000


def chi2_directions(dirs, pdf_fn, axis=np.array([0.0, 0.0, 1.0]), res=(20, 40), sub=8):
    """Mitsuba-style chi-square test of directions against a pdf.

    Bins are a (cos theta, phi) grid about ``axis`` (equal solid angle); the
    expected count of a bin is ``n`` times the pdf integrated over it by a
    ``sub x sub`` midpoint rule in (cos theta, phi); bins expecting fewer than 5
    samples are pooled. Returns the p-value.
    """
    t, b = tangent_frame(axis)
    local = np.stack([dirs @ t, dirs @ b, dirs @ axis], axis=-1)
    nz, nphi = res
    z = np.clip(local[:, 2], -1, 1 - 1e-15)
    phi = np.mod(np.arctan2(local[:, 1], local[:, 0]), 2 * np.pi)
    iz = np.minimum(((z + 1) / 2 * nz).astype(int), nz - 1)
    ip = np.minimum((phi / (2 * np.pi) * nphi).astype(int), nphi - 1)
    observed = np.bincount(iz * nphi + ip, minlength=nz * nphi).astype(float)
    # integrate the pdf per bin
    zz = -1 + (np.arange(nz * sub) + 0.5) * 2 / (nz * sub)
    pp = (np.arange(nphi * sub) + 0.5) * 2 * np.pi / (nphi * sub)
    Z, P = np.meshgrid(zz, pp, indexing="ij")
    r = np.sqrt(1 - Z * Z)
    w_local = np.stack([r * np.cos(P), r * np.sin(P), Z], axis=-1)
    w = w_local[..., 0:1] * t + w_local[..., 1:2] * b + w_local[..., 2:3] * axis
    dA = (2 / (nz * sub)) * (2 * np.pi / (nphi * sub))
    dens = pdf_fn(w) * dA
    integral = dens.reshape(nz, sub, nphi, sub).sum(axis=(1, 3)).reshape(-1)
    assert integral.sum() == pytest.approx(1.0, abs=1e-3)  # the pdf integrates to 1
    expected = integral * len(dirs)
    return _pooled_pvalue(observed, expected)


def _pooled_pvalue(observed, expected):
    small = expected < 5
    assert observed[expected == 0].sum() == 0, "samples where the pdf is zero"
    obs = np.append(observed[~small], observed[small].sum())
    exp = np.append(expected[~small], expected[small].sum())
    if exp[-1] == 0:
        obs, exp = obs[:-1], exp[:-1]
    exp *= obs.sum() / exp.sum()
    return chisquare(obs, exp).pvalue


# ------------------------------------------------------------- deterministic sets


def test_fibonacci_unit_and_balanced():
    d = fibonacci_sphere(1000)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.abs(d.mean(axis=0)).max() < 2e-3
    assert fibonacci_sphere(0).shape == (0, 3)


@pytest.mark.parametrize("frequency, n", [(1, 12), (2, 42), (3, 92), (4, 162)])
def test_geodesic_counts_and_orientation(frequency, n):
    v, f = geodesic_sphere(frequency)
    assert v.shape == (n, 3) and f.shape == (20 * frequency**2, 3)
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # outward faces
    assert len(np.unique(f)) == n
    np.testing.assert_array_equal(geodesic_directions(n), v)


def test_geodesic_92_structure():
    v = geodesic_directions(92)
    ico = geodesic_directions(12)
    np.testing.assert_allclose(v[:12], ico, atol=1e-12)  # icosahedron vertices first
    # the 3-frequency class I (flat subdivision, projected) chords of a unit sphere are A = 0.34862
    # (at the 12 five-fold vertices), B = 0.40355, C = 0.41241 (Kenner, Geodesic Math and How to Use
    # It, 1976, 3v icosahedron table, 5 digits); a vertex's nearest neighbour is at chord A or C
    v3, f3 = geodesic_sphere(3)
    edges = np.concatenate([f3[:, [0, 1]], f3[:, [1, 2]], f3[:, [2, 0]]])
    chords = np.linalg.norm(v3[edges[:, 0]] - v3[edges[:, 1]], axis=1)
    kenner = np.array([0.34862, 0.40355, 0.41241])
    np.testing.assert_allclose(kenner[np.argmin(np.abs(chords[:, None] - kenner), axis=1)], chords, atol=5e-6)
    assert set(np.unique(np.argmin(np.abs(chords[:, None] - kenner), axis=1))) == {0, 1, 2}
    dots = v @ v.T
    np.fill_diagonal(dots, -1)
    nn = 2 * np.sin(np.arccos(dots.max(axis=1)) / 2)  # nearest-neighbour chords
    # every vertex and edge point has an A neighbour; the 20 face centres are ringed by C chords
    np.testing.assert_allclose(np.sort(nn), kenner[[0] * 72 + [2] * 20], atol=5e-6)


def test_geodesic_frequency_two_matches_icosphere_once_subdivided():
    ours = geodesic_directions(42)
    theirs = trimesh.creation.icosphere(subdivisions=1).vertices
    assert len(ours) == len(theirs)
    np.testing.assert_allclose((ours @ theirs.T).max(axis=1), 1.0, atol=1e-12)  # the same point set


# ------------------------------------------------------------------ chi-square


def test_uniform_sphere_chi2(rng):
    d, pdf = uniform_sphere(CHI2_SAMPLES, rng)
    np.testing.assert_allclose(pdf, 1 / (4 * np.pi))
    assert chi2_directions(d, lambda w: np.full(w.shape[:-1], 1 / (4 * np.pi))) > CHI2_SIGNIFICANCE


def test_cosine_hemisphere_chi2_rotated(rng):
    n = random_directions(rng, 1)[0]
    d, pdf = cosine_hemisphere(CHI2_SAMPLES, rng, normal=n)
    np.testing.assert_allclose(pdf, cosine_hemisphere_pdf(d, n), atol=1e-12)
    assert chi2_directions(d, lambda w: cosine_hemisphere_pdf(w, n), axis=random_directions(rng, 1)[0]) > (
        CHI2_SIGNIFICANCE
    )


def test_uniform_and_stratified_hemisphere_chi2(rng):
    n = np.array([0.0, 1.0, 0.0])
    hemi = lambda w: (w @ n > 0) / (2 * np.pi)  # noqa: E731
    d, _ = uniform_hemisphere(CHI2_SAMPLES, rng, normal=n)
    assert chi2_directions(d, hemi, axis=n) > CHI2_SIGNIFICANCE
    # stratified sets are too even for a chi-square test of independence: pool many
    # independent stratified sets of a small size instead
    d = stratified_hemisphere(16, rng, normal=np.tile(n, (CHI2_SAMPLES // 16, 1)))[0].reshape(-1, 3)
    assert chi2_directions(d, hemi, axis=n) > CHI2_SIGNIFICANCE
    d = stratified_hemisphere(16, rng, normal=np.tile(n, (CHI2_SAMPLES // 16, 1)), cosine=True)[0].reshape(-1, 3)
    assert chi2_directions(d, lambda w: cosine_hemisphere_pdf(w, n), axis=n) > CHI2_SIGNIFICANCE


def test_stratified_sphere_one_per_cell(rng):
    d, pdf = stratified_sphere(32, rng)  # 4 x 8 cells in (z, phi)
    z_cell = np.floor((1 - d[:, 2]) / 2 * 4).astype(int)
    phi_cell = np.floor(np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi) / (2 * np.pi) * 8).astype(int)
    assert len(set(zip(z_cell, phi_cell))) == 32
    d = np.concatenate([stratified_sphere(7, rng)[0] for _ in range(4000)])  # prime n: bands in z
    assert chi2_directions(d, lambda w: np.full(w.shape[:-1], 1 / (4 * np.pi))) > CHI2_SIGNIFICANCE


def test_mesh_area_chi2_per_face(rng):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    mesh.vertices *= [1.0, 2.0, 0.5]  # unequal face areas
    s = sample_mesh_area(mesh, CHI2_SAMPLES, rng)
    observed = np.bincount(s.face_ids, minlength=len(mesh.faces)).astype(float)
    expected = mesh.area_faces / mesh.area * CHI2_SAMPLES
    assert chisquare(observed, expected).pvalue > CHI2_SIGNIFICANCE
    np.testing.assert_allclose(s.pdf, 1 / mesh.area)
    # points on their faces, normals are the face normals, barycentrics uniform within a face
    a, b, c = (mesh.vertices[mesh.faces[s.face_ids, k]] for k in range(3))
    u, v = s.barycentrics[:, :1], s.barycentrics[:, 1:]
    np.testing.assert_allclose(s.points, (1 - u - v) * a + u * b + v * c, atol=1e-12)
    np.testing.assert_allclose(s.normals, mesh.face_normals[s.face_ids], atol=1e-12)
    grid = 10  # uniform on the triangle: the map (u, v) -> cell of a fine triangular grid
    iu, iv = (s.barycentrics * grid).astype(int).T
    lower = (s.barycentrics * grid).sum(axis=1) - iu - iv < 1
    cell = (iu * grid + iv) * 2 + (~lower)
    obs = np.bincount(cell, minlength=2 * grid * grid).astype(float)
    valid = np.zeros(2 * grid * grid, bool)
    for i in range(grid):
        for j in range(grid - i):
            valid[(i * grid + j) * 2] = True
            if i + j < grid - 1:
                valid[(i * grid + j) * 2 + 1] = True
    assert obs[~valid].sum() == 0
    assert chisquare(obs[valid]).pvalue > CHI2_SIGNIFICANCE


def test_parallelogram_chi2(rng):
    center, u, v = np.array([0.0, 3.0, 0.0]), np.array([0.5, 0.0, 0.2]), np.array([0.0, 0.1, 0.7])
    p, pdf = sample_parallelogram(center, u, v, CHI2_SAMPLES, rng)
    np.testing.assert_allclose(pdf, 1 / (4 * np.linalg.norm(np.cross(u, v))))
    st = np.linalg.lstsq(np.stack([u, v], axis=1), (p - center).T, rcond=None)[0].T
    assert np.all(np.abs(st) <= 1 + 1e-12)
    cells = np.minimum(((st + 1) / 2 * 10).astype(int), 9)
    obs = np.bincount(cells[:, 0] * 10 + cells[:, 1], minlength=100).astype(float)
    assert chisquare(obs).pvalue > CHI2_SIGNIFICANCE


# ------------------------------------------------------------- frames and shapes


def test_tangent_frame_orthonormal(rng):
    n = np.concatenate([random_directions(rng, 100), [[0, 0, 1], [0, 0, -1], [1, 0, 0]]])
    t, b = tangent_frame(n)
    frame = np.stack([t, b, n], axis=-1)
    np.testing.assert_allclose(frame.transpose(0, 2, 1) @ frame, np.broadcast_to(np.eye(3), (103, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(frame), 1.0, atol=1e-12)


@given(seed=st.integers(0, 2**31 - 1), pole=st.sampled_from([None, 1.0, -1.0]))
def test_hemisphere_samplers_stay_on_their_side(seed, pole):
    rng = np.random.default_rng(seed)
    n = random_directions(rng, 8)
    if pole is not None:
        n[0] = [0.0, 0.0, pole]  # the frame's singular direction
        n[1] = [0.0, 0.0, pole * (1 - 1e-12)] / np.linalg.norm([0.0, 0.0, pole * (1 - 1e-12)])
    for sampler in (cosine_hemisphere, uniform_hemisphere, stratified_hemisphere):
        d, pdf = sampler(16, rng, normal=n)
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
        assert np.all(np.sum(d * n[:, None, :], axis=-1) >= -1e-12)
        assert np.all(pdf > 0) or sampler is cosine_hemisphere


def test_batched_normals_shapes(rng):
    normals = np.stack([random_rotation(rng)[:, 2] for _ in range(6)]).reshape(2, 3, 3)
    d, pdf = cosine_hemisphere(5, rng, normal=normals)
    assert d.shape == (2, 3, 5, 3) and pdf.shape == (2, 3, 5)
    assert np.all(np.sum(d * normals[..., None, :], axis=-1) >= 0)
    assert cosine_hemisphere(0, rng)[0].shape == (0, 3)
    assert stratified_hemisphere(0, rng, normal=normals)[0].shape == (2, 3, 0, 3)
    assert uniform_sphere(0, rng)[0].shape == (0, 3)
    assert sample_mesh_area(trimesh.creation.box(), 0, rng).points.shape == (0, 3)


def test_errors(rng):
    with pytest.raises(TypeError, match=r"n must be an int >= 0 \(sample count\)"):
        uniform_sphere(2.5, rng)
    with pytest.raises(ValueError, match="n must be an int >= 0"):
        fibonacci_sphere(-1)
    with pytest.raises(TypeError, match="rng must be a numpy.random.Generator"):
        cosine_hemisphere(4, 0)
    with pytest.raises(ValueError, match=r"normal must be a \(\.\.\., 3\) array"):
        cosine_hemisphere(4, rng, normal=[1.0, 0.0])
    with pytest.raises(ValueError, match="normal contains NaN"):
        cosine_hemisphere(4, rng, normal=[np.nan, 0.0, 1.0])
    with pytest.raises(ValueError, match="normal contains zero vectors"):
        uniform_hemisphere(4, rng, normal=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"dirs must be a \(\.\.\., 3\)"):
        cosine_hemisphere_pdf([1.0, 0.0])
    with pytest.raises(ValueError, match="a geodesic sphere has 10"):
        geodesic_directions(90)
    with pytest.raises(ValueError, match="frequency must be an int >= 1"):
        geodesic_sphere(0)
    with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh"):
        sample_mesh_area("box", 3, rng)
    with pytest.raises(ValueError, match=r"mesh needs \(V, 3\) vertices"):
        sample_mesh_area((np.zeros((3, 2)), np.zeros((1, 3), dtype=int)), 3, rng)
    with pytest.raises(ValueError, match="mesh has no area"):
        sample_mesh_area((np.zeros((3, 3)), np.array([[0, 1, 2]])), 3, rng)
    with pytest.raises(ValueError, match=r"u must be a finite \(3,\) vector"):
        sample_parallelogram(np.zeros(3), [1.0, 0.0], [0.0, 1.0, 0.0], 3, rng)
    with pytest.raises(ValueError, match="u and v span no area"):
        sample_parallelogram(np.zeros(3), [1.0, 0, 0], [2.0, 0, 0], 3, rng)
