"""Interior lights and the light leaving through the portals (the paper's future work; ``_interior.py``).

Closed forms: a point light's factor ``cos / r^2``; a square area light's factor over an on-axis point (the
differential-area-to-rectangle form factor times pi); a blocker's shadow; the leaving transfer of a room of
uniform radiance (the SH projection of the outward hemisphere). Pipeline: a lamp of zero emission leaves the sky's
frame bitwise as without it; the lamp's light is linear in its emission; refusals (moved lamp, paper mode, bad
emission). Against Mitsuba: ``tests/fidelity/test_portals_interior.py``.
"""

import numpy as np
import pytest

import prtlab.sh as sh
from prtlab.geometry import RayCaster
from prtlab.pipeline import FrameState
from prtlab.portals import Portals, find_portals, interior_light_factor, leaving_radiance, leaving_transfer
from prtlab.scene import AreaLight, PointLight, Scene

from .conftest import window_box

TINY = {"direct_samples": 16, "gather_rays": 16, "cube_resolution": 8, "bounces": 2, "light_samples": 16}
LAMP = {"type": "point", "position": [0.3, 2.0, 0.2], "intensity": [2.0, 1.5, 1.0]}


def _plane_scene(blocker: bool = False):
    objs = [{"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [2, 2]}}]
    if blocker:
        objs.append({"name": "blocker", "mesh": {"builtin": "plane", "size": [1, 1], "resolution": [1, 1]},
                     "transform": {"translate": [0, 1, 0]}})
    return Scene.from_dict({"objects": objs, "lights": [{"type": "environment", "constant": [1, 1, 1]}]})


def _lamp_box(lamp=LAMP, sky=True):
    scene = window_box(cell=0.5)
    d = scene.to_dict()
    if not sky:
        d["lights"][0] = {"type": "environment", "constant": [0.0, 0.0, 0.0]}
    d["lights"].append(dict(lamp))
    return Scene.from_dict(d)


# ------------------------------------------------------------------ known answers


def test_point_light_factor_is_cos_over_r2():
    caster = RayCaster(_plane_scene())
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 1, 20), np.full(20, 1e-3), rng.uniform(-1, 1, 20)])
    nrm = np.tile([0.0, 1.0, 0.0], (20, 1))
    light = PointLight(np.array([0.2, 1.5, -0.1]), np.ones(3))
    d = light.position - pts
    want = d[:, 1] / np.linalg.norm(d, axis=1) ** 3
    np.testing.assert_allclose(interior_light_factor(caster, pts, nrm, light), want, rtol=1e-12)


def test_point_light_shadow_and_back_side():
    caster = RayCaster(_plane_scene(blocker=True))
    pts = np.array([[0.0, 1e-3, 0.0], [1.8, 1e-3, 0.0]])
    nrm = np.tile([0.0, 1.0, 0.0], (2, 1))
    f = interior_light_factor(caster, pts, nrm, PointLight(np.array([0.0, 2.0, 0.0]), np.ones(3)))
    assert f[0] == 0.0 and f[1] > 0.0  # under the blocker, and beside it
    assert interior_light_factor(caster, pts, -nrm, PointLight(np.array([0.0, 2.0, 0.0]), np.ones(3)))[1] == 0.0


def _rect_form_factor(a, b, c):
    """Differential area to a parallel a x b rectangle at height c, over one of its corners."""
    x, y = a / c, b / c
    return (x / np.sqrt(1 + x**2) * np.arctan(y / np.sqrt(1 + x**2))
            + y / np.sqrt(1 + y**2) * np.arctan(x / np.sqrt(1 + y**2))) / (2 * np.pi)


def test_area_light_factor_against_the_form_factor():
    caster = RayCaster(_plane_scene())
    h, c = 0.4, 1.2
    light = AreaLight(np.array([0.0, c, 0.0]), np.array([h, 0, 0]), np.array([0, 0, h]), np.ones(3))
    assert light.normal[1] < 0  # emits down
    want = np.pi * 4 * _rect_form_factor(h, h, c - 1e-3)
    got = interior_light_factor(caster, [[0.0, 1e-3, 0.0]], [[0.0, 1.0, 0.0]], light, 4096,
                                np.random.default_rng(2))
    np.testing.assert_allclose(got, want, rtol=2e-3)
    up = AreaLight(light.center, light.v, light.u, np.ones(3))  # the back of a one-sided light: dark
    assert interior_light_factor(caster, [[0.0, 1e-3, 0.0]], [[0.0, 1.0, 0.0]], up, 64)[0] == 0.0


