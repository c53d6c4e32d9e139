"""Glossy (Phong) receivers and sources of the interreflection pipeline against Monte Carlo.

A Phong material enters the pipeline only through its separable approximation
``f(wi, wo) ~ sum_k g_k(wi) h_k(wo)`` with ``K = K_glossy`` terms (Iwasaki et al. 2007,
Eq. 7, 11-13; :func:`prtlab.brdf.separable`): a receiver's reflected light is
``sum_k h_k(wo) colour_k < L_in, P_n(V g_k cos) >``, a source emits ``h_k(-w_in)`` times its
basis functions. What that costs is derived here with the brdf module's own functions:

* the **separable truncation** of a receiver lit by order-n radiance ``ell`` (SH coefficients) is
  exactly ``< ell, T(wo) - T_K(wo) >`` with ``T(wo) = int f(wi, wo) cos Y(wi) dwi`` (the Phong
  formula, quadrature) and ``T_K(wo) = sum_k colour_k h_k(wo) P_n(g_k cos)``
  (:func:`prtlab.brdf.project_h`, :func:`prtlab.brdf.project_g_cos`); by Cauchy-Schwarz it is at
  most ``||ell|| ||T - T_K||``;
* the **SH truncation** of the light (here: an environment of bands l <= 2 sampled in an equirect
  image, so only the image's bilinear interpolation is left) costs at most
  ``||L - ell Y|| ||f cos||``.

Measured (Phong kd 0.3, ks 0.5, exponent 10 as the journal's Fig. 9, K = 4, order 4): on a glossy
plane under that environment the pipeline's direct light is 13-16 % too bright on average, and
adding the derived ``< ell, T - T_K >`` brings every vertex to Monte Carlo within 4 standard errors
(z RMS 0.93): the glossy direct path computes exactly the separable BRDF. At K = 8 the mean is
within 0.5 %, at K = 16 within 0.2 %. ``brdf.transfer_error`` of this BRDF (order 4) is 0.63 / 0.34
/ 0.13 at K = 1 / 4 / 8: K = 4 (the paper's) is a coarse approximation of a Phong lobe of exponent 10.
Under the Fig. 9 area light the same plane's error splits exactly into the separation (+20-27 %) and
the order-4 SH truncation of light and lobe (-2.2..-3.5 %; a Lambertian plane's: +1.4 %).

Vertices facing away from the camera are left out for glossy receivers: there ``h_k`` takes its
horizon value (:func:`prtlab.brdf.project_h`) while the reference evaluates the Phong formula as
given below the horizon; such vertices are not seen in an image (measured on a glossy ball:
+16-23 % there, within 1 % on the camera-facing vertices at K = 16).

One bounce (quick fields, per-object means of the camera-facing vertices, 128 paths), against
the all-diffuse scene's +3.7 % (ball indirect); the means are held to the paper's indirect goal by
``mean_bound`` of test_pipeline.py (``|mean d| <= 0.15 rms(ref)``, a necessary condition of a
relative RMS of 15 %, plus ``MC_SIGMAS`` standard errors of the reference's mean):

* diffuse source onto a glossy receiver: ball indirect +15..17 % at K = 4, +3.5 % at K = 16;
  adding the derived separable term ``< ell_ind, T - T_K >`` (``ell_ind``: the floor's radiance
  at the ball's vertices as the pipeline represents it, ray-cast) gives +3.5..3.8 %;
* glossy source onto a diffuse receiver: ball indirect +9 % at K = 4, +8 % at K = 16; the
  glossy source adds about 4-5 % to the diffuse machinery's bias (not traced to a stage yet; the
  candidates are its view-dependent basis radiance at SH order 4 and the PCA fit of its K light
  terms), bounded with the indirect goal plus the source's own separable error toward the receiver (relative RMS over the floor's vertices,
  0.13-0.15 at K = 4; a loose bound: the ball integrates it, and K = 16 gives nearly the same +8 %).

Fig. 7, reduced (``data/scenes/interreflection_teapots.yaml``, defaults, one bounce, Mitsuba 3 at
``TEAPOTS_SPP``): figures in ``TEAPOTS_KNOWN``. With the ray-traced direct light (``shadows="rays"``) the
direct light is within 1.2 % on every object (the glossy teapots' too: it is evaluated with the Phong
BRDF itself) and the diffuse objects' totals meet 5 %; the glossy teapots' indirect light misses on the
K = 4 separation. With the paper's order-4 SH direct light (256 spp) no total met 5 %
(0.15-0.20 on diffuse objects); with both glossy teapots made Lambertian the indirect light was 0.12-0.22
everywhere.
"""

