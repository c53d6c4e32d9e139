"""Moving portals (option ``portal_strips``): the sunlit room with its window part open, against references.

``sunlit_window_room`` precomputed once with the whole window and :data:`STRIPS` strips; each frame opens part
of it (``FrameState.deformations`` of the window, :meth:`prtlab.portals.Portals.opening_vertices`). The reference
scene models the same frame independently: the portal object shrunk to the open part and a black (albedo 0)
diffuse shutter quad over the closed part of the hole (:func:`opened_room`). Direct light against the window
quadrature over the open part (``tests/fidelity/test_portals.py``: the room is an empty box, so no visibility
term), cheap; indirect and total against Mitsuba 3 (1.5-4 minutes of Mitsuba: marked ``slow`` and skipped in the
quick fidelity run, ``PRTLAB_QUICK=1``; ``make test-slow`` runs it), per surface, the reference's noise in
quadrature. Goal: issue 17's binding 3% per surface.

Openings: the lower half (on the strips' boundaries: exact up to the transfer's own error) and the lower 45%
(the top open strip part open: its light taken as that fraction of the strip's, the approximation measured here).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import prtlab
import prtlab.api
from prtlab.pipeline import FrameState
from prtlab.reference import shade_mitsuba
from prtlab.scene import Scene, ShadeResult

from .test_portals import SPP, SUN_GOAL, SURFACES, UNLIT, by_surface, window_quadrature

pytestmark = pytest.mark.xdist_group("fidelity-portals-aperture")

STRIPS = 8
BOUNCES = 4
WINDOW_Y = (0.9, 2.1)  # the sunlit room's window, bottom and top


def opened_room(low: float, high: float) -> Scene:
    """``sunlit_window_room`` with its window open over ``low..high`` (fractions of its height from the bottom):
    the portal object shrunk to that part, a black diffuse shutter quad over the rest of the hole."""
    d = prtlab.load_scene("sunlit_window_room").to_dict()
    y0, y1 = WINDOW_Y
    a, b = y0 + (y1 - y0) * low, y0 + (y1 - y0) * high
    window = d["objects"][1]["mesh"]
    window["center"], window["size"] = [0.0, (a + b) / 2], [window["size"][0], b - a]
    for i, (p, q) in enumerate(((y0, a), (b, y1))):
        if q - p > 1e-9:
            d["objects"].append({"name": f"shutter{i}", "mesh": {
                "builtin": "window", "room_size": [4, 3, 4], "wall": "-z", "center": [0.0, (p + q) / 2],
                "size": [window["size"][0], q - p]}, "material": {"type": "diffuse", "albedo": [0.0, 0.0, 0.0]}})
    return Scene.from_dict(d)


@pytest.fixture(scope="module")
def aperture_pre():
    """The whole window precomputed with :data:`STRIPS` strips (defaults otherwise, :data:`BOUNCES` bounces)."""
    return prtlab.api.precompute(prtlab.load_scene("sunlit_window_room"), "portals", progress=False,
                                 bounces=BOUNCES, portal_strips=STRIPS)


def ours_open(pre, low: float, high: float) -> ShadeResult:
    state = FrameState.from_scene(pre.scene)
    state.deformations["window"] = pre.opening_vertices("window", low, high)
    return pre.shade(state, bounces=BOUNCES)


def _direct_comparison(pre, low, high):
    scene = opened_room(low, high)
    normals = scene.object("room").world_normals()
    ours = ours_open(pre, low, high)
    fine, coarse = window_quadrature(scene, 128), window_quadrature(scene, 64)
    ref = ShadeResult()
    ref.direct["room"], ref.stderr["direct"] = fine, {"room": np.abs(fine - coarse)}
    for part in ("indirect", "total"):
        getattr(ref, part)["room"] = fine
    comparison = prtlab.compare(by_surface(ours, normals), by_surface(ref, normals), parts=("direct",))
    print(f"\nsunlit_window_room open {low}..{high}, {STRIPS} strips, direct vs the window quadrature\n"
          f"{comparison.table()}")
    return comparison


OPENINGS = {"half": (0.0, 0.5), "part_strip": (0.0, 0.45)}
DIRECT_CASES = [(o, s) for o in OPENINGS for s in SURFACES if s not in UNLIT]


@pytest.fixture(scope="module")
def direct_comparisons():
    """Each opening's direct comparison, made once."""
    return {}


