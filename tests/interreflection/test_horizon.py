"""Tests of prtlab/interreflection/_horizon.py: the environment's bands above the SH order through a flat
occluder's half-space (``horizon_sky``).

The added light against the Funk-Hecke closed form (a sky of one band above the order, the half-space the
cosine's own), against an independent fine quadrature of ``int (L - L_n) H g cos`` (a clear sky, normals
across the horizon, a map summed into cells), and in the pipeline: only the points that take a half-space
change, by that light. Against Monte Carlo: ``tests/fidelity/test_interreflection.py`` (a box on a floor).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from prtlab import brdf, sh
from prtlab.geometry import equirect_directions
from prtlab.interreflection import Interreflection
from prtlab.interreflection import _horizon as horizon
from prtlab.pipeline import FrameState
from prtlab.scene import EnvironmentLight, Scene, environment_sh

UP = np.array([0.0, 1.0, 0.0])
LAMBERT = brdf.separable(brdf.lambert([1.0, 1.0, 1.0]), 1)
SKY = {"type": "environment", "sky": {"sun_elevation_deg": 30, "sun_azimuth_deg": 40, "turbidity": 3,
                                      "height": 32, "width": 64}}


def _sky(**spec) -> EnvironmentLight:
    scene = Scene.from_dict({"objects": [{"name": "p", "mesh": {"builtin": "plane", "size": [1, 1],
                                                                "resolution": [1, 1]}}],
                             "lights": [{**SKY, **spec}]})
    return scene.environment


def _added(env, normal, axes, cell_rows: int = horizon.CELL_ROWS) -> np.ndarray:
    """``dL`` (3,) of a Lambertian point with ``normal`` taking the half-spaces ``axes``, by the module."""
    _, dirs, residual = horizon.sky_cells(env, environment_sh(env, 4), cell_rows)
    axes = np.atleast_2d(axes)
    (group,) = horizon.horizon_weights(np.atleast_2d(normal), np.zeros(len(axes), np.int64), axes, LAMBERT, dirs)
    assert group.points.tolist() == [0] and group.which.tolist() == [0]
    return horizon.horizon_sums(group, residual)[0, 0]


def _fine(env, normals, axes, n: int = 2048) -> np.ndarray:
    """``int (L - L_n) H max(0, n . w) / pi dw`` (P, 3) at ``normals`` (P, 3) or (3,) -> (3,), by the midpoint
    rule on an ``n x 2n`` grid about ``+Y`` (the horizon of ``+Y`` on a cell boundary), ``L`` the map's bilinear
    radiance: independent of the module's rule."""
    theta, phi = (np.arange(n) + 0.5) * math.pi / n, (np.arange(2 * n) + 0.5) * math.pi / n
    st = np.sin(theta)[:, None]
    d = np.stack(np.broadcast_arrays(st * np.sin(phi), np.cos(theta)[:, None], -st * np.cos(phi)), -1).reshape(-1, 3)
    w = np.repeat(np.sin(theta) * (math.pi / n) ** 2, 2 * n)
    for a in np.atleast_2d(axes):
        w = w * (d @ a > 0.0)
    r = (env.radiance(d) - sh.basis(d, 4) @ environment_sh(env, 4)) * w[:, None]
    return np.maximum(np.asarray(normals) @ d.T, 0.0) @ r / math.pi


def test_a_constant_environment_has_no_higher_bands():
    env = EnvironmentLight(constant=np.array([1.0, 2.0, 3.0]))
    _, dirs, residual = horizon.sky_cells(env, environment_sh(env, 4))
    assert dirs.shape == residual.shape == (0, 3)
    assert np.all(_added(env, np.array([1.0, 0.0, 0.0]), UP) == 0.0)


@pytest.mark.parametrize("band", [4, 5, 6])
def test_one_band_above_the_order_through_the_cosines_own_halfspace_is_funk_hecke(band):
    """A sky ``Y_l0`` about ``+Y`` (``l >= 4``: none of it in the order-4 SH but the rule's leak) at a point with
    normal and half-space ``+Y``: ``dL = lambda_l Y_l0(+Y) / pi`` with ``lambda_l = 2 pi int_0^1 t P_l(t) dt``
    (Funk-Hecke). The integrand has a kink, no jump: the error falls as the rows' spacing squared (at least 3-fold
    per doubling) and is under 0.5 % of band 4's light at the default rows (odd bands give none)."""

    def light(band):  # lambda_l Y_l0(+Y) / pi
        legendre = np.polynomial.legendre.Legendre.basis(band).convert(kind=np.polynomial.Polynomial)
        integral = (legendre * np.polynomial.Polynomial([0.0, 1.0])).integ()
        return 2 * (integral(1.0) - integral(0.0)) * math.sqrt((2 * band + 1) / (4 * math.pi))

    errors = []
    for rows in (horizon.CELL_ROWS, 2 * horizon.CELL_ROWS):
        y = equirect_directions(rows, 2 * rows)[..., 1]
        image = math.sqrt((2 * band + 1) / (4 * math.pi)) * np.polynomial.legendre.Legendre.basis(band)(y)
        env = EnvironmentLight(image=np.repeat(image[..., None], 3, axis=2))
        errors.append(np.abs(_added(env, UP, UP, cell_rows=rows) - light(band)).max())
    assert errors[0] < 5e-3 * abs(light(4))
    assert errors[1] < errors[0] / 3


