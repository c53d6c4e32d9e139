"""The spherical-lights pipeline (Guerrero et al. 2008) against Mitsuba 3 on its paper's Fig. 8 scenes at
reduced size, every object scored (the ground and each object; direct, indirect and total).

Goals (issue 16, binding for objects on a ground under a low-frequency sky, one bounce): direct within 5 %
and indirect within 15 % relative RMS on every object (20 % indirect for the bunny with 16 spheres). The
total has no goal of its own: its bound is derived from the two by the triangle inequality,
``||e_total|| <= 0.05 ||D|| + g_ind ||I||``, i.e. a relative goal ``(0.05 rms(D) + g_ind rms(I)) / rms(D + I)``
with the reference's ``D``, ``I`` of that object. A goal is met when ``rel_rms <= hypot(goal, noise)``
(:meth:`prtlab.metrics.ComparisonRow.meets`); :meth:`prtlab.metrics.Comparison.check` refuses a reference
noisier than a third of the goal, so ``SPP`` is chosen for that and the scenes are made small instead.

Where the method cannot reach a goal the case is a strict xfail (``raises=AssertionError``, so a reference
too noisy to judge errors instead of passing as expected) whose reason gives the measured figure (Mitsuba
``SPP`` samples per vertex, seed 0) and its cause.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

import prtlab
from prtlab.geometry import builtin_mesh
from prtlab.pipeline import FrameState
from prtlab.scene import Transform
from prtlab.spherelights import SphereLights

pytestmark = [pytest.mark.mitsuba, pytest.mark.xdist_group("fidelity-spherelights")]

SPP = 8192
#: cases whose reference needs more samples to stay within a third of the goal (the moved sphere's ground
#: indirect: noise 0.050 at 8192 spp)
SPP_FOR = {"moved sphere": 16384}
GRID = 24  # the sphere fit's voxel grid (the slow tier uses 40)
DIRECT_GOAL = 0.05
INDIRECT_GOAL = {"spheres": 0.15, "tiny ball": 0.15, "moved sphere": 0.15, "cube (8 spheres)": 0.15,
                 "bunny (16 spheres)": 0.20}
MOVED = Transform(translate=np.array([-0.6, 0.5, 0.5]), rotate_deg=np.array([30.0, 0.0, 20.0]))


def _small(sc, plane_cells=12, sphere_subdivisions=2):
    """The scene with a coarser ground grid and coarser icospheres (same sizes, poses and materials)."""
    for o in sc.objects:
        spec = o.mesh_spec if isinstance(o.mesh_spec, dict) else {}
        if spec.get("builtin") == "plane":
            o.mesh_spec = dict(spec, resolution=[plane_cells, plane_cells])
        elif spec.get("builtin") == "icosphere":
            o.mesh_spec = dict(spec, subdivisions=sphere_subdivisions)
        else:
            continue
        o.mesh = builtin_mesh(**{"name": o.mesh_spec["builtin"]},
                              **{k: v for k, v in o.mesh_spec.items() if k != "builtin"})
    return sc


def _spheres():
    return _small(prtlab.load_scene("spheres_on_plane_env"))


def _moved_spheres():
    sc = _spheres()
    sc.object("sphere_red").transform = copy.deepcopy(MOVED)
    return sc


def _bunny():
    return _small(prtlab.load_scene("bunny_spheres_env"))


def _cube():
    sc = _small(prtlab.load_scene("spheres_on_plane_env"))
    box = prtlab.scene.Scene.from_dict({
        "objects": [{"name": "cube", "mesh": {"builtin": "box", "size": [0.9, 0.9, 0.9], "subdivisions": 2},
                     "transform": {"translate": [0, 0.45, 0], "rotate_deg": [0, 30, 0]},
                     "material": {"type": "diffuse", "albedo": [0.8, 0.5, 0.2]}, "dynamic": True}],
        "lights": [{"type": "environment", "constant": [1, 1, 1]}]}).objects[0]
    sc.objects = [o for o in sc.objects if o.name == "plane"] + [box]
    return sc


# name: (scene precomputed, options, scene Mitsuba renders, frame transforms applied before shading)
CASES = {
    "tiny ball": (lambda: prtlab.load_scene("tiny_ball_env"), {"n_spheres": 1}, None, {}),
    "spheres": (_spheres, {"n_spheres": 1}, None, {}),
    "moved sphere": (_spheres, {"n_spheres": 1}, _moved_spheres, {"sphere_red": MOVED}),
    "cube (8 spheres)": (_cube, {"n_spheres": 8}, None, {}),
    "bunny (16 spheres)": (_bunny, {"n_spheres": {"bunny": 16, "sphere_green": 1, "sphere_orange": 1}}, None, {}),
}
OBJECTS = {
    "tiny ball": ("ground", "ball"),
    "spheres": ("plane", "sphere_red", "sphere_white", "sphere_blue"),
    "moved sphere": ("plane", "sphere_red", "sphere_white", "sphere_blue"),
    "cube (8 spheres)": ("plane", "cube"),
    "bunny (16 spheres)": ("plane", "bunny", "sphere_green", "sphere_orange"),
}

_BELOW = ("the environment below the horizon, which the ground hides, still reaches the object's vertices (the "
          "ground blocks it only for the first pass's surface samples; issue 16)")
_NO_GROUND = "the ground reflects nothing onto objects (issue 16): only the other objects' light arrives"
_BOTH = "the direct excess and the missing ground light above, partly cancelling"


def _fig(rel_rms, noise, error, ratio):
    return f"measured rel_rms {rel_rms} (noise {noise}, error {error}), mean ratio {ratio}: "


_XFAIL: dict[tuple[str, str, str], str] = {
    ("tiny ball", "ball", "direct"): _fig(0.193, 0.012, 0.192, 1.13) + _BELOW,
    ("tiny ball", "ball", "indirect"): _fig(1.000, 0.018, 1.000, 0.0) + _NO_GROUND + " (there are none)",
    ("tiny ball", "ball", "total"): _fig(0.095, 0.011, 0.094, 0.97) + _BOTH,
    ("spheres", "sphere_red", "direct"): _fig(0.307, 0.013, 0.307, 1.24) + _BELOW,
    ("spheres", "sphere_red", "indirect"): _fig(0.915, 0.018, 0.915, 0.13) + _NO_GROUND,
    ("spheres", "sphere_red", "total"): _fig(0.144, 0.011, 0.143, 1.04) + _BOTH,
    ("spheres", "sphere_white", "direct"): _fig(0.281, 0.013, 0.280, 1.26) + _BELOW,
    ("spheres", "sphere_white", "indirect"): _fig(0.909, 0.022, 0.909, 0.13) + _NO_GROUND,
    ("spheres", "sphere_white", "total"): _fig(0.178, 0.012, 0.177, 1.03) + _BOTH,
    ("spheres", "sphere_blue", "direct"): _fig(0.124, 0.012, 0.123, 1.15) + _BELOW,
    ("spheres", "sphere_blue", "indirect"): _fig(0.950, 0.022, 0.950, 0.09) + _NO_GROUND,
    ("spheres", "sphere_blue", "total"): _fig(0.164, 0.011, 0.164, 0.92) + _BOTH,
    ("moved sphere", "sphere_red", "direct"): _fig(0.316, 0.012, 0.316, 1.26) + _BELOW,
    ("moved sphere", "sphere_red", "indirect"): _fig(0.905, 0.018, 0.905, 0.15) + _NO_GROUND,
    ("moved sphere", "sphere_red", "total"): _fig(0.150, 0.011, 0.149, 1.04) + _BOTH,
    ("moved sphere", "sphere_white", "direct"): _fig(0.328, 0.013, 0.327, 1.32) + _BELOW,
    ("moved sphere", "sphere_white", "indirect"): _fig(0.904, 0.026, 0.903, 0.12) + _NO_GROUND,
    ("moved sphere", "sphere_white", "total"): _fig(0.189, 0.013, 0.188, 1.08) + _BOTH,
    ("moved sphere", "sphere_blue", "direct"): _fig(0.121, 0.012, 0.121, 1.14) + _BELOW,
    ("moved sphere", "sphere_blue", "indirect"): _fig(0.953, 0.022, 0.953, 0.10) + _NO_GROUND,
    ("moved sphere", "sphere_blue", "total"): _fig(0.162, 0.012, 0.161, 0.92) + _BOTH,
    ("cube (8 spheres)", "plane", "direct"): _fig(0.157, 0.012, 0.156, 0.95)
    + "8 bounding spheres shadow the ground as a cluster of balls, not a box (their outside volume; Fig. 10)",
    ("cube (8 spheres)", "plane", "indirect"): _fig(0.480, 0.049, 0.478, 1.59)
    + "8 intersecting lights with precomputed mutual occlusion over-light the ground (the paper's Fig. 7), and "
    "their outside volume emits from where the box is not",
    ("cube (8 spheres)", "plane", "total"): _fig(0.153, 0.012, 0.153, 0.96) + "the direct and indirect errors above",
    ("cube (8 spheres)", "cube", "direct"): _fig(0.287, 0.012, 0.287, 1.18) + _BELOW,
    ("cube (8 spheres)", "cube", "indirect"): _fig(0.996, 0.023, 0.996, 0.005) + _NO_GROUND + " (there are none)",
    ("cube (8 spheres)", "cube", "total"): _fig(0.181, 0.011, 0.181, 1.03) + _BOTH,
    ("bunny (16 spheres)", "plane", "indirect"): _fig(0.237, 0.041, 0.234, 1.23)
    + "the precomputed occlusion of the bunny's 16 intersecting lights brightens their emission (the paper's "
    "Fig. 7) and their outside volume lights the ground from where the bunny is not",
    ("bunny (16 spheres)", "bunny", "direct"): _fig(0.187, 0.009, 0.187, 1.13) + _BELOW,
    ("bunny (16 spheres)", "bunny", "indirect"): _fig(0.927, 0.016, 0.927, 0.11) + _NO_GROUND,
    ("bunny (16 spheres)", "bunny", "total"): _fig(0.188, 0.008, 0.188, 0.87) + _BOTH,
    ("bunny (16 spheres)", "sphere_green", "direct"): _fig(0.163, 0.008, 0.163, 1.11) + _BELOW,
    ("bunny (16 spheres)", "sphere_green", "indirect"): _fig(0.945, 0.014, 0.944, 0.19) + _NO_GROUND,
    ("bunny (16 spheres)", "sphere_green", "total"): _fig(0.175, 0.006, 0.175, 0.86) + _BOTH,
    ("bunny (16 spheres)", "sphere_orange", "direct"): _fig(0.192, 0.011, 0.191, 1.16) + _BELOW,
    ("bunny (16 spheres)", "sphere_orange", "indirect"): _fig(0.931, 0.014, 0.931, 0.10) + _NO_GROUND,
    ("bunny (16 spheres)", "sphere_orange", "total"): _fig(0.122, 0.009, 0.122, 0.90) + _BOTH,
}


@pytest.fixture(scope="module")
def comparisons():
    pytest.importorskip("mitsuba")
    from prtlab.reference import shade_mitsuba

    out, pres = {}, {}
    for name, (make, opts, make_ref, moves) in CASES.items():
        sc = make()
        key = (make, repr(opts))
        if key not in pres:  # the moved case shades the precomputation of the case at rest
            pres[key] = SphereLights.precompute(sc, dict(opts, fit_resolution=GRID), cache=False, progress=False)
        pre = pres[key]
        state = FrameState.from_scene(sc)
        state.transforms.update({k: copy.deepcopy(v) for k, v in moves.items()})
        ours = pre.shade(state, bounces=1)
        ref = shade_mitsuba((make_ref or make)(), bounces=1, spp=SPP_FOR.get(name, SPP), seed=0)
        out[name] = (prtlab.compare(ours, ref, objects=OBJECTS[name]), ref)
        print(f"\n{name}\n{out[name][0].table()}")
    return out


def _goal(name, obj, part, ref):
    """The goal of ``part`` of ``obj`` (see the module docstring: the total's is derived from the other two)."""
    g_ind = INDIRECT_GOAL[name]
    if part == "direct":
        return DIRECT_GOAL
    if part == "indirect":
        return g_ind

    def rms(x):
        return float(np.sqrt(np.mean(np.asarray(x, dtype=np.float64) ** 2)))

    return (DIRECT_GOAL * rms(ref.direct[obj]) + g_ind * rms(ref.indirect[obj])) / rms(ref.total[obj])


def _params():
    for name, objects in OBJECTS.items():
        for obj in objects:
            for part in ("direct", "indirect", "total"):
                reason = _XFAIL.get((name, obj, part))
                marks = [pytest.mark.xfail(strict=True, raises=AssertionError, reason=reason)] if reason else []
                yield pytest.param(name, obj, part, marks=marks, id=f"{name}-{obj}-{part}")


@pytest.mark.parametrize("name,obj,part", list(_params()))
def test_against_mitsuba(comparisons, name, obj, part):
    cmp, ref = comparisons[name]
    goal = _goal(name, obj, part, ref)
    failures = cmp.check(goal, parts=[part], objects=[obj])  # raises if the reference is too noisy
    assert not failures, failures


def test_the_moved_sphere_was_moved(comparisons):
    """The moved case is another frame: the ground's direct light in Mitsuba at the new pose differs from the
    one at rest by more than three times the two references' combined noise (the red sphere's shadow moved),
    so scoring it is not scoring the pose the precomputation was made at."""
    at_rest, moved = comparisons["spheres"][1], comparisons["moved sphere"][1]
    d = moved.direct["plane"] - at_rest.direct["plane"]
    noise = np.hypot(moved.stderr["direct"]["plane"], at_rest.stderr["direct"]["plane"])
    assert np.sqrt(np.mean(d**2)) > 3 * np.sqrt(np.mean(noise**2))
