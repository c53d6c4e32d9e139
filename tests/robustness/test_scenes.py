"""Malformed scene files and dicts: each refused with one line naming the file and the key, before any work."""

from __future__ import annotations

import time

import pytest
import yaml

import prtlab.scene._load as load_module
from prtlab.scene import Scene, SceneError, load_scene
from tests.scenes import DELETE as _DELETE
from tests.scenes import with_change



def base_dict() -> dict:
    """A small valid scene: a floor, a ball, a constant environment, an area light, a camera, an animation."""
    return {
        "name": "small",
        "objects": [
            {"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [2, 2]}},
            {
                "name": "ball",
                "mesh": {"builtin": "icosphere", "subdivisions": 1, "radius": 0.5},
                "transform": {"translate": [0, 0.5, 0], "scale": 1.0},
                "material": {"type": "phong", "kd": [0.3, 0.3, 0.3], "ks": [0.5, 0.4, 0.3], "exponent": 20},
                "dynamic": True,
            },
        ],
        "lights": [
            {"type": "environment", "constant": [0.5, 0.6, 0.7], "scale": 2.0},
            {"type": "area", "center": [0, 3, 0], "u": [0.5, 0, 0], "v": [0, 0, 0.5], "radiance": [10, 10, 10]},
        ],
        "camera": {"position": [0, 2, 6], "look_at": [0, 0.5, 0], "up": [0, 1, 0], "fov_deg": 40, "resolution": [64, 48]},
        "animation": {
            "tracks": [
                {"object": "ball", "keys": [{"time": 0, "translate": [0, 0.5, 0]}, {"time": 1, "translate": [1, 0.5, 0]}]},
                {"light": 0, "keys": [{"time": 0, "scale": 1.0}, {"time": 1, "scale": 2.0}]},
            ]
        },
    }


def changed(path: str, value) -> dict:
    """``base_dict()`` with the item at a dotted path (``objects.0.mesh``) replaced (or deleted)."""
    return with_change(base_dict(), path, value)


def write(tmp_path, d) -> str:
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False))
    return path


def test_the_base_scene_loads(tmp_path):
    scene = load_scene(write(tmp_path, base_dict()))
    assert [o.name for o in scene.objects] == ["floor", "ball"]


# ----------------------------------------------------------------------------- the file itself

_BOMB = "\n".join(
    ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    + [f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 9) + "]" for k in range(1, 9)]
    + ["objects: *a8", ""]
)

_FILE_CASES = [
    ("empty", b"", r"scene\.yaml: the scene is empty"),
    ("only-comments", b"# nothing here\n", r"scene\.yaml: the scene is empty"),
    ("top-level-list", b"- a\n- b\n", r"scene\.yaml: a scene is a mapping .* at the top level, got a list \['a', 'b'\]"),
    ("top-level-scalar", b"hello\n", r"scene\.yaml: a scene is a mapping .* at the top level, got str 'hello'"),
    ("top-level-number", b"3.5\n", r"scene\.yaml: a scene is a mapping .* at the top level, got float 3\.5"),
    ("unclosed-bracket", b"objects: [\n", r"scene\.yaml: invalid YAML: .*\(line \d+, column \d+\)"),
    ("bad-indentation", b"objects:\n  - name: a\n   mesh: x\n", r"scene\.yaml: invalid YAML: .*line 3"),
    ("tab-indentation", b"objects:\n\t- name: a\n", r"scene\.yaml: invalid YAML: .*found character .* that cannot start any token \(line 2"),
    ("duplicate-key", b"objects: []\nobjects: []\n", r"scene\.yaml: invalid YAML: duplicate key 'objects' \(line 2"),
    ("python-tag", b"!!python/object/apply:os.system ['echo hi']\n", r"scene\.yaml: invalid YAML: .*python/object"),
    ("unknown-alias", b"objects: *nowhere\n", r"scene\.yaml: invalid YAML: found undefined alias"),
    ("two-documents", b"objects: []\n---\nobjects: []\n", r"scene\.yaml: invalid YAML: expected a single document"),
    ("alias-bomb", _BOMB.encode(), r"scene\.yaml: the YAML expands to more than 1,000,000 values .*alias bomb"),
    ("recursive-alias", b"objects:\n  - {name: a, mesh: {builtin: plane, size: &s [1, *s]}}\n", r"scene\.yaml: the alias \*s refers to a value containing itself \(line 2\)"),
    ("deep-nesting", b"objects: " + b"[" * 5000 + b"]" * 5000, r"scene\.yaml: lists and mappings are nested more than 64 levels deep"),
    ("deep-mappings", b"".join(b"  " * k + b"k:\n" for k in range(200)), r"scene\.yaml: lists and mappings are nested more than 64 levels"),
    ("nul-bytes", bytes(range(256)), r"scene\.yaml: not a UTF-8 text file \(it holds NUL bytes\)"),
    ("latin-1", "name: café\nobjects: []\n".encode("latin-1"), r"scene\.yaml: not a UTF-8 text file \(byte 0xe9 at offset 9"),
    ("utf-16", "objects: []\n".encode("utf-16"), r"scene\.yaml: not a UTF-8 text file \(it is UTF-16, by its byte-order mark\)"),
    ("png-renamed", b"\x89PNG\r\n\x1a\n" + b"\x01" * 64, r"scene\.yaml: not a UTF-8 text file \(byte 0x89 at offset 0"),
]


