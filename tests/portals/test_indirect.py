"""Indirect light of a simple box room with a window, against prtlab.reference.

The photon density estimate at a vertex (Christensen 1999: the ``k`` nearest photons over the disc of their
radius ``r``) had two biases that follow from its geometry: **disc truncation** (on a wall's edge the photons come
from the part ``f`` of the disc on the wall, 1/2, in a corner 1/4, but the whole disc divided them) and **the k-th
neighbour** (``E[k / (pi r_k^2)] = lambda k / (k - 1)``). :func:`radiance_estimate` now sums the ``k - 1`` photons
inside the ``k``-th one's radius and divides by the disc's part on the surface (``surface=``); the closed form of a
uniform photon density on a square checks both (edges and corners included), and the box room's gathered indirect
light must then agree with the reference within the noise of both.

The final gather is linear in the vertex exitance, so one gather of several exitance columns (with the same rays)
gives ours ``T(B)`` and the photon-map noise: ``T(sigma s)`` for random signs ``s`` has ``E[T(sigma s)^2] = sum_v
a_v^2 sigma_v^2`` (independent vertices: their discs do not overlap at these photon counts), with ``sigma_v`` the
compound-Poisson standard deviation of vertex ``v``'s estimate. The gather's own noise is the spread of independent
gathers of the same total ray count.
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from prtlab.geometry import RayCaster
from prtlab.portals import final_gather, find_portals, radiance_estimate, trace_photons
from prtlab.portals._indirect import _NORMAL_AGREEMENT
from prtlab.reference import radiance_at

from ..conftest import MC_SIGMAS

POINTS = np.array([[0.3, 0.0, 0.5], [1.5, 1.0, 0.2], [0.0, 2.5, 0.5], [-0.5, 0.0, -1.0], [0.2, 1.2, 1.5]])
NORMALS = np.array([[0, 1.0, 0], [-1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1]])
PHOTON_K = 32
N_SIGNS = 16     # random-sign columns for the photon-map noise
N_GATHERS = 16   # independent gathers (same total rays) for the gather noise


def _sunflower(n):
    """``n`` points spread evenly over the unit disc (Vogel's spiral)."""
    i = np.arange(n) + 0.5
    r, a = np.sqrt(i / n), i * np.pi * (3 - np.sqrt(5))
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def _estimate_terms(photons, scene, k=PHOTON_K):
    """Per room vertex: the fraction ``f`` of its estimate's disc that lies on its wall, the number ``k_v`` of
    photons it uses, and the relative standard deviation of its estimate (compound Poisson: ``sqrt(sum Phi^2) / sum
    Phi`` over those photons), with the estimator's own neighbour rule (among the ``4 k`` nearest, those whose
    normals agree; the radius is the distance of the ``k``-th of them, or of the last one near a corner)."""
    room, window = scene.objects[0], scene.objects[1]
    verts, normals = room.world_vertices(), room.world_normals()
    lo, hi = verts.min(0), verts.max(0)
    wlo, whi = window.world_vertices().min(0), window.world_vertices().max(0)
    dist, idx = cKDTree(photons.position, balanced_tree=False, compact_nodes=False).query(verts, 4 * k)
    ok = np.einsum("vqk,vk->vq", photons.normal[idx], normals) > _NORMAL_AGREEMENT
    rank = np.cumsum(ok, axis=1)
    k_v = np.minimum(k, rank[:, -1])
    radius = dist[np.arange(len(verts)), np.argmax(rank >= np.maximum(k_v, 1)[:, None], axis=1)]
    phi = np.where(ok & (rank <= k), photons.throughput[idx][..., 0], 0.0)
    total = phi.sum(1)
    rel_sd = np.sqrt((phi**2).sum(1)) / np.where(total > 0, total, 1.0)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    d = _sunflower(512)
    p = verts[:, None] + radius[:, None, None] * (d[None, :, :1] * t1[:, None] + d[None, :, 1:] * t2[:, None])
    eps = 1e-9
    on_box = np.all((p >= lo - eps) & (p <= hi + eps), axis=-1)
    in_window = np.all((p > wlo - eps) & (p < whi + eps), axis=-1)
    return (on_box & ~in_window).mean(1), k_v, rel_sd


def _columns(x, terms, seed=0):
    """Columns ``[x, x / f * (k_v - 1) / k_v, x rel_sd s_1 .. x rel_sd s_N_SIGNS]`` of a vertex estimate ``x`` of
    shape ``(V, ..., 1, 3)`` (its SH axis of length 1 becomes the column axis): ours, ours with the derived biases
    removed, and the photon noise under random signs ``s`` (the same signs for every estimate of one photon map).
    A vertex with fewer than two photons (a wall no light of that bounce reaches) keeps its estimate."""
    f, k_v, rel_sd = terms
    excess = 1.0  # the estimator is unbiased now (surface coverage, k - 1 photons): nothing to remove
    f = np.ones_like(f)
    signs = np.random.default_rng(seed).choice([-1.0, 1.0], size=(len(x), N_SIGNS))
    w = np.concatenate([np.ones((len(x), 1)), (excess / f)[:, None], signs * rel_sd[:, None]], axis=1)
    return x * w.reshape((len(x),) + (1,) * (x.ndim - 3) + (w.shape[1], 1))


def _gathered(columns):
    """From ``(N_GATHERS, P, 2 + N_SIGNS, 3)`` independent gathers of the columns: ours, ours with the derived
    biases removed, the gather's standard error and the photon map's standard error, each ``(P, 3)``."""
    mean = columns.mean(0)
    se_gather = columns[:, :, 0].std(0, ddof=1) / np.sqrt(len(columns))
    se_photons = np.sqrt((mean[:, 2:] ** 2).mean(1))
    return mean[:, 0], mean[:, 1], se_gather, se_photons


def _indirect(scene, bounces, n_photons, seed):
    room = scene.objects[0]
    caster = RayCaster(scene)
    (portal,) = find_portals(scene)
    albedo = np.array([room.material.albedo])
    rng = np.random.default_rng(seed)
    photons = trace_photons(caster, albedo, portal, n_photons, bounces, rng)
    verts, normals = room.world_vertices(), room.world_normals()
    n = len(verts)
    exitance = radiance_estimate(photons, verts, normals, np.tile(albedo, (n, 1)), 1, k=PHOTON_K,
                                 surface=(caster, np.zeros(n, np.int64)))
    columns = _columns(exitance, _estimate_terms(photons, scene))
    gathers = np.array([final_gather(caster, POINTS, NORMALS, np.tile(albedo, (len(POINTS), 1)), columns,
                                     np.array([0, n]), room.world_normals(), 16384 // N_GATHERS, rng)
                        for _ in range(N_GATHERS)])
    c00 = np.sqrt(4 * np.pi)  # constant sky L = 1: c_00 = sqrt(4 pi)
    return tuple(x * c00 for x in _gathered(gathers))


@pytest.mark.parametrize("bounces", [2])
def test_box_indirect_against_reference(constant_box, bounces):
    """Ours (edge-corrected estimates) agrees with the reference within the noise of both (in quadrature)."""
    ours, corrected, se_gather, se_photons = _indirect(constant_box, bounces, 1_000_000, 11)
    ref = radiance_at(constant_box, POINTS, NORMALS, NORMALS, 1 << 16, np.random.default_rng(7), bounces=bounces,
                      material=constant_box.objects[0].material)
    noise = MC_SIGMAS * np.sqrt(ref.indirect_stderr**2 + se_gather**2 + se_photons**2)
    assert np.all(np.abs(corrected - ref.indirect) <= noise), (corrected, ref.indirect, noise)
    assert np.all(np.abs(ours - ref.indirect) <= noise + np.abs(corrected - ours)), (ours, ref.indirect, noise)


def test_photon_map_records(constant_box):
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    photons = trace_photons(caster, np.array([[0.5, 0.5, 0.5]]), portal, 2000, 3, np.random.default_rng(0))
    assert set(np.unique(photons.depth)) == {0, 1, 2}
    first = photons.depth == 0
    # every photon enters: none is backward-occluded in an empty exterior, all hit the closed room
    assert first.sum() == 2000
    np.testing.assert_allclose(photons.throughput[first], portal.area * np.pi / 2000)
    np.testing.assert_allclose(photons.throughput[photons.depth == 2], 0.25 * portal.area * np.pi / 2000)
    assert np.all(photons.emit_dir[:, 2] < 0)  # light comes from outside, through the -z wall
    with pytest.raises(ValueError, match="n_photons"):
        trace_photons(caster, np.ones((1, 3)), portal, 0, 1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="bounces must be an int >= 1"):
        trace_photons(caster, np.ones((1, 3)), portal, 10, 0, np.random.default_rng(0))


def test_sh_response_is_one_trace_for_all_bases(constant_box):
    """The order-n estimate's band-0 coefficient equals the order-1 estimate (same photons)."""
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    photons = trace_photons(caster, np.array([[0.7] * 3]), portal, 5000, 1, np.random.default_rng(0))
    room = constant_box.objects[0]
    v, n = room.world_vertices(), room.world_normals()
    alb = np.full((len(v), 3), 0.7)
    e1 = radiance_estimate(photons, v, n, alb, 1)
    e4 = radiance_estimate(photons, v, n, alb, 4)
    np.testing.assert_allclose(e4[:, :1], e1, rtol=1e-12)
    assert e4.shape == (len(v), 16, 3)


def test_radiance_estimate_split_by_depth(constant_box):
    """The per-bounce estimates (same neighbours and radius) sum to the undivided estimate."""
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    photons = trace_photons(caster, np.array([[0.7] * 3]), portal, 5000, 3, np.random.default_rng(1))
    room = constant_box.objects[0]
    v, n = room.world_vertices(), room.world_normals()
    alb = np.full((len(v), 3), 0.7)
    split = radiance_estimate(photons, v, n, alb, 2, depths=3)
    assert split.shape == (len(v), 3, 4, 3)
    np.testing.assert_allclose(split.sum(1), radiance_estimate(photons, v, n, alb, 2), rtol=1e-12, atol=1e-15)
    assert np.all(split[:, 2, 0] >= 0) and split[:, 2, 0].max() > 0


def test_radiance_estimate_path_halves(constant_box):
    """``halves``: the main estimate unchanged, and ``E_a - E_b`` of two halves of the photon paths (a path's
    photons in one half at every depth) bounded by the estimate's sum of absolute contributions; over the vertices
    its mean square matches the spread of the estimate between photon seeds (a one-sample standard error), within
    the two figures' sampling error (4 SD of ~a 100-vertex chi-square mean: 0.6-1.6)."""
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    room = constant_box.objects[0]
    v, n = room.world_vertices(), room.world_normals()
    alb = np.full((len(v), 3), 0.7)
    runs = [radiance_estimate(trace_photons(caster, alb[:1], portal, 5000, 3, np.random.default_rng(s)), v, n, alb,
                              2, depths=3, halves=True) for s in range(6)]
    plain = radiance_estimate(trace_photons(caster, alb[:1], portal, 5000, 3, np.random.default_rng(0)), v, n, alb,
                              2, depths=3)
    np.testing.assert_array_equal(runs[0][0], plain)
    assert runs[0][1].shape == plain.shape
    band0 = np.stack([r[0][:, :, 0, 0].sum(1) for r in runs])
    reported = np.mean([np.mean(r[1][:, :, 0, 0].sum(1) ** 2) for r in runs])
    spread = np.mean(band0.var(axis=0, ddof=1))
    assert 0.6 < reported / spread < 1.6, (reported, spread)


def test_phong_lobe_zh():
    from scipy.integrate import trapezoid

    from prtlab.portals import phong_lobe_zh

    mu = np.linspace(0.0, 1.0, 200_001)  # the lobe vanishes below the horizon
    y_l0 = np.polynomial.legendre.legvander(mu, 5) * np.sqrt((2 * np.arange(6) + 1) / (4 * np.pi))
    for e in (1.0, 10.0, 33.0):
        expected = 2 * np.pi * trapezoid(y_l0 * ((e + 2) / (2 * np.pi) * mu**e)[:, None], mu, axis=0)
        np.testing.assert_allclose(phong_lobe_zh(e, 6), expected, rtol=1e-7, atol=1e-9)
    # band 0: int g dw / sqrt(4 pi), int g dw = (e + 2) / (e + 1)
    assert phong_lobe_zh(10.0, 1)[0] == pytest.approx((12 / 11) / np.sqrt(4 * np.pi), rel=1e-12)
    with pytest.raises(ValueError, match="exponent"):
        phong_lobe_zh(-1.0, 3)


def test_glossy_indirect_against_reference(constant_box):
    """Indirect light leaving glossy (Phong 10) floor points toward given views, against prtlab.reference.

    Ours: diffuse transfer ``kd`` + the SH->SH matrix evaluated at the view (order 8 out: the constant sky
    needs order 1 in). Bound: ours with the photon-density biases removed (module docstring) within MC_SIGMAS *
    sqrt(se_ref^2 + se_gather^2 + se_photons^2) + ``ks max|g - g_8| E_in``: the truncation of the lobe's ZH to 8
    bands (projecting over ``w_o`` truncates the zonal lobe), times the indirect irradiance; ours itself within
    that plus the derived biases.
    """
    from prtlab.portals import phong_lobe_zh
    from prtlab.scene import Material
    from prtlab.sh import basis

    kd, ks, e, order_out = 0.3, 0.5, 10.0, 8
    points = POINTS[[0, 3]]
    normals = NORMALS[[0, 3]]
    views = np.array([[0.0, 0.6, 0.8], [0.5, 0.5, -0.7]])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    room = constant_box.objects[0]
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    albedo = np.array([room.material.albedo])
    rng = np.random.default_rng(12)
    photons = trace_photons(caster, albedo, portal, 1_000_000, 1, rng)
    verts, vnormals = room.world_vertices(), room.world_normals()
    exitance = radiance_estimate(photons, verts, vnormals, np.tile(albedo, (len(verts), 1)), 1, k=PHOTON_K)
    columns = _columns(exitance, _estimate_terms(photons, constant_box))
    runs, irradiance = [], []
    c00 = np.sqrt(4 * np.pi)
    for _ in range(N_GATHERS):  # 32768 gather rays in all
        t, m = final_gather(caster, points, normals, np.full((2, 3), kd), columns, np.array([0, len(verts)]),
                            vnormals, 32768 // N_GATHERS, rng, glossy=(np.full((2, 3), ks), np.full(2, e), order_out))
        assert m.shape == (2, order_out**2, 2 + N_SIGNS, 3)
        runs.append(t * c00 + np.einsum("vj,vjkc->vkc", basis(views, order_out), m) * c00)
        irradiance.append(np.pi * t[:, 0] * c00 / kd)
    ours, corrected, se_gather, se_photons = _gathered(np.array(runs))
    mu = np.linspace(-1, 1, 4001)
    y_l0 = np.polynomial.legendre.legvander(mu, order_out - 1) * np.sqrt((2 * np.arange(order_out) + 1) / (4 * np.pi))
    truncation = np.abs(y_l0 @ phong_lobe_zh(e, order_out) - (e + 2) / (2 * np.pi) * np.maximum(mu, 0) ** e).max()
    material = Material(type="phong", kd=np.full(3, kd), ks=np.full(3, ks), exponent=e)
    ref = radiance_at(constant_box, points, normals, views, 1 << 15, np.random.default_rng(8), bounces=1,
                      material=material)
    bound = MC_SIGMAS * np.sqrt(ref.indirect_stderr**2 + se_gather**2 + se_photons**2) \
        + ks * truncation * np.mean(irradiance, axis=0)
    assert np.all(np.abs(corrected - ref.indirect) <= bound), (corrected, ref.indirect, bound)
    assert np.all(np.abs(ours - ref.indirect) <= bound + np.abs(corrected - ours)), (ours, ref.indirect, bound)


def test_phong_lobe_sample():
    from prtlab.portals import phong_lobe_sample

    rng = np.random.default_rng(3)
    axis = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, -0.8], [0.0, -1.0, 0.0]])
    for e in (0.0, 10.0):
        w = phong_lobe_sample(np.repeat(axis, 20000, axis=0), np.full(60000, e), rng).reshape(3, 20000, 3)
        np.testing.assert_allclose(np.linalg.norm(w, axis=-1), 1.0, rtol=1e-12)
        c = np.einsum("vnk,vk->vn", w, axis)
        # E[cos] = (e + 1) / (e + 2) under the pdf (e + 1) / (2 pi) cos^e; the azimuth averages out
        se = c.std(axis=1, ddof=1) / np.sqrt(c.shape[1])
        assert np.all(np.abs(c.mean(1) - (e + 1) / (e + 2)) <= MC_SIGMAS * se)
        perp = w - c[..., None] * axis[:, None, :]
        assert np.all(np.abs(perp.mean(1)) <= MC_SIGMAS * perp.std(1, ddof=1) / np.sqrt(c.shape[1]))
    with pytest.raises(ValueError, match="ks must have shape"):
        trace_photons(None, np.ones((1, 3)), None, 10, 1, rng, ks=np.ones((2, 3)))  # checked before any tracing
    with pytest.raises(ValueError, match="ks must be >= 0"):
        trace_photons(None, np.ones((1, 3)), None, 10, 1, rng, ks=-np.ones((1, 3)), exponent=np.ones(1))


