"""The two-phase base every PRT pipeline plugs into.

A pipeline is a subclass of :class:`Precomputation` that implements only its
passes::

    class SphereLights(Precomputation):
        method = "spherelights"
        format_version = 1
        max_bounces = 1
        options_type = SphereLightOptions        # a dataclass of the method's options

        @classmethod
        def compute(cls, scene, options, progress):   # the slow passes -> dict of arrays
            ...

        def shade_frame(self, state, bounces):       # the fast per-frame passes -> ShadeResult
            ...

The base owns the loop: option validation, the content-addressed HDF5 cache
(keyed by the scene's geometry and materials, the options, the method and its
format version), the per-frame state, and the ``bounces`` check::

    pre = SphereLights.precompute(scene, {"n_spheres": 8})   # slow, cached
    frame = pre.shade(FrameState.from_scene(scene))            # fast, per frame

Per-frame code is a batched numba loop over vertices (``parallel=True``,
``prange``) with one function per shader pass, named after the pass.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

import numpy as np

from prtlab._validate import check_int
from prtlab.cache import Cache, cache_key
from prtlab.scene import Camera, Scene, ShadeResult, Transform

__all__ = ["FrameState", "Precomputation", "check_int_options", "scene_geometry_key_parts"]


@dataclass
class FrameState:
    """What changes per frame: object transforms, lights, camera."""

    transforms: dict[str, Transform] = field(default_factory=dict)
    lights: list = field(default_factory=list)
    camera: Camera | None = None

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


class Precomputation:
    """Base of every pipeline's precomputed data; see the module docstring."""

    method: ClassVar[str] = ""
    format_version: ClassVar[int] = 1
    max_bounces: ClassVar[int | None] = None
    options_type: ClassVar[type | None] = None

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
        unknown = sorted(set(options) - valid)
        if unknown:
            raise ValueError(f"unknown option(s) {unknown} for method {cls.method!r}; valid: {sorted(valid)}")
        return cls.options_type(**options)

    @classmethod
    def cache_key_parts(cls, scene: Scene, options) -> list:
        """What the precomputation depends on (override to narrow or widen)."""
        opts = dataclasses.asdict(options) if dataclasses.is_dataclass(options) else options
        return [cls.method, cls.format_version, scene_geometry_key_parts(scene), opts]

    # ----------------------------------------------------------------- the two phases

    @classmethod
    def compute(cls, scene: Scene, options, progress: bool) -> dict:
        """The slow passes: return a dict of arrays (nested dicts allowed)."""
        raise NotImplementedError

    @classmethod
    def precompute(cls, scene: Scene, options=None, cache: Cache | bool | None = True, progress: bool = True):
        """Run (or load from the cache) the precomputation of ``scene``.

        ``cache``: True for the default cache (``$PRTLAB_CACHE`` or
        ``~/.cache/prtlab``), a :class:`prtlab.cache.Cache`, or False/None to
        compute without caching.
        """
        options = cls.make_options(options)
        if not cache:
            return cls(scene, options, cls.compute(scene, options, progress))
        store = Cache(progress=progress) if cache is True else cache
        key = cache_key(*cls.cache_key_parts(scene, options))
        data = store.get_or_compute(key, lambda: cls.compute(scene, options, progress), name=cls.method)
        return cls(scene, options, data)

    def shade_frame(self, state: FrameState, bounces: int) -> ShadeResult:
        """The fast per-frame passes."""
        raise NotImplementedError

    def shade(self, state: FrameState | None = None, bounces: int = 1) -> ShadeResult:
        """Per-vertex radiance for one frame (``state`` defaults to the scene as loaded)."""
        bounces = check_int(bounces, "bounces", 0)
        if self.max_bounces is not None and bounces > self.max_bounces:
            raise ValueError(
                f"method {self.method!r} computes at most {self.max_bounces} indirect bounce(s), "
                f"got bounces={bounces}; use method='reference' for more"
            )
        return self.shade_frame(state or FrameState.from_scene(self.scene), bounces)

    @classmethod
    def shade_scene(cls, scene: Scene, bounces: int = 1, cache=True, progress: bool = True, **options) -> ShadeResult:
        """``precompute(scene, options).shade(bounces=bounces)``: the ``prtlab.shade`` entry point."""
        return cls.precompute(scene, options, cache=cache, progress=progress).shade(bounces=bounces)
