"""Scenes the tests of several packages share (built from dicts, as a scene file would be)."""

from __future__ import annotations

from prtlab.scene import Scene


def ball_over_floor(floor_material=None):
    """A 4 x 4 floor (12 x 12 quads) under a ball of radius 0.5 at height 1, in a Preetham sky (scale 0.1)."""
    return Scene.from_dict({
        "objects": [
            {"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [12, 12]},
             "material": floor_material or {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]}},
            {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 3},
             "transform": {"translate": [0, 1.0, 0]}, "material": {"type": "diffuse", "albedo": [0.5, 0.6, 0.7]}},
        ],
        "lights": [{"type": "environment", "sky": {"sun_elevation_deg": 40, "sun_azimuth_deg": 30,
                                                   "turbidity": 3}, "scale": 0.1}],
        "camera": {"position": [0, 3, 6], "look_at": [0, 0, 0]},
    })
