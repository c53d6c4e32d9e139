"""The prtlab command: every method runs, options are typed, outputs are checked first, one line per error.

Commands run in-process (``cli.main(argv)``) on tiny scenes with tiny method options, so each
precomputation takes well under a second once numba's kernels are compiled.
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import types
import typing

import numpy as np
import pytest

import prtlab
from prtlab import _compile_notice, api, cli
from prtlab.scene import ShadeResult
from tests.scenes import TINY_ROOM, TINY_SCENE

# The smallest options each method accepts that still exercise all of its passes.
TINY_OPTIONS = {
    "reference": ["--samples", "4"],
    "mitsuba": ["--samples", "4"],
    "interreflection": ["-o", "n_lights=8", "-o", "n_basis=4", "-o", "n_radii=4", "-o", "resolution=4",
                        "-o", "order=2"],
    "spherelights": ["-o", "n_spheres=2", "-o", "fit_resolution=10", "-o", "n_directions=12",
                     "-o", "cube_resolution=4"],
    "portals": ["-o", "cube_resolution=4", "-o", "direct_samples=16", "-o", "n_photons=2000", "-o", "gather_rays=16",
                "-o", "order=2", "-o", "photon_k=8", "-o", "view_res=1"],
}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scenes")
    (folder / "tiny.yaml").write_text(TINY_SCENE)
    (folder / "room.yaml").write_text(TINY_ROOM)
    return {"tiny": str(folder / "tiny.yaml"), "room": str(folder / "room.yaml")}


def scene_for(method, scenes):
    return scenes["room"] if method == "portals" else scenes["tiny"]


def run(capsys, *argv):
    """``prtlab -q argv`` in-process: (exit code, stdout, stderr)."""
    code = cli.main(["-q", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


# --------------------------------------------------------------------------- help and version


def test_help_lists_every_subcommand():
    proc = subprocess.run([sys.executable, "-m", "prtlab.cli", "--help"], capture_output=True, text=True)
    assert proc.returncode == 0
    for command in ("shade", "render", "compare", "precompute", "cache", "reproduce", "bench"):
        assert command in proc.stdout


def test_every_flag_and_subcommand_has_help():
    parser = cli._parser()
    subparsers = next(a for a in parser._actions if a.dest == "command")
    for name, sub in subparsers.choices.items():
        assert sub.description, name
        for action in sub._actions:
            assert action.help, f"prtlab {name} {action.option_strings or action.dest} has no help text"
    assert all(choice.help for choice in subparsers._choices_actions)
    assert all(a.help for a in parser._actions)


def test_version(capsys):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"prtlab {prtlab.__version__}"


def test_version_is_the_package_version():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    from pathlib import Path

    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    assert tomllib.loads(pyproject.read_text())["project"]["version"] == prtlab.__version__


# --------------------------------------------------------------------------- every method runs


@pytest.mark.parametrize("method", ["reference", "interreflection", "spherelights", "portals",
                                    pytest.param("mitsuba", marks=pytest.mark.mitsuba)])
def test_every_method_shades_from_the_command_line(method, scenes, tmp_path, capsys):
    if method == "mitsuba":
        pytest.importorskip("mitsuba")
    out = tmp_path / "radiance.npz"
    code, stdout, err = run(capsys, "shade", scene_for(method, scenes), "--method", method, *TINY_OPTIONS[method],
                            "--out", out)
    assert code == 0, err
    assert f"wrote {out}" in stdout
    result = ShadeResult.load_npz(out)
    assert result.total and all(np.all(np.isfinite(v)) for v in result.total.values())


def _ones(scene):
    res = ShadeResult()
    for obj in scene.objects:
        res.direct[obj.name] = res.indirect[obj.name] = res.total[obj.name] = np.ones((obj.n_vertices, 3))
    return res


def _capture_shade(monkeypatch):
    """Replace the api's shade (references) and precompute (pipelines): (method, bounces, options) per call."""
    calls = []

    def fake_shade(scene, method="reference", bounces=1, **options):
        calls.append((method, bounces, options))
        return _ones(scene)

    def fake_precompute(scene, method, **options):
        class Precomputed:
            def shade(self, state=None, bounces=1):
                calls.append((method, bounces, options))
                return _ones(scene)

        return Precomputed()

    monkeypatch.setattr(api, "shade", fake_shade)
    monkeypatch.setattr(api, "precompute", fake_precompute)
    return calls


