"""The YAML scene format: loading, validation and writing (``docs/SCENE_FORMAT.md``).

Everything is checked before any mesh is built or image read: first the file
itself (size, UTF-8 text, YAML nesting and alias expansion), then the whole
dict (keys, numbers, colours, file existence), then the environment images
(readable, 2:1, finite, non-negative, finite once scaled), then the meshes
(faces, coordinates, degenerate triangles). Every failure is a
:class:`SceneError` naming the file and the key path.
"""

from __future__ import annotations

import copy
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ._scene import AreaLight, Camera, EnvironmentLight, Material, PointLight, Scene, SceneObject, Transform
from ._validate import InwardNormalsWarning, SceneError, Validator, child, clip, index, show

__all__ = ["load_scene", "scene_from_dict", "scene_to_dict", "save_scene", "build_environment",
           "DEGENERATE_FACE_FRACTION", "DEGENERATE_AREA_RTOL", "MAX_SCENE_BYTES", "MAX_YAML_NODES", "MAX_YAML_DEPTH",
           "MAX_COORDINATE"]

#: A mesh is rejected when more than this fraction of its faces have zero area.
DEGENERATE_FACE_FRACTION = 0.01
#: A face has "zero area" when its area is <= this times the squared bounding-box diagonal.
DEGENERATE_AREA_RTOL = 1e-12
#: Scene files above this size are refused before parsing (the shipped scenes are about 3 kB).
MAX_SCENE_BYTES = 4 * 1024 * 1024
#: Most YAML nodes a scene may hold once every alias is expanded (nested aliases of a
#: "billion laughs" file expand exponentially; the shipped scenes have a few hundred).
MAX_YAML_NODES = 1_000_000
#: Deepest nesting of YAML lists and mappings (the format itself needs 7 levels).
MAX_YAML_DEPTH = 64
#: Largest accepted ``|coordinate|`` of a vertex, in object and in world space: squared
#: distances must stay inside float32's range (3.4e38), which the ray tracer (Embree) uses.
MAX_COORDINATE = 1e18
#: Environment maps must be equirect: width = 2 x height, to this relative tolerance.
_ASPECT_RTOL = 0.01

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
                None, None, f"duplicate key {show(key)}", key_node.start_mark
            )
        out[key] = loader.construct_object(value_node, deep=deep)
    return out


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def _yaml_error(source: str, err: Exception) -> SceneError:
    """One-line message of a YAML error (problem and position; the quoted context is left out)."""
    mark = getattr(err, "problem_mark", None) or getattr(err, "context_mark", None)
    problem = getattr(err, "problem", None) or getattr(err, "context", None)
    if problem is None:
        return SceneError(f"{source}: invalid YAML: {clip(str(err).splitlines()[0] if str(err) else type(err).__name__, 200)}")
    where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
    context = f"{err.context}; " if getattr(err, "context", None) and err.context != problem else ""
    return SceneError(f"{source}: invalid YAML: {clip(context + problem, 200)}{where}")


def _check_yaml_shape(text: str, source: str) -> None:
    """Refuse YAML nested deeper than :data:`MAX_YAML_DEPTH` or expanding to more than
    :data:`MAX_YAML_NODES` nodes, by streaming the parser's events (no recursion, no construction).

    The expanded size counts each alias as the whole node it refers to, so a
    "billion laughs" file is refused after reading a few hundred bytes of it.
    """
    sizes: dict[str, int] = {}  # anchor -> expanded node count
    starts: list[tuple[str | None, int]] = []  # open collections: (anchor, count when opened)
    count = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, yaml.ScalarEvent):
            count += 1
            if event.anchor:
                sizes[event.anchor] = 1
        elif isinstance(event, yaml.AliasEvent):
            if any(anchor == event.anchor for anchor, _ in starts):
                line = event.start_mark.line + 1 if event.start_mark else "?"
                raise SceneError(f"{source}: the alias *{clip(event.anchor)} refers to a value containing itself (line {line})")
            count += sizes.get(event.anchor, 0)  # an unknown anchor is the composer's error
        elif isinstance(event, yaml.CollectionStartEvent):
            count += 1
            starts.append((event.anchor, count - 1))
            if len(starts) > MAX_YAML_DEPTH:
                line = event.start_mark.line + 1 if event.start_mark else "?"
                raise SceneError(
                    f"{source}: lists and mappings are nested more than {MAX_YAML_DEPTH} levels deep "
                    f"(line {line}; MAX_YAML_DEPTH); a scene needs at most 7"
                )
        elif isinstance(event, yaml.CollectionEndEvent):
            anchor, start = starts.pop()
            if anchor:
                sizes[anchor] = count - start
        if count > MAX_YAML_NODES:
            raise SceneError(
                f"{source}: the YAML expands to more than {MAX_YAML_NODES:,} values once its aliases "
                "(*name) are expanded (MAX_YAML_NODES); is it an alias bomb? write the scene out without nested aliases"
            )


