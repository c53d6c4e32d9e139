"""The prtlab command: subcommands exist, unimplemented methods say so and exit non-zero."""

import subprocess
import sys

import pytest

from prtlab import api, cli


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "prtlab.cli", *args], capture_output=True, text=True)


def test_help_lists_every_subcommand():
    proc = run_cli("--help")
    assert proc.returncode == 0
    for command in ("shade", "render", "precompute", "reproduce", "bench"):
        assert command in proc.stdout


def test_unimplemented_method_exits_nonzero(monkeypatch, tmp_path):
    monkeypatch.setitem(api.METHODS, "radiosity", "a future method (issue 99)")
    monkeypatch.setattr(cli, "METHOD_NAMES", cli.METHOD_NAMES + ("radiosity",))
    scene = tmp_path / "scene.yaml"
    scene.write_text("objects: []\n")
    assert cli.main(["shade", str(scene), "--method", "radiosity"]) == 2


def test_references_have_nothing_to_precompute(tmp_path, capsys):
    assert cli.main(["precompute", str(tmp_path / "any.yaml"), "--method", "reference"]) == 0
    assert "has no precomputation" in capsys.readouterr().out


def test_unknown_method_is_rejected():
    proc = run_cli("shade", "scene.yaml", "--method", "radiosity")
    assert proc.returncode != 0 and "invalid choice" in proc.stderr


def test_api_unknown_method_message():
    with pytest.raises(ValueError, match="unknown method 'radiosity'; choose one of reference"):
        api._entry_point("radiosity")


def test_api_unimplemented_method_message(monkeypatch):
    monkeypatch.setitem(api.METHODS, "radiosity", "a future method (issue 99)")
    with pytest.raises(api.MethodUnavailable, match="method 'radiosity' is not implemented yet: a future method"):
        api._entry_point("radiosity")


def test_every_design_method_is_registered():
    for method in ("reference", "mitsuba", "interreflection", "spherelights", "portals"):
        assert isinstance(api.METHODS[method], tuple), method


def test_api_rejects_bad_bounces():
    from prtlab.scene import Scene

    with pytest.raises(ValueError, match="bounces must be an int >= 0"):
        api.shade(Scene(), method="reference", bounces=-1)


def test_api_rejects_bad_scene_type():
    with pytest.raises(TypeError, match="scene must be a prtlab.Scene"):
        api.shade(42, method="reference")


def test_api_precompute_rejects_references():
    with pytest.raises(ValueError, match="method 'mitsuba' has no precomputation"):
        api.precompute("scene.yaml", "mitsuba")


def test_dask_map_runs_chunks_and_yields_each_once():
    distributed = pytest.importorskip("dask.distributed")
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        results = dict(api.dask_map(client=client)(lambda i: {"value": i * i}, [0, 1, 2, 3]))
    assert results == {i: {"value": i * i} for i in range(4)}


def test_dask_map_rejects_bad_workers():
    pytest.importorskip("dask.distributed")
    with pytest.raises(ValueError, match="workers must be a positive int"):
        api.dask_map(workers=0)
