"""Tests of prtlab.spherelights._ground (the ground as an occluder of the first pass) and of the controlled case
of the indirect light: one diffuse sphere resting on a ground under a constant white environment."""

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import geodesic_directions
from prtlab.pipeline import FrameState
from prtlab.reference import radiance_at
from prtlab.scene import Scene
from prtlab.spherelights import (
    SphereLights,
    environment_transfer,
    first_pass,
    ground_blocked_transfer,
    ground_hidden_projection,
    ground_rectangles,
    hidden_transfer,
    second_pass,
    voronoi_cell_sums,
)
from prtlab.spherelights._ground import (UP_FRAME, _grid_directions, _grid_factors, _ground_weights,
                                        _ground_weights_reference, _lower_hemisphere_grid, ground_light, ground_raster,
                                        ground_texture)
from tests.conftest import MC_SIGMAS, random_directions
from tests.spherelights.test_tables import _sphere_irradiance_brute

ORDER = 4
WHITE = np.zeros((16, 3))
WHITE[0] = np.sqrt(4 * np.pi)  # constant radiance 1


def _scene(plane_size=6.0, albedo=0.8, translate=(0.0, 0.5, 0.0), rotate_y=0.0):
    return Scene.from_dict({"objects": [
        {"name": "plane", "mesh": {"builtin": "plane", "size": [plane_size, plane_size], "resolution": [2, 2]},
         "transform": {"rotate_deg": [0, rotate_y, 0]}, "material": {"type": "diffuse", "albedo": [0.7] * 3}},
        {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 4},
         "transform": {"translate": list(translate)}, "material": {"type": "diffuse", "albedo": [albedo] * 3},
         "dynamic": True}],
        "lights": [{"type": "environment", "constant": [1, 1, 1]}]})


def test_weight_kernel_matches_reference(rng):
    dirs, w = _lower_hemisphere_grid(32, 8)
    pts = rng.uniform(-2, 2, size=(40, 3))
    nrm = random_directions(rng, 40)
    rects = np.array([[-0.5, 0.2, -0.1, 1.5, 0.3, -0.2, 0.8], [0.3, -1.0, 0.5, 0.4, 0.0, 0.0, 0.6]])
    out = np.empty((40, dirs.shape[0]))
    _ground_weights(pts, nrm, np.ascontiguousarray(dirs), np.ascontiguousarray(w), rects, out)
    np.testing.assert_allclose(out, _ground_weights_reference(pts, nrm, dirs, w, rects), atol=1e-15)
    a = ground_blocked_transfer(pts, nrm, WHITE, rects)
    b = ground_blocked_transfer(pts, nrm, WHITE, rects, method="reference")
    np.testing.assert_allclose(a, b, atol=1e-13)


def test_grid_factors_give_the_grid_basis():
    """The azimuth and elevation factors of ``_grid_factors`` rebuild the SH basis at the grid's directions in the
    ground's frame (``UP_FRAME``) to rounding."""
    phi0 = 0.37
    t, e, groups = _grid_factors(13, 32, 8, phi0)
    dirs, _ = _grid_directions(phi0, 32, 8)
    y = sh.basis(dirs @ UP_FRAME.T, 13).reshape(8, 32, -1)
    col = np.empty(169, dtype=np.int64)
    for c, ls in enumerate(groups):
        col[ls] = c
    np.testing.assert_allclose(e[:, None, :] * t[None, :, col], y, rtol=0, atol=1e-14)


