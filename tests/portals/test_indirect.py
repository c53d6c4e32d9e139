"""Indirect light of a simple box room with a window, against prtlab.reference.

Bias of photon density estimation (Christensen 1999 radiance estimates + final gathering),
measured on this box (constant sky, albedo 0.7, 1M photons, k = 32, 16384 gather rays,
mean of 4 independent runs vs a 2^18-path reference with 1-1.4% relative standard error,
at the five points below, B = 1 and 2):

    relative difference (ours - reference) in [-3.1%, +1.9%], per-run relative standard
    error of ours <= 1.7%.

The estimate over a disc of radius r loses the part of the disc beyond a surface's edge
(the room's edges, the window opening), so the bias is mostly negative and grows with k
(k = 128: down to -3.5%; k = 64: down to -4.9% at B = 2). The test allows
``MC_SIGMAS * sqrt(se_ref^2 + (0.017 ref)^2) + 0.031 ref``.
"""

import numpy as np
import pytest

from prtlab.geometry import RayCaster
from prtlab.portals import final_gather, find_portals, radiance_estimate, trace_photons
from prtlab.reference import radiance_at

from ..conftest import MC_SIGMAS

POINTS = np.array([[0.3, 0.0, 0.5], [1.5, 1.0, 0.2], [0.0, 2.5, 0.5], [-0.5, 0.0, -1.0], [0.2, 1.2, 1.5]])
NORMALS = np.array([[0, 1.0, 0], [-1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1]])
MEASURED_BIAS = 0.031
MEASURED_RUN_SE = 0.017


def _indirect(scene, bounces, n_photons, seed):
    room = scene.objects[0]
    caster = RayCaster(scene)
    (portal,) = find_portals(scene)
    albedo = np.array([room.material.albedo])
    rng = np.random.default_rng(seed)
    photons = trace_photons(caster, albedo, portal, n_photons, bounces, rng)
    verts, normals = room.world_vertices(), room.world_normals()
    exitance = radiance_estimate(photons, verts, normals, np.tile(albedo, (len(verts), 1)), 1, k=32)
    transfer = final_gather(caster, POINTS, NORMALS, np.tile(albedo, (len(POINTS), 1)), exitance,
                            np.array([0, len(verts)]), normals, 16384, rng)
    return transfer[:, 0, :] * np.sqrt(4 * np.pi)  # constant sky L = 1: c_00 = sqrt(4 pi)


@pytest.mark.parametrize("bounces", [2])
def test_box_indirect_against_reference(constant_box, bounces):
    ours = _indirect(constant_box, bounces, 1_000_000, 11)
    ref = radiance_at(constant_box, POINTS, NORMALS, NORMALS, 1 << 16, np.random.default_rng(7), bounces=bounces,
                      material=constant_box.objects[0].material)
    bound = MC_SIGMAS * np.sqrt(ref.indirect_stderr**2 + (MEASURED_RUN_SE * ref.indirect) ** 2) \
        + MEASURED_BIAS * ref.indirect
    assert np.all(np.abs(ours - ref.indirect) <= bound), (ours, ref.indirect, bound)


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
    needs order 1 in). Bound: MC_SIGMAS * sqrt(se_ref^2 + se_gather^2 + (MEASURED_RUN_SE ref)^2) +
    MEASURED_BIAS ref (photon density, above) + ``ks max|g - g_8| E_in``: the truncation of the lobe's ZH
    to 8 bands (projecting over ``w_o`` truncates the zonal lobe), times the indirect irradiance.
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
    exitance = radiance_estimate(photons, verts, vnormals, np.tile(albedo, (len(verts), 1)), 1, k=32)
    runs, irradiance = [], []
    c00 = np.sqrt(4 * np.pi)
    for _ in range(4):
        t, m = final_gather(caster, points, normals, np.full((2, 3), kd), exitance, np.array([0, len(verts)]),
                            vnormals, 8192, rng, glossy=(np.full((2, 3), ks), np.full(2, e), order_out))
        assert m.shape == (2, order_out**2, 1, 3)
        runs.append(t[:, 0] * c00 + np.einsum("vj,vjc->vc", basis(views, order_out), m[:, :, 0]) * c00)
        irradiance.append(np.pi * t[:, 0] * c00 / kd)
    runs = np.array(runs)
    ours, se_gather = runs.mean(0), runs.std(0, ddof=1) / np.sqrt(len(runs))
    mu = np.linspace(-1, 1, 4001)
    y_l0 = np.polynomial.legendre.legvander(mu, order_out - 1) * np.sqrt((2 * np.arange(order_out) + 1) / (4 * np.pi))
    truncation = np.abs(y_l0 @ phong_lobe_zh(e, order_out) - (e + 2) / (2 * np.pi) * np.maximum(mu, 0) ** e).max()
    material = Material(type="phong", kd=np.full(3, kd), ks=np.full(3, ks), exponent=e)
    ref = radiance_at(constant_box, points, normals, views, 1 << 15, np.random.default_rng(8), bounces=1,
                      material=material)
    bound = MC_SIGMAS * np.sqrt(ref.indirect_stderr**2 + se_gather**2 + (MEASURED_RUN_SE * ref.indirect) ** 2) \
        + MEASURED_BIAS * ref.indirect + ks * truncation * np.mean(irradiance, axis=0)
    assert np.all(np.abs(ours - ref.indirect) <= bound), (ours, ref.indirect, bound)


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


