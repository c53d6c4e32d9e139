"""Test helper: the SH shadow fields of a whole scene, assembled from the public building blocks.

For every (non-portal) object of a :class:`prtlab.scene.Scene`, :func:`precompute_scene` computes its
occlusion field and its vertices' self-visibility (object space); :func:`scene_visibility` assembles the
world-frame visibility of every vertex for a pose of the scene (:func:`prtlab.shadowfields.occluder_order`,
:func:`prtlab.shadowfields.visibility_pass`), and :func:`direct_environment` lights it with the scene's
environment through each object's separable BRDF (Zhou et al. 2005 / Iwasaki et al. 2007 Eq. 7-8). No
pipeline uses this assembly; the tests of :mod:`prtlab.shadowfields` check the blocks with it.

Occlusion fields are clamped to their innermost sphere (0.2 bounding radii by default), so a receiver very
close to a large occluder gets a blurred visibility; area lights do not occlude the environment here.
"""

from __future__ import annotations

import numpy as np

from prtlab import sh
from prtlab.shadowfields import (
    OcclusionField,
    direct_pass,
    occluder_order,
    occlusion_field,
    self_visibility,
    visibility_pass,
)


def _shaded(scene):
    return [o for o in scene.objects if not o.portal]


def precompute_scene(scene, order: int = 4, *, n_radii: int = 16, resolution: int = 16, r_min: float = 0.2,
                     r_max: float = 8.0, spacing: str = "geometric", degree: int | None = None) -> dict:
    """Occlusion fields and self-visibility of every object (object space).

    Returns
    -------
    data : dict
        ``data[name] = {"oof": OcclusionField.to_arrays(), "self_visibility": (V, n*n)}``.
    """
    out = {}
    for obj in _shaded(scene):
        oof = occlusion_field(obj.mesh, order, n_radii=n_radii, resolution=resolution, r_min=r_min,
                              r_max=r_max, spacing=spacing, degree=degree)
        vis = self_visibility(obj.mesh, order, degree=degree)
        out[obj.name] = {"oof": oof.to_arrays(), "self_visibility": vis}
    return out


def scene_visibility(scene, data: dict, transforms: dict | None = None, method: str = "numba") -> dict:
    """World-frame SH visibility of every vertex of every object in a pose of the scene.

    Parameters
    ----------
    scene : prtlab.Scene
    data : dict
        From :func:`precompute_scene`.
    transforms : dict name -> Transform, optional
        The frame's poses (default: the scene's).
    method : {"numba", "reference"}
        Interpolation tier of the occlusion-field lookups.

    Returns
    -------
    visibility : dict name -> (n_vertices, n*n)
    """
    objs = _shaded(scene)
    transforms = transforms or {}
    pose = {o.name: transforms.get(o.name, o.transform) for o in objs}
    fields = {o.name: OcclusionField.from_arrays(data[o.name]["oof"]) for o in objs}
    centers = {o.name: pose[o.name].apply_points(fields[o.name].grid.center) for o in objs}
    out = {}
    for obj in objs:
        T = pose[obj.name]
        own = np.asarray(data[obj.name]["self_visibility"], dtype=np.float64)
        if len(own):
            own = sh.rotate(own, T.rotation, channels=False)
        others = [o for o in objs if o.name != obj.name]
        order_idx = occluder_order(centers[obj.name], [centers[o.name] for o in others]) if others else []
        x = obj.world_vertices(T)
        occ = [fields[others[i].name].lookup(x, pose[others[i].name], method=method) for i in order_idx]
        out[obj.name] = visibility_pass(own, occ)
    return out


def separable_brdfs(scene, K_glossy: int = 4, resolution=(32, 64)) -> dict:
    """``prtlab.brdf.separable`` of every object's material: K = 1 for Lambert, ``K_glossy`` for Phong."""
    from prtlab import brdf

    out = {}
    for obj in _shaded(scene):
        model = brdf.from_material(obj.material)
        K = 1 if obj.material.type == "diffuse" else K_glossy
        out[obj.name] = brdf.separable(model, K, resolution=resolution)
    return out


def direct_environment(scene, visibility: dict, seps: dict, order: int, transforms: dict | None = None,
                       environment=None, camera=None, method: str = "numba") -> dict:
    """Outgoing radiance toward the camera from the environment, per vertex (Iwasaki et al. Eq. 7-8).

    Parameters
    ----------
    scene : prtlab.Scene
    visibility : dict name -> (V, n*n)
        From :func:`scene_visibility`.
    seps : dict name -> SeparableBRDF
        From :func:`separable_brdfs`.
    order : int
    transforms, environment, camera : optional
        The frame's poses, environment light and camera (default: the scene's).
    method : {"numba", "reference"}
        Tier of :func:`direct_pass`.

    Returns
    -------
    radiance : dict name -> (V, 3)
    """
    from prtlab import brdf
    from prtlab.scene import environment_sh

    env = environment if environment is not None else scene.environment
    camera = camera if camera is not None else scene.camera
    transforms = transforms or {}
    out = {}
    light = environment_sh(env, order) if env is not None else None
    for obj in _shaded(scene):
        T = transforms.get(obj.name, obj.transform)
        if light is None:
            out[obj.name] = np.zeros((obj.n_vertices, 3))
            continue
        normals = obj.world_normals(T)
        sep = seps[obj.name]
        g_cos = brdf.project_g_cos(sep, normals, order)
        wo = np.asarray(camera.position, float) - obj.world_vertices(T)
        wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-300)
        h = brdf.project_h(sep, wo, normals)
        out[obj.name] = direct_pass(light, visibility[obj.name], g_cos, h, sep.colour, method=method)
    return out
