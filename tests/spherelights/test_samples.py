"""Tests of prtlab.spherelights._samples: segments (Eq. 2), the three surface-sample rules and the surface
albedo of Guerrero et al. 2008, Sec. 4.2, on meshes whose answers are known by hand (boxes: planes, so the ray
hits are the slab intersections; a torus: a tube of known radius).

Hit locations come from trimesh's ray engine (embree: single precision), so positions are compared to 1e-5.
"""

import numpy as np
import pytest

from prtlab import sh
from prtlab.geometry import builtin_mesh, cubemap_directions, cubemap_solid_angles, geodesic_directions
from prtlab.spherelights import first_pass, segment_of, surface_albedo_sh, surface_samples, voronoi_cell_sums
from tests.conftest import random_rotation
from tests.spherelights.test_shadows import _env_sh

ORDER = 4
EMBREE_TOL = 1e-5   # single-precision hit distances on meshes of unit size
MARGIN = 1e-3       # hand answers are only asserted where no rounding can flip them (checked per direction)
ALBEDO = np.array([0.8, 0.5, 0.3])


def _directions(rng):
    """The paper's 92 geodesic directions in a generic orientation: none lies on a box edge, a segment boundary
    or a tangent (the symmetric set has directions exactly on the planes ``|w_x| = |w_y|`` of the boxes below)."""
    return geodesic_directions(92) @ random_rotation(rng).T


def _slab(o, w, lo, hi):
    """Ray ``o + t w`` against the box ``[lo, hi]``: (t_in, t_out, entry normal, exit normal); a hit iff
    ``t_in < t_out`` (and ``t_out > 0`` forwards). The entry face of axis k faces ``-sign(w_k) e_k``."""
    with np.errstate(divide="ignore"):
        t1, t2 = (lo - o) / w, (hi - o) / w
    tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
    k_in, k_out = int(np.argmax(tmin)), int(np.argmin(tmax))
    n_in, n_out = np.zeros(3), np.zeros(3)
    n_in[k_in], n_out[k_out] = -np.sign(w[k_in]), np.sign(w[k_out])
    return tmin[k_in], tmax[k_out], n_in, n_out


def _box_rules(lo, hi, centres, radii, light, dirs):
    """The three rules of Sec. 4.2 by hand for a box (convex: a ray from inside has one hit, the back-face exit;
    a ray from outside that hits has a front-face entry and a back-face exit):

    * forward hit, exit in ``P_S``: rule 1, the exit; exit outside ``P_S``: rule 2, no sample;
    * no forward hit: rule 3, the entry of ``-w`` if it lies in ``P_S``, else no sample.

    The segment is Eq. 2 written out (``argmin |p - x_i| / r_i``), not :func:`segment_of`.
    Returns (points, normals, valid, case) with case in {"exit", "rule2", "entry", "entry outside", "miss"},
    and asserts that every direction is at least ``MARGIN`` away from a case boundary.
    """
    o = np.asarray(centres[light], dtype=float)
    m = len(dirs)
    points, normals, valid, case = np.zeros((m, 3)), np.zeros((m, 3)), np.zeros(m, bool), []

    def seg(p):
        d = np.linalg.norm(np.asarray(centres) - p, axis=1) / np.asarray(radii)
        if len(d) > 1:
            assert np.sort(d)[1] - np.sort(d)[0] > MARGIN, "a hit on a segment boundary"
        return int(np.argmin(d))

    def off_edges(p):
        inside = np.minimum(p - lo, hi - p)
        assert np.sort(inside)[1] > MARGIN, "a hit on a box edge"

    for j, w in enumerate(dirs):
        t_in, t_out, n_in, n_out = _slab(o, w, lo, hi)
        assert abs(t_out) > MARGIN and (t_out < 0 or abs(t_out - t_in) > MARGIN), "a grazing ray"
        if t_in < t_out and t_out > 0:
            q = o + t_out * w
            off_edges(q)
            if seg(q) == light:
                points[j], normals[j], valid[j] = q, n_out, True
                case.append("exit")
            else:
                case.append("rule2")
            continue
        b_in, b_out, bn_in, _ = _slab(o, -w, lo, hi)
        assert abs(b_out - b_in) > MARGIN, "a grazing opposite ray"
        if b_in < b_out and b_in > 0:
            q = o - b_in * w
            off_edges(q)
            if seg(q) == light:
                points[j], normals[j], valid[j] = q, bn_in, True
                case.append("entry")
            else:
                case.append("entry outside")
        else:
            case.append("miss")
    return points, normals, valid, np.array(case)