@pytest.mark.parametrize("text, match", [c[1:] for c in _FILE_CASES], ids=[c[0] for c in _FILE_CASES])
def test_malformed_files(tmp_path, text, match):
    path = tmp_path / "scene.yaml"
    path.write_bytes(text)
    start = time.perf_counter()
    with pytest.raises(SceneError, match=match) as info:
        load_scene(path)
    assert time.perf_counter() - start < 5.0  # refused at once, never after expanding anything
    assert "\n" not in str(info.value) and len(str(info.value)) < 400 + len(str(path))


def test_utf8_with_bom_and_non_ascii_names_load(tmp_path):
    d = changed("objects.0.name", "Fußboden")
    path = tmp_path / "scene.yaml"
    path.write_bytes(b"\xef\xbb\xbf" + yaml.safe_dump(d, allow_unicode=True).encode("utf-8"))
    assert load_scene(path).objects[0].name == "Fußboden"


def test_oversized_file_is_refused_before_reading(tmp_path, monkeypatch):
    monkeypatch.setattr(load_module, "MAX_SCENE_BYTES", 1000)
    path = tmp_path / "scene.yaml"
    path.write_text("# padding\n" * 200)
    with pytest.raises(SceneError, match=r"scene\.yaml: the file is 2,000 bytes, above the 1,000-byte limit"):
        load_scene(path)


def test_shallow_aliases_still_load(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text(
        "objects:\n"
        "  - {name: a, mesh: {builtin: plane}, material: {albedo: &grey [0.5, 0.5, 0.5]}}\n"
        "  - {name: b, mesh: {builtin: plane}, material: {albedo: *grey}}\n"
    )
    scene = load_scene(path)
    assert scene.objects[1].material.albedo.tolist() == [0.5, 0.5, 0.5]


def test_folder_and_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"scene file is a folder, not a scene file"):
        load_scene(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"scene file not found: '.*nope\.yaml'"):
        load_scene(tmp_path / "nope.yaml")


def test_huge_values_are_cut_in_messages(tmp_path):
    d = changed("objects.0.material", {"albedo": [0.5] * 5000})
    with pytest.raises(SceneError, match=r"objects\[0\]\.material\.albedo: expected 3 non-negative finite numbers, got \[0\.5, 0\.5, .*\.\.\.$") as info:
        load_scene(write(tmp_path, d))
    assert len(str(info.value)) < 200 + len(str(tmp_path))
    d = changed("objects.0.name", "x" * 5000)
    d["objects"][1]["name"] = "x" * 5000
    with pytest.raises(SceneError, match=r"objects\[1\]\.name: duplicate object name 'xxx.*\.\.\." ) as info:
        load_scene(write(tmp_path, d))
    assert len(str(info.value)) < 400 + len(str(tmp_path))
    d = changed("objects.0.m" + "e" * 500, 1)
    with pytest.raises(SceneError, match=r"objects\[0\]\.meee*\.\.\.: unknown key") as info:
        load_scene(write(tmp_path, d))
    assert len(str(info.value)) < 300 + len(str(tmp_path))


