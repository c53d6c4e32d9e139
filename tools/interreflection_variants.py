"""Measure the interreflection variants tabled in docs/notes/interreflection.md (issue 18).

    python tools/interreflection_variants.py settings    # estimator settings: accuracy and frame time
    python tools/interreflection_variants.py occlusion   # the products' order, occlusion="exp", its floor

Run from the repository's root (it reads the fidelity tier's scenes from ``tests/fidelity``); prints
Markdown tables. Accuracy is the relative RMS of an object's indirect (and total) light against
Mitsuba 3 at the fidelity tier's samples per vertex (``CORNER_SPP``, seed 0), one bounce, scored as
the tier scores it (the box's bottom face, on the floor, left out). Each reference is rendered once a
run; each scene is precomputed once at the defaults and every variant is a run-time option of that
precomputation (``Interreflection(scene, options, data)``).

* ``settings``: run-time settings that cast fewer rays in a moving-object frame, scored on the moved
  corner (precomputed with the torus 1.16 m away, moved back by a FrameState) and the cluster (torus,
  box and ball 2 cm apart); each timed on the room benchmark's moving-object frame
  (``interreflection.frame.move_one``: 2 threads, the variants' frames interleaved in one process,
  medians) and given as a ratio to the defaults'.
* ``occlusion``: how the occluders' SH visibilities combine, on the corner (in place), the corner with
  the torus moved 2.5 cm beside the box, and the cluster: the products nearest first (the paper, the
  default), the products farthest first (``occluder_order`` reversed, for this measurement only),
  ``occlusion="exp"`` with HYB and with the exact exponential, and (cluster) the logs floored at 1e-3
  instead of ``LOG_FLOOR``; then how much reversing the products' order changes the cluster's indirect
  light (relative RMS of the difference).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import prtlab  # noqa: E402
from prtlab.interreflection import Interreflection  # noqa: E402
from prtlab.interreflection import _pipeline  # noqa: E402
from prtlab.pipeline import FrameState  # noqa: E402
from prtlab.reference import shade_mitsuba  # noqa: E402
from prtlab.shadowfields import log_occlusion_field  # noqa: E402
from tests.fidelity import test_interreflection as fidelity  # noqa: E402

#: label -> run-time options of a moving-object frame
SETTINGS = {"defaults (`residual_rays=64`, `near_field=0.5`)": {}, "`near_field=0.25`": {"near_field": 0.25},
            "`near_field=0` (the paper)": {"near_field": 0.0}, "`residual_rays=48`": {"residual_rays": 48},
            "`residual_rays=32`": {"residual_rays": 32},
            "`near_field=0.25`, `residual_rays=48`": {"near_field": 0.25, "residual_rays": 48}}
FRAMES = 6  # timed frames per setting (after one warm-up)


def _scored(scene, reference, shaded, objects, parts=("indirect",)) -> dict:
    """(object, part) -> relative RMS against the reference, as the fidelity tier scores it."""
    masks = {"box": scene.object("box").world_vertices()[:, 1] > 0.01}
    comparison = prtlab.compare(shaded, reference, objects=list(objects), parts=list(parts), masks=masks)
    return {(o, p): comparison.row(o, p).rel_rms for o in objects for p in parts}


def _variant(pre, **options) -> Interreflection:
    return Interreflection(pre.scene, dataclasses.replace(pre.options, **options), pre.data)


def _with_logs(pre, logs: dict) -> dict:
    """``pre.data`` with each stored entry's log field ``logs[name]`` (objects stored ``same_as`` others read
    theirs)."""
    return {name: ({**entry, "log_oof": logs[name].to_arrays()} if "same_as" not in entry else entry)
            for name, entry in pre.data.items()}


def _moved_corner():
    """``(scene, precomputation, state)``: the corner precomputed with the torus away, moved back."""
    scene = fidelity.corner_scene()
    away = fidelity.corner_scene(fidelity.TORUS_AWAY)
    pre = Interreflection.precompute(away, progress=False)
    state = FrameState.from_scene(away)
    state.transforms["torus"] = scene.object("torus").transform
    return scene, pre, state


def settings() -> None:
    spp = fidelity.CORNER_SPP
    scene, pre, state = _moved_corner()
    reference = shade_mitsuba(scene, bounces=1, spp=spp, seed=0)
    corner = {k: _scored(scene, reference, _variant(pre, **o).shade(state, bounces=1), ("torus", "wall_back",
                                                                                        "wall_left"))
              for k, o in SETTINGS.items()}
    cluster_scene = fidelity.cluster_scene()
    reference = shade_mitsuba(cluster_scene, bounces=1, spp=spp, seed=0)
    pre = Interreflection.precompute(cluster_scene, progress=False)
    cluster = {k: _scored(cluster_scene, reference, _variant(pre, **o).shade(bounces=1), ("box", "ball", "torus"))
               for k, o in SETTINGS.items()}

    from prtlab.bench import _threads
    from prtlab.benchmarks import bench_interreflection as bench

    room = bench._precomputed(False)
    seconds: dict = {k: [] for k in SETTINGS}
    with _threads(2):
        runs = {k: bench._moving(_variant(room, **o))[:2] for k, o in SETTINGS.items()}
        for _ in range(FRAMES):
            for k, (setup, run) in runs.items():
                setup()
                t0 = time.perf_counter()
                run()
                seconds[k].append(time.perf_counter() - t0)
    base = np.median(seconds[next(iter(SETTINGS))])
    print(f"load {os.getloadavg()[0]:.1f}; {FRAMES} frames a setting; Mitsuba {spp} spp; indirect relative RMS\n")
    print("| setting | frame (ms) | frame ratio | corner_moved torus / walls | cluster box / ball / torus |")
    print("|---|---|---|---|---|")
    for k in SETTINGS:
        c, u = corner[k], cluster[k]
        walls = sorted((c["wall_back", "indirect"], c["wall_left", "indirect"]))
        print(f"| {k} | {1000 * np.median(seconds[k]):.0f} | {np.median(seconds[k]) / base:.2f} | "
              f"{c['torus', 'indirect']:.3f} / {walls[0]:.3f}-{walls[1]:.3f} | {u['box', 'indirect']:.3f} / "
              f"{u['ball', 'indirect']:.3f} / {u['torus', 'indirect']:.3f} |")


def occlusion() -> None:
    spp = fidelity.CORNER_SPP
    nearest = _pipeline.occluder_order
    shipped = fidelity.corner_scene()
    pre_corner = Interreflection.precompute(shipped, progress=False)
    corner_logs = _variant(pre_corner, occlusion="exp").occluders
    by_box = FrameState.from_scene(shipped)
    by_box.transforms["torus"] = fidelity.TORUS_BY_BOX
    cluster_scene = fidelity.cluster_scene()
    pre_cluster = Interreflection.precompute(cluster_scene, progress=False)
    cluster_logs = _variant(pre_cluster, occlusion="exp").occluders
    floored = {n: log_occlusion_field(f, floor=1e-3) for n, f in
               Interreflection(cluster_scene, pre_cluster.options, pre_cluster.data).fields.items()}
    cases = [("corner (one non-flat occluder per pair)", shipped, pre_corner, None, corner_logs),
             ("torus 2.5 cm beside the box", fidelity.corner_scene(fidelity.TORUS_BY_BOX), pre_corner, by_box,
              corner_logs),
             ("cluster: torus, box and a ball 2 cm apart", cluster_scene, pre_cluster, None, cluster_logs)]
    objects = ("floor", "box", "torus", "ball")
    rows, order_change = [], {}
    for label, scene, pre, state, logs in cases:
        reference = shade_mitsuba(scene, bounces=1, spp=spp, seed=0)
        data = _with_logs(pre, logs)
        variants = [("products (default)", lambda: _variant(pre)),
                    ("products, farthest first", lambda: _variant(pre)),
                    ("`exp` (HYB)", lambda: Interreflection(pre.scene, dataclasses.replace(
                        pre.options, occlusion="exp"), data)),
                    ("`exp`, exact exponential", lambda: Interreflection(pre.scene, dataclasses.replace(
                        pre.options, occlusion="exp", exp_method="exact"), data))]
        if logs is cluster_logs:
            variants.append(("`exp` (HYB), logs floored at 1e-3", lambda: Interreflection(
                pre.scene, dataclasses.replace(pre.options, occlusion="exp"), _with_logs(pre, floored))))
        shaded = {}
        for name, make in variants:
            _pipeline.occluder_order = ((lambda c, cs: list(nearest(c, cs))[::-1]) if "farthest" in name
                                        else nearest)
            try:
                shaded[name] = make().shade(state, bounces=1)
            finally:
                _pipeline.occluder_order = nearest
            present = [o for o in objects if o in shaded[name].indirect]
            scores = _scored(scene, reference, shaded[name], present, ("indirect", "total"))
            rows.append((label, name, scores))
        if logs is cluster_logs:
            a, b = shaded["products (default)"], shaded["products, farthest first"]
            order_change = {o: np.sqrt(np.mean((a.indirect[o] - b.indirect[o]) ** 2) / np.mean(a.indirect[o] ** 2))
                            for o in a.indirect}
    print(f"Mitsuba {spp} spp; relative RMS, one bounce\n")
    print("| scene | variant | floor ind. | box ind. | torus ind. | ball ind. | box total | torus total | ball total |")
    print("|---|---|---|---|---|---|---|---|---|")
    last = None
    for label, name, scores in rows:
        cell = [f"{scores[o, 'indirect']:.3f}" if (o, "indirect") in scores else "-" for o in objects]
        cell += [f"{scores[o, 'total']:.3f}" if (o, "total") in scores else "-" for o in objects[1:]]
        print(f"| {label if label != last else ''} | {name} | " + " | ".join(cell) + " |")
        last = label
    print("\nReversing the products' order, cluster, relative RMS of the change of the indirect light: "
          + ", ".join(f"{o} {v:.4f}" for o, v in order_change.items()))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("table", choices=("settings", "occlusion"))
    args = parser.parse_args(argv)
    {"settings": settings, "occlusion": occlusion}[args.table]()


if __name__ == "__main__":
    main()
