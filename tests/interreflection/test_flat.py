"""Tests of prtlab/interreflection/_flat.py: a flat occluder's visibility on its plane (``flat_visibility``).

The half-space's SH against closed values and a dense quadrature; which points take it (inside the footprint,
on the plane, away from its boundary and out of its holes); the pipeline's occlusion rows (the half-space there,
the field's lookup bit for bit elsewhere and with ``flat_visibility="field"``); and the direct light of a box's
faces standing on a floor, equal to the order-n SH triple product of the half-space and the cosine with the
environment's SH. Against Monte Carlo: ``tests/fidelity/test_interreflection.py``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from prtlab import sh
from prtlab.geometry import builtin_mesh
from prtlab.interreflection import Interreflection
from prtlab.interreflection._flat import NEAR_RATIO, FlatOccluder, halfspace_visibility, halfspace_zh
from prtlab.pipeline import FrameState
from prtlab.scene import Scene, Transform, environment_sh

#: options of a small precomputation (order 4 as the defaults)
SMALL = dict(n_radii=6, resolution=6, degree=15, n_lights=16, n_basis=4)


def _fibonacci(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def test_halfspace_zh_is_the_hemisphere_projection():
    """Closed values ``sqrt(pi)``, ``sqrt(3 pi) / 2``, 0, ``-sqrt(7 pi) / 8`` and a dense quadrature of the
    indicator of ``z > 0`` (equal-area points, numpy's Legendre polynomials)."""
    z = halfspace_zh(8)
    np.testing.assert_allclose(z[:4], [math.sqrt(math.pi), math.sqrt(3 * math.pi) / 2, 0.0,
                                       -math.sqrt(7 * math.pi) / 8], atol=1e-15)
    assert np.all(z[2::2] == 0.0)
    dirs = _fibonacci(400_000)
    up = dirs[:, 2] > 0
    for band in range(8):
        p = np.polynomial.legendre.Legendre.basis(band)(dirs[:, 2])
        quad = 4 * math.pi / len(dirs) * np.sum(up * math.sqrt((2 * band + 1) / (4 * math.pi)) * p)
        assert abs(quad - z[band]) < 2e-4


def _ring(size: float = 4.0) -> trimesh.Trimesh:
    """A square plane in ``y = 0`` (normals ``+y``) of 3 x 3 cells, the middle one left out."""
    n = 3
    g = np.linspace(-size / 2, size / 2, n + 1)
    v = np.array([[x, 0.0, z] for z in g for x in g])
    faces = []
    for j in range(n):
        for i in range(n):
            if (i, j) != (1, 1):
                a, b, c, d = j * (n + 1) + i, j * (n + 1) + i + 1, (j + 1) * (n + 1) + i, (j + 1) * (n + 1) + i + 1
                faces += [[a, c, b], [b, c, d]]
    return trimesh.Trimesh(v, np.array(faces), process=False)


def _with(pre, **options) -> Interreflection:
    """``pre`` with other run-time options (a new pipeline over the same data)."""
    return Interreflection(pre.scene, dataclasses.replace(pre.options, **options), pre.data)


def test_near_takes_points_on_the_plane_inside_its_footprint_away_from_its_boundary():
    """A 4 m plane placed turned, scaled and moved: points within ``NEAR_RATIO d`` of its plane and inside take
    the side they are on (in the plane: its normals' side); outside the footprint, farther from the plane or close
    to its boundary they do not."""
    mesh = builtin_mesh("plane", size=[4.0, 4.0], resolution=[4, 4])
    assert np.allclose(mesh.vertex_normals, [0.0, 1.0, 0.0])
    flat = FlatOccluder(mesh.vertices, mesh.faces, mesh.vertex_normals)
    pose = Transform(translate=np.array([0.3, -1.0, 2.0]), rotate_deg=np.array([20.0, 35.0, -10.0]), scale=1.5)
    up = pose.rotation @ np.array([0.0, 1.0, 0.0])
    local = np.array([[0.5, 1e-6, 0.2], [0.5, -1e-6, 0.2], [0.5, 0.0, 0.2],  # above, below, in the plane
                      [0.5, 0.1, 0.2],  # farther than NEAR_RATIO d (d = 1.5)
                      [2.5, 1e-6, 0.0],  # outside the footprint
                      [1.9999, 1e-3, 0.0],  # inside, but d = 1e-4 < |h| / NEAR_RATIO
                      [1.9, 1e-5, 0.0]])  # d = 0.1: taken
    rows, axes = flat.near(pose.apply_points(local), pose)
    assert rows.tolist() == [0, 1, 2, 6]
    np.testing.assert_allclose(axes, [up, -up, up, up], atol=1e-12)
    assert 0.1 > NEAR_RATIO * 1.5 and 1e-3 > NEAR_RATIO * 1e-4 and 1e-5 < NEAR_RATIO * 0.1  # as they claim


def test_near_leaves_a_hole_out():
    ring = _ring()
    flat = FlatOccluder(ring.vertices, ring.faces, np.tile([0.0, 1.0, 0.0], (len(ring.vertices), 1)))
    rows, _ = flat.near(np.array([[0.0, 1e-7, 0.0], [2.5, 1e-7, 0.0], [0.0, 1e-7, 1.3]]), Transform())
    assert rows.tolist() == [2]  # the hole's centre and a point outside are not taken


def box_on_floor_scene(light: dict, transform: dict | None = None) -> Scene:
    """A 0.6 box resting on a 4 x 4 floor (``transform`` its pose, default moved to ``(0.3, 0.3, 0)``) under
    ``light``."""
    return Scene.from_dict({
        "objects": [
            {"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [8, 8]},
             "material": {"type": "diffuse", "albedo": [0.6, 0.6, 0.6]}},
            {"name": "box", "mesh": {"builtin": "box", "size": [0.6, 0.6, 0.6], "subdivisions": 1},
             "transform": transform or {"translate": [0.3, 0.3, 0.0]}, "dynamic": True,
             "material": {"type": "diffuse", "albedo": [0.8, 0.5, 0.3]}},
        ],
        "lights": [light],
    })


@pytest.fixture(scope="module")
def box_on_floor():
    scene = box_on_floor_scene({"type": "environment", "sky": {"sun_elevation_deg": 30, "sun_azimuth_deg": 40,
                                                               "turbidity": 3, "height": 32, "width": 64}})
    return Interreflection.precompute(scene, SMALL, cache=False, progress=False)


@pytest.mark.parametrize("occlusion", ["product", "exp"])
def test_the_occlusion_rows_are_the_halfspace_on_the_plane_and_the_field_elsewhere(box_on_floor, occlusion):
    """``_occlusion``: the floor's rows at the box's points on it are the half-space (its SH log with
    ``occlusion="exp"``, whose ``exp*`` is ``floor + (1 - floor) V``), every other row the field's lookup bit for
    bit; with ``flat_visibility="field"`` every row is the lookup."""
    from prtlab.shadowfields import LOG_FLOOR

    out = {}
    for mode in ("plane", "field"):
        pre = _with(box_on_floor, flat_visibility=mode, occlusion=occlusion)
        state = FrameState.from_scene(pre.scene)
        geo = pre._frame_geometry(state)
        out[mode] = (pre._occlusion(geo)["box"]["floor"].copy(), geo)
    geo = out["field"][1]
    lookup = _with(box_on_floor, occlusion=occlusion).occluders["floor"].lookup(geo["box"]["x"],
                                                                                      geo["floor"]["T"])
    np.testing.assert_array_equal(out["field"][0], lookup)
    x = geo["box"]["x"]
    on = np.flatnonzero(x[:, 1] < 0.01)  # the bottom face and the sides' bottom row
    assert len(on) >= 16
    taken = np.flatnonzero(np.any(out["plane"][0] != lookup, axis=1))
    assert taken.tolist() == on.tolist()
    want = halfspace_visibility(np.tile([0.0, 1.0, 0.0], (len(on), 1)), 4,
                                LOG_FLOOR if occlusion == "exp" else None)
    np.testing.assert_allclose(out["plane"][0][on], want, atol=1e-12)
    if occlusion == "exp":
        up = sh.zh_rotate(halfspace_zh(4), np.array([0.0, 1.0, 0.0]))
        one = np.zeros(16)
        one[0] = math.sqrt(4 * math.pi)
        np.testing.assert_allclose(sh.exp(want[:1], channels=False, method="exact")[0],
                                   LOG_FLOOR * one + (1 - LOG_FLOOR) * up, atol=1e-5)


def test_a_face_standing_on_the_floor_gets_the_order_n_light_of_the_halfspace(box_on_floor):
    """The direct light of the box's sides' bottom row (only the floor occludes them) is
    ``albedo sum_k h_k (P_n(P_n(V_self H) G_k) . L)`` with ``H`` the half-space above the floor
    (:func:`halfspace_zh`) and ``L`` the environment's SH: the order-n SH light, no field between (the bands
    above it, ``horizon_sky``: ``test_horizon.py``)."""
    pre = _with(box_on_floor, flat_visibility="plane", horizon_sky=False)
    state = FrameState.from_scene(pre.scene)
    result = pre.shade(state, bounces=0)
    geo = pre._frame_geometry(state)
    g = geo["box"]
    rows = np.flatnonzero((g["x"][:, 1] < 0.01) & (np.abs(g["n"][:, 1]) < 0.1))
    assert len(rows) >= 8
    half = halfspace_visibility(np.tile([0.0, 1.0, 0.0], (len(rows), 1)), 4)
    vis = sh.product(g["self"][rows], half, 4, channels=False)
    transfer = sh.product(np.broadcast_to(vis[:, None], g["g_cos"][rows].shape), g["g_cos"][rows], 4,
                          channels=False)
    light = environment_sh(pre.scene.environment, 4)  # (16, 3)
    sep = pre.seps["box"]
    want = np.einsum("vk,vkc,kc->vc", g["h"][rows], transfer @ light, np.asarray(sep.colour).reshape(sep.K, -1))
    np.testing.assert_allclose(result.direct["box"][rows], want, rtol=1e-9)
    field = _with(box_on_floor, flat_visibility="field").shade(state, bounces=0).direct["box"][rows]
    assert field.sum() < 0.8 * want.sum()  # the field, interpolated across the plane, hides more


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), ring=st.booleans())
def test_the_kernel_takes_the_points_the_reference_tier_takes(seed, ring):
    """:meth:`FlatOccluder.taken`'s kernel against its numpy tier: random points over and around a plane (with a
    hole or not), heights from 0 to beyond the band, some on the grid's lines and vertices."""
    mesh = _ring() if ring else builtin_mesh("plane", size=[4.0, 4.0], resolution=[3, 3])
    flat = FlatOccluder(mesh.vertices, mesh.faces, np.tile([0.0, 1.0, 0.0], (len(mesh.vertices), 1)))
    rng = np.random.default_rng(seed)
    p = rng.uniform(-2.5, 2.5, (400, 2))
    p[::7] = np.round(p[::7] * 3 / 4) * 4 / 3  # on the grid's vertices and lines
    h = rng.choice([0.0, 1e-9, 1e-4, 1e-2, 0.1]) * rng.uniform(-1.0, 1.0, 400)
    h[:50] = 0.0  # in the plane: taken wherever inside and off the boundary
    got = flat.taken(p, h)
    np.testing.assert_array_equal(got, flat.taken(p, h, method="reference"))
    assert np.any(got[:50])