def _assert_box_samples(mesh, lo, hi, centres, radii, dirs):
    """:func:`surface_samples` against :func:`_box_rules` for every light: the same valid directions, the slab
    points and the face normals; returns the samples and the cases per light."""
    pts, nrm, valid = surface_samples(mesh, centres, radii, dirs)
    cases = []
    for i in range(len(radii)):
        p, n, v, case = _box_rules(lo, hi, centres, radii, i, dirs)
        np.testing.assert_array_equal(valid[i], v, err_msg=f"light {i}: {case[valid[i] != v]}")
        np.testing.assert_allclose(pts[i, v], p[v], atol=EMBREE_TOL)
        # the box's sides do not share vertices: interpolated vertex normals are the face normals
        np.testing.assert_allclose(nrm[i, v], n[v], atol=1e-12)
        assert np.all(np.einsum("ij,ij->i", nrm[i, v], dirs[v]) > 0)  # every sample faces along its w
        cases.append(case)
    return pts, nrm, valid, cases


# ----------------------------------------------------------------- segments (Eq. 2)


def test_segments_are_by_radius_scaled_distance():
    """``d(p, S) = |p - x_S| / r_S``: lights at x = 0 (r = 1) and x = 3 (r = 2) split the x axis where
    ``|x| = |x - 3| / 2``: at x = 1 and x = -3 (the Apollonius circle), so the larger light also owns the far
    side beyond x = -3; the nearest centre alone would give the split x = 1.5 only."""
    c = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    r = np.array([1.0, 2.0])
    x = np.array([0.9, 1.1, 1.4, -2.9, -3.1, 5.0])
    got = segment_of(np.stack([x, np.zeros(6), np.zeros(6)], -1), c, r)
    np.testing.assert_array_equal(got, [0, 1, 1, 0, 1, 1])
    assert segment_of(np.zeros((0, 3)), c, r).shape == (0,)


# ----------------------------------------------------------------- the three rules


def test_rule_2_direction_into_another_lights_segment_is_discarded(rng):
    """Box [-1, 1] x [-0.5, 0.5]^2, two equal lights at x = -0.5 and x = 0.5: the segments are the halves
    x < 0 and x > 0 (Eq. 2, equal radii: the bisector plane), each the unit cube centred on its light. From the
    light at x = -0.5 a ray has one hit, the back-face exit (rule 1: the sample) unless it leaves its cube
    through the inner face x = 0, i.e. unless ``w_x > max(|w_y|, |w_z|)``: then its only hit is on the far face
    x = 1, in the other segment (rule 2: no sample). So exactly the directions of the cube's +x face (a sixth of
    the sphere) are discarded, and their mirror images for the other light."""
    mesh = builtin_mesh("box", size=[2.0, 1.0, 1.0], subdivisions=1)
    lo, hi = np.array([-1.0, -0.5, -0.5]), np.array([1.0, 0.5, 0.5])
    centres, radii = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]), np.array([0.75, 0.75])
    dirs = _directions(rng)
    pts, nrm, valid, cases = _assert_box_samples(mesh, lo, hi, centres, radii, dirs)
    inner = np.maximum(np.abs(dirs[:, 1]), np.abs(dirs[:, 2]))
    np.testing.assert_array_equal(valid[0], ~(dirs[:, 0] > inner))
    np.testing.assert_array_equal(valid[1], ~(-dirs[:, 0] > inner))
    assert set(cases[0]) == {"exit", "rule2"} and set(cases[1]) == {"exit", "rule2"}
    assert np.all(pts[0, valid[0], 0] < 0) and np.all(pts[1, valid[1], 0] > 0)  # samples stay in their segment


