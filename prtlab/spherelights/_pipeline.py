"""The spherical-lights pipeline as a :class:`prtlab.pipeline.Precomputation` (Guerrero et al. 2008).

Precomputation (Sec. 4), per *source* object (a closed mesh once coincident
vertices are merged; open meshes such as ground planes and walls carry no
spherical lights, as in the paper's scenes; a ground, flat and horizontal,
takes part through the option ``ground``, see ``_ground``):

* ``centres, radii`` of a variational bounding sphere set
  (:func:`fit_spheres`, object space);
* ``sample_points, sample_normals, sample_valid`` along the 92 geodesic
  directions (:func:`surface_samples`);
* ``albedo_sh`` per light (:func:`surface_albedo_sh`);
* ``segment_coverage``: per light and sample direction, the part of its disc its segment fills seen from afar
  (:func:`segment_coverage`; an extension, option ``emission_coverage``);
* ``intersect``: pairs of lights of the object that overlap (their mutual
  occlusion is precomputed in the samples, Sec. 6.2);
* ``vertex_light``: the light each vertex of the object's mesh was fitted to
  (the fit's face assignment, carried to the vertices), for soft deformations.

Per frame (Secs. 5-7), with the object transforms of the frame state
(translation, uniform scale, rotation; Sec. 7.1): the sphere centres,
radii and samples move with their object; the lights' SH stay in object
space and the receiver direction is rotated into it instead (``w_theta``
rotated by the inverse rotation). Then :func:`first_pass` and
:func:`second_pass`, the grounds shaded first, and at the other receivers the
ground's terms (:func:`ground_light`: the light it hides leaves the direct
irradiance, the light it reflects joins the indirect). With ``ground_shading="rays"`` (default) a
ground's own direct light is found against the objects' meshes by ray casting and its indirect light is
gathered from the objects' shaded radiance after they are shaded (``_groundrays``). The environment is
the only scene light handled (area and point lights raise); local lights are spherical lights with a user
radiance (option ``local_lights``, Sec. 7.3).

Every object may move (the precomputed data are in object space; the
grounds' rectangles are taken per frame): a moved state shades as a
precomputation at the new pose would. The direct and indirect irradiance
are clamped at 0 before the albedo: their order-n SH products (visibility
from the exponentiated log visibility, times the environment) ring below 0
beside a sphere on a ground (down to -0.19 at the ground's vertices beside
the spheres of ``spheres_on_plane_env`` fitted with 8 spheres each), and
the ground's hidden light, found with binary visibility, is subtracted from
a direct term found with the SH visibility.

Soft deformations (Sec. 7.1, ``FrameState.deformations``, or ``shade(..., deformed=)``): each light of a
deformed object turns and moves with the best-fit rotation and the mean
translation of its vertices (:func:`light_motions`): its centre and surface
samples move rigidly with them and its frame (the rotation its ``w_theta``
is turned by) is the object's rotation times that turn, so a rigid motion
given as a deformation is the moved object.

Hierarchies (Sec. 7.3, option ``hierarchy_children``): see ``_hierarchy``;
per receiving object, clusters whose cut is all leaves are shaded by the flat
pass, the others take their direct light from the leaves' shadows-only pass
and their indirect light from their cut, each node's emission scaled by its
reflection ratio.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass
from types import MappingProxyType
from typing import NamedTuple

import numpy as np

from prtlab import sh
from prtlab._tasks import run_ahead
from prtlab._validate import check_bool, check_choice, check_float, check_int
from prtlab.geometry import geodesic_directions
from prtlab.pipeline import FrameState, MemoryNeed, Precomputation, scene_geometry_key_parts
from prtlab.scene import EnvironmentLight, ShadeResult, environment_sh

from ._fit import fit_spheres
from ._ground import (covered_points, covered_texels, fill_covered, fill_covered_vertices, ground_hidden_projection,
                      ground_light, ground_objects, ground_raster, ground_sample_sums, ground_samples,
                      ground_samples_update, ground_texture)
from ._groundrays import (MAX_SPACING, contact_radiance, ground_direct_hits, ground_direct_sums, ground_hits_update,
                          ground_light_hits, ground_light_sums, ground_ray_rule, mesh_blockers, object_size)
from ._hierarchy import (LightHierarchy, build_hierarchy, cluster_samples, per_light_indirect, receiver_clusters,
                         reflection_ratio, select_cut)
from ._meshdirect import (MeshOccluder, fibonacci_directions, inner_spheres, mesh_direct_sums, mesh_direct_visible,
                          mesh_direct_visible_update, mesh_occluder, self_blocked)
from ._nearcaps import (has_near_blocker, near_blocker_direct, near_blocker_sums, near_blocker_visibility,
                        near_blocker_visibility_update)
from ._passes import first_pass, second_pass
from ._reuse import FrameReuse, same_inputs
from ._samples import coverage_weights, segment_coverage, surface_albedo_sh, surface_samples
from ._tables import voronoi_cell_sums

__all__ = ["SphereLightOptions", "SphereLights", "WorldLights", "light_motions", "shade_scene"]


@dataclass(frozen=True)
class SphereLightOptions:
    """Options of the spherical-lights pipeline.

    Attributes
    ----------
    n_spheres : int or dict
        Spheres per source object (or a ``{"object name": n}`` dict, default 8).
    order : int
        SH order of the visibility (the shadows and the exponentiation; the paper: 4).
    emission_order : int
        SH order of the lights' emission (their light intensity distributions, Eqs. 10-11) and of the kernel
        of their average radiance (an extension): default 6; 0 (or anything up to ``order``) is the paper's
        single order. The emission of a light beside a touching neighbour varies faster than order 4 holds (its
        dark contact side), and the error bounces onto every receiver; a higher emission order costs only the
        per-light kernel (``(m + 1)^2`` coefficients), not the exponentials (docs/DECISIONS.md).
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
    fit_resolution : int
        Cells per edge of the interior grid of the sphere fit (:func:`fit_spheres`'s ``grid_resolution``).
    cube_resolution : int
        Face resolution of the albedo cubemaps.
    local_lights : sequence of (centre (3,), radius, radiance (3,))
        Local lights (Sec. 7.3): opaque spheres in world space emitting a
        constant RGB radiance (a run-time choice). Their light is direct light.
    hierarchy_children : int
        Sec. 7.3: 0 (default) shades with every light (the flat pipeline); ``k >= 2`` builds per object a sphere
        hierarchy with parents bounding ``k`` children and shades the indirect light of each receiver cluster
        with its own cut (a run-time choice; see ``_hierarchy``). The direct soft shadows keep the leaves
        (the cheap shadows-only pass), so only the indirect term is approximated.
    cut_threshold : float
        In ``[0, 1)``: a parent joins a cluster's cut when its angular size ``r / (d - R_C)`` from the cluster's
        ball is below this (0: leaves everywhere, the flat result).
    cluster_size : int
        Receivers per cluster: a receiving object of ``V`` vertices gets ``ceil(V / cluster_size)`` clusters
        (k-means on its rest shading points and normals). Each coarse cluster costs one call of the second
        pass, so clusters of a few receivers make the hierarchy slower than the flat pass.
    reflection_ratio : bool
        Scale each cut node's diffuse reflection by its reflection ratio at the cluster centre (Eqs. 25-26).
    ratio_samples : int
        Receivers of a cluster at which the ratio is fitted: 1 is the paper's Eq. 25 at the cluster centre (the
        centre then gets the flat value exactly); ``k > 1`` adds ``k - 1`` farthest-point receivers and takes the
        least-squares best scaling (the paper's wording for ``t``), which is steadier where the centre sees a
        node near its horizon (the measurement behind the default: ``docs/NOTES.md``).
    ground : {"reflects", "blocks", "paper"}
        The scene's grounds (flat, horizontal, receiving-only objects) in light
        transport, an extension (see ``_ground``). ``"reflects"`` (default): a
        ground hides what lies beyond it (the environment below the horizon, a
        local light under it) from the first pass's surface samples and from
        every receiver above it, and its exit radiance reaches them as indirect
        light (its direct light with one bounce, its total with two), blocked
        by the spherical lights in between. ``"blocks"``: it hides but does not
        reflect. ``"paper"``: it neither hides nor reflects, as in the paper
        (Sec. 8: large flat surfaces only receive); objects on a ground are
        then lit from below. No effect in a scene without a ground.
    ground_texels : int
        Where the ground's reflected light is read (``ground="reflects"``): ``k >= 2``
        (default 64) shades a ``k x k`` grid of points over each ground (the direct
        light, a shadows-only pass) and interpolates it bilinearly; 0 interpolates the
        ground's shaded vertices over its mesh (cheaper; a coarse ground mesh blurs
        the dark contact shadows under the objects).
    ground_shading : {"rays", "lights"}
        How a ground itself is shaded (an extension, a run-time choice; no effect with ``ground="paper"``).
        ``"rays"`` (default): its direct light (at its vertices and in the texture it reflects) against the
        objects' meshes by ray casting, and its indirect light gathered along rays from the objects' shaded
        radiance at the mesh hits (see ``_groundrays``); the ground light of the first pass's samples
        (``bounces=2``) stays the second pass's. ``"lights"``: as any receiver, through the spherical lights (the
        paper's second pass), with the sphere proxy's shadow and emission where the object is not. Measured cost (one
        thread): 1.03 times the frame of the fidelity bunny scene (169 ground vertices), 1.32 at full size (1,681;
        the rays grow with the ground's vertices; ``docs/notes/spherelights.md``).
    ground_ray_spacing : float
        With ``ground_shading="rays"``: ``s`` in ``(0, 0.7]`` (default 0.5) casts the rays of a ground only at its
        vertices (and texels) near the objects and interpolates the others bilinearly from the nodes of square
        cells of side at most ``s`` times the distance to the nearest light's sphere, the finest cells twice the
        points' mean spacing (a run-time choice; see ``_groundrays.ground_ray_nodes``); 0 casts at every vertex and
        texel. Measured: the fidelity rows within 0.0012 of 0 (none lost), the interpolated light as close to a fine
        rule as the per-vertex rule's; the benchmark frame (16,800 ground points) 2.0 times faster, the full-size
        ``bunny_spheres_env`` (1,681) 1.28 (one thread; ``docs/notes/spherelights.md``).
    near_blockers : int
        The direct light's blockers taken exactly per receiver (an extension, a run-time choice; see
        ``_nearcaps``): 0 is the paper's ``V_n . T_n`` over every blocker (Sec. 5.1); ``k >= 1`` (default 2)
        takes at each receiver the ``k`` spheres of largest angular radius (at least 10 degrees) out
        of the exponentiated log sum and removes their caps from the lighting-times-cosine exactly
        (``E = V_rest . (T_n - Q)``), and the ground's terms then test those lights unadjusted. Only lights of
        other objects fitted with one sphere are taken (a multi-sphere set's outside volume would shadow exactly
        where the object is not). Applies to the flat second pass and the ground's texture (with
        ``ground_shading="lights"``; the rays' shadows are exact), not to the first
        pass's samples (nor the ground light they receive with ``bounces=2``) nor to a hierarchy's shadows.
        Costs a second direct pass at the receivers with such a blocker (measured: 1.7-1.8 times the per-object
        frame with the ground, 21k receivers; ``docs/notes/spherelights.md``). With ``mesh_blockers`` (default) the
        source objects' receivers take their direct light from the meshes instead, so this option then acts at the
        first pass's samples and the ground's texture only.
    mesh_blockers : bool
        The source objects' direct light against the real meshes (an extension, a run-time choice; see
        ``_meshdirect``): the closed-form unshadowed irradiance less the environment along the rays (1,024
        directions of a spherical Fibonacci set) that meet the receiver's own mesh, another object's mesh, a ground
        or a local light; the ground's hidden light is then not subtracted again. The own mesh's rays are cast once
        per object in object space (kept for every rigid pose; a deformed object's per frame against its deformed
        mesh), another object's in its space along the rays meeting its lights' spheres (a deformed one: a ball
        around its vertices). Replaces ``near_blockers`` and the paper's ``V_n . T_n`` at those receivers (not at
        the first pass's samples nor at the grounds, nor at receivers of objects without lights); the indirect
        light does not change. Default True (False: the spheres, as the options above say). Measured: the fidelity
        bunny scene's direct light 0.098 / 0.061 / 0.072 -> 0.020 / 0.012 / 0.016 (bunny, green, orange), at 1.21
        times the frame of the full-size ``bunny_spheres_env`` (one thread; ``docs/notes/spherelights.md``).
    emission_coverage : bool
        The lights' emission toward other objects scaled by their segments' projected coverage (an extension, a
        run-time choice; :func:`segment_coverage`, :func:`coverage_weights`): a light of the paper emits its
        segment's radiance over its whole sphere, so a sphere set bounding a thin object (a bunny's ears, the fit's
        outside volume) lights its neighbours as the fatter spheres would. Default True: the lights send the
        segments' projected area instead; a receiver's own object's lights keep the paper's emission (its
        near field). Measured: the fidelity bunny scene's green ball indirect 0.212 -> 0.062, at 1.05 times the
        frame of the full-size ``bunny_spheres_env`` (one thread; ``docs/notes/spherelights.md``).
    """

    n_spheres: int | dict = 8
    order: int = 4
    emission_order: int = 6
    exp_method: str = "hyb"
    blocking: str = "object"
    average: str = "cosine"
    n_directions: int = 92
    fit_resolution: int = 40
    cube_resolution: int = 16
    ground: str = "reflects"
    ground_texels: int = 64
    ground_shading: str = "rays"
    ground_ray_spacing: float = 0.5
    near_blockers: int = 2
    mesh_blockers: bool = True
    emission_coverage: bool = True
    local_lights: tuple = ()
    hierarchy_children: int = 0
    cut_threshold: float = 0.25
    cluster_size: int = 128
    reflection_ratio: bool = True
    ratio_samples: int = 5

    def __post_init__(self):
        _check_n_spheres(self.n_spheres)
        check_int(self.order, "option order", 1, 8)
        check_int(self.emission_order, "option emission_order", 0, 8, meaning="0: the visibility's order")
        check_choice(self.exp_method, "option exp_method", ("hyb", "ol", "exact"))
        check_choice(self.blocking, "option blocking", ("object", "sphere"))
        check_choice(self.average, "option average", ("cosine", "paper"))
        check_int(self.n_directions, "option n_directions", 12, meaning="a geodesic sphere's 10 f^2 + 2 vertices")
        f = int(round(math.sqrt((self.n_directions - 2) / 10.0)))
        if 10 * f * f + 2 != self.n_directions:
            raise ValueError(f"option n_directions must be the vertex count 10 f^2 + 2 of a geodesic sphere "
                             f"(12, 42, 92, 162, ...), got {self.n_directions!r}")
        check_int(self.fit_resolution, "option fit_resolution", 4, meaning="cells per edge of the sphere fit's grid")
        check_int(self.cube_resolution, "option cube_resolution", 1)
        check_choice(self.ground, "option ground", ("reflects", "blocks", "paper"))
        check_choice(self.ground_shading, "option ground_shading", ("rays", "lights"))
        check_float(self.ground_ray_spacing, "option ground_ray_spacing", 0.0, MAX_SPACING,
                    meaning="0: every ground vertex cast")
        check_int(self.near_blockers, "option near_blockers", 0, meaning="0: the paper's direct light")
        check_bool(self.mesh_blockers, "option mesh_blockers")
        check_bool(self.emission_coverage, "option emission_coverage")
        if check_int(self.ground_texels, "option ground_texels", 0, meaning="0: the ground's vertices") == 1:
            raise ValueError("option ground_texels must be 0 (the ground's vertices) or an int >= 2, got 1")
        object.__setattr__(self, "local_lights", _check_local_lights(self.local_lights))
        if check_int(self.hierarchy_children, "option hierarchy_children", 0) == 1:
            raise ValueError("option hierarchy_children must be 0 (no hierarchy) or an int >= 2, got 1")
        check_float(self.cut_threshold, "option cut_threshold", 0.0, 1.0, max_open=True,
                    meaning="0: leaves everywhere")
        check_int(self.cluster_size, "option cluster_size", 1, meaning="receivers per cluster")
        check_int(self.ratio_samples, "option ratio_samples", 1, meaning="1: the cluster centre, Eq. 25")
        check_bool(self.reflection_ratio, "option reflection_ratio")

    @property
    def light_order(self) -> int:
        """The SH order of the lights' emission: ``max(order, emission_order)``."""
        return max(self.order, self.emission_order)


