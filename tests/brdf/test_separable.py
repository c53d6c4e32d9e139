"""Tests of prtlab.brdf._separable: the separable approximation and the error table."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.brdf import lambert, phong, relative_error_table, separable
from prtlab.brdf._kernels import factor_eval_kernel, factor_eval_numpy
from prtlab.brdf._separable import _dense_svd_spectrum, _lobe_to_world, _reflection_to_lobe
from tests.conftest import FLOAT_TOLERANCE, random_directions

TOL = FLOAT_TOLERANCE[np.float64]
SMALL = (8, 11)  # odd azimuth count: no Nyquist frequency, the grid SVD is complete


def _upper(rng, n):
    d = random_directions(rng, n)
    d[:, 2] = np.abs(d[:, 2])
    return d


def _grid_dirs(theta, n_phi):
    phi = 2.0 * np.pi * np.arange(n_phi) / n_phi
    st_, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(np.broadcast_arrays(st_ * np.cos(phi), st_ * np.sin(phi), ct), axis=-1).reshape(-1, 3)


def _pair_boundaries(sep_full):
    """Term counts K that do not split a cos/sin pair (distinct consecutive singular values)."""
    s = sep_full.singular_values
    return [k for k in range(1, len(s)) if s[k - 1] - s[k] > 1e-9 * s[0]]


# --------------------------------------------------------------------------- known answers


@pytest.mark.parametrize("parameterisation", ["plain", "reflection"])
def test_lambert_is_one_exact_term(rng, parameterisation):
    """Lambert's one term is ``g = 1/pi``, ``h = 1`` exactly (not the SVD's values, about 1e-13 off), and its
    factors at any direction are those values exactly (the interpolation between equal nodes returns them)."""
    b = lambert([0.5, 0.2, 0.9])
    sep = separable(b, 1, parameterisation=parameterisation)
    assert np.all(sep.g_radial == 1.0 / np.pi) and np.all(sep.h_radial == 1.0)
    for method in ("numba", "reference"):
        assert np.all(sep.g(random_directions(rng, 50), method=method) == 1.0 / np.pi)
        assert np.all(sep.h(random_directions(rng, 50), method=method) == 1.0)
    np.testing.assert_allclose(sep.colour, [[0.5, 0.2, 0.9]], rtol=TOL)
    assert sep.freq.tolist() == [0] and sep.isotropic
    assert np.all(sep.relative_error() < 1e-12)
    assert np.all(sep.relative_error("quadrature", n_nodes=12) < 1e-12)
    wi, wo, n = random_directions(rng, 20), random_directions(rng, 20), random_directions(rng, 20)
    np.testing.assert_allclose(sep.eval(wi, wo, n), b.eval(wi, wo, n), atol=TOL)


def test_reflection_parameterisation_separates_the_lobe_exactly():
    # Kautz-McCool: about the mirror direction, the Phong lobe depends on v alone (rank 1)
    sep = separable(phong(0.0, 1.0, 20.0), 1, resolution=SMALL, parameterisation="reflection")
    assert sep.relative_error()[0] < 1e-12
    both = separable(phong(0.4, 0.6, 20.0), 2, resolution=SMALL, parameterisation="reflection")
    assert both.relative_error()[0] < 1e-12
    plain = separable(phong(0.0, 1.0, 20.0), 1, resolution=SMALL)
    assert plain.relative_error()[0] > 0.9


def test_reflection_frame(rng):
    wi = _upper(rng, 50)
    v = random_directions(rng, 50)
    np.testing.assert_allclose(_reflection_to_lobe(wi, _lobe_to_world(wi, v)), v, atol=TOL)
    r = wi * [-1.0, -1.0, 1.0]
    np.testing.assert_allclose(_reflection_to_lobe(wi, r), np.broadcast_to([0, 0, 1.0], r.shape), atol=TOL)


# --------------------------------------------------------------------------- outside reference: dense SVD


@pytest.mark.parametrize("parameterisation", ["plain", "reflection"])
@pytest.mark.parametrize("kd,ks,e", [(0.0, 1.0, 10.0), (0.3, 0.6, 4.0), (1.0, 0.0, 0.0)])
def test_spectrum_matches_dense_svd(parameterisation, kd, ks, e):
    b = phong(kd, ks, e)
    sep = separable(b, 1, resolution=SMALL, parameterisation=parameterisation)
    dense, *_ = _dense_svd_spectrum(b, SMALL, parameterisation)
    n = len(sep.singular_values)
    np.testing.assert_allclose(sep.singular_values, dense[:n], rtol=0, atol=1e-12 * dense[0])
    assert np.all(dense[n:] < 1e-12 * dense[0])


@pytest.mark.parametrize("e", [3.0, 16.0])
def test_grid_error_and_reconstruction_match_dense_truncation(e):
    b = phong(0.0, 1.0, e)
    s, table, di, do, wri, wro = _dense_svd_spectrum(b, SMALL)
    u, s_, vt = np.linalg.svd(table)
    full = separable(b, len(s) - 1, resolution=SMALL)
    for K in _pair_boundaries(full)[:6]:
        sep = separable(b, K, resolution=SMALL)
        assert sep.isotropic
        expected_err = np.sqrt(np.sum(s[K:] ** 2) / np.sum(s**2))
        np.testing.assert_allclose(sep.relative_error()[0], expected_err, rtol=1e-10)
        approx = (u[:, :K] * s_[:K]) @ vt[:K] / np.sqrt(wri)[:, None] / np.sqrt(wro)[None, :]
        got = sep.eval(np.repeat(di, len(do), axis=0), np.tile(do, (len(di), 1)))[:, 0].reshape(approx.shape)
        np.testing.assert_allclose(got, approx, atol=1e-10 * np.abs(approx).max())


@pytest.mark.parametrize("kd,ks", [([0.3, 0.1, 0.0], [0.6, 0.2, 0.0]), ([0.3, 0.1, 0.5], [0.2, 0.8, 0.1])])
def test_exact_at_full_rank_on_the_grid(kd, ks):
    b = phong(kd, ks, 12.0)
    probe = separable(b, 1, resolution=SMALL)
    # one colour per term when kd and ks have the same chromaticity; otherwise one more term for the second colour
    same_colour = np.allclose(np.array(kd) * np.mean(ks), np.array(ks) * np.mean(kd))
    K = len(probe.singular_values) + (0 if same_colour else 1)
    sep = separable(b, K, resolution=SMALL)
    assert np.all(sep.relative_error() < 1e-10)
    d = _grid_dirs(sep.theta_in, SMALL[1])
    wi, wo = np.repeat(d, len(d), axis=0), np.tile(d, (len(d), 1))
    np.testing.assert_allclose(sep.eval(wi, wo), b.eval(wi, wo), atol=1e-10)


# --------------------------------------------------------------------------- identities


@pytest.mark.parametrize("e", [10.0, 64.0])
def test_error_decreases_with_K(e):
    errs = [separable(phong(0.2, 0.7, e), K, resolution=(24, 48)).relative_error()[0] for K in range(1, 10)]
    assert np.all(np.diff(errs) <= 1e-12) and errs[-1] < errs[0]


def test_colour_paths():
    grey = separable(phong([0.2, 0.1, 0.0], [0.4, 0.2, 0.0], 8.0), 3, resolution=SMALL)
    np.testing.assert_allclose(grey.colour, np.tile([0.6, 0.3, 0.0], (3, 1)))
    err = grey.relative_error()
    assert err[0] == pytest.approx(err[1], rel=1e-12) and err[2] == 0.0
    split = separable(phong([0.2, 0.1, 0.3], [0.6, 0.2, 0.1], 8.0), 3, resolution=SMALL)
    np.testing.assert_allclose(split.colour, [[0.2, 0.1, 0.3], [0.6, 0.2, 0.1], [0.6, 0.2, 0.1]])
    np.testing.assert_allclose(split.g_radial[0], 1.0 / np.pi)
    black = separable(lambert(0.0), 1, resolution=SMALL)
    assert black.relative_error()[0] == 0.0 and black.colour[0, 0] == 0.0


def test_isotropic_approximation_is_invariant_about_the_normal(rng):
    b = phong(0.1, 0.8, 10.0)
    full = separable(b, 60, resolution=(16, 32))
    K = _pair_boundaries(full)[3]
    sep = separable(b, K, resolution=(16, 32))
    assert sep.isotropic
    wi, wo = _upper(rng, 30), _upper(rng, 30)
    a = 0.7
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    np.testing.assert_allclose(sep.eval(wi @ Rz.T, wo @ Rz.T), sep.eval(wi, wo), atol=1e-10)
    split = separable(b, K + 1, resolution=(16, 32))
    assert not split.isotropic


@given(seed=st.integers(0, 2**32 - 1))
def test_factor_kernel_matches_numpy(seed):
    rng = np.random.default_rng(seed)
    nodes = np.sort(np.concatenate([[0.0, np.pi / 2], rng.uniform(0, np.pi / 2, 6)]))
    values = rng.normal(size=(3, nodes.size))
    freq = np.array([0, 2, 5], dtype=np.int64)
    parity = np.array([0, 1, 0], dtype=np.int64)
    dirs = random_directions(rng, 40)
    dirs[0] = [0, 0, 1.0]
    out = np.empty((40, 3))
    factor_eval_kernel(nodes, values, freq, parity, dirs, out)
    np.testing.assert_allclose(out, factor_eval_numpy(nodes, values, freq, parity, dirs), rtol=1e-12, atol=1e-13)


def test_g_h_tiers_and_shapes(rng):
    sep = separable(phong(0.2, 0.7, 10.0), 5, resolution=SMALL)
    d = random_directions(rng, 24).reshape(2, 3, 4, 3)
    assert sep.g(d).shape == (2, 3, 4, 5) and sep.h(d).shape == (2, 3, 4, 5)
    np.testing.assert_allclose(sep.g(d), sep.g(d, method="reference"), atol=1e-13)
    np.testing.assert_allclose(sep.h(d), sep.h(d, method="reference"), atol=1e-13)
    assert sep.g(np.zeros((0, 3))).shape == (0, 5)
    assert sep.eval(np.ones((0, 3)), [0, 0, 1]).shape == (0, 1)
    # two-sided like the BRDF
    wi, wo = _upper(rng, 10), _upper(rng, 10)
    np.testing.assert_array_equal(sep.eval(-wi, wo), np.zeros((10, 1)))


def test_quadrature_error_converges_to_grid_error():
    b = phong(0.0, 1.0, 10.0)
    gaps = []
    for res in ((8, 16), (16, 32)):
        sep = separable(b, 6, resolution=res)
        gaps.append(abs(sep.relative_error("quadrature")[0] - sep.relative_error()[0]))
    assert gaps[1] < gaps[0]


# --------------------------------------------------------------------------- the paper's table


def test_relative_error_table():
    table = relative_error_table(exponents=(10, 16, 64), K=(1, 2, 4), resolution=(24, 48))
    assert table.error.shape == (3, 3)
    sep = separable(phong(0.0, 1.0, 16.0), 4, resolution=(24, 48))
    assert table.error[1, 2] == pytest.approx(sep.relative_error()[0], rel=1e-12)
    assert np.all(np.diff(table.error, axis=1) < 0)  # more terms, smaller error
    assert np.all(np.diff(table.error, axis=0) > 0)  # sharper lobes, larger error (the journal's Fig. 10)
    assert "K=4" in str(table)


# --------------------------------------------------------------------------- errors


def test_errors():
    b = phong(0.2, 0.7, 10.0)
    with pytest.raises(ValueError, match="K must be an int >= 1"):
        separable(b, 0, resolution=SMALL)
    with pytest.raises(ValueError, match="rank of the grid table"):
        separable(b, 10_000, resolution=SMALL)
    with pytest.raises(TypeError, match="K must be an int"):
        separable(b, 2.0)
    with pytest.raises(TypeError, match="K must be an int"):
        separable(b, True)
    with pytest.raises(TypeError, match="brdf must be a prtlab.brdf Lambert or Phong"):
        separable("phong", 2)
    with pytest.raises(ValueError, match="resolution must be n_theta or"):
        separable(b, 2, resolution=(1, 8))
    with pytest.raises(ValueError, match="resolution must be n_theta or"):
        separable(b, 2, resolution="fine")
    with pytest.raises(ValueError, match="parameterisation must be 'plain' or 'reflection'"):
        separable(b, 2, resolution=SMALL, parameterisation="half")
    sep = separable(b, 2, resolution=SMALL)
    with pytest.raises(ValueError, match="method must be 'grid' or 'quadrature'"):
        sep.relative_error("mc")
    with pytest.raises(ValueError, match="n_nodes must be an int >= 2"):
        sep.relative_error("quadrature", n_nodes=0)
    with pytest.raises(ValueError, match=r"wi_local must be a \(\.\.\., 3\)"):
        sep.g(np.ones(4))
    with pytest.raises(ValueError, match="method must be one of"):
        sep.h([0, 0, 1], method="gpu")
    with pytest.raises(ValueError, match="exponents and K must be non-empty"):
        relative_error_table(exponents=())
    with pytest.raises(ValueError, match="kd and ks must be scalars"):
        relative_error_table(exponents=(4,), K=(1,), kd=[0.1, 0.2], ks=0.5, resolution=SMALL)
    with pytest.raises(ValueError, match="parameterisation must be"):
        relative_error_table(parameterisation="x")


def test_relative_error_table_of_transfer_error():
    from prtlab.brdf import transfer_error

    table = relative_error_table(exponents=(10,), K=(2, 4), resolution=(12, 24), order=3)
    for j, k in enumerate((2, 4)):
        sep = separable(phong(0.0, 1.0, 10.0), k, resolution=(12, 24))
        assert table.error[0, j] == pytest.approx(transfer_error(sep, 3)[0], rel=1e-12)


@pytest.mark.slow
def test_default_table_is_converged_in_resolution():
    coarse = relative_error_table(resolution=(48, 96))
    fine = relative_error_table()  # (64, 128)
    np.testing.assert_allclose(fine.error, coarse.error, atol=1e-3)
    assert np.all(np.diff(fine.error, axis=0) > 0) and np.all(np.diff(fine.error, axis=1) < 0)