from __future__ import annotations

import numpy as np
import pytest

from prtlab import brdf, sh
from prtlab.geometry import equirect_directions
from prtlab.interreflection import Interreflection, basis_radiance_at, fit_weights
from prtlab.pipeline import FrameState
from prtlab.reference import path_trace
from prtlab.scene import AreaLight, EnvironmentLight, Material, Scene, environment_sh
from tests.conftest import MC_SIGMAS
from tests.interreflection.test_pipeline import GOAL, QUICK, mean_bound

GLOSSY = {"type": "phong", "kd": [0.3, 0.25, 0.2], "ks": [0.5, 0.5, 0.5], "exponent": 10}
RED = {"type": "diffuse", "albedo": [0.8, 0.3, 0.3]}
BLUE = {"type": "diffuse", "albedo": [0.3, 0.4, 0.8]}
ORDER = QUICK.get("order", 4)
#: Quadrature degree of the derived terms (the Phong lobe of exponent 10 and the clamped cosine;
#: degree 63 and 95 agree to 1e-4 of the value).
DEGREE = 63


def smooth_environment(height: int = 64, width: int = 128) -> EnvironmentLight:
    """Bands l <= 2 (brighter above and toward +x), sampled in an equirect image."""
    d = equirect_directions(height, width)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    base = 1.0 + 0.8 * y + 0.5 * x + 0.6 * (y * y - 1.0 / 3.0) + 0.4 * x * z
    return EnvironmentLight(image=np.stack([base, 0.9 * base, 0.7 * base + 0.1], axis=-1))


def _scene(objects, camera):
    scene = Scene.from_dict({"objects": objects, "lights": [{"type": "environment", "constant": [1, 1, 1]}],
                             "camera": camera})
    scene.lights = [smooth_environment()]
    return scene


def glossy_plane():
    return _scene([{"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [10, 10]},
                    "material": GLOSSY}],
                  {"position": [0.5, 1.2, 3.0], "look_at": [0, 0, 0]})


def ball_over_floor(floor_material, ball_material):
    return _scene([
        {"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [12, 12]},
         "material": floor_material},
        {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 3},
         "transform": {"translate": [0, 0.7, 0]}, "material": ball_material},
    ], {"position": [0, 2.0, 4.0], "look_at": [0, 0.4, 0]})


def _view(scene, obj):
    """World shading points, normals and unit directions toward the camera of one object."""
    x, n = obj.world_shading_points(), obj.world_normals()
    wo = np.asarray(scene.camera.position, float) - x
    return x, n, wo / np.linalg.norm(wo, axis=1, keepdims=True)


def separable_transfer(material, sep, normals, wo, order=ORDER, degree=DEGREE):
    """``T(wo)`` (exact Phong, quadrature) and ``T_K(wo)`` (what the pipeline uses), (V, n*n, C) each,
    and ``||f cos||`` (V, C) over the incident directions."""
    model = brdf.from_material(material)
    dirs, w = sh.quadrature(1, degree)
    fc = model.eval(dirs[None], wo[:, None], normals[:, None]) * np.maximum(normals @ dirs.T, 0.0)[..., None]
    T = np.einsum("d,vdc,di->vic", w, fc, sh.basis(dirs, order))
    TK = np.einsum("vk,kc,vki->vic", brdf.project_h(sep, wo, normals), sep.colour,
                   brdf.project_g_cos(sep, normals, order))
    return T, TK, np.sqrt(np.einsum("d,vdc->vc", w, fc**2))


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    from prtlab.cache import Cache

    return Cache(tmp_path_factory.mktemp("prtlab-cache-glossy"), progress=False)