def _glossy_room_indirect(scene, points, normals, views, kd, ks, e, order_out, rng, rays):
    """Ours at points of an all-Phong room (photons reflect by the lobe, gather rays read the walls' specular
    exitance): :func:`_gathered` of ``N_GATHERS`` independent gathers of ``rays`` rays in all."""
    from prtlab.sh import basis

    room = scene.objects[0]
    caster = RayCaster(scene)
    (portal,) = find_portals(scene)
    kd_obj, ks_obj = np.full((1, 3), kd), np.full((1, 3), ks)
    photons = trace_photons(caster, kd_obj, portal, 500_000, 2, rng, ks=ks_obj, exponent=np.array([e]))
    verts, vnormals = room.world_vertices(), room.world_normals()
    n = len(verts)
    exitance, spec = radiance_estimate(photons, verts, vnormals, np.full((n, 3), kd), 1, k=PHOTON_K,
                                       glossy=(np.arange(n), np.full((n, 3), ks), e, order_out))
    terms = _estimate_terms(photons, scene)
    columns, spec_columns = _columns(exitance, terms), _columns(spec, terms)
    c00 = np.sqrt(4 * np.pi)
    out = []
    for _ in range(N_GATHERS):
        t, m = final_gather(caster, points, normals, np.full((len(points), 3), kd), columns, np.array([0, n]),
                            vnormals, rays // N_GATHERS, rng, glossy=(np.full((len(points), 3), ks),
                                                                    np.full(len(points), e), order_out),
                            glossy_exitance=(np.arange(n), spec_columns))
        out.append(t * c00 + np.einsum("vj,vjkc->vkc", basis(views, order_out), m) * c00)
    return _gathered(np.array(out))


