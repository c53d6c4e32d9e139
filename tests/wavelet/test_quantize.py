"""Tests of prtlab/wavelet/_quantize.py: 8-bit quantisation with per-vertex scale, the pulse/Haar
choice of Yue et al. 2009, and the sparse per-vertex dot product (numba) against dense references."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from prtlab.wavelet import (
    Quantized8,
    SparseTransfer,
    dequantize8,
    encode_transfer,
    haar2d,
    ihaar2d,
    quantize8,
    solid_angle_weight,
)

METHODS = ["numba", "reference"]


def portal_transfer(rng, n_vertices, r, max_cells):
    """Transfer cubemaps that see a portal through a rectangle of cells (the rest occluded)."""
    t = np.zeros((n_vertices, 6, r, r))
    for v in range(n_vertices):
        size = rng.integers(1, max_cells + 1, size=2)
        face = rng.integers(6)
        i0, j0 = rng.integers(0, r - size + 1)
        t[v, face, i0 : i0 + size[0], j0 : j0 + size[1]] = 0.5 + 0.01 * rng.random(tuple(size))
    return t


# --------------------------------------------------------------------------- quantize8


@given(st.integers(0, 2**32 - 1), st.sampled_from([0, 1, 2, 3]), st.booleans())
def test_quantisation_error_bound(seed, group_ndim, signed):
    rng = np.random.default_rng(seed)
    values = rng.random((4, 6, 4, 4)) * 10.0 ** rng.uniform(-30, 30)
    if signed:
        values -= values.mean()
    q = quantize8(values, group_ndim=group_ndim)
    assert q.codes.dtype == np.uint8 and q.scale.dtype == np.float32 and q.negative.dtype == bool
    assert q.scale.shape == values.shape[: values.ndim - group_ndim]
    axes = tuple(range(values.ndim - group_ndim, values.ndim))
    peak = np.abs(values).max(axis=axes) if axes else np.abs(values)
    scale = q.scale.astype(np.float64)
    # the scale is the least float32 >= the group maximum
    assert np.all(scale >= peak)
    assert np.all(np.nextafter(q.scale, np.float32(0)).astype(np.float64) < peak)
    s = scale.reshape(scale.shape + (1,) * group_ndim)
    err = np.abs(dequantize8(q) - values)
    assert np.all(err <= s / 510.0 * (1 + 1e-12))
    assert np.all(q.codes.max(axis=axes) == 255) if axes else np.all(q.codes[values != 0] == 255)


def test_rounding_is_half_up():
    # scale 255 makes |v| * 255 / scale = |v| exact: 0.5 -> 1, 1.5 -> 2, 2.5 -> 3, 0.49 -> 0
    values = np.array([255.0, 0.5, 1.5, 2.5, 0.49, -3.5])
    q = quantize8(values, group_ndim=1)
    assert q.scale == 255.0
    assert q.codes.tolist() == [255, 1, 2, 3, 0, 4]
    assert q.negative.tolist() == [False, False, False, False, False, True]
    np.testing.assert_allclose(dequantize8(q), [255.0, 1.0, 2.0, 3.0, 0.0, -4.0])


def test_zero_groups_and_empty_input():
    q = quantize8(np.zeros((3, 6, 2, 2)))
    assert np.all(q.scale == 0) and np.all(q.codes == 0)
    assert np.all(dequantize8(q) == 0)
    q = quantize8(np.zeros((0, 6, 2, 2)))
    assert q.codes.shape == (0, 6, 2, 2) and q.scale.shape == (0,)
    assert dequantize8(q).shape == (0, 6, 2, 2)


def test_quantize_errors():
    with pytest.raises(ValueError, match="NaN or inf"):
        quantize8(np.array([1.0, np.nan]), group_ndim=1)
    with pytest.raises(ValueError, match="group_ndim must be between"):
        quantize8(np.zeros((6, 2, 2)), group_ndim=4)
    with pytest.raises(TypeError, match="group_ndim must be an int"):
        quantize8(np.zeros((6, 2, 2)), group_ndim=1.0)
    with pytest.raises(ValueError, match="float32 range"):
        quantize8(np.array([1e300]), group_ndim=1)
    with pytest.raises(TypeError, match="real array"):
        quantize8(np.array(["a"]), group_ndim=1)
    with pytest.raises(TypeError, match="codes must be uint8"):
        dequantize8(Quantized8(np.zeros(3), np.float32(1), np.zeros(3, bool)))
    with pytest.raises(ValueError, match="scale must have the leading shape"):
        dequantize8(Quantized8(np.zeros((2, 3), np.uint8), np.ones(3, np.float32), np.zeros((2, 3), bool)))


# --------------------------------------------------------------------------- encode_transfer


@pytest.mark.parametrize("r", [4, 16])
def test_auto_picks_the_basis_with_fewer_nonzero_codes(r, rng):
    t = np.concatenate([portal_transfer(rng, 20, r, 2), portal_transfer(rng, 20, r, r)])
    sparse = encode_transfer(t)
    n_pulse = np.count_nonzero(quantize8(t).codes, axis=(1, 2, 3))
    n_haar = np.count_nonzero(quantize8(haar2d(t)).codes, axis=(1, 2, 3))
    np.testing.assert_array_equal(sparse.basis, (n_haar < n_pulse).astype(np.uint8))
    np.testing.assert_array_equal(np.diff(sparse.indptr), np.minimum(n_pulse, n_haar))
    # both kinds of vertex occur: small portal -> pulse, a whole bright face -> Haar
    assert set(sparse.basis.tolist()) == {0, 1}
    assert encode_transfer(t, basis="pulse").codes.size >= sparse.codes.size
    assert encode_transfer(t, basis="haar").codes.size >= sparse.codes.size


def test_known_choices():
    r = 8
    t = np.zeros((3, 6, r, r))
    t[0, 4, 3, 5] = 2.0  # one cell sees the portal: 1 pulse code vs 1 + levels Haar codes
    t[1, 2] = 1.0  # a whole face: r*r pulse codes vs 1 Haar code
    sparse = encode_transfer(t)  # vertex 2 all zero: no entries, pulse
    assert sparse.basis.tolist() == [0, 1, 0]
    assert np.diff(sparse.indptr).tolist() == [1, 1, 0]
    assert sparse.scale[2] == 0
    np.testing.assert_allclose(sparse.to_dense(), t, atol=1e-15)


@pytest.mark.parametrize("basis", ["auto", "pulse", "haar"])
def test_to_dense_within_quantisation_error(basis, rng):
    r = 8
    t = portal_transfer(rng, 30, r, r) * 10.0 ** rng.uniform(-5, 5, size=(30, 1, 1, 1))
    sparse = encode_transfer(t, basis=basis)
    dense = sparse.to_dense()
    assert dense.shape == t.shape
    bound = sparse.scale.astype(np.float64) / 510.0 * (1 + 1e-12)
    coeff_err = np.where(
        (sparse.basis == 1)[:, None, None, None], haar2d(t), t
    ) - sparse.coefficients()
    assert np.all(np.abs(coeff_err).max(axis=(1, 2, 3)) <= bound)
    # the texel-domain error is the coefficient error rotated by an orthogonal transform
    texel_err = np.sqrt(((dense - t) ** 2).sum(axis=(1, 2, 3)))
    np.testing.assert_allclose(texel_err, np.sqrt((coeff_err**2).sum(axis=(1, 2, 3))), rtol=1e-9, atol=1e-300)


@pytest.mark.parametrize("method", METHODS)
def test_sparse_dot_equals_dense_dot(method, rng):
    r = 16
    t = solid_angle_weight(np.concatenate([portal_transfer(rng, 25, r, 3), portal_transfer(rng, 25, r, r)]))
    sparse = encode_transfer(t)
    light = rng.random((6, r, r, 3)) * 5.0
    dense = sparse.to_dense()
    expected = np.einsum("vfij,fijc->vc", dense, light)
    got = sparse.dot(light, method=method)
    assert got.shape == (50, 3)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-14 * np.abs(expected).max())
    np.testing.assert_allclose(
        sparse.dot(light, haar2d(light, channels=True), method=method), got, rtol=1e-12, atol=1e-15
    )
    mono = sparse.dot(light[..., 0], method=method)
    assert mono.shape == (50,)
    np.testing.assert_allclose(mono, expected[:, 0], rtol=1e-12, atol=1e-14 * np.abs(expected).max())
    # and close to the unquantised relighting (8 bits of the per-vertex maximum)
    exact = np.einsum("vfij,fij->v", t, light[..., 0])
    assert np.all(np.abs(mono - exact) <= np.abs(light).sum() * sparse.scale / 510.0 * 6 * r)


@given(st.integers(0, 2**32 - 1), st.sampled_from([1, 2, 8, 32]), st.integers(0, 12))
def test_sparse_dot_tiers_agree(seed, r, n_vertices):
    rng = np.random.default_rng(seed)
    t = rng.normal(size=(n_vertices, 6, r, r)) * (rng.random((n_vertices, 6, r, r)) < 0.2)
    sparse = encode_transfer(t)
    light = rng.normal(size=(6, r, r))
    ref = sparse.dot(light, method="reference")
    np.testing.assert_allclose(sparse.dot(light), ref, rtol=1e-12, atol=1e-12 * (1 + np.abs(ref).max(initial=0)))
    np.testing.assert_allclose(ref, np.einsum("vfij,fij->v", sparse.to_dense(), light), rtol=1e-10, atol=1e-10)


def test_wide_indices_for_large_cubemaps(rng):
    r = 128  # 6 r**2 = 98304 > 2**15: uint32 indices with the sign in bit 31
    t = np.zeros((2, 6, r, r))
    t[0, 5, 100:104, 7:9] = 1.0
    t[1, 1] = rng.random((r, r)) - 0.5
    sparse = encode_transfer(t, basis="haar")
    assert sparse.indices.dtype == np.uint32 and sparse.sign_bit == 1 << 31
    light = rng.random((6, r, r))
    np.testing.assert_allclose(sparse.dot(light), sparse.dot(light, method="reference"), rtol=1e-12)


def test_memory_accounting(rng):
    r = 32
    t = portal_transfer(rng, 100, r, 4)
    sparse = encode_transfer(t)
    assert sparse.indices.dtype == np.uint16
    expected = 8 * 101 + 2 * sparse.codes.size + sparse.codes.size + 4 * 100 + 100
    assert sparse.nbytes == expected
    assert sparse.nbytes < t.nbytes / 100


def test_empty_transfer():
    sparse = encode_transfer(np.zeros((0, 6, 4, 4)))
    assert isinstance(sparse, SparseTransfer) and sparse.n_vertices == 0
    assert sparse.to_dense().shape == (0, 6, 4, 4)
    for method in METHODS:
        assert sparse.dot(np.ones((6, 4, 4)), method=method).shape == (0,)
        assert sparse.dot(np.ones((6, 4, 4, 3)), method=method).shape == (0, 3)


def test_container_validation():
    good = encode_transfer(np.ones((2, 6, 2, 2)))
    parts = dict(indptr=good.indptr, indices=good.indices, codes=good.codes, scale=good.scale, basis=good.basis, res=2)
    assert SparseTransfer(**parts).nbytes == good.nbytes
    with pytest.raises(TypeError, match="SparseTransfer.codes must be a 1D uint8"):
        SparseTransfer(**{**parts, "codes": good.codes.astype(np.int16)})
    with pytest.raises(ValueError, match="arrays are inconsistent"):
        SparseTransfer(**{**parts, "indptr": good.indptr[:-1]})
    with pytest.raises(ValueError, match="arrays are inconsistent"):
        SparseTransfer(**{**parts, "basis": np.array([0, 2], np.uint8)})
    with pytest.raises(ValueError, match="point beyond"):
        SparseTransfer(**{**parts, "indices": good.indices + np.uint16(30)})
    with pytest.raises(ValueError, match="power of two"):
        SparseTransfer(**{**parts, "res": 3})


def test_encode_errors():
    t = np.zeros((2, 6, 4, 4))
    with pytest.raises(ValueError, match="basis must be one of"):
        encode_transfer(t, basis="sh")
    with pytest.raises(ValueError, match=r"reshape it to \(-1, 6, r, r\)"):
        encode_transfer(np.zeros((2, 2, 6, 4, 4)))
    with pytest.raises(ValueError, match="six faces"):
        encode_transfer(np.zeros((2, 5, 4, 4)))
    with pytest.raises(ValueError, match="power of two"):
        encode_transfer(np.zeros((2, 6, 5, 5)))
    bad = t.copy()
    bad[1, 2, 3, 3] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        encode_transfer(bad)
    sparse = encode_transfer(t)
    with pytest.raises(ValueError, match="to match the transfer"):
        sparse.dot(np.ones((6, 8, 8)))
    with pytest.raises(ValueError, match="light_haar must have the shape"):
        sparse.dot(np.ones((6, 4, 4)), np.ones((6, 4, 4, 3)))
    with pytest.raises(ValueError, match="light_haar contains NaN"):
        sparse.dot(np.ones((6, 4, 4)), np.full((6, 4, 4), np.nan))
    with pytest.raises(ValueError, match="method must be one of"):
        sparse.dot(np.ones((6, 4, 4)), method="gpu")
    assert np.allclose(ihaar2d(haar2d(t)), t)