def _precompute(scene, cache, **options):
    return Interreflection.precompute(scene, dict(QUICK, **options), cache=cache, progress=False)


# --------------------------------------------------------------------------- (a) direct light on a glossy receiver


def test_glossy_direct_is_the_separable_brdf_against_monte_carlo(cache):
    """A glossy plane under a smooth environment, seen from the camera (no visibility: a plane sees
    none of itself). Per vertex: our direct light plus the derived separable term ``< ell, T - T_K >``
    is Monte Carlo within ``MC_SIGMAS`` standard errors plus the light's SH residual bound; our
    direct light itself is within the Cauchy-Schwarz bound of the separable truncation."""
    scene = glossy_plane()
    pre = _precompute(scene, cache)
    ours = pre.shade(bounces=0).direct["floor"]
    ref = path_trace(scene, 0, 256, np.random.default_rng(1))
    truth, se = ref.direct["floor"], ref.stderr["direct"]["floor"]
    obj = scene.object("floor")
    _, n, wo = _view(scene, obj)
    env = scene.lights[0]
    T, TK, norm_fc = separable_transfer(obj.material, pre.seps["floor"], n, wo)
    ell = environment_sh(env, ORDER)
    dirs, w = sh.quadrature(1, DEGREE)
    residual = np.sqrt(np.einsum("d,dc->c", w, (env.radiance(dirs) - sh.basis(dirs, ORDER) @ ell) ** 2))
    light_bound = residual * norm_fc  # |< L - ell Y, f cos >|
    predicted = np.einsum("ic,vic->vc", ell, T - TK)  # truth - ours from the K-term truncation
    sep_bound = np.linalg.norm(ell, axis=0) * np.linalg.norm(T - TK, axis=1)
    assert np.all(light_bound < 0.01 * truth)  # the environment is band-limited up to its interpolation
    assert np.all(np.abs(ours + predicted - truth) <= MC_SIGMAS * se + light_bound)
    assert np.all(np.abs(ours - truth) <= MC_SIGMAS * se + sep_bound + light_bound)
    # what K = 4 costs here (module docstring): 13-16 % too bright, not noise
    ratio = ours.mean(0) / truth.mean(0)
    assert np.all((ratio > 1.10) & (ratio < 1.20)), ratio
    # and the view dependence is real: the glossy radiance varies far more across the plane than a
    # Lambertian plane's would under this (smooth) environment
    assert np.ptp(truth[:, 0]) > 0.3 * truth[:, 0].mean()


def light_integral(light, material, points, normals, wo, n_nodes):
    """``int_A f(w_y, wo) max(0, n . w_y) L_e max(0, -n_l . w_y) / |y - x|^2 dA_y`` (V, C): the exact direct
    light of an unoccluded area light, by a tensor Gauss-Legendre rule over the parallelogram."""
    t, w = np.polynomial.legendre.leggauss(n_nodes)
    s_, t_ = np.meshgrid(t, t, indexing="ij")
    y = light.center + s_.reshape(-1, 1) * light.u + t_.reshape(-1, 1) * light.v  # (P, 3)
    dA = np.outer(w, w).ravel() * np.linalg.norm(np.cross(light.u, light.v))
    d = y[None] - points[:, None]  # (V, P, 3)
    r2 = np.sum(d * d, axis=-1)
    wy = d / np.sqrt(r2)[..., None]
    geometric = np.maximum(np.sum(normals[:, None] * wy, -1), 0.0) * np.maximum(-(wy @ light.normal), 0.0) / r2
    f = brdf.from_material(material).eval(wy, wo[:, None], normals[:, None])  # (V, P, C)
    return np.einsum("vp,p,vpc->vc", geometric, dA, f) * light.radiance