def test_seed_and_samples_are_passed_only_when_given_and_taken(scenes, tmp_path, monkeypatch, capsys):
    calls = _capture_shade(monkeypatch)
    out = tmp_path / "r.npz"
    assert run(capsys, "shade", scenes["tiny"], "--method", "interreflection", "--out", out)[0] == 0
    assert run(capsys, "shade", scenes["tiny"], "--method", "reference", "--seed", "3", "--samples", "8",
               "--bounces", "2", "--out", out)[0] == 0
    assert run(capsys, "shade", scenes["room"], "--method", "portals", "--seed", "5", "--out", out)[0] == 0
    assert calls[0] == ("interreflection", 1, {"progress": False})
    assert calls[1] == ("reference", 2, {"seed": 3, "n_samples": 8, "progress": False})
    assert calls[2] == ("portals", 1, {"seed": 5, "bounces": 1, "progress": False})  # stores --bounces bounces


def test_a_pipeline_may_store_more_bounces_than_it_shades(scenes, tmp_path, monkeypatch, capsys):
    calls = _capture_shade(monkeypatch)
    out = tmp_path / "r.npz"
    assert run(capsys, "shade", scenes["room"], "--method", "portals", "-o", "bounces=4", "--bounces", "2",
               "--out", out)[0] == 0
    assert calls == [("portals", 2, {"bounces": 4, "progress": False})]


def test_options_are_typed_by_the_method(scenes, tmp_path, monkeypatch, capsys):
    calls = _capture_shade(monkeypatch)
    out = tmp_path / "r.npz"
    code, _, err = run(capsys, "shade", scenes["tiny"], "--method", "spherelights", "-o", "n_spheres={ball: 3}",
                       "-o", "ground=paper", "-o", "cut_threshold=0.5", "-o", "exp_method=ol",
                       "-o", "spherelights.order=3", "--out", out)
    assert code == 0, err
    assert calls[0][2] == {"n_spheres": {"ball": 3}, "ground": "paper", "cut_threshold": 0.5,
                           "exp_method": "ol", "order": 3, "progress": False}
    code, _, err = run(capsys, "shade", scenes["tiny"], "--method", "reference", "-o", "env_sampling=bsdf",
                       "-o", "area_lights_block=false", "--out", out)
    assert code == 0, err
    assert calls[1][2] == {"env_sampling": "bsdf", "area_lights_block": False, "progress": False}


@pytest.mark.parametrize("text, tp, value", [
    ("3", int, 3), ("-2", int, -2), ("0.25", float, 0.25), ("1e-3", float, 1e-3), ("haar", str, "haar"),
    ("true", bool, True), ("Yes", bool, True), ("1", bool, True), ("false", bool, False), ("no", bool, False),
    ("0", bool, False), ("{bunny: 8, floor: 1}", dict, {"bunny": 8, "floor": 1}),
    ('{"bunny": 8}', int | dict, {"bunny": 8}), ("8", int | dict, 8), ("none", int | None, None),
    ("5", typing.Optional[int], 5), ("[[0, 1, 0], 0.5, [1, 1, 1]]", tuple, ([0, 1, 0], 0.5, [1, 1, 1])),
    ("[1, 2]", list, [1, 2]),
])
def test_option_values_parse_by_type(text, tp, value):
    assert cli._parse_value(text, tp) == value
    assert type(cli._parse_value(text, tp)) is type(value)


@pytest.mark.parametrize("text, tp", [
    ("2.7", int), ("1e3", int), ("eight", int), ("x", float), ("maybe", bool), ("2", bool), ("[1]", dict),
    ("{a: 1}", list), ("{a: [", dict), ("2.7", int | dict), ("none", int),
])
def test_bad_option_values_are_refused(text, tp):
    with pytest.raises(ValueError):
        cli._parse_value(text, tp)


