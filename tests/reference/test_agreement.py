"""prtlab's own Monte Carlo estimators against Mitsuba 3 on the same small scenes.

Two independent estimators of the same per-vertex radiance must agree within
their combined standard errors. Per vertex and channel

    z = (own - mitsuba) / sqrt(se_own^2 + se_mitsuba^2),

and, aggregated honestly over every vertex of the scene (z of two 256-sample
means is Gaussian to within their excess kurtosis, measured 2.7..3.4 here):
(1) the count of vertices with some |z| > MC_SIGMAS is within the binomial
bound at two-sided significance CHI2_SIGNIFICANCE for a per-vertex rate of
3 x P(|N(0,1)| > MC_SIGMAS) (Bonferroni over the channels; at most 1 of
111 vertices, 2 of 189); (2) the mean of z is within MC_SIGMAS standard errors
of 0 (the vertices are independent, so the standard error of the mean is
1 / sqrt(n)); (3) the spread of z over the vertices whose estimates are not
both exact lies in the chi-square band of n degrees of freedom at the same
significance (channels are strongly correlated: n vertices, not 3 n values,
the wider band), so errors are neither under- nor overestimated across the board.

Scenes avoid two places where the conventions of the two renderers differ
(see the report in the notebook ``01_ground_truth``): vertices lying exactly
on another surface (room corners; walls here stop short of the floor) and
surfaces behind an area light (Mitsuba's rectangle emitters are opaque, the
own estimators' lights are not geometry; here nothing lies behind the light).
"""

from __future__ import annotations

import numpy as np
import pytest

from prtlab.geometry import builtin_mesh, equirect_directions
from prtlab.scene import AreaLight, Camera, EnvironmentLight, Material, Scene, SceneObject, Transform
from tests.conftest import MC_SIGMAS
from tests.geometry.test_sampling import CHI2_SIGNIFICANCE

pytestmark = pytest.mark.mitsuba

_PARTS = ("direct", "indirect", "total")


def open_box_scene(resolution: int = 6) -> Scene:
    """Floor, a red wall, a glossy (Phong) back wall and a ball under a small ceiling-less area light."""
    plane = lambda: builtin_mesh("plane", size=[1, 1], resolution=[resolution, resolution])  # noqa: E731
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


def sky_map(height: int = 32, width: int = 64) -> np.ndarray:
    """A smooth synthetic sky: blue gradient above, dark ground, and a bright sun blob."""
    d = equirect_directions(height, width)
    sun = np.array([0.5, 0.6, -0.62])
    sun /= np.linalg.norm(sun)
    up = np.clip(d[..., 1], 0, 1)[..., None]
    sky = 0.3 + 0.7 * up * np.array([0.4, 0.6, 1.0]) + 0.05 * (d[..., 1] < 0)[..., None]
    blob = np.exp((d @ sun - 1.0) / 0.02)[..., None] * np.array([30.0, 28.0, 22.0])
    return sky + blob


def env_scene() -> Scene:
    """A floor, a slab and a ball under an equirect sky (no area light)."""
    objects = [
        SceneObject("floor", builtin_mesh("plane", size=[2, 2], resolution=[6, 6]),
                    material=Material(albedo=np.array([0.7, 0.7, 0.6]))),
        SceneObject("slab", builtin_mesh("plane", size=[1, 0.8], resolution=[4, 3]),
                    Transform(np.array([-0.2, 0.45, -0.6]), np.array([75.0, 0.0, 0.0])),
                    Material(type="phong", kd=np.array([0.4, 0.3, 0.3]), ks=np.array([0.2, 0.2, 0.2]), exponent=20.0)),
        SceneObject("ball", builtin_mesh("icosphere", radius=0.3, subdivisions=1), Transform(np.array([0.3, 0.32, 0.1])),
                    Material(albedo=np.array([0.8, 0.8, 0.8]))),
    ]
    camera = Camera(position=np.array([0.0, 1.2, 3.0]), look_at=np.array([0, 0.3, 0]), fov_deg=40, resolution=(64, 48))
    return Scene(objects=objects, lights=[EnvironmentLight(image=sky_map())], camera=camera, name="env_sky")