def test_glossy_direct_under_an_area_light_costs_the_sh_truncation_of_the_lobe(cache):
    """A glossy plane under the Fig. 9 area light (0.6 x 0.6, 2.5 up). The pipeline's direct light is
    exactly ``sum_k h_k colour_k < ell_A, P_n(g_k cos) >`` with ``ell_A`` the light's order-n SH
    (:func:`prtlab.shadowfields.area_light_sh`), so its error against the true integral (a Gauss-Legendre
    rule over the light, itself held to Monte Carlo within ``MC_SIGMAS``) is exactly
    ``< ell_A, T - T_K >`` (the K-term separation) plus ``int L f cos - < ell_A, T >`` (the SH
    truncation of light and lobe: ``< L - P_n L, f cos - P_n(f cos) >``). Measured (mean over the
    plane): the separation makes it 20-27 % too bright (K = 4; the channels differ by ``kd``), the
    truncation 2.2-3.5 % too dark; on a Lambertian plane the truncation is 1.4 % (too bright). Without
    visibility the order-4 truncation of a lobe of exponent 10 is thus small: the large SH error of
    the glossy teapots (Fig. 7 below) comes with their visibility products."""
    from prtlab.shadowfields import area_light_sh

    scene = glossy_plane()
    scene.lights = [fig9_area_light()]
    pre = _precompute(scene, cache, shadows="sh")  # the paper's SH direct light, whose error this splits
    ours = pre.shade(bounces=0).direct["floor"]
    ref = path_trace(scene, 0, 256, np.random.default_rng(2))
    truth, se = ref.direct["floor"], ref.stderr["direct"]["floor"]
    obj = scene.object("floor")
    x, n, wo = _view(scene, obj)
    light = scene.lights[0]
    exact = light_integral(light, obj.material, x, n, wo, 48)
    quadrature = np.abs(exact - light_integral(light, obj.material, x, n, wo, 24))  # its own error, at most
    assert np.all(np.abs(exact - truth) <= MC_SIGMAS * se + quadrature)
    ell = area_light_sh(light, x, ORDER)  # (V, n2, C)
    T, TK, _ = separable_transfer(obj.material, pre.seps["floor"], n, wo)
    np.testing.assert_allclose(ours, np.einsum("vic,vic->vc", ell, TK), rtol=1e-9, atol=1e-12)
    separation = np.einsum("vic,vic->vc", ell, T - TK)
    truncation = exact - np.einsum("vic,vic->vc", ell, T)
    np.testing.assert_allclose(ours + separation + truncation, exact, rtol=1e-9, atol=1e-12)
    assert np.all(np.abs(ours - truth) <= MC_SIGMAS * se + quadrature + np.abs(separation + truncation))
    shares = truncation.mean(0) / exact.mean(0), -separation.mean(0) / exact.mean(0)
    assert np.all((shares[0] > 0.0) & (shares[0] < 0.06)) and np.all((shares[1] > 0.15) & (shares[1] < 0.35)), shares
    # a Lambertian plane: the SH truncation of the clamped cosine against the same light
    lambert = Material(type="diffuse", albedo=np.full(3, 0.7))
    T_l, _, _ = separable_transfer(lambert, brdf.separable(brdf.from_material(lambert), 1), n, wo)
    exact_l = light_integral(light, lambert, x, n, wo, 48)
    lambert_share = (exact_l - np.einsum("vic,vic->vc", ell, T_l)).mean(0) / exact_l.mean(0)
    assert np.all((lambert_share > -0.03) & (lambert_share < 0.0)), lambert_share


