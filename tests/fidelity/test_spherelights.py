"""The spherical-lights pipeline (Guerrero et al. 2008) against Mitsuba 3 on its paper's Fig. 8 scenes at
reduced size, plus three touching spheres (``three_spheres_env``), the tiny ball with two bounces (through the
ground, ``bounces=2``) and a box resting on the ground (its indirect light read from the ground's texture at the
foot of its walls; ``docs/notes/spherelights.md``, "A box on the ground"), every object scored (the ground and each
object; direct, indirect and total), with the default options (the ground hides and reflects, ``ground="reflects"``;
each receiver's two largest one-sphere neighbours block exactly, ``near_blockers=2``; the ground shaded against the
objects' meshes, ``ground_shading="rays"``; the objects' direct light against the meshes, ``mesh_blockers=True``; the lights'
emission toward other objects weighted by their segments' projected coverage, ``emission_coverage=True``), and
the paper's direct light
(``near_blockers=0``) on the scenes of one-sphere objects, and the paper's method (``PAPER_OPTIONS``, every
extension off) on every case.

Goals (issue 16, binding for objects on a ground under a low-frequency sky, one bounce): direct within 5 %
and indirect within 15 % relative RMS on every object (20 % indirect for the bunny with 16 spheres). The
total has no goal of its own: its bound is derived from the two by the triangle inequality,
``||e_total|| <= 0.05 ||D|| + g_ind ||I||``, i.e. a relative goal ``(0.05 rms(D) + g_ind rms(I)) / rms(D + I)``
with the reference's ``D``, ``I`` of that object. A goal is met when ``rel_rms <= hypot(goal, noise)``
(:meth:`prtlab.metrics.ComparisonRow.meets`); :meth:`prtlab.metrics.Comparison.check` refuses a reference
noisier than a third of the goal, so ``SPP`` is chosen for that and the scenes are made small instead.

Where the method cannot reach a goal the case is a strict xfail (``raises=AssertionError``, so a reference
too noisy to judge errors instead of passing as expected) whose reason gives the measured figure (Mitsuba
``SPP`` samples per vertex, seed 0) and its cause; causes quoting ``order=6`` were measured with that option
against the same references.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

import prtlab
from prtlab.geometry import builtin_mesh
from prtlab.pipeline import FrameState
from prtlab.scene import Transform
from prtlab.spherelights import PAPER_OPTIONS, SphereLights

pytestmark = [pytest.mark.mitsuba, pytest.mark.xdist_group("fidelity-spherelights")]

SPP = 8192
#: cases whose reference needs more samples to stay within a third of the goal (the moved sphere's ground
#: indirect: noise 0.050 at 8192 spp)
SPP_FOR = {"moved sphere": 16384}
GRID = 24  # the sphere fit's voxel grid (the slow tier uses 40)
DIRECT_GOAL = 0.05
INDIRECT_GOAL = {"tiny ball, 2 bounces": 0.15, "spheres": 0.15, "three touching spheres": 0.15, "tiny ball": 0.15, "moved sphere": 0.15, "cube (8 spheres)": 0.15,
                 "box on the ground": 0.15, "bunny (16 spheres)": 0.20}
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


def _three():
    return _small(prtlab.load_scene("three_spheres_env"))


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


def _box_on_ground():
    """A box of 486 vertices resting on the ground, its faces along the axes (no plane vertex on its walls): its
    indirect light is the ground's, read at the foot of its walls beside the footprint."""
    sc = _small(prtlab.load_scene("spheres_on_plane_env"))
    box = prtlab.scene.Scene.from_dict({
        "objects": [{"name": "box", "mesh": {"builtin": "box", "size": [0.6, 0.6, 0.6], "subdivisions": 3},
                     "transform": {"translate": [0.35, 0.3, 0.05]},
                     "material": {"type": "diffuse", "albedo": [0.8, 0.5, 0.2]}, "dynamic": True}],
        "lights": [{"type": "environment", "constant": [1, 1, 1]}]}).objects[0]
    sc.objects = [o for o in sc.objects if o.name == "plane"] + [box]
    return sc


