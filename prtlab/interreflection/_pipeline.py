"""The Iwasaki et al. 2007 pipeline: precomputation (cached) and the four per-frame steps.

Precomputation, per (non-portal) object, in object space (:meth:`Interreflection.compute`):

* the occlusion field and the vertices' self-visibility (:mod:`prtlab.shadowfields`);
* the PCA basis of its surface intensity, ``N`` functions from ``n_lights`` point
  lights (:func:`prtlab.pca.fit_pca_basis`; lights on a grid for a flat object);
* the basis radiance field ``S_(k,i)`` on its sample spheres (:mod:`._fields`), stored without its zero
  sample points in the format of option ``storage`` (:class:`._fields.StoredBasisRadiance`).

Objects of one mesh and one BRDF's ``g_k``, ``h_k`` (albedo apart) share one stored entry (``same_as``), unless
``pca_occluders`` makes each basis depend on the poses.

Per frame (:meth:`Interreflection.shade_frame`), Fig. 4 of the paper:

1. **direct**: the visibility of every vertex (self-visibility times the other
   objects' occlusion fields, nearest first), the transfer ``P_n(V G_k)`` and the
   direct light ``L_k = < L_in, P_n(V G_k) >`` from the environment and the area
   lights (exactly, :func:`prtlab.shadowfields.area_light_sh`, or from their source
   radiance fields with ``area_lights="field"``);
2. **basis irradiance** (Eq. 13) of every source on every other receiver, with the
   visibility between them (the occluders other than source and receiver);
   a pair is recomputed only when the pose of its source or receiver, or of an
   occluder whose field reaches the receiver, changed since it was last computed
   (:class:`FrameReuse` holds what frames reuse);
3. **weights** (Eq. 14) of every object from its ``L_k``;
4. **bounces** (Eq. 12, Sec. 5.3): ``L_k'^(b) = sum_s Phi^s w^s(b-1)``, radiance
   ``sum_k' h_k' colour_k' L_k'^(b)``, new weights; ``bounces`` times.

``direct`` of the result is step 1's radiance, ``indirect`` the sum over the bounces.
With ``threshold > 0`` a pair whose basis irradiance on a plane at the receiver's
centre, ``I_c`` (:meth:`Interreflection.pair_importance`), is below ``threshold`` is
skipped (Sec. 5.4; counted in ``info["skipped_pairs"]``).

Extensions beyond the paper, each an option (how they were measured: ``docs/NOTES.md``):
``pca_occluders`` (PCA bases trained with the other objects' shadows), ``self_interreflection``,
``near_field`` (ray-cast basis radiance near a source), ``residual_rays`` (the residual gather: per frame,
by ray casting, the part of each source's radiance that its basis misses, so bounced light stays right
when objects move; step 4), ``residual_near`` (its first-bounce hits near the receiver carry the source's
direct light evaluated at the hit, not interpolated from its vertices), ``shadows="haar"`` (all-frequency direct
shadows and point lights, :func:`prtlab.shadowfields.haar_direct`), ``irradiance="haar"``
(all-frequency basis irradiance, :func:`prtlab.interreflection.haar_basis_irradiance`); and
always: Lambertian light clamped at 0 (:meth:`Interreflection._clamp_diffuse`), a flat occluder
with receiver and source on one side of it left out of their visibility
(:meth:`Interreflection._plane_separates`). Vertices are shaded at
:func:`prtlab.geometry.shading_points` (``docs/DECISIONS.md``).

Conventions and limits: vertices are shaded on the side of their normal; a source emits only
from the side of its vertex normals; inter-object visibility takes every object other than
source and receiver as an occluder (also those behind the source); area lights occlude nothing
here (keep them out of the objects' line of sight to each other); point lights need
``shadows="haar"``. An object that encloses a light (a closed room) blocks it everywhere: a
shadow field holds one visibility per point, not per distance; build rooms from separate walls.
"""

from __future__ import annotations

import copy
import time
import dataclasses
import functools
import itertools
from concurrent.futures import wait as futures_wait
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numba
import numpy as np

from prtlab import _tasks, brdf, pca, sh
from prtlab._tasks import concurrent_kernels, run_tasks
from prtlab._validate import check_bool, check_choice, check_float, check_int
from prtlab.geometry import RayCaster, offset_origins, shading_points
from prtlab.pipeline import FrameState, MemoryNeed, Precomputation, check_int_options, scene_geometry_key_parts
from prtlab.scene import AreaLight, EnvironmentLight, PointLight, ShadeResult, environment_sh
from prtlab.sh._gaunt import _gaunt_block
from prtlab.shadowfields import (
    LOG_FLOOR,
    OcclusionField,
    area_light_sh,
    log_occlusion_field,
    occluder_order,
    occlusion_field,
    HaarOcclusionField,
    SparseCubemaps,
    haar_direct,
    haar_occlusion_field,
    haar_self_visibility,
    project_visibility,
    source_radiance_field,
)

from ._fields import (
    STORAGES,
    StoredBasisRadiance,
    basis_radiance_at,
    basis_radiance_field,
    self_basis_irradiance,
    store_basis_radiance,
)
from ._flat import FlatOccluder, halfspace_visibility
from ._horizon import horizon_sums, horizon_weights, sky_cells
from ._haar_fields import HaarBasisRadianceField, haar_basis_radiance_field
from ._haar_passes import haar_basis_irradiance, haar_transfer, near_basis_irradiance
from ._kernels import (PRODUCT_TILE, SERIAL_ITEMS, VISIBILITY_BLOCK, bounce_kernel, masked_product_kernel,
                       masked_product_serial, may_block_kernel, may_block_serial, near_decided_kernel,
                       visibility_product_kernel, visibility_product_serial)
from ._passes import basis_irradiance, fit_weights, outgoing_radiance
from ._direct_rays import (blocker_bounds, light_terms, mirror_wo, object_bound, sample_count,
                          widened_sphere)
from ._residual import (PackedGather, _bounding_radius, _facing, _points_box, _rgb_ready, apply_gather, bounce_rgb,
                        gather_operator, gather_residual, light_outer_kernel, near_hit_correction, near_hits,
                        residual_hits)

__all__ = ["InterreflectionOptions", "Interreflection", "precompute", "shade_scene"]

#: Type of the stacked basis irradiance that :func:`bounce_rgb` reads (``K' = 1`` receivers): float32 halves the
#: bytes of each bounce's product; each value rounded once (relative ``2**-24``) moves a point's ``stacked @ w`` by
#: at most ``2**-24 sum_m |Phi_m w_m|`` (``tests/interreflection/test_residual.py``). The reference tier stays
#: float64.
STACKED_IRRADIANCE = np.float32

#: Whether :meth:`Interreflection.shade_frame` runs step 1 (the direct light) and each receiver's residual-gather
#: casts (:meth:`Interreflection._residual_entry`) on a second Python thread while step 2 (the basis irradiance) runs
#: on the caller's, when an object moved since the scene's ray caster was made (else step 2 and the entries stand):
#: each part's Python work then overlaps the other's parallel kernels. The parts share no state they write, so the
#: frame is the same, bit for bit (test); False runs them one after another, as does numba's ``workqueue`` threading
#: layer (it cannot run kernels from two threads at once: :func:`prtlab._tasks.concurrent_kernels`).
OVERLAP = True


@dataclass
class InterreflectionOptions:
    """Options of the interreflection pipeline (defaults as in the paper, Sec. 6, but for the extensions
    ``self_interreflection``, ``near_field`` and ``residual_rays``: ``docs/notes/interreflection.md``).

    Attributes
    ----------
    order : int
        SH order n of the transfer, visibility and basis radiance (4: 16 coefficients).
    n_basis : int
        PCA basis functions N per object (16).
    n_lights : int
        Point lights of the PCA training renders (256).
    K_glossy : int
        Separable-BRDF terms of Phong materials (Lambert uses 1).
    n_radii, resolution : int
        Sample spheres of the occlusion and basis radiance fields: ``n_radii`` spheres, each a cubemap of
        ``resolution`` texels per face edge (:func:`prtlab.shadowfields.sphere_grid`).
    r_min, r_max : float
        Radii of the innermost and outermost sample spheres, in bounding radii (``r_min <= r_max``).
    spacing : {"geometric", "uniform"}
        Spacing of the sample spheres' radii.
    degree : int or None
        Quadrature degree of the visibility and basis radiance projections (None: 47).
    threshold : float
        Sec. 5.4 skip threshold of source/receiver pairs (0: compute all; a run-time choice).
    pca_occluders : bool
        Train each object's PCA basis with the shadows the other objects cast on it in the scene as given
        (True), or on the object alone as in the paper (False, the default). With True the basis spans the
        shadows of the precomputed poses only, so a moved object's shadow is held only by the residual gather
        (``residual_rays``); with False the precomputation does not depend on the poses and a moved state
        shades exactly as a precomputation at the new pose.
    self_interreflection : bool
        Include the light an object bounces onto itself (True), or only light from the other objects as in the
        paper (False).
    near_field : float
        Receiver points nearer a source's surface than ``near_field`` times their distance to its centre get
        its basis radiance by ray casting (:func:`basis_radiance_at`) instead of the field's interpolation
        (0: always interpolate, as the paper; a run-time choice).
    shadows : {"sh", "haar", "rays"}
        Direct shadows: order-n SH visibility (the paper), all-frequency Haar visibility with point lights
        (:func:`prtlab.shadowfields.haar_direct`), or area and point lights by shadow rays at the frame's poses
        with the environment in SH (:mod:`prtlab.interreflection._direct_rays`; the same precomputation as
        ``"sh"``).
    cube_resolution : int
        Texels per face edge (a power of two) of the Haar visibility and basis radiance cubemaps of
        ``shadows="haar"`` and ``irradiance="haar"``.
    haar_keep : int
        Haar coefficients kept per visibility cubemap of ``shadows="haar"``.
    area_lights : {"exact", "field"}
        SH radiance of an area light at the vertices with ``shadows="sh"``: a quadrature over the light per
        vertex (:func:`prtlab.shadowfields.area_light_sh`), or its source radiance field (Zhou et al. 2005
        Sec. 3; 2-3 % relative error, cheaper when lights move; a run-time choice).
    irradiance : {"sh", "haar"}
        Basis irradiance (Eq. 13): order-n SH basis radiance fields (the paper), or all-frequency sparse Haar
        basis radiance cubemaps times the Haar visibility (:func:`prtlab.interreflection.haar_basis_irradiance`;
        needs ``shadows="haar"``).
    haar_radiance_keep : int
        Haar coefficients kept per (sample point, k, i) basis radiance cubemap of ``irradiance="haar"``.
    residual_rays : int
        Rays per receiver point and source of the residual gather (:mod:`prtlab.interreflection._residual`):
        the part of each source's radiance that its PCA basis misses (a shadow the basis cannot hold) gathered
        per frame by ray casting at the frame's poses (0: off, the paper; a run-time choice). When objects move,
        the rays whose first hit they may change are cast again.
    residual_cone : float
        Solid angle in steradians (times the largest cosine to the normal inside the cone) of a source's bounding
        sphere from which a receiver point casts all ``residual_rays``; a point that sees it smaller casts
        proportionally fewer, at least 4, each weighted by their number, so the gather stays unbiased with fewer
        rays toward far, small sources (0: every point casts ``residual_rays``, the former gather; a run-time
        choice).
    light_samples : int
        Points per vertex on each area light with ``shadows="rays"`` (a jittered grid; a run-time choice).
    light_probe : int
        With ``shadows="rays"``, about this many of a vertex's ``light_samples`` (a sub-grid spread over the light,
        its corners included) are cast first; where their shadow rays all agree (all blocked or all clear) the
        other samples take that answer without rays (the penumbra early-out: biased where a shadow's edge crosses
        the light between them and misses every probe). 0 (or ``light_samples`` and more): every sample cast,
        unbiased. A run-time choice.
    light_exact_lit : bool
        With ``shadows="rays"``, on a receiver whose BRDF and separable form do not depend on the direction (a
        Lambertian one), a vertex some of whose samples of an area light are live and none blocked takes the exact
        unshadowed integral of its cosine over the light (clipped to its horizon; Lambert's polygon formula) in
        place of the samples' estimate: no sampling noise where the light is wholly seen, and no samples drawn
        where that is known beforehand. The near hits of ``residual_near`` keep their samples' estimate (at 2
        samples the integral costs more than the draw). False: the samples' estimate everywhere. A run-time
        choice.
    residual_near : float
        With ``shadows="rays"`` and the residual gather, its first-bounce rays whose hit lies nearer the receiver
        point than ``residual_near`` times the hit triangle's longest edge carry the source's radiance from the
        area and point lights evaluated at the hit (shadow rays from the hit point) instead of its interpolation
        between the source's vertices (:func:`prtlab.interreflection._residual.near_hit_correction`; 0: off,
        every hit interpolated; a run-time choice).
    residual_near_samples : int
        Points on each area light per near hit of ``residual_near`` (a jittered grid; a run-time choice).
    residual_near_probe : bool
        With ``residual_near``: a near hit whose triangle's three vertices agree for a light in the frame's direct
        light (every sample of their shadow masks clear and some lit at each, or every sample blocked at each)
        takes that answer for its own samples without shadow rays, as ``light_probe``'s agreement decides a
        vertex's samples (biased where a shadow's edge crosses the triangle between its vertices and misses
        them); its samples' weights, ``g_k`` and BRDF are still computed. False: every sample cast. A run-time
        choice.
    residual_whole : bool
        With ``residual_near``: at the receiver points with a near hit on a source, gather the source's whole
        radiance by the residual gather's rays (every bounce) in place of its basis irradiance ``Phi w`` plus the
        gathered residual (False: the basis part stays; a run-time choice).
    occlusion : {"product", "exp"}
        How the SH visibilities of a receiver's occluders combine (the direct transfer and Eq. 13): their order-n
        SH products, nearest occluder first (the paper, Sec. 6: products truncated to order n depend on their
        order), or ``exp*`` of the sum of their SH logs (Ren et al. 2006; the paper's future work: any order
        gives the same sum). The logs are those of the occlusion fields' samples
        (:func:`prtlab.shadowfields.log_occlusion_field`, 15-35 s a distinct object at the default field sizes):
        stored by a precomputation made with ``occlusion="exp"`` (a cache entry of its own), computed when the
        pipeline is built from one made without; otherwise a run-time choice.
    exp_method : {"hyb", "ol", "exact"}
        The SH exponential of ``occlusion="exp"`` (:func:`prtlab.sh.exp`; a run-time choice).
    flat_visibility : {"plane", "field"}
        A flat occluder's visibility at points close to its plane (``|h|`` under 0.05 times the distance to its
        footprint's boundary, inside the footprint): the SH of the half-space it hides there
        (``"plane"``, :mod:`prtlab.interreflection._flat`), or its occlusion field's interpolation, which mixes
        the samples of both sides of the plane (``"field"``, the paper). A run-time choice.
    horizon_sky : bool
        With ``flat_visibility="plane"``: at the points that take a half-space, the environment's bands above
        ``order``, which the plane's hard horizon carries into the light, added through the half-spaces and
        ``g_k cos`` exactly (on a quadrature of the map; :mod:`prtlab.interreflection._horizon`); other occluders
        are not counted in them. Off (the paper's bands only): the sides' bottom row of a box resting on a floor
        under a clear sky gets 11 % too little direct light at order 4. A run-time choice.
    storage : {"int16", "float32", "float64"}
        Format of the basis radiance fields, at rest and in memory
        (:func:`prtlab.interreflection._fields.store_basis_radiance`; sample points
        where a field is 0 are not stored in any): per ``(point, k, i)`` block integers times a float32 scale
        (absolute error at most half the block's step, ``max |S| / 65534``), float32, or every float64 value
        as computed (the reference). The other arrays are kept in float64.
    """

    order: int = 4
    n_basis: int = 16
    n_lights: int = 256
    K_glossy: int = 4
    n_radii: int = 16
    resolution: int = 16
    r_min: float = 0.2
    r_max: float = 8.0
    spacing: str = "geometric"
    degree: int | None = None
    threshold: float = 0.0
    pca_occluders: bool = False
    self_interreflection: bool = True
    near_field: float = 0.5
    shadows: str = "rays"
    cube_resolution: int = 32
    haar_keep: int = 512
    area_lights: str = "exact"
    irradiance: str = "sh"
    haar_radiance_keep: int = 64
    residual_rays: int = 64
    residual_cone: float = 0.5
    light_samples: int = 64
    light_probe: int = 16
    light_exact_lit: bool = True
    residual_near: float = 2.0
    residual_near_samples: int = 2
    residual_near_probe: bool = True
    residual_whole: bool = False
    occlusion: str = "product"
    exp_method: str = "hyb"
    flat_visibility: str = "plane"
    horizon_sky: bool = True
    storage: str = "int16"

    def __post_init__(self):
        check_int_options(self, ("order", "n_basis", "n_lights", "K_glossy", "n_radii", "resolution",
                                 "cube_resolution", "haar_keep", "haar_radiance_keep"))
        check_int(self.residual_rays, "option residual_rays", 0, meaning="rays per receiver point, 0: off")
        check_float(self.residual_cone, "option residual_cone", 0.0,
                    meaning="steradians from which a point casts every residual ray, 0: off")
        check_int(self.light_samples, "option light_samples", 1, meaning="points per vertex on an area light")
        check_int(self.light_probe, "option light_probe", 0, meaning="samples per vertex cast first, 0: off")
        check_float(self.residual_near, "option residual_near", 0.0, meaning="in edge lengths, 0: off")
        check_int(self.residual_near_samples, "option residual_near_samples", 1,
                  meaning="points per near hit on an area light")
        check_bool(self.residual_whole, "option residual_whole")
        check_bool(self.light_exact_lit, "option light_exact_lit")
        check_bool(self.residual_near_probe, "option residual_near_probe")
        check_bool(self.horizon_sky, "option horizon_sky")
        check_float(self.r_min, "option r_min", 0.0, min_open=True, meaning="in bounding radii")
        check_float(self.r_max, "option r_max", 0.0, min_open=True, meaning="in bounding radii")
        if self.r_min > self.r_max:
            raise ValueError(f"options r_min and r_max must satisfy r_min <= r_max, got r_min={self.r_min!r} > "
                             f"r_max={self.r_max!r}")
        check_choice(self.spacing, "option spacing", ("geometric", "uniform"))
        if self.degree is not None:
            check_int(self.degree, "option degree", 0, meaning="quadrature degree, or None for 47")
        check_float(self.threshold, "option threshold", 0.0)
        check_float(self.near_field, "option near_field", 0.0)
        check_bool(self.pca_occluders, "option pca_occluders")
        check_bool(self.self_interreflection, "option self_interreflection")
        check_choice(self.shadows, "option shadows", ("sh", "haar", "rays"))
        check_choice(self.irradiance, "option irradiance", ("sh", "haar"))
        check_choice(self.flat_visibility, "option flat_visibility", ("plane", "field"))
        if self.irradiance == "haar" and self.shadows != "haar":
            raise ValueError("option irradiance='haar' needs the Haar visibility of shadows='haar'; pass "
                             "shadows='haar' as well (or irradiance='sh')")
        check_choice(self.area_lights, "option area_lights", ("exact", "field"))
        check_choice(self.occlusion, "option occlusion", ("product", "exp"))
        check_choice(self.exp_method, "option exp_method", ("hyb", "ol", "exact"))
        check_choice(self.storage, "option storage", STORAGES)
        if self.cube_resolution & (self.cube_resolution - 1):
            raise ValueError(f"option cube_resolution must be a power of two (Haar on the faces), got "
                             f"{self.cube_resolution}")


