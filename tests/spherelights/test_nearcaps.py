"""Tests of prtlab.spherelights._nearcaps (the direct light with the nearest blockers as exact caps)."""

import math

import numpy as np
import pytest

from prtlab import sh
from prtlab.spherelights import SphereLightOptions, ground_light
from prtlab.spherelights._nearcaps import N_AZIMUTH, N_RADIAL, environment_cube, near_blocker_direct

ORDER = 4


def _white(order=10):
    env = np.zeros((order * order, 3))
    env[0] = math.sqrt(4 * math.pi)  # radiance 1
    return env


def _sky(order=10):
    """A positive environment of order 10 (brighter above)."""
    env = np.zeros((order * order, 3))
    env[0] = [3.0, 2.5, 2.0]
    env[2] = [0.8, 0.9, 1.0]
    env[1] = [0.4, 0.5, 0.6]
    env[6] = [0.2, 0.2, 0.2]
    env[20] = [0.1, -0.1, 0.05]
    return env


def _spheres():
    return np.array([[1.1, 0.5, 0.0], [-1.1, 0.5, 0.0], [0.0, 0.5, -0.4]]), np.full(3, 0.5)


def _receivers(seed=0, n=40):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c, _ = _spheres()
    return c[2] + 0.5 * d, d


@pytest.mark.parametrize("dist", [1.0, 2.0, 3.0])
def test_one_cap_above_the_horizon_is_exact(dist):
    """A white sky and one sphere wholly above the tangent plane, facing it: ``E = pi - pi sin^2 theta`` (the
    cosine-weighted solid angle of a cap of half-angle theta about the normal is ``pi sin^2 theta``); the rule is
    Gauss-Legendre in cos(alpha), exact for the integrand ``cos alpha``."""
    e = near_blocker_direct([[0, 0, 0.0]], [[0, 1.0, 0]], [[0, dist, 0]], [0.6], _white(), ORDER, 1)
    assert e[0, 0] == pytest.approx(math.pi - math.pi * (0.6 / dist) ** 2, rel=1e-12)


def test_a_small_blocker_stays_in_the_log_sum():
    """A blocker of angular radius below ``MIN_ANGLE_DEG`` is not taken: the paper's direct light, and
    :func:`has_near_blocker` says so."""
    from prtlab.spherelights._nearcaps import MIN_ANGLE_DEG, has_near_blocker

    d = 0.6 / math.sin(math.radians(0.9 * MIN_ANGLE_DEG))
    args = ([[0, 0, 0.0]], [[0, 1.0, 0]], [[0, d, 0]], [0.6], _white())
    np.testing.assert_allclose(near_blocker_direct(*args, ORDER, 2), near_blocker_direct(*args, ORDER, 0),
                               rtol=1e-12)
    assert not has_near_blocker(*args[:4])[0]
    assert has_near_blocker([[0, 0, 0.0]], [[0, 1.0, 0]], [[0, 1.0, 0]], [0.6])[0]


def test_no_blocker_is_the_unoccluded_irradiance():
    """No sphere: ``V = 1``, ``E = int L max(0, n.w)``, for a white sky ``pi``."""
    e = near_blocker_direct([[0, 0, 0.0]], [[0, 1.0, 0]], np.zeros((0, 3)), np.zeros(0), _white(), ORDER, 2)
    assert e[0] == pytest.approx([math.pi] * 3, rel=1e-12)