#: The paper's method as options: every extension of this package that changes the result turned off. The
#: lights' emission at the visibility's order with the paper's average radiance (Eqs. 15-18), grounds that neither
#: hide nor reflect (Sec. 8: large flat surfaces only receive), every blocker in the SH product ``V_n . T_n``
#: (Sec. 5.1), the spheres (not the meshes) for the objects' direct light, a light's emission over its whole
#: sphere, and a hierarchy's reflection ratio fitted at the cluster centre alone (Eq. 25). ``emission_order`` is
#: fixed by the precomputation; the others are run-time choices. ``SphereLights.precompute(scene, {**options,
#: **PAPER_OPTIONS})`` shades as the paper does; the fidelity tier's "paper's method" cases use it.
PAPER_OPTIONS = MappingProxyType({"emission_order": 0, "average": "paper", "ground": "paper", "near_blockers": 0,
                                  "mesh_blockers": False, "emission_coverage": False, "ratio_samples": 1})


def _check_n_spheres(n_spheres) -> None:
    """``n_spheres``: an int >= 1, or a dict of them by object name."""
    if isinstance(n_spheres, dict):
        for name, n in n_spheres.items():
            if not isinstance(name, str):
                raise TypeError(f"option n_spheres must map object names (str) to ints >= 1, got key {name!r}")
            check_int(n, f"option n_spheres[{name!r}]", 1, meaning="spheres of the object")
    else:
        check_int(n_spheres, "option n_spheres", 1, meaning="spheres per object, or a dict of them by object name")


def _check_local_lights(lights) -> tuple:
    """``local_lights`` as a tuple of ``(centre tuple(3), radius float, radiance tuple(3))``."""
    msg = ("option local_lights must be a sequence of (centre (3,), radius > 0, radiance RGB (3,) >= 0) with "
           "finite values, e.g. [((0, 2, 0), 0.3, (5, 5, 5))]")
    if isinstance(lights, (str, bytes, dict)) or not hasattr(lights, "__iter__"):
        raise TypeError(f"{msg}; got {lights!r}")
    out = []
    for item in lights:
        try:
            centre, radius, radiance = item
            centre = np.asarray(centre, dtype=np.float64)
            radius = float(radius)
            radiance = np.asarray(radiance, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{msg}; got {item!r}") from None
        if (centre.shape != (3,) or radiance.shape != (3,) or not np.all(np.isfinite(centre))
                or not np.all(np.isfinite(radiance)) or not math.isfinite(radius) or radius <= 0
                or np.any(radiance < 0)):
            raise ValueError(f"{msg}; got {item!r}")
        out.append((tuple(centre.tolist()), radius, tuple(radiance.tolist())))
    return tuple(out)


def _vertex_light(mesh, merged, face_sphere, centres, radii) -> np.ndarray:
    """(V,) the light of each vertex of ``mesh``: the light of a face of the merged mesh at that vertex (the
    fit's assignment); a vertex on no face takes the light it is deepest inside."""
    from scipy.spatial import cKDTree

    per_merged = np.full(len(merged.vertices), -1, dtype=np.int64)
    faces = np.asarray(merged.faces)
    per_merged[faces.reshape(-1)] = np.repeat(np.asarray(face_sphere, dtype=np.int64), 3)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    _, idx = cKDTree(np.asarray(merged.vertices)).query(verts)
    out = per_merged[idx]
    lost = out < 0
    if lost.any():
        depth = np.linalg.norm(verts[lost, None] - centres[None], axis=2) - radii[None]
        out[lost] = np.argmin(depth, axis=1)
    return out


def _closed_mesh(mesh):
    """The mesh with coincident vertices merged (built-in boxes split their corners per side), or None if
    it is not closed: only closed objects carry spherical lights."""
    import trimesh

    merged = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=True)
    merged.merge_vertices()
    return merged if merged.is_watertight else None


