"""Tests of prtlab.reference: the Monte Carlo estimators against closed forms.

Every comparison is bounded by ``MC_SIGMAS`` standard errors of the estimate
(plus, where the geometry is tessellated, a derived bound on the tessellation
bias); estimators with zero variance are held to float precision.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from scipy.stats import chisquare

from prtlab.geometry import direction_to_equirect, equirect_directions, equirect_lookup
from prtlab.reference import direct, irradiance_at, path_trace, radiance_at, shade_reference
from prtlab.reference._estimators import _EnvSampler
from prtlab.reference._kernels import bsdf_eval_kernel, bsdf_eval_numpy, bsdf_sample_kernel, hit_frame_kernel
from prtlab.scene import (
    AreaLight,
    Camera,
    EnvironmentLight,
    Material,
    PointLight,
    Scene,
    SceneObject,
    Transform,
)
from tests.conftest import MC_SIGMAS, random_directions
from tests.geometry.test_sampling import CHI2_SIGNIFICANCE, chi2_directions

EXACT = 1e-10  # estimators with zero variance


def grid_plane(size=4.0, res=8, y=0.0, flip=False):
    """A (res+1)^2-vertex square in the xz plane at height y, normal +y (or -y)."""
    g = np.linspace(-size / 2, size / 2, res + 1)
    x, z = np.meshgrid(g, g, indexing="ij")
    v = np.stack([x.ravel(), np.full(x.size, y), z.ravel()], axis=-1)
    idx = np.arange(v.shape[0]).reshape(res + 1, res + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])  # normal +y
    if flip:
        f = f[:, ::-1]
    mesh = trimesh.Trimesh(v, f, process=False)
    assert np.allclose(mesh.vertex_normals, [0, -1 if flip else 1, 0])
    return mesh


def diffuse(rho):
    return Material(type="diffuse", albedo=np.broadcast_to(np.asarray(rho, float), 3).copy())


def polygon_irradiance(points, normals, corners, radiance):
    """Lambert's exact formula: irradiance from a uniform polygon above the horizon."""
    out = np.zeros(len(points))
    for i in range(len(corners)):
        r1 = corners[i] - points
        r2 = corners[(i + 1) % len(corners)] - points
        r1 /= np.linalg.norm(r1, axis=1, keepdims=True)
        r2 /= np.linalg.norm(r2, axis=1, keepdims=True)
        theta = np.arccos(np.clip(np.sum(r1 * r2, axis=1), -1, 1))
        g = np.cross(r1, r2)
        g /= np.linalg.norm(g, axis=1, keepdims=True)
        out += theta * np.sum(normals * g, axis=1)
    return 0.5 * np.abs(out)[:, None] * radiance


def assert_within(est, stderr, truth, extra=0.0):
    est, stderr, truth = np.broadcast_arrays(est, stderr, truth)
    bound = MC_SIGMAS * stderr + extra + EXACT
    bad = np.abs(est - truth) > bound
    assert not bad.any(), (
        f"{bad.sum()} of {bad.size} values off by more than {MC_SIGMAS} sigma: est {est[bad][:5]}, "
        f"truth {truth[bad][:5]}, stderr {stderr[bad][:5]}"
    )


# ------------------------------------------------------------------ known answers


def test_plane_under_constant_sky_is_exact(rng):
    sky = np.array([1.0, 2.0, 0.5])
    rho = np.array([0.5, 0.6, 0.7])
    scene = Scene([SceneObject("floor", grid_plane(), material=diffuse(rho))], [EnvironmentLight(constant=sky)])
    res = path_trace(scene, 1, 4, rng)
    assert_within(res.direct["floor"], res.stderr["direct"]["floor"], rho * sky)
    assert np.abs(res.stderr["direct"]["floor"]).max() < 1e-12  # diffuse * cosine sampling: zero variance
    np.testing.assert_array_equal(res.indirect["floor"], 0.0)
    np.testing.assert_allclose(res.total["floor"], res.direct["floor"])
    e = irradiance_at(scene, [[0.3, 0.0, 0.2]], [[0.0, 1.0, 0.0]], 4, rng)
    assert_within(e.total, e.stderr, np.pi * sky)


def test_back_side_gets_nothing(rng):
    # facing -y: the point light above is behind every vertex; a constant sky reaches it from below
    scene = Scene([SceneObject("floor", grid_plane(flip=True), material=diffuse(0.5))],
                  [PointLight(np.array([0.0, 2.0, 0.0]), np.ones(3))])
    np.testing.assert_array_equal(direct(scene, 4, rng).direct["floor"], 0.0)
    scene.lights = [EnvironmentLight(constant=np.ones(3))]
    np.testing.assert_allclose(direct(scene, 4, rng).direct["floor"], 0.5, rtol=1e-12)


