"""Tests of prtlab.spherelights._passes (first and second pass)."""

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import builtin_mesh, geodesic_directions
from prtlab.spherelights import (
    accumulate_blockers,
    first_pass,
    second_pass,
    surface_albedo_sh,
    surface_samples,
    voronoi_cell_sums,
    w_theta_zh,
)
from tests.conftest import MC_SIGMAS, random_directions
from tests.spherelights.test_shadows import _env_eval, _env_sh, _sphere_hit

ORDER = 4


@pytest.mark.parametrize("blocking", ["object", "sphere"])
def test_accumulation_kernel_matches_reference(blocking, rng):
    p = rng.normal(size=(25, 3))
    n = random_directions(rng, 25)
    c = rng.normal(size=(7, 3)) * 2.0
    r = rng.uniform(0.2, 0.8, 7)
    obj = np.array([0, 0, 1, 1, 1, 2, 0])
    inter = np.zeros((7, 7), dtype=bool)
    inter[0, 1] = inter[1, 0] = inter[2, 3] = inter[3, 2] = True
    a = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking=blocking)
    b = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking=blocking, method="reference")
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, atol=1e-12)


def test_front_sums_partition_the_blockers(rng):
    """Per-object blocking: the farthest light of the farthest object sees every other light in front,
    except the ones it intersects."""
    p = np.zeros((1, 3))
    n = np.array([[0.0, 1.0, 0.0]])
    c = np.array([[0.0, 2.0, 0.0], [0.0, 4.0, 0.0], [0.0, 6.0, 0.0]])
    r = np.array([0.5, 0.5, 0.5])
    obj = np.array([0, 1, 1])
    inter = np.zeros((3, 3), dtype=bool)
    gs, gf, th, ax = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking="object")
    np.testing.assert_allclose(gf[0, 2], gs[0, 0] + gs[0, 1], atol=1e-14)
    np.testing.assert_allclose(gf[0, 0], 0.0)
    inter[1, 2] = inter[2, 1] = True
    gs, gf, th, ax = accumulate_blockers(p, n, c, r, obj, inter, ORDER, blocking="sphere")
    np.testing.assert_allclose(gf[0, 2], gs[0, 0], atol=1e-14)


def _one_sphere_light(centre, radius, albedo, env, exp_method="exact"):
    mesh = builtin_mesh("icosphere", subdivisions=4)
    mesh.apply_scale(radius)
    mesh.apply_translation(centre)
    dirs = geodesic_directions(92)
    c, r = np.asarray([centre], dtype=float), np.array([radius])
    pts, nrm, valid = surface_samples(mesh, c, r, dirs)
    alb = surface_albedo_sh(mesh, c, r, albedo, ORDER)
    emission = first_pass(pts, nrm, valid, c, r, env, voronoi_cell_sums(ORDER), alb, exp_method=exp_method)
    return c, r, emission


def test_first_pass_of_a_lone_sphere_is_its_diffuse_reflection():
    """Unoccluded sphere: the emission is albedo/pi times the irradiance at normal w, which is band-limited
    (order 4) for a band-limited environment; the only errors are the Voronoi nearest-neighbour
    interpolation of 92 values (O(cell size x gradient)) and the albedo-coverage product."""
    env = _env_sh()
    albedo = np.array([0.8, 0.5, 0.3])
    c, r, emission = _one_sphere_light([0.0, 1.0, 0.0], 0.5, albedo, env)
    conv = np.repeat(np.pi * np.array([1.0, 2.0 / 3.0, 0.25, 0.0]), 2 * np.arange(ORDER) + 1)
    truth = albedo / np.pi * conv[:, None] * env
    # Voronoi interpolation error: |L - L_nn| <= max|grad L| * (max cell radius); band-limited L of
    # order 4 has |grad L| <= sum_l sqrt(l(l+1)) |band l| ... bound the whole vector by the L2 norm:
    dirs, w = sh.quadrature(1, degree=40)
    L = sh.basis(dirs, ORDER) @ truth
    cells = geodesic_directions(92)
    nn = np.argmax(dirs @ cells.T, axis=1)
    l_nn = L[np.argmax(cells @ dirs.T, axis=1)][nn]  # value at the cell's nearest quadrature node
    # the direct L2 distance between L and its nearest-neighbour resampling on the cells
    vals = sh.basis(cells, ORDER) @ truth
    err_nn = np.sqrt((w[:, None] * (L - vals[nn]) ** 2).sum(0))
    err = np.linalg.norm(emission[0] - truth, axis=0)
    # Bessel: the SH projection of (L_nn - L) has norm <= its L2 norm; plus the stratified-projection
    # error of Y_j (tested < 5e-3 per coefficient on the constant) times the largest cell value
    assert np.all(err <= err_nn * 1.05 + 16 * 5e-3 * np.abs(vals).max(0)), (err, err_nn)


