"""Tests of prtlab.geometry._raycast: Embree ray casting against float64 brute force."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from prtlab.geometry import RAY_EPSILON_SCALE, RayCaster, offset_origins
from prtlab.scene import Material, Scene, SceneObject, Transform
from tests.conftest import random_directions


METHODS = pytest.mark.parametrize("method", ["embree", "embreex", "numpy"])


# ------------------------------------------------------------------ known answers


@METHODS
def test_box_distance_and_normal(method):
    caster = RayCaster([trimesh.creation.box()])
    hits = caster.closest_hit([[0.0, 0.0, 5.0], [0.0, 0.0, -5.0]], [[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]], method=method)
    np.testing.assert_allclose(hits.distance, [4.5, 4.5], atol=1e-6)
    np.testing.assert_allclose(hits.normal, [[0, 0, 1], [0, 0, -1]], atol=1e-12)
    np.testing.assert_allclose(hits.point[:, 2], [0.5, -0.5], atol=1e-12)
    assert hits.hit.all() and (hits.object == 0).all()


@METHODS
def test_miss_fields(method):
    caster = RayCaster([trimesh.creation.box()])
    hits = caster.closest_hit([0.0, 5.0, 0.0], [0.0, 1.0, 0.0], method=method)
    assert hits.hit.shape == () and not hits.hit
    assert hits.object == -1 and hits.triangle == -1 and np.isinf(hits.distance)
    assert np.isnan(hits.point).all() and (hits.normal == 0).all()


@METHODS
def test_object_index_and_transforms(method):
    box = trimesh.creation.box()
    move = Transform(translate=np.array([5.0, 0.0, 0.0]))
    caster = RayCaster([box, box], [None, move])
    hits = caster.closest_hit([[-5.0, 0, 0], [10.0, 0, 0]], [[1.0, 0, 0], [-1.0, 0, 0]], method=method)
    np.testing.assert_array_equal(hits.object, [0, 1])
    np.testing.assert_allclose(hits.distance, [4.5, 4.5], atol=1e-6)


def test_hit_point_from_barycentrics_matches_ray(rng):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    caster = RayCaster([mesh])
    origins = 3.0 * random_directions(rng, 200)
    dirs = random_directions(rng, 200) * 0.3 - origins / 3.0
    hits = caster.closest_hit(origins, dirs)
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    along = origins + hits.distance[:, None] * unit
    np.testing.assert_allclose(hits.point[hits.hit], along[hits.hit], atol=1e-5)
    np.testing.assert_allclose(hits.normal[hits.hit], mesh.face_normals[hits.triangle[hits.hit]], atol=1e-12)


@METHODS
def test_tmax_limits_both_queries(method):
    caster = RayCaster([trimesh.creation.box()])
    o, d = [0.0, 0.0, 5.0], [0.0, 0.0, -1.0]
    assert not caster.closest_hit(o, d, tmax=4.4, method=method).hit
    assert caster.closest_hit(o, d, tmax=4.6, method=method).hit
    assert not caster.occluded(o, d, 4.4, method=method)
    assert caster.occluded(o, d, 4.6, method=method)
    np.testing.assert_array_equal(caster.occluded([o, o], [d, d], tmax=[4.4, 4.6], method=method), [False, True])
    assert not caster.occluded(o, d, 0.0, method=method)


@METHODS
def test_offset_prevents_self_intersection(rng, method):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    caster = RayCaster([mesh])
    p, n = mesh.vertices, mesh.vertex_normals
    out = n + 0.5 * random_directions(rng, len(n))
    out[np.sum(out * n, axis=1) < 1e-3] = n[np.sum(out * n, axis=1) < 1e-3]
    assert not caster.occluded(p, out, normals=n, method=method).any()
    # rays into the sphere from its surface reach the far side: chord = 2 cos
    inward = -n + 0.3 * random_directions(rng, len(n))
    hits = caster.closest_hit(p, inward, normals=n, method=method)
    cos = -np.sum(inward * n, axis=1) / np.linalg.norm(inward, axis=1)
    assert hits.hit.all()
    np.testing.assert_allclose(hits.distance, 2 * cos * 0.99, rtol=0.03)


@METHODS
def test_surfaces_right_next_to_the_origin_are_never_skipped(method):
    # Rays leaving a path vertex near an edge meet the neighbouring surface within a few
    # float32 ulps; skipping such hits (a positive tnear) leaks light through room corners.
    wall = (np.array([[0, 0, -1], [0, 2, -1], [0, 2, 1], [0, 0, 1.0]]), np.array([[0, 1, 2], [0, 2, 3]]))
    caster = RayCaster([wall])
    assert caster.tnear == 0.0
    o = np.array([[1e-6, 0.5, 0.2], [1e-6, 0.5, 0.2]])
    d = np.array([[-1.0, 0.3, 0.1], [1.0, 0.3, 0.1]])
    np.testing.assert_array_equal(caster.occluded(o, d, method=method), [True, False])
    np.testing.assert_array_equal(caster.closest_hit(o, d, method=method).hit, [True, False])
    # a ray from just in front hits it at the right distance
    hits = caster.closest_hit([[0.5, 0.5, 0.2]], [[-1.0, 0.0, 0.0]], method=method)
    assert hits.hit[0] and hits.distance[0] == pytest.approx(0.5, abs=1e-6)


def test_epsilon_scales_with_scene():
    caster = RayCaster([trimesh.creation.box(extents=[2.0, 2.0, 2.0])])
    assert caster.epsilon == pytest.approx(RAY_EPSILON_SCALE * 2.0 * np.sqrt(3.0))
    assert RayCaster([trimesh.creation.box()], epsilon=0.25).epsilon == 0.25


def test_offset_origins_side():
    o = offset_origins([0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], 0.1)
    np.testing.assert_allclose(o, [[0, 0.1, 0], [0, -0.1, 0]])


def test_update_transforms_rebuilds_only_on_change():
    box = trimesh.creation.box()
    caster = RayCaster([box, box], [None, Transform(translate=np.array([5.0, 0, 0]))])
    assert caster.n_builds == 1
    assert not caster.update_transforms([None, Transform(translate=np.array([5.0, 0, 0]))])
    assert caster.n_builds == 1
    assert caster.update_transforms({1: Transform(translate=np.array([0.0, 5.0, 0]))})
    assert caster.n_builds == 2
    hits = caster.closest_hit([0.0, 10.0, 0.0], [0.0, -1.0, 0.0])
    assert hits.object == 1 and hits.distance == pytest.approx(4.5, abs=1e-6)


def test_moved_copy_equals_a_fresh_caster(rng):
    """A caster moved by ``moved`` (unmoved objects keep their posed arrays) has the world vertices, face normals,
    bounds, sphere, offsets and hits of a caster built at the new poses, bit for bit, after one build; the original
    keeps its poses; with no pose changed it shares the original's scene."""
    meshes = [trimesh.creation.icosphere(2), trimesh.creation.box(), trimesh.creation.cylinder(0.5, 2.0)]
    before = [Transform(translate=np.array([0.0, 0, 0])), Transform(translate=np.array([3.0, 0, 0])),
              Transform(translate=np.array([0.0, 2.5, 0]), rotate_deg=np.array([30.0, 0, 10.0]))]
    after = [before[0], Transform(translate=np.array([2.5, 0.3, 0]), rotate_deg=np.array([0.0, 45.0, 0])), before[2]]
    caster = RayCaster(meshes, before)
    moved = caster.moved(after)
    assert moved.n_builds == caster.n_builds + 1
    fresh = RayCaster(meshes, after)
    assert moved.world_vertices(0) is caster.world_vertices(0) and moved.world_vertices(1) is not caster.world_vertices(1)
    for i in range(3):
        np.testing.assert_array_equal(moved.world_vertices(i), fresh.world_vertices(i))
        np.testing.assert_array_equal(moved.face_normals(i), fresh.face_normals(i))
    np.testing.assert_array_equal(moved.bounds, fresh.bounds)
    for a, b in zip(moved.may_hit_bounds(), fresh.may_hit_bounds()):
        np.testing.assert_array_equal(a, b)
    assert (moved.epsilon, moved.tnear) == (fresh.epsilon, fresh.tnear)
    origins, dirs = rng.normal(size=(500, 3)) * 4.0, random_directions(rng, 500)
    got, want = moved.closest_hit(origins, dirs), fresh.closest_hit(origins, dirs)
    assert got.hit.any()
    for name in ("hit", "object", "triangle", "distance", "barycentric"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    np.testing.assert_array_equal(caster.world_vertices(1), RayCaster(meshes, before).world_vertices(1))
    same = caster.moved(before)
    assert same._scene is caster._scene and same.n_builds == caster.n_builds


def test_scene_input_skips_portals():
    objs = [
        SceneObject("floor", trimesh.creation.box(), Transform(), Material()),
        SceneObject("window", trimesh.creation.box(), Transform(translate=np.array([5.0, 0, 0])), portal=True),
    ]
    caster = RayCaster(Scene(objects=objs))
    assert caster.n_objects == 1 and caster.object_index == [0]
    assert not caster.occluded([3.0, 0, 0], [1.0, 0, 0])


def test_empty_mesh_keeps_object_ids():
    empty = (np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    caster = RayCaster([empty, trimesh.creation.box()])
    assert caster.closest_hit([0.0, 0, 5], [0.0, 0, -1]).object == 1


def test_empty_batch_shapes():
    caster = RayCaster([trimesh.creation.box()])
    hits = caster.closest_hit(np.zeros((0, 3)), np.zeros((0, 3)))
    assert hits.hit.shape == (0,) and hits.point.shape == (0, 3) and hits.barycentric.shape == (0, 2)
    assert caster.occluded(np.zeros((2, 0, 3)), np.ones((2, 0, 3))).shape == (2, 0)


# -------------------------------------------------- float64 brute-force reference


@given(seed=st.integers(0, 2**31 - 1))
def test_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    mesh = trimesh.creation.icosphere(subdivisions=1)
    mesh.vertices *= rng.uniform(0.5, 1.5, size=3)
    box = trimesh.creation.box(extents=rng.uniform(0.2, 0.8, size=3))
    box.apply_translation(rng.normal(size=3) * 1.5)
    caster = RayCaster([mesh, box], [None, Transform(rotate_deg=rng.uniform(0, 90, 3))])
    origins = rng.normal(size=(40, 3)) * 3.0
    dirs = random_directions(rng, 40)
    dirs[:20] = -origins[:20] + 0.3 * rng.normal(size=(20, 3))  # aim most rays at the scene
    tmax = np.where(rng.random(40) < 0.3, rng.uniform(1, 5, 40), np.inf)
    hits = caster.closest_hit(origins, dirs, tmax)
    ref = caster.closest_hit(origins, dirs, tmax, method="numpy")
    # float32 traversal: edge-grazing rays may differ; everything else must agree
    agree = ref.hit == hits.hit
    assert agree.mean() >= 0.95
    both = hits.hit & ref.hit
    assert both.sum() >= 0.9 * ref.hit.sum()
    np.testing.assert_allclose(hits.distance[both], ref.distance[both], rtol=1e-5, atol=1e-5)
    same = both & (hits.triangle == ref.triangle) & (hits.object == ref.object)
    assert same.sum() >= 0.9 * both.sum()
    np.testing.assert_allclose(hits.barycentric[same], ref.barycentric[same], atol=1e-4)
    # points are rebuilt from the barycentrics, so they carry the barycentric error times an edge
    longest_edge = max(mesh.edges_unique_length.max(), box.edges_unique_length.max())
    np.testing.assert_allclose(hits.point[same], ref.point[same], atol=2e-4 * longest_edge)
    np.testing.assert_array_equal(hits.normal[same], ref.normal[same])
    occ = caster.occluded(origins, dirs, tmax)
    assert np.mean(occ == caster.occluded(origins, dirs, tmax, method="numpy")) >= 0.95
    assert (occ == hits.hit).all()


@given(seed=st.integers(0, 2**31 - 1))
def test_a_ray_that_may_not_hit_hits_nothing(seed):
    """``may_hit`` is False only for rays that miss the geometry's bounding sphere: no such ray hits (with or
    without the origin offset of ``normals=``), and rays grazing the sphere are kept."""
    rng = np.random.default_rng(seed)
    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.vertices *= rng.uniform(0.5, 1.5, size=3)
    caster = RayCaster([mesh], [Transform(translate=rng.normal(size=3), rotate_deg=rng.uniform(0, 90, 3))])
    origins = rng.normal(size=(30, 3)) * 2.5
    dirs = random_directions(rng, 200)
    may = caster.may_hit(origins, dirs)
    assert may.shape == (30, 200) and 0 < may.mean() < 1
    hits = caster.closest_hit(origins[:, None], dirs[None])
    assert not np.any(hits.hit & ~may)
    normals = random_directions(rng, 30)
    assert not np.any(caster.occluded(origins[:, None], dirs[None], normals=normals[:, None]) & ~may)
    # from outside: a ray at the centre is kept, one just past the bounding sphere's tangent is not
    centre, radius = caster._sphere
    o = centre + np.array([0.0, 0.0, -3.0 * radius])
    alpha = np.arcsin(1.0 / 3.0)  # the tangent's angle from the direction to the centre
    at_centre, outward = np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])
    beyond = np.array([np.sin(1.01 * alpha), 0.0, np.cos(1.01 * alpha)])
    np.testing.assert_array_equal(caster.may_hit(o[None], np.stack([at_centre, beyond, outward])),
                                  [[True, False, False]])
    assert caster.may_hit(centre[None], outward[None]).all()  # inside the sphere and the box: every ray