def test_point_light_exact_diffuse_and_phong(rng):
    light = PointLight(position=np.array([0.5, 2.0, -0.3]), intensity=np.array([3.0, 2.0, 1.0]))
    phong = Material(type="phong", kd=np.array([0.2, 0.3, 0.1]), ks=np.array([0.4, 0.2, 0.3]), exponent=12.0)
    cam = Camera(position=np.array([1.0, 3.0, 4.0]))
    plane = grid_plane(res=6)
    for material in (diffuse([0.5, 0.6, 0.7]), phong):
        scene = Scene([SceneObject("floor", plane, material=material)], [light], camera=cam)
        res = path_trace(scene, 0, 2, rng)
        x, n = scene.objects[0].world_shading_points(), plane.vertex_normals  # where vertices are shaded
        d = light.position - x
        r2 = np.sum(d * d, axis=1)
        wi = d / np.sqrt(r2)[:, None]
        wo = cam.position - x
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        cos = np.sum(n * wi, axis=1)
        if material.type == "phong":
            refl = 2 * cos[:, None] * n - wi  # mirror of wi: Material's definition
            spec = np.maximum(0, np.sum(refl * wo, axis=1)) ** material.exponent
            f = material.kd / np.pi + material.ks * ((material.exponent + 2) / (2 * np.pi) * spec)[:, None]
        else:
            f = np.broadcast_to(material.albedo / np.pi, x.shape)
        truth = f * (cos / r2)[:, None] * light.intensity
        np.testing.assert_allclose(res.direct["floor"], truth, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(res.stderr["direct"]["floor"], 0.0)


def test_point_light_shadow_half_plane(rng):
    plane = grid_plane(size=4.0, res=8)
    roof = trimesh.creation.box(extents=[4.0, 0.05, 2.0])  # a slab over half of the floor:
    roof.apply_translation([0.0, 1.0, -1.0])  # covers z in [-2, 0]
    light = PointLight(position=np.array([0.0, 3.0, 0.0]), intensity=np.ones(3))
    scene = Scene(
        [SceneObject("floor", plane, material=diffuse(1.0)), SceneObject("roof", roof, material=diffuse(0.5))], [light]
    )
    res = direct(scene, 2, rng)
    x = scene.objects[0].world_shading_points()
    # the shadow of the roof edge (z = 0 at y = 1) from y = 3 falls at z = 0 * 3/2 = 0 on the floor
    shadowed = x[:, 2] < -0.01
    lit = x[:, 2] > 0.01
    assert np.all(res.direct["floor"][shadowed] == 0)
    d = light.position - x[lit]
    r2 = np.sum(d * d, axis=1)
    truth = (d[:, 1] / np.sqrt(r2) / r2 / np.pi)[:, None] * np.ones(3)
    np.testing.assert_allclose(res.direct["floor"][lit], truth, rtol=1e-9)


def test_area_light_lambert_formula_and_one_sided(rng):
    light = AreaLight(center=np.array([0.3, 1.5, 0.0]), u=np.array([0.4, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.3]),
                      radiance=np.array([5.0, 4.0, 3.0]))
    assert light.normal[1] < -0.99  # cross(u, v) points down: toward the floor
    scene = Scene([SceneObject("floor", grid_plane(), material=diffuse(0.5))], [light])
    pts = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 1.0], [-1.0, 0.0, -1.5], [0.3, 0.0, 0.1]])
    nrm = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    e = irradiance_at(scene, pts, nrm, 4000, rng)
    corners = light.center + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) @ np.stack([light.u, light.v])
    truth = polygon_irradiance(pts, nrm, corners, light.radiance)
    assert_within(e.total, e.stderr, truth)
    assert np.all(e.stderr > 0)
    # small distant light: E ~ L A cos cos / r^2
    far = AreaLight(center=np.array([0.0, 20.0, 0.0]), u=np.array([0.05, 0, 0]), v=np.array([0, 0, 0.05]),
                    radiance=np.ones(3))
    e = irradiance_at(Scene([], [far]), [[0.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]], 64, rng)
    np.testing.assert_allclose(e.total, far.area / 400.0, rtol=1e-5)
    # flipped light emits upward: the floor gets nothing
    up = AreaLight(center=light.center, u=light.v, v=light.u, radiance=light.radiance)
    e = irradiance_at(Scene([], [up]), pts, nrm, 16, rng)
    np.testing.assert_array_equal(e.total, 0.0)


def test_light_lying_on_a_ceiling_is_not_shadowed_by_it(rng):
    # the light is exactly in the ceiling's plane; grazing shadow rays must still reach it
    ceiling = grid_plane(size=8.0, res=4, y=1.0, flip=True)
    light = AreaLight(center=np.array([0.0, 1.0, 0.0]), u=np.array([0.3, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.3]),
                      radiance=np.ones(3))
    scene = Scene([SceneObject("ceiling", ceiling, material=diffuse(0.5))], [light])
    pts = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.5], [3.5, 0.0, -1.0]])
    nrm = np.tile([0.0, 1.0, 0.0], (3, 1))
    e = irradiance_at(scene, pts, nrm, 2000, rng)
    corners = light.center + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) @ np.stack([light.u, light.v])
    assert_within(e.total, e.stderr, polygon_irradiance(pts, nrm, corners, light.radiance))


