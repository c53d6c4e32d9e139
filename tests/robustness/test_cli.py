"""Bad command lines: each is refused with one line on stderr, the right exit code, no traceback, no work done.

Every case runs ``prtlab.cli.main`` in-process with ``prtlab.api.shade`` and
``prtlab.api.precompute`` replaced by a function that fails the test, so a case that
reached the expensive work before refusing would be caught.
"""

from __future__ import annotations

import sys

import pytest

from prtlab import api, cli
from tests.scenes import TINY_SCENE as SCENE

# (argv with {scene} / {tmp} / {file} placeholders, exit code, regex the one line must match)
CASES = [
    ([], 2, r"the following arguments are required: COMMAND"),
    (["shade", "{scene}", "--method", "reference", "--bogus"], 2, r"unrecognized arguments: --bogus"),
    (["explode"], 2, r"invalid choice: 'explode'"),
    (["shade"], 2, r"required: scene, --method"),
    (["shade", "{scene}"], 2, r"required: --method"),
    (["shade", "{scene}", "--method", "radiosity"], 2, r"argument --method: invalid choice: 'radiosity'"),
    (["shade", "{tmp}/missing.yaml", "--method", "reference"], 1, r"scene file not found: .*missing\.yaml"),
    (["shade", "{tmp}/broken.yaml", "--method", "reference"], 1, r"broken\.yaml: invalid YAML"),
    (["shade", "{scene}", "--method", "reference", "--seed", "-5"], 2, r"argument --seed: must be an int >= 0, got -5"),
    (["shade", "{scene}", "--method", "reference", "--seed", "abc"], 2, r"argument --seed: must be an int"),
    (["shade", "{scene}", "--method", "reference", "--bounces", "-1"], 2, r"argument --bounces: must be an int >= 0"),
    (["shade", "{scene}", "--method", "reference", "--bounces", "1.5"], 2, r"argument --bounces: must be an int"),
    (["shade", "{scene}", "--method", "reference", "--samples", "0"], 2, r"argument --samples: must be an int >= 1"),
    (["shade", "{scene}", "--method", "interreflection", "--seed", "3"], 2,
     r"--seed: method 'interreflection' has no seed option"),
    (["shade", "{scene}", "--method", "spherelights", "--samples", "64"], 2,
     r"--samples: method 'spherelights' has no n_samples option"),
    (["shade", "{scene}", "--method", "spherelights", "-o", "n_spheres"], 2,
     r"argument -o/--option: must be KEY=VALUE"),
    (["shade", "{scene}", "--method", "spherelights", "-o", "=3"], 2, r"argument -o/--option: must be KEY=VALUE"),
    (["shade", "{scene}", "--method", "spherelights", "-o", "n_sphere=3"], 2,
     r"-o n_sphere=3: method 'spherelights' has no option 'n_sphere'; valid: n_spheres, order"),
    (["shade", "{scene}", "--method", "spherelights", "-o", "n_spheres=2.7"], 2,
     r"option 'n_spheres' of method 'spherelights' must be an int or a mapping such as \{key: value\}, got '2.7'"),
    (["shade", "{scene}", "--method", "spherelights", "-o", "n_spheres={ball: ["], 2, r"option 'n_spheres'"),
    (["shade", "{scene}", "--method", "interreflection", "-o", "order=four"], 2,
     r"option 'order' of method 'interreflection' must be an int, got 'four'"),
    (["shade", "{scene}", "--method", "interreflection", "-o", "pca_occluders=maybe"], 2,
     r"option 'pca_occluders' .* must be true or false"),
    (["shade", "{scene}", "--method", "interreflection", "-o", "order=0"], 1, r"option order must be an int >= 1"),
    (["shade", "{scene}", "--method", "reference", "-o", "n_samples=2", "--samples", "4"], 2,
     r"--samples and -o n_samples=... both set 'n_samples'"),
    (["shade", "{scene}", "--method", "portals", "-o", "bounces=1", "--bounces", "2"], 2,
     r"-o bounces=1 stores fewer bounces than --bounces 2; give -o bounces >= 2"),
    (["render", "{scene}", "--method", "portals", "-o", "bounces=0", "--out", "{tmp}/r"], 2,
     r"-o bounces=0 stores fewer bounces than --bounces 1"),
    (["shade", "{scene}", "--method", "spherelights", "-o", "portals.cube_resolution=4"], 2,
     r"names method 'portals', but --method is 'spherelights'"),
    (["shade", "{scene}", "--method", "spherelights", "--bounces", "3"], 1,
     r"method 'spherelights' computes at most 2 indirect bounce\(s\), got bounces=3"),
    (["shade", "{scene}", "--method", "reference", "--out", "{file}/out.npz"], 1,
     r"--out .*a_file: is a file, not a folder"),
    (["shade", "{scene}", "--method", "reference", "--out", "{file}/sub/out.npz"], 1,
     r"--out .*a_file/sub: cannot write there"),
    (["shade", "{scene}", "--method", "reference", "--out", "{tmp}/taken"], 1,
     r"taken/radiance\.npz is a folder; give a file name ending in \.npz"),
    (["render", "{scene}", "--method", "reference", "--frames", "0", "--out", "{tmp}/r"], 2,
     r"argument --frames: must be an int >= 1, got 0"),
    (["render", "{scene}", "--method", "reference", "--frames", "-3", "--out", "{tmp}/r"], 2,
     r"argument --frames: must be an int >= 1, got -3"),
    (["render", "{scene}", "--method", "reference"], 2, r"required: --out"),
    (["render", "{scene}", "--method", "reference", "--out", "{file}"], 1, r"--out .*a_file: is a file, not a folder"),
    (["render", "{scene}", "--method", "reference", "--exposure", "nan", "--out", "{tmp}/r"], 2,
     r"argument --exposure: must be a finite number"),
    (["compare", "{scene}"], 2, r"required: --methods"),
    (["compare", "{scene}", "--methods", ""], 2, r"argument --methods: must be method names separated by commas"),
    (["compare", "{scene}", "--methods", "interreflection,,portals"], 2, r"argument --methods: must be method names"),
    (["compare", "{scene}", "--methods", "interreflection,radiosity"], 2,
     r"argument --methods: unknown method\(s\) 'radiosity'; choose from reference"),
    (["compare", "{scene}", "--methods", "spherelights,spherelights"], 2, r"'spherelights' listed more than once"),
    (["compare", "{scene}", "--methods", "reference"], 2, r"--methods lists only the reference 'reference'"),
    (["compare", "{scene}", "--methods", "spherelights", "--reference", "pbrt"], 2,
     r"argument --reference: invalid choice: 'pbrt'"),
    (["compare", "{scene}", "--methods", "spherelights", "-o", "nothing=1"], 2,
     r"no method of this run \(reference, spherelights\) has option 'nothing'"),
    (["compare", "{scene}", "--methods", "spherelights", "-o", "portals.cube_resolution=4"], 2,
     r"'portals' is not among the methods of this run"),
    (["compare", "{scene}", "--methods", "spherelights", "--seed", "-1"], 2, r"argument --seed"),
    (["compare", "{scene}", "--methods", "spherelights", "-o", "spherelights.order=0"], 1,
     r"option order must be an int >= 1 and <= 8, got 0"),
    (["compare", "{scene}", "--methods", "interreflection", "--out", "{file}/sub"], 1, r"--out .*cannot write there"),
    (["precompute", "{scene}", "--method", "spherelights", "--workers", "0"], 2,
     r"argument --workers: must be an int >= 1"),
    (["precompute", "{scene}", "--method", "spherelights", "--workers", "2", "--scheduler", "tcp://x:1"], 2,
     r"argument --scheduler: not allowed with argument --workers"),
    (["precompute", "{scene}", "--method", "spherelights", "--scheduler", "tcp://x:1", "--timeout", "0"], 2,
     r"argument --timeout: must be a number of seconds > 0"),
    (["precompute", "{scene}", "--method", "spherelights", "-o", "n_spheres=-"], 2, r"option 'n_spheres'"),
    (["cache", "frobnicate"], 2, r"argument action: invalid choice: 'frobnicate'"),
    (["reproduce", "--out", "{file}"], 1, r"--out .*a_file: is a file, not a folder"),
    (["bench", "--json", "{file}/bench.json"], 1, r"--json .*a_file: is a file, not a folder"),
]


