"""Malformed mesh files and ill-placed meshes: refused at load naming the file and the key; inward normals warned about."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import trimesh
import yaml

from prtlab.geometry import builtin_mesh
from prtlab.scene import InwardNormalsWarning, SceneError, closed_signed_volume, load_scene

_PLY_HEADER = (
    "ply\nformat ascii 1.0\nelement vertex {nv}\nproperty float x\nproperty float y\nproperty float z\n"
    "element face {nf}\nproperty list uchar int vertex_indices\nend_header\n"
)


def ascii_ply(vertices, faces, nv=None, nf=None) -> str:
    head = _PLY_HEADER.format(nv=len(vertices) if nv is None else nv, nf=len(faces) if nf is None else nf)
    body = "".join(" ".join(repr(float(c)) for c in v) + "\n" for v in vertices)
    body += "".join(f"{len(f)} " + " ".join(str(int(i)) for i in f) + "\n" for f in faces)
    return head + body


_TRIANGLE = [[0, 0, 0], [1, 0, 0], [0, 0, -1]]


def scene_with_mesh(tmp_path, mesh, camera=None, transform=None) -> str:
    obj = {"name": "thing", "mesh": mesh}
    if transform is not None:
        obj["transform"] = transform
    d = {"objects": [obj]}
    if camera is not None:
        d["camera"] = camera
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def binary_box_ply() -> bytes:
    return trimesh.creation.box().export(file_type="ply", encoding="binary")


_FILE_CASES = [
    # (id, file name, content (str or bytes), match after "scene.yaml: objects[0].mesh: ")
    ("empty-ply", "m.ply", b"", r"cannot read mesh file .*m\.ply"),
    ("empty-obj", "m.obj", "", r"mesh file .*m\.obj' holds no triangle mesh \(no faces\)"),
    ("points-only-ply", "m.ply", _PLY_HEADER.replace("element face {nf}\nproperty list uchar int vertex_indices\n", "").format(nv=3) + "0 0 0\n1 0 0\n0 1 0\n", r"holds no triangle mesh"),
    ("garbage-stl", "m.stl", b"\x00\x01garbage" * 7, r"m\.stl' holds no triangle mesh \(no faces\)"),
    ("unknown-suffix", "m.xyz", "1 2 3\n", r"cannot read mesh file .*m\.xyz"),
    ("truncated-binary-ply", "m.ply", binary_box_ply()[:-20], r"cannot read mesh file .*m\.ply.*unexpected length"),
    ("truncated-ascii-ply", "m.ply", ascii_ply(_TRIANGLE * 2, [[0, 1, 2], [3, 4, 5]], nf=2)[:-8], r"m\.ply' is truncated or corrupt: its header declares 6 vertices and 2 faces, but 6 vertices and 1 faces were read"),
    ("truncated-obj-face", "m.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2", r"cannot read mesh file .*m\.obj', line 4: a face needs at least 3 vertices"),
    ("nan-vertex-obj", "m.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", r"mesh has NaN or inf vertex coordinates: vertex 1 of .*m\.obj' is \[nan, 0\.0, 0\.0\]"),
    ("inf-vertex-ply", "m.ply", ascii_ply([[0, 0, 0], [1, 0, 0], [0, float("inf"), 0]], [[0, 1, 2]]), r"mesh has NaN or inf vertex coordinates: vertex 2"),
    ("out-of-range-obj", "m.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", r"m\.obj': face index 9 > 3 vertices"),
    ("zero-index-obj", "m.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"line 4: OBJ indices start at 1, got 0"),
    ("relative-index-before-start", "m.obj", "v 0 0 0\nf -1 -2 -3\n", r"line 2: relative index '-2' reaches before the first vertex"),
    ("text-coordinate-obj", "m.obj", "v 0 zero 0\n", r"line 1: could not convert string to float"),
    ("out-of-range-ply", "m.ply", ascii_ply(_TRIANGLE, [[0, 1, 5]]), r"m\.ply': face indices must lie in \[0, 2\], found 0\.\.5"),
    ("negative-index-ply", "m.ply", ascii_ply(_TRIANGLE, [[0, 1, -1]]), r"face indices must lie in \[0, 2\], found -1\.\.1"),
    ("all-degenerate", "m.obj", "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", r"1 of 1 faces \(100\.0%\) have zero area, above the 1% limit"),
    ("one-point", "m.obj", "v 1 1 1\nf 1 1 1\n", r"1 of 1 faces \(100\.0%\) have zero area"),
    ("huge-coordinates", "m.obj", "v 0 0 0\nv 1e300 0 0\nv 0 0 -1e300\nf 1 2 3\n", r"mesh coordinates reach 1e\+300, beyond the \+-1e\+18 limit \(MAX_COORDINATE"),
    ("coordinates-above-limit", "m.obj", "v 0 0 0\nv 1e19 0 0\nv 0 0 -1e19\nf 1 2 3\n", r"mesh coordinates reach 1e\+19, beyond the \+-1e\+18 limit"),
]


@pytest.mark.parametrize("name, content, match", [c[1:] for c in _FILE_CASES], ids=[c[0] for c in _FILE_CASES])
def test_malformed_mesh_files(tmp_path, name, content, match):
    target = tmp_path / name
    if isinstance(content, bytes):
        target.write_bytes(content)
    else:
        target.write_text(content)
    path = scene_with_mesh(tmp_path, name)
    with pytest.raises(SceneError, match=r"scene\.yaml: objects\[0\]\.mesh: .*" + match) as info:
        load_scene(path)
    assert "\n" not in str(info.value)


def test_missing_mesh_and_folder(tmp_path):
    with pytest.raises(SceneError, match=r"scene\.yaml: objects\[0\]\.mesh: file not found: 'meshes/nope\.ply' \(relative to "):
        load_scene(scene_with_mesh(tmp_path, "meshes/nope.ply"))
    (tmp_path / "folder.ply").mkdir()
    with pytest.raises(SceneError, match=r"objects\[0\]\.mesh: file not found: 'folder\.ply'"):
        load_scene(scene_with_mesh(tmp_path, "folder.ply"))


@pytest.mark.parametrize("size", [1e-200, 1e-30, 1e15])
def test_tiny_and_large_meshes_are_not_called_degenerate(tmp_path, size):
    """Areas are measured relative to the mesh's own size: neither underflow nor overflow."""
    box = trimesh.creation.box()
    text = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in (box.vertices * size).tolist())  # float64 text, not float32 PLY
    text += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces)
    (tmp_path / "m.obj").write_text(text)
    scene = load_scene(scene_with_mesh(tmp_path, "m.obj"))
    assert len(scene.objects[0].mesh.faces) == 12


