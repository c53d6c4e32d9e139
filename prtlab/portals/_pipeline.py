"""The portals pipeline as a :class:`prtlab.pipeline.Precomputation` (Yue et al. 2009).

Precomputation, per portal (Section 4): the direct transfer cubemaps
(:func:`direct_transfer`), 8-bit encoded in pulse or Haar per vertex
(:func:`prtlab.wavelet.encode_transfer`), and the indirect SH transfer
vectors by photon tracing, radiance estimates and final gathering
(:mod:`prtlab.portals._indirect`). Per frame (Section 5): the shell light of
each portal as a cubemap (direct pass) and its SH projection (indirect pass).

Scope here: Lambertian vertices (Phong materials with ``ks > 0`` are refused:
the glossy transfer of Section 4.1.2 / Appendix is not implemented), distant
environments or user-given shell cubemaps (:meth:`Portals.shade_shells`),
``bounces`` fixed at precomputation (the transfer stores light with
``1..bounces`` indirect bounces). A dynamic exterior: pass per-frame shells
from :func:`prtlab.portals.exterior_shell`; portal materials:
:func:`prtlab.portals.tint`, :func:`prtlab.portals.frosted`.

Accuracy measured on ``data/scenes/box_window_sky.yaml`` (B = 3, 2048 portal
samples, 2M photons, 1024 gather rays; reference 8192 paths per vertex with
3.7% relative standard error; vertices on two walls left out): average
relative difference of the total 3.9%, 3.0% with the reference's noise
removed at SH order 4 (1.7% at order 8: most of the rest is the SH
truncation of the sky seen through the window, Section 4.2); signed mean -0.2%.

Examples
--------
>>> import prtlab
>>> from prtlab.portals import Portals
>>> scene = prtlab.load_scene(prtlab.api.Path(prtlab.__file__).parents[1] / "data/scenes/box_window_sky.yaml")
>>> pre = Portals.precompute(scene, {"direct_samples": 16, "n_photons": 5000, "gather_rays": 8, "res": 8},
...                          cache=False, progress=False)
>>> pre.shade(bounces=2).total["room"].shape
(2058, 3)
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from prtlab.cache import Cache, cache_key
from prtlab.geometry import RayCaster
from prtlab.pipeline import FrameState, Precomputation, check_int_options
from prtlab.scene import EnvironmentLight, Scene, ShadeResult
from prtlab.wavelet import SparseTransfer, encode_transfer

from ._direct import direct_transfer
from ._indirect import final_gather, radiance_estimate, trace_photons
from ._shade import direct_pass, indirect_pass
from ._shell import find_portals, shell_light, shell_sh

__all__ = ["PortalsOptions", "Portals", "shade_scene"]


@dataclass
class PortalsOptions:
    """Options of the portals precomputation (the paper's values in brackets).

    res : cubemap face resolution of the direct transfer [32].
    direct_samples : portal points per vertex [4096].
    n_photons : photons emitted per portal, shared by all SH bases [2M per basis].
    gather_rays : final-gather rays per vertex [4096].
    order : SH order of the indirect transfer [4].
    photon_k : photons per radiance estimate.
    bounces : indirect bounces stored [9].
    direct_basis : "auto" (pulse or Haar, whichever is smaller per vertex), "pulse" or "haar".
    merge_portals : one portal (and shell) for all portal objects (Section 3.1: windows of one material under a
        distant environment), instead of one per portal object.
    seed : random seed.
    """

    res: int = 32
    direct_samples: int = 1024
    n_photons: int = 200_000
    gather_rays: int = 256
    order: int = 4
    photon_k: int = 32
    bounces: int = 2
    direct_basis: str = "auto"
    merge_portals: bool = False
    seed: int = 0

    def __post_init__(self):
        check_int_options(self, ("res", "direct_samples", "n_photons", "gather_rays", "order", "photon_k"))
        check_int_options(self, ("seed", "bounces"), minimum=0)
        if self.res & (self.res - 1):
            raise ValueError(f"option res must be a power of two (Haar on the faces), got {self.res}")
        if not isinstance(self.merge_portals, (bool, np.bool_)):
            raise ValueError(f"option merge_portals must be True or False, got {self.merge_portals!r}")
        if self.direct_basis not in ("auto", "pulse", "haar"):
            raise ValueError(f"option direct_basis must be 'auto', 'pulse' or 'haar', got {self.direct_basis!r}")


def _concatenate_chunks(chunks: list[dict]) -> dict:
    """Chunk dicts ``{portal: {name: array}}`` concatenated along axis 0 (as the cache assembles them)."""
    return {p: {name: np.concatenate([c[p][name] for c in chunks]) for name in chunks[0][p]} for p in chunks[0]}


def _shaded(scene: Scene):
    objs = [o for o in scene.objects if not o.portal]
    for o in objs:
        if o.material.type == "phong" and np.any(np.asarray(o.material.ks) > 0):
            raise ValueError(
                f"object {o.name!r} is glossy (phong, ks > 0): the portals pipeline handles Lambertian vertices "
                "only so far (glossy transfer matrices are not implemented); use method='reference' or a diffuse material"
            )
    return objs


class Portals(Precomputation):
    """Precomputed portal transfer of a static interior (Yue et al. 2009)."""

    method = "portals"
    format_version = 2  # 2: vertices shaded at world_shading_points
    max_bounces = None
    options_type = PortalsOptions

    #: vertices per precomputation chunk (one resumable cache part each)
    chunk_vertices: int = 2048

    @classmethod
    def precompute(cls, scene: Scene, options=None, cache=True, progress: bool = True, map_fn=None):
        """Run (or load) the precomputation; with a cache, in resumable chunks of vertices.

        Photon maps and their radiance estimates (one per portal) are cached as
        their own entries; the per-vertex work (direct transfer, final gathering)
        runs in chunks of :attr:`chunk_vertices` vertices, each stored as soon as it
        finishes, so an interrupted run resumes from the missing chunks.
        ``map_fn`` (see :meth:`prtlab.cache.Cache.get_or_compute_chunks`) runs
        chunks in parallel, e.g. on Dask. Every chunk draws from its own seeded
        generator, so the result does not depend on the order or on resuming.
        """
        options = cls.make_options(options)
        if not cache:
            return cls(scene, options, cls.compute(scene, options, progress))
        store = Cache(progress=progress) if cache is True else cache
        key = cache_key(*cls.cache_key_parts(scene, options))
        data = store.get_or_compute(
            key, lambda: cls.compute(scene, options, progress, store=store, key=key, map_fn=map_fn), name=cls.method)
        return cls(scene, options, data)

    @classmethod
    def compute(cls, scene: Scene, options: PortalsOptions, progress: bool, store=None, key=None,
                map_fn=None) -> dict:
        objs = _shaded(scene)
        names = [o.name for o in scene.objects if o.portal]
        portals = find_portals(scene, [names] if options.merge_portals and names else None)
        if not portals:
            raise ValueError("the scene has no portal: mark the window objects with 'portal: true'")
        caster = RayCaster(scene)
        points = np.concatenate([o.world_shading_points() for o in objs])
        normals = np.concatenate([o.world_normals() for o in objs])
        albedo = np.concatenate([np.tile(o.material.diffuse_albedo, (o.n_vertices, 1)) for o in objs])
        obj_albedo = np.array([o.material.diffuse_albedo for o in objs], dtype=np.float64).reshape(-1, 3)
        offsets = np.concatenate([[0], np.cumsum([o.n_vertices for o in objs])]).astype(np.int64)
        n_vertices = len(points)

        # photons and radiance estimates: one per portal (Section 4.1.1, steps 1a-1b)
        exitance, photon_seconds, n_stored = [], [], []
        for k, portal in enumerate(portals):
            def estimate(k=k, portal=portal):
                t0 = time.perf_counter()
                rng = np.random.default_rng([options.seed, k, 1])
                photons = trace_photons(caster, obj_albedo, portal, options.n_photons, options.bounces, rng)
                b = radiance_estimate(photons, points, normals, albedo, options.order, options.photon_k)
                return {"exitance": b, "seconds": np.array(time.perf_counter() - t0),
                        "n_photons_stored": np.array(len(photons))}

            if options.bounces == 0:
                entry = {"exitance": None, "seconds": np.array(0.0), "n_photons_stored": np.array(0)}
            elif store is not None:
                entry = store.get_or_compute(cache_key(key, "exitance", k), estimate, name="portals-photons")
            else:
                entry = estimate()
            exitance.append(entry["exitance"])
            photon_seconds.append(float(entry["seconds"]))
            n_stored.append(int(entry["n_photons_stored"]))

        # per-vertex work in chunks (Section 4.1.2 and 4.1.1 step 2)
        size = cls.chunk_vertices
        n_chunks = max(1, -(-n_vertices // size))

        def chunk_fn(i):
            sl = slice(i * size, min(n_vertices, (i + 1) * size))
            out = {}
            for k, portal in enumerate(portals):
                rng = np.random.default_rng([options.seed, k, 2, i])
                t0 = time.perf_counter()
                dense = direct_transfer(caster, points[sl], normals[sl], portal, options.direct_samples,
                                        options.res, rng)
                sparse = encode_transfer(dense, options.direct_basis)
                t1 = time.perf_counter()
                entry = {"counts": np.diff(sparse.indptr), "indices": sparse.indices, "codes": sparse.codes,
                         "scale": sparse.scale, "basis": sparse.basis, "seconds_direct": np.array([t1 - t0])}
                if options.bounces > 0:
                    entry["indirect"] = final_gather(caster, points[sl], normals[sl], albedo[sl], exitance[k],
                                                     offsets, normals, options.gather_rays, rng).astype(np.float32)
                entry["seconds_indirect"] = np.array([time.perf_counter() - t1])
                out[f"portal{k}"] = entry
            return out

        if store is not None:
            chunks = store.get_or_compute_chunks(cache_key(key, "chunks"), n_chunks, chunk_fn,
                                                 name="portals-chunks", map_fn=map_fn)
        else:
            from tqdm.auto import tqdm

            chunks = _concatenate_chunks([chunk_fn(i) for i in tqdm(range(n_chunks), desc="portals precompute",
                                                                    unit="chunk", disable=not progress)])
        data: dict = {"n_portals": np.array(len(portals)), "albedo": albedo}
        for k in range(len(portals)):
            c = chunks[f"portal{k}"]
            indptr = np.concatenate([[0], np.cumsum(c["counts"])]).astype(np.int64)
            entry = {"indptr": indptr, "indices": c["indices"], "codes": c["codes"], "scale": c["scale"],
                     "basis": c["basis"], "res": np.array(options.res),
                     "seconds_direct": np.array(float(np.sum(c["seconds_direct"]))),
                     "seconds_indirect": np.array(float(np.sum(c["seconds_indirect"])) + photon_seconds[k]),
                     "n_photons_stored": np.array(n_stored[k])}
            if options.bounces > 0:
                entry["indirect"] = c["indirect"]
            data[f"portal{k}"] = entry
        return data

    # ------------------------------------------------------------------ run time

    def direct_transfer(self, k: int = 0) -> SparseTransfer:
        """The 8-bit sparse direct transfer of portal ``k``."""
        cached = self.__dict__.setdefault("_direct_cache", {})
        if k not in cached:
            e = self.data[f"portal{k}"]
            cached[k] = SparseTransfer(np.asarray(e["indptr"], np.int64), e["indices"], e["codes"], e["scale"],
                                       e["basis"], int(e["res"]))
        return cached[k]

    @property
    def n_portals(self) -> int:
        return int(self.data["n_portals"])

    def shade_shells(self, shells, bounces: int | None = None, method: str = "numba") -> ShadeResult:
        """Per-vertex radiance from given shell lights, one ``(6, r, r, 3)`` cubemap per portal.

        Use it for a dynamic exterior (cubemaps rendered from each portal
        centre) or portal materials: ``tint(cube, colour)``, ``frosted(cube, sigma_deg)``.
        """
        if bounces is None:
            bounces = self.options.bounces
        if bounces not in (0, self.options.bounces):
            raise ValueError(
                f"the transfer was precomputed with bounces={self.options.bounces}; shade with bounces=0 or "
                f"{self.options.bounces}, or precompute again with the bounces option set to {bounces}"
            )
        shells = list(shells)
        if len(shells) != self.n_portals:
            raise ValueError(f"give one shell cubemap per portal ({self.n_portals}), got {len(shells)}")
        objs = _shaded(self.scene)
        albedo = np.asarray(self.data["albedo"], dtype=np.float64)
        n = len(albedo)
        direct = np.zeros((n, 3))
        indirect = np.zeros((n, 3))
        for k, cube in enumerate(shells):
            cube = np.asarray(cube, dtype=np.float64)
            direct += direct_pass(self.direct_transfer(k), albedo, cube, method=method)
            if bounces > 0:
                indirect += indirect_pass(self.data[f"portal{k}"]["indirect"], shell_sh(cube, self.options.order),
                                          method=method)
        result = ShadeResult()
        offsets = np.concatenate([[0], np.cumsum([o.n_vertices for o in objs])])
        for o, a, b in zip(objs, offsets[:-1], offsets[1:]):
            result.direct[o.name] = direct[a:b]
            result.indirect[o.name] = indirect[a:b]
            result.total[o.name] = direct[a:b] + indirect[a:b]
        result.info = {"method": "portals", "bounces": bounces}
        return result

    def shade_frame(self, state: FrameState, bounces: int) -> ShadeResult:
        envs = [light for light in state.lights if isinstance(light, EnvironmentLight)]
        if len(envs) != 1 or len(envs) != len(state.lights):
            raise ValueError(
                "the portals pipeline is lit by exactly one environment light seen through the portals; "
                f"got lights {[type(x).__name__ for x in state.lights]}"
            )
        cube = shell_light(envs[0], self.options.res)
        return self.shade_shells([cube] * self.n_portals, bounces)

    @classmethod
    def shade_scene(cls, scene: Scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
        """``prtlab.shade(scene, method="portals", bounces=B)``: precompute ``B`` bounces, shade."""
        options.setdefault("bounces", bounces)
        return cls.precompute(scene, options, cache=cache, progress=progress).shade(bounces=bounces)


def shade_scene(scene: Scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
    """Entry point of ``prtlab.shade(scene, method="portals", ...)``; see :class:`Portals`."""
    return Portals.shade_scene(scene, bounces=bounces, cache=cache, progress=progress, **options)


def precompute(scene: Scene, options=None, cache=True, progress: bool = True, map_fn=None) -> Portals:
    """``Portals.precompute``: the slow, cached phase (chunks run through ``map_fn``,
    e.g. :func:`prtlab.api.dask_map`); then ``.shade(state, bounces)`` per frame."""
    return Portals.precompute(scene, options, cache=cache, progress=progress, map_fn=map_fn)
