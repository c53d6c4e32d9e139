"""Direct transfer through a window onto floor points, against closed forms and prtlab.reference."""

import numpy as np
import pytest

from prtlab.geometry import RayCaster, cubemap_directions, equirect_lookup
from prtlab.portals import PortalsOptions, direct_pass, direct_transfer, find_portals, shell_light
from prtlab.reference import radiance_at
from prtlab.scene import Scene
from prtlab.wavelet import encode_transfer, haar2d

from ..conftest import MC_SIGMAS
from .conftest import SKY, window_box

FLOOR = np.array([[0.3, 0.0, -0.8], [-0.4, 0.0, 0.6]])
UP = np.array([[0.0, 1.0, 0.0]] * 2)


def _window_form_factor(x, m=1000):
    """(1/pi) int cos_v cos_p / d^2 dA over the 1 x 1 window at z = -1.5 (midpoint rule, 1e6 cells)."""
    a = (np.arange(m) + 0.5) / m
    gx, gy = np.meshgrid(-0.5 + a, 0.9 + a)
    p = np.stack([gx, gy, np.full_like(gx, -1.5)], -1)
    d = p - x
    r = np.linalg.norm(d, axis=-1)
    return float((d[..., 1] / r * (x[2] - p[..., 2]) / r / r**2).sum() / m / m / np.pi)


def _repeats(scene, points, normals, n_samples, res, n_rep=6, seed=1):
    caster = RayCaster(scene)
    (portal,) = find_portals(scene)
    rng = np.random.default_rng(seed)
    return np.stack([direct_transfer(caster, points, normals, portal, n_samples, res, rng) for _ in range(n_rep)])


def test_known_answer_constant_sky(constant_box):
    """sum_k T_k = (1/pi) int_window cos cos / d^2: the unoccluded form factor."""
    reps = _repeats(constant_box, FLOOR, UP, 4096, 8).sum(axis=(2, 3, 4))  # (rep, V)
    mean, se = reps.mean(0), reps.std(0, ddof=1) / np.sqrt(len(reps))
    exact = np.array([_window_form_factor(x) for x in FLOOR])
    assert np.all(np.abs(mean - exact) <= MC_SIGMAS * se + 1e-6 * exact)


def test_against_reference_under_sky(sky_box, rng):
    """Direct radiance under a sky vs the reference path tracer (bounces=0).

    Bound: MC_SIGMAS * sqrt(se_ref^2 + se_ours^2) plus the cubemap-resolution bound
    ``sum_k T_k (max_{texel k} L - min_{texel k} L)`` (max/min over 8x8 sub-texel directions),
    plus the 8-bit quantisation bound ``scale / 510 * sum |L coefficients|``.
    """
    res = 16
    albedo = 0.7
    reps = _repeats(sky_box, FLOOR, UP, 4096, res)
    cube = shell_light(sky_box.environment, res)
    values = np.einsum("rvfij,fijc->rvc", reps, cube) * albedo
    ours, se_ours = values.mean(0), values.std(0, ddof=1) / np.sqrt(len(values))
    fine = equirect_lookup(sky_box.environment.image, cubemap_directions(res * 8)).reshape(6, res, 8, res, 8, 3)
    spread = fine.max(axis=(2, 4)) - fine.min(axis=(2, 4))
    t_mean = reps.mean(0)
    resolution_bound = albedo * np.einsum("vfij,fijc->vc", t_mean, spread)
    sparse = encode_transfer(t_mean)
    quant = albedo * sparse.scale[:, None] / 510 * np.maximum(np.abs(cube).sum((0, 1, 2)),
                                                            np.abs(haar2d(cube, channels=True)).sum((0, 1, 2)))
    encoded = direct_pass(sparse, np.full((2, 3), albedo), cube)
    assert np.all(np.abs(encoded - ours) <= quant + 1e-12)
    ref = radiance_at(sky_box, FLOOR, UP, UP, 16384, rng, material=sky_box.objects[0].material)
    bound = MC_SIGMAS * np.sqrt(ref.direct_stderr**2 + se_ours**2) + resolution_bound + quant
    assert np.all(np.abs(encoded - ref.direct) <= bound), (encoded, ref.direct, bound)


