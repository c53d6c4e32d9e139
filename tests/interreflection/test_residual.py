"""Tests of prtlab/interreflection/_residual.py: the residual gather (issue 18) against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import brdf
from prtlab.geometry import RayCaster, builtin_mesh
from prtlab.interreflection import InterreflectionOptions
from prtlab.interreflection._residual import cosine_directions, gather_residual, residual_hits

LAMBERT = brdf.separable(brdf.lambert([0.5, 0.5, 0.5]), 1)


def _square_form_factor(a: float, h: float) -> float:
    """Point-to-parallel-square form factor, the point ``h`` above the centre of a square of half-side ``a``:
    four corner rectangles ``(1 / 2 pi) [X / sqrt(1 + X^2) atan(Y / sqrt(1 + X^2)) + (X <-> Y)]``, X = Y = a/h."""
    x = a / h
    s = np.sqrt(1.0 + x * x)
    return 4.0 * (2.0 * x / s * np.arctan(x / s)) / (2.0 * np.pi)


def test_cosine_directions_are_cosine_weighted():
    """Unit, in the hemisphere, and E[cos] = 2/3 under the density cos / pi (closed form)."""
    normals = np.array([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]])
    d = cosine_directions(normals, 1024)
    assert d.shape == (2, 1024, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    cos = np.einsum("vni,vi->vn", d, normals)
    assert np.all(cos >= 0)
    np.testing.assert_allclose(cos.mean(axis=1), 2.0 / 3.0, atol=0.005)  # stratified: well under 1/sqrt(n)


@pytest.mark.parametrize("h", [0.05, 0.5, 2.0, 5.0])
def test_gather_of_a_constant_residual_is_the_form_factor(h):
    """A square source of constant residual ``r`` (Lambertian, ``h_k = 1``) under a point facing it:
    ``L = r F`` with F the point-to-square form factor: near (h = 0.05, 0.5: the point inside the source's
    bounding sphere, hemisphere rays) and far (h = 2, 5: rays in the sphere's cone)."""
    a = 1.0
    plane = builtin_mesh("plane", size=[2 * a, 2 * a], resolution=[8, 8])
    caster = RayCaster([plane])
    point, normal = np.array([[0.0, h, 0.0]]), np.array([[0.0, -1.0, 0.0]])
    sources = {0: (np.asarray(plane.faces), np.asarray(plane.vertex_normals), LAMBERT, np.zeros(3), np.sqrt(2.0))}
    hits = residual_hits(point, normal, LAMBERT, caster, sources, 4096)
    residual = np.full((len(plane.vertices), 1, 3), 0.3)
    light = gather_residual(hits[0], residual, 1)
    # Lambert: g = 1 / pi, so L = (1 / pi) r int cos = r F
    np.testing.assert_allclose(light[0, 0], 0.3 * _square_form_factor(a, h), rtol=0.02)


def test_the_back_of_a_source_sends_nothing():
    """A point below the plane (which faces +y) sees its back: no hits are kept."""
    plane = builtin_mesh("plane", size=[2, 2], resolution=[2, 2])
    sources = {0: (np.asarray(plane.faces), np.asarray(plane.vertex_normals), LAMBERT, np.zeros(3), np.sqrt(2.0))}
    hits = residual_hits(np.array([[0.0, -0.5, 0.0]]), np.array([[0.0, 1.0, 0.0]]), LAMBERT, RayCaster([plane]),
                         sources, 64)
    assert hits == {}


def test_residual_rays_is_validated():
    with pytest.raises(ValueError, match="residual_rays"):
        InterreflectionOptions(residual_rays=-1)
