"""Every pipeline killed (SIGKILL) in the middle of its precomputation, then rerun: the rerun resumes from
what was finished (portals: its stored chunks) or starts clean (no entry was left), and gives the result of
an uninterrupted run. Also a chunked pipeline resumed with another chunk size, and empty groups through the
cache on a real pipeline. Tiny scenes and options: each case takes seconds."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from prtlab.cache import Cache, CacheWarning
from prtlab.scene import Scene
from tests.scenes import floor_and_ball

REPO = Path(__file__).resolve().parents[2]

#: vertices per portals chunk in these tests (the window box below has 272 shaded vertices: 7 chunks)
CHUNK_VERTICES = 40


def make_case(method: str):
    """(pipeline class, tiny scene, tiny options) of ``method``."""
    if method == "interreflection":
        from prtlab.interreflection import Interreflection

        scene = floor_and_ball(3, 1, (0, 0.7, 0), floor_material={"type": "diffuse", "albedo": [0.8, 0.3, 0.3]},
                               ball_albedo=(0.5, 0.6, 0.7))
        return Interreflection, scene, dict(order=2, n_radii=2, resolution=4, degree=7, n_lights=8, n_basis=2)
    if method == "spherelights":
        from prtlab.spherelights import SphereLights

        scene = floor_and_ball(6, 1, (0.3, 0.6, -0.2), floor_name="plane", ball_albedo=(0.8, 0.3, 0.2), dynamic=True)
        return SphereLights, scene, {"n_spheres": 2, "fit_resolution": 16}
    if method == "portals":
        from prtlab.portals import Portals
        from tests.portals.conftest import window_box

        return Portals, window_box(cell=0.5), {"cube_resolution": 8, "direct_samples": 64, "n_photons": 20000, "gather_rays": 32,
                                               "order": 3, "bounces": 1, "indirect": "paper"}
    raise ValueError(method)


KILLED_CHILD = """
    import sys, time
    from pathlib import Path
    from prtlab.cache import Cache
    from tests.robustness.test_resume import CHUNK_VERTICES, make_case

    method, root, marker = sys.argv[1:4]
    cls, scene, options = make_case(method)
    cache = Cache(root, progress=False)
    if method == "portals":
        cls.chunk_vertices = CHUNK_VERTICES

        def two_chunks_then_hang(fn, indices):
            for n, i in enumerate(indices):
                if n == 2:
                    Path(marker).touch()
                    time.sleep(120)  # killed here, with two chunks stored
                yield i, fn(i)

        cls.precompute(scene, options, cache=cache, progress=False, map_fn=two_chunks_then_hang)
    else:
        compute = cls.compute.__func__

        def compute_then_hang(klass, *args, **kwargs):
            out = compute(klass, *args, **kwargs)
            Path(marker).touch()
            time.sleep(120)  # killed here: all the work done, nothing stored yet
            return out

        cls.compute = classmethod(compute_then_hang)
        cls.precompute(scene, options, cache=cache, progress=False)
"""


def _kill_mid_precompute(method: str, root: Path, marker: Path) -> None:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    proc = subprocess.Popen([sys.executable, "-c", textwrap.dedent(KILLED_CHILD), method, str(root), str(marker)],
                            env=env, cwd=str(REPO), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            if proc.poll() is not None:
                raise AssertionError(f"the {method} child ended before the kill: {proc.communicate()[1][-2000:]}")
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for the {method} child")
            time.sleep(0.05)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL


def _arrays(data, prefix=""):
    """Every array of a precomputation's data by path, without timings (they differ run to run)."""
    out = {}
    for k, v in data.items():
        if k == "attrs" or k.startswith("seconds"):
            continue
        if isinstance(v, dict):
            out.update(_arrays(v, f"{prefix}{k}/"))
        elif v is not None:
            out[prefix + k] = np.asarray(v)
    return out


def _assert_same_precomputation(a, b):
    fa, fb = _arrays(a.data), _arrays(b.data)
    assert sorted(fa) == sorted(fb)
    for name in fa:
        np.testing.assert_array_equal(fa[name], fb[name], err_msg=name)
    ra, rb = a.shade(bounces=1), b.shade(bounces=1)
    for name in ra.total:
        np.testing.assert_array_equal(ra.total[name], rb.total[name], err_msg=name)


