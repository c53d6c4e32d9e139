"""Yue et al. 2009: interiors lit through portals by a dynamic environment.

Portals and shells (Section 3.1), the direct transfer as 8-bit pulse/Haar
cubemaps per vertex (Section 4.1.2), the indirect transfer as SH vectors by
photon tracing from the portal and final gathering (Section 4.1.1), run-time
passes (Section 5), portal materials (Section 3.3) and the validity criteria
of dynamic exteriors (Section 6).

Departure (issue 17): by default a diffuse interior's indirect light is driven
by each frame's direct radiance through a precomputed interior-to-interior
transfer (``indirect="surface"``, :mod:`prtlab.portals._surface`), so a sharp
sun bounces from where it lands; the paper's SH transfer is
``indirect="paper"``. Measured in ``docs/notes/portals.md``.

Per frame only the light (the environment, or shell cubemaps per portal) and the camera change. Objects inside
are precomputed: moving one (a pose in the ``FrameState``, or the scene's object edited in place) is refused with
a one-line error; re-precompute at the new pose. A window may open and close (option ``portal_strips``: the
portal object's deformation in the ``FrameState`` is its open part, the rest a black shutter).
Interior point and area lights (placed at precompute time, their emission per frame) light the room with the sky,
and option ``leaving_order`` gives the radiance leaving each portal toward the exterior (``docs/notes/portals.md``,
section 14).
"""

from ._direct import (direct_transfer, glossy_direct_transfer, phong_lipschitz, strip_frame, strip_weights,
                      view_interpolation)
from ._exterior import exterior_shell
from ._interior import interior_light_factor, leaving_radiance, leaving_transfer
from ._indirect import (PhotonMap, disc_coverage, final_gather, phong_lobe_sample, phong_lobe_zh, radiance_estimate,
                        trace_photons)
from ._pipeline import PAPER_OPTIONS, Portals, PortalsOptions, precompute, shade_scene
from ._shade import direct_pass, glossy_direct_pass, glossy_indirect_pass, glossy_lobe_pass, indirect_pass
from ._shell import Portal, find_portals, frosted, shell_light, shell_sh, tint
from ._validity import PortalValidityWarning, check_interior_solid_angle, check_shell_distance

__all__ = [
    # portals and shells
    "Portal",
    "find_portals",
    "shell_light",
    "shell_sh",
    "tint",
    "frosted",
    "exterior_shell",
    # precomputation
    "direct_transfer",
    "glossy_direct_transfer",
    "view_interpolation",
    "phong_lipschitz",
    "strip_frame",
    "strip_weights",
    "phong_lobe_zh",
    "phong_lobe_sample",
    "PhotonMap",
    "trace_photons",
    "radiance_estimate",
    "disc_coverage",
    "final_gather",
    # interior lights and the light leaving through the portals (the paper's future work)
    "interior_light_factor",
    "leaving_transfer",
    "leaving_radiance",
    # run time
    "direct_pass",
    "indirect_pass",
    "glossy_direct_pass",
    "glossy_lobe_pass",
    "glossy_indirect_pass",
    # pipeline
    "PAPER_OPTIONS",
    "Portals",
    "PortalsOptions",
    "precompute",
    "shade_scene",
    # validity (Section 6)
    "PortalValidityWarning",
    "check_shell_distance",
    "check_interior_solid_angle",
]
