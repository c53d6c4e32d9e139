"""The two-phase base every PRT pipeline plugs into, and the contract all of them follow.

A pipeline is a subclass of :class:`Precomputation` that implements only its
passes; the base owns the loop (options, cache, checks, per-frame state)::

    @dataclass(frozen=True)
    class SphereLightOptions:                       # every option: default, validation, docstring entry
        \"\"\"...

        Attributes
        ----------
        n_spheres : int
            Spheres per source object.
        \"\"\"

        n_spheres: int = 8

        def __post_init__(self):
            check_int(self.n_spheres, "option n_spheres", 1)

    class SphereLights(Precomputation):
        method = "spherelights"
        format_version = 1
        max_bounces = 1
        options_type = SphereLightOptions

        @classmethod
        def compute(cls, scene, options, progress):   # the slow passes -> dict of arrays
            ...

        def shade_frame(self, state, bounces):       # the fast per-frame passes -> ShadeResult
            ...

    pre = SphereLights.precompute(scene, {"n_spheres": 8})   # slow, cached
    frame = pre.shade(FrameState.from_scene(scene))            # fast, per frame

The contract
------------
**Options.** One dataclass (``options_type``) per method. Every field is
validated in ``__post_init__`` by the shared validators of :mod:`prtlab._validate` (type,
range, choice, cross-field: ``TypeError`` for a wrong type, ``ValueError`` out of range,
naming the option), and documented in the class docstring's numpydoc ``Attributes``
section, from which ``docs/OPTIONS.md`` is generated (:func:`prtlab.api.options_reference`).
One name per concept across methods: ``order`` (SH order), ``cube_resolution`` (face
resolution of a per-point cubemap of directions), ``n_basis``, ``seed``; a renamed option
stays in ``renamed_options`` so that its old name fails with the new one. Options that
do not change the precomputed data are left out of the cache key (``cache_key_parts``).

**Precomputation** runs only through :meth:`Precomputation.precompute`: the options,
:meth:`Precomputation.check_scene` (what the method needs, and the memory its options
need, :meth:`Precomputation.memory_needs`), then ``compute`` or the content-addressed
cache (keyed by the scene's geometry and materials, the options, the method and its
``format_version``). A ``resumable`` method's ``compute`` takes ``store``, ``key`` and
``map_fn`` and runs its work through :meth:`Precomputation.run_part` and
:meth:`Precomputation.run_chunks`, which store each part as it finishes and distribute
the chunks (``map_fn``, e.g. :func:`prtlab.api.dask_map`).

**Per frame**, everything that changes is in :class:`FrameState`: object transforms,
soft deformations (only where ``supports_deformations``), lights and camera; no other
way in. :meth:`Precomputation.shade` checks ``bounces``, then the state
(:meth:`Precomputation.check_state`: every name is an object of the scene, an object
whose pose the data bakes in, :meth:`Precomputation.baked_objects`, has not moved,
and the lights, :meth:`Precomputation.check_lights`), then calls ``shade_frame``. What
consecutive frames reuse is held by one object owned by the precomputation, keyed by
the poses it was made at (never by ``id()`` of arrays).

**Results.** ``bounces`` defaults to 1 in every entry point (``prtlab.shade``,
``shade_scene``, ``shade``); a method that cannot shade as many raises
(:meth:`Precomputation.check_bounces`). A :class:`prtlab.scene.ShadeResult` holds
``direct``, ``indirect`` and ``total`` of every object that is not a portal (portals are
openings, not surfaces), and ``info`` holds at least ``method``, ``bounces`` and
``timings`` (``{pass name: seconds}`` of the frame's passes), plus method-specific keys.

**Order of checks**: ``shade_scene`` (``prtlab.shade``) checks the options, ``bounces``
and the scene's lights before precomputing, so that nothing heavy runs before a
refusal.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from prtlab._validate import MemoryNeed, check_int, check_memory, memory_limit
from prtlab.cache import Cache, cache_key
from prtlab.scene import Camera, Scene, ShadeResult, Transform

__all__ = ["FrameState", "MemoryNeed", "Precomputation", "check_int_options", "check_memory", "concatenate_chunks",
           "memory_limit", "scene_geometry_key_parts"]


@dataclass
class FrameState:
    """What changes per frame: object transforms, lights, camera, and soft deformations.

    ``deformations``: ``{object name: (V, 3) object-space vertex positions}`` of softly
    deformed objects (only methods with ``supports_deformations`` take them).
    """

    transforms: dict[str, Transform] = field(default_factory=dict)
    lights: list = field(default_factory=list)
    camera: Camera | None = None
    deformations: dict[str, np.ndarray] = field(default_factory=dict)

    @classmethod
    def from_scene(cls, scene: Scene) -> "FrameState":
        """The state a scene is in as loaded (or as returned by ``scene.at_frame``)."""
        return cls(
            transforms={obj.name: obj.transform for obj in scene.objects},
            lights=list(scene.lights),
            camera=scene.camera,
        )


def check_int_options(options, names, minimum: int = 1) -> None:
    """The one validator of integer options: each of ``names`` on ``options`` must be an int >= ``minimum``."""
    for name in names:
        value = getattr(options, name)
        check_int(value, f"option {name}", minimum)


def check_vertex_normals(scene: Scene) -> None:
    """Refuse a shaded (non-portal) object with a vertex whose normal is zero: a vertex on no face of non-zero
    area (unreferenced, or only on degenerate faces) or whose faces' normals cancel. The PRT methods project
    their transfer about every vertex's normal, so such a vertex has nothing to be shaded with; the Monte Carlo
    references, which need no normal, give it zero light."""
    for obj in scene.objects:
        if obj.portal:
            continue
        bad = np.flatnonzero(~np.any(np.asarray(obj.mesh.vertex_normals) != 0.0, axis=1))
        if len(bad):
            shown = ", ".join(str(i) for i in bad[:5]) + (", ..." if len(bad) > 5 else "")
            verb = "has" if len(bad) == 1 else "have"
            raise ValueError(
                f"object {obj.name!r}: {len(bad)} of its {obj.n_vertices} vertices {verb} no normal (vertex {shown}: "
                "on no face of non-zero area, or its faces' normals cancel), and this method shades every vertex "
                "about its normal; remove them first (trimesh: mesh.update_faces(mesh.nondegenerate_faces()), then "
                "mesh.remove_unreferenced_vertices())"
            )


def scene_geometry_key_parts(scene: Scene, dynamic_transforms: bool = False) -> list:
    """What a precomputation over ``scene`` depends on by default: meshes and materials
    of every object, and the transforms of static objects (of all objects if
    ``dynamic_transforms``). Lights and camera are per-frame state, not keyed."""
    parts: list[Any] = []
    for obj in scene.objects:
        parts += [obj.name, np.asarray(obj.mesh.vertices), np.asarray(obj.mesh.faces),
                  obj.material.to_dict(), bool(obj.dynamic), bool(obj.portal)]
        if dynamic_transforms or not obj.dynamic:
            parts.append(obj.transform.to_dict())
    return parts


def concatenate_chunks(chunks: list[dict]) -> dict:
    """Chunk dicts (nested dicts of arrays) concatenated along axis 0, as the cache assembles them."""
    first = chunks[0]
    return {name: concatenate_chunks([c[name] for c in chunks]) if isinstance(first[name], dict)
            else np.concatenate([c[name] for c in chunks]) for name in first}


def _same_pose(a: Transform, b: Transform) -> bool:
    ma, mb = a.matrix(), b.matrix()
    return bool(np.allclose(ma, mb, rtol=0.0, atol=1e-12 * max(1.0, float(np.abs(mb).max()))))


class Precomputation:
    """Base of every pipeline's precomputed data; see the module docstring."""

    method: ClassVar[str] = ""
    format_version: ClassVar[int] = 1
    max_bounces: ClassVar[int | None] = None
    options_type: ClassVar[type | None] = None
    #: ``compute`` takes ``store``, ``key`` and ``map_fn`` and stores resumable parts itself
    resumable: ClassVar[bool] = False
    #: the method takes ``FrameState.deformations``
    supports_deformations: ClassVar[bool] = False
    #: former option names -> their names now, for a clear error when an old name is passed
    renamed_options: ClassVar[dict[str, str]] = {}
    #: why moving a baked object is refused (see :meth:`baked_objects`)
    baked_reason: ClassVar[str] = "the precomputation bakes in the poses of the objects"

    def __init__(self, scene: Scene, options: Any, data: Mapping[str, Any]):
        self.scene = scene
        self.options = options
        self.data = dict(data)

    # ----------------------------------------------------------------- options

    @classmethod
    def make_options(cls, options: Mapping[str, Any] | Any | None = None):
        """Coerce a dict (or an options dataclass) to ``options_type``; unknown keys are an error."""
        if cls.options_type is None:
            if options:
                raise ValueError(f"method {cls.method!r} takes no options, got {sorted(dict(options))}")
            return None
        if options is None:
            return cls.options_type()
        if isinstance(options, cls.options_type):
            return options
        valid = {f.name for f in dataclasses.fields(cls.options_type)}
        renamed = sorted(set(options) & set(cls.renamed_options) - valid)
        if renamed:
            old = renamed[0]
            raise ValueError(f"option {old!r} of method {cls.method!r} is now called "
                             f"{cls.renamed_options[old]!r}; pass {cls.renamed_options[old]}=... instead")
        unknown = sorted(set(options) - valid)
        if unknown:
            raise ValueError(f"unknown option(s) {unknown} for method {cls.method!r}; valid: {sorted(valid)}")
        return cls.options_type(**options)

    @classmethod
    def cache_key_parts(cls, scene: Scene, options) -> list:
        """What the precomputation depends on (override to narrow or widen)."""
        opts = dataclasses.asdict(options) if dataclasses.is_dataclass(options) else options
        return [cls.method, cls.format_version, scene_geometry_key_parts(scene), opts]

    # ----------------------------------------------------------------- checks before any work

    @classmethod
    def check_bounces(cls, bounces, options) -> int:
        """``bounces`` as an int the method can shade (``0 <= bounces <= max_bounces``)."""
        bounces = check_int(bounces, "bounces", 0)
        if cls.max_bounces is not None and bounces > cls.max_bounces:
            raise ValueError(
                f"method {cls.method!r} computes at most {cls.max_bounces} indirect bounce(s), "
                f"got bounces={bounces}; use method='reference' for more"
            )
        return bounces

    @classmethod
    def check_lights(cls, lights, options) -> None:
        """Raise ValueError for a light the method cannot shade (default: every light is taken)."""

    @classmethod
    def memory_needs(cls, scene: Scene, options) -> tuple[list[MemoryNeed], str]:
        """The dominant allocations of ``compute`` and what they are counted for (e.g. ``"2,191 vertices"``)."""
        return [], "the scene"

    @classmethod
    def check_scene(cls, scene: Scene, options) -> None:
        """Refuse, before ``compute``, a scene the method cannot precompute (a shaded vertex without a normal,
        :func:`check_vertex_normals`) and options whose memory does not fit (:func:`check_memory`); subclasses
        add their own needs and call this."""
        check_vertex_normals(scene)
        needs, context = cls.memory_needs(scene, options)
        check_memory(cls.method, options, needs, context)

    def baked_objects(self) -> tuple[str, ...]:
        """Names of the objects whose pose the precomputed data bakes in (default: none, every object may move)."""
        return ()

    def moved_objects(self, state: "FrameState") -> list[str]:
        """The baked objects (:meth:`baked_objects`) whose transform in ``state`` differs from the scene's."""
        moved = []
        for name in self.baked_objects():
            now = state.transforms.get(name)
            if now is not None and not _same_pose(now, self.scene.object(name).transform):
                moved.append(name)
        return moved

    def check_state(self, state: "FrameState") -> "FrameState":
        """``state`` checked against the precomputation (names, baked poses, deformations, lights);
        returns it with its deformations as float64 arrays."""
        names = [o.name for o in self.scene.objects]
        for label, entries in (("transforms", state.transforms), ("deformations", state.deformations)):
            unknown = sorted(set(entries) - set(names))
            if unknown:
                raise ValueError(f"the frame state's {label} name unknown object(s) {unknown}; objects: {names}")
        moved = self.moved_objects(state)
        if moved:
            raise ValueError(
                f"{self.baked_reason}: object {moved[0]!r} moved; keep it at its precomputed pose (mark it static) "
                "or re-precompute at the new pose (e.g. precompute(scene.at_frame(i, n)))"
            )
        deformations = {}
        if state.deformations:
            if not self.supports_deformations:
                raise ValueError(f"method {self.method!r} does not take soft deformations (FrameState.deformations "
                                 f"of {sorted(state.deformations)}); re-precompute the deformed meshes")
            for name, verts in state.deformations.items():
                v = np.asarray(verts, dtype=np.float64)
                n_v = self.scene.object(name).n_vertices
                if v.shape != (n_v, 3) or not np.all(np.isfinite(v)):
                    raise ValueError(f"deformed[{name!r}] must be finite object-space vertex positions of shape "
                                     f"({n_v}, 3), got shape {v.shape}")
                deformations[name] = v
        self.check_lights(state.lights, self.options)
        return dataclasses.replace(state, deformations=deformations)

    # ----------------------------------------------------------------- the two phases

    @classmethod
    def compute(cls, scene: Scene, options, progress: bool) -> dict:
        """The slow passes: return a dict of arrays (nested dicts allowed)."""
        raise NotImplementedError

    @classmethod
    def precompute(cls, scene: Scene, options=None, cache: Cache | bool | None = True, progress: bool = True,
                   map_fn=None):
        """Run (or load from the cache) the precomputation of ``scene``.

        ``cache``: True for the default cache (``$PRTLAB_CACHE`` or
        ``~/.cache/prtlab``), a :class:`prtlab.cache.Cache`, or False/None to
        compute without caching. :meth:`check_scene` runs first. A ``resumable``
        method stores its parts as they finish (``map_fn`` runs them in parallel,
        see :meth:`prtlab.cache.Cache.get_or_compute_chunks`).
        """
        options = cls.make_options(options)
        cls.check_scene(scene, options)
        if map_fn is not None and not cls.resumable:
            raise ValueError(f"method {cls.method!r} cannot distribute its precomputation (map_fn)")
        if not cache:
            return cls(scene, options, cls.compute(scene, options, progress))
        store = Cache(progress=progress) if cache is True else cache
        key = cache_key(*cls.cache_key_parts(scene, options))
        extra = {"store": store, "key": key, "map_fn": map_fn} if cls.resumable else {}
        data = store.get_or_compute(key, lambda: cls.compute(scene, options, progress, **extra), name=cls.method)
        return cls(scene, options, data)

    @classmethod
    def run_part(cls, store: Cache | None, key: str | None, part: tuple, name: str, fn):
        """``fn()`` (a dict of arrays), stored as the resumable part ``part`` of the precomputation ``key`` when
        ``store`` is given (a ``resumable`` method's ``compute`` gets ``store`` and ``key``), else computed here."""
        if store is None:
            return fn()
        return store.get_or_compute(cache_key(key, *part), fn, name=name)

    @classmethod
    def run_chunks(cls, n_chunks: int, chunk_fn, store: Cache | None = None, key: str | None = None, map_fn=None,
                   progress: bool = True, chunking=None) -> dict:
        """``chunk_fn(i)`` for every chunk, concatenated along axis 0 (nested dicts of arrays).

        With ``store`` each chunk is a resumable part of the precomputation ``key``
        (:meth:`prtlab.cache.Cache.get_or_compute_chunks`, which runs them through ``map_fn``, e.g.
        :func:`prtlab.api.dask_map`); ``chunking`` (what the chunks are, e.g. ``{"vertices": 2048}``) is
        recorded with each part so that parts of another chunking are recomputed. Without ``store`` the
        chunks run here in order, with a progress bar.
        """
        if store is not None:
            return store.get_or_compute_chunks(cache_key(key, "chunks"), n_chunks, chunk_fn,
                                               name=f"{cls.method}-chunks", map_fn=map_fn, chunking=chunking)
        from tqdm.auto import tqdm

        return concatenate_chunks([chunk_fn(i) for i in tqdm(range(n_chunks), desc=f"{cls.method} precompute",
                                                             unit="chunk", disable=not progress)])

    def shade_frame(self, state: FrameState, bounces: int) -> ShadeResult:
        """The fast per-frame passes."""
        raise NotImplementedError

    def shade(self, state: FrameState | None = None, bounces: int = 1) -> ShadeResult:
        """Per-vertex radiance for one frame (``state`` defaults to the scene as loaded)."""
        bounces = self.check_bounces(bounces, self.options)
        state = self.check_state(state or FrameState.from_scene(self.scene))
        return self.shade_frame(state, bounces)

    @classmethod
    def shade_scene(cls, scene: Scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
        """``precompute(scene, options).shade(bounces=bounces)``: the ``prtlab.shade`` entry point.

        Options, ``bounces`` and the scene's lights are checked before the precomputation runs.
        """
        return cls.shade_once(scene, cls.make_options(options), bounces, cache=cache, progress=progress)

    @classmethod
    def shade_once(cls, scene: Scene, options, bounces: int = 1, cache=True, progress: bool = True) -> ShadeResult:
        """:meth:`shade_scene` with the options as one object (a dict or the options dataclass)."""
        options = cls.make_options(options)
        bounces = cls.check_bounces(bounces, options)
        cls.check_lights(scene.lights, options)
        return cls.precompute(scene, options, cache=cache, progress=progress).shade(bounces=bounces)