@pytest.mark.parametrize("block", [False, True])
def test_area_light_as_opaque_quad_or_not(rng, block):
    light = AreaLight(center=np.array([0.2, 1.0, 0.0]), u=np.array([0.5, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.4]),
                      radiance=np.array([3.0, 2.0, 1.0]))
    sky = np.array([0.5, 0.5, 1.0])
    scene = Scene([], [light, EnvironmentLight(constant=sky)])
    pts = np.array([[0.0, 0.0, 0.0], [0.9, 0.0, -0.4], [3.0, 0.0, 0.0]])
    nrm = np.tile([0.0, 1.0, 0.0], (3, 1))
    e = irradiance_at(scene, pts, nrm, 4000, rng, area_lights_block=block)
    corners = light.center + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) @ np.stack([light.u, light.v])
    truth = np.pi * sky + polygon_irradiance(pts, nrm, corners, light.radiance)
    if block:  # the black quad hides its patch of sky
        truth -= polygon_irradiance(pts, nrm, corners, sky)
    assert_within(e.total, e.stderr, truth)


def test_sky_occluded_by_roof(rng):
    # a square roof (single sheet) of half size a at height h over the floor blocks the sky
    a, h = 1.0, 1.0
    roof = grid_plane(size=2 * a, res=2, y=h)
    scene = Scene([SceneObject("roof", roof, material=diffuse(0.8))], [EnvironmentLight(constant=np.ones(3))])
    pts = np.array([[0.0, 0.0, 0.0], [0.7, 0.0, 0.3], [2.0, 0.0, 0.0], [-1.0, 0.0, -1.0]])
    nrm = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    e = irradiance_at(scene, pts, nrm, 2000, rng)
    corners = np.array([[-a, h, -a], [a, h, -a], [a, h, a], [-a, h, a]])
    truth = np.pi - polygon_irradiance(pts, nrm, corners, np.ones(3))
    assert_within(e.total, e.stderr, truth)
    np.testing.assert_array_equal(e.indirect, 0.0)


def _furnace_bounds(mesh, rho, bounces):
    """Bounds on the indirect radiance inside a tessellated sphere with a point light at its centre.

    On the exact unit sphere every wall point gets E = I, so light with k bounces is
    rho^k L0 (L0 = rho I / pi) and the indirect part is L0 sum_{k=1..B} rho^k. On the
    tessellation a hit point's irradiance I cos / d^2 lies in I [c, 1 / r^2] (r the
    smallest face-plane distance, c the smallest cosine between corner normals), and at
    most a share 2 (1 - c) of the cosine lobe leaves between the shading and geometric
    tangent planes.
    """
    f, v, n = mesh.faces, mesh.vertices, mesh.vertex_normals
    r = np.abs(np.sum(mesh.face_normals * v[f[:, 0]], axis=1)).min()
    c = min(np.sum(n[f[:, i]] * n[f[:, j]], axis=1).min() for i, j in ((0, 1), (1, 2), (0, 2)))
    lo_k, hi_k = c - 2 * (1 - c), 1 / r**2
    l0 = rho / np.pi
    lo = l0 * sum((rho * lo_k) ** k for k in range(1, bounces + 1))
    hi = l0 * sum((rho * hi_k) ** k for k in range(1, bounces + 1))
    return l0, lo, hi


def test_furnace_sphere_bounce_sums(rng):
    rho = 0.6
    sphere = trimesh.creation.icosphere(subdivisions=4)
    sphere.invert()  # inward normals: the inside is the shaded side
    scene = Scene([SceneObject("sphere", sphere, material=diffuse(rho))], [PointLight(np.zeros(3), np.ones(3))])
    pts = sphere.vertices[::64]
    nrm = sphere.vertex_normals[::64]
    for bounces in (0, 1, 3):
        est = radiance_at(scene, pts, nrm, nrm, 64, rng, material=diffuse(rho), bounces=bounces)
        l0, lo, hi = _furnace_bounds(sphere, rho, bounces)
        r = np.linalg.norm(pts, axis=1)
        exact = l0 * np.sum(nrm * -pts, axis=1) / r**3  # a shadow ray, no sampling: exact
        np.testing.assert_allclose(est.direct, np.repeat(exact[:, None], 3, 1), rtol=1e-12)
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        assert_within(est.indirect, est.indirect_stderr, mid, extra=half)
        assert_within(est.total, est.stderr, exact[:, None] + mid, extra=half)


