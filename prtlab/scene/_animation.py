"""Keyframe animation of object transforms and light parameters.

Format (the optional ``animation`` key of a scene file)::

    animation:
      duration: 4.0                  # seconds; default: the latest key time
      tracks:
        - object: bunny              # an object name
          keys:
            - {time: 0, translate: [0, 0, 0], rotate_deg: [0, 0, 0]}
            - {time: 2, translate: [1, 0, 0], rotate_deg: [0, 90, 0]}
            - {time: 4, translate: [0, 0, 0], rotate_deg: [0, 180, 0], scale: 1.0}
        - light: 0                   # an index into `lights`
          keys:
            - {time: 0, center: [0, 3, 0], radiance: [10, 10, 10]}
            - {time: 4, center: [1, 3, 0], radiance: [5, 5, 5]}

Animatable fields: objects ``translate``, ``rotate_deg``, ``scale``; area
lights ``center``, ``u``, ``v``, ``radiance``; point lights ``position``,
``intensity``; environment lights ``scale`` and, for a sky,
``sun_elevation_deg``, ``sun_azimuth_deg``, ``turbidity`` (for a constant
environment, ``constant``). Every key of a track sets the same fields; fields
no track animates keep their scene value. Key times are >= 0 and strictly
increasing.

Interpolation between the keys around ``t`` (``a = (t - t0) / (t1 - t0)``):
linear for every field except rotations, which are slerped as unit
quaternions along the shorter arc and converted back to ``rotate_deg``
(``R = Rz Ry Rx``, x first). Before the first key a track holds its first
key, after the last its last key; at a key time the key's values are
returned exactly.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from prtlab._validate import check_int
from ._scene import AreaLight, EnvironmentLight, PointLight, Scene, euler_to_matrix
from ._validate import Validator, child, clip, index, show

__all__ = [
    "scene_at_time",
    "scene_at_frame",
    "quaternion_from_matrix",
    "quaternion_to_matrix",
    "matrix_to_euler",
    "slerp",
]

_OBJECT_FIELDS = ("translate", "rotate_deg", "scale")
_LIGHT_FIELDS = {
    "area": ("center", "u", "v", "radiance"),
    "point": ("position", "intensity"),
    "environment/sky": ("scale", "sun_elevation_deg", "sun_azimuth_deg", "turbidity"),
    "environment/constant": ("scale", "constant"),
    "environment/file": ("scale",),
}


# --------------------------------------------------------------------------- rotations


def quaternion_from_matrix(matrix) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a (3, 3) rotation matrix (Shepperd's method)."""
    m = np.asarray(matrix, dtype=np.float64)
    trace = np.trace(m)
    candidates = np.array([trace, m[0, 0], m[1, 1], m[2, 2]])
    k = int(np.argmax(candidates))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quaternion_to_matrix(q) -> np.ndarray:
    """(3, 3) rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_euler(matrix) -> np.ndarray:
    """``[rx, ry, rz]`` in degrees with ``R = Rz(rz) Ry(ry) Rx(rx)``; ``ry`` in [-90, 90]."""
    m = np.asarray(matrix, dtype=np.float64)
    ry = np.arcsin(np.clip(-m[2, 0], -1.0, 1.0))
    if abs(m[2, 0]) < 1.0 - 1e-12:
        rx = np.arctan2(m[2, 1], m[2, 2])
        rz = np.arctan2(m[1, 0], m[0, 0])
    else:  # gimbal lock: only rx -+ rz is defined; put it all in rx
        rz = 0.0
        rx = np.arctan2(-m[1, 2], m[1, 1])
    return np.degrees(np.array([rx, ry, rz]))


def slerp(q0, q1, alpha: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    ``slerp(q0, q1, a) = sin((1 - a) W) / sin W q0 + sin(a W) / sin W q1`` with
    ``cos W = |q0 . q1|`` (``q1`` negated if ``q0 . q1 < 0``); nearly equal
    quaternions fall back to normalised linear interpolation.
    """
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 1.0 - 1e-12:
        q = (1.0 - alpha) * q0 + alpha * q1
    else:
        omega = np.arccos(dot)
        q = (np.sin((1.0 - alpha) * omega) * q0 + np.sin(alpha * omega) * q1) / np.sin(omega)
    return q / np.linalg.norm(q)


# --------------------------------------------------------------------------- validation


