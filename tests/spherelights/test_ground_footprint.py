"""Tests of the ground texture under an object's footprint (prtlab.spherelights._ground: covered_texels,
fill_covered): the covered ground is never seen, and a receiver at the foot of an object's wall must read the light
just outside the footprint, not the dark texels under the object."""

import numpy as np
import pytest

import prtlab
from prtlab.scene import Scene
from prtlab.spherelights._ground import covered_texels, fill_covered, ground_light

K = 64
RECT = np.array([0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 2.0])  # a 4 x 4 ground at y = 0, edges along x and z


def _texel_centres(k=K):
    a = -1.0 + (np.arange(k) + 0.5) * (2.0 / k)
    return np.meshgrid(2.0 * a, 2.0 * a, indexing="ij")  # x, z of the centres (RECT's half edges are 2)


def _box_mesh(lo, hi):
    """A closed, outward-oriented box (12 triangles)."""
    import trimesh

    box = trimesh.creation.box(extents=np.subtract(hi, lo))
    return np.asarray(box.vertices) + 0.5 * (np.asarray(lo) + np.asarray(hi)), np.asarray(box.faces)


# --- known answers ------------------------------------------------------------------------------------------------

def test_covered_texels_are_the_footprint_of_a_resting_box():
    x, z = _texel_centres()
    lo, hi = (0.0, 0.0, -0.3), (0.6, 0.6, 0.3)
    got = covered_texels(RECT, K, [_box_mesh(lo, hi)])
    want = (x > 0) & (x < 0.6) & (z > -0.3) & (z < 0.3)
    np.testing.assert_array_equal(got, want)
    sunk = covered_texels(RECT, K, [_box_mesh((0.0, -0.2, -0.3), (0.6, 0.4, 0.3))])
    np.testing.assert_array_equal(sunk, want)


def test_nothing_is_covered_by_a_lifted_object_or_a_ball_touching_at_a_point():
    assert not covered_texels(RECT, K, [_box_mesh((0.0, 0.01, -0.3), (0.6, 0.61, 0.3))]).any()
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    assert not covered_texels(RECT, K, [(np.asarray(ball.vertices) + [0.03, 0.5, 0.03], ball.faces)]).any()
    assert not covered_texels(RECT, K, []).any()


def test_fill_keeps_uncovered_texels_and_carries_the_edge_inward():
    rng = np.random.default_rng(3)
    tex = rng.uniform(size=(8, 8, 3))
    covered = np.zeros((8, 8), dtype=bool)
    covered[2:6, 3:7] = True
    out = fill_covered(np.where(covered[..., None], 0.0, tex), covered)
    np.testing.assert_array_equal(out[~covered], tex[~covered])  # bit for bit
    # a covered texel of the first ring: the mean of its uncovered 8-neighbours
    nb = [(1, 2), (1, 3), (1, 4), (2, 2), (3, 2)]
    np.testing.assert_allclose(out[2, 3], np.mean([tex[i, j] for i, j in nb], axis=0), rtol=1e-15)
    const = fill_covered(np.where(covered[..., None], 0.0, 0.7), covered)
    np.testing.assert_allclose(const, 0.7, rtol=1e-15)


def test_fill_degenerate_masks():
    tex = np.arange(2 * 3 * 3, dtype=np.float64).reshape(2, 3, 3)
    np.testing.assert_array_equal(fill_covered(tex, np.ones((2, 3), dtype=bool)), tex)  # all covered: unchanged
    np.testing.assert_array_equal(fill_covered(tex, np.zeros((2, 3), dtype=bool)), tex)
    assert fill_covered(np.zeros((0, 0, 3)), np.zeros((0, 0), dtype=bool)).shape == (0, 0, 3)


def test_fill_rejects_a_mask_of_another_shape():
    with pytest.raises(ValueError, match="covered must have shape"):
        fill_covered(np.zeros((4, 4, 3)), np.zeros((4, 5), dtype=bool))


def test_a_receiver_at_the_foot_of_a_wall_reads_the_ground_outside_the_footprint():
    """Unit exit radiance around a box's footprint (0 under it, as its rays give there): a receiver at the foot of
    the box's wall, facing away from it, sees ground of radiance 1 over the lower half of its hemisphere, ``pi / 2``.
    The texture as shaded reads the covered texels across the wall (the wall at x = 0 lies on a texel edge: about
    half); filled, it reads the outside."""
    x, z = _texel_centres()
    covered = covered_texels(RECT, K, [_box_mesh((0.0, 0.0, -0.3), (0.6, 0.6, 0.3))])
    shaded = np.where(covered[..., None], 0.0, np.ones((K, K, 3)))
    p, n = np.array([[-1e-4, 1e-4, 0.05]]), np.array([[-1.0, 0.0, 0.0]])
    _, as_shaded = ground_light(p, n, RECT[None], shaded[None], np.zeros((16, 3)))
    _, filled = ground_light(p, n, RECT[None], fill_covered(shaded, covered)[None], np.zeros((16, 3)))
    np.testing.assert_allclose(filled[0], np.pi / 2, rtol=5e-3)  # the rule's error at the wall (0.3 %)
    assert as_shaded[0, 0] < 0.6 * np.pi / 2