@pytest.mark.slow
def test_furnace_sum_over_bounces_converges(rng):
    rho = 0.5
    sphere = trimesh.creation.icosphere(subdivisions=5)
    sphere.invert()
    scene = Scene([SceneObject("s", sphere, material=diffuse(rho))], [PointLight(np.zeros(3), np.ones(3))],
                  camera=Camera(position=np.zeros(3)))
    previous = 0.0
    for bounces in (1, 2, 4, 8):
        res = path_trace(scene, bounces, 8, rng)
        l0, lo, hi = _furnace_bounds(sphere, rho, bounces)
        ind, se = res.indirect["s"], res.stderr["indirect"]["s"]
        assert_within(ind, se, (lo + hi) / 2, extra=(hi - lo) / 2)
        assert ind.mean() > previous
        previous = ind.mean()
    # the limit rho / (1 - rho) * L0 within the truncation rho^9 / (1 - rho) and tessellation
    assert abs(previous / l0 - rho / (1 - rho)) < rho**9 / (1 - rho) + 2e-3


def test_phong_vertex_under_constant_sky(rng):
    # normalised Phong under a constant sky: L = kd L + ks L (e+2)/(2pi) int max(0, r.wi)^e cos dwi
    kd, ks, e = np.array([0.3, 0.2, 0.1]), np.array([0.5, 0.5, 0.5]), 20.0
    mat = Material(type="phong", kd=kd, ks=ks, exponent=e)
    scene = Scene([], [EnvironmentLight(constant=np.ones(3))])
    wo = np.array([0.6, 0.8, 0.0])
    est = radiance_at(scene, np.zeros((1, 3)), [[0.0, 1.0, 0.0]], wo, 20000, rng, material=mat)
    # the specular integral by quadrature over the hemisphere in (cos theta, phi)
    z = (np.arange(1000) + 0.5) / 1000
    phi = (np.arange(2000) + 0.5) / 2000 * 2 * np.pi
    Z, P = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - Z * Z)
    w = np.stack([s * np.cos(P), Z, s * np.sin(P)], axis=-1)
    r = 2 * wo[1] * np.array([0.0, 1.0, 0.0]) - wo
    spec = np.sum(np.maximum(0, w @ r) ** e * Z) * (1 / 1000) * (2 * np.pi / 2000) * (e + 2) / (2 * np.pi)
    truth = kd + ks * spec
    assert_within(est.total[0], est.stderr[0], truth, extra=1e-4 * truth)


def _sun_sky(h=16, w=32):
    img = np.full((h, w, 3), 0.2)
    img[:, :, 2] += np.linspace(0.5, 0.0, h)[:, None]
    img[4, 9] = [400.0, 300.0, 200.0]  # a one-pixel "sun"
    return img


def _quadrature_irradiance(image, normals, n=(512, 1024)):
    """Irradiance (..., 3) at ``normals`` (..., 3) by the midpoint rule in (z, phi)."""
    z = -1 + (np.arange(n[0]) + 0.5) * 2 / n[0]
    phi = (np.arange(n[1]) + 0.5) * 2 * np.pi / n[1]
    Z, P = np.meshgrid(z, phi, indexing="ij")
    s = np.sqrt(1 - Z * Z)
    w = np.stack([s * np.cos(P), s * np.sin(P), Z], axis=-1).reshape(-1, 3)
    L = equirect_lookup(image, w) * (2 / n[0]) * (2 * np.pi / n[1])
    normals = np.asarray(normals, float)
    flat = normals.reshape(-1, 3)
    out = np.concatenate([np.maximum(0, flat[i : i + 16] @ w.T) @ L for i in range(0, len(flat), 16)])
    return out.reshape(normals.shape[:-1] + (3,))


def test_environment_map_importance_sampling_with_mis(rng):
    img = _sun_sky()
    scene = Scene([], [EnvironmentLight(image=img)])
    normal = np.array([0.3, 0.9, 0.2])
    normal /= np.linalg.norm(normal)
    truth = _quadrature_irradiance(img, normal)
    e = irradiance_at(scene, np.zeros((1, 3)), normal[None], 4000, rng)
    assert_within(e.total[0], e.stderr[0], truth, extra=2e-4 * truth)


def test_mis_and_bsdf_sampling_agree(rng):
    """Two independent unbiased strategies for the same integral agree within their errors."""
    scene = Scene([], [EnvironmentLight(image=_sun_sky())])
    normals = random_directions(rng, 24)
    mis = irradiance_at(scene, np.zeros((24, 3)), normals, 512, rng)
    bsdf = irradiance_at(scene, np.zeros((24, 3)), normals, 20000, rng, env_sampling="bsdf")
    z = (mis.total - bsdf.total) / np.hypot(mis.stderr, bsdf.stderr)
    assert np.abs(z).max() < MC_SIGMAS
    # importance sampling pays where the sun is in view: the variance per sample relative to BSDF
    # sampling's is the design's (Veach's power heuristic over the sampler's pdf, by quadrature), and < 1
    sun = equirect_directions(16, 32)[4, 9]
    sees_sun = normals @ sun > 0.3
    efficiency = (mis.stderr[sees_sun] ** 2 * 512) / (bsdf.stderr[sees_sun] ** 2 * 20000)
    design, rel_se = _mis_efficiency(_sun_sky(), normals[sees_sun], 512, 20000)
    assert sees_sun.sum() >= 5 and np.all(design < 1)
    assert np.all(np.abs(efficiency / design - 1) <= MC_SIGMAS * rel_se), (efficiency, design, rel_se)


