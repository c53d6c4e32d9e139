"""The call the interreflection pipeline makes for ``shadows="haar"`` (``/tmp/h5b_pipeline.patch``):
per object a Haar occlusion field and a self-visibility at its shading points (object space), per frame
``haar_direct`` of every receiver with the other objects' fields at their poses."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import brdf
from prtlab.geometry import shading_points
from prtlab.reference import direct
from prtlab.scene import Scene, Transform
from prtlab.shadowfields import (
    HaarOcclusionField,
    SparseCubemaps,
    haar_direct,
    haar_occlusion_field,
    haar_self_visibility,
)
from tests.conftest import MC_SIGMAS

QUICK = dict(resolution=16, keep=6 * 16 * 16, n_radii=6, grid_resolution=4)


def scene_of(ball_at):
    return Scene.from_dict({
        "objects": [
            {"name": "floor", "mesh": {"builtin": "plane", "size": [3, 3], "resolution": [6, 6]},
             "material": {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]}},
            {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 2},
             "transform": {"translate": list(ball_at), "rotate_deg": [20, 30, 0]},
             "material": {"type": "diffuse", "albedo": [0.5, 0.4, 0.3]}},
        ],
        "lights": [{"type": "area", "center": [0.2, 2.5, 0], "u": [0.3, 0, 0], "v": [0, 0, 0.3],
                    "radiance": [10, 10, 10]},
                   {"type": "point", "position": [-0.5, 2.0, 0.4], "intensity": [2, 2, 2]}],
        "camera": {"position": [0, 3, 6], "look_at": [0, 0, 0]},
    })


@pytest.fixture(scope="module")
def precomputed():
    """What ``Interreflection.compute`` stores with ``shadows="haar"`` (object space, HDF5-friendly arrays)."""
    scene = scene_of([0, 1.0, 0])
    data = {}
    for obj in scene.objects:
        mesh = obj.mesh
        pts = shading_points(mesh.vertices, np.asarray(mesh.faces), mesh.vertex_normals)
        data[obj.name] = {
            "haar_oof": haar_occlusion_field(mesh, **QUICK).to_arrays(),
            "haar_self": haar_self_visibility(mesh, points=pts, resolution=QUICK["resolution"],
                                              keep=QUICK["keep"]).to_arrays(),
        }
    return data


def direct_light_k(scene, data, transforms=None):
    """The pipeline's direct step: L_k per object (V, K, C), then the radiance toward the camera."""
    transforms = transforms or {}
    fields = {o.name: HaarOcclusionField.from_arrays(data[o.name]["haar_oof"]) for o in scene.objects}
    own = {o.name: SparseCubemaps.from_arrays(data[o.name]["haar_self"]) for o in scene.objects}
    out = {}
    for r in scene.objects:
        T = transforms.get(r.name, r.transform)
        x, n = r.world_shading_points(T), r.world_normals(T)
        sep = brdf.separable(brdf.from_material(r.material), 1 if r.material.type == "diffuse" else 4)
        occ = [(fields[o.name], transforms.get(o.name, o.transform)) for o in scene.objects if o is not r]
        lk = haar_direct(x, n, scene.lights, sep, self_visibility=own[r.name], self_transform=T, occluders=occ)
        wo = scene.camera.position - x
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        h = brdf.project_h(sep, wo, n)
        out[r.name] = np.einsum("vk,kc,vkc->vc", h, sep.colour, lk)
    return out


def test_lit_ball_against_monte_carlo(precomputed, rng):
    """The ball's upper half sees both lights past nothing but itself (the floor's field blocks only the
    lower hemisphere, which no light reaches): exact self-visibility (all coefficients kept), exact
    light pieces, a Lambertian BRDF (exact with K = 1). Bound: MC_SIGMAS standard errors plus the
    resolution bound, here at most the light falling on the self-shadow's edge texels, which
    :func:`edge_bound` gives per vertex from the world self-visibility cubemaps."""
    from prtlab.geometry import RayCaster
    from prtlab.shadowfields import edge_bound, light_pieces, visibility_cubemaps

    scene = scene_of([0, 1.0, 0])
    ours = direct_light_k(scene, precomputed)
    ref = direct(scene, 256, rng)
    ball = scene.objects[1]
    up = ball.world_normals()[:, 1] > 0.3
    got, want, se = ours["ball"][up], ref.direct["ball"][up], ref.stderr["direct"]["ball"][up]
    x, n = ball.world_shading_points()[up], ball.world_normals()[up]
    vis = visibility_cubemaps(RayCaster([(ball.world_vertices(), ball.mesh.faces)]), x, QUICK["resolution"],
                              normals=n)
    sep = brdf.separable(brdf.from_material(ball.material), 1)
    texel, gw, rad, _ = light_pieces(scene.lights, x, n, sep, QUICK["resolution"])
    bound = edge_bound(texel, gw, rad, vis, QUICK["resolution"])[:, 0] * sep.colour[0]
    assert np.all(np.abs(got - want) <= MC_SIGMAS * se + bound + 1e-9)


def test_moving_the_ball_away_unshadows_the_floor(precomputed):
    """Only the moved object's shadow changes: beyond its outermost sample sphere it casts none."""
    scene = scene_of([0, 1.0, 0])
    here = direct_light_k(scene, precomputed)
    far = direct_light_k(scene, precomputed, {"ball": Transform(translate=np.array([50.0, 1.0, 0.0]),
                                                                  rotate_deg=np.array([20.0, 30.0, 0.0]))})
    free = direct_light_k(Scene(objects=scene.objects[:1], lights=scene.lights, camera=scene.camera),
                          {"floor": precomputed["floor"]})
    np.testing.assert_allclose(far["floor"], free["floor"], rtol=1e-12, atol=1e-15)
    assert np.any(here["floor"][:, 0] < far["floor"][:, 0] - 1e-3)  # the shadow was there
    # the ball's own light depends only on its pose relative to the lights, not on the floor's field
    np.testing.assert_array_less(-1e-12, here["ball"])
