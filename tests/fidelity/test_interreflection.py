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
:class:`prtlab.pipeline.FrameState`, at the defaults and with
``pca_occluders=False`` (the paper's basis). The reference is Mitsuba at B for every case. Bunny
vertices on the floor (y <= 0.01) are left out (``docs/DECISIONS.md``). Ball over floor
(``tests/interreflection/test_pipeline.py``, quick options) against prtlab's own path tracer with 16,384
paths per vertex.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

import prtlab
from prtlab.interreflection import Interreflection
from prtlab.pipeline import FrameState
from prtlab.scene import Scene, Transform
from tests.conftest import MC_SIGMAS

pytestmark = [pytest.mark.mitsuba, pytest.mark.xdist_group("fidelity-interreflection")]

GOAL = {"direct": 0.05, "indirect": 0.15, "total": 0.05}
PARTS = tuple(GOAL)
#: Mitsuba samples per vertex: the bunny's indirect noise is about 0.097 at 256 spp, 0.040 here (<= 0.05)
SPP = 1536
#: Monte Carlo paths per vertex of the ball-over-floor reference: the floor's indirect noise 0.043 (<= 0.05)
PATHS = 16384
#: Pose A of the bunny (precompute pose of the moved cases): 1.1 m from pose B, turned 60 degrees
POSE_A = Transform(translate=np.array([0.9, 0.0, -0.8]), rotate_deg=np.array([0.0, 60.0, 0.0]))

CASES = {
    "fig9": ({}, False),
    "moved": ({}, True),
    "moved_paper_basis": ({"pca_occluders": False}, True),
    "fig9_haar": ({"shadows": "haar"}, False),
}


def _measured(rel_rms, noise, error, mean, cause):
    return f"measured rel_rms {rel_rms} (noise {noise}, error {error}; mean {mean}): {cause}"


_SH_DIRECT = "the order-4 SH direct light of the small area light (issue 18, item 2)"
_DIRECT = {"floor": ("0.131", "0.005", "0.131", "-2 %"), "bunny": ("0.137", "0.004", "0.137", "-8 %")}
_MOVED = ("the PCA bases hold the other objects' shadows at the precompute pose (pca_occluders), not at the "
          "new one (issue 18)")
_PAPER = "the paper's basis (no occluders in the PCA training) cannot hold the bunny's shadow on the floor (issue 18)"
#: Strict xfails of test_fig9_against_mitsuba: measured figures (SPP, seed 0) and causes.
KNOWN: dict = {
    **{(case, obj, "direct"): _measured(*_DIRECT[obj], _SH_DIRECT)
       for case in ("fig9", "moved", "moved_paper_basis") for obj in _DIRECT},
    ("fig9", "floor", "total"): _measured("0.131", "0.005", "0.131", "-2 %", f"its direct light, {_SH_DIRECT}"),
    ("fig9", "bunny", "total"): _measured("0.146", "0.008", "0.146", "-5 %", f"its direct light, {_SH_DIRECT}"),
    ("fig9", "floor", "indirect"): _measured("0.516", "0.234", "0.460", "-1 %", "mostly the bunny's direct light "
                                             f"it re-emits, {_SH_DIRECT} (error 0.201 with shadows='haar')"),
    ("fig9", "bunny", "indirect"): _measured("0.353", "0.040", "0.350", "+8 %", "not traced; not the direct light "
                                             "(error 0.315 with shadows='haar')"),
    ("fig9_haar", "floor", "indirect"): _measured("0.309", "0.234", "0.201", "+5 %", "not traced"),
    ("fig9_haar", "bunny", "indirect"): _measured("0.317", "0.040", "0.315", "+8 %", "not traced (0.350 at the "
                                                  "defaults: not the direct light)"),
    ("fig9_haar", "bunny", "total"): _measured("0.054", "0.008", "0.054", "+1 %", "its indirect light (above)"),
    ("moved", "floor", "total"): _measured("0.132", "0.005", "0.132", "-2 %", f"its direct light, {_SH_DIRECT}"),
    ("moved", "bunny", "total"): _measured("0.170", "0.008", "0.170", "-4 %", f"{_SH_DIRECT}, and its indirect"),
    ("moved", "floor", "indirect"): _measured("0.651", "0.234", "0.608", "+4 %", "not traced (0.460 in place; "
                                              "the bunny's direct light, which it re-emits, is the same)"),
    ("moved", "bunny", "indirect"): _measured("0.593", "0.040", "0.591", "+15 %", _MOVED),
    ("moved_paper_basis", "floor", "total"): _measured("0.132", "0.005", "0.132", "-2 %",
                                                       f"its direct light, {_SH_DIRECT}"),
    ("moved_paper_basis", "bunny", "total"): _measured("0.162", "0.008", "0.162", "-4 %",
                                                       f"{_SH_DIRECT}, and its indirect"),
    ("moved_paper_basis", "floor", "indirect"): _measured("1.147", "0.234", "1.123", "+15 %", _PAPER),
    ("moved_paper_basis", "bunny", "indirect"): _measured("0.527", "0.040", "0.526", "+13 %", _PAPER),
}


def fig9_scene(bunny: Transform | None = None) -> Scene:
    """Fig. 9 with a 16 x 16 floor (289 vertices; the bunny's 1,839); ``bunny`` overrides its pose."""
    spec = yaml.safe_load(prtlab.data.scene_path("interreflection_fig9").read_text(encoding="utf-8"))
    spec["objects"][0]["mesh"] = {"builtin": "plane", "size": [3, 3], "resolution": [16, 16]}
    if bunny is not None:
        spec["objects"][1]["transform"] = bunny.to_dict()
    return Scene.from_dict(spec)


@pytest.fixture(scope="module")
def reference():
    pytest.importorskip("mitsuba")
    from prtlab.reference import shade_mitsuba

    scene = fig9_scene()
    return scene, shade_mitsuba(scene, bounces=1, spp=SPP, seed=0)


@pytest.fixture(scope="module")
def shaded(reference):
    """``shaded(case)``: the case's shade at pose B, computed once per module."""
    scene_b, _ = reference
    memo = {}

    def get(case):
        if case not in memo:
            options, moved = CASES[case]
            scene = fig9_scene(POSE_A) if moved else scene_b
            pre = Interreflection.precompute(scene, options, progress=False)
            state = FrameState.from_scene(scene)
            state.transforms["bunny"] = scene_b.object("bunny").transform
            memo[case] = pre.shade(state, bounces=1)
        return memo[case]

    return get


def scored_vertices(scene: Scene) -> dict:
    """Bunny vertices off the floor (its bottom has no meaningful radiance); every floor vertex."""
    return {"bunny": scene.object("bunny").world_vertices()[:, 1] > 0.01}


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

BALL_KNOWN = {("floor", "indirect"): "measured rel_rms 0.301 (noise 0.043, error 0.298; mean +18 %): the ball's "
                                    "bounce light on the floor is too bright; the floor is a plane (visibility 1, "
                                    "exact transfer), so the error is in the ball as a source (its N = 8 PCA radiance "
                                    "on the quick sample spheres), not traced further"}


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
