"""Tests of prtlab.spherelights._pipeline (the Precomputation subclass and prtlab.shade)."""

import numpy as np
import pytest

import prtlab
from prtlab.pipeline import FrameState
from prtlab.scene import Scene, Transform
from prtlab.spherelights import SphereLights
from tests.conftest import MC_SIGMAS


def _scene(constant=(1.0, 0.9, 0.8), lights=None):
    return Scene.from_dict({
        "objects": [
            {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [8, 8]},
             "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 2},
             "transform": {"translate": [0.3, 0.6, -0.2]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.2]}, "dynamic": True},
            {"name": "box", "mesh": {"builtin": "box", "size": [0.6, 0.6, 0.6], "subdivisions": 1},
             "transform": {"translate": [-0.9, 0.3, 0.4], "rotate_deg": [0, 30, 0]},
             "material": {"type": "diffuse", "albedo": [0.3, 0.6, 0.8]}, "dynamic": True},
        ],
        "lights": lights if lights is not None else [{"type": "environment", "constant": list(constant)}],
    })


@pytest.fixture(scope="module")
def pre():
    return SphereLights.precompute(_scene(), {"n_spheres": 2, "fit_resolution": 16}, cache=False, progress=False)


def _moved(pre, f):
    """FrameState with every object's transform composed with the similarity ``f``."""
    return FrameState(transforms={o.name: f(o.transform) for o in pre.scene.objects}, lights=list(pre.scene.lights))


def test_shade_through_the_api(tmp_path):
    res = prtlab.shade(_scene(), method="spherelights", bounces=1, cache=False, progress=False,
                       n_spheres=1, fit_resolution=16)
    for name in ("plane", "ball", "box"):
        assert res.total[name].shape == res.direct[name].shape
        assert np.all(np.isfinite(res.total[name]))
        np.testing.assert_allclose(res.total[name], res.direct[name] + res.indirect[name])
    # the spheres light the plane (positive indirect somewhere) and bounces=0 removes it
    assert res.indirect["plane"].max() > 0
    res0 = prtlab.shade(_scene(), method="spherelights", bounces=0, cache=False, progress=False,
                        n_spheres=1, fit_resolution=16)
    assert np.all(res0.indirect["plane"] == 0)
    np.testing.assert_allclose(res0.direct["plane"], res.direct["plane"])


def test_emission_order():
    """``emission_order`` up to ``order`` is the paper's single order (the same result); a higher one changes only
    the indirect light, and is part of the cache key (the albedo SH is precomputed at it)."""
    sc = _scene(lights=[{"type": "environment", "sky": {"sun_elevation_deg": 40.0, "sun": False,
                                                        "height": 32, "width": 64}}])
    opts = {"n_spheres": 2, "fit_resolution": 16}
    pres = {m: SphereLights.precompute(sc, dict(opts, emission_order=m), cache=False, progress=False) for m in (0, 4, 6)}
    res = {m: pre.shade(bounces=1) for m, pre in pres.items()}
    for name in ("plane", "ball", "box"):
        np.testing.assert_array_equal(res[0].total[name], res[4].total[name])
        np.testing.assert_array_equal(res[6].direct[name], res[4].direct[name])
    assert any(np.abs(res[6].indirect[n] - res[4].indirect[n]).max() > 1e-4 for n in ("plane", "ball", "box"))
    key = {m: SphereLights.cache_key_parts(sc, SphereLights.make_options(dict(opts, emission_order=m)))[-1]
           for m in (4, 6)}
    assert key[4]["emission_order"] == 4 and key[6]["emission_order"] == 6
    with pytest.raises(ValueError, match="emission_order"):
        SphereLights.make_options({"emission_order": 9})
    # data precomputed at a higher emission order shades a lower one exactly (the SH nest by order), not the reverse
    lower = SphereLights(sc, pres[4].options, pres[6].data).shade(bounces=1)
    for name in ("plane", "ball", "box"):
        np.testing.assert_array_equal(lower.total[name], res[4].total[name])
    with pytest.raises(ValueError, match="below the emission order 6"):
        SphereLights(sc, pres[6].options, pres[4].data).shade(bounces=1)


def test_unoccluded_plane_vertex_gets_the_constant_environment(pre):
    res = pre.shade(bounces=0)
    # far corner of the plane: tiny spheres' shadow; E = pi L for a constant environment
    corner = np.argmax(np.linalg.norm(pre.scene.object("plane").world_vertices(), axis=1))
    np.testing.assert_allclose(res.direct["plane"][corner], 0.7 * np.array([1.0, 0.9, 0.8]), rtol=0.02)


