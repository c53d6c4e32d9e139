"""The glossy bunny of Yue et al. Fig. 11 against Mitsuba 3: every object, direct / indirect / total (issue 17).

Scene: ``box_window_glossy_bunny_fig11`` (the 4 x 2.5 x 4 m box lit through a 1.5 x 1.0 m window by a sunless
Preetham sky, a Phong-10 bunny of 1,839 vertices) with the room at :data:`CELL` m cells (392 vertices; the scene's
0.2 m cells would take twice the reference's time and the precomputation's memory for the room alone), precomputed
at the defaults with :data:`BOUNCES` bounces: ``glossy_direct="lobe"``, and ``indirect="auto"``, which is the
paper's photon SH transfer here (the bunny is glossy; ``indirect="surface"`` takes diffuse interiors only). The
bunny's vertices resting on the floor and facing into it (``y < 0.02``) are left out: their radiance is not
defined.

References, relative RMS per vertex (:func:`prtlab.compare`), the reference's noise in quadrature
(:meth:`prtlab.metrics.ComparisonRow.meets`), goal issue 17's 5% (:data:`GOAL`, as the tiny room of
``tests/fidelity/test_portals.py``: the paper's 2.1% for Fig. 11 needs a reference noise of 0.7%, about 10^6
samples per vertex):

- direct light: a quadrature over the window, not Mitsuba (at 16,384 samples per vertex Mitsuba's direct light is
  3.1% noisy on the room): ``int_window L(d) f(d, wo) cos_v cos_w / r^2 V dA`` over an ``n x n`` midpoint grid with
  a shadow ray per point (the scene's ray caster) and the normalised Phong BRDF toward the camera that Mitsuba's
  reference uses, its error taken as its difference from a 64 x 64 grid (:func:`window_direct`); it agrees with
  Mitsuba's direct light within Mitsuba's noise (measured, and :func:`test_direct_quadrature_against_mitsuba`);
- indirect light: Mitsuba 3 at :data:`SPP` samples per vertex, the same bounces;
- total: the quadrature's direct light plus Mitsuba's indirect light, so its noise is the indirect part's alone.

The module costs about 2.5 CPU-minutes (the precomputation, the reference at :data:`SPP`, the quadratures). A
noise of a third of the goal on the indirect rows would need about 93,000 samples per vertex (the room) and 65,000
(the bunny): those rows miss by far more than the noise (:data:`MEASURED`), so they stay at :data:`SPP` and ``check``
refuses them as too noisy (strict xfails, ``ValueError``, their measured figures in the reason).
"""

from __future__ import annotations

import numpy as np
import pytest

import prtlab
import prtlab.api
from prtlab.geometry import RayCaster
from prtlab.reference import shade_mitsuba
from prtlab.scene import Scene, ShadeResult

from ..conftest import MC_SIGMAS
from .conftest import on_the_floor

pytestmark = pytest.mark.xdist_group("fidelity-portals-glossy")

GOAL = 0.05
CELL = 0.5
BOUNCES = 2
SPP = 32768
SEED = 17
QUADRATURE = 128  # window points per side of the direct reference (its error: the difference from 64)
OBJECTS = ("room", "bunny")
PARTS = ("direct", "indirect", "total")
RESTING = 0.02  # bunny vertices below this height, facing into the floor, rest on it (not scored)


def glossy_box() -> Scene:
    """``box_window_glossy_bunny_fig11`` with the room at :data:`CELL` m cells."""
    d = prtlab.load_scene("box_window_glossy_bunny_fig11").to_dict()
    d["objects"][0]["mesh"]["cell_size"] = CELL
    return Scene.from_dict(d)


