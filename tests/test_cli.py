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


@pytest.mark.parametrize("method", ["interreflection", "spherelights", "portals"])
def test_unimplemented_pipeline_exits_nonzero(method, tmp_path):
    assert cli.main(["precompute", str(tmp_path / "any.yaml"), "--method", method]) == 2


def test_unknown_method_is_rejected():
    proc = run_cli("shade", "scene.yaml", "--method", "radiosity")
    assert proc.returncode != 0 and "invalid choice" in proc.stderr


def test_api_unknown_method_message():
    with pytest.raises(ValueError, match="unknown method 'radiosity'; choose one of reference"):
        api._entry_point("radiosity")


def test_api_unimplemented_method_message():
    with pytest.raises(api.MethodUnavailable, match="method 'portals' is not implemented yet"):
        api._entry_point("portals")


def test_api_rejects_bad_bounces():
    from prtlab.scene import Scene

    with pytest.raises(ValueError, match="bounces must be a non-negative int"):
        api.shade(Scene(), method="reference", bounces=-1)


def test_api_rejects_bad_scene_type():
    with pytest.raises(TypeError, match="scene must be a prtlab.Scene"):
        api.shade(42, method="reference")
