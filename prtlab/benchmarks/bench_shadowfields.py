"""Benchmarks of prtlab.shadowfields: the all-frequency (Haar) direct light per frame, and its precomputation.

Scenes: a bunny (the first 4,096 vertices of the once-subdivided built-in bunny; quick mode 1,024) under
a 0.6 x 0.6 area light 2.5 units up (the Fig. 9 light), shadowed by itself and 1 or 3 balls; a
224 x 224 floor (50,176 vertices; quick mode 64 x 64) under the bunny and 2 balls. Occlusion fields
are precomputed once per process with a reduced grid (8 spheres x 6 x 8 x 8 points, quick mode 4 x 6 x 4 x 4;
32^2-texel faces, 512 coefficients): the per-frame cost depends on the cubemap resolution and ``keep``, not
on the grid.
The peer of the bunny case is the SH path (order 4: visibility products, area-light SH, triple
integral) on the same vertices.

Times are in docs/BENCHMARKS.md, written by ``prtlab bench --write-docs``.
"""

from __future__ import annotations

import numpy as np

from prtlab.bench import case

_DATA: dict = {}
LIGHT = {"center": [0.0, 2.5, 0.0], "u": [0.3, 0.0, 0.0], "v": [0.0, 0.0, 0.3], "radiance": [10.0, 10.0, 10.0]}
GRID = {True: {"n_radii": 4, "grid_resolution": 4}, False: {"n_radii": 8, "grid_resolution": 8}}


def _light():
    from prtlab.scene import AreaLight

    return AreaLight(**{k: np.asarray(v, float) for k, v in LIGHT.items()})


def _ball_field(quick: bool):
    if ("ball", quick) not in _DATA:
        from prtlab.geometry import builtin_mesh
        from prtlab.shadowfields import haar_occlusion_field

        mesh = builtin_mesh("icosphere", radius=0.3, subdivisions=3)
        _DATA["ball", quick] = (mesh, haar_occlusion_field(mesh, **GRID[quick]))
    return _DATA["ball", quick]


def _balls(n: int, quick: bool):
    from prtlab.scene import Transform

    _, field = _ball_field(quick)
    spots = [(0.0, 1.5, 0.0), (0.8, 0.8, 0.3), (-0.7, 1.2, -0.4)]
    return [(field, Transform(translate=np.array(p))) for p in spots[:n]]


def _bunny(quick: bool):
    key = ("bunny", quick)
    if key not in _DATA:
        from prtlab.geometry import RayCaster, builtin_mesh
        from prtlab.shadowfields import encode_sparse, visibility_cubemaps

        mesh = builtin_mesh("bunny", subdivisions=1)
        n = 1024 if quick else 4096
        x, nrm = np.asarray(mesh.vertices[:n], float), np.asarray(mesh.vertex_normals[:n], float)
        # haar_self_visibility of these vertices only
        vis = visibility_cubemaps(RayCaster([(mesh.vertices, mesh.faces)]), x, 32, normals=nrm)
        _DATA[key] = (mesh, x, nrm, encode_sparse(vis))
    return _DATA[key]


def _haar_case(points, normals, self_vis, occluders, lights, peer=None) -> dict:
    from prtlab import brdf
    from prtlab.shadowfields import haar_direct

    sep = brdf.separable(brdf.lambert(np.full(3, 0.7)), 1)

    def run():
        return haar_direct(points, normals, lights, sep, self_visibility=self_vis, occluders=occluders)

    return {"run": run, "gflop": None, "items": len(points), "peer": peer}