@pytest.mark.parametrize("kind", ["translate", "rotate", "scale"])
def test_similarity_of_the_whole_scene_changes_nothing(pre, kind):
    """Under a constant environment, moving every object by one similarity leaves each vertex's radiance
    unchanged: lights rotate by their ``w_theta`` (Sec. 7.1), blockers move with the centres."""
    base = pre.shade(bounces=1)
    R = Transform(rotate_deg=np.array([0.0, 70.0, 0.0])).rotation
    s = 1.7

    def move(t):
        if kind == "translate":
            return Transform(translate=t.translate + [2.0, 0.0, -1.0], rotate_deg=t.rotate_deg, scale=t.scale)
        if kind == "scale":
            return Transform(translate=s * t.translate, rotate_deg=t.rotate_deg, scale=s * t.scale)
        from prtlab.scene import matrix_to_euler

        return Transform(translate=R @ t.translate, rotate_deg=matrix_to_euler(R @ t.rotation), scale=t.scale)

    moved = pre.shade(_moved(pre, move), bounces=1)
    for name in base.total:
        np.testing.assert_allclose(moved.direct[name], base.direct[name], atol=1e-8)
        np.testing.assert_allclose(moved.indirect[name], base.indirect[name], atol=1e-8)


def test_blocking_and_exp_methods_run(pre):
    for blocking in ("object", "sphere"):
        for exp_method in ("hyb", "ol", "exact"):
            p = SphereLights(pre.scene, SphereLights.make_options(
                {"n_spheres": 2, "fit_resolution": 16, "blocking": blocking, "exp_method": exp_method}), pre.data)
            res = p.shade(bounces=1)
            assert np.all(np.isfinite(res.total["plane"]))


def test_errors(pre):
    with pytest.raises(ValueError, match="at most 2 indirect bounce"):
        pre.shade(bounces=3)
    with pytest.raises(ValueError, match="exp_method must be"):
        SphereLights.make_options({"exp_method": "taylor"})
    with pytest.raises(ValueError, match="blocking must be"):
        SphereLights.make_options({"blocking": "pixel"})
    with pytest.raises(ValueError, match="option order must be an int >= 1 and <= 8, got 9"):
        SphereLights.make_options({"order": 9})
    scene = _scene(lights=[{"type": "point", "position": [0, 3, 0], "intensity": [1, 1, 1]}])
    p = SphereLights(scene, pre.options, pre.data)
    with pytest.raises(ValueError, match="environment lighting only"):
        p.shade(bounces=1)


def test_emission_coverage(pre):
    """``emission_coverage``: the direct light and the ground's light do not change; an object's lights send less
    light to the other objects in all (the fitted spheres bound the box and the ball: their segments fill only part of
    their discs); False is the paper's emission."""
    from dataclasses import replace

    paper = SphereLights(pre.scene, replace(pre.options, emission_coverage=False), pre.data).shade(bounces=1)
    cov = pre.shade(bounces=1)
    assert pre.options.emission_coverage
    for name in ("plane", "ball", "box"):
        np.testing.assert_array_equal(cov.direct[name], paper.direct[name])
    np.testing.assert_array_equal(cov.indirect["plane"], paper.indirect["plane"])  # gathered by rays
    for name in ("ball", "box"):
        assert cov.indirect[name].sum() < paper.indirect[name].sum()
    data = pre.data["objects"]["box"]
    assert data["segment_coverage"].shape == data["sample_valid"].shape
    assert np.all((data["segment_coverage"] >= 0) & (data["segment_coverage"] <= 1))
    with pytest.raises(TypeError, match="option emission_coverage must be True or False"):
        SphereLights.make_options({"emission_coverage": 1})


def test_the_papers_options_turn_every_extension_off(pre):
    """``PAPER_OPTIONS`` are options of the pipeline, and a frame of a scene with a ground shaded with them
    computes none of the extensions' geometry (no ray against the meshes, no ground term, no near blocker's cap:
    ``info["geometry"]`` names nothing); each of ``ground="reflects"``, ``mesh_blockers=True`` and
    ``near_blockers=2`` turned back on computes some. The paper's ground neither hides nor reflects, so the ball's
    lowest vertex gets more direct light (the environment below the horizon) and no light from the ground."""
    import dataclasses

    from prtlab.spherelights import PAPER_OPTIONS, SphereLightOptions

    assert set(PAPER_OPTIONS) <= {f.name for f in dataclasses.fields(SphereLightOptions)}
    opts = {"n_spheres": {"ball": 1, "box": 2}, "fit_resolution": 16}  # the ball's light may block exactly
    paper = SphereLights.precompute(pre.scene, {**opts, **PAPER_OPTIONS}, cache=False, progress=False)
    assert all(getattr(paper.options, k) == v for k, v in PAPER_OPTIONS.items())
    res = paper.shade(bounces=1)
    assert res.info["geometry"] == {"computed": [], "reused": [], "updated": []}
    for change in ({"ground": "reflects"}, {"mesh_blockers": True}, {"near_blockers": 2}):
        again = SphereLights(paper.scene, dataclasses.replace(paper.options, **change), paper.data)
        assert again.shade(bounces=1).info["geometry"]["computed"], change
    full = SphereLights(paper.scene, dataclasses.replace(paper.options, ground="reflects"), paper.data).shade(bounces=1)
    low = int(np.argmin(paper.scene.object("ball").mesh.vertices[:, 1]))
    assert np.all(res.direct["ball"][low] > full.direct["ball"][low])
    assert np.all(res.total["ball"] >= 0) and np.all(np.isfinite(res.total["plane"]))