def test_backward_occlusion():
    """A slab outside the window blocks part of the sky: the backward rays see it (Fig. 4(b))."""
    base = window_box()
    scene = Scene.from_dict({
        "objects": [o.to_dict() for o in base.objects] + [{
            "name": "slab", "mesh": {"builtin": "plane", "size": [3, 3], "resolution": [1, 1]},
            "transform": {"translate": [0, 2.0, -3.2]}, "material": {"type": "diffuse", "albedo": [0, 0, 0]}}],
        "lights": [{"type": "environment", "constant": [1.0, 1.0, 1.0]}],
        "camera": base.camera.to_dict(),
    })
    reps = _repeats(scene, FLOOR[:1], UP[:1], 4096, 8).sum(axis=(2, 3, 4))[:, 0]
    mean, se = reps.mean(), reps.std(ddof=1) / np.sqrt(len(reps))
    unblocked = _window_form_factor(FLOOR[0])
    assert mean < 0.9 * unblocked - MC_SIGMAS * se  # the slab (z < -1.7) is outside the room
    ref = radiance_at(scene, FLOOR[:1], UP[:1], UP[:1], 32768, np.random.default_rng(5),
                      material=scene.objects[0].material)
    ours = 0.7 * mean
    assert abs(ours - ref.direct[0, 0]) <= MC_SIGMAS * np.hypot(ref.direct_stderr[0, 0], 0.7 * se)


def test_direct_pass_tiers(rng):
    transfer = np.where(rng.random((20, 6, 4, 4)) < 0.2, rng.random((20, 6, 4, 4)), 0.0)
    sparse = encode_transfer(transfer)
    albedo = rng.random((20, 3))
    cube = rng.random((6, 4, 4, 3))
    from .test_shade import direct_float32_bound

    assert np.all(np.abs(direct_pass(sparse, albedo, cube) - direct_pass(sparse, albedo, cube, "reference"))
                  <= direct_float32_bound(sparse, albedo, cube))
    with pytest.raises(ValueError, match=r"albedo must have shape \(20, 3\)"):
        direct_pass(sparse, albedo[:3], cube)
    with pytest.raises(ValueError, match="'numba' or 'reference'"):
        direct_pass(sparse, albedo, cube, "fast")


def test_direct_transfer_errors(constant_box):
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=r"points must have shape \(V, 3\)"):
        direct_transfer(caster, np.zeros(3), UP[:1], portal, 4, 4, rng)
    with pytest.raises(ValueError, match="normals must have the shape"):
        direct_transfer(caster, FLOOR, UP[:1], portal, 4, 4, rng)
    with pytest.raises(ValueError, match="finite"):
        direct_transfer(caster, FLOOR * np.nan, UP, portal, 4, 4, rng)
    with pytest.raises(ValueError, match="n_samples"):
        direct_transfer(caster, FLOOR, UP, portal, 0, 4, rng)
    with pytest.raises(TypeError, match="RayCaster"):
        direct_transfer(None, FLOOR, UP, portal, 4, 4, rng)
    empty = direct_transfer(caster, np.zeros((0, 3)), np.zeros((0, 3)), portal, 4, 4, rng)
    assert empty.shape == (0, 6, 4, 4)