def test_leaving_transfer_of_uniform_radiance():
    """Every interior vertex at radiance 1: every ray from the window hits a front face, so the coefficients are
    the outward hemisphere's projection: ``sqrt(pi)`` in band 0 exactly and ``pi sqrt(3 / (4 pi))`` along the
    outward axis in band 1; the other band-1 terms vanish."""
    scene = window_box(cell=0.5)
    caster = RayCaster(scene)
    room = scene.object("room")
    n = room.n_vertices
    portal = find_portals(scene)[0]
    w, w_light = leaving_transfer(caster, portal, np.array([0, n]), room.world_normals(), 3, 1 << 14,
                                  np.random.default_rng(3))
    assert w.shape == (9, n) and w_light.shape == (9, 0)
    c = w @ np.ones(n)
    np.testing.assert_allclose(c[0], np.sqrt(np.pi), rtol=1e-12)
    outward = -portal.normal
    axis = sh.basis(outward, 2)[1:4] / np.linalg.norm(sh.basis(outward, 2)[1:4])  # band 1 ~ the direction
    np.testing.assert_allclose(c[1:4] @ axis, np.pi * np.sqrt(3 / (4 * np.pi)), rtol=2e-3)
    np.testing.assert_allclose(c[1:4] - (c[1:4] @ axis) * axis, 0.0, atol=5e-3)
    # the order-3 series of the hemisphere's indicator at its pole: 1/2 + 3/4 (band 2 of a step is zero)
    np.testing.assert_allclose(leaving_radiance(np.tile(c[:, None], 3), outward[None])[0], 1.25, rtol=3e-3)


def test_sent_direct_keeps_constants_and_power(lamp_pre):
    """The direct light the vertices send (the limited projection of hat averages) keeps a constant, and keeps the
    power ``sum a_v s_v`` of any non-negative source, non-negative."""
    st = lamp_pre.surface_transfer()
    n = st.n_patches
    np.testing.assert_allclose(st.sent_direct(np.ones((n, 3))), 1.0, rtol=1e-6)  # the projection stored in float32
    s = np.random.default_rng(4).random((n, 3)) ** 4
    sent = st.sent_direct(s)
    assert np.all(sent >= -1e-12)
    np.testing.assert_allclose(st.areas @ sent, st.areas @ s, rtol=1e-6)


def test_empty_inputs():
    caster = RayCaster(_plane_scene())
    assert interior_light_factor(caster, np.zeros((0, 3)), np.zeros((0, 3)),
                                 PointLight(np.ones(3), np.ones(3))).shape == (0,)
    assert leaving_radiance(np.zeros((4, 3)), np.zeros((0, 3))).shape == (0, 3)


# ------------------------------------------------------------------ the pipeline


@pytest.fixture(scope="module")
def lamp_pre():
    return Portals.precompute(_lamp_box(), {**TINY, "leaving_order": 2, "leaving_rays": 4096}, cache=False,
                              progress=False)


def test_dark_lamp_leaves_the_sky_frame_unchanged(lamp_pre):
    """The sky's transfer does not depend on the lamp: a zero lamp gives bitwise the frame without a lamp."""
    plain = Portals.precompute(window_box(cell=0.5), TINY, cache=False, progress=False)
    a = lamp_pre.shade_shells(_shells(lamp_pre), bounces=2, lights=np.zeros((1, 3)))
    b = plain.shade_shells(_shells(plain), bounces=2)
    for part in ("direct", "indirect"):
        np.testing.assert_array_equal(getattr(a, part)["room"], getattr(b, part)["room"])


def _shells(pre, scale=1.0):
    from prtlab.portals import shell_light

    return [scale * shell_light(pre.scene.lights[0], int(pre.data["portal0"]["res"]))]


def test_lamp_light_is_linear_and_leaves(lamp_pre):
    black = _shells(lamp_pre, 0.0)
    one = lamp_pre.shade_shells(black, bounces=2, lights=[[1.0, 1.0, 1.0]], method="reference")
    two = lamp_pre.shade_shells(black, bounces=2, lights=[[2.0, 2.0, 2.0]], method="reference")
    np.testing.assert_allclose(two.direct["room"], 2 * one.direct["room"], rtol=1e-12)
    np.testing.assert_allclose(two.indirect["room"], 2 * one.indirect["room"], rtol=1e-9, atol=1e-15)
    assert one.indirect["room"].mean() > 0
    assert np.all(one.info["leaving_sh"][0][0] > 0)  # the lit room is seen through the window
    # numba and reference tiers agree within the float32 sums' forward error bound 2 (C + 2) eps_32 (C <= the
    # vertices: the clusters; every term is >= 0, so the bound is relative to the result itself)
    fast = lamp_pre.shade_shells(black, bounces=2, lights=[[1.0, 1.0, 1.0]])
    n_v = len(lamp_pre.scene.object("room").world_vertices())
    np.testing.assert_allclose(fast.total["room"], one.total["room"], rtol=2 * (n_v + 2) * np.finfo(np.float32).eps)
    # the frame through FrameState: the scene's own lamp
    state = FrameState.from_scene(lamp_pre.scene)
    r = lamp_pre.shade(state, bounces=2)
    assert r.info["leaving_sh"].shape == (1, 4, 3) and "lights" in r.info["timings"]