def test_rule_3_centre_outside_shoots_the_opposite_ray(rng):
    """Unit cube, one light centred 0.1 above its top face (outside the closed object). A direction that hits
    the cube has a front-face entry and a back-face exit: rule 1 takes the exit (the farthest back-face hit).
    A direction that misses (pointing up) shoots ``-w``: rule 3 takes the closest front-face hit, the entry
    (the exit of ``-w`` farther on is a back face and is ignored). Near-horizontal directions whose two rays
    both miss are discarded. All three cases occur among the 92 directions; points are the slab intersections
    and normals the face normals, which point along ``w`` in both rules (``n . w > 0``)."""
    mesh = builtin_mesh("box", size=[1.0, 1.0, 1.0], subdivisions=1)
    lo, hi = np.full(3, -0.5), np.full(3, 0.5)
    centres, radii = np.array([[0.07, 0.6, -0.04]]), np.array([0.7])
    dirs = _directions(rng)
    pts, nrm, valid, cases = _assert_box_samples(mesh, lo, hi, centres, radii, dirs)
    counts = {c: int(np.sum(cases[0] == c)) for c in ("exit", "entry", "miss")}
    assert min(counts.values()) > 0 and sum(counts.values()) == 92, counts
    entry = cases[0] == "entry"
    np.testing.assert_allclose(pts[0, entry, 1], 0.5, atol=EMBREE_TOL)  # all entries of -w: the top face
    assert np.all(dirs[entry, 1] > 0)


def test_rule_3_keeps_only_hits_inside_the_segment(rng):
    """Box [-1, 1] x [-0.5, 0.5]^2 with an inside light at (0.5, 0, 0) and an outside light at (-0.5, 0.7, 0.05)
    (equal radii: the segments are split by the bisector plane of the two centres). For the outside light every
    case of the rules occurs: exits in its segment (rule 1), exits in the other's (rule 2), entries of ``-w``
    in its segment (rule 3) and in the other's, which rule 3 discards too, and misses of both rays."""
    mesh = builtin_mesh("box", size=[2.0, 1.0, 1.0], subdivisions=1)
    lo, hi = np.array([-1.0, -0.5, -0.5]), np.array([1.0, 0.5, 0.5])
    centres, radii = np.array([[-0.5, 0.7, 0.05], [0.5, 0.0, 0.0]]), np.array([0.75, 0.75])
    dirs = _directions(rng)
    pts, nrm, valid, cases = _assert_box_samples(mesh, lo, hi, centres, radii, dirs)
    assert set(cases[0]) == {"exit", "rule2", "entry", "entry outside", "miss"}, set(cases[0])
    assert set(cases[1]) == {"exit", "rule2"}


def test_rule_3_ignores_back_faces_of_the_opposite_ray(rng):
    """Rule 3 allows front faces only. Box [-1, 1] x [-0.5, 0.5]^2, a small inside light (r = 0.3) just under the
    top face and a larger one (r = 0.5) outside above it: the small light's segment (inside an Apollonius
    sphere about its centre) holds the middle of the top face but not the bottom. For an upward ``w`` of the
    outside light, ``-w`` enters through the top face in the small light's segment and leaves through the
    bottom in its own: the exit is a back face, so there is no sample (taking the closest hit of any face
    inside the segment would take the exit)."""
    mesh = builtin_mesh("box", size=[2.0, 1.0, 1.0], subdivisions=1)
    lo, hi = np.array([-1.0, -0.5, -0.5]), np.array([1.0, 0.5, 0.5])
    centres, radii = np.array([[0.05, 0.8, -0.02], [-0.03, 0.35, 0.02]]), np.array([0.5, 0.3])
    dirs = _directions(rng)
    pts, nrm, valid, cases = _assert_box_samples(mesh, lo, hi, centres, radii, dirs)
    trap = []
    for j in np.nonzero(cases[0] == "entry outside")[0]:
        b_in, b_out, _, _ = _slab(centres[0], -dirs[j], lo, hi)
        exit_ = centres[0] - b_out * dirs[j]
        trap.append(np.argmin(np.linalg.norm(centres - exit_, axis=1) / radii) == 0)
    assert sum(trap) >= 3 and not valid[0, np.nonzero(cases[0] == "entry outside")[0]].any()


