"""The Mitsuba 3 adapter: variant choice, scene translation, and known answers."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from prtlab.reference._mitsuba import LLVM_LIBRARIES, MitsubaUnavailable, _choose_variant
from prtlab.scene import AreaLight, Camera, EnvironmentLight, Material, PointLight, Scene, SceneObject, Transform
from tests.conftest import MC_SIGMAS, random_directions

# --------------------------------------------------------------------------- variant choice (no mitsuba needed)


def _exists_only(*paths):
    return lambda p: p in paths


def test_variant_llvm_when_libllvm19_present():
    variant, lib = _choose_variant(None, {}, _exists_only(LLVM_LIBRARIES[1]), drjit_imported=False)
    assert variant == "llvm_ad_rgb"
    assert lib == LLVM_LIBRARIES[1]


def test_variant_falls_back_to_scalar_without_libllvm19():
    assert _choose_variant(None, {}, _exists_only(), drjit_imported=False) == ("scalar_rgb", None)


def test_variant_falls_back_when_drjit_already_imported_without_path():
    # DRJIT_LIBLLVM_PATH can no longer take effect: do not risk Dr.Jit's default LLVM.
    assert _choose_variant(None, {}, _exists_only(*LLVM_LIBRARIES), drjit_imported=True) == ("scalar_rgb", None)


def test_variant_respects_user_llvm_path():
    env = {"DRJIT_LIBLLVM_PATH": "/opt/llvm/libLLVM.so"}
    assert _choose_variant(None, env, _exists_only(), drjit_imported=True) == ("llvm_ad_rgb", None)


def test_variant_forced_by_environment_variable():
    env = {"PRTLAB_MITSUBA_VARIANT": "scalar_rgb"}
    assert _choose_variant(None, env, _exists_only(*LLVM_LIBRARIES), drjit_imported=False) == ("scalar_rgb", None)


def test_variant_rejects_unknown_name():
    with pytest.raises(ValueError, match="variant must be one of"):
        _choose_variant("cuda_ad_rgb", {}, _exists_only(), drjit_imported=False)


def test_variant_llvm_requested_without_library_is_a_clear_error():
    with pytest.raises(MitsubaUnavailable, match="libllvm19"):
        _choose_variant("llvm_ad_rgb", {}, _exists_only(), drjit_imported=False)


def test_missing_mitsuba_raises_mitsuba_unavailable(monkeypatch):
    from prtlab.reference import _mitsuba

    monkeypatch.setitem(sys.modules, "mitsuba", None)
    monkeypatch.setitem(sys.modules, "drjit", None)
    with pytest.raises(MitsubaUnavailable, match=r"pip install 'prtlab\[reference\]'"):
        _mitsuba._import_mitsuba("scalar_rgb")


# --------------------------------------------------------------------------- scenes


def _plane_mesh(size=2.0, resolution=2):
    from prtlab.geometry import builtin_mesh

    return builtin_mesh("plane", size=[size, size], resolution=[resolution, resolution])


def _plane_scene(material, lights, resolution=2):
    floor = SceneObject("floor", _plane_mesh(resolution=resolution), material=material)
    camera = Camera(position=np.array([0.3, 3.0, 2.0]), look_at=np.zeros(3), resolution=(16, 12))
    return Scene(objects=[floor], lights=list(lights), camera=camera)


def _assert_within_stderr(estimate, stderr, truth, sigmas=MC_SIGMAS):
    estimate, stderr, truth = np.broadcast_arrays(estimate, stderr, truth)
    assert np.all(stderr > 0)
    z = (estimate - truth) / stderr
    assert np.all(np.abs(z) < sigmas), f"max |z| = {np.abs(z).max():.2f}"


def _polygon_irradiance(point, normal, corners):
    """Exact irradiance factor of a polygon of unit radiance (Lambert's formula), one-sided.

    ``E = 1/2 sum_i acos(v_i . v_(i+1)) normalize(v_i x v_(i+1)) . n`` with ``v_i`` the unit
    vectors to the corners, ordered so the polygon is seen counter-clockwise from the point.
    """
    v = corners - point
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    total = 0.0
    for i in range(len(v)):
        a, b = v[i], v[(i + 1) % len(v)]
        g = np.cross(a, b)
        total += np.arccos(np.clip(a @ b, -1, 1)) * (g / np.linalg.norm(g)) @ normal
    return 0.5 * abs(total)


mitsuba = pytest.mark.mitsuba


def _v(cls, a):
    """A Dr.Jit 3-vector from an (n, 3) numpy array."""
    a = np.asarray(a, dtype=np.float32)
    return cls(*(np.ascontiguousarray(c) for c in a.T))


@pytest.fixture(scope="module")
def mi_dr():
    pytest.importorskip("mitsuba")
    from prtlab.reference._mitsuba import _import_mitsuba

    return _import_mitsuba()


# --------------------------------------------------------------------------- translation


@mitsuba
def test_envmap_orientation_matches_design_convention(mi_dr):
    """A single bright texel: Mitsuba's envmap is bright exactly where prtlab's lookup is."""
    mi, dr = mi_dr
    from prtlab.geometry import equirect_directions, equirect_lookup

    from prtlab.reference import to_mitsuba

    h, w = 9, 16
    image = np.zeros((h, w, 3))
    i0, j0 = 3, 5
    image[i0, j0] = [100.0, 50.0, 25.0]
    scene = _plane_scene(Material(), [EnvironmentLight(image=image)])
    mscene = mi.load_dict(to_mitsuba(scene, sensor=False))
    env = mscene.environment()
    rng = np.random.default_rng(5)
    dirs = np.concatenate([equirect_directions(h, w)[1:-1].reshape(-1, 3), random_directions(rng, 4000)])
    si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
    si.wi = _v(mi.Vector3f, -dirs)
    ours = equirect_lookup(image, dirs)
    theirs = np.asarray(env.eval(si), dtype=np.float64).reshape(3, -1).T
    np.testing.assert_allclose(theirs, ours, rtol=1e-4, atol=1e-3)
    # the texel's own direction holds its value; importance sampling lands around it
    texel_dir = equirect_directions(h, w)[i0, j0]
    assert np.argmax(theirs[: (h - 2) * w, 0]) == (i0 - 1) * w + j0
    ref = dr.zeros(mi.Interaction3f, 2000)
    samples = np.ascontiguousarray(rng.random((2, 2000)).astype(np.float32))
    ds, _ = env.sample_direction(ref, mi.Point2f(samples[0], samples[1]))
    sampled = np.asarray(ds.d, dtype=np.float64).reshape(3, -1).T
    mean_dir = sampled.mean(axis=0)
    mean_dir /= np.linalg.norm(mean_dir)
    assert np.degrees(np.arccos(np.clip(mean_dir @ texel_dir, -1, 1))) < 12.0


@mitsuba
def test_to_mitsuba_keeps_vertices_and_faces(mi_dr):
    mi, _ = mi_dr
    from prtlab.reference import to_mitsuba

    obj = SceneObject("floor", _plane_mesh(resolution=3), Transform(np.array([1.0, 2.0, 3.0]), np.array([10.0, 20, 30])))
    scene = Scene(objects=[obj], lights=[EnvironmentLight(constant=np.ones(3))])
    desc = to_mitsuba(scene)
    params = mi.traverse(desc["object_0"])
    verts = np.asarray(params["vertex_positions"]).reshape(-1, 3)
    faces = np.asarray(params["faces"]).reshape(-1, 3)
    np.testing.assert_allclose(verts, obj.world_vertices(), atol=1e-5)
    np.testing.assert_array_equal(faces, obj.mesh.faces)
    assert desc["sensor"]["fov_axis"] == "y"


@mitsuba
def test_rectangle_covers_the_parallelogram_and_emits_one_side(mi_dr):
    mi, dr = mi_dr
    from prtlab.reference import to_mitsuba

    light = AreaLight(np.array([0.0, 2.0, 0.0]), np.array([0.5, 0.0, 0.2]), np.array([0.0, 0.0, -0.3]),
                      np.array([2.0, 3.0, 4.0]))
    scene = _plane_scene(Material(), [light])
    mscene = mi.load_dict(to_mitsuba(scene, sensor=False))
    rng = np.random.default_rng(1)
    st = rng.uniform(-0.98, 0.98, size=(50, 2))
    targets = light.center + st[:, :1] * light.u + st[:, 1:] * light.v
    n = light.normal
    for side, expect in ((+1.0, light.radiance), (-1.0, np.zeros(3))):
        origins = targets + side * n
        d = targets - origins
        ray = mi.Ray3f(_v(mi.Point3f, origins), _v(mi.Vector3f, d))
        si = mscene.ray_intersect(ray)
        assert np.all(np.asarray(si.is_valid()))
        np.testing.assert_allclose(np.asarray(si.t), 1.0, atol=1e-5)
        le = np.asarray(si.emitter(mscene).eval(si)).reshape(3, -1).T
        np.testing.assert_allclose(le, np.broadcast_to(expect, le.shape), rtol=1e-6)
    # just outside the parallelogram the ray passes the light (and hits the floor far below)
    out = light.center + 1.05 * light.u + n
    ray = mi.Ray3f(_v(mi.Point3f, out[None]), _v(mi.Vector3f, -n[None]))
    assert float(np.asarray(mscene.ray_intersect(ray).t)[0]) > 1.5


@mitsuba
def test_phong_bsdf_matches_closed_form(mi_dr):
    mi, dr = mi_dr
    kd, ks, e = np.array([0.3, 0.2, 0.1]), np.array([0.4, 0.5, 0.6]), 12.0
    bsdf = mi.load_dict({"type": "prtlab_phong", "kd": kd.tolist(), "ks": ks.tolist(), "exponent": e})
    rng = np.random.default_rng(2)
    wi = random_directions(rng, 500)
    wi[:, 2] = np.abs(wi[:, 2])
    wo = random_directions(rng, 500)
    wo[:, 2] = np.abs(wo[:, 2])
    si = dr.zeros(mi.SurfaceInteraction3f, 500)
    si.wi = _v(mi.Vector3f, wi)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    ctx = mi.BSDFContext()
    value = np.asarray(bsdf.eval(ctx, si, _v(mi.Vector3f, wo))).reshape(3, -1).T
    r = np.stack([-wi[:, 0], -wi[:, 1], wi[:, 2]], axis=1)
    c = np.maximum(np.sum(r * wo, axis=1), 0)
    expect = (kd / np.pi + ks * ((e + 2) / (2 * np.pi) * c**e)[:, None]) * wo[:, 2:3]
    np.testing.assert_allclose(value, expect, rtol=2e-4, atol=1e-6)
    # the sampling weight is eval / pdf, and the pdf integrates to one over the hemisphere
    n = 200_000
    s = np.ascontiguousarray(rng.random((3, n)).astype(np.float32))
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(0.3, 0.1, float(np.sqrt(0.9)))
    bs, weight = bsdf.sample(ctx, si, mi.Float(s[0]), mi.Point2f(s[1], s[2]))
    val, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    weight = np.asarray(weight).reshape(3, -1).T
    ratio = np.asarray(val).reshape(3, -1).T / np.maximum(np.asarray(pdf), 1e-30)[:, None]
    np.testing.assert_allclose(weight, ratio, rtol=1e-4, atol=1e-6)
    u = random_directions(rng, n)
    u[:, 2] = np.abs(u[:, 2])
    pdf_u = np.asarray(bsdf.pdf(ctx, si, _v(mi.Vector3f, u)), dtype=np.float64)
    integral = pdf_u * 2 * np.pi
    assert abs(integral.mean() - 1.0) < MC_SIGMAS * integral.std() / np.sqrt(n)


# --------------------------------------------------------------------------- known answers


@mitsuba
@pytest.mark.parametrize("bounces", [0, 2])
def test_constant_environment_furnace_on_a_plane(mi_dr, bounces):
    """A lone two-sided plane under a constant sky: L_o = albedo * L (irradiance pi * L)."""
    from prtlab.reference import shade_mitsuba

    albedo, sky = np.array([0.5, 0.6, 0.8]), np.array([1.0, 2.0, 0.5])
    scene = _plane_scene(Material(albedo=albedo), [EnvironmentLight(constant=sky)])
    res = shade_mitsuba(scene, bounces=bounces, spp=256, seed=3)
    _assert_within_stderr(res.total["floor"], res.stderr["total"]["floor"], albedo * sky)
    np.testing.assert_array_equal(res.indirect["floor"], 0.0)
    np.testing.assert_allclose(res.total["floor"], res.direct["floor"] + res.indirect["floor"])


@mitsuba
def test_constant_environment_phong_plane_against_quadrature(mi_dr):
    """Normalised Phong under a constant sky: kd L + ks L int (e+2)/(2pi) cos^e(alpha) cos(theta) dw."""
    from scipy import integrate

    from prtlab.reference import shade_mitsuba

    kd, ks, e = np.array([0.2, 0.3, 0.1]), np.array([0.5, 0.3, 0.6]), 20.0
    scene = _plane_scene(Material(type="phong", kd=kd, ks=ks, exponent=e), [EnvironmentLight(constant=np.ones(3))])
    res = shade_mitsuba(scene, bounces=0, spp=512, seed=4)
    obj = scene.objects[0]
    p = obj.world_vertices()
    for k in range(len(p)):
        wo = scene.camera.position - p[k]
        wo /= np.linalg.norm(wo)
        r = np.array([-wo[0], wo[1], -wo[2]])  # mirror about +Y

        def integrand(phi, theta):
            wi = np.array([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)])
            return (e + 2) / (2 * np.pi) * max(wi @ r, 0.0) ** e * np.cos(theta) * np.sin(theta)

        spec, _ = integrate.dblquad(integrand, 0, np.pi / 2, 0, 2 * np.pi, epsabs=1e-7)
        _assert_within_stderr(res.total["floor"][k], res.stderr["total"]["floor"][k], kd + ks * spec)


@mitsuba
def test_small_area_light_on_a_plane_against_closed_form(mi_dr):
    """A small square light high above a plane: L_o = albedo / pi * L * (exact polygon form factor)."""
    from prtlab.reference import shade_mitsuba

    albedo, radiance = np.array([0.7, 0.5, 0.3]), np.array([40.0, 30.0, 20.0])
    light = AreaLight(np.array([0.2, 2.5, -0.1]), np.array([0.1, 0.0, 0.0]), np.array([0.0, 0.0, 0.1]), radiance)
    assert light.normal[1] < 0  # cross(+x, +z) = -y: it shines down
    scene = _plane_scene(Material(albedo=albedo), [light], resolution=3)
    res = shade_mitsuba(scene, bounces=1, spp=1024, seed=5)
    corners = np.array([light.center + s * light.u + t * light.v for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    p = scene.objects[0].world_vertices()
    truth = np.array([albedo / np.pi * radiance * _polygon_irradiance(q, np.array([0, 1.0, 0]), corners) for q in p])
    _assert_within_stderr(res.direct["floor"], res.stderr["direct"]["floor"], truth)
    np.testing.assert_array_equal(res.indirect["floor"], 0.0)
    # upside down, the one-sided light does not reach the floor at all
    flipped = AreaLight(light.center, light.v, light.u, radiance)
    res = shade_mitsuba(_plane_scene(Material(albedo=albedo), [flipped]), bounces=0, spp=16, seed=6)
    np.testing.assert_array_equal(res.total["floor"], 0.0)


@mitsuba
def test_point_light_on_a_plane(mi_dr):
    from prtlab.reference import shade_mitsuba

    albedo, intensity, pos = np.array([0.6, 0.6, 0.6]), np.array([5.0, 4.0, 3.0]), np.array([0.3, 1.5, 0.2])
    scene = _plane_scene(Material(albedo=albedo), [PointLight(pos, intensity)])
    res = shade_mitsuba(scene, bounces=0, spp=4, seed=7)
    p = scene.objects[0].world_shading_points()
    d = pos - p
    r2 = np.sum(d * d, axis=1)
    truth = albedo / np.pi * intensity * (d[:, 1] / np.sqrt(r2) / r2)[:, None]
    np.testing.assert_allclose(res.direct["floor"], truth, rtol=1e-4)


@mitsuba
def test_prtlab_shade_dispatches_to_mitsuba(mi_dr):
    import prtlab

    albedo, sky = np.array([0.5, 0.6, 0.8]), np.array([1.0, 2.0, 0.5])
    scene = _plane_scene(Material(albedo=albedo), [EnvironmentLight(constant=sky)])
    res = prtlab.shade(scene, method="mitsuba", bounces=0, n_samples=64, seed=1)
    assert res.info["method"] == "mitsuba" and res.info["spp"] == 64
    _assert_within_stderr(res.total["floor"], res.stderr["total"]["floor"], albedo * sky)


@mitsuba
def test_indirect_appears_with_bounces_between_facing_planes(mi_dr):
    """Two facing planes under a constant sky: indirect is zero at bounces=0, positive at 1."""
    from prtlab.reference import shade_mitsuba

    floor = SceneObject("floor", _plane_mesh(resolution=1), material=Material(albedo=np.full(3, 0.8)))
    ceiling = SceneObject("ceiling", _plane_mesh(resolution=1), Transform(np.array([0, 0.5, 0.0]), np.array([180.0, 0, 0])),
                          Material(albedo=np.full(3, 0.8)))
    scene = Scene(objects=[floor, ceiling], lights=[EnvironmentLight(constant=np.ones(3))],
                  camera=Camera(position=np.array([0, 0.25, 5.0])))
    r0 = shade_mitsuba(scene, bounces=0, spp=64, seed=8)
    r1 = shade_mitsuba(scene, bounces=1, spp=64, seed=8)
    np.testing.assert_array_equal(r0.indirect["floor"], 0.0)
    assert np.all(r1.indirect["floor"] > 0) and np.all(r1.indirect["ceiling"] > 0)
    # same seed: the direct part is the same estimate whatever the bounce limit
    np.testing.assert_allclose(r0.direct["floor"], r1.direct["floor"])


@mitsuba
def test_scalar_fallback_agrees_with_llvm():
    """The scalar_rgb path (the fallback) gives the same answer as llvm_ad_rgb within errors."""
    pytest.importorskip("mitsuba")
    from prtlab.reference import shade_mitsuba

    albedo = np.array([0.5, 0.5, 0.5])
    light = AreaLight(np.array([0.0, 1.5, 0.0]), np.array([0.3, 0, 0]), np.array([0, 0, 0.3]), np.full(3, 8.0))
    scene = _plane_scene(Material(albedo=albedo), [light, EnvironmentLight(constant=np.full(3, 0.2))], resolution=1)
    a = shade_mitsuba(scene, bounces=0, spp=64, seed=9, variant="scalar_rgb")
    b = shade_mitsuba(scene, bounces=0, spp=256, seed=9, variant="llvm_ad_rgb")
    assert a.info["variant"] == "scalar_rgb" and b.info["variant"] == "llvm_ad_rgb"
    err = np.hypot(a.stderr["total"]["floor"], b.stderr["total"]["floor"])
    z = (a.total["floor"] - b.total["floor"]) / err
    assert np.all(np.abs(z) < MC_SIGMAS)


@mitsuba
def test_render_mitsuba_image_shape_and_sky(mi_dr):
    from prtlab.reference import render_mitsuba

    scene = _plane_scene(Material(albedo=np.full(3, 0.5)), [EnvironmentLight(constant=np.array([1.0, 2.0, 3.0]))])
    scene.camera = Camera(position=np.array([0, 1.0, 5.0]), look_at=np.array([0, 1.0, 0]), resolution=(8, 6))
    img = render_mitsuba(scene, spp=16, bounces=0)
    assert img.shape == (6, 8, 3)
    # the top row looks at the sky, the bottom rows at the lit floor (albedo * sky)
    np.testing.assert_allclose(img[0], np.broadcast_to([1.0, 2.0, 3.0], (8, 3)), rtol=1e-5)


# --------------------------------------------------------------------------- errors


@mitsuba
def test_errors(mi_dr):
    from prtlab.reference import render_mitsuba, shade_mitsuba, to_mitsuba

    scene = _plane_scene(Material(), [EnvironmentLight(constant=np.ones(3))])
    with pytest.raises(TypeError, match="scene must be a prtlab.Scene"):
        to_mitsuba({"objects": []})
    with pytest.raises(ValueError, match="scene has no objects"):
        shade_mitsuba(Scene())
    with pytest.raises(ValueError, match="bounces must be an int >= 0"):
        shade_mitsuba(scene, bounces=-1)
    with pytest.raises(TypeError, match="bounces must be an int"):
        shade_mitsuba(scene, bounces=1.5)
    with pytest.raises(ValueError, match=r"spp \(n_samples\) must be an int >= 2"):
        shade_mitsuba(scene, spp=1)
    with pytest.raises(TypeError, match="seed must be an int"):
        shade_mitsuba(scene, seed="x")
    with pytest.raises(ValueError, match="offset must be a finite float"):
        shade_mitsuba(scene, offset=float("nan"))
    with pytest.raises(ValueError, match="chunk_rays must be >= 1"):
        shade_mitsuba(scene, chunk_rays=0)
    with pytest.raises(ValueError, match="spp must be an int >= 1"):
        render_mitsuba(scene, spp=0)
    bad = _plane_scene(Material(type="glass"), [EnvironmentLight(constant=np.ones(3))])
    with pytest.raises(NotImplementedError, match="object 'floor': material type 'glass'"):
        to_mitsuba(bad)
    with pytest.raises(NotImplementedError, match="light 1 of type str has no Mitsuba translation"):
        to_mitsuba(_plane_scene(Material(), [EnvironmentLight(constant=np.ones(3)), "sun"]))
    import trimesh

    empty = _plane_scene(Material(), [EnvironmentLight(constant=np.ones(3))])
    empty.objects[0].mesh = trimesh.Trimesh(vertices=np.zeros((3, 3)), faces=np.zeros((0, 3), int), process=False)
    with pytest.raises(ValueError, match="object 'floor' has a mesh with no faces"):
        to_mitsuba(empty)
    nan_scene = _plane_scene(Material(), [EnvironmentLight(constant=np.ones(3))])
    nan_scene.objects[0].transform = Transform(np.array([np.nan, 0, 0]))
    with pytest.raises(ValueError, match="NaN or inf"):
        shade_mitsuba(nan_scene)


@mitsuba
def test_render_mitsuba_matches_prtlab_camera_pixel_for_pixel(mi_dr):
    """An off-centre black ball against a white sky, non-square image: the silhouettes coincide."""
    from scipy import ndimage

    from prtlab.geometry import builtin_mesh
    from prtlab.reference import render_mitsuba
    from prtlab.render import render_image
    from prtlab.scene import ShadeResult

    ball = SceneObject("ball", builtin_mesh("icosphere", radius=0.5, subdivisions=4), Transform(np.array([-0.7, 0.4, 0.0])),
                       Material(albedo=np.zeros(3)))
    camera = Camera(position=np.array([0.0, 0.0, 4.0]), look_at=np.zeros(3), fov_deg=35.0, resolution=(40, 24))
    scene = Scene(objects=[ball], lights=[EnvironmentLight(constant=np.ones(3))], camera=camera)
    theirs = render_mitsuba(scene, spp=64, bounces=0)[..., 0]
    black = ShadeResult(total={"ball": np.zeros((ball.n_vertices, 3))})
    ours = render_image(scene, black)[..., 0]
    inside = ndimage.binary_erosion(ours == 0.0)
    outside = ndimage.binary_erosion(ours == 1.0)
    assert inside.sum() > 20 and outside.sum() > 500
    np.testing.assert_allclose(theirs[inside], 0.0, atol=1e-6)
    np.testing.assert_allclose(theirs[outside], 1.0, atol=1e-5)