#: The paper's method as options: every extension of this package that changes the result turned off (the
#: always-on ones, the Lambertian clamp and a flat occluder left out where it separates receiver and source,
#: stay). ``pca_occluders`` and ``self_interreflection`` are fixed by the precomputation; the others are run-time
#: choices. ``Interreflection.precompute(scene, {**options, **PAPER_OPTIONS})`` shades as the paper does, and the
#: fidelity tier's "paper's method" cases and the benchmark's frame peers use it.
PAPER_OPTIONS = MappingProxyType({"pca_occluders": False, "self_interreflection": False, "near_field": 0.0,
                                  "shadows": "sh", "area_lights": "field", "residual_rays": 0,
                                  "flat_visibility": "field", "horizon_sky": False, "occlusion": "product",
                                  "irradiance": "sh"})

def _is_flat(mesh) -> bool:
    v = np.asarray(mesh.vertices, float)
    if len(v) < 4:
        return True
    s = np.linalg.svd(v - v.mean(axis=0), compute_uv=False)
    return bool(s[-1] <= 1e-9 * max(s[0], 1e-300))


def _separables(objects, K_glossy: int) -> dict:
    """``{object name: separable BRDF}`` (K = 1 for Lambert), factorised once per distinct material.

    A factorisation (an SVD per azimuthal frequency of a 64 x 128 table) takes 0.1-1 s; objects of one
    material share it.
    """
    by_material: dict = {}
    out = {}
    for obj in objects:
        K = 1 if obj.material.type == "diffuse" else int(K_glossy)
        key = (repr(sorted(obj.material.to_dict().items())), K)
        if key not in by_material:
            by_material[key] = brdf.separable(brdf.from_material(obj.material), K)
        out[obj.name] = by_material[key]
    return out


def _object_space_key(mesh, sep) -> str:
    """A hash of what an object's precomputed arrays depend on (without ``pca_occluders``): its mesh and its
    BRDF's ``g_k``, ``h_k`` (not its colour)."""
    from prtlab.cache import cache_key

    return cache_key(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64),
                     np.asarray(mesh.vertex_normals, np.float64), int(sep.K), str(sep.parameterisation),
                     *(np.asarray(getattr(sep, f), np.float64) for f in (
                         "theta_in", "theta_out", "weights_in", "weights_out", "g_radial", "h_radial", "freq",
                         "parity")))


def _local_shading_points(mesh) -> np.ndarray:
    """Object-space shading points of a mesh (``docs/DECISIONS.md``), placed per frame like the vertices."""
    return shading_points(mesh.vertices, np.asarray(mesh.faces), mesh.vertex_normals)


def _to_object(points, transform) -> np.ndarray:
    """World points to the object space of ``transform`` (``x -> t + R (s x)`` inverted)."""
    return ((np.asarray(points, float) - transform.translate) @ transform.rotation) / float(transform.scale)


def _pca_basis(mesh, n_basis: int, n_lights: int, plane: bool, occluders) -> pca.PCABasis:
    """The PCA basis of Sec. 4.2, trained with the shadows of ``occluders`` (object-space meshes).

    Without occluders it is :func:`prtlab.pca.fit_pca_basis` (the paper). With them, the
    training renders ``B_eta`` (unit point lights at :func:`prtlab.pca.pca_light_positions`)
    are shadowed by the object *and* the other objects at their poses in the scene, so the
    basis spans the shadows they cast on it (a floor under a bunny; measured in ``docs/NOTES.md``).
    The mean, SVD, sign convention and cut are those of :func:`prtlab.pca.fit_pca_basis`
    (:func:`prtlab.pca.principal_basis`).
    """
    v = np.asarray(mesh.vertices, float)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    distance = None
    if not plane and np.mean(np.sum((v - centre) * np.asarray(mesh.vertex_normals), axis=1)) < 0:
        # normals inward (a room): the training lights go inside it, not around it
        distance = 0.8 * 0.5 * float(np.min(v.max(axis=0) - v.min(axis=0)))
    if not occluders and distance is None:
        return pca.fit_pca_basis(mesh, n_basis, n_lights, plane=plane)
    lights = pca.pca_light_positions(mesh, n_lights, distance, plane=plane)
    unshadowed = pca.point_light_intensity(mesh, lights, shadows=False)  # (L, V)
    # shadow rays leave the shading points, where the pipeline and the references shade: a vertex on
    # another object's surface (a floor's row along a wall) is moved off it; from the vertex itself
    # every ray grazes that surface, the row is dark in every training render and the basis is 0 there
    points = _local_shading_points(mesh)
    normals = np.asarray(mesh.vertex_normals, float)
    caster = RayCaster([mesh, *occluders])
    eps = caster.epsilon
    li, vi = np.nonzero(unshadowed > 0)
    visible = np.zeros(unshadowed.shape, bool)
    step = 1 << 21
    for a in range(0, len(li), step):
        lj, vj = li[a:a + step], vi[a:a + step]
        d = lights[lj] - points[vj]
        o = offset_origins(points[vj], normals[vj], d, eps)
        dd = lights[lj] - o
        r = np.linalg.norm(dd, axis=1)
        visible[lj, vj] = ~caster.occluded(o, dd, tmax=np.maximum(r - eps, 0.0))
    training = (unshadowed * visible).T  # (V, L)
    basis, sv, energy = pca.principal_basis(training, n_basis, rank_tol=1e-12)  # rank-deficient: fewer functions
    samples = np.arange(len(points))
    return pca.PCABasis(basis, sv, energy, samples, lights, pca.WeightSolver.from_basis(basis, samples))


class OcclusionFields(Mapping):
    """The occlusion fields (their logs with ``occlusion="exp"``) of the other objects at one receiver's vertices,
    all in one array so that one kernel call takes any of them.

    ``fields`` : (n_occluders, V, n2); ``index`` : occluder name -> its slice; ``self[name]`` is that (V, n2)
    slice, a view: :meth:`Interreflection._occlusion` overwrites it in place when the occluder's pose relative
    to the receiver changes (``poses`` holds the poses each slice was looked up at).
    """

    def __init__(self, names, fields: np.ndarray):
        self.index = {name: i for i, name in enumerate(names)}
        self.fields = fields
        self.poses = [None] * len(self.index)

    @classmethod
    def stacked(cls, fields: Mapping) -> "OcclusionFields":
        """A copy of ``fields`` (name -> (V, n2) arrays of one shape) in one array."""
        names = list(fields)
        return cls(names, np.ascontiguousarray(np.array([fields[name] for name in names], dtype=np.float64)))

    def __getitem__(self, name) -> np.ndarray:
        return self.fields[self.index[name]]

    def __iter__(self):
        return iter(self.index)

    def __len__(self) -> int:
        return len(self.index)