def test_type_names_in_messages():
    assert cli._type_name(int | dict) == "an int or a mapping such as {key: value}"
    assert cli._type_name(typing.Optional[float]) == "a number or none"
    assert cli._type_name(types.SimpleNamespace) == "a YAML value"


# --------------------------------------------------------------------------- outputs


def test_out_without_npz_gets_it_and_the_real_path_is_printed(scenes, tmp_path, monkeypatch, capsys):
    _capture_shade(monkeypatch)
    code, out, _ = run(capsys, "shade", scenes["tiny"], "--method", "reference", "--out", tmp_path / "x.txt")
    assert code == 0
    assert (tmp_path / "x.txt.npz").is_file() and not (tmp_path / "x.txt").exists()
    assert f"wrote {tmp_path / 'x.txt.npz'} " in out


def test_out_folder_gets_radiance_npz_inside(scenes, tmp_path, monkeypatch, capsys):
    _capture_shade(monkeypatch)
    for target in (tmp_path, str(tmp_path / "new") + "/"):
        code, out, _ = run(capsys, "shade", scenes["tiny"], "--method", "reference", "--out", target)
        assert code == 0
    assert (tmp_path / "radiance.npz").is_file() and (tmp_path / "new" / "radiance.npz").is_file()
    assert f"wrote {tmp_path / 'new' / 'radiance.npz'} " in out


@pytest.mark.parametrize("command", ["shade", "render", "compare"])
def test_unwritable_out_is_refused_before_any_work(command, scenes, tmp_path, monkeypatch, capsys):
    def must_not_run(*args, **kwargs):
        raise AssertionError("computed before checking the output")

    monkeypatch.setattr(api, "shade", must_not_run)
    monkeypatch.setattr(api, "precompute", must_not_run)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    method = ["--methods", "interreflection"] if command == "compare" else ["--method", "interreflection"]
    code, _, err = run(capsys, command, scenes["tiny"], *method, "--out", blocker / "sub" / "out.npz")
    assert code == 1
    assert err.count("\n") == 1 and "--out" in err and "cannot write there" in err


# --------------------------------------------------------------------------- render


def test_render_precomputes_once_and_shades_each_frame(scenes, tmp_path, monkeypatch, capsys):
    from prtlab.pipeline import Precomputation

    precomputes, frames = [], []
    real_precompute, real_shade = api.precompute, Precomputation.shade

    def counting_precompute(*args, **kwargs):
        precomputes.append(kwargs)
        return real_precompute(*args, **kwargs)

    def counting_shade(self, state=None, bounces=1):
        frames.append(state.transforms["ball"].translate.copy())
        return real_shade(self, state, bounces)

    monkeypatch.setattr(api, "precompute", counting_precompute)
    monkeypatch.setattr(Precomputation, "shade", counting_shade)
    code, out, err = run(capsys, "render", scenes["tiny"], "--method", "interreflection",
                         *TINY_OPTIONS["interreflection"], "--frames", "3", "--out", tmp_path / "frames")
    assert code == 0, err
    assert len(precomputes) == 1 and len(frames) == 3
    np.testing.assert_allclose([f[0] for f in frames], [0.0, 0.5, 1.0])  # the ball's animation, frame by frame
    for i in range(3):
        assert (tmp_path / "frames" / f"frame_{i:04d}.png").is_file()
        assert (tmp_path / "frames" / f"frame_{i:04d}.exr").is_file()
        assert f"frame {i + 1}/3: shaded in" in out


def test_render_with_a_reference_shades_every_frame_scene(scenes, tmp_path, monkeypatch, capsys):
    calls = _capture_shade(monkeypatch)
    code, out, err = run(capsys, "render", scenes["tiny"], "--method", "reference", "--samples", "4",
                         "--frames", "2", "--out", tmp_path)
    assert code == 0, err
    assert len(calls) == 2 and calls[0][2] == {"n_samples": 4, "progress": False}
    assert "frame 2/2" in out