def test_refusals(lamp_pre):
    state = FrameState.from_scene(lamp_pre.scene)
    state.lights = [state.lights[0], PointLight(np.array([0.0, 1.0, 0.0]), np.ones(3))]
    with pytest.raises(ValueError, match="interior lights were precomputed where they stand"):
        lamp_pre.shade(state, bounces=1)
    state.lights = [state.lights[0]]
    with pytest.raises(ValueError, match="interior lights were precomputed where they stand"):
        lamp_pre.shade(state, bounces=1)
    with pytest.raises(ValueError, match=r"lights must be the 1 interior lights' finite non-negative RGB"):
        lamp_pre.shade_shells(_shells(lamp_pre), bounces=1, lights=[[1.0, -1.0, 1.0]])
    plain = Portals.precompute(window_box(cell=1.0), {**TINY, "bounces": 0}, cache=False, progress=False)
    with pytest.raises(ValueError, match="precomputed without interior lights"):
        plain.shade_shells(_shells(plain), bounces=0, lights=[[1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="interior lights .* need indirect='surface'"):
        Portals.precompute(_lamp_box(), {**TINY, "indirect": "paper"}, cache=False, progress=False)
    with pytest.raises(ValueError, match="option leaving_order needs fixed windows"):
        Portals.precompute(_lamp_box(), {**TINY, "leaving_order": 2, "portal_strips": 2}, cache=False,
                           progress=False)
    with pytest.raises(ValueError, match="option leaving_order"):
        Portals.precompute(_lamp_box(), {**TINY, "leaving_order": -1}, cache=False, progress=False)
    with pytest.raises(TypeError, match="light must be a PointLight or AreaLight"):
        interior_light_factor(RayCaster(_plane_scene()), np.zeros((1, 3)), np.zeros((1, 3)), "lamp")
    with pytest.raises(ValueError, match=r"coeffs must be \(n\*n, 3\)"):
        leaving_radiance(np.zeros((5, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"dirs must be \(\.\.\., 3\) directions"):
        leaving_radiance(np.zeros((4, 3)), np.zeros((1, 2)))
    with pytest.raises(ValueError, match=r"points and normals must both be \(N, 3\)"):
        interior_light_factor(RayCaster(_plane_scene()), np.zeros((2, 3)), np.zeros((1, 3)),
                              PointLight(np.ones(3), np.ones(3)))


def test_area_lamp_seen_through_the_window():
    """An area light facing the window adds its radiance to the leaving light in the directions it fills."""
    lamp = {"type": "area", "center": [0.0, 1.4, 0.5], "u": [0.3, 0, 0], "v": [0, -0.3, 0], "radiance": [5, 5, 5]}
    scene = _lamp_box(lamp, sky=False)
    assert scene.lights[1].normal[2] < 0  # toward the window (-z)
    pre = Portals.precompute(scene, {**TINY, "leaving_order": 2, "leaving_rays": 4096}, cache=False, progress=False)
    assert np.all(pre.data["portal0"]["leaving_light"][0] > 0)
    with_lamp = pre.shade(bounces=2).info["leaving_sh"][0]
    room_only = (pre.data["portal0"]["leaving"] @ pre.shade(bounces=2).total["room"])
    assert np.all(with_lamp[0] > room_only[0])


def test_cache_key_holds_what_changes_the_data():
    """Without interior lights and ``leaving_order=0`` the new options leave the key (keys made before them stay
    valid); with a lamp its position and ``light_samples`` are in it, with ``leaving_order`` the leaving rays."""
    from prtlab.cache import cache_key

    def key(scene, **options):
        return cache_key(*Portals.cache_key_parts(scene, Portals.make_options({**TINY, **options})))

    plain = window_box(cell=1.0)
    assert key(plain) == key(plain, light_samples=7) == key(plain, leaving_rays=99)
    assert key(plain) != key(plain, leaving_order=2) != key(plain, leaving_order=2, leaving_rays=99)
    lamp = _lamp_box()
    moved = _lamp_box({**LAMP, "position": [0.0, 2.0, 0.0]})
    brighter = _lamp_box({**LAMP, "intensity": [9.0, 9.0, 9.0]})
    assert key(lamp) != key(plain) and key(lamp) != key(moved) and key(lamp) == key(brighter)
    assert key(lamp) != key(lamp, light_samples=7)
