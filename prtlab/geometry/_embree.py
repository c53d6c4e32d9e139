"""Embree 4 through ``ctypes``, traced from numba kernels on every core.

:class:`EmbreeScene` builds one Embree scene (robust mode, one triangle
geometry per object, geometry id = object index) with the C API of the Embree 4
library that ships inside the ``embreex`` wheel. Numba kernels trace rays
through ``rtcIntersect1`` / ``rtcOccluded1`` by their addresses
(:func:`rtc_call`), each block of :data:`RAYS_PER_TASK` rays through its own
``RTCRayHit`` slot (:func:`ray_slots`, :func:`set_ray`), the threads of a
``prange`` loop taking blocks from a shared counter (:func:`fetch_add`): no
Python and no GIL per ray, so every numba thread traces (the kernels are in
:mod:`prtlab.geometry._raycast`).

Why not ``embreex``: its ``EmbreeScene.run`` holds the GIL while it traces, so
Python threads over ray chunks run one at a time; Embree's own thread pool
(TBB) only builds acceleration structures.

Contract and limits
    * Rays are float32 with ``tnear = 0`` (the caller offsets origins, see
      :mod:`prtlab.geometry._raycast`).
    * The library is found beside ``embreex`` (``embreex.libs/`` on Linux,
      ``embreex/.dylibs/`` on macOS, the ``embreex`` folder on Windows), else
      on the system path; :func:`load_library` raises :class:`EmbreeUnavailable`
      with one line saying what is missing.
    * Struct layouts follow ``embree4/rtcore_ray.h``: ``RTCRay`` is 48 bytes,
      ``RTCHit`` follows at byte 48 (``u, v`` at 60, 64; ``primID, geomID`` at
      68, 72). Each block's ``RTCRayHit`` lives in a 128-byte, 64-byte aligned
      slot, larger than any Embree 4 build's struct (80 or 96 bytes).
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

__all__ = ["EmbreeScene", "EmbreeUnavailable", "load_library", "ray_slots", "rtc_call", "set_ray", "fetch_add",
           "PACKET", "packet_slots", "rtc_call_packet", "set_packet_ray"]

RTC_SCENE_FLAG_ROBUST = 1 << 2
RTC_GEOMETRY_TYPE_TRIANGLE = 0
RTC_BUFFER_TYPE_INDEX = 0
RTC_BUFFER_TYPE_VERTEX = 1
RTC_FORMAT_UINT3 = 0x5003
RTC_FORMAT_FLOAT3 = 0x9003

#: Bytes of one ray slot and its alignment.
SLOT_BYTES = 128
SLOT_ALIGN = 64

#: Rays of one packet (``rtcIntersect16`` / ``rtcOccluded16``), and the bytes of a packet's slot: an
#: ``RTCRayHit16`` is the single ray's struct with every field an array of 16 (field ``f`` of lane ``k``
#: at word ``f * PACKET + k``), 1,280 or 1,344 bytes by the build.
PACKET = 16
PACKET_SLOT_BYTES = 1536

#: Rays a thread takes at a time from the queue of a query (:func:`fetch_add`).
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
    "rtcIntersect16": (None, [ctypes.c_void_p] * 4),
    "rtcOccluded16": (None, [ctypes.c_void_p] * 4),
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
        self.intersect16_fn = ctypes.cast(lib.rtcIntersect16, ctypes.c_void_p).value
        self.occluded16_fn = ctypes.cast(lib.rtcOccluded16, ctypes.c_void_p).value
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


def ray_slots(n_rays: int) -> tuple[np.ndarray, np.ndarray]:
    """Scratch ``RTCRayHit`` slots for a query of ``n_rays``, one per task of :data:`RAYS_PER_TASK` rays:
    64-byte aligned rows of 128 bytes, as float32 and uint32 views of the same memory."""
    n_tasks = max(1, -(-n_rays // RAYS_PER_TASK))
    raw = np.zeros(n_tasks * SLOT_BYTES + SLOT_ALIGN, dtype=np.uint8)
    start = (-raw.ctypes.data) % SLOT_ALIGN
    block = raw[start : start + n_tasks * SLOT_BYTES].reshape(n_tasks, SLOT_BYTES)
    return block.view(np.float32), block.view(np.uint32)


def packet_slots(n_tasks: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scratch ``RTCRayHit16`` slots, one per task: float32 and uint32 views of 64-byte aligned rows of
    :data:`PACKET_SLOT_BYTES`, and each task's 64-byte aligned ``valid`` mask (int32, 16 lanes)."""
    n_tasks = max(1, int(n_tasks))
    row = PACKET_SLOT_BYTES + 4 * PACKET  # the packet, then its mask (both 64-byte multiples)
    raw = np.zeros(n_tasks * row + SLOT_ALIGN, dtype=np.uint8)
    start = (-raw.ctypes.data) % SLOT_ALIGN
    block = raw[start : start + n_tasks * row].reshape(n_tasks, row)
    rays = block[:, :PACKET_SLOT_BYTES]
    return rays.view(np.float32), rays.view(np.uint32), block[:, PACKET_SLOT_BYTES:].view(np.int32)