def test_glossy_direct_against_reference(sky_box, rng):
    """Phong floor points viewed along discretised directions: ks * S . L + kd * T . L vs the reference.

    Bound as in the diffuse test: MC_SIGMAS combined standard errors plus the cubemap-resolution bound.
    """
    from prtlab.portals import glossy_direct_transfer
    from prtlab.scene import Material

    res = 16
    views = np.array([[0.0, 0.6, 0.8], [0.3, 0.9, -0.3]])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    material = Material(type="phong", kd=np.full(3, 0.3), ks=np.full(3, 0.5), exponent=10.0)
    caster = RayCaster(sky_box)
    (portal,) = find_portals(sky_box)
    gen = np.random.default_rng(3)
    cube = shell_light(sky_box.environment, res)
    fine = equirect_lookup(sky_box.environment.image, cubemap_directions(res * 8)).reshape(6, res, 8, res, 8, 3)
    spread = fine.max(axis=(2, 4)) - fine.min(axis=(2, 4))
    values, bounds = [], []
    for _ in range(6):
        spec = glossy_direct_transfer(caster, FLOOR, UP, portal, views, 10.0, 2048, res, gen)  # (V, J, 6, r, r)
        diff = direct_transfer(caster, FLOOR, UP, portal, 2048, res, gen)
        # vertex v viewed along views[v]
        s = spec[np.arange(2), np.arange(2)]
        transfer = 0.5 * s + 0.3 * diff
        values.append(np.einsum("vfij,fijc->vc", transfer, cube))
        bounds.append(np.einsum("vfij,fijc->vc", transfer, spread))
    values = np.array(values)
    ours, se_ours = values.mean(0), values.std(0, ddof=1) / np.sqrt(len(values))
    ref = radiance_at(sky_box, FLOOR, UP, views, 16384, rng, material=material)
    bound = MC_SIGMAS * np.sqrt(ref.direct_stderr**2 + se_ours**2) + np.mean(bounds, axis=0)
    assert np.all(np.abs(ours - ref.direct) <= bound), (ours, ref.direct, bound)
    with pytest.raises(ValueError, match=r"view_dirs must be a finite \(J, 3\)"):
        glossy_direct_transfer(caster, FLOOR, UP, portal, np.zeros(3), 10.0, 4, 4, gen)
    with pytest.raises(ValueError, match="exponent"):
        glossy_direct_transfer(caster, FLOOR, UP, portal, views, -1.0, 4, 4, gen)


def test_view_interpolation_and_lipschitz():
    from prtlab.portals import phong_lipschitz, view_interpolation

    grid = cubemap_directions(4).reshape(-1, 3)
    index, weight = view_interpolation(grid, 4)  # a texel centre picks itself
    np.testing.assert_array_equal(index[np.arange(96), weight.argmax(1)], np.arange(96))
    np.testing.assert_allclose(weight.max(1), 1.0)
    d = np.random.default_rng(0).normal(size=(500, 3))
    index, weight = view_interpolation(d, 3)
    np.testing.assert_allclose(weight.sum(1), 1.0)
    assert weight.min() >= 0 and index.max() < 54
    a = np.linspace(0, np.pi / 2, 200001)
    for e in (1.0, 10.0, 40.0):
        g = (e + 2) / (2 * np.pi) * np.cos(a) ** e
        assert np.abs(np.diff(g) / np.diff(a)).max() == pytest.approx(phong_lipschitz(e), rel=1e-4)
    assert phong_lipschitz(0.5) == np.inf and phong_lipschitz(0.0) == 0.0
    with pytest.raises(ValueError, match=r"view_dirs must be a finite \(N, 3\)"):
        view_interpolation(np.zeros(3), 4)


def _check_glossy_against_reference(values, bounds, scene, views, e, kd, ks, rng):
    """Repeated estimates ``values`` of the floor points' radiance toward ``views`` within ``MC_SIGMAS`` combined
    standard errors plus the mean of their ``bounds`` of a Monte Carlo reference (a Phong ``kd, ks, e`` floor);
    returns (their mean, the reference)."""
    from prtlab.scene import Material

    values = np.array(values)
    ours, se_ours = values.mean(0), values.std(0, ddof=1) / np.sqrt(len(values))
    material = Material(type="phong", kd=np.full(3, kd), ks=np.full(3, ks), exponent=e)
    ref = radiance_at(scene, FLOOR, UP, views, 16384, rng, material=material)
    bound = MC_SIGMAS * np.sqrt(ref.direct_stderr**2 + se_ours**2) + np.mean(bounds, axis=0)
    assert np.all(np.abs(ours - ref.direct) <= bound), (ours, ref.direct, bound)
    return ours, ref.direct