def _light_kind(plan: dict) -> str:
    if plan["type"] != "environment":
        return plan["type"]
    return "environment/" + next(k for k in ("sky", "constant", "file") if k in plan["spec"])


def _check_field(v: Validator, name: str, value, path: str):
    if name in ("translate", "center", "position"):
        return [float(c) for c in v.vector(value, path)]
    if name in ("u", "v"):
        return [float(c) for c in v.nonzero_vector(value, path)]
    if name == "rotate_deg":
        return [float(c) for c in v.vector(value, path)]
    if name in ("radiance", "intensity", "constant"):
        return [float(c) for c in v.colour(value, path)]
    if name == "scale":
        return v.number(value, path, minimum=0.0)  # objects are re-checked for > 0 below
    if name == "sun_elevation_deg":
        return v.number(value, path, minimum=0.0, maximum=90.0)
    if name == "sun_azimuth_deg":
        return v.number(value, path)
    if name == "turbidity":
        return v.number(value, path, minimum=1.7, maximum=10.0)
    raise AssertionError(name)  # pragma: no cover - fields come from the tables above


def check_animation(v: Validator, anim, path: str, object_names: list[str], light_plans: list[dict]) -> dict:
    """Validate the ``animation`` mapping; return it normalised (floats, lists, ``duration`` filled in)."""
    from ._load import check_area_frame

    v.mapping(anim, path, ("duration", "tracks"), required=("tracks",))
    tracks = []
    latest = 0.0
    for k, track in enumerate(v.sequence(anim["tracks"], child(path, "tracks"), nonempty=True)):
        tpath = index(child(path, "tracks"), k)
        v.mapping(track, tpath, ("object", "light", "keys"), required=("keys",))
        if ("object" in track) == ("light" in track):
            raise v.error(tpath, "a track animates exactly one target: set either 'object' or 'light'")
        if "object" in track:
            name = v.text(track["object"], child(tpath, "object"))
            if name not in object_names:
                raise v.error(
                    child(tpath, "object"), f"no object named {show(name)}; objects: {clip(', '.join(object_names), 200)}"
                )
            target: dict = {"object": name}
            allowed = _OBJECT_FIELDS
        else:
            i = v.integer(track["light"], child(tpath, "light"), minimum=0)
            if i >= len(light_plans):
                raise v.error(child(tpath, "light"), f"light index {i} out of range: the scene has {len(light_plans)} lights")
            target = {"light": i}
            allowed = _LIGHT_FIELDS[_light_kind(light_plans[i])]
        keys = []
        fields = None
        previous = -np.inf
        for j, key in enumerate(v.sequence(track["keys"], child(tpath, "keys"), nonempty=True)):
            kpath = index(child(tpath, "keys"), j)
            v.mapping(key, kpath, ("time", *allowed), required=("time",))
            time = v.number(key["time"], child(kpath, "time"), minimum=0.0)
            if not time > previous:
                raise v.error(child(kpath, "time"), f"key times must increase strictly, got {show(time)} after {show(previous)}")
            previous = time
            these = tuple(f for f in allowed if f in key)
            if not these:
                raise v.error(kpath, f"a key must set at least one of {', '.join(allowed)}")
            if fields is None:
                fields = these
            elif these != fields:
                raise v.error(kpath, f"every key of a track must set the same fields; the first sets {', '.join(fields)}")
            values = {"time": time}
            for f in these:
                values[f] = _check_field(v, f, key[f], child(kpath, f))
            if "object" in target and "scale" in values and not values["scale"] > 0.0:
                raise v.error(child(kpath, "scale"), f"expected a finite number > 0, got {show(key['scale'])}")
            if "u" in values or "v" in values:
                plan = light_plans[target["light"]]
                u = np.asarray(values.get("u", plan["u"]))
                w = np.asarray(values.get("v", plan["v"]))
                check_area_frame(v, u, w, kpath)
            keys.append(values)
        latest = max(latest, keys[-1]["time"])
        tracks.append({**target, "keys": keys})
    duration = v.number(anim["duration"], child(path, "duration"), minimum=0.0) if "duration" in anim else latest
    return {"duration": float(duration), "tracks": tracks}


# --------------------------------------------------------------------------- evaluation


