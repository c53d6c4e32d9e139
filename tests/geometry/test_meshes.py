"""Built-in meshes, committed assets, loading, subdivision, Cornell box and room."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from prtlab.geometry import (
    BUILTIN_MESHES,
    CORNELL_BOX_PARTS,
    DATA_DIR,
    builtin_mesh,
    cornell_box_light,
    cornell_box_objects,
    load_mesh,
    normalize_mesh,
    room_with_windows,
    subdivide,
    window_quad,
)

SINGLE_MESH_BUILTINS = sorted(set(BUILTIN_MESHES) - {"cornell_box"})
CLOSED_BUILTINS = ["box", "icosphere", "uv_sphere", "torus", "cylinder", "bunny"]


def boundary_edges(mesh: trimesh.Trimesh) -> np.ndarray:
    """(n, 2) sorted vertex pairs of edges used by exactly one face."""
    return mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]


def assert_normalised(mesh: trimesh.Trimesh) -> None:
    lo, hi = mesh.bounds
    assert lo[1] == 0.0
    assert hi[1] == pytest.approx(1.0, abs=1e-12)
    assert lo[0] + hi[0] == pytest.approx(0.0, abs=1e-12)
    assert lo[2] + hi[2] == pytest.approx(0.0, abs=1e-12)


# --------------------------------------------------------------------------- every builtin


@pytest.mark.parametrize("name", SINGLE_MESH_BUILTINS)
def test_builtin_builds_with_defaults(name):
    mesh = builtin_mesh(name)
    assert isinstance(mesh, trimesh.Trimesh)
    assert len(mesh.faces) > 0
    assert mesh.vertices.dtype == np.float64
    assert np.all(np.isfinite(mesh.vertices))
    assert mesh.is_winding_consistent
    assert np.all(mesh.area_faces > 0.0), "no degenerate triangles"
    # every vertex is used, so every vertex has a shading normal
    assert len(np.unique(mesh.faces)) == len(mesh.vertices)


@pytest.mark.parametrize(
    "name, params",
    [
        ("box", {"size": [1, 2, 3]}),
        ("box", {"size": [1, 2, 3], "subdivisions": 2}),
        ("icosphere", {"radius": 0.5, "subdivisions": 2}),
        ("uv_sphere", {"radius": 2.0, "count": [8, 12]}),
        ("torus", {"major_radius": 2.0, "minor_radius": 0.5, "sections": [24, 12]}),
        ("cylinder", {"radius": 0.3, "height": 2.0, "sections": 12}),
        ("bunny", {}),
        ("bunny", {"subdivisions": 1}),
    ],
)
def test_closed_builtins_are_watertight_with_outward_normals(name, params):
    mesh = builtin_mesh(name, **params)
    welded = mesh.copy()
    welded.merge_vertices()  # box and cylinder split vertices at sharp edges on purpose
    assert welded.is_watertight
    assert mesh.is_winding_consistent
    assert mesh.volume > 0.0  # positive signed volume: normals point out


@pytest.mark.parametrize("name", ["box", "cylinder"])
def test_sharp_edges_keep_flat_vertex_normals(name):
    # sides do not share vertices, so every vertex normal is a face normal of its own side
    mesh = builtin_mesh(name)
    normals = mesh.vertex_normals
    flat = np.isclose(np.abs(normals[:, 1]), 1.0) | np.isclose(normals[:, 1], 0.0)
    assert flat.all()


def test_builtin_params_shape_the_primitives():
    box = builtin_mesh("box", size=[1, 2, 3])
    np.testing.assert_allclose(box.bounds, [[-0.5, -1, -1.5], [0.5, 1, 1.5]])
    assert box.volume == pytest.approx(6.0)

    fine = builtin_mesh("box", size=[1, 2, 3], subdivisions=1)
    assert (len(fine.vertices), len(fine.faces)) == (6 * 3 * 3, 4 * 12)
    assert fine.volume == pytest.approx(6.0)

    for k in range(4):
        ico = builtin_mesh("icosphere", radius=2.0, subdivisions=k)
        assert len(ico.vertices) == 10 * 4**k + 2
        np.testing.assert_allclose(np.linalg.norm(ico.vertices, axis=1), 2.0)

    uv = builtin_mesh("uv_sphere", radius=2.0, count=[8, 12])
    assert uv.bounds[1, 1] == pytest.approx(2.0)  # poles on +-Y
    assert uv.bounds[0, 1] == pytest.approx(-2.0)

    torus = builtin_mesh("torus", major_radius=2.0, minor_radius=0.5)
    np.testing.assert_allclose(torus.bounds, [[-2.5, -0.5, -2.5], [2.5, 0.5, 2.5]], atol=1e-12)

    cyl = builtin_mesh("cylinder", radius=0.3, height=2.0, sections=12)
    np.testing.assert_allclose(cyl.bounds[:, 1], [-1.0, 1.0])  # axis +Y, centred
    radii = np.hypot(cyl.vertices[:, 0], cyl.vertices[:, 2])
    assert np.sum(radii == 0.0) == 2  # the two cap centres
    np.testing.assert_allclose(radii[radii > 0.0], 0.3)


def test_plane_is_a_regular_grid_facing_up():
    plane = builtin_mesh("plane", size=[6, 4], resolution=[3, 2])
    assert len(plane.vertices) == 4 * 3
    assert len(plane.faces) == 2 * 3 * 2
    assert np.all(plane.vertices[:, 1] == 0.0)
    np.testing.assert_allclose(plane.face_normals, np.tile([0.0, 1.0, 0.0], (12, 1)), atol=1e-15)
    np.testing.assert_allclose(plane.bounds, [[-3, 0, -2], [3, 0, 2]])
    # x varies slowest: vertex i * (nz + 1) + k sits at (x_i, 0, z_k)
    np.testing.assert_allclose(plane.vertices[:3, 2], [-2, 0, 2])
    np.testing.assert_allclose(plane.vertices[::3, 0], [-3, -1, 1, 3])
    assert plane.area == pytest.approx(24.0)
    assert len(builtin_mesh("plane", resolution=5).vertices) == 36  # one int: both axes


# --------------------------------------------------------------------------- assets


def test_bunny_is_the_1839_vertex_stanford_bunny_normalised():
    bunny = builtin_mesh("bunny")
    bunny.vertices[0] = 0.0  # a private copy: the cached asset is not touched
    bunny.faces[0] = [0, 1, 2]
    bunny = builtin_mesh("bunny")
    assert bunny.vertices[0, 1] > 0.0
    assert (len(bunny.vertices), len(bunny.faces)) == (1839, 3674)
    assert_normalised(bunny)
    raw = load_mesh(DATA_DIR / "meshes" / "bunny.ply")
    # normalisation is a uniform scale plus a shift: vertex order and shape kept
    scale = 1.0 / np.ptp(raw.vertices[:, 1])
    np.testing.assert_allclose(
        np.diff(bunny.vertices, axis=0), np.diff(raw.vertices, axis=0) * scale, atol=1e-12
    )


@pytest.mark.parametrize("levels, n_vertices", [(1, 7350), (2, 29394)])
def test_bunny_subdivision_reaches_paper_scale(levels, n_vertices):
    bunny = builtin_mesh("bunny", subdivisions=levels)
    assert len(bunny.vertices) == n_vertices
    assert len(bunny.faces) == 3674 * 4**levels
    assert bunny.is_watertight and bunny.volume > 0.0
    assert_normalised(bunny)


@pytest.mark.parametrize("variant, counts", [("5k", (5203, 10980)), ("23k", (22982, 47592))])
def test_dragon_variants(variant, counts):
    dragon = builtin_mesh("dragon", variant=variant)
    assert (len(dragon.vertices), len(dragon.faces)) == counts
    assert_normalised(dragon)
    assert dragon.is_winding_consistent
    assert dragon.volume > 0.0  # not watertight (decimation holes), but outward overall


@pytest.mark.parametrize("n", [2, 4, 8])
def test_teapot_tessellation(n):
    teapot = builtin_mesh("teapot", resolution=n)
    # three.js's count: 32 patches * 2 n^2 triangles minus 8 n collapsed at the two cusps
    assert len(teapot.faces) == 32 * 2 * n * n - 8 * n
    assert teapot.is_winding_consistent
    assert_normalised(teapot)
    # four sheets: body (+ bottom), lid, handle, spout; each encloses positive volume,
    # i.e. its normals face out, though none is closed (documented openings)
    parts = teapot.split(only_watertight=False)
    assert len(parts) == 4
    assert all(p.volume > 0.0 for p in parts)
    assert not teapot.is_watertight
    assert len(boundary_edges(teapot)) > 0


def test_teapot_seams_are_welded_and_variants():
    teapot = builtin_mesh("teapot", resolution=6)
    # no two vertices coincide after welding
    from scipy.spatial import cKDTree

    assert len(cKDTree(teapot.vertices).query_pairs(1e-6)) == 0
    bottomless = builtin_mesh("teapot", resolution=6, bottom=False)
    assert len(bottomless.faces) < len(teapot.faces)
    narrow_lid = builtin_mesh("teapot", resolution=6, fit_lid=False)
    assert len(narrow_lid.vertices) == len(teapot.vertices)


def test_teapot_body_normals_point_away_from_the_axis():
    teapot = builtin_mesh("teapot", resolution=8)
    centres, normals = teapot.triangles_center, teapot.face_normals
    # the body's widest band (no handle or spout there: |z| large)
    band = (np.abs(centres[:, 2]) > 0.5) & (centres[:, 1] > 0.2) & (centres[:, 1] < 0.6)
    assert band.sum() > 10
    radial = centres[band] * [1.0, 0.0, 1.0]
    assert np.all(np.einsum("ij,ij->i", radial, normals[band]) > 0.0)


# --------------------------------------------------------------------------- Cornell box


def test_cornell_box_objects_and_extents():
    parts = cornell_box_objects()
    assert tuple(parts) == CORNELL_BOX_PARTS
    everything = trimesh.util.concatenate(list(parts.values()))
    lo, hi = everything.bounds
    np.testing.assert_allclose(lo, [0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(hi, [0.556, 0.5488, 0.5592], atol=1e-6)  # metres
    centre = np.array([0.278, 0.2744, 0.2796])
    for name in ("floor", "ceiling", "back_wall", "green_wall", "red_wall"):
        wall = parts[name]
        towards_centre = centre - wall.triangles_center
        assert np.all(np.einsum("ij,ij->i", wall.face_normals, towards_centre) > 0.0), name
    for name in ("short_block", "tall_block"):
        block = parts[name].copy()
        block.merge_vertices()
        assert block.is_watertight and block.is_winding_consistent and block.volume > 0.0, name
    assert parts["short_block"].bounds[1, 1] == pytest.approx(0.165)
    assert parts["tall_block"].bounds[1, 1] == pytest.approx(0.330)


def test_cornell_box_light_faces_down_and_matches_its_quad():
    light = cornell_box_light()
    normal = np.cross(light["u"], light["v"])
    np.testing.assert_allclose(normal / np.linalg.norm(normal), [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(light["center"], [0.278, 0.548, 0.2795], atol=1e-9)
    assert 4 * np.linalg.norm(normal) == pytest.approx(0.130 * 0.105)  # area of the quad
    assert np.all(light["radiance"] > 0.0)
    quad = cornell_box_objects()["light"]
    corners = [light["center"] + a * light["u"] + b * light["v"] for a in (-1, 1) for b in (-1, 1)]
    for c in corners:
        assert np.min(np.linalg.norm(quad.vertices - c, axis=1)) < 1e-9
    np.testing.assert_allclose(quad.face_normals, [[0.0, -1.0, 0.0]] * 2, atol=1e-12)


def test_cornell_box_resolution_and_builtin_parts():
    coarse, fine = cornell_box_objects(), cornell_box_objects(resolution=3)
    for name in CORNELL_BOX_PARTS:
        n_quads = len(coarse[name].faces) // 2
        assert len(fine[name].vertices) == n_quads * 16
        assert len(fine[name].faces) == n_quads * 18
        # planar quads keep their area; the red wall's quad is skewed by 6.4 mm out of
        # its plane, so its bilinear patch differs from the two triangles by ~5e-6
        rel = 1e-5 if name == "red_wall" else 1e-12
        assert fine[name].area == pytest.approx(coarse[name].area, rel=rel)
        # any triangulation with the same boundary has the same mean gradient (a boundary integral): the
        # summed unit normals differ only by their normalisation, 1 - |grad z|^2 / 2 per triangle, so by at
        # most (skew / shortest side)^2 for the quad's two triangles; planar quads agree to rounding
        normal_tol = 1e-12
        if name == "red_wall":
            v = np.asarray(coarse[name].vertices)
            skew = abs(np.dot(v[3] - v[0], coarse[name].face_normals[0]))
            side = np.linalg.norm(np.diff(v[[0, 1, 2, 3, 0]], axis=0), axis=1).min()
            normal_tol = (skew / side) ** 2
        np.testing.assert_allclose(
            fine[name].face_normals.sum(0) / 9, coarse[name].face_normals.sum(0), atol=normal_tol
        )
    floor = builtin_mesh("cornell_box", part="floor", resolution=3)
    np.testing.assert_array_equal(floor.vertices, fine["floor"].vertices)
    with pytest.raises(ValueError, match="not a single mesh: pass part= one of floor"):
        builtin_mesh("cornell_box")
    with pytest.raises(ValueError, match="resolution must be <= 256"):
        cornell_box_objects(resolution=1000)


# --------------------------------------------------------------------------- room


ROOM = [4.0, 3.0, 5.0]
WINDOWS = [
    {"wall": "+x", "center": [0.5, 1.5], "size": [1.0, 1.0]},
    {"wall": "-x", "center": [-1.0, 1.2], "size": [0.8, 1.5]},
    {"wall": "+y", "center": [0.0, 0.0], "size": [1.0, 2.0]},
    {"wall": "-z", "center": [-1.0, 1.0], "size": [1.0, 0.5]},
    {"wall": "-z", "center": [1.0, 1.0], "size": [1.0, 0.5]},
    {"wall": "+z", "center": [0.0, 1.0], "size": [4.0, 2.0]},  # a whole-width opening
]


def test_room_windows_fill_their_openings_and_face_inward():
    walls, windows = room_with_windows(size=ROOM, windows=WINDOWS, cell_size=0.5)
    assert len(windows) == len(WINDOWS)
    w, h, d = ROOM
    full_area = 2 * (w * h + w * d + h * d)
    window_area = sum(win.area for win in windows)
    assert walls.area + window_area == pytest.approx(full_area, rel=1e-12)
    assert window_area == pytest.approx(1 + 1.2 + 2 + 0.5 + 0.5 + 8)
    inside = np.array([0.0, h / 2, 0.0])
    assert np.all(np.einsum("ij,ij->i", walls.face_normals, inside - walls.triangles_center) > 0)
    wall_edges = {tuple(map(tuple, walls.vertices[e])) for e in boundary_edges(walls)}
    wall_vertices = {tuple(v) for v in walls.vertices}
    for spec, win in zip(WINDOWS, windows):
        assert (len(win.vertices), len(win.faces)) == (4, 2)
        assert np.all(np.einsum("ij,ij->i", win.face_normals, inside - win.triangles_center) > 0)
        # its corners are exactly vertices of the wall grid
        assert all(tuple(v) in wall_vertices for v in win.vertices)
        # and each of its edges is a hole boundary of the walls, or the wall's border
        assert win.area == pytest.approx(np.prod(spec["size"]))
        for a, b in boundary_edges(win):
            pa, pb = win.vertices[a], win.vertices[b]
            on_boundary = any(
                np.allclose(np.cross(pb - pa, q - pa), 0.0) and np.allclose(np.cross(pb - pa, r - pa), 0.0)
                for q, r in wall_edges
                for q, r in [(np.array(q), np.array(r))]
            )
            assert on_boundary


def test_room_surfaces_and_builtins_agree():
    walls, windows = room_with_windows(size=ROOM, windows=WINDOWS[:2], cell_size=0.5)
    same = builtin_mesh("room", size=ROOM, windows=WINDOWS[:2], cell_size=0.5)
    np.testing.assert_array_equal(same.vertices, walls.vertices)
    np.testing.assert_array_equal(same.faces, walls.faces)
    one = builtin_mesh("window", room_size=ROOM, **WINDOWS[1])
    np.testing.assert_array_equal(one.vertices, windows[1].vertices)
    np.testing.assert_array_equal(one.faces, windows[1].faces)
    floor = builtin_mesh("room", size=ROOM, windows=[], surfaces=["-y"])
    np.testing.assert_allclose(floor.face_normals, [[0.0, 1.0, 0.0]] * len(floor.faces), atol=1e-15)
    assert floor.area == pytest.approx(ROOM[0] * ROOM[2])
    assert len(floor.vertices) == 17 * 21  # 0.25 m cells
    # defaults: a 4 x 2.5 x 4 room with the default window on -z, and that window
    default_walls, (default_window,) = room_with_windows()
    assert default_walls.area + default_window.area == pytest.approx(2 * (10 + 16 + 10))
    np.testing.assert_array_equal(builtin_mesh("window").vertices, default_window.vertices)
    assert np.all(default_window.vertices[:, 2] == -2.0)


def test_room_errors():
    with pytest.raises(ValueError, match=r"windows\[0\]: the opening .* does not fit on wall '\+x'"):
        room_with_windows(size=ROOM, windows=[{"wall": "+x", "center": [2.4, 1], "size": [1, 1]}])
    with pytest.raises(ValueError, match=r"windows\[0\] and windows\[1\] overlap on wall '-z'"):
        room_with_windows(size=ROOM, windows=[WINDOWS[3], {**WINDOWS[3], "center": [-0.5, 1.2]}])
    with pytest.raises(ValueError, match="wall must be one of"):
        room_with_windows(size=ROOM, windows=[{"wall": "-y", "center": [0, 0], "size": [1, 1]}])
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['colour'\]"):
        room_with_windows(size=ROOM, windows=[{**WINDOWS[0], "colour": 1}])
    with pytest.raises(TypeError, match="windows must be a list"):
        room_with_windows(size=ROOM, windows=WINDOWS[0])
    with pytest.raises(ValueError, match="surfaces must be a non-empty list"):
        room_with_windows(size=ROOM, surfaces=["floor"])
    with pytest.raises(ValueError, match="size must be > 0"):
        room_with_windows(size=[4, 0, 4])
    with pytest.raises(ValueError, match="cell_size .* is too small"):
        room_with_windows(cell_size=1e-4)
    with pytest.raises(ValueError, match="window: the opening"):
        window_quad(room_size=ROOM, wall="+y", center=[0, 0], size=[5, 1])


# --------------------------------------------------------------------------- helpers


def test_subdivide_counts_and_methods():
    mesh = builtin_mesh("icosphere", subdivisions=1)  # 42 vertices, 120 edges, 80 faces
    loop = subdivide(mesh, levels=1)
    assert (len(loop.vertices), len(loop.faces)) == (42 + 120, 320)
    mid = subdivide(mesh, levels=2, method="midpoint")
    assert (len(mid.vertices), len(mid.faces)) == (42 + 120 + 480, 1280)
    np.testing.assert_array_equal(mid.vertices[:42], mesh.vertices)  # coarse vertices first, unmoved
    assert mid.is_watertight and mid.volume > 0
    # children of face f are f, F + f, 2F + f, 3F + f, with the parent's orientation
    F = len(mesh.faces)
    one = subdivide(mesh, levels=1, method="midpoint")
    for k in range(4):
        children = one.triangles_center[k * F : (k + 1) * F]
        inside = trimesh.triangles.points_to_barycentric(mesh.triangles, children)
        assert np.all(inside > 0.0)  # each child lies inside its parent
        np.testing.assert_allclose(one.face_normals[k * F : (k + 1) * F], mesh.face_normals, atol=1e-12)
    copy = subdivide(mesh, levels=0)
    np.testing.assert_array_equal(copy.vertices, mesh.vertices)
    assert copy is not mesh
    with pytest.raises(ValueError, match="unknown method 'butterfly'; valid methods: loop, midpoint"):
        subdivide(mesh, method="butterfly")
    with pytest.raises(ValueError, match="levels must be an integer >= 0"):
        subdivide(mesh, levels=-1)
    with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh"):
        subdivide(mesh.vertices)


@pytest.mark.parametrize("name", ["icosphere", "torus", "bunny"])
def test_loop_subdivision_matches_trimesh_on_closed_meshes(name):
    from scipy.spatial import cKDTree

    mesh = builtin_mesh(name)
    ours = subdivide(mesh, levels=1, method="loop")
    vertices, faces = trimesh.remesh.subdivide_loop(mesh.vertices, mesh.faces, iterations=1)
    assert len(ours.vertices) == len(vertices) and len(ours.faces) == len(faces)
    distance, _ = cKDTree(vertices).query(ours.vertices)
    assert distance.max() < 1e-12
    np.testing.assert_allclose(ours.vertices[: len(mesh.vertices)], vertices[: len(mesh.vertices)], atol=1e-12)
    assert ours.area == pytest.approx(trimesh.Trimesh(vertices, faces).area, rel=1e-12)


def test_loop_subdivision_keeps_open_flat_meshes_flat():
    plane = builtin_mesh("plane", size=[2, 2], resolution=4)
    fine = subdivide(plane, levels=2)
    assert len(fine.vertices) == 17 * 17
    assert np.all(fine.vertices[:, 1] == 0.0)
    assert fine.is_winding_consistent
    np.testing.assert_allclose(fine.face_normals[:, 1], 1.0)
    # the boundary x = -1 stays straight; its corners are rounded (B-spline rule)
    old = fine.vertices[: len(plane.vertices)]
    edge = (plane.vertices[:, 0] == -1.0) & (np.abs(plane.vertices[:, 2]) < 1.0)
    corner = (plane.vertices[:, 0] == -1.0) & (np.abs(plane.vertices[:, 2]) == 1.0)
    np.testing.assert_array_equal(old[edge, 0], -1.0)
    assert np.all(old[corner, 0] > -1.0)
    assert np.all(np.abs(fine.vertices[:, [0, 2]]) <= 1.0)


def test_normalize_mesh():
    mesh = trimesh.Trimesh([[1, 2, 3], [3, 2, 3], [1, 6, 7]], [[0, 1, 2]], process=False)
    out = normalize_mesh(mesh, height=2.0)
    np.testing.assert_allclose(out.vertices, [[-0.5, 0, -1], [0.5, 0, -1], [-0.5, 2, 1]])
    np.testing.assert_array_equal(out.faces, mesh.faces)
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 0, 1]], [[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="flat in y"):
        normalize_mesh(flat)


def test_builtin_errors_name_the_problem():
    with pytest.raises(ValueError, match="unknown builtin mesh 'teacup'; valid names: box, bunny"):
        builtin_mesh("teacup")
    with pytest.raises(
        ValueError, match=r"builtin 'plane': unknown parameter\(s\) 'radius'; valid parameters: size, resolution"
    ):
        builtin_mesh("plane", radius=1.0)
    with pytest.raises(ValueError, match="builtin 'box': size must be > 0"):
        builtin_mesh("box", size=[1, -1, 1])
    with pytest.raises(ValueError, match="builtin 'box': size must be a list of 3 numbers"):
        builtin_mesh("box", size=[1, 1])
    with pytest.raises(ValueError, match="builtin 'icosphere': radius must be finite"):
        builtin_mesh("icosphere", radius=float("nan"))
    with pytest.raises(TypeError, match="builtin 'icosphere': subdivisions must be an integer"):
        builtin_mesh("icosphere", subdivisions=1.5)
    with pytest.raises(ValueError, match="subdivisions must be <= 7"):
        builtin_mesh("icosphere", subdivisions=9)
    with pytest.raises(ValueError, match="minor_radius must be < major_radius"):
        builtin_mesh("torus", major_radius=1.0, minor_radius=1.0)
    with pytest.raises(ValueError, match="count must be an integer >= 3"):
        builtin_mesh("uv_sphere", count=[2, 8])
    with pytest.raises(ValueError, match="variant must be one of '5k', '23k'"):
        builtin_mesh("dragon", variant="100k")
    with pytest.raises(TypeError, match="bottom must be true or false"):
        builtin_mesh("teapot", bottom="yes")
    with pytest.raises(ValueError, match="resolution must be <= 128"):
        builtin_mesh("teapot", resolution=1000)
    with pytest.raises(ValueError, match="subdivisions must be <= 4"):
        builtin_mesh("bunny", subdivisions=5)
    with pytest.raises(TypeError, match="builtin mesh name must be a string"):
        builtin_mesh(3)
    with pytest.raises(TypeError, match="builtin 'cylinder': height must be a number"):
        builtin_mesh("cylinder", height="tall")


def test_builtin_meshes_lists_parameters_and_defaults():
    assert BUILTIN_MESHES["plane"] == {"size": (1.0, 1.0), "resolution": (1, 1)}
    assert BUILTIN_MESHES["dragon"] == {"variant": "5k"}
    assert "teapot" in BUILTIN_MESHES and len(BUILTIN_MESHES) == len(list(BUILTIN_MESHES))


# --------------------------------------------------------------------------- loading


def test_load_mesh_keeps_vertex_order(tmp_path, rng):
    vertices = rng.normal(size=(10, 3))
    faces = np.array([[9, 3, 1], [2, 5, 7], [0, 8, 4], [6, 2, 9]])
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    for ext in ("ply", "obj", "off", "glb"):
        path = tmp_path / f"mesh.{ext}"
        mesh.export(path)
        loaded = load_mesh(path)
        np.testing.assert_allclose(loaded.vertices, vertices, atol=1e-6, err_msg=ext)
        np.testing.assert_array_equal(loaded.faces, faces, err_msg=ext)


def test_load_mesh_obj_relative_indices_and_polygons(tmp_path):
    path = tmp_path / "cornell_like.obj"
    path.write_text(
        "o first\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n"
        "f -4/1/1 -3/1/1 -2/1/1 -1/1/1  # a quad, relative indices\n"
        "v 5 5 5\n"  # unreferenced: kept, in place
        "o second\nv 0 0 1\nv 1 0 1\nv 0 1 1\nf 6//1 7//1 8//1\n"
    )
    mesh = load_mesh(path)
    assert len(mesh.vertices) == 8
    np.testing.assert_array_equal(mesh.vertices[4], [5, 5, 5])
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [5, 6, 7]])
    cornell = tmp_path / "bad.obj"
    cornell.write_text("v 0 0 0\nf -2 -1 1\n")
    with pytest.raises(ValueError, match="line 2: relative index '-2' reaches before the first vertex"):
        load_mesh(cornell)
    cornell.write_text("v 0 0 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="face index 3 > 1 vertices"):
        load_mesh(cornell)


def test_load_mesh_concatenates_scenes(tmp_path):
    scene = trimesh.Scene([builtin_mesh("box"), builtin_mesh("icosphere", subdivisions=1)])
    path = tmp_path / "scene.glb"
    scene.export(path)
    mesh = load_mesh(path)
    assert (len(mesh.vertices), len(mesh.faces)) == (24 + 42, 12 + 80)


def test_load_mesh_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="mesh file not found: .*nothing.ply"):
        load_mesh(tmp_path / "nothing.ply")
    points = tmp_path / "points.ply"
    trimesh.PointCloud(np.eye(3)).export(points)
    with pytest.raises(ValueError, match="holds no triangle mesh \\(no faces"):
        load_mesh(points)
    empty = tmp_path / "empty.obj"
    empty.write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(ValueError, match="holds no triangle mesh \\(no faces\\)"):
        load_mesh(empty)
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=r"mesh has NaN or inf vertex coordinates: vertex 1 of .*nan.obj' is \[1.0, nan, 0.0\]"):
        load_mesh(nan)
    garbage = tmp_path / "garbage.ply"
    garbage.write_text("not a mesh")
    with pytest.raises(ValueError, match="cannot read mesh file .*garbage.ply"):
        load_mesh(garbage)


# --------------------------------------------------------------------------- data/


def test_every_asset_is_documented_and_data_stays_small():
    readme = (DATA_DIR / "README.md").read_text()
    files = [p for d in ("meshes", "envmaps") for p in (DATA_DIR / d).rglob("*") if p.is_file()]
    assert files
    for path in files:
        assert path.relative_to(DATA_DIR).as_posix() in readme, path
    assert sum(p.stat().st_size for p in files) < 4_000_000


@pytest.mark.parametrize("name", ["sunset", "interior", "courtyard"])
def test_light_probes_are_lossless_equirect_maps(name):
    import OpenEXR

    with OpenEXR.File(str(DATA_DIR / "envmaps" / f"{name}.exr")) as exr:
        assert exr.header()["compression"] == OpenEXR.ZIP_COMPRESSION
        rgb = np.asarray(exr.channels()["RGB"].pixels, dtype=np.float64)
    assert rgb.shape == (256, 512, 3)
    assert np.all(np.isfinite(rgb)) and np.all(rgb >= 0.0)
    assert rgb.max() > 10.0  # high dynamic range


def test_sunset_probe_orientation():
    """Row 0 is the +Y pole: the sky is above, and the sun sits just above the horizon."""
    import OpenEXR

    from prtlab.geometry import equirect_directions

    with OpenEXR.File(str(DATA_DIR / "envmaps" / "sunset.exr")) as exr:
        rgb = np.asarray(exr.channels()["RGB"].pixels, dtype=np.float64)
    luminance = rgb @ [0.2126, 0.7152, 0.0722]
    assert luminance[:128].mean() > 3 * luminance[128:].mean()
    sun = equirect_directions(*luminance.shape)[np.unravel_index(luminance.argmax(), luminance.shape)]
    assert 0.0 < sun[1] < 0.15  # a few degrees of elevation