def _mis_efficiency(image, normals, n_mis, n_bsdf, n=(256, 512)):
    """Variance per sample of the irradiance by MIS (one map and one cosine sample, power heuristic, Veach
    1997 eq. 9.13) over that of cosine sampling alone, and the relative standard error of that ratio when
    both variances are estimated from ``n_mis`` / ``n_bsdf`` samples: ``Var(s^2) = (m4 - (n-3)/(n-1)
    sigma^4) / n``, central moments by the midpoint rule in (z, phi); the MIS sum's ``m4 = m4_A + m4_B +
    6 var_A var_B`` (independent samples). Returns ``(..., 3)`` arrays."""
    z = -1 + (np.arange(n[0]) + 0.5) * 2 / n[0]
    phi = (np.arange(n[1]) + 0.5) * 2 * np.pi / n[1]
    Z, P = np.meshgrid(z, phi, indexing="ij")
    w = np.stack([np.sqrt(1 - Z * Z) * np.cos(P), np.sqrt(1 - Z * Z) * np.sin(P), Z], axis=-1).reshape(-1, 3)
    dw = (2 / n[0]) * (2 * np.pi / n[1])
    radiance, p_env = equirect_lookup(image, w), _EnvSampler(image).pdf(w)

    def moments(f, pdf, weight):
        g = np.divide(f * weight[:, None], pdf[:, None], out=np.zeros_like(f), where=pdf[:, None] > 0)
        mu = (g * pdf[:, None]).sum(0) * dw
        return ((g - mu) ** 2 * pdf[:, None]).sum(0) * dw, ((g - mu) ** 4 * pdf[:, None]).sum(0) * dw

    def rel_var(var, m4, k):
        return (m4 / var**2 - (k - 3) / (k - 1)) / k

    ratio, rel_se = [], []
    for normal in normals:
        f = radiance * np.maximum(0.0, w @ normal)[:, None]
        p_cos = np.maximum(0.0, w @ normal) / np.pi
        total = p_env**2 + p_cos**2
        w_env = np.divide(p_env**2, total, out=np.zeros_like(total), where=total > 0)
        (va, m4a), (vb, m4b) = moments(f, p_env, w_env), moments(f, p_cos, 1 - w_env)
        v_cos, m4_cos = moments(f, p_cos, np.ones_like(p_cos))
        v_mis, m4_mis = va + vb, m4a + m4b + 6 * va * vb
        ratio.append(v_mis / v_cos)
        rel_se.append(np.sqrt(rel_var(v_mis, m4_mis, n_mis) + rel_var(v_cos, m4_cos, n_bsdf)))
    return np.array(ratio), np.array(rel_se)


def test_env_sampler_chi2_and_pdf(rng):
    img = _sun_sky()
    h, w = img.shape[:2]
    sampler = _EnvSampler(img)
    n = 200_000
    dirs, pdf = sampler.sample(rng.random((n, 3)))
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(pdf, sampler.pdf(dirs), rtol=1e-12)
    # cells: rows between the map's sample rows, columns between its sample columns
    u, v = direction_to_equirect(dirs)
    i = np.clip(np.floor(v * (h - 1)).astype(int), 0, h - 2)
    j = np.mod(np.floor(u * w - 0.5).astype(int), w)
    z_top, z_bot = np.cos(np.pi * i / (h - 1)), np.cos(np.pi * (i + 1) / (h - 1))
    omega = (z_top - z_bot) * 2 * np.pi / w
    # the pdf integrates to one over the sphere
    zz = np.cos(np.pi * np.arange(h) / (h - 1))
    cell_omega = np.repeat((zz[:-1] - zz[1:]) * 2 * np.pi / w, w)
    centers = np.stack(np.meshgrid(np.arange(h - 1), np.arange(w), indexing="ij"), -1).reshape(-1, 2)
    cz = np.cos(np.pi * (centers[:, 0] + 0.5) / (h - 1))
    cu = (centers[:, 1] + 1.0) / w
    cdir = np.stack([np.sqrt(1 - cz**2) * np.sin(2 * np.pi * cu), cz, -np.sqrt(1 - cz**2) * np.cos(2 * np.pi * cu)], -1)
    cell_pdf = sampler.pdf(cdir)
    assert np.sum(cell_pdf * cell_omega) == pytest.approx(1.0, abs=1e-12)
    # counts per cell follow pdf * solid angle
    expected = cell_pdf * cell_omega * n
    observed = np.bincount(i * w + j, minlength=(h - 1) * w).astype(float)
    keep = expected > 0
    assert observed[~keep].sum() == 0
    assert chisquare(observed[keep], expected[keep] * observed.sum() / expected[keep].sum()).pvalue > CHI2_SIGNIFICANCE
    np.testing.assert_allclose(pdf, cell_pdf[i * w + j])
    # uniform in solid angle inside each cell: (z, phi) fractions on a 4 x 4 grid
    fz = (z_top - dirs[:, 1]) / (z_top - z_bot)
    fu = np.mod(u * w - 0.5, 1.0)
    sub = np.minimum((fz * 4).astype(int), 3) * 4 + np.minimum((fu * 4).astype(int), 3)
    assert chisquare(np.bincount(sub, minlength=16)).pvalue > CHI2_SIGNIFICANCE
    assert np.all(omega > 0)


