"""Moving portals (option ``portal_strips``): a window whose aperture opens and closes per frame."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from prtlab.pipeline import FrameState
from prtlab.portals import Portals, find_portals, shell_light, strip_frame, strip_weights
from prtlab.portals._direct import _portal_points, _strip_of
from prtlab.portals._shade import shell_coefficients
from prtlab.scene import Material, Transform
from prtlab.wavelet import SparseTransfer

from .conftest import SKY, window_box

BOUNCES = 2
RES = 8
OPTIONS = {"direct_samples": 256, "cube_resolution": RES, "gather_rays": 64, "bounces": BOUNCES, "clusters": 64}
STRIPS = 4


def small_room():
    """109 vertices: one batch of the direct transfer with 4 strips (128 vertices), so both transfers draw the same
    portal samples."""
    return window_box(SKY, room=(2.0, 2.0, 2.0), window=(1.0, 0.8), cell=0.7)


@pytest.fixture(scope="module")
def fixed():
    return Portals.precompute(small_room(), OPTIONS, cache=False, progress=False)


@pytest.fixture(scope="module")
def strips():
    return Portals.precompute(small_room(), {**OPTIONS, "portal_strips": STRIPS}, cache=False, progress=False)


def _cube(pre):
    return shell_light(pre.scene.lights[0], RES)


def _shade(pre, openings=None, method="reference"):
    return pre.shade_shells([_cube(pre)], BOUNCES, method=method, openings=openings)


# ----------------------------------------------------------------------------- known answers


def test_strip_frame_of_a_wall_window():
    """The strips of a window on a wall stack along its vertical edge, ``u = 0`` at the bottom."""
    portal = find_portals(small_room())[0]
    corner, strip, other = strip_frame(portal)
    np.testing.assert_allclose(strip, [0.0, 0.8, 0.0], atol=1e-12)
    assert abs(abs(other[0]) - 1.0) < 1e-12 and abs(other[1]) < 1e-12
    assert corner[1] == pytest.approx(portal.vertices[:, 1].min())


def test_strip_weights():
    np.testing.assert_allclose(strip_weights(4, 0.0, 1.0), [1, 1, 1, 1])
    np.testing.assert_allclose(strip_weights(4, 0.3, 0.3), [0, 0, 0, 0])
    np.testing.assert_allclose(strip_weights(4, 0.125, 0.6), [0.5, 1.0, 0.4, 0.0])


def test_sobol_strips_hold_equal_counts(rng):
    """With Sobol' points and ``K``, ``N`` powers of two, every strip holds exactly ``N / K`` points per vertex."""
    portal = find_portals(small_room())[0]
    points, _ = _portal_points(portal, 3, 256, rng, "sobol")
    for k in (2, 4, 8, 16):
        strip = _strip_of(points, k, strip_frame(portal))
        counts = np.stack([np.bincount(s, minlength=k) for s in strip])
        assert np.all(counts == 256 // k), (k, counts)


def test_fully_open_equals_fixed_portal(fixed, strips):
    """All strips open give the fixed portal's direct light up to the 8-bit quantisation.

    Both transfers come from the same portal samples (the strips partition them), so their float transfers sum
    alike; every stored coefficient is within ``scale / 510`` of its float value (:func:`prtlab.wavelet.quantize8`)
    in the row's orthonormal basis (pulse or Haar), so ``|L_strips - L_fixed| <= rho / 510 (s_0 |L|_{1,b_0} +
    sum_j s_j |L|_{1,b_j})``, ``s`` the rows' scales and ``|L|_{1,b}`` the light's L1 norm in basis ``b``.
    """
    a, b = _shade(strips), _shade(fixed)
    light = shell_coefficients(_cube(fixed))
    n = len(light) // 2
    norm1 = np.stack([np.abs(light[:n]).sum(0), np.abs(light[n:]).sum(0)])  # (basis, 3)
    t0, tk = fixed.direct_transfer(0), strips.direct_transfer(0)
    bound = t0.scale[:, None].astype(np.float64) * norm1[t0.basis]
    bound += (tk.scale[:, None].astype(np.float64) * norm1[tk.basis]).reshape(STRIPS, -1, 3).sum(0)  # row j V + v
    bound *= np.asarray(fixed.data["albedo"]) / 510.0
    diff = np.abs(a.direct["room"] - b.direct["room"])
    assert np.all(diff <= bound + 1e-12 * np.abs(b.direct["room"]).max()), (diff / np.maximum(bound, 1e-300)).max()
    assert diff.max() > 0  # the two encodings differ: the bound is what is tested


def test_closed_window_is_black(strips):
    for openings in ([(0.0, 0.0)], [(0.6, 0.6)], [(1.0, 1.0)]):
        for method in ("reference", "numba"):
            r = _shade(strips, openings, method)
            assert np.all(r.direct["room"] == 0) and np.all(r.indirect["room"] == 0), (openings, method)


# ----------------------------------------------------------------------------- identities


def test_strips_sum(strips):
    """The light is linear in the openings: disjoint parts of the window add up to the whole (a part-open strip
    split between two openings included); the interior's patches are clusters here, so the indirect light is
    linear too (the limited projection of ``clusters >= V`` is not)."""
    whole = _shade(strips, [(0.0, 1.0)])
    parts = [_shade(strips, [o]) for o in ((0.0, 0.3), (0.3, 0.6), (0.6, 1.0))]
    for part in ("direct", "indirect"):
        total = sum(getattr(p, part)["room"] for p in parts)
        np.testing.assert_allclose(total, getattr(whole, part)["room"], rtol=0,
                                   atol=1e-12 * np.abs(getattr(whole, part)["room"]).max())


def test_numba_tier_matches_reference(strips):
    for openings in ([(0.0, 1.0)], [(0.2, 0.7)]):
        a, b = _shade(strips, openings, "numba"), _shade(strips, openings, "reference")
        for part in ("direct", "indirect"):
            ref = getattr(b, part)["room"]
            np.testing.assert_allclose(getattr(a, part)["room"], ref, rtol=0, atol=1e-5 * np.abs(ref).max())


def test_frame_state_deformation_is_the_opening(strips):
    """``shade(FrameState)`` with the window's deformation from :meth:`Portals.opening_vertices` is
    ``shade_shells`` with that opening; no deformation is the whole window."""
    state = FrameState.from_scene(strips.scene)
    state.deformations["window"] = strips.opening_vertices("window", 0.2, 0.7)
    assert strips.openings(state) == [pytest.approx((0.2, 0.7))]
    a, b = strips.shade(state, bounces=BOUNCES), _shade(strips, [(0.2, 0.7)], "numba")
    for part in ("direct", "indirect"):
        np.testing.assert_allclose(getattr(a, part)["room"], getattr(b, part)["room"], rtol=1e-12, atol=1e-15)
    assert a.info["openings"] == [pytest.approx((0.2, 0.7))]
    full, whole = strips.shade(bounces=BOUNCES), _shade(strips, None, "numba")
    np.testing.assert_array_equal(full.total["room"], whole.total["room"])


def test_memory_estimate_bounds_the_stored_transfer(strips):
    """The estimate of the encoded direct and source transfers is at least what was stored (5 bytes an entry)."""
    needs = {n.what: n.nbytes for n in Portals.memory_needs(strips.scene, strips.options)[0]}
    assert 5.0 * len(strips.direct_transfer(0).codes) <= needs["the encoded direct transfer"]
    assert 5.0 * len(strips.direct_transfer(0, source=True).codes) <= needs["the hat-averaged source transfer"]
    fixed_needs = {n.what: n.nbytes for n in Portals.memory_needs(strips.scene, Portals.make_options(OPTIONS))[0]}
    assert needs["the hat-averaged source transfer"] > fixed_needs["the hat-averaged source transfer"]


# ----------------------------------------------------------------------------- refused inputs


def _moved_top(pre, top):
    """The window's vertices with its top edge at ``top`` (a fraction of the window; > 1 is beyond it)."""
    corner, strip, _ = strip_frame(find_portals(pre.scene)[0])
    v = pre.scene.object("window").world_vertices().copy()
    upper = (v - corner) @ strip / (strip @ strip) > 0.5
    v[upper] = v[upper] + (top - 1.0) * strip
    return v


def test_opening_beyond_the_window_refused(strips):
    state = FrameState.from_scene(strips.scene)
    state.deformations["window"] = _moved_top(strips, 1.2)
    with pytest.raises(ValueError, match="open part of portal 'window' .* must be the precomputed window cut"):
        strips.shade(state, bounces=BOUNCES)
    state.deformations["window"] = _moved_top(strips, 0.6)  # within the window: taken
    assert strips.openings(state) == [pytest.approx((0.0, 0.6))]
    with pytest.raises(ValueError, match=r"0 <= low <= high <= 1"):
        strips.opening_vertices("window", 0.0, 1.2)
    with pytest.raises(ValueError, match=r"an opening must have 0 <= low <= high <= 1"):
        _shade(strips, [(0.5, 0.2)])
    with pytest.raises(ValueError, match=r"one opening \(low, high\) per portal \(1\)"):
        _shade(strips, [(0.0, 0.5), (0.0, 0.5)])


def test_rotated_portal_refused(strips):
    """A window rotated (by its transform, or by a deformation turning it in its plane) is refused, naming it."""
    state = FrameState.from_scene(strips.scene)
    state.transforms["window"] = Transform(rotate_deg=np.array([0.0, 0.0, 10.0]))
    with pytest.raises(ValueError, match="object 'window' moved"):
        strips.shade(state, bounces=BOUNCES)
    state = FrameState.from_scene(strips.scene)
    v = strips.scene.object("window").world_vertices()
    c = v.mean(0)
    turn = np.array([[np.cos(0.1), -np.sin(0.1), 0.0], [np.sin(0.1), np.cos(0.1), 0.0], [0.0, 0.0, 1.0]])
    state.deformations["window"] = (v - c) @ turn.T * 0.5 + c
    with pytest.raises(ValueError, match="open part of portal 'window' .* nothing else moved or rotated"):
        strips.shade(state, bounces=BOUNCES)


def test_other_deformations_refused(strips, fixed):
    state = FrameState.from_scene(strips.scene)
    state.deformations["room"] = strips.scene.object("room").mesh.vertices
    with pytest.raises(ValueError, match=r"does not take soft deformations .*\['room'\]\), only a portal's opening"):
        strips.shade(state, bounces=BOUNCES)
    with pytest.raises(ValueError, match="only a portal object opens and closes.*'room' is not a portal"):
        strips.opening_vertices("room", 0.0, 0.5)
    state = FrameState.from_scene(fixed.scene)
    state.deformations["window"] = fixed.scene.object("window").mesh.vertices
    with pytest.raises(ValueError, match=r"portal 'window' is fixed \(option portal_strips=0\)"):
        fixed.shade(state, bounces=BOUNCES)
    with pytest.raises(ValueError, match=r"the portals are fixed \(option portal_strips=0\)"):
        _shade(fixed, [(0.0, 0.5)])
    with pytest.raises(ValueError, match=r"portal 'window' is fixed"):
        fixed.opening_vertices("window", 0.0, 0.5)


def test_non_parallelogram_portal_refused():
    scene = small_room()
    window = scene.object("window")
    v = np.asarray(window.mesh.vertices, dtype=np.float64).copy()
    top = v[:, 1] > v[:, 1].mean()
    v[top, 0] *= 0.5  # a trapezoid
    window.mesh = trimesh.Trimesh(vertices=v, faces=np.asarray(window.mesh.faces), process=False)
    with pytest.raises(ValueError, match=r"portal_strips needs parallelogram portals .*\['window'\]"):
        Portals.precompute(scene, {**OPTIONS, "portal_strips": 4}, cache=False, progress=False)


def test_paper_mode_refused():
    with pytest.raises(ValueError, match=r"portal_strips needs indirect='surface'.*but indirect='paper'"):
        Portals.precompute(small_room(), {**OPTIONS, "portal_strips": 4, "indirect": "paper"}, cache=False,
                           progress=False)


def test_glossy_interior_refused():
    """A glossy interior needs the paper's indirect transfer, which strips do not take."""
    scene = small_room()
    scene.object("room").material = Material(type="phong", kd=np.full(3, 0.5), ks=np.full(3, 0.2), exponent=10.0)
    with pytest.raises(ValueError, match=r"portal_strips needs indirect='surface'.*'room' is glossy"):
        Portals.precompute(scene, {**OPTIONS, "portal_strips": 4}, cache=False, progress=False)


def test_bad_option_refused():
    with pytest.raises(ValueError, match="option portal_strips"):
        Portals.make_options({"portal_strips": -1})
    with pytest.raises(TypeError, match="option portal_strips"):
        Portals.make_options({"portal_strips": 2.0})


def test_strip_rows_are_strip_major(strips):
    """The per-strip transfer has ``K V`` rows, ``j V + v``; ``strips=(j, j + 1)`` is that block."""
    t = strips.direct_transfer(0)
    n_v = len(strips.data["albedo"])
    assert isinstance(t, SparseTransfer) and t.n_vertices == STRIPS * n_v
    cube = _cube(strips)
    whole = t.dot(cube, method="reference").reshape(STRIPS, n_v, 3)
    for j in range(STRIPS):
        block = strips.direct_transfer(0, strips=(j, j + 1))
        assert block.n_vertices == n_v
        np.testing.assert_array_equal(block.dot(cube, method="reference"), whole[j])