@pytest.mark.parametrize("method", ["interreflection", "spherelights", "portals"])
def test_killed_precomputation_then_rerun_matches_an_uninterrupted_run(tmp_path, monkeypatch, method):
    cls, scene, options = make_case(method)
    if method == "portals":
        monkeypatch.setattr(cls, "chunk_vertices", CHUNK_VERTICES)
    root = tmp_path / "cache"
    _kill_mid_precompute(method, root, tmp_path / "marker")
    cache = Cache(root, progress=False)
    computed = []
    kwargs = {}
    if method == "portals":
        n_chunks = -(-scene.object("room").n_vertices // CHUNK_VERTICES)
        assert n_chunks >= 4
        assert [e.kind for e in cache.entries()] == ["parts", "entry"]  # the chunks, the photons' estimate
        assert len(list(cache.entries()[0].path.glob("chunk-*.h5"))) == 2

        def counting(fn, indices):
            for i in indices:
                computed.append(i)
                yield i, fn(i)

        kwargs["map_fn"] = counting
    else:
        assert cache.entries() == []  # killed before its store: nothing half-made is left
    assert not list(root.rglob("*.tmp-*"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rerun = cls.precompute(scene, options, cache=cache, progress=False, **kwargs)
    if method == "portals":
        assert len(computed) == n_chunks - 2  # the two stored chunks were resumed from, not recomputed
    fresh = cls.precompute(scene, options, cache=False, progress=False)
    _assert_same_precomputation(rerun, fresh)
    assert [e.kind for e in cache.entries()] == ["entry"] * len(cache.entries())  # no parts left over
    again = cls.precompute(scene, options, cache=cache, progress=False, **kwargs)  # a hit
    if method == "portals":
        assert len(computed) == n_chunks - 2
    _assert_same_precomputation(again, fresh)


def test_portals_resumed_with_another_chunk_size(tmp_path, monkeypatch):
    """Issue 13's scenario: interrupted in 16-vertex chunks, resumed with the default size; the stale
    16-vertex part is never assembled as the whole mesh, and later runs succeed."""
    cls, scene, options = make_case("portals")
    cache = Cache(tmp_path, progress=False)
    monkeypatch.setattr(cls, "chunk_vertices", 16)

    def one_then_interrupt(fn, indices):
        yield indices[0], fn(indices[0])
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cls.precompute(scene, options, cache=cache, progress=False, map_fn=one_then_interrupt)
    monkeypatch.setattr(cls, "chunk_vertices", 2048)
    with pytest.warns(CacheWarning, match="prtlab_chunking"):
        resumed = cls.precompute(scene, options, cache=cache, progress=False)
    fresh = cls.precompute(scene, options, cache=False, progress=False)
    _assert_same_precomputation(resumed, fresh)
    n = scene.object("room").n_vertices
    assert resumed.shade(bounces=1).total["room"].shape == (n, 3)
    later = cls.precompute(scene, options, cache=cache, progress=False)
    _assert_same_precomputation(later, fresh)


def test_spherelights_without_closed_objects_through_the_cache(tmp_path):
    """Issue 13.4: the empty ``objects`` group survives the cache (miss and hit)."""
    from prtlab.spherelights import SphereLights

    scene = Scene.from_dict({
        "objects": [{"name": "plane", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [4, 4]},
                     "material": {"type": "diffuse", "albedo": [0.7, 0.7, 0.7]}}],
        "lights": [{"type": "environment", "constant": [1.0, 1.0, 1.0]}],
    })
    options = {"n_spheres": 2, "fit_resolution": 16}
    cache = Cache(tmp_path, progress=False)
    fresh = SphereLights.precompute(scene, options, cache=False, progress=False)
    miss = SphereLights.precompute(scene, options, cache=cache, progress=False)
    hit = SphereLights.precompute(scene, options, cache=cache, progress=False)
    assert miss.data["objects"] == hit.data["objects"] == {}
    for pre in (miss, hit):
        np.testing.assert_array_equal(pre.shade(bounces=1).total["plane"], fresh.shade(bounces=1).total["plane"])