# name: (scene precomputed, options, scene Mitsuba renders, frame transforms applied before shading)
CASES = {
    "tiny ball": (lambda: prtlab.load_scene("tiny_ball_env"), {"n_spheres": 1}, None, {}),
    "tiny ball, 2 bounces": (lambda: prtlab.load_scene("tiny_ball_env"), {"n_spheres": 1}, None, {}),
    "spheres": (_spheres, {"n_spheres": 1}, None, {}),
    "three touching spheres": (_three, {"n_spheres": 1}, None, {}),
    "moved sphere": (_spheres, {"n_spheres": 1}, _moved_spheres, {"sphere_red": MOVED}),
    "cube (8 spheres)": (_cube, {"n_spheres": 8}, None, {}),
    "box on the ground": (_box_on_ground, {"n_spheres": 8}, None, {}),
    "bunny (16 spheres)": (_bunny, {"n_spheres": {"bunny": 16, "sphere_green": 1, "sphere_orange": 1}}, None, {}),
}
#: cases shaded (and rendered by Mitsuba) with two bounces: ball -> ground -> ball and ground -> ball -> ground
BOUNCES = {"tiny ball, 2 bounces": 2}
OBJECTS = {
    "tiny ball": ("ground", "ball"),
    "tiny ball, 2 bounces": ("ground", "ball"),
    "spheres": ("plane", "sphere_red", "sphere_white", "sphere_blue"),
    "three touching spheres": ("plane", "sphere_left", "sphere_middle", "sphere_right"),
    "moved sphere": ("plane", "sphere_red", "sphere_white", "sphere_blue"),
    "cube (8 spheres)": ("plane", "cube"),
    "box on the ground": ("plane", "box"),
    "bunny (16 spheres)": ("plane", "bunny", "sphere_green", "sphere_orange"),
}

_ORDER = "the order-4 SH shadows of the neighbouring spheres (Ren et al. 2006, the paper's visibility); with order=6: "
_NOT_ORDER = "not the SH order (with order=6: {}); cause not isolated"
_BOTH = "the direct and indirect errors above"


def _fig(rel_rms, noise, error, ratio):
    return f"measured rel_rms {rel_rms} (noise {noise}, error {error}), mean ratio {ratio}: "


_XFAIL: dict[tuple[str, str, str], str] = {}


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
        ours = pre.shade(state, bounces=BOUNCES.get(name, 1))
        ref = shade_mitsuba((make_ref or make)(), bounces=BOUNCES.get(name, 1), spp=SPP_FOR.get(name, SPP), seed=0)
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


#: the paper's direct light (``near_blockers=0``: every blocker in the exponentiated SH visibility) scored against
#: the same references on the scenes of one-sphere objects (the default, ``near_blockers=2``, takes each receiver's
#: two largest one-sphere neighbours exactly, ``_nearcaps``)
PAPER_DIRECT = {"near_blockers": 0, "mesh_blockers": False}
PAPER_DIRECT_CASES = ("tiny ball", "spheres", "three touching spheres", "moved sphere")
_PAPER_DIRECT_XFAIL: dict[tuple[str, str, str], str] = {
    ("spheres", "sphere_red", "direct"): _fig(0.060, 0.013, 0.059, 0.97) + _ORDER + "0.052",
    ("spheres", "sphere_white", "direct"): _fig(0.089, 0.013, 0.088, 1.04) + _ORDER + "0.059 (the side facing the "
    "blue sphere is 1.31 times too bright; exact exponentiation: 0.087)",
    ("three touching spheres", "sphere_left", "direct"): _fig(0.089, 0.013, 0.088, 1.01) + _ORDER + "0.077",
    ("three touching spheres", "sphere_left", "total"): _fig(0.079, 0.011, 0.078, 1.00) + _BOTH,
    ("three touching spheres", "sphere_middle", "direct"): _fig(0.079, 0.012, 0.078, 1.04) + _ORDER + "0.068",
    ("moved sphere", "sphere_white", "direct"): _fig(0.112, 0.009, 0.111, 1.07) + _ORDER + "0.075",
    ("moved sphere", "sphere_white", "total"): _fig(0.100, 0.009, 0.100, 1.05) + _BOTH,
}