def test_render_reports_a_frame_the_pipeline_refuses(scenes, tmp_path, monkeypatch, capsys):
    from prtlab.pipeline import Precomputation

    real_shade = Precomputation.shade

    def refuse_moved(self, state=None, bounces=1):
        if state.transforms["ball"].translate[0] != 0.0:
            raise ValueError("the interreflection method precomputes the scene: object 'ball' moved; re-precompute")
        return real_shade(self, state, bounces)

    monkeypatch.setattr(Precomputation, "shade", refuse_moved)
    code, out, err = run(capsys, "render", scenes["tiny"], "--method", "interreflection",
                         *TINY_OPTIONS["interreflection"], "--frames", "2", "--out", tmp_path)
    assert code == 1
    assert err == "prtlab render: error: the interreflection method precomputes the scene: object 'ball' moved; " \
                  "re-precompute\n"
    assert (tmp_path / "frame_0000.png").is_file()  # the finished frame is kept


def test_render_precomputes_again_when_a_frame_moves_a_baked_object(scenes, tmp_path, monkeypatch, capsys):
    """A method that bakes poses (portals) gets a new precomputation at every frame whose poses moved."""
    from prtlab import api
    from prtlab.pipeline import Precomputation

    precomputes = []
    real_precompute = api.precompute

    def counting_precompute(scene, *args, **kwargs):
        precomputes.append(scene.object("ball").transform.translate[0])
        return real_precompute(scene, *args, **kwargs)

    def ball_is_baked(self, state):
        return ["ball"] if state.transforms["ball"].translate[0] != self.scene.object("ball").transform.translate[0] \
            else []

    monkeypatch.setattr(api, "precompute", counting_precompute)
    monkeypatch.setattr(Precomputation, "moved_objects", ball_is_baked)
    code, out, err = run(capsys, "render", scenes["tiny"], "--method", "interreflection",
                         *TINY_OPTIONS["interreflection"], "--frames", "3", "--out", tmp_path)
    assert code == 0, err
    assert precomputes == [0.0, 0.5, 1.0]
    assert out.count("precomputing again at the new pose") == 2


def test_render_stores_as_many_portal_bounces_as_asked(scenes, tmp_path, capsys):
    code, _, err = run(capsys, "render", scenes["room"], "--method", "portals", *TINY_OPTIONS["portals"],
                       "--bounces", "3", "--out", tmp_path)
    assert code == 0, err


# --------------------------------------------------------------------------- compare


def test_compare_prints_tables_writes_images_and_json_and_reports_failures(scenes, tmp_path, capsys):
    opts = [f"interreflection.{o}" if o != "-o" else o for o in TINY_OPTIONS["interreflection"]]
    opts += [f"spherelights.{o}" if o != "-o" else o for o in TINY_OPTIONS["spherelights"]]
    code, out, err = run(capsys, "compare", scenes["tiny"], "--methods", "interreflection,spherelights,portals",
                         "--samples", "8", *opts, "--out", tmp_path)
    assert code == 1  # portals cannot shade a scene without a portal
    assert "prtlab compare: portals cannot shade this scene: the scene has no portal" in err
    assert "interreflection against reference" in out and "spherelights against reference" in out
    assert "mean ratio" in out
    report = json.loads((tmp_path / "compare.json").read_text())
    assert set(report["methods"]) == {"interreflection", "spherelights"} and set(report["failed"]) == {"portals"}
    rows = report["methods"]["spherelights"]["rows"]
    assert {(r["object"], r["part"]) for r in rows} == {(o, p) for o in ("floor", "ball")
                                                        for p in ("direct", "indirect", "total")}
    for method in ("interreflection", "spherelights"):
        for kind in ("difference", "comparison", "agreement"):
            assert (tmp_path / f"{kind}_{method}.png").stat().st_size > 0