def z_scores(own, mitsuba, part: str) -> np.ndarray:
    """(n_vertices, 3) z-scores of one part over every object (0 where both are exact and equal)."""
    out = []
    for name in mitsuba.total:
        d = getattr(own, part)[name] - getattr(mitsuba, part)[name]
        s = np.hypot(own.stderr[part][name], mitsuba.stderr[part][name])
        exact = s == 0
        if np.any(exact & (np.abs(d) > 1e-12)):
            raise AssertionError(f"{name}/{part}: zero standard errors but different values")
        out.append(np.where(exact, 0.0, d / np.where(exact, 1.0, s)))
    return np.concatenate(out)


def assert_agree(own, mitsuba, label: str) -> dict:
    from scipy.stats import binom, chi2, norm

    stats = {}
    for part in _PARTS:
        z = z_scores(own, mitsuba, part)
        per_vertex = z.mean(axis=1)  # channels are strongly correlated: one number per vertex
        n = len(z)
        outliers = int(np.sum(np.abs(z).max(axis=1) > MC_SIGMAS))
        allowed = int(binom.isf(CHI2_SIGNIFICANCE / 2, n, 3 * 2 * norm.sf(MC_SIGMAS)))
        noisy = z[np.any(z != 0, axis=1)]
        std = float(np.sqrt(np.mean(noisy**2))) if len(noisy) else 0.0  # spread about the truth, 0
        band = np.sqrt(chi2.ppf([CHI2_SIGNIFICANCE / 2, 1 - CHI2_SIGNIFICANCE / 2], len(noisy)) / max(len(noisy), 1))
        stats[part] = dict(mean_z=per_vertex.mean(), std_z=std, outliers=outliers)
        assert outliers <= allowed, f"{label}/{part}: {outliers} of {n} vertices have |z| > {MC_SIGMAS} (<= {allowed})"
        assert abs(per_vertex.mean()) <= MC_SIGMAS / np.sqrt(n), f"{label}/{part}: mean z = {per_vertex.mean():.3f}"
        if len(noisy):
            assert band[0] <= std <= band[1], f"{label}/{part}: rms of z = {std:.3f}, band {band[0]:.3f}..{band[1]:.3f}"
    return stats


@pytest.fixture(scope="module")
def estimators():
    pytest.importorskip("mitsuba")
    from prtlab.reference import shade_mitsuba, shade_reference

    return shade_reference, shade_mitsuba


@pytest.mark.parametrize("bounces", [0, 1, 4], ids=["direct", "one_bounce", "full"])
def test_own_and_mitsuba_agree_in_an_open_box_with_an_area_light(estimators, bounces):
    shade_reference, shade_mitsuba = estimators
    scene = open_box_scene()
    own = shade_reference(scene, bounces=bounces, n_samples=256, seed=1, progress=False)
    mit = shade_mitsuba(scene, bounces=bounces, spp=256, seed=2)
    assert_agree(own, mit, f"open_box B={bounces}")
    if bounces == 0:
        for name in mit.indirect:
            np.testing.assert_array_equal(own.indirect[name], 0.0)
            np.testing.assert_array_equal(mit.indirect[name], 0.0)
    else:
        assert all(np.all(mit.indirect[name] >= 0) for name in mit.indirect)
        assert np.mean(mit.indirect["floor"]) > 0.0


@pytest.mark.parametrize("bounces", [0, 2], ids=["direct", "two_bounces"])
def test_own_and_mitsuba_agree_under_an_environment_map(estimators, bounces):
    shade_reference, shade_mitsuba = estimators
    scene = env_scene()
    own = shade_reference(scene, bounces=bounces, n_samples=256, seed=3, progress=False)
    mit = shade_mitsuba(scene, bounces=bounces, spp=256, seed=4)
    assert_agree(own, mit, f"env_sky B={bounces}")


def test_disagreement_is_detected(estimators):
    """The aggregate test has teeth: a 3 % change of one albedo is caught."""
    shade_reference, shade_mitsuba = estimators
    scene = open_box_scene()
    own = shade_reference(scene, bounces=0, n_samples=256, seed=1, progress=False)
    scene.objects[0].material = Material(albedo=np.array([0.8, 0.8, 0.8]) * 1.03)
    mit = shade_mitsuba(scene, bounces=0, spp=256, seed=2)
    with pytest.raises(AssertionError, match=r"perturbed/direct: \d+ of 189 vertices have \|z\| > 4"):
        assert_agree(own, mit, "perturbed")