def test_glossy_room_interreflection_against_reference(constant_box):
    """A room whose every surface is Phong (kd 0.2, ks 0.5, exponent 4), B = 2, against prtlab.reference.

    Light the walls reflect *specularly* onto the floor points must arrive: photons reflect by the lobe and a
    gather ray reaching a glossy wall reads its specular exitance toward the point. (With both left out, the
    former kd-only approximation, ours was 63-75% low here.) Bound: ours with the photon-density biases removed
    (module docstring; the specular exitance comes from the same photons and discs) within MC_SIGMAS *
    sqrt(se_ref^2 + se_gather^2 + se_photons^2) + the ZH truncation of the lobe to 8 bands at the point and at
    the walls: every radiance is <= 1 under the unit sky (kd + ks <= 1, the lobe's directional albedo <= 1), so
    each costs <= ``ks t pi`` with ``t = max|g - g_8|``, the walls' reaching the point through its BRDF
    (directional albedo <= kd + ks (e + 2) / (e + 1)); ours itself within that plus the derived biases.
    """
    from prtlab.portals import phong_lobe_zh
    from prtlab.scene import Material

    kd, ks, e, order_out = 0.2, 0.5, 4.0, 8
    scene = constant_box
    saved = scene.objects[0].material
    scene.objects[0].material = Material(type="phong", kd=np.full(3, kd), ks=np.full(3, ks), exponent=e)
    try:
        points, normals = POINTS[[0, 3]], NORMALS[[0, 3]]
        views = np.array([[0.0, 0.6, 0.8], [0.5, 0.5, -0.7]])
        views /= np.linalg.norm(views, axis=1, keepdims=True)
        ours, corrected, se_gather, se_photons = _glossy_room_indirect(
            scene, points, normals, views, kd, ks, e, order_out, np.random.default_rng(21), 3 * 8192)
        ref = radiance_at(scene, points, normals, views, 1 << 14, np.random.default_rng(9), bounces=2,
                          material=scene.objects[0].material)
    finally:
        scene.objects[0].material = saved
    mu = np.linspace(-1, 1, 4001)
    y_l0 = np.polynomial.legendre.legvander(mu, order_out - 1) * np.sqrt((2 * np.arange(order_out) + 1) / (4 * np.pi))
    t = np.abs(y_l0 @ phong_lobe_zh(e, order_out) - (e + 2) / (2 * np.pi) * np.maximum(mu, 0) ** e).max()
    bound = MC_SIGMAS * np.sqrt(ref.indirect_stderr**2 + se_gather**2 + se_photons**2) \
        + ks * t * np.pi * (1 + kd + ks * (e + 2) / (e + 1))
    assert np.all(np.abs(corrected - ref.indirect) <= bound), (corrected, ref.indirect, bound)
    assert np.all(np.abs(ours - ref.indirect) <= bound + np.abs(corrected - ours)), (ours, ref.indirect, bound)


