"""Iwasaki et al. 2007 interreflection against Mitsuba 3 and Monte Carlo, whole scenes at reduced size.

Every object is scored, on direct, indirect and total light, with :func:`prtlab.compare`. Goals
(Iwasaki et al. 2007 as issue 15 sets them): relative RMS of per-vertex radiance 5 % on the total
and 15 % on the indirect light; the direct light, most of the total, is held to the total's 5 %.
A goal is met when ``rel_rms <= hypot(goal, noise)`` (:meth:`prtlab.metrics.ComparisonRow.meets`),
and :meth:`prtlab.metrics.Comparison.check` refuses a reference whose noise exceeds a third of it.

The Fig. 9 floor's indirect light (the bunny's bounce light) is the one part whose reference cannot
meet that within this module's budget: a BRDF-sampled ray from the floor rarely hits the bunny, and
a per-vertex noise of 0.05 needs about 28k samples per vertex (several CPU-minutes per pose). Its
noise (0.23) only widens the budget ``hypot(goal, noise)``, so a miss of that budget is still a miss; a
pass is further checked through the mean: ``|mean(ours - ref)| <= goal * rms(ref) + MC_SIGMAS * se``, a
necessary condition of ``rel_rms <= goal`` (``|mean d| <= rms d``) plus the k-sigma interval of the
reference's mean (``se`` its standard error).

Scenes: Fig. 9 (``interreflection_fig9``: the bunny standing on a floor under a small square area
light, one bounce) with a 16 x 16 floor; the pose it ships in is pose B. Cases: defaults at B;
``shadows="haar"`` at B (with ``irradiance="haar"`` too in the slow tier,
``tests/interreflection/test_haar_passes.py``: its precomputation is beyond this module's budget);
precomputed with the bunny at pose A (moved and turned away) and moved to B by a
:class:`prtlab.pipeline.FrameState`: at the defaults (the paper's basis plus the residual gather, the direct light
by shadow rays), with the paper's method (``prtlab.interreflection.PAPER_OPTIONS``) and with the
basis trained with the other objects' shadows and no gather (the former defaults). The reference is Mitsuba at
B for every case. Bunny vertices on the floor facing into it (its bottom) are left out (``docs/DECISIONS.md``).
The open room corner (``interreflection_corner``, issue 18: a torus 3 cm above the floor of a corner of two
walls, a box, a near
1 x 1 area light) precomputed in place and with the torus 1.16 m away then moved back by a FrameState,
scored per object against the module's goals and the issue's binding bounds (total 10 %, indirect 20 %); and
the corner precomputed as it ships, then its area light moved and turned, or its torus moved beside the box, by a
FrameState, against Mitsuba at the new state; the torus beside the box with a ball 2 cm from both (pairs with two
non-flat occluders) with the SH products (defaults) and with ``occlusion="exp"`` (order-independent, Sec. 6).
Ball over floor (``tests/interreflection/test_pipeline.py``, quick options) against prtlab's own path
tracer with 16,384 paths per vertex.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

import prtlab
from prtlab.interreflection import PAPER_OPTIONS, Interreflection
from prtlab.pipeline import FrameState
from prtlab.scene import AreaLight, Scene, Transform
from tests.conftest import MC_SIGMAS
from tests.fidelity.conftest import on_the_floor

pytestmark = [pytest.mark.mitsuba, pytest.mark.xdist_group("fidelity-interreflection")]

GOAL = {"direct": 0.05, "indirect": 0.15, "total": 0.05}
PARTS = tuple(GOAL)
#: Mitsuba samples per vertex: the bunny's indirect noise is about 0.097 at 256 spp, 0.040 here (<= 0.05)
SPP = 1536
#: Monte Carlo paths per vertex of the ball-over-floor reference: the floor's indirect noise 0.043 (<= 0.05)
PATHS = 16384
#: Pose A of the bunny (precompute pose of the moved cases): 1.1 m from pose B, turned 60 degrees
POSE_A = Transform(translate=np.array([0.9, 0.0, -0.8]), rotate_deg=np.array([0.0, 60.0, 0.0]))

#: the paper's method: its PCA basis (no occluders in the training), no self-interreflection, the basis radiance
#: interpolated everywhere, no residual gather, the SH direct light (area lights by their source radiance fields)
PAPER = dict(PAPER_OPTIONS)
CASES = {
    "fig9": ({}, False),
    "moved": ({}, True),
    "moved_paper": (PAPER, True),
    "moved_occluders": ({"pca_occluders": True, "residual_rays": 0}, True),
    "fig9_haar": ({"shadows": "haar"}, False),
}


def _measured(rel_rms, noise, error, mean, cause):
    return f"measured rel_rms {rel_rms} (noise {noise}, error {error}; mean {mean}): {cause}"


_SH_DIRECT = ("the paper's order-4 SH direct light of the near area light, from its source radiance field "
              "(shadows='sh', area_lights='field'; issue 18, item 2)")
_MOVED = ("the PCA bases hold the other objects' shadows at the precompute pose (pca_occluders), not at the "
          "new one, and no residual gather (issue 18)")
_PAPER = "the paper's basis (no occluders in the PCA training) cannot hold the bunny's shadow on the floor (issue 18)"
_NOT_TRACED = "not traced (the same with shadows='haar')"
#: Strict xfails of test_fig9_against_mitsuba: measured (SPP, seed 0) rel_rms, noise, error, mean; and causes.
#: The paper's method (moved_paper) has the SH direct light; every other case the ray-traced one (within 1 %).
_FIG9 = {
    "fig9": {("floor", "indirect"): ("0.322", "0.234", "0.221", "+4 %", _NOT_TRACED)},
    "moved_paper": {("floor", "direct"): ("0.127", "0.005", "0.127", "-0 %", _SH_DIRECT),
                    ("floor", "indirect"): ("0.816", "0.234", "0.782", "+29 %", _PAPER),
                    ("floor", "total"): ("0.128", "0.005", "0.128", "+0 %", f"its direct light, {_SH_DIRECT}"),
                    ("bunny", "direct"): ("0.114", "0.004", "0.114", "+4 %", _SH_DIRECT),
                    ("bunny", "indirect"): ("0.743", "0.040", "0.742", "-3 %",
                                            f"{_PAPER}; no self-interreflection (0.595 with it) and the floor's "
                                            "basis radiance interpolated near it (0.695 with near_field=0.5)"),
                    ("bunny", "total"): ("0.168", "0.008", "0.168", "+2 %", f"{_SH_DIRECT}, and its indirect")},
    "moved_occluders": {("floor", "indirect"): ("0.364", "0.234", "0.279", "+7 %", _MOVED),
                        ("bunny", "indirect"): ("0.587", "0.040", "0.586", "+18 %", _MOVED),
                        ("bunny", "total"): ("0.100", "0.008", "0.099", "+3 %", f"its indirect light, {_MOVED}")},
    "fig9_haar": {("floor", "indirect"): ("0.333", "0.234", "0.236", "+4 %", "not traced"),
                  ("bunny", "indirect"): ("0.193", "0.040", "0.189", "+4 %", "the floor's radiance under the bunny "
                                          "interpolated from its vertices (residual_near needs shadows='rays': "
                                          "0.110 there)")},
}
_FIG9["moved"] = dict(_FIG9["fig9"])  # the paper's basis and the gather: the same figures after the move
KNOWN: dict = {(case, obj, part): _measured(*v) for case, rows in _FIG9.items() for (obj, part), v in rows.items()}


def fig9_scene(bunny: Transform | None = None) -> Scene:
    """Fig. 9 with a 16 x 16 floor (289 vertices; the bunny's 1,839); ``bunny`` overrides its pose."""
    spec = yaml.safe_load(prtlab.data.scene_path("interreflection_fig9").read_text(encoding="utf-8"))
    spec["objects"][0]["mesh"] = {"builtin": "plane", "size": [3, 3], "resolution": [16, 16]}
    if bunny is not None:
        spec["objects"][1]["transform"] = bunny.to_dict()
    return Scene.from_dict(spec)


def _mitsuba(scene: Scene, spp: int):
    """``(scene, its one-bounce Mitsuba reference at spp samples per vertex, seed 0)``."""
    pytest.importorskip("mitsuba")
    from prtlab.reference import shade_mitsuba

    return scene, shade_mitsuba(scene, bounces=1, spp=spp, seed=0)


@pytest.fixture(scope="module")
def reference():
    return _mitsuba(fig9_scene(), SPP)


def _shades(scene: Scene, cases: dict, moved_scene: Scene, name: str):
    """``get(case)``: the case's shade with object ``name`` at its pose in ``scene``, computed once: precomputed
    on ``scene``, or for a moved case on ``moved_scene`` and moved back by a FrameState."""
    memo = {}

    def get(case):
        if case not in memo:
            options, moved = cases[case]
            source = moved_scene if moved else scene
            pre = Interreflection.precompute(source, options, progress=False)
            state = FrameState.from_scene(source)
            state.transforms[name] = scene.object(name).transform
            memo[case] = pre.shade(state, bounces=1)
        return memo[case]

    return get


@pytest.fixture(scope="module")
def shaded(reference):
    """``shaded(case)``: the case's shade at pose B, computed once per module."""
    return _shades(reference[0], CASES, fig9_scene(POSE_A), "bunny")


def scored_vertices(scene: Scene) -> dict:
    """Every vertex but the bunny's bottom (:func:`on_the_floor`)."""
    return {"bunny": ~on_the_floor(scene, "bunny")}


def mean_within_goal(ours: np.ndarray, ref: np.ndarray, stderr: np.ndarray, goal: float):
    """``(|mean(ours - ref)|, goal * rms(ref) + MC_SIGMAS * se(mean(ref)))`` per channel."""
    err = np.abs(np.mean(ours - ref, axis=0))
    se = np.sqrt(np.sum(stderr**2, axis=0)) / len(ref)
    return err, goal * np.sqrt(np.mean(ref**2, axis=0)) + MC_SIGMAS * se


def _param(case, obj, part):
    key = (case, obj, part)
    marks = [pytest.mark.xfail(strict=True, reason=KNOWN[key])] if key in KNOWN else []
    return pytest.param(case, obj, part, marks=marks, id=f"{case}-{obj}-{part}")


@pytest.mark.parametrize("case, obj, part", [_param(c, o, p) for c in CASES for o in ("floor", "bunny") for p in PARTS])
def test_fig9_against_mitsuba(reference, shaded, case, obj, part):
    """Fig. 9 reduced at pose B against Mitsuba at B: in place (defaults, ``shadows="haar"``) and after a
    move from pose A by a FrameState (defaults, ``pca_occluders=False``)."""
    scene, ref = reference
    ours = shaded(case)
    row = prtlab.compare(ours, ref, objects=[obj], parts=[part], masks=scored_vertices(scene)).row(obj, part)
    print(f"\n{case} {obj} {part}: rel_rms {row.rel_rms:.4f} noise {row.noise:.4f} error {row.error:.4f} "
          f"mean ratio {row.mean_ratio:.4f}")
    if (obj, part) == ("floor", "indirect"):  # its noise is above goal / 3 (module docstring)
        assert row.meets(GOAL[part]), row
        err, bound = mean_within_goal(ours.indirect["floor"], ref.indirect["floor"], ref.stderr["indirect"]["floor"],
                                      GOAL[part])
        assert np.all(err <= bound), (err, bound, row)
        return
    comparison = prtlab.compare(ours, ref, objects=[obj], parts=[part], masks=scored_vertices(scene))
    failures = comparison.check(GOAL[part])
    assert not failures, failures


# --------------------------------------------------------------------------- ball over floor, Monte Carlo

#: (measured rel_rms 0.148, noise 0.043, for the floor's indirect light; 0.301 without the residual gather)
BALL_KNOWN: dict = {}


@pytest.fixture(scope="module")
def ball_over_floor():
    from prtlab.reference import path_trace
    from tests.interreflection.test_pipeline import QUICK, scene

    pre = Interreflection.precompute(scene(), QUICK, progress=False)
    return pre.shade(bounces=1), path_trace(pre.scene, 1, PATHS, np.random.default_rng(11))


def _ball_param(obj, part):
    key = (obj, part)
    marks = [pytest.mark.xfail(strict=True, reason=BALL_KNOWN[key])] if key in BALL_KNOWN else []
    return pytest.param(obj, part, marks=marks, id=f"{obj}-{part}")


@pytest.mark.parametrize("obj, part", [_ball_param(o, p) for o in ("floor", "ball") for p in PARTS])
def test_ball_over_floor_against_monte_carlo(ball_over_floor, obj, part):
    """One bounce between a ball and a red floor (quick options) against 16,384 paths per vertex."""
    ours, ref = ball_over_floor
    comparison = prtlab.compare(ours, ref, objects=[obj], parts=[part])
    row = comparison.row(obj, part)
    print(f"\nball_over_floor {obj} {part}: rel_rms {row.rel_rms:.4f} noise {row.noise:.4f} error {row.error:.4f} "
          f"mean ratio {row.mean_ratio:.4f}")
    failures = comparison.check(GOAL[part])
    assert not failures, failures


# --------------------------------------------------------------------------- a box resting on a floor under a sky

#: Monte Carlo paths per vertex of the box on the floor: noise <= 0.033 (indirect) on both objects
BOX_PATHS = 8192
_BAND_LIMIT = ("the order-4 sky against the floor's hard horizon at the box's bottom row (the half-space's exact "
               "order-4 light, test_flat.py; with the sky's higher bands, horizon_sky: met)")
#: The box's cases: the defaults (the half-space and the sky's higher bands through it), the half-space with the
#: order-4 sky alone, and the paper's occlusion field
BOX_MODES = {"plane": {}, "plane_order4": {"horizon_sky": False}, "field": {"flat_visibility": "field"}}
#: Strict xfails of test_box_on_floor_against_monte_carlo (BOX_PATHS, seed 5): measured rel_rms, noise, error, mean
BOX_KNOWN = {
    ("plane_order4", "box", "direct"): _measured("0.055", "0.007", "0.055", "-1 %", _BAND_LIMIT),
    ("plane_order4", "box", "total"): _measured("0.065", "0.006", "0.065", "-2 %", _BAND_LIMIT),
    ("field", "box", "direct"): _measured("0.162", "0.007", "0.162", "-5 %", "the floor's occlusion field, "
                                          "interpolated across its plane, at the box's bottom row (the paper)"),
    ("field", "box", "total"): _measured("0.159", "0.006", "0.159", "-6 %", "its direct light (the paper)"),
    ("field", "floor", "indirect"): _measured("0.258", "0.033", "0.256", "-4 %", "the box's bottom row's light "
                                              "it gathers (the paper)"),
}


def box_on_floor_scene() -> Scene:
    """A 0.6 m box (subdivided twice, turned 25 degrees) resting on a 4 x 4 m floor under a clear sky (sun 30
    degrees up)."""
    return Scene.from_dict({
        "objects": [
            {"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [16, 16]},
             "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}},
            {"name": "box", "mesh": {"builtin": "box", "size": [0.6, 0.6, 0.6], "subdivisions": 2},
             "transform": {"translate": [0.3, 0.3, -0.2], "rotate_deg": [0, 25, 0]}, "dynamic": True,
             "material": {"type": "diffuse", "albedo": [0.8, 0.5, 0.3]}},
        ],
        "lights": [{"type": "environment", "sky": {"sun_elevation_deg": 30, "sun_azimuth_deg": 40, "turbidity": 3,
                                                   "height": 32, "width": 64}}],
    })


@pytest.fixture(scope="module")
def box_on_floor():
    """``(scene, reference, {mode: shade})``: one bounce, the defaults with each of :data:`BOX_MODES`."""
    from prtlab.reference import path_trace

    scene = box_on_floor_scene()
    pre = Interreflection.precompute(scene, progress=False)
    shades = {mode: Interreflection(scene, dataclasses.replace(pre.options, **options), pre.data).shade(bounces=1)
              for mode, options in BOX_MODES.items()}
    return scene, path_trace(scene, 1, BOX_PATHS, np.random.default_rng(5)), shades


def _box_param(mode, obj, part):
    key = (mode, obj, part)
    marks = [pytest.mark.xfail(strict=True, reason=BOX_KNOWN[key])] if key in BOX_KNOWN else []
    return pytest.param(mode, obj, part, marks=marks, id=f"{mode}-{obj}-{part}")


@pytest.mark.parametrize("mode, obj, part", [_box_param(m, o, p) for m in BOX_MODES for o in ("floor", "box")
                                             for p in PARTS])
def test_box_on_floor_against_monte_carlo(box_on_floor, mode, obj, part):
    """A box resting on a floor under a sky, every vertex scored but the box's bottom face (its normal into the
    floor, ``docs/DECISIONS.md``): its sides' bottom row counts. ``flat_visibility="plane"`` with the sky's
    higher bands through it (the defaults), without them (``horizon_sky=False``), and the paper's field."""
    scene, ref, shades = box_on_floor
    masks = {"box": ~on_the_floor(scene, "box")}
    comparison = prtlab.compare(shades[mode], ref, objects=[obj], parts=[part], masks=masks)
    row = comparison.row(obj, part)
    print(f"\nbox_on_floor {mode} {obj} {part}: rel_rms {row.rel_rms:.4f} noise {row.noise:.4f} "
          f"error {row.error:.4f} mean ratio {row.mean_ratio:.4f}")
    failures = comparison.check(GOAL[part])
    assert not failures, failures


# --------------------------------------------------------------------------- open room corner, moved torus

#: Mitsuba samples per vertex of the corner: indirect noise <= 0.05 (goal / 3) on every object
CORNER_SPP = 2048
#: The torus's precompute pose of the moved corner cases: 1.16 m from its pose in the scene, raised, turned
TORUS_AWAY = Transform(translate=np.array([1.2, 0.45, 1.1]), rotate_deg=np.array([20.0, 40.0, 0.0]))
CORNER_OBJECTS = ("floor", "wall_back", "wall_left", "box", "torus")
CORNER_CASES = {
    "corner": ({}, False),
    "corner_moved": ({}, True),
    "corner_moved_paper": (PAPER, True),
}
#: The issue's binding bounds (issue 18), checked besides the goals (GOAL)
BOUND = {"indirect": 0.20, "total": 0.10}
#: Misses at the defaults (CORNER_SPP, seed 0), the same in place and after the move: none. (The torus's indirect
#: light, 0.328 with every gather hit interpolated from the floor's vertices 0.25 m apart under the torus's shadow
#: 3 cm below, is within the goal with the near hits' radiance evaluated at the hit, ``residual_near``.)
_CORNER: dict = {}
#: The paper's method after the move (PAPER): misses per object, (rel_rms, noise, error, mean) of direct, indirect and
#: total; which bounds each part misses; and the causes.
_NEAR = ("basis radiance interpolated at points near a source's surface (near_field=0; with near_field=0.5: floor "
         "0.172, back wall 0.118, left wall 0.107)")
_CORNER_PAPER_ROWS = {
    "floor": ((("0.109", "0.005", "0.109", "+0 %"), ("0.259", "0.033", "0.256", "-5 %"), ("0.105", "0.006", "0.105",
                                                                                           "-0 %")),
              ("goal", "bound"), f"the other objects' light it gathers: {_NEAR}"),
    "wall_back": ((("0.089", "0.006", "0.089", "-1 %"), ("0.209", "0.038", "0.205", "-7 %"), ("0.110", "0.010",
                                                                                              "0.110", "-3 %")),
                  ("goal", "bound"), f"the floor's light it gathers at its bottom edge: {_NEAR}"),
    "wall_left": ((("0.091", "0.006", "0.090", "-2 %"), ("0.200", "0.038", "0.196", "-7 %"), ("0.109", "0.011",
                                                                                              "0.109", "-3 %")),
                  ("goal",), f"the floor's light it gathers at its bottom edge: {_NEAR}"),
    "box": ((("0.110", "0.006", "0.110", "+12 %"), ("0.279", "0.023", "0.278", "-11 %"), ("0.111", "0.009", "0.110",
                                                                                         "+3 %")),
            ("goal", "bound"), "its sides' bottom row, on the floor: the floor's light there through the paper's "
                               "basis interpolated at the floor's surface, no gather"),
    "torus": ((("0.102", "0.003", "0.102", "+9 %"), ("0.820", "0.025", "0.819", "+27 %"), ("0.253", "0.008", "0.253",
                                                                                           "+14 %")),
              ("goal", "bound"), "the paper's basis cannot hold the torus's shadow on the floor under it (issue 18)"),
}
_CORNER_PAPER = {}
for _o, ((_direct, _indirect, _total), _indirect_bounds, _cause) in _CORNER_PAPER_ROWS.items():
    _CORNER_PAPER[_o, "direct", "goal"] = (*_direct, _SH_DIRECT)
    _CORNER_PAPER.update({(_o, "indirect", b): (*_indirect, _cause) for b in _indirect_bounds})
    _CORNER_PAPER.update({(_o, "total", b): (*_total, f"its direct light ({_SH_DIRECT}) and its indirect light")
                          for b in ("goal", "bound")})
CORNER_KNOWN: dict = {(case, *key): _measured(*v) for case, table in
                      (("corner", _CORNER), ("corner_moved", _CORNER), ("corner_moved_paper", _CORNER_PAPER))
                      for key, v in table.items()}


def corner_scene(torus: Transform | None = None, light: AreaLight | None = None) -> Scene:
    """``interreflection_corner`` (a 4 x 4 floor, two 3 m walls, a box, a torus 3 cm above the floor, a 1 x 1
    area light 2.6 m up); ``torus`` overrides the torus's pose, ``light`` the area light."""
    spec = yaml.safe_load(prtlab.data.scene_path("interreflection_corner").read_text(encoding="utf-8"))
    if torus is not None:
        next(o for o in spec["objects"] if o["name"] == "torus")["transform"] = torus.to_dict()
    if light is not None:
        spec["lights"] = [light.to_dict()]
    return Scene.from_dict(spec)


@pytest.fixture(scope="module")
def corner_reference():
    return _mitsuba(corner_scene(), CORNER_SPP)


@pytest.fixture(scope="module")
def corner_shaded(corner_reference):
    """``corner_shaded(case)``: the case's shade with the torus at its scene pose, computed once per module."""
    return _shades(corner_reference[0], CORNER_CASES, corner_scene(TORUS_AWAY), "torus")


def _bounded_params(cases, objects, known: dict) -> list:
    """``(case, obj, part, bound)`` params over ``cases`` and ``objects``: every part against the module's goal
    (GOAL) and the issue's bound (BOUND), a strict xfail where ``known`` gives the measured miss."""
    params = []
    for case in cases:
        for obj in objects:
            for part, bound in [*((p, "goal") for p in PARTS), *((p, "bound") for p in BOUND)]:
                key = (case, obj, part, bound)
                marks = [pytest.mark.xfail(strict=True, reason=known[key])] if key in known else []
                params.append(pytest.param(case, obj, part, bound, marks=marks, id=f"{case}-{obj}-{part}-{bound}"))
    return params


def _check_row(scene, ref, ours, case, obj, part, bound):
    """One object's part against Mitsuba, within GOAL or BOUND; the box's bottom face, on the floor, left out
    (``docs/DECISIONS.md``)."""
    comparison = prtlab.compare(ours, ref, objects=[obj], parts=[part], masks={"box": ~on_the_floor(scene, "box")})
    row = comparison.row(obj, part)
    print(f"\n{case} {obj} {part}: rel_rms {row.rel_rms:.4f} noise {row.noise:.4f} error {row.error:.4f} "
          f"mean ratio {row.mean_ratio:.4f}")
    failures = comparison.check(GOAL[part] if bound == "goal" else BOUND[part])
    assert not failures, failures


@pytest.mark.parametrize("case, obj, part, bound", _bounded_params(CORNER_CASES, CORNER_OBJECTS, CORNER_KNOWN))
def test_corner_against_mitsuba(corner_reference, corner_shaded, case, obj, part, bound):
    """The open room corner against Mitsuba with the torus at its scene pose: precomputed there, and precomputed
    with the torus 1.16 m away then moved back by a FrameState (defaults; the paper's method). ``bound``:
    the module's goal (GOAL) or the issue's binding bound (BOUND). The box's bottom face, on the floor, is
    left out (``docs/DECISIONS.md``)."""
    _check_row(*corner_reference, corner_shaded(case), case, obj, part, bound)


# --------------------------------------------------------------------------- the corner after a move

#: The area light moved and turned after the precomputation: 0.9 m from its place in the scene, 17 degrees
#: off the vertical, nearer the torus
LIGHT_MOVED = AreaLight(center=np.array([0.7, 2.2, 0.6]), u=np.array([0.5, 0.0, 0.0]),
                        v=np.array([0.0, -0.15, 0.48]), radiance=np.array([12.0, 12.0, 12.0]))
#: The torus moved beside the box after the precomputation: 2.5 cm from the box's side, still 3 cm above the floor
TORUS_BY_BOX = Transform(translate=np.array([-0.11, 0.18, -0.31]), rotate_deg=np.array([0.0, 15.0, 0.0]))
#: case -> (the scene the reference renders, the frame's change to the precomputed corner)
AFTER_MOVES = {"light_moved": (dict(light=LIGHT_MOVED), ("lights", [LIGHT_MOVED])),
               "torus_by_box": (dict(torus=TORUS_BY_BOX), ("torus", TORUS_BY_BOX))}
#: Misses at the defaults (CORNER_SPP, seed 0): none.
AFTER_KNOWN: dict = {}


@pytest.fixture(scope="module")
def corner_after_move():
    """``get(case)``: ``(scene, Mitsuba at CORNER_SPP, ours)`` for a case of AFTER_MOVES: the corner precomputed
    as it ships (defaults), then the light or the torus moved by a FrameState; computed once, when first asked."""
    memo = {}

    def get(case):
        if case not in memo:
            scene_args, (what, value) = AFTER_MOVES[case]
            scene, ref = _mitsuba(corner_scene(**scene_args), CORNER_SPP)
            shipped = corner_scene()
            state = FrameState.from_scene(shipped)
            if what == "lights":
                state.lights = list(value)
            else:
                state.transforms[what] = value
            ours = Interreflection.precompute(shipped, {}, progress=False).shade(state, bounces=1)
            memo[case] = scene, ref, ours
        return memo[case]

    return get


@pytest.mark.parametrize("case, obj, part, bound", _bounded_params(AFTER_MOVES, CORNER_OBJECTS, AFTER_KNOWN))
def test_corner_after_a_move_against_mitsuba(corner_after_move, case, obj, part, bound):
    """Issue 18's motion tests: the corner precomputed as it ships, then the area light moved and turned
    (``light_moved``) or the torus moved beside the box (``torus_by_box``) by a FrameState, against Mitsuba at
    the new state; every object, direct / indirect / total, the module's goal and the issue's bound."""
    _check_row(*corner_after_move(case), case, obj, part, bound)


# --------------------------------------------------------------------------- three objects nearly touching

#: The corner with the torus beside the box and a ball 2 cm from both, 3 cm above the floor: pairs with two
#: non-flat occluders, where the SH products' order could matter (the paper's Sec. 6)
CLUSTER_BALL = {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.25, "subdivisions": 3},
                "transform": {"translate": [-0.89, 0.28, -0.19]},
                "material": {"type": "diffuse", "albedo": [0.3, 0.5, 0.8]}, "dynamic": True}
#: case -> options: the products nearest first (defaults), the order-independent exp* of the summed logs
CLUSTER_CASES = {"cluster": {}, "cluster_exp": {"occlusion": "exp"}}
CLUSTER_OBJECTS = (*CORNER_OBJECTS, "ball")
#: Misses (CORNER_SPP, seed 0): none.
CLUSTER_KNOWN: dict = {}


def cluster_scene() -> Scene:
    scene = corner_scene(TORUS_BY_BOX)
    spec = scene.to_dict()
    spec["objects"].append(CLUSTER_BALL)
    return Scene.from_dict(spec)


@pytest.fixture(scope="module")
def cluster():
    """``get(case)``: ``(scene, Mitsuba at CORNER_SPP, ours)`` of a CLUSTER_CASES case, computed when first asked."""
    memo = {}

    def get(case):
        if "reference" not in memo:
            memo["reference"] = _mitsuba(cluster_scene(), CORNER_SPP)
        if "pre" not in memo:
            memo["pre"] = Interreflection.precompute(memo["reference"][0], progress=False)
        if case not in memo:  # the run-time options on the defaults' precomputation (exp: its logs built here)
            pre = memo["pre"]
            options = dataclasses.replace(pre.options, **CLUSTER_CASES[case])
            memo[case] = Interreflection(pre.scene, options, pre.data).shade(bounces=1)
        return (*memo["reference"], memo[case])

    return get


@pytest.mark.parametrize("case, obj, part, bound", _bounded_params(CLUSTER_CASES, CLUSTER_OBJECTS, CLUSTER_KNOWN))
def test_cluster_against_mitsuba(cluster, case, obj, part, bound):
    """Three objects 2 cm apart on the corner's floor (torus, box, ball), one bounce, against Mitsuba: the SH
    products nearest first (defaults) and ``occlusion="exp"`` (the paper's future work, Sec. 6); every object."""
    _check_row(*cluster(case), case, obj, part, bound)
