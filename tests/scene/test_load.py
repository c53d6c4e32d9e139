"""Tests of prtlab/scene/_load.py and _validate.py: the YAML scene format, validation messages, round trips."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import yaml

import prtlab
import prtlab.data
from prtlab.scene import (
    DEGENERATE_FACE_FRACTION,
    AreaLight,
    EnvironmentLight,
    Material,
    PointLight,
    Scene,
    SceneError,
    SceneObject,
    load_scene,
    preetham_sky,
    save_scene,
    write_exr,
)
from tests import scenes
from tests.scenes import DELETE as _DELETE

SCENES_DIR = prtlab.data.path("scenes")


def base_dict() -> dict:
    """A small valid scene touching every key."""
    return {
        "name": "small",
        "objects": [
            {
                "name": "floor",
                "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [3, 3]},
                "transform": {"translate": [0, 0, 0], "rotate_deg": [0, 0, 0], "scale": 1.0},
                "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]},
                "dynamic": False,
            },
            {
                "name": "ball",
                "mesh": {"builtin": "icosphere", "subdivisions": 1, "radius": 0.5},
                "transform": {"translate": [0, 0.5, 0], "rotate_deg": [10, 20, 30], "scale": 2.0},
                "material": {"type": "phong", "kd": [0.3, 0.3, 0.3], "ks": [0.5, 0.4, 0.3], "exponent": 20},
                "dynamic": True,
            },
        ],
        "lights": [
            {"type": "environment", "constant": [0.5, 0.6, 0.7], "scale": 2.0},
            {"type": "area", "center": [0, 3, 0], "u": [0.5, 0, 0], "v": [0, 0, 0.5], "radiance": [10, 10, 10]},
            {"type": "point", "position": [1, 3, 0], "intensity": [5, 5, 5]},
        ],
        "camera": {"position": [0, 2, 6], "look_at": [0, 0.5, 0], "up": [0, 1, 0], "fov_deg": 40, "resolution": [64, 48]},
    }


def with_change(path: str, value, d: dict | None = None) -> dict:
    """A copy of ``d`` (default ``base_dict()``) with the item at a dotted path replaced or deleted."""
    return scenes.with_change(d or base_dict(), path, value)


# ----------------------------------------------------------------------------- loading and round trips


def test_from_dict_builds_every_part():
    scene = Scene.from_dict(base_dict())
    assert scene.name == "small"
    assert [o.name for o in scene.objects] == ["floor", "ball"]
    assert scene.object("floor").n_vertices == 16
    ball = scene.object("ball")
    assert ball.dynamic and not ball.portal
    assert ball.material.type == "phong" and ball.material.exponent == 20.0
    np.testing.assert_allclose(ball.transform.rotate_deg, [10, 20, 30])
    env = scene.environment
    np.testing.assert_allclose(env.constant, [1.0, 1.2, 1.4])  # constant times scale
    np.testing.assert_allclose(env.radiance(np.array([[0.0, 1.0, 0.0]])), [[1.0, 1.2, 1.4]])
    np.testing.assert_allclose(env.image[3, 5], [1.0, 1.2, 1.4])  # a small constant map for image readers
    assert isinstance(scene.area_lights[0], AreaLight) and isinstance(scene.point_lights[0], PointLight)
    np.testing.assert_allclose(scene.area_lights[0].normal, [0, -1, 0])
    assert scene.camera.resolution == (64, 48)


def test_defaults():
    scene = Scene.from_dict({"objects": [{"name": "a", "mesh": {"builtin": "plane"}}]})
    obj = scene.objects[0]
    assert obj.material == Material() and obj.transform.scale == 1.0 and not obj.dynamic and not obj.portal
    assert scene.lights == [] and scene.animation is None and scene.name == "scene"


def test_dict_round_trip():
    scene = Scene.from_dict(base_dict())
    d = scene.to_dict()
    again = Scene.from_dict(d)
    assert again == scene
    assert yaml.safe_load(yaml.safe_dump(d)) == d  # plain YAML types only
    changed = Scene.from_dict(with_change("objects.1.transform.scale", 2.5))
    assert changed != scene


def test_sky_round_trip_fills_defaults():
    d = base_dict()
    d["lights"][0] = {"type": "environment", "sky": {"sun_elevation_deg": 30, "height": 16, "width": 32}}
    scene = Scene.from_dict(d)
    sky = scene.environment.to_dict()["sky"]
    assert sky == {"sun_elevation_deg": 30.0, "sun_azimuth_deg": 0.0, "turbidity": 3.0, "sun": False, "height": 16, "width": 32}
    np.testing.assert_array_equal(scene.environment.image, preetham_sky(30.0, 0.0, 3.0, 16, 32))
    assert Scene.from_dict(scene.to_dict()) == scene


def test_file_round_trip_with_relative_paths(tmp_path, monkeypatch):
    folder = tmp_path / "scene"
    (folder / "meshes").mkdir(parents=True)
    trimesh.creation.box().export(folder / "meshes" / "box.ply")
    image = np.full((8, 16, 3), 0.25)
    write_exr(folder / "env.exr", image)
    d = base_dict()
    d["objects"][0]["mesh"] = "meshes/box.ply"
    d["lights"][0] = {"type": "environment", "file": "env.exr", "scale": 4.0}
    (folder / "scene.yaml").write_text(yaml.safe_dump(d))
    monkeypatch.chdir(tmp_path)  # paths resolve against the scene file, not the working directory
    scene = load_scene(folder / "scene.yaml")
    assert scene.base_dir == folder
    assert len(scene.object("floor").mesh.faces) == 12
    np.testing.assert_allclose(scene.environment.image, 1.0)  # file times scale
    out = save_scene(scene, folder / "copy.yaml")
    assert load_scene(out) == scene
    assert prtlab.load_scene(folder / "scene.yaml") == Scene.load(folder / "scene.yaml") == scene
    assert "meshes/box.ply" in out.read_text()


def test_name_defaults_to_file_stem(tmp_path):
    d = base_dict()
    del d["name"]
    (tmp_path / "my_scene.yaml").write_text(yaml.safe_dump(d))
    assert load_scene(tmp_path / "my_scene.yaml").name == "my_scene"


def test_python_built_objects_need_a_mesh_spec():
    obj = SceneObject(name="a", mesh=trimesh.creation.box())
    with pytest.raises(ValueError, match="has no mesh_spec"):
        Scene(objects=[obj]).to_dict()
    with pytest.raises(ValueError, match="no spec"):
        EnvironmentLight(image=np.ones((4, 8, 3))).to_dict()


@pytest.mark.parametrize("path", sorted(SCENES_DIR.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_scene_file_loads(path):
    scene = load_scene(path)
    assert scene.objects and scene.lights
    assert scene.name == path.stem
    assert sum(o.n_vertices for o in scene.objects) < 10_000  # quick reference renders
    for obj in scene.objects:
        assert np.all(np.isfinite(obj.world_vertices()))
    assert Scene.from_dict(scene.to_dict(), base_dir=scene.base_dir) == scene
    if scene.animation:
        scene.at_frame(1, 3)


def test_scene_files_cover_the_papers():
    names = {p.stem for p in SCENES_DIR.glob("*.yaml")}
    assert {
        "bunny_floor_arealight",
        "teapots_room",
        "spheres_on_plane_env",
        "bunny_spheres_env",
        "box_window_sky",
        "box_window_glossy_bunny",
        "cornell_box",
    } <= names
    assert any(o.portal for o in load_scene(SCENES_DIR / "box_window_sky.yaml").objects)


# ----------------------------------------------------------------------------- validation messages


@pytest.mark.parametrize(
    "path, value, match",
    [
        # unknown keys, with the closest valid one suggested
        ("objects.0.materal", {}, r"objects\[0\]\.materal: unknown key; did you mean 'material'\?"),
        ("camra", {}, r"camra: unknown key; did you mean 'camera'\?"),
        ("objects.0.transform.rotate", [0, 0, 0], r"objects\[0\]\.transform\.rotate: unknown key; did you mean 'rotate_deg'"),
        ("objects.0.mesh.sise", [1, 1], r"objects\[0\]\.mesh\.sise: unknown key; did you mean 'size'"),
        ("lights.1.radience", [1, 1, 1], r"lights\[1\]\.radience: unknown key; did you mean 'radiance'"),
        ("objects.0.material.kd", [0.5, 0.5, 0.5], r"objects\[0\]\.material\.kd: unknown key"),
        # colours and reflectances
        ("objects.0.material.albedo", [0.5, float("nan"), 1], r"objects\[0\]\.material\.albedo: expected 3 non-negative finite numbers, got \[0\.5, nan, 1\]"),
        ("objects.0.material.albedo", [0.5, -0.1, 0.5], r"albedo: expected 3 non-negative finite numbers, got \[0\.5, -0\.1, 0\.5\]"),
        ("objects.0.material.albedo", [0.5, 1.2, 0.5], r"albedo: reflectance above 1 reflects more light than it receives \(energy gain\)"),
        ("objects.0.material.albedo", [0.5, 0.5], r"albedo: expected 3 non-negative finite numbers, got \[0\.5, 0\.5\]"),
        ("objects.1.material.ks", [0.8, 0.4, 0.3], r"objects\[1\]\.material: kd \+ ks must be <= 1 in every channel"),
        ("objects.1.material.exponent", -1, r"objects\[1\]\.material\.exponent: expected a finite number >= 0"),
        ("objects.1.material.kd", _DELETE, r"objects\[1\]\.material: missing required key 'kd'"),
        ("objects.0.material.type", "lambert", r"objects\[0\]\.material\.type: unknown material type 'lambert'"),
        ("objects.0.material.type", "difuse", r"unknown material type 'difuse'; did you mean 'diffuse'\?"),
        # lights
        ("lights.1.radiance", [1, float("nan"), 1], r"lights\[1\]\.radiance: expected 3 non-negative finite numbers, got \[1, nan, 1\]"),
        ("lights.1.radiance", [1, -1, 1], r"lights\[1\]\.radiance: expected 3 non-negative finite numbers"),
        ("lights.2.intensity", [1, 1, float("inf")], r"lights\[2\]\.intensity: expected 3 non-negative finite numbers, got \[1, 1, inf\]"),
        ("lights.0.constant", [-1, 1, 1], r"lights\[0\]\.constant: expected 3 non-negative finite numbers"),
        ("lights.0.scale", float("nan"), r"lights\[0\]\.scale: expected a finite number >= 0"),
        ("lights.1.v", [1.0, 0, 0], r"lights\[1\]: u \[0\.5, 0\.0, 0\.0\] and v \[1\.0, 0\.0, 0\.0\] are parallel"),
        ("lights.1.u", [0, 0, 0], r"lights\[1\]\.u: expected a non-zero vector"),
        ("lights.1.type", "spot", r"lights\[1\]\.type: unknown light type 'spot'"),
        ("lights.1.type", "aera", r"unknown light type 'aera'; did you mean 'area'\?"),
        ("lights.1.center", _DELETE, r"lights\[1\]: missing required key 'center'"),
        ("lights.0.file", "sky.exr", r"lights\[0\]: an environment light needs exactly one of file, sky, constant"),
        ("lights.0", {"type": "environment", "sky": {"sun_elevation_deg": -10}}, r"lights\[0\]\.sky\.sun_elevation_deg: expected a finite number in \[0\.0, 90\.0\]"),
        # transforms
        ("objects.1.transform.translate", [0, float("inf"), 0], r"objects\[1\]\.transform\.translate: expected 3 finite numbers, got \[0, inf, 0\]"),
        ("objects.1.transform.rotate_deg", [0, float("nan"), 0], r"objects\[1\]\.transform\.rotate_deg: expected 3 finite numbers"),
        ("objects.1.transform.scale", 0, r"objects\[1\]\.transform\.scale: expected a finite number > 0, got 0"),
        ("objects.1.transform.scale", -2.0, r"objects\[1\]\.transform\.scale: expected a finite number > 0, got -2\.0"),
        ("objects.1.transform.scale", [1, 1, 1], r"objects\[1\]\.transform\.scale: expected a finite number > 0"),
        # objects
        ("objects.1.name", "floor", r"objects\[1\]\.name: duplicate object name 'floor' \(also objects\[0\]\)"),
        ("objects.1.name", _DELETE, r"objects\[1\]: missing required key 'name'"),
        ("objects.1.dynamic", "yes", r"objects\[1\]\.dynamic: expected true or false"),
        ("objects.0.mesh", {"builtin": "plnae"}, r"objects\[0\]\.mesh\.builtin: unknown builtin mesh 'plnae'; did you mean 'plane'\?"),
        ("objects.0.mesh", {"builtin": "plane", "size": [-1, 1]}, r"objects\[0\]\.mesh: builtin 'plane': size must be > 0"),
        ("objects.0.mesh", 3, r"objects\[0\]\.mesh: expected a file path or \{builtin: name, \.\.\.\}"),
        ("objects", [], r"objects: expected a non-empty list"),
        # camera
        ("camera.look_at", [0, 2, 6], r"camera\.look_at: look_at equals position \[0, 2, 6\]"),
        ("camera.up", [0, -3, -12], r"camera\.up: up .* is parallel to the view direction"),
        ("camera.fov_deg", 0, r"camera\.fov_deg: expected a finite number > 0"),
        ("camera.fov_deg", 180, r"camera\.fov_deg: expected a finite number > 0 <= 179"),
        ("camera.resolution", [64], r"camera\.resolution: expected \[width, height\]"),
        ("camera.resolution", [64, 0], r"camera\.resolution\[1\]: expected an integer >= 1"),
    ],
)
def test_validation_messages(path, value, match):
    with pytest.raises(SceneError, match=match) as info:
        Scene.from_dict(with_change(path, value))
    assert str(info.value).startswith("<dict>: ")


def test_errors_name_the_file(tmp_path):
    d = with_change("objects.0.material.albedo", [0.5, float("nan"), 1])
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(SceneError, match=r"scene\.yaml: objects\[0\]\.material\.albedo: expected 3 non-negative finite numbers, got \[0\.5, nan, 1\]"):
        load_scene(path)


def test_missing_files(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(with_change("objects.0.mesh", "meshes/nope.ply")))
    with pytest.raises(SceneError, match=r"scene\.yaml: objects\[0\]\.mesh: file not found: 'meshes/nope\.ply' \(relative to "):
        load_scene(path)
    d = base_dict()
    d["lights"][0] = {"type": "environment", "file": "sky.exr"}
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(SceneError, match=r"lights\[0\]\.file: file not found: 'sky\.exr'"):
        load_scene(path)
    with pytest.raises(FileNotFoundError, match="scene file not found"):
        load_scene(tmp_path / "missing.yaml")


def test_unreadable_environment_file(tmp_path):
    (tmp_path / "sky.exr").write_bytes(b"garbage")
    d = base_dict()
    d["lights"][0] = {"type": "environment", "file": "sky.exr"}
    with pytest.raises(SceneError, match=r"lights\[0\]\.file: cannot read EXR file"):
        Scene.from_dict(d, base_dir=tmp_path)


def test_mesh_without_faces(tmp_path):
    (tmp_path / "points.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n0 0 0\n1 0 0\n0 1 0\n"
    )
    with pytest.raises(SceneError, match=r"objects\[0\]\.mesh: .*no faces"):
        Scene.from_dict(with_change("objects.0.mesh", "points.ply"), base_dir=tmp_path)


def test_degenerate_faces(tmp_path):
    plane = trimesh.creation.box()
    faces = np.asarray(plane.faces)
    n_bad = int(np.ceil(DEGENERATE_FACE_FRACTION * 200)) + 1
    bad = np.repeat(faces[:1, [0, 0, 1]], n_bad, axis=0)  # repeated vertex: zero area
    good = np.repeat(faces, 200 // len(faces), axis=0)
    mesh = trimesh.Trimesh(plane.vertices, np.concatenate([good, bad]), process=False)
    mesh.export(tmp_path / "bad.ply")
    with pytest.raises(SceneError, match=rf"objects\[0\]\.mesh: {n_bad} of {len(mesh.faces)} faces .* have zero area, above the 1% limit"):
        Scene.from_dict(with_change("objects.0.mesh", "bad.ply"), base_dir=tmp_path)
    ok = trimesh.Trimesh(plane.vertices, np.concatenate([good, bad[:1]]), process=False)  # 1 of 205: below the limit
    ok.export(tmp_path / "ok.ply")
    Scene.from_dict(with_change("objects.0.mesh", "ok.ply"), base_dir=tmp_path)


def test_non_finite_mesh_vertices(tmp_path):
    box = trimesh.creation.box()
    vertices = np.array(box.vertices)
    vertices[0, 0] = np.nan
    trimesh.Trimesh(vertices, box.faces, process=False).export(tmp_path / "nan.ply")
    with pytest.raises(SceneError, match=r"objects\[0\]\.mesh: mesh has NaN or inf vertex coordinates"):
        Scene.from_dict(with_change("objects.0.mesh", "nan.ply"), base_dir=tmp_path)


def test_structure_errors():
    with pytest.raises(SceneError, match="<dict>: the scene is empty"):
        Scene.from_dict(None)
    with pytest.raises(SceneError, match="<dict>: missing required key 'objects'"):
        Scene.from_dict({"lights": []})
    with pytest.raises(SceneError, match=r"<dict>: objects: expected a list, got a mapping"):
        Scene.from_dict({"objects": {"name": "a"}})
    with pytest.raises(SceneError, match=r"objects\[0\]: expected a mapping with keys name, mesh"):
        Scene.from_dict({"objects": ["floor"]})
    d = base_dict()
    d["lights"].append({"type": "environment", "constant": [1, 1, 1]})
    with pytest.raises(SceneError, match=r"lights\[3\]: a scene has at most one environment light \(lights\[0\] is one already\)"):
        Scene.from_dict(d)


def test_yaml_errors(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("objects: [\n")
    with pytest.raises(SceneError, match=r"scene\.yaml: invalid YAML"):
        load_scene(path)
    path.write_text("objects: []\nobjects: []\n")
    with pytest.raises(SceneError, match=r"scene\.yaml: invalid YAML: .*duplicate key 'objects'"):
        load_scene(path)
    path.write_text("!!python/object/apply:os.system ['echo hi']\n")
    with pytest.raises(SceneError, match="invalid YAML"):  # safe loading: no code runs
        load_scene(path)


def test_validation_happens_before_any_mesh_is_built(monkeypatch):
    import prtlab.geometry as geometry

    def fail(*args, **kwargs):
        raise AssertionError("a mesh was built before validation finished")

    monkeypatch.setattr(geometry, "builtin_mesh", fail)
    with pytest.raises(SceneError, match=r"camera\.fov_deg"):
        Scene.from_dict(with_change("camera.fov_deg", -1))


def test_more_structure_messages():
    with pytest.raises(SceneError, match=r"objects\[0\]: keys must be strings, got 1"):
        Scene.from_dict({"objects": [{1: "a", "name": "a", "mesh": {"builtin": "plane"}}]})
    with pytest.raises(SceneError, match=r"objects\[0\]\.name: expected a non-empty string, got nothing \(null\)"):
        Scene.from_dict(with_change("objects.0.name", None))
    with pytest.raises(SceneError, match=r"objects\[0\]\.name: expected a non-empty string, got int 3"):
        Scene.from_dict(with_change("objects.0.name", 3))


def test_mesh_checks_on_what_the_builders_return(monkeypatch):
    import prtlab.geometry as geometry

    monkeypatch.setattr(geometry, "builtin_mesh", lambda name, **p: trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False))
    with pytest.raises(SceneError, match=r"objects\[0\]\.mesh: mesh has no faces"):
        Scene.from_dict(base_dict())
    box = trimesh.creation.box()
    monkeypatch.setattr(
        geometry, "builtin_mesh", lambda name, **p: trimesh.Trimesh(box.vertices, np.asarray(box.faces) + 5, process=False)
    )
    with pytest.raises(SceneError, match=r"objects\[0\]\.mesh: mesh faces index vertices outside 0\.\.7"):
        Scene.from_dict(base_dict())


def test_environment_file_with_negative_radiance(tmp_path):
    write_exr(tmp_path / "neg.exr", -np.ones((4, 8, 3)))
    d = base_dict()
    d["lights"][0] = {"type": "environment", "file": "neg.exr"}
    with pytest.raises(SceneError, match=r"lights\[0\]\.file: environment map .neg\.exr. has 32 pixels with negative radiance \(the first at row 0, column 0"):
        Scene.from_dict(d, base_dir=tmp_path)


# ----------------------------------------------------------------------------- saving elsewhere, names, messages


def test_save_into_another_folder_rewrites_relative_paths(tmp_path, monkeypatch):
    folder = tmp_path / "project" / "scenes"
    (tmp_path / "project" / "meshes").mkdir(parents=True)
    folder.mkdir()
    trimesh.creation.box().export(tmp_path / "project" / "meshes" / "box.ply")
    write_exr(folder / "env.exr", np.full((8, 16, 3), 0.25))
    absolute = tmp_path / "abs.ply"
    trimesh.creation.box().export(absolute)
    d = base_dict()
    d["objects"][0]["mesh"] = "../meshes/box.ply"
    d["objects"][1]["mesh"] = str(absolute)
    d["lights"][0] = {"type": "environment", "file": "env.exr", "scale": 4.0}
    (folder / "scene.yaml").write_text(yaml.safe_dump(d))
    scene = load_scene(folder / "scene.yaml")
    monkeypatch.chdir(tmp_path / "project")  # the working directory plays no part
    for target in (tmp_path / "elsewhere" / "deeper" / "copy.yaml", tmp_path / "copy.yaml", folder / "same.yaml"):
        out = save_scene(scene, target)
        saved = yaml.safe_load(out.read_text())
        assert (target.parent / saved["objects"][0]["mesh"]).resolve() == (tmp_path / "project" / "meshes" / "box.ply").resolve()
        assert saved["objects"][1]["mesh"] == str(absolute)  # absolute paths are kept
        assert (target.parent / saved["lights"][0]["file"]).resolve() == (folder / "env.exr").resolve()
        again = load_scene(out)
        for a, b in zip(again.objects, scene.objects):
            np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
            np.testing.assert_array_equal(a.mesh.faces, b.mesh.faces)
        assert [o.transform for o in again.objects] == [o.transform for o in scene.objects]
        np.testing.assert_array_equal(again.environment.image, scene.environment.image)
    assert yaml.safe_load((folder / "same.yaml").read_text())["objects"][0]["mesh"] == "../meshes/box.ply"
    assert scene.objects[0].mesh_spec == "../meshes/box.ply"  # the scene itself is unchanged


def test_save_scene_refuses_a_folder(tmp_path):
    with pytest.raises(IsADirectoryError, match=r"save_scene: .* is a folder; give the scene file's path"):
        save_scene(Scene.from_dict(base_dict()), tmp_path)


def test_load_a_shipped_scene_by_name(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)  # anywhere: the name is not a path
    scene = prtlab.load_scene("cornell_box")
    assert scene.name == "cornell_box" and scene == load_scene(SCENES_DIR / "cornell_box.yaml")


def test_a_file_named_like_a_scene_wins(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "cornell_box").write_text(yaml.safe_dump(base_dict()))
    assert load_scene("cornell_box").name == "small"


def test_show_is_cut_and_fast():
    from prtlab.scene._validate import SHOW_LIMIT, show

    leaf = ["lol"] * 9
    for _ in range(9):  # 9^10 leaves, shared: rendering must stop at the limit
        leaf = [leaf] * 9
    text = show(leaf)
    assert len(text) == SHOW_LIMIT and text.endswith("...") and text.startswith("[[[[")
    assert show([0.5, float("nan"), 1]) == "[0.5, nan, 1]"
    assert show("x" * 1000).endswith("...") and len(show("x" * 1000)) == SHOW_LIMIT
    assert show({"a": [1, 2]}) == "{a: [1, 2]}"
