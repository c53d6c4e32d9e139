"""The window box of Yue et al. Fig. 10 against Mitsuba 3, whole scene (slow).

Scored with :func:`prtlab.compare` (relative RMS per vertex, the reference's noise removed in quadrature) against
the goal ``GOAL``: the paper reports a 1.5% (Fig. 10) and 2.1% (Fig. 11) average relative error, but judging those
needs a reference noise of a third of them (0.5%: about 10^6 Mitsuba samples per vertex on these 2,000-vertex
rooms), so the goal is issue 15's 5%, judged against references of at most 5% / 3 relative noise. The room's
vertices on its edges are left out (vertices where two walls meet carry the normal of one wall only). The fidelity
tier (``tests/fidelity/test_portals.py``) scores the same method on a smaller room in CI, and the glossy bunny of
Fig. 11 (``tests/fidelity/test_portals_glossy.py``).
"""

import numpy as np
import pytest

import prtlab
from prtlab.geometry import cubemap_directions, equirect_lookup
from prtlab.portals import Portals, shell_light
from prtlab.reference import shade_mitsuba
from prtlab.scene import load_scene
from prtlab.wavelet import haar2d

from ..conftest import MC_SIGMAS

GOAL = 0.05
SPP = 65536  # Mitsuba samples per vertex: relative noise about 1.4-1.6% on a window-lit room (< GOAL / 3)

SCENE = prtlab.__file__.rsplit("/", 2)[0] + "/data/scenes/box_window_sky.yaml"


def _interior(obj):
    """The vertices of a room that lie on one wall only (not on an edge or corner)."""
    v = obj.world_vertices()
    lo, hi = v.min(0), v.max(0)
    return ((np.abs(v - lo) < 1e-9) | (np.abs(v - hi) < 1e-9)).sum(1) == 1


@pytest.fixture(scope="module")
def fig10():
    """Fig. 10, B = 2: the precomputation, its shading and a Mitsuba 3 reference of 131,072 samples per vertex
    (65,536 left the indirect part's relative noise at 1.9% > GOAL / 3)."""
    scene = load_scene(SCENE)
    bounces = 2
    pre = Portals.precompute(scene, {"direct_samples": 1024, "n_photons": 1_000_000, "gather_rays": 512,
                                     "order": 4, "bounces": bounces}, cache=False, progress=False)
    ours = pre.shade(bounces=bounces)
    ref = shade_mitsuba(scene, bounces=bounces, spp=2 * SPP, seed=5)
    comparison = prtlab.compare(ours, ref, objects=["room"])
    print(f"\nFig. 10\n{comparison.table()}")
    return scene, pre, ours, ref, comparison


@pytest.mark.slow
def test_box_window_sky_direct_mean(fig10):
    """The mean direct radiance of the room's vertices off its edges within the reference's error plus the
    per-vertex cubemap-resolution bound (test_direct.py) and the 8-bit bound."""
    scene, pre, ours, ref, _ = fig10
    interior = _interior(scene.objects[0])
    # sum_k T_k (max - min of L over texel k) (test_direct.py) and the 8-bit bound scale / 510 * |L|_1.
    sparse = pre.direct_transfer(0)
    res = sparse.res
    fine = equirect_lookup(scene.environment.image, cubemap_directions(res * 8)).reshape(6, res, 8, res, 8, 3)
    spread = fine.max(axis=(2, 4)) - fine.min(axis=(2, 4))
    cube = shell_light(scene.environment, res)
    albedo = pre.data["albedo"]
    bound = albedo * (np.einsum("vfij,fijc->vc", sparse.to_dense(), spread)
                      + sparse.scale[:, None] / 510 * np.abs(haar2d(cube, channels=True)).sum((0, 1, 2))
                      + sparse.scale[:, None] / 510 * np.abs(cube).sum((0, 1, 2)))
    a, e, se = (x["room"][interior] for x in (ours.direct, ref.direct, ref.stderr["direct"]))
    diff = np.abs(a.mean(0) - e.mean(0))
    allowed = MC_SIGMAS * np.sqrt((se**2).sum(0)) / len(a) + bound[interior].mean(0)
    assert np.all(diff <= allowed), (a.mean(0), e.mean(0))


@pytest.mark.slow
@pytest.mark.parametrize("part", ["direct", "indirect", "total"])
def test_box_window_sky_against_reference(fig10, part):
    """Fig. 10: the room's relative RMS per vertex within ``hypot(GOAL, noise)``, per part. Measured at the defaults
    (``indirect="surface"``, res 64): direct 0.012 (noise 0.011), indirect 0.040 (0.013, mean ratio 1.007), total
    0.020 (0.010); the paper's SH transfer had indirect 0.114 and total 0.055 (res 32, before the edge-corrected
    estimate)."""
    comparison = fig10[-1]
    assert comparison.check(GOAL, parts=(part,)) == [], comparison.table()
