"""The per-frame passes: the numba tiers held to the float64 reference tiers (hypothesis)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from prtlab.portals import direct_pass, indirect_pass
from prtlab.wavelet import encode_transfer


def direct_float32_bound(sparse, albedo, cube):
    """The numba direct pass's forward error bound against the float64 reference: ``(n + 2) eps_32`` times each row's
    sum of absolute terms (``n`` the row's entries; float32 light and sums of the pulse rows; the Haar rows' float64
    sums are far inside it), plus float64 roundoff."""
    from prtlab.bench import transfer_csr
    from prtlab.portals._shade import shell_coefficients

    if sparse.n_vertices == 0:
        return np.zeros((0, 3))
    light = shell_coefficients(cube)
    absolute = (abs(transfer_csr(sparse)) @ np.abs(light)) * albedo
    n = np.diff(sparse.indptr)[:, None]
    return (n + 2) * np.finfo(np.float32).eps * absolute + 1e-12 * absolute.max(initial=0.0)


@given(n=st.integers(0, 12), density=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1),
       basis=st.sampled_from(["auto", "pulse", "haar"]), black=st.floats(0.0, 1.0), horizon=st.booleans())
def test_direct_pass_tiers(n, density, seed, basis, black, horizon):
    """Numba tier (texel runs, runs under black texels skipped, float32 pulse sums) against the float64 reference
    within its forward error bound, with texels the light leaves black at random and, with ``horizon``, the lower
    half of every face black (a black ground)."""
    rng = np.random.default_rng(seed)
    transfer = np.where(rng.random((n, 6, 4, 4)) < density, rng.random((n, 6, 4, 4)), 0.0)
    sparse = encode_transfer(transfer, basis)
    albedo = rng.random((n, 3))
    cube = rng.random((6, 4, 4, 3)) * 10
    cube[rng.random((6, 4, 4)) < black] = 0.0
    if horizon:
        cube[:, 2:] = 0.0
    fast = direct_pass(sparse, albedo, cube)
    assert fast.shape == (n, 3)
    assert np.all(np.abs(fast - direct_pass(sparse, albedo, cube, "reference")) <= direct_float32_bound(sparse, albedo,
                                                                                                        cube))
    # 8-bit bound against the unquantised transfer (pulse basis: |dT| <= scale / 510 per texel)
    if basis == "pulse":
        exact = np.einsum("vfij,fijc->vc", transfer, cube) * albedo
        bound = albedo * sparse.scale[:, None] / 510 * np.abs(cube).sum((0, 1, 2))
        assert np.all(np.abs(fast - exact) <= bound + 1e-12)


def test_texel_runs_cover_the_pulse_rows():
    """Runs of consecutive texels: each pulse row's runs cover exactly its entries' indices, in order; Haar rows have
    none."""
    from prtlab.portals._shade import texel_runs

    rng = np.random.default_rng(3)
    transfer = np.where(rng.random((30, 6, 4, 4)) < 0.6, rng.random((30, 6, 4, 4)), 0.0)
    transfer[::3] = rng.normal(size=(10, 6, 4, 4))  # dense signed rows: Haar under "auto" at times
    sparse = encode_transfer(transfer, "auto")
    run_ptr, run_start, run_len = texel_runs(sparse)
    assert texel_runs(sparse)[0] is run_ptr  # cached
    for v in range(sparse.n_vertices):
        runs = range(run_ptr[v], run_ptr[v + 1])
        covered = [k for q in runs for k in range(run_start[q], run_start[q] + run_len[q])]
        if sparse.basis[v] == sparse.HAAR:
            assert covered == []
        else:
            assert covered == sparse.indices[sparse.indptr[v]:sparse.indptr[v + 1]].astype(int).tolist()


@given(n=st.integers(0, 20), order=st.integers(1, 6), seed=st.integers(0, 2**32 - 1))
def test_indirect_pass_tiers(n, order, seed):
    rng = np.random.default_rng(seed)
    t = rng.normal(size=(n, order * order, 3)).astype(np.float32)
    c = rng.normal(size=(order * order, 3))
    fast = indirect_pass(t, c)
    assert fast.shape == (n, 3)
    np.testing.assert_allclose(fast, indirect_pass(t, c, "reference"), rtol=1e-9, atol=1e-9)


def test_direct_pass_errors(rng):
    import pytest

    transfer = rng.random((3, 6, 4, 4))
    sparse = encode_transfer(transfer)
    albedo = np.ones((3, 3))
    with pytest.raises(ValueError, match=r"shell_cube must have shape \(6, 4, 4, 3\)"):
        direct_pass(sparse, albedo, np.ones((6, 8, 8, 3)))
    with pytest.raises(ValueError, match="shell_cube has NaN"):
        direct_pass(sparse, albedo, np.full((6, 4, 4, 3), np.nan))
    assert direct_pass(encode_transfer(transfer[:0]), albedo[:0], np.ones((6, 4, 4, 3))).shape == (0, 3)


@given(n=st.integers(0, 8), views=st.integers(1, 6), density=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1),
       basis=st.sampled_from(["auto", "pulse", "haar"]))
def test_glossy_direct_pass_tiers(n, views, density, seed, basis):
    from prtlab.portals import glossy_direct_pass

    rng = np.random.default_rng(seed)
    transfer = np.where(rng.random((n * views, 6, 4, 4)) < density, rng.random((n * views, 6, 4, 4)), 0.0)
    sparse = encode_transfer(transfer, basis)
    rows = rng.integers(0, max(n * views, 1), size=(n, 4))
    weights = rng.dirichlet(np.ones(4), size=n) if n else np.zeros((0, 4))
    ks = rng.random((n, 3))
    cube = rng.random((6, 4, 4, 3))
    fast = glossy_direct_pass(sparse, rows, weights, ks, cube)
    assert fast.shape == (n, 3)
    np.testing.assert_allclose(fast, glossy_direct_pass(sparse, rows, weights, ks, cube, "reference"),
                               rtol=1e-9, atol=1e-12)
    if n:  # the blend of exact (unquantised) rows within the 8-bit bound of the pulse basis
        exact = np.einsum("vq,vqfij,fijc->vc", weights, transfer[rows], cube) * ks
        if basis == "pulse":
            bound = ks * np.einsum("vq,vq->v", weights, sparse.scale[rows])[:, None] / 510 * cube.sum((0, 1, 2))
            assert np.all(np.abs(fast - exact) <= bound + 1e-12)


@given(n=st.integers(0, 8), density=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_glossy_lobe_pass_tiers(n, density, seed):
    """The numba kernel against the float64 tier, and the tier against the lobe summed texel by texel."""
    from prtlab.geometry import cubemap_directions
    from prtlab.portals import glossy_lobe_pass

    rng = np.random.default_rng(seed)
    dense = np.where(rng.random((n, 96)) < density, rng.random((n, 96)), 0.0).astype(np.float32)
    v, k = np.nonzero(dense)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(v, minlength=n))])
    r = rng.normal(size=(n, 3))
    r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
    e, ks, cube = rng.uniform(0, 60, n), rng.random((n, 3)), rng.random((6, 4, 4, 3))
    fast = glossy_lobe_pass(indptr, k, dense[v, k], 4, r, e, ks, cube)
    ref = glossy_lobe_pass(indptr, k, dense[v, k], 4, r, e, ks, cube, "reference")
    assert fast.shape == (n, 3)
    np.testing.assert_allclose(fast, ref, rtol=1e-9, atol=1e-12)
    lobe = (e[:, None] + 2) / 2 * np.maximum(0.0, r @ cubemap_directions(4).reshape(-1, 3).T) ** e[:, None]
    np.testing.assert_allclose(ref, ks * ((dense * lobe) @ cube.reshape(-1, 3)), rtol=1e-9, atol=1e-12)


def test_glossy_lobe_pass_errors():
    import pytest

    from prtlab.portals import glossy_lobe_pass

    indptr, idx, val = np.array([0, 1, 2]), np.array([0, 95]), np.ones(2, np.float32)
    r, e, ks, cube = np.array([[0, 0, 1.0]] * 2), np.full(2, 10.0), np.ones((2, 3)), np.ones((6, 4, 4, 3))
    with pytest.raises(ValueError, match="one per row"):
        glossy_lobe_pass(indptr, idx, val, 4, r[:1], e, ks, cube)
    with pytest.raises(ValueError, match=r"indices must be texels of the 4 x 4 shell cubemap"):
        glossy_lobe_pass(indptr, idx + 1, val, 4, r, e, ks, cube)
    with pytest.raises(ValueError, match=r"shell_cube must have shape \(6, 8, 8, 3\)"):
        glossy_lobe_pass(indptr, idx, val, 8, r, e, ks, cube)


@given(n=st.integers(0, 10), order=st.integers(1, 4), seed=st.integers(0, 2**32 - 1))
def test_glossy_indirect_pass_tiers(n, order, seed):
    from prtlab.portals import glossy_indirect_pass

    rng = np.random.default_rng(seed)
    m = rng.normal(size=(n, order**2, order**2, 3)).astype(np.float32)
    c = rng.normal(size=(order**2, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    fast = glossy_indirect_pass(m, c, d)
    assert fast.shape == (n, 3)
    np.testing.assert_allclose(fast, glossy_indirect_pass(m, c, d, "reference"), rtol=1e-9, atol=1e-9)


def test_glossy_pass_errors(rng):
    import pytest

    from prtlab.portals import glossy_direct_pass, glossy_indirect_pass

    sparse = encode_transfer(rng.random((4, 6, 4, 4)))
    cube = np.ones((6, 4, 4, 3))
    rows, w, ks = np.zeros((2, 4), int), np.full((2, 4), 0.25), np.ones((2, 3))
    with pytest.raises(ValueError, match=r"rows must be an integer \(V_g, Q\) array"):
        glossy_direct_pass(sparse, rows, w[:, :2], ks, cube)
    with pytest.raises(ValueError, match="rows must index the 4 rows"):
        glossy_direct_pass(sparse, rows + 4, w, ks, cube)
    with pytest.raises(ValueError, match=r"ks must have shape \(2, 3\)"):
        glossy_direct_pass(sparse, rows, w, ks[:1], cube)
    with pytest.raises(ValueError, match="shell_cube has NaN"):
        glossy_direct_pass(sparse, rows, w, ks, cube * np.nan)
    m = np.ones((2, 4, 4, 3), np.float32)
    c = np.ones((4, 3))
    d = np.array([[0, 0, 1.0]] * 2)
    with pytest.raises(ValueError, match=r"matrix must have shape \(V_g, n_out\^2, n\^2, 3\)"):
        glossy_indirect_pass(m[..., 0], c, d)
    with pytest.raises(ValueError, match="light_sh must have shape"):
        glossy_indirect_pass(m, c[:1], d)
    with pytest.raises(ValueError, match="light_sh has NaN"):
        glossy_indirect_pass(m, c * np.nan, d)
    with pytest.raises(ValueError, match=r"view_dirs must be a finite \(2, 3\)"):
        glossy_indirect_pass(m, c, d[:1])
    with pytest.raises(ValueError, match="must be a square"):
        glossy_indirect_pass(np.ones((2, 3, 4, 3)), c, d)


def test_passes_on_all_threads_match_reference(monkeypatch, rng):
    """Small batches run on one thread (PARALLEL_MIN_WORK); force the parallel path and compare the tiers."""
    from prtlab.portals import _shade, glossy_direct_pass, glossy_indirect_pass

    monkeypatch.setattr(_shade, "PARALLEL_MIN_WORK", 0)
    transfer = np.where(rng.random((40, 6, 4, 4)) < 0.3, rng.random((40, 6, 4, 4)), 0.0)
    sparse = encode_transfer(transfer)
    cube = rng.random((6, 4, 4, 3))
    albedo = rng.random((40, 3))
    assert np.all(np.abs(direct_pass(sparse, albedo, cube) - direct_pass(sparse, albedo, cube, "reference"))
                  <= direct_float32_bound(sparse, albedo, cube))
    t = rng.normal(size=(40, 9, 3)).astype(np.float32)
    c = rng.normal(size=(9, 3))
    np.testing.assert_allclose(indirect_pass(t, c), indirect_pass(t, c, "reference"), rtol=1e-9, atol=1e-12)
    rows = rng.integers(0, 40, size=(10, 4))
    w = rng.dirichlet(np.ones(4), size=10)
    ks = rng.random((10, 3))
    np.testing.assert_allclose(glossy_direct_pass(sparse, rows, w, ks, cube),
                               glossy_direct_pass(sparse, rows, w, ks, cube, "reference"), rtol=1e-9)
    m = rng.normal(size=(10, 9, 9, 3)).astype(np.float32)
    d = rng.normal(size=(10, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(glossy_indirect_pass(m, c, d), glossy_indirect_pass(m, c, d, "reference"), rtol=1e-9,
                               atol=1e-9)


@given(res=st.sampled_from([1, 2, 4]), black=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1))
def test_light_layout_kernel_is_exact(res, black, seed):
    """The direct pass's light layouts in one pass: channel-major float64, float32 texels (then 7 zero columns) and
    the running count of lit texels, each exactly numpy's (a texel is lit when any channel is non-zero, negative
    values included)."""
    from prtlab.portals import _kernels
    from prtlab.portals._shade import shell_coefficients

    rng = np.random.default_rng(seed)
    cube = rng.normal(size=(6, res, res, 3)) * 10
    cube[rng.random((6, res, res)) < black] = 0.0
    cube[rng.random((6, res, res, 3)) < 0.2] = 0.0  # single black channels: still lit
    light = shell_coefficients(cube)
    n = len(light) // 2
    light_t, lit = np.empty((3, 2 * n)), np.empty(n + 1, dtype=np.int32)
    light32_t = np.full((3, n + 7), np.nan, np.float32)
    _kernels.light_layout_kernel(light, light_t, lit, light32_t)
    np.testing.assert_array_equal(light_t, light.T)
    np.testing.assert_array_equal(light32_t[:, :n], light[:n].T.astype(np.float32))
    np.testing.assert_array_equal(light32_t[:, n:], 0.0)  # the masked lanes' texels: zero, finite
    np.testing.assert_array_equal(lit, np.concatenate([[0], np.cumsum(np.any(light[:n] != 0.0, axis=1))]))