def test_compare_rows_are_prtlab_compare(scenes, tmp_path, capsys):
    """The JSON rows are exactly prtlab.compare of the two shadings (here the reference against itself)."""
    ref = prtlab.shade(prtlab.load_scene(scenes["tiny"]), method="reference", n_samples=4, seed=2, progress=False)
    code, out, err = run(capsys, "compare", scenes["tiny"], "--methods", "spherelights",
                         *TINY_OPTIONS["spherelights"], "--samples", "4", "--seed", "2", "--out", tmp_path)
    assert code == 0, err
    ours = prtlab.shade(prtlab.load_scene(scenes["tiny"]), method="spherelights", progress=False, n_spheres=2,
                        fit_resolution=10, n_directions=12, cube_resolution=4)
    expected = prtlab.compare(ours, ref).to_dict(json_safe=True)["rows"]
    assert json.loads((tmp_path / "compare.json").read_text())["methods"]["spherelights"]["rows"] == expected


# --------------------------------------------------------------------------- logs, cache, notices


def test_prtlab_log_records_are_one_line_on_stderr_and_quiet_hides_them(scenes, tmp_path, monkeypatch, capsys):
    def logging_shade(scene, method="reference", bounces=1, **options):
        logging.getLogger("prtlab.cache").info("hit spherelights\n(entry abc)")
        res = ShadeResult()
        res.total["floor"] = res.direct["floor"] = res.indirect["floor"] = np.ones((1, 3))
        return res

    monkeypatch.setattr(api, "shade", logging_shade)
    argv = ["shade", scenes["tiny"], "--method", "reference", "--out", str(tmp_path / "r.npz")]
    assert cli.main(argv) == 0
    assert "prtlab.cache: hit spherelights (entry abc)\n" in capsys.readouterr().err
    assert cli.main(["-q", *argv]) == 0
    assert "prtlab.cache" not in capsys.readouterr().err