# ----------------------------------------------------------------------------- keys and values

_KEY_CASES = [
    # structure
    ("no-objects", "objects", _DELETE, r"scene\.yaml: missing required key 'objects'"),
    ("objects-mapping", "objects", {"name": "a"}, r"scene\.yaml: objects: expected a list, got a mapping"),
    ("objects-empty", "objects", [], r"objects: expected a non-empty list, got \[\]"),
    ("object-no-mesh", "objects.0.mesh", _DELETE, r"objects\[0\]: missing required key 'mesh'"),
    ("object-string", "objects.0", "floor", r"objects\[0\]: expected a mapping with keys name, mesh"),
    ("unknown-top-key", "camra", {}, r"scene\.yaml: camra: unknown key; did you mean 'camera'\?"),
    ("unknown-object-key", "objects.1.dynamc", True, r"objects\[1\]\.dynamc: unknown key; did you mean 'dynamic'\?"),
    ("unknown-builtin-param", "objects.0.mesh.sise", [1, 1], r"objects\[0\]\.mesh\.sise: unknown key; did you mean 'size'"),
    ("lights-mapping", "lights", {"type": "area"}, r"lights: expected a list, got a mapping"),
    ("light-no-type", "lights.1.type", _DELETE, r"lights\[1\]: missing required key 'type'"),
    ("name-number", "name", 5, r"scene\.yaml: name: expected a non-empty string, got int 5"),
    ("object-name-empty", "objects.0.name", "", r"objects\[0\]\.name: expected a non-empty string"),
    ("duplicate-object-name", "objects.1.name", "floor", r"objects\[1\]\.name: duplicate object name 'floor' \(also objects\[0\]\)"),
    ("two-environments", "lights.1", {"type": "environment", "constant": [1, 1, 1]}, r"lights\[1\]: a scene has at most one environment light"),
    # floats are not ints; booleans are not numbers
    ("float-resolution", "camera.resolution", [64.0, 48], r"camera\.resolution\[0\]: expected an integer >= 1, got 64\.0"),
    ("bool-resolution", "camera.resolution", [True, 48], r"camera\.resolution\[0\]: expected an integer >= 1, got True"),
    ("float-plane-resolution", "objects.0.mesh.resolution", [2.5, 2], r"objects\[0\]\.mesh: builtin 'plane': resolution must be an integer >= 1, got 2\.5"),
    ("integral-float-plane-resolution", "objects.0.mesh.resolution", [4.0, 4], r"objects\[0\]\.mesh: builtin 'plane': resolution must be an integer >= 1, got 4\.0"),
    ("bool-subdivisions", "objects.1.mesh.subdivisions", True, r"objects\[1\]\.mesh: builtin 'icosphere': subdivisions must be an integer >= 0, got True"),
    ("bool-plane-size", "objects.0.mesh.size", [True, 1], r"objects\[0\]\.mesh: builtin 'plane': size must be a list of 2 numbers, got \[True, 1\]"),
    ("bool-radius", "objects.1.mesh.radius", False, r"objects\[1\]\.mesh: builtin 'icosphere': radius must be a number, got False"),
    ("bool-scale", "objects.1.transform.scale", True, r"objects\[1\]\.transform\.scale: expected a finite number > 0, got True"),
    ("bool-albedo", "objects.0.material", {"albedo": [True, 0.5, 0.5]}, r"objects\[0\]\.material\.albedo: expected 3 non-negative finite numbers, got \[True, 0\.5, 0\.5\]"),
    ("int-dynamic", "objects.1.dynamic", 1, r"objects\[1\]\.dynamic: expected true or false, got int 1"),
    ("string-portal", "objects.1.portal", "yes", r"objects\[1\]\.portal: expected true or false, got str 'yes'"),
    ("string-fov", "camera.fov_deg", "wide", r"camera\.fov_deg: expected a finite number > 0 <= 179\.0, got 'wide'"),
    ("float-light-index", "animation.tracks.1.light", 0.0, r"animation\.tracks\[1\]\.light: expected an integer >= 0, got 0\.0"),
    ("float-sky-height", "lights.0", {"type": "environment", "sky": {"sun_elevation_deg": 30, "height": 16.0}}, r"lights\[0\]\.sky\.height: expected an integer >= 2, got 16\.0"),
    # NaN, inf, negative, out of range
    ("nan-fov", "camera.fov_deg", float("nan"), r"camera\.fov_deg: expected a finite number > 0 <= 179\.0, got nan"),
    ("inf-translate", "objects.1.transform.translate", [0, float("inf"), 0], r"objects\[1\]\.transform\.translate: expected 3 finite numbers, got \[0, inf, 0\]"),
    ("negative-scale", "objects.1.transform.scale", -1.0, r"objects\[1\]\.transform\.scale: expected a finite number > 0, got -1\.0"),
    ("nan-radiance", "lights.1.radiance", [1, float("nan"), 1], r"lights\[1\]\.radiance: expected 3 non-negative finite numbers, got \[1, nan, 1\]"),
    ("negative-radiance", "lights.1.radiance", [1, -1, 1], r"lights\[1\]\.radiance: expected 3 non-negative finite numbers"),
    ("nan-u", "lights.1.u", [float("nan"), 0, 0], r"lights\[1\]\.u: expected 3 finite numbers, got \[nan, 0, 0\]"),
    ("negative-env-scale", "lights.0.scale", -1.0, r"lights\[0\]\.scale: expected a finite number >= 0\.0, got -1\.0"),
    ("inf-env-scale", "lights.0.scale", float("inf"), r"lights\[0\]\.scale: expected a finite number >= 0\.0, got inf"),
    ("negative-exponent", "objects.1.material.exponent", -1, r"objects\[1\]\.material\.exponent: expected a finite number >= 0"),
    ("energy-gain", "objects.1.material.ks", [0.8, 0.4, 0.3], r"objects\[1\]\.material: kd \+ ks must be <= 1 in every channel"),
    ("sun-below-horizon", "lights.0", {"type": "environment", "sky": {"sun_elevation_deg": 95}}, r"lights\[0\]\.sky\.sun_elevation_deg: expected a finite number in \[0\.0, 90\.0\], got 95"),
    ("string-turbidity", "lights.0", {"type": "environment", "sky": {"sun_elevation_deg": 30, "turbidity": "high"}}, r"lights\[0\]\.sky\.turbidity: expected a finite number in \[1\.7, 10\.0\], got 'high'"),
    # numbers too large: overflow and the limits of builtins
    ("huge-translate", "objects.1.transform.translate", [1e300, 0, 0], r"objects\[1\]\.transform: places the mesh at world coordinates up to 1e\+300, beyond the \+-1e\+18 limit"),
    ("huge-scale", "objects.1.transform.scale", 1e300, r"objects\[1\]\.transform: places the mesh at world coordinates up to 5e\+299"),
    ("overflowing-translate", "objects.1.transform", {"translate": [1.7e308, 0, 0], "scale": 1e308}, r"objects\[1\]\.transform: places the mesh at world coordinates up to inf"),
    ("overflowing-scale", "objects.1.transform.scale", 1.7e308, r"objects\[1\]\.transform: places the mesh at world coordinates up to 8\.5e\+307"),
    ("huge-env-scale", "lights.0.scale", 1.0e308, r"lights\[0\]\.scale: scale 1e\+308 times the map .* overflows float64"),
    ("huge-env-constant", "lights.0.constant", [1e308, 1, 1], r"lights\[0\]\.constant: values up to 1e\+308 make the map's total radiance overflow float64"),
    ("huge-plane-resolution", "objects.0.mesh.resolution", [100000, 100000], r"objects\[0\]\.mesh: builtin 'plane': resolution \[100000, 100000\] makes about 10,000,200,001 vertices, above the 4,100,000 limit"),
    ("huge-box-subdivisions", "objects.1.mesh", {"builtin": "box", "subdivisions": 40}, r"objects\[1\]\.mesh: builtin 'box': subdivisions 40 makes about .* vertices, above the"),
    ("huge-uv-sphere", "objects.1.mesh", {"builtin": "uv_sphere", "count": [5000, 5000]}, r"objects\[1\]\.mesh: builtin 'uv_sphere': count \[5000, 5000\] makes about 25,000,000 vertices"),
    ("huge-torus", "objects.1.mesh", {"builtin": "torus", "sections": [4000, 4000]}, r"objects\[1\]\.mesh: builtin 'torus': sections \[4000, 4000\] makes about 16,000,000 vertices"),
    ("huge-cylinder", "objects.1.mesh", {"builtin": "cylinder", "sections": 10**7}, r"objects\[1\]\.mesh: builtin 'cylinder': sections 10000000 makes about 40,000,002 vertices"),
    ("tiny-room-cells", "objects.0.mesh", {"builtin": "room", "cell_size": 1e-6}, r"objects\[0\]\.mesh: builtin 'room': cell_size 1e-06 makes about .* vertices"),
    # animation
    ("track-unknown-object", "animation.tracks.0.object", "balll", r"animation\.tracks\[0\]\.object: no object named 'balll'"),
    ("track-light-out-of-range", "animation.tracks.1.light", 5, r"animation\.tracks\[1\]\.light: light index 5 out of range: the scene has 2 lights"),
    ("key-times-decrease", "animation.tracks.0.keys.1.time", 0, r"animation\.tracks\[0\]\.keys\[1\]\.time: key times must increase strictly"),
    ("key-unknown-field", "animation.tracks.0.keys.1.radiance", [1, 1, 1], r"animation\.tracks\[0\]\.keys\[1\]\.radiance: unknown key"),
    ("key-huge-translate", "animation.tracks.0.keys.1.translate", [0, 1e300, 0], r"animation\.tracks\[0\]\.keys\[1\]: places object 'ball' beyond world coordinates"),
    ("key-huge-env-scale", "animation.tracks.1.keys.1.scale", 1e308, r"animation\.tracks\[1\]\.keys\[1\]\.scale: scale 1e\+308 times the map .* overflows"),
    ("key-huge-env-constant", "animation.tracks.1.keys", [{"time": 0, "constant": [1, 1, 1]}, {"time": 1, "constant": [1e308, 1, 1]}], r"animation\.tracks\[1\]\.keys\[1\]\.constant: values up to 1e\+308 make the map's total radiance overflow"),
    ("key-nan-time", "animation.tracks.0.keys.0.time", float("nan"), r"animation\.tracks\[0\]\.keys\[0\]\.time: expected a finite number >= 0\.0, got nan"),
]


@pytest.mark.parametrize("path, value, match", [c[1:] for c in _KEY_CASES], ids=[c[0] for c in _KEY_CASES])
def test_bad_keys_name_file_and_key(tmp_path, path, value, match):
    with pytest.raises(SceneError, match=match) as info:
        load_scene(write(tmp_path, changed(path, value)))
    message = str(info.value)
    assert message.startswith(str(tmp_path / "scene.yaml") + ": ")
    assert "\n" not in message


def test_the_same_checks_apply_to_dicts():
    with pytest.raises(SceneError, match=r"^<dict>: objects\[1\]\.transform: places the mesh at world coordinates"):
        Scene.from_dict(changed("objects.1.transform.translate", [1e300, 0, 0]))