class WorldLights(NamedTuple):
    """The spherical lights of one frame in world space (S lights, m surface samples each)."""

    centres: np.ndarray  # (S, 3)
    radii: np.ndarray  # (S,)
    object_index: np.ndarray  # (S,) int: the source object of each light
    intersect: np.ndarray  # (S, S) bool: overlapping lights of one object
    rotations: np.ndarray  # (S, 3, 3): each light's frame (its object's rotation, turned by a deformation)
    sample_points: np.ndarray  # (S, m, 3)
    sample_normals: np.ndarray  # (S, m, 3)
    sample_valid: np.ndarray  # (S, m) bool
    albedo_sh: np.ndarray  # (S, n*n, 3)


class _FrameLights(NamedTuple):
    """Every light of a frame as the second pass takes them: the spherical lights, then the local ones."""

    centres: np.ndarray  # (S + L, 3)
    radii: np.ndarray  # (S + L,)
    object_index: np.ndarray  # (S + L,) int
    intersect: np.ndarray  # (S + L, S + L) bool
    rotations: np.ndarray  # (S + L, 3, 3)
    env: np.ndarray  # (N*N, 3) environment SH
    local_only: np.ndarray  # (S + L, n*n, 3): the local lights' emission, 0 for the spherical lights
    local_radiance: np.ndarray  # (S + L, 3): a local light's radiance, NaN for a spherical light
    n_sl: int
    n_loc: int


#: The rays of ``ground_shading="rays"`` (``_groundrays``): at a ground's vertices (its direct and gathered light)
#: 64 azimuths x 16 nodes, at the texels of the light it reflects 32 x 8 (docs/notes/spherelights.md).
_GROUND_RAYS = ground_ray_rule(64, 16)
_TEXEL_RAYS = ground_ray_rule(32, 8)

#: Options that do not change the precomputed data (left out of the cache key).
_RUN_TIME = ("exp_method", "blocking", "average", "local_lights", "hierarchy_children", "cut_threshold",
             "cluster_size", "reflection_ratio", "ratio_samples", "ground",
             "ground_texels", "ground_shading", "ground_ray_spacing", "near_blockers", "mesh_blockers",
             "emission_coverage")