def window_direct(scene: Scene, n: int, batch: int = 32) -> dict[str, np.ndarray]:
    """Direct radiance toward the camera of every shaded object's vertices, ``{name: (V, 3)}``, by an ``n x n``
    midpoint grid over the scene's one axis-aligned window on a -z wall, a shadow ray to each grid point (the
    scene's objects, the window excepted, occlude) and the normalised Phong (or Lambert) BRDF."""
    window, light = scene.object("window"), scene.lights[0]
    w = window.world_vertices()
    lo, hi = w.min(0), w.max(0)
    corners = np.all((np.abs(w[:, :2] - lo[:2]) < 1e-9) | (np.abs(w[:, :2] - hi[:2]) < 1e-9))
    if hi[2] - lo[2] > 1e-9 or len(w) != 4 or not corners:
        raise ValueError("window_direct needs one axis-aligned rectangular window in a plane z = const")
    u = (np.arange(n) + 0.5) / n
    gx, gy = np.meshgrid(lo[0] + u * (hi[0] - lo[0]), lo[1] + u * (hi[1] - lo[1]))
    grid = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, lo[2])])
    area = (hi[0] - lo[0]) * (hi[1] - lo[1]) / gx.size
    caster = RayCaster(scene)
    camera = np.asarray(scene.camera.position, float)
    out = {}
    for obj in scene.objects:
        if obj.portal:
            continue
        x = obj.world_shading_points()
        normals = obj.world_normals()
        normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        m = obj.material
        kd, ks, e = ((np.asarray(m.kd, float), np.asarray(m.ks, float), float(m.exponent)) if m.type == "phong"
                     else (np.asarray(m.albedo, float), np.zeros(3), 0.0))
        view = camera - x
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        radiance = np.zeros((len(x), 3))
        for s in range(0, len(x), batch):
            xs, ns, ws = x[s:s + batch], normals[s:s + batch], view[s:s + batch]
            d = grid[None] - xs[:, None]
            r = np.linalg.norm(d, axis=2)
            d /= r[..., None]
            cos_v = np.einsum("vsk,vk->vs", d, ns)
            weight = np.maximum(cos_v, 0.0) * np.abs(d[..., 2]) / r**2 * area
            vi, si = np.nonzero(weight > 0)
            seen = ~caster.occluded(xs[vi], d[vi, si], r[vi, si] * (1 - 1e-6), normals=ns[vi])
            vi, si = vi[seen], si[seen]
            wi = d[vi, si]
            f = np.broadcast_to(kd / np.pi, (len(vi), 3)).copy()
            if ks.any():
                mirror = 2 * cos_v[vi, si, None] * ns[vi] - wi
                f += ks * ((e + 2) / (2 * np.pi) * np.maximum(np.einsum("sk,sk->s", mirror, ws[vi]), 0.0) ** e)[:, None]
            np.add.at(radiance, s + vi, light.radiance(wi) * f * weight[vi, si, None])
        out[obj.name] = radiance
    return out