def test_objects_with_different_sphere_counts():
    pre = SphereLights.precompute(_scene(), {"n_spheres": {"ball": 1, "box": 3}, "fit_resolution": 12},
                                  cache=False, progress=False)
    centres, radii, sl_object, inter, *_ = pre.world_lights(FrameState.from_scene(pre.scene))
    assert radii.shape == (4,) and inter.shape == (4, 4)
    assert not inter[:1, 1:].any()  # lights of different objects never count as intersecting
    assert np.all(np.isfinite(pre.shade(bounces=1).total["plane"]))


def test_ground_option_hides_and_reflects(pre):
    """``ground="paper"``: the ground neither hides nor reflects (the paper); ``"blocks"``: it hides the environment
    from the first pass's samples (less light on the ground) and from the objects (less direct light on them);
    ``"reflects"`` (default): as ``"blocks"``, plus its light reaching the objects (more indirect light). The
    ground's own rows are compared with the ground shaded through the lights (``ground_shading="lights"``); with
    rays (the default) its light does not depend on what it reflects, and ``ground="paper"`` shades it through
    the lights."""
    from prtlab.spherelights import ground_rectangles

    rect = ground_rectangles([pre.scene.object("plane")])
    np.testing.assert_allclose(rect, [[0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0]], atol=1e-12)  # 4 x 4 plane at y = 0
    assert ground_rectangles([pre.scene.object("ball")]).shape == (0, 7)  # not flat: no ground
    assert pre.options.ground == "reflects"

    def variant(ground, shading="lights"):
        opts = SphereLights.make_options({"n_spheres": 2, "fit_resolution": 16, "ground": ground,
                                          "ground_shading": shading})
        return SphereLights(pre.scene, opts, pre.data).shade(bounces=1)

    a, blocks, paper = variant("reflects"), variant("blocks"), variant("paper")
    rays = {g: variant(g, "rays") for g in ("reflects", "blocks", "paper")}
    default = pre.shade(bounces=1)
    assert pre.options.ground_shading == "rays"
    for part in ("direct", "indirect"):
        np.testing.assert_array_equal(getattr(rays["reflects"], part)["plane"], getattr(rays["blocks"], part)["plane"])
    for part in ("direct", "indirect", "total"):
        for name in ("plane", "ball", "box"):
            np.testing.assert_array_equal(getattr(rays["paper"], part)[name], getattr(paper, part)[name])
            np.testing.assert_array_equal(getattr(rays["reflects"], part)[name], getattr(default, part)[name])
    assert a.info["ground"] == "reflects" and paper.info["ground"] == "paper"
    np.testing.assert_allclose(a.direct["plane"], paper.direct["plane"])
    np.testing.assert_allclose(a.indirect["plane"], blocks.indirect["plane"])
    assert a.indirect["plane"].sum() < paper.indirect["plane"].sum()
    for name in ("ball", "box"):
        np.testing.assert_allclose(a.direct[name], blocks.direct[name])
        assert a.direct[name].sum() < paper.direct[name].sum()
        assert a.indirect[name].sum() > blocks.indirect[name].sum()
    with pytest.raises(ValueError, match="option ground must be one of"):
        SphereLights.make_options({"ground": "mirror"})
    with pytest.raises(ValueError, match="'occluding_ground' of method 'spherelights' is now called 'ground'"):
        SphereLights.make_options({"occluding_ground": False})
    with pytest.raises(ValueError, match="option ground_texels must be 0 .* or an int >= 2, got 1"):
        SphereLights.make_options({"ground_texels": 1})
    with pytest.raises(TypeError, match="option ground_texels must be an int"):
        SphereLights.make_options({"ground_texels": 2.5})
    # the ground's light read from its shaded vertices instead of a grid of its points: the same light, blurred
    for shading, grid in (("lights", a), ("rays", default)):
        opts = SphereLights.make_options({"n_spheres": 2, "fit_resolution": 16, "ground_texels": 0,
                                          "ground_shading": shading})
        from_vertices = SphereLights(pre.scene, opts, pre.data).shade(bounces=1)
        for name in ("ball", "box"):
            np.testing.assert_allclose(from_vertices.direct[name], grid.direct[name])
            np.testing.assert_allclose(from_vertices.indirect[name].sum(), grid.indirect[name].sum(), rtol=0.1)