# ----------------------------------------------------------------------------- inward normals


def flipped_torus(tmp_path) -> str:
    torus = builtin_mesh("torus")
    trimesh.Trimesh(torus.vertices, np.asarray(torus.faces)[:, ::-1], process=False).export(tmp_path / "torus.ply")
    return "torus.ply"


def test_closed_signed_volume():
    torus = builtin_mesh("torus")
    volume = closed_signed_volume(torus.vertices, torus.faces)
    assert volume == pytest.approx(torus.volume)
    assert volume == pytest.approx(2 * np.pi**2 * 1.0 * 0.25**2, rel=0.05)  # 2 pi^2 R r^2, up to faceting
    assert closed_signed_volume(torus.vertices, np.asarray(torus.faces)[:, ::-1]) == pytest.approx(-volume)
    box = builtin_mesh("box", size=[1, 2, 3])  # split vertices along the edges: closed after merging
    assert closed_signed_volume(box.vertices, box.faces) == pytest.approx(6.0)
    assert closed_signed_volume(builtin_mesh("plane").vertices, builtin_mesh("plane").faces) is None  # open
    teapot = builtin_mesh("teapot", resolution=2)
    assert closed_signed_volume(teapot.vertices, teapot.faces) is None  # open sheets
    assert closed_signed_volume(np.zeros((0, 3)), np.zeros((0, 3), int)) is None


def test_inward_torus_warns(tmp_path):
    path = scene_with_mesh(tmp_path, flipped_torus(tmp_path))
    with pytest.warns(
        InwardNormalsWarning,
        match=r"scene\.yaml: objects\[0\] \('thing'\): the mesh is closed but its faces point inward \(signed volume -1\.19 < 0\).*flip its faces",
    ):
        load_scene(path)
    assert issubclass(InwardNormalsWarning, UserWarning)


def test_inward_box_with_split_vertices_warns(tmp_path):
    box = builtin_mesh("box")
    trimesh.Trimesh(box.vertices, np.asarray(box.faces)[:, ::-1], process=False).export(tmp_path / "box.ply")
    with pytest.warns(InwardNormalsWarning, match=r"objects\[0\] \('thing'\)"):
        load_scene(scene_with_mesh(tmp_path, "box.ply"))


@pytest.mark.parametrize(
    "case",
    ["outward-torus", "flipped-plane", "flipped-teapot", "room-camera-inside", "closed-room-shipped"],
)
def test_no_warning(tmp_path, case):
    """Open meshes, outward meshes and inward rooms around the camera are as meant."""
    camera = None
    if case == "outward-torus":
        mesh = {"builtin": "torus"}
    elif case == "flipped-plane":
        plane = builtin_mesh("plane")
        trimesh.Trimesh(plane.vertices, np.asarray(plane.faces)[:, ::-1], process=False).export(tmp_path / "p.ply")
        mesh = "p.ply"
    elif case == "flipped-teapot":
        pot = builtin_mesh("teapot", resolution=2)
        trimesh.Trimesh(pot.vertices, np.asarray(pot.faces)[:, ::-1], process=False).export(tmp_path / "t.ply")
        mesh = "t.ply"
    elif case == "room-camera-inside":
        mesh = flipped_torus(tmp_path)  # a closed inward mesh, seen from inside its bounding box
        camera = {"position": [0.9, 0.0, 0.0], "look_at": [0.9, 0.0, -1.0]}
    else:
        mesh = {"builtin": "room", "size": [4, 2.5, 4], "windows": [], "cell_size": 1.0}
        camera = {"position": [0, 1.5, 1.9], "look_at": [0, 0.3, -0.2]}
    with warnings.catch_warnings():
        warnings.simplefilter("error", InwardNormalsWarning)
        scene = load_scene(scene_with_mesh(tmp_path, mesh, camera))
    if case == "closed-room-shipped":  # the room really is closed and inward: the camera rule is what spares it
        obj = scene.objects[0]
        assert closed_signed_volume(obj.mesh.vertices, obj.mesh.faces) == pytest.approx(-40.0)


def test_inward_room_seen_from_outside_warns(tmp_path):
    mesh = {"builtin": "room", "size": [4, 2.5, 4], "windows": [], "cell_size": 1.0}
    with pytest.warns(InwardNormalsWarning, match=r"or place the camera inside it if it is a room"):
        load_scene(scene_with_mesh(tmp_path, mesh, {"position": [0, 1.5, 9], "look_at": [0, 1, 0]}))
