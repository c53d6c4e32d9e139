"""The shell light of a dynamic exterior (Yue et al. 2009, Sections 3.1, 5, 6).

Each frame, the shell of a portal is "rendered" from the portal centre: a
cubemap whose texel ``k`` holds the radiance arriving at the centre from the
texel's direction ``w_k``: the environment where the ray escapes, else the
radiance leaving the first exterior surface hit toward the centre, estimated
with :func:`prtlab.reference.radiance_at` (direct light of the environment and
``bounces`` more, with exterior shadows). The interior is not part of the
exterior scene: light it reflects outward is neglected, which Section 6's
second criterion bounds (:func:`prtlab.portals.check_interior_solid_angle`).
The first criterion (:func:`prtlab.portals.check_shell_distance`) is checked
against the nearest exterior hit.
"""

from __future__ import annotations

import numpy as np

from prtlab.geometry import RayCaster, cubemap_directions
from prtlab.scene import Scene

from ._shell import Portal, shell_light
from ._validity import check_shell_distance

__all__ = ["exterior_shell"]


def exterior_shell(exterior: Scene, portal: Portal, res: int = 32, n_samples: int = 64, rng=None,
                   bounces: int = 0, max_angle_deg: float = 5.0) -> np.ndarray:
    """A shell cubemap seen from ``portal.center`` in an exterior scene.

    Parameters
    ----------
    exterior : prtlab.Scene
        Exterior objects (their current transforms) and one environment light.
    portal : Portal
    res : int
        Face resolution.
    n_samples : int
        Paths per hit texel for its radiance.
    rng : numpy.random.Generator, optional
    bounces : int
        Bounces among exterior objects.
    max_angle_deg : float
        Directional error allowed by the first validity criterion.

    Returns
    -------
    (6, res, res, 3) float64
        One ray per texel centre (no texel averaging where an object is hit).
    """
    from prtlab.reference import radiance_at

    if not isinstance(exterior, Scene):
        raise TypeError(f"exterior must be a prtlab.Scene, got {type(exterior).__name__}")
    if exterior.environment is None:
        raise ValueError("the exterior scene needs an environment light (the sky behind the exterior objects)")
    rng = np.random.default_rng() if rng is None else rng
    cube = shell_light(exterior.environment, res)
    solid = [o for o in exterior.objects if not o.portal]
    if not solid:
        return cube
    dirs = cubemap_directions(res).reshape(-1, 3)
    caster = RayCaster(exterior)
    hits = caster.closest_hit(np.broadcast_to(portal.center, dirs.shape), dirs)
    if np.any(hits.hit):
        check_shell_distance(portal.size, float(hits.distance[hits.hit].min()), max_angle_deg)
    flat = cube.reshape(-1, 3)
    for k in np.unique(hits.object[hits.hit]):
        sel = np.nonzero(hits.hit & (hits.object == k))[0]
        obj = exterior.objects[caster.object_index[k]]
        normal = hits.normal[sel]
        normal = np.where((np.sum(normal * dirs[sel], axis=-1) > 0)[:, None], -normal, normal)  # toward the centre
        est = radiance_at(exterior, hits.point[sel], normal, -dirs[sel], n_samples, rng, material=obj.material,
                          bounces=bounces)
        flat[sel] = est.total
    return flat.reshape(cube.shape)