def test_rays_leaving_a_flat_objects_side_may_not_hit_it():
    """A floor's bounding box is a thin slab: from above it, only rays going down may hit it."""
    floor = trimesh.Trimesh([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], [[0, 2, 1], [0, 3, 2]])
    caster = RayCaster([floor])
    dirs = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.6, -0.8, 0.0], [0.6, 0.8, 0.0]])
    np.testing.assert_array_equal(caster.may_hit(np.array([[0.0, 0.5, 0.0]]), dirs),
                                  [[False, True, False, True, False]])


# ------------------------------------------------------------------------- errors


def test_errors():
    caster = RayCaster([trimesh.creation.box()])
    with pytest.raises(ValueError, match=r"origins must be a \(\.\.\., 3\) array"):
        caster.closest_hit(np.zeros((4, 2)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="origins or dirs contain NaN"):
        caster.closest_hit(np.zeros(3), [np.nan, 0.0, 1.0])
    with pytest.raises(ValueError, match="zero vectors"):
        caster.occluded(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="do not broadcast"):
        caster.closest_hit(np.zeros((4, 3)), np.ones((5, 3)))
    with pytest.raises(ValueError, match="tmax contains NaN"):
        caster.occluded(np.zeros(3), np.ones(3), np.nan)
    with pytest.raises(ValueError, match="tmax of shape"):
        caster.occluded(np.zeros((3, 3)), np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match=r"normals must be a \(\.\.\., 3\)"):
        caster.occluded(np.zeros(3), np.ones(3), normals=np.ones(2))
    with pytest.raises(ValueError, match="normals .* do not broadcast"):
        caster.occluded(np.zeros((3, 3)), np.ones(3), normals=np.ones((4, 3)))
    with pytest.raises(ValueError, match="transforms has 2 entries for 1 meshes"):
        RayCaster([trimesh.creation.box()], [None, None])
    with pytest.raises(ValueError, match="transforms has 2 entries for 1 objects"):
        caster.update_transforms([None, None])
    with pytest.raises(ValueError, match=r"object index 3 is out of range"):
        caster.update_transforms({3: np.eye(4)})
    with pytest.raises(ValueError, match=r"a transform must be a prtlab Transform or a \(4, 4\)"):
        RayCaster([trimesh.creation.box()], [np.eye(3)])
    with pytest.raises(ValueError, match="a transform contains NaN"):
        RayCaster([trimesh.creation.box()], [np.full((4, 4), np.nan)])
    with pytest.raises(TypeError, match=r"meshes\[0\] must be a trimesh.Trimesh"):
        RayCaster(["box"])
    with pytest.raises(ValueError, match=r"meshes\[0\] vertices must be"):
        RayCaster([(np.zeros((3, 2)), np.zeros((1, 3), dtype=int))])
    with pytest.raises(ValueError, match=r"meshes\[0\] faces must be an integer"):
        RayCaster([(np.zeros((3, 3)), np.zeros((1, 3)))])
    with pytest.raises(ValueError, match=r"meshes\[0\] vertices contain NaN"):
        RayCaster([(np.full((3, 3), np.nan), np.zeros((1, 3), dtype=int))])
    with pytest.raises(ValueError, match=r"meshes\[0\] faces index vertices outside"):
        RayCaster([(np.zeros((3, 3)), np.full((1, 3), 7))])
    with pytest.raises(ValueError, match="method must be one of"):
        caster.closest_hit(np.zeros(3), np.ones(3), method="optix")
    with pytest.raises(ValueError, match="normals contain NaN"):
        caster.occluded(np.zeros(3), np.ones(3), normals=[np.nan, 0.0, 1.0])
    with pytest.raises(ValueError, match="origins or dirs contain NaN"):
        caster.occluded([np.inf, 0.0, 0.0], np.ones(3), method="numpy")
    with pytest.raises(ValueError, match="zero vectors"):
        caster.closest_hit(np.zeros(3), np.zeros(3), method="numpy")
    with pytest.raises(ValueError, match="normals contain NaN"):
        caster.occluded(np.zeros(3), np.ones(3), normals=[np.nan, 0.0, 1.0], method="numpy")
    with pytest.raises(ValueError, match="epsilon must be a finite number"):
        RayCaster([trimesh.creation.box()], epsilon=-1.0)


def test_caster_survives_pickling_for_distributed_workers(rng):
    import pickle

    caster = RayCaster([trimesh.creation.icosphere(subdivisions=2)])
    clone = pickle.loads(pickle.dumps(caster))
    o = random_directions(rng, 64) * 3.0
    d = -o / 3.0
    a, b = caster.closest_hit(o, d), clone.closest_hit(o, d)
    np.testing.assert_array_equal(a.triangle, b.triangle)
    np.testing.assert_array_equal(a.distance, b.distance)
    assert clone.n_builds == caster.n_builds
