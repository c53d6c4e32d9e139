import numpy as np
import pytest

from prtlab.geometry import cubemap_directions
from prtlab.portals import PortalValidityWarning, exterior_shell, find_portals
from prtlab.scene import Scene

from .conftest import window_box


def _exterior(y):
    return Scene.from_dict({
        "objects": [{"name": "ground", "mesh": {"builtin": "plane", "size": [200, 200], "resolution": [1, 1]},
                     "transform": {"translate": [0, y, 0]}, "material": {"type": "diffuse", "albedo": [0.5, 0.5, 0.5]}}],
        "lights": [{"type": "environment", "constant": [1.0, 1.0, 1.0]}],
        "camera": {"position": [0, 1, 1], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 60,
                   "resolution": [8, 8]},
    })


def test_ground_under_constant_sky():
    """A white-sky-lit ground of albedo 0.5 reflects 0.5 (no occlusion above it); the sky gives 1."""
    (portal,) = find_portals(window_box())
    cube = exterior_shell(_exterior(-10.0), portal, res=4, n_samples=64, rng=np.random.default_rng(0))
    dirs = cubemap_directions(4)
    down = dirs[..., 1] < -0.2
    up = dirs[..., 1] > 0
    np.testing.assert_allclose(cube[up], 1.0)
    np.testing.assert_allclose(cube[down], 0.5, atol=1e-9)  # constant sky over a plane: zero variance


def test_close_object_warns():
    (portal,) = find_portals(window_box())
    with pytest.warns(PortalValidityWarning, match="split the portal"):
        exterior_shell(_exterior(1.0), portal, res=2, n_samples=4, rng=np.random.default_rng(0))
    with pytest.raises(TypeError, match="prtlab.Scene"):
        exterior_shell(None, portal)


def test_exterior_needs_environment():
    (portal,) = find_portals(window_box())
    scene = _exterior(-10.0)
    scene.lights = []
    with pytest.raises(ValueError, match="needs an environment light"):
        exterior_shell(scene, portal)
