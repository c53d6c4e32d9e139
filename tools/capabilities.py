"""Measure what each method costs and write README.md's table of what each method can and cannot do.

    python tools/capabilities.py            # measure, print the table, rewrite it in README.md
    python tools/capabilities.py --print    # measure and print only

The capability columns (light types, bounces, glossy, moving objects, ground) are stated here
from the code of each method (the module named in each row); the measured columns come from one
run per method, each in its own process on a small shipped scene with the options named in the
table's caption:

* precompute: wall time of ``Precomputation.precompute(scene, options, cache=False)``;
* data: bytes of the precomputed arrays (what the cache stores and a frame reads);
* peak memory: the process's peak resident set (``ru_maxrss``) minus its resident set after the
  imports and the scene were loaded, i.e. what the precomputation and the frame added;
* frame: median wall time of ``pre.shade(FrameState)`` over three frames alternating between
  the animation's first and middle frames (the object moved or another sky), after one warm-up;
  for the references, the whole estimate (they have no precomputation).

Each measuring process is run twice and the second run is kept, so numba's compilation (cached
on disk after the first run) is not counted. The table is written between the markers
``<!-- capabilities:begin -->`` and ``<!-- capabilities:end -->`` of README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- capabilities:begin -->", "<!-- capabilities:end -->"

# method -> (shipped scene, options, frame bounces): each pipeline on a scene of its paper, default options
RUNS = {
    "reference": ("bunny_floor_arealight", {"n_samples": 256}, 1),
    "mitsuba": ("bunny_floor_arealight", {"spp": 256}, 1),
    "interreflection": ("bunny_floor_arealight", {}, 1),
    "spherelights": ("bunny_spheres_env", {}, 1),
    "portals": ("box_window_sky", {}, 2),
}

# Read from each method's code: lights it accepts, bounces, materials, motion, grounds.
CAPABILITIES = {
    "reference": (  # prtlab/reference/_estimators.py
        "environment, area, point",
        "any",
        "yes (Phong)",
        "yes (re-estimated per frame)",
        "yes (any object)",
    ),
    "mitsuba": (  # prtlab/reference/_mitsuba.py; needs the 'reference' extra
        "environment, area, point",
        "any",
        "yes (Phong)",
        "yes (re-estimated per frame)",
        "yes (any object)",
    ),
    "interreflection": (  # prtlab/interreflection/_pipeline.py
        "environment, area; point with `shadows=haar`",
        "any (chosen per frame)",
        "yes (Phong, separable BRDF)",
        "rigid motion of any object; no deformation",
        "yes: a plane is an object that casts, receives and reflects",
    ),
    "spherelights": (  # prtlab/spherelights/_pipeline.py
        "environment only (+ spherical lights as option `local_lights`)",
        "1, or 2 through the ground (`bounces=2`)",
        "no (Phong shaded with its diffuse part)",
        "rigid motion, uniform scale, soft deformation",
        "a flat ground: hides the sky below the horizon, reflects onto the objects (ray-cast against their meshes) and receives",
    ),
    "portals": (  # prtlab/portals/_pipeline.py
        "environment seen through portals (distant or per-frame shell cubemaps); interior point and area lights",
        "up to the precomputed `bounces`",
        "yes (Phong lobe toward the exact view; the paper's view cubemaps as an option)",
        "no: the interior is precomputed (lighting and exterior change)",
        "the room's floor is part of the precomputed interior",
    ),
}

_MEASURE = r'''
import json, os, resource, statistics, sys, time
import numpy as np
import prtlab, prtlab.data
from prtlab.pipeline import FrameState

method, scene_name, options, bounces = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), int(sys.argv[4])

def rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

def nbytes(value):
    if isinstance(value, dict):
        return sum(nbytes(v) for v in value.values())
    return value.nbytes if isinstance(value, np.ndarray) else 0

scene = prtlab.load_scene(prtlab.data.scene_path(scene_name))
classes = {}
if method in ("interreflection", "spherelights", "portals"):
    from prtlab.interreflection import Interreflection
    from prtlab.portals import Portals
    from prtlab.spherelights import SphereLights
    classes = {"interreflection": Interreflection, "spherelights": SphereLights, "portals": Portals}
    classes[method]  # imports (and their kernels) before the baseline
else:
    import prtlab.reference
base = rss_mb()
state_scene = scene.at_frame(1, 3) if scene.animation is not None else scene
result = {"vertices": sum(o.n_vertices for o in scene.objects if not o.portal)}
if method in classes:
    t0 = time.perf_counter()
    pre = classes[method].precompute(scene, options, cache=False, progress=False)
    result["precompute_s"] = time.perf_counter() - t0
    result["data_mb"] = nbytes(pre.data) / 2**20
    state = FrameState.from_scene(state_scene)
    pre.shade(FrameState.from_scene(scene), bounces=bounces)
    times = []
    for k in range(3):
        # alternate the two poses so that every frame is a frame after a change
        s = state if k % 2 == 0 else FrameState.from_scene(scene)
        t0 = time.perf_counter()
        pre.shade(s, bounces=bounces)
        times.append(time.perf_counter() - t0)
    result["frame_s"] = statistics.median(times)
else:
    t0 = time.perf_counter()
    prtlab.shade(state_scene, method=method, bounces=bounces, progress=False, **options)
    result["frame_s"] = time.perf_counter() - t0
result["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - base
print(json.dumps(result))
'''


def measure(method: str) -> dict:
    scene, options, bounces = RUNS[method]
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "PRTLAB_CACHE": cache, "PRTLAB_QUICK": "0"}
        env.pop("PYTHONPATH", None)
        env["PYTHONPATH"] = str(ROOT)
        for _ in range(2):  # the first run compiles the numba kernels (cached on disk)
            proc = subprocess.run([sys.executable, "-c", _MEASURE, method, scene, json.dumps(options), str(bounces)],
                                  capture_output=True, text=True, env=env, cwd=cache)
            if proc.returncode != 0:
                raise RuntimeError(f"measuring {method} failed:\n{proc.stderr[-3000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result["load"] = os.getloadavg()[0]
    return result


def _seconds(s: float | None) -> str:
    if s is None:
        return "none"
    return f"{s * 1e3:.0f} ms" if s < 1 else f"{s:.1f} s"


def table(results: dict) -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    runs = "; ".join(
        f"{m}: `{RUNS[m][0]}` ({results[m]['vertices']} vertices), "
        + (", ".join(f"{k}={v}" for k, v in RUNS[m][1].items()) or "default options")
        + f", bounces={RUNS[m][2]}"
        for m in results
    )
    lines = [
        "| method | lights | bounces | glossy | moving objects | ground | precompute | data | peak memory | frame |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for method, r in results.items():
        caps = CAPABILITIES[method]
        data = "none" if "data_mb" not in r else (
            f"{r['data_mb']:.1f} MB" if r["data_mb"] >= 1 else f"{r['data_mb'] * 1024:.0f} KB")
        lines.append(f"| {method} | " + " | ".join(caps) + f" | {_seconds(r.get('precompute_s'))} | {data} | "
                     f"{r['peak_mb']:.0f} MB | {_seconds(r['frame_s'])} |")
    loads = [r["load"] for r in results.values()]
    caption = (f"Measured by `python tools/capabilities.py` on {cpu} ({os.cpu_count()} cores, shared with other "
               f"work: 1-minute load average {min(loads):.1f}-{max(loads):.1f} during the runs, so times are "
               "upper bounds), one process per method, numba kernels already compiled. "
               f"Scenes and options: {runs}. "
               "Precompute: wall time, no cache; data: the precomputed arrays; peak memory: peak resident "
               "set above the process after imports; frame: median time of `shade(FrameState)` over "
               "three frames alternating between the scene's first and middle animation frames (the object "
               "moved or another sky), after one warm-up (the references: the whole estimate). Times and sizes grow with "
               "the vertices and the options (docs/BENCHMARKS.md has the papers' sizes).")
    return "\n".join(lines) + "\n\n" + caption


def write_readme(text: str, readme: Path = ROOT / "README.md") -> None:
    content = readme.read_text(encoding="utf-8")
    if BEGIN not in content or END not in content:
        raise ValueError(f"{readme}: the markers {BEGIN} and {END} are missing; add them where the table goes")
    head, rest = content.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    readme.write_text(f"{head}{BEGIN}\n{text}\n{END}{tail}", encoding="utf-8")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--print", action="store_true", help="print the table, do not rewrite README.md")
    parser.add_argument("--methods", default=",".join(RUNS), help="comma-separated methods (default: all)")
    args = parser.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",")]
    unknown = [m for m in methods if m not in RUNS]
    if unknown:
        parser.error(f"--methods: unknown method(s) {unknown}; choose from {', '.join(RUNS)}")
    results = {}
    for method in methods:
        print(f"measuring {method} ...", file=sys.stderr)
        results[method] = measure(method)
        print(f"  {results[method]}", file=sys.stderr)
    text = table(results)
    print(text)
    if not args.print:
        write_readme(text)
        print("wrote the table into README.md", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