@intrinsic
def rtc_call_packet(typingctx, function, valid, scene, ray):
    """``function(valid, scene, ray, NULL)`` for ``void (*)(const int*, RTCScene, RTCRay[Hit]16*, args*)``
    given as integer addresses (``rtcIntersect16``, ``rtcOccluded16``); nopython code only. Lanes whose
    ``valid`` word is 0 are neither traced nor written."""
    if not all(isinstance(t, types.Integer) for t in (function, valid, scene, ray)):
        return None

    def codegen(context, builder, signature, args):
        pointer = ir.IntType(8).as_pointer()
        fnty = ir.FunctionType(ir.VoidType(), [pointer] * 4)
        target = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(target, [builder.inttoptr(a, pointer) for a in args[1:]] + [ir.Constant(pointer, None)])
        return context.get_dummy_value()

    return types.void(function, valid, scene, ray), codegen


@intrinsic
def rtc_call(typingctx, function, scene, ray):
    """``function(scene, ray, NULL)`` for C functions ``void (*)(RTCScene, RTCRay[Hit]*, args*)`` given
    as integer addresses (``rtcIntersect1``, ``rtcOccluded1``); callable from nopython code only."""
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


@intrinsic
def fetch_add(typingctx, counter, increment):
    """Atomically ``counter[0] += increment``, returning the previous value (``counter``: int64 array).

    Threads of a ``prange`` loop take blocks of rays from one counter (dynamic scheduling): numba's
    ``prange`` splits its range evenly between threads ahead of time, so a thread that the operating
    system pauses, or that draws the costly rays, would otherwise hold up the whole query."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64
            and isinstance(increment, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        step = context.cast(builder, args[1], signature.args[1], types.int64)
        return builder.atomic_rmw("add", array.data, step, "monotonic")

    return types.int64(counter, increment), codegen


#: Offsets in an ``RTCRayHit`` slot, in 4-byte words.
TFAR, HIT_U, HIT_V, HIT_PRIM, HIT_GEOM = 8, 15, 16, 17, 18

#: ``RTC_INVALID_GEOMETRY_ID``: a miss.
INVALID_ID = 0xFFFFFFFF


@numba.njit(cache=True, inline="always")
def set_ray(f32, u32, ox, oy, oz, dx, dy, dz, tfar):
    """Write a float32 ray (tnear 0, every mask bit, no flags) into a slot and reset its hit."""
    f32[0], f32[1], f32[2], f32[3] = ox, oy, oz, 0.0
    f32[4], f32[5], f32[6], f32[7] = dx, dy, dz, 0.0
    f32[TFAR] = tfar
    u32[9], u32[10], u32[11] = INVALID_ID, 0, 0  # mask, id, flags
    u32[HIT_GEOM] = INVALID_ID
    u32[HIT_GEOM + 1] = INVALID_ID  # instID[0]


@numba.njit(cache=True, inline="always")
def set_packet_ray(f32, u32, k, ox, oy, oz, dx, dy, dz, tfar):
    """:func:`set_ray` for lane ``k`` of a packet slot (:func:`packet_slots`)."""
    w = PACKET
    f32[k], f32[w + k], f32[2 * w + k], f32[3 * w + k] = ox, oy, oz, 0.0
    f32[4 * w + k], f32[5 * w + k], f32[6 * w + k], f32[7 * w + k] = dx, dy, dz, 0.0
    f32[TFAR * w + k] = tfar
    u32[9 * w + k], u32[10 * w + k], u32[11 * w + k] = INVALID_ID, 0, 0
    u32[HIT_GEOM * w + k] = INVALID_ID
    u32[(HIT_GEOM + 1) * w + k] = INVALID_ID