def test_rule_1_takes_the_farthest_back_face_hit_inside_the_segment():
    """Torus (R = 1, r = 0.25, in the xz plane), light at the tube centre (1, 0, 0). Along -x the ray leaves the
    tube at x = 0.75 (back face), enters the far side at x = -0.75 (front) and leaves it at x = -1.25 (back).
    With this light alone (one segment: the whole torus) the sample is the farthest back-face hit, x = -1.25;
    with four equal lights at (+-1, 0, 0), (0, 0, +-1) the hit at x = -1.25 lies in the segment of (-1, 0, 0),
    so the sample is x = 0.75. Along +x and +y the only hits are (1.25, 0, 0) and (1, 0.25, 0). A light outside
    at (-2, 0, 0): along +x rule 1 gives the farthest back-face hit (1.25, 0, 0); along -x nothing is hit, and
    rule 3's ray along +x has front-face hits at x = -1.25 and 0.75: the closest, (-1.25, 0, 0), is the sample.
    These points are mesh vertices (section angles 0, 90, 180 degrees), so they are exact; the normals are the
    tube's outward normals up to the vertex-normal averaging (within one minor step, pi/16)."""
    mesh = builtin_mesh("torus")
    d = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    four = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    for centres, first in ((four[:1], [-1.25, 0.0, 0.0]), (four, [0.75, 0.0, 0.0])):
        pts, nrm, valid = surface_samples(mesh, centres, np.full(len(centres), 0.3), d)
        assert valid[0].all()
        np.testing.assert_allclose(pts[0], [first, [1.25, 0.0, 0.0], [1.0, 0.25, 0.0]], atol=EMBREE_TOL)
        exact = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
        np.testing.assert_allclose(np.linalg.norm(nrm[0], axis=1), 1.0, atol=1e-12)
        assert np.all(np.einsum("ij,ij->i", nrm[0], exact) > np.cos(np.pi / 16))
    pts, nrm, valid = surface_samples(mesh, [[-2.0, 0.0, 0.0]], [0.5], d[:2])
    assert valid[0].all()
    np.testing.assert_allclose(pts[0], [[-1.25, 0.0, 0.0], [1.25, 0.0, 0.0]], atol=EMBREE_TOL)
    assert np.all(np.einsum("ij,ij->i", nrm[0], [[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]) > np.cos(np.pi / 16))


def test_rule_3_discards_when_the_opposite_ray_misses_too():
    """Light at the centre of the torus hole (outside the object). A ray at elevation ``alpha`` meets the tube
    circle (centre distance R = 1, radius r = 0.25) iff ``|sin alpha| < r / R = 0.25``; then rule 1 gives the
    outer exit of the near side of the tube, at ``t = R cos alpha + sqrt(r^2 - R^2 sin^2 alpha)``. Otherwise the
    ray misses and so does ``-w`` (the torus is symmetric through its centre): rule 3 discards it. The
    tessellated tangent differs from 0.25 by less than the sagittas (0.011); the 92 symmetric geodesic
    directions have ``|w_y|`` in {0, 0.202, 0.326, ...}, so 24 directions are valid and none is ambiguous.
    Samples lie on the mesh: within the two sagittas ``(R + r)(1 - cos(pi/32)) + r (1 - cos(pi/16)) = 0.0108``
    of the exact torus (32 x 16 sections; measured 0.0107 on 200k area samples of the mesh), on the ray, the outer
    exit, with normals within a minor plus a major section step of the exact normal."""
    mesh = builtin_mesh("torus")
    dirs = geodesic_directions(92)
    pts, nrm, valid = surface_samples(mesh, np.zeros((1, 3)), [1.25], dirs)
    s = np.abs(dirs[:, 1])
    assert np.all(np.abs(s - 0.25) > 0.04)
    np.testing.assert_array_equal(valid[0], s < 0.25)
    assert valid[0].sum() == 24
    w, q, n = dirs[valid[0]], pts[0, valid[0]], nrm[0, valid[0]]
    cos_a = np.sqrt(1 - w[:, 1] ** 2)
    t = np.einsum("ij,ij->i", q, w)
    np.testing.assert_allclose(q, t[:, None] * w, atol=EMBREE_TOL)         # on the ray
    sag = 1.25 * (1 - np.cos(np.pi / 32)) + 0.25 * (1 - np.cos(np.pi / 16))
    rho = np.hypot(q[:, 0], q[:, 2])
    assert np.all(np.abs(np.hypot(rho - 1.0, q[:, 1]) - 0.25) <= sag + EMBREE_TOL)
    root = np.sqrt(0.25**2 - w[:, 1] ** 2)
    # the outer exit, not the entry (t = cos a - root): a surface within ``sag`` of the torus moves the hit by at
    # most sag / cos(incidence) along the ray, to first order, with cos(incidence) = root / r
    assert np.all(t > cos_a) and np.all(np.abs(t - (cos_a + root)) <= sag / (root / 0.25))
    ring = np.stack([q[:, 0] / rho, np.zeros(len(q)), q[:, 2] / rho], -1)
    n_exact = q - ring
    n_exact /= np.linalg.norm(n_exact, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", n, n_exact) > np.cos(np.pi / 8 + np.pi / 16))
    assert np.all(np.einsum("ij,ij->i", n, w) > 0)


def test_a_discarded_direction_emits_nothing():
    """The light emits nothing towards a discarded direction: the first pass reads no data at invalid samples
    (garbage stored there changes nothing), and a light with every direction discarded emits exactly zero."""
    mesh = builtin_mesh("torus")
    dirs = geodesic_directions(92)
    c, r = np.zeros((1, 3)), np.array([1.25])
    pts, nrm, valid = surface_samples(mesh, c, r, dirs)
    alb = surface_albedo_sh(mesh, c, r, ALBEDO, ORDER, resolution=8)
    env, cells = _env_sh(), voronoi_cell_sums(ORDER, n_strata=32)
    e = first_pass(pts, nrm, valid, c, r, env, cells, alb, exp_method="exact")
    junk = np.random.default_rng(0).normal(size=pts.shape)
    pts2, nrm2 = np.where(valid[..., None], pts, junk), np.where(valid[..., None], nrm, junk)
    np.testing.assert_array_equal(first_pass(pts2, nrm2, valid, c, r, env, cells, alb, exp_method="exact"), e)
    assert np.abs(e).max() > 1e-3
    none = first_pass(pts2, nrm2, np.zeros_like(valid), c, r, env, cells, alb, exp_method="exact")
    np.testing.assert_array_equal(none, 0.0)


def test_surface_samples_rejects_a_non_mesh():
    with pytest.raises(TypeError, match="mesh must be a trimesh.Trimesh, got ndarray"):
        surface_samples(np.zeros((3, 3)), np.zeros((1, 3)), [1.0], geodesic_directions(12))


# ----------------------------------------------------------------- surface albedo


@pytest.mark.parametrize("centre", [[0.0, 0.0, 0.0], [0.2, -0.1, 0.3]])
def test_albedo_of_a_closed_sphere_around_its_light(centre):
    """Closed icosphere of constant albedo ``a`` around one light (centred or not: the centre is inside): every
    cubemap texel's ray leaves the sphere through a back face in the light's (only) segment, so ``A_S = a``
    everywhere, whatever the tessellation. The cubemap rule has exact texel solid angles (summing to 4 pi) and
    the symmetry of the cube, under which no harmonic of bands 1-3 is invariant, so its sums of those vanish:
    ``c_S = a (sqrt(4 pi), 0, ..., 0)`` to rounding."""
    mesh = builtin_mesh("icosphere", subdivisions=2)
    c = surface_albedo_sh(mesh, [centre], [1.0], ALBEDO, ORDER)
    expect = np.zeros((ORDER * ORDER, 3))
    expect[0] = ALBEDO * np.sqrt(4 * np.pi)
    np.testing.assert_allclose(c[0], expect, atol=1e-12)


def _face_projection(order, n=40):
    """``int_F y_k(w) dw`` over the +x face of the cube seen from its centre: Gauss-Legendre on the face
    ``q = (1, u, v)``, ``dw = du dv / |q|^3`` (a smooth integrand: exact to rounding at n = 40)."""
    x, wx = np.polynomial.legendre.leggauss(n)
    u, v = np.meshgrid(x, x, indexing="ij")
    q = np.stack([np.ones(u.size), u.ravel(), v.ravel()], -1)
    rq = np.linalg.norm(q, axis=1)
    return sh.basis(q / rq[:, None], order).T @ (np.outer(wx, wx).ravel() / rq**3)


def test_albedo_of_a_box_segment_misses_the_discarded_face():
    """The two-light box of the rule-2 test: light 0 sits at the centre of its segment, the unit cube
    [-1, 0] x [-0.5, 0.5]^2 axis-aligned with the cubemap, and its rule-2 directions are exactly the cubemap's
    +x face. So ``c_0 = a (P_n 1 - P_F)`` with ``F`` that face, in the cubemap rule: the DC is exactly
    ``a (5/6) sqrt(4 pi)`` (each face's texels sum to 4 pi / 6), the coefficients odd in y or z vanish (the
    face is symmetric in both), light 1 is the mirror image (coefficients odd in x flip sign), and the result
    is ``a`` times the rule's sum over the texels off that face. Against the exact projection ``a (P_n 1 - int_F
    y)`` the only error is the cubemap rule's second-order (midpoint) error on a smooth integrand, since the
    mask's edge lies on texel edges: it falls by 4 from resolution 16 to 32 (a misclassified texel would not)."""
    mesh = builtin_mesh("box", size=[2.0, 1.0, 1.0], subdivisions=1)
    centres, radii = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]), np.array([0.75, 0.75])
    c16 = surface_albedo_sh(mesh, centres, radii, ALBEDO, ORDER, resolution=16)
    c32 = surface_albedo_sh(mesh, centres, radii, ALBEDO, ORDER, resolution=32)
    np.testing.assert_allclose(c16[:, 0], np.broadcast_to(ALBEDO * 5 / 6 * np.sqrt(4 * np.pi), (2, 3)), rtol=1e-13)
    odd_yz = [1, 2, 4, 5, 7, 9, 10, 11, 12, 14]   # y, z, xy, yz, xz, y(3x^2-y^2), xyz, y(5z^2-1), z(5z^2-3), z(x^2-y^2)
    odd_x = [3, 13, 15]                            # x, x(5z^2-1), x(x^2-3y^2): the others odd in x are in odd_yz
    np.testing.assert_allclose(c16[:, odd_yz], 0.0, atol=1e-12)
    mirror = c16[0].copy()
    mirror[odd_x] *= -1
    np.testing.assert_allclose(c16[1], mirror, atol=1e-12)
    dirs = cubemap_directions(16).reshape(-1, 3)
    off_face = ~((dirs[:, 0] > np.abs(dirs[:, 1])) & (dirs[:, 0] > np.abs(dirs[:, 2])))
    rule = (cubemap_solid_angles(16).reshape(-1) * off_face) @ sh.basis(dirs, ORDER)
    np.testing.assert_allclose(c16[0], np.outer(rule, ALBEDO), atol=1e-12)
    exact = -_face_projection(ORDER)
    exact[0] += np.sqrt(4 * np.pi)
    err16 = np.abs(c16[0] / ALBEDO - exact[:, None]).max()
    err32 = np.abs(c32[0] / ALBEDO - exact[:, None]).max()
    assert 3.5 < err16 / err32 < 4.5, (err16, err32)