def _t_moments(n_samples):
    """``E z^2`` and ``Var z^2`` for z Student t with ``nu = n_samples - 1``: ``nu / (nu - 2)`` and
    ``E z^4 - (E z^2)^2`` with ``E z^4 = 3 nu^2 / ((nu - 2)(nu - 4))``."""
    nu = n_samples - 1
    mean_z2 = nu / (nu - 2)
    return mean_z2, 3 * nu * nu / ((nu - 2) * (nu - 4)) - mean_z2**2


def _z_bands(n_samples, n_values):
    """Acceptance bands for ``mean(z^2)`` and ``mean(z)`` of ``n_values`` independent z-scores, each an
    estimate over ``n_samples`` samples against the truth divided by its ``std(ddof=1) / sqrt(n)``.

    For honest errors z is Student t (normal samples; :func:`_t_moments`); the means are held to the normal
    approximation at the suite's two-sided significance ``CHI2_SIGNIFICANCE`` (``mean(z)``: ``MC_SIGMAS`` of
    its standard error). The skew of ``z^2`` moves the realised rate to about 1.4e-3 (simulated)."""
    from scipy.stats import norm

    mean_z2, var_z2 = _t_moments(n_samples)
    half = norm.isf(CHI2_SIGNIFICANCE / 2) * np.sqrt(var_z2 / n_values)
    return (mean_z2 - half, mean_z2 + half), MC_SIGMAS * np.sqrt(mean_z2 / n_values)


def test_t_moments_match_simulated_student_t():
    """The moments behind :func:`_z_bands` against 200,000 Student-t draws with 31 dof: the mean of ``z^2``
    within ``MC_SIGMAS`` standard errors, its variance within ``MC_SIGMAS`` standard errors of a sample
    variance (``sqrt((m4 - var^2) / M)``, from the draws' own eighth moment)."""
    z2 = np.random.default_rng(11).standard_t(31, size=200_000) ** 2
    mean_z2, var_z2 = _t_moments(32)
    assert abs(z2.mean() - mean_z2) <= MC_SIGMAS * np.sqrt(var_z2 / z2.size), (z2.mean(), mean_z2)
    se_var = np.sqrt((np.mean((z2 - mean_z2) ** 4) - var_z2**2) / z2.size)
    assert abs(z2.var(ddof=1) - var_z2) <= MC_SIGMAS * se_var, (z2.var(ddof=1), var_z2, se_var)


def test_standard_errors_are_honest(rng):
    """z-scores of many independent estimates against the truth have unit variance (Student t, 31 dof)."""
    light = AreaLight(center=np.array([0.0, 1.0, 0.0]), u=np.array([0.5, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.5]),
                      radiance=np.ones(3))
    pts = np.column_stack([rng.uniform(-1, 1, 400), np.zeros(400), rng.uniform(-1, 1, 400)])
    nrm = np.tile([0.0, 1.0, 0.0], (400, 1))
    e = irradiance_at(Scene([], [light]), pts, nrm, 32, rng)
    corners = light.center + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) @ np.stack([light.u, light.v])
    z = (e.total[:, 0] - polygon_irradiance(pts, nrm, corners, light.radiance)[:, 0]) / e.stderr[:, 0]
    (lo, hi), mean_band = _z_bands(32, 400)
    assert lo < np.mean(z**2) < hi, (np.mean(z**2), lo, hi)
    assert abs(np.mean(z)) < mean_band


@pytest.mark.slow
def test_standard_errors_are_honest_under_a_smooth_sky_with_sun(rng):
    d = equirect_directions(32, 64)
    sun = np.array([0.5, 0.6, -0.62]) / np.linalg.norm([0.5, 0.6, -0.62])
    img = 0.3 + 0.7 * np.clip(d[..., 1:2], 0, 1) * [0.4, 0.6, 1.0] + np.exp((d @ sun - 1) / 0.02)[..., None] * 30.0
    normals = random_directions(rng, 400)
    scene = Scene([], [EnvironmentLight(image=img)])
    e = irradiance_at(scene, np.zeros((400, 3)), normals, 64, rng)
    truth = _quadrature_irradiance(img, normals, n=(512, 1024))
    z = ((e.total - truth) / e.stderr)[:, 0]
    (lo, hi), mean_band = _z_bands(64, 400)
    assert lo < np.mean(z**2) < hi and abs(np.mean(z)) < mean_band, (np.mean(z**2), lo, hi, np.mean(z))