@pytest.mark.parametrize("normal", [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.6, 0.8, 0.0], [0.6, -0.8, 0.0],
                                    [0.0, 0.6, 0.8]])
def test_a_clear_sky_through_the_floors_halfspace_is_the_fine_integral(normal):
    """A clear sky (sun 30 degrees up, a 32 x 64 map sampled on the rule's 64 rows): ``dL`` within 1 % of the
    independent fine integral for normals facing the horizon, across it and away from it, the horizon's jump
    included; and the rule converges to it (256 rows: within 0.1 %)."""
    env, normal = _sky(), np.array(normal) / np.linalg.norm(normal)
    want = _fine(env, normal, UP)
    assert np.all(want > 0.1)  # the sky's higher bands are a real part of the light here
    np.testing.assert_allclose(_added(env, normal, UP), want, rtol=1e-2)
    np.testing.assert_allclose(_added(env, normal, UP, cell_rows=256), want, rtol=1e-3)


def test_a_large_map_summed_into_cells_and_two_halfspaces():
    """A 600 x 1200 map (10 x 10 pixels per cell) keeps its radiance times solid angle, and a point in a corner
    (half-spaces ``+Y`` and ``+X``) gets the fine integral within 1 %."""
    from prtlab.geometry import equirect_solid_angles

    env = EnvironmentLight(image=_sky().radiance(equirect_directions(600, 1200)))
    _, dirs, energy = horizon.sky_cells(env, np.zeros((16, 3)))  # no SH subtracted: each cell's L dw
    assert len(dirs) == 60 * 120
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(energy.sum(axis=0), np.einsum("hwc,hw->c", env.image, equirect_solid_angles(600, 1200)),
                               rtol=1e-12)
    normal = np.array([0.5, 0.5, -math.sqrt(0.5)])
    axes = np.array([UP, [1.0, 0.0, 0.0]])
    np.testing.assert_allclose(_added(env, normal, axes), _fine(env, normal, axes), rtol=1e-2)


@pytest.fixture(scope="module")
def box_on_floor():
    from tests.interreflection.test_flat import SMALL, box_on_floor_scene

    scene = box_on_floor_scene(SKY, {"translate": [0.3, 0.3, 0.0], "rotate_deg": [0, 25, 0]})
    return Interreflection.precompute(scene, SMALL, cache=False, progress=False)


def test_the_pipeline_adds_it_at_the_points_that_take_the_halfspace_only(box_on_floor):
    """``horizon_sky`` on against off, the direct light: the box's points that take the floor's half-space gain
    ``albedo dL`` (the fine integral, within 1 %; their light grows by more than 5 %), every other value of
    every object is the same bit for bit, and the paper's options leave it off."""
    from prtlab.interreflection import PAPER_OPTIONS

    assert PAPER_OPTIONS["horizon_sky"] is False
    state = FrameState.from_scene(box_on_floor.scene)
    on, off = (Interreflection(box_on_floor.scene, dataclasses.replace(box_on_floor.options, horizon_sky=h),
                               box_on_floor.data) for h in (True, False))
    a, b = on.shade(state, bounces=0), off.shade(state, bounces=0)
    np.testing.assert_array_equal(a.direct["floor"], b.direct["floor"])
    g = on._frame_geometry(state)["box"]
    rows = np.flatnonzero(g["x"][:, 1] < 0.01)
    others = np.setdiff1d(np.arange(len(g["x"])), rows)
    np.testing.assert_array_equal(a.direct["box"][others], b.direct["box"][others])
    sides = rows[np.abs(g["n"][rows, 1]) < 0.1]  # the sides' bottom row (the bottom face sees nothing above)
    assert len(sides) >= 8
    albedo = np.array([0.8, 0.5, 0.3])
    want = _fine(box_on_floor.scene.environment, g["n"][sides], UP, n=1024) * albedo
    np.testing.assert_allclose(a.direct["box"][sides] - b.direct["box"][sides], want, rtol=1e-2)
    assert np.all(a.direct["box"][sides] > 1.05 * b.direct["box"][sides])