@pytest.mark.parametrize("n_env", [1, 4, 10])
def test_hidden_projection_gives_the_grids_sum(rng, n_env):
    """The hidden transfer through the points' projection (``ground_hidden_projection``, then ``hidden_transfer``) is
    the grid's sum ``W @ A`` of the numpy reference, for skies up to the pipeline's order (10 for order 4): within
    ``1e-13`` of the largest coefficient, the rounding of sums of a few thousand terms of size one (a projection
    too short for the sky is refused)."""
    pts = rng.uniform(-2, 2, size=(40, 3))
    nrm = random_directions(rng, 40)
    rects = np.array([[-0.5, 0.2, -0.1, 1.5, 0.3, -0.2, 0.8], [0.3, -1.0, 0.5, 0.4, 0.0, 0.0, 0.6]])
    env = rng.normal(size=(n_env * n_env, 3))
    ref = ground_blocked_transfer(pts, nrm, env, rects, order=4, method="reference", n_azimuth=64, n_elevation=16)
    v = ground_hidden_projection(pts, nrm, rects, 4 + n_env - 1, n_azimuth=64, n_elevation=16)
    np.testing.assert_allclose(hidden_transfer(v, env, 4), ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    np.testing.assert_allclose(ground_blocked_transfer(pts, nrm, env, rects, order=4, n_azimuth=64, n_elevation=16),
                               ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    with pytest.raises(ValueError, match="needs order"):
        hidden_transfer(v[:, : (3 + n_env - 1) ** 2], env, 4)
    with pytest.raises(ValueError, match="n_azimuth"):
        ground_hidden_projection(pts, nrm, rects, 33, n_azimuth=64)


def test_blocked_transfer_in_blocks_of_rows(rng, monkeypatch):
    """The weights in blocks of rows (7 points a block here, the last one short) give the product of the whole
    weight matrix."""
    import prtlab.spherelights._ground as ground

    pts = rng.uniform(-2, 2, size=(40, 3))
    nrm = random_directions(rng, 40)
    rects = np.array([[-0.5, 0.2, -0.1, 1.5, 0.3, -0.2, 0.8]])
    env = rng.normal(size=(16, 3))
    whole = ground_blocked_transfer(pts, nrm, env, rects, n_azimuth=32, n_elevation=8)
    monkeypatch.setattr(ground, "_WEIGHT_BLOCK_BYTES", 7 * 8 * 32 * 8)
    np.testing.assert_allclose(ground_blocked_transfer(pts, nrm, env, rects, n_azimuth=32, n_elevation=8), whole,
                               rtol=1e-13, atol=1e-15)


def test_infinite_ground_leaves_the_sky_view_factor():
    """Under a constant sky with an infinite ground, a point sees E = pi (1 + n_y) / 2 (closed form). The product
    rule's error comes from the kink of the clamped cosine (the ground's edge is the horizon, a node-free end)."""
    n = random_directions(np.random.default_rng(5), 30)
    p = np.tile([0.0, 1.0, 0.0], (30, 1))
    huge = [[0.0, 0.0, 0.0, 1e6, 0.0, 0.0, 1e6]]
    t = environment_transfer(n, WHITE) - ground_blocked_transfer(p, n, WHITE, huge)
    e = t[:, 0, 0] * np.sqrt(4 * np.pi)
    fine = environment_transfer(n, WHITE) - ground_blocked_transfer(p, n, WHITE, huge, n_azimuth=512, n_elevation=128)
    quad = np.abs(e - fine[:, 0, 0] * np.sqrt(4 * np.pi))  # the refinement estimate of the rule's error
    np.testing.assert_array_less(np.abs(e - np.pi * (1 + n[:, 1]) / 2), 2 * quad + 1e-12)
    assert np.all(quad < 2e-3 * np.pi)


def test_first_pass_samples_with_the_ground_against_monte_carlo():
    """Stage (a): the radiance of the surface samples of a sphere resting on a finite (6 x 6) ground, against the own
    Monte Carlo of the same scene. The sphere's own light is culled at its samples, so E = T_q . e_0 exactly up to
    the ground quadrature (bounded by its refinement)."""
    sc = _scene()
    pre = SphereLights.precompute(sc, {"n_spheres": 1, "fit_resolution": 16}, cache=False, progress=False)
    c, r, so, inter, rot, spts, snrm, sval, albsh = pre.world_lights(FrameState.from_scene(sc))
    sel = np.nonzero(sval[0])[0][::3]
    p, n = spts[0, sel], snrm[0, sel]
    rect = ground_rectangles([sc.object("plane")])
    e = (environment_transfer(n, WHITE) - ground_blocked_transfer(p, n, WHITE, rect))[:, 0, 0] * np.sqrt(4 * np.pi)
    fine = (environment_transfer(n, WHITE)
            - ground_blocked_transfer(p, n, WHITE, rect, n_azimuth=512, n_elevation=128))[:, 0, 0] * np.sqrt(4 * np.pi)
    mc = radiance_at(sc, p + 1e-4 * n, n, n, 2000, np.random.default_rng(11))
    err = np.abs(e / np.pi - mc.direct[:, 0])
    # the faceted mesh hides grazing directions that the smooth sphere leaves open: within delta of the tangent
    # plane (delta the largest angle between a vertex normal and its faces' normals), projected solid angle
    # pi sin^2(2 delta) at most, radiance sin^2(2 delta) under a white sky
    mesh = sc.object("ball").mesh
    fn = np.asarray(mesh.face_normals)[np.asarray(mesh.vertex_faces)]
    dev = np.einsum("vj,vfj->vf", np.asarray(mesh.vertex_normals), fn)[np.asarray(mesh.vertex_faces) >= 0]
    facets = np.sin(2 * np.arccos(np.clip(dev.min(), -1, 1))) ** 2
    np.testing.assert_array_less(err, MC_SIGMAS * mc.direct_stderr[:, 0] + 2 * np.abs(e - fine) / np.pi + facets)
    # and the paper's first pass (no ground) over-lights the lower samples
    low = n[:, 1] < -0.5
    assert np.all(environment_transfer(n[low], WHITE)[:, 0, 0] * np.sqrt(4 * np.pi) / np.pi
                  > mc.direct[low, 0] + MC_SIGMAS * mc.direct_stderr[low, 0])


def _l2_weight(centre, radius, p, n, n_alpha=300, n_phi=300):
    """|| W_n ||_2 over the light's sphere: W_n(u) = max(0, n.w) r^2 cos(gamma) / d^2 on the visible part."""
    d_vec = p - centre
    dist = np.linalg.norm(d_vec)
    b, s = d_vec / dist, radius / dist
    t, wt = np.polynomial.legendre.leggauss(n_alpha)
    t, wt = s + (1 - s) * 0.5 * (t + 1), wt * 0.5 * (1 - s)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    e1 = np.cross(b, [1.0, 0, 0] if abs(b[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(b, e1)
    st = np.sqrt(1 - t * t)
    u = (t[:, None, None] * b + st[:, None, None] * (np.cos(phi)[None, :, None] * e1
                                                        + np.sin(phi)[None, :, None] * e2)).reshape(-1, 3)
    w = (wt[:, None] * np.full(n_phi, 2 * np.pi / n_phi)).reshape(-1)
    v = centre + radius * u - p
    d = np.linalg.norm(v, axis=1)
    om = v / d[:, None]
    f = np.maximum(np.einsum("ij,ij->i", u, -om), 0) * radius**2 / d**2 * np.maximum(om @ n, 0)
    return np.sqrt(w @ (f * f))


def test_first_pass_takes_a_kept_ground_projection(rng):
    """``first_pass`` given the valid samples' ``ground_hidden_projection`` (as ``SphereLights`` keeps it) gives the
    emission it makes itself, to rounding; a projection with another number of rows is refused."""
    sc = _scene()
    pre = SphereLights.precompute(sc, {"n_spheres": 1, "fit_resolution": 16}, cache=False, progress=False)
    c, r, so, inter, rot, spts, snrm, sval, albsh = pre.world_lights(FrameState.from_scene(sc))
    rect = ground_rectangles([sc.object("plane")])
    env = rng.normal(size=(100, 3)) * 0.1
    env[0] += 2.0
    nrm = snrm[sval] / np.linalg.norm(snrm[sval], axis=1, keepdims=True)
    v = ground_hidden_projection(spts[sval], nrm, rect, ORDER + 10 - 1)
    args = (spts, snrm, sval, c, r, env, voronoi_cell_sums(ORDER), albsh[:, :16])
    made = first_pass(*args, ground=rect, order=ORDER)
    kept = first_pass(*args, ground=rect, order=ORDER, ground_projection=v)
    np.testing.assert_allclose(kept, made, rtol=0, atol=1e-13 * np.abs(made).max())
    with pytest.raises(ValueError, match="a row per valid sample"):
        first_pass(*args, ground=rect, order=ORDER, ground_projection=v[1:])


def test_one_sphere_on_an_infinite_ground_against_closed_form():
    """Stages (b)-(d) in one closed-form chain: a sphere resting on an infinite ground under a white sky has the exit
    radiance L*(u) = a (1 + u_y) / 2 (band-limited, order 2). The first pass must project it (Eq. 10) to the right
    constant and gradient, and the ground's indirect irradiance (cosine average, exact exp) must equal
    int L* W_n up to ||L^c - L*||_2 ||W_n||_2 (Cauchy-Schwarz over the light's sphere) plus the sample-radiance
    quadrature error (bounded by its refinement, times int W_n)."""
    alb = 0.8
    sc = _scene(plane_size=2e6, albedo=alb)
    pre = SphereLights.precompute(sc, {"n_spheres": 1, "fit_resolution": 16, "emission_order": 0}, cache=False,
                                  progress=False)  # the emission at ORDER, as the truth
    c, r, so, inter, rot, spts, snrm, sval, albsh = pre.world_lights(FrameState.from_scene(sc))
    rect = ground_rectangles([sc.object("plane")])
    em = first_pass(spts, snrm, sval, c, r, WHITE, voronoi_cell_sums(ORDER), albsh, exp_method="exact", ground=rect)
    truth = np.zeros(16)
    truth[0], truth[2 - 1] = alb * np.sqrt(4 * np.pi) / 2, alb / 2 * np.sqrt(4 * np.pi / 3)  # a/2 (1 + y)
    centre, radius = c[0], r[0]
    np.testing.assert_allclose(centre, [0, 0.5, 0], atol=1e-9)
    np.testing.assert_allclose(em[0, :2, 0], truth[:2], rtol=0.03)  # (b) normalisation: DC and y gradient
    # sample-radiance quadrature error, bounded by refinement
    pv, nv = spts[0][sval[0]], snrm[0][sval[0]]
    e1 = ground_blocked_transfer(pv, nv, WHITE, rect)[:, 0, 0]
    e2 = ground_blocked_transfer(pv, nv, WHITE, rect, n_azimuth=512, n_elevation=128)[:, 0, 0]
    quad = 2 * alb * np.abs(e1 - e2).max() * np.sqrt(4 * np.pi) / np.pi
    xs = np.array([0.55, 0.8, 1.2, 2.0, 3.0])
    pts = np.stack([xs, np.zeros_like(xs), 0.2 * xs], -1)
    nrm = np.tile([0.0, 1.0, 0.0], (len(xs), 1))
    _, ind = second_pass(pts, nrm, c, r, so, inter, rot, em, WHITE, exp_method="exact", method="numba")
    err_l = np.linalg.norm(em[0, :, 0] - truth)
    refs, bounds = [], []
    for k, p in enumerate(pts):
        ref = _sphere_irradiance_brute(truth, centre, radius, p, nrm[k])
        total_w = _sphere_irradiance_brute(np.eye(16)[0] * np.sqrt(4 * np.pi), centre, radius, p, nrm[k])
        bound = err_l * _l2_weight(centre, radius, p, nrm[k]) + quad * total_w
        assert abs(ind[k, 0] - ref) <= bound, (k, ind[k, 0], ref, bound)
        refs.append(ref)
        bounds.append(bound)
    # the paper's average radiance (Eqs. 15-18) misses the brute-force value by more than the bound near the sphere
    _, ind_paper = second_pass(pts, nrm, c, r, so, inter, rot, em, WHITE, exp_method="exact", average="paper")
    assert abs(ind_paper[1, 0] - refs[1]) > bounds[1], (ind_paper[1, 0], refs[1], bounds[1])


# --------------------------------------------------------------------------- the ground in the second pass


def _ground_light_brute(p, n, rects, tex, env, centres, radii, local, n_az=720, n_el=360):
    """numpy rule of the same integrals over a fixed product grid of the lower hemisphere (midpoint in azimuth,
    Gauss-Legendre in elevation), independent of the per-azimuth intervals: ray-sphere tests against the adjusted
    lights, bilinear texture lookup, the environment from its SH."""
    from prtlab.spherelights import adjust_blockers

    dirs, w = _lower_hemisphere_grid(n_az, n_el)
    env_w = sh.basis(dirs, int(np.sqrt(env.shape[0]))) @ env
    hidden, reflected = np.zeros((len(p), 3)), np.zeros((len(p), 3))
    ca, ra = adjust_blockers(p, n, centres, radii) if len(radii) else (np.zeros((len(p), 0, 3)), np.zeros((len(p), 0)))
    for q in range(len(p)):
        cos = np.maximum(dirs @ n[q], 0.0)
        for g, (y0, cx, cz, ux, uz, vx, vz) in enumerate(rects):
            h = p[q, 1] - y0
            if h <= 0:
                continue
            t = h / -dirs[:, 1]
            x = p[q] + t[:, None] * dirs
            a = ((x[:, 0] - cx) * ux + (x[:, 2] - cz) * uz) / (ux * ux + uz * uz)
            b = ((x[:, 0] - cx) * vx + (x[:, 2] - cz) * vz) / (vx * vx + vz * vz)
            hit = (np.abs(a) <= 1) & (np.abs(b) <= 1) & (cos > 0)
            blocked = np.zeros(len(dirs), bool)
            beyond = np.full(len(dirs), -1)
            t_beyond = np.full(len(dirs), np.inf)
            for s in range(len(radii)):
                if ra[q, s] <= 0:
                    continue
                o = ca[q, s] - p[q]
                bb = dirs @ o
                disc = bb * bb - (o @ o - ra[q, s] ** 2)
                ok = (bb > 0) & (disc > 0)
                th = np.where(ok, bb - np.sqrt(np.maximum(disc, 0)), np.inf)
                blocked |= th < t
                if not np.isnan(local[s]).any():
                    closer = (th >= t) & (th < t_beyond)
                    beyond[closer], t_beyond[closer] = s, th[closer]
            open_ = hit & ~blocked
            lg = np.where((beyond >= 0)[:, None], np.nan_to_num(local)[np.maximum(beyond, 0)], env_w)
            wt = (w * cos)[open_]
            hidden[q] += wt @ lg[open_]
            r = tex.shape[1]
            fx = np.clip(0.5 * (a[open_] + 1) * r - 0.5, 0, r - 1)
            fy = np.clip(0.5 * (b[open_] + 1) * r - 0.5, 0, r - 1)
            i, j = np.minimum(fx.astype(int), r - 2), np.minimum(fy.astype(int), r - 2)
            sx, sy = (fx - i)[:, None], (fy - j)[:, None]
            val = ((1 - sx) * (1 - sy) * tex[g, i, j] + sx * (1 - sy) * tex[g, i + 1, j]
                   + (1 - sx) * sy * tex[g, i, j + 1] + sx * sy * tex[g, i + 1, j + 1])
            reflected[q] += wt @ val
    return hidden, reflected


def test_ground_light_under_a_white_sky_over_an_infinite_ground():
    """Closed form: over an infinite ground, a point with normal n sees it in pi (1 - n_y) / 2 of its projected
    solid angle; with the ground's radiance 1 both integrals are that. The rule's error is the azimuth sum's
    (the elevation intervals are exact), bounded by its refinement."""
    rng = np.random.default_rng(3)
    n = random_directions(rng, 40)
    p = np.tile([0.0, 1.0, 0.0], (40, 1))
    huge = [[0.0, 0.0, 0.0, 1e6, 0.0, 0.0, 1e6]]
    tex = np.ones((1, 2, 2, 3))
    hidden, reflected = ground_light(p, n, huge, tex, WHITE)
    fine, _ = ground_light(p, n, huge, tex, WHITE, n_azimuth=256, n_elevation=16)
    exact = np.pi * (1 - n[:, 1]) / 2
    band = 2 * np.pi * 1e-6  # the sky band between the horizon and the edge of the 1e6 ground, atan(1e-6) deep
    np.testing.assert_array_less(np.abs(hidden[:, 0] - exact), 2 * np.abs(hidden[:, 0] - fine[:, 0]) + band)
    assert np.abs(hidden[:, 0] - exact).max() < 2e-3 * np.pi  # 0.2 % of the whole sky's irradiance
    np.testing.assert_allclose(reflected, hidden)
    # below the ground, or on it looking up: nothing
    h, r = ground_light([[0, -1.0, 0], [0, 0.0, 0]], [[0, -1.0, 0], [0, 1.0, 0]], huge, tex, WHITE)
    assert not h.any() and not r.any()


def test_ground_light_hidden_environment_matches_the_product_grid_rule():
    """Finite rectangles under a non-constant sky: the hidden environment is the DC term of the first pass's
    ``ground_blocked_transfer`` (another rule: a fixed product grid), both refined until their difference is
    within the sum of their refinement estimates."""
    rng = np.random.default_rng(4)
    env = np.zeros((100, 3))
    env[0] = 2 * np.sqrt(4 * np.pi)
    env[1:] = 0.3 * rng.normal(size=(99, 3))
    n = random_directions(rng, 20)
    p = rng.uniform([-2, 0.1, -2], [2, 2, 2], size=(20, 3))
    rects = np.array([[0.0, 0.3, -0.2, 1.5, 0.4, -0.4, 1.5]])
    ours, _ = ground_light(p, n, rects, np.zeros((1, 2, 2, 3)), env)
    ours_fine, _ = ground_light(p, n, rects, np.zeros((1, 2, 2, 3)), env, n_azimuth=128, n_elevation=16)
    grid = ground_blocked_transfer(p, n, env, rects, order=1)[:, 0] * np.sqrt(4 * np.pi)
    grid_fine = ground_blocked_transfer(p, n, env, rects, order=1, n_azimuth=1024, n_elevation=256)[:, 0] * np.sqrt(
        4 * np.pi)
    bound = np.abs(ours - ours_fine) + np.abs(grid - grid_fine) + 1e-9
    np.testing.assert_array_less(np.abs(ours_fine - grid_fine), 2 * bound)
    assert np.abs(ours - grid_fine).max() < 0.01 * np.abs(grid_fine).max()


def test_ground_light_with_blockers_and_a_local_light_against_a_brute_force_rule():
    """Lights between receiver and ground block (ray tests against the lights adjusted as in the second pass), a
    local light below the ground is seen beyond it (its radiance, not the sky's, is hidden), and the reflected light
    reads the texture where the ray meets the ground: against a dense product-grid rule in numpy."""
    rng = np.random.default_rng(5)
    env = np.zeros((16, 3))
    env[0] = np.sqrt(4 * np.pi) * np.array([1.0, 0.8, 0.6])
    env[2] = [0.5, 0.4, 0.3]
    rects = np.array([[0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.5]])
    tex = rng.uniform(0, 1, size=(1, 8, 8, 3))
    centres = np.array([[0.4, 0.3, 0.0], [-0.5, 0.6, 0.3], [0.0, -0.8, 0.2]])
    radii = np.array([0.3, 0.25, 0.4])
    local = np.array([[np.nan] * 3, [np.nan] * 3, [5.0, 4.0, 3.0]])
    p = np.array([[0.0, 0.8, 0.0], [0.9, 0.3, 0.1], [-0.2, 1.5, -0.6], [0.4, 0.7, 0.0]])
    n = np.array([[0.0, -1.0, 0.0], [0.3, -0.5, 0.2], [-0.1, 0.2, 0.9], [0.0, 1.0, 0.0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ours = ground_light(p, n, rects, tex, env, centres, radii, local, n_azimuth=256, n_elevation=32)
    coarse = ground_light(p, n, rects, tex, env, centres, radii, local)
    brute = _ground_light_brute(p, n, rects, tex, env, centres, radii, local)
    for a, b, c in zip(ours, brute, coarse):
        # both rules err at the lights' silhouettes (steps): the fine rule within 2 % of the brute one, the default
        # within that plus twice its refinement estimate
        np.testing.assert_allclose(a, b, rtol=0.02, atol=2e-3)
        np.testing.assert_array_less(np.abs(c - b), 2 * np.abs(c - a) + 0.02 * np.abs(b) + 2e-3)
    assert ours[0][0, 0] > 0 and np.any(ours[0] != ground_light(p, n, rects, tex, env, centres, radii)[0])


def test_elevation_spans_are_the_rays_that_meet_the_rectangle_in_front(rng):
    """``_elevation_span`` (selects, no branch) against the rays themselves: inside a non-empty interval every ray
    meets the rectangle in front of the tangent plane; just outside it, or anywhere in an empty one, none does.
    Normals horizontal (``n_y = 0``), straight down and up, receivers over edges and corners and beside the
    rectangle, and azimuths parallel to an edge pair (the slab's divisor 0), called outside a parallel loop (no
    division by zero under numba's Python error model)."""
    from prtlab.spherelights._ground import _elevation_span, _rect_coordinates, ground_quadrature

    quad = ground_quadrature(24, 6, 0.0)
    c, s = quad.cos_az[0], quad.sin_az[0]
    rects = np.array([[0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 3.0], [-0.3, 1.0, 0.5, 2 * c, 2 * s, -2 * s, 2 * c]])
    pts = np.concatenate([rng.uniform(-4.5, 4.5, (150, 3)) * [1, 0, 1] + [0, 0, 0],
                          [[3.0, 0, 0.0], [-3.0, 0, 3.0], [1.0 + 2 * c, 0, 0.5 + 2 * s], [0.0, 0, 0.0]]])
    heights = rng.uniform(0.05, 1.5, len(pts))
    normals = random_directions(rng, len(pts))
    normals[:30, 1] = 0.0
    normals[:30] /= np.linalg.norm(normals[:30], axis=1, keepdims=True)
    normals[30:40], normals[40:45] = [0.0, -1.0, 0.0], [0.0, 1.0, 0.0]
    flat = inside = empty = 0
    for rect in rects:
        for p, h, n in zip(pts, heights, normals):
            coords = _rect_coordinates(p[0], p[2], rect)
            for ux, uz in zip(quad.cos_az, quad.sin_az):
                flat += (ux * rect[3] + uz * rect[4]) == 0.0 or (ux * rect[5] + uz * rect[6]) == 0.0
                lo, hi = _elevation_span(coords, h, *n, ux, uz, rect)

                def meets(e, tol):  # the ray at elevation e hits the rectangle in front of the tangent plane
                    w = np.array([np.cos(e) * ux, -np.sin(e), np.cos(e) * uz])
                    x = p[[0, 2]] + h / np.sin(e) * w[[0, 2]] - rect[1:3]
                    a = x @ rect[3:5] / (rect[3:5] @ rect[3:5])
                    b = x @ rect[5:7] / (rect[5:7] @ rect[5:7])
                    return max(abs(a), abs(b)) < 1 + tol and n @ w > -tol

                if lo < hi:
                    inside += 1
                    assert 0.0 <= lo and hi <= np.pi / 2
                    assert all(meets(lo + f * (hi - lo), 1e-9) for f in (1e-6, 0.5, 1 - 1e-6))
                    outside = [e for e in (lo - 1e-3, hi + 1e-3) if 1e-3 < e < np.pi / 2 - 1e-3]
                    assert not any(meets(e, -1e-6) for e in outside)
                else:
                    empty += 1
                    assert not any(meets(e, -1e-6) for e in np.linspace(1e-3, np.pi / 2 - 1e-3, 64))
    assert flat > 0 and inside > 500 and empty > 500


def test_ground_texture_interpolates_the_mesh_linearly():
    """A per-vertex value linear in position gives, at every texel centre, that linear function (barycentric
    interpolation is exact for it), whatever the triangulation."""
    from prtlab.geometry import builtin_mesh

    mesh = builtin_mesh("plane", size=[3.0, 2.0], resolution=[5, 3])
    v = np.asarray(mesh.vertices)
    value = np.stack([v[:, 0], v[:, 2], 1 + 0 * v[:, 0]], -1)
    tex = ground_texture(ground_raster(mesh, 16), value)
    lo, hi = v.min(axis=0), v.max(axis=0)
    flat = int(np.argmin(hi - lo))
    a1, a2 = [k for k in range(3) if k != flat]
    c = (np.arange(16) + 0.5) / 16
    np.testing.assert_allclose(tex[:, :, 0], (lo[a1] + c * (hi - lo)[a1])[:, None] * np.ones(16), atol=1e-12)
    np.testing.assert_allclose(tex[:, :, 1], np.ones(16)[:, None] * (lo[a2] + c * (hi - lo)[a2]), atol=1e-12)
    np.testing.assert_allclose(tex[:, :, 2], 1.0)


def test_errors():
    with pytest.raises(ValueError, match="method must be"):
        ground_blocked_transfer(np.zeros((1, 3)), np.ones((1, 3)), WHITE, np.zeros((1, 7)), method="gpu")
    with pytest.raises(ValueError, match="average must be"):
        second_pass(np.zeros((1, 3)), np.ones((1, 3)), np.zeros((1, 3)), [1.0], [0], np.zeros((1, 1), bool),
                    np.eye(3)[None], np.zeros((1, 16, 3)), WHITE, average="mean")
    assert ground_blocked_transfer(np.zeros((0, 3)), np.zeros((0, 3)), WHITE, np.zeros((1, 7))).shape == (0, 16, 3)
    h, r = ground_light(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((1, 7)), np.zeros((1, 2, 2, 3)), WHITE)
    assert h.shape == r.shape == (0, 3)
    rect = [[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]]
    with pytest.raises(ValueError, match=r"textures must have shape \(G, R, R, 3\) with G = 1 rectangles"):
        ground_light([[0, 1.0, 0]], [[0, -1.0, 0]], rect, np.zeros((2, 2, 2, 3)), WHITE)
    with pytest.raises(ValueError, match="n_azimuth must be an int >= 1"):
        ground_light([[0, 1.0, 0]], [[0, -1.0, 0]], rect, np.zeros((1, 2, 2, 3)), WHITE, n_azimuth=0)
    with pytest.raises(TypeError, match="n_elevation must be an int"):
        ground_light([[0, 1.0, 0]], [[0, -1.0, 0]], rect, np.zeros((1, 2, 2, 3)), WHITE, n_elevation=2.0)
    assert geodesic_directions(92).shape == (92, 3)
    _ = sh  # noqa
