"""Images: the pinhole camera, per-vertex radiance to pixels, tone mapping, figure helpers."""

from ._camera import camera_frame, camera_rays, pixel_directions, project_points
from ._figures import agreement_plot, comparison_figure, difference_figure, luminance
from ._raster import barycentric_coordinates, interpolate_vertex_values, intersect_area_lights, render_image
from ._tonemap import (
    TONE_CURVES,
    aces_narkowicz,
    load_exr,
    reinhard,
    save_exr,
    save_png,
    srgb_decode,
    srgb_encode,
    tonemap,
)

__all__ = [
    "camera_frame",
    "camera_rays",
    "pixel_directions",
    "project_points",
    "render_image",
    "barycentric_coordinates",
    "interpolate_vertex_values",
    "intersect_area_lights",
    "TONE_CURVES",
    "tonemap",
    "srgb_encode",
    "srgb_decode",
    "reinhard",
    "aces_narkowicz",
    "save_png",
    "save_exr",
    "load_exr",
    "comparison_figure",
    "difference_figure",
    "agreement_plot",
    "luminance",
]
