"""The YAML scene format: loading, validation and writing (``../shared/DESIGN.md``, "Scene files").

Everything is checked before any mesh is built or image read: first the whole
dict (keys, numbers, colours, file existence), then the environment images
(readable, finite, non-negative), then the meshes (faces, degenerate
triangles). Every failure is a
:class:`SceneError` naming the file and the key path.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ._scene import AreaLight, Camera, EnvironmentLight, Material, PointLight, Scene, SceneObject, Transform
from ._validate import SceneError, Validator, child, index, show

__all__ = [
    "load_scene",
    "scene_from_dict",
    "scene_to_dict",
    "save_scene",
    "build_environment",
    "DEGENERATE_FACE_FRACTION",
    "DEGENERATE_AREA_RTOL",
]

#: A mesh is rejected when more than this fraction of its faces have zero area.
DEGENERATE_FACE_FRACTION = 0.01
#: A face has "zero area" when its area is <= this times the squared bounding-box diagonal.
DEGENERATE_AREA_RTOL = 1e-12

_TOP_KEYS = ("name", "objects", "lights", "camera", "animation")
_OBJECT_KEYS = ("name", "mesh", "transform", "material", "dynamic", "portal")
_TRANSFORM_KEYS = ("translate", "rotate_deg", "scale")
_MATERIAL_KEYS = {"diffuse": ("type", "albedo"), "phong": ("type", "kd", "ks", "exponent")}
_LIGHT_KEYS = {
    "environment": ("type", "file", "sky", "constant", "scale"),
    "area": ("type", "center", "u", "v", "radiance"),
    "point": ("type", "position", "intensity"),
}
_ENV_SOURCES = ("file", "sky", "constant")
_SKY_KEYS = ("sun_elevation_deg", "sun_azimuth_deg", "turbidity", "sun", "height", "width")
_SKY_DEFAULTS = {"sun_azimuth_deg": 0.0, "turbidity": 3.0, "sun": False, "height": 128, "width": 256}
_CAMERA_KEYS = ("position", "look_at", "up", "fov_deg", "resolution")
#: Size of the image kept next to a constant environment (for methods that read ``image``).
_CONSTANT_MAP_SIZE = (8, 16)


# --------------------------------------------------------------------------- YAML


class _StrictLoader(yaml.SafeLoader):
    """Safe YAML (no object construction) that rejects duplicate keys instead of keeping the last."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    loader.flatten_mapping(node)
    out = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in out:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        out[key] = loader.construct_object(value_node, deep=deep)
    return out


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def load_scene(path) -> Scene:
    """Load and validate a YAML scene file.

    Parameters
    ----------
    path : str or path-like
        The scene file; relative paths inside it are relative to its folder.

    Returns
    -------
    Scene
        ``scene.name`` is the file's stem unless the file sets ``name``.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    SceneError
        (a ``ValueError``) for anything invalid, naming the file and the key
        path, before any mesh is built.
    """
    path = Path(os.fspath(path))
    if not path.is_file():
        raise FileNotFoundError(f"scene file not found: {str(path)!r}")
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=_StrictLoader)
    except yaml.YAMLError as err:
        raise SceneError(f"{path}: invalid YAML: {err}") from err
    return scene_from_dict(data, base_dir=path.parent, source=str(path), default_name=path.stem)


class _FlowListDumper(yaml.SafeDumper):
    """Safe YAML writer that puts lists of scalars on one line (``[0, 1, 0]``)."""


