"""The portals pipeline (Yue et al. 2009) against Mitsuba 3: rooms lit through a window by the sky (and its sun).

Scenes:

- ``tiny_window_room`` (a 2 m box room, 0.5 m cells, one 1.0 x 0.8 m window on its -z wall, a clear Preetham
  sky) with a dynamic diffuse block inside, under the sky alone (the paper's Fig. 10 setting at reduced size),
  two bounces; goal 5% (see below);
- ``sunlit_window_room`` (issue 17: a closed 4 x 3 x 4 m room, 0.5 m cells, a 1.6 x 1.2 m window, the sky with a
  ~5-degree sun at 35 degrees elevation casting a sharp patch on the floor), 12 bounces (the light past them is
  about 2% of the total, left out of both sides alike); the binding goal 3% per surface (the paper reports 1.5%).

The method runs at its default options (``indirect="auto"``: ``"surface"`` on these diffuse interiors; the
paper's SH transfer is ``indirect="paper"``, measured in ``docs/notes/portals.md``).

Metric: relative RMS per vertex (:func:`prtlab.compare`), direct / indirect / total apart, the reference's noise
removed in quadrature (:meth:`prtlab.metrics.ComparisonRow.meets`); the sunlit room is scored per surface (floor,
ceiling, each wall: the room's vertices split by their normal). References are sampled so their relative noise is
at most a third of the goal (65,536 samples per vertex; :meth:`prtlab.metrics.Comparison.check` refuses a noisier
one). The sunlit room's direct light through its small window is too noisy in Mitsuba at that count on the walls
(2%), so its direct reference is a quadrature instead: the room is an empty box, so every segment from a vertex to a
window point is unoccluded and the direct radiance is ``rho / pi int_window L(d) cos_v cos_w / r^2 dA`` over a
128 x 128 midpoint grid (the sky's own bilinear lookup), its error taken as its difference from a 64 x 64 grid
(measured: 200 x 200 against Mitsuba 0.0048, Mitsuba's noise 0.0047); the indirect and total references are
Mitsuba's. A surface the sky cannot reach directly (the ceiling: below the horizon through the window; the window's
own wall) has a black direct reference: ours must be black there too.

A second sun elevation (:data:`HIGH_ELEVATION`, the patch on the floor close under the window) is shaded from the
same precomputation (the light is per-frame state) and scored on the same rows against its own Mitsuba reference
at :data:`HIGH_BOUNCES` bounces (both sides), which costs about a third of the 12-bounce one.

Motion: the method bakes every object's pose into its transfer, so ``shade(FrameState)`` with the block moved is
refused.
"""

from __future__ import annotations

import numpy as np
import pytest

import prtlab
import prtlab.api
from prtlab.pipeline import FrameState
from prtlab.reference import shade_mitsuba
from prtlab.scene import Scene, ShadeResult

pytestmark = pytest.mark.xdist_group("fidelity-portals")

GOAL = 0.05  # the tiny room: the looser goal (judging 1.5% needs 10^6 samples per vertex)
SUN_GOAL = 0.03  # issue 17, binding (goal 1.5%)
BOUNCES = 2
SUN_BOUNCES = 12
SPP = 65536
POSES = {"first": [0.3, 0.25, 0.2], "moved": [-0.4, 0.25, -0.35]}
OBJECTS = ("room", "block")
PARTS = ("direct", "indirect", "total")
SURFACES = {"floor": (1, 1.0), "ceiling": (1, -1.0), "wall+x": (0, -1.0), "wall-x": (0, 1.0),
            "wall-z": (2, 1.0), "wall+z": (2, -1.0)}  # (axis, sign of the inward normal); the window is on -z
UNLIT = ("ceiling", "wall-z")  # no direct light: the window shows them only the ground (black)
HIGH_ELEVATION = 60  # the second sun elevation of the sunlit room
HIGH_BOUNCES = 4
HIGH_SPP = 4 * SPP  # at 65,536 spp the 60-degree indirect rows' reference noise was 0.015-0.018 (> SUN_GOAL / 3)