def _with_options(comparisons, names, options, label):
    """``{name: (comparison, reference)}`` of the cases ``names`` precomputed and shaded with ``options`` added,
    scored against the references of ``comparisons``."""
    out = {}
    for name in names:
        make, opts, _, moves = CASES[name]
        sc = make()
        pre = SphereLights.precompute(sc, dict(opts, fit_resolution=GRID, **options), cache=False, progress=False)
        state = FrameState.from_scene(sc)
        state.transforms.update({k: copy.deepcopy(v) for k, v in moves.items()})
        ref = comparisons[name][1]
        out[name] = (prtlab.compare(pre.shade(state, bounces=BOUNCES.get(name, 1)), ref, objects=OBJECTS[name]), ref)
        print(f"\n{name}, {label}\n{out[name][0].table()}")
    return out


@pytest.fixture(scope="module")
def paper_direct_comparisons(comparisons):
    return _with_options(comparisons, PAPER_DIRECT_CASES, PAPER_DIRECT, "near_blockers=0")


# On the bound: met in one run (0.0780) and missed in another (0.0782) against hypot(goal, noise) = 0.0775, with the
# same seed (Mitsuba's LLVM variant sums in a thread-dependent order): not strict, so neither outcome fails the tier.
_PAPER_DIRECT_BORDERLINE = {
    ("spheres", "sphere_white", "total"): "measured rel_rms 0.078-0.0782 against 0.0775 (noise 0.012, mean ratio "
    "1.03), on the bound: " + _BOTH,
}


def _variant_params(names, xfail, borderline, prefix):
    """The rows of ``names``' objects and parts, marked by ``xfail`` (strict) and ``borderline`` (not strict)."""
    for name in names:
        for obj in OBJECTS[name]:
            for part in ("direct", "indirect", "total"):
                marks = []
                if (name, obj, part) in xfail:
                    marks = [pytest.mark.xfail(strict=True, raises=AssertionError, reason=xfail[name, obj, part])]
                elif (name, obj, part) in borderline:
                    marks = [pytest.mark.xfail(strict=False, raises=AssertionError,
                                               reason=borderline[name, obj, part])]
                yield pytest.param(name, obj, part, marks=marks, id=f"{prefix}-{name}-{obj}-{part}")


@pytest.mark.parametrize("name,obj,part", list(_variant_params(PAPER_DIRECT_CASES, _PAPER_DIRECT_XFAIL,
                                                               _PAPER_DIRECT_BORDERLINE, "paper_direct")))
def test_papers_direct_light_against_mitsuba(paper_direct_comparisons, name, obj, part):
    cmp, ref = paper_direct_comparisons[name]
    failures = cmp.check(_goal(name, obj, part, ref), parts=[part], objects=[obj])
    assert not failures, failures


@pytest.mark.parametrize("name,obj,part", list(_params()))
def test_against_mitsuba(comparisons, name, obj, part):
    cmp, ref = comparisons[name]
    goal = _goal(name, obj, part, ref)
    failures = cmp.check(goal, parts=[part], objects=[obj])  # raises if the reference is too noisy
    assert not failures, failures


#: The paper's method (``PAPER_OPTIONS``: the ground neither hides nor reflects, every blocker in the SH visibility,
#: the spheres' direct light, the lights' emission at order 4 over their whole spheres, the paper's average radiance)
#: on every case, against the same references and goals: what the defaults' extensions buy. Its misses are strict
#: xfails with the measured figures.
_PAPER_DIRECT_CAUSE = ("too bright (mean ratio above 1): the paper's ground does not hide the sky below the "
                       "objects' horizon (Sec. 8: it only receives; the defaults' ground='reflects' hides it), with "
                       "the spheres' order-4 SH shadows in place of the meshes' (mesh_blockers); not isolated per "
                       "option")
_PAPER_INDIRECT_CAUSE = ("the paper's ground reflects nothing onto the objects: what is left (mean ratio 0-0.21) is "
                         "the other objects' light")
_PAPER_GROUND_INDIRECT_CAUSE = ("the objects, lit from below by the sky the paper's ground does not hide, send the "
                                "ground too much light (mean ratio above 1; with two bounces the paper has no "
                                "ground -> object -> ground light either), with the paper's average radiance and "
                                "emission; not isolated per option")