def test_interreflection_between_two_planes_one_bounce(rng):
    # a white-lit floor below a roof: the roof's underside sees the floor lit by a
    # point light; one bounce equals rho_roof/pi * int L_floor cos over the floor
    floor = grid_plane(size=40.0, res=4)
    scene = Scene([SceneObject("floor", floor, material=diffuse(0.5))],
                  [PointLight(np.array([0.0, 1.0, 0.0]), np.ones(3))])
    # the point (0, 1, 0) facing down receives, after one floor bounce,
    # E1 = int_floor (rho/pi) (I h / r^3) (h / r) (h / r^3) dA = rho I h^3 / pi int r^-7 dA (r^2 = h^2 + s^2)
    # = rho I h^3 / pi * (2 pi / 5) [h^-5 - (h^2 + R^2)^(-5/2)] over a disc of radius R; the square floor of
    # half size 20 is bracketed by the discs of radius 20 and 20 sqrt 2
    est = irradiance_at(scene, [[0.0, 1.0 - 1e-9, 0.0]], [[0.0, -1.0, 0.0]], 20000, rng, bounces=1)
    h, rho = 1.0, 0.5
    disc = lambda R: rho * h**3 / np.pi * 2 * np.pi / 5 * (h**-5 - (h * h + R * R) ** -2.5)  # noqa: E731
    lo, hi = disc(20.0), disc(20.0 * np.sqrt(2))
    assert_within(est.indirect[0], est.indirect_stderr[0], (lo + hi) / 2, extra=(hi - lo) / 2)
    np.testing.assert_array_equal(est.direct, 0.0)  # the light is on the back side


# ---------------------------------------------------------------- kernel tiers