def _interpolate(keys: list[dict], t: float) -> dict:
    """Values of a track at time ``t`` (fields other than ``time``)."""
    times = [key["time"] for key in keys]
    if t <= times[0]:
        return {f: copy.deepcopy(x) for f, x in keys[0].items() if f != "time"}
    if t >= times[-1]:
        return {f: copy.deepcopy(x) for f, x in keys[-1].items() if f != "time"}
    j = int(np.searchsorted(times, t, side="right")) - 1
    k0, k1 = keys[j], keys[j + 1]
    if t == k0["time"]:
        return {f: copy.deepcopy(x) for f, x in k0.items() if f != "time"}
    a = (t - k0["time"]) / (k1["time"] - k0["time"])
    out = {}
    for f in k0:
        if f == "time":
            continue
        if f == "rotate_deg":
            q0 = quaternion_from_matrix(euler_to_matrix(k0[f]))
            q1 = quaternion_from_matrix(euler_to_matrix(k1[f]))
            out[f] = matrix_to_euler(quaternion_to_matrix(slerp(q0, q1, a))).tolist()
        else:
            x0, x1 = np.asarray(k0[f], dtype=np.float64), np.asarray(k1[f], dtype=np.float64)
            value = (1.0 - a) * x0 + a * x1
            out[f] = value.tolist() if value.ndim else float(value)
    return out


def _check_time(t) -> float:
    if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) or not np.isfinite(t):
        raise ValueError(f"t must be a finite number of seconds, got {t!r}")
    return float(t)


def scene_at_time(scene: Scene, t: float) -> Scene:
    """The scene at time ``t``: a new :class:`Scene` (meshes shared) with animated transforms and lights.

    A scene without animation is returned as a shallow copy at any ``t``.
    """
    from ._load import build_environment

    t = _check_time(t)
    objects = [dataclasses.replace(obj) for obj in scene.objects]
    lights = list(scene.lights)
    tracks = (scene.animation or {}).get("tracks", [])
    by_name = {obj.name: obj for obj in objects}
    for track in tracks:
        values = _interpolate(track["keys"], t)
        if "object" in track:
            obj = by_name[track["object"]]
            tr = obj.transform
            obj.transform = dataclasses.replace(
                tr,
                translate=np.asarray(values.get("translate", tr.translate), dtype=np.float64),
                rotate_deg=np.asarray(values.get("rotate_deg", tr.rotate_deg), dtype=np.float64),
                scale=float(values.get("scale", tr.scale)),
            )
            continue
        i = track["light"]
        light = lights[i]
        if isinstance(light, AreaLight):
            lights[i] = AreaLight(
                **{f: np.asarray(values.get(f, getattr(light, f)), dtype=np.float64) for f in ("center", "u", "v", "radiance")}
            )
        elif isinstance(light, PointLight):
            lights[i] = PointLight(
                **{f: np.asarray(values.get(f, getattr(light, f)), dtype=np.float64) for f in ("position", "intensity")}
            )
        elif isinstance(light, EnvironmentLight):
            lights[i] = _environment_at(light, values, scene, build_environment)
    return dataclasses.replace(scene, objects=objects, lights=lights)


def _environment_at(light: EnvironmentLight, values: dict, scene: Scene, build_environment) -> EnvironmentLight:
    scale = float(values.get("scale", light.scale))
    spec = copy.deepcopy(light.spec)
    if "sky" in spec:
        for f in ("sun_elevation_deg", "sun_azimuth_deg", "turbidity"):
            if f in values:
                spec["sky"][f] = float(values[f])
        return build_environment(spec, scale, scene.base_dir)
    if "constant" in spec:
        if "constant" in values:
            spec["constant"] = list(values["constant"])
        return build_environment(spec, scale, scene.base_dir)
    if light.scale > 0.0:  # a file: rescale the loaded image instead of reading it again
        return dataclasses.replace(light, image=light.image * (scale / light.scale), scale=scale)
    return build_environment(spec, scale, scene.base_dir)


def scene_at_frame(scene: Scene, i: int, n_frames: int) -> Scene:
    """Frame ``i`` of ``n_frames``: ``scene_at_time(scene, duration * i / (n_frames - 1))`` (time 0 if one frame)."""
    n_frames = check_int(n_frames, "n_frames", 1)
    i = check_int(i, "frame index i", 0, n_frames - 1)
    t = 0.0 if n_frames == 1 else scene.duration * i / (n_frames - 1)
    return scene_at_time(scene, t)