@pytest.fixture
def paths(tmp_path, monkeypatch):
    def must_not_run(*args, **kwargs):
        raise AssertionError("prtlab computed before refusing the command line")

    monkeypatch.setattr(api, "shade", must_not_run)
    monkeypatch.setattr(api, "precompute", must_not_run)
    (tmp_path / "scene.yaml").write_text(SCENE)
    (tmp_path / "broken.yaml").write_text("objects: [\n")
    (tmp_path / "a_file").write_text("a file, not a folder")
    (tmp_path / "taken" / "radiance.npz").mkdir(parents=True)
    return {"scene": str(tmp_path / "scene.yaml"), "tmp": str(tmp_path), "file": str(tmp_path / "a_file")}


@pytest.mark.parametrize("argv, code, message", CASES, ids=[" ".join(c[0])[:60] or "no-args" for c in CASES])
def test_bad_command_line_is_one_line(argv, code, message, paths, capsys):
    for name, value in paths.items():
        argv = [a.replace("{" + name + "}", value) for a in argv]
    assert cli.main(argv) == code
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert err.startswith("prtlab"), err
    assert "Traceback" not in err
    import re

    assert re.search(message, err), err


@pytest.mark.parametrize("command", ["shade", "render", "precompute"])
def test_an_unwritable_cache_folder_is_refused_before_any_work(command, paths, monkeypatch, capsys):
    monkeypatch.setenv("PRTLAB_CACHE", paths["file"] + "/cache")
    argv = [command, paths["scene"], "--method", "spherelights"]
    argv += ["--out", paths["tmp"] + "/out"] if command != "precompute" else []
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "cache folder" in err and "a_file/cache: cannot write there" in err and "set PRTLAB_CACHE" in err


def test_missing_mitsuba_is_one_line(paths, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    assert cli.main(["compare", paths["scene"], "--methods", "spherelights", "--reference", "mitsuba"]) == 2
    assert capsys.readouterr().err == (
        "prtlab compare: error: method 'mitsuba' needs Mitsuba 3: pip install 'prtlab[reference]'\n")


def test_unreachable_scheduler_is_one_line(tmp_path, capsys):
    pytest.importorskip("dask.distributed")
    (tmp_path / "scene.yaml").write_text(SCENE)
    argv = ["precompute", str(tmp_path / "scene.yaml"), "--method", "portals", "--scheduler", "tcp://127.0.0.1:9",
            "--timeout", "1"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "prtlab precompute: error: cannot reach the Dask scheduler at 'tcp://127.0.0.1:9' within 1 s" in err