@functools.lru_cache(maxsize=None)
def _gaunt_runs(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(gi, gj, gv, starts)``: the order-``order`` Gaunt entries of ``_gaunt_block`` (sorted by k; a stable
    sort keeps each k's order) and ``starts`` (n2 + 1,), where each k's entries start."""
    gi, gj, gk, gv = _gaunt_block(order, order, order)
    by_k = np.argsort(gk, kind="stable")
    starts = np.searchsorted(gk[by_k], np.arange(order * order + 1)).astype(np.int64)
    return gi[by_k], gj[by_k], gv[by_k], starts


@dataclass
class FrameReuse:
    """What consecutive frames of one :class:`Interreflection` reuse, each entry with the poses it was made at.

    An entry is used again only while the poses (and camera) in its key are those of the new frame; objects that
    did not move keep their geometry, lookups and pairs, and a pair whose occluders moved is updated only at the
    receiver points they may block (:meth:`Interreflection.basis_irradiance_step`).
    """

    #: the last frame's key (poses, camera) and its (geometry, occlusion lookups, direct transfer)
    frame: tuple | None = None
    #: object -> (pose and camera, per-object geometry of :meth:`Interreflection._frame_geometry`)
    geometry: dict = dataclasses.field(default_factory=dict)
    #: receiver -> the other objects' occlusion fields looked up at its points (:class:`OcclusionFields`, with
    #: the poses of each)
    occlusion: dict = dataclasses.field(default_factory=dict)
    #: (receiver, flat occluder) -> (their poses, the receiver's points that take its half-space, each one's side)
    halfspaces: dict = dataclasses.field(default_factory=dict)
    #: receiver -> (poses, P_n(V G_k), the occluders' geometry)
    direct_transfer: dict = dataclasses.field(default_factory=dict)
    #: (receiver, light index) -> (pose and light, SH radiance at the points, transfer, their product)
    area_light_sh: dict = dataclasses.field(default_factory=dict)
    #: source radiance fields of the area light shapes seen so far (``area_lights="field"``)
    source_fields: list = dataclasses.field(default_factory=list)
    #: (receiver, source) -> (poses of receiver, source and occluders, Phi, the occluders' geometry)
    pair_irradiance: dict = dataclasses.field(default_factory=dict)
    #: (poses of every object, Phi of every pair, the counts of a step that reuses them all) of the last
    #: :meth:`Interreflection.basis_irradiance_step`
    irradiance_step: tuple | None = None
    #: a place of :meth:`Interreflection._visibility` (("pair", receiver, source), ("direct", receiver)) -> {the
    #: receiver's pose, the last call's factors (name, poses of its field), prefix: {its first factors, their
    #: product at each receiver row, those rows' masks, where made}} of the kept partial visibility products
    visibility_prefix: dict = dataclasses.field(default_factory=dict)
    #: (receiver, source) -> how many times the pair's Phi was replaced (the stacked irradiance's key)
    revision: dict = dataclasses.field(default_factory=dict)
    #: receiver -> (sources and their revisions, [Phi^s_1 | ... | Phi^self])
    stacked: dict = dataclasses.field(default_factory=dict)
    #: (source, receiver points in its frame) -> (near points, their ray-cast S)
    near_field: dict = dataclasses.field(default_factory=dict)
    #: (receiver, source) -> (poses of every object, {object: whether it may block the pair}, the blockers nearest
    #: first) of :meth:`Interreflection._blockers`
    pair_blockers: dict = dataclasses.field(default_factory=dict)
    #: (plane, receiver, source) -> (poses, whether the plane separates them)
    plane_separates: dict = dataclasses.field(default_factory=dict)
    #: source -> k-d tree of its vertices / ray caster of its mesh (object frame, built on first use)
    vertex_trees: dict = dataclasses.field(default_factory=dict)
    casters: dict = dataclasses.field(default_factory=dict)
    #: receiver -> {poses of every object, its sources, the caster's offsets, the objects' bounding spheres,
    #: {source index: ResidualHits}, {source index: GatherOperator}, and once used their terms packed for
    #: :func:`bounce_rgb` (``packed``, a :class:`PackedGather` passed on from entry to entry)} of the residual gather
    residual_hits: dict = dataclasses.field(default_factory=dict)
    #: (poses of every object, a ray caster of every object at them, their bounding spheres) for the
    #: residual gather
    scene_caster: tuple | None = None
    #: receiver -> {poses of every object, the caster's offsets, light_samples, the objects' bounding spheres,
    #: lights: {light index: {its geometry, camera, S and F at unit emission, per-sample shadow mask}},
    #: light_k: the frame's ``L_k`` (V, K, C) from those lights} of the direct light by rays
    #: (:meth:`Interreflection.direct_step_rays`)
    direct_rays: dict = dataclasses.field(default_factory=dict)
    #: the direct light's shadow rays cast in the last frame (``info["direct_rays_cast"]``)
    direct_counts: dict = dataclasses.field(default_factory=lambda: {"rays_cast": 0})
    #: the residual gather's rays cast in the last frame (``info["residual_rays_cast"]``)
    residual_counts: dict = dataclasses.field(default_factory=lambda: {"rays_cast": 0})
    #: {"key": (poses, sources, lights), "corrections": {receiver: (V, K', C)}} of ``residual_near``
    near_exact: dict = dataclasses.field(default_factory=dict)
    #: (receiver, source index) -> (its ResidualHits, residual_near, their near hits) of ``residual_near``
    near_hits: dict = dataclasses.field(default_factory=dict)
    #: object number left out (or None) -> (poses, caster's offsets, shadow-ray blockers of :func:`blocker_bounds`)
    blockers: dict = dataclasses.field(default_factory=dict)
    #: object number -> (its world vertices array, caster's epsilon, its :func:`object_bound`): a blocker's bound
    #: stands while the caster keeps the object's array (it did not move)
    object_bounds: dict = dataclasses.field(default_factory=dict)
    #: source index -> {lights' geometry, samples, ray offsets, poses, bounding spheres, the near-hit parts
    #: (receiver, near-hit points, their normals), per light (S, F, shadow mask)} of
    #: :meth:`Interreflection._near_exact`
    near_sources: dict = dataclasses.field(default_factory=dict)
    #: (a copy of the environment light, SH order, its SH coefficients) of the direct light by rays
    environment_sh: tuple | None = None
    #: (the environment's SH coefficients, :func:`sky_cells` of it) of ``horizon_sky``
    sky_cells: tuple | None = None
    #: receiver -> {key: the poses of its half-spaces and the cells' grid, groups: their :func:`horizon_weights`,
    #: light: (the environment's SH, the points, their dL)} of ``horizon_sky``
    horizon: dict = dataclasses.field(default_factory=dict)


class Interreflection(Precomputation):
    """Iwasaki et al. 2007: PRT for dynamic scenes with interreflections (module docstring)."""

    method = "interreflection"
    format_version = 4  # 4: basis radiance fields stored sparse, in the format of option ``storage``
    max_bounces = None
    options_type = InterreflectionOptions
    renamed_options = {"haar_resolution": "cube_resolution"}

    @classmethod
    def cache_key_parts(cls, scene, options) -> list:
        """Run-time options are left out; with ``pca_occluders`` every object's pose in the scene is in."""
        # per-frame options: not part of the precomputed data
        run_time = ("threshold", "near_field", "area_lights", "residual_rays", "residual_cone", "light_samples",
                    "light_probe", "light_exact_lit", "residual_near", "residual_near_samples", "residual_near_probe",
                    "residual_whole", "occlusion", "exp_method", "flat_visibility", "horizon_sky")
        if options.irradiance == "sh":  # keys of the SH-irradiance caches made before the option existed
            run_time += ("irradiance", "haar_radiance_keep")
        opts = {k: v for k, v in dataclasses.asdict(options).items() if k not in run_time}
        if options.occlusion == "exp":  # the fields' logs are stored too (the products' keys stay as they were)
            opts["occlusion"] = "exp"
        if opts["shadows"] == "rays":  # precomputes what "sh" does
            opts["shadows"] = "sh"
        parts = [cls.method, cls.format_version, scene_geometry_key_parts(scene), opts]
        if options.pca_occluders:
            parts.append([o.transform.to_dict() for o in scene.objects])
        return parts

    @classmethod
    def check_lights(cls, lights, options) -> None:
        """Point lights need the all-frequency direct shadows (``shadows="haar"`` or ``"rays"``)."""
        if options.shadows == "sh" and any(isinstance(light, PointLight) for light in lights):
            raise ValueError("the interreflection pipeline with shadows='sh' supports environment and area "
                             "lights, not point lights; pass shadows='rays' or 'haar' (or replace the point "
                             "light by a small area light)")

    @classmethod
    def memory_needs(cls, scene, options):
        """Per object: the occlusion and basis radiance fields on the sample spheres, the PCA training
        renders, the visibility projection and the Haar fields (with ``shadows``/``irradiance="haar"``)."""
        objs = [o for o in scene.objects if not o.portal]
        n_v = sum(o.n_vertices for o in objs)
        v_max = max([o.n_vertices for o in objs] or [0])
        k = max([1 if o.material.type == "diffuse" else options.K_glossy for o in objs] or [1])
        n2 = options.order**2
        n_b = options.n_basis
        texels = float(options.n_radii) * 6 * options.resolution**2
        degree = 47 if options.degree is None else options.degree
        quadrature = (degree + 1) ** 2 / 2.0  # directions of a degree-d product rule
        n_o = len(objs)
        needs = [
            MemoryNeed("the occlusion fields", n_o * texels * n2 * 8.0, ("n_radii", "resolution", "order")),
            # one object's dense float64 field (and its projection) while it is computed, every object's stored
            MemoryNeed("the basis radiance fields",
                       texels * n_b * k * n2 * (8.0 * 2 + n_o * {"float64": 8.0, "float32": 4.0}.get(options.storage,
                                                                                                    2.25)),
                       ("n_radii", "resolution", "n_basis", "storage")),
            MemoryNeed("the PCA training renders", 3.0 * 8 * options.n_lights * v_max, ("n_lights",)),
            MemoryNeed("the visibility projection", 2.0 * 8 * v_max * quadrature, ("degree",)),
            MemoryNeed("the self-interreflection", n_v * k * k * n_b * 8.0, ("n_basis", "K_glossy")),
        ]
        if options.shadows == "haar":
            needs.append(MemoryNeed("the Haar occlusion fields", (n_o * texels + n_v) * options.haar_keep * 12.0,
                                    ("haar_keep", "n_radii", "resolution")))
        if options.irradiance == "haar":
            needs.append(MemoryNeed("the Haar basis radiance fields",
                                    n_o * texels * n_b * k * options.haar_radiance_keep * 12.0,
                                    ("haar_radiance_keep", "n_basis", "n_radii")))
        return needs, f"{n_o} objects of {n_v:,} vertices"

    @classmethod
    def compute(cls, scene, options: InterreflectionOptions, progress: bool) -> dict:
        objs = [o for o in scene.objects if not o.portal]
        world = {o.name: o.world_vertices() for o in objs}
        it = objs
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(objs, desc="interreflection precompute", unit="object")
        seps = _separables(objs, options.K_glossy)
        data = {}
        first = {}  # object-space inputs -> index of the first object with them
        for i, obj in enumerate(it):
            if not options.pca_occluders:  # else the basis depends on the other objects' poses
                inputs = _object_space_key(obj.mesh, seps[obj.name])
                if inputs in first:  # the same mesh and BRDF terms (albedo apart): the same arrays, stored once
                    data[obj.name] = {"same_as": np.int64(first[inputs])}
                    continue
                first[inputs] = i
            mesh = obj.mesh
            oof = occlusion_field(mesh, options.order, n_radii=options.n_radii, resolution=options.resolution,
                                  r_min=options.r_min, r_max=options.r_max, spacing=options.spacing,
                                  degree=options.degree)
            points = _local_shading_points(mesh)
            normals = np.asarray(mesh.vertex_normals, float)
            vis = project_visibility(RayCaster([mesh]), points, options.order, normals=normals,
                                     degree=options.degree)
            n_basis = min(options.n_basis, len(mesh.vertices), options.n_lights + 1)
            occluders = [(_to_object(world[o.name], obj.transform), np.asarray(o.mesh.faces))
                         for o in objs if o is not obj] if options.pca_occluders else []
            basis = _pca_basis(mesh, n_basis, options.n_lights, _is_flat(mesh), occluders)
            sep = seps[obj.name]
            field = basis_radiance_field(mesh, basis.basis, sep, oof.grid, options.order, options.degree)
            own = np.zeros((len(points), sep.K, sep.K, basis.n_basis))
            if options.self_interreflection and not _is_flat(mesh):  # a plane sees none of itself
                own = self_basis_irradiance(mesh, basis.basis, sep, points, normals, degree=options.degree)
            stored = store_basis_radiance(field, options.storage)
            del field
            data[obj.name] = {"oof": oof.to_arrays(), "self_visibility": vis, "pca_basis": basis.basis,
                              "pca_samples": np.asarray(basis.samples, np.int32),
                              "basis_radiance": stored.to_arrays(), "self_irradiance": own}
            if options.occlusion == "exp":
                data[obj.name]["log_oof"] = log_occlusion_field(oof).to_arrays()
            if options.shadows == "haar":
                haar = {"resolution": options.cube_resolution, "keep": options.haar_keep}
                data[obj.name]["haar_oof"] = haar_occlusion_field(
                    mesh, n_radii=options.n_radii, grid_resolution=options.resolution, r_min=options.r_min,
                    r_max=options.r_max, spacing=options.spacing, **haar).to_arrays()
                data[obj.name]["haar_self"] = haar_self_visibility(mesh, points=points, normals=normals,
                                                                   **haar).to_arrays()
            if options.irradiance == "haar":
                data[obj.name]["haar_radiance"] = haar_basis_radiance_field(
                    mesh, basis.basis, sep, oof.grid, options.cube_resolution, options.haar_radiance_keep).to_arrays()
        return data

    def __init__(self, scene, options, data):
        super().__init__(scene, options, data)
        self.objects = [o for o in scene.objects if not o.portal]
        #: object -> its precomputed arrays (an object stored ``same_as`` another reads the other's)
        self.entries = {o.name: data[self.objects[int(data[o.name]["same_as"])].name] if "same_as" in data[o.name]
                        else data[o.name] for o in self.objects}
        built: dict = {}

        def shared(kind, o, make):
            """One object per stored entry: objects that share their arrays share what is built from them."""
            key = (kind, id(self.entries[o.name]))
            if key not in built:
                built[key] = make(self.entries[o.name])
            return built[key]

        def pca_basis(d):
            b = np.asarray(d["pca_basis"], float)
            samples = np.asarray(d["pca_samples"], np.int64)
            # the fit's spectrum and training lights are not needed per frame: basis and A^-1 only
            return pca.PCABasis(b, np.zeros(0), np.zeros(len(b)), samples, np.zeros((0, 3)),
                                pca.WeightSolver.from_basis(b, samples))

        self.fields = {o.name: shared("oof", o, lambda d: OcclusionField.from_arrays(d["oof"])) for o in self.objects}
        #: the occlusion fields' SH logs (``occlusion="exp"``), else the fields themselves
        self.occluders = self._log_fields(shared) if options.occlusion == "exp" else self.fields
        self.radiance = {o.name: shared("radiance", o, lambda d: StoredBasisRadiance.from_arrays(d["basis_radiance"]))
                         for o in self.objects}
        self.bases = {o.name: shared("pca", o, pca_basis) for o in self.objects}
        self.seps = _separables(self.objects, options.K_glossy)
        self.local_points = {o.name: _local_shading_points(o.mesh) for o in self.objects}
        self.self_irradiance = {o.name: shared("self", o, lambda d: np.ascontiguousarray(d["self_irradiance"],
                                                                                         dtype=float))
                                for o in self.objects}
        haar = options.shadows == "haar"
        self.haar_fields = {o.name: shared("haar_oof", o, lambda d: HaarOcclusionField.from_arrays(d["haar_oof"]))
                            for o in self.objects} if haar else {}
        self.haar_self = {o.name: shared("haar_self", o, lambda d: SparseCubemaps.from_arrays(d["haar_self"]))
                          for o in self.objects} if haar else {}
        self.haar_radiance = {o.name: shared("haar_radiance", o,
                                             lambda d: HaarBasisRadianceField.from_arrays(d["haar_radiance"]))
                              for o in self.objects} if options.irradiance == "haar" else {}
        self.flat = {o.name: _is_flat(o.mesh) for o in self.objects}
        #: the flat occluders' planes and footprints (``flat_visibility="plane"``)
        self.flat_occluders = {o.name: FlatOccluder(o.mesh.vertices, o.mesh.faces, o.mesh.vertex_normals)
                               for o in self.objects if self.flat[o.name] and options.flat_visibility == "plane"}
        #: a convex mesh's rays leave it (or meet its back): no residual gather from itself
        self.convex = {o.name: bool(getattr(o.mesh, "is_convex", False)) for o in self.objects}
        self.reuse = FrameReuse()

    def _log_fields(self, shared) -> dict:
        """Object -> the SH log of its occlusion field (``occlusion="exp"``): as stored by a precomputation made
        with the option, else computed here, once per stored entry, with a progress bar (15-35 s an object)."""
        missing = {id(self.entries[o.name]) for o in self.objects if "log_oof" not in self.entries[o.name]}
        bar = None
        if missing:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(missing), desc="SH logs of the occlusion fields", unit="object", disable=None)

        def make(o, d):
            if "log_oof" in d:
                return OcclusionField.from_arrays(d["log_oof"])
            field = log_occlusion_field(self.fields[o.name])
            bar.update()
            return field

        logs = {o.name: shared("log_oof", o, lambda d: make(o, d)) for o in self.objects}
        if bar is not None:
            bar.close()
        return logs

    def truncated(self, n_basis: int | None = None, order: int | None = None) -> "Interreflection":
        """The same precomputation with fewer basis functions and/or SH bands, without recomputing.

        SH projections are orthogonal, so the first ``order**2`` coefficients of an order-n
        projection are the lower-order projection; the first ``n_basis`` PCA functions (mean
        first) are the smaller basis, their weights solved with their own ``A^{-1}``. Used for
        error-versus-N and error-versus-order studies.
        """
        n = self.options.n_basis if n_basis is None else check_int(n_basis, "n_basis", 1)
        o = self.options.order if order is None else check_int(order, "order", 1, self.options.order,
                                                                meaning="at most the precomputed order")
        n2 = o * o
        data = {}
        for obj in self.objects:
            if "same_as" in self.data[obj.name]:
                data[obj.name] = self.data[obj.name]
                continue
            d = self.data[obj.name]
            oof = dict(d["oof"])
            oof["coeffs"] = np.asarray(oof["coeffs"])[..., :n2]
            oof["order"] = np.int64(o)
            data[obj.name] = {"oof": oof, "self_visibility": np.asarray(d["self_visibility"])[:, :n2],
                              "pca_basis": np.asarray(d["pca_basis"])[:n], "pca_samples": d["pca_samples"],
                              "basis_radiance": self.radiance[obj.name].truncated(n, o).to_arrays(),
                              "self_irradiance": np.asarray(d["self_irradiance"])[..., :n]}
            for key in ("haar_oof", "haar_self"):  # the all-frequency direct shadows do not depend on n, N
                if key in d:
                    data[obj.name][key] = d[key]
            if "log_oof" in d and o == self.options.order:  # a log's lower bands are not the lower bands' log
                data[obj.name]["log_oof"] = d["log_oof"]
            if "haar_radiance" in d:  # the Haar basis radiance keeps no SH bands: only N is cut
                data[obj.name]["haar_radiance"] = HaarBasisRadianceField.from_arrays(
                    d["haar_radiance"]).truncated(n).to_arrays()
        options = dataclasses.replace(self.options, order=o, n_basis=min(n, self.options.n_basis))
        return type(self)(self.scene, options, data)

    # ------------------------------------------------------------------ per-frame passes

    def _frame_geometry(self, state: FrameState):
        """Per object: pose, world points and normals, self-visibility, ``G_k``, ``h_k`` toward the camera, and
        the bounding sphere (``center``, ``radius``) and field reach (``reach``) in the world; an object whose
        pose and camera did not change keeps its entry."""
        order = self.options.order
        geo = {}
        camera = state.camera or self.scene.camera
        for o in self.objects:
            T = state.transforms.get(o.name, o.transform)
            key = (tuple(T.matrix().ravel()), tuple(np.asarray(camera.position, float)))
            cached = self.reuse.geometry.get(o.name)
            if cached is not None and cached[0] == key:
                geo[o.name] = cached[1]
                continue
            x, n = T.apply_points(self.local_points[o.name]), o.world_normals(T)
            sep = self.seps[o.name]
            wo = np.asarray(camera.position, float) - x
            wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-300)
            own = np.asarray(self.entries[o.name]["self_visibility"], float)
            if len(own):
                own = sh.rotate(own, T.rotation, channels=False)
            grid = self.fields[o.name].grid
            geo[o.name] = {"T": T, "pose": key[0], "x": x, "n": n, "wo": wo, "self": own,
                           "g_cos": brdf.project_g_cos(sep, n, order), "h": brdf.project_h(sep, wo, n),
                           "center": T.apply_points(grid.center), "radius": grid.radius * float(T.scale),
                           "reach": grid.radii[-1] * float(T.scale)}
            self.reuse.geometry[o.name] = (key, geo[o.name])
        return geo

    def _occlusion(self, geo):
        """occ[r] (:class:`OcclusionFields`): occ[r][o] is the occlusion field of object o (its log with
        ``occlusion="exp"``) looked up at the vertices of r (world frame), a flat occluder's half-space near its
        plane (``flat_visibility="plane"``). Only the fields whose receiver or
        occluder moved are looked up again, into the receiver's array (the last frame's ``occ`` changes with it)."""
        occ = {}
        for r in self.objects:
            names = [o.name for o in self.objects if o.name != r.name]
            stack = self.reuse.occlusion.get(r.name)
            for i, name in enumerate(names):
                key = (geo[r.name]["pose"], geo[name]["pose"])
                if stack is not None and stack.poses[i] == key:
                    continue
                field = self.occluders[name].lookup(geo[r.name]["x"], geo[name]["T"])
                if name in self.flat_occluders:  # near its plane: the half-space it hides
                    rows, axes = self.flat_occluders[name].near(geo[r.name]["x"], geo[name]["T"])
                    self.reuse.halfspaces[r.name, name] = (key, rows, axes)
                    if len(rows):
                        field[rows] = halfspace_visibility(axes, self.options.order, LOG_FLOOR
                                                           if self.options.occlusion == "exp" else None)
                if stack is None:
                    stack = self.reuse.occlusion[r.name] = OcclusionFields(names, np.empty((len(names),) + field.shape))
                stack.fields[i] = field
                stack.poses[i] = key
            occ[r.name] = stack if stack is not None else OcclusionFields([], np.zeros((0, len(geo[r.name]["x"]), 0)))
        return occ

    @staticmethod
    def _within_reach(x, go) -> np.ndarray:
        """(V,) bool: the points that the occlusion field of ``go`` reaches (beyond it its lookup is exactly 1)."""
        d = x - go["center"]
        return np.einsum("vi,vi->v", d, d) <= go["reach"] ** 2

    @staticmethod
    def _may_block(x, go, gs, method: str = "numba") -> np.ndarray:
        """(V,) bool: the points from which ``go`` may block a ray toward ``gs``.

        A ray from ``x`` that reaches the source's bounding sphere (centre ``c_s``, radius ``R_s``)
        stays inside the capsule of radius ``R_s`` about the segment ``x c_s``; an occluder whose
        bounding sphere misses that capsule, or whose field does not reach ``x``, blocks none of the
        directions in which the source's basis radiance is non-zero. ``method``: the parallel kernel or
        ``"reference"`` (numpy, below).
        """
        if method != "reference":
            out = np.empty(len(x), dtype=np.bool_)
            kernel = may_block_kernel if len(x) >= SERIAL_ITEMS else may_block_serial
            kernel(np.ascontiguousarray(x, dtype=np.float64), np.asarray(go["center"], np.float64),
                   float(go["radius"] + gs["radius"]), float(go["reach"]), np.asarray(gs["center"], np.float64), out)
            return out
        d = gs["center"] - x
        t = np.clip(np.einsum("vi,vi->v", go["center"] - x, d) / np.maximum(np.einsum("vi,vi->v", d, d), 1e-300),
                    0.0, 1.0)
        gap = x + t[:, None] * d - go["center"]
        return (np.einsum("vi,vi->v", gap, gap) <= (go["radius"] + gs["radius"]) ** 2) & Interreflection._within_reach(
            x, go)

    def _visibility(self, g, occ_r, factors, rows, method: str = "numba", keep=None):
        """``V_j`` at ``rows`` of receiver ``g``: its self-visibility times each ``(name, mask)`` factor's occlusion
        ``occ_r[name]`` (in the given order) where ``mask`` (aligned with ``rows``) is set; elsewhere the factor is
        1 and its product is skipped. ``method``: one kernel call for every factor (``"numba"``; ``occ_r`` an
        :class:`OcclusionFields`, else its fields are copied into one), one call per factor (``"per_factor"``,
        the same bits) or ``"reference"`` (``prtlab.sh.product``). With ``occlusion="exp"`` (``occ_r`` the logs)
        the self-visibility times ``exp*`` of the sum of the set factors' logs, the same in any order of
        ``factors`` up to the rounding of the sum.

        ``keep`` (a key naming the call's place, with ``method="numba"`` and the products): the partial product
        of the factors before the first one whose field changed since the last call with that key is kept per
        receiver row (``FrameReuse.visibility_prefix``) and taken again at a row whose masks of those factors are
        the same (each row's products are its own: the same bits as the whole product)."""
        order = self.options.order
        gaunt = _gaunt_block(order, order, order)
        vis = np.ascontiguousarray(g["self"][rows])
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        if self.options.occlusion == "exp":
            logs, any_set = np.zeros(vis.shape), np.zeros(len(rows), bool)
            for name, mask in factors:
                at = np.flatnonzero(mask)
                logs[at] += occ_r[name][rows[at]]
                any_set[at] = True
            at = np.flatnonzero(any_set)
            if len(at):
                vis[at] = sh.product(vis[at], sh.exp(logs[at], method=self.options.exp_method, channels=False),
                                     order, channels=False)
            return vis
        if method == "numba":
            if not len(factors) or not len(rows):
                return vis
            if not isinstance(occ_r, OcclusionFields):
                occ_r, keep = OcclusionFields.stacked({name: occ_r[name] for name, _ in factors}), None
            masks = np.array([mask for _, mask in factors], dtype=np.bool_).reshape(len(factors), len(rows))
            which = np.array([occ_r.index[name] for name, _ in factors], dtype=np.int64)
            if keep is not None:
                return self._kept_visibility(g, occ_r, factors, rows, vis, masks, which, keep)
            self._visibility_products(vis, occ_r, which, masks, rows)
            return vis
        for name, mask in factors:
            at = np.flatnonzero(mask)
            if not len(at):
                continue
            if method == "reference":
                vis[at] = sh.product(vis[at], occ_r[name][rows[at]], order, channels=False)
            else:
                kernel = masked_product_kernel if len(at) > PRODUCT_TILE else masked_product_serial  # one task
                kernel(vis, np.ascontiguousarray(occ_r[name]), at, rows, *gaunt)
        return vis

    def _visibility_products(self, vis, occ_r, which, masks, rows):
        """``visibility_product_kernel`` (its serial twin below ``SERIAL_ITEMS`` products) on ``vis`` in place."""
        parallel = np.count_nonzero(masks) >= SERIAL_ITEMS and len(rows) > VISIBILITY_BLOCK
        kernel = visibility_product_kernel if parallel else visibility_product_serial
        kernel(vis, occ_r.fields, which, masks, rows, *_gaunt_runs(self.options.order))

    def _kept_visibility(self, g, occ_r, factors, rows, vis, masks, which, keep):
        """:meth:`_visibility`'s products with the partial product kept under ``keep``.

        The kept entry holds the factors of the last call (names, and the poses their fields were looked up at),
        and the product of the first ``k`` of them at the rows where it was made, with those rows' masks. ``k``
        is the length of the run of factors that this call shares with the last one (the factors before the one
        that moved; all of them when none did): a row whose masks of those ``k`` factors are the kept ones takes
        the kept product, the others make it, and the factors from ``k`` on are applied to every row."""
        fields = [(name, occ_r.poses[occ_r.index[name]]) for name, _ in factors]
        entry = self.reuse.visibility_prefix.get(keep)
        k = 0
        if entry is not None and entry["self"] == g["pose"]:
            while k < len(fields) and k < len(entry["last"]) and fields[k] == entry["last"][k]:
                k += 1
        if k == 0:
            self._visibility_products(vis, occ_r, which, masks, rows)
            self.reuse.visibility_prefix[keep] = {"self": g["pose"], "last": fields, "prefix": None}
            return vis
        kept = entry["prefix"]
        if kept is None or kept["fields"] != fields[:k] or kept["vis"].shape[1] != vis.shape[1]:
            n_v = len(g["x"])
            kept = {"fields": fields[:k], "vis": np.empty((n_v, vis.shape[1])), "masks": np.zeros((k, n_v), np.bool_),
                    "valid": np.zeros(n_v, np.bool_)}
        same = kept["valid"][rows] & np.all(kept["masks"][:, rows] == masks[:k], axis=0)
        at = np.flatnonzero(same)
        vis[at] = kept["vis"][rows[at]]
        if len(at) < len(rows):  # the rows without a kept product make it (a set mask skips none of their factors)
            self._visibility_products(vis, occ_r, which[:k], masks[:k] & ~same, rows)
            kept["vis"][rows] = vis
            kept["masks"][:, rows] = masks[:k]
            kept["valid"][rows] = True
        if k < len(fields):
            self._visibility_products(vis, occ_r, which[k:], masks[k:], rows)
        self.reuse.visibility_prefix[keep] = {"self": g["pose"], "last": fields, "prefix": kept}
        return vis

    def _transfer(self, visibility, g_cos):
        order = self.options.order
        if len(visibility) == 0:
            return np.zeros(g_cos.shape)
        return sh.product(np.broadcast_to(visibility[:, None, :], g_cos.shape), g_cos, order, channels=False)

    def direct_transfer(self, geo, occ, lights=None):
        """``P_n(V_j G_jk)`` (V, K, n2) per object, with the visibility toward every other object.

        With ``lights`` (no environment light among them) a flat occluder is left out at the points it cannot
        shadow from any of them (:meth:`_lit_past`).
        """
        transfer = {}
        light_points = None if lights is None else self._light_points(lights)
        light_key = None if light_points is None else light_points.tobytes()
        by_name = {o.name: o for o in self.objects}
        for r in self.objects:
            g = geo[r.name]
            others = [o.name for o in self.objects if o.name != r.name and self._reaches(geo, o, r)]
            key = (g["pose"], tuple((o, geo[o]["pose"]) for o in others), light_key)
            now = {o: geo[o] for o in others}
            cached = self.reuse.direct_transfer.get(r.name)
            if cached is None or cached[0] != key:
                idx = occluder_order(g["center"], [geo[o]["center"] for o in others]) if others else []
                if cached is None or cached[0][0] != g["pose"] or cached[0][2] != light_key:
                    rows = np.arange(len(g["x"]))
                else:  # only occluders moved, came or went: the points their fields reach, before or now
                    rows = self._changed_rows(g["x"], cached[2], now, self._within_reach)
                x, n = g["x"][rows], g["n"][rows]
                factors = [(others[i], self._within_reach(x, geo[others[i]])
                            & ~self._lit_past(geo, by_name[others[i]], x, light_points, n)) for i in idx]
                visibility = self._visibility(g, occ[r.name], factors, rows, keep=("direct", r.name))
                if len(rows) == len(g["x"]):
                    value = self._transfer(visibility, g["g_cos"])
                else:
                    value = cached[1].copy()
                    value[rows] = self._transfer(visibility, g["g_cos"][rows])
                cached = self.reuse.direct_transfer[r.name] = (key, value, now)
            transfer[r.name] = cached[1]
        return transfer

    @staticmethod
    def _light_points(lights):
        """(P, 3) points whose convex hull holds every light (area-light corners, point-light positions);
        None with an environment light (it lies on every side)."""
        points = []
        for light in lights:
            if isinstance(light, EnvironmentLight):
                return None
            if isinstance(light, AreaLight):
                c, u, v = (np.asarray(getattr(light, f), float) for f in ("center", "u", "v"))
                points += [c + a * u + b * v for a in (-1.0, 1.0) for b in (-1.0, 1.0)]
            elif isinstance(light, PointLight):
                points.append(np.asarray(light.position, float))
        return np.asarray(points, float).reshape(-1, 3)

    def _lit_past(self, geo, o, x, light_points, normals=None) -> np.ndarray:
        """(V,) bool: the points ``x`` that flat object ``o`` cannot shadow from the lights spanned by
        ``light_points``: those in its plane, and those on the side of it where every light lies (a plane
        blocks no segment between two points on one side). Its occlusion field, interpolated across its
        own plane, would darken a floor's row at the foot of a wall (``docs/notes/interreflection.md``).
        With ``normals`` (the SH direct step) only the points not facing the plane: at a point facing it
        the plane's SH visibility, exact or not, cancels the ringing of the order-n transfer below the
        point's horizon (measured in the notes)."""
        out = np.zeros(len(x), bool)
        if light_points is None or not self.flat[o.name] or not len(x):
            return out
        go = geo[o.name]
        v = go["T"].apply_points(np.asarray(o.mesh.vertices, float))
        normal = np.mean(go["n"], axis=0)
        normal /= max(float(np.linalg.norm(normal)), 1e-300)
        centre = v.mean(axis=0)
        side, lit = (x - centre) @ normal, (light_points - centre) @ normal
        eps = 1e-6 * max(float(np.ptp(v, axis=0).max()), 1e-300)
        out = (np.abs(side) <= eps) | ((side > 0) & bool(np.all(lit >= -eps))) | ((side < 0) & bool(np.all(lit <= eps)))
        if normals is not None:  # facing the plane: n . normal has the opposite sign of the point's side
            out &= (normals @ normal) * np.where(side < 0, -1.0, 1.0) >= -1e-6
        return out

    def direct_step(self, state: FrameState, geo, transfer):
        """Step 1: ``L_k`` (V, K, C) per object from the environment and area lights, and the radiance."""
        if self.options.shadows == "haar":
            return self.direct_step_haar(state, geo)
        if self.options.shadows == "rays":
            return self.direct_step_rays(state, geo, transfer)
        order = self.options.order
        lights = state.lights  # no point lights (check_lights)
        env = [light for light in lights if isinstance(light, EnvironmentLight)]
        env_sh = self._environment_sh(env[0]) if env else None
        horizon = self._horizon_light(geo, env[0], env_sh) if env else {}
        areas = [light for light in lights if isinstance(light, AreaLight)]
        light_k, radiance = {}, {}
        for r in self.objects:
            g = geo[r.name]
            t = transfer[r.name]  # (V, K, n2)
            lk = np.zeros(t.shape[:2] + (3,))
            if env_sh is not None:
                lk += self._environment_terms(r, t, env_sh, horizon.get(r.name))
            for i, light in enumerate(areas):
                # the light's SH at the vertices stands while it and the receiver stand; its product with
                # the transfer while the transfer does too
                key = (g["pose"], *(np.asarray(getattr(light, f), float).tobytes()
                                    for f in ("center", "u", "v", "radiance")))
                cached = self.reuse.area_light_sh.get((r.name, i))
                if cached is None or cached[0] != key:
                    cached = (key, self._area_light_sh(light, g["x"]), None, None)
                if cached[2] is not t:
                    cached = self.reuse.area_light_sh[(r.name, i)] = (key, cached[1], t,
                                                              np.einsum("vki,vic->vkc", t, cached[1]))
                lk += cached[3]
            lk = self._clamp_diffuse(r, lk)
            light_k[r.name] = lk
            radiance[r.name] = outgoing_radiance(lk, g["h"], self.seps[r.name].colour)
        return light_k, radiance

    def _area_light_sh(self, light, points) -> np.ndarray:
        """(V, n2, 3) SH radiance of an area light at world points: exact, or from its shape's source radiance field."""
        o = self.options
        if o.area_lights == "exact":
            return area_light_sh(light, points, o.order)
        field = next((f for f in self.reuse.source_fields if f.fits(light)), None)
        if field is None:
            field = source_radiance_field(light, o.order, n_radii=o.n_radii, resolution=o.resolution, r_min=o.r_min,
                                          r_max=o.r_max, spacing=o.spacing)
            self.reuse.source_fields.append(field)
        return field.lookup(light, points)

    def direct_step_rays(self, state: FrameState, geo, transfer):
        """Step 1 with ``shadows="rays"``: area and point lights by shadow rays against every object at the
        frame's poses (:func:`light_terms`; their radiance toward the camera with the BRDF itself), the
        environment through the SH transfer as the paper.

        Each receiver keeps, per light, its terms at unit emission and its per-sample shadow mask
        (``FrameReuse.direct_rays``): a light whose emission alone changed is rescaled (no rays), a new camera
        reshades from the mask (no rays), and when other objects moved only the samples whose segment meets
        a moved object's bounding sphere (before or after) are cast again; a moved light or receiver, or new
        ray offsets, cast every sample."""
        env = [light for light in state.lights if isinstance(light, EnvironmentLight)]
        near = [light for light in state.lights if isinstance(light, (AreaLight, PointLight))]
        env_sh = self._environment_sh(env[0]) if env else None
        horizon = self._horizon_light(geo, env[0], env_sh) if env else {}
        poses = tuple(geo[o.name]["pose"] for o in self.objects)
        caster, spheres = self._scene_caster(geo, poses) if near else (None, None)
        offsets = None if caster is None else (caster.epsilon, caster.tnear)
        samples = (self.options.light_samples, self.options.light_probe, self.options.light_exact_lit)
        blockers = [self._shadow_blockers(caster, poses, me, True) if near else None
                    for me in range(len(self.objects))]

        def receiver(me, r):  # a task of run_tasks: its light terms and environment, and its rays cast
            g = geo[r.name]
            lk, rad = np.zeros(g["g_cos"].shape[:2] + (3,)), np.zeros((len(g["x"]), 3))
            entry = self.reuse.direct_rays.get(r.name)
            if entry is not None and not (caster is not None and entry["offsets"] == offsets
                                          and entry["samples"] == samples and entry["poses"][me] == poses[me]):
                entry = None  # the receiver's points or the rays' offsets changed: every sample is cast
            moved = None
            if entry is not None:
                changed = [i for i in range(len(poses)) if entry["poses"][i] != poses[i]]
                moved = np.array([widened_sphere(sphere, caster.epsilon) for i in changed
                                  for sphere in (entry["spheres"][i], spheres[i])]).reshape(-1, 4)
            terms, counts = {}, {"rays_cast": 0}
            for i, light in enumerate(near):
                key = (type(light).__name__, *(np.asarray(getattr(light, f), float).tobytes()
                                               for f in ("center", "u", "v", "position") if hasattr(light, f)))
                old = None if entry is None else entry["lights"].get(i)
                if old is not None and old["key"] == key and not len(moved) and old["wo"] == g["wo"].tobytes():
                    new = old  # the emission alone may have changed
                else:
                    new = dict(key=key, wo=g["wo"].tobytes())
                    reuse = old is not None and old["key"] == key
                    new["S"], new["F"], new["mask"] = light_terms(
                        g["x"], g["n"], mirror_wo(g["wo"], g["n"]), brdf.from_material(r.material),
                        self.seps[r.name], caster, light, i, samples[0], probe=samples[1], exact_lit=samples[2],
                        visibility=old["mask"] if reuse else None, moved=moved if reuse else None,
                        stats=counts, blockers=blockers[me],
                        previous=(old["S"], old["F"]) if reuse and old["wo"] == new["wo"] else None)
                terms[i] = new
                emission = np.asarray(light.radiance if isinstance(light, AreaLight) else light.intensity, float)
                lk += new["S"][:, :, None] * emission
                rad += new["F"] * emission
            environment = None if entry is None else entry.get("environment")
            if env_sh is not None and (environment is None or not (
                    environment[0] is env_sh and environment[1] is transfer[r.name] and environment[2] is g["h"])):
                env_k = self._clamp_diffuse(r, self._environment_terms(r, transfer[r.name], env_sh,
                                                                       horizon.get(r.name)))
                environment = (env_sh, transfer[r.name], g["h"], env_k,
                               outgoing_radiance(env_k, g["h"], self.seps[r.name].colour))
            return lk, rad, terms, environment, counts

        done = run_tasks([functools.partial(receiver, me, r) for me, r in enumerate(self.objects)],
                           [len(geo[r.name]["x"]) for r in self.objects])
        light_k, radiance = {}, {}
        self.reuse.direct_counts = {"rays_cast": 0}
        for r, (lk, rad, terms, environment, counts) in zip(self.objects, done):
            self.reuse.direct_counts["rays_cast"] += counts["rays_cast"]
            self.reuse.direct_rays[r.name] = dict(poses=poses, offsets=offsets, samples=samples, spheres=spheres,
                                                  lights=terms, light_k=lk, environment=environment)
            if env_sh is not None:  # the environment's terms stand while its SH, the transfer and h_k do
                lk = lk + environment[3]
                rad = rad + environment[4]
            light_k[r.name], radiance[r.name] = lk, rad
        return light_k, radiance

    def _environment_terms(self, r, transfer_r, env_sh, horizon) -> np.ndarray:
        """``L_k`` (V, K, 3) of the environment (its SH ``env_sh``) at receiver ``r``: through its SH transfer
        ``transfer_r`` (V, K, n^2), plus the bands above the order at the points that take a half-space
        (:meth:`_horizon_light`'s ``(points, dL)``, or None)."""
        # Eq. 12's contraction with the sky's SH as the weights (numpy's einsum took 15 times as long; a BLAS product
        # here, inside the receivers' tasks, waits for BLAS's workers beside numba's)
        lk = np.zeros(transfer_r.shape[:2] + (env_sh.shape[1],))
        bounce_kernel(np.ascontiguousarray(transfer_r, dtype=np.float64),
                      np.ascontiguousarray(env_sh, dtype=np.float64), lk)
        if horizon is not None:
            lk[horizon[0]] += horizon[1]
        return lk

    def _horizon_light(self, geo, env, env_sh) -> dict:
        """``horizon_sky``: ``{receiver: (points, dL (P, K, 3))}``, the environment's bands above the order through
        the half-spaces its points take (:mod:`._horizon`; receivers without any left out). The cells' weights are
        kept while the half-spaces' poses and the map's size stand, ``dL`` while the environment does too."""
        out = {}
        for r in self.objects if self.options.horizon_sky else ():
            taken = [(name, *self.reuse.halfspaces[r.name, name]) for name in self.flat_occluders
                     if (r.name, name) in self.reuse.halfspaces]
            taken = [(name, poses, rows, axes) for name, poses, rows, axes in taken  # those of this frame's poses
                     if len(rows) and poses == (geo[r.name]["pose"], geo[name]["pose"])]
            if not taken:
                continue
            cells = self.reuse.sky_cells
            if cells is None or cells[0] is not env_sh:  # kept while the environment is
                cells = self.reuse.sky_cells = (env_sh, sky_cells(env, env_sh))
            grid, dirs, residual = cells[1]
            key = (tuple((name, poses) for name, poses, _, _ in taken), grid)
            kept = self.reuse.horizon.get(r.name)
            if kept is None or kept["key"] != key:
                kept = self.reuse.horizon[r.name] = {"key": key, "light": None, "groups": horizon_weights(
                    geo[r.name]["n"], np.concatenate([t[2] for t in taken]), np.concatenate([t[3] for t in taken]),
                    self.seps[r.name], dirs)}
            if kept["light"] is None or kept["light"][0] is not env_sh:
                kept["light"] = (env_sh, np.concatenate([g.points for g in kept["groups"]]),
                                 np.concatenate([horizon_sums(g, residual) for g in kept["groups"]]))
            out[r.name] = kept["light"][1:]
        return out

    def _environment_sh(self, env) -> np.ndarray:
        """The SH coefficients (n^2, 3) of environment light ``env`` (:func:`environment_sh`), projected again only
        when it differs from the last one's copy."""
        cached = self.reuse.environment_sh
        if cached is None or cached[1] != self.options.order or not cached[0] == env:
            cached = self.reuse.environment_sh = (copy.deepcopy(env), self.options.order,
                                                  environment_sh(env, self.options.order))
        return cached[2]

    def _shadow_blockers(self, caster, poses, me: int, vertices: bool = False):
        """The bounds of every object a shadow ray from object number ``me`` may hit (:func:`blocker_bounds`; its
        own plane left out if it is flat, and with ``vertices`` (rays from its shading points, each in its vertex's
        tangent plane) its own bound if it is convex: that plane supports it, so a ray above it cannot meet it),
        made once per pose set and ray offsets."""
        name = self.objects[me].name
        exclude = me if self.flat[name] or (vertices and self.convex[name]) else None
        key = (poses, caster.epsilon, caster.tnear)
        cached = self.reuse.blockers.get(exclude)
        if cached is None or cached[0] != key:
            flat = [self.flat[o.name] for o in self.objects]
            cached = self.reuse.blockers[exclude] = (key, blocker_bounds(
                caster, flat, exclude, bounds=lambda i: self._object_bound(caster, i)))
        return cached[1]

    def _object_bound(self, caster, i: int):
        """:func:`object_bound` of object number ``i`` at ``caster``'s pose, made again only when it moved."""
        vertices = caster.world_vertices(i)
        cached = self.reuse.object_bounds.get(i)
        if cached is None or cached[0] is not vertices or cached[1] != caster.epsilon:
            cached = self.reuse.object_bounds[i] = (vertices, caster.epsilon, object_bound(
                vertices, self.flat[self.objects[i].name], caster.epsilon))
        return cached[2]

    def direct_step_haar(self, state: FrameState, geo):
        """Step 1 with all-frequency shadows: ``L_k`` (V, K, C) per object from every light (Zhou et al. 2005
        Sec. 5: Haar visibility products; lights as exact cubemap pieces), and the radiance."""
        light_k, radiance = {}, {}
        for r in self.objects:
            g = geo[r.name]
            others = [o for o in self.objects if o.name != r.name]
            light_points = self._light_points(state.lights)
            # the flat occluders each point is left out of (_lit_past), as bits; one pass per distinct set
            left_out = np.zeros(len(g["x"]), np.int64)
            for i, o in enumerate(others):
                left_out |= self._lit_past(geo, o, g["x"], light_points).astype(np.int64) << i
            lk = np.zeros((len(g["x"]), self.seps[r.name].K, 3))
            own = self.haar_self[r.name]
            for bits in np.unique(left_out):
                at = np.flatnonzero(left_out == bits)
                occluders = [(self.haar_fields[o.name], geo[o.name]["T"]) for i, o in enumerate(others)
                             if not (int(bits) >> i) & 1]
                lk[at] = haar_direct(g["x"][at], g["n"][at], state.lights, self.seps[r.name],
                                     self_visibility=SparseCubemaps(own.resolution, own.indices[at], own.values[at],
                                                                    own.energy_lost[at]),
                                     self_transform=g["T"], occluders=occluders)
            light_k[r.name] = self._clamp_diffuse(r, lk)
            radiance[r.name] = outgoing_radiance(light_k[r.name], g["h"], self.seps[r.name].colour)
        return light_k, radiance

    def _clamp_diffuse(self, obj, light):
        """``max(L, 0)`` for a Lambertian object (K = 1: ``L`` is its irradiance over pi, never negative).

        Order-n SH products of a small area light, a clamped cosine and a visibility ring
        negative where the light is below a vertex's horizon (``docs/NOTES.md``). Glossy terms
        (K > 1) may be negative by construction and are left alone.
        """
        return np.maximum(light, 0.0) if self.seps[obj.name].K == 1 else light

    def _pair_skipped(self, geo, r, s) -> bool:
        return self.options.threshold > 0 and self.pair_importance(geo, r, s) < self.options.threshold

    def pair_importance(self, geo, r, s) -> float:
        """Sec. 5.4: ``I_c = max_(k',k,i) |int S_(k,i)(x_c^r, w) g_k'(w) (w_c . w) dw|`` of source ``s`` on
        receiver ``r``.

        The basis irradiance of a plane at the receiver's bounding-sphere centre facing the
        source's centre (unoccluded), from the interpolated basis radiance field. A receiver vertex ``x`` at
        most ``R_r`` from that centre, with the source ``d`` away, sees the source's radiance over a solid
        angle at most ``(d / (d - R_r))^2`` times larger, so ``|Phi_(k',k,i)(x)| <= I_c (d / (d - R_r))^2``
        (visibility only lowers it), up to the SH truncation of both sides.
        """
        gs, gr = geo[s.name], geo[r.name]
        wc = gs["center"] - gr["center"]
        dist = np.linalg.norm(wc)
        if dist == 0:
            return np.inf
        wc /= dist
        g_c = brdf.project_g_cos(self.seps[r.name], wc, self.options.order)  # (K', n2), world frame
        # S at the centre as the basis irradiance sees it: the field's interpolation (with its 1 / r^2
        # beyond the outermost sphere), not a ray-cast quadrature that may miss a small, far source
        phi_c = basis_irradiance(self.radiance[s.name], self.fields[s.name].grid,
                                 gr["center"][None], g_c[None], gs["T"])
        return float(np.max(np.abs(phi_c)))

    def _reaches(self, geo, o, r) -> bool:
        """Whether the occlusion field of ``o`` can reach a vertex of ``r`` (else its lookup is 1 there)."""
        go, gr = geo[o.name], geo[r.name]
        reach = self.fields[o.name].grid.radii[-1] * float(go["T"].scale)
        extent = self.fields[r.name].grid.radius * float(gr["T"].scale)
        return bool(np.linalg.norm(go["center"] - gr["center"]) <= reach + extent)

    def _near_field(self, s, T, x, rows, transfer, phi) -> int:
        """Replace ``phi`` (in place) at receiver points near source ``s`` by the ray-cast basis radiance.

        ``x`` are all the receiver's points; ``transfer`` and ``phi`` hold the rows ``rows`` of them.

        Near a large source (a floor under an object) the basis radiance changes faster than the
        sample spheres resolve (``docs/NOTES.md``).
        """
        if self.options.near_field <= 0 or len(rows) == 0:
            return 0
        grid = self.fields[s.name].grid
        local = _to_object(x, T)
        key = (s.name, local.shape, local.tobytes())  # the receiver points relative to the source
        cached = self.reuse.near_field.get(key)
        if cached is None:
            cached = self._near_cast(s, local, grid)
            if len(self.reuse.near_field) >= 4 * len(self.objects) ** 2:  # bounded: poses come and go
                self.reuse.near_field.clear()
            self.reuse.near_field[key] = cached  # an occluder that moves later changes the transfer, not S
        near, S = cached
        at = np.flatnonzero(np.isin(rows, near))  # positions in rows of the near points among them
        if len(at) == 0:
            return 0
        S = S[np.searchsorted(near, rows[at])]
        t_obj = sh.rotate(transfer[at], T.rotation.T, channels=False)  # <S_world, T> = <S_obj, R^T T>
        phi[at] = np.einsum("vkni,vqi->vqkn", S, t_obj)
        return len(at)

    def _near_points(self, s, local, grid) -> np.ndarray:
        """Indices of the points ``local`` (object frame of ``s``) whose distance to the source's surface (its
        nearest vertex) is below ``near_field`` times their distance to its centre.

        The distance to the nearest vertex is at least the distance to the bounding sphere
        (``|x - c| - R``), so only the points with ``|x - c| - R < near_field |x - c|`` are looked up."""
        dist = np.linalg.norm(local - grid.center, axis=1)
        candidates = np.flatnonzero(dist - grid.radius < self.options.near_field * dist)
        if len(candidates) == 0:
            return candidates
        if s.name not in self.reuse.vertex_trees:
            from scipy.spatial import cKDTree

            self.reuse.vertex_trees[s.name] = cKDTree(np.asarray(s.mesh.vertices, float))
        gap, _ = self.reuse.vertex_trees[s.name].query(local[candidates])  # distance to the source's nearest vertex
        return candidates[gap < self.options.near_field * dist[candidates]]

    def _near_cast(self, s, local, grid):
        """The near points (indices into ``local``, object frame of ``s``) and their cast ``S`` (v, K, N, n2)."""
        near = self._near_points(s, local, grid)
        S = np.zeros((0,))
        if len(near):
            if s.name not in self.reuse.casters:
                self.reuse.casters[s.name] = RayCaster([(np.asarray(s.mesh.vertices, float), np.asarray(s.mesh.faces))])
            S = basis_radiance_at(s.mesh, self.bases[s.name].basis, self.seps[s.name], local[near],
                                  self.options.order, self.options.degree,
                                  caster=self.reuse.casters[s.name])  # (v, K, N, n2), object frame
        return near, S

    def _plane_separates(self, geo, o, r, s) -> bool:
        """Whether ``o`` is flat and ``r``'s points and ``s``'s vertices all lie on one side of its plane.

        Then ``o`` blocks no segment from ``r`` to ``s`` and is left out of their visibility: its
        order-n SH visibility (a half-space at a receiver near it) would only leak onto the
        source's directions (``docs/NOTES.md``).
        """
        if not self.flat[o.name]:
            return False
        poses = (geo[o.name]["pose"], geo[r.name]["pose"], geo[s.name]["pose"])
        cached = self.reuse.plane_separates.get((o.name, r.name, s.name))
        if cached is None or cached[0] != poses:
            cached = self.reuse.plane_separates[(o.name, r.name, s.name)] = (poses, self._one_side(geo, o, r, s))
        return cached[1]

    def _one_side(self, geo, o, r, s) -> bool:
        go = geo[o.name]
        if "plane" not in go:  # o's plane and extent, kept with its pose's entry (``_frame_geometry``)
            v = go["T"].apply_points(np.asarray(o.mesh.vertices, float))
            normal = np.mean(go["n"], axis=0)
            normal /= max(float(np.linalg.norm(normal)), 1e-300)
            go["plane"] = (v.mean(axis=0), normal, float(np.ptp(v, axis=0).max()))
        centre, normal, extent = go["plane"]
        gs, gr = geo[s.name], geo[r.name]
        if "vertices" not in gs:
            gs["vertices"] = gs["T"].apply_points(np.asarray(s.mesh.vertices, float))
            gs["vertex_box"] = _points_box(gs["vertices"])
        if "x_box" not in gr:
            gr["x_box"] = _points_box(gr["x"])
        points = np.concatenate([gr["x"], gs["vertices"]])
        side = (points - centre) @ normal
        # np.ptp(points, axis=0): the boxes' extremes are those of the points
        lo, hi = np.minimum(gr["x_box"][0], gs["vertex_box"][0]), np.maximum(gr["x_box"][1], gs["vertex_box"][1])
        eps = 1e-9 * max(float((hi - lo).max()), extent, 1e-300)
        return bool(np.all(side >= -eps) or np.all(side <= eps))

    def _haar_pair(self, geo, r, s, others):
        """Eq. 13 of one pair with ``irradiance="haar"`` (:func:`haar_basis_irradiance`), by chunks of vertices.

        The transfer is the receiver's Haar self-visibility times the Haar occlusion fields of ``others``
        times ``g_k' cos`` per texel; receivers near the source (as :meth:`_near_field`) take ``S`` cast at
        the receiver (:func:`near_basis_irradiance`, not cached).
        """
        g, T, res = geo[r.name], geo[s.name]["T"], self.options.cube_resolution
        field, own = self.haar_radiance[s.name], self.haar_self[r.name]
        occluders = [(self.haar_fields[o], geo[o]["T"]) for o in others]
        local = _to_object(g["x"], T)
        near = np.zeros(len(local), bool)
        if self.options.near_field > 0 and len(local):
            near[self._near_points(s, local, field.grid)] = True
        out = np.empty((len(local), self.seps[r.name].K) + field.n_terms)
        step = 256
        caster = None
        for a in range(0, len(local), step):
            b = min(len(local), a + step)
            transfer = haar_transfer(g["x"][a:b], g["n"][a:b], self.seps[r.name], res,
                                     self_visibility=SparseCubemaps(own.resolution, own.indices[a:b],
                                                                    own.values[a:b], own.energy_lost[a:b]),
                                     self_transform=g["T"], occluders=occluders)
            out[a:b] = haar_basis_irradiance(field, g["x"][a:b], transfer, T)
            idx = np.flatnonzero(near[a:b])
            if len(idx):
                caster = caster or RayCaster([(np.asarray(s.mesh.vertices, float), np.asarray(s.mesh.faces))])
                out[a + idx] = near_basis_irradiance(s.mesh, self.bases[s.name].basis, self.seps[s.name],
                                                     local[a + idx], transfer[idx], T, caster=caster)
        return out

    def _blockers(self, geo, r, s) -> list:
        """The objects that may block a ray from ``r`` to ``s``, nearest to ``r`` first (Sec. 6.1).

        Every such ray lies in the capsule of radius ``R_r + R_s`` about the segment between the two
        bounding-sphere centres (:meth:`_may_block` per point); an object whose bounding sphere misses
        it, whose field does not reach ``r``, or a plane with ``r`` and ``s`` on one side
        (:meth:`_plane_separates`) is no occluder of the pair.
        """
        gr, gs = geo[r.name], geo[s.name]
        poses = tuple(geo[o.name]["pose"] for o in self.objects)
        cached = self.reuse.pair_blockers.get((r.name, s.name))
        if cached is not None and cached[0] == poses:
            return cached[2]
        # whether o blocks depends on the poses of o, r and s alone: with r and s in place, only moved objects
        # are tested again
        ends = cached is not None and all(cached[0][i] == poses[i] for i, o in enumerate(self.objects)
                                          if o.name in (r.name, s.name))
        d = gs["center"] - gr["center"]
        member = {}
        for i, o in enumerate(self.objects):
            if o.name in (r.name, s.name):
                continue
            if ends and cached[0][i] == poses[i]:
                member[o.name] = cached[1][o.name]
                continue
            go = geo[o.name]
            t = min(max(float((go["center"] - gr["center"]) @ d) / max(float(d @ d), 1e-300), 0.0), 1.0)
            member[o.name] = bool(
                np.linalg.norm(gr["center"] + t * d - go["center"]) <= go["radius"] + gr["radius"] + gs["radius"]
                and self._reaches(geo, o, r) and not self._plane_separates(geo, o, r, s))
        names = [name for name, blocks in member.items() if blocks]
        idx = occluder_order(gr["center"], [geo[o]["center"] for o in names]) if names else []
        out = [names[i] for i in idx]
        self.reuse.pair_blockers[(r.name, s.name)] = (poses, member, out)
        return out

    @staticmethod
    def _changed_rows(x, before: dict, now: dict, affects) -> np.ndarray:
        """Receiver rows that an occluder that moved, came or went may affect (``affects(x, geo_o)``, (V,) bool)
        at its old or its new pose."""
        mask = np.zeros(len(x), bool)
        for name in set(before) | set(now):
            old, new = before.get(name), now.get(name)
            if old is not None and new is not None and old["pose"] == new["pose"]:
                continue
            for go in (old, new):
                if go is not None:
                    mask |= affects(x, go)
        return np.flatnonzero(mask)

    def _pair_irradiance(self, geo, occ, r, s, blockers, rows):
        """Eq. 13 of source ``s`` at the ``rows`` of receiver ``r``: masked visibility, transfer, field, near field."""
        g, gs = geo[r.name], geo[s.name]
        x = g["x"][rows]
        factors = [(o, self._may_block(x, geo[o], gs)) for o in blockers]
        vis = self._visibility(g, occ[r.name], factors, rows, keep=("pair", r.name, s.name))
        transfer = self._transfer(vis, g["g_cos"][rows])
        value = basis_irradiance(self.radiance[s.name], self.fields[s.name].grid, g["x"][rows],
                                 transfer, gs["T"])
        self._near_field(s, gs["T"], g["x"], rows, transfer, value)
        return value

    def basis_irradiance_step(self, geo, occ, done=None):
        """Step 2: ``Phi[r][s]`` (V_r, K'_r, K_s, N_s) for every ordered pair, recomputing only what changed.

        A pair whose receiver or source moved is recomputed; when only its occluders moved (or came or
        went), only the receiver points from which they may block the source (:meth:`_may_block`, at
        their old and new poses) are (``info["updated_pairs"]``, ``info["updated_rows"]``). ``done``: called with
        each receiver and its finished ``Phi[r]`` (a dict not changed afterwards) as soon as its pairs are made.
        """
        poses = tuple(geo[o.name]["pose"] for o in self.objects)
        last = self.reuse.irradiance_step
        if last is not None and last[0] == poses:  # nothing moved: every pair as the last step left it
            phi = {name: dict(pairs) for name, pairs in last[1].items()}
            if done is not None:
                for r in self.objects:
                    done(r, phi[r.name])
            return phi, dict(last[2])
        phi = {}
        counts = {"computed_pairs": 0, "updated_pairs": 0, "updated_rows": 0, "skipped_pairs": 0, "reused_pairs": 0}
        for r in self.objects:
            phi[r.name] = {}
            g = geo[r.name]
            for s in self.objects:
                if s.name == r.name:
                    continue
                key = (r.name, s.name)
                blockers = self._blockers(geo, r, s)
                depends = (g["pose"], geo[s.name]["pose"], tuple((o, geo[o]["pose"]) for o in blockers))
                now = {o: geo[o] for o in blockers}
                cached = self.reuse.pair_irradiance.get(key)
                rows = None
                if cached is not None and cached[0][:2] == depends[:2]:
                    if cached[0] == depends:
                        phi[r.name][s.name] = cached[1]
                        counts["reused_pairs"] += 1
                        continue
                    if self.options.irradiance != "haar":
                        rows = self._changed_rows(g["x"], cached[2], now,
                                                  lambda x, go: self._may_block(x, go, geo[s.name]))
                if rows is None and self._pair_skipped(geo, r, s):
                    counts["skipped_pairs"] += 1
                    continue
                if rows is None:
                    if self.options.irradiance == "haar":
                        value = self._haar_pair(geo, r, s, blockers)
                    else:
                        value = self._pair_irradiance(geo, occ, r, s, blockers, np.arange(len(g["x"])))
                    counts["computed_pairs"] += 1
                elif len(rows):
                    value = cached[1].copy()
                    value[rows] = self._pair_irradiance(geo, occ, r, s, blockers, rows)
                    counts["updated_pairs"] += 1
                    counts["updated_rows"] += len(rows)
                else:
                    value = cached[1]
                    counts["reused_pairs"] += 1
                phi[r.name][s.name] = value
                if cached is None or value is not cached[1]:  # a new value: the stacked irradiance is rebuilt
                    self.reuse.revision[key] = self.reuse.revision.get(key, 0) + 1
                self.reuse.pair_irradiance[key] = (depends, value, now)
            if done is not None:
                done(r, phi[r.name])
        # a step at these poses again reuses every pair kept, and skips the same pairs (a pair's answers depend on
        # the poses alone, as the keys above)
        self.reuse.irradiance_step = (poses, {name: dict(pairs) for name, pairs in phi.items()}, dict(
            counts, computed_pairs=0, updated_pairs=0, updated_rows=0,
            reused_pairs=sum(len(pairs) for pairs in phi.values())))
        return phi, counts

    def _stacked_irradiance(self, r, phi_r, dtype=np.float64):
        """``[Phi^s_1 | Phi^s_2 | ... | Phi^self]`` (V, K', M) of receiver ``r`` in ``dtype``, made again only when
        a pair changed (or the type asked for did): with the same sources, shapes and type only the changed pairs'
        blocks are written over (the same values as a new concatenation).

        The bounce loop then is one matrix product per receiver and bounce
        (:func:`reflected_light` with ``method="reference"`` is the specification).
        """
        sources = list(phi_r)
        arrays = [phi_r[s] for s in sources]
        if self.options.self_interreflection:
            sources.append(r.name)
            arrays.append(self.self_irradiance[r.name])
        key = (np.dtype(dtype).str,) + tuple((s, self.reuse.revision.get((r.name, s), 0)) for s in sources)
        cached = self.reuse.stacked.get(r.name)
        if cached is not None and cached[0] == key:
            return cached[1], sources
        if not arrays:
            return None, sources
        n_v, n_kp = arrays[0].shape[:2]
        widths = [a.size // (n_v * n_kp) if n_v * n_kp else 0 for a in arrays]
        if (cached is not None and cached[0][0] == key[0] and [s for s, _ in cached[0][1:]] == sources
                and cached[1].shape == (n_v, n_kp, sum(widths))
                and all(a.shape[:2] == (n_v, n_kp) for a in arrays)):
            stacked, at = cached[1], 0
            for (_, old), (_, new), a, width in zip(cached[0][1:], key[1:], arrays, widths):
                if old != new:  # this pair's Phi was replaced: its block alone is written again
                    stacked[:, :, at:at + width] = a.reshape(n_v, n_kp, width)
                at += width
            self.reuse.stacked[r.name] = (key, stacked)
            return stacked, sources
        stacked = np.ascontiguousarray(np.concatenate([a.reshape(n_v, n_kp, -1) for a in arrays], axis=2), dtype)
        self.reuse.stacked[r.name] = (key, stacked)
        return stacked, sources

    def _pose_key(self, state: FrameState):
        camera = state.camera or self.scene.camera
        poses = tuple((o.name, tuple(state.transforms.get(o.name, o.transform).matrix().ravel()))
                      for o in self.objects)
        return poses, tuple(np.asarray(camera.position, float))

    def _bounces(self, geo, phi, light_k, bounces: int, lights=(), method: str = "numba"):
        """Steps 3-4 (Sec. 5.3): the indirect radiance of ``bounces`` bounces, and the seconds of each step (the
        weights, the bounces, the near hits).

        ``method="numba"``: a receiver with ``K' = 1`` and RGB light takes one pass per bounce
        (:func:`bounce_rgb`); ``"reference"``: BLAS's ``stacked @ w`` and the float64 sum over the residual
        gather's hits (:func:`gather_residual`), the specification.

        Bounce ``b`` reflects ``L^(b) = max(0, sum_s Phi^s w^s(b-1))`` (Eq. 12; the clamp for a Lambertian
        receiver), one ``(V K', M) x (M, 3)`` product per receiver, and its weights ``w(b)`` (Eq. 14) are
        fitted to it at the PCA sample vertices (every vertex, as the pipeline builds its bases). With
        ``residual_near`` the first bounce adds :meth:`_near_corrections` (``lights``: the frame's lights).
        """
        indirect = {o.name: np.zeros((o.n_vertices, 3)) for o in self.objects}
        t_weights = t_bounces = t_near = 0.0
        for bounce in range(bounces):
            t0 = time.perf_counter()
            weights = {o.name: fit_weights(self.bases[o.name], light_k[o.name], self.seps[o.name].colour)
                       for o in self.objects}
            residuals = self._residuals(light_k, weights) if self.options.residual_rays else {}
            t_weights += time.perf_counter() - t0
            t0 = time.perf_counter()
            corrections = self._near_corrections(geo, phi, lights) if residuals and bounce == 0 \
                and self._near_on(lights) else {}
            t_near += time.perf_counter() - t0
            t0 = time.perf_counter()
            stacked_residual = offsets = None  # every object's residual (K = 1, RGB), stacked for bounce_rgb
            if residuals and method != "reference" and all(v.shape[1:] == (1, 3) for v in residuals.values()):
                offsets = np.cumsum([0] + [len(residuals[o.name]) for o in self.objects])
                stacked_residual = np.concatenate([residuals[o.name].reshape(-1, 3) for o in self.objects])
            entries = {r.name: self._residual_entry(geo, r, phi[r.name]) if residuals else {} for r in self.objects}

            def receiver(r):  # a task of run_tasks: the receiver's reflected light and its outgoing radiance
                g = geo[r.name]
                fused = method != "reference" and self.seps[r.name].K == 1  # bounce_rgb may take it
                stacked, sources = self._stacked_irradiance(r, phi[r.name],
                                                            STACKED_IRRADIANCE if fused else np.float64)
                entry = entries[r.name]
                operators = entry.get("operators", {})
                if (method != "reference" and stacked is not None and stacked.shape[1] == 1
                        and (not residuals or (stacked_residual is not None and _rgb_ready(operators.values())))):
                    # one pass per receiver (bounce_rgb): Eq. 12, the residual gather, the near hits' correction
                    w = np.concatenate([weights[s].reshape(-1, 3) for s in sources], axis=0)
                    extra = corrections.get(r.name)
                    packed = None
                    if operators:  # their terms packed per source, kept (re-packed where an operator changed)
                        packed = entry.get("packed")
                        if packed is None:  # made once, then updated in place
                            packed = entry["packed"] = PackedGather()
                        packed.update(list(operators.values()), list(operators), offsets)
                    lk = bounce_rgb(stacked.reshape(len(stacked), -1), w, list(operators.values()), list(operators),
                                    stacked_residual, offsets,
                                    None if extra is None else extra.reshape(len(stacked), 3), packed=packed)
                    lk = lk.reshape(len(stacked), 1, 3)
                    if residuals and self.options.residual_whole and self._near_on(lights):
                        lk = lk + self._whole_light(geo, r, phi[r.name], weights)
                else:
                    if sources:
                        # Eq. 12 before h: every source's (k, i) side by side
                        w = np.concatenate([weights[s].reshape(-1, 3) for s in sources], axis=0)
                        lk = (stacked.reshape(-1, stacked.shape[2]) @ w).reshape(stacked.shape[:2] + (3,))
                    else:
                        lk = np.zeros(g["g_cos"].shape[:2] + (3,))
                    if residuals:
                        lk = lk + self._residual_light(geo, r, residuals, phi[r.name], method=method)
                        if corrections:
                            lk = lk + corrections[r.name]
                        if self.options.residual_whole and self._near_on(lights):
                            lk = lk + self._whole_light(geo, r, phi[r.name], weights)
                lk = self._clamp_diffuse(r, lk)
                return lk, outgoing_radiance(lk, g["h"], self.seps[r.name].colour)

            jobs = [functools.partial(receiver, r) for r in self.objects]
            done = ([job() for job in jobs] if method == "reference"
                    else run_tasks(jobs, [o.n_vertices for o in self.objects]))
            new_light = {}
            for r, (lk, radiance) in zip(self.objects, done):
                new_light[r.name] = lk
                indirect[r.name] += radiance
            light_k = new_light
            t_bounces += time.perf_counter() - t0
        return indirect, t_weights, t_bounces, t_near

    # ------------------------------------------------------------------ residual gather (an extension)

    def _residuals(self, light_k, weights) -> dict:
        """Per source: ``colour_k L_k - P(colour_k L_k)`` (V, K, C) at its vertices, what its basis misses."""
        return {s.name: light_k[s.name] * self.seps[s.name].colour[None]
                - np.matmul(self.bases[s.name].basis.T, weights[s.name]).transpose(1, 0, 2) for s in self.objects}

    def _scene_caster(self, geo, key):
        """``(caster, spheres)``: a ray caster of every object at the poses ``key`` and their bounding spheres
        (n_objects, 4: centre, radius through the farthest vertex), built once per pose set."""
        if self.reuse.scene_caster is None or self.reuse.scene_caster[0] != key:
            transforms = [geo[o.name]["T"] for o in self.objects]
            if self.reuse.scene_caster is None:
                caster, before = RayCaster([(np.asarray(o.mesh.vertices, float), np.asarray(o.mesh.faces))
                                            for o in self.objects], transforms=transforms), None
            else:  # the previous poses' caster moved (a new one: others may hold it); unmoved objects keep arrays
                _, before, old_spheres = self.reuse.scene_caster
                caster = before.moved(transforms)
            spheres = np.array([old_spheres[i] if before is not None and caster.world_vertices(i) is
                                before.world_vertices(i) and np.array_equal(old_spheres[i, :3], geo[o.name]["center"])
                                else [*geo[o.name]["center"],
                                      _bounding_radius(caster.world_vertices(i), geo[o.name]["center"])]
                                for i, o in enumerate(self.objects)]).reshape(-1, 4)
            self.reuse.scene_caster = (key, caster, spheres)
        return self.reuse.scene_caster[1], self.reuse.scene_caster[2]

    def _residual_entry(self, geo, r, phi_r, stats: dict | None = None):
        """The receiver's residual-gather entry at the frame's poses (``FrameReuse.residual_hits``): its hits
        and their gather operators, made again only where a pose change may have changed them; the rays cast are
        counted in ``stats`` (default the frame's ``residual_counts``).

        When objects other than ``r`` moved and the caster's offsets stand, only the rays they may block or
        unblock are cast again (:func:`residual_hits` with ``previous``), and a source whose hits did not change
        keeps its operator; else every ray is cast."""
        poses = tuple(geo[o.name]["pose"] for o in self.objects)
        sources = tuple(i for i, s in enumerate(self.objects)
                        if s.name in phi_r or (s.name == r.name and self.options.self_interreflection
                                               and not self.flat[r.name] and not self.convex[r.name]))
        entry = self.reuse.residual_hits.get(r.name)
        if entry is not None and entry["poses"] == poses and entry["sources"] == sources:
            return entry
        g = geo[r.name]
        caster, spheres = self._scene_caster(geo, poses)
        offsets = (caster.epsilon, caster.tnear)
        me = next(i for i, o in enumerate(self.objects) if o.name == r.name)
        previous = moved = None
        if entry is not None and entry["sources"] == sources and entry["offsets"] == offsets \
                and entry["poses"][me] == poses[me]:
            moved = {i: np.stack([entry["spheres"][i], spheres[i]]) for i in range(len(poses))
                     if entry["poses"][i] != poses[i]}
            if len(moved) <= len(poses) // 2:  # else casting everything again is as cheap
                previous = entry["hits"]
            else:
                moved = None
        src = {i: (np.asarray(self.objects[i].mesh.faces), geo[self.objects[i].name]["n"],
                   self.seps[self.objects[i].name], geo[self.objects[i].name]["center"],
                   geo[self.objects[i].name]["radius"], spheres[i, 3], self._facing(geo, self.objects[i]),
                   self._world_box(geo, caster, i))
               for i in sources}
        hits = residual_hits(g["x"], g["n"], self.seps[r.name], caster, src, self.options.residual_rays,
                             previous=previous, moved=moved,
                             stats=self.reuse.residual_counts if stats is None else stats,
                             full=self.options.residual_cone)
        operators = {}
        for i, h in hits.items():
            if previous is not None and previous.get(i) is h:
                operators[i] = entry["operators"][i]
            else:
                operators[i] = gather_operator(h, len(g["x"]))
        entry = {"poses": poses, "sources": sources, "offsets": offsets, "spheres": spheres, "hits": hits,
                 "operators": operators, **({"packed": entry["packed"]} if entry and "packed" in entry else {})}
        self.reuse.residual_hits[r.name] = entry
        return entry

    def _world_box(self, geo, caster, i) -> np.ndarray:
        """The box (2, 3) of object ``i``'s world vertices, kept with its pose's geometry entry (``"vertex_box"``)."""
        gs = geo[self.objects[i].name]
        if "vertex_box" not in gs:
            gs["vertex_box"] = _points_box(caster.world_vertices(i))
        return gs["vertex_box"]

    @staticmethod
    def _facing(geo, s) -> np.ndarray:
        """``_residual._facing`` of source ``s``'s world vertex normals, kept with its pose's geometry entry."""
        gs = geo[s.name]
        if "facing" not in gs:
            gs["facing"] = _facing(gs["n"])
        return gs["facing"]

    def _residual_light(self, geo, r, residuals, phi_r, method: str = "numba"):
        """The residual gather (V, K', C) on receiver ``r`` from the sources of ``phi_r`` (the pairs not
        skipped by ``threshold``; itself too with ``self_interreflection``): one pass over the hits per source
        (:func:`apply_gather`), or with ``method="reference"`` the float64 sum over the hits
        (:func:`gather_residual`)."""
        g = geo[r.name]
        entry = self._residual_entry(geo, r, phi_r)
        out = np.zeros(g["g_cos"].shape[:2] + (3,))
        for i, op in entry["operators"].items():
            residual = residuals[self.objects[i].name]
            if method == "reference":
                out += gather_residual(entry["hits"][i], residual, len(g["x"]))
            else:
                apply_gather(op, residual, out)
        return out

    def _whole_light(self, geo, r, phi_r, weights):
        """``residual_whole``: on the receiver points with a near hit on a source (:meth:`_near_corrections`'s
        near hits), the ray gather of the source's projected radiance ``P(colour L)`` less its basis irradiance
        ``Phi w`` (V, K', C), so that with the residual gather those points gather the whole radiance."""
        g = geo[r.name]
        entry = self._residual_entry(geo, r, phi_r)
        out = np.zeros(g["g_cos"].shape[:2] + (3,))
        for i, op in entry["operators"].items():
            s = self.objects[i]
            near = self.reuse.near_hits.get((r.name, i))
            if near is None or near[0] is not entry["hits"][i] or not len(near[2][0]):
                continue
            rows = np.unique(near[0].rows[near[2][0]])
            w = weights[s.name]  # (K, N, C)
            basis = phi_r.get(s.name) if s.name != r.name else self.self_irradiance[r.name]
            projected = np.einsum("nv,knc->vkc", self.bases[s.name].basis, w)
            gathered = apply_gather(op, projected, np.zeros_like(out))
            out[rows] += gathered[rows]
            if basis is not None:
                out[rows] -= np.einsum("vqkn,knc->vqc", np.asarray(basis)[rows], w)
        return out

    def _near_on(self, lights) -> bool:
        """Whether ``residual_near`` applies: the ray-traced direct light and an area or point light."""
        return (self.options.residual_near > 0 and self.options.shadows == "rays"
                and any(isinstance(light, (AreaLight, PointLight)) for light in lights))

    def _near_corrections(self, geo, phi, lights) -> dict:
        """The first bounce's near-hit corrections ``{receiver: (V, K', C)}``: over the residual gather's hits nearer
        than ``residual_near`` edge lengths, each source's ``colour_k L_k`` from the area and point lights by
        shadow rays at the hit point (:func:`ray_traced_direct`, ``residual_near_samples`` per area light; one
        call per source over every receiver's near hits) less its interpolation from the source's vertices
        (:func:`near_hit_correction`). Stand while the poses, the sources and the lights do; the near hits
        (:func:`near_hits`) while the receiver's hits do."""
        near = [light for light in lights if isinstance(light, (AreaLight, PointLight))]
        entries = {r.name: self._residual_entry(geo, r, phi[r.name]) for r in self.objects}
        key = (tuple(geo[o.name]["pose"] for o in self.objects), tuple(e["sources"] for e in entries.values()),
               repr([light.to_dict() for light in near]))
        if self.reuse.near_exact.get("key") == key:
            return self.reuse.near_exact["corrections"]
        caster, spheres = self._scene_caster(geo, key[0])
        selected = {}  # source index -> [(receiver, hits, index, points, normals)]
        for r in self.objects:
            for i, hits in entries[r.name]["hits"].items():
                cached = self.reuse.near_hits.get((r.name, i))
                if cached is None or cached[0] is not hits or cached[1] != self.options.residual_near:
                    cached = self.reuse.near_hits[(r.name, i)] = (hits, self.options.residual_near, near_hits(
                        hits, geo[r.name]["x"], caster.world_vertices(i), geo[self.objects[i].name]["n"],
                        self.options.residual_near))
                if len(cached[2][0]):
                    selected.setdefault(i, []).append((r.name, hits, *cached[2]))
        for i in selected:  # made here, then read by the tasks
            self._shadow_blockers(caster, key[0], i)

        def source(i, parts):  # a task of run_tasks: the source's near-hit light and each part's correction
            colour = np.asarray(self.seps[self.objects[i].name].colour, float)[None]
            counts = {"rays_cast": 0}
            exact = self._near_exact(i, parts, caster, spheres, near, key[0], counts)
            vertex = self.reuse.direct_rays[self.objects[i].name]["light_k"] * colour  # its vertices' L_k
            bounds = np.cumsum([0] + [len(p[2]) for p in parts])
            return len(exact), counts["rays_cast"], [
                near_hit_correction(hits, index, exact[a:b] * colour, vertex, len(geo[name]["x"]))
                for (name, hits, index, _, _), a, b in zip(parts, bounds[:-1], bounds[1:])]

        done = run_tasks([functools.partial(source, i, parts) for i, parts in selected.items()],
                           [sum(len(p[2]) for p in parts) for parts in selected.values()])
        out = {r.name: np.zeros(geo[r.name]["g_cos"].shape[:2] + (3,)) for r in self.objects}
        stats = self.reuse.residual_counts
        for parts, (n_hits, n_rays, corrections) in zip(selected.values(), done):
            stats["near_hits"] = stats.get("near_hits", 0) + n_hits
            stats["near_rays_cast"] = stats.get("near_rays_cast", 0) + n_rays
            for (name, *_), correction in zip(parts, corrections):
                out[name] += correction
        self.reuse.near_exact = {"key": key, "corrections": out}
        return out

    def _near_exact(self, i: int, parts, caster, spheres, lights, poses, counts: dict) -> np.ndarray:
        """``L_k`` (Q, K, C) of the lights at source ``i``'s near hits (``parts``' points one after another), as
        :func:`ray_traced_direct` (``residual_near_samples``, seed ``1 + i``) computes it; the shadow rays cast are
        added to ``counts["rays_cast"]``.

        Per light the terms and shadow masks are kept (``FrameReuse.near_sources``). When the lights' geometry,
        the source's pose and the ray offsets stand, the leading parts whose near-hit points and normals are the
        same arrays as before keep their random streams, so :func:`light_terms` recomputes only their points
        whose segments may meet a moved object's bounding sphere (before or after) and re-casts only those
        samples; the points after them are cast anew (``first=``): the result equals the full call bit for
        bit. With ``residual_near_probe`` a hit takes the answer its triangle's vertices agree on in the frame's
        direct light (:meth:`_near_decided`; ``decided=`` of :func:`light_terms`)."""
        s = self.objects[i]
        f, sep, m = brdf.from_material(s.material), self.seps[s.name], self.options.residual_near_samples
        blockers = self._shadow_blockers(caster, poses, i)
        light_keys = [(type(light).__name__, *(np.asarray(getattr(light, a), float).tobytes()
                                               for a in ("center", "u", "v", "position") if hasattr(light, a)))
                      for light in lights]
        identity = [(p[0], p[3], p[4]) for p in parts]
        old = self.reuse.near_sources.get(i)
        same = [old is not None and k < len(old["parts"]) and name == old["parts"][k][0]
                and (points is old["parts"][k][1] or np.array_equal(points, old["parts"][k][1]))
                and (normal is old["parts"][k][2] or np.array_equal(normal, old["parts"][k][2]))
                for k, (name, points, normal) in enumerate(identity)]
        if old is not None and all(same) and len(identity) == len(old["parts"]):  # the parts stand: points as before
            at, normals, corners = old["at"], old["normals"], old["corners"]
        else:
            at, normals = (np.concatenate([p[k] for p in parts]) for k in (3, 4))
            corners = np.concatenate([hits.faces[hits.triangles[index]] for _, hits, index, _, _ in parts])
        kept = 0  # points of the leading parts that stand
        if (old is not None and old["light_keys"] == light_keys and old["samples"] == m
                and old["offsets"] == (caster.epsilon, caster.tnear) and old["poses"][i] == poses[i]):
            kept = sum(len(points) for (_, points, _), _ in zip(identity, itertools.takewhile(bool, same)))
            moved = np.array([widened_sphere(sphere, caster.epsilon) for j in range(len(poses))
                              if old["poses"][j] != poses[j] for sphere in (old["spheres"][j], spheres[j])])
        wo = normals  # toward the normal: mirror_wo(normals, normals) is the normals themselves (n . n >= 0)
        light_k, terms = np.empty((len(at), sep.K, 3)), []
        for li, light in enumerate(lights):
            decided = self._near_decided(s.name, li, corners) if self.options.residual_near_probe else None
            calls = [(kept, len(at), {})]  # the points after the standing parts: cast anew
            if kept:  # the standing parts: their previous masks and terms
                S_old, F_old, mask_old, decided_old = old["terms"][li]
                calls.insert(0, (0, kept, dict(visibility=mask_old[:kept], moved=moved,
                                               previous=(S_old[:kept], F_old[:kept]),
                                               decided_before=None if decided_old is None else decided_old[:kept])))
            whole = (np.empty((len(at), sep.K)), np.empty((len(at), f.channels)),
                     np.empty((len(at), sample_count(light, m)), np.bool_))
            for a, b, extra in calls:  # each part written into its rows of ``whole``
                if b > a or len(calls) == 1:
                    light_terms(at[a:b], normals[a:b], wo[a:b], f, sep, caster, light, li, m, seed=1 + i,
                                stats=counts, blockers=blockers, first=a, **extra,
                                decided=None if decided is None else decided[a:b], out=tuple(w[a:b] for w in whole))
            terms.append((*whole, decided))
            light_outer_kernel(np.ascontiguousarray(terms[-1][0], np.float64),  # (Q, K, 3): light_k + S radiance
                               np.broadcast_to(light.radiance if isinstance(light, AreaLight) else light.intensity,
                                               (3,)).astype(np.float64), light_k, li > 0)
        self.reuse.near_sources[i] = dict(light_keys=light_keys, samples=m, offsets=(caster.epsilon, caster.tnear),
                                          poses=poses, spheres=spheres, parts=identity, at=at, normals=normals,
                                          corners=corners, terms=terms)
        return light_k if lights else np.zeros((len(at), sep.K, 3))

    def _near_decided(self, source: str, light: int, corners, method: str = "numba") -> np.ndarray:
        """(Q,) int8 of ``residual_near_probe`` at near hits on ``source`` whose triangles have the vertices
        ``corners`` (Q, 3): 1 where the three vertices have every sample of light number ``light`` clear in the
        frame's direct light (:meth:`direct_step_rays`' masks) and some of it lit, 2 where every sample is blocked
        at all three, else 0. ``method``: one pass of :func:`near_decided_kernel`, or ``"reference"`` (numpy)."""
        entry = self.reuse.direct_rays[source]["lights"][light]
        mask = entry["mask"]
        if method != "reference":
            out = np.empty(len(corners), np.int8)
            near_decided_kernel(np.ascontiguousarray(mask), np.ascontiguousarray(entry["S"]),
                                np.ascontiguousarray(corners), out)
            return out
        code = np.zeros(len(mask), np.int8)  # bits: 1 clear and lit, 2 blocked; their AND over a triangle agrees
        code[~mask.any(axis=1) & entry["S"].any(axis=1)] = 1
        code[mask.all(axis=1)] = 2
        at = code[corners]
        return at[:, 0] & at[:, 1] & at[:, 2]

    def _overlapped(self, state: FrameState, geo, occ, transfer, t0: float):
        """``((*direct_step, transfer), basis_irradiance_step, seconds to the direct step's end, seconds from there to
        the end)`` of :data:`OVERLAP`: the SH transfer (``transfer``, or its call when it is one), step 1, then each
        receiver's residual-gather entry as soon as its ``Phi`` is made, on a second thread (numba's thread count
        carried over) while step 2 runs here; the entries not started when step 2 ends are made here.

        The worker's first task makes the scene caster and the direct light's reuse entries; each entry task writes
        its receiver's entry and its own ray counts (added to the frame's at the end); step 2 its pairs, blockers
        and near field; any may fill the same pose-derived entries of ``geo``, with the same values.
        """
        threads = numba.get_num_threads()
        ended = []

        def direct():
            numba.set_num_threads(threads)
            if self.options.residual_rays:  # the entries' caster, before any entry task
                self._scene_caster(geo, tuple(geo[o.name]["pose"] for o in self.objects))
            sh_transfer = transfer() if callable(transfer) else transfer
            out = (*self.direct_step(state, geo, sh_transfer), sh_transfer)
            ended.append(time.perf_counter())
            return out

        def entry(r, phi_r, stats):
            numba.set_num_threads(threads)
            self._residual_entry(geo, r, phi_r, stats)

        tasks = []  # (future, receiver, Phi[r], ray counts)
        worker = _tasks.side_worker()
        step1 = worker.submit(direct)

        def done(r, phi_r):
            stats = {"rays_cast": 0}
            tasks.append((worker.submit(entry, r, phi_r, stats), r, phi_r, stats))

        try:
            step2 = self.basis_irradiance_step(geo, occ, done=done if self.options.residual_rays else None)
            step1.result()  # the scene caster stands before an entry is made here
            for future, r, phi_r, stats in tasks:
                if future.cancel():  # not started: made here
                    self._residual_entry(geo, r, phi_r, stats)
        finally:  # no task of this frame runs on after it
            for future in [step1] + [task[0] for task in tasks]:
                if not future.cancel():
                    futures_wait([future])
        for future in [step1] + [task[0] for task in tasks]:
            if not future.cancelled():
                future.result()
        for *_, stats in tasks:
            self.reuse.residual_counts["rays_cast"] += stats["rays_cast"]
        return step1.result(), step2, ended[0] - t0, time.perf_counter() - ended[0]

    def shade_frame(self, state: FrameState, bounces: int) -> ShadeResult:
        times = {}
        self.reuse.residual_counts = {"rays_cast": 0}
        t0 = time.perf_counter()
        light_points = self._light_points(state.lights)
        key = (self._pose_key(state), None if light_points is None else light_points.tobytes())
        if self.reuse.frame is not None and self.reuse.frame[0] == key:
            geo, occ, transfer = self.reuse.frame[1]
        else:  # poses, camera or the lights' extent changed: look the fields up again
            geo = self._frame_geometry(state)
            occ = self._occlusion(geo)
            # shadows="rays" needs the SH transfer for an environment light alone
            rays_only = self.options.shadows == "rays" and not any(isinstance(light, EnvironmentLight)
                                                                   for light in state.lights)
            transfer = None if rays_only else functools.partial(self.direct_transfer, geo, occ, state.lights)
        poses = tuple(geo[o.name]["pose"] for o in self.objects)
        if OVERLAP and bounces and concurrent_kernels() and (self.reuse.scene_caster is None
                                                             or self.reuse.scene_caster[0] != poses):
            (light_k, direct, transfer), (phi, counts), times["direct"], times["basis_irradiance"] = \
                self._overlapped(state, geo, occ, transfer, t0)
        else:
            transfer = transfer() if callable(transfer) else transfer
            light_k, direct = self.direct_step(state, geo, transfer)
            times["direct"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            phi, counts = self.basis_irradiance_step(geo, occ) if bounces else ({o.name: {} for o in self.objects},
                                                                                {})
            times["basis_irradiance"] = time.perf_counter() - t0
        self.reuse.frame = (key, (geo, occ, transfer))
        indirect, t_weights, t_bounces, t_near = self._bounces(geo, phi, light_k, bounces, state.lights)
        times["weights"], times["bounces"], times["near_hits"] = t_weights, t_bounces, t_near
        result = ShadeResult()
        for o in self.objects:
            result.direct[o.name] = direct[o.name]
            result.indirect[o.name] = indirect[o.name]
            result.total[o.name] = direct[o.name] + indirect[o.name]
        result.info = {"method": self.method, "bounces": bounces, "timings": times, **counts,
                       "residual_rays_cast": self.reuse.residual_counts["rays_cast"],
                       "residual_near_hits": self.reuse.residual_counts.get("near_hits", 0),
                       "residual_near_rays_cast": self.reuse.residual_counts.get("near_rays_cast", 0),
                       "direct_rays_cast": self.reuse.direct_counts["rays_cast"]}
        return result


def precompute(scene, options=None, cache=True, progress: bool = True) -> Interreflection:
    """``Interreflection.precompute``: the slow, cached phase; then ``.shade(state, bounces)`` per frame."""
    return Interreflection.precompute(scene, options, cache=cache, progress=progress)


def shade_scene(scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
    """Entry point of ``prtlab.shade(scene, method="interreflection", bounces=..., **options)``.

    Options are the fields of :class:`InterreflectionOptions`; ``cache`` as in
    :meth:`prtlab.pipeline.Precomputation.precompute`.
    """
    return Interreflection.shade_scene(scene, bounces=bounces, cache=cache, progress=progress, **options)
