"""Guerrero, Jeschke, Wimmer 2008: spherical lights (issue 6).

Sphere-set fitting (Sec. 4.1), surface samples and albedo (Sec. 4.2), the
direct soft shadows of Ren et al. 2006 (Sec. 5.1, Eqs. 3-8), the tables
(Eqs. 10, 16-17), the first and second pass (Eqs. 9-24, per-sphere and
per-object blocking), the ground in light transport (option ``ground``, an extension), local lights (Sec. 7.3,
option ``local_lights``), hierarchies of lights with
the reflection ratio (Sec. 7.3, option ``hierarchy_children``), soft
deformations (Sec. 7.1, ``SphereLights.shade(..., deformed=...)``) and the
pipeline ``SphereLights`` (``prtlab.shade(scene, method="spherelights")``).
"""

from ._fit import SphereFit, fit_spheres, sphere_set_coverage, sphere_set_figure
from ._pipeline import PAPER_OPTIONS, SphereLightOptions, SphereLights, WorldLights, light_motions, precompute, shade_scene
from ._ground import (ground_blocked_transfer, ground_hidden_projection, ground_light, ground_raster, ground_rectangles,
                      ground_texture, hidden_transfer)
from ._hierarchy import (LightHierarchy, bounding_sphere, build_hierarchy, cluster_samples, per_light_indirect,
                         receiver_clusters, reflection_ratio, select_cut)
from ._passes import accumulate_blockers, emission_times_direction, first_pass, second_pass
from ._samples import coverage_weights, segment_coverage, segment_of, surface_albedo_sh, surface_samples
from ._shadows import adjust_blockers, blocker_log_sum, direct_irradiance, environment_transfer
from ._tables import average_radiance_weight, irradiance_kernel_zh, voronoi_cell_sums, w_theta_zh

__all__ = [
    "SphereFit",
    "fit_spheres",
    "sphere_set_coverage",
    "sphere_set_figure",
    # direct soft shadows (Ren et al. 2006)
    "adjust_blockers",
    "blocker_log_sum",
    "direct_irradiance",
    "environment_transfer",
    # precomputed tables (Eqs. 10, 16-17)
    "average_radiance_weight",
    "irradiance_kernel_zh",
    "voronoi_cell_sums",
    "w_theta_zh",
    # surface samples and albedo (Sec. 4.2)
    "segment_of",
    "surface_albedo_sh",
    "surface_samples",
    # the segments' projected coverage, weights of the emission (an extension)
    "coverage_weights",
    "segment_coverage",
    # the ground in light transport: it hides and reflects (an extension)
    "ground_blocked_transfer",
    "ground_hidden_projection",
    "hidden_transfer",
    "ground_light",
    "ground_raster",
    "ground_rectangles",
    "ground_texture",
    # hierarchies of spherical lights and the reflection ratio (Sec. 7.3)
    "LightHierarchy",
    "bounding_sphere",
    "build_hierarchy",
    "cluster_samples",
    "per_light_indirect",
    "receiver_clusters",
    "reflection_ratio",
    "select_cut",
    # run-time passes (Secs. 5-7)
    "accumulate_blockers",
    "emission_times_direction",
    "first_pass",
    "second_pass",
    # the pipeline (prtlab.shade(scene, method="spherelights"))
    "PAPER_OPTIONS",
    "SphereLightOptions",
    "SphereLights",
    "WorldLights",
    "light_motions",
    "precompute",
    "shade_scene",
]
