"""Interior lights and the light leaving through the portal (the paper's future work, Section 9) against Mitsuba 3.

``sunlit_window_room`` with a point light hung 0.6 m under the ceiling (:func:`lit_room`), the window open,
precomputed once at the defaults with :data:`BOUNCES` bounces and ``leaving_order=`` :data:`LEAVING_ORDER`. Two
frames of the same precomputation: the sky black (the room lit by the lamp alone: the light reaching the window
leaves) and the sky with its sun (both at once). Per surface, direct / indirect / total, against Mitsuba's
per-vertex estimate (:data:`SPP` samples, the same bounces), the reference's noise in quadrature; the direct
reference is exact instead (the room is an empty box: the lamp's ``rho / pi I cos / r^2`` plus the window
quadrature of ``tests/fidelity/test_portals.py``). Goal: issue 17's binding 3% per surface.

The radiance leaving the window (``info["leaving_sh"]``, order-:data:`LEAVING_ORDER` SH over the outward
directions) against a Monte Carlo projection of Mitsuba's radiance along :data:`LEAVING_RAYS` rays from uniform
window points into the room (uniform outward directions): the coefficients as a whole (relative L2, the Monte
Carlo error in quadrature) and the flux the window sends out. Mitsuba takes minutes: ``slow``.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import prtlab
import prtlab.api
from prtlab.pipeline import FrameState
from prtlab.reference import shade_mitsuba
from prtlab.scene import EnvironmentLight, Scene, ShadeResult

from .test_portals import SPP, SUN_GOAL, SURFACES, by_surface, window_quadrature

pytestmark = [pytest.mark.xdist_group("fidelity-portals-interior"), pytest.mark.slow,
              pytest.mark.skipif(os.environ.get("PRTLAB_QUICK") == "1",
                                 reason="slow (Mitsuba, several minutes): make test-slow")]

BOUNCES = 4
LEAVING_ORDER = 4
LEAVING_RAYS = 1 << 21
LAMP = {"type": "point", "position": [0.5, 2.4, 0.5], "intensity": [3.0, 2.6, 2.0]}


def lit_room(sky: bool = True) -> Scene:
    """``sunlit_window_room`` with the :data:`LAMP` inside; the sky black (a zero constant) unless ``sky``."""
    d = prtlab.load_scene("sunlit_window_room").to_dict()
    if not sky:
        d["lights"][0] = {"type": "environment", "constant": [0.0, 0.0, 0.0]}
        d.pop("animation", None)
    d["lights"].append(dict(LAMP))
    return Scene.from_dict(d)


def lamp_direct(scene: Scene) -> np.ndarray:
    """The lamp's direct radiance at the room's vertices, exact in the empty box: ``rho / pi I max(0, cos) / r^2``."""
    room = scene.object("room")
    x, n = room.world_shading_points(), room.world_normals()
    d = np.asarray(LAMP["position"]) - x
    r = np.linalg.norm(d, axis=1)
    cos = np.maximum(np.einsum("vk,vk->v", d, n) / r, 0.0)
    return np.asarray(room.material.diffuse_albedo) / np.pi * (cos / r**2)[:, None] * np.asarray(LAMP["intensity"])


@pytest.fixture(scope="module")
def interior_pre():
    """The room with the lamp and the sky, precomputed at the defaults (``leaving_order`` on)."""
    return prtlab.api.precompute(lit_room(), "portals", progress=False, bounces=BOUNCES, leaving_order=LEAVING_ORDER)


def ours(pre, sky: bool) -> ShadeResult:
    state = FrameState.from_scene(lit_room(sky))
    return pre.shade(state, bounces=BOUNCES)


@pytest.fixture(scope="module", params=["dark", "sky"])
def frame(request, interior_pre):
    """Ours and the reference, per surface, for the sky black (``dark``) or on (``sky``)."""
    sky = request.param == "sky"
    scene = lit_room(sky)
    normals = scene.object("room").world_normals()
    mine = ours(interior_pre, sky)
    ref = shade_mitsuba(scene, bounces=BOUNCES, spp=SPP, seed=11)
    exact = lamp_direct(scene)
    ref.stderr["direct"]["room"] = np.zeros_like(exact)
    if sky:
        fine, coarse = window_quadrature(scene, 128), window_quadrature(scene, 64)
        exact = exact + fine
        ref.stderr["direct"]["room"] = np.abs(fine - coarse)
    ref.direct["room"] = exact
    comparison = prtlab.compare(by_surface(mine, normals), by_surface(ref, normals))
    print(f"\nsunlit_window_room + lamp, sky {'on' if sky else 'black'} ({SPP} spp, {BOUNCES} bounces)\n"
          f"{comparison.table()}")
    return request.param, mine, comparison


CASES = [(s, p) for s in SURFACES for p in ("direct", "indirect", "total")]


@pytest.mark.parametrize("surface, part", CASES)
def test_lamp_and_sky_against_mitsuba(frame, surface, part):
    """Every surface and part within ``hypot(SUN_GOAL, noise)`` of the reference (``check`` refuses a reference
    whose noise is over a third of the goal: such rows are reported, see ``docs/notes/portals.md``, section 14)."""
    name, _, comparison = frame
    try:
        failed = comparison.check(SUN_GOAL, parts=(part,), objects=(surface,))
    except ValueError as err:  # the reference is too noisy to judge this row: reported, not judged
        pytest.xfail(f"{name}: {err}")
    assert failed == [], comparison.table()


def mitsuba_leaving(scene: Scene, portal, order: int, n_rays: int, seed: int):
    """Monte Carlo SH coefficients ``(n^2, 3)`` of the radiance leaving ``portal`` (Mitsuba's path integrator
    along rays from uniform window points into the room, uniform outward directions), their standard errors and
    the flux ``A int Lbar cos``."""
    import prtlab.sh as sh
    from prtlab.reference._mitsuba import _import_mitsuba, _load, _max_depth, _np3, _to_vec

    mi, _ = _import_mitsuba(None)
    mscene = _load(mi, scene, sensor=False)
    depth = _max_depth(BOUNCES, from_camera=True)
    integrator = mi.load_dict({"type": "path", "max_depth": depth, "rr_depth": max(5, depth)})
    rng = np.random.default_rng(seed)
    verts = portal.vertices
    lo, hi = verts.min(0), verts.max(0)
    outward = -portal.normal
    samples, flux = [], []
    chunk = 1 << 18
    for i in range(0, n_rays, chunk):
        m = min(chunk, n_rays - i)
        y = lo + rng.random((m, 3)) * (hi - lo)  # the window is an axis-aligned rectangle (zero extent in z)
        z = rng.random(m)
        phi = 2 * np.pi * rng.random(m)
        s = np.sqrt(1 - z**2)
        local = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)  # uniform over the hemisphere about +z
        w = local * np.sign(outward[2])  # outward is -z or +z: flip
        ray = mi.Ray3f(_to_vec(mi, mi.Point3f, y), _to_vec(mi, mi.Vector3f, -w))
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(seed * 1000 + i // chunk, m)
        radiance, _, _ = integrator.sample(mscene, sampler, mi.RayDifferential3f(ray), None, True)
        L = _np3(radiance)
        samples.append(2 * np.pi * sh.basis(w, order)[:, :, None] * L[:, None, :])
        flux.append(portal.area * 2 * np.pi * np.abs(w[:, 2])[:, None] * L)
    samples, flux = np.concatenate(samples), np.concatenate(flux)
    return (samples.mean(0), samples.std(0, ddof=1) / np.sqrt(len(samples)), flux.mean(0),
            flux.std(0, ddof=1) / np.sqrt(len(flux)))


def flux_of(coeffs, portal) -> np.ndarray:
    """``A int_{outward} Lbar(w) |n . w| dw`` from SH coefficients: the projection of ``|n . w|`` restricted to the
    outward hemisphere (a clamped cosine about the outward normal) needs every band; its order-``n`` part
    is exact for ``Lbar`` of order ``n`` (``Lbar`` is zero inward), computed here by quadrature."""
    import prtlab.sh as sh

    dirs, _ = prtlab.geometry.stratified_sphere(1 << 16, np.random.default_rng(0))
    cos = np.maximum(dirs @ -portal.normal, 0.0)
    return portal.area * (4 * np.pi / len(dirs)) * (cos[:, None] * (sh.basis(dirs, int(np.sqrt(len(coeffs))))
                                                                     @ coeffs)).sum(0)


@pytest.mark.parametrize("sky", [False, True], ids=["dark", "sky"])
def test_leaving_radiance_against_monte_carlo(interior_pre, sky):
    """The SH coefficients of the radiance leaving the window within ``hypot(SUN_GOAL, noise)`` (relative L2 over
    coefficients and channels) of Mitsuba's Monte Carlo projection, and the flux it sends out within 3%."""
    portal = interior_pre._portals()[0]
    scene = lit_room(sky)
    c = ours(interior_pre, sky).info["leaving_sh"][0]
    ref, stderr, flux_ref, flux_err = mitsuba_leaving(scene, portal, LEAVING_ORDER, LEAVING_RAYS, seed=5)
    norm = np.linalg.norm(ref)
    err, noise = np.linalg.norm(c - ref) / norm, np.linalg.norm(stderr) / norm
    flux = flux_of(c, portal)
    flux_rel = np.abs(flux - flux_ref) / flux_ref
    print(f"\nleaving radiance, sky {'on' if sky else 'black'}: coefficients rel L2 {err:.4f} (MC noise {noise:.4f}), "
          f"band 0 ours/ref {c[0] / ref[0]}, flux ours {flux} ref {flux_ref} (stderr {flux_err}), rel {flux_rel}")
    assert noise < SUN_GOAL / 3
    assert err <= np.hypot(SUN_GOAL, noise)
    assert np.all(flux_rel <= np.hypot(SUN_GOAL, flux_err / flux_ref))
