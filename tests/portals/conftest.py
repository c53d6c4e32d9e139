"""Small window-box scenes shared by the portals tests."""

from __future__ import annotations

import pytest

from prtlab.scene import Scene


def window_box(light=None, room=(3.0, 2.5, 3.0), window=(1.0, 1.0), cell=0.25, albedo=(0.7, 0.7, 0.7)):
    """A box room with one window on the -z wall (the portal), lit by ``light``."""
    w = {"wall": "-z", "center": [0, 1.4], "size": list(window)}
    return Scene.from_dict({
        "objects": [
            {"name": "room", "mesh": {"builtin": "room", "size": list(room), "windows": [w], "cell_size": cell},
             "material": {"type": "diffuse", "albedo": list(albedo)}},
            {"name": "window", "mesh": {"builtin": "window", "room_size": list(room), **w}, "portal": True},
        ],
        "lights": [light or {"type": "environment", "constant": [1.0, 1.0, 1.0]}],
        "camera": {"position": [0, 1, 1], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 60,
                   "resolution": [64, 64]},
    })


SKY = {"type": "environment", "sky": {"sun_elevation_deg": 35, "sun_azimuth_deg": 0, "turbidity": 3, "sun": False,
                                      "height": 64, "width": 128}}


@pytest.fixture(scope="module")
def constant_box():
    return window_box()


@pytest.fixture(scope="module")
def sky_box():
    return window_box(SKY)
