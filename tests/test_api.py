"""prtlab.api: dispatch by method name, options per method, checks before any work, Dask."""

from __future__ import annotations

import time

import pytest

import prtlab
from prtlab import api
from prtlab.scene import Scene


def test_api_unknown_method_message():
    with pytest.raises(ValueError, match="unknown method 'radiosity'; choose one of reference"):
        api._entry_point("radiosity")


def test_every_design_method_is_registered():
    for method in ("reference", "mitsuba", "interreflection", "spherelights", "portals"):
        assert isinstance(api.METHODS[method], tuple), method


def test_pipeline_classes():
    from prtlab.interreflection import Interreflection
    from prtlab.portals import Portals
    from prtlab.spherelights import SphereLights

    assert api.pipeline_class("interreflection") is Interreflection
    assert api.pipeline_class("spherelights") is SphereLights
    assert api.pipeline_class("portals") is Portals
    assert api.pipeline_class("reference") is None and api.pipeline_class("mitsuba") is None


def test_method_options_are_the_options_dataclass_or_the_keyword_arguments():
    import dataclasses

    from prtlab.spherelights import SphereLightOptions

    options = api.method_options("spherelights")
    assert list(options) == [f.name for f in dataclasses.fields(SphereLightOptions)]
    assert options["order"] is int and options["n_spheres"] == int | dict
    reference = api.method_options("reference")
    assert reference["n_samples"] is int and reference["seed"] is int and reference["area_lights_block"] is bool
    assert not {"scene", "bounces", "progress"} & set(reference)
    assert "seed" not in api.method_options("interreflection")
    assert api.method_options("portals")["seed"] is int
    assert {"spp", "n_samples", "seed"} <= set(api.method_options("mitsuba"))


def test_api_rejects_bad_bounces():
    with pytest.raises(ValueError, match="bounces must be an int >= 0"):
        api.shade(Scene(), method="reference", bounces=-1)
    with pytest.raises(TypeError, match="bounces must be an int >= 0"):
        api.shade(Scene(), method="reference", bounces=1.5)


def test_too_many_bounces_are_refused_before_loading_the_scene(tmp_path):
    with pytest.raises(ValueError, match="method 'spherelights' computes at most 2 indirect bounce"):
        api.shade(tmp_path / "never_read.yaml", method="spherelights", bounces=3)


def test_api_rejects_bad_scene_type():
    with pytest.raises(TypeError, match="scene must be a prtlab.Scene"):
        api.shade(42, method="reference")
    with pytest.raises(TypeError, match="scene must be a prtlab.Scene"):
        api.precompute(42, "spherelights")


def test_api_precompute_rejects_references():
    with pytest.raises(ValueError, match="method 'mitsuba' has no precomputation"):
        api.precompute("scene.yaml", "mitsuba")


def test_api_precompute_checks_options_before_loading_the_scene(tmp_path):
    with pytest.raises(ValueError, match=r"unknown option\(s\) \['n_sphere'\] for method 'spherelights'"):
        api.precompute(tmp_path / "never_read.yaml", "spherelights", n_sphere=3)


def test_dask_map_runs_chunks_and_yields_each_once():
    distributed = pytest.importorskip("dask.distributed")
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None) as client:
        results = dict(api.dask_map(client=client)(lambda i: {"value": i * i}, [0, 1, 2, 3]))
    assert results == {i: {"value": i * i} for i in range(4)}


def test_dask_map_rejects_bad_workers():
    pytest.importorskip("dask.distributed")
    with pytest.raises(ValueError, match="workers must be a positive int"):
        api.dask_map(workers=0)


def test_an_unreachable_scheduler_times_out_naming_its_address():
    pytest.importorskip("dask.distributed")
    start = time.perf_counter()
    with pytest.raises(ConnectionError, match=r"cannot reach the Dask scheduler at 'tcp://127.0.0.1:9' within 1 s"):
        api.dask_map(scheduler="tcp://127.0.0.1:9", timeout=1.0)
    assert time.perf_counter() - start < 10.0  # the timeout, not dask's default 30 s
    with pytest.raises(ValueError, match="timeout must be a number of seconds > 0"):
        api.dask_map(scheduler="tcp://127.0.0.1:9", timeout=0)


def test_check_bounces():
    assert api.check_bounces("interreflection", 3) == 3
    assert api.check_bounces("reference", 0) == 0
    with pytest.raises(ValueError, match="method 'spherelights' computes at most 2 indirect bounce"):
        api.check_bounces("spherelights", 3)
    with pytest.raises(TypeError, match="bounces must be an int >= 0"):
        api.check_bounces("portals", True)


def test_only_resumable_pipelines_distribute_their_precomputation(monkeypatch):
    from prtlab.spherelights import SphereLights

    monkeypatch.setattr(SphereLights, "compute", classmethod(lambda *a, **k: pytest.fail("computed before refusing")))
    with pytest.raises(api.MethodUnavailable, match=r"method 'spherelights' cannot distribute its precomputation yet; "
                                                    r"run it without --workers/--scheduler"):
        api.precompute(prtlab.load_scene("tiny_ball_env"), "spherelights", workers=2, progress=False)
