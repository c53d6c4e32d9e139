"""Whole scenes against Mitsuba 3 at full size (Guerrero et al. 2008, Fig. 8 and Fig. 10), every object scored
(the ground and each object; direct, indirect and total) with :func:`prtlab.compare`. Slow: run with ``-m slow``
(the fidelity tier, ``tests/fidelity/test_spherelights.py``, runs the same cases at reduced size in CI).

Goals (issue 16): direct within 5 % and indirect within 15 % relative RMS on every object (20 % indirect for the
bunny with 16 spheres); the total's goal is derived from the two by the triangle inequality,
``(0.05 rms(D) + g_ind rms(I)) / rms(D + I)`` with the reference's ``D``, ``I`` of the object. A goal is met when
``rel_rms <= hypot(goal, noise)``; :meth:`prtlab.metrics.Comparison.check` refuses a reference noisier than a
third of the goal (hence ``SPP``, and ``SPP_ONE_SPHERE`` for the scene whose plane's indirect noise was 0.057 at
8192 samples: ``(0.057 / 0.05)^2 x 8192 = 10,650`` needed). Where a goal is not met the test is
``xfail(strict=True, raises=AssertionError)`` with the measured figure (Mitsuba ``SPP`` samples per vertex, seed 0;
the default pipeline options) and its cause.
"""

import numpy as np
import pytest

import prtlab
from prtlab.scene import Scene
from prtlab.spherelights import SphereLights

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]

SPP = 8192
SPP_ONE_SPHERE = 16384
DIRECT_GOAL = 0.05


def _one_sphere():
    sc = prtlab.load_scene("spheres_on_plane_env")
    sc.objects = [o for o in sc.objects if o.name in ("plane", "sphere_white")]
    return sc


def _cube():
    sc = prtlab.load_scene("spheres_on_plane_env")
    box = Scene.from_dict({"objects": [{"name": "cube", "mesh": {"builtin": "box", "size": [0.9, 0.9, 0.9],
                                                                 "subdivisions": 3},
                                        "transform": {"translate": [0, 0.45, 0], "rotate_deg": [0, 30, 0]},
                                        "material": {"type": "diffuse", "albedo": [0.8, 0.5, 0.2]}}],
                           "lights": [{"type": "environment", "constant": [1, 1, 1]}]}).objects[0]
    sc.objects = [o for o in sc.objects if o.name == "plane"] + [box]
    return sc


CASES = {
    "one sphere": (_one_sphere, {"n_spheres": 1}),
    "several spheres": (lambda: prtlab.load_scene("spheres_on_plane_env"), {"n_spheres": 1}),
    "bunny (16 spheres)": (lambda: prtlab.load_scene("bunny_spheres_env"),
                           {"n_spheres": {"bunny": 16, "sphere_green": 1, "sphere_orange": 1}}),
    "cube (1 sphere)": (_cube, {"n_spheres": 1}),
    "cube (8 spheres)": (_cube, {"n_spheres": 8}),
}
OBJECTS = {
    "one sphere": ("plane", "sphere_white"),
    "several spheres": ("plane", "sphere_red", "sphere_white", "sphere_blue"),
    "bunny (16 spheres)": ("plane", "bunny", "sphere_green", "sphere_orange"),
    "cube (1 sphere)": ("plane", "cube"),
    "cube (8 spheres)": ("plane", "cube"),
}
INDIRECT_GOAL = {name: 0.20 if name.startswith("bunny") else 0.15 for name in CASES}

_XFAIL: dict[tuple[str, str, str], str] = {}


def _goal(name, obj, part, ref):
    """The goal of ``part`` of ``obj`` (the total's derived from the other two, see the module docstring)."""
    if part == "direct":
        return DIRECT_GOAL
    if part == "indirect":
        return INDIRECT_GOAL[name]

    def rms(x):
        return float(np.sqrt(np.mean(np.asarray(x, dtype=np.float64) ** 2)))

    return (DIRECT_GOAL * rms(ref.direct[obj]) + INDIRECT_GOAL[name] * rms(ref.indirect[obj])) / rms(ref.total[obj])


@pytest.fixture(scope="module")
def shaded():
    """``shaded(name)``: case ``name``'s comparison at the default options and its Mitsuba reference, each
    rendered and shaded once, when a test first asks for it (so ``-k`` renders only what it selects)."""
    pytest.importorskip("mitsuba")
    from prtlab.reference import shade_mitsuba

    out, refs = {}, {}

    def get(name):
        if name not in out:
            make, opts = CASES[name]
            sc = make()
            if make not in refs:  # the two cube cases share their scene
                spp = SPP_ONE_SPHERE if name == "one sphere" else SPP
                refs[make] = shade_mitsuba(sc, bounces=1, spp=spp, seed=0, progress=False)
            ref = refs[make]
            ours = SphereLights.precompute(sc, dict(opts, fit_resolution=40), cache=True, progress=False).shade(bounces=1)
            out[name] = (prtlab.compare(ours, ref, objects=OBJECTS[name]), ref)
            print(f"\n{name}\n{out[name][0].table()}")
        return out[name]

    return get


def _params():
    for name, objects in OBJECTS.items():
        for obj in objects:
            for part in ("direct", "indirect", "total"):
                reason = _XFAIL.get((name, obj, part))
                marks = [pytest.mark.xfail(strict=True, raises=AssertionError, reason=reason)] if reason else []
                yield pytest.param(name, obj, part, marks=marks, id=f"{name}-{obj}-{part}")


@pytest.mark.parametrize("name,obj,part", list(_params()))
def test_fig8_against_mitsuba(shaded, name, obj, part):
    cmp, ref = shaded(name)
    failures = cmp.check(_goal(name, obj, part, ref), parts=[part], objects=[obj])  # raises on a noisy reference
    assert not failures, failures


def test_indirect_error_falls_with_the_number_of_spheres(shaded):
    """The paper's Fig. 10 claim: a tighter sphere set approximates the blocker better, so the ground's indirect
    error (the reference's noise removed in quadrature) with 16 spheres on the bunny is no larger than with 1;
    every count is scored against the same Mitsuba reference, whose noise is within a third of the goal. The claim
    is about the ground shaded through the spherical lights, the paper's ``ground_shading="lights"``: with the
    default rays the ground's light is cast against the bunny's mesh, and the sphere count no longer enters it
    (0.0385 with 1 sphere, 0.0388 with 16, both within the goal)."""
    _, ref = shaded("bunny (16 spheres)")
    sc = CASES["bunny (16 spheres)"][0]()
    rows = []
    for n in (1, 16):
        pre = SphereLights.precompute(sc, {"n_spheres": {"bunny": n, "sphere_green": 1, "sphere_orange": 1},
                                           "fit_resolution": 40, "ground_shading": "lights"},
                                      cache=True, progress=False)
        rows.append(prtlab.compare(pre.shade(bounces=1), ref, objects=["plane"], parts=["indirect"]).rows[0])
    assert rows[0].noise <= INDIRECT_GOAL["bunny (16 spheres)"] / 3, rows[0]
    assert rows[1].error <= rows[0].error, rows