@pytest.mark.parametrize("scene", ["outside cube", "torus hole", "two lights"])
def test_albedo_texels_follow_the_sample_rules(scene):
    """The albedo cubemap uses the same three rules as the samples (Sec. 4.2): ``c_S = a sum_T Omega_T
    valid_T y(w_T)`` with ``valid_T`` what :func:`surface_samples` gives along the texel directions, for a light
    outside the object (rules 1 and 3), in a torus hole (rule 3 discarding) and two lights (rule 2)."""
    if scene == "outside cube":
        mesh, c, r = builtin_mesh("box", subdivisions=1), np.array([[0.07, 0.6, -0.04]]), np.array([0.7])
    elif scene == "torus hole":
        mesh, c, r = builtin_mesh("torus"), np.zeros((1, 3)), np.array([1.25])
    else:
        mesh = builtin_mesh("box", size=[2.0, 1.0, 1.0], subdivisions=1)
        c, r = np.array([[-0.5, 0.7, 0.05], [0.5, 0.0, 0.0]]), np.array([0.75, 0.75])
    res = 8
    dirs = cubemap_directions(res).reshape(-1, 3)
    _, _, valid = surface_samples(mesh, c, r, dirs)
    assert 0 < valid.sum() < valid.size
    got = surface_albedo_sh(mesh, c, r, ALBEDO, ORDER, resolution=res)
    rule = (cubemap_solid_angles(res).reshape(-1) * valid) @ sh.basis(dirs, ORDER)
    np.testing.assert_allclose(got, rule[:, :, None] * ALBEDO, atol=1e-12)


