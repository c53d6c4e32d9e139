"""Tests of prtlab/cache.py: keys, hits and misses, corrupted files, wrong keys, resumable chunks, no pickle."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import trimesh

from prtlab.cache import FORMAT_VERSION, Cache, CacheWarning, cache_key, default_cache_root


class Counter:
    """A compute function that counts its calls."""

    def __init__(self, result):
        self.calls = 0
        self.result = result

    def __call__(self):
        self.calls += 1
        return self.result


@pytest.fixture
def cache(tmp_path):
    return Cache(tmp_path / "cache", progress=False)


# ----------------------------------------------------------------------------- keys


def test_key_is_deterministic_and_sensitive():
    a = np.arange(6.0).reshape(2, 3)
    k = cache_key("transfer", a, {"order": 4, "samples": 100})
    assert k == cache_key("transfer", a.copy(), {"samples": 100, "order": 4})  # dict order irrelevant
    assert len(k) == 64
    assert k != cache_key("transfer", a.reshape(3, 2), {"order": 4, "samples": 100})  # shape
    assert k != cache_key("transfer", a.astype(np.float32), {"order": 4, "samples": 100})  # dtype
    b = a.copy()
    b[0, 0] = np.nextafter(0.0, 1.0)
    assert k != cache_key("transfer", b, {"order": 4, "samples": 100})  # one ulp
    assert k != cache_key("transfer", a, {"order": 5, "samples": 100})  # option
    assert cache_key(1) != cache_key(1.0) != cache_key("1")  # types are tagged
    assert cache_key(np.asfortranarray(a)) == cache_key(a)  # memory layout irrelevant


def test_key_hashes_meshes_by_geometry():
    m1 = trimesh.creation.box()
    m2 = trimesh.Trimesh(m1.vertices.copy(), m1.faces.copy(), process=False)
    assert cache_key(m1) == cache_key(m2)
    m2.vertices[0] += 1e-9
    assert cache_key(m1) != cache_key(m2)


def test_key_includes_format_version(monkeypatch):
    import prtlab.cache as c

    k = cache_key("x")
    monkeypatch.setattr(c, "FORMAT_VERSION", FORMAT_VERSION + 1)
    assert c.cache_key("x") != k


def test_key_rejects_unhashable():
    with pytest.raises(TypeError, match="cannot hash a object"):
        cache_key(object())
    with pytest.raises(TypeError, match="arrays must be numeric or boolean"):
        cache_key(np.array(["a"], dtype=object))
    with pytest.raises(TypeError, match="dict keys must be strings"):
        cache_key({1: 2})


def test_default_root(monkeypatch, tmp_path):
    monkeypatch.setenv("PRTLAB_CACHE", str(tmp_path / "c"))
    assert default_cache_root() == tmp_path / "c"
    assert Cache().root == tmp_path / "c"
    monkeypatch.delenv("PRTLAB_CACHE")
    assert default_cache_root().parts[-2:] == (".cache", "prtlab")


# ----------------------------------------------------------------------------- entries


def test_miss_then_hit(cache):
    key = cache_key("a")
    fn = Counter({"x": np.arange(5.0), "group": {"y": np.eye(2, dtype=np.int32)}, "attrs": {"order": 3}})
    first = cache.get_or_compute(key, fn, name="test")
    second = cache.get_or_compute(key, fn, name="test")
    assert fn.calls == 1
    for out in (first, second):
        np.testing.assert_array_equal(out["x"], np.arange(5.0))
        assert out["group"]["y"].dtype == np.int32
        assert out["attrs"] == {"order": 3}
    assert cache.path(key, "test").exists()
    assert not list(cache.root.glob("*.tmp-*"))  # the temporary file was renamed


def test_corrupted_file_is_reported_and_recomputed(cache):
    key = cache_key("b")
    fn = Counter({"x": np.ones(3)})
    cache.get_or_compute(key, fn)
    cache.path(key).write_bytes(b"not an hdf5 file")
    with pytest.warns(CacheWarning, match="is unusable"):
        out = cache.get_or_compute(key, fn)
    assert fn.calls == 2
    np.testing.assert_array_equal(out["x"], np.ones(3))
    cache.get_or_compute(key, fn)  # repaired: a plain hit again
    assert fn.calls == 2


def test_truncated_file_is_reported(cache):
    key = cache_key("t")
    fn = Counter({"x": np.arange(100000.0)})
    cache.get_or_compute(key, fn)
    data = cache.path(key).read_bytes()
    cache.path(key).write_bytes(data[: len(data) // 2])
    with pytest.warns(CacheWarning, match="is unusable"):
        cache.get_or_compute(key, fn)
    assert fn.calls == 2


def test_wrong_key_is_reported_and_recomputed(cache):
    key = cache_key("c")
    fn = Counter({"x": np.ones(3)})
    cache.get_or_compute(key, fn)
    with h5py.File(cache.path(key), "r+") as f:
        f.attrs["prtlab_key"] = cache_key("something else")
    with pytest.warns(CacheWarning, match="holds key"):
        cache.get_or_compute(key, fn)
    assert fn.calls == 2


def test_wrong_format_version_is_reported(cache):
    key = cache_key("v")
    fn = Counter({"x": np.ones(3)})
    cache.get_or_compute(key, fn)
    with h5py.File(cache.path(key), "r+") as f:
        f.attrs["prtlab_format"] = FORMAT_VERSION + 7
    with pytest.warns(CacheWarning, match="format version"):
        cache.get_or_compute(key, fn)
    assert fn.calls == 2


def test_no_pickle_only_plain_datasets(cache):
    key = cache_key("p")
    cache.get_or_compute(key, lambda: {"x": np.ones((2, 3)), "g": {"y": np.zeros(4, bool)}, "attrs": {"a": [1, 2]}})
    with h5py.File(cache.path(key), "r") as f:
        kinds = []
        f.visititems(lambda name, obj: kinds.append(obj.dtype.kind) if isinstance(obj, h5py.Dataset) else None)
        assert sorted(kinds) == ["b", "f"]
        assert json.loads(f.attrs["prtlab_attrs"]) == {"a": [1, 2]}
    raw = cache.path(key).read_bytes()
    assert b"numpy.core" not in raw and b"\x80\x04\x95" not in raw  # no pickle stream


def test_rejects_object_arrays_and_bad_results(cache):
    key = cache_key("o")
    with pytest.raises(TypeError, match="numeric or boolean arrays only"):
        cache.get_or_compute(key, lambda: {"x": np.array([{}], dtype=object)})
    with pytest.raises(TypeError, match="result must be a dict of arrays"):
        cache.get_or_compute(key, lambda: [1, 2])
    with pytest.raises(ValueError, match="without '/'"):
        cache.get_or_compute(key, lambda: {"a/b": np.ones(1)})
    with pytest.raises(ValueError, match="key must be a hex digest"):
        cache.get_or_compute("not a key", lambda: {})
    with pytest.raises(ValueError, match="name must be a non-empty string"):
        cache.get_or_compute(key, lambda: {}, name="../evil")
    assert not list(cache.root.glob("**/*.tmp-*"))  # failed writes leave no temporary files


# ----------------------------------------------------------------------------- chunks


def _chunk(i):
    return {"values": np.full((3, 2), float(i)), "ids": np.arange(3) + 3 * i, "attrs": {"n": 3}}


def test_chunks_assemble_in_order(cache):
    key = cache_key("chunks")
    out = cache.get_or_compute_chunks(key, 4, _chunk, name="ch")
    np.testing.assert_array_equal(out["ids"], np.arange(12))
    np.testing.assert_array_equal(out["values"][:, 0], np.repeat(np.arange(4.0), 3))
    assert out["attrs"] == {"n": 3}
    assert not cache._parts_dir(key, "ch").exists()  # parts removed after assembly
    again = cache.get_or_compute_chunks(key, 4, lambda i: pytest.fail("recomputed"), name="ch")
    np.testing.assert_array_equal(again["ids"], np.arange(12))


def test_chunks_resume_after_crash(cache):
    key = cache_key("resume")
    calls = []

    def crashing(i):
        if i == 2:
            raise KeyboardInterrupt("simulated crash")
        calls.append(i)
        return _chunk(i)

    with pytest.raises(KeyboardInterrupt):
        cache.get_or_compute_chunks(key, 5, crashing, name="r")
    assert calls == [0, 1]
    assert cache.finished_chunks(key, 5, name="r") == [0, 1]
    assert cache.missing_chunks(key, 5, name="r") == [2, 3, 4]

    resumed = []
    out = cache.get_or_compute_chunks(key, 5, lambda i: resumed.append(i) or _chunk(i), name="r")
    assert resumed == [2, 3, 4]
    np.testing.assert_array_equal(out["ids"], np.arange(15))


def test_corrupted_chunk_is_recomputed(cache):
    key = cache_key("badchunk")
    def fails_at_2(i):
        if i == 2:
            raise RuntimeError("worker died")
        return _chunk(i)

    with pytest.raises(RuntimeError, match="worker died"):
        cache.get_or_compute_chunks(key, 3, fails_at_2)
    cache._chunk_path(key, "data", 1).write_bytes(b"garbage")
    resumed = []
    with pytest.warns(CacheWarning, match="cache chunk .* is unusable"):
        out = cache.get_or_compute_chunks(key, 3, lambda i: resumed.append(i) or _chunk(i))
    assert resumed == [1, 2]
    np.testing.assert_array_equal(out["ids"], np.arange(9))


def test_chunks_with_external_map_and_custom_assembly(cache):
    key = cache_key("map")
    seen = []

    def reversed_map(fn, indices):  # finishes chunks out of order, as a parallel executor would
        for i in reversed(indices):
            seen.append(i)
            yield i, fn(i)

    out = cache.get_or_compute_chunks(
        key, 3, _chunk, map_fn=reversed_map, assemble=lambda chunks: {"total": np.sum([c["values"].sum() for c in chunks])}
    )
    assert seen == [2, 1, 0]
    assert float(out["total"]) == 6.0 * (0 + 1 + 2)


def test_chunk_count_is_validated(cache):
    with pytest.raises(ValueError, match="n_chunks must be an int >= 1"):
        cache.get_or_compute_chunks(cache_key("n"), 0, _chunk)


def test_mismatched_chunks_are_rejected(cache):
    with pytest.raises(ValueError, match="they must match"):
        cache.get_or_compute_chunks(cache_key("mm"), 2, lambda i: {"a": np.ones(1)} if i == 0 else {"b": np.ones(1)})


def test_chunk_result_must_be_a_dict(cache):
    with pytest.raises(TypeError, match="chunk result must be a dict of arrays"):
        cache.get_or_compute_chunks(cache_key("d"), 2, lambda i: [i])


def test_map_fn_that_skips_chunks_is_an_error(cache):
    def lazy_map(fn, indices):
        i = indices[0]
        yield i, fn(i)

    with pytest.raises(RuntimeError, match=r"chunks \[1, 2\] of 'data' are missing after computing them"):
        cache.get_or_compute_chunks(cache_key("skip"), 3, _chunk, map_fn=lazy_map)
