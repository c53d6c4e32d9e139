"""Direct light by shadow rays (prtlab/interreflection/_direct_rays.py, ``shadows="rays"``).

The estimator of an area light is ``A / m sum_j F(y_j)`` over ``m`` points of a grid jittered per vertex;
stratification never raises the variance above that of ``m`` independent uniform points, so each vertex is
within ``MC_SIGMAS * sqrt(Var F / m)`` of the integral, ``Var F = A int F^2 dA - (int F dA)^2`` (both by a
Gauss-Legendre rule over the light, whose own error is bounded by the difference of two rules). A point
light's visibility is held to a segment-box test written here (slabs), independent of Embree.
"""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import brdf
from prtlab.cache import cache_key
from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.interreflection import Interreflection, InterreflectionOptions
from prtlab.interreflection._direct_rays import ray_traced_direct
from prtlab.scene import AreaLight, Material, PointLight, Transform
from tests.conftest import MC_SIGMAS
from tests.scenes import floor_and_ball

LIGHT = AreaLight(center=np.array([0.3, 2.5, 0.4]), u=np.array([0.3, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.3]),
                  radiance=np.array([30.0, 20.0, 10.0]))


def _floor_points(n=7, size=3.0):
    s = np.linspace(-size / 2, size / 2, n)
    x, z = np.meshgrid(s, s)
    points = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    return points, np.tile([0.0, 1.0, 0.0], (len(points), 1))


def _moments(light, factor, points, normals, n_nodes):
    """``(int F dA, int F^2 dA)`` (V, J) of the area-light integrand ``F = q_j(w) cos_x cos_l / d^2`` (unit
    radiance; ``factor(w)`` (V, P, J) gives ``q``), by a tensor Gauss-Legendre rule over the parallelogram."""
    t, w = np.polynomial.legendre.leggauss(n_nodes)
    s_, t_ = np.meshgrid(t, t, indexing="ij")
    y = light.center + s_.reshape(-1, 1) * light.u + t_.reshape(-1, 1) * light.v
    dA = np.outer(w, w).ravel() * np.linalg.norm(np.cross(light.u, light.v))
    d = y[None] - points[:, None]
    r2 = np.sum(d * d, axis=-1)
    wy = d / np.sqrt(r2)[..., None]
    F = (np.maximum(np.einsum("vpi,vi->vp", wy, normals), 0.0) * np.maximum(-(wy @ light.normal), 0.0) / r2)[..., None]
    F = F * factor(wy)
    return np.einsum("vpk,p->vk", F, dA), np.einsum("vpk,p->vk", F**2, dA)


@pytest.mark.parametrize("material", [Material(albedo=np.array([0.7, 0.6, 0.5])),
                                      Material(type="phong", kd=np.array([0.3] * 3), ks=np.array([0.5] * 3),
                                               exponent=10.0)], ids=["lambert", "phong"])
@pytest.mark.parametrize("samples", [16, 256])
def test_an_unoccluded_area_light_is_its_integral_within_the_estimators_error(material, samples):
    """Both outputs, ``L_k`` (the separable terms ``g_k``) and the radiance toward the viewer (the BRDF
    itself), each within the estimator's standard error bound of the integral."""
    f = brdf.from_material(material)
    sep = brdf.separable(f, K=4 if material.type == "phong" else 1)
    points, normals = _floor_points()
    wo = np.array([0.2, 1.0, 0.9]) - 0.1 * points
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    caster = RayCaster(builtin_mesh("icosphere", subdivisions=1), transforms=[Transform(translate=[0, -50, 0])])
    light_k, radiance = ray_traced_direct(points, normals, wo, f, sep, caster, [LIGHT], samples)
    m = int(np.sqrt(samples)) ** 2

    def integral_and_bound(factor):
        first, second = _moments(LIGHT, factor, points, normals, 48)
        quadrature = np.abs(first - _moments(LIGHT, factor, points, normals, 24)[0])
        sigma = np.sqrt(np.maximum(LIGHT.area * second - first**2, 0.0) / m)
        assert np.all(first[:, 0] > 0.0)  # every point sees the light: the check is not of zeros
        return first, MC_SIGMAS * sigma + quadrature

    first, bound = integral_and_bound(lambda w: sep.g(brdf.to_local(w, np.broadcast_to(normals[:, None], w.shape))))
    assert np.all(np.abs(light_k - first[..., None] * LIGHT.radiance) <= bound[..., None] * LIGHT.radiance + 1e-12)
    first, bound = integral_and_bound(lambda w: f.eval(w, wo[:, None], normals[:, None]))  # (V, P, C)
    assert np.all(np.abs(radiance - first * LIGHT.radiance) <= bound * LIGHT.radiance + 1e-12)