def test_zero_near_blockers_is_the_papers_direct_light():
    """``n_near=0``: ``exp*(sum of every blocker's log) . T_n`` (Sec. 5.1), the same as composing the public parts."""
    from prtlab.spherelights import blocker_log_sum, environment_transfer

    p, n = _receivers()
    c, r = _spheres()
    ours = near_blocker_direct(p, n, c, r, _sky(), ORDER, 0)
    v = sh.exp(blocker_log_sum(p, n, c, r, ORDER), method="hyb", channels=False)
    want = np.einsum("bk,bkc->bc", v, environment_transfer(n, _sky(), ORDER))
    np.testing.assert_allclose(ours, want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("k", [1, 2, 3])
def test_numba_against_reference(k):
    """The kernels against the numpy tier (the same nodes; the radiance from the SH there, from the cube map
    here: bilinear over 32 x 32 texels per face of an order-10 environment, bounded by 0.5 % of the irradiance)."""
    p, n = _receivers()
    c, r = _spheres()
    ours = near_blocker_direct(p, n, c, r, _sky(), ORDER, k)
    ref = near_blocker_direct(p, n, c, r, _sky(), ORDER, k, method="reference")
    assert np.max(np.abs(ours - ref)) <= 5e-3 * np.max(np.abs(ref))
    white = near_blocker_direct(p, n, c, r, _white(), ORDER, k)  # a constant cube map is read exactly
    np.testing.assert_allclose(white, near_blocker_direct(p, n, c, r, _white(), ORDER, k, method="reference"),
                               rtol=1e-10, atol=1e-10)


def test_two_exact_caps_against_a_fine_quadrature():
    """Both neighbours exact (the receiver's own sphere holds it and is culled): ``E`` is the integral of
    ``L max(0, n.w)`` over the directions missing both spheres; against a Gauss-Legendre x uniform rule of
    400 x 800 nodes on the sphere, within the cap rule's error (4 x 12 nodes per cap; the integrand has a kink
    at the horizon): 1 % of the unoccluded irradiance."""
    p, n = _receivers(1, 12)
    c, r = _spheres()
    ours = near_blocker_direct(p, n, c, r, _white(), ORDER, 3)
    z, wz = np.polynomial.legendre.leggauss(400)
    phi = (np.arange(800) + 0.5) * 2 * np.pi / 800
    s = np.sqrt(1 - z * z)
    w = np.stack([s[:, None] * np.cos(phi), s[:, None] * np.sin(phi), np.broadcast_to(z[:, None], (400, 800))],
                 -1).reshape(-1, 3)
    dw = np.repeat(wz * 2 * np.pi / 800, 800)
    for b in range(len(p)):
        hit = np.zeros(len(w), bool)
        for cc, rr in zip(c, r):
            e = cc - p[b]
            if e @ e < rr * rr:
                continue
            t = w @ e
            hit |= (t > 0) & (e @ e - t * t < rr * rr)
        want = np.sum(dw * np.maximum(w @ n[b], 0) * ~hit)
        assert abs(ours[b, 0] - want) <= 0.01 * math.pi, b


def test_cube_map_reads_the_environment():
    """The cube map's texel centres hold the SH radiance (bilinear reads between them: the kernel tests above)."""
    cube = environment_cube(_sky(), res=4)
    assert cube.shape == (6, 4, 4, 3)
    d = np.array([1.0, -0.75, -0.75])  # face +x, texel (0, 0) centre: u = v = -1 + 1/4
    np.testing.assert_allclose(cube[0, 0, 0], sh.basis(d / np.linalg.norm(d), 10) @ _sky(), rtol=1e-12)


def test_quadrature_sizes():
    assert N_RADIAL >= 4 and N_AZIMUTH >= 8


def test_bad_input():
    p, n = _receivers()
    c, r = _spheres()
    with pytest.raises(ValueError, match="n_near"):
        near_blocker_direct(p, n, c, r, _sky(), ORDER, -1)
    with pytest.raises(ValueError, match="eligible must be a bool array"):
        near_blocker_direct(p, n, c, r, _sky(), ORDER, 1, eligible=[True])
    with pytest.raises(ValueError, match="method must be"):
        near_blocker_direct(p, n, c, r, _sky(), ORDER, 1, method="fast")
    with pytest.raises(ValueError, match="near_blockers"):
        SphereLightOptions(near_blockers=-1)
    with pytest.raises(ValueError, match="unadjusted must be a bool array"):
        rect = np.array([[0.0, 0, 0, 3, 0, 0, 3]])
        ground_light(p + [0, 1, 0], n, rect, np.zeros((1, 2, 2, 3)), _sky(), c, r, unadjusted=[True])


def test_unadjusted_lights_block_as_true_spheres():
    """``ground_light(unadjusted=...)``: a sphere crossing a receiver's tangent plane hides the ground as the true
    sphere (bigger than the adjusted one), so it hides less environment; with ``unadjusted`` all False it is the
    default call."""
    rect = np.array([[0.0, 0, 0, 3, 0, 0, 3]])
    p = np.array([[0.0, 0.9, 0.0]])
    n = np.array([[1.0, 0.0, 0.0]])
    c, r = np.array([[0.6, 0.3, 0.0]]), np.array([0.4])  # h = 0.6 >= r: kept as it is either way
    c2 = np.array([[0.2, 0.3, 0.0]])  # h = 0.2 < r = 0.4: adjusted by default
    base = ground_light(p, n, rect, np.zeros((1, 2, 2, 3)), _white(), c2, r)[0]
    same = ground_light(p, n, rect, np.zeros((1, 2, 2, 3)), _white(), c2, r, unadjusted=[False])[0]
    true = ground_light(p, n, rect, np.zeros((1, 2, 2, 3)), _white(), c2, r, unadjusted=[True])[0]
    np.testing.assert_array_equal(base, same)
    assert np.all(true < base)
    kept = ground_light(p, n, rect, np.zeros((1, 2, 2, 3)), _white(), c, r)[0]
    np.testing.assert_array_equal(kept, ground_light(p, n, rect, np.zeros((1, 2, 2, 3)), _white(), c, r,
                                                     unadjusted=[True])[0])


def test_pipeline_option_gives_the_closed_form():
    """Two balls under a white sky, no ground, ``near_blockers=1``: at each vertex of ball A that sees all of B
    above its horizon (``n . a >= sin theta``) the direct irradiance is ``pi - (n . a) pi sin^2 theta`` (the
    cosine-weighted solid angle of a cap wholly above the horizon), the other ball's light taken exactly and the
    own one culled; radiance ``albedo / pi`` times it (``mesh_blockers=False``: the spheres' path)."""
    from prtlab.pipeline import FrameState
    from prtlab.scene import Scene
    from prtlab.spherelights import SphereLights

    ball = {"builtin": "icosphere", "radius": 0.5, "subdivisions": 2}
    sc = Scene.from_dict({
        "objects": [{"name": "a", "mesh": ball, "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}},
                    {"name": "b", "mesh": ball, "transform": {"translate": [1.3, 0.0, 0.0]},
                     "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}],
        "lights": [{"type": "environment", "constant": [1, 1, 1]}]})
    pre = SphereLights.precompute(sc, {"n_spheres": 1, "fit_resolution": 16, "near_blockers": 1,
                                       "mesh_blockers": False}, cache=False, progress=False)
    world = pre.world_lights(FrameState.from_scene(sc))
    k = int(np.argmax(world.centres[:, 0]))  # b's light
    c, r = world.centres[k], world.radii[k]
    out = pre.shade(FrameState.from_scene(sc), bounces=0)
    obj = sc.object("a")
    p, n = obj.world_shading_points(obj.transform), obj.world_normals(obj.transform)
    e = c - p
    d = np.linalg.norm(e, axis=1)
    sin_t = r / d
    cos_na = np.einsum("bk,bk->b", n, e) / d
    sel = cos_na >= sin_t + 1e-9
    assert sel.sum() >= 5
    want = (math.pi - cos_na[sel] * math.pi * sin_t[sel] ** 2) * 0.5 / math.pi
    np.testing.assert_allclose(out.direct["a"][sel, 0], want, rtol=1e-9)


@pytest.mark.parametrize("order", [4, 6])
def test_split_kernel_against_reference(order):
    """The lanes kernel of the split (the chosen caps and the others' log sum) against its numpy tier, to
    rounding, over more receivers than one block of lanes and a partial last block (71 = 2 x 32 + 7), with some
    spheres not eligible."""
    from prtlab.spherelights._nearcaps import (
        _min_sin, _near_split, _near_split_reference, _SplitTables)
    from prtlab.spherelights._shadows import _blocker_log_knots, blocker_log_table

    p, n = _receivers(3, 71)
    c, r = _spheres()
    c = np.concatenate([c, [[0.0, 1.6, 0.2], [0.3, -0.8, 0.1]]])
    r = np.concatenate([r, [0.3, 0.2]])
    elig = np.array([True, True, False, True, True])
    for k in (0, 1, 2, 3):
        g = np.zeros((len(p), order * order))
        axis = np.zeros((len(p), k, 3))
        cosq = np.full((len(p), k), 2.0)
        _near_split(p, n, c, r, elig, _min_sin(), _SplitTables(blocker_log_table(order), _blocker_log_knots()),
                    order, k, g, axis, cosq)
        g_ref, axis_ref, cos_ref = _near_split_reference(p, n, c, r, elig, order, k)
        np.testing.assert_allclose(g, g_ref, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(axis, axis_ref, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(cosq, cos_ref, rtol=1e-12, atol=1e-12)
        assert np.any(cosq <= 1.0) == (k > 0)


@pytest.mark.parametrize("order", [2, 4])
def test_transfer_kernel_against_environment_transfer(order):
    """The near pass's transfer (``cos_{2n-1}(n) @ M`` in a numba kernel) against the public
    :func:`environment_transfer` (BLAS), to rounding; no receivers gives an empty result."""
    from prtlab.spherelights import environment_transfer
    from prtlab.spherelights._nearcaps import _environment_transfer

    _, n = _receivers(4, 37)
    np.testing.assert_allclose(_environment_transfer(n, _sky(), order), environment_transfer(n, _sky(), order),
                               rtol=1e-12, atol=1e-12)
    assert _environment_transfer(np.zeros((0, 3)), _sky(), order).shape == (0, order * order, 3)
