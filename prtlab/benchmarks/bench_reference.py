"""Benchmarks of the Monte Carlo references: prtlab's own estimator vs Mitsuba 3 at equal error.

``reference.own_vs_mitsuba``: per-vertex radiance with one indirect bounce on
a small scene (an open box: floor, red wall, glossy Phong back wall, a ball,
one area light; 189 vertices). The own estimator
(:func:`prtlab.reference.shade_reference`) runs ``n`` samples per vertex; the
peer (:func:`prtlab.reference.shade_mitsuba`, ``llvm_ad_rgb``) runs as many
samples as it needs for the *same median standard error* of the total
radiance, calibrated by a pilot run of each (standard errors scale as
``1 / sqrt(samples)``). The runner's ``x`` ratio is then the time ratio at
equal standard error (> 1: the own estimator is faster).
"""

from __future__ import annotations

import numpy as np

from prtlab.bench import case


def _open_box():
    from prtlab.geometry import builtin_mesh
    from prtlab.scene import AreaLight, Camera, Material, Scene, SceneObject, Transform

    plane = lambda: builtin_mesh("plane", size=[1, 1], resolution=[6, 6])  # noqa: E731
    objects = [
        SceneObject("floor", plane(), material=Material(albedo=np.array([0.8, 0.8, 0.8]))),
        SceneObject("red_wall", plane(), Transform(np.array([-0.52, 0.51, 0.0]), np.array([0.0, 0.0, -90.0])),
                    Material(albedo=np.array([0.8, 0.1, 0.1]))),
        SceneObject("back_wall", plane(), Transform(np.array([0.0, 0.51, -0.52]), np.array([90.0, 0.0, 0.0])),
                    Material(type="phong", kd=np.array([0.3, 0.4, 0.3]), ks=np.array([0.3, 0.3, 0.3]), exponent=8.0)),
        SceneObject("ball", builtin_mesh("icosphere", radius=0.2, subdivisions=1), Transform(np.array([0.1, 0.21, 0.05])),
                    Material(albedo=np.array([0.2, 0.5, 0.8]))),
    ]
    light = AreaLight(np.array([0.1, 1.2, 0.1]), np.array([0.15, 0, 0]), np.array([0, 0, 0.15]), np.full(3, 20.0))
    camera = Camera(position=np.array([0.3, 0.7, 2.2]), look_at=np.array([0, 0.4, 0]), fov_deg=45, resolution=(64, 48))
    return Scene(objects=objects, lights=[light], camera=camera, name="open_box")


def median_relative_stderr(result, part: str = "total") -> float:
    """Median over vertices (with nonzero radiance) of stderr / value, green channel."""
    ratios = []
    for name, values in getattr(result, part).items():
        v = values[:, 1]
        s = result.stderr[part][name][:, 1]
        ok = v > 0
        ratios.append(s[ok] / v[ok])
    return float(np.median(np.concatenate(ratios)))


def equal_error_samples(pilot_samples: int, pilot_error: float, target_error: float) -> int:
    """Samples per vertex that bring a ``1/sqrt(n)`` estimator from ``pilot_error`` to ``target_error``."""
    return max(2, int(np.ceil(pilot_samples * (pilot_error / target_error) ** 2)))


@case("reference.own_vs_mitsuba")
def own_vs_mitsuba(quick: bool):
    from prtlab.reference import shade_mitsuba, shade_reference

    scene = _open_box()
    bounces = 1
    n_own = 32 if quick else 256
    pilot = 64
    own_pilot = shade_reference(scene, bounces=bounces, n_samples=pilot, seed=11, progress=False)
    mit_pilot = shade_mitsuba(scene, bounces=bounces, spp=pilot, seed=12)
    target = median_relative_stderr(own_pilot) * np.sqrt(pilot / n_own)
    n_mit = equal_error_samples(pilot, median_relative_stderr(mit_pilot), target)
    n_vertices = sum(o.n_vertices for o in scene.objects)
    peer_name = f"mitsuba {mit_pilot.info['variant']} ({n_mit} spp vs own {n_own}, equal median stderr)"
    return {
        "run": lambda: shade_reference(scene, bounces=bounces, n_samples=n_own, seed=1, progress=False),
        "gflop": None,
        "items": n_vertices,
        "peer": (peer_name, lambda: shade_mitsuba(scene, bounces=bounces, spp=n_mit, seed=2)),
    }