@pytest.mark.parametrize("opening, surface", DIRECT_CASES)
def test_part_open_direct_against_quadrature(aperture_pre, direct_comparisons, opening, surface):
    """The direct light of each lit surface with the window part open within ``hypot(SUN_GOAL, noise)``."""
    if opening not in direct_comparisons:
        direct_comparisons[opening] = _direct_comparison(aperture_pre, *OPENINGS[opening])
    comparison = direct_comparisons[opening]
    assert comparison.check(SUN_GOAL, parts=("direct",), objects=(surface,)) == [], comparison.table()


def test_closed_part_is_black(aperture_pre):
    """Through a closed window no light enters: every part of every vertex is black."""
    r = ours_open(aperture_pre, 0.3, 0.3)
    assert np.all(r.total["room"] == 0)


@pytest.fixture(scope="module")
def half_open(aperture_pre):
    """Ours and Mitsuba (the direct part by the window quadrature) with the lower half open, per surface."""
    scene = opened_room(*OPENINGS["half"])
    normals = scene.object("room").world_normals()
    ours = by_surface(ours_open(aperture_pre, *OPENINGS["half"]), normals)
    mitsuba = shade_mitsuba(scene, bounces=BOUNCES, spp=SPP, seed=7)
    fine, coarse = window_quadrature(scene, 128), window_quadrature(scene, 64)
    mitsuba.direct["room"], mitsuba.stderr["direct"]["room"] = fine, np.abs(fine - coarse)
    ref = by_surface(mitsuba, normals)
    comparison = prtlab.compare(ours, ref)
    print(f"\nsunlit_window_room, lower half open ({STRIPS} strips, {SPP} spp, {BOUNCES} bounces)\n"
          f"{comparison.table()}")
    return ours, ref, comparison


# Rows whose Mitsuba reference (65,536 spp, 4 bounces, seed 7) is noisier than goal / 3, so that ``check`` refuses
# them (ValueError): (surface, part) -> (rel_rms, noise), measured (docs/notes/portals.md, "Moving portals").
# Without the noise in quadrature 0.018-0.031 (mean ratios 1.00-1.01), as the fixed half window precomputed on its
# own gives (0.018-0.029): the surface mode's indirect excess (docs/notes/portals.md, section 6), not the strips.
NOISY = {
    ("floor", "indirect"): (0.032, 0.018), ("ceiling", "indirect"): (0.026, 0.016),
    ("ceiling", "total"): (0.026, 0.016), ("wall+x", "indirect"): (0.032, 0.017),
    ("wall+x", "total"): (0.029, 0.016), ("wall-x", "indirect"): (0.036, 0.017),
    ("wall-x", "total"): (0.031, 0.016), ("wall-z", "indirect"): (0.033, 0.016),
    ("wall-z", "total"): (0.033, 0.016), ("wall+z", "indirect"): (0.029, 0.017),
    ("wall+z", "total"): (0.024, 0.016),
}


def _case(surface, part):
    if (surface, part) in NOISY:
        rel_rms, noise = NOISY[surface, part]
        reason = (f"measured rel_rms {rel_rms:.3f} (noise {noise:.4f}): the reference's noise > goal / 3 at {SPP} "
                  "spp, refused by check")
        return pytest.param(surface, part, marks=pytest.mark.xfail(strict=True, raises=ValueError, reason=reason))
    return (surface, part)


CASES = [(s, p) for s in SURFACES for p in ("direct", "indirect", "total") if not (s in UNLIT and p == "direct")]


@pytest.mark.slow
@pytest.mark.skipif(os.environ.get("PRTLAB_QUICK") == "1", reason="slow (Mitsuba, 1.5-4 minutes): make test-slow")
@pytest.mark.parametrize("surface, part", [_case(s, p) for s, p in CASES])
def test_half_open_against_mitsuba(half_open, surface, part):
    """Every surface and part it receives with the lower half of the window open, within ``hypot(SUN_GOAL,
    noise)`` of Mitsuba's render of the shrunk window and a black shutter."""
    _, _, comparison = half_open
    assert comparison.check(SUN_GOAL, parts=(part,), objects=(surface,)) == [], comparison.table()