def window_room(sun: bool = False, pose: str = "first") -> Scene:
    """``tiny_window_room`` with a dynamic block (a 0.5 m cube) at ``POSES[pose]``; the sky's sun disk if ``sun``."""
    d = prtlab.load_scene("tiny_window_room").to_dict()
    d["objects"].append({"name": "block", "mesh": {"builtin": "box"}, "dynamic": True,
                         "transform": {"translate": POSES[pose], "scale": 0.5},
                         "material": {"type": "diffuse", "albedo": [0.6, 0.5, 0.4]}})
    d["lights"][0]["sky"]["sun"] = sun
    return Scene.from_dict(d)


def window_quadrature(scene: Scene, n: int) -> np.ndarray:
    """Direct radiance of the empty sunlit room's vertices by an ``n x n`` midpoint grid over its (axis-aligned,
    -z wall) window: no occluder, so no visibility term; ``(V, 3)``."""
    room, window, light = scene.object("room"), scene.object("window"), scene.lights[0]
    x, normals = room.world_shading_points(), room.world_normals()
    w = window.world_vertices()
    lo, hi = w.min(0), w.max(0)
    u = (np.arange(n) + 0.5) / n
    gx, gy = np.meshgrid(lo[0] + u * (hi[0] - lo[0]), lo[1] + u * (hi[1] - lo[1]))
    q = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, lo[2])])
    area = (hi[0] - lo[0]) * (hi[1] - lo[1]) / gx.size
    out = np.zeros((len(x), 3))
    for v in range(len(x)):
        d = q - x[v]
        r = np.linalg.norm(d, axis=1)
        d /= r[:, None]
        weight = np.maximum(d @ normals[v], 0.0) * np.abs(d[:, 2]) / r**2 * area
        if np.any(weight > 0):
            out[v] = (light.radiance(d[weight > 0]) * weight[weight > 0, None]).sum(0)
    return out * np.asarray(room.material.albedo) / np.pi


def by_surface(result: ShadeResult, normals) -> ShadeResult:
    """``result``'s room split into its six surfaces by the vertex normals (keys of :data:`SURFACES`)."""
    out = ShadeResult()
    for name, (axis, sign) in SURFACES.items():
        m = normals[:, axis] * sign > 0.9
        for part in PARTS:
            getattr(out, part)[name] = getattr(result, part)["room"][m]
            if part in result.stderr:
                out.stderr.setdefault(part, {})[name] = result.stderr[part]["room"][m]
    return out


@pytest.fixture(scope="module")
def sky_pre():
    return prtlab.api.precompute(window_room(), "portals", progress=False, bounces=BOUNCES)


@pytest.fixture(scope="module")
def sky(sky_pre):
    ours = sky_pre.shade(bounces=BOUNCES)
    ref = shade_mitsuba(sky_pre.scene, bounces=BOUNCES, spp=SPP, seed=1)
    comparison = prtlab.compare(ours, ref, objects=OBJECTS)
    print(f"\ntiny_window_room + block, sky ({SPP} spp)\n{comparison.table()}")
    return comparison


@pytest.fixture(scope="module")
def sunlit_pre():
    """The sunlit room's precomputation (defaults, :data:`SUN_BOUNCES`); the light is per-frame state."""
    return prtlab.api.precompute(prtlab.load_scene("sunlit_window_room"), "portals", progress=False,
                                 bounces=SUN_BOUNCES)