# --------------------------------------------------------------------------- projected coverage of the segments


def test_segment_coverage_of_a_ball_and_a_box():
    """Known answers: a ball's one light (its own sphere) is covered by the ball's projection (the icosphere's
    silhouette, about ``1 - 1e-2`` of the disc at 4 subdivisions); a unit cube's one light (radius ``sqrt(3) / 2``)
    seen along an axis is covered by a face, ``1 / (pi 3 / 4) = 0.4244``; two lights splitting a long box cover
    it seen across (each its half), and seen along the box the nearer light covers its disc's part of the end face
    while the farther one is hidden (its segment lies behind)."""
    from prtlab.spherelights import segment_coverage

    ball = builtin_mesh("icosphere", subdivisions=4)
    cov = segment_coverage(ball, np.zeros((1, 3)), np.ones(1), geodesic_directions(42), n_rays=1024)
    assert cov.shape == (1, 42) and np.all(cov > 0.98) and np.all(cov <= 1.0)
    cube = builtin_mesh("box", size=[1.0, 1.0, 1.0])
    axes = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cov = segment_coverage(cube, np.zeros((1, 3)), [np.sqrt(3) / 2], axes, n_rays=4096)
    np.testing.assert_allclose(cov, 1.0 / (np.pi * 0.75), atol=0.01)
    bar = builtin_mesh("box", size=[2.0, 0.5, 0.5])
    centres, radii = np.array([[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]), np.full(2, 0.62)
    cov = segment_coverage(bar, centres, radii, np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), n_rays=4096)
    across = 1.0 * 0.5 / (np.pi * 0.62**2)  # each light's half of the bar's side, inside its disc
    np.testing.assert_allclose(cov[:, 0], across, atol=0.01)
    np.testing.assert_allclose(cov[:, 1], [0.0, 0.25 / (np.pi * 0.62**2)], atol=0.01)
    assert segment_coverage(cube, np.zeros((0, 3)), np.zeros(0), axes).shape == (0, 3)


def test_coverage_weights():
    """Every sample valid: the weights are the coverage; none: 0; a light valid on half its directions gets its
    coverage over the valid part of each direction's hemisphere."""
    from prtlab.spherelights import coverage_weights

    dirs = geodesic_directions(92)
    cov = np.full((3, 92), 0.4)
    valid = np.stack([np.ones(92, bool), np.zeros(92, bool), dirs[:, 2] > 0])
    w = coverage_weights(cov, valid, dirs)
    np.testing.assert_allclose(w[0], 0.4)
    np.testing.assert_array_equal(w[1], 0.0)
    cosw = np.maximum(dirs @ dirs.T, 0.0)
    part = valid[2] @ cosw / cosw.sum(0)
    assert np.any(part == 0)  # the directions far below see no valid sample
    np.testing.assert_allclose(w[2], np.where(part > 0, 0.4 / np.where(part > 0, part, 1.0), 0.0))