def fig9_area_light():
    """The area light of the Fig. 9 scene (``data/scenes/interreflection_fig9.yaml``)."""
    return AreaLight(center=np.array([0.3, 2.5, 0.4]), u=np.array([0.3, 0.0, 0.0]), v=np.array([0.0, 0.0, 0.3]),
                     radiance=np.full(3, 30.0))


# --------------------------------------------------------------------------- one bounce


def _facing(scene, name):
    _, n, wo = _view(scene, scene.object(name))
    return np.sum(n * wo, axis=1) > 0.0


@pytest.fixture(scope="module")
def diffuse_onto_glossy(cache):
    scene = ball_over_floor(RED, GLOSSY)
    pre = _precompute(scene, cache)
    return pre, pre.shade(bounces=1), path_trace(scene, 1, 128, np.random.default_rng(3))


@pytest.fixture(scope="module")
def glossy_onto_diffuse(cache):
    scene = ball_over_floor(GLOSSY, BLUE)
    pre = _precompute(scene, cache)
    return pre, pre.shade(bounces=1), path_trace(scene, 1, 128, np.random.default_rng(3))


def test_one_bounce_from_a_diffuse_source_onto_a_glossy_receiver(diffuse_onto_glossy):
    """A red floor lights a glossy ball. The ball's indirect light (camera-facing vertices) plus the
    derived separable term ``< ell_ind, T - T_K >`` (``ell_ind``: the floor's radiance at the ball's
    shading points, :func:`basis_radiance_at` with the pipeline's weights) is Monte Carlo within the
    indirect goal (``mean_bound``, test_pipeline.py); the ball's direct light as
    well (the separable term of its direct light, against the unshadowed environment, added)."""
    pre, res, ref = diffuse_onto_glossy
    scene = pre.scene
    ball, floor = scene.object("ball"), scene.object("floor")
    x, n, wo = _view(scene, ball)
    state = FrameState.from_scene(scene)
    geo = pre._frame_geometry(state)
    light_k, _ = pre.direct_step(state, geo, pre.direct_transfer(geo, pre._occlusion(geo)))
    weights = fit_weights(pre.bases["floor"], light_k["floor"], pre.seps["floor"].colour)  # (K, N, C)
    S = basis_radiance_at(floor.mesh, pre.bases["floor"].basis, pre.seps["floor"], x, ORDER)  # (V, K, N, n2)
    ell_ind = np.einsum("vkni,knc->vic", S, weights)
    T, TK, _ = separable_transfer(ball.material, pre.seps["ball"], n, wo)
    predicted = np.einsum("vic,vic->vc", ell_ind, T - TK)
    m = _facing(scene, "ball")
    truth, se = ref.indirect["ball"][m], ref.stderr["indirect"]["ball"][m]
    err, bound = mean_bound(res.indirect["ball"][m] + predicted[m], truth, se, GOAL["indirect"])
    assert np.all(err <= bound), (err, bound, truth.mean(0))
    # the derived separable term is what K = 4 costs here: without it the mean is further from Monte Carlo
    assert np.all(np.abs(res.indirect["ball"][m].mean(0) - truth.mean(0)) > err), err
    # the red floor tints the glossy ball
    ind = res.indirect["ball"][m].mean(0)
    assert ind[0] > 1.5 * ind[2]
    # direct light of the glossy ball, camera-facing vertices
    ell = environment_sh(scene.lights[0], ORDER)
    predicted_direct = np.einsum("ic,vic->vc", ell, T - TK)
    truth, se = ref.direct["ball"][m], ref.stderr["direct"]["ball"][m]
    err, bound = mean_bound(res.direct["ball"][m] + predicted_direct[m], truth, se, GOAL["direct"])
    assert np.all(err <= bound), (err, bound, truth.mean(0))


