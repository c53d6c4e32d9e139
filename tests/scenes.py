"""Scenes the tests of several packages share: scene files (YAML text) for the command line, and
:class:`prtlab.Scene` objects built from dicts as a scene file would be."""

from __future__ import annotations

import copy

from prtlab.scene import Scene

#: ``with_change(d, path, DELETE)`` deletes the item at ``path``.
DELETE = object()


def with_change(d: dict, path: str, value) -> dict:
    """A deep copy of the scene dict ``d`` with the item at a dotted path (``objects.0.material.albedo``)
    replaced by ``value``, or deleted if ``value`` is :data:`DELETE`."""
    d = copy.deepcopy(d)
    *parents, last = path.split(".")
    node = d
    for p in parents:
        node = node[int(p)] if isinstance(node, list) else node[p]
    key = int(last) if isinstance(node, list) else last
    if value is DELETE:
        del node[key]
    else:
        node[key] = value
    return d


#: A floor and a moving ball under a small sky, with a camera and a one-second animation (command-line tests).
TINY_SCENE = """\
name: tiny
objects:
  - name: floor
    mesh: {builtin: plane, size: [4, 4], resolution: [4, 4]}
    material: {type: diffuse, albedo: [0.7, 0.7, 0.7]}
  - name: ball
    mesh: {builtin: icosphere, radius: 0.5, subdivisions: 1}
    transform: {translate: [0, 0.5, 0]}
    material: {type: diffuse, albedo: [0.8, 0.2, 0.2]}
    dynamic: true
lights:
  - type: environment
    sky: {sun_elevation_deg: 35, sun_azimuth_deg: 0, turbidity: 3, sun: false, height: 16, width: 32}
    scale: 0.5
camera: {position: [0, 2.0, 4.5], look_at: [0, 0.4, 0], up: [0, 1, 0], fov_deg: 40, resolution: [32, 24]}
animation:
  tracks:
    - object: ball
      keys:
        - {time: 0, translate: [0, 0.5, 0]}
        - {time: 1, translate: [1, 0.5, 0]}
"""

#: A room with one window portal (command-line tests of the portals pipeline).
TINY_ROOM = """\
name: tiny_room
objects:
  - name: room
    mesh:
      builtin: room
      size: [4, 2.5, 4]
      windows: [{wall: -z, center: [0, 1.4], size: [1.5, 1.0]}]
      cell_size: 1.0
    material: {type: diffuse, albedo: [0.7, 0.7, 0.7]}
  - name: window
    mesh: {builtin: window, room_size: [4, 2.5, 4], wall: -z, center: [0, 1.4], size: [1.5, 1.0]}
    portal: true
lights:
  - type: environment
    sky: {sun_elevation_deg: 35, sun_azimuth_deg: 0, turbidity: 3, sun: false, height: 16, width: 32}
    scale: 0.2
camera: {position: [0.8, 1.3, 1.9], look_at: [-0.2, 0.7, -1.0], up: [0, 1, 0], fov_deg: 60, resolution: [32, 24]}
"""


def floor_and_ball(floor_resolution: int = 4, subdivisions: int = 1, ball_at=(0.0, 0.5, 0.0), *,
                   floor_name: str = "floor", floor_material=None, ball_albedo=(0.8, 0.2, 0.2),
                   dynamic: bool = False, lights=None, camera=None) -> Scene:
    """A 4 x 4 floor (``floor_resolution`` quads a side) and a ball of radius 0.5 at ``ball_at``; default light a
    constant environment ``(1, 0.9, 0.8)``."""
    ball = {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": subdivisions},
            "transform": {"translate": list(ball_at)}, "material": {"type": "diffuse", "albedo": list(ball_albedo)}}
    if dynamic:
        ball["dynamic"] = True
    scene = {
        "objects": [
            {"name": floor_name, "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [floor_resolution] * 2},
             "material": floor_material or {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}},
            ball,
        ],
        "lights": lights or [{"type": "environment", "constant": [1.0, 0.9, 0.8]}],
    }
    if camera is not None:
        scene["camera"] = camera
    return Scene.from_dict(scene)


def ball_over_floor(floor_material=None):
    """A 4 x 4 floor (12 x 12 quads) under a ball of radius 0.5 at height 1, in a Preetham sky (scale 0.1)."""
    return floor_and_ball(
        12, 3, (0, 1.0, 0), floor_material=floor_material or {"type": "diffuse", "albedo": [0.8, 0.8, 0.8]},
        ball_albedo=(0.5, 0.6, 0.7),
        lights=[{"type": "environment", "sky": {"sun_elevation_deg": 40, "sun_azimuth_deg": 30, "turbidity": 3},
                 "scale": 0.1}],
        camera={"position": [0, 3, 6], "look_at": [0, 0, 0]})