@pytest.fixture(scope="module")
def glossy_scored():
    """Ours (defaults, :data:`BOUNCES` bounces), Mitsuba's per-vertex reference, the reference with its direct
    light by the window quadrature (total = quadrature + Mitsuba's indirect), and their comparison."""
    scene = glossy_box()
    pre = prtlab.api.precompute(scene, "portals", progress=False, bounces=BOUNCES)
    ours = pre.shade(bounces=BOUNCES)
    mitsuba = shade_mitsuba(scene, bounces=BOUNCES, spp=SPP, seed=SEED)
    fine, coarse = window_direct(scene, QUADRATURE), window_direct(scene, QUADRATURE // 2)
    ref = ShadeResult()
    ref.stderr = {p: {} for p in PARTS}
    for o in OBJECTS:
        quad_err = np.abs(fine[o] - coarse[o])
        ref.direct[o], ref.stderr["direct"][o] = fine[o], quad_err
        ref.indirect[o], ref.stderr["indirect"][o] = mitsuba.indirect[o], mitsuba.stderr["indirect"][o]
        ref.total[o] = fine[o] + mitsuba.indirect[o]
        ref.stderr["total"][o] = np.hypot(quad_err, mitsuba.stderr["indirect"][o])
    masks = {"bunny": ~on_the_floor(scene, "bunny", RESTING)}
    comparison = prtlab.compare(ours, ref, objects=OBJECTS, masks=masks)
    print(f"\n{scene.name} (room cells {CELL} m), Mitsuba {SPP} spp, {BOUNCES} bounces\n{comparison.table()}")
    return scene, mitsuba, fine, coarse, masks, comparison


# Measured (this module: the defaults, seed SEED, SPP): relative RMS per vertex, the reference's relative noise, mean
# ratio ours / reference; the last field: the xfail's exception (ValueError: the reference too noisy for check; None:
# on its bound, a non-strict xfail). Rows within the goal: room direct 0.0009, bunny direct 0.0009 (the quadrature
# and the pipeline's direct light are both exact up to their sampling; against Mitsuba's direct light 0.031 and
# 0.017, its noise 0.031 and 0.016 at 16,384 spp), bunny total 0.034 (noise 0.005).
MEASURED = {
    ("room", "indirect"): (0.106, 0.028, 1.03, ValueError),
    ("bunny", "indirect"): (0.161, 0.024, 1.02, ValueError),
    ("room", "total"): (0.0516, 0.0136, 1.02, None),  # budget hypot(0.05, 0.0136) = 0.0518: on its bound
}
CAUSE = ("a glossy object makes indirect='auto' the paper's photon SH transfer (order-4 SH of the shell light, "
         "photon radiance estimates), which indirect='surface' (diffuse interiors only) does not replace yet")
DETAIL = {  # docs/notes/portals.md, "The glossy bunny as a fidelity case"
    "room": "surface mode with the bunny as a diffuse kd + ks proxy measured 0.062 (total 0.030)",
    "bunny": "64% of the squared error is in its 127 vertices 2-5 cm above the floor (0.56 there, 70% too bright; "
             "0.10 above 5 cm)",
}


def _case(obj, part):
    if (obj, part) not in MEASURED:
        return (obj, part)
    rel_rms, noise, ratio, raises = MEASURED[obj, part]
    figure = f"measured rel_rms {rel_rms:.4f} (noise {noise:.4f}, mean ratio {ratio:.2f})"
    if raises is ValueError:
        reason = (f"{figure}: misses goal {GOAL} by far more than the noise, but the reference's noise > goal / 3 at "
                  f"{SPP} spp (a third needs ~3x the samples, beyond the tier's time), so check refuses it; {CAUSE} "
                  f"({DETAIL[obj]})")
        mark = pytest.mark.xfail(strict=True, raises=ValueError, reason=reason)
    else:
        reason = (f"{figure}: on its bound hypot({GOAL}, noise) = {np.hypot(GOAL, noise):.4f} (met at this seed by "
                  f"0.0002; the indirect light 3% high); {CAUSE} ({DETAIL[obj]})")
        mark = pytest.mark.xfail(strict=False, raises=AssertionError, reason=reason)
    return pytest.param(obj, part, marks=mark)


@pytest.mark.parametrize("obj, part", [_case(o, p) for o in OBJECTS for p in PARTS])
def test_glossy_bunny_against_mitsuba(glossy_scored, obj, part):
    """``rel_rms <= hypot(GOAL, noise)`` for one object and part; ``check`` refuses a reference noisier than
    ``GOAL / 3``."""
    comparison = glossy_scored[-1]
    assert comparison.check(GOAL, parts=(part,), objects=(obj,)) == [], comparison.table()


def test_every_object_scored(glossy_scored):
    """The room and the bunny are scored on each part; the bunny without its vertices resting on the floor."""
    scene, *_, masks, comparison = glossy_scored
    assert {(r.object, r.part) for r in comparison.rows} == {(o, p) for o in OBJECTS for p in PARTS}
    rows = {r.object: r.n_vertices for r in comparison.rows}
    assert rows == {"room": scene.object("room").n_vertices, "bunny": int(masks["bunny"].sum())}
    assert 0 < rows["bunny"] < scene.object("bunny").n_vertices


def test_direct_quadrature_against_mitsuba(glossy_scored):
    """The direct reference: the quadrature's mean over each object's vertices within ``MC_SIGMAS`` standard errors
    of Mitsuba's mean (plus the quadrature's own error), per channel; and converged (the 64 x 64 grid within 1%
    relative RMS of the 128 x 128 one)."""
    _, mitsuba, fine, coarse, masks, _ = glossy_scored
    for o in OBJECTS:
        keep = masks.get(o, np.ones(len(fine[o]), bool))
        q, m, se, c = fine[o][keep], mitsuba.direct[o][keep], mitsuba.stderr["direct"][o][keep], coarse[o][keep]
        allowed = MC_SIGMAS * np.sqrt((se**2).sum(0)) / len(q) + np.abs(q - c).mean(0)
        assert np.all(np.abs(q.mean(0) - m.mean(0)) <= allowed), (o, q.mean(0), m.mean(0), allowed)
        assert np.sqrt(np.sum((q - c) ** 2) / np.sum(q**2)) < 0.01, o


def test_window_direct_refuses_other_windows():
    """The quadrature integrates one axis-aligned rectangle in a plane z = const: a window on an x wall is refused."""
    d = glossy_box().to_dict()
    for obj in d["objects"][:2]:
        windows = obj["mesh"].get("windows")
        if windows:
            windows[0]["wall"] = "+x"
        else:
            obj["mesh"]["wall"] = "+x"
    with pytest.raises(ValueError, match="axis-aligned rectangular window in a plane z = const"):
        window_direct(Scene.from_dict(d), 4)