def test_cache_hits_and_misses_are_visible(scenes, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PRTLAB_CACHE", str(tmp_path / "cache"))
    argv = ["shade", scenes["tiny"], "--method", "spherelights", *TINY_OPTIONS["spherelights"],
            "--out", str(tmp_path / "r.npz")]
    assert cli.main(argv) == 0
    first = capsys.readouterr().err
    assert cli.main(argv) == 0
    second = capsys.readouterr().err
    assert "prtlab.cache: " in first and "prtlab.cache: " in second
    assert first != second  # a miss, then a hit


def test_cache_info_list_and_clear(scenes, tmp_path, monkeypatch, capsys):
    root = tmp_path / "cache"
    monkeypatch.setenv("PRTLAB_CACHE", str(root))
    assert run(capsys, "shade", scenes["tiny"], "--method", "spherelights", *TINY_OPTIONS["spherelights"],
               "--out", tmp_path / "r.npz")[0] == 0
    code, out, _ = run(capsys, "cache", "info")
    assert code == 0 and str(root) in out and "spherelights" in out
    code, out, _ = run(capsys, "cache", "list", "--method", "spherelights")
    assert code == 0 and out.count("spherelights") >= 1 and str(root) in out
    code, out, _ = run(capsys, "cache", "list", "--method", "portals")
    assert code == 0 and "no cache entries of method 'portals'" in out
    code, out, _ = run(capsys, "cache", "clear", "--method", "spherelights")
    assert code == 0 and out.startswith("removed ") and "spherelights" in out
    code, out, _ = run(capsys, "cache", "list")
    assert code == 0 and out.startswith("no cache entries")


@pytest.mark.parametrize("n_bytes, text", [(0, "0 B"), (1023, "1023 B"), (1536, "1.5 KiB"),
                                           (5 * 1024**3, "5.0 GiB"), (None, "no cap")])
def test_sizes_are_human_readable(n_bytes, text):
    assert cli._size(n_bytes) == text


def _kernel(body, module):
    """A fresh numba function (never cached) that numba sees as defined in ``module``."""
    import numba

    def kernel(x):
        return body(x)

    kernel.__module__ = module
    return numba.njit(kernel)


def test_compile_notice_is_printed_once_per_process(monkeypatch, capsys):
    import numba

    monkeypatch.setitem(_compile_notice._state, "announced", False)
    _compile_notice.install()
    add_one, double = numba.njit(lambda x: x + 1), numba.njit(lambda x: x * 2)
    assert _kernel(add_one, "tests.user_code")(1) == 2  # the user's own numba code: no notice
    assert _compile_notice.MESSAGE not in capsys.readouterr().err
    first, second = _kernel(add_one, "prtlab.sh._kernels"), _kernel(double, "prtlab.sh._kernels")
    assert first(1) == 2 and second(2) == 4
    assert capsys.readouterr().err.count(_compile_notice.MESSAGE) == 1
    monkeypatch.setitem(_compile_notice._state, "announced", False)
    with _compile_notice.suppressed():
        assert first(1.5) == 2.5  # a new signature compiles, silently
    assert _compile_notice.MESSAGE not in capsys.readouterr().err


# --------------------------------------------------------------------------- errors


def test_mitsuba_missing_is_one_line(scenes, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    code, _, err = run(capsys, "shade", scenes["tiny"], "--method", "mitsuba", "--out", tmp_path / "r.npz")
    assert code == 2
    assert err == "prtlab shade: error: method 'mitsuba' needs Mitsuba 3: pip install 'prtlab[reference]'\n"


def test_debug_shows_the_traceback(tmp_path, monkeypatch):
    monkeypatch.setenv("PRTLAB_DEBUG", "1")
    with pytest.raises(FileNotFoundError, match="scene file not found"):
        cli.main(["shade", str(tmp_path / "missing.yaml"), "--method", "reference"])


def test_a_user_error_in_a_real_process_is_one_line():
    proc = subprocess.run([sys.executable, "-m", "prtlab.cli", "shade", "missing.yaml", "--method", "reference"],
                          capture_output=True, text=True)
    assert proc.returncode == 1
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr and "missing.yaml" in proc.stderr


def test_a_method_not_installed_exits_2(monkeypatch, tmp_path, capsys):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mitsuba" else real(name, *a))
    scene = tmp_path / "scene.yaml"
    scene.write_text("objects: []\n")
    code = cli.main(["shade", str(scene), "--method", "mitsuba", "--out", str(tmp_path / "r.npz")])
    assert code == 2
    assert "method 'mitsuba' needs Mitsuba 3: pip install 'prtlab[reference]'" in capsys.readouterr().err


def test_references_have_nothing_to_precompute(tmp_path, capsys):
    assert cli.main(["precompute", str(tmp_path / "any.yaml"), "--method", "reference"]) == 0
    assert "has no precomputation" in capsys.readouterr().out


@pytest.mark.parametrize("error, line", [
    (KeyError("objects"), "KeyError: 'objects'"),
    (KeyError("no object 'x' in the scene"), "no object 'x' in the scene"),
    (ValueError("first\nsecond"), "first second"),
    (MemoryError(), "MemoryError"),
])
def test_errors_are_shown_on_one_line(error, line):
    assert cli._one_line(error) == line


def test_warnings_are_one_line(scenes, tmp_path, monkeypatch, capsys):
    import warnings

    def warning_shade(scene, method="reference", bounces=1, **options):
        warnings.warn("the portal faces away\nfrom the room", RuntimeWarning)
        res = ShadeResult()
        res.total["floor"] = res.direct["floor"] = res.indirect["floor"] = np.ones((1, 3))
        return res

    monkeypatch.setattr(api, "shade", warning_shade)
    code, _, err = run(capsys, "shade", scenes["tiny"], "--method", "reference", "--out", tmp_path / "r.npz")
    assert code == 0
    assert err == "prtlab: RuntimeWarning: the portal faces away from the room\n"


def test_compare_skips_a_method_that_cannot_do_the_bounces(scenes, monkeypatch, capsys):
    def must_not_run(*args, **kwargs):
        raise AssertionError("computed although no method can shade")

    monkeypatch.setattr(api, "shade", must_not_run)
    code, _, err = run(capsys, "compare", scenes["tiny"], "--methods", "spherelights", "--bounces", "3")
    assert code == 1
    assert err.splitlines() == [
        "prtlab compare: spherelights cannot shade this scene: method 'spherelights' computes at most 2 indirect "
        "bounce(s), got bounces=3; use method='reference' for more",
        "prtlab compare: no method can shade this scene with --bounces 3",
    ]