_PAPER_GROUND_DIRECT_CAUSE = ("the ground shaded through the spherical lights' order-4 SH shadows (the paper's), not "
                              "against the objects' meshes (ground_shading='rays'; for the cube and the box, an "
                              "8-sphere set's shadow is not the mesh's)")
_PAPER_XFAIL: dict[tuple[str, str, str], str] = {
    ("tiny ball", "ground", "indirect"): _fig(0.667, 0.047, 0.666, 1.25) + _PAPER_GROUND_INDIRECT_CAUSE,
    ("tiny ball", "ground", "total"): _fig(0.062, 0.013, 0.061, 1.02) + _BOTH,
    ("tiny ball", "ball", "direct"): _fig(0.193, 0.011, 0.192, 1.13) + _PAPER_DIRECT_CAUSE,
    ("tiny ball", "ball", "indirect"): _fig(1.000, 0.018, 1.000, 0.00) + _PAPER_INDIRECT_CAUSE,
    ("tiny ball", "ball", "total"): _fig(0.095, 0.011, 0.095, 0.97) + _BOTH,
    ("tiny ball, 2 bounces", "ground", "indirect"): _fig(0.401, 0.037, 0.399, 0.94) + _PAPER_GROUND_INDIRECT_CAUSE,
    ("tiny ball, 2 bounces", "ball", "direct"): _fig(0.193, 0.011, 0.192, 1.13) + _PAPER_DIRECT_CAUSE,
    ("tiny ball, 2 bounces", "ball", "indirect"): _fig(1.000, 0.017, 1.000, 0.00) + _PAPER_INDIRECT_CAUSE,
    ("tiny ball, 2 bounces", "ball", "total"): _fig(0.083, 0.011, 0.083, 0.95) + _BOTH,
    ("spheres", "plane", "indirect"): _fig(0.822, 0.048, 0.820, 1.41) + _PAPER_GROUND_INDIRECT_CAUSE,
    ("spheres", "plane", "total"): _fig(0.063, 0.013, 0.062, 1.01) + _BOTH,
    ("spheres", "sphere_red", "direct"): _fig(0.307, 0.013, 0.307, 1.24) + _PAPER_DIRECT_CAUSE,
    ("spheres", "sphere_red", "indirect"): _fig(0.903, 0.018, 0.903, 0.15) + _PAPER_INDIRECT_CAUSE,
    ("spheres", "sphere_red", "total"): _fig(0.147, 0.011, 0.147, 1.04) + _BOTH,
    ("spheres", "sphere_white", "direct"): _fig(0.281, 0.013, 0.280, 1.26) + _PAPER_DIRECT_CAUSE,
    ("spheres", "sphere_white", "indirect"): _fig(0.894, 0.022, 0.893, 0.16) + _PAPER_INDIRECT_CAUSE,
    ("spheres", "sphere_white", "total"): _fig(0.178, 0.012, 0.178, 1.03) + _BOTH,
    ("spheres", "sphere_blue", "direct"): _fig(0.123, 0.012, 0.123, 1.15) + _PAPER_DIRECT_CAUSE,
    ("spheres", "sphere_blue", "indirect"): _fig(0.944, 0.022, 0.944, 0.11) + _PAPER_INDIRECT_CAUSE,
    ("spheres", "sphere_blue", "total"): _fig(0.163, 0.011, 0.162, 0.92) + _BOTH,
    ("three touching spheres", "plane", "direct"): _fig(0.054, 0.013, 0.053, 1.00) + _PAPER_GROUND_DIRECT_CAUSE,
    ("three touching spheres", "plane", "indirect"): _fig(0.839, 0.047, 0.838, 1.41) + _PAPER_GROUND_INDIRECT_CAUSE,
    ("three touching spheres", "plane", "total"): _fig(0.071, 0.013, 0.070, 1.01) + _BOTH,
    ("three touching spheres", "sphere_left", "direct"): _fig(0.340, 0.013, 0.339, 1.28) + _PAPER_DIRECT_CAUSE,
    ("three touching spheres", "sphere_left", "indirect"): _fig(0.933, 0.019, 0.933, 0.16) + _PAPER_INDIRECT_CAUSE,
    ("three touching spheres", "sphere_left", "total"): _fig(0.196, 0.011, 0.196, 1.06) + _BOTH,
    ("three touching spheres", "sphere_middle", "direct"): _fig(0.263, 0.012, 0.263, 1.26) + _PAPER_DIRECT_CAUSE,
    ("three touching spheres", "sphere_middle", "indirect"): _fig(0.920, 0.021, 0.919, 0.18) + _PAPER_INDIRECT_CAUSE,
    ("three touching spheres", "sphere_middle", "total"): _fig(0.178, 0.011, 0.178, 1.05) + _BOTH,
    ("three touching spheres", "sphere_right", "direct"): _fig(0.142, 0.012, 0.142, 1.17) + _PAPER_DIRECT_CAUSE,
    ("three touching spheres", "sphere_right", "indirect"): _fig(0.962, 0.022, 0.962, 0.12) + _PAPER_INDIRECT_CAUSE,
    ("three touching spheres", "sphere_right", "total"): _fig(0.152, 0.011, 0.152, 0.96) + _BOTH,
    ("moved sphere", "plane", "indirect"): _fig(0.966, 0.035, 0.966, 1.50) + _PAPER_GROUND_INDIRECT_CAUSE,
    ("moved sphere", "plane", "total"): _fig(0.064, 0.009, 0.063, 1.01) + _BOTH,
    ("moved sphere", "sphere_red", "direct"): _fig(0.314, 0.009, 0.314, 1.26) + _PAPER_DIRECT_CAUSE,
    ("moved sphere", "sphere_red", "indirect"): _fig(0.899, 0.013, 0.899, 0.18) + _PAPER_INDIRECT_CAUSE,
    ("moved sphere", "sphere_red", "total"): _fig(0.154, 0.008, 0.154, 1.05) + _BOTH,
    ("moved sphere", "sphere_white", "direct"): _fig(0.329, 0.009, 0.329, 1.32) + _PAPER_DIRECT_CAUSE,
    ("moved sphere", "sphere_white", "indirect"): _fig(0.886, 0.018, 0.886, 0.15) + _PAPER_INDIRECT_CAUSE,
    ("moved sphere", "sphere_white", "total"): _fig(0.192, 0.009, 0.192, 1.08) + _BOTH,
    ("moved sphere", "sphere_blue", "direct"): _fig(0.119, 0.009, 0.119, 1.14) + _PAPER_DIRECT_CAUSE,
    ("moved sphere", "sphere_blue", "indirect"): _fig(0.947, 0.016, 0.947, 0.12) + _PAPER_INDIRECT_CAUSE,
    ("moved sphere", "sphere_blue", "total"): _fig(0.163, 0.008, 0.163, 0.92) + _BOTH,
    ('cube (8 spheres)', 'plane', 'direct'): _fig(0.157, 0.012, 0.156, 0.95) + _PAPER_GROUND_DIRECT_CAUSE,
    ('cube (8 spheres)', 'plane', 'indirect'): _fig(0.740, 0.049, 0.738, 1.84) + _PAPER_GROUND_INDIRECT_CAUSE,
    ('cube (8 spheres)', 'plane', 'total'): _fig(0.154, 0.012, 0.154, 0.96) + _BOTH,
    ('cube (8 spheres)', 'cube', 'direct'): _fig(0.287, 0.012, 0.286, 1.18) + _PAPER_DIRECT_CAUSE,
    ('cube (8 spheres)', 'cube', 'indirect'): _fig(0.996, 0.022, 0.995, 0.01) + _PAPER_INDIRECT_CAUSE,
    ('cube (8 spheres)', 'cube', 'total'): _fig(0.181, 0.011, 0.181, 1.03) + _BOTH,
    ("box on the ground", "plane", "direct"): _fig(0.080, 0.012, 0.079, 0.96) + _PAPER_GROUND_DIRECT_CAUSE,
    ("box on the ground", "plane", "indirect"): _fig(0.782, 0.045, 0.781, 1.93) + _PAPER_GROUND_INDIRECT_CAUSE,
    ("box on the ground", "plane", "total"): _fig(0.079, 0.012, 0.079, 0.97) + _BOTH,
    ("box on the ground", "box", "direct"): _fig(0.311, 0.013, 0.311, 1.22) + _PAPER_DIRECT_CAUSE,
    ("box on the ground", "box", "indirect"): _fig(0.995, 0.021, 0.995, 0.01) + _PAPER_INDIRECT_CAUSE,
    ("box on the ground", "box", "total"): _fig(0.172, 0.011, 0.172, 1.05) + _BOTH,
    ('bunny (16 spheres)', 'plane', 'indirect'): _fig(0.458, 0.041, 0.456, 1.43) + _PAPER_GROUND_INDIRECT_CAUSE,
    ('bunny (16 spheres)', 'bunny', 'direct'): _fig(0.187, 0.009, 0.187, 1.13) + _PAPER_DIRECT_CAUSE,
    ('bunny (16 spheres)', 'bunny', 'indirect'): _fig(0.921, 0.016, 0.921, 0.11) + _PAPER_INDIRECT_CAUSE,
    ('bunny (16 spheres)', 'bunny', 'total'): _fig(0.188, 0.008, 0.187, 0.87) + _BOTH,
    ('bunny (16 spheres)', 'sphere_green', 'direct'): _fig(0.163, 0.008, 0.163, 1.11) + _PAPER_DIRECT_CAUSE,
    ('bunny (16 spheres)', 'sphere_green', 'indirect'): _fig(0.933, 0.014, 0.933, 0.21) + _PAPER_INDIRECT_CAUSE,
    ('bunny (16 spheres)', 'sphere_green', 'total'): _fig(0.171, 0.006, 0.170, 0.86) + _BOTH,
    ('bunny (16 spheres)', 'sphere_orange', 'direct'): _fig(0.192, 0.011, 0.191, 1.16) + _PAPER_DIRECT_CAUSE,
    ('bunny (16 spheres)', 'sphere_orange', 'indirect'): _fig(0.922, 0.014, 0.922, 0.12) + _PAPER_INDIRECT_CAUSE,
    ('bunny (16 spheres)', 'sphere_orange', 'total'): _fig(0.120, 0.009, 0.120, 0.91) + _BOTH,
}
#: rows within 3 % of their bound (``hypot(goal, noise)``) in the measurement: xfail, not strict (Mitsuba's LLVM
#: variant sums in a thread-dependent order)
_PAPER_BORDERLINE: dict[tuple[str, str, str], str] = {
    ("spheres", "plane", "direct"): ("met at rel_rms 0.0513 against 0.0516 (noise 0.0127), on the bound: "
                                     + _PAPER_GROUND_DIRECT_CAUSE),
    ("moved sphere", "plane", "direct"): ("met at rel_rms 0.0502 against 0.0508 (noise 0.0090), on the bound: "
                                          + _PAPER_GROUND_DIRECT_CAUSE),
}


@pytest.fixture(scope="module")
def paper_comparisons(comparisons):
    return _with_options(comparisons, CASES, PAPER_OPTIONS, "the paper's method (PAPER_OPTIONS)")


@pytest.mark.parametrize("name,obj,part", list(_variant_params(OBJECTS, _PAPER_XFAIL, _PAPER_BORDERLINE, "paper")))
def test_papers_method_against_mitsuba(paper_comparisons, name, obj, part):
    cmp, ref = paper_comparisons[name]
    failures = cmp.check(_goal(name, obj, part, ref), parts=[part], objects=[obj])
    assert not failures, failures


def test_the_moved_sphere_was_moved(comparisons):
    """The moved case is another frame: the ground's direct light in Mitsuba at the new pose differs from the
    one at rest by more than three times the two references' combined noise (the red sphere's shadow moved),
    so scoring it is not scoring the pose the precomputation was made at."""
    at_rest, moved = comparisons["spheres"][1], comparisons["moved sphere"][1]
    d = moved.direct["plane"] - at_rest.direct["plane"]
    noise = np.hypot(moved.stderr["direct"]["plane"], at_rest.stderr["direct"]["plane"])
    assert np.sqrt(np.mean(d**2)) > 3 * np.sqrt(np.mean(noise**2))
