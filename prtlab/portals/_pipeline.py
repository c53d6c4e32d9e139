"""The portals pipeline as a :class:`prtlab.pipeline.Precomputation` (Yue et al. 2009).

Precomputation, per portal (Section 4): the direct transfer cubemaps
(:func:`direct_transfer`), 8-bit encoded in pulse or Haar per vertex
(:func:`prtlab.wavelet.encode_transfer`), and the indirect SH transfer
vectors by photon tracing, radiance estimates and final gathering
(:mod:`prtlab.portals._indirect`). Per frame (Section 5): the shell light of
each portal as a cubemap (direct pass) and its SH projection (indirect pass).

Glossy (Phong, ``ks > 0``) vertices (Section 4.1.2, Appendix): the Lambertian
part ``kd`` as above; the specular direct part as one 8-bit cubemap per
discretised outgoing direction (the texel centres of a ``view_res`` cubemap),
blended bilinearly toward the camera at run time
(:func:`prtlab.portals.view_interpolation`); the specular indirect part as an
SH->SH transfer matrix from the same final-gather rays (Eq. 6). Photons reflect
off glossy objects by their Phong lobe, and the radiance estimate at a glossy
vertex has a specular part (:func:`radiance_estimate`) that gather rays read
toward the gathering point.

The interior is static: every object's transform is in the cache key, and
``shade(state)`` and :meth:`Portals.shade_shells` refuse, in one line, a state in
which an object moved, or a scene whose object was moved in place after the
precomputation (re-precompute at the new pose, e.g. on ``scene.at_frame(i, n)``);
nothing is updated incrementally. The camera may move; the light is
one environment seen through the portals (or user-given shell cubemaps,
:meth:`Portals.shade_shells`: a dynamic exterior from
:func:`prtlab.portals.exterior_shell`, portal materials :func:`prtlab.portals.tint`,
:func:`prtlab.portals.frosted`). Each portal faces the interior whatever its
winding (:func:`find_portals`). The indirect transfer is stored per bounce, so
``shade(bounces=b)`` takes any ``b <=`` the precomputed ``bounces`` option.
A window may open and close (option ``portal_strips``, ``indirect="surface"``): its direct and source transfers
are stored per strip, and a frame gives the open part as the portal object's deformation
(``FrameState.deformations``, :meth:`Portals.opening_vertices`), the closed part a black shutter; any other
motion or deformation is refused, naming the object.
Interior point and area lights (``indirect="surface"``; :mod:`prtlab.portals._interior`) are placed at precompute
time, their emission per frame (``FrameState.lights``, or ``shade_shells(lights=...)``); option ``leaving_order``
gives the radiance leaving each portal, ``shade(...).info["leaving_sh"]``.
Measured accuracy: ``docs/NOTES.md``.

Examples
--------
>>> import prtlab
>>> from prtlab.portals import Portals
>>> scene = prtlab.load_scene(prtlab.api.Path(prtlab.__file__).parents[1] / "data/scenes/box_window_sky.yaml")
>>> pre = Portals.precompute(scene, {"direct_samples": 16, "n_photons": 5000, "gather_rays": 8,
...                                  "cube_resolution": 8},
...                          cache=False, progress=False)
>>> pre.shade(bounces=1).total["room"].shape
(2058, 3)
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import time
import warnings
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from prtlab._validate import check_bool, check_choice, check_float
from prtlab.geometry import RayCaster, cubemap_directions
from prtlab.cache import cache_key
from prtlab.pipeline import FrameState, MemoryNeed, Precomputation, check_int_options, scene_geometry_key_parts
from prtlab.scene import AreaLight, EnvironmentLight, Scene, ShadeResult
from prtlab.wavelet import SparseTransfer, encode_transfer

from . import _surface
from ._direct import (PORTAL_SAMPLERS, direct_transfer, glossy_direct_transfer, strip_frame, strip_weights,
                      view_interpolation)
from ._indirect import CHUNK_BYTES, final_gather, radiance_estimate, trace_photons
from ._interior import INTERIOR_LIGHTS, interior_light_factor, leaving_transfer
from ._shade import (_check_cube, _check_method, direct_from_light, direct_pass, glossy_direct_pass,
                     glossy_indirect_pass, glossy_lobe_pass, indirect_pass, shell_coefficients)
from ._shell import find_portals, shell_light, shell_sh
from ._surface import (SourceOperator, SurfaceTransfer, cluster_vertices, hat_points, hat_projection, mass_matrix,
                       patch_gather, patch_operator, power_sum, quantize_rows, shade_surface, vertex_areas)

__all__ = ["PortalsOptions", "Portals", "shade_scene"]


@dataclass
class PortalsOptions:
    """Options of the portals precomputation (the paper's values in brackets).

    Attributes
    ----------
    cube_resolution : int
        Face resolution (a power of two) of the direct transfer cubemaps and of the shell light [32]; 0: 64, or
        32 with a glossy object under ``glossy_direct="views"`` (its cubemap per view direction grows as ``res^2``:
        the glossy bunny box would need ~25 GB at 64). At 32 a texel cut by the window's edge takes the shell light averaged
        over the whole texel, and a bright sky near the sun put 16% too much light on the sunlit room's wall
        opposite the window.
    direct_samples : int
        Portal points per vertex of the direct transfer [4096], drawn by ``portal_sampler``.
    portal_sampler : {"sobol", "jittered", "random"}
        How the direct transfer's portal points are drawn, uniform by area with each: ``"sobol"`` scrambled
        Sobol' points (on a parallelogram portal mapped affinely, so its edges fall on the net's boxes);
        ``"jittered"`` one point per cell of a grid mapped over the portal's triangles (the sampler before);
        ``"random"`` independent points, the paper's uniform portal samples [random]. Sobol' has the least noise
        at a given count (``docs/notes/portals.md``, section 8).
    n_photons : int
        Photons emitted per portal, shared by all SH bases [2M per basis].
    gather_rays : int
        Final-gather rays per vertex [4096] (stratified for ``indirect="surface"``); with ``target_noise`` the
        starting count.
    target_noise : float
        The gather noise to reach, relative RMS under the scene's own light (0: off, ``gather_rays`` as given).
        The gather runs in two independent halves of the rays; their difference gives each vertex's standard
        error, and ``noise = RMS(stderr) / RMS(indirect)`` over the vertices (``shade(...).info
        ["indirect_noise"]``). While ``noise > target_noise``, more rays are gathered for every vertex (the
        count doubled, or multiplied by the power of two that ``(noise / target)^2`` predicts) up to
        ``max_gather_rays``, with a warning if that is not enough. Covers the final gather only (not the photons
        of ``indirect="paper"``, the hat-averaged operator or the direct transfer). The result then depends on the
        scene's environment, which joins the cache key. A third of the 3% accuracy goal: 0.01.
    max_gather_rays : int
        ``target_noise``: the most gather rays per vertex.
    order : int
        SH order of the indirect transfer [4].
    photon_k : int
        Photons per radiance estimate.
    bounces : int
        Indirect bounces stored (photon depth) [9]; shading takes any ``bounces`` up to it.
    direct_basis : {"auto", "pulse", "haar"}
        Basis of the 8-bit direct transfer: pulse or Haar, or whichever is smaller per vertex ("auto").
    merge_portals : bool
        One portal (and shell) for all portal objects (Section 3.1: windows of one material under a distant
        environment), instead of one per portal object.
    glossy_direct : {"lobe", "views"}
        The specular direct light of glossy vertices. ``"views"``: the paper's one 8-bit transfer cubemap per
        discretised outgoing direction (Section 4.1.2, ``view_res``), blended toward the viewer. ``"lobe"``: each
        frame evaluates the Phong lobe toward the exact view direction at the centre of every shell texel the
        vertex sees, weighted by the vertex's visible cosine-weighted solid angle of that texel (its diffuse
        direct transfer, stored in float32; :func:`prtlab.portals.glossy_lobe_pass`): no view discretisation,
        and close while the lobe spans several texels. On the Fig. 11 bunny (Phong 10, the room at 0.5 m cells)
        the bunny's direct light was 0.088 off Mitsuba with ``"views"`` and 0.018 (noise 0.016) with ``"lobe"``
        (``docs/notes/portals.md``, "Glossy direct light").
    view_res : int
        ``glossy_direct="views"``: face resolution of the cubemap of discretised outgoing directions (one direct
        transfer cubemap per direction, ``6 view_res^2`` of them; Section 4.1.2).
    glossy_order : int
        SH order over the outgoing direction of the glossy indirect matrices (``n_out^2 x order^2``); 0:
        ``order`` (the paper's square matrix). A Phong lobe needs more bands than the light it reflects.
    indirect : {"auto", "surface", "paper"}
        The indirect transfer. ``"paper"``: SH transfer vectors from photons and final gathers (Section 4.1.1),
        the shell light projected on ``order`` SH bands. ``"surface"``: bounces driven by each frame's direct
        radiance of the interior through a precomputed interior-to-interior gather (exact where a sharp sun
        lands; diffuse interiors only; :mod:`prtlab.portals._surface`). ``"auto"``: ``"surface"`` unless an
        interior object is glossy. Measured against Mitsuba in ``docs/notes/portals.md``.
    clusters : int
        ``indirect="surface"``: source patches of the gather; an interior with more vertices is clustered to this
        many (memory and per-frame cost grow as vertices x clusters).
    near_reads : float
        ``indirect="surface"``: gather rays that land closer than this fraction of their triangle's longest edge
        (a vertex on a concave edge sees the adjacent surface from millimetres) read the surface's point values
        at the triangle's corners on the edge the two surfaces share, not the interpolated coefficients
        (``SurfaceTransfer.near_correction``); 0: every ray reads the coefficients (the form before). On the
        sunlit room at a 60-degree sun the window wall's indirect light was 0.046 off with 0 and 0.027 with 0.25
        (``docs/notes/portals.md``, section 10).
    seed : int
        Random seed of the photons and of the direct and gather samples.
    portal_strips : int
        0: the paper's fixed portal. ``K > 0``: a window whose aperture opens and closes per frame (a shutter or
        blind; the paper's future work): the direct transfer and the hat-averaged source transfer are stored per
        strip of each portal, ``K`` strips stacked along its edge nearest the vertical (parallelogram portals
        only; ``indirect="surface"`` only), and each frame sums the open strips (a part-open strip weighted by
        its open fraction); the open part is the portal object's deformation in ``FrameState.deformations``
        (:meth:`Portals.opening_vertices`). At ``K = 8`` on the sunlit room the direct rows take 1.5x, the source
        rows 4.1x, the frame 1.35x half open and 2.3x wholly open (closed strips are skipped); an opening on the
        strips' boundaries is as accurate as the fixed window, a part-open strip costs up to 3.5% of the direct
        light (``docs/notes/portals.md``, "Moving portals").
    light_samples : int
        Interior area lights (:class:`prtlab.scene.AreaLight` in the scene's lights; ``indirect="surface"``): points
        on the light per shading point of its direct light factor (a point light needs one). Interior lights
        (point or area, the paper's future work) are placed at precompute time, their intensity or radiance
        changes per frame; their direct light and every bounce are shaded with the sky's, light reaching a portal
        leaves the room (:mod:`prtlab.portals._interior`; ``docs/notes/portals.md``, section 14).
    leaving_order : int
        0: off. ``n > 0``: precompute the radiance leaving each portal toward the exterior (the interior's lit
        surfaces and area lights seen through the window, averaged over it) as order-``n`` SH per portal; each
        frame gives it in ``shade(...).info["leaving_sh"]`` (``(P, n^2, 3)``; evaluate with
        :func:`prtlab.portals.leaving_radiance`). Fixed windows only (not with ``portal_strips``).
    leaving_rays : int
        ``leaving_order > 0``: (portal point, outward direction) rays per portal of the leaving transfer.
    """

    cube_resolution: int = 0
    direct_samples: int = 4096
    portal_sampler: str = "sobol"
    n_photons: int = 200_000
    gather_rays: int = 4096
    target_noise: float = 0.0
    max_gather_rays: int = 16384
    order: int = 4
    photon_k: int = 32
    bounces: int = 2
    direct_basis: str = "auto"
    merge_portals: bool = False
    glossy_direct: str = "lobe"
    view_res: int = 4
    glossy_order: int = 0
    indirect: str = "auto"
    clusters: int = 1024
    near_reads: float = 0.25
    seed: int = 0
    portal_strips: int = 0
    light_samples: int = 64
    leaving_order: int = 0
    leaving_rays: int = 1_048_576

    def __post_init__(self):
        check_int_options(self, ("direct_samples", "n_photons", "gather_rays", "max_gather_rays", "order",
                                 "photon_k", "view_res", "clusters", "light_samples", "leaving_rays"))
        check_float(self.target_noise, "option target_noise", 0.0, meaning="relative RMS, 0: off")
        check_int_options(self, ("seed", "bounces", "glossy_order", "cube_resolution", "portal_strips",
                                 "leaving_order"), minimum=0)
        if self.cube_resolution & (self.cube_resolution - 1):
            raise ValueError(f"option cube_resolution must be a power of two (Haar on the faces), got "
                             f"{self.cube_resolution}")
        check_bool(self.merge_portals, "option merge_portals")
        check_choice(self.direct_basis, "option direct_basis", ("auto", "pulse", "haar"))
        check_choice(self.indirect, "option indirect", ("auto", "surface", "paper"))
        check_choice(self.glossy_direct, "option glossy_direct", ("lobe", "views"))
        check_choice(self.portal_sampler, "option portal_sampler", PORTAL_SAMPLERS)
        self.near_reads = check_float(self.near_reads, "option near_reads", minimum=0.0, maximum=1.0)


#: The paper's method as options: every extension of this package that changes the result turned off. The
#: indirect light from the SH transfer vectors of photons and final gathers (Section 4.1.1) and the glossy direct
#: light from one 8-bit transfer cubemap per discretised outgoing direction (Section 4.1.2); the extensions that
#: are off by default (``portal_strips``, ``leaving_order``, interior lights) stay off. Both are fixed by the
#: precomputation. ``Portals.precompute(scene, {**options, **PAPER_OPTIONS})`` shades as the paper does; the
#: benchmark's paper-mode frame uses it.
PAPER_OPTIONS = MappingProxyType({"indirect": "paper", "glossy_direct": "views"})


def n_photons_bytes(n_photons: int, bounces: int, n_coeffs: int) -> float:
    """Bytes of a photon map and its radiance estimate's per-photon arrays, at most: every emitted photon stored
    at each of ``bounces`` depths (photons are not ended by Russian roulette, only by escaping), each with five
    3-vectors and a depth (twice, while the map is assembled), a one-hot over the depths and ``n_coeffs`` SH
    values."""
    return float(n_photons) * bounces * (32 + bounces + n_coeffs) * 8.0


def _shaded(scene: Scene):
    return [o for o in scene.objects if not o.portal]


def _is_glossy(obj) -> bool:
    return obj.material.type == "phong" and bool(np.any(np.asarray(obj.material.ks) > 0))


#: glossy vertices per batch of the glossy direct transfer (bounds its dense (batch, J, 6, r, r) memory)
_GLOSSY_BATCH = 16

#: vertices per batch of the (dense, then encoded) direct and source transfers
_DIRECT_BATCH = 512


def _concat_encoded(parts, prefix: str = "") -> dict:
    """Encoded transfers of consecutive row batches as one chunk entry (``counts`` per row for the CSR)."""
    return {f"{prefix}counts": np.concatenate([np.diff(q.indptr) for q in parts]),
            **{f"{prefix}{name}": np.concatenate([getattr(q, name) for q in parts])
               for name in ("indices", "codes", "scale", "basis")}}


@dataclass
class _Interior:
    """The shaded vertices of a scene (its non-portal objects, concatenated in scene order, world space)
    and their materials: what the photons, the direct transfer and the final gather read."""

    points: np.ndarray  # (V, 3) shading points
    normals: np.ndarray  # (V, 3)
    albedo: np.ndarray  # (V, 3) Lambertian albedo
    glossy: np.ndarray  # (V,) bool: Phong with ks > 0
    ks: np.ndarray  # (V, 3), 0 off the glossy vertices
    exponent: np.ndarray  # (V,), 0 off the glossy vertices
    object_albedo: np.ndarray  # (O, 3) per object, for the photons
    object_ks: np.ndarray  # (O, 3)
    object_exponent: np.ndarray  # (O,)
    offsets: np.ndarray  # (O + 1,) first vertex of each object

    @classmethod
    def of(cls, objs) -> "_Interior":
        glossy = [_is_glossy(o) for o in objs]
        ks = [np.asarray(o.material.ks, float) if g else np.zeros(3) for o, g in zip(objs, glossy)]
        exponent = [float(o.material.exponent) if g else 0.0 for o, g in zip(objs, glossy)]
        counts = [o.n_vertices for o in objs]
        return cls(
            points=np.concatenate([o.world_shading_points() for o in objs]),
            normals=np.concatenate([o.world_normals() for o in objs]),
            albedo=np.concatenate([np.tile(o.material.diffuse_albedo, (o.n_vertices, 1)) for o in objs]),
            glossy=np.repeat(np.array(glossy, dtype=bool), counts),
            ks=np.repeat(np.array(ks, dtype=np.float64).reshape(-1, 3), counts, axis=0),
            exponent=np.repeat(np.array(exponent, dtype=np.float64), counts),
            object_albedo=np.array([o.material.diffuse_albedo for o in objs], dtype=np.float64).reshape(-1, 3),
            object_ks=np.array(ks, dtype=np.float64).reshape(-1, 3),
            object_exponent=np.array(exponent, dtype=np.float64),
            offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        )

    @property
    def glossy_row(self) -> np.ndarray:
        """(V,) the row of each vertex among the glossy ones (-1 off them)."""
        row = np.full(len(self.glossy), -1, dtype=np.int64)
        row[self.glossy] = np.arange(int(self.glossy.sum()))
        return row


def _photon_estimates(caster, interior: _Interior, portal, k: int, options: PortalsOptions) -> dict:
    """Section 4.1.1 steps 1a-1b for portal ``k``: photons from the portal, then the per-bounce SH radiance
    estimate at every vertex (``exitance``) and the specular SH->SH response at the glossy ones."""
    if options.bounces == 0:
        return {"exitance": None, "glossy_exitance": None, "seconds": np.array(0.0),
                "n_photons_stored": np.array(0)}
    t0 = time.perf_counter()
    rng = np.random.default_rng([options.seed, k, 1])
    photons = trace_photons(caster, interior.object_albedo, portal, options.n_photons, options.bounces, rng,
                            ks=interior.object_ks, exponent=interior.object_exponent)
    g = np.nonzero(interior.glossy)[0]
    exitance, glossy_exitance, halves = radiance_estimate(
        photons, interior.points, interior.normals, interior.albedo, options.order, options.photon_k,
        depths=options.bounces, glossy=(g, interior.ks[g], interior.exponent[g], options.order),
        surface=(caster, np.repeat(np.arange(len(interior.offsets) - 1), np.diff(interior.offsets))), halves=True)
    return {"exitance": exitance, "glossy_exitance": glossy_exitance,
            "exitance_diff": halves.sum(axis=1).astype(np.float32),
            "seconds": np.array(time.perf_counter() - t0), "n_photons_stored": np.array(len(photons))}


def _direct_part(caster, interior: _Interior, rows: slice, portal, options: PortalsOptions, rng) -> dict:
    """Section 4.1.2 for the vertices ``rows``: the 8-bit direct transfer cubemaps, and for the glossy ones one
    cubemap per discretised outgoing direction (``glossy_*``), in batches of :data:`_GLOSSY_BATCH` vertices."""
    res, basis = options.cube_resolution, options.direct_basis
    encoded, lobe = [], []
    step = max(1, _DIRECT_BATCH // max(options.portal_strips, 1))  # bounds the dense cubemaps and the encoder's arrays
    for b0 in range(rows.start, rows.stop, step):
        b = slice(b0, min(rows.stop, b0 + step))
        t = direct_transfer(caster, interior.points[b], interior.normals[b], portal, options.direct_samples, res,
                            rng, sampler=options.portal_sampler, strips=options.portal_strips)
        encoded.append(encode_transfer(t.reshape(-1, 6, res, res), basis))  # with strips: row v K + j
        if options.glossy_direct == "lobe":  # the glossy rows unquantised (no strips: glossy needs "paper")
            lobe.append(t.reshape(len(t), -1)[interior.glossy[b]])
    entry = _concat_encoded(encoded)
    if options.glossy_direct == "lobe":
        rows_g = np.concatenate(lobe) if lobe else np.zeros((0, 6 * res * res))
        k = np.nonzero(rows_g)
        entry["lobe_counts"] = np.bincount(k[0], minlength=len(rows_g)).astype(np.int64)
        entry["lobe_indices"] = k[1].astype(np.int32)
        entry["lobe_values"] = rows_g[k].astype(np.float32)
        entry.update(_concat_encoded([encode_transfer(np.zeros((0, 6, res, res)), basis)], "glossy_"))  # no views
        return entry
    g = np.nonzero(interior.glossy[rows])[0] + rows.start
    view_dirs = cubemap_directions(options.view_res).reshape(-1, 3)
    parts = [encode_transfer(np.zeros((0, 6, res, res)), basis)]
    for b0 in range(0, len(g), _GLOSSY_BATCH):
        gb = g[b0 : b0 + _GLOSSY_BATCH]
        spec = np.empty((len(gb), len(view_dirs), 6, res, res))
        for e in np.unique(interior.exponent[gb]):
            m = interior.exponent[gb] == e
            spec[m] = glossy_direct_transfer(caster, interior.points[gb[m]], interior.normals[gb[m]], portal,
                                             view_dirs, float(e), options.direct_samples, res, rng,
                                             sampler=options.portal_sampler)
        parts.append(encode_transfer(spec.reshape(-1, 6, res, res), basis))
    entry["glossy_counts"] = np.concatenate([np.diff(q.indptr) for q in parts])
    for name in ("indices", "codes", "scale", "basis"):
        entry[f"glossy_{name}"] = np.concatenate([getattr(q, name) for q in parts])
    return entry


#: sub-points per triangle edge of the hat-averaged source transfer (``indirect="surface"``)
_HAT_SPLIT = 4


def _source_part(caster, interior: _Interior, rows: slice, portal, options: PortalsOptions, rng) -> dict:
    """``indirect="surface"``: the direct transfer averaged over each vertex's hat function (``source_*``, 8-bit
    like the direct transfer), the light a vertex sends on: a sun patch's power is kept whatever the mesh (point
    values at 0.5 m vertices put 4.5% less sun on the sunlit room's floor). ``direct_samples / split^2`` portal
    samples per sub-point (as many rays per vertex as the direct transfer, about twice over). With
    ``portal_strips`` one row per vertex and strip, as the direct transfer."""
    res = options.cube_resolution
    n_samples = max(1, options.direct_samples // _HAT_SPLIT**2)
    encoded = []
    n_strips = max(options.portal_strips, 1)
    # the dense arrays' bytes whatever the strips
    step = max(1, _DIRECT_BATCH // n_strips)
    for r0 in range(rows.start, rows.stop, step):
        sub = slice(r0, min(rows.stop, r0 + step))
        points, normals, weights = hat_points(caster, interior.offsets, interior.normals, sub, _HAT_SPLIT)
        dense = direct_transfer(caster, points, normals, portal, n_samples, res, rng, sampler=options.portal_sampler,
                                strips=options.portal_strips, combine=weights)
        encoded.append(encode_transfer(dense.reshape(-1, 6, res, res), options.direct_basis))
    return _concat_encoded(encoded, "source_")


def _indirect_part(caster, interior: _Interior, rows: slice, estimate: dict, options: PortalsOptions, rng,
                   n_rays: int | None = None) -> dict:
    """Section 4.1.1 step 2 for the vertices ``rows``: the per-bounce SH transfer vectors by final gathering
    (``indirect``, (v, bounces, n*n, 3)) and the glossy vertices' SH->SH matrices (``glossy_matrix``), from
    ``n_rays`` (default ``gather_rays``) rays per vertex in two independent halves, and the difference of the
    halves' transfer vectors summed over the bounces (``indirect_diff``, (v, n*n, 3)), which gives their noise."""
    n_rays = options.gather_rays if n_rays is None else int(n_rays)
    n_c = options.order * options.order
    g = np.nonzero(interior.glossy[rows])[0] + rows.start
    diffuse = np.nonzero(~interior.glossy[rows])[0] + rows.start
    order_out = options.glossy_order or options.order
    gather = dict(glossy_exitance=(interior.glossy_row, estimate["glossy_exitance"]))
    halves = [m for m in (n_rays // 2, n_rays - n_rays // 2) if m > 0]
    parts = []
    for m in halves:
        indirect = np.zeros((rows.stop - rows.start, options.bounces, n_c, 3))
        if len(diffuse):
            indirect[diffuse - rows.start] = final_gather(
                caster, interior.points[diffuse], interior.normals[diffuse], interior.albedo[diffuse],
                estimate["exitance"], interior.offsets, interior.normals, m, rng, **gather)
        matrix = np.zeros((len(g), options.bounces, order_out**2, n_c, 3))
        if len(g):
            indirect[g - rows.start], matrix = final_gather(
                caster, interior.points[g], interior.normals[g], interior.albedo[g], estimate["exitance"],
                interior.offsets, interior.normals, m, rng,
                glossy=(interior.ks[g], interior.exponent[g], order_out), **gather)
        parts.append((indirect, matrix))
    indirect = sum(m * p[0] for m, p in zip(halves, parts)) / n_rays
    matrix = sum(m * p[1] for m, p in zip(halves, parts)) / n_rays
    diff = (parts[0][0] - parts[-1][0]).sum(axis=1)
    return {"indirect": indirect.astype(np.float32), "glossy_matrix": matrix.astype(np.float32),
            "indirect_diff": diff.astype(np.float32)}


def _vertex_chunk(caster, interior: _Interior, portals, estimates, options: PortalsOptions, size: int, patch,
                  i: int) -> dict:
    """Chunk ``i`` (vertices ``i size .. (i + 1) size``) of every portal: ``{"portal<k>": arrays}``, with the
    seconds of its direct and indirect parts; with ``patch`` (``indirect="surface"``) also the rows of the
    interior gather over the source patches (``{"surface": {"gather", "gather_diff", "hat_gather", "seconds"}}``:
    the gather from two independent halves of the rays, their difference giving its noise). One random stream per
    (portal, chunk), so a chunk's result does not depend on which process runs it."""
    rows = slice(i * size, min(len(interior.points), (i + 1) * size))
    out = {}
    if patch is not None:
        t0 = time.perf_counter()
        rng = np.random.default_rng([options.seed, 3, i])
        n_patches = int(patch.max()) + 1
        halves = [patch_gather(caster, interior.points[rows], interior.normals[rows], interior.offsets,
                               interior.normals, patch, n_patches, m, rng, near=options.near_reads)
                  for m in (options.gather_rays // 2, options.gather_rays - options.gather_rays // 2) if m > 0]
        weights = [options.gather_rays // 2, options.gather_rays - options.gather_rays // 2][-len(halves):]
        near = None
        if options.near_reads > 0:
            near = [sum(w * h[j] for w, h in zip(weights, halves)) / options.gather_rays for j in (1, 2)]
            halves = [h[0] for h in halves]
        gather = sum(w * h for w, h in zip(weights, halves)) / options.gather_rays
        diff = halves[0] - halves[-1]
        points, normals, hat_weights = hat_points(caster, interior.offsets, interior.normals, rows, _HAT_SPLIT)
        sub = patch_gather(caster, points, normals, interior.offsets, interior.normals, patch, n_patches,
                           max(16, options.gather_rays // _HAT_SPLIT**2), rng)
        out["surface"] = {"gather": gather, "gather_diff": diff, "hat_gather": (hat_weights @ sub).astype(np.float32),
                          "seconds": np.array([time.perf_counter() - t0])}
        if near is not None:
            out["surface"].update(_near_triplets(near, rows.start))
    for k, portal in enumerate(portals):
        rng = np.random.default_rng([options.seed, k, 2, i])
        t0 = time.perf_counter()
        entry = _direct_part(caster, interior, rows, portal, options, rng)
        t1 = time.perf_counter()
        entry["seconds_direct"] = np.array([t1 - t0])
        if options.bounces > 0 and estimates[k]["exitance"] is not None:
            entry.update(_indirect_part(caster, interior, rows, estimates[k], options, rng))
        if patch is not None:
            entry.update(_source_part(caster, interior, rows, portal, options, rng))
        entry["seconds_indirect"] = np.array([time.perf_counter() - t1])
        out[f"portal{k}"] = entry
    return out


def _extra_gather_chunk(caster, interior: _Interior, estimates, options: PortalsOptions, size: int, patch,
                        n_rays: int, total: int, i: int) -> dict:
    """``target_noise``: ``n_rays`` more final-gather rays (even; two independent halves) for the vertices of chunk
    ``i``, on the way to ``total`` rays per vertex: ``{"surface": {"gather", "gather_diff"}}`` with ``patch``
    (``indirect="surface"``), else ``{"portal<k>": {"indirect", "glossy_matrix", "indirect_diff"}}``."""
    rows = slice(i * size, min(len(interior.points), (i + 1) * size))
    if patch is not None:
        rng = np.random.default_rng([options.seed, 5, total, i])
        n_patches = int(patch.max()) + 1
        a, b = (patch_gather(caster, interior.points[rows], interior.normals[rows], interior.offsets,
                             interior.normals, patch, n_patches, n_rays // 2, rng, near=options.near_reads)
                for _ in range(2))
        if options.near_reads <= 0:
            return {"surface": {"gather": (a + b) / 2, "gather_diff": a - b}}
        near = _near_triplets([(a[j] + b[j]) / 2 for j in (1, 2)], rows.start)
        return {"surface": {"gather": (a[0] + b[0]) / 2, "gather_diff": a[0] - b[0], **near}}
    return {f"portal{k}": _indirect_part(caster, interior, rows, e, options,
                                         np.random.default_rng([options.seed, k, 6, total, i]), n_rays)
            for k, e in enumerate(estimates)}


def _surface_data(chunks: dict, interior: _Interior, patch, areas, project, options: PortalsOptions) -> dict:
    """``indirect="surface"``: the gather ``F``, the bounce operator ``K``, the projection of hat averages and
    ``S_B`` (:mod:`._surface`)."""
    t0 = time.perf_counter()
    gather = chunks["surface"]["gather"]
    operator = patch_operator(chunks["surface"]["hat_gather"], interior.albedo, patch, areas, gather.shape[1],
                              project)
    total = power_sum(operator, options.bounces, project)
    seconds = float(np.sum(chunks["surface"]["seconds"])) + time.perf_counter() - t0
    codes, scale = quantize_rows(gather)
    out = {"gather_codes": codes, "gather_scale": scale, "patch": patch, "areas": areas,
           "operator": operator.astype(np.float32),
           "sum": total.astype(np.float32), "seconds": np.array(seconds)}
    if project is not None:
        out["project"] = project.astype(np.float32)
    if "near_patch_row" in chunks["surface"]:
        out.update(_near_stored(_near_matrices(chunks["surface"], gather.shape)))
    return out


def _near_triplets(near, row0: int) -> dict:
    """The near reads of a chunk of gathers (``(near_patch, near_point)`` sparse, rows from ``row0``) as COO
    triplets with global rows, ``{"<name>_row", "<name>_col", "<name>_value"}``, for :meth:`run_chunks` to join."""
    out = {}
    for name, m in zip(("near_patch", "near_point"), near):
        m = m.tocoo()
        out.update({f"{name}_row": m.row.astype(np.int64) + row0, f"{name}_col": m.col.astype(np.int64),
                    f"{name}_value": m.data})
    return out


def _near_matrices(triplets: dict, gather_shape) -> list:
    """``[near_patch (V, C), near_point (V, V)]`` CSR float64 from joined :func:`_near_triplets`."""
    from scipy.sparse import coo_matrix

    n_v, n_patches = gather_shape
    return [coo_matrix((triplets[f"{name}_value"], (triplets[f"{name}_row"], triplets[f"{name}_col"])),
                       shape=(n_v, columns)).tocsr()
            for name, columns in (("near_patch", n_patches), ("near_point", n_v))]


def _near_stored(near) -> dict:
    """The near reads as stored: per matrix CSR ``indptr``, ``indices`` (int64) and float32 ``values``."""
    out = {}
    for name, m in zip(("near_patch", "near_point"), near):
        out.update({f"{name}_indptr": m.indptr.astype(np.int64), f"{name}_indices": m.indices.astype(np.int64),
                    f"{name}_values": m.data.astype(np.float32)})
    return out


def _gather_noise(data: dict, diff, scene: Scene, options: PortalsOptions) -> dict:
    """The surface transfer's gather noise under the scene's own light: ``stderr (V, 3)`` per vertex, ``|rho (F_1 -
    F_2) S_B s| / 2`` from the two halves of the gather rays (the standard error of their mean), and ``noise``,
    its RMS relative to the RMS indirect radiance (``bounces`` bounces)."""
    e = data["surface"]
    albedo = np.asarray(data["albedo"], dtype=np.float64)
    if scene.environment is None:
        return {"stderr": np.zeros(albedo.shape, np.float32), "noise": np.array(float("nan"))}
    cube = shell_light(scene.environment, options.cube_resolution)
    source, direct = np.zeros_like(albedo), np.zeros_like(albedo)
    n_strips = max(options.portal_strips, 1)
    for k in range(int(data["n_portals"])):
        p = data[f"portal{k}"]
        for prefix, out in (("source_", source), ("", direct)):
            transfer = SparseTransfer(p[prefix + "indptr"], p[prefix + "indices"], p[prefix + "codes"],
                                      p[prefix + "scale"], p[prefix + "basis"], options.cube_resolution)
            out += _block_sum(direct_pass(transfer, np.tile(albedo, (n_strips, 1)), cube), n_strips)
    st = _surface_transfer(e, albedo, options.bounces, mass=None)
    u = st.patch_light(source, options.bounces).astype(np.float64)
    indirect = st.frame(st.patch_source(source), options.bounces, direct=direct)
    stderr = np.abs(albedo * (np.asarray(diff, dtype=np.float64) @ u)) / 2.0
    scale = float(np.mean(indirect**2))
    noise = float(np.sqrt(np.mean(stderr**2) / scale)) if scale > 0 else 0.0
    return {"stderr": stderr.astype(np.float32), "noise": np.array(noise)}


def _surface_transfer(e: dict, albedo, bounces: int, mass) -> SurfaceTransfer:
    """The :class:`SurfaceTransfer` of the stored ``data["surface"]`` entry ``e`` (``mass``: the consistent mass
    matrix of the interior, for the limited projection; None leaves it out)."""
    near = None
    if "near_patch_indptr" in e:
        from scipy.sparse import csr_matrix

        rows = len(e["gather_scale"])
        near = [csr_matrix((np.asarray(e[f"{n}_values"], np.float64), e[f"{n}_indices"], e[f"{n}_indptr"]),
                           shape=(rows, columns))
                for n, columns in (("near_patch", e["gather_codes"].shape[1]), ("near_point", len(albedo)))]
    return SurfaceTransfer((e["gather_codes"], e["gather_scale"]), e["patch"], e["areas"], albedo, e["operator"],
                           {bounces: e["sum"]}, e.get("project"), mass, near=near)


def _block_sum(rows, n_strips: int) -> np.ndarray:
    """``(K V, 3)`` strip-major rows (``j V + v``) summed over the strips, ``(V, 3)``."""
    return rows if n_strips == 1 else rows.reshape(n_strips, -1, 3).sum(axis=0)


def _strip_major(indptr, entries: dict, rows: dict, n_strips: int):
    """A per-strip CSR transfer's rows from vertex-major (``v K + j``, as the chunks make them) to strip-major
    (``j V + v``: each strip a contiguous block of ``V`` rows, so a frame skips a closed strip):
    ``(indptr, entries, rows)`` reordered (``entries``: arrays per stored entry; ``rows``: arrays per row)."""
    n_rows = len(indptr) - 1
    n_v = n_rows // n_strips
    old = (np.arange(n_v)[None, :] * n_strips + np.arange(n_strips)[:, None]).ravel()  # old row of new row j V + v
    counts = np.diff(indptr)[old]
    new_ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    take = np.repeat(indptr[old] - new_ptr[:-1], counts) + np.arange(new_ptr[-1])
    return new_ptr, {n: a[take] for n, a in entries.items()}, {n: a[old] for n, a in rows.items()}


def _paper_noise(data: dict, diffs: list, scene: Scene, options: PortalsOptions) -> dict:
    """``indirect="paper"``: the final gather's noise under the scene's own light, as :func:`_gather_noise`:
    ``stderr = |sum_k (T_1 - T_2)_k . c| / 2`` per vertex from the halves' transfer vectors summed over the bounces
    (``diffs``, one ``(V, n*n, 3)`` per portal), ``c`` the shell light's SH; ``noise`` relative to the RMS indirect
    radiance (the diffuse part; the glossy vertices' specular matrices are not covered)."""
    albedo = np.asarray(data["albedo"], dtype=np.float64)
    if scene.environment is None or not diffs:
        return {"stderr": np.zeros(albedo.shape, np.float32), "noise": np.array(float("nan"))}
    c = shell_sh(shell_light(scene.environment, options.cube_resolution), options.order)
    indirect = np.zeros_like(albedo)
    diff = np.zeros_like(albedo)
    for k, d in enumerate(diffs):
        t = np.asarray(data[f"portal{k}"]["indirect"], dtype=np.float64).sum(axis=1)
        indirect += np.einsum("vic,ic->vc", t, c)
        diff += np.einsum("vic,ic->vc", np.asarray(d, dtype=np.float64), c)
    stderr = np.abs(diff) / 2.0
    scale = float(np.mean(indirect**2))
    noise = float(np.sqrt(np.mean(stderr**2) / scale)) if scale > 0 else 0.0
    return {"stderr": stderr.astype(np.float32), "noise": np.array(noise)}


def _photon_noise(estimates: list, scene: Scene, options: PortalsOptions) -> np.ndarray:
    """``indirect="paper"``: the photon noise of the radiance estimates at the vertices (before the final gather,
    which averages it over its rays' hits), under the scene's own light: ``RMS |sum_k D_k . c| / RMS |sum_k E_k .
    c|`` with ``E`` the exitance summed over the bounces and ``D`` its two path halves' difference
    (:func:`radiance_estimate` ``halves``), ``c`` the shell light's SH."""
    if scene.environment is None or not estimates or estimates[0].get("exitance_diff") is None:
        return np.array(float("nan"))
    c = shell_sh(shell_light(scene.environment, options.cube_resolution), options.order)
    exitance = sum(np.einsum("vdic,ic->vc", np.asarray(e["exitance"], dtype=np.float64), c) for e in estimates)
    diff = sum(np.einsum("vic,ic->vc", np.asarray(e["exitance_diff"], dtype=np.float64), c) for e in estimates)
    scale = float(np.mean(exitance**2))
    return np.array(float(np.sqrt(np.mean(diff**2) / scale)) if scale > 0 else 0.0)


def _assemble(chunks: dict, estimates: list, interior: _Interior, options: PortalsOptions, surface=None) -> dict:
    """The stored data: per portal the sparse direct transfer (CSR ``indptr`` from the chunks' counts), the
    per-bounce indirect transfer (``indirect="paper"``), the seconds of each part; the vertices' materials; and
    with ``surface`` (``(patch, areas)``) the interior-to-interior transfer (:func:`_surface_data`)."""
    data: dict = {"n_portals": np.array(len(estimates)), "albedo": interior.albedo,
                  "glossy": interior.glossy.astype(np.uint8), "ks": interior.ks, "exponent": interior.exponent}
    if surface is not None and options.bounces > 0:
        data["surface"] = _surface_data(chunks, interior, *surface, options)
    for k, estimate in enumerate(estimates):
        c = chunks[f"portal{k}"]
        entry = {"indptr": np.concatenate([[0], np.cumsum(c["counts"])]).astype(np.int64), "indices": c["indices"],
                 "codes": c["codes"], "scale": c["scale"], "basis": c["basis"],
                 "res": np.array(options.cube_resolution),
                 "seconds_direct": np.array(float(np.sum(c["seconds_direct"]))),
                 "seconds_indirect": np.array(float(np.sum(c["seconds_indirect"])) + float(estimate["seconds"])),
                 "n_photons_stored": np.array(int(estimate["n_photons_stored"])),
                 "glossy_indptr": np.concatenate([[0], np.cumsum(c["glossy_counts"])]).astype(np.int64)}
        for name in ("indices", "codes", "scale", "basis"):
            entry[f"glossy_{name}"] = c[f"glossy_{name}"]
        if "lobe_counts" in c:  # glossy_direct="lobe"
            entry["lobe_indptr"] = np.concatenate([[0], np.cumsum(c["lobe_counts"])]).astype(np.int64)
            entry["lobe_indices"], entry["lobe_values"] = c["lobe_indices"], c["lobe_values"]
        if "source_counts" in c:
            entry["source_indptr"] = np.concatenate([[0], np.cumsum(c["source_counts"])]).astype(np.int64)
            for name in ("indices", "codes", "scale", "basis"):
                entry[f"source_{name}"] = c[f"source_{name}"]
        for p in ("", "source_") if options.portal_strips else ():
            if p + "indptr" in entry:
                entry[p + "indptr"], moved, per_row = _strip_major(
                    entry[p + "indptr"], {n: entry[p + n] for n in ("indices", "codes")},
                    {n: entry[p + n] for n in ("scale", "basis")}, options.portal_strips)
                entry.update({p + n: a for n, a in {**moved, **per_row}.items()})
        if options.bounces > 0 and "indirect" in c:
            entry["indirect"] = c["indirect"]
            entry["glossy_matrix"] = c["glossy_matrix"]
        data[f"portal{k}"] = entry
    return data


def _interior_lights(lights) -> list:
    """The interior lights (point and area lights) among ``lights``, in order."""
    return [light for light in lights if isinstance(light, INTERIOR_LIGHTS)]


def _light_geometry(light) -> np.ndarray:
    """What of an interior light the precomputation bakes: its position (point) or rectangle (area), flat."""
    if isinstance(light, AreaLight):
        return np.concatenate([[1.0], light.center, light.u, light.v]).astype(np.float64)
    return np.concatenate([[0.0], light.position]).astype(np.float64)


def _light_emission(light) -> np.ndarray:
    """``E (3,)``: a point light's intensity or an area light's radiance."""
    return np.asarray(light.radiance if isinstance(light, AreaLight) else light.intensity, dtype=np.float64)


def _interior_light_data(caster, interior: _Interior, lights, options: PortalsOptions, rng) -> dict:
    """Per interior light the direct light factor at the vertices (``factor (L, V)``) and, with bounces, averaged
    over each vertex's hat function (``source (L, V)``: the light a vertex sends on, as the hat-averaged source
    transfer of the sky), and the baked geometry (``geometry (L, 10)``, zero-padded)."""
    t0 = time.perf_counter()
    n_v = len(interior.points)
    factor, source = np.zeros((len(lights), n_v)), np.zeros((len(lights), n_v))
    hat_samples = max(1, options.light_samples // _HAT_SPLIT**2)
    for i, light in enumerate(lights):
        factor[i] = interior_light_factor(caster, interior.points, interior.normals, light, options.light_samples, rng)
        if options.bounces > 0:
            for r0 in range(0, n_v, Portals.chunk_vertices):
                rows = slice(r0, min(n_v, r0 + Portals.chunk_vertices))
                points, normals, weights = hat_points(caster, interior.offsets, interior.normals, rows, _HAT_SPLIT)
                source[i, rows] = weights @ interior_light_factor(caster, points, normals, light, hat_samples, rng)
    geometry = np.zeros((len(lights), 10))
    for i, light in enumerate(lights):
        g = _light_geometry(light)
        geometry[i, : len(g)] = g
    return {"factor": factor, "source": source, "geometry": geometry,
            "seconds": np.array(time.perf_counter() - t0)}


class Portals(Precomputation):
    """Precomputed portal transfer of a static interior (Yue et al. 2009)."""

    method = "portals"
    format_version = 9  # 2: vertices shaded at world_shading_points; 3: per-bounce indirect, glossy vertices
    # 4: photons reflect off glossy objects by their Phong lobe too; 5: edge-corrected radiance estimates
    # 6: indirect="surface"; 7: Sobol' portal samples of the direct transfer (portal_sampler); 8: near_reads
    # (and portal_strips); 9: glossy_direct="lobe"
    max_bounces = None
    options_type = PortalsOptions
    renamed_options = {"res": "cube_resolution"}
    resumable = True
    baked_reason = "the portals method precomputes the interior"
    #: a portal object's deformation is its open part (option ``portal_strips``); no other object deforms
    supports_deformations = True

    #: vertices per precomputation chunk (one resumable cache part each)
    chunk_vertices: int = 2048

    def __init__(self, scene: Scene, options, data):
        super().__init__(scene, options, data)
        #: every object's pose when the transfer was made (its matrix, copied: the scene may be edited in place)
        self._baked_poses = {o.name: np.array(o.transform.matrix(), dtype=np.float64) for o in scene.objects}

    def moved_objects(self, state: FrameState) -> list[str]:
        """The objects whose pose in ``state``, or in :attr:`scene` itself (edited in place after the
        precomputation), differs from the pose the transfer was made at (objects added since count as moved)."""
        moved = []
        for o in self.scene.objects:
            baked = self._baked_poses.get(o.name)
            poses = [o.transform] + ([state.transforms[o.name]] if o.name in state.transforms else [])
            tol = 1e-12 * max(1.0, float(np.abs(baked).max())) if baked is not None else 0.0
            if baked is None or any(not np.allclose(t.matrix(), baked, rtol=0.0, atol=tol) for t in poses):
                moved.append(o.name)
        return moved

    def check_state(self, state: FrameState) -> FrameState:
        """The base checks, then: only portal objects deform (their opening, option ``portal_strips``)."""
        state = super().check_state(state)
        others = sorted(n for n in state.deformations if not self.scene.object(n).portal)
        if others:
            raise ValueError(f"method {self.method!r} does not take soft deformations (FrameState.deformations of "
                             f"{others}), only a portal's opening (option portal_strips); re-precompute the deformed "
                             "meshes")
        return state

    def _check_not_moved(self) -> None:
        """Refuse to shade once an object of :attr:`scene` moved (or was added) after the precomputation."""
        moved = self.moved_objects(FrameState())
        if moved:
            raise ValueError(f"{self.baked_reason}: object {moved[0]!r} moved after the precomputation; put it back "
                             "or re-precompute at the new pose (e.g. precompute(scene.at_frame(i, n)))")

    @classmethod
    def cache_key_parts(cls, scene: Scene, options) -> list:
        """Every object's transform is in the key: the photons, gather rays and shadow rays are traced against
        every object where it stands, dynamic or not; with ``target_noise`` the scene's environment too."""
        opts = dataclasses.asdict(options)
        lights = _interior_lights(scene.lights)
        # options that cannot change the data leave the key (so keys made before they existed stay valid)
        unused = (() if lights else ("light_samples",)) + (() if options.leaving_order else ("leaving_order",
                                                                                             "leaving_rays"))
        for name in unused:
            del opts[name]
        parts = [cls.method, cls.format_version, scene_geometry_key_parts(scene, dynamic_transforms=True), opts]
        if lights:  # interior lights' positions are baked (their emission is per frame)
            parts.append([_light_geometry(light) for light in lights])
        env = scene.environment
        if options.target_noise > 0 and env is not None:  # the gather's ray count follows the scene's light
            parts.append(np.asarray(env.image if env.image is not None else env.constant, dtype=np.float64))
        return parts

    def baked_objects(self) -> tuple[str, ...]:
        """Every object: the transfer is traced against the whole scene as it stands."""
        return tuple(o.name for o in self.scene.objects)

    @classmethod
    def check_bounces(cls, bounces, options) -> int:
        """``0 <= bounces <=`` the precomputed ``bounces`` option."""
        bounces = super().check_bounces(bounces, options)
        if bounces > options.bounces:
            raise ValueError(
                f"the transfer was precomputed with bounces={options.bounces}; shade with bounces <= "
                f"{options.bounces}, or precompute again with the bounces option set to {bounces}"
            )
        return bounces

    @classmethod
    def check_lights(cls, lights, options) -> None:
        """Exactly one environment light, seen through the portals, and any interior point and area lights."""
        envs = [light for light in lights if isinstance(light, EnvironmentLight)]
        if len(envs) != 1 or len(envs) + len(_interior_lights(lights)) != len(lights):
            raise ValueError(
                "the portals pipeline is lit by exactly one environment light seen through the portals (and any "
                f"interior point and area lights); got lights {[type(x).__name__ for x in lights]}"
            )

    @classmethod
    def resolved(cls, scene: Scene, options):
        """``options`` with ``cube_resolution=0`` resolved: 32 with a glossy object under ``glossy_direct="views"``
        (a cubemap per view direction), else 64."""
        if options.cube_resolution:
            return options
        views = options.glossy_direct == "views" and any(_is_glossy(o) for o in _shaded(scene))
        return dataclasses.replace(options, cube_resolution=32 if views else 64)

    @classmethod
    def indirect_mode(cls, scene: Scene, options) -> str:
        """The ``indirect`` option resolved: ``"auto"`` is ``"surface"`` unless an interior object is glossy."""
        if options.indirect != "auto":
            return options.indirect
        return "paper" if any(_is_glossy(o) for o in _shaded(scene)) else "surface"

    @classmethod
    def check_scene(cls, scene: Scene, options) -> None:
        """A portal is needed, and a diffuse interior for ``indirect="surface"``; then the memory check
        (:meth:`memory_needs`)."""
        if not any(o.portal for o in scene.objects):
            raise ValueError("the scene has no portal: mark the window objects with 'portal: true'")
        glossy = [o.name for o in _shaded(scene) if _is_glossy(o)]
        if _interior_lights(scene.lights) and cls.indirect_mode(scene, options) != "surface":
            why = f"{glossy[0]!r} is glossy, so indirect='auto' is 'paper'" if glossy else "indirect='paper'"
            raise ValueError(f"interior lights (point and area lights in the scene) need indirect='surface' (the "
                             f"photon SH transfer carries the exterior's light only), but {why}")
        if options.leaving_order and options.portal_strips:
            raise ValueError("option leaving_order needs fixed windows (the leaving transfer is traced through the "
                             "whole window): use portal_strips=0, or leaving_order=0 with portal_strips")
        if options.indirect == "surface" and glossy:
            raise ValueError(f"option indirect='surface' needs a diffuse interior, but {glossy[0]!r} is glossy: "
                             "use indirect='paper' (or 'auto')")
        if options.portal_strips:
            if cls.indirect_mode(scene, options) != "surface":
                why = f"{glossy[0]!r} is glossy, so indirect='auto' is 'paper'" if glossy else "indirect='paper'"
                raise ValueError(f"option portal_strips needs indirect='surface' (the photon SH transfer of "
                                 f"indirect='paper' is made with the whole window open), but {why}: use "
                                 "portal_strips=0 (a fixed window)")
            names = [o.name for o in scene.objects if o.portal]
            for portal in find_portals(scene, [names] if options.merge_portals else None):
                strip_frame(portal)  # refuses a portal that is not one parallelogram
        super().check_scene(scene, cls.resolved(scene, options))

    @classmethod
    def memory_needs(cls, scene: Scene, options) -> tuple[list[MemoryNeed], str]:
        """The per-bounce SH transfer and exitance, the photon map, the dense direct cubemaps of a chunk (and the
        encoder's work arrays, about 8 times their size), the encoded direct transfer (pulse worst case) and the
        final-gather rays of a chunk; for ``indirect="surface"`` instead of the SH transfer, photons and gather
        rays: the interior gather (float32 and its hat average, a float64 copy, the 16-bit codes), the bounce
        operator's power sums (and the dense mass matrix and projection when the patches are the vertices) and the
        hat-averaged source transfer; with ``portal_strips`` the direct and source transfers per strip (with
        ``target_noise``, a refinement round's gathers). The estimate is an upper bound (photons bounded by one per
        bounce); measured against the peak resident memory in
        ``docs/notes/portals.md``."""
        options = cls.resolved(scene, options)
        objs = _shaded(scene)
        n_v = sum(o.n_vertices for o in objs)
        n_g = sum(o.n_vertices for o in objs if _is_glossy(o))
        n_p = 1 if options.merge_portals else max(1, sum(1 for o in scene.objects if o.portal))
        b, n2 = options.bounces, options.order**2
        n_out2 = (options.glossy_order or options.order) ** 2
        texels = 6.0 * options.cube_resolution**2
        views = 6.0 * options.view_res**2 if options.glossy_direct == "views" else 0.0
        strips = max(options.portal_strips, 1)
        # stored entries of a vertex's direct and source rows: every texel (pulse worst case); with strips, every
        # texel per strip but, in pulse ("auto" keeps the smaller basis), one per portal sample in all (the
        # strips' samples add up to direct_samples; a source row averages the sub-points of the vertex's triangles,
        # direct_samples between the 16 of each)
        direct_entries, source_entries = float(texels), n_v * float(texels)
        if strips > 1:
            direct_entries = strips * texels if options.direct_basis == "haar" else min(
                strips * texels, max(texels, float(options.direct_samples)))
            triangles = np.concatenate([np.bincount(np.asarray(o.mesh.faces).ravel(), minlength=o.n_vertices)
                                        for o in objs]).astype(np.float64)
            source_entries = float(np.sum(strips * texels if options.direct_basis == "haar" else np.minimum(
                strips * texels, np.maximum(texels, triangles * options.direct_samples))))
        per_vertex_gather = 4.0 * options.gather_rays * b * n2 * 3 * 8
        needs = [
            MemoryNeed("the per-bounce SH transfer", n_p * (n_v * b * n2 * 3 * 12.0 + n_g * b * n_out2 * n2 * 3 * 12.0)
                       + min(n_v, cls.chunk_vertices) * b * n2 * 3 * 8.0, ("order", "bounces")),
            MemoryNeed("the photon map", n_photons_bytes(options.n_photons, b, n2), ("n_photons", "bounces")),
            MemoryNeed("the dense direct transfer cubemaps",
                       min(n_v, max(1, _DIRECT_BATCH // strips)) * strips * texels * 8.0 * 8, ("cube_resolution",)),
            MemoryNeed("the encoded direct transfer", n_p * (n_v * direct_entries + n_g * views * texels) * 5.0
                       + n_p * (n_g * texels * 8.0 if options.glossy_direct == "lobe" else 0.0),
                       ("cube_resolution", "view_res", "portal_strips")),
            MemoryNeed("the glossy direct cubemaps", min(n_g, _GLOSSY_BATCH) * views * texels * 8.0 * 2,
                       ("view_res", "cube_resolution")),
            MemoryNeed("the final-gather rays", 0.0 if b == 0 else min(min(n_v, 512) * per_vertex_gather,
                                                                      max(float(CHUNK_BYTES), per_vertex_gather)),
                       ("gather_rays", "order", "bounces")),
        ]
        if cls.indirect_mode(scene, options) == "surface":
            needs = [n for n in needs if n.what not in ("the per-bounce SH transfer", "the photon map",
                                                        "the final-gather rays")]
            c = min(n_v, options.clusters) if b > 0 else 0
            needs += [
                MemoryNeed("the interior gather (vertices x clusters)", n_v * c * (4 + 4 + 8 + 2.0), ("clusters",)),
                MemoryNeed("the bounce operator and its power sums", c * c * 3 * 8 * 6.0
                           + (3 * 8.0 * n_v * n_v if n_v <= options.clusters and b > 0 else 0.0), ("clusters",)),
                MemoryNeed("the hat-averaged source transfer", n_p * source_entries * 5.0
                           + (min(n_v, max(1, _DIRECT_BATCH // strips)) + max(1, 512 // strips)) * strips * texels
                           * 8.0,
                           ("cube_resolution", "portal_strips")),
                MemoryNeed("the gather rays of a chunk", 0.0 if b == 0 else 160.0 * max(options.gather_rays, 1 << 22),
                           ("gather_rays",)),
            ]
            if options.target_noise > 0 and b > 0:  # a round's gather and halves' difference, and the new sums
                needs.append(MemoryNeed("the gather's refinement (target_noise)", n_v * c * 16.0, ("clusters",)))
        return needs, f"{n_v:,} vertices"

    @classmethod
    def compute(cls, scene: Scene, options: PortalsOptions, progress: bool, store=None, key=None,
                map_fn=None) -> dict:
        """Per portal: the photon map's radiance estimates (Section 4.1.1, steps 1a-1b), then per chunk of
        :attr:`chunk_vertices` vertices the direct transfer (Section 4.1.2) and the final gather (step 2).

        Each portal's estimates and each chunk are resumable cache parts (:meth:`Precomputation.run_part`,
        :meth:`Precomputation.run_chunks`); ``map_fn`` runs the chunks in parallel.
        """
        options = cls.resolved(scene, options)
        names = [o.name for o in scene.objects if o.portal]
        portals = find_portals(scene, [names] if options.merge_portals and names else None)
        caster = RayCaster(scene)
        interior = _Interior.of(_shaded(scene))
        surface = cls.indirect_mode(scene, options) == "surface"
        estimates = []
        for k, portal in enumerate(portals):
            estimate = functools.partial(_photon_estimates, caster, interior, portal, k,
                                         dataclasses.replace(options, bounces=0) if surface else options)
            estimates.append(estimate() if options.bounces == 0 or surface else  # nothing to store
                             cls.run_part(store, key, ("exitance", k), "portals-photons", estimate))
        patch = areas = project = None
        if surface and options.bounces > 0:
            objects = np.repeat(np.arange(len(interior.offsets) - 1), np.diff(interior.offsets))
            patch = cluster_vertices(interior.points, interior.normals, objects, options.clusters, options.seed)
            areas = vertex_areas(caster)
            project = hat_projection(caster, patch)
        size = cls.chunk_vertices
        n_chunks = max(1, -(-len(interior.points) // size))
        chunk_fn = functools.partial(_vertex_chunk, caster, interior, portals, estimates, options, size, patch)
        chunks = cls.run_chunks(n_chunks, chunk_fn, store=store, key=key, map_fn=map_fn, progress=progress,
                                chunking={"vertices": size})
        data = _assemble(chunks, estimates, interior, options, None if patch is None else (patch, areas, project))
        if "surface" in data or (options.bounces > 0 and "indirect_diff" in chunks.get("portal0", {})):
            refine = functools.partial(_extra_gather_chunk, caster, interior, estimates, options, size, patch)
            data["gather_noise"] = cls._converge_gather(data, chunks, scene, options, refine, n_chunks, store, key,
                                                        map_fn, progress)
            if not surface:
                data["gather_noise"]["photon_noise"] = _photon_noise(estimates, scene, options)
        lights = _interior_lights(scene.lights)
        if lights:
            data["lights"] = _interior_light_data(caster, interior, lights, options,
                                                  np.random.default_rng([options.seed, 17]))
        if options.leaving_order > 0:
            area = [light for light in lights if isinstance(light, AreaLight)]
            for k, portal in enumerate(portals):
                t0 = time.perf_counter()
                w, w_light = leaving_transfer(caster, portal, interior.offsets, interior.normals, options.leaving_order,
                                              options.leaving_rays, np.random.default_rng([options.seed, 18, k]), area)
                data[f"portal{k}"].update(leaving=w, leaving_light=w_light,
                                          seconds_leaving=np.array(time.perf_counter() - t0))
        return data

    @classmethod
    def _converge_gather(cls, data: dict, chunks: dict, scene: Scene, options: PortalsOptions, refine, n_chunks: int,
                         store, key, map_fn, progress) -> dict:
        """The final gather's noise (:func:`_gather_noise`, :func:`_paper_noise`) and, with ``target_noise``, more
        rays for every vertex until it is reached or ``max_gather_rays`` is: the count is multiplied by the power of
        two ``>= (noise / target)^2`` (noise ~ 1 / sqrt(rays)), at least 2, each round's rays in two independent
        halves joined to the old halves in proportion (so the halves stay alike and their difference still gives
        the standard error). Updates ``data`` in place; returns ``{"stderr", "noise", "gather_rays"}``."""
        surface = "surface" in data
        n_portals = int(data["n_portals"])
        if surface:
            sums = {"gather": chunks["surface"]["gather"], "gather_diff": chunks["surface"]["gather_diff"]}
        else:
            sums = {k: {name: chunks[f"portal{k}"][name] for name in ("indirect", "glossy_matrix", "indirect_diff")}
                    for k in range(n_portals)}

        def measure():
            if surface:
                return _gather_noise(data, sums["gather_diff"], scene, options)
            return _paper_noise(data, [sums[k]["indirect_diff"] for k in range(n_portals)], scene, options)

        rays, target = options.gather_rays, options.target_noise
        result = measure()
        while target > 0 and float(result["noise"]) > target and 2 * rays <= options.max_gather_rays:
            t0 = time.perf_counter()
            factor = 2 ** max(1, int(np.ceil(np.log2((float(result["noise"]) / target) ** 2))))
            factor = min(factor, 2 ** int(np.floor(np.log2(options.max_gather_rays / rays))))
            extra_rays = 2 * (-(-rays * (factor - 1) // 2))
            total = rays + extra_rays
            extra = cls.run_chunks(n_chunks, functools.partial(refine, extra_rays, total), store=store,
                                   key=None if key is None else cache_key(key, "gather", total), map_fn=map_fn,
                                   progress=progress, chunking={"vertices": cls.chunk_vertices})
            w_old, w_new = rays / total, extra_rays / total
            if surface:
                for name in sums:
                    sums[name] = (w_old * sums[name] + w_new * extra["surface"][name]).astype(np.float32)
                data["surface"]["gather_codes"], data["surface"]["gather_scale"] = quantize_rows(sums["gather"])
                if "near_patch_row" in extra["surface"]:  # the near reads of all the rays, as the gather
                    st = _surface_transfer(data["surface"], data["albedo"], options.bounces, mass=None)
                    new = _near_matrices(extra["surface"], sums["gather"].shape)
                    data["surface"].update(_near_stored([w_old * a + w_new * b for a, b in zip(st.near, new)]))
                data["surface"]["seconds"] = np.array(float(data["surface"]["seconds"]) + time.perf_counter() - t0)
            else:
                for k in range(n_portals):
                    for name in sums[k]:
                        sums[k][name] = (w_old * sums[k][name] + w_new * extra[f"portal{k}"][name]).astype(np.float32)
                    entry = data[f"portal{k}"]
                    entry["indirect"], entry["glossy_matrix"] = sums[k]["indirect"], sums[k]["glossy_matrix"]
                    entry["seconds_indirect"] = np.array(float(entry["seconds_indirect"]) + (time.perf_counter() - t0)
                                                         / n_portals)
            rays = total
            result = measure()
        if target > 0 and float(result["noise"]) > target:
            warnings.warn(f"portals: the final gather's noise {float(result['noise']):.4g} is above target_noise="
                          f"{target:g} at {rays} gather rays per vertex (max_gather_rays={options.max_gather_rays}); "
                          "raise max_gather_rays", RuntimeWarning, stacklevel=4)
        if surface:
            data["surface"].update(result)
        return {**result, "gather_rays": np.array(rays)}

    # ------------------------------------------------------------------ run time

    def direct_transfer(self, k: int = 0, glossy: bool = False, source: bool = False,
                        strips: tuple[int, int] | None = None) -> SparseTransfer:
        """The 8-bit sparse direct transfer of portal ``k`` (``glossy``: the specular rows of the glossy
        vertices, ``J = 6 view_res^2`` per vertex, vertex-major; ``source``: averaged over each vertex's hat
        function, ``indirect="surface"``). With ``portal_strips = K``: ``K V`` rows, strip-major (row ``j V +
        v``), or with ``strips = (j0, j1)`` the rows of strips ``j0 <= j < j1`` (views)."""
        cached = self.__dict__.setdefault("_direct_cache", {})
        if (k, glossy, source, strips) not in cached:
            if strips is None:
                e = self.data[f"portal{k}"]
                p = "glossy_" if glossy else "source_" if source else ""
                cached[k, glossy, source, strips] = SparseTransfer(
                    np.asarray(e[p + "indptr"], np.int64), e[p + "indices"], e[p + "codes"], e[p + "scale"],
                    e[p + "basis"], int(e["res"]))
            else:
                whole = self.direct_transfer(k, glossy, source)
                n_v = whole.n_vertices // max(self.options.portal_strips, 1)
                a, b = strips[0] * n_v, strips[1] * n_v
                ptr = whole.indptr[a : b + 1]
                cached[k, glossy, source, strips] = SparseTransfer(
                    ptr - ptr[0], whole.indices[ptr[0] : ptr[-1]], whole.codes[ptr[0] : ptr[-1]], whole.scale[a:b],
                    whole.basis[a:b], whole.res)
        return cached[k, glossy, source, strips]

    def indirect_transfer(self, k: int = 0, bounces: int | None = None, glossy: bool = False) -> np.ndarray:
        """Indirect transfer of portal ``k`` for light that bounced ``1..bounces`` times (default: all stored).

        Returns the diffuse transfer vectors ``(V, n*n, 3)``, or with ``glossy`` the specular transfer
        matrices of the glossy vertices ``(V_g, n_out^2, n*n, 3)`` (float32): the sums of the stored per-bounce parts.
        """
        bounces = self._check_bounces(bounces)
        cached = self.__dict__.setdefault("_indirect_cache", {})
        if (k, bounces, glossy) not in cached:
            per_bounce = self.data[f"portal{k}"]["glossy_matrix" if glossy else "indirect"]
            cached[k, bounces, glossy] = np.ascontiguousarray(
                np.asarray(per_bounce[:, :bounces], dtype=np.float64).sum(axis=1), dtype=np.float32)
        return cached[k, bounces, glossy]

    def surface_transfer(self) -> SurfaceTransfer | None:
        """The interior-to-interior transfer of ``indirect="surface"`` (None for ``"paper"``)."""
        if "surface" not in self.data:
            return None
        if "_surface" not in self.__dict__:
            e = self.data["surface"]
            mass = mass_matrix(RayCaster(self.scene)) if e.get("project") is not None else None
            self._surface = _surface_transfer(e, self.data["albedo"], self.options.bounces, mass)
        return self._surface

    def source_operator(self, k: int = 0, strips: tuple[int, int] | None = None):
        """``indirect="surface"``: ``Pbar diag(rho) T_src`` of portal ``k`` (:class:`prtlab.portals._surface.
        SourceOperator`), built on first use from the stored source transfer. With ``portal_strips = K`` its rows
        are (strip, patch) pairs, row ``j C + c``; ``strips = (j0, j1)``: the operator of strips ``j0 <= j < j1``
        (the same entries, its row pointers cut)."""
        cached = self.__dict__.setdefault("_source_cache", {})
        if (k, strips) not in cached:
            surface, n = self.surface_transfer(), self.options.portal_strips
            if strips is not None:
                block = copy.copy(self.source_operator(k))
                block.indptr = block.indptr[strips[0] * surface.n_patches : strips[1] * surface.n_patches + 1]
                cached[k, strips] = block
            elif not n:
                cached[k, strips] = surface.source_operator(self.direct_transfer(k, source=True))
            else:
                pair = (np.arange(n)[:, None] * surface.n_patches + surface.patch[None, :]).ravel()
                cached[k, strips] = SourceOperator(self.direct_transfer(k, source=True), pair,
                                                   np.tile(surface.mean_weight, n), np.tile(surface.albedo, (n, 1)),
                                                   surface.n_patches * n)
        return cached[k, strips]

    # ------------------------------------------------------------------ the aperture (portal_strips)

    def _portals(self) -> list:
        if "_portal_list" not in self.__dict__:
            names = [o.name for o in self.scene.objects if o.portal]
            self._portal_list = find_portals(self.scene, [names] if self.options.merge_portals and names else None)
        return self._portal_list

    def _strip_coordinates(self, name: str, deformed=None):
        """Portal index of portal object ``name`` and ``(u, v, w) (P, 3)`` of its world vertices (or of the
        object-space ``deformed`` ones) in its portal's strip frame (:func:`strip_frame`; ``w`` off the plane,
        in portal sizes); refuses an object that cannot open."""
        obj = self.scene.object(name)
        if not obj.portal:
            raise ValueError(f"only a portal object opens and closes (FrameState.deformations): object {name!r} is "
                             "not a portal; the portals method bakes the interior's shape, re-precompute it deformed")
        if not self.options.portal_strips:
            raise ValueError(f"portal {name!r} is fixed (option portal_strips=0): precompute with portal_strips=K "
                             "(e.g. 8) to open and close it")
        k = next(i for i, p in enumerate(self._portals()) if name in p.names)
        portal = self._portals()[k]
        corner, strip, other = strip_frame(portal)
        normal = np.cross(strip, other)
        basis = np.column_stack([strip, other, normal * portal.size / np.linalg.norm(normal)])
        world = obj.world_vertices() if deformed is None else obj.transform.apply_points(deformed)
        return k, np.linalg.solve(basis, (world - corner).T).T

    def opening_vertices(self, name: str, low: float, high: float) -> np.ndarray:
        """Object-space vertices ``(P, 3)`` of portal object ``name`` open over ``low <= u <= high`` (fractions of
        the window along its strip edge, ``0`` its bottom edge: :func:`prtlab.portals.strip_frame`): the
        deformation that :meth:`shade` takes in ``FrameState.deformations[name]`` (option ``portal_strips``)."""
        low, high = float(low), float(high)
        if not 0.0 <= low <= high <= 1.0:
            raise ValueError(f"the opening must have 0 <= low <= high <= 1 (fractions of the window along its strip "
                             f"edge, 0 at the bottom), got low={low}, high={high}")
        k, uvw = self._strip_coordinates(name)
        corner, strip, other = strip_frame(self._portals()[k])
        u = np.where(uvw[:, 0] < 0.5, low, high)
        world = corner + u[:, None] * strip + uvw[:, 1:2] * other
        t = self.scene.object(name).transform
        return (world - t.translate) @ t.rotation / t.scale

    def openings(self, state: FrameState) -> list | None:
        """The open part of each portal in ``state``, ``[(low, high)]`` per portal (``None``: no portal deformed),
        from the portal objects' deformations (:meth:`opening_vertices`). A deformation must keep the window's
        vertices in place along its other edge and in its plane and move its bottom and top edges to ``low <=
        high`` within it: the window cut to a part of the precomputed one; anything else is refused."""
        if not state.deformations:
            return None
        out: list = [(0.0, 1.0)] * self.n_portals
        for name, deformed in state.deformations.items():
            k, before = self._strip_coordinates(name)
            _, after = self._strip_coordinates(name, deformed)
            tol = 1e-6
            bottom = before[:, 0] < 0.5
            low, high = after[bottom, 0], after[~bottom, 0]
            ok = (np.all(np.abs(before[:, 0] - np.round(before[:, 0])) < tol) and bottom.any() and (~bottom).any()
                  and np.all(np.abs(after[:, 1:] - before[:, 1:]) < tol) and np.ptp(low) < tol and np.ptp(high) < tol
                  and low.min() > -tol and high.max() < 1.0 + tol and low.max() <= high.min() + tol)
            if not ok:
                raise ValueError(
                    f"the open part of portal {name!r} (FrameState.deformations) must be the precomputed window cut "
                    "along its strip edge (the edge nearest the vertical): its bottom and top edges moved to 0 <= "
                    f"low <= high <= 1 within the window, nothing else moved or rotated; got bottom at {low.round(4)}, "
                    f"top at {high.round(4)}; build it with pre.opening_vertices({name!r}, low, high)")
            out[k] = (float(np.clip(low.mean(), 0.0, 1.0)), float(np.clip(high.mean(), low.mean(), 1.0)))
        return out

    def _strip_weights(self, openings) -> list:
        """``(K,)`` open fraction of each strip per portal (``[1.0]`` per portal with ``portal_strips=0``)."""
        n = self.options.portal_strips
        if openings is None:
            return [np.ones(max(n, 1))] * self.n_portals
        if not n:
            raise ValueError("the portals are fixed (option portal_strips=0): give openings=None, or precompute "
                             "with portal_strips=K to open and close them")
        openings = list(openings)
        if len(openings) != self.n_portals:
            raise ValueError(f"give one opening (low, high) per portal ({self.n_portals}), got {len(openings)}")
        weights = []
        for o in openings:
            low, high = (0.0, 1.0) if o is None else (float(o[0]), float(o[1]))
            if not 0.0 <= low <= high <= 1.0:
                raise ValueError(f"an opening must have 0 <= low <= high <= 1 (fractions of the window along its "
                                 f"strip edge, 0 at the bottom), got {o!r}")
            weights.append(strip_weights(n, low, high))
        return weights

    def _check_bounces(self, bounces):
        return self.options.bounces if bounces is None else self.check_bounces(bounces, self.options)

    @property
    def n_portals(self) -> int:
        return int(self.data["n_portals"])

    def view_directions(self, camera=None) -> np.ndarray:
        """Unit directions from the glossy vertices toward the camera (``scene.camera`` by default), ``(V_g, 3)``."""
        camera = camera or self.scene.camera
        objs = _shaded(self.scene)
        points = np.concatenate([o.world_shading_points() for o in objs])[self.data["glossy"].astype(bool)]
        d = np.asarray(camera.position, dtype=np.float64) - points
        norm = np.linalg.norm(d, axis=1, keepdims=True)
        if np.any(norm == 0):
            raise ValueError("the camera sits on a glossy vertex: its view direction is undefined; move the camera")
        return d / norm

    def shade_shells(self, shells, bounces: int | None = None, method: str = "numba", camera=None,
                     openings=None, lights=None) -> ShadeResult:
        """Per-vertex radiance from given shell lights, one ``(6, r, r, 3)`` cubemap per portal.

        Use it for a dynamic exterior (cubemaps rendered from each portal
        centre) or portal materials: ``tint(cube, colour)``, ``frosted(cube, sigma_deg)``.
        ``bounces``: any ``0 <= bounces <=`` the precomputed number (the transfer is
        stored per bounce). ``camera``: the viewer of glossy vertices (default the scene's).
        ``method``: ``"numba"`` (the fast passes) or ``"reference"`` (every pass's float64 reference tier).
        ``openings`` (option ``portal_strips``): per portal ``(low, high)``, the open part ``low <= u <= high``
        of the window along its strip edge (:func:`prtlab.portals.strip_frame`; ``None`` wholly open), the rest
        a black (absorbing) shutter. The direct light and the interior's source light sum the strips, each
        weighted by its open fraction (exact for strips wholly open or closed; a part-open strip's light taken
        as that fraction of the strip's). The indirect light then follows exactly: the interior gather's rays
        that leave through the portal carry no light, as they would off a black shutter (the exterior enters only
        through the direct transfer). Refused once an object of the scene moved after the precomputation.
        ``lights``: the interior lights' emission this frame, ``(L, 3)`` (each point light's intensity or area
        light's radiance, in the scene's order; default the scene's): their direct light and bounces add to the
        sky's. With option ``leaving_order`` the radiance leaving each portal is ``info["leaving_sh"]`` (``(P,
        n^2, 3)`` SH over world directions; :func:`prtlab.portals.leaving_radiance`).
        """
        bounces = self._check_bounces(bounces)
        _check_method(method)
        self._check_not_moved()
        shells = list(shells)
        if len(shells) != self.n_portals:
            raise ValueError(f"give one shell cubemap per portal ({self.n_portals}), got {len(shells)}")
        strip_open = self._strip_weights(openings)
        n_strips = max(self.options.portal_strips, 1)
        objs = _shaded(self.scene)
        albedo = np.asarray(self.data["albedo"], dtype=np.float64)
        n = len(albedo)
        direct = np.zeros((n, 3))
        indirect = np.zeros((n, 3))
        g = np.nonzero(np.asarray(self.data["glossy"]).astype(bool))[0]
        if len(g):
            view = self.view_directions(camera)
            ks = np.asarray(self.data["ks"], dtype=np.float64)[g]
            if self.options.glossy_direct == "lobe":
                n_g = np.concatenate([o.world_normals() for o in objs])[g]
                reflected = 2.0 * np.einsum("vk,vk->v", view, n_g)[:, None] * n_g - view  # the view's mirror
                exponent = np.asarray(self.data["exponent"], dtype=np.float64)[g]
            else:
                rows, weights = view_interpolation(view, self.options.view_res)
                rows += (np.arange(len(g)) * 6 * self.options.view_res**2)[:, None]
        timings = {"direct": 0.0, "indirect": 0.0}
        surface = self.surface_transfer() if bounces > 0 else None
        source = np.zeros((surface.n_patches if surface is not None else 0, 3))
        # one portal, the default frame: its direct pass and its surface indirect light overlapped (shade_surface)
        overlap = (method == "numba" and surface is not None and self.n_portals == 1 and n_strips == 1
                   and not len(g) and "lights" not in self.data and "leaving" not in self.data["portal0"]
                   and _surface.tasks_on())
        for k, cube in enumerate(shells):
            t0 = time.perf_counter()
            cube = np.asarray(cube, dtype=np.float64)
            # portal_strips: the strips not closed, a contiguous block (j0, j1), and their open fractions
            block, w = None, np.ones(1)
            if n_strips > 1:
                is_open = np.nonzero(strip_open[k] > 0)[0]
                block = (int(is_open[0]), int(is_open[-1]) + 1) if len(is_open) else None
                w = strip_open[k][block[0] : block[1]] if block else np.zeros(0)
            rows_albedo = albedo if block is None else (w[:, None, None] * albedo[None]).reshape(-1, 3)
            if method == "reference" or (surface is None and not len(g)):
                if len(w):
                    direct += _block_sum(direct_pass(self.direct_transfer(k, strips=block), rows_albedo, cube,
                                                     method=method), len(w))
            else:  # the shell light's coefficients once, for the direct pass, the glossy rows and the source
                _check_cube(cube, int(self.data[f"portal{k}"]["res"]))
                if overlap:
                    radiance, indirect = shade_surface(self.direct_transfer(k), albedo, cube, self.source_operator(k),
                                                       surface, bounces)
                    direct += radiance
                    timings["direct_and_indirect"] = time.perf_counter() - t0
                    break
                light = shell_coefficients(cube)
                if len(w):
                    direct += _block_sum(direct_from_light(self.direct_transfer(k, strips=block), rows_albedo, light),
                                         len(w))
            if len(g) and self.options.glossy_direct == "lobe":
                e = self.data[f"portal{k}"]
                direct[g] += glossy_lobe_pass(e["lobe_indptr"], e["lobe_indices"], e["lobe_values"], int(e["res"]),
                                              reflected, exponent, ks, cube, method=method)
            elif len(g):
                direct[g] += glossy_direct_pass(self.direct_transfer(k, glossy=True), rows, weights, ks, cube,
                                                method=method)
            t1 = time.perf_counter()
            if surface is not None:
                if not len(w):
                    pass  # every strip closed
                elif method == "reference":
                    source += surface.patch_source(_block_sum(direct_pass(
                        self.direct_transfer(k, source=True, strips=block), rows_albedo, cube, method="reference"),
                        len(w)))
                elif block is None:
                    source += self.source_operator(k).apply(light)
                else:  # rows (strip, patch) of the open block, weighted by their open fraction
                    source += np.einsum("jcx,j->cx", self.source_operator(k, block).apply(light).reshape(
                        len(w), -1, 3), w)
            elif bounces > 0:
                c = shell_sh(cube, self.options.order)
                indirect += indirect_pass(self.indirect_transfer(k, bounces), c, method=method)
                if len(g):
                    indirect[g] += glossy_indirect_pass(self.indirect_transfer(k, bounces, glossy=True), c, view,
                                                        method=method)
            timings["direct"] += t1 - t0
            timings["indirect"] += time.perf_counter() - t1
        emission = self._interior_emission(lights)
        if emission is not None:  # interior lights: direct light, and the hat-averaged light the vertices send on
            t0 = time.perf_counter()
            e = self.data["lights"]
            direct += albedo / np.pi * (np.asarray(e["factor"], dtype=np.float64).T @ emission)
            if surface is not None:
                source += surface.patch_source(albedo / np.pi * (np.asarray(e["source"], dtype=np.float64).T
                                                                 @ emission))
            timings["lights"] = time.perf_counter() - t0
        if surface is not None and not overlap:
            t0 = time.perf_counter()
            indirect = surface.frame(source, bounces, method=method, direct=direct)
            timings["indirect"] += time.perf_counter() - t0
        if "leaving" in self.data["portal0"]:
            t0 = time.perf_counter()
            area = np.zeros((0, 3)) if emission is None else emission[self._area_light_rows()]
            # the direct light read through the window with its hat averages' power (a sun patch's point values
            # at the vertices lose part of it), when the patches are the vertices; else the point values
            sent = None if surface is None else surface.sent_direct(source)
            total = (direct if sent is None else sent) + indirect
            leaving = [self.data[f"portal{k}"]["leaving"] @ total + self.data[f"portal{k}"]["leaving_light"] @ area
                       for k in range(self.n_portals)]
            timings["leaving"] = time.perf_counter() - t0
        result = ShadeResult()
        offsets = np.concatenate([[0], np.cumsum([o.n_vertices for o in objs])])
        for o, a, b in zip(objs, offsets[:-1], offsets[1:]):
            result.direct[o.name] = direct[a:b]
            result.indirect[o.name] = indirect[a:b]
            result.total[o.name] = direct[a:b] + indirect[a:b]
        result.info = {"method": self.method, "bounces": bounces, "timings": timings,
                       "direct_samples": self.options.direct_samples}
        if "leaving" in self.data["portal0"]:
            result.info["leaving_sh"] = np.stack(leaving)
        if self.options.portal_strips:
            result.info["openings"] = [(0.0, 1.0)] * self.n_portals if openings is None else \
                [(0.0, 1.0) if o is None else (float(o[0]), float(o[1])) for o in openings]
        if "gather_noise" in self.data:  # the final gather's, under the scene's own light, all precomputed bounces
            result.info["indirect_noise"] = float(self.data["gather_noise"]["noise"])
            result.info["gather_rays"] = int(self.data["gather_noise"]["gather_rays"])
        if "surface" not in self.data and self.options.bounces > 0:
            result.info["n_photons"] = self.options.n_photons
            if "photon_noise" in self.data.get("gather_noise", {}):  # of the radiance estimates, before the gather
                result.info["photon_noise"] = float(self.data["gather_noise"]["photon_noise"])
        return result

    def _area_light_rows(self) -> np.ndarray:
        """Which interior lights are area lights (their radiance is seen through the window), ``(L,) bool``."""
        return np.asarray(self.data["lights"]["geometry"])[:, 0] == 1.0

    def _interior_emission(self, lights) -> np.ndarray | None:
        """The interior lights' emission ``(L, 3)`` float64 (default: the scene's), None without interior lights."""
        if "lights" not in self.data:
            if lights is not None and len(lights):
                raise ValueError("the scene was precomputed without interior lights: add the point or area lights to "
                                 "the scene and precompute again")
            return None
        n = len(self.data["lights"]["geometry"])
        if lights is None:
            lights = [_light_emission(light) for light in _interior_lights(self.scene.lights)]
        emission = np.asarray(lights, dtype=np.float64)
        if emission.shape != (n, 3) or not np.all(np.isfinite(emission)) or np.any(emission < 0):
            raise ValueError(f"lights must be the {n} interior lights' finite non-negative RGB emission (intensity "
                             f"of a point light, radiance of an area light), shape ({n}, 3); got shape "
                             f"{emission.shape}")
        return emission

    def shade_frame(self, state: FrameState, bounces: int) -> ShadeResult:
        env = next(light for light in state.lights if isinstance(light, EnvironmentLight))
        cube = shell_light(env, int(self.data["portal0"]["res"]))
        interior = _interior_lights(state.lights)
        baked = np.asarray(self.data["lights"]["geometry"]) if "lights" in self.data else np.zeros((0, 10))
        geometry = [_light_geometry(light) for light in interior]
        if len(geometry) != len(baked) or any(
                not np.allclose(g, b[: len(g)], rtol=0.0, atol=1e-9) for g, b in zip(geometry, baked)):
            raise ValueError(f"the interior lights were precomputed where they stand ({len(baked)} of them): a "
                             "frame may change their intensity or radiance, not move, add or remove one; "
                             "re-precompute with the lights at their new places")
        return self.shade_shells([cube] * self.n_portals, bounces, camera=state.camera,
                                 openings=self.openings(state),
                                 lights=[_light_emission(light) for light in interior] if interior else None)

    @classmethod
    def shade_scene(cls, scene: Scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
        """``prtlab.shade(scene, method="portals", bounces=B)``: precompute ``B`` bounces, shade."""
        options.setdefault("bounces", bounces)
        return cls.shade_once(scene, options, bounces, cache=cache, progress=progress)


def shade_scene(scene: Scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
    """Entry point of ``prtlab.shade(scene, method="portals", ...)``; see :class:`Portals`."""
    return Portals.shade_scene(scene, bounces=bounces, cache=cache, progress=progress, **options)


def precompute(scene: Scene, options=None, cache=True, progress: bool = True, map_fn=None) -> Portals:
    """``Portals.precompute``: the slow, cached phase (chunks run through ``map_fn``,
    e.g. :func:`prtlab.api.dask_map`); then ``.shade(state, bounces)`` per frame."""
    return Portals.precompute(scene, options, cache=cache, progress=progress, map_fn=map_fn)