@given(seed=st.integers(0, 2**31 - 1))
def test_bsdf_kernels_match_numpy(seed):
    rng = np.random.default_rng(seed)
    n = 64
    nrm = random_directions(rng, n)
    wo = random_directions(rng, n)
    wi = random_directions(rng, n)
    kd = rng.uniform(0, 1, (n, 3)) * (rng.random((n, 1)) < 0.8)
    ks = rng.uniform(0, 1, (n, 3)) * (rng.random((n, 1)) < 0.7)
    ex = rng.choice([0.0, 1.0, 7.5, 100.0], n)
    fcos, pdf = np.empty((n, 3)), np.empty(n)
    bsdf_eval_kernel(nrm, wo, wi, kd, ks, ex, fcos, pdf)
    f_ref, p_ref = bsdf_eval_numpy(nrm, wo, wi, kd, ks, ex)
    np.testing.assert_allclose(fcos, f_ref, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(pdf, p_ref, rtol=1e-12, atol=1e-300)
    # sampled directions carry weight f cos / pdf of the numpy tier
    wi_s, weight, pdf_s = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    bsdf_sample_kernel(nrm, wo, kd, ks, ex, rng.random((n, 3)), wi_s, weight, pdf_s)
    np.testing.assert_allclose(np.linalg.norm(wi_s, axis=1), 1.0, atol=1e-12)
    f_ref, p_ref = bsdf_eval_numpy(nrm, wo, wi_s, kd, ks, ex)
    np.testing.assert_allclose(pdf_s, p_ref, rtol=1e-12)
    ok = p_ref > 0
    np.testing.assert_allclose(weight[ok], f_ref[ok] / p_ref[ok, None], rtol=1e-10)
    assert np.all(weight[~ok] == 0)


def test_hit_frame_kernel_matches_numpy(rng):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    vn = mesh.vertex_normals
    faces = np.asarray(mesh.faces, dtype=np.int64)
    n = 200
    tri = rng.integers(0, len(faces), n)
    uv = rng.dirichlet([1, 1, 1], n)[:, 1:]
    ng = mesh.face_normals[tri] * np.where(rng.random(n) < 0.2, -1.0, 1.0)[:, None]  # some reversed windings
    wi = random_directions(rng, n)
    ns, ng_out, wo = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
    hit_frame_kernel(np.zeros(n, np.int64), tri, uv, ng, wi, np.zeros(1, np.int64), faces, vn, ns, ng_out, wo)
    f = faces[tri]
    interp = (1 - uv.sum(1))[:, None] * vn[f[:, 0]] + uv[:, :1] * vn[f[:, 1]] + uv[:, 1:] * vn[f[:, 2]]
    interp /= np.linalg.norm(interp, axis=1, keepdims=True)
    interp *= np.sign(np.sum(interp * ng, axis=1))[:, None]
    side = np.where(np.sum(ng * -wi, axis=1) < 0, -1.0, 1.0)[:, None]
    np.testing.assert_allclose(ns, interp * side, atol=1e-12)
    np.testing.assert_allclose(ng_out, ng * side, atol=1e-15)
    np.testing.assert_array_equal(wo, -wi)
    assert np.all(np.sum(ng_out * wo, axis=1) >= 0)


def test_phong_sampler_chi2(rng):
    n = 100_000
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    wo = np.tile([0.5, 0.0, np.sqrt(0.75)], (n, 1))
    kd = np.tile([0.2, 0.2, 0.2], (n, 1))
    ks = np.tile([0.6, 0.6, 0.6], (n, 1))
    ex = np.full(n, 15.0)
    wi, weight, pdf = np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
    bsdf_sample_kernel(nrm, wo, kd, ks, ex, rng.random((n, 3)), wi, weight, pdf)

    def mixture_pdf(w):
        # p_s = sum(ks) / (sum(kd) + sum(ks)) = 0.75; the lobe part also covers directions
        # below the surface (rejected later with weight 0), so no hemisphere cut here
        r = 2 * wo[0, 2] * np.array([0, 0, 1.0]) - wo[0]
        spec = np.maximum(0, w @ r) ** 15
        return 0.25 * np.maximum(w[..., 2], 0) / np.pi + 0.75 * 16 / (2 * np.pi) * spec

    assert chi2_directions(wi, mixture_pdf) > CHI2_SIGNIFICANCE


# --------------------------------------------------------------- entry point


def test_shade_reference_result_layout_and_seed():
    plane = grid_plane(res=3)
    box = trimesh.creation.box(extents=[0.5, 0.5, 0.5])
    scene = Scene(
        [SceneObject("floor", plane, material=diffuse(0.5)),
         SceneObject("box", box, Transform(translate=np.array([0.0, 0.3, 0.0])), diffuse(0.7)),
         SceneObject("window", trimesh.creation.box(), portal=True)],
        [EnvironmentLight(constant=np.ones(3)), PointLight(np.array([1.0, 2.0, 0.0]), np.ones(3))],
    )
    a = shade_reference(scene, bounces=1, n_samples=8, seed=3, progress=False)
    b = shade_reference(scene, bounces=1, n_samples=8, seed=3, progress=False)
    assert set(a.total) == {"floor", "box"}
    for part in ("direct", "indirect", "total"):
        assert getattr(a, part)["floor"].shape == (16, 3)
        assert a.stderr[part]["box"].shape == (len(box.vertices), 3)
        np.testing.assert_array_equal(getattr(a, part)["box"], getattr(b, part)["box"])
    np.testing.assert_allclose(a.total["floor"], a.direct["floor"] + a.indirect["floor"])
    assert a.info["method"] == "reference" and a.info["bounces"] == 1 and a.info["n_samples"] == 8
    assert np.all(a.indirect["floor"] >= 0) and a.indirect["floor"].max() > 0  # the box reflects onto the floor


def test_prtlab_shade_dispatches_to_the_reference():
    import prtlab

    scene = Scene([SceneObject("floor", grid_plane(res=2), material=diffuse(0.5))],
                  [PointLight(np.array([0.0, 2.0, 0.0]), np.ones(3)), EnvironmentLight(constant=np.ones(3))])
    a = prtlab.shade(scene, method="reference", bounces=1, n_samples=4, seed=5, progress=False)
    b = shade_reference(scene, bounces=1, n_samples=4, seed=5, progress=False)
    np.testing.assert_array_equal(a.total["floor"], b.total["floor"])


def test_empty_point_set(rng):
    scene = Scene([], [EnvironmentLight(constant=np.ones(3))])
    e = irradiance_at(scene, np.zeros((0, 3)), np.zeros((0, 3)), 4, rng)
    assert e.total.shape == (0, 3) and e.stderr.shape == (0, 3)


def test_errors(rng):
    scene = Scene([], [EnvironmentLight(constant=np.ones(3))])
    with pytest.raises(TypeError, match="scene must be a prtlab.Scene"):
        path_trace("scene.yaml", 1, 4, rng)
    with pytest.raises(ValueError, match="bounces must be an int >= 0"):
        path_trace(scene, -1, 4, rng)
    with pytest.raises(ValueError, match="n_samples must be an int >= 2"):
        direct(scene, 1, rng)
    with pytest.raises(TypeError, match="rng must be a numpy.random.Generator"):
        path_trace(scene, 0, 4, 42)
    with pytest.raises(TypeError, match="seed must be an int"):
        shade_reference(scene, seed="x")
    with pytest.raises(ValueError, match=r"points must be a \(\.\.\., 3\) array"):
        irradiance_at(scene, np.zeros((2, 2)), np.zeros((2, 3)), 4, rng)
    with pytest.raises(ValueError, match="normals contains NaN"):
        irradiance_at(scene, np.zeros((2, 3)), np.full((2, 3), np.nan), 4, rng)
    with pytest.raises(ValueError, match="env_sampling must be 'mis'"):
        direct(scene, 4, rng, env_sampling="nee")
    with pytest.raises(TypeError, match="area_lights_block must be True or False"):
        direct(scene, 4, rng, area_lights_block="yes")
    with pytest.raises(ValueError, match="view_dirs of shape"):
        radiance_at(scene, np.zeros((2, 3)), np.ones((2, 3)), np.ones((3, 3)), 4, rng)