def _mc_indirect(p, n, centre, radius, truth_sh, n_samples, rng):
    u1, u2 = rng.random(n_samples), rng.random(n_samples)
    rr, ph = np.sqrt(u1), 2 * np.pi * u2
    local = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.sqrt(1 - u1)], -1)
    t = np.cross(n, [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    dirs = local @ np.stack([t, np.cross(n, t), n])
    oc = p - centre
    bq = dirs @ oc
    disc = bq * bq - (oc @ oc - radius**2)
    hit = disc > 0
    tq = -bq - np.sqrt(np.maximum(disc, 0))
    q = p + tq[:, None] * dirs
    nq = (q - centre) / radius
    f = np.pi * hit[:, None] * (sh.basis(nq, ORDER) @ truth_sh)
    return f.mean(0), f.std(0, ddof=1) / np.sqrt(n_samples)


def test_one_sphere_indirect_against_monte_carlo(rng):
    """One diffuse sphere lighting a plane (the paper's optimal case), against exact-up-to-noise MC, with the
    paper's average radiance (Eqs. 15-18).

    Derived bound per receiver (``E = L~ V~`` ours, ``E* = Lbar* V*`` the truth):
    ``|E - E*| <= (|w'| |L^c - L*| + (max_cap L* - min_cap L*)) |V~| + max_cap L* |V~ - V*|`` with
    ``|V~ - V*| <= |v - P_n(1 - B)| |rho_n| + |(I - P_n)(1 - B)|_2 |(I - P_n) rho|_2`` (Cauchy-Schwarz).
    """
    env = _env_sh()
    albedo = np.array([0.8, 0.5, 0.3])
    centre, radius = np.array([0.0, 1.0, 0.0]), 0.5
    c, r, emission = _one_sphere_light(centre, radius, albedo, env)
    conv = np.repeat(np.pi * np.array([1.0, 2.0 / 3.0, 0.25, 0.0]), 2 * np.arange(ORDER) + 1)
    truth = albedo / np.pi * conv[:, None] * env
    xs = np.array([0.0, 0.5, 1.0, 2.0])
    pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], -1)
    nrm = np.broadcast_to([0.0, 1.0, 0.0], pts.shape)
    _, ind = second_pass(pts, nrm, c, r, [0], np.zeros((1, 1), bool), np.eye(3)[None], emission, env,
                         exp_method="exact", average="paper")
    cos_n = sh.zh_rotate(sh.clamped_cosine_zh(ORDER), [0.0, 1.0, 0.0])
    # |(I - P_n) rho|_2 for the clamped cosine: |rho|^2 = 2 pi / 3
    rho_tail = np.sqrt(2 * np.pi / 3 - sh.clamped_cosine_zh(ORDER) @ sh.clamped_cosine_zh(ORDER))
    for k, p in enumerate(pts):
        ref, se = _mc_indirect(p, nrm[k], centre, radius, truth, 400_000, rng)
        d = centre - p
        dist = np.linalg.norm(d)
        theta = np.arcsin(radius / dist)
        axis = d / dist
        one_minus_b = -sh.zh_rotate(sh.blocker_zh(theta, ORDER), axis)
        one_minus_b[0] += np.sqrt(4 * np.pi)
        v_ours = sh.exp(np.zeros(16)) - sh.exp(sh.zh_rotate(sh.blocker_log_zh(theta, ORDER), axis), method="exact")
        v_tilde = v_ours @ cos_n
        cap = 2 * np.pi * (1 - np.cos(theta))
        b_tail = np.sqrt(max(cap - one_minus_b @ one_minus_b, 0.0))
        dv = np.linalg.norm(v_ours - one_minus_b) * np.linalg.norm(cos_n) + b_tail * rho_tail
        # true emission over the cap of the sphere visible from p (cos alpha > sin theta about -axis)
        sdirs = random_directions(np.random.default_rng(0), 20000)
        vis = sdirs @ (-axis) > np.sin(theta)
        lv = sh.basis(sdirs[vis], ORDER) @ truth
        spread = lv.max(0) - lv.min(0)
        w = sh.zh_rotate(w_theta_zh(theta, ORDER), -axis)
        dl = np.linalg.norm(w) * np.linalg.norm(emission[0] - truth, axis=0)
        bound = (dl + spread) * abs(v_tilde) + lv.max(0) * dv
        assert np.all(np.abs(ind[k] - ref) <= bound + MC_SIGMAS * se), (k, ind[k], ref, bound, se)


def test_errors():
    with pytest.raises(ValueError, match="blocking must be"):
        accumulate_blockers(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], [0], np.zeros((1, 1), bool), 4,
                            blocking="pixel")
    with pytest.raises(ValueError, match="method must be"):
        accumulate_blockers(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0], [0], np.zeros((1, 1), bool), 4,
                            method="gpu")
    with pytest.raises(ValueError, match="must agree in S"):
        accumulate_blockers(np.zeros((1, 3)), np.ones((1, 3)), [[0, 1, 0]], [1.0, 2.0], [0], np.zeros((1, 1), bool), 4)


@pytest.mark.parametrize("blocking,average", [("object", "cosine"), ("sphere", "cosine"), ("object", "paper")])
def test_fused_second_pass_matches_composed_tier(blocking, average, rng):
    p = rng.uniform(-2, 2, size=(60, 3))
    n = random_directions(rng, 60)
    c = rng.normal(size=(6, 3)) * 1.5
    r = rng.uniform(0.2, 0.6, 6)
    obj = np.array([0, 0, 0, 1, 2, 2])
    inter = np.zeros((6, 6), dtype=bool)
    inter[0, 1] = inter[1, 0] = True
    rot = np.stack([np.eye(3)] * 3 + [np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])] * 3)
    em = rng.normal(size=(6, 16, 3)) * 0.1
    em[:, 0] += 1.0
    env = _env_sh()
    for exp_method in ("ol", "hyb"):
        args = (p, n, c, r, obj, inter, rot, em, env)
        d1, i1 = second_pass(*args, blocking=blocking, exp_method=exp_method, method="fused", average=average)
        d2, i2 = second_pass(*args, blocking=blocking, exp_method=exp_method, method="numba", average=average)
        np.testing.assert_allclose(d1, d2, atol=1e-11)
        np.testing.assert_allclose(i1, i2, atol=1e-11)
