"""Malformed environment maps and scales: refused at load naming the file and the key, never inside a method."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from prtlab.scene import SceneError, load_scene, write_exr, write_hdr


def scene_with_map(tmp_path, name, scale=1.0, animation=None) -> str:
    d = {
        "objects": [{"name": "floor", "mesh": {"builtin": "plane"}}],
        "lights": [{"type": "environment", "file": name, "scale": scale}],
    }
    if animation is not None:
        d["animation"] = animation
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def exr(shape, value=0.5, where=None, bad=None):
    image = np.full(shape, value, dtype=np.float64)
    if where is not None:
        image[where] = bad
    return image


def write_channels(path, channels):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}).write(str(path))


def raw_exr(image):
    """A maker writing ``image`` as R, G, B channels as is (``write_exr`` refuses NaN and inf)."""
    return lambda path: write_channels(path, {c: image[..., k] for k, c in enumerate("RGB")})


def truncated(writer, name, shape, keep):
    def make(path):
        writer(path, np.full(shape, 0.5))
        data = path.read_bytes()
        path.write_bytes(data[: keep(len(data))])

    return make


_CASES = [
    # (id, file name, maker(path) or image, match after "scene.yaml: lights[0].file: ")
    ("1x1", "m.exr", exr((1, 1, 3)), r"environment map 'm\.exr' is 1 x 1 pixels \(width x height\); an equirect .* width = 2 x height and height >= 2"),
    ("1x2", "m.exr", exr((1, 2, 3)), r"is 2 x 1 pixels"),
    ("square", "m.exr", exr((16, 16, 3)), r"environment map 'm\.exr' is 16 x 16 pixels \(width x height\)"),
    ("tall", "m.exr", exr((16, 8, 3)), r"is 8 x 16 pixels"),
    ("cross-4x3", "m.exr", exr((12, 16, 3)), r"is 16 x 12 pixels"),
    ("almost-2to1", "m.exr", exr((64, 126, 3)), r"is 126 x 64 pixels"),
    ("nan-pixel", "m.exr", raw_exr(exr((8, 16, 3), where=(3, 5, 1), bad=np.nan)), r"environment map 'm\.exr' has 1 NaN or inf pixels \(the first at row 3, column 5\); radiance must be finite"),
    ("inf-pixels", "m.exr", raw_exr(exr((8, 16, 3), where=(slice(0, 2), 7), bad=np.inf)), r"has 2 NaN or inf pixels \(the first at row 0, column 7\)"),
    ("negative-pixel", "m.exr", exr((8, 16, 3), where=(6, 2, 0), bad=-0.25), r"has 1 pixels with negative radiance \(the first at row 6, column 2: \[-0\.25, 0\.5, 0\.5\]\); radiance must be >= 0"),
    ("all-negative", "m.exr", exr((8, 16, 3), value=-1.0), r"has 128 pixels with negative radiance"),
    ("truncated-exr", "m.exr", truncated(write_exr, "m.exr", (8, 16, 3), lambda n: n // 2), r"cannot read EXR file .*m\.exr' \(truncated, or not OpenEXR\?\)"),
    ("header-only-exr", "m.exr", truncated(write_exr, "m.exr", (8, 16, 3), lambda n: 40), r"cannot read EXR file .*m\.exr' \(truncated"),
    ("empty-exr", "m.exr", lambda path: path.write_bytes(b""), r"cannot read EXR file"),
    ("garbage-exr", "m.exr", lambda path: path.write_bytes(b"not an exr at all" * 10), r"cannot read EXR file"),
    ("alpha-only-exr", "m.exr", lambda path: write_channels(path, {"A": np.ones((4, 8))}), r"EXR file .*m\.exr' has channels \['A'\]; need R, G, B \(or Y\)"),
    ("truncated-hdr", "m.hdr", truncated(write_hdr, "m.hdr", (8, 16, 3), lambda n: n - 30), r"HDR file .*m\.hdr'.*truncated"),
    ("no-header-end-hdr", "m.hdr", truncated(write_hdr, "m.hdr", (8, 16, 3), lambda n: 20), r"HDR file .*m\.hdr': header has no end"),
    ("not-radiance-hdr", "m.hdr", lambda path: path.write_bytes(b"P6\n16 8\n255\n" + bytes(384)), r"does not start with '#\?RADIANCE' or '#\?RGBE'"),
    ("bad-resolution-hdr", "m.hdr", lambda path: path.write_bytes(b"#?RADIANCE\n\n-Y x +X 16\n"), r"unsupported resolution line b'-Y x \+X 16'"),
    ("giant-resolution-hdr", "m.hdr", lambda path: path.write_bytes(b"#?RADIANCE\n\n-Y 100000000 +X 200000000\n" + bytes(64)), r"200000000 x 100000000 pixels; expected 1 to 134,217,728 pixels"),
    ("png", "m.png", lambda path: path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64)), r"cannot use .*m\.png' as an environment map: \.png images hold 8-bit display values .*convert the HDR original to OpenEXR"),
    ("jpeg", "m.JPG", lambda path: path.write_bytes(b"\xff\xd8\xff" + bytes(64)), r"\.jpg images hold 8-bit display values"),
    ("unknown-suffix", "m.txt", lambda path: path.write_text("0.5\n"), r"unknown extension '\.txt'; use an OpenEXR \(\.exr\) or Radiance RGBE \(\.hdr\) file"),
]


@pytest.mark.parametrize("name, content, match", [c[1:] for c in _CASES], ids=[c[0] for c in _CASES])
def test_malformed_maps(tmp_path, name, content, match):
    target = tmp_path / name
    if callable(content):
        content(target)
    else:
        write_exr(target, content)
    with pytest.raises(SceneError, match=r"scene\.yaml: lights\[0\]\.file: .*" + match) as info:
        load_scene(scene_with_map(tmp_path, name))
    assert "\n" not in str(info.value)


def test_missing_map(tmp_path):
    with pytest.raises(SceneError, match=r"scene\.yaml: lights\[0\]\.file: file not found: 'sky\.exr' \(relative to "):
        load_scene(scene_with_map(tmp_path, "sky.exr"))


@pytest.mark.parametrize("shape", [(2, 4, 3), (8, 16, 3), (100, 199, 3)], ids=["smallest", "2to1", "within-1%"])
def test_equirect_maps_load(tmp_path, shape):
    write_exr(tmp_path / "m.exr", exr(shape))
    scene = load_scene(scene_with_map(tmp_path, "m.exr", scale=2.0))
    np.testing.assert_allclose(scene.environment.image, 1.0)


def test_luminance_only_exr_loads_as_grey(tmp_path):
    write_channels(tmp_path / "m.exr", {"Y": np.full((4, 8), 0.25)})
    np.testing.assert_allclose(load_scene(scene_with_map(tmp_path, "m.exr")).environment.image, 0.25)


@pytest.mark.parametrize(
    "scale, pixel, match",
    [
        (1.0e308, 1.0, r"lights\[0\]\.scale: scale 1e\+308 times the map \(total 384 over its pixels\) overflows float64; use a smaller scale"),
        (1.0e300, 1.0e30, r"lights\[0\]\.scale: scale 1e\+300 times the map .* overflows float64"),
        (float("inf"), 1.0, r"lights\[0\]\.scale: expected a finite number >= 0\.0, got inf"),
        (float("nan"), 1.0, r"lights\[0\]\.scale: expected a finite number >= 0\.0, got nan"),
        (-1.0, 1.0, r"lights\[0\]\.scale: expected a finite number >= 0\.0, got -1\.0"),
        (True, 1.0, r"lights\[0\]\.scale: expected a finite number >= 0\.0, got True"),
    ],
    ids=["1e308", "1e300-bright", "inf", "nan", "negative", "bool"],
)
def test_bad_scales(tmp_path, scale, pixel, match):
    write_exr(tmp_path / "m.exr", exr((8, 16, 3), value=pixel))
    with pytest.raises(SceneError, match=r"scene\.yaml: " + match):
        load_scene(scene_with_map(tmp_path, "m.exr", scale=scale))


def test_animated_scale_that_overflows(tmp_path):
    write_exr(tmp_path / "m.exr", exr((8, 16, 3)))
    animation = {"tracks": [{"light": 0, "keys": [{"time": 0, "scale": 1.0}, {"time": 1, "scale": 1.0e308}]}]}
    with pytest.raises(SceneError, match=r"scene\.yaml: animation\.tracks\[0\]\.keys\[1\]\.scale: scale 1e\+308 times the map"):
        load_scene(scene_with_map(tmp_path, "m.exr", animation=animation))


def test_a_scale_of_zero_is_darkness(tmp_path):
    write_exr(tmp_path / "m.exr", exr((8, 16, 3)))
    assert not np.any(load_scene(scene_with_map(tmp_path, "m.exr", scale=0.0)).environment.image)


@pytest.mark.parametrize(
    "sky, match",
    [
        ({"sun_elevation_deg": 30, "height": 1}, r"lights\[0\]\.sky\.height: expected an integer >= 2, got 1"),
        ({"sun_elevation_deg": 30, "width": 0}, r"lights\[0\]\.sky\.width: expected an integer >= 1, got 0"),
        ({"sun_elevation_deg": 30, "width": 8.0}, r"lights\[0\]\.sky\.width: expected an integer >= 1, got 8\.0"),
        ({"sun_elevation_deg": 30, "sun": "yes"}, r"lights\[0\]\.sky\.sun: expected true or false, got str 'yes'"),
        ({"sun_azimuth_deg": 10}, r"lights\[0\]\.sky: missing required key 'sun_elevation_deg'"),
    ],
    ids=["height-1", "width-0", "float-width", "string-sun", "no-elevation"],
)
def test_bad_skies(tmp_path, sky, match):
    d = {"objects": [{"name": "floor", "mesh": {"builtin": "plane"}}], "lights": [{"type": "environment", "sky": sky}]}
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(SceneError, match=r"scene\.yaml: " + match):
        load_scene(path)