def test_glossy_gather_white_furnace(constant_box):
    """A glossy vertex under uniform incident radiance 1 (every gather ray reads B = 1): the diffuse transfer is
    exactly ``kd``, the specular one seen along the normal is ``ks`` times ``2 pi int_0^1 g_n(mu) mu dmu`` (the
    lobe's ZH truncated to ``n`` bands; 1 without truncation: the normalised Phong reflects all of a uniform
    light toward the normal), within MC_SIGMAS of its cosine-sampling standard error."""
    from prtlab.portals import phong_lobe_zh
    from prtlab.sh import basis

    room = constant_box.objects[0]
    caster = RayCaster(constant_box)
    verts, vnormals = room.world_vertices(), room.world_normals()
    points = np.array([[0.0, 1.2, 0.0], [0.5, 0.8, -0.3]])
    normals = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])  # facing away from the window (-z wall): all rays hit
    kd, ks, e, order_out, m = np.array([0.3, 0.2, 0.1]), np.array([0.5, 0.4, 0.6]), 10.0, 8, 4096
    t, mat = final_gather(caster, points, normals, np.tile(kd, (2, 1)), np.ones((len(verts), 1, 3)),
                          np.array([0, len(verts)]), vnormals, m, np.random.default_rng(4),
                          glossy=(np.tile(ks, (2, 1)), np.full(2, e), order_out))
    np.testing.assert_allclose(t[:, 0], np.tile(kd, (2, 1)), rtol=1e-12)
    along_normal = np.einsum("vj,vjc->vc", basis(normals, order_out), mat[:, :, 0])
    mu, w = np.polynomial.legendre.leggauss(64)
    mu, w = 0.5 * (mu + 1), 0.5 * w
    g = np.polynomial.legendre.legvander(mu, order_out - 1) * np.sqrt((2 * np.arange(order_out) + 1) / (4 * np.pi)) \
        @ phong_lobe_zh(e, order_out)
    mean = 2 * np.pi * np.sum(w * g * mu)  # E[pi g(mu)] under cos / pi
    var = 2 * np.pi**2 * np.sum(w * g**2 * mu) - mean**2
    assert np.all(np.abs(along_normal - ks * mean) <= MC_SIGMAS * ks * np.sqrt(var / m)), (along_normal, ks * mean)
    assert abs(mean - 1.0) < 0.05  # 8 bands of the exponent-10 lobe keep nearly all of its energy along the normal