def test_glossy_direct_view_interpolated_against_reference(sky_box, rng):
    """The pipeline's glossy direct path: 8-bit rows per discretised w_o, blended toward off-grid views.

    Bound: MC_SIGMAS combined standard errors + cubemap resolution (as above) + 8-bit quantisation
    + the view discretisation ``ks Lip(g) sum_q w_q angle(w_o, w_oq) * pi sum_k T_k max_k L``
    (:func:`prtlab.portals.view_interpolation`).
    """
    from prtlab.portals import glossy_direct_pass, glossy_direct_transfer, phong_lipschitz, view_interpolation

    res, view_res, e, kd, ks = 16, 8, 10.0, 0.3, 0.5
    views = np.array([[0.1, 0.6, 0.8], [0.35, 0.9, -0.3]])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    grid = cubemap_directions(view_res).reshape(-1, 3)
    n_views = len(grid)
    rows, w = view_interpolation(views, view_res)
    rows = rows + (np.arange(2) * n_views)[:, None]
    caster = RayCaster(sky_box)
    (portal,) = find_portals(sky_box)
    gen = np.random.default_rng(4)
    cube = shell_light(sky_box.environment, res)
    fine = equirect_lookup(sky_box.environment.image, cubemap_directions(res * 8)).reshape(6, res, 8, res, 8, 3)
    spread = fine.max(axis=(2, 4)) - fine.min(axis=(2, 4))
    l1 = np.maximum(np.abs(cube).sum((0, 1, 2)), np.abs(haar2d(cube, channels=True)).sum((0, 1, 2)))
    values, bounds = [], []
    for _ in range(4):
        spec = glossy_direct_transfer(caster, FLOOR, UP, portal, grid, e, 1024, res, gen)
        diff = direct_transfer(caster, FLOOR, UP, portal, 1024, res, gen)
        s8, d8 = encode_transfer(spec.reshape(-1, 6, res, res)), encode_transfer(diff)
        values.append(glossy_direct_pass(s8, rows, w, np.full((2, 3), ks), cube)
                      + direct_pass(d8, np.full((2, 3), kd), cube))
        s_rows = spec.reshape(-1, 6, res, res)[rows]  # (2, 4, 6, r, r)
        resolution = ks * np.einsum("vq,vqfij,fijc->vc", w, s_rows, spread) + kd * np.einsum("vfij,fijc->vc", diff,
                                                                                            spread)
        quant = (ks * np.einsum("vq,vq->v", w, s8.scale[rows]) + kd * d8.scale)[:, None] / 510 * l1
        angles = np.arccos(np.clip(np.einsum("vk,vqk->vq", views, grid[rows - (np.arange(2) * n_views)[:, None]]),
                                   -1, 1))
        view_bound = ks * phong_lipschitz(e) * np.einsum("vq,vq->v", w, angles)[:, None] * np.pi \
            * np.einsum("vfij,fijc->vc", diff, cube + spread)
        bounds.append(resolution + quant + view_bound)
    _check_glossy_against_reference(values, bounds, sky_box, views, e, kd, ks, rng)


