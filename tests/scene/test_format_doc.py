"""docs/SCENE_FORMAT.md documents every key the loader accepts, and every YAML example in it loads."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

import prtlab.data
import prtlab.scene._animation as animation_module
import prtlab.scene._load as load_module
from prtlab.geometry import BUILTIN_MESHES
from prtlab.scene import load_scene, write_exr

DOC = Path(__file__).resolve().parents[2] / "docs" / "SCENE_FORMAT.md"
SCENES_DIR = prtlab.data.path("scenes")


def doc_text() -> str:
    return DOC.read_text(encoding="utf-8")


def yaml_examples() -> list[str]:
    return re.findall(r"```yaml\n(.*?)```", doc_text(), flags=re.S)


def accepted_keys() -> set[str]:
    """Every key (and key value such as a type name) of the loader's tables."""
    keys = set(load_module._TOP_KEYS) | set(load_module._OBJECT_KEYS) | set(load_module._TRANSFORM_KEYS)
    keys |= set(load_module._MATERIAL_KEYS)  # the material types
    keys |= {k for ks in load_module._MATERIAL_KEYS.values() for k in ks}
    keys |= set(load_module._LIGHT_KEYS)  # the light types
    keys |= {k for ks in load_module._LIGHT_KEYS.values() for k in ks}
    keys |= set(load_module._ENV_SOURCES) | set(load_module._SKY_KEYS) | set(load_module._CAMERA_KEYS)
    keys |= {"duration", "tracks", "object", "light", "keys", "time"}  # check_animation's mappings
    keys |= set(animation_module._OBJECT_FIELDS) | {f for fs in animation_module._LIGHT_FIELDS.values() for f in fs}
    keys |= {"builtin"} | set(BUILTIN_MESHES) | {p for name in BUILTIN_MESHES for p in BUILTIN_MESHES[name]}
    return keys


def test_the_animation_key_list_matches_the_validator():
    """The animation keys listed above are the ones check_animation accepts (it would refuse others)."""
    source = Path(animation_module.__file__).read_text()
    assert '("duration", "tracks")' in source and '("object", "light", "keys")' in source and '("time", *allowed)' in source


@pytest.mark.parametrize("key", sorted(accepted_keys()))
def test_every_key_is_documented(key):
    assert f"`{key}`" in doc_text(), f"docs/SCENE_FORMAT.md does not mention `{key}`"


def test_every_shipped_scene_is_listed():
    listed = set(re.findall(r"^\| `(\w+)` \|", doc_text().split("## Shipped scenes")[1].split("##")[0], flags=re.M))
    assert listed == {p.stem for p in SCENES_DIR.glob("*.yaml")}


def _provide_files(d: dict, folder: Path) -> None:
    """Create the mesh and map files an example names (small stand-ins), relative to ``folder``."""
    for obj in d.get("objects", []):
        if isinstance(obj.get("mesh"), str):
            target = folder / obj["mesh"]
            target.parent.mkdir(parents=True, exist_ok=True)
            trimesh.creation.box().export(target)
    for light in d.get("lights", []) or []:
        if isinstance(light.get("file"), str):
            target = folder / light["file"]
            target.parent.mkdir(parents=True, exist_ok=True)
            write_exr(target, np.full((8, 16, 3), 0.5))


def test_there_are_examples():
    assert len(yaml_examples()) >= 5


@pytest.mark.parametrize("k", range(len(yaml_examples())))
def test_every_example_loads(tmp_path, k):
    text = yaml_examples()[k]
    _provide_files(yaml.safe_load(text), tmp_path)
    (tmp_path / "example.yaml").write_text(text)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an example must not warn either
        scene = load_scene(tmp_path / "example.yaml")
    assert scene.objects
    if scene.animation:
        scene.at_frame(1, 3)