def _read_yaml(path: Path) -> Any:
    """The YAML document of a scene file, after the checks on size, encoding, nesting and aliases."""
    source = str(path)
    size = path.stat().st_size
    if size > MAX_SCENE_BYTES:
        raise SceneError(
            f"{source}: the file is {size:,} bytes, above the {MAX_SCENE_BYTES:,}-byte limit of a scene file "
            "(MAX_SCENE_BYTES); keep meshes and maps in their own files and refer to them by path"
        )
    raw = path.read_bytes()
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise SceneError(f"{source}: not a UTF-8 text file (it is UTF-16, by its byte-order mark); save it as UTF-8")
    if b"\x00" in raw:
        raise SceneError(f"{source}: not a UTF-8 text file (it holds NUL bytes); a scene file is YAML text")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise SceneError(
            f"{source}: not a UTF-8 text file (byte 0x{raw[err.start]:02x} at offset {err.start} is not UTF-8); "
            "a scene file is YAML text saved as UTF-8"
        ) from None
    try:
        _check_yaml_shape(text, source)
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as err:
        raise _yaml_error(source, err) from None
    except RecursionError:  # pragma: no cover - the depth check comes first
        raise SceneError(f"{source}: lists and mappings are nested too deeply") from None


def _resolve_scene_path(path) -> Path:
    """``path`` itself, or for a bare name (no folder, no suffix, not a file) the shipped scene of that name."""
    if isinstance(path, str) and path and not os.path.exists(path):
        if "/" not in path and os.sep not in path and not Path(path).suffix:
            from prtlab.data import scene_path

            return Path(scene_path(path))
    return Path(os.fspath(path))


def load_scene(path) -> Scene:
    """Load and validate a YAML scene file, or a shipped scene by name.

    Parameters
    ----------
    path : str or path-like
        The scene file; relative paths inside it are relative to its folder.
        A bare name that is not a file (no folder, no suffix, e.g.
        ``"cornell_box"``) is a shipped scene, found by
        :func:`prtlab.data.scene_path`.

    Returns
    -------
    Scene
        ``scene.name`` is the file's stem unless the file sets ``name``.

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist (for a name: no shipped scene has it).
    SceneError
        (a ``ValueError``) for anything invalid, naming the file and the key
        path, before any mesh is built. Files above :data:`MAX_SCENE_BYTES`,
        that are not UTF-8 text, nest deeper than :data:`MAX_YAML_DEPTH` or
        expand past :data:`MAX_YAML_NODES` values are refused before they are
        parsed into Python objects.

    Warns
    -----
    InwardNormalsWarning
        For a closed mesh whose faces point inward while the camera is
        outside it (it would render black).
    """
    path = _resolve_scene_path(path)
    if not path.is_file():
        what = "is a folder, not a scene file" if path.is_dir() else "not found"
        raise FileNotFoundError(f"scene file {what}: {clip(repr(str(path)), 200)}")
    data = _read_yaml(path)
    return scene_from_dict(data, base_dir=path.parent, source=str(path), default_name=path.stem)


class _FlowListDumper(yaml.SafeDumper):
    """Safe YAML writer that puts lists of scalars on one line (``[0, 1, 0]``)."""