def _glossy_room_indirect(scene, points, normals, views, kd, ks, e, order_out, glossy_light, rng, runs):
    """Ours at points of an all-Phong room: photons reflect by the lobe (``glossy_light``) and gather rays read
    the walls' specular exitance, or both left out (the former kd-only approximation)."""
    from prtlab.sh import basis

    room = scene.objects[0]
    caster = RayCaster(scene)
    (portal,) = find_portals(scene)
    kd_obj, ks_obj = np.full((1, 3), kd), np.full((1, 3), ks)
    photons = trace_photons(caster, kd_obj, portal, 500_000, 2, rng, ks=ks_obj if glossy_light else None,
                            exponent=np.array([e]))
    verts, vnormals = room.world_vertices(), room.world_normals()
    n = len(verts)
    exitance, spec = radiance_estimate(photons, verts, vnormals, np.full((n, 3), kd), 1, k=32,
                                       glossy=(np.arange(n), np.full((n, 3), ks), e, order_out))
    glossy_exitance = (np.arange(n), spec) if glossy_light else None
    c00 = np.sqrt(4 * np.pi)
    out = []
    for _ in range(runs):
        t, m = final_gather(caster, points, normals, np.full((len(points), 3), kd), exitance, np.array([0, n]),
                            vnormals, 8192, rng, glossy=(np.full((len(points), 3), ks), np.full(len(points), e),
                                                         order_out), glossy_exitance=glossy_exitance)
        out.append(t[:, 0] * c00 + np.einsum("vj,vjc->vc", basis(views, order_out), m[:, :, 0]) * c00)
    return np.array(out)


def test_glossy_room_interreflection_against_reference(constant_box):
    """A room whose every surface is Phong (kd 0.2, ks 0.5, exponent 4), B = 2, against prtlab.reference.

    Light the walls reflect *specularly* onto the floor points must arrive: photons reflect by the lobe and a
    gather ray reaching a glossy wall reads its specular exitance toward the point. (With both left out, the
    former kd-only approximation, ours was 63-75% low here.) Bound: MC_SIGMAS * sqrt(se_ref^2 + se_ours^2 +
    (MEASURED_RUN_SE ref)^2) + MEASURED_BIAS ref (photon density) + the ZH truncation of the lobe to 8 bands
    at the point and at the walls: every radiance is <= 1 under the unit sky (kd + ks <= 1, the lobe's
    directional albedo <= 1), so each costs <= ``ks t pi`` with ``t = max|g - g_8|``, the walls' reaching the
    point through its BRDF (directional albedo <= kd + ks (e + 2) / (e + 1)).
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
        runs = _glossy_room_indirect(scene, points, normals, views, kd, ks, e, order_out, True,
                                     np.random.default_rng(21), 3)
        ours, se_ours = runs.mean(0), runs.std(0, ddof=1) / np.sqrt(len(runs))
        ref = radiance_at(scene, points, normals, views, 1 << 14, np.random.default_rng(9), bounces=2,
                          material=scene.objects[0].material)
    finally:
        scene.objects[0].material = saved
    mu = np.linspace(-1, 1, 4001)
    y_l0 = np.polynomial.legendre.legvander(mu, order_out - 1) * np.sqrt((2 * np.arange(order_out) + 1) / (4 * np.pi))
    t = np.abs(y_l0 @ phong_lobe_zh(e, order_out) - (e + 2) / (2 * np.pi) * np.maximum(mu, 0) ** e).max()
    bound = MC_SIGMAS * np.sqrt(ref.indirect_stderr**2 + se_ours**2 + (MEASURED_RUN_SE * ref.indirect) ** 2) \
        + MEASURED_BIAS * ref.indirect + ks * t * np.pi * (1 + kd + ks * (e + 2) / (e + 1))
    assert np.all(np.abs(ours - ref.indirect) <= bound), (ours, ref.indirect, bound)


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
