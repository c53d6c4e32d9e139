"""The portals pipeline (Yue et al. 2009) against Mitsuba 3: a room lit through a window by the sky.

Scenes: the shipped ``tiny_window_room`` (a 2 m box room, 0.5 m cells, one 1.0 x 0.8 m window on its -z wall,
a clear Preetham sky) with a dynamic diffuse block inside, under the sky alone (the paper's Fig. 10 setting at
reduced size) and under the sky with its sun disk (a sunlit room, issue 17), and the block moved to a second
pose. The method runs at its default options with ``bounces=2``; Mitsuba 3 renders the same two bounces.

Metric: relative RMS per vertex (:func:`prtlab.compare`), every object, direct / indirect / total apart, the
reference's noise removed in quadrature (:meth:`prtlab.metrics.ComparisonRow.meets`). Goal: 5%. The paper reports
a 1.5% average relative error on its diffuse box (2.1% on the glossy bunny); a per-vertex relative RMS is at
least the average relative error, and judging 1.5% needs a reference noise of 0.5% (about 10^6 Mitsuba samples
per vertex here, far beyond this module's budget of about 6 CPU-minutes), so the goal is the issue's looser 5%,
judged against references whose noise is at most a third of it (65,536 samples per vertex).

Motion: the method bakes every object's pose into its transfer, so ``shade(FrameState)`` with the block moved is
refused, and the block at its new pose is scored after a precomputation at that pose
(``prtlab.api.precompute(scene_at_new_pose, "portals", ...)``).
"""

from __future__ import annotations

import numpy as np
import pytest

import prtlab
import prtlab.api
from prtlab.pipeline import FrameState
from prtlab.reference import shade_mitsuba
from prtlab.scene import Scene

pytestmark = pytest.mark.xdist_group("fidelity-portals")

GOAL = 0.05
BOUNCES = 2
SPP = 65536
OPTIONS = {"bounces": BOUNCES}  # the method's defaults otherwise
POSES = {"first": [0.3, 0.25, 0.2], "moved": [-0.4, 0.25, -0.35]}
OBJECTS = ("room", "block")
PARTS = ("direct", "indirect", "total")


def window_room(sun: bool = False, pose: str = "first") -> Scene:
    """``tiny_window_room`` with a dynamic block (a 0.5 m cube) at ``POSES[pose]``; the sky's sun disk if ``sun``."""
    d = prtlab.load_scene("tiny_window_room").to_dict()
    d["objects"].append({"name": "block", "mesh": {"builtin": "box"}, "dynamic": True,
                         "transform": {"translate": POSES[pose], "scale": 0.5},
                         "material": {"type": "diffuse", "albedo": [0.6, 0.5, 0.4]}})
    d["lights"][0]["sky"]["sun"] = sun
    return Scene.from_dict(d)


def _compare(pre, scene, seed):
    ours = pre.shade(bounces=BOUNCES)
    ref = shade_mitsuba(scene, bounces=BOUNCES, spp=SPP, seed=seed)
    comparison = prtlab.compare(ours, ref, objects=OBJECTS)
    print(f"\n{scene.name} ({len(ref.total)} objects, {SPP} spp)\n{comparison.table()}")
    return comparison


@pytest.fixture(scope="module")
def sky_pre():
    return prtlab.api.precompute(window_room(), "portals", progress=False, **OPTIONS)


@pytest.fixture(scope="module")
def sky(sky_pre):
    return _compare(sky_pre, sky_pre.scene, seed=1)


@pytest.fixture(scope="module")
def moved():
    scene = window_room(pose="moved")
    return _compare(prtlab.api.precompute(scene, "portals", progress=False, **OPTIONS), scene, seed=2)


@pytest.fixture(scope="module")
def sunlit():
    scene = window_room(sun=True)
    return _compare(prtlab.api.precompute(scene, "portals", progress=False, **OPTIONS), scene, seed=3)


# Measured (this module, the seeds below): relative RMS per vertex, the reference's relative noise, mean ratio.
MEASURED = {
    ("sky", "room", "indirect"): (0.293, 0.016, 0.75), ("sky", "block", "indirect"): (0.274, 0.013, 0.78),
    ("sky", "room", "total"): (0.145, 0.011, 0.85), ("sky", "block", "total"): (0.091, 0.008, 0.91),
    ("moved", "room", "indirect"): (0.313, 0.016, 0.74), ("moved", "block", "indirect"): (0.211, 0.014, 0.83),
    ("moved", "room", "total"): (0.154, 0.011, 0.85), ("moved", "block", "total"): (0.058, 0.007, 0.94),
    ("sunlit", "room", "direct"): (0.093, 0.006, 1.02), ("sunlit", "block", "direct"): (0.051, 0.004, 1.03),
    ("sunlit", "room", "indirect"): (0.544, 0.013, 0.76), ("sunlit", "block", "indirect"): (0.390, 0.010, 0.89),
    ("sunlit", "room", "total"): (0.214, 0.007, 0.87), ("sunlit", "block", "total"): (0.101, 0.004, 0.99),
}
LOW_INDIRECT = ("indirect light too dark: a vertex's photon density estimate on a wall's edge (corner) gathers "
                "photons over 1/2 (1/4) of its disc but divides by the whole disc, and 69% of this room's 0.5 m-cell "
                "vertices are on edges (on the same room under a constant sky, removing that and the k/(k-1) excess "
                "of the k-NN estimate takes the gathered indirect light from 10-15% low to 2-7% low)")
SUN_EDGES = ("the sun patch's edges: a vertex near them gets the wrong share of the sun at the default res=32 "
             "(issue 17)")


def _case(case, obj, part):
    if (case, obj, part) not in MEASURED:
        return (case, obj, part)
    rel_rms, noise, ratio = MEASURED[case, obj, part]
    cause = {"direct": SUN_EDGES, "indirect": LOW_INDIRECT, "total": "its indirect part's " + LOW_INDIRECT}[part]
    if case == "sunlit" and part != "direct":
        cause += "; the larger per-vertex spread under the sun is not analysed here"
    reason = f"measured rel_rms {rel_rms:.3f} (noise {noise:.3f}, mean ratio {ratio:.2f}) > goal {GOAL}: {cause}"
    return pytest.param(case, obj, part, marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason=reason))


CASES = [_case(c, o, p) for c in ("sky", "moved", "sunlit") for o in OBJECTS for p in PARTS]


@pytest.mark.parametrize("case, obj, part", CASES)
def test_against_mitsuba(request, case, obj, part):
    """``rel_rms <= hypot(GOAL, noise)`` for one object and part; ``check`` refuses a reference noisier than
    ``GOAL / 3``."""
    comparison = request.getfixturevalue(case)
    assert comparison.check(GOAL, parts=(part,), objects=(obj,)) == [], comparison.table()


def test_every_object_scored(sky):
    """The comparison covers every shaded object of the scene, each part (the window is a portal, not a surface)."""
    assert sorted(sky.objects) == sorted(OBJECTS)
    assert {(r.object, r.part) for r in sky.rows} == {(o, p) for o in OBJECTS for p in PARTS}


def test_moved_block_refused(sky_pre):
    """Shading a frame in which the block moved is refused (the transfer bakes its pose), naming the object."""
    state = FrameState.from_scene(sky_pre.scene)
    state.transforms["block"] = window_room(pose="moved").object("block").transform
    with pytest.raises(ValueError, match="object 'block' moved; .*re-precompute at the new pose"):
        sky_pre.shade(state, bounces=BOUNCES)