def _sh_peer(quick: bool, n_occ: int):
    """The SH path (order 4) on the bunny vertices: lookups, truncated products, area-light SH, direct pass."""
    from prtlab import brdf
    from prtlab.geometry import RayCaster
    from prtlab.shadowfields import (
        area_light_sh,
        direct_pass,
        occlusion_field,
        project_visibility,
        visibility_pass,
    )

    mesh, x, n, _ = _bunny(quick)
    key = ("sh", quick)
    if key not in _DATA:
        ball_mesh, _ = _ball_field(quick)
        grid = GRID[quick]
        _DATA[key] = (occlusion_field(ball_mesh, 4, n_radii=grid["n_radii"], resolution=grid["grid_resolution"]),
                      project_visibility(RayCaster([(mesh.vertices, mesh.faces)]), x, 4, normals=n))
    oof, own = _DATA[key]
    T = [t for _, t in _balls(n_occ, quick)]
    sep = brdf.separable(brdf.lambert(np.full(3, 0.7)), 1)
    g = brdf.project_g_cos(sep, n, 4)
    light = _light()

    def run():
        vis = visibility_pass(own, [oof.lookup(x, t) for t in T])
        return direct_pass(area_light_sh(light, x, 4), vis, g, np.ones((len(x), 1)), sep.colour)

    return ("sh path (order 4)", run)


@case("shadowfields.haar_direct.bunny4k.area.1occluder")
def haar_bunny_one(quick: bool) -> dict:
    """Self-visibility x 1 ball field, area light: per-vertex pieces, point-evaluated Haar products."""
    _, x, n, sv = _bunny(quick)
    return _haar_case(x, n, sv, _balls(1, quick), [_light()], peer=_sh_peer(quick, 1))


@case("shadowfields.haar_direct.bunny4k.area.3occluders")
def haar_bunny_three(quick: bool) -> dict:
    _, x, n, sv = _bunny(quick)
    return _haar_case(x, n, sv, _balls(3, quick), [_light()], peer=_sh_peer(quick, 3))


@case("shadowfields.haar_direct.bunny4k.environment.1occluder")
def haar_bunny_env(quick: bool) -> dict:
    """A constant environment: every texel is lit, so each factor is synthesised whole (6 x 32^2 texels)."""
    from prtlab.scene import EnvironmentLight

    _, x, n, sv = _bunny(quick)
    m = 256 if quick else len(x)
    env = EnvironmentLight(constant=np.ones(3))
    return _haar_case(x[:m], n[:m], _subset(sv, m), _balls(1, quick), [env])


def _subset(sv, m):
    from prtlab.shadowfields import SparseCubemaps

    return SparseCubemaps(sv.resolution, sv.indices[:m], sv.values[:m], sv.energy_lost[:m])


@case("shadowfields.haar_direct.floor50k.area.3occluders")
def haar_floor(quick: bool) -> dict:
    """A 50k-vertex floor (no self-shadowing) under the bunny and 2 balls, area light."""
    from prtlab.geometry import builtin_mesh
    from prtlab.scene import Transform
    from prtlab.shadowfields import haar_occlusion_field

    side = 64 if quick else 224
    floor = builtin_mesh("plane", size=[4, 4], resolution=[side - 1, side - 1])
    if ("bunny_field", quick) not in _DATA:
        _DATA["bunny_field", quick] = haar_occlusion_field(builtin_mesh("bunny"), **GRID[quick])
    occ = [(_DATA["bunny_field", quick], Transform())] + _balls(3, quick)[1:]
    x = np.asarray(floor.vertices, float)
    n = np.tile([0.0, 1.0, 0.0], (len(x), 1))
    return _haar_case(x, n, None, occ, [_light()])


@case("shadowfields.haar_field.precompute")
def haar_precompute(quick: bool) -> dict:
    """Precompute a ball's Haar occlusion field: (quick 2 x 6 x 4 x 4, full 4 x 6 x 8 x 8) points x 6144 rays."""
    from prtlab.geometry import builtin_mesh
    from prtlab.shadowfields import haar_occlusion_field

    mesh = builtin_mesh("icosphere", radius=0.3, subdivisions=3)
    grid = dict(n_radii=2, grid_resolution=4) if quick else dict(n_radii=4, grid_resolution=8)
    points = grid["n_radii"] * 6 * grid["grid_resolution"] ** 2

    def run():
        return haar_occlusion_field(mesh, **grid)

    return {"run": run, "gflop": None, "items": points, "peer": None}