def test_one_bounce_from_a_glossy_source_onto_a_diffuse_receiver(glossy_onto_diffuse):
    """A glossy floor lights a diffuse ball. The receiver's BRDF is exact (Lambert, K = 1); the source
    emits ``sum_k h_k(-w_in) colour_k L_k``. Bound of the ball's mean indirect light: the diffuse
    indirect goal (``mean_bound``) plus the source's separable error toward the receiver, derived on the
    floor's vertices under the (unshadowed) environment: ``rms_x < ell, T - T_K >(x -> ball centre)``
    relative to ``rms_x < ell, T >``."""
    pre, res, ref = glossy_onto_diffuse
    scene = pre.scene
    floor = scene.object("floor")
    xf, nf = floor.world_shading_points(), floor.world_normals()
    to_ball = scene.object("ball").transform.translate - xf
    to_ball /= np.linalg.norm(to_ball, axis=1, keepdims=True)
    T, TK, _ = separable_transfer(floor.material, pre.seps["floor"], nf, to_ball)
    ell = environment_sh(scene.lights[0], ORDER)
    emitted, error = np.einsum("ic,vic->vc", ell, T), np.einsum("ic,vic->vc", ell, T - TK)
    tau_source = np.sqrt(np.mean(error**2, axis=0) / np.mean(emitted**2, axis=0))
    m = _facing(scene, "ball")  # as seen in an image (all vertices: +14 % at K = 16, +8 % all-diffuse)
    truth, se = ref.indirect["ball"][m], ref.stderr["indirect"]["ball"][m]
    err, bound = mean_bound(res.indirect["ball"][m], truth, se, GOAL["indirect"] + tau_source)
    assert np.all(err <= bound), (err, bound, truth.mean(0))
    # the glossy floor's direct light (camera-facing: all of a plane under this camera) as in (a)
    _, n, wo = _view(scene, floor)
    T, TK, _ = separable_transfer(floor.material, pre.seps["floor"], n, wo)
    truth, se = ref.direct["floor"], ref.stderr["direct"]["floor"]
    err, bound = mean_bound(res.direct["floor"] + np.einsum("ic,vic->vc", ell, T - TK), truth, se,
                            GOAL["direct"])
    assert np.all(err <= bound), (err, bound, truth.mean(0))


@pytest.mark.slow
@pytest.mark.parametrize("which", ["diffuse_onto_glossy", "glossy_onto_diffuse"])
def test_one_bounce_with_many_separable_terms_is_the_diffuse_machinery(which, cache):
    """With K = 16 (``brdf.transfer_error`` 0.03 here) the glossy ball's / the diffuse ball's indirect
    light is within the indirect goal of Monte Carlo (``mean_bound``) without any separable correction
    (measured: +3.5 % and +8 %)."""
    materials = {"diffuse_onto_glossy": (RED, GLOSSY), "glossy_onto_diffuse": (GLOSSY, BLUE)}[which]
    scene = ball_over_floor(*materials)
    res = _precompute(scene, cache, K_glossy=16).shade(bounces=1)
    ref = path_trace(scene, 1, 128, np.random.default_rng(3))
    m = _facing(scene, "ball")
    err, bound = mean_bound(res.indirect["ball"][m], ref.indirect["ball"][m], ref.stderr["indirect"]["ball"][m],
                            GOAL["indirect"])
    assert np.all(err <= bound), (err, bound)


# --------------------------------------------------------------------------- Fig. 7, reduced, against Mitsuba 3

#: Mitsuba samples per vertex of Fig. 7: relative noise within a third of the goals (``Comparison.check``).
TEAPOTS_SPP = 2048
TEAPOTS = ("floor", "wall_back", "wall_left", "teapot_glossy", "teapot_purple", "teapot_yellow")
#: Measured rel_rms at the defaults (one bounce, Mitsuba at TEAPOTS_SPP) with what limits them; strict: a fix fails
#: loudly. Every direct part is within 1.2 % (``shadows="rays"``: the radiance toward the camera with the BRDF itself);
#: the glossy teapots' indirect light is the K = 4 separable BRDF's.
_SEPARABLE = ("the K = 4 separable Phong (exponent 10; +13-16 % on a glossy plane under smooth light, "
              "test_glossy_direct_is_the_separable_brdf_against_monte_carlo)")