def _sunlit_comparison(pre, scene: Scene, bounces: int, seed: int, label: str, spp: int = SPP):
    """Ours (``pre`` shaded under ``scene``'s sky) and the reference (Mitsuba at ``spp`` samples per vertex; the
    direct light by the window quadrature), split per surface: ``(ours, ref, comparison)``."""
    normals = scene.object("room").world_normals()
    state = FrameState.from_scene(pre.scene)
    state.lights = list(scene.lights)
    ours = by_surface(pre.shade(state, bounces=bounces), normals)
    mitsuba = shade_mitsuba(scene, bounces=bounces, spp=spp, seed=seed)
    fine, coarse = window_quadrature(scene, 128), window_quadrature(scene, 64)
    mitsuba.direct["room"], mitsuba.stderr["direct"]["room"] = fine, np.abs(fine - coarse)
    ref = by_surface(mitsuba, normals)
    comparison = prtlab.compare(ours, ref)
    print(f"\nsunlit_window_room, {label} ({spp} spp, {bounces} bounces)\n{comparison.table()}")
    return ours, ref, comparison


@pytest.fixture(scope="module")
def sunlit(sunlit_pre):
    """The sunlit room (sun at 35 degrees): ours (defaults) and the reference, split per surface."""
    return _sunlit_comparison(sunlit_pre, prtlab.load_scene("sunlit_window_room"), SUN_BOUNCES, 3, "sun 35 deg")


def sunlit_room_at(elevation_deg: float) -> Scene:
    """``sunlit_window_room`` with its sun at ``elevation_deg`` (same azimuth)."""
    d = prtlab.load_scene("sunlit_window_room").to_dict()
    d["lights"][0]["sky"]["sun_elevation_deg"] = float(elevation_deg)
    return Scene.from_dict(d)


@pytest.fixture(scope="module")
def sunlit_high(sunlit_pre):
    """The sunlit room with the sun at :data:`HIGH_ELEVATION` (its patch on the floor close under the window),
    shaded from the same precomputation (the light is per-frame state), :data:`HIGH_BOUNCES` bounces on both sides
    (fewer than :data:`SUN_BOUNCES`: the reference's run time grows with them), the reference at :data:`HIGH_SPP`
    (its indirect light is noisier here than at 35 degrees)."""
    return _sunlit_comparison(sunlit_pre, sunlit_room_at(HIGH_ELEVATION), HIGH_BOUNCES, 5,
                              f"sun {HIGH_ELEVATION} deg", spp=HIGH_SPP)


# Measured (this module, the seeds above, the defaults): relative RMS per vertex, the reference's relative noise,
# mean ratio. The tiny room's direct light: room 0.011, block 0.008; the room's indirect 0.030 and total 0.015
# (within the goal since the near reads, docs/notes/portals.md section 10: they were 0.059 and 0.030).
MEASURED = {
    ("sky", "block", "indirect"): (0.165, 0.013, 0.92), ("sky", "block", "total"): (0.056, 0.008, 0.97),
}
CAUSE = ("per-vertex light interpolated linearly over 0.5 m cells: a floor vertex inside the block's footprint is "
         "dark and darkens the floor round the block, which the block (24 vertices, all on its corners) gathers "
         "from; the block's sides meet the floor between its vertices, so the near reads do not apply there "
         "(docs/notes/portals.md, sections 4 and 10)")


def _case(case, obj, part):
    if (case, obj, part) not in MEASURED:
        return (case, obj, part)
    rel_rms, noise, ratio = MEASURED[case, obj, part]
    reason = f"measured rel_rms {rel_rms:.3f} (noise {noise:.3f}, mean ratio {ratio:.2f}) > goal {GOAL}: {CAUSE}"
    return pytest.param(case, obj, part, marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason=reason))


@pytest.mark.parametrize("case, obj, part", [_case("sky", o, p) for o in OBJECTS for p in PARTS])
def test_against_mitsuba(request, case, obj, part):
    """``rel_rms <= hypot(GOAL, noise)`` for one object and part; ``check`` refuses a reference noisier than
    ``GOAL / 3``."""
    comparison = request.getfixturevalue(case)
    assert comparison.check(GOAL, parts=(part,), objects=(obj,)) == [], comparison.table()


SUN_CASES = [(s, p) for s in SURFACES for p in PARTS if not (s in UNLIT and p == "direct")] + [("all", "total")]


