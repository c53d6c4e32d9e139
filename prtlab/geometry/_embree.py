"""Embree 4 through ``ctypes``, traced from numba kernels on every core.

:class:`EmbreeScene` builds one Embree scene (robust mode, one triangle
geometry per object, geometry id = object index) with the C API of the Embree 4
library that ships inside the ``embreex`` wheel. :func:`intersect` and
:func:`occluded` cast float32 rays through ``rtcIntersect1`` / ``rtcOccluded1``
from a numba ``prange`` kernel that calls the C functions through their
addresses: no Python and no GIL per ray, so every numba thread traces.

Why not ``embreex``: its ``EmbreeScene.run`` holds the GIL while it traces, so
Python threads over ray chunks run one at a time; Embree's own thread pool
(TBB) only builds acceleration structures.

Contract and limits
    * Rays are float32 with ``tnear = 0`` (the caller offsets origins, see
      :mod:`prtlab.geometry._raycast`); a ray with ``tfar <= 0`` is not cast
      and reports a miss.
    * The library is found beside ``embreex`` (``embreex.libs/`` on Linux,
      ``embreex/.dylibs/`` on macOS, the ``embreex`` folder on Windows), else
      on the system path; :func:`load_library` raises :class:`EmbreeUnavailable`
      with one line saying what is missing.
    * Struct layouts follow ``embree4/rtcore_ray.h``: ``RTCRay`` is 48 bytes,
      ``RTCHit`` follows at byte 48 (``u, v`` at 60, 64; ``primID, geomID`` at
      68, 72). Each thread's ``RTCRayHit`` lives in a 128-byte, 64-byte aligned
      slot, larger than any Embree 4 build's struct.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
import threading
import weakref

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

__all__ = ["EmbreeScene", "EmbreeUnavailable", "load_library", "intersect", "occluded"]

RTC_SCENE_FLAG_ROBUST = 1 << 2
RTC_GEOMETRY_TYPE_TRIANGLE = 0
RTC_BUFFER_TYPE_INDEX = 0
RTC_BUFFER_TYPE_VERTEX = 1
RTC_FORMAT_UINT3 = 0x5003
RTC_FORMAT_FLOAT3 = 0x9003

#: Bytes of one ray slot (an ``RTCRayHit`` is 80 or 96 bytes, by build) and its alignment.
SLOT_BYTES = 128
SLOT_ALIGN = 64

#: Rays a thread takes at a time from the queue of a query (dynamic scheduling).
RAYS_PER_TASK = 256

_SIGNATURES = {
    "rtcNewDevice": (ctypes.c_void_p, [ctypes.c_char_p]),
    "rtcReleaseDevice": (None, [ctypes.c_void_p]),
    "rtcGetDeviceError": (ctypes.c_int, [ctypes.c_void_p]),
    "rtcGetDeviceLastErrorMessage": (ctypes.c_char_p, [ctypes.c_void_p]),
    "rtcNewScene": (ctypes.c_void_p, [ctypes.c_void_p]),
    "rtcSetSceneFlags": (None, [ctypes.c_void_p, ctypes.c_int]),
    "rtcCommitScene": (None, [ctypes.c_void_p]),
    "rtcReleaseScene": (None, [ctypes.c_void_p]),
    "rtcNewGeometry": (ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_int]),
    "rtcSetNewGeometryBuffer": (
        ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t, ctypes.c_size_t]
    ),
    "rtcCommitGeometry": (None, [ctypes.c_void_p]),
    "rtcAttachGeometry": (ctypes.c_uint, [ctypes.c_void_p, ctypes.c_void_p]),
    "rtcReleaseGeometry": (None, [ctypes.c_void_p]),
    "rtcIntersect1": (None, [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]),
    "rtcOccluded1": (None, [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]),
}


class EmbreeUnavailable(RuntimeError):
    """The Embree 4 shared library or one of its functions was not found."""


_LOCK = threading.Lock()
_LIBRARY: list = []  # [ctypes.CDLL] once loaded


def _candidates() -> list[str]:
    """Paths of Embree 4 libraries beside ``embreex`` (its wheel's vendored copy), then the system's."""
    found = []
    try:
        import embreex
    except ImportError:
        embreex = None
    if embreex is not None and getattr(embreex, "__file__", None):
        package = os.path.dirname(os.path.abspath(embreex.__file__))
        site = os.path.dirname(package)
        for pattern in (os.path.join(site, "embreex.libs", "libembree4*.so*"),
                        os.path.join(package, ".dylibs", "libembree4*.dylib"),
                        os.path.join(package, "embree4*.dll"),
                        os.path.join(site, "embreex.libs", "embree4*.dll")):
            found += sorted(glob.glob(pattern))
    system = ctypes.util.find_library("embree4")
    if system:
        found.append(system)
    return found


def load_library(paths: list[str] | None = None) -> ctypes.CDLL:
    """The Embree 4 library with the functions prtlab calls, their signatures set (loaded once).

    Parameters
    ----------
    paths : list of str, optional
        Library files to try in order; default: beside ``embreex``, then ``find_library("embree4")``.
        Given paths are loaded afresh (not cached).

    Raises
    ------
    EmbreeUnavailable
        No library could be loaded, or it lacks one of the functions.
    """
    if paths is None and _LIBRARY:
        return _LIBRARY[0]
    tried = _candidates() if paths is None else list(paths)
    if not tried:
        raise EmbreeUnavailable("no Embree 4 library found beside embreex or on the system path; "
                                "install embreex (pip install embreex)")
    errors = []
    for path in tried:
        try:
            lib = ctypes.CDLL(path)
        except OSError as err:
            errors.append(f"{path}: {err}")
            continue
        missing = [name for name in _SIGNATURES if not hasattr(lib, name)]
        if missing:
            errors.append(f"{path} lacks {', '.join(missing)}")
            continue
        for name, (restype, argtypes) in _SIGNATURES.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
        if paths is None:
            with _LOCK:
                if not _LIBRARY:
                    _LIBRARY.append(lib)
            return _LIBRARY[0]
        return lib
    raise EmbreeUnavailable("no usable Embree 4 library: " + "; ".join(errors))


def _release(lib, scene: int, device: int) -> None:
    if scene:
        lib.rtcReleaseScene(scene)
    if device:
        lib.rtcReleaseDevice(device)


class EmbreeScene:
    """One committed Embree scene of triangle meshes (geometry id = index in ``meshes``).

    Parameters
    ----------
    meshes : sequence of ((n_vertices, 3) float, (n_faces, 3) int)
        World-space vertices (rounded to float32 here) and faces. An object
        with no faces becomes one zero-area triangle that no ray hits, so ids stay
        object indices.
    library : ctypes.CDLL, optional
        From :func:`load_library` (the default).

    Notes
    -----
    The scene owns its own device (``rtcNewDevice``); both are released when
    the object is garbage collected or :meth:`release` is called. Queries from
    several threads at once are safe (Embree's traversal is thread-safe).
    """

    def __init__(self, meshes, library: ctypes.CDLL | None = None):
        self._lib = lib = load_library() if library is None else library
        self.intersect_fn = ctypes.cast(lib.rtcIntersect1, ctypes.c_void_p).value
        self.occluded_fn = ctypes.cast(lib.rtcOccluded1, ctypes.c_void_p).value
        self._device = lib.rtcNewDevice(None)
        if not self._device:
            raise EmbreeUnavailable("rtcNewDevice failed: this CPU or build of Embree 4 cannot trace rays")
        self._scene = lib.rtcNewScene(self._device)
        self._finalizer = weakref.finalize(self, _release, lib, self._scene, self._device)
        lib.rtcSetSceneFlags(self._scene, RTC_SCENE_FLAG_ROBUST)
        for index, (vertices, faces) in enumerate(meshes):
            self._attach(index, vertices, faces)
        lib.rtcCommitScene(self._scene)
        self._check("rtcCommitScene")

    def _check(self, where: str) -> None:
        code = self._lib.rtcGetDeviceError(self._device)
        if code:
            message = self._lib.rtcGetDeviceLastErrorMessage(self._device) or b""
            raise RuntimeError(f"Embree error {code} in {where}: {message.decode(errors='replace')}")

    def _attach(self, index: int, vertices, faces) -> None:
        lib = self._lib
        vertices = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
        faces = np.ascontiguousarray(faces, dtype=np.uint32).reshape(-1, 3)
        if not len(faces):
            vertices, faces = np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.uint32)
        geometry = lib.rtcNewGeometry(self._device, RTC_GEOMETRY_TYPE_TRIANGLE)
        try:
            for kind, fmt, data in ((RTC_BUFFER_TYPE_VERTEX, RTC_FORMAT_FLOAT3, vertices),
                                    (RTC_BUFFER_TYPE_INDEX, RTC_FORMAT_UINT3, faces)):
                buffer = lib.rtcSetNewGeometryBuffer(geometry, kind, 0, fmt, 12, len(data))
                if not buffer:
                    self._check("rtcSetNewGeometryBuffer")
                    raise RuntimeError(f"Embree could not allocate a buffer of {len(data)} items")
                ctypes.memmove(buffer, data.ctypes.data, data.nbytes)
            lib.rtcCommitGeometry(geometry)
            geometry_id = lib.rtcAttachGeometry(self._scene, geometry)
        finally:
            lib.rtcReleaseGeometry(geometry)  # the scene holds its own reference
        self._check("rtcAttachGeometry")
        if geometry_id != index:
            raise RuntimeError(f"Embree gave geometry id {geometry_id} to object {index}")

    @property
    def handle(self) -> int:
        """The ``RTCScene`` pointer as an int (valid while this object lives)."""
        return self._scene

    def release(self) -> None:
        """Release the scene and its device now (idempotent)."""
        self._finalizer()


def _slots(n_tasks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-task ``RTCRayHit`` scratch: 64-byte aligned rows of 128 bytes, as float32 and uint32 views."""
    raw = np.zeros(n_tasks * SLOT_BYTES + SLOT_ALIGN, dtype=np.uint8)
    start = (-raw.ctypes.data) % SLOT_ALIGN
    block = raw[start : start + n_tasks * SLOT_BYTES].reshape(n_tasks, SLOT_BYTES)
    return block.view(np.float32), block.view(np.uint32)


@intrinsic
def _rtc_call(typingctx, function, scene, ray):
    """``function(scene, ray, NULL)`` for C functions ``void (*)(RTCScene, RTCRay[Hit]*, args*)`` given
    as integer addresses (``rtcIntersect1``, ``rtcOccluded1``)."""
    if not all(isinstance(t, types.Integer) for t in (function, scene, ray)):
        return None

    def codegen(context, builder, signature, args):
        pointer = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [pointer, pointer, pointer])
        target = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(target, [builder.inttoptr(args[1], pointer), builder.inttoptr(args[2], pointer),
                              ir.Constant(pointer, None)])
        return context.get_dummy_value()

    return types.void(function, scene, ray), codegen


@numba.njit(cache=True, inline="always")
def _load_ray(f32, u32, origins, dirs, tfar, i):
    """Fill an ``RTCRay`` slot with ray ``i`` (tnear 0, every mask bit, no flags) and reset its hit."""
    for k in range(3):
        f32[k] = origins[i, k]
        f32[4 + k] = dirs[i, k]
    f32[3] = 0.0  # tnear
    f32[7] = 0.0  # time
    f32[8] = tfar[i]
    u32[9] = 0xFFFFFFFF  # mask
    u32[10] = 0  # id
    u32[11] = 0  # flags
    u32[18] = 0xFFFFFFFF  # hit.geomID = RTC_INVALID_GEOMETRY_ID
    u32[19] = 0xFFFFFFFF  # hit.instID[0]


@numba.njit(cache=True, parallel=True, nogil=True)
def _intersect_kernel(function, scene, origins, dirs, tfar, slot_f32, slot_u32, geom, prim, uv, dist):
    """Closest hits of float32 rays; per task ``t`` rays ``[t*step, (t+1)*step)`` through slot ``t``."""
    n = origins.shape[0]
    n_tasks = slot_f32.shape[0]
    step = (n + n_tasks - 1) // n_tasks
    for task in numba.prange(n_tasks):
        f32, u32 = slot_f32[task], slot_u32[task]
        address = f32.ctypes.data
        for i in range(task * step, min(n, (task + 1) * step)):
            if not tfar[i] > 0.0:
                continue
            _load_ray(f32, u32, origins, dirs, tfar, i)
            _rtc_call(function, scene, address)
            if u32[18] != 0xFFFFFFFF:
                geom[i] = u32[18]
                prim[i] = u32[17]
                uv[i, 0] = f32[15]
                uv[i, 1] = f32[16]
                dist[i] = f32[8]


@numba.njit(cache=True, parallel=True, nogil=True)
def _occluded_kernel(function, scene, origins, dirs, tfar, slot_f32, slot_u32, out):
    """Any-hit of float32 rays: Embree sets ``tfar`` to ``-inf`` on an occluded ray."""
    n = origins.shape[0]
    n_tasks = slot_f32.shape[0]
    step = (n + n_tasks - 1) // n_tasks
    for task in numba.prange(n_tasks):
        f32, u32 = slot_f32[task], slot_u32[task]
        address = f32.ctypes.data
        for i in range(task * step, min(n, (task + 1) * step)):
            if not tfar[i] > 0.0:
                continue
            _load_ray(f32, u32, origins, dirs, tfar, i)
            _rtc_call(function, scene, address)
            out[i] = f32[8] < 0.0


def _n_tasks(n: int) -> int:
    return max(1, -(-n // RAYS_PER_TASK))


def intersect(scene: EmbreeScene, origins, dirs, tfar, geom, prim, uv, dist) -> None:
    """Closest hits of ``n`` float32 rays into preset outputs (left as they are on a miss).

    Parameters
    ----------
    scene : EmbreeScene
    origins, dirs : (n, 3) float32, C-contiguous
    tfar : (n,) float32
        End of each ray; rays with ``tfar <= 0`` are not cast.
    geom, prim : (n,) int64
        Geometry (object) and primitive (face) ids of each hit.
    uv : (n, 2) float64
    dist : (n,) float64
    """
    slot_f32, slot_u32 = _slots(_n_tasks(len(origins)))
    with numba.parallel_chunksize(1):
        _intersect_kernel(scene.intersect_fn, scene.handle, origins, dirs, tfar, slot_f32, slot_u32,
                          geom, prim, uv, dist)


def occluded(scene: EmbreeScene, origins, dirs, tfar, out) -> None:
    """Any-hit of ``n`` float32 rays into ``out`` ((n,) bool, preset False); as :func:`intersect`."""
    slot_f32, slot_u32 = _slots(_n_tasks(len(origins)))
    with numba.parallel_chunksize(1):
        _occluded_kernel(scene.occluded_fn, scene.handle, origins, dirs, tfar, slot_f32, slot_u32, out)
