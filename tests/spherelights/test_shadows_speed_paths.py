"""The fused second pass's fast paths (issue 20) give the results of the paths they replace, bit for bit.

The normals divided by their norms inside the kernel (numpy's ``n / norm(n, axis=1)`` before), the blocks shared
between the threads (interleaved, one scratch per thread), the packed inputs kept from call to call, and the
shadows-only pass summing the blockers' logs without storing them: each is checked against its old form on
scenes with the degenerate receivers on purpose (no light above the horizon, inside a light, on its surface, at
its horizon, lights touching and intersecting), and the fused pass still against the composed tier.
"""

import numba
import numpy as np
import pytest

from prtlab.spherelights import second_pass
from prtlab.spherelights import _passes

ORDER = 4


def _bits(x):
    """The float64 array as its bit patterns (signed zeros and NaN payloads told apart)."""
    return np.ascontiguousarray(x, dtype=np.float64).view(np.int64)


def _assert_bitwise(a, b):
    for x, y in zip(a, b):
        np.testing.assert_array_equal(_bits(x), _bits(y))


def _edge_scene(rng, n_recv):
    """Seven lights in five objects (0-1 intersecting, 1-2 touching: ``|c1 - c2| = r1 + r2``; one light under the
    plane ``y = 0``) and receivers of six kinds: on the plane facing up, above every light facing up (no light
    above the horizon), inside a light, on a light's surface, level with a light's lowest point (at its horizon,
    ``h = -r``), anywhere with a normal of length 0.01-100."""
    c = np.array([[0, 1, 0], [0.5, 1, 0], [1.1, 1, 0], [0, -1, 0], [2, 0.2, 0], [-2, 0.0, 1], [0, 3, 0.0]])
    r = np.array([0.3, 0.3, 0.3, 0.5, 0.2, 0.2, 0.4])
    obj = np.array([0, 0, 0, 1, 2, 3, 4])
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    inter = (d < r[:, None] + r[None]) & (obj[:, None] == obj[None])
    np.fill_diagonal(inter, False)
    kind = rng.integers(0, 6, n_recv)
    light = rng.integers(0, 7, n_recv)
    u = rng.normal(size=(n_recv, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    p = rng.uniform(-2, 2, (n_recv, 3))
    n = rng.normal(size=(n_recv, 3))
    up = np.array([0.0, 1.0, 0.0])
    p[kind == 0, 1], n[kind == 0] = 0.0, up
    p[kind == 1, 1], n[kind == 1] = 5.0, up
    p[kind == 2] = c[light[kind == 2]] + 0.5 * r[light[kind == 2], None] * u[kind == 2]
    p[kind == 3], n[kind == 3] = c[light[kind == 3]] + r[light[kind == 3], None] * u[kind == 3], u[kind == 3]
    p[kind == 4], n[kind == 4] = c[light[kind == 4]] - r[light[kind == 4], None] * up + [3.0, 0.0, 0.0], up
    n[kind == 5] *= rng.uniform(0.01, 100.0, (int(np.sum(kind == 5)), 1))
    rot = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(7)])
    env = rng.normal(size=(ORDER * ORDER, 3))
    env[0] += 3.0
    emission = 0.1 * rng.normal(size=(7, 36, 3))
    emission[:, 0] += 1.0
    return (p, n, c, r, obj, inter, rot, emission, env)


MODES = [dict(blocking=b, exp_method=e, indirect=i) for b in ("object", "sphere") for e in ("hyb", "ol")
         for i in (False, True)]


# ----------------------------------------------------------------------------- identities with the old forms


def test_unit_normal_is_numpys_normalisation(rng):
    """The kernel's ``n / |n|`` is numpy's ``n / np.linalg.norm(n, axis=1, keepdims=True)`` bit for bit (which the
    pass computed before), over magnitudes from 1e-150 to 1e150, axis-aligned and zero normals, C and F order."""
    n = rng.normal(size=(20_000, 3)) * 10.0 ** rng.uniform(-150, 150, (20_000, 1))
    n[:6] = [[0, 0, 0], [0, 1, 0], [0, 0, -3], [1e-300, 0, 0], [1, 1, 1], [-0.0, 2.0, -0.0]]

    @numba.njit(error_model="numpy")
    def unit_rows(n):
        out = np.empty_like(n)
        for b in range(n.shape[0]):
            out[b, 0], out[b, 1], out[b, 2] = _passes._unit_normal(n[b, 0], n[b, 1], n[b, 2])
        return out

    with np.errstate(invalid="ignore", divide="ignore"):
        for layout in (np.ascontiguousarray(n), np.asfortranarray(n)):
            np.testing.assert_array_equal(_bits(unit_rows(n)), _bits(layout / np.linalg.norm(layout, axis=1,
                                                                                              keepdims=True)))


