"""All-frequency shadow fields against the Monte Carlo reference (prtlab.reference).

Bounds: ``MC_SIGMAS`` standard errors of the estimate plus the cubemap-resolution
bound of :func:`prtlab.shadowfields.edge_bound` (the light on texels whose
visibility is not constant; the light pieces themselves are exact) plus the Haar
truncation (zero here: the stored coefficients are checked to be exact).

The occlusion-field interpolation between sample points has no derived bound;
its error is measured in the slow test (and reported against the SH path).
"""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import brdf
from prtlab.geometry import RayCaster
from prtlab.reference import irradiance_at
from prtlab.scene import Scene
from prtlab.shadowfields import (
    area_light_sh,
    direct_pass,
    edge_bound,
    haar_direct,
    haar_occlusion_field,
    haar_self_visibility,
    light_pieces,
    occlusion_field,
    visibility_cubemaps,
)
from tests.conftest import MC_SIGMAS

LAMBERT = brdf.separable(brdf.lambert(1.0), 1)
RES = 32


def ball_scene(light):
    return Scene.from_dict({
        "objects": [{"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 3},
                     "transform": {"translate": [0, 1.0, 0]}, "material": {"type": "diffuse", "albedo": [1, 1, 1]}}],
        "lights": [light],
        "camera": {"position": [0, 3, 6], "look_at": [0, 0, 0]},
    })


AREA = {"type": "area", "center": [0, 2.5, 0], "u": [0.3, 0, 0], "v": [0, 0, 0.3], "radiance": [10, 10, 10]}
POINT = {"type": "point", "position": [0.1, 2.5, 0.0], "intensity": [5, 5, 5]}


def floor_points(n=15):
    xs = np.linspace(-0.9, 0.9, n)
    pts = np.stack([xs, np.zeros(n), np.full(n, 0.05)], axis=1)
    return pts, np.tile([0.0, 1.0, 0.0], (n, 1))


def _check(E, E_mc, se, bound):
    excess = np.abs(E - E_mc) - (MC_SIGMAS * se + bound + 1e-12)
    assert np.all(excess <= 0), f"worst excess {excess.max():.3g} at {np.argmax(excess)}"


@pytest.mark.parametrize("light", [AREA, POINT], ids=["area", "point"])
def test_shadow_of_a_ball_with_exact_visibility_at_the_vertex(light, rng):
    """The Haar path with the visibility cubemap ray cast at each receiver: resolution bound only."""
    scene = ball_scene(light)
    pts, nrm = floor_points()
    ref = irradiance_at(scene, pts, nrm, 2048, rng)
    ball = scene.objects[0]
    caster = RayCaster([(ball.world_vertices(), ball.mesh.faces)])
    vis = visibility_cubemaps(caster, pts, RES)
    texel, gw, rad, _ = light_pieces(scene.lights, pts, nrm, LAMBERT, RES)
    E = np.pi * np.einsum("vp,vpk,vpc->vkc", np.take_along_axis(vis.reshape(len(pts), -1), texel, 1), gw, rad)[:, 0]
    bound = np.pi * edge_bound(texel, gw, rad, vis, RES)[:, 0]
    _check(E, ref.total, ref.stderr, bound)
    assert np.any(ref.total[:, 0] < 1e-3) and np.any(ref.total[:, 0] > 0.1)  # umbra and lit points both tested


def test_self_shadowing_of_a_torus_under_an_area_light(rng):
    scene = Scene.from_dict({
        "objects": [{"name": "torus", "mesh": {"builtin": "torus", "sections": [32, 12]},
                     "transform": {"rotate_deg": [60, 0, 0]}, "material": {"type": "diffuse", "albedo": [1, 1, 1]}}],
        "lights": [{"type": "area", "center": [0.3, 2.0, 0.2], "u": [0.4, 0, 0], "v": [0, 0, 0.4],
                    "radiance": [5, 5, 5]}],
        "camera": {"position": [0, 3, 6], "look_at": [0, 0, 0]},
    })
    torus = scene.objects[0]
    sel = np.arange(0, len(torus.mesh.vertices), 7)
    sv = haar_self_visibility(torus.mesh, resolution=RES, keep=6 * RES * RES)  # exact storage
    x, n = torus.world_vertices()[sel], torus.world_normals()[sel]
    from prtlab.shadowfields import SparseCubemaps

    sub = SparseCubemaps(RES, sv.indices[sel], sv.values[sel], sv.energy_lost[sel])
    E = np.pi * haar_direct(x, n, scene.lights, LAMBERT, self_visibility=sub, self_transform=torus.transform)[:, 0]
    ref = irradiance_at(scene, x, n, 1024, rng)
    # the bound uses the world visibility cubemaps (ray cast from the same offset points)
    caster = RayCaster([(torus.world_vertices(), torus.mesh.faces)])
    vis = visibility_cubemaps(caster, x, RES, normals=n)
    texel, gw, rad, _ = light_pieces(scene.lights, x, n, LAMBERT, RES)
    bound = np.pi * edge_bound(texel, gw, rad, vis, RES)[:, 0]
    # the rotation of the self-visibility (60 deg about x) resamples texels: add the rotation's edge texels,
    # already counted by edge_bound (the resampled texels differ from the ray-cast ones only at edges)
    _check(E, ref.total, ref.stderr, bound)
    shadowed = ref.total[:, 0] < 0.5 * np.max(ref.total[:, 0])
    assert shadowed.sum() >= 3


@pytest.mark.slow
def test_field_interpolation_error_against_the_sh_path(rng):
    """The default occlusion-field grid (16 x 6 x 16 x 16), trilinear: the irradiance over the floor points
    under the ball, Haar against SH order 4, both against Monte Carlo: Haar's squared error is the smaller
    (relative RMS figures in docs/notes/shadowfields.md)."""
    scene = ball_scene(AREA)
    xs = np.linspace(-1.0, 1.0, 9)
    gx, gz = np.meshgrid(xs, xs)
    pts = np.stack([gx.ravel(), np.zeros(gx.size), gz.ravel()], axis=1)
    nrm = np.tile([0.0, 1, 0], (len(pts), 1))
    ref = irradiance_at(scene, pts, nrm, 4096, rng)
    ball = scene.objects[0]
    field = haar_occlusion_field(ball.mesh)
    E = np.pi * haar_direct(pts, nrm, scene.lights, LAMBERT, occluders=[(field, ball.transform)])[:, 0]
    oof = occlusion_field(ball.mesh, 4)
    vsh = oof.lookup(pts, ball.transform)
    g = brdf.project_g_cos(LAMBERT, nrm, 4)
    Esh = np.pi * direct_pass(area_light_sh(scene.lights[0], pts, 4), vsh, g, np.ones((len(pts), 1)), np.ones((1, 3)))
    scale = np.sqrt(np.mean(ref.total[:, 0] ** 2))
    err_haar = np.sqrt(np.mean((E[:, 0] - ref.total[:, 0]) ** 2)) / scale
    err_sh = np.sqrt(np.mean((Esh[:, 0] - ref.total[:, 0]) ** 2)) / scale
    print(f"relative RMS: haar {err_haar:.3f}, sh {err_sh:.3f}")
    # paired per point: the reference's noise enters both squared errors alike, so the mean difference is an
    # unbiased estimate of the true one; Haar's below SH's by 4 standard errors
    d = (Esh[:, 0] - ref.total[:, 0]) ** 2 - (E[:, 0] - ref.total[:, 0]) ** 2
    assert d.mean() > 4.0 * d.std(ddof=1) / np.sqrt(len(d)), (d.mean(), d.std(ddof=1) / np.sqrt(len(d)))
