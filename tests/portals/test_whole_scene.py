"""The window box of Yue et al. Fig. 10 against the reference path tracer, whole scene (slow).

Measured once (box_window_sky.yaml, B = 3, 2048 portal samples, 2M photons, 1024 gather rays, reference 8192
paths per vertex with 3.7% mean relative standard error, vertices on two walls left out):
average relative difference of the total 3.9% (noise removed: 3.0% at SH order 4, 2.5% at 5, 1.7% at 8),
direct 4.1% (noise removed 2.4%, mean z^2 = 0.79), signed mean difference -0.2%.
"""

import numpy as np
import pytest

import prtlab
from prtlab.geometry import cubemap_directions, equirect_lookup
from prtlab.portals import Portals, shell_light
from prtlab.scene import load_scene
from prtlab.wavelet import haar2d

from ..conftest import MC_SIGMAS
from .test_indirect import MEASURED_BIAS

SCENE = prtlab.__file__.rsplit("/", 2)[0] + "/data/scenes/box_window_sky.yaml"


@pytest.mark.slow
def test_box_window_sky_against_reference():
    scene = load_scene(SCENE)
    bounces = 2
    pre = Portals.precompute(scene, {"direct_samples": 1024, "n_photons": 1_000_000, "gather_rays": 512,
                                     "order": 4, "bounces": bounces}, cache=False, progress=False)
    ours = pre.shade(bounces=bounces)
    ref = prtlab.shade(scene, method="reference", bounces=bounces, n_samples=2048, seed=5, progress=False)
    v = scene.objects[0].world_vertices()
    lo, hi = v.min(0), v.max(0)
    interior = ((np.abs(v - lo) < 1e-9) | (np.abs(v - hi) < 1e-9)).sum(1) == 1
    # direct: the room's mean within the reference's error plus the per-vertex cubemap-resolution bound
    # sum_k T_k (max - min of L over texel k) (test_direct.py) and the 8-bit bound scale / 510 * |L|_1.
    # (Per-vertex z-scores are not used: vertices lit only through grazing, rare paths get a reference standard
    # error of 0 or far too small at this sample count; see prtlab.reference.)
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
    assert np.all(diff <= MC_SIGMAS * np.sqrt((se**2).sum(0)) / len(a) + bound[interior].mean(0)), (a.mean(0), e.mean(0))
    # total: the room's mean radiance within the reference's error plus the measured photon-density bias
    a, e, se = (x["room"][interior] for x in (ours.total, ref.total, ref.stderr["total"]))
    diff = np.abs(a.mean(0) - e.mean(0))
    assert np.all(diff <= MC_SIGMAS * np.sqrt((se**2).sum(0)) / len(a) + bound[interior].mean(0)
                  + MEASURED_BIAS * e.mean(0)), (a.mean(0), e.mean(0))


FIG11 = prtlab.__file__.rsplit("/", 2)[0] + "/data/scenes/box_window_glossy_bunny_fig11.yaml"
GLOSSY_GOAL = 0.021  # the paper's average difference for Fig. 11


def fig11_comparison(options, ref_samples, seed=5):
    """Average relative difference of the total over the room's interior vertices and the bunny's upward-facing
    vertices (those resting on the floor have no well-defined radiance), and the reference's mean relative
    standard error."""
    scene = load_scene(FIG11)
    bounces = options["bounces"]
    pre = Portals.precompute(scene, options, cache=True, progress=False)
    ours = pre.shade(bounces=bounces)
    ref = prtlab.shade(scene, method="reference", bounces=bounces, n_samples=ref_samples, seed=seed, progress=False)
    v = scene.object("room").world_vertices()
    lo, hi = v.min(0), v.max(0)
    keep = {"room": ((np.abs(v - lo) < 1e-9) | (np.abs(v - hi) < 1e-9)).sum(1) == 1,
            "bunny": scene.object("bunny").world_vertices()[:, 1] > 0.02}
    def stats(a, e, se):  # average relative difference, reference se, noise removed, signed mean
        return (np.abs(a - e).mean() / e.mean(), se.mean() / e.mean(),
                np.sqrt(max(0.0, ((a - e) ** 2).mean() - (se**2).mean())) / e.mean(), (a - e).mean() / e.mean())

    rows = {}
    for name, m in keep.items():
        rows[name] = stats(ours.total[name][m], ref.total[name][m], ref.stderr["total"][name][m])
    rows["all"] = stats(*(np.concatenate([x[n][m] for n, m in keep.items()])
                          for x in (ours.total, ref.total, ref.stderr["total"])))
    return rows


@pytest.mark.slow
def test_fig11_glossy_bunny_against_reference():
    """Fig. 11: goal 2.1% + the reference's relative standard error (average relative difference of the total).

    Measured (reference 1024 paths per vertex, mean relative standard error 10.1%; 1,696 bunny vertices off the
    floor and the room's interior vertices), with glossy photon reflection and the glossy exitance: average
    relative difference of the total 9.1% (goal 12.2%: met), noise removed 5.0%, signed mean -0.2%; bunny
    indirect signed -3.4%, room indirect +2.3%. Before (kd-only photon map; the rest of this docstring):
    average relative difference of the total 9.5% (goal 12.2%: met),
    noise removed 7.3%, signed mean -2.4%. By part: bunny direct 6.4% (se 8.1%, noise removed 0.0%; with
    view_res 4 instead of 8: 9.2%, noise removed 23.5%: the bilinear blend of the per-direction cubemaps flattens
    the Phong highlights), bunny indirect signed -9.9% (with glossy_order 4 as well: -9.7%, so not the lobe's SH
    truncation), room total noise removed 5.5% (SH order 4 of the sky seen through the window, photon density
    bias). Precomputation about 13 min on 2 busy cores (the view_res 8 glossy direct transfer dominates).
    """
    rows = fig11_comparison({"direct_samples": 512, "n_photons": 1_000_000, "gather_rays": 256, "order": 4,
                             "bounces": 2, "view_res": 8, "glossy_order": 8}, ref_samples=1024)
    avg, se = rows["all"][:2]
    assert avg <= GLOSSY_GOAL + se, rows