def test_two_bounces_go_through_the_ground(pre):
    """``bounces=2`` adds the paths through the ground (object -> ground -> object, ground -> object -> ground):
    more indirect light on every object than one bounce and the same direct light; without a ground taking part
    (``ground="paper"``) it is one bounce. Against Mitsuba: the fidelity tier's ``tiny ball, 2 bounces``."""
    one, two = pre.shade(bounces=1), pre.shade(bounces=2)
    assert two.info["bounces"] == 2
    for name in ("plane", "ball", "box"):
        np.testing.assert_allclose(two.direct[name], one.direct[name])
        assert two.indirect[name].sum() > one.indirect[name].sum()
    opts = SphereLights.make_options({"n_spheres": 2, "fit_resolution": 16, "ground": "paper"})
    paper = SphereLights(pre.scene, opts, pre.data)
    a, b = paper.shade(bounces=1), paper.shade(bounces=2)
    for name in ("plane", "ball", "box"):
        np.testing.assert_allclose(b.total[name], a.total[name])


def test_no_negative_radiance_beside_a_sphere():
    """Raw order-4 SH products ring below 0 at ground vertices beside a sphere resting on the ground (the
    exponentiated visibility of a blocker covering most of the upper hemisphere undershoots where the true
    visibility is 0), and the ground's hidden light is subtracted from the objects' direct light: every
    radiance the pipeline returns is clamped at 0 (irradiance is non-negative)."""
    from prtlab.spherelights import first_pass, ground_rectangles, second_pass, voronoi_cell_sums

    sc = prtlab.load_scene("spheres_on_plane_env")
    pre8 = SphereLights.precompute(sc, {"n_spheres": 8, "fit_resolution": 16}, cache=False, progress=False)
    st = FrameState.from_scene(sc)
    env = pre8._environment(st)
    c, r, so, inter, rot, spts, snrm, sval, alb = pre8.world_lights(st)
    opts = pre8.options
    em = first_pass(spts, snrm, sval, c, r, env, voronoi_cell_sums(opts.light_order), alb,
                    ground=ground_rectangles([sc.object("plane")]), order=opts.order)
    plane = sc.object("plane")
    raw, _ = second_pass(plane.world_shading_points(plane.transform), plane.world_normals(plane.transform), c, r, so,
                         inter, rot, em, env, order=opts.order)
    assert raw.min() < -0.05  # the ringing the clamp removes
    res = pre8.shade(st, bounces=1)
    for part in (res.direct, res.indirect, res.total):
        for name, value in part.items():
            assert np.all(value >= 0.0), name


# ------------------------------------------------------------------ local lights (Sec. 7.3)


