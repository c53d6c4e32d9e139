"""The ``prtlab`` command: a thin layer over :mod:`prtlab.api`.

::

    prtlab shade SCENE --method M [--bounces B] [--out radiance.npz]
    prtlab render SCENE --method M [--frames N] --out out/
    prtlab precompute SCENE --method M [--workers N | --scheduler ADDRESS]
    prtlab reproduce [--quick] [--out report/]
    prtlab bench [--quick] [--json bench.json] [--select NAME]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

METHOD_NAMES = ("reference", "mitsuba", "interreflection", "spherelights", "portals")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="prtlab", description="Precomputed radiance transfer for dynamic scenes.")
    sub = parser.add_subparsers(dest="command", required=True)

    def method_args(p):
        p.add_argument("scene", type=Path, help="scene file (YAML)")
        p.add_argument("--method", required=True, choices=METHOD_NAMES)
        p.add_argument("--bounces", type=int, default=1, help="indirect bounces (0 = direct only)")
        p.add_argument("--samples", type=int, default=None, help="Monte Carlo samples per vertex (references)")
        p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser("shade", help="per-vertex radiance of a scene")
    method_args(p)
    p.add_argument("--out", type=Path, default=Path("radiance.npz"), help="keys <object>/direct|indirect|total")

    p = sub.add_parser("render", help="images of a scene (one per animation frame)")
    method_args(p)
    p.add_argument("--frames", type=int, default=1)
    p.add_argument("--out", type=Path, required=True, help="output folder (PNG and EXR per frame)")
    p.add_argument("--exposure", type=float, default=0.0, help="exposure in stops")

    p = sub.add_parser("precompute", help="run and cache a method's precomputation")
    p.add_argument("scene", type=Path)
    p.add_argument("--method", required=True, choices=METHOD_NAMES)
    group = p.add_mutually_exclusive_group()
    group.add_argument("--workers", type=int, default=None, help="local Dask workers")
    group.add_argument("--scheduler", default=None, help="address of a Dask scheduler")

    p = sub.add_parser("reproduce", help="every paper figure and table that exists so far, as report/index.html")
    p.add_argument("--quick", action="store_true", help="small sizes (PRTLAB_QUICK=1)")
    p.add_argument("--out", type=Path, default=Path("report"))
    p.add_argument("--only", default=None, help="run only notebooks whose name contains this")

    p = sub.add_parser("bench", help="benchmarks, with peers and the machine's peak measured in the same run")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--select", default=None, help="run only cases whose name contains this")
    return parser


def _shade_options(args) -> dict:
    options = {"seed": args.seed}
    if args.samples is not None:
        options["n_samples"] = args.samples
    return options


def _cmd_shade(args) -> int:
    from prtlab import api

    result = api.shade(args.scene, method=args.method, bounces=args.bounces, **_shade_options(args))
    path = result.save_npz(args.out)
    print(f"wrote {path} ({len(result.total)} objects)")
    return 0


def _cmd_render(args) -> int:
    from prtlab import api
    from prtlab.render import save_exr, save_png
    from prtlab.scene import load_scene

    scene = load_scene(args.scene)
    args.out.mkdir(parents=True, exist_ok=True)
    for frame in range(args.frames):
        frame_scene = scene.at_frame(frame, args.frames) if args.frames > 1 else scene
        result = api.shade(frame_scene, method=args.method, bounces=args.bounces, **_shade_options(args))
        image = api.render_image(frame_scene, result)
        stem = args.out / f"frame_{frame:04d}"
        save_png(stem.with_suffix(".png"), image, exposure=args.exposure)
        save_exr(stem.with_suffix(".exr"), image)
        print(f"wrote {stem}.png and .exr")
    return 0


def _cmd_precompute(args) -> int:
    from prtlab import api

    if args.method in ("reference", "mitsuba"):
        print(f"method {args.method!r} has no precomputation: it estimates radiance directly")
        return 0
    pre = api.precompute(args.scene, args.method, workers=args.workers, scheduler=args.scheduler)
    print(f"{args.method}: precomputation of {args.scene} is cached ({type(pre).__name__})")
    return 0


def _cmd_reproduce(args) -> int:
    from prtlab.reproduce import reproduce

    return 0 if reproduce(args.out, quick=args.quick, only=args.only) else 1


def _cmd_bench(args) -> int:
    from prtlab.bench import run_benchmarks

    run_benchmarks(quick=args.quick, select=args.select, json_path=args.json)
    return 0


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    handler = {
        "shade": _cmd_shade,
        "render": _cmd_render,
        "precompute": _cmd_precompute,
        "reproduce": _cmd_reproduce,
        "bench": _cmd_bench,
    }[args.command]
    try:
        return handler(args)
    except NotImplementedError as error:
        print(f"prtlab {args.command}: {error}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError) as error:
        print(f"prtlab {args.command}: error: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
