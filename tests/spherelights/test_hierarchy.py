"""Tests of prtlab.spherelights._hierarchy (sphere hierarchies, receiver clusters, cuts, reflection ratio)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from prtlab.spherelights import (
    bounding_sphere,
    build_hierarchy,
    cluster_samples,
    receiver_clusters,
    reflection_ratio,
    select_cut,
)


def _spheres(seed, n):
    g = np.random.default_rng(seed)
    return g.normal(size=(n, 3)), g.uniform(0.05, 0.5, n)


# ------------------------------------------------------------------ identities (hypothesis)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 12), k=st.integers(2, 4))
def test_parents_bound_their_children_and_weights_sum_intensities(seed, n, k):
    c, r = _spheres(seed, n)
    h = build_hierarchy(c, r, k)
    assert h.n_leaves == n and len(h.roots) == 1
    np.testing.assert_array_equal(h.weights[:n], np.eye(n))
    np.testing.assert_array_equal(h.centres[:n], c)
    for p, kids in enumerate(h.children):
        if not kids:
            assert p < n
            continue
        assert 2 <= len(kids) <= k
        for q in kids:  # the child's sphere lies inside the parent's
            assert np.linalg.norm(h.centres[q] - h.centres[p]) + h.radii[q] <= h.radii[p] * (1 + 1e-12)
        leaves = h.leaves_under(p)
        np.testing.assert_allclose(h.weights[p, leaves], (r[leaves] / h.radii[p]) ** 2)
    # a far viewer sees the parent's intensity pi r_P^2 L_P equal the sum of the leaves' pi r_j^2 L_j
    root = h.roots[0]
    np.testing.assert_allclose(h.radii[root] ** 2 * h.weights[root].sum(), np.sum(r**2))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 12), k=st.integers(2, 4),
       threshold=st.floats(0.0, 0.99), far=st.floats(0.0, 20.0))
def test_a_cut_covers_every_leaf_exactly_once(seed, n, k, threshold, far):
    c, r = _spheres(seed, n)
    h = build_hierarchy(c, r, k)
    x = np.array([far, 0.3, 0.0])
    cut = select_cut(h, h.centres, h.radii, x, 0.2, threshold)
    covered = np.concatenate([h.leaves_under(i) for i in cut])
    np.testing.assert_array_equal(np.sort(covered), np.arange(n))
    for i in cut:  # every parent taken passes the angular-size test
        if h.children[i]:
            assert h.radii[i] < threshold * (np.linalg.norm(h.centres[i] - x) - 0.2)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 10))
def test_bounding_sphere_holds_every_sphere(seed, n):
    c, r = _spheres(seed, n)
    x, rad = bounding_sphere(c, r)
    assert np.all(np.linalg.norm(c - x, axis=1) + r <= rad * (1 + 1e-12))


# ------------------------------------------------------------------ known answers


def test_bounding_sphere_of_two_spheres_is_tight():
    x, rad = bounding_sphere([[0.0, 0, 0], [4.0, 0, 0]], [1.0, 1.0])
    np.testing.assert_allclose(x, [2.0, 0, 0], atol=0.05)
    assert rad == pytest.approx(3.0, rel=0.02)
    x, rad = bounding_sphere([[1.0, 2, 3]], [0.5])
    np.testing.assert_allclose(x, [1.0, 2, 3])
    assert rad == 0.5


def test_threshold_zero_cuts_at_the_leaves_and_far_clusters_take_the_root():
    c, r = _spheres(3, 8)
    h = build_hierarchy(c, r, 2)
    assert len(h.radii) == 15  # 8 leaves, 4 + 2 + 1 parents
    assert select_cut(h, h.centres, h.radii, [0.0, 0, 0], 0.1, 0.0) == list(range(8))
    assert select_cut(h, h.centres, h.radii, [1e3, 0, 0], 0.1, 0.5) == [h.roots[0]]
    # a cluster ball reaching into the root takes no parent that it reaches into
    cut = select_cut(h, h.centres, h.radii, h.centres[h.roots[0]], 0.0, 0.99)
    assert h.roots[0] not in cut


def test_receiver_clusters():
    g = np.random.default_rng(0)
    blobs = np.concatenate([g.normal(size=(30, 3)) * 0.1 + o for o in ([0, 0, 0], [5, 0, 0], [0, 5, 0])])
    labels, medoid = receiver_clusters(blobs, 3)
    assert sorted(np.bincount(labels).tolist()) == [30, 30, 30]
    assert np.all(labels[medoid] == np.arange(3))
    again = receiver_clusters(blobs, 3)
    np.testing.assert_array_equal(again[0], labels)
    # more clusters than distinct points, empty input
    labels, medoid = receiver_clusters(np.zeros((4, 3)), 3)
    assert labels.tolist() == [0, 0, 0, 0] and len(medoid) == 1
    labels, medoid = receiver_clusters(np.zeros((0, 3)), 3)
    assert labels.shape == (0,) and medoid.shape == (0,)
    # normals split a flat sheet's two faces
    sheet = np.concatenate([blobs[:30] * [1, 0, 1]] * 2)
    normals = np.concatenate([np.tile([0.0, 1, 0], (30, 1)), np.tile([0.0, -1, 0], (30, 1))])
    labels, _ = receiver_clusters(sheet, 2, normals=normals)
    assert len(set(labels[:30])) == 1 and len(set(labels[30:])) == 1 and labels[0] != labels[30]


def test_cluster_samples_start_at_the_centre():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [9, 0, 0]])
    labels = np.array([0, 0, 0, 1])
    s = cluster_samples(p, labels, np.array([1, 3]), 3)
    assert s[0, 0] == 1 and set(s[0, 1:].tolist()) == {0, 2}
    assert s[1].tolist() == [3, 3, 3]


def test_reflection_ratio():
    a = np.array([[[2.0, 1.0, 0.0], [1.0, 1.0, 1.0]]])  # (P=1, K=2, 3)
    b = np.array([[[1.0, 2.0, 0.0], [1.0, 0.1, 1e-40]]])
    t = reflection_ratio(a, b)
    np.testing.assert_allclose(t, [[2.0, 0.5, 1.0], [1.0, 4.0, 1.0]])  # Eq. 25, 0/0 -> 1, clipped at 4
    # several points: the least-squares best scaling
    a2 = np.array([[[1.0] * 3], [[3.0] * 3]])
    b2 = np.array([[[1.0] * 3], [[2.0] * 3]])
    np.testing.assert_allclose(reflection_ratio(a2, b2), [[7.0 / 5.0] * 3])
    assert reflection_ratio(np.zeros((2, 0, 3)), np.zeros((2, 0, 3))).shape == (0, 3)


# ------------------------------------------------------------------ errors


def test_errors():
    c, r = _spheres(0, 3)
    with pytest.raises(ValueError, match="n_children must be an int >= 2"):
        build_hierarchy(c, r, 1)
    with pytest.raises(ValueError, match="radii > 0"):
        build_hierarchy(c, -r, 2)
    with pytest.raises(ValueError, match="at least one sphere"):
        bounding_sphere(np.zeros((0, 3)), np.zeros(0))
    with pytest.raises(ValueError, match="n_clusters must be an int >= 1"):
        receiver_clusters(c, 0)
    with pytest.raises(ValueError, match="normals must have the shape of points"):
        receiver_clusters(c, 2, normals=np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"one shape \(..., P, K, 3\)"):
        reflection_ratio(np.zeros((1, 2, 3)), np.zeros((1, 3, 3)))


@pytest.mark.parametrize("blocking,average,exp_method", [("object", "cosine", "hyb"), ("sphere", "paper", "ol")])
def test_per_light_values_sum_to_the_second_pass(blocking, average, exp_method):
    """The terms of Eq. 14 kept apart add up to the second pass's indirect light (both tiers); a light's term is
    the second pass with only that light emitting (linearity in the emission)."""
    from prtlab.spherelights import per_light_indirect, second_pass

    g = np.random.default_rng(5)
    S, order = 5, 4
    centres = g.normal(size=(S, 3)) * 0.8 + [0, 1.5, 0]
    radii = g.uniform(0.1, 0.4, S)
    obj = np.array([0, 0, 1, 1, 2])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    inter = (d < radii[:, None] + radii[None]) & (obj[:, None] == obj[None])
    np.fill_diagonal(inter, False)
    rot = np.stack([np.linalg.qr(g.normal(size=(3, 3)))[0] for _ in range(S)])
    rot *= np.sign(np.linalg.det(rot))[:, None, None]
    emission = g.normal(size=(S, order * order, 3)) * 0.1
    emission[:, 0] += 1.0
    env = g.normal(size=(100, 3)) * 0.1
    pts = np.concatenate([g.uniform(-2, 2, (12, 3)) * [1, 0, 1], np.zeros((1, 3))])
    nrm = np.tile([0.0, 1.0, 0.0], (13, 1))
    args = (pts, nrm, centres, radii, obj, inter, rot, emission, env)
    kw = dict(blocking=blocking, average=average, exp_method=exp_method)
    values = per_light_indirect(*args, **kw)
    assert values.shape == (13, S, 3) and np.abs(values).max() > 1e-3
    for method in ("numba", "fused"):
        np.testing.assert_allclose(values.sum(axis=1), second_pass(*args, method=method, **kw)[1], atol=1e-11)
    one = np.zeros_like(emission)
    one[2] = emission[2]
    np.testing.assert_allclose(values[:, 2], second_pass(*args[:7], one, env, **kw)[1], atol=1e-11)
    assert per_light_indirect(pts[:0], nrm[:0], *args[2:], **kw).shape == (0, S, 3)
    with pytest.raises(ValueError, match="average must be 'cosine' or 'paper'"):
        per_light_indirect(*args, average="mean")