def test_glossy_direct_lobe_against_reference(sky_box, rng):
    """``glossy_direct="lobe"``: the Phong lobe at the texel centres, weighted by the float32 diffuse transfer.

    Bound: MC_SIGMAS combined standard errors + the shell light's spread over a texel (as above), weighted by the
    lobe's largest value on the texel, + the lobe's change over a texel ``ks Lip(g) theta pi sum_k T_k L_k`` with
    ``theta`` the largest angle from a texel's centre to its corners.
    """
    from prtlab.portals import glossy_lobe_pass, phong_lipschitz

    res, e, kd, ks = 16, 10.0, 0.3, 0.5
    views = np.array([[0.1, 0.6, 0.8], [0.35, 0.9, -0.3]])
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    mirror = 2 * np.einsum("vk,vk->v", views, UP)[:, None] * UP - views
    caster = RayCaster(sky_box)
    (portal,) = find_portals(sky_box)
    gen = np.random.default_rng(4)
    cube = shell_light(sky_box.environment, res)
    fine = equirect_lookup(sky_box.environment.image, cubemap_directions(res * 8)).reshape(6, res, 8, res, 8, 3)
    spread = (fine.max(axis=(2, 4)) - fine.min(axis=(2, 4))).reshape(-1, 3)
    centres = cubemap_directions(res).reshape(-1, 3)
    on_cube = cubemap_directions(res, normalize=False).reshape(-1, 3)  # |major coordinate| = 1
    in_face = np.abs(on_cube) < 1 - 1e-9  # the two face coordinates, texels 2 / res wide
    theta = 0.0
    for sa in (-1, 1):
        for sb in (-1, 1):
            step = np.where(in_face, 1.0 / res, 0.0)
            first = np.cumsum(in_face, axis=1) == 1  # the first face coordinate of each texel
            corner = on_cube + step * np.where(first, sa, sb)
            corner /= np.linalg.norm(corner, axis=1, keepdims=True)
            theta = max(theta, float(np.arccos(np.clip(np.einsum("tk,tk->t", corner, centres), -1, 1)).max()))
    assert theta == pytest.approx(np.arctan(np.sqrt(2) / res), rel=0.01)  # the texels beside the face centre
    l1 = np.maximum(np.abs(cube).sum((0, 1, 2)), np.abs(haar2d(cube, channels=True)).sum((0, 1, 2)))
    lip = phong_lipschitz(e)
    values, bounds = [], []
    for _ in range(4):
        diff = direct_transfer(caster, FLOOR, UP, portal, 1024, res, gen).reshape(2, -1)
        v, k = np.nonzero(diff)
        indptr = np.concatenate([[0], np.cumsum(np.bincount(v, minlength=2))])
        spec = glossy_lobe_pass(indptr, k, diff[v, k].astype(np.float32), res, mirror, np.full(2, e),
                                np.full((2, 3), ks), cube)
        values.append(spec + direct_pass(encode_transfer(diff.reshape(2, 6, res, res)), np.full((2, 3), kd), cube))
        g_max = (e + 2) / (2 * np.pi) * np.maximum(0, mirror @ centres.T) ** e + lip * theta
        resolution = (ks * np.pi * g_max + kd) * diff @ spread  # the 8-bit diffuse rows' error is below it
        bounds.append(resolution + ks * lip * theta * np.pi * diff @ (cube.reshape(-1, 3) + spread)
                      + kd * encode_transfer(diff.reshape(2, 6, res, res)).scale[:, None] / 510 * l1)
    ours, ref = _check_glossy_against_reference(values, bounds, sky_box, views, e, kd, ks, rng)
    assert np.all(np.abs(ours - ref) <= 0.1 * ref), (ours, ref)  # the bound is not vacuous


def _rect_form_factor(x1, x2, y1, y2, c):
    """Form factor from a differential area to the rectangle ``[x1, x2] x [y1, y2]`` of the parallel plane at
    distance ``c`` (coordinates from the normal's foot): the corner formula, signed (odd in both coordinates)."""
    def corner(a, b):
        ha, hb = np.hypot(a, c), np.hypot(b, c)
        return (a / ha * np.arctan(b / ha) + b / hb * np.arctan(a / hb)) / (2.0 * np.pi)
    return corner(x2, y2) - corner(x1, y2) - corner(x2, y1) + corner(x1, y1)