TEAPOTS_KNOWN: dict = {
    ("teapot_glossy", "indirect"): f"0.287 (noise 0.027, mean +11 %): {_SEPARABLE}",
    ("teapot_glossy", "total"): f"0.077 (noise 0.009, mean +3.1 %): its indirect light, {_SEPARABLE}",
    ("teapot_purple", "indirect"): f"0.226 (noise 0.030, mean +4 %): {_SEPARABLE}",
    ("teapot_purple", "total"): f"0.055 (noise 0.009): its indirect light, {_SEPARABLE}",
}
# teapot_yellow's indirect light met the goal with ``residual_near`` (0.161 -> 0.104: the floor's radiance under it
# evaluated at the gather's near hits instead of interpolated from its vertices); glossy 0.359 -> 0.287.
# Diagnosis with the paper's SH direct light (quick fields: 8 radii x 6 x 8 x 8, N = 8 from 64 lights; Mitsuba
# 256 spp), direct light rel. RMS (mean) of glossy / purple / yellow teapot: K = 4 0.510 (+20 %) / 0.472 (+24 %) /
# 0.188 (+16 %); K = 16 0.422 (+27 %) / 0.327 (+8 %) / 0.188; K = 16 with shadows="haar" (16-texel faces) 0.167
# (-12 %) / 0.131 / 0.027, and with shadows="haar" at K = 4 0.463 (-11 %) / 0.415 (+14 %) / 0.027: a Phong lobe of
# exponent 10 under a small area light needs more than 4 SH bands, and beyond order-4 light the K-term separation
# errs more than brdf.transfer_error(sep, 4) says (relative_error() of this BRDF: 0.59 at K = 4, 0.21 at K = 16).


def scored_vertices(scene, name):
    """Vertices an image shows and whose radiance is well defined: not the bottoms of objects standing on
    the floor (``docs/DECISIONS.md``) and, for glossy objects, facing the camera (module docstring)."""
    obj = scene.object(name)
    keep = np.ones(obj.n_vertices, bool)
    if not name.startswith(("floor", "wall")):
        keep &= obj.world_vertices()[:, 1] > 0.01
    if obj.material.type == "phong":
        keep &= _facing(scene, name)
    return keep


@pytest.fixture(scope="module")
def teapots_scene():
    import prtlab
    from prtlab.reference import shade_mitsuba

    pytest.importorskip("mitsuba")
    scene = prtlab.load_scene("interreflection_teapots")
    ref = shade_mitsuba(scene, bounces=1, spp=TEAPOTS_SPP, seed=0)
    ours = Interreflection.precompute(scene, {}, progress=False).shade(bounces=1)
    return scene, ours, ref


def _teapots_case(obj, part):
    key = (obj, part)
    marks = [pytest.mark.xfail(strict=True, reason=TEAPOTS_KNOWN[key])] if key in TEAPOTS_KNOWN else []
    return pytest.param(obj, part, marks=marks, id=f"{obj}-{part}")


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize("obj, part", [_teapots_case(o, p) for o in TEAPOTS for p in GOAL])
def test_fig7_teapots_against_mitsuba(teapots_scene, obj, part):
    """Fig. 7 reduced (``data/scenes/interreflection_teapots.yaml``), one bounce, defaults, against Mitsuba at
    ``TEAPOTS_SPP``: ``rel_rms <= hypot(goal, noise)`` on the scored vertices (:func:`scored_vertices`)."""
    import prtlab

    scene, ours, ref = teapots_scene
    comparison = prtlab.compare(ours, ref, objects=[obj], parts=[part], masks={obj: scored_vertices(scene, obj)})
    failures = comparison.check(GOAL[part])
    assert not failures, failures
