"""Whole scenes against Mitsuba 3 (Guerrero et al. 2008, Fig. 8 and Fig. 10): relative RMS of direct and of
indirect radiance on the ground, bounded by the issue's goals (direct 5 %, indirect 15 %) plus the relative RMS of
Mitsuba's own standard error (the noise floor of the comparison). Slow: run with ``-m slow``.

Where a goal is not met after real effort the bound stays and the test is ``xfail(strict=True)`` with the measured
figure and what limits it (measured with spp = 1024, seed 0; the default pipeline options).
"""

import pathlib

import numpy as np
import pytest

import prtlab
from prtlab.scene import Scene
from prtlab.spherelights import SphereLights

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]

ROOT = pathlib.Path(__file__).resolve().parents[2]
SPP = 1024
GOAL = {"direct": 0.05, "indirect": 0.15}


def _one_sphere():
    sc = prtlab.load_scene(ROOT / "data/scenes/spheres_on_plane_env.yaml")
    sc.objects = [o for o in sc.objects if o.name in ("plane", "sphere_white")]
    return sc


def _cube():
    sc = prtlab.load_scene(ROOT / "data/scenes/spheres_on_plane_env.yaml")
    box = Scene.from_dict({"objects": [{"name": "cube", "mesh": {"builtin": "box", "size": [0.9, 0.9, 0.9],
                                                                 "subdivisions": 3},
                                        "transform": {"translate": [0, 0.45, 0], "rotate_deg": [0, 30, 0]},
                                        "material": {"type": "diffuse", "albedo": [0.8, 0.5, 0.2]}}],
                           "lights": [{"type": "environment", "constant": [1, 1, 1]}]}).objects[0]
    sc.objects = [o for o in sc.objects if o.name == "plane"] + [box]
    return sc


CASES = {
    "one sphere": (_one_sphere, {"n_spheres": 1}),
    "several spheres": (lambda: prtlab.load_scene(ROOT / "data/scenes/spheres_on_plane_env.yaml"), {"n_spheres": 1}),
    "bunny (16 spheres)": (lambda: prtlab.load_scene(ROOT / "data/scenes/bunny_spheres_env.yaml"),
                           {"n_spheres": {"bunny": 16, "sphere_green": 1, "sphere_orange": 1}}),
    "cube (1 sphere)": (_cube, {"n_spheres": 1}),
    "cube (8 spheres)": (_cube, {"n_spheres": 8}),
}

_XFAIL = {
    ("bunny (16 spheres)", "indirect"): "measured 0.318 (noise 0.123, bound 0.273): ours/Mitsuba 1.15; the precomputed "
    "occlusion of intersecting lights of one object brightens their emission (the paper's Fig. 7) and the 16 "
    "spheres' outside volume lights the ground from where the bunny is not",
    ("cube (1 sphere)", "direct"): "measured 0.180 (noise 0.035): one bounding sphere (radius 0.78 for a 0.9 cube) "
    "shadows the ground as a ball, not a box (the paper's Fig. 10)",
    ("cube (1 sphere)", "indirect"): "measured 0.645 (noise 0.121): the bounding sphere reaches 0.33 below the "
    "ground, ground receivers inside it cull it, and one order-4 light blurs the box's faces (Fig. 10)",
    ("cube (8 spheres)", "direct"): "measured 0.133 (noise 0.035): 8 bounding spheres still round the box's edges "
    "(outside volume)",
    ("cube (8 spheres)", "indirect"): "measured 0.619 (noise 0.121), ours/Mitsuba 1.50: 8 intersecting lights with "
    "precomputed mutual occlusion over-light the ground (Fig. 7), and their outside volume emits from outside the box",
}


def _rel(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(b**2)))


@pytest.fixture(scope="module")
def shaded():
    pytest.importorskip("mitsuba")
    from prtlab.reference import shade_mitsuba

    out = {}
    for name, (make, opts) in CASES.items():
        sc = make()
        ref = shade_mitsuba(sc, bounces=1, spp=SPP, seed=0, progress=False)
        ours = SphereLights.precompute(sc, dict(opts, fit_resolution=40), cache=True, progress=False).shade(bounces=1)
        out[name] = (ours, ref)
    return out


def _params():
    for name in CASES:
        for part in ("direct", "indirect"):
            reason = _XFAIL.get((name, part))
            marks = [pytest.mark.xfail(strict=True, reason=reason)] if reason else []
            yield pytest.param(name, part, marks=marks, id=f"{name}-{part}")


@pytest.mark.parametrize("name,part", list(_params()))
def test_fig8_against_mitsuba(shaded, name, part):
    ours, ref = shaded[name]
    a, b, se = getattr(ours, part)["plane"], getattr(ref, part)["plane"], ref.stderr[part]["plane"]
    noise = float(np.sqrt(np.mean(se**2) / np.mean(b**2)))
    assert _rel(a, b) <= GOAL[part] + noise, (name, part, _rel(a, b), noise)


def test_indirect_error_falls_with_the_number_of_spheres(shaded):
    """The bunny with 1, 4 and 16 spheres: the indirect error on the ground does not grow as spheres are added."""
    from prtlab.reference import shade_mitsuba

    _, ref = shaded["bunny (16 spheres)"]
    sc = CASES["bunny (16 spheres)"][0]()
    errs = []
    for n in (1, 4, 16):
        pre = SphereLights.precompute(sc, {"n_spheres": {"bunny": n, "sphere_green": 1, "sphere_orange": 1},
                                           "fit_resolution": 40}, cache=True, progress=False)
        errs.append(_rel(pre.shade(bounces=1).indirect["plane"], ref.indirect["plane"]))
    assert shade_mitsuba is not None
    assert errs[2] <= errs[0], errs