def _represent_list(dumper: yaml.SafeDumper, data: list):
    flow = all(not isinstance(x, (list, tuple, dict)) for x in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_FlowListDumper.add_representer(list, _represent_list)


def save_scene(scene: Scene, path) -> Path:
    """Write ``scene.to_dict()`` as YAML (paths inside stay as the scene stated them)."""
    path = Path(os.fspath(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    text = yaml.dump(scene_to_dict(scene), Dumper=_FlowListDumper, sort_keys=False)
    path.write_text(text, encoding="utf-8")
    return path


# --------------------------------------------------------------------------- dict -> Scene


def scene_from_dict(d: Any, base_dir=None, source: str | None = None, default_name: str = "scene") -> Scene:
    """Validate a scene dict (the YAML format) and build the :class:`Scene`.

    Parameters
    ----------
    d : dict
        Keys ``objects`` (required), ``lights``, ``camera``, ``animation``, ``name``.
    base_dir : path-like, optional
        Folder that relative file paths are relative to (default: the
        current directory).
    source : str, optional
        Name used in error messages (default ``<dict>``).
    """
    v = Validator(source or "<dict>")
    base_dir = Path(os.fspath(base_dir)) if base_dir is not None else None
    if d is None:
        raise v.error("", "the scene is empty; expected a mapping with an 'objects' list")
    v.mapping(d, "", _TOP_KEYS, required=("objects",))
    name = v.text(d["name"], "name") if "name" in d else default_name

    # ---- phase 1: the whole dict, no heavy work
    object_plans = []
    seen: dict[str, int] = {}
    for i, item in enumerate(v.sequence(d["objects"], "objects", nonempty=True)):
        plan = _check_object(v, item, index("objects", i), base_dir)
        if plan["name"] in seen:
            raise v.error(
                child(index("objects", i), "name"),
                f"duplicate object name {plan['name']!r} (also objects[{seen[plan['name']]}]); names must be unique",
            )
        seen[plan["name"]] = i
        object_plans.append(plan)
    light_plans = []
    env_index = None
    for i, item in enumerate(v.sequence(d.get("lights", []) or [], "lights")):
        plan = _check_light(v, item, index("lights", i), base_dir)
        if plan["type"] == "environment":
            if env_index is not None:
                raise v.error(
                    index("lights", i),
                    f"a scene has at most one environment light (lights[{env_index}] is one already); "
                    "combine them into one map",
                )
            env_index = i
        light_plans.append(plan)
    camera = _check_camera(v, d["camera"], "camera") if "camera" in d else Camera()
    animation = None
    if d.get("animation") is not None:
        from ._animation import check_animation

        animation = check_animation(v, d["animation"], "animation", [p["name"] for p in object_plans], light_plans)

    # ---- phase 2: lights (reading environment images is cheaper than building meshes)
    lights = [_build_light(v, plan, base_dir) for plan in light_plans]
    # ---- phase 3: meshes
    objects = [_build_object(v, plan, base_dir) for plan in object_plans]
    return Scene(objects=objects, lights=lights, camera=camera, animation=animation, base_dir=base_dir, name=name)


def _check_transform(v: Validator, t: Any, path: str) -> Transform:
    v.mapping(t, path, _TRANSFORM_KEYS)
    translate = v.vector(t["translate"], child(path, "translate")) if "translate" in t else np.zeros(3)
    rotate = v.vector(t["rotate_deg"], child(path, "rotate_deg")) if "rotate_deg" in t else np.zeros(3)
    scale = v.number(t["scale"], child(path, "scale"), positive=True) if "scale" in t else 1.0
    return Transform(translate=translate, rotate_deg=rotate, scale=scale)


def _check_material(v: Validator, m: Any, path: str) -> Material:
    if not isinstance(m, dict):
        v.mapping(m, path, ("type",))
    kind = v.choice(m.get("type", "diffuse"), child(path, "type"), _MATERIAL_KEYS, "material type")
    v.mapping(m, path, _MATERIAL_KEYS[kind])
    if kind == "diffuse":
        albedo = v.colour(m["albedo"], child(path, "albedo"), at_most_one=True) if "albedo" in m else np.full(3, 0.7)
        return Material(type="diffuse", albedo=albedo)
    v.mapping(m, path, _MATERIAL_KEYS[kind], required=("kd", "ks", "exponent"))
    kd = v.colour(m["kd"], child(path, "kd"), at_most_one=True)
    ks = v.colour(m["ks"], child(path, "ks"), at_most_one=True)
    if np.any(kd + ks > 1.0):
        raise v.error(
            path,
            f"kd + ks must be <= 1 in every channel (energy conservation of normalised Phong), "
            f"got kd={show(m['kd'])}, ks={show(m['ks'])}",
        )
    exponent = v.number(m["exponent"], child(path, "exponent"), minimum=0.0)
    return Material(type="phong", kd=kd, ks=ks, exponent=exponent)


def _check_mesh_spec(v: Validator, spec: Any, path: str, base_dir: Path | None) -> dict:
    from prtlab.geometry import BUILTIN_MESHES

    if isinstance(spec, str):
        return {"file": v.file(spec, path, base_dir)}
    if not isinstance(spec, dict) or "builtin" not in spec:
        raise v.error(path, f"expected a file path or {{builtin: name, ...}}, got {show(spec)}")
    name = v.choice(spec["builtin"], child(path, "builtin"), list(BUILTIN_MESHES), "builtin mesh")
    params = [k for k in spec if k != "builtin"]
    v.mapping(spec, path, ["builtin", *BUILTIN_MESHES[name]])
    return {"builtin": name, "params": {k: copy.deepcopy(spec[k]) for k in params}}


def _check_object(v: Validator, item: Any, path: str, base_dir: Path | None) -> dict:
    v.mapping(item, path, _OBJECT_KEYS, required=("name", "mesh"))
    return {
        "path": path,
        "name": v.text(item["name"], child(path, "name")),
        "mesh_spec": copy.deepcopy(item["mesh"]),
        "mesh": _check_mesh_spec(v, item["mesh"], child(path, "mesh"), base_dir),
        "transform": _check_transform(v, item["transform"], child(path, "transform"))
        if "transform" in item
        else Transform(),
        "material": _check_material(v, item["material"], child(path, "material"))
        if "material" in item
        else Material(),
        "dynamic": v.flag(item["dynamic"], child(path, "dynamic")) if "dynamic" in item else False,
        "portal": v.flag(item["portal"], child(path, "portal")) if "portal" in item else False,
    }


def _check_mesh(v: Validator, mesh, path: str) -> None:
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(faces) == 0:
        raise v.error(path, "mesh has no faces")
    if not np.all(np.isfinite(vertices)):
        raise v.error(path, "mesh has NaN or inf vertex coordinates")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise v.error(path, f"mesh faces index vertices outside 0..{len(vertices) - 1}")
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    diagonal2 = float(np.sum((vertices.max(axis=0) - vertices.min(axis=0)) ** 2))
    n_zero = int(np.count_nonzero(area <= DEGENERATE_AREA_RTOL * diagonal2))
    if n_zero > DEGENERATE_FACE_FRACTION * len(faces):
        raise v.error(
            path,
            f"{n_zero} of {len(faces)} faces ({100.0 * n_zero / len(faces):.1f}%) have zero area, above the "
            f"{100 * DEGENERATE_FACE_FRACTION:g}% limit (DEGENERATE_FACE_FRACTION); remove them first "
            "(e.g. trimesh's update_faces(mesh.nondegenerate_faces()))",
        )


def _build_object(v: Validator, plan: dict, base_dir: Path | None) -> SceneObject:
    from prtlab.geometry import builtin_mesh, load_mesh

    path = child(plan["path"], "mesh")
    spec = plan["mesh"]
    try:
        mesh = load_mesh(spec["file"]) if "file" in spec else builtin_mesh(spec["builtin"], **spec["params"])
    except (ValueError, TypeError) as err:
        raise v.error(path, str(err)) from err
    _check_mesh(v, mesh, path)
    return SceneObject(
        name=plan["name"],
        mesh=mesh,
        transform=plan["transform"],
        material=plan["material"],
        dynamic=plan["dynamic"],
        portal=plan["portal"],
        mesh_spec=plan["mesh_spec"],
    )


def check_sky(v: Validator, sky: Any, path: str) -> dict:
    """Validated sky parameters with defaults filled in (the normalised spec)."""
    v.mapping(sky, path, _SKY_KEYS, required=("sun_elevation_deg",))
    out = dict(_SKY_DEFAULTS)
    out.update(sky)
    return {
        "sun_elevation_deg": v.number(out["sun_elevation_deg"], child(path, "sun_elevation_deg"), minimum=0.0, maximum=90.0),
        "sun_azimuth_deg": v.number(out["sun_azimuth_deg"], child(path, "sun_azimuth_deg")),
        "turbidity": v.number(out["turbidity"], child(path, "turbidity"), minimum=1.7, maximum=10.0),
        "sun": v.flag(out["sun"], child(path, "sun")),
        "height": v.integer(out["height"], child(path, "height"), minimum=2),
        "width": v.integer(out["width"], child(path, "width"), minimum=1),
    }


def check_area_frame(v: Validator, u: np.ndarray, w: np.ndarray, path: str) -> None:
    """Area-light half edges must span a parallelogram (non-zero, not parallel)."""
    if np.linalg.norm(np.cross(u, w)) <= 1e-9 * np.linalg.norm(u) * np.linalg.norm(w):
        raise v.error(path, f"u {show(u)} and v {show(w)} are parallel: the area light has no area")


def _check_light(v: Validator, item: Any, path: str, base_dir: Path | None) -> dict:
    if not isinstance(item, dict):
        v.mapping(item, path, ("type",))
    v.mapping(item, path, list(dict.fromkeys(k for keys in _LIGHT_KEYS.values() for k in keys)), required=("type",))
    kind = v.choice(item["type"], child(path, "type"), _LIGHT_KEYS, "light type")
    v.mapping(item, path, _LIGHT_KEYS[kind])
    plan: dict[str, Any] = {"type": kind, "path": path}
    if kind == "environment":
        given = [k for k in _ENV_SOURCES if k in item]
        if len(given) != 1:
            raise v.error(path, f"an environment light needs exactly one of file, sky, constant; got {given or 'none'}")
        plan["scale"] = v.number(item["scale"], child(path, "scale"), minimum=0.0) if "scale" in item else 1.0
        if "file" in item:
            plan["file"] = v.file(item["file"], child(path, "file"), base_dir)
            plan["spec"] = {"file": item["file"]}
        elif "sky" in item:
            plan["spec"] = {"sky": check_sky(v, item["sky"], child(path, "sky"))}
        else:
            constant = v.colour(item["constant"], child(path, "constant"))
            plan["spec"] = {"constant": [float(c) for c in constant]}
    elif kind == "area":
        v.mapping(item, path, _LIGHT_KEYS[kind], required=("center", "u", "v", "radiance"))
        plan["center"] = v.vector(item["center"], child(path, "center"))
        plan["u"] = v.nonzero_vector(item["u"], child(path, "u"))
        plan["v"] = v.nonzero_vector(item["v"], child(path, "v"))
        check_area_frame(v, plan["u"], plan["v"], path)
        plan["radiance"] = v.colour(item["radiance"], child(path, "radiance"))
    else:
        v.mapping(item, path, _LIGHT_KEYS[kind], required=("position", "intensity"))
        plan["position"] = v.vector(item["position"], child(path, "position"))
        plan["intensity"] = v.colour(item["intensity"], child(path, "intensity"))
    return plan


def build_environment(spec: dict, scale: float, base_dir: Path | None = None, file: Path | None = None) -> EnvironmentLight:
    """The :class:`EnvironmentLight` of a validated spec (``file``, ``sky`` or ``constant``) times ``scale``."""
    from ._envmap import constant_envmap, preetham_sky, read_envmap

    constant = None
    if "file" in spec:
        path = file if file is not None else Path(spec["file"]) if Path(spec["file"]).is_absolute() else (
            (base_dir or Path.cwd()) / spec["file"]
        )
        image = read_envmap(path) * scale
    elif "sky" in spec:
        sky = spec["sky"]
        image = scale * preetham_sky(
            sky["sun_elevation_deg"], sky["sun_azimuth_deg"], sky["turbidity"], sky["height"], sky["width"], sky["sun"]
        )
    else:
        constant = scale * np.asarray(spec["constant"], dtype=np.float64)
        image = constant_envmap(constant, *_CONSTANT_MAP_SIZE)
    return EnvironmentLight(image=image, constant=constant, scale=float(scale), spec=copy.deepcopy(spec))


def _build_light(v: Validator, plan: dict, base_dir: Path | None):
    if plan["type"] == "area":
        return AreaLight(center=plan["center"], u=plan["u"], v=plan["v"], radiance=plan["radiance"])
    if plan["type"] == "point":
        return PointLight(position=plan["position"], intensity=plan["intensity"])
    try:
        env = build_environment(plan["spec"], plan["scale"], base_dir, plan.get("file"))
    except (ValueError, OSError) as err:
        raise v.error(child(plan["path"], "file"), str(err)) from err
    if env.image is not None and (not np.all(np.isfinite(env.image)) or np.any(env.image < 0)):
        raise v.error(child(plan["path"], "file"), "environment map has NaN, inf or negative radiance")
    return env


def _check_camera(v: Validator, c: Any, path: str) -> Camera:
    v.mapping(c, path, _CAMERA_KEYS)
    default = Camera()
    position = v.vector(c["position"], child(path, "position")) if "position" in c else default.position
    look_at = v.vector(c["look_at"], child(path, "look_at")) if "look_at" in c else default.look_at
    up = v.nonzero_vector(c["up"], child(path, "up")) if "up" in c else default.up
    view = look_at - position
    if not np.linalg.norm(view) > 0.0:
        raise v.error(child(path, "look_at"), f"look_at equals position {show(c.get('position', position))}; the camera looks nowhere")
    if np.linalg.norm(np.cross(view, up)) <= 1e-9 * np.linalg.norm(view) * np.linalg.norm(up):
        raise v.error(child(path, "up"), f"up {show(up)} is parallel to the view direction {show(view)}")
    fov = v.number(c["fov_deg"], child(path, "fov_deg"), positive=True, maximum=179.0) if "fov_deg" in c else default.fov_deg
    if "resolution" in c:
        res = c["resolution"]
        if not isinstance(res, (list, tuple)) or len(res) != 2:
            raise v.error(child(path, "resolution"), f"expected [width, height], got {show(res)}")
        resolution = tuple(v.integer(r, index(child(path, "resolution"), k), minimum=1) for k, r in enumerate(res))
    else:
        resolution = default.resolution
    return Camera(position=position, look_at=look_at, up=up, fov_deg=fov, resolution=resolution)


# --------------------------------------------------------------------------- Scene -> dict


def scene_to_dict(scene: Scene) -> dict:
    """The scene as a YAML-ready dict: ``Scene.from_dict(scene_to_dict(s), s.base_dir) == s``."""
    out: dict[str, Any] = {"name": scene.name}
    out["objects"] = [obj.to_dict() for obj in scene.objects]
    out["lights"] = [light.to_dict() for light in scene.lights]
    out["camera"] = scene.camera.to_dict()
    if scene.animation is not None:
        out["animation"] = copy.deepcopy(scene.animation)
    return out
