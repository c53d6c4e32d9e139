"""The per-frame passes: the numba tiers held to the float64 reference tiers (hypothesis)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from prtlab.portals import direct_pass, indirect_pass
from prtlab.wavelet import encode_transfer


@given(n=st.integers(0, 12), density=st.floats(0.0, 1.0), seed=st.integers(0, 2**32 - 1),
       basis=st.sampled_from(["auto", "pulse", "haar"]))
def test_direct_pass_tiers(n, density, seed, basis):
    rng = np.random.default_rng(seed)
    transfer = np.where(rng.random((n, 6, 4, 4)) < density, rng.random((n, 6, 4, 4)), 0.0)
    sparse = encode_transfer(transfer, basis)
    albedo = rng.random((n, 3))
    cube = rng.random((6, 4, 4, 3)) * 10
    fast = direct_pass(sparse, albedo, cube)
    assert fast.shape == (n, 3)
    np.testing.assert_allclose(fast, direct_pass(sparse, albedo, cube, "reference"), rtol=1e-9, atol=1e-12)
    # 8-bit bound against the unquantised transfer (pulse basis: |dT| <= scale / 510 per texel)
    if basis == "pulse":
        exact = np.einsum("vfij,fijc->vc", transfer, cube) * albedo
        bound = albedo * sparse.scale[:, None] / 510 * np.abs(cube).sum((0, 1, 2))
        assert np.all(np.abs(fast - exact) <= bound + 1e-12)


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
