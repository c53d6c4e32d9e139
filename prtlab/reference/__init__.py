"""Monte Carlo ground truth: small estimators for tests and the Mitsuba 3 adapter."""

from ._estimators import (
    PATHS_PER_CHUNK,
    Estimate,
    direct,
    irradiance_at,
    path_trace,
    radiance_at,
    shade_reference,
)
from ._mitsuba import MitsubaUnavailable, mitsuba_variant, render_mitsuba, shade_mitsuba, to_mitsuba

__all__ = [
    "MitsubaUnavailable",
    "mitsuba_variant",
    "render_mitsuba",
    "shade_mitsuba",
    "to_mitsuba",
    "PATHS_PER_CHUNK",
    "Estimate",
    "direct",
    "irradiance_at",
    "path_trace",
    "radiance_at",
    "shade_reference",
]