# --- whole pipeline -----------------------------------------------------------------------------------------------

def _box_scene(shift):
    return Scene.from_dict({"objects": [
        {"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [2, 2]},
         "material": {"type": "diffuse", "albedo": [0.5] * 3}},
        {"name": "box", "mesh": {"builtin": "box", "size": [0.6, 0.6, 0.6]},
         "transform": {"translate": [0.3 + shift, 0.3, 0.3 + shift]},
         "material": {"type": "diffuse", "albedo": [0.5] * 3}}],
        "lights": [{"type": "environment", "constant": [1, 1, 1]}]})


def test_contact_light_does_not_depend_on_the_texel_grid():
    """A box resting on the ground under a constant sky, moved by 0, 1/4 and 1/2 of a texel (64 texels over 4 m):
    the indirect light of its side corners on the ground (the ground at the wall's foot reflected) stays within
    10 % of its mean; the ground's texels under the box (dark) must not leak into the lookup beside it (without the
    fill of ``_ground_textures`` the corners' indirect light was 0.020-0.074 over the shifts; with it 0.083-0.093)."""
    values = []
    for shift in (0.0, 0.015625, 0.03125):
        sc = _box_scene(shift)
        r = prtlab.shade(sc, method="spherelights", cache=False, progress=False, n_spheres=2, fit_resolution=12)
        box = sc.object("box")
        foot = (box.world_vertices()[:, 1] < 1e-9) & (np.abs(box.world_normals()[:, 1]) < 0.1)
        values.append(r.indirect["box"][foot, 0])
    values = np.concatenate(values)
    assert np.abs(values / values.mean() - 1).max() < 0.10, values


@pytest.mark.parametrize("seed", range(4))
def test_winding_kernel_matches_the_numpy_tier(seed):
    """``_winding_numbers``' kernel against its numpy tier (the specification) at random points around a turned,
    shifted icosphere and a box, and at points on the box's faces (in a face's plane: +pi, so 1 on the surface):
    within rounding, and 1 / 0 well inside / outside."""
    import trimesh

    from prtlab.spherelights._ground import _winding_numbers

    rng = np.random.default_rng(seed)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    meshes = [(np.asarray(ball.vertices) @ np.linalg.qr(rng.normal(size=(3, 3)))[0] + rng.normal(size=3) * 0.1,
               np.asarray(ball.faces)), _box_mesh([-0.3, 0.0, -0.2], [0.4, 0.5, 0.6])]
    for v, f in meshes:
        pts = rng.uniform(-1.2, 1.2, size=(300, 3))
        fast, ref = _winding_numbers(pts, v, f), _winding_numbers(pts, v, f, method="reference")
        np.testing.assert_allclose(fast, ref, rtol=0, atol=1e-12)
        assert np.all((np.abs(fast) < 1e-9) | (np.abs(fast - 1.0) < 1e-9))  # closed: 0 or 1 off the surface
        assert 0 < np.count_nonzero(fast > 0.5) < len(pts)
    v, f = meshes[1]
    on_face = np.column_stack([rng.uniform(-0.29, 0.39, 50), rng.uniform(0.01, 0.49, 50), np.full(50, 0.6)])
    for method in ("numba", "reference"):
        np.testing.assert_allclose(_winding_numbers(on_face, v, f, method=method), 1.0, atol=1e-9)


def test_covered_vertices_take_their_known_neighbours_light():
    """``covered_points`` marks the points inside (and on) a box; ``fill_covered_vertices`` gives a covered vertex
    the mean of its known neighbours, ring by ring (a chain 0-1-2-3 with 2 and 3 covered: 2 takes 1's value, then 3
    takes 2's), leaves the others bit for bit, and a vertex with no known neighbour as it is."""
    from prtlab.spherelights._ground import covered_points, fill_covered_vertices

    v, f = _box_mesh([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
    pts = np.array([[0.5, 1e-6, 0.5], [1.5, 1e-6, 0.5], [1.0, 1e-6, 0.5], [-0.2, 1e-6, 0.3]])
    np.testing.assert_array_equal(covered_points(pts, v, f), [True, False, True, False])
    values = np.array([[1.0, 2.0], [3.0, 4.0], [0.0, 0.0], [0.0, 0.0], [7.0, 7.0]])
    edges = np.array([[0, 1], [1, 2], [2, 3]])
    out = fill_covered_vertices(values, edges, np.array([False, False, True, True, True]))
    np.testing.assert_array_equal(out, [[1.0, 2.0], [3.0, 4.0], [3.0, 4.0], [3.0, 4.0], [7.0, 7.0]])
    two = fill_covered_vertices(values, np.array([[0, 2], [1, 2]]), np.array([False, False, True, False, False]))
    np.testing.assert_array_equal(two[2], [2.0, 3.0])