def _plane_and(objects=(), lights=()):
    return Scene.from_dict({
        "objects": [{"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [6, 6]},
                     "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}}, *objects],
        "lights": list(lights),
    })


def test_local_light_over_a_plane_is_the_closed_form():
    """A uniform spherical emitter wholly above every receiver's horizon: ``E* = pi L sin^2(a) cos(t)``.

    Ours: ``E = E_n min(1, V~ / V~')`` with ``V~ = (1 - exp* G) . rho_n`` and ``V~' = P_n(cap) . rho_n``,
    so ``|E - E*| <= E* |v - P_n cap| |rho_n| / V~' + |E_n - E*|``; for a constant light
    ``E_n = L (s K_1 - sqrt(4 pi) K_0) (n . b)`` (``b`` light -> receiver), whose only error is the kernel
    table's interpolation: ``|E_n - E*| <= L |n . b| (s |dK_1| + sqrt(4 pi) |dK_0|)``, ``dK`` table minus
    the direct quadrature (:func:`irradiance_kernel_zh`).
    """
    from prtlab import sh
    from prtlab.spherelights import accumulate_blockers, irradiance_kernel_zh

    centre, radius, L = np.array([0.3, 1.0, -0.2]), 0.25, np.array([5.0, 4.0, 3.0])
    pre = SphereLights.precompute(_plane_and(), {"local_lights": [(centre, radius, L)]}, cache=False,
                                  progress=False)
    res = pre.shade(bounces=1)
    plane = pre.scene.object("plane")
    p, n = plane.world_shading_points(), plane.world_normals()
    d = centre - p
    dist = np.linalg.norm(d, axis=1)
    s, cos_t = radius / dist, np.einsum("bk,bk->b", d, n) / dist
    truth = np.pi * L * (s * s * cos_t)[:, None]
    ours = res.direct["plane"] / (0.7 / np.pi)
    np.testing.assert_array_equal(res.indirect["plane"], 0.0)
    gs, _, th, ax = accumulate_blockers(p, n, centre[None], [radius], [0], np.zeros((1, 1), bool), 4)
    v = sh.exp(np.zeros(16)) - sh.exp(gs[:, 0])
    cos_n = sh.zh_rotate(sh.clamped_cosine_zh(4), n)
    cap = -sh.zh_rotate(sh.blocker_zh(th[:, 0], 4), ax[:, 0])
    cap[:, 0] += np.sqrt(4 * np.pi)
    v_open = np.einsum("bk,bk->b", cap, cos_n)
    dk = irradiance_kernel_zh(th[:, 0], 5) - irradiance_kernel_zh(th[:, 0], 5, method="direct")
    k_err = np.abs(cos_t) * (s * np.abs(dk[:, 1]) + np.sqrt(4 * np.pi) * np.abs(dk[:, 0]))
    bound = (truth * (np.linalg.norm(v - cap, axis=1) * np.linalg.norm(cos_n, axis=1) / v_open)[:, None]
             + L * k_err[:, None])
    assert np.all(np.abs(ours - truth) <= bound + 1e-12), np.max(np.abs(ours - truth) / truth)
    assert np.all(bound <= 0.05 * truth)  # the order-4 exp* of one cap costs at most a few per cent here


def test_local_light_behind_a_blocker_against_monte_carlo(rng):
    """The local light seen past a black ball (its fitted sphere; its own light is zero): the
    test_passes MC of rays whose first hit is the emitter, with that test's derived order-4 bound."""
    from prtlab.spherelights import accumulate_blockers, second_pass
    from tests.spherelights.test_passes import _behind_check

    ball = {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.3, "subdivisions": 2},
            "transform": {"translate": [0.0, 0.7, 0.0]}, "material": {"type": "diffuse", "albedo": [0.0, 0.0, 0.0]}}
    centre, radius, L = np.array([0.9, 1.7, 0.0]), 0.4, np.array([5.0, 4.0, 3.0])
    pre = SphereLights.precompute(_plane_and([ball]), {"n_spheres": 1, "fit_resolution": 16,
                                                       "local_lights": [(centre, radius, L)]},
                                  cache=False, progress=False)
    res = pre.shade(bounces=1)
    c_b, r_b, *_ = pre.world_lights(FrameState.from_scene(pre.scene))
    c, r = np.concatenate([c_b, centre[None]]), np.concatenate([r_b, [radius]])
    plane = pre.scene.object("plane")
    pts, nrm = plane.world_shading_points(), plane.world_normals()
    pick = np.argsort(np.abs(pts[:, 2]) + np.abs(pts[:, 0] + 0.6))[:4]  # receivers near the ball's shadow
    pts, nrm = pts[pick], nrm[pick]
    inter = np.zeros((2, 2), bool)
    gs, gf, *_ = accumulate_blockers(pts, nrm, c, r, [0, 1], inter, 4)
    em = np.zeros((1, 16, 3))
    em[0, 0] = L * np.sqrt(4 * np.pi)
    _, e_n = second_pass(pts, nrm, c[1:], r[1:], [0], inter[:1, :1], np.eye(3)[None], em, np.zeros((16, 3)))
    ours = res.direct["plane"][pick] / (0.7 / np.pi)
    np.testing.assert_allclose(res.indirect["plane"], 0.0, atol=1e-12)
    partial = 0
    for k in range(len(pts)):
        ref, se, bound, open_true, frac = _behind_check(pts[k], nrm[k], c, r, 1, gf[k, 1], gs[k, 1], e_n[k], L, rng)
        partial += 0.1 < frac < 0.9
        assert np.all(np.abs(ours[k] - ref) <= bound + MC_SIGMAS * se), (k, ours[k], ref, bound, se)
        assert np.all(ours[k] < e_n[k])
    assert partial >= 1


def test_local_light_lights_objects_through_the_first_pass():
    """An object lit only by a local light beside it reflects it onto the plane (indirect light, mostly on the
    lit side), and nothing without bounces."""
    ball = {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.3, "subdivisions": 2},
            "transform": {"translate": [0.0, 0.5, 0.0]}, "material": {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]}}
    opts = {"n_spheres": 1, "fit_resolution": 16, "local_lights": [((1.0, 0.6, 0.0), 0.2, (5.0, 5.0, 5.0))]}
    pre = SphereLights.precompute(_plane_and([ball]), opts, cache=False, progress=False)
    res = pre.shade(bounces=1)
    ind = res.indirect["plane"][:, 0]
    x = pre.scene.object("plane").world_vertices()[:, 0]
    assert ind.sum() > 0 and ind[x > 0].sum() > 2 * abs(ind[x < 0].sum())
    assert res.direct["ball"].max() > 0  # the top of the ball is lit
    np.testing.assert_array_equal(pre.shade(bounces=0).indirect["plane"], 0.0)
    np.testing.assert_allclose(pre.shade(bounces=0).direct["plane"], res.direct["plane"])