def test_portal_samplers_per_texel_against_closed_form(constant_box):
    """A point facing the 1 x 1 window squarely: each -Z texel's cone cuts the window plane in an axis-aligned
    rectangle, so ``T_k`` is the form factor to its overlap with the window (closed form). Every sampler is
    unbiased per texel within MC_SIGMAS standard errors; the independent sampler's summed squared error matches its
    variance ``(A int g^2 dA - sum_k T_k^2) / N`` (``g = cos_v cos_p / (pi r^2)``), and the Sobol' and jittered
    samplers' summed squared errors are below that variance by more than MC_SIGMAS standard errors."""
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    x0, c, res, n, reps = np.array([0.05, 1.37, -0.9]), 0.6, 8, 1024, 48
    lo = np.array([-0.5, 0.9]) - x0[:2]  # the window relative to the normal's foot
    hi = lo + 1.0
    edges = np.linspace(-1.0, 1.0, res + 1)  # face -Z: s = -dx / c, t = -dy / c
    exact = np.zeros((res, res))
    for i in range(res):
        y1, y2 = np.clip(np.sort(-c * edges[i : i + 2]), lo[1], hi[1])
        for j in range(res):
            x1, x2 = np.clip(np.sort(-c * edges[j : j + 2]), lo[0], hi[0])
            exact[i, j] = _rect_form_factor(x1, x2, y1, y2, c) if x2 > x1 and y2 > y1 else 0.0
    assert np.isclose(exact.sum(), _rect_form_factor(lo[0], hi[0], lo[1], hi[1], c), rtol=1e-12)
    m = 1000  # midpoint rule for int g^2 dA (smooth integrand, relative error ~1e-6)
    gx, gy = np.meshgrid(lo[0] + (np.arange(m) + 0.5) / m, lo[1] + (np.arange(m) + 0.5) / m)
    g2 = (c**2 / (np.pi * (gx**2 + gy**2 + c**2) ** 2)) ** 2
    iid_variance = (portal.area * g2.mean() * portal.area - (exact**2).sum()) / n
    sq_err = {}
    for sampler in ("random", "jittered", "sobol"):
        rng = np.random.default_rng(7)
        t = np.stack([direct_transfer(caster, x0[None], np.array([[0.0, 0.0, -1.0]]), portal, n, res, rng,
                                      sampler=sampler)[0] for _ in range(reps)])
        assert np.all(t[:, [0, 1, 2, 3, 4]] == 0.0), sampler  # the window is seen through -Z only
        err = t[:, 5] - exact
        se = t[:, 5].std(0, ddof=1) / np.sqrt(reps)
        assert np.all(np.abs(err.mean(0)) <= MC_SIGMAS * se + 1e-12), sampler
        sq_err[sampler] = (err**2).sum(axis=(1, 2))
    s = sq_err["random"]
    assert abs(s.mean() - iid_variance) <= MC_SIGMAS * s.std(ddof=1) / np.sqrt(reps)
    for sampler in ("jittered", "sobol"):
        s = sq_err[sampler]
        assert s.mean() + MC_SIGMAS * s.std(ddof=1) / np.sqrt(reps) < iid_variance, sampler
    sobol, jittered = sq_err["sobol"], sq_err["jittered"]  # measured: 0.06 and 0.34 of the i.i.d. variance
    assert sobol.mean() + MC_SIGMAS * sobol.std(ddof=1) / np.sqrt(reps) < (
        jittered.mean() - MC_SIGMAS * jittered.std(ddof=1) / np.sqrt(reps))


def test_portal_sampler_errors(constant_box):
    caster = RayCaster(constant_box)
    (portal,) = find_portals(constant_box)
    with pytest.raises(ValueError, match="sampler must be one of"):
        direct_transfer(caster, FLOOR, UP, portal, 4, 4, np.random.default_rng(0), sampler="halton")
    from prtlab.portals import glossy_direct_transfer

    with pytest.raises(ValueError, match="sampler must be one of"):
        glossy_direct_transfer(caster, FLOOR, UP, portal, UP, 10.0, 4, 4, np.random.default_rng(0), sampler="qmc")
    with pytest.raises(ValueError, match="option portal_sampler must be one of"):
        PortalsOptions(portal_sampler="grid")


def test_parallelogram_portal_detected(constant_box):
    """The Sobol' sampler maps a parallelogram portal affinely; any other portal goes through its triangles."""
    from prtlab.portals._direct import _parallelogram, _portal_points
    from prtlab.portals._shell import _make_portal

    (window,) = find_portals(constant_box)
    corner, e1, e2 = _parallelogram(window)
    assert np.isclose(abs(np.cross(e1, e2) @ window.normal), window.area)
    trapezoid = _make_portal(["t"], [(np.array([[0, 0, 0], [2, 0, 0], [1.5, 1, 0], [0.5, 1, 0.0]]),
                                      np.array([[0, 1, 2], [0, 2, 3]]))])
    assert _parallelogram(trapezoid) is None
    p, _ = _portal_points(trapezoid, 2, 4096, np.random.default_rng(3))
    assert np.all((p[..., 1] >= 0) & (p[..., 1] <= 1) & (p[..., 0] >= 0.5 * p[..., 1] - 1e-12)
                  & (p[..., 0] <= 2 - 0.5 * p[..., 1] + 1e-12))
    # uniform by area: the mean height is the centroid's 4/9 (standard error sqrt(var / n), var <= 1/4)
    assert np.all(np.abs(p[..., 1].mean(1) - 4.0 / 9.0) <= MC_SIGMAS * 0.5 / np.sqrt(4096))
