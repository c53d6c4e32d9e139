"""Tests of prtlab/shadowfields/_sources.py: SH of the radiance of an area light."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab.scene import AreaLight
from prtlab.shadowfields import area_light_sh

LIGHT = AreaLight(center=np.array([0.0, 2.0, 0.0]), u=np.array([0.3, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.2]),
                  radiance=np.array([1.0, 2.0, 3.0]))  # cross(u, v) = -y: emits downward


def corner_form_factor(x, y):
    """Differential area to a parallel rectangle with one corner above it (sides x, y in heights)."""
    ax, ay = x / np.sqrt(1 + x * x), y / np.sqrt(1 + y * y)
    return (ax * np.arctan(y / np.sqrt(1 + x * x)) + ay * np.arctan(x / np.sqrt(1 + y * y))) / (2 * np.pi)


def test_known_answers_below_the_centre():
    """c_00 = L Omega / sqrt(4 pi) with the rectangle's solid angle; c_1,-1 = L sqrt(3 / 4 pi) pi F (F the
    form factor of the four corner rectangles): the y moment of the light's directions."""
    h, a, b = 2.0, 0.3, 0.2
    c = area_light_sh(LIGHT, np.zeros(3), 2)
    omega = 4 * np.arcsin(a * b / np.sqrt((a * a + h * h) * (b * b + h * h)))
    np.testing.assert_allclose(c[0], LIGHT.radiance * omega / np.sqrt(4 * np.pi), rtol=1e-8)
    form = 4 * corner_form_factor(a / h, b / h)
    np.testing.assert_allclose(c[1], LIGHT.radiance * np.sqrt(3 / (4 * np.pi)) * np.pi * form, rtol=1e-8)
    np.testing.assert_allclose(c[[2, 3]], 0.0, atol=1e-14)  # symmetric about the y axis


def test_behind_the_light_is_dark_and_tiers_agree(rng):
    np.testing.assert_array_equal(area_light_sh(LIGHT, [[0.0, 3.0, 0.0], [1.0, 2.0, 0.0]], 3), 0.0)
    pts = rng.normal(size=(7, 3))
    np.testing.assert_allclose(area_light_sh(LIGHT, pts, 4), area_light_sh(LIGHT, pts, 4, method="reference"),
                               atol=1e-12)
    assert area_light_sh(LIGHT, np.zeros((0, 3)), 2).shape == (0, 4, 3)
    assert area_light_sh(LIGHT, np.zeros((2, 5, 3)), 2).shape == (2, 5, 4, 3)


def test_errors():
    with pytest.raises(ValueError, match="n_nodes must be"):
        area_light_sh(LIGHT, np.zeros(3), 2, n_nodes=0)
    with pytest.raises(ValueError, match="points must be"):
        area_light_sh(LIGHT, np.zeros(2), 2)
    with pytest.raises(ValueError, match="NaN or inf"):
        area_light_sh(LIGHT, [np.nan, 0, 0], 2)
    with pytest.raises(ValueError, match="method must be"):
        area_light_sh(LIGHT, np.zeros(3), 2, method="gpu")
    with pytest.raises(TypeError, match="order must be an int"):
        area_light_sh(LIGHT, np.zeros(3), 2.0)


# --------------------------------------------------------------------------- source radiance fields


@pytest.fixture(scope="module")
def srf():
    from prtlab.shadowfields import source_radiance_field

    return source_radiance_field(LIGHT, 4, n_radii=8, resolution=8)


def _room_points(rng, n):
    """Points around the light (the light is at y = 2, emitting downward): a receiver's region."""
    pts = rng.uniform(-2.0, 2.0, size=(n, 3))
    pts[:, 1] = rng.uniform(-1.0, 1.7, n)
    return pts


