"""Tests of prtlab/scene/_animation.py: keyframes, interpolation, slerp, frames, validation."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from prtlab.scene import (
    Scene,
    SceneError,
    euler_to_matrix,
    matrix_to_euler,
    preetham_sky,
    quaternion_from_matrix,
    quaternion_to_matrix,
    slerp,
)
from tests.conftest import FLOAT_TOLERANCE, random_rotation

TOL = FLOAT_TOLERANCE[np.float64]


def animated_dict() -> dict:
    return {
        "objects": [
            {"name": "floor", "mesh": {"builtin": "plane"}},
            {"name": "ball", "mesh": {"builtin": "icosphere", "subdivisions": 1}, "transform": {"scale": 0.5}},
        ],
        "lights": [
            {"type": "area", "center": [0, 3, 0], "u": [0.5, 0, 0], "v": [0, 0, 0.5], "radiance": [10, 10, 10]},
            {"type": "point", "position": [0, 3, 0], "intensity": [1, 1, 1]},
            {"type": "environment", "sky": {"sun_elevation_deg": 30, "height": 8, "width": 16}, "scale": 0.5},
        ],
        "animation": {
            "tracks": [
                {
                    "object": "ball",
                    "keys": [
                        {"time": 0.0, "translate": [0, 0, 0], "rotate_deg": [0, 0, 0], "scale": 1.0},
                        {"time": 2.0, "translate": [2, 0, 0], "rotate_deg": [0, 90, 0], "scale": 2.0},
                        {"time": 3.0, "translate": [2, 1, 0], "rotate_deg": [30, 120, 45], "scale": 2.0},
                    ],
                },
                {"light": 0, "keys": [{"time": 0, "radiance": [10, 10, 10]}, {"time": 2, "radiance": [0, 20, 10]}]},
                {"light": 1, "keys": [{"time": 1, "position": [0, 3, 0]}, {"time": 3, "position": [1, 3, 0]}]},
                {"light": 2, "keys": [{"time": 0, "sun_elevation_deg": 10}, {"time": 2, "sun_elevation_deg": 50}]},
            ]
        },
    }


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene.from_dict(animated_dict())


# ----------------------------------------------------------------------------- rotations


def test_quaternion_matrix_round_trip(rng):
    for _ in range(20):
        r = random_rotation(rng)
        q = quaternion_from_matrix(r)
        assert abs(np.linalg.norm(q) - 1.0) < TOL and q[0] >= 0
        np.testing.assert_allclose(quaternion_to_matrix(q), r, atol=1e-12)


def test_euler_round_trip(rng):
    for _ in range(20):
        r = random_rotation(rng)
        np.testing.assert_allclose(euler_to_matrix(matrix_to_euler(r)), r, atol=1e-12)
    for gimbal in ([10, 90, 20], [10, -90, 20]):  # ry = +-90: only rx -+ rz is defined
        r = euler_to_matrix(gimbal)
        np.testing.assert_allclose(euler_to_matrix(matrix_to_euler(r)), r, atol=1e-12)


def test_slerp_unit_and_endpoints(rng):
    q0 = quaternion_from_matrix(random_rotation(rng))
    q1 = quaternion_from_matrix(random_rotation(rng))
    for a in np.linspace(0.0, 1.0, 11):
        assert abs(np.linalg.norm(slerp(q0, q1, a)) - 1.0) < TOL
    np.testing.assert_allclose(slerp(q0, q1, 0.0), q0, atol=1e-12)
    end = slerp(q0, q1, 1.0)
    np.testing.assert_allclose(end * np.sign(end @ q1), q1, atol=1e-12)


def test_slerp_constant_angular_speed_on_shorter_arc(rng):
    q0 = quaternion_from_matrix(euler_to_matrix([0, 0, 0]))
    q1 = quaternion_from_matrix(euler_to_matrix([0, 300, 0]))  # the shorter way is -60 degrees
    for a in (0.25, 0.5, 0.75):
        np.testing.assert_allclose(matrix_to_euler(quaternion_to_matrix(slerp(q0, q1, a))), [0, -60 * a, 0], atol=1e-9)
    np.testing.assert_allclose(slerp(q0, -q0, 0.3), q0, atol=1e-12)  # same rotation: no motion


# ----------------------------------------------------------------------------- evaluation


def test_keyframes_are_hit_exactly(scene):
    for key in animated_dict()["animation"]["tracks"][0]["keys"]:
        tr = scene.at_time(key["time"]).object("ball").transform
        np.testing.assert_array_equal(tr.translate, key["translate"])
        np.testing.assert_array_equal(tr.rotate_deg, key["rotate_deg"])
        assert tr.scale == key["scale"]
    np.testing.assert_array_equal(scene.at_time(2.0).area_lights[0].radiance, [0, 20, 10])


def test_linear_interpolation_and_slerp(scene):
    tr = scene.at_time(0.5).object("ball").transform
    np.testing.assert_allclose(tr.translate, [0.5, 0, 0], rtol=TOL)
    assert tr.scale == pytest.approx(1.25, rel=TOL)
    np.testing.assert_allclose(tr.rotate_deg, [0, 22.5, 0], atol=1e-9)
    np.testing.assert_allclose(scene.at_time(1.0).area_lights[0].radiance, [5, 15, 10], rtol=TOL)
    np.testing.assert_allclose(scene.at_time(2.0).point_lights[0].position, [0.5, 3, 0], rtol=TOL)


def test_holds_outside_the_keys(scene):
    first = scene.at_time(0.0).point_lights[0].position
    np.testing.assert_array_equal(first, [0, 3, 0])  # the point light's track starts at t = 1
    late = scene.at_time(10.0)
    np.testing.assert_array_equal(late.object("ball").transform.translate, [2, 1, 0])
    np.testing.assert_array_equal(late.point_lights[0].position, [1, 3, 0])


def test_sky_is_recomputed(scene):
    env = scene.at_time(1.0).environment
    assert env.spec["sky"]["sun_elevation_deg"] == 30.0
    np.testing.assert_allclose(env.image, 0.5 * preetham_sky(30.0, 0.0, 3.0, 8, 16), rtol=TOL)
    assert scene.at_time(2.0).environment.spec["sky"]["sun_elevation_deg"] == 50.0


def test_frames_span_the_duration(scene):
    assert scene.duration == 3.0
    assert scene.at_frame(0, 4) == scene.at_time(0.0)
    assert scene.at_frame(3, 4) == scene.at_time(3.0)
    assert scene.at_frame(1, 4) == scene.at_time(1.0)
    assert scene.at_frame(0, 1) == scene.at_time(0.0)


def test_at_time_shares_meshes_and_leaves_the_scene_alone(scene):
    before = copy.deepcopy(scene.to_dict())
    frame = scene.at_time(1.5)
    assert frame.object("ball").mesh is scene.object("ball").mesh
    assert scene.to_dict() == before
    assert frame.object("floor").transform == scene.object("floor").transform


def test_scene_without_animation():
    d = animated_dict()
    del d["animation"]
    s = Scene.from_dict(d)
    assert s.duration == 0.0 and s.at_time(5.0) == s and s.at_frame(2, 3) == s


def test_animation_round_trip(scene):
    d = scene.to_dict()
    assert d["animation"]["duration"] == 3.0
    assert Scene.from_dict(d) == scene


def test_explicit_duration():
    d = animated_dict()
    d["animation"]["duration"] = 6.0
    s = Scene.from_dict(d)
    assert s.duration == 6.0
    np.testing.assert_array_equal(s.at_frame(1, 3).object("ball").transform.translate, [2, 1, 0])


def test_time_and_frame_errors(scene):
    with pytest.raises(ValueError, match="t must be a finite number of seconds"):
        scene.at_time(float("nan"))
    with pytest.raises(ValueError, match="n_frames must be an int >= 1"):
        scene.at_frame(0, 0)
    with pytest.raises(ValueError, match="frame index i must be an int >= 0 and <= 2"):
        scene.at_frame(3, 3)


# ----------------------------------------------------------------------------- validation


def _with_track(track: dict) -> dict:
    d = animated_dict()
    d["animation"]["tracks"] = [track]
    return d


@pytest.mark.parametrize(
    "track, match",
    [
        ({"object": "cube", "keys": [{"time": 0, "translate": [0, 0, 0]}]}, r"animation\.tracks\[0\]\.object: no object named 'cube'"),
        ({"light": 5, "keys": [{"time": 0, "radiance": [1, 1, 1]}]}, r"animation\.tracks\[0\]\.light: light index 5 out of range"),
        ({"keys": [{"time": 0}]}, r"animation\.tracks\[0\]: a track animates exactly one target"),
        (
            {"object": "ball", "light": 0, "keys": [{"time": 0, "scale": 1}]},
            r"animation\.tracks\[0\]: a track animates exactly one target",
        ),
        (
            {"object": "ball", "keys": [{"time": 1, "scale": 1}, {"time": 1, "scale": 2}]},
            r"animation\.tracks\[0\]\.keys\[1\]\.time: key times must increase strictly",
        ),
        (
            {"object": "ball", "keys": [{"time": 0, "scale": 1}, {"time": 1, "translate": [0, 0, 0]}]},
            r"animation\.tracks\[0\]\.keys\[1\]: every key of a track must set the same fields",
        ),
        ({"object": "ball", "keys": [{"time": 0}]}, r"animation\.tracks\[0\]\.keys\[0\]: a key must set at least one of"),
        (
            {"object": "ball", "keys": [{"time": 0, "translat": [0, 0, 0]}]},
            r"animation\.tracks\[0\]\.keys\[0\]\.translat: unknown key; did you mean 'translate'\?",
        ),
        ({"object": "ball", "keys": [{"time": 0, "radiance": [1, 1, 1]}]}, r"keys\[0\]\.radiance: unknown key"),
        ({"object": "ball", "keys": [{"time": 0, "scale": 0}]}, r"keys\[0\]\.scale: expected a finite number > 0, got 0"),
        ({"object": "ball", "keys": [{"time": -1, "scale": 1}]}, r"keys\[0\]\.time: expected a finite number >= 0"),
        (
            {"object": "ball", "keys": [{"time": 0, "rotate_deg": [0, float("nan"), 0]}]},
            r"keys\[0\]\.rotate_deg: expected 3 finite numbers",
        ),
        ({"light": 0, "keys": [{"time": 0, "radiance": [1, -1, 1]}]}, r"keys\[0\]\.radiance: expected 3 non-negative finite numbers"),
        ({"light": 0, "keys": [{"time": 0, "v": [1, 0, 0]}]}, r"keys\[0\]: u \[0\.5, 0\.0, 0\.0\] and v \[1\.0, 0\.0, 0\.0\] are parallel"),
        ({"light": 2, "keys": [{"time": 0, "sun_elevation_deg": 95}]}, r"keys\[0\]\.sun_elevation_deg: expected a finite number in \[0\.0, 90\.0\]"),
        ({"light": 2, "keys": [{"time": 0, "constant": [1, 1, 1]}]}, r"keys\[0\]\.constant: unknown key"),
        ({"object": "ball", "keys": []}, r"animation\.tracks\[0\]\.keys: expected a non-empty list"),
    ],
)
def test_validation_messages(track, match):
    with pytest.raises(SceneError, match=match):
        Scene.from_dict(_with_track(track))


def test_animation_structure_errors():
    d = animated_dict()
    d["animation"] = {"trakcs": []}
    with pytest.raises(SceneError, match=r"animation\.trakcs: unknown key; did you mean 'tracks'\?"):
        Scene.from_dict(d)
    d["animation"] = {"tracks": [], "duration": 1}
    with pytest.raises(SceneError, match=r"animation\.tracks: expected a non-empty list"):
        Scene.from_dict(d)
    d["animation"] = {"tracks": animated_dict()["animation"]["tracks"], "duration": -1}
    with pytest.raises(SceneError, match=r"animation\.duration: expected a finite number >= 0"):
        Scene.from_dict(d)