def _represent_list(dumper: yaml.SafeDumper, data: list):
    flow = all(not isinstance(x, (list, tuple, dict)) for x in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_FlowListDumper.add_representer(list, _represent_list)


def _moved_path(name: str, base_dir: Path | None, new_dir: Path) -> str:
    """A file reference of a scene in ``base_dir``, rewritten for a scene file in ``new_dir``.

    Absolute paths stay as they are; a relative one becomes relative to
    ``new_dir`` (with ``/`` separators), or absolute where no relative path
    exists (another drive).
    """
    p = Path(name).expanduser()
    if p.is_absolute():
        return name
    target = Path(os.path.abspath((base_dir or Path.cwd()) / p))
    try:
        return Path(os.path.relpath(target, os.path.abspath(new_dir))).as_posix()
    except ValueError:  # another drive (Windows): no relative path
        return str(target)


def save_scene(scene: Scene, path) -> Path:
    """Write ``scene.to_dict()`` as a YAML scene file that :func:`load_scene` reads back.

    Relative mesh and environment-map paths are relative to the scene's
    ``base_dir`` (the folder of the file it came from; the working directory
    if None); they are rewritten relative to the new file's folder, so a
    scene saved in another folder still finds its files. Absolute paths are
    kept.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(os.fspath(path))
    if path.is_dir():
        raise IsADirectoryError(f"save_scene: {str(path)!r} is a folder; give the scene file's path (e.g. scene.yaml)")
    d = scene_to_dict(scene)
    new_dir = path.parent if str(path.parent) else Path(".")
    for obj in d["objects"]:
        if isinstance(obj["mesh"], str):
            obj["mesh"] = _moved_path(obj["mesh"], scene.base_dir, new_dir)
    for light in d["lights"]:
        if light.get("type") == "environment" and isinstance(light.get("file"), str):
            light["file"] = _moved_path(light["file"], scene.base_dir, new_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = yaml.dump(d, Dumper=_FlowListDumper, sort_keys=False, allow_unicode=True)
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
    if not isinstance(d, dict):
        raise v.error(
            "",
            f"a scene is a mapping (keys {', '.join(_TOP_KEYS)}) at the top level, got {_describe(d)}",
        )
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
                f"duplicate object name {show(plan['name'])} (also objects[{seen[plan['name']]}]); names must be unique",
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
    if animation is not None:
        _check_animated_scales(v, animation, light_plans)
    # ---- phase 3: meshes
    objects = [_build_object(v, plan, base_dir) for plan in object_plans]
    if animation is not None:
        _check_animated_placements(v, animation, object_plans, objects)
    for plan, obj in zip(object_plans, objects):
        _warn_if_inward(v, plan["path"], obj, camera)
    return Scene(objects=objects, lights=lights, camera=camera, animation=animation, base_dir=base_dir, name=name)


def _describe(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return f"a list {show(value)}"
    return f"{type(value).__name__} {show(value)}"


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
    largest = float(np.abs(vertices).max())
    if largest > MAX_COORDINATE:
        raise v.error(
            path,
            f"mesh coordinates reach {largest:.3g}, beyond the +-{MAX_COORDINATE:g} limit (MAX_COORDINATE: "
            "squared distances must fit in float32 for ray tracing); rescale the mesh file and set transform.scale",
        )
    area = _relative_face_areas(vertices, faces)
    n_zero = int(np.count_nonzero(area <= DEGENERATE_AREA_RTOL))
    if n_zero > DEGENERATE_FACE_FRACTION * len(faces):
        raise v.error(
            path,
            f"{n_zero} of {len(faces)} faces ({100.0 * n_zero / len(faces):.1f}%) have zero area, above the "
            f"{100 * DEGENERATE_FACE_FRACTION:g}% limit (DEGENERATE_FACE_FRACTION); remove them first "
            "(e.g. trimesh's update_faces(mesh.nondegenerate_faces()))",
        )


def _relative_face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) face areas over the squared bounding-box diagonal, computed on vertices
    scaled to a unit diagonal (no overflow or underflow at any mesh size)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    scale = float(np.max(hi - lo))
    if not scale > 0.0:
        return np.zeros(len(faces))
    unit = (vertices - 0.5 * (lo + hi)) / scale
    diagonal2 = float(np.sum(((hi - lo) / scale) ** 2))
    tri = unit[faces]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / diagonal2


def closed_signed_volume(vertices, faces) -> float | None:
    """Signed volume of a closed, consistently wound mesh; ``None`` if the mesh is open.

    Coincident vertices are merged first (positions equal to 1e-9 of the
    bounding box), so meshes that split their vertices along sharp edges
    (the built-in box) count as closed. The mesh is closed when every
    directed edge ``a -> b`` of a face meets exactly one reversed edge
    ``b -> a`` of another face. The volume ``sum_f v0 . (v1 x v2) / 6`` is
    positive when the faces wind counter-clockwise seen from outside
    (outward normals) and negative when they point inward.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0 or len(vertices) == 0:
        return None
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    scale = float(np.max(hi - lo))
    if not (scale > 0.0 and np.isfinite(scale)):
        return None
    unit = (vertices - 0.5 * (lo + hi)) / scale
    _, first, inverse = np.unique(np.round(unit * 1e9), axis=0, return_index=True, return_inverse=True)
    merged = inverse.reshape(-1)[faces]
    merged = merged[(merged[:, 0] != merged[:, 1]) & (merged[:, 1] != merged[:, 2]) & (merged[:, 0] != merged[:, 2])]
    if len(merged) == 0:
        return None
    n = np.int64(len(first))
    heads = merged.reshape(-1)
    tails = np.roll(merged, -1, axis=1).reshape(-1)
    directed = heads * n + tails
    reverse = tails * n + heads
    unique_directed = np.unique(directed)
    if len(unique_directed) != len(directed):  # an edge used twice in one direction: inconsistent or non-manifold
        return None
    if not np.array_equal(unique_directed, np.unique(reverse)):  # a boundary edge: open
        return None
    points = unit[first]
    a, b, c = points[merged[:, 0]], points[merged[:, 1]], points[merged[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0) * scale**3


def _warn_if_inward(v: Validator, path: str, obj: SceneObject, camera: Camera) -> None:
    """Warn about a closed mesh with inward faces when the camera is outside its bounding box."""
    volume = closed_signed_volume(obj.mesh.vertices, obj.mesh.faces)
    if volume is None or not volume < 0.0:
        return
    world = obj.world_vertices()
    lo, hi = world.min(axis=0), world.max(axis=0)
    if np.all(camera.position >= lo) and np.all(camera.position <= hi):
        return  # a room seen from inside: inward faces are what it needs
    warnings.warn(
        InwardNormalsWarning(
            f"{v.source}: {path} ({show(obj.name)}): the mesh is closed but its faces point inward (signed volume "
            f"{volume:.3g} < 0), so seen from outside it shades black; flip its faces (reverse each face's "
            "vertex order, trimesh's mesh.invert()), or place the camera inside it if it is a room"
        ),
        stacklevel=4,
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
    _check_placement(v, mesh, plan["transform"], child(plan["path"], "transform"))
    return SceneObject(
        name=plan["name"],
        mesh=mesh,
        transform=plan["transform"],
        material=plan["material"],
        dynamic=plan["dynamic"],
        portal=plan["portal"],
        mesh_spec=plan["mesh_spec"],
    )


def _placement_bound(mesh, transform: Transform) -> float:
    """An upper bound of ``|world coordinate|`` of the mesh under ``transform`` (inf on overflow)."""
    radius = float(np.sqrt(np.max(np.sum(np.asarray(mesh.vertices, dtype=np.float64) ** 2, axis=1))))
    with np.errstate(over="ignore", invalid="ignore"):
        return float(transform.scale) * radius + float(np.linalg.norm(transform.translate))


def _check_placement(v: Validator, mesh, transform: Transform, path: str) -> None:
    """World coordinates must stay within :data:`MAX_COORDINATE` (scale and translate can push them out)."""
    with np.errstate(over="ignore", invalid="ignore"):
        world = transform.apply_points(mesh.vertices)
    largest = float(np.abs(world).max()) if np.all(np.isfinite(world)) else np.inf
    if not largest <= MAX_COORDINATE:
        raise v.error(
            path,
            f"places the mesh at world coordinates up to {largest:.3g}, beyond the +-{MAX_COORDINATE:g} limit "
            "(MAX_COORDINATE); use a smaller scale or translate",
        )


def _check_animated_placements(v: Validator, animation: dict, object_plans: list, objects: list) -> None:
    """Every key of an object track must keep the object's world coordinates within :data:`MAX_COORDINATE`."""
    by_name = {obj.name: obj for obj in objects}
    for k, track in enumerate(animation["tracks"]):
        if "object" not in track:
            continue
        obj = by_name[track["object"]]
        for j, key in enumerate(track["keys"]):
            moved = Transform(
                translate=np.asarray(key.get("translate", obj.transform.translate), dtype=np.float64),
                rotate_deg=obj.transform.rotate_deg,
                scale=float(key.get("scale", obj.transform.scale)),
            )
            if not _placement_bound(obj.mesh, moved) <= MAX_COORDINATE:
                raise v.error(
                    index(child(index("animation.tracks", k), "keys"), j),
                    f"places object {show(obj.name)} beyond world coordinates +-{MAX_COORDINATE:g} (MAX_COORDINATE); "
                    "use a smaller scale or translate",
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


def _environment_file(spec: dict, base_dir: Path | None, file: Path | None) -> Path:
    if file is not None:
        return file
    name = Path(spec["file"]).expanduser()
    return name if name.is_absolute() else (base_dir or Path.cwd()) / name


def _unscaled_environment(spec: dict, base_dir: Path | None = None, file: Path | None = None):
    """(image, constant) of a validated spec before ``scale``: a file's pixels, the sky, or the constant."""
    from ._envmap import constant_envmap, preetham_sky, read_envmap

    if "file" in spec:
        return read_envmap(_environment_file(spec, base_dir, file)), None
    if "sky" in spec:
        sky = spec["sky"]
        image = preetham_sky(
            sky["sun_elevation_deg"], sky["sun_azimuth_deg"], sky["turbidity"], sky["height"], sky["width"], sky["sun"]
        )
        return image, None
    constant = np.asarray(spec["constant"], dtype=np.float64)
    return constant_envmap(constant, *_CONSTANT_MAP_SIZE), constant


def build_environment(spec: dict, scale: float, base_dir: Path | None = None, file: Path | None = None) -> EnvironmentLight:
    """The :class:`EnvironmentLight` of a validated spec (``file``, ``sky`` or ``constant``) times ``scale``."""
    image, constant = _unscaled_environment(spec, base_dir, file)
    return _scaled_environment(image, constant, scale, spec)


def _scaled_environment(image, constant, scale: float, spec: dict) -> EnvironmentLight:
    image = image * scale
    constant = None if constant is None else scale * constant
    return EnvironmentLight(image=image, constant=constant, scale=float(scale), spec=copy.deepcopy(spec))


def _check_environment_image(v: Validator, image: np.ndarray, path: str, name: str) -> None:
    """An environment file's pixels: equirect 2:1, at least 2 x 4, finite, non-negative."""
    height, width = image.shape[:2]
    if height < 2 or abs(width - 2 * height) > _ASPECT_RTOL * width:
        raise v.error(
            path,
            f"environment map {clip(repr(name))} is {width} x {height} pixels (width x height); an equirect "
            "(latitude-longitude) map has width = 2 x height and height >= 2: convert cubemaps, mirror balls "
            "and crops to equirect first",
        )
    bad = ~np.isfinite(image)
    if np.any(bad):
        i, j = np.argwhere(bad)[0][:2]
        raise v.error(
            path,
            f"environment map {clip(repr(name))} has {int(bad.any(axis=-1).sum()):,} NaN or inf pixels "
            f"(the first at row {i}, column {j}); radiance must be finite",
        )
    if np.any(image < 0):
        i, j = np.argwhere(image < 0)[0][:2]
        raise v.error(
            path,
            f"environment map {clip(repr(name))} has {int((image < 0).any(axis=-1).sum()):,} pixels with negative "
            f"radiance (the first at row {i}, column {j}: {show(image[i, j])}); radiance must be >= 0",
        )


def _check_scale(v: Validator, image: np.ndarray, scale: float, path: str) -> None:
    """``scale`` times the map must stay finite, and so must its sum over the sphere."""
    with np.errstate(over="ignore", invalid="ignore"):
        raw = float(np.sum(image, dtype=np.float64))
        total = raw * scale
    if not np.isfinite(raw):
        raise v.error(path, f"values up to {float(np.max(image)):.3g} make the map's total radiance overflow float64; use smaller values")
    if not np.isfinite(total):
        raise v.error(
            path, f"scale {show(scale)} times the map (total {raw:.3g} over its pixels) overflows float64; use a smaller scale"
        )


def _build_light(v: Validator, plan: dict, base_dir: Path | None):
    if plan["type"] == "area":
        return AreaLight(center=plan["center"], u=plan["u"], v=plan["v"], radiance=plan["radiance"])
    if plan["type"] == "point":
        return PointLight(position=plan["position"], intensity=plan["intensity"])
    file_key = child(plan["path"], "file")
    try:
        image, constant = _unscaled_environment(plan["spec"], base_dir, plan.get("file"))
    except (ValueError, OSError) as err:
        raise v.error(file_key, str(err)) from err
    if "file" in plan["spec"]:
        _check_environment_image(v, image, file_key, plan["spec"]["file"])
    elif "constant" in plan["spec"]:
        _check_scale(v, image, 1.0, child(plan["path"], "constant"))
    _check_scale(v, image, plan["scale"], child(plan["path"], "scale"))
    plan["unscaled_image"] = image  # for the animated scales
    return _scaled_environment(image, constant, plan["scale"], plan["spec"])


def _check_animated_scales(v: Validator, animation: dict, light_plans: list) -> None:
    """The animated ``scale`` of an environment light must keep the map finite at every key."""
    for k, track in enumerate(animation["tracks"]):
        if "light" not in track or "unscaled_image" not in light_plans[track["light"]]:
            continue
        plan = light_plans[track["light"]]
        for j, key in enumerate(track["keys"]):
            kpath = index(child(index("animation.tracks", k), "keys"), j)
            image = plan["unscaled_image"]
            if "constant" in key:
                image = np.broadcast_to(np.asarray(key["constant"], dtype=np.float64), image.shape)
                _check_scale(v, image, 1.0, child(kpath, "constant"))
            _check_scale(v, image, key.get("scale", plan["scale"]), child(kpath, "scale"))


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