def test_the_field_is_exact_at_its_nodes_in_any_pose(srf, rng):
    """At the sample points the lookup is the projection itself, also for a moved, turned, scaled light
    (solid angles do not change under a uniform scale; SH rotation is exact)."""
    from prtlab.scene import AreaLight
    from tests.conftest import random_rotation

    nodes = srf.grid.points()[2:5, :, 3:5, 3:5].reshape(-1, 3)  # texel centres: no clamped borders
    e1, e3 = LIGHT.u / np.linalg.norm(LIGHT.u), LIGHT.normal
    frame = np.stack([e1, np.cross(e3, e1), e3], axis=1)  # the light's canonical frame
    R, a, c = random_rotation(rng), 1.7, np.array([0.3, -1.0, 2.0])
    moved = AreaLight(center=c, u=a * R @ LIGHT.u, v=a * R @ LIGHT.v, radiance=LIGHT.radiance)
    world = c + a * (R @ frame @ nodes.T).T  # the canonical nodes placed by the moved light's frame
    np.testing.assert_allclose(srf.lookup(moved, world), area_light_sh(moved, world, 4),
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(srf.lookup(moved, world, method="reference"), srf.lookup(moved, world), atol=1e-12)


def test_the_field_converges_to_the_exact_projection(rng):
    """Relative L2 distance to :func:`area_light_sh` over points around the light falls with the sample
    spheres at least at half per doubling of the radii (trilinear interpolation errs like the spacing
    squared, a quarter; the angular spacing stays; measured: 0.10-0.13 at 8 radii x 16^2, 0.022-0.026 at
    16 x 16^2 (the default), 0.009-0.011 at 32 x 16^2);
    beyond the outermost sphere the ``(r_max / r)^2`` law holds to the light's finite size there (its
    angular radius at ``r_max = 8 R`` is 1/8: higher bands differ from a point source's by O(1/64))."""
    from prtlab.shadowfields import source_radiance_field

    pts = _room_points(rng, 600)
    exact = area_light_sh(LIGHT, pts, 4, n_nodes=24)
    errors = [np.linalg.norm(source_radiance_field(LIGHT, 4, n_radii=n, resolution=16).lookup(LIGHT, pts) - exact)
              / np.linalg.norm(exact) for n in (8, 16, 32)]
    assert errors[1] <= 0.5 * errors[0] and errors[2] <= 0.5 * errors[1], errors
    far = LIGHT.center + 30.0 * (pts - LIGHT.center)
    srf = source_radiance_field(LIGHT, 4, n_radii=4, resolution=16)
    exact = area_light_sh(LIGHT, far, 4)
    assert np.linalg.norm(srf.lookup(LIGHT, far) - exact) / np.linalg.norm(exact) < 2 / 64


def test_field_shapes_round_trip_and_errors(srf):
    from prtlab.scene import AreaLight
    from prtlab.shadowfields import SourceRadianceField

    assert srf.lookup(LIGHT, np.zeros((0, 3))).shape == (0, 16, 3)
    assert srf.lookup(LIGHT, np.zeros((2, 5, 3))).shape == (2, 5, 16, 3)
    back = SourceRadianceField.from_arrays(srf.to_arrays())
    np.testing.assert_array_equal(back.lookup(LIGHT, [0.1, 0.5, 0.2]), srf.lookup(LIGHT, [0.1, 0.5, 0.2]))
    wider = AreaLight(center=LIGHT.center, u=2 * LIGHT.u, v=LIGHT.v, radiance=LIGHT.radiance)
    assert not srf.fits(wider) and srf.fits(AreaLight(LIGHT.center, 3 * LIGHT.u, 3 * LIGHT.v, LIGHT.radiance))
    with pytest.raises(ValueError, match="not a uniform scale of the field's"):
        srf.lookup(wider, np.zeros(3))
    with pytest.raises(ValueError, match="not parallel"):
        srf.lookup(AreaLight(LIGHT.center, LIGHT.u, 2 * LIGHT.u, LIGHT.radiance), np.zeros(3))
    with pytest.raises(ValueError, match="points must be"):
        srf.lookup(LIGHT, np.zeros(2))


# --------------------------------------------------------------------------- point lights


def test_point_light_direct_is_the_exact_delta_of_the_haar_path(rng):
    from prtlab import brdf
    from prtlab.scene import PointLight
    from prtlab.shadowfields import haar_direct, point_light_direct

    sep = brdf.separable(brdf.phong(0.3, 0.5, 8.0), 3, resolution=(16, 32))
    light = PointLight(np.array([0.3, 2.0, -0.2]), np.array([1.0, 2.0, 3.0]))
    x = rng.uniform(-1, 1, size=(6, 3))
    n = rng.normal(size=(6, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(point_light_direct(light, x, n, sep), haar_direct(x, n, [light], sep, resolution=4),
                               rtol=1e-12, atol=1e-15)
    half = point_light_direct(light, x, n, sep, visibility=np.full(6, 0.5))
    np.testing.assert_allclose(half, 0.5 * point_light_direct(light, x, n, sep), rtol=1e-12)
    assert point_light_direct(light, np.zeros((0, 3)), np.zeros((0, 3)), sep).shape == (0, 3, 3)


def _cap_visibility_sh(cos_alpha, cos_theta, order):
    """Order-``order`` SH projection of the visibility ``1 - [w . a >= cos_alpha]`` outside a cap (a ball
    seen from a point), at angle ``theta`` from the cap's axis: ``1 - sum_l (2l+1)/2 c_l P_l(cos theta)``
    with ``c_l = int_{cos alpha}^1 P_l = (P_{l-1} - P_{l+1})(cos alpha) / (2l+1)`` (addition theorem)."""
    from numpy.polynomial.legendre import legval

    def p(l, x):
        return legval(x, [0.0] * l + [1.0])

    v = np.ones_like(cos_theta)
    for l in range(order):
        c = 1 - cos_alpha if l == 0 else (p(l - 1, cos_alpha) - p(l + 1, cos_alpha)) / (2 * l + 1)
        v -= (2 * l + 1) / 2 * c * p(l, cos_theta)
    return v


def test_what_the_sh_visibility_costs_a_point_light():
    """A ball's hard shadow from a point light: visibility toward the light from order-4 SH (clamped) against
    the shadow ray and against the texel of the Haar cubemap (32^2 per face). The SH visibility is the
    order-4 projection of the ball's cap (closed form, :func:`_cap_visibility_sh`) up to the product
    quadrature's error on a step (estimated by doubling the degree twice: ``|d47 - d95| + 2 |d95 - d191|``,
    first-order convergence) and the icosphere's departure from the ball (its points lie between the
    inscribed and circumscribed spheres: at most ``n^2 / (4 pi)`` times the solid angle between the two
    caps, as ``|P_l| <= 1``). Its mean absolute error toward the light is then the closed form's (0.344 over
    these points); the Haar texel is exact unless a shadow edge crosses it."""
    from prtlab import sh
    from prtlab.geometry import RayCaster, builtin_mesh, direction_to_cubemap
    from prtlab.shadowfields import (
        project_visibility,
        sh_visibility_toward,
        visibility_cubemaps,
    )

    ball = builtin_mesh("icosphere", radius=0.5, subdivisions=3)
    centre = np.array([0.0, 1.0, 0.0])
    caster = RayCaster([(ball.vertices + centre, ball.faces)])
    xs = np.linspace(-1.2, 1.2, 25)
    pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    light_pos = np.array([0.0, 2.5, 0.0])
    d = light_pos - pts
    dist = np.linalg.norm(d, axis=1)
    exact = ~caster.occluded(pts, d, dist)
    coeffs = {deg: project_visibility(caster, pts, 4, degree=deg) for deg in (47, 95, 191)}
    np.testing.assert_array_equal(project_visibility(caster, pts[:2], 4), coeffs[47][:2])  # 47: the default
    raw = {deg: np.einsum("vi,vi->v", c, sh.basis(d / dist[:, None], 4)) for deg, c in coeffs.items()}
    to_ball = centre - pts
    r_ball = np.linalg.norm(to_ball, axis=1)
    cos_theta = np.einsum("ij,ij->i", to_ball / r_ball[:, None], d / dist[:, None])
    closed = _cap_visibility_sh(np.sqrt(1 - (0.5 / r_ball) ** 2), cos_theta, 4)
    r_in = np.min(np.einsum("ij,ij->i", ball.face_normals, ball.triangles_center))
    cap = [2 * np.pi * (1 - np.sqrt(1 - (r / r_ball) ** 2)) for r in (r_in, 0.5)]
    bound = (np.abs(raw[47] - raw[95]) + 2 * np.abs(raw[95] - raw[191])) + 16 / (4 * np.pi) * (cap[1] - cap[0])
    assert np.all(np.abs(raw[47] - closed) <= bound), np.abs(raw[47] - closed) / bound
    v_sh = sh_visibility_toward(coeffs[47], d)
    np.testing.assert_array_equal(v_sh, np.clip(raw[47], 0, 1))
    err_sh = np.abs(v_sh - exact).mean()
    err_closed = np.abs(np.clip(closed, 0, 1) - exact).mean()
    assert abs(err_sh - err_closed) <= bound.mean(), (err_sh, err_closed, bound.mean())
    cubes = visibility_cubemaps(caster, pts, 32).reshape(len(pts), -1)
    face, _, _, i, j = direction_to_cubemap(d, 32)
    v_haar = cubes[np.arange(len(pts)), face * 1024 + i * 32 + j]
    assert np.abs(v_haar - exact).mean() == 0.0


def test_point_light_errors():
    from prtlab import brdf
    from prtlab.scene import PointLight
    from prtlab.shadowfields import point_light_direct, sh_visibility_toward

    sep = brdf.separable(brdf.lambert(1.0), 1)
    light = PointLight(np.array([0.0, 2.0, 0.0]), np.ones(3))
    with pytest.raises(TypeError, match="sep must be a SeparableBRDF"):
        point_light_direct(light, np.zeros((1, 3)), np.ones((1, 3)), "lambert")
    with pytest.raises(ValueError, match="points and normals must be"):
        point_light_direct(light, np.zeros((1, 3)), np.ones((2, 3)), sep)
    with pytest.raises(ValueError, match="NaN or inf"):
        point_light_direct(light, np.full((1, 3), np.nan), np.ones((1, 3)), sep)
    with pytest.raises(ValueError, match=r"visibility must be \(V,\)"):
        point_light_direct(light, np.zeros((1, 3)), np.ones((1, 3)), sep, visibility=np.ones(3))
    with pytest.raises(ValueError, match=r"visibility must be \(V, n\*n\)"):
        sh_visibility_toward(np.ones(4), np.ones((1, 3)))
    with pytest.raises(ValueError, match="n\\*n coefficients"):
        sh_visibility_toward(np.ones((1, 5)), np.ones((1, 3)))
    with pytest.raises(ValueError, match="dirs must be"):
        sh_visibility_toward(np.ones((1, 4)), np.ones((2, 3)))
    with pytest.raises(ValueError, match="NaN or inf"):
        sh_visibility_toward(np.full((1, 4), np.nan), np.ones((1, 3)))
    assert sh_visibility_toward(np.zeros((0, 4)), np.zeros((0, 3))).shape == (0,)
