"""The spherical-lights pipeline as a :class:`prtlab.pipeline.Precomputation` (Guerrero et al. 2008).

Precomputation (Sec. 4), per *source* object (a closed mesh once coincident
vertices are merged; open meshes
such as ground planes and walls only receive, as in the paper's scenes, and
neither block nor reflect):

* ``centres, radii`` of a variational bounding sphere set
  (:func:`fit_spheres`, object space);
* ``sample_points, sample_normals, sample_valid`` along the 92 geodesic
  directions (:func:`surface_samples`);
* ``albedo_sh`` per light (:func:`surface_albedo_sh`);
* ``intersect``: pairs of lights of the object that overlap (their mutual
  occlusion is precomputed in the samples, Sec. 6.2).

Per frame (Secs. 5-7), with the object transforms of the frame state
(translation, uniform scale, rotation; Sec. 7.1): the sphere centres,
radii and samples move with their object; the lights' SH stay in object
space and the receiver direction is rotated into it instead (``w_theta``
rotated by the inverse rotation). Then :func:`first_pass` and
:func:`second_pass`. The environment is the only light source handled
(area and point lights raise: local lights as spherical lights with a
user intensity are not implemented). Soft deformations (Sec. 7.1) are not
implemented.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from prtlab.geometry import geodesic_directions
from prtlab.pipeline import FrameState, Precomputation
from prtlab.scene import EnvironmentLight, ShadeResult, environment_sh

from ._fit import fit_spheres
from ._ground import ground_rectangles
from ._passes import first_pass, second_pass
from ._samples import surface_albedo_sh, surface_samples
from ._tables import voronoi_cell_sums

__all__ = ["SphereLightOptions", "SphereLights", "shade_scene"]


@dataclass(frozen=True)
class SphereLightOptions:
    """Options of the spherical-lights pipeline.

    Attributes
    ----------
    n_spheres : int
        Spheres per source object (or a ``{"object name": n}`` dict, default 8).
    order : int
        SH order (the paper: 4).
    exp_method : {"hyb", "ol", "exact"}
        SH exponentiation (a run-time choice; not part of the cache key's precomputed data).
    blocking : {"object", "sphere"}
        Per-object or per-sphere blocking (Sec. 7.2).
    average : {"cosine", "paper"}
        Average radiance of a light at a receiver (a run-time choice): the
        receiver-cosine-weighted average (default) or the paper's Eqs. 15-18
        (see :func:`second_pass`).
    n_directions : int
        Sample directions per light (92).
    grid_resolution : int
        Interior grid of the sphere fit.
    cube_resolution : int
        Face resolution of the albedo cubemaps.
    occluding_ground : bool
        An extension, on by default: the scene's grounds (flat, horizontal,
        receiving-only objects) hide the environment from the surface samples of
        the first pass, as they do in a reference renderer (see ``_ground``). The
        paper's ground neither blocks nor reflects; then objects resting on a
        ground are lit from below in the first pass and their undersides
        over-light the ground. No effect in a scene without a ground.
    """

    n_spheres: int | dict = 8
    order: int = 4
    exp_method: str = "hyb"
    blocking: str = "object"
    average: str = "cosine"
    n_directions: int = 92
    grid_resolution: int = 40
    cube_resolution: int = 16
    occluding_ground: bool = True

    def __post_init__(self):
        if self.exp_method not in ("hyb", "ol", "exact"):
            raise ValueError(f"exp_method must be 'hyb', 'ol' or 'exact', got {self.exp_method!r}")
        if self.average not in ("cosine", "paper"):
            raise ValueError(f"average must be 'cosine' or 'paper', got {self.average!r}")
        if self.blocking not in ("object", "sphere"):
            raise ValueError(f"blocking must be 'object' or 'sphere', got {self.blocking!r}")
        if isinstance(self.order, bool) or not isinstance(self.order, int) or not 1 <= self.order <= 8:
            raise ValueError(f"order must be an int in 1..8, got {self.order!r}")


def _closed_mesh(mesh):
    """The mesh with coincident vertices merged (built-in boxes split their corners per side), or None if
    it is not closed: only closed objects carry spherical lights."""
    import trimesh

    merged = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=True)
    merged.merge_vertices()
    return merged if merged.is_watertight else None


def _is_source(obj) -> bool:
    return not obj.portal and _closed_mesh(obj.mesh) is not None


class SphereLights(Precomputation):
    """Guerrero et al. 2008: soft shadows and one-bounce diffuse indirect light from spherical lights."""

    method = "spherelights"
    format_version = 1
    max_bounces = 1
    options_type = SphereLightOptions

    @classmethod
    def cache_key_parts(cls, scene, options):
        # the run-time choices do not change the precomputed data
        from dataclasses import asdict

        opts = {k: v for k, v in asdict(options).items() if k not in ("exp_method", "blocking", "average")}
        from prtlab.pipeline import scene_geometry_key_parts

        return [cls.method, cls.format_version, scene_geometry_key_parts(scene, dynamic_transforms=False), opts]

    @classmethod
    def compute(cls, scene, options, progress):
        dirs = geodesic_directions(options.n_directions)
        objects = {}
        for obj in scene.objects:
            mesh = None if obj.portal else _closed_mesh(obj.mesh)
            if mesh is None:
                continue
            n = options.n_spheres.get(obj.name, 8) if isinstance(options.n_spheres, dict) else options.n_spheres
            n = min(int(n), len(mesh.faces))
            fit = fit_spheres(mesh, n, grid_resolution=options.grid_resolution)
            pts, nrm, valid = surface_samples(mesh, fit.centres, fit.radii, dirs)
            albedo = surface_albedo_sh(mesh, fit.centres, fit.radii, obj.material.diffuse_albedo, options.order,
                                       options.cube_resolution)
            d = np.linalg.norm(fit.centres[:, None] - fit.centres[None], axis=2)
            inter = d < (fit.radii[:, None] + fit.radii[None])
            np.fill_diagonal(inter, False)
            objects[obj.name] = {
                "centres": fit.centres,
                "radii": fit.radii,
                "sample_points": pts,
                "sample_normals": nrm,
                "sample_valid": valid,
                "albedo_sh": albedo,
                "intersect": inter,
                "outside_volume": np.array(fit.outside_volume),
                "coverage": np.array(fit.coverage),
            }
        return {"objects": objects}

    # ------------------------------------------------------------------ per frame

    def world_lights(self, state: FrameState):
        """World-space lights of a frame: centres (S, 3), radii (S,), object index (S,),
        intersect (S, S), rotations (S, 3, 3), and the samples (S, m, 3) x 2 with validity (S, m)."""
        parts = []
        for k, (name, data) in enumerate(sorted(self.data["objects"].items())):
            tr = state.transforms.get(name) or self.scene.object(name).transform
            rot = np.asarray(tr.rotation)
            s = len(data["radii"])
            parts.append((
                tr.apply_points(data["centres"]), np.asarray(data["radii"]) * float(tr.scale), np.full(s, k),
                np.asarray(data["intersect"], dtype=bool), np.broadcast_to(rot, (s, 3, 3)),
                tr.apply_points(data["sample_points"]), tr.apply_normals(data["sample_normals"]),
                np.asarray(data["sample_valid"], dtype=bool), np.asarray(data["albedo_sh"]),
            ))
        if not parts:
            order = self.options.order
            return (np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 0), bool),
                    np.zeros((0, 3, 3)), np.zeros((0, 92, 3)), np.zeros((0, 92, 3)), np.zeros((0, 92), bool),
                    np.zeros((0, order * order, 3)))
        s_total = sum(len(p[1]) for p in parts)
        inter = np.zeros((s_total, s_total), dtype=bool)
        i = 0
        for p in parts:
            s = len(p[1])
            inter[i : i + s, i : i + s] = p[3]
            i += s
        cat = [inter if j == 3 else np.concatenate([p[j] for p in parts]) for j in range(9)]
        return tuple(cat)

    def _environment(self, state: FrameState) -> np.ndarray:
        """Environment SH of order ``3n - 2``: the transfer ``P_n(L cos)`` is then exact (see
        :func:`environment_transfer`); projections are cached per light object."""
        order = 3 * self.options.order - 2
        env = np.zeros((order * order, 3))
        cache = self.__dict__.setdefault("_env_cache", {})
        for light in state.lights:
            if isinstance(light, EnvironmentLight):
                key = (id(light), order)
                if key not in cache or cache[key][0] is not light:
                    cache[key] = (light, environment_sh(light, order))
                env += cache[key][1]
            else:
                raise ValueError(
                    f"method 'spherelights' handles environment lighting only, got a {type(light).__name__}; "
                    "remove area/point lights or use method='reference'"
                )
        return env

    def shade_frame(self, state: FrameState, bounces: int) -> ShadeResult:
        opts = self.options
        env = self._environment(state)
        centres, radii, sl_object, inter, rot, spts, snrm, svalid, albedo_sh = self.world_lights(state)
        emission = np.zeros((len(radii), opts.order**2, 3))
        if bounces > 0 and len(radii):
            ground = None
            if opts.occluding_ground:
                ground = ground_rectangles([o for o in self.scene.objects if o.name not in self.data["objects"]],
                                           state.transforms)
            emission = first_pass(spts, snrm, svalid, centres, radii, env,
                                  voronoi_cell_sums(opts.order, opts.n_directions), albedo_sh,
                                  exp_method=opts.exp_method, ground=ground)
        result = ShadeResult(info={"method": self.method, "n_lights": int(len(radii)),
                                   "exp_method": opts.exp_method, "blocking": opts.blocking,
                                   "average": opts.average})
        for obj in self.scene.objects:
            tr = state.transforms.get(obj.name) or obj.transform
            pts = obj.world_shading_points(tr)
            nrm = obj.world_normals(tr)
            direct, indirect = second_pass(pts, nrm, centres, radii, sl_object, inter, rot, emission, env,
                                           blocking=opts.blocking, exp_method=opts.exp_method,
                                           average=opts.average, indirect=bounces > 0 and len(radii) > 0)
            albedo = np.asarray(obj.material.diffuse_albedo, dtype=np.float64) / math.pi
            result.direct[obj.name] = direct * albedo
            result.indirect[obj.name] = indirect * albedo
            result.total[obj.name] = result.direct[obj.name] + result.indirect[obj.name]
        return result


def shade_scene(scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
    """``prtlab.shade(scene, method="spherelights", bounces, **options)``: see :class:`SphereLightOptions`."""
    return SphereLights.shade_scene(scene, bounces=bounces, cache=cache, progress=progress, **options)


def precompute(scene, options=None, cache=True, progress: bool = True) -> SphereLights:
    """``SphereLights.precompute``: the slow, cached phase; then ``.shade(state, bounces)`` per frame."""
    return SphereLights.precompute(scene, options, cache=cache, progress=progress)