def test_local_light_errors():
    with pytest.raises(TypeError, match="option local_lights must be a sequence"):
        SphereLights.make_options({"local_lights": 5})
    for bad in ([((0, 1, 0), 0.0, (1, 1, 1))], [((0, 1), 0.3, (1, 1, 1))], [((0, 1, 0), 0.3, (-1, 1, 1))],
                [((0, 1, 0), 0.3)], [((0, np.nan, 0), 0.3, (1, 1, 1))]):
        with pytest.raises(ValueError, match="local_lights must be a sequence"):
            SphereLights.make_options({"local_lights": bad})


# ------------------------------------------------------------------ soft deformations (Sec. 7.1)


def test_rigid_translation_as_a_deformation_is_the_translated_object(pre):
    t = np.array([0.3, 0.2, -0.4])
    ball = pre.scene.object("ball")
    deformed = pre.shade(bounces=1, deformed={"ball": np.asarray(ball.mesh.vertices) + t})
    state = FrameState.from_scene(pre.scene)
    state.transforms["ball"] = Transform(translate=ball.transform.translate + t, rotate_deg=ball.transform.rotate_deg,
                                         scale=ball.transform.scale)
    moved = pre.shade(state, bounces=1)
    for name in moved.total:
        np.testing.assert_allclose(deformed.direct[name], moved.direct[name], atol=1e-10)
        np.testing.assert_allclose(deformed.indirect[name], moved.indirect[name], atol=1e-10)
    # and the identity deformation is the rest pose
    rest = pre.shade(bounces=1, deformed={"ball": ball.mesh.vertices})
    np.testing.assert_allclose(rest.total["plane"], pre.shade(bounces=1).total["plane"], atol=1e-12)


@pytest.mark.parametrize("hierarchy", [0, 2])
def test_rigid_rotation_as_a_deformation_is_the_rotated_object(pre, hierarchy):
    """Sec. 7.1: each light turns with the best-fit rotation of its vertices, so a rigid rotation (about a point
    off the object, plus a translation) given as a deformation equals the object turned by its transform
    (the box has its own rotation, composed on the left); with a hierarchy, the parents turn too."""
    from prtlab.scene import matrix_to_euler
    from tests.conftest import random_rotation

    R = random_rotation(np.random.default_rng(11))
    b = np.array([0.2, 0.15, -0.1])
    box = pre.scene.object("box")
    other = _with(pre, hierarchy_children=hierarchy, cut_threshold=0.9, cluster_size=48) if hierarchy else pre
    verts = np.asarray(box.mesh.vertices) @ R.T + b
    deformed = other.shade(bounces=1, deformed={"box": verts})
    state = FrameState.from_scene(pre.scene)
    tr = box.transform
    state.transforms["box"] = Transform(translate=tr.translate + tr.scale * tr.rotation @ b,
                                        rotate_deg=matrix_to_euler(tr.rotation @ R), scale=tr.scale)
    moved = other.shade(state, bounces=1)
    assert not np.allclose(moved.total["plane"], other.shade(bounces=1).total["plane"], atol=1e-4)
    for name in moved.total:
        np.testing.assert_allclose(deformed.direct[name], moved.direct[name], atol=1e-10)
        np.testing.assert_allclose(deformed.indirect[name], moved.indirect[name], atol=1e-10)