def test_glossy_estimate_needs_photon_directions():
    from prtlab.portals import PhotonMap

    z = np.zeros((1, 3))
    photons = PhotonMap(z, np.array([[0.0, 0.0, 1.0]]), np.ones((1, 3)), np.array([[0.0, 0.0, -1.0]]),
                        np.zeros(1, dtype=np.int64), 1)
    with pytest.raises(ValueError, match="no photon directions"):
        radiance_estimate(photons, z, np.array([[0.0, 0.0, 1.0]]), np.ones((1, 3)), 1,
                          glossy=(np.array([0]), np.ones((1, 3)), 10.0, 2))


def _plane_scene():
    from prtlab.scene import Scene

    return Scene.from_dict({
        "objects": [{"name": "plane", "mesh": {"builtin": "plane", "size": [1.0, 1.0]},
                     "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}],
        "lights": [{"type": "environment", "constant": [1.0, 1.0, 1.0]}],
        "camera": {"position": [0, 1, 1], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 60,
                   "resolution": [8, 8]},
    })


@pytest.mark.parametrize("where", ["inside", "edge", "corner"])
def test_radiance_estimate_uniform_density_closed_form(where):
    """Photons of power ``w`` spread uniformly (density ``lambda = N``) on the unit square ``y = 0``: the irradiance
    response is ``E_00 = lambda w Y_00`` everywhere on it, edges and corners included (closed form), so ``B_00 =
    rho / pi lambda w Y_00``. The mean over many independent estimates (points far enough apart that their discs
    share no photon) agrees within 4 standard errors; the old whole-disc estimate is off by the disc's part off the
    square (1/2 on an edge, 1/4 in a corner)."""
    from prtlab.portals import PhotonMap

    rng = np.random.default_rng(5)
    n, w, k, rho = 100_000, 1e-3, 32, 0.5
    pos = np.column_stack([rng.random(n) - 0.5, np.zeros(n), rng.random(n) - 0.5])
    up = np.tile([0.0, 1.0, 0.0], (n, 1))
    photons = PhotonMap(pos, up, np.full((n, 3), w), up, np.zeros(n, np.int64), n, up)
    # r_k = sqrt(k / (pi n)) is about 0.01: points 0.04 apart use disjoint photons
    t = np.linspace(-0.48, 0.48, 25)
    if where == "inside":
        xz = np.stack(np.meshgrid(t[::2], t[::2]), -1).reshape(-1, 2)
    elif where == "edge":
        xz = np.concatenate([np.column_stack([t, np.full_like(t, s)]) for s in (-0.5, 0.5)]
                            + [np.column_stack([np.full_like(t, s), t]) for s in (-0.5, 0.5)])
    else:  # the 4 corners, over 16 independent photon maps
        xz = np.array([[-0.5, -0.5], [-0.5, 0.5], [0.5, -0.5], [0.5, 0.5]])
    points = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    caster = RayCaster(_plane_scene())
    expected = rho / np.pi * n * w * 0.5 / np.sqrt(np.pi)  # Y_00 = 1 / (2 sqrt(pi))
    reps = 16 if where == "corner" else 1
    est, old = [], []
    for rep in range(reps):
        if rep:
            photons.position = np.column_stack([rng.random(n) - 0.5, np.zeros(n), rng.random(n) - 0.5])
        albedo = np.full((len(points), 3), rho)
        est.append(radiance_estimate(photons, points, normals, albedo, 1, k,
                                     surface=(caster, np.zeros(len(points), np.int64)))[:, 0, 0])
        old.append(radiance_estimate(photons, points, normals, albedo, 1, k)[:, 0, 0])
    est, old = np.concatenate(est) / expected, np.concatenate(old) / expected
    se = 1.0 / np.sqrt(k - 2) / np.sqrt(len(est))  # the estimate's relative sd is 1/sqrt(k-2) (Gamma(k))
    assert abs(est.mean() - 1.0) <= 4 * se, (est.mean(), se)
    fraction = {"inside": 1.0, "edge": 0.5, "corner": 0.25}[where]
    assert abs(old.mean() - fraction) <= 4 * se, (old.mean(), fraction)


def test_disc_coverage_of_the_box_room(constant_box):
    """The part of a disc (radius 0.3) on the room's surface, by probe rays, against the room's geometry (the box
    face minus the window opening, 512 points): within 0.06 everywhere (64 probes), 1/2 on edges, 1/4 in
    corners."""
    from prtlab.portals import disc_coverage

    room, window = constant_box.objects[0], constant_box.objects[1]
    verts, normals = room.world_vertices(), room.world_normals()
    radius = np.full(len(verts), 0.3)
    got = disc_coverage(RayCaster(constant_box), np.zeros(len(verts), np.int64), verts, normals, radius)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    d = _sunflower(512)
    p = verts[:, None] + 0.3 * (d[None, :, :1] * t1[:, None] + d[None, :, 1:] * t2[:, None])
    lo, hi = verts.min(0), verts.max(0)
    wlo, whi = window.world_vertices().min(0), window.world_vertices().max(0)
    eps = 1e-9
    f = (np.all((p >= lo - eps) & (p <= hi + eps), -1) & ~np.all((p > wlo - eps) & (p < whi + eps), -1)).mean(1)
    assert np.max(np.abs(got - f)) <= 0.06, np.max(np.abs(got - f))
    assert np.min(got) < 0.3 and np.max(got) == 1.0