@pytest.mark.parametrize("surface, part", SUN_CASES)
def test_sunlit_room_against_mitsuba(sunlit, surface, part):
    """Every surface of the sunlit room, each part it receives, within ``hypot(SUN_GOAL, noise)``; and the whole
    room's total."""
    _check_sunlit_row(sunlit, surface, part)


def _check_sunlit_row(sunlit, surface, part):
    ours, ref, comparison = sunlit
    if surface == "all":
        ours_all, ref_all = ShadeResult(), ShadeResult()
        ours_all.total["room"] = np.concatenate(list(ours.total.values()))
        ref_all.total["room"] = np.concatenate(list(ref.total.values()))
        ref_all.stderr["total"] = {"room": np.concatenate(list(ref.stderr["total"].values()))}
        whole = prtlab.compare(ours_all, ref_all, parts=("total",))
        assert whole.check(SUN_GOAL) == [], whole.table()
        return
    assert comparison.check(SUN_GOAL, parts=(part,), objects=(surface,)) == [], comparison.table()


# Measured at HIGH_ELEVATION (this module, seed 5, the defaults, 4 bounces, HIGH_SPP): every row within the goal;
# the whole room's total 0.008, the window wall's indirect light 0.027 (the worst row; it was 0.050 before the near
# reads and 4096 gather rays, docs/notes/portals.md section 10). A row that misses goes to MISSED_HIGH with its
# figures (AssertionError); one whose reference is noisier than goal / 3 to NOISY_HIGH (ValueError from check).
MISSED_HIGH: dict = {}
MISSED_HIGH_CAUSE = "see docs/notes/portals.md"
NOISY_HIGH: dict = {}


def _high_case(surface, part):
    for table, raises in ((MISSED_HIGH, AssertionError), (NOISY_HIGH, ValueError)):
        if (surface, part) in table:
            rel_rms, noise, ratio = table[surface, part]
            figure = f"measured rel_rms {rel_rms:.3f} (noise {noise:.4f}" + (
                f", mean ratio {ratio:.2f})" if ratio is not None else ")")
            reason = (f"{figure} > goal {SUN_GOAL}: {MISSED_HIGH_CAUSE}" if raises is AssertionError else
                      f"{figure}: the reference's noise > goal / 3 at {SPP} spp, refused by check")
            return pytest.param(surface, part, marks=pytest.mark.xfail(strict=True, raises=raises, reason=reason))
    return (surface, part)


@pytest.mark.parametrize("surface, part", [_high_case(s, p) for s, p in SUN_CASES])
def test_sunlit_room_second_elevation_against_mitsuba(sunlit_high, surface, part):
    """The sun at :data:`HIGH_ELEVATION`: every surface and part it receives, and the whole room's total, within
    ``hypot(SUN_GOAL, noise)`` (the same rows as at 35 degrees)."""
    _check_sunlit_row(sunlit_high, surface, part)


def test_sunlit_room_unlit_surfaces_black(sunlit):
    """Where the reference's direct light is black (the ceiling and the window's wall), ours is black too."""
    ours, ref, _ = sunlit
    for surface in UNLIT:
        assert np.all(ref.direct[surface] == 0)
        assert np.all(ours.direct[surface] == 0), surface


def test_every_object_scored(sky, sunlit):
    """Every shaded object of the tiny room and every surface of the sunlit room is scored on each part."""
    assert sorted(sky.objects) == sorted(OBJECTS)
    assert {(r.object, r.part) for r in sky.rows} == {(o, p) for o in OBJECTS for p in PARTS}
    assert sorted(sunlit[2].objects) == sorted(SURFACES)


def test_moved_block_refused(sky_pre):
    """Shading a frame in which the block moved is refused (the transfer bakes its pose), naming the object."""
    state = FrameState.from_scene(sky_pre.scene)
    state.transforms["block"] = window_room(pose="moved").object("block").transform
    with pytest.raises(ValueError, match="object 'block' moved; .*re-precompute at the new pose"):
        sky_pre.shade(state, bounces=BOUNCES)