def test_light_motions_of_a_rigid_motion_and_degenerate_lights():
    from prtlab.spherelights import light_motions
    from tests.conftest import random_rotation

    g = np.random.default_rng(3)
    rest = g.normal(size=(20, 3))
    R = random_rotation(g)
    owner = np.repeat([0, 1, 2, 3], [10, 6, 2, 2])
    rest[18:] = [[0.0, 0, 0], [1.0, 0, 0]]
    verts = rest @ R.T + [1.0, 2.0, 3.0]
    turn, m0, m1 = light_motions(verts, rest, owner, 5)
    # lights 2 and 3 have 2 vertices, light 4 none: they take the rotation of all the vertices
    np.testing.assert_allclose(turn, np.broadcast_to(R, (5, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(m1, m0 @ R.T + [1.0, 2.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(m0[4], rest.mean(axis=0), atol=1e-15)
    # a bend leaves a collinear light's rotation to the whole object's, not to chance
    bent = rest.copy()
    bent[10:16] += [0.0, 0.3, 0.0]
    turn, _, _ = light_motions(bent, rest, owner, 5)
    np.testing.assert_allclose(turn[0], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(turn[3], turn[4], atol=1e-15)
    # a reflection is fitted by the nearest proper rotation
    mirror = rest * [1.0, 1.0, -1.0]
    assert np.linalg.det(light_motions(mirror, rest, owner, 5)[0][0]) == pytest.approx(1.0)


def test_bend_moves_each_light_with_its_vertices():
    """A bar bent upward at its ends (y += k x^2): every light moves and turns with the vertices it was fitted
    to (which lie in it): its centre goes to ``R (c - m) + m'`` with the best-fit rotation ``R``, a turn about
    z, up on the right half and down on the left (y' = 2 k x); the end lights rise most, and the bent bar's
    shading changes."""
    bar = {"name": "bar", "mesh": {"builtin": "box", "size": [2.0, 0.3, 0.3], "subdivisions": 3},
           "transform": {"translate": [0.0, 0.6, 0.0]}, "material": {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]}}
    scene = _plane_and([bar], [{"type": "environment", "constant": [1.0, 1.0, 1.0]}])
    pre = SphereLights.precompute(scene, {"n_spheres": 4, "fit_resolution": 24}, cache=False, progress=False)
    data = pre.data["objects"]["bar"]
    verts = np.asarray(scene.object("bar").mesh.vertices)
    owner = np.asarray(data["vertex_light"])
    dist = np.linalg.norm(verts - data["centres"][owner], axis=1)
    assert np.all(dist <= data["radii"][owner] * (1 + 1e-6))  # each vertex lies in the light it was fitted to
    bent = verts + np.stack([0 * verts[:, 0], 0.2 * verts[:, 0] ** 2, 0 * verts[:, 0]], -1)
    state = FrameState.from_scene(scene)
    c0 = pre.world_lights(state)[0]
    lights = pre.world_lights(state, {"bar": bent})
    c1, rot1 = lights[0], lights[4]
    shift = c1 - c0
    order = np.argsort(c0[:, 0])
    assert shift[order[0], 1] > shift[order[1], 1] > 0 and shift[order[-1], 1] > shift[order[-2], 1] > 0
    angles = np.arctan2(rot1[:, 1, 0], rot1[:, 0, 0])  # the turn about z, the bend's axis
    for i in range(len(c0)):
        x0 = verts[owner == i]
        x1 = bent[owner == i]
        m0, m1 = x0.mean(axis=0), x1.mean(axis=0)
        np.testing.assert_allclose(c1[i], rot1[i] @ (data["centres"][i] - m0) + m1 + [0.0, 0.6, 0.0], atol=1e-12)

        def residual(R):
            return np.sum(((x0 - m0) @ R.T - (x1 - m1)) ** 2)

        # the best-fit rotation: no worse than the best turn about z alone (2D Kabsch) nor than none
        a, b = x0[:, :2] - m0[:2], x1[:, :2] - m1[:2]
        best_z = np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b))
        rz = np.array([[np.cos(best_z), -np.sin(best_z), 0], [np.sin(best_z), np.cos(best_z), 0], [0, 0, 1]])
        assert residual(rot1[i]) <= residual(rz) + 1e-12 < residual(np.eye(3))
        assert np.sign(angles[i]) == np.sign(m0[0])  # y' = 2 k x: the right half turns up, the left down
    # shading follows: the bent bar's ends rise, so less shadow right under them
    res0, res1 = pre.shade(bounces=1), pre.shade(bounces=1, deformed={"bar": bent})
    assert np.all(np.isfinite(res1.total["bar"])) and not np.allclose(res0.total["plane"], res1.total["plane"])


def test_deformed_errors(pre):
    with pytest.raises(TypeError, match="deformed must be a dict"):
        pre.shade(bounces=1, deformed=[1, 2])
    with pytest.raises(ValueError, match=r"deformations name unknown object\(s\) \['teapot'\]"):
        pre.shade(bounces=1, deformed={"teapot": np.zeros((3, 3))})
    with pytest.raises(ValueError, match="must be finite object-space vertex positions of shape"):
        pre.shade(bounces=1, deformed={"ball": np.zeros((3, 3))})


# ------------------------------------------------------------------ hierarchies and the reflection ratio (Sec. 7.3)


@pytest.fixture(scope="module")
def pre8():
    """Every receiver shaded through the lights (the plane too: ``ground_shading="lights"``), as the hierarchy's cuts
    approximate them."""
    return SphereLights.precompute(_scene(), {"n_spheres": 8, "fit_resolution": 16, "ground_shading": "lights"},
                                   cache=False, progress=False)


@pytest.fixture(scope="module")
def flat8(pre8):
    return pre8.shade(bounces=1)


def _with(pre, **options):
    """The precomputation with other run-time options (they are not part of its data)."""
    from dataclasses import replace

    other = object.__new__(type(pre))
    other.__dict__.update({k: v for k, v in pre.__dict__.items() if not k.startswith("_")})
    other.options = replace(pre.options, **options)
    return other


def _relative_rms(res, flat):
    num = sum(np.sum((res.indirect[n] - flat.indirect[n]) ** 2) for n in flat.indirect)
    return float(np.sqrt(num / sum(np.sum(flat.indirect[n] ** 2) for n in flat.indirect)))


def test_hierarchy_with_leaf_cuts_is_the_flat_pipeline(pre8, flat8):
    res = _with(pre8, hierarchy_children=2, cut_threshold=0.0, cluster_size=48).shade(bounces=1)
    for name in flat8.total:
        np.testing.assert_array_equal(res.direct[name], flat8.direct[name])
        np.testing.assert_array_equal(res.indirect[name], flat8.indirect[name])


def test_reflection_ratio_gives_the_cluster_centre_the_leaves_value(pre8, flat8):
    """Eq. 25 by construction: with one ratio point (the paper's form) every cluster centre gets the flat
    pipeline's indirect light, whatever its cut; the direct light keeps the leaves."""
    h = _with(pre8, hierarchy_children=2, cut_threshold=0.9, cluster_size=16, ratio_samples=1)
    res = h.shade(bounces=1)
    n_coarse = 0
    for obj in pre8.scene.objects:
        _, medoid, _ = h._clusters(obj)
        np.testing.assert_allclose(res.indirect[obj.name][medoid], flat8.indirect[obj.name][medoid],
                                   rtol=1e-9, atol=1e-14)
        np.testing.assert_array_equal(res.direct[obj.name], flat8.direct[obj.name])
        n_coarse += int(np.any(res.indirect[obj.name] != flat8.indirect[obj.name]))
    assert n_coarse >= 2  # the cuts are coarse somewhere


@pytest.mark.parametrize("threshold", [0.5, 0.7])
def test_reflection_ratio_reduces_the_error_of_coarse_cuts(pre8, flat8, threshold):
    """Relative RMS indirect error over all receivers against the flat pass, measured (test scene, clusters of
    16 receivers): threshold 0.5: 1.6 % without the ratio, 0.9 % with it (5 points), 3.4 % with the paper's
    centre ratio; 0.7: 2.9 %, 2.2 % and 6.4 %. The centre ratio fails on the curved receivers (a centre that
    sees a node at a grazing angle gives the rest of its cluster a wrong ratio); on the plane (flat) it
    helps at 0.7: 1.9 -> 1.0 % (at 0.5 it changes nothing: 0.36 -> 0.38 %). No error bound is derived for a
    coarse cut, so the test checks the claims only: the ratio lowers the error, and at 0.7 the centre ratio
    lowers it on the flat receiver."""
    kw = dict(hierarchy_children=2, cut_threshold=threshold, cluster_size=16)
    without = _with(pre8, reflection_ratio=False, **kw).shade(bounces=1)
    ratio = _with(pre8, **kw).shade(bounces=1)
    e_without, e_ratio = _relative_rms(without, flat8), _relative_rms(ratio, flat8)
    assert 0 < e_ratio < e_without
    if threshold == 0.7:
        centre = _with(pre8, ratio_samples=1, **kw).shade(bounces=1)

        def plane_error(res):
            d = res.indirect["plane"] - flat8.indirect["plane"]
            return float(np.sqrt(np.sum(d**2) / np.sum(flat8.indirect["plane"] ** 2)))

        assert plane_error(centre) < plane_error(without)


def test_hierarchy_through_the_api():
    res = prtlab.shade(_scene(), method="spherelights", bounces=1, cache=False, progress=False, n_spheres=2,
                       fit_resolution=16, hierarchy_children=2, cut_threshold=0.6, cluster_size=32)
    flat = prtlab.shade(_scene(), method="spherelights", bounces=1, cache=False, progress=False, n_spheres=2,
                        fit_resolution=16)
    for name in flat.total:
        np.testing.assert_array_equal(res.direct[name], flat.direct[name])
        assert np.all(np.isfinite(res.indirect[name]))
    assert any(not np.array_equal(res.indirect[n], flat.indirect[n]) for n in flat.total)


def test_hierarchy_option_errors():
    from prtlab.spherelights import SphereLightOptions

    with pytest.raises(ValueError, match="hierarchy_children must be 0"):
        SphereLightOptions(hierarchy_children=1)
    with pytest.raises(ValueError, match=r"option cut_threshold must be a finite number >= 0.0 and < 1.0"):
        SphereLightOptions(cut_threshold=1.0)
    with pytest.raises(ValueError, match="cluster_size must be an int >= 1"):
        SphereLightOptions(cluster_size=0)
    with pytest.raises(ValueError, match="ratio_samples must be an int >= 1"):
        SphereLightOptions(ratio_samples=0)
    with pytest.raises(TypeError, match="option reflection_ratio must be True or False"):
        SphereLightOptions(reflection_ratio=1)