class SphereLights(Precomputation):
    """Guerrero et al. 2008: soft shadows and one-bounce diffuse indirect light from spherical lights; with a ground
    taking part (option ``ground``), ``bounces=2`` adds the paths through it (object -> ground -> object, ground ->
    object -> ground); light between objects stays one bounce."""

    method = "spherelights"
    format_version = 3
    max_bounces = 2
    options_type = SphereLightOptions
    renamed_options = {"grid_resolution": "fit_resolution", "occluding_ground": "ground"}
    supports_deformations = True
    _RASTER = 128  # texels per edge of a ground's radiance texture (see ``_ground``)

    @classmethod
    def check_lights(cls, lights, options) -> None:
        """Environment lights only (local lights are the option ``local_lights``)."""
        for light in lights:
            if not isinstance(light, EnvironmentLight):
                raise ValueError(
                    f"method 'spherelights' handles environment lighting only, got a {type(light).__name__}; "
                    "remove area/point lights (a spherical emitter can be given as the option local_lights) or use "
                    "method='reference'"
                )

    @classmethod
    def memory_needs(cls, scene, options):
        """The interior grid of the sphere fit, its face-to-sphere distances, the surface samples, the albedo
        cubemaps, and per frame the receivers-by-lights SH products."""
        n_s, n_faces, n_v = [], 0, 0
        for obj in scene.objects:
            n_v += obj.n_vertices
            if obj.portal:
                continue
            n = options.n_spheres.get(obj.name, 8) if isinstance(options.n_spheres, dict) else options.n_spheres
            n_s.append(min(int(n), len(obj.mesh.faces)))
            n_faces = max(n_faces, len(obj.mesh.faces))
        s_total = float(sum(n_s))
        n2 = options.order**2
        needs = [
            MemoryNeed("the interior grid of the sphere fit", 4.0 * 8 * 3 * options.fit_resolution**3,
                       ("fit_resolution",)),
            MemoryNeed("the sphere fit's distances", 2.0 * 8 * n_faces * max(n_s or [0]), ("n_spheres",)),
            MemoryNeed("the surface samples", 10.0 * 8 * s_total * options.n_directions, ("n_directions", "n_spheres")),
            MemoryNeed("the albedo cubemaps", 4.0 * 8 * 3 * max(n_s or [0]) * 6 * options.cube_resolution**2,
                       ("cube_resolution", "n_spheres")),
            MemoryNeed("the per-frame SH products", 4.0 * 8 * n_v * s_total * n2, ("n_spheres", "order")),
        ]
        return needs, f"{n_v:,} vertices and {int(s_total):,} spheres"

    @classmethod
    def check_scene(cls, scene, options) -> None:
        """A ``n_spheres`` dict names objects of the scene; then the memory check."""
        if isinstance(options.n_spheres, dict):
            names = [o.name for o in scene.objects]
            unknown = sorted(set(options.n_spheres) - set(names))
            if unknown:
                raise ValueError(f"option n_spheres names unknown object(s) {unknown}; objects: {names}")
        super().check_scene(scene, options)

    @classmethod
    def cache_key_parts(cls, scene, options):
        """The run-time choices (``_RUN_TIME``) are left out: they do not change the precomputed data."""
        opts = {k: v for k, v in dataclasses.asdict(options).items() if k not in _RUN_TIME}
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
            n = min(n, len(mesh.faces))
            fit = fit_spheres(mesh, n, grid_resolution=options.fit_resolution)
            pts, nrm, valid = surface_samples(mesh, fit.centres, fit.radii, dirs)
            albedo = surface_albedo_sh(mesh, fit.centres, fit.radii, obj.material.diffuse_albedo, options.light_order,
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
                "segment_coverage": segment_coverage(mesh, fit.centres, fit.radii, dirs),
                "intersect": inter,
                "outside_volume": np.array(fit.outside_volume),
                "coverage": np.array(fit.coverage),
                "vertex_light": _vertex_light(obj.mesh, mesh, fit.face_sphere, fit.centres, fit.radii),
            }
        return {"objects": objects}

    # ------------------------------------------------------------------ per frame

    def world_lights(self, state: FrameState, deformed=None) -> WorldLights:
        """World-space lights of a frame (:class:`WorldLights`).
        ``deformed``: ``{name: (V, 3)}`` object-space vertex positions; each light of such an object
        (centre, samples and its frame) follows the average rotation and translation of its vertices
        (:func:`light_motions`, Sec. 7.1)."""
        parts = []
        deformed = deformed or {}
        for k, (name, data) in enumerate(sorted(self.data["objects"].items())):
            tr = state.transforms.get(name) or self.scene.object(name).transform
            rot = np.asarray(tr.rotation)
            s = len(data["radii"])
            centres = np.asarray(data["centres"], dtype=np.float64)
            samples = np.asarray(data["sample_points"], dtype=np.float64)
            normals = np.asarray(data["sample_normals"], dtype=np.float64)
            rots = np.broadcast_to(rot, (s, 3, 3))
            if name in deformed:
                turn, rest_mean, moved_mean = light_motions(deformed[name], self.scene.object(name).mesh.vertices,
                                                            np.asarray(data["vertex_light"]), s)
                centres = np.einsum("sij,sj->si", turn, centres - rest_mean) + moved_mean
                samples = np.einsum("sij,smj->smi", turn, samples - rest_mean[:, None]) + moved_mean[:, None]
                normals = np.einsum("sij,smj->smi", turn, normals)
                rots = np.einsum("ij,sjk->sik", rot, turn)  # the light's frame turns with its vertices (Sec. 7.1)
            parts.append((
                tr.apply_points(centres), np.asarray(data["radii"]) * float(tr.scale), np.full(s, k),
                np.asarray(data["intersect"], dtype=bool), rots,
                tr.apply_points(samples), tr.apply_normals(normals),
                np.asarray(data["sample_valid"], dtype=bool), np.asarray(data["albedo_sh"]),
            ))
        if not parts:
            order = self.options.order
            m = self.options.n_directions
            return WorldLights(np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 0), bool),
                               np.zeros((0, 3, 3)), np.zeros((0, m, 3)), np.zeros((0, m, 3)), np.zeros((0, m), bool),
                               np.zeros((0, self.options.light_order**2, 3)))
        s_total = sum(len(p[1]) for p in parts)
        inter = np.zeros((s_total, s_total), dtype=bool)
        i = 0
        for p in parts:
            s = len(p[1])
            inter[i : i + s, i : i + s] = p[3]
            i += s
        return WorldLights(*(inter if j == 3 else np.concatenate([p[j] for p in parts]) for j in range(9)))

    def _environment(self, state: FrameState) -> np.ndarray:
        """Environment SH of order ``3n - 2``: the transfer ``P_n(L cos)`` is then exact (see
        :func:`environment_transfer`); projections are cached per light object."""
        order = 3 * self.options.order - 2
        env = np.zeros((order * order, 3))
        cache = self.__dict__.setdefault("_env_cache", {})
        for light in state.lights:  # environment lights only (check_lights)
            key = (id(light), order)
            if key not in cache or cache[key][0] is not light:
                cache[key] = (light, environment_sh(light, order))
            env += cache[key][1]
        return env

    def shade(self, state: FrameState | None = None, bounces: int = 1, *, deformed=None) -> ShadeResult:
        """Per-vertex radiance of one frame; ``deformed``: ``{object name: (V, 3) object-space vertex
        positions}`` of softly deformed objects (Sec. 7.1; see the module docstring), a shorthand for
        ``FrameState.deformations``."""
        if deformed is not None:
            if not isinstance(deformed, dict):
                raise TypeError(f"deformed must be a dict {{object name: (V, 3) vertex positions}}, got "
                                f"{type(deformed).__name__}")
            state = dataclasses.replace(state or FrameState.from_scene(self.scene), deformations=deformed)
        return super().shade(state, bounces)

    def _local_lights(self):
        """The option's local lights: centres (L, 3), radii (L,), emission SH (L, m*m, 3) (constant radiance)."""
        ll = self.options.local_lights
        n2 = self.options.light_order ** 2
        centres = np.array([x[0] for x in ll], dtype=np.float64).reshape(-1, 3)
        radii = np.array([x[1] for x in ll], dtype=np.float64).reshape(-1)
        emission = np.zeros((len(ll), n2, 3))
        if ll:
            emission[:, 0] = np.array([x[2] for x in ll]) * math.sqrt(4.0 * math.pi)
        return centres, radii, emission

    def _frame_lights(self, state: FrameState) -> tuple[_FrameLights, WorldLights]:
        """The frame's lights as the second pass takes them (spherical lights, then local ones) and the world
        lights (with their surface samples)."""
        opts = self.options
        world = self.world_lights(state, state.deformations)
        n_sl = len(world.radii)
        # local lights (Sec. 7.3) join as lights of their own objects with a given emission
        l_c, l_r, l_em = self._local_lights()
        n_loc = len(l_r)
        n_obj = int(world.object_index.max()) + 1 if n_sl else 0
        inter = np.zeros((n_sl + n_loc, n_sl + n_loc), dtype=bool)
        inter[:n_sl, :n_sl] = world.intersect
        lights = _FrameLights(
            np.concatenate([world.centres, l_c]), np.concatenate([world.radii, l_r]),
            np.concatenate([world.object_index, n_obj + np.arange(n_loc)]).astype(np.int64), inter,
            np.concatenate([world.rotations, np.broadcast_to(np.eye(3), (n_loc, 3, 3))]), self._environment(state),
            np.concatenate([np.zeros((n_sl, opts.light_order**2, 3)), l_em]),
            np.concatenate([np.full((n_sl, 3), np.nan), l_em[:, 0] / math.sqrt(4.0 * math.pi)]), n_sl, n_loc)
        return lights, world

    def _pass(self, lights: _FrameLights, p, n, emission, indirect: bool):
        """:func:`second_pass` at receivers ``p, n`` with the frame's lights and the options."""
        o = self.options
        return second_pass(p, n, lights.centres, lights.radii, lights.object_index, lights.intersect,
                           lights.rotations, emission, lights.env, blocking=o.blocking, exp_method=o.exp_method,
                           average=o.average, indirect=indirect, order=o.order)

    def _near_eligible(self, lights: _FrameLights, own: int) -> np.ndarray:
        """(S,) the lights the direct light may take exactly (``near_blockers``): those of objects other than the
        receiver's (``own``) fitted with one sphere. A multi-sphere set bounds its object with an outside volume
        whose exact shadow is darker than the object's (measured on the cube of 8 spheres: the cube's indirect
        light 0.149 -> 0.180 through the ground's darker direct light); one sphere fitted to a ball is the ball."""
        obj = lights.object_index
        counts = np.bincount(obj, minlength=int(obj.max()) + 1 if len(obj) else 0)
        return (obj != own) & (counts[obj] == 1)

    def _irradiance(self, lights: _FrameLights, p, n, emission, indirect: bool, own: int = -1, near: bool = True):
        """Direct (environment and local lights) and indirect irradiance at receivers; ``own``: the receivers'
        object index among the lights' objects (-1: none), whose lights are not taken exactly (``near_blockers``)."""
        k = self.options.near_blockers if near else 0  # near=False: the first pass's ground light (see the option)
        direct, ind = self._pass(lights, p, n, emission, indirect)
        if k:  # the environment's direct light with the nearest blockers exact (``_nearcaps``) where they are large
            elig = self._near_eligible(lights, own)
            sel = has_near_blocker(p, n, lights.centres, lights.radii, elig)
            if sel.any():
                direct = direct.copy()
                direct[sel] = near_blocker_direct(p[sel], n[sel], lights.centres, lights.radii, lights.env,
                                                  self.options.order, k, eligible=elig,
                                                  exp_method=self.options.exp_method)
        if lights.n_loc:
            direct = direct + self._pass(lights, p, n, lights.local_only, True)[1]
        return direct, ind

    def _emission(self, lights: _FrameLights, world: WorldLights, rects, ground_below, state) -> np.ndarray:
        """The first pass (Eqs. 3-11): emission ``(S, n*n, 3)`` of the spherical lights, or with
        ``emission_coverage`` ``(2, S, n*n, 3)``: the paper's, then the one weighted by the segments' projected
        coverage (:func:`coverage_weights`). The surface samples also
        receive the local lights (Sec. 7.3) and, given ``ground_below`` (bounces=2), the ground's direct light (the
        paper's, whatever ``ground_shading``: the rays' there measured worse, docs/notes/spherelights.md)."""
        opts = self.options
        spts, snrm, svalid = world.sample_points, world.sample_normals, world.sample_valid
        extra = self._near_samples(lights, spts, snrm, svalid)  # None without near_blockers
        if svalid.any() and (lights.n_loc or ground_below):
            extra = np.zeros(svalid.shape + (3,)) if extra is None else extra
            if lights.n_loc:  # the second pass's computation at the surface samples, local lights only
                extra[svalid] += self._pass(lights, spts[svalid], snrm[svalid], lights.local_only, True)[1]
            if ground_below:  # ground -> object: the ground's direct light reaches the samples
                tex = self._ground_textures(ground_below, lambda p, n, _: self._irradiance(
                    lights, p, n, lights.local_only, False, near=False)[0], state)
                extra[svalid] += ground_light(spts[svalid], snrm[svalid], rects, tex, lights.env, lights.centres,
                                              lights.radii, lights.local_radiance)[1]
        m = opts.light_order
        if world.albedo_sh.shape[1] < m * m:
            raise ValueError(f"the precomputed albedo SH has order {math.isqrt(world.albedo_sh.shape[1])}, below the "
                             f"emission order {m} of the options (emission_order): precompute with these options")
        weight = None
        if opts.emission_coverage:
            dirs = geodesic_directions(opts.n_directions)
            weight = np.concatenate([coverage_weights(data["segment_coverage"], data["sample_valid"], dirs)
                                     for _, data in sorted(self.data["objects"].items())])
            weight = np.stack([np.ones_like(weight), weight])
        return first_pass(spts, snrm, svalid, lights.centres, lights.radii, lights.env,
                          voronoi_cell_sums(m, opts.n_directions), world.albedo_sh[:, : m * m],  # SH nest by order
                          exp_method=opts.exp_method, ground=rects if len(rects) else None, extra_irradiance=extra,
                          order=opts.order, sample_weight=weight,
                          ground_projection=self._ground_projection(lights, spts, snrm, svalid, rects))

    def _ground_projection(self, lights: _FrameLights, spts, snrm, svalid, rects):
        """``(V, P*P)`` :func:`ground_hidden_projection` of the valid surface samples (``P = n + N - 1``, the sky's
        order ``N``), made per object and kept while the object's samples and the grounds stay
        (:attr:`frame_reuse`); None without a ground."""
        if not len(rects) or not svalid.any():
            return None
        n_proj = self.options.order + math.isqrt(lights.env.shape[0]) - 1
        out = np.zeros(svalid.shape + (n_proj * n_proj,))
        obj = lights.object_index[: svalid.shape[0]]
        for own in np.unique(obj):
            mask = np.zeros(svalid.shape, dtype=bool)
            mask[obj == own] = svalid[obj == own]
            p, n = spts[mask], snrm[mask]
            n = n / np.linalg.norm(n, axis=1, keepdims=True)  # as first_pass takes them
            out[mask] = self.frame_reuse.get(("ground_projection", int(own)), (p, n, rects, n_proj),
                                             lambda: ground_hidden_projection(p, n, rects, n_proj))
        return out[svalid]

    def _near_samples(self, lights: _FrameLights, spts, snrm, svalid):
        """``(S, m, 3)`` correction of the surface samples' direct irradiance for ``near_blockers`` (the nearest
        one-sphere lights of other objects as exact caps, less the paper's ``V_n . T_n``), or None. The ground's
        hidden light stays the first pass's (``V_n`` of every blocker times the ground's transfer)."""
        k = self.options.near_blockers
        if not k or not svalid.any():
            return None
        out = np.zeros(svalid.shape + (3,))
        obj = lights.object_index
        for own in np.unique(obj[: svalid.shape[0]]):
            rows = np.nonzero(obj[: svalid.shape[0]] == own)[0]
            mask = np.zeros(svalid.shape, dtype=bool)
            mask[rows] = svalid[rows]
            elig = self._near_eligible(lights, int(own))
            p, n = spts[mask], snrm[mask]
            n = n / np.linalg.norm(n, axis=1, keepdims=True)
            sel = has_near_blocker(p, n, lights.centres, lights.radii, elig)
            if not sel.any():
                continue
            args = (p[sel], n[sel], lights.centres, lights.radii, self.options.order)
            exp_method = self.options.exp_method
            key = (p, n, sel, lights.centres, lights.radii, self.options.order, k, elig, exp_method)
            near, far = self.frame_reuse.get(  # the caps and the visibility: geometry, kept while it stays
                ("near_samples", int(own)), key,
                lambda: tuple(near_blocker_visibility(*args, m, eligible=elig, exp_method=exp_method) for m in (k, 0)),
                near_samples_reuse(key))
            corr = np.zeros((len(p), 3))
            corr[sel] = near_blocker_sums(near, lights.env) - near_blocker_sums(far, lights.env)
            out[mask] = corr
        return out

    def shade_frame(self, state: FrameState, bounces: int) -> ShadeResult:
        """The first pass (the lights' emission, Secs. 5-6) and the second pass per receiving object (Sec. 6), the
        grounds first; at the other receivers the ground's terms (``_ground``). With ``bounces=2`` the ground's
        light also reaches the surface samples and the objects receive the ground's total light. The geometry-only
        results (the grounds' ray hits, the objects' visible rays, ``ground_light``'s samples) are those of the frame
        before when every input they depend on is exactly the same (:attr:`frame_reuse`); kept ones (the objects'
        visible rays, the grounds' ray hits) are updated on a second thread (:func:`prtlab._tasks.run_ahead`, one
        numba thread) while the objects are shaded: the same frame, bit for bit."""
        t_start = time.perf_counter()
        opts = self.options
        lights, world = self._frame_lights(state)
        n_sl = lights.n_sl
        grounds = [] if opts.ground == "paper" else ground_objects(
            [o for o in self.scene.objects if o.name not in self.data["objects"] and not o.portal], state.transforms)
        rects = np.array([row for _, row in grounds]).reshape(-1, 7)
        reflects = opts.ground == "reflects" and bounces > 0 and len(grounds) > 0
        sources = sorted(self.data["objects"])
        reuse = self.frame_reuse
        reuse.start_frame()
        blockers = ground_direct = None
        if opts.ground_shading == "rays" and len(grounds):  # the grounds against the objects' meshes
            blocker_inputs = self._mesh_blocker_inputs(state, lights, sources, rects)
            blockers = reuse.get("mesh_blockers", blocker_inputs, lambda: mesh_blockers(*blocker_inputs))

            def ground_hits(name, pts):  # the closest hits of a ground's rays, kept while the geometry stays
                spacing = opts.ground_ray_spacing
                inputs = (blocker_inputs, pts, _GROUND_RAYS.dirs, _GROUND_RAYS.weights, spacing)
                return reuse.get(("ground_rays", name), inputs,
                                 lambda: ground_light_hits(pts, blockers, _GROUND_RAYS, spacing=spacing),
                                 ground_hits_reuse(inputs, blockers, pts, _GROUND_RAYS, spacing))

            def ground_direct(p, n, name):  # the texels' rule
                inputs = (blocker_inputs, p, _TEXEL_RAYS.dirs, _TEXEL_RAYS.weights, opts.ground_ray_spacing)
                hits = reuse.get(("texel_rays", name), inputs,
                                 lambda: ground_direct_hits(p, blockers, _TEXEL_RAYS, spacing=opts.ground_ray_spacing),
                                 ground_hits_reuse(inputs, blockers, p, _TEXEL_RAYS, opts.ground_ray_spacing))
                e = ground_direct_sums(hits, lights.env, blockers)
                return e + self._pass(lights, p, n, lights.local_only, True)[1] if lights.n_loc else e
        receivers = {}  # world points and normals per object, for the grounds' gathered light
        # geometry kept from the last frame updated on a second thread while the first pass and the objects are
        # shaded here, in the order they are needed: the objects' visible rays (with their sums, the direct light),
        # then the grounds' ray hits; a result made afresh (nothing kept) is made here, on every thread
        ahead = {}  # (kind, name) -> future
        if opts.mesh_blockers:
            for name in sources:
                if reuse.holds(("mesh_direct", name)):
                    obj = self.scene.object(name)
                    receivers[name] = self._receivers(state, obj)
                    ahead["mesh_direct", name] = run_ahead(functools.partial(self._mesh_direct, state, lights, obj,
                                                                             *receivers[name], rects))
        if blockers is not None:
            for obj, _ in grounds:
                if reuse.holds(("ground_rays", obj.name)):
                    receivers[obj.name] = self._receivers(state, obj)
                    ahead["ground_rays", obj.name] = run_ahead(functools.partial(ground_hits, obj.name,
                                                                                 receivers[obj.name][0]))
        try:
            emission = np.zeros((n_sl + lights.n_loc, opts.light_order**2, 3))
            own_emission = None  # with ``emission_coverage``: the paper's emission, for the lights' own object
            if bounces > 0 and n_sl:
                first = self._emission(lights, world, rects, grounds if reflects and bounces > 1 else [], state)
                if opts.emission_coverage:
                    own_emission = emission.copy()
                    own_emission[:n_sl], emission[:n_sl] = first
                else:
                    emission[:n_sl] = first
            t_first = time.perf_counter()
            result = ShadeResult(info={"method": self.method, "bounces": bounces, "n_lights": int(n_sl),
                                       "n_local_lights": int(lights.n_loc), "exp_method": opts.exp_method,
                                       "blocking": opts.blocking, "average": opts.average, "ground": opts.ground,
                                       "ground_shading": opts.ground_shading, "mesh_blockers": opts.mesh_blockers})
            ground_names = [obj.name for obj, _ in grounds]
            order = sorted((o for o in self.scene.objects if not o.portal),  # portals are openings, not surfaces
                           key=lambda o: o.name not in ground_names)  # grounds first: their light reaches the others
            textures = np.zeros((len(grounds), 1, 1, 3))
            if reflects and ground_direct is not None:  # its indirect light (two bounces) stays the second pass's
                textures = self._ground_textures(grounds, lambda p, n, name: ground_direct(p, n, name) + (
                    self._pass(lights, p, n, emission, True)[1] if bounces > 1 and n_sl else 0.0), state)
            elif reflects:  # the ground's exit radiance: its direct light (one bounce) or its total (two)
                textures = self._ground_textures(grounds, lambda p, n, _: sum(
                    self._irradiance(lights, p, n, emission, bounces > 1 and n_sl > 0)), state)
            nodes = None
            local_direct = {}  # the local lights' direct light at the grounds (with rays, the rest is added below)
            for obj in order:
                if obj.name not in receivers:
                    receivers[obj.name] = self._receivers(state, obj)
                pts, nrm = receivers[obj.name]
                own = sorted(self.data["objects"]).index(obj.name) if obj.name in self.data["objects"] else -1
                emission_in = emission
                if own >= 0 and own_emission is not None:  # its own lights with the paper's emission (near field)
                    emission_in = np.where((lights.object_index == own)[:, None, None], own_emission, emission)
                near_used = opts.near_blockers > 0  # the flat pass's direct light takes the nearest lights exactly
                exact = opts.mesh_blockers and own >= 0  # the direct light against the meshes (``_meshdirect``)
                if blockers is not None and obj.name in ground_names:  # the environment's light and the gathered: below
                    direct = self._pass(lights, pts, nrm, lights.local_only, True)[1] if lights.n_loc else 0.0
                    direct, indirect = direct + np.zeros((len(pts), 3)), np.zeros((len(pts), 3))
                    local_direct[obj.name] = direct
                elif opts.hierarchy_children and bounces > 0 and n_sl:
                    near_used = False
                    if nodes is None:
                        nodes = self._hierarchy_nodes(state, state.deformations, lights.centres, lights.radii,
                                                      lights.object_index, lights.rotations)
                    direct, indirect = self._hierarchical_second_pass(obj, pts, nrm, nodes, *lights[:5], emission_in,
                                                                      lights.env)
                    if lights.n_loc:
                        direct = direct + self._pass(lights, pts, nrm, lights.local_only, True)[1]
                elif exact:  # the second pass for the indirect light; the direct light below
                    direct, indirect = self._pass(lights, pts, nrm, emission_in, bounces > 0 and n_sl > 0)
                else:
                    direct, indirect = self._irradiance(lights, pts, nrm, emission_in, bounces > 0 and n_sl > 0, own)
                if exact:
                    direct = (ahead["mesh_direct", obj.name].result() if ("mesh_direct", obj.name) in ahead
                              else self._mesh_direct(state, lights, obj, pts, nrm, rects))
                    if lights.n_loc:
                        direct = direct + self._pass(lights, pts, nrm, lights.local_only, True)[1]
                if obj.name not in ground_names and len(grounds):
                    # the ground hides what lies beyond it and reflects its own light (see ``_ground``)
                    unadjusted = self._near_eligible(lights, own) & near_used
                    args = (pts, nrm, rects, lights.centres, lights.radii, lights.local_radiance)
                    samples = reuse.get(("ground_light", obj.name), args + (unadjusted,),
                                        lambda: ground_samples(*args, unadjusted=unadjusted),
                                        ground_samples_reuse(args + (unadjusted,)))
                    hidden, reflected = ground_sample_sums(samples, textures, lights.env, lights.local_radiance)
                    direct = direct if exact else direct - hidden  # the rays of ``exact`` meet the grounds
                    indirect = indirect + reflected if reflects else indirect
                albedo = np.asarray(obj.material.diffuse_albedo, dtype=np.float64) / math.pi
                # irradiance is never negative: clamp the order-n SH products' ringing (see the module docstring)
                result.direct[obj.name] = np.maximum(direct, 0.0) * albedo
                result.indirect[obj.name] = np.maximum(indirect, 0.0) * albedo
                result.total[obj.name] = result.direct[obj.name] + result.indirect[obj.name]
            if blockers is not None:  # the grounds' direct light and their indirect light from the objects' radiance
                # the rays' offset
                tol = blockers.caster.epsilon * blockers.scale if blockers.caster is not None else 0.0
                radiance = [contact_radiance(*receivers[name], (result.total if bounces > 1 else result.direct)[name],
                                             rects[:, 0], tol) for name in sources]
                for obj, _ in grounds:
                    albedo = np.asarray(obj.material.diffuse_albedo, dtype=np.float64) / math.pi
                    pts = receivers[obj.name][0]
                    hits = (ahead["ground_rays", obj.name].result() if ("ground_rays", obj.name) in ahead
                            else ground_hits(obj.name, pts))
                    e_dir, e_ind = ground_light_sums(hits, lights.env, blockers, radiance)
                    if not (bounces > 0 and n_sl):
                        e_ind = np.zeros_like(e_ind)
                    result.direct[obj.name] = np.maximum(local_direct[obj.name] + e_dir, 0.0) * albedo
                    result.indirect[obj.name] = np.maximum(e_ind, 0.0) * albedo
                    result.total[obj.name] = result.direct[obj.name] + result.indirect[obj.name]
        finally:  # no task of this frame runs on after it
            futures_wait(list(ahead.values()))
        result.info["timings"] = {"first_pass": t_first - t_start, "second_pass": time.perf_counter() - t_first}
        result.info["geometry"] = reuse.end_frame()
        return result

    @staticmethod
    def _receivers(state: FrameState, obj) -> tuple[np.ndarray, np.ndarray]:
        """An object's receiver points and normals at the frame's pose (world space; deformed as the frame says)."""
        tr = state.transforms.get(obj.name) or obj.transform
        if obj.name in state.deformations:
            return _deformed_receivers(obj, state.deformations[obj.name], tr)
        return obj.world_shading_points(tr), obj.world_normals(tr)

    @property
    def frame_reuse(self) -> FrameReuse:
        """The geometry-only results of the last frame (the grounds' ray hits, the objects' visible rays and
        ``ground_light``'s samples), each reused by the next frame only while every input it was computed from is
        exactly the same (``_reuse``); a frame's ``info["geometry"]`` names the results it computed and those it
        reused. ``frame_reuse.clear()`` frees them."""
        return self.__dict__.setdefault("_frame_reuse", FrameReuse())

    def _mesh_blocker_inputs(self, state: FrameState, lights: _FrameLights, sources, rects) -> tuple:
        """The arguments of :func:`mesh_blockers` for the frame: the objects' meshes at the frame's pose (``sources``:
        their names, in this order; in the frame of the first ground of ``rects``), their lights as
        bounding spheres (a deformed object, which may leave its lights: one ball around its vertices) and the
        local lights as opaque spheres (``_groundrays.MeshBlockers``)."""
        meshes, bounds, size = [], [], 0.0
        spheres = np.concatenate([lights.centres, lights.radii[:, None]], axis=1)
        for g, name in enumerate(sources):
            obj = self.scene.object(name)
            tr = state.transforms.get(name) or obj.transform
            local = state.deformations[name] if name in state.deformations else obj.mesh.vertices
            size = max(size, object_size(local, tr.scale))
            if name in state.deformations:
                verts = tr.apply_points(np.asarray(state.deformations[name], dtype=np.float64))
                centre = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
                bounds.append(np.append(centre, 1.000001 * np.linalg.norm(verts - centre, axis=1).max())[None])
            else:
                verts = obj.world_vertices(tr)
                bounds.append(spheres[: lights.n_sl][lights.object_index[: lights.n_sl] == g])
            meshes.append((np.asarray(verts, dtype=np.float64), np.asarray(obj.mesh.faces)))
        ground = rects[0]  # the rays in the first ground's frame (its centre, edge u and half length)
        return (meshes, np.concatenate(bounds or [np.zeros((0, 4))]), spheres[lights.n_sl:],
                np.array([ground[1], ground[0], ground[2]]), math.atan2(ground[4], ground[3]),
                math.hypot(ground[3], ground[4]), size)

    #: Directions of the rays of ``mesh_blockers`` (``_meshdirect``; docs/notes/spherelights.md).
    _MESH_DIRECTIONS = 1024

    def _mesh_visible(self, state: FrameState, lights: _FrameLights, obj, pts, nrm, rects) -> tuple:
        """``(visible, rotation, directions)``: the visible rays (``_meshdirect.mesh_direct_visible``) of the
        receivers ``pts, nrm`` of the source object ``obj``, every object's mesh, the grounds ``rects`` and the local
        lights blocking (``mesh_blockers``), along ``directions`` turned by ``rotation``; reused from the last frame
        (:attr:`frame_reuse`) while all their inputs are the same, updated where only other objects moved."""
        dirs = fibonacci_directions(self._MESH_DIRECTIONS)
        sources = sorted(self.data["objects"])
        tr = state.transforms.get(obj.name) or obj.transform
        rot = np.asarray(tr.rotation, dtype=np.float64)
        faces = np.asarray(obj.mesh.faces)
        cache = self.__dict__.setdefault("_mesh_direct_cache", {})
        reuse = self.frame_reuse
        if obj.name in state.deformations:  # its own rays at the deformed mesh, every frame, in the frame turned
            # by the best-fit rotation of its vertices (Sec. 7.1): a rigid motion given as a deformation casts the rays
            # of the moved object
            verts = np.asarray(state.deformations[obj.name], dtype=np.float64)
            turn, m0, m1 = light_motions(verts, obj.mesh.vertices, np.zeros(len(verts), dtype=np.int64), 1)
            local = ((pts - tr.translate) @ rot / float(tr.scale) - m1[0]) @ turn[0] + m0[0]
            args = (local, nrm @ rot @ turn[0], (verts - m1[0]) @ turn[0] + m0[0], faces, dirs)
            bits = reuse.get(("self_blocked", obj.name), args, lambda: self_blocked(*args))
            rot = rot @ turn[0]
        else:  # rigid: its own rays in object space, once
            key = ("self", obj.name, len(dirs))
            if key not in cache or cache[key][0] is not obj.mesh:
                from prtlab.scene import Transform

                cache[key] = (obj.mesh, self_blocked(obj.world_shading_points(Transform()), obj.mesh.vertex_normals,
                                                     obj.mesh.vertices, faces, dirs))
            bits = cache[key][1]
        occluders = []  # per other object: the inputs of its MeshOccluder and how to make it
        for g, name in enumerate(sources):
            if name == obj.name:
                continue
            other = self.scene.object(name)
            tr_o = state.transforms.get(name) or other.transform
            rot_o = np.asarray(tr_o.rotation, dtype=np.float64)
            s_o, t_o = float(tr_o.scale), np.asarray(tr_o.translate, dtype=np.float64)
            if name in state.deformations:  # its deformed mesh, in a ball around its vertices
                args = (np.asarray(state.deformations[name], dtype=np.float64), np.asarray(other.mesh.faces), rot_o,
                        s_o, t_o)
                occluders.append((args, functools.partial(mesh_occluder, *args)))
                continue
            key = ("caster", name)
            if key not in cache or cache[key][0] is not other.mesh:  # object space, once: the mesh, inner balls
                closed = _closed_mesh(other.mesh)  # a source object's mesh is closed
                inner = inner_spheres(closed.vertices, closed.faces, self.data["objects"][name]["centres"])
                cache[key] = (other.mesh, mesh_occluder(other.mesh.vertices, other.mesh.faces, inner=inner))
            mine = lights.object_index[: lights.n_sl] == g
            base = cache[key][1]
            args = (base.caster, rot_o, s_o, t_o,
                    np.concatenate([lights.centres[: lights.n_sl][mine], lights.radii[: lights.n_sl][mine, None]],
                                   axis=1),
                    np.concatenate([base.inner[:, :3] @ (s_o * rot_o).T + t_o, s_o * base.inner[:, 3:]], axis=1))
            # the caster is this object's mesh in object space: its vertices and faces stand for it
            occluders.append(((np.asarray(other.mesh.vertices, dtype=np.float64), np.asarray(other.mesh.faces),
                               base.inner) + args[1:], functools.partial(MeshOccluder, *args)))
        balls = np.concatenate([lights.centres[lights.n_sl:], lights.radii[lights.n_sl:, None]], axis=1)
        key = (pts, nrm, rot, bits, [o[0] for o in occluders], rects, balls, dirs)

        def compute():
            made = [make() for _, make in occluders]
            return mesh_direct_visible(pts, nrm, rot, bits, made, rects, balls, dirs), made

        def update(kept_key, kept):  # only some occluders moved: the rays that cannot meet them keep their bits
            if len(kept_key[4]) != len(key[4]) or not same_inputs(kept_key[:4] + kept_key[5:], key[:4] + key[5:]):
                return None
            made = [make() for _, make in occluders]
            moved = [not same_inputs(a, b) for a, b in zip(kept_key[4], key[4])]
            visible, counts = mesh_direct_visible_update(kept[0], kept[1], pts, nrm, rot, bits, made, moved, rects,
                                                         balls, dirs)
            return (visible, made), counts

        visible, _ = reuse.get(("mesh_direct", obj.name), key, compute, update)
        return visible, rot, dirs

    def _mesh_direct(self, state: FrameState, lights: _FrameLights, obj, pts, nrm, rects) -> np.ndarray:
        """The environment's direct light (P, 3) at the receivers ``pts, nrm`` of the source object ``obj`` through
        their visible rays (:meth:`_mesh_visible`)."""
        visible, rot, dirs = self._mesh_visible(state, lights, obj, pts, nrm, rects)
        return mesh_direct_sums(visible, nrm, lights.env, rot, dirs)

    def _ground_textures(self, grounds, irradiance, state: FrameState) -> np.ndarray:
        """``(G, R, R, 3)`` exit radiance over each ground's rectangle from ``irradiance(points, normals, ground's
        name) (P, 3)``:
        with ``ground_texels = k > 0`` at a ``k x k`` grid of points over the rectangle (its texel centres), else at
        the ground's vertices, interpolated over its mesh (rasters cached per ground mesh); then the texels under a
        closed object resting on or sunk into the ground take their uncovered neighbours' light (:meth:`_covered`,
        ``fill_covered``: what a receiver at the object's foot reads across its wall)."""
        k = self.options.ground_texels
        transforms = state.transforms
        out = []
        for obj, row in grounds:
            albedo = np.asarray(obj.material.diffuse_albedo, dtype=np.float64) / math.pi
            if k:
                pts = _rectangle_grid(row, k).reshape(-1, 3)
                e = irradiance(pts, np.broadcast_to([0.0, 1.0, 0.0], pts.shape), obj.name)
                lit = np.maximum(e, 0.0).reshape(k, k, 3) * albedo
                out.append(fill_covered(lit, self._covered(obj, row, k, state)))
                continue
            tr = transforms.get(obj.name) or obj.transform
            e = irradiance(obj.world_shading_points(tr), obj.world_normals(tr), obj.name)
            cache = self.__dict__.setdefault("_raster_cache", {})
            if obj.name not in cache or cache[obj.name][0] is not obj.mesh:
                cache[obj.name] = (obj.mesh, ground_raster(obj.mesh, self._RASTER))
            # the vertices under an object first (their darkness would spread past its wall by the interpolation)
            radiance = fill_covered_vertices(np.maximum(e, 0.0) * albedo, obj.mesh.edges_unique,
                                             self._covered_points(obj.world_vertices(tr), row, state))
            out.append(fill_covered(ground_texture(cache[obj.name][1], radiance),
                                    self._covered(obj, row, self._RASTER, state)))
        return np.ascontiguousarray(np.stack(out))

    def _covered_points(self, points, row, state: FrameState) -> np.ndarray:
        """``(P,)`` bool: the ground ``points`` (on the rectangle ``row``) under a source object at the frame's pose,
        tested as :func:`covered_texels` tests its texel centres."""
        size = 2.0 * max(math.hypot(row[3], row[4]), math.hypot(row[5], row[6]), 1e-300)
        p = np.array(points, dtype=np.float64).reshape(-1, 3)
        p[:, 1] = row[0] + 1e-6 * size
        covered = np.zeros(len(p), dtype=bool)
        for name in sorted(self.data["objects"]):
            verts, faces = self._world_mesh(name, state)
            if len(p) and verts[:, 1].min() <= p[0, 1]:  # else above the ground: it covers nothing
                covered |= covered_points(p, verts, faces)
        return covered

    def _covered(self, ground, row, k: int, state: FrameState) -> np.ndarray:
        """``(k, k)`` bool: the texels of ``ground``'s texture under a source object at the frame's pose (deformed
        as the frame says) resting on or sunk into it (``covered_texels``: inside by the generalised winding number,
        so a closed surface with split vertices counts; an open one covers where it encloses more than half the
        sphere); each object's texels kept in :attr:`frame_reuse` while the rectangle and its world vertices stay."""
        covered = np.zeros((k, k), dtype=bool)
        for name in sorted(self.data["objects"]):
            mesh = self._world_mesh(name, state)
            covered |= self.frame_reuse.get(("covered_texels", ground.name, name), (np.asarray(row), int(k), mesh),
                                            lambda: covered_texels(row, k, [mesh]))
        return covered

    def _world_mesh(self, name: str, state: FrameState) -> tuple[np.ndarray, np.ndarray]:
        """The source object ``name``'s world vertices at the frame's pose (deformed as the frame says) and its
        faces."""
        obj = self.scene.object(name)
        tr = state.transforms.get(name) or obj.transform
        local = state.deformations[name] if name in state.deformations else obj.mesh.vertices
        return tr.apply_points(np.asarray(local, dtype=np.float64)), np.asarray(obj.mesh.faces)

    # ------------------------------------------------------------------ hierarchies (Sec. 7.3)

    def hierarchies(self) -> dict:
        """``{object name: LightHierarchy}`` of the source objects (object space, built once per option)."""
        k = self.options.hierarchy_children
        cache = self.__dict__.setdefault("_hierarchy_cache", {})
        if k not in cache:
            cache[k] = {name: build_hierarchy(data["centres"], data["radii"], k)
                        for name, data in sorted(self.data["objects"].items())}
        return cache[k]

    def _clusters(self, obj):
        """Receiver clusters of an object: labels (V,), medoids (C,) and the ratio points (C, P), from its rest
        shading points (fixed for the object: the same receivers whatever its motion or deformation)."""
        cache = self.__dict__.setdefault("_cluster_cache", {})
        key = (obj.name, self.options.cluster_size, self.options.ratio_samples)
        if key not in cache:
            pts = obj.world_shading_points(obj.transform)
            labels, medoid = receiver_clusters(pts, -(-len(pts) // self.options.cluster_size),
                                               normals=obj.world_normals(obj.transform))
            cache[key] = labels, medoid, cluster_samples(pts, labels, medoid, self.options.ratio_samples)
        return cache[key]

    def _hierarchy_nodes(self, state, deformed, all_c, all_r, all_obj, all_rot):
        """Every node of the scene's light forest in world space, leaves first (the lights of the flat pass, local
        lights as single-leaf trees): centres (N, 3), radii (N,), object (N,), rotation (N, 3, 3), leaf weights
        (N, S) and per tree (LightHierarchy, global index of each node)."""
        S = len(all_r)
        c, r, o, rot, w, trees = [all_c], [all_r], [all_obj], [all_rot], [np.eye(S)], []
        n_next, off = S, 0
        for k, (name, h) in enumerate(self.hierarchies().items()):
            s = h.n_leaves
            tr = state.transforms.get(name) or self.scene.object(name).transform
            n_par = len(h.radii) - s
            gmap = np.concatenate([off + np.arange(s), n_next + np.arange(n_par)])
            par_c = h.centres[s:]
            par_rot = np.broadcast_to(np.asarray(tr.rotation, dtype=np.float64), (n_par, 3, 3))
            if name in deformed and n_par:
                # a parent follows the average rotation and translation of its leaves' vertices (Sec. 7.1)
                rest = np.asarray(self.scene.object(name).mesh.vertices, dtype=np.float64)
                owner = np.asarray(self.data["objects"][name]["vertex_light"])
                par_c, par_rot = par_c.copy(), par_rot.copy()
                for q in range(n_par):
                    mask = np.isin(owner, h.leaves_under(s + q))
                    turn, m0, m1 = light_motions(deformed[name][mask], rest[mask], np.zeros(mask.sum(), int), 1)
                    par_c[q] = turn[0] @ (par_c[q] - m0[0]) + m1[0]
                    par_rot[q] = np.asarray(tr.rotation) @ turn[0]
            c.append(tr.apply_points(par_c))
            r.append(h.radii[s:] * float(tr.scale))
            o.append(np.full(n_par, all_obj[off]))
            rot.append(par_rot)
            par_w = h.weights[s:]
            wk = np.zeros((n_par, S))
            wk[:, off:off + s] = par_w
            w.append(wk)
            trees.append((h, gmap))
            off += s
            n_next += n_par
        for i in range(off, S):  # local lights
            trees.append((LightHierarchy(all_c[i:i + 1], all_r[i:i + 1], ((),), np.ones((1, 1)), (0,)),
                          np.array([i])))
        return (np.concatenate(c), np.concatenate(r), np.concatenate(o).astype(np.int64),
                np.concatenate(rot), np.concatenate(w), trees)

    def _node_emission(self, nodes, cut, emission):
        """(K, n*n, 3) light of the cut's nodes: ``sum_j w_Pj L_j`` (see ``_hierarchy``), each leaf's SH turned
        from its own frame into the node's first."""
        _, _, _, rot, w, _ = nodes
        out = np.empty((len(cut),) + emission.shape[1:])
        for i, k in enumerate(cut):
            leaves = np.nonzero(w[k])[0]
            if len(leaves) == 1 and leaves[0] == k:
                out[i] = emission[k]
                continue
            em = emission[leaves]
            rel = np.einsum("ji,ljk->lik", rot[k], rot[leaves])  # node-from-leaf: R_P^T R_j
            turn = ~np.all(np.abs(rel - np.eye(3)) < 1e-14, axis=(1, 2))
            if turn.any():
                em = em.copy()
                em[turn] = sh.rotate(em[turn], rel[turn], channels=True)
            out[i] = np.einsum("l,lkc->kc", w[k, leaves], em)
        return out

    def _hierarchical_second_pass(self, obj, pts, nrm, nodes, all_c, all_r, all_obj, all_inter, all_rot, emission,
                                  env):
        """Direct and indirect irradiance of one receiving object with a hierarchy cut per receiver cluster and the
        reflection ratio (Sec. 7.3, Eqs. 25-26; see ``_hierarchy``). Clusters whose cut is all leaves are the flat
        pass exactly; the others take their direct light from the leaves (shadows-only pass) and their indirect
        light from their cut."""
        opts = self.options
        kw = dict(blocking=opts.blocking, exp_method=opts.exp_method, average=opts.average, order=opts.order)
        node_c, node_r, node_o, node_rot, node_w, trees = nodes
        S = len(all_r)
        labels, medoid, samples = self._clusters(obj)
        cuts = []
        for k, m in enumerate(medoid):
            radius = float(np.max(np.linalg.norm(pts[labels == k] - pts[m], axis=1)))
            cut = []
            for h, gmap in trees:
                cut.extend(gmap[select_cut(h, node_c[gmap], node_r[gmap], pts[m], radius, opts.cut_threshold)])
            cuts.append(tuple(sorted(int(i) for i in cut)))
        coarse = np.array([max(cut) >= S for cut in cuts], dtype=bool)
        direct, ind = np.zeros((len(pts), 3)), np.zeros((len(pts), 3))
        flat = ~coarse[labels]
        if flat.any():
            direct[flat], ind[flat] = second_pass(pts[flat], nrm[flat], all_c, all_r, all_obj, all_inter, all_rot,
                                                  emission, env, indirect=True, **kw)
        if not coarse.any():
            return direct, ind
        rough = ~flat
        direct[rough], _ = second_pass(pts[rough], nrm[rough], all_c, all_r, all_obj, all_inter, all_rot, emission,
                                       env, indirect=False, **kw)
        coarse_ids = np.nonzero(coarse)[0]
        if opts.reflection_ratio:
            # every leaf's value at the ratio points of the coarse clusters, in one batched evaluation
            samples = samples[coarse_ids]  # (Cc, P)
            P = samples.shape[1]
            flat_values = per_light_indirect(pts[samples.reshape(-1)], nrm[samples.reshape(-1)], all_c, all_r,
                                             all_obj, all_inter, all_rot, emission, env, **kw).reshape(-1, P, S, 3)
        by_cut = {}
        for i, k in enumerate(coarse_ids):
            by_cut.setdefault(cuts[k], []).append((i, k))
        for cut, members in by_cut.items():
            cut = np.array(cut)
            cc, cr, co, crot = node_c[cut], node_r[cut], node_o[cut], node_rot[cut]
            d = np.linalg.norm(cc[:, None] - cc[None], axis=2)
            inter = (d < cr[:, None] + cr[None]) & (co[:, None] == co[None])
            np.fill_diagonal(inter, False)
            leaf = cut < S
            inter[np.ix_(leaf, leaf)] = all_inter[np.ix_(cut[leaf], cut[leaf])]
            em = self._node_emission(nodes, cut, emission)
            if not opts.reflection_ratio:  # one call for every cluster with this cut
                sel = np.isin(labels, [k for _, k in members])
                _, ind[sel] = second_pass(pts[sel], nrm[sel], cc, cr, co, inter, crot, em, env, indirect=True, **kw)
                continue
            rows = [i for i, _ in members]
            at = samples[rows].reshape(-1)
            node_values = per_light_indirect(pts[at], nrm[at], cc, cr, co, inter, crot, em, env, **kw)
            under = (node_w[cut] > 0).astype(np.float64)  # (K, S) leaves under each node
            flat_sums = np.einsum("ks,mpsc->mpkc", under, flat_values[rows])
            t = reflection_ratio(flat_sums, node_values.reshape(len(members), P, len(cut), 3))  # Eq. 25
            for (_, k), tk in zip(members, t):  # Eq. 26: each node's reflection scaled by its ratio
                sel = labels == k
                _, ind[sel] = second_pass(pts[sel], nrm[sel], cc, cr, co, inter, crot, em * tk[:, None, :], env,
                                          indirect=True, **kw)
        return direct, ind


#: Above this fraction of the meshes moved, a ground's rays are all cast again rather than updated
#: (:func:`ground_hits_reuse`): the update's zones then hold most rays, and finding them costs more than it saves
#: (the shipped bunny scene, one thread: every object moving 136 ms updated, 128 ms cast again; two balls of three
#: 110 and 129 ms; the numbers in ``docs/notes/spherelights.md``).
MOVED_FRACTION = 2.0 / 3.0


def ground_hits_reuse(inputs, blockers, points, rule, spacing: float):
    """The ``update`` of :meth:`FrameReuse.get` for a ground's ray hits (``_groundrays.GroundHits``) keyed by
    ``inputs = (mesh_blockers' arguments, *rest)``: when only the meshes' vertices and the bounding spheres differ
    from the kept inputs (the faces, the opaque spheres, the rays' frame and ``rest`` the same), the kept hits of the
    meshes that did not move are kept (``_groundrays.ground_hits_update`` against ``blockers``, made from the new
    arguments); else None (cast afresh)."""

    def update(kept_inputs, kept):
        (old, *old_rest), (new, *new_rest) = kept_inputs, inputs
        if not same_inputs(old_rest, new_rest) or not same_inputs(list(old[2:]), list(new[2:])):
            return None
        if len(old[0]) != len(new[0]) or not all(same_inputs(a[1], b[1]) for a, b in zip(old[0], new[0])):
            return None
        moved = [not same_inputs(a[0], b[0]) for a, b in zip(old[0], new[0])]
        if sum(moved) > MOVED_FRACTION * len(moved):
            return None
        return ground_hits_update(kept, points, blockers, moved, rule, spacing=spacing)

    return update


def ground_samples_reuse(inputs):
    """The ``update`` of :meth:`FrameReuse.get` for ``ground_light``'s samples keyed by ``inputs = (points, normals,
    rectangles, centres, radii, local_radiance, unadjusted)`` (:func:`ground_samples`' arguments): when the
    receivers and the rectangles are the kept ones, the receivers that no changed light can reach keep their samples
    (``_ground.ground_samples_update``); else None (computed afresh)."""

    def update(kept_inputs, kept):
        if not same_inputs(kept_inputs[:3], inputs[:3]):
            return None
        return ground_samples_update(kept, kept_inputs[3:], *inputs[:6], unadjusted=inputs[6])

    return update


def near_samples_reuse(inputs):
    """The ``update`` of :meth:`FrameReuse.get` for the near blockers' caps at receivers (the pair of
    :func:`near_blocker_visibility` with ``n_near`` and 0 blockers at the ``selected`` ones) keyed by ``inputs =
    (points, normals, selected, centres, radii, order, n_near, eligible, exp_method)``: when the receivers, the order,
    ``n_near`` and ``exp_method`` are the kept ones, the selected receivers selected before whose tangent plane every
    changed light lies below keep their rows (``_nearcaps.near_blocker_visibility_update``); else None (computed
    afresh)."""
    points, normals, sel, centres, radii, order, n_near, elig, exp_method = inputs

    def update(kept_inputs, kept):
        k_points, k_normals, k_sel, k_centres, k_radii, *k_rest = kept_inputs
        k_elig = k_rest[2]
        if not same_inputs((k_points, k_normals, k_rest[0], k_rest[1], k_rest[3]),
                           (points, normals, order, n_near, exp_method)):
            return None
        rows = np.full(len(k_sel), -1, dtype=np.int64)
        rows[k_sel] = np.arange(int(k_sel.sum()))
        out, counts = [], None
        for vis, m in zip(kept, (n_near, 0)):
            made = near_blocker_visibility_update(vis, (k_centres, k_radii, k_elig), points[sel], normals[sel], centres,
                                                  radii, order, m, eligible=elig, kept_from=rows[sel],
                                                  exp_method=exp_method)
            if made is None:
                return None
            out.append(made[0])
            counts = made[1]
        return tuple(out), counts

    return update


def _rectangle_grid(row, k: int) -> np.ndarray:
    """``(k, k, 3)`` world points at the cell centres of a ground rectangle (a :func:`ground_rectangles` row)."""
    y0, cx, cz, ux, uz, vx, vz = row
    a = -1.0 + (np.arange(k) + 0.5) * (2.0 / k)
    aa, bb = np.meshgrid(a, a, indexing="ij")
    return np.stack([cx + aa * ux + bb * vx, np.full_like(aa, y0), cz + aa * uz + bb * vz], -1)


def light_motions(verts, rest, vertex_light, n_lights) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average rotation and translation of each light's vertices under a soft deformation (Sec. 7.1).

    Parameters
    ----------
    verts, rest : (V, 3) float
        Deformed and rest vertex positions (object space).
    vertex_light : (V,) int
        The light of each vertex.
    n_lights : int

    Returns
    -------
    rotation : (S, 3, 3) float64
        The best-fit rotation of each light's vertices about their centroids (Kabsch: the proper rotation
        minimising ``sum |R (x - m) - (x' - m')|^2``). A light with fewer than 3 vertices or collinear ones
        (its turn about their line is undetermined) takes the best-fit rotation of all the vertices.
    rest_mean, moved_mean : (S, 3) float64
        Centroids of each light's vertices before and after (of all the vertices for a light without any). A
        point ``q`` of the light moves to ``R (q - m) + m'``: exactly the rigid motion when the deformation is
        rigid.
    """
    x1 = np.asarray(verts, dtype=np.float64)
    x0 = np.asarray(rest, dtype=np.float64)
    lab = np.asarray(vertex_light, dtype=np.int64)
    rotation, m0, m1, ok = _kabsch(x1, x0, lab, n_lights)
    if not ok.all():
        whole, w0, w1, _ = _kabsch(x1, x0, np.zeros(len(lab), dtype=np.int64), 1)
        rotation[~ok] = whole[0]
        empty = np.bincount(lab, minlength=n_lights) == 0
        m0[empty], m1[empty] = w0[0], w1[0]
    return rotation, m0, m1


def _kabsch(x1, x0, lab, n_lights):
    """Per label: best-fit rotation (identity where undetermined), centroids, and whether it was determined."""
    counts = np.bincount(lab, minlength=n_lights)[:, None]
    sums0, sums1 = np.zeros((n_lights, 3)), np.zeros((n_lights, 3))
    np.add.at(sums0, lab, x0)
    np.add.at(sums1, lab, x1)
    m0 = np.where(counts > 0, sums0 / np.maximum(counts, 1), 0.0)
    m1 = np.where(counts > 0, sums1 / np.maximum(counts, 1), 0.0)
    cov = np.zeros((n_lights, 3, 3))  # sum (x0 - m0)(x1 - m1)^T
    np.add.at(cov, lab, np.einsum("vi,vj->vij", x0 - m0[lab], x1 - m1[lab]))
    u, sv, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(np.einsum("sji,skj->sik", vt, u)))
    d = np.where(d == 0, 1.0, d)
    fix = np.ones((n_lights, 3))
    fix[:, 2] = d
    rotation = np.einsum("sji,sj,skj->sik", vt, fix, u)  # V diag(1, 1, d) U^T
    ok = (counts[:, 0] >= 3) & (sv[:, 1] > 1e-9 * np.maximum(sv[:, 0], 1e-300))
    rotation[~ok] = np.eye(3)
    return rotation, m0, m1, ok


def _deformed_receivers(obj, verts, transform):
    """World shading points and normals of an object's deformed mesh (object-space ``verts``)."""
    import trimesh

    from prtlab.geometry import shading_points

    mesh = trimesh.Trimesh(verts, np.asarray(obj.mesh.faces), process=False)
    normals = np.asarray(mesh.vertex_normals)
    local = shading_points(verts, np.asarray(obj.mesh.faces), normals)
    return transform.apply_points(local), transform.apply_normals(normals)


def shade_scene(scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
    """``prtlab.shade(scene, method="spherelights", bounces, **options)``: see :class:`SphereLightOptions`."""
    return SphereLights.shade_scene(scene, bounces=bounces, cache=cache, progress=progress, **options)


def precompute(scene, options=None, cache=True, progress: bool = True) -> SphereLights:
    """``SphereLights.precompute``: the slow, cached phase; then ``.shade(state, bounces)`` per frame."""
    return SphereLights.precompute(scene, options, cache=cache, progress=progress)