def test_normals_of_any_length_are_normalised_once(rng):
    """A normal scaled by a power of two gives the unit normal's results bit for bit (the division is exact):
    the kernel divides once, whatever the length."""
    p, n, *rest = _edge_scene(rng, 300)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    scaled = n * 2.0 ** rng.integers(-20, 20, (300, 1))
    for mode in MODES:
        _assert_bitwise(second_pass(p, scaled, *rest, order=ORDER, **mode),
                        second_pass(p, n, *rest, order=ORDER, **mode))


@pytest.mark.parametrize("n_recv", [1, 33, 700, 2500])
def test_results_depend_on_neither_threads_nor_blocks(n_recv, rng):
    """One thread against two (blocks interleaved between the threads; under 1,024 receivers runs of blocks as
    tasks), and the receivers in one call against slices of 96 in several: the same bits."""
    scene = _edge_scene(rng, n_recv)
    p, n, *rest = scene
    threads = numba.get_num_threads()
    for mode in MODES:
        try:
            numba.set_num_threads(1)
            one = second_pass(*scene, order=ORDER, **mode)
        finally:
            numba.set_num_threads(threads)
        _assert_bitwise(second_pass(*scene, order=ORDER, **mode), one)
        parts = [second_pass(p[s:s + 96], n[s:s + 96], *rest, order=ORDER, **mode) for s in range(0, n_recv, 96)]
        _assert_bitwise([np.concatenate([x[0] for x in parts]), np.concatenate([x[1] for x in parts])], one)


def test_shadows_only_direct_is_the_full_pass_direct(rng):
    """Shadows only, the logs are summed without being stored (``_blocker_lanes(keep_logs=False)``): the direct
    light is that of the pass with indirect light (which keeps them) bit for bit, and its indirect light zero."""
    scene = _edge_scene(rng, 1500)
    for blocking in ("object", "sphere"):
        for exp_method in ("hyb", "ol"):
            d0, i0 = second_pass(*scene, order=ORDER, blocking=blocking, exp_method=exp_method, indirect=False)
            d1, _ = second_pass(*scene, order=ORDER, blocking=blocking, exp_method=exp_method, indirect=True)
            np.testing.assert_array_equal(_bits(d0), _bits(d1))
            np.testing.assert_array_equal(i0, 0.0)


def test_kept_inputs_follow_every_change(rng):
    """The packed inputs kept from the last call: any input changed (in place too) gives the results of a call
    with nothing kept; calls alternating between two scenes give each its own results."""
    scene = list(_edge_scene(rng, 200))

    def fresh(args, **mode):
        _passes._FUSED_INPUTS.clear()
        return second_pass(*args, order=ORDER, **mode)

    first = fresh(scene)
    for i in range(2, len(scene)):  # centres, radii, objects, intersect, rotations, emission, environment
        changed = [np.array(x, copy=True) for x in scene]
        if changed[i].dtype == bool:
            changed[i][0, 1] = changed[i][1, 0] = not changed[i][0, 1]
        elif i == 4:
            changed[i][2] = 3
        else:
            changed[i].reshape(-1)[1] += 0.25
        expect = fresh(changed)
        _assert_bitwise(second_pass(*scene, order=ORDER), first)
        _assert_bitwise(second_pass(*changed, order=ORDER), expect)
        _assert_bitwise(second_pass(*scene, order=ORDER), first)
    env = np.array(scene[-1], copy=True)
    args = scene[:-1] + [env]
    before = fresh(args, indirect=False)
    env[3] += 1.0  # the same array, changed in place
    _assert_bitwise(second_pass(*args, order=ORDER, indirect=False), fresh(args, indirect=False))
    assert not np.array_equal(second_pass(*args, order=ORDER, indirect=False)[0], before[0])
    for mode in MODES:  # the mode is part of the key
        _assert_bitwise(second_pass(*scene, order=ORDER, **mode), fresh(scene, **mode))


# ----------------------------------------------------------------------------- against the composed tier


@pytest.mark.parametrize("mode", MODES, ids=lambda m: "-".join(str(v) for v in m.values()))
def test_degenerate_receivers_match_the_composed_tier(mode, rng):
    """The fused pass on the degenerate receivers against ``method="numba"`` (numpy's normalisation, batched
    exponentials), to rounding as ``test_passes``' fused-against-composed tests."""
    scene = _edge_scene(rng, 600)
    d1, i1 = second_pass(*scene, order=ORDER, **mode)
    d2, i2 = second_pass(*scene, order=ORDER, method="numba", **mode)
    np.testing.assert_allclose(d1, d2, atol=1e-11)
    np.testing.assert_allclose(i1, i2, atol=1e-11)
    p, n = scene[:2]
    no_light = p[:, 1] == 5.0  # above every light, facing up
    assert no_light.any()
    np.testing.assert_array_equal(i1[no_light], 0.0)