def test_a_lambertian_vertex_seen_from_behind_keeps_its_radiance():
    """The camera below a floor: its Lambertian radiance is the same as seen from above (two-sided BRDF)."""
    f = brdf.from_material(Material(albedo=np.array([0.7, 0.6, 0.5])))
    sep = brdf.separable(f, K=1)
    points, normals = _floor_points()
    caster = RayCaster(builtin_mesh("icosphere", subdivisions=1), transforms=[Transform(translate=[0, -50, 0])])
    above = ray_traced_direct(points, normals, normals, f, sep, caster, [LIGHT], 16)
    below = ray_traced_direct(points, normals, -normals, f, sep, caster, [LIGHT], 16)
    np.testing.assert_array_equal(below[1], above[1])
    np.testing.assert_allclose(above[1], np.einsum("vkc,kc->vc", above[0], sep.colour), rtol=1e-12)
    assert np.all(above[1] > 0.0)


def _segment_hits_box(a, b, lo, hi) -> np.ndarray:
    """Whether the open segments ``a -> b`` (V, 3) meet the axis-aligned box ``[lo, hi]`` (slab test)."""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - a) / d, (hi - a) / d
    near = np.nanmax(np.where(d == 0, np.where((a >= lo) & (a <= hi), -np.inf, np.inf), np.minimum(t0, t1)), axis=1)
    far = np.nanmin(np.where(d == 0, np.where((a >= lo) & (a <= hi), np.inf, -np.inf), np.maximum(t0, t1)), axis=1)
    return (near <= far) & (far > 0.0) & (near < 1.0)


def test_a_point_light_is_shadowed_exactly_by_a_moved_box():
    """Points on a floor under a point light, a 0.6 m box moved there by its transform: a point is dark
    exactly when its segment to the light meets the box (points near the shadow's edge left out)."""
    sep = brdf.separable(brdf.from_material(Material(albedo=np.array([0.7, 0.7, 0.7]))), K=1)
    points, normals = _floor_points(41, 4.0)
    light = PointLight(position=np.array([0.2, 3.0, -0.1]), intensity=np.array([5.0, 4.0, 3.0]))
    box = builtin_mesh("box", size=[0.6, 0.6, 0.6])
    pose = Transform(translate=np.array([0.5, 1.0, 0.3]))
    caster = RayCaster([box], transforms=[pose])
    f = brdf.from_material(Material(albedo=np.array([0.7, 0.7, 0.7])))
    ours = ray_traced_direct(points, normals, normals, f, sep, caster, [light], 1)[0][:, 0, 0]
    d = light.position - points
    r2 = np.sum(d * d, axis=1)
    lit = light.intensity[0] * (d[:, 1] / np.sqrt(r2)) / r2 / np.pi  # g = 1 / pi for a Lambertian term
    lo, hi = pose.translate - 0.3, pose.translate + 0.3
    dark = _segment_hits_box(points, np.broadcast_to(light.position, points.shape), lo, hi)
    clear = ~_segment_hits_box(points, np.broadcast_to(light.position, points.shape), lo - 0.02, hi + 0.02)
    inside = _segment_hits_box(points, np.broadcast_to(light.position, points.shape), lo + 0.02, hi - 0.02)
    assert inside.sum() >= 20 and clear.sum() >= 200
    np.testing.assert_allclose(ours[inside], 0.0, atol=0.0)
    np.testing.assert_allclose(ours[clear], lit[clear], rtol=1e-12)
    assert np.all(dark[inside])
    # a small area light there: a point whose segments to its four corners all meet the convex box sees none
    # of it (the box's shadow on the light's plane is convex and holds the corners)
    small = AreaLight(center=light.position, u=np.array([0.1, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.1]),
                      radiance=np.array([1.0, 1.0, 1.0]))
    area = ray_traced_direct(points, normals, normals, f, sep, caster, [small], 64)[0][:, 0, 0]
    corners = [small.center + a * small.u + b * small.v for a in (-1, 1) for b in (-1, 1)]
    umbra = np.all([_segment_hits_box(points, np.broadcast_to(c, points.shape), lo + 0.02, hi - 0.02)
                    for c in corners], axis=0)
    assert umbra.sum() >= 10
    np.testing.assert_array_equal(area[umbra], 0.0)
    assert np.all(area[clear & ~dark] > 0.0)


def test_rays_precompute_what_sh_does_and_take_point_lights():
    scene = floor_and_ball()
    def key(scene, options):
        return cache_key(*Interreflection.cache_key_parts(scene, options))

    assert key(scene, InterreflectionOptions(shadows="rays")) == key(scene, InterreflectionOptions(shadows="sh"))
    assert key(scene, InterreflectionOptions(light_samples=16)) == key(scene, InterreflectionOptions())
    light = [PointLight(position=np.array([0.0, 3.0, 0.0]), intensity=np.array([1.0, 1.0, 1.0]))]
    Interreflection.check_lights(light, InterreflectionOptions(shadows="rays"))
    with pytest.raises(ValueError, match="shadows='rays' or 'haar'"):
        Interreflection.check_lights(light, InterreflectionOptions(shadows="sh"))
    with pytest.raises(ValueError, match="light_samples"):
        InterreflectionOptions(light_samples=0)