def test_points_with_one_normal_and_one_set_of_halfspaces_share_their_weights():
    """Four points: two on a floor beside a wall (normal ``+Y``, sides ``+Y`` and ``+X`` given in either order),
    one on the floor alone, one with another normal. Two sets of half-spaces; in the floor's alone two normals.
    Each row keeps the cells its set lets through, and equals the one computed alone (to the rounding of a matrix
    product of another shape)."""
    normals = np.array([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.6, 0.8, 0.0]])
    x = np.array([1.0, 0.0, 0.0])
    rows = np.array([0, 0, 1, 1, 2, 3])
    axes = np.array([UP, x, x, UP, UP, UP])
    dirs = horizon.sky_cells(_sky(), environment_sh(_sky(), 4))[1]
    groups = horizon.horizon_weights(normals, rows, axes, LAMBERT, dirs)
    assert sorted(g.points.tolist() for g in groups) == [[0, 1], [2, 3]]
    for g in groups:
        corner = g.points.tolist() == [0, 1]
        assert np.all(dirs[g.cells] @ UP > 0) and (not corner or np.all(dirs[g.cells] @ x > 0))
        assert len(g.weights) == (1 if corner else 2)
        for p, row in zip(g.points, g.which):
            (alone,) = horizon.horizon_weights(normals[p:p + 1], np.zeros(2 if corner else 1, np.int64),
                                               np.array([UP, x] if corner else [UP]), LAMBERT, dirs)
            np.testing.assert_array_equal(alone.cells, g.cells)
            np.testing.assert_allclose(g.weights[row], alone.weights[0], rtol=1e-6)


def test_the_weights_are_g_k_cos_at_the_cells():
    """A glossy BRDF's terms (``K = 3``) and a Lambertian one's single constant (read once): the weights equal
    ``g_k(R^T w) max(0, n . w)`` evaluated at each cell through :func:`prtlab.brdf.to_local`, to float32
    rounding."""
    g = LAMBERT.g(_fibonacci_hemisphere())
    assert np.ptp(g) <= 4 * np.finfo(float).eps * g.max()  # one constant, to the profile's rounding
    glossy = brdf.separable(brdf.phong([0.3, 0.3, 0.3], [0.5, 0.5, 0.5], 20), 3)
    dirs = horizon.sky_cells(_sky(), environment_sh(_sky(), 4))[1]
    normal = np.array([[0.6, 0.48, 0.64]])
    for sep in (LAMBERT, glossy):
        (g,) = horizon.horizon_weights(normal, np.array([0]), UP[None], sep, dirs)
        d = dirs[g.cells]
        want = sep.g(brdf.to_local(d, np.broadcast_to(normal, d.shape))) * np.maximum(d @ normal[0], 0.0)[:, None]
        np.testing.assert_allclose(g.weights[0].T, want, rtol=2e-7, atol=1e-9)


def _fibonacci_hemisphere(n: int = 500) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - i / n
    phi = math.pi * (1.0 + math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


@pytest.mark.parametrize("seed, u, k", [(0, 37, 2), (1, 19, 1), (2, 4, 1), (3, 1, 1), (4, 9, 1)])
def test_the_sums_kernel_is_the_float64_product(seed, u, k):
    """:func:`horizon_sums`' kernel against numpy's float64 product of the same float32 weights (random rows of
    both signs, some cells left out, points sharing rows; ``u k`` rows: whole blocks of 4 and 0-3
    left over), within the float64 rounding of sums in another order: ``2 C eps`` of the sum of the terms'
    magnitudes."""
    rng = np.random.default_rng(seed)
    q, c = 900, 700
    cells = np.sort(rng.choice(q, c, replace=False))
    group = horizon.HorizonGroup(np.arange(50), rng.integers(0, u, 50), cells,
                                 rng.normal(size=(u, k, c)).astype(np.float32))
    residual = rng.normal(size=(q, 3))
    got, want = horizon.horizon_sums(group, residual), horizon.horizon_sums(group, residual, method="reference")
    bound = 2 * c * np.finfo(float).eps * (np.abs(group.weights.astype(float)) @ np.abs(residual[cells]))[group.which]
    assert got.shape == (50, k, 3)
    assert np.all(np.abs(got - want) <= bound)


def test_a_frame_after_a_move_or_a_new_sky_is_a_fresh_pipelines(box_on_floor):
    """One pipeline through frames (the box moved along the floor, lifted off it, back; the sky scaled; a
    constant sky; the first sky again) against a fresh pipeline per frame: every object's direct and total light
    the same bit for bit (the kept half-spaces, weights and sky residual follow the poses and the sky)."""
    from prtlab.scene import Transform

    scene = box_on_floor.scene
    sky = scene.environment
    box = scene.object("box").transform
    moved = Transform(translate=box.translate + [0.4, 0.0, -0.3], rotate_deg=[0, 60, 0])
    lifted = Transform(translate=box.translate + [0.0, 0.5, 0.0], rotate_deg=box.rotate_deg)
    frames = [(box, sky), (moved, sky), (lifted, sky), (box, sky),
              (box, EnvironmentLight(image=sky.image * 1.5)), (moved, EnvironmentLight(constant=np.ones(3))),
              (moved, sky)]
    kept = Interreflection(scene, box_on_floor.options, box_on_floor.data)
    for transform, env in frames:
        state = FrameState.from_scene(scene)
        state.transforms["box"] = transform
        state.lights = [env]
        fresh = Interreflection(scene, box_on_floor.options, box_on_floor.data).shade(state, bounces=1)
        got = kept.shade(state, bounces=1)
        for name in ("floor", "box"):
            np.testing.assert_array_equal(got.direct[name], fresh.direct[name])
            np.testing.assert_array_equal(got.total[name], fresh.total[name])
    assert kept.reuse.horizon  # the frames on the floor took the half-space
