"""Tests of prtlab/cache.py: keys and the code fingerprint, hits and misses, checksums, empty groups, resumable
chunks and their chunking, listing, the size cap, writability. Faults: tests/robustness/test_cache_faults.py."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import trimesh

import prtlab.cache as c
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
    key, other = cache_key("c"), cache_key("something else")
    fn = Counter({"x": np.ones(3)})
    cache.get_or_compute(key, fn)
    cache.store(other, {"x": np.zeros(3)})
    cache.path(other).replace(cache.path(key))  # an intact entry of another key under this key's name
    with pytest.warns(CacheWarning, match="holds key"):
        out = cache.get_or_compute(key, fn)
    assert fn.calls == 2
    np.testing.assert_array_equal(out["x"], np.ones(3))


def test_wrong_format_version_is_reported(cache):
    key = cache_key("v")
    fn = Counter({"x": np.ones(3)})
    cache.get_or_compute(key, fn)
    path = cache.path(key)
    data = bytearray(path.read_bytes())
    digest = hashlib.blake2b(bytes(data[c._HEADER_SIZE:]), digest_size=32).hexdigest()
    data[: c._HEADER_SIZE] = c._header(digest, version=FORMAT_VERSION + 7)  # an intact file of another format
    path.write_bytes(bytes(data))
    with pytest.warns(CacheWarning, match=f"format version {FORMAT_VERSION + 7}, not {FORMAT_VERSION}"):
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
        key, 3, _chunk, map_fn=reversed_map,
        assemble=lambda chunks: {"total": np.sum([chunk["values"].sum() for chunk in chunks])}
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


# ----------------------------------------------------------------------------- checksums


def test_every_array_dataset_has_fletcher32_and_the_file_a_checked_header(cache):
    key = cache_key("f32")
    cache.store(key, {"x": np.ones((2, 3)), "big": np.arange(20000.0), "empty": np.zeros((0, 3)),
                      "g": {"b": np.ones(2, bool)}, "n": np.array(3)})
    with h5py.File(cache.path(key), "r") as f:
        flags = {}
        f.visititems(lambda name, obj: flags.__setitem__(name, (obj.ndim, obj.fletcher32))
                     if isinstance(obj, h5py.Dataset) else None)
        assert f.userblock_size == c._HEADER_SIZE
        assert f.attrs["prtlab_code"] == c.code_fingerprint()
        assert len(f.attrs["prtlab_checksum"]) == 64
    assert flags == {"x": (2, True), "big": (1, True), "empty": (2, True), "g/b": (1, True), "n": (0, False)}
    head = cache.path(key).read_bytes()[: c._HEADER_SIZE]
    assert head.startswith(b"prtlab-cache\nformat ") and head.endswith(b"\0")


def test_content_checksum_catches_a_changed_value_even_with_a_valid_header(cache):
    """A dataset rewritten through HDF5 and the header re-stamped: only the inner checksum can tell."""
    key = cache_key("inner")
    fn = Counter({"radius": np.array([0.4]), "attrs": {"order": 3}})
    cache.get_or_compute(key, fn)
    with h5py.File(cache.path(key), "r+") as f:
        f["radius"][0] = 0.2
    c._stamp(cache.path(key))
    with pytest.warns(CacheWarning, match="do not match its checksum"):
        out = cache.get_or_compute(key, fn)
    assert fn.calls == 2 and out["radius"][0] == 0.4


# ----------------------------------------------------------------------------- empty groups


@pytest.mark.parametrize("result", [
    {"objects": {}},
    {"objects": {}, "x": np.ones(2)},
    {"a": {"b": {}, "c": {"d": np.arange(3)}}, "e": {}},
    {},
])
def test_empty_groups_round_trip(cache, result):
    key = cache_key("groups", repr(result))
    miss = cache.get_or_compute(key, lambda: result, name="g")
    hit = cache.get_or_compute(key, lambda: pytest.fail("recomputed"), name="g")

    def shape(d):
        return {k: shape(v) if isinstance(v, dict) else np.asarray(v).tolist() for k, v in d.items()}

    assert shape(miss) == shape(hit) == shape(result)


def test_chunk_assembly_keeps_empty_groups(cache):
    out = cache.get_or_compute_chunks(cache_key("cg"), 3, lambda i: {"v": np.full(2, i), "objects": {}})
    assert out["objects"] == {}
    np.testing.assert_array_equal(out["v"], [0, 0, 1, 1, 2, 2])


# ----------------------------------------------------------------------------- code fingerprint


def test_code_fingerprint_is_in_every_key(monkeypatch):
    keys = [cache_key(), cache_key("x"), cache_key("interreflection", np.ones(3), {"order": 4}), cache_key(1.0)]
    assert c.code_fingerprint() == c._fingerprint_of(Path(c.__file__).resolve().parent)
    monkeypatch.setattr(c, "_CODE_FINGERPRINT", "0" * 64)
    changed = [cache_key(), cache_key("x"), cache_key("interreflection", np.ones(3), {"order": 4}), cache_key(1.0)]
    assert all(a != b for a, b in zip(keys, changed))


def test_code_fingerprint_follows_every_source_file(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "a.py").write_text("x = 1\n")
    (pkg / "sub" / "b.py").write_text("y = 2\n")
    base = c._fingerprint_of(pkg)
    assert len(base) == 64 and base == c._fingerprint_of(pkg)
    (pkg / "notes.txt").write_text("not code")
    assert c._fingerprint_of(pkg) == base  # only .py files
    (pkg / "sub" / "b.py").write_text("y = 3\n")
    assert c._fingerprint_of(pkg) != base  # an edit in a subpackage
    (pkg / "sub" / "b.py").write_text("y = 2\n")
    assert c._fingerprint_of(pkg) == base
    (pkg / "sub" / "b.py").rename(pkg / "sub" / "c.py")
    assert c._fingerprint_of(pkg) != base  # a rename
    (pkg / "sub" / "c.py").rename(pkg / "sub" / "b.py")
    (pkg / "new.py").write_text("")
    assert c._fingerprint_of(pkg) != base  # a new (even empty) module


# ----------------------------------------------------------------------------- chunking


def _vertex_chunks(values, size, log=None):
    """chunk_fn over ``values`` in chunks of ``size`` (the pattern of a pipeline's per-vertex chunks)."""
    def chunk_fn(i):
        if log is not None:
            log.append(i)
        return {"v": 2.0 * values[i * size:(i + 1) * size]}
    return chunk_fn, -(-len(values) // size)


def test_resume_with_another_chunk_size_never_assembles_stale_parts(cache):
    """A run in 16-vertex chunks interrupted, resumed in 64-vertex chunks (the scenario of issue 13)."""
    values = np.arange(100.0)
    key = cache_key("resize")
    fn16, n16 = _vertex_chunks(values, 16)

    def interrupted(fn, indices):
        for i in indices[:1]:
            yield i, fn(i)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cache.get_or_compute_chunks(key, n16, fn16, map_fn=interrupted, chunking={"vertices": 16})
    assert cache.finished_chunks(key, n16, chunking={"vertices": 16}) == [0]
    assert cache.finished_chunks(key, 2, chunking={"vertices": 64}) == []  # another chunking: not finished
    calls = []
    fn64, n64 = _vertex_chunks(values, 64, calls)
    with pytest.warns(CacheWarning, match=r"cache chunk .*chunk-00000.h5.* prtlab_chunking"):
        out = cache.get_or_compute_chunks(key, n64, fn64, chunking={"vertices": 64})
    assert calls == [0, 1]
    np.testing.assert_array_equal(out["v"], 2.0 * values)
    assert not cache._parts_dir(key, "data").exists()
    again = cache.get_or_compute_chunks(key, n16, fn16, chunking={"vertices": 16})  # later runs: a plain hit
    np.testing.assert_array_equal(again["v"], 2.0 * values)


def test_chunk_count_alone_identifies_parts(cache):
    """Without a descriptor, a part of a run with another chunk count is recomputed."""
    key = cache_key("count")
    cache.store_chunk(key, 0, {"v": np.zeros(16)}, n_chunks=7)
    calls = []
    with pytest.warns(CacheWarning, match='is unusable.*"n_chunks": 7'):
        out = cache.get_or_compute_chunks(key, 1, lambda i: calls.append(i) or {"v": np.ones(100)})
    assert calls == [0] and out["v"].shape == (100,)


def test_same_count_other_descriptor_is_recomputed(cache):
    key = cache_key("desc")
    cache.store_chunk(key, 0, {"v": np.zeros(3)}, n_chunks=2, chunking={"vertices": 3})
    cache.store_chunk(key, 1, {"v": np.zeros(3)}, n_chunks=2, chunking={"vertices": 3})
    assert cache.missing_chunks(key, 2, chunking={"vertices": 3}) == []
    assert cache.missing_chunks(key, 2, chunking={"vertices": 4}) == [0, 1]
    with pytest.warns(CacheWarning):
        out = cache.get_or_compute_chunks(key, 2, lambda i: {"v": np.ones(4)}, chunking={"vertices": 4})
    np.testing.assert_array_equal(out["v"], np.ones(8))


def test_chunk_api_errors(cache):
    key = cache_key("api")
    with pytest.raises(ValueError, match=r"chunk index must be < n_chunks = 2, got 2"):
        cache.store_chunk(key, 2, {"v": np.ones(1)}, n_chunks=2)
    with pytest.raises(ValueError, match="chunk index must be an int >= 0, got -1"):
        cache.load_chunk(key, -1, n_chunks=2)
    with pytest.raises(TypeError, match="chunk index must be an int"):
        cache.store_chunk(key, 1.0, {"v": np.ones(1)}, n_chunks=2)
    with pytest.raises(TypeError, match="n_chunks"):
        cache.store_chunk(key, 0, {"v": np.ones(1)})  # the chunk count is required
    with pytest.raises(TypeError, match="chunking must be JSON-serialisable"):
        cache.get_or_compute_chunks(key, 2, lambda i: pytest.fail("computed"), chunking={"f": object()})
    with pytest.raises(TypeError, match="chunking must be JSON-serialisable"):
        cache.get_or_compute_chunks(key, 2, lambda i: pytest.fail("computed"), chunking=float("nan"))


# ----------------------------------------------------------------------------- a visible cache


def _age(path, seconds_ago):
    t = time.time() - seconds_ago
    os.utime(path, (t, t))


def test_entries_info_and_clear(tmp_path):
    cache = Cache(tmp_path, progress=False)
    a = cache.store(cache_key("a"), {"x": np.ones(10)}, name="interreflection")
    b = cache.store(cache_key("b"), {"x": np.ones(1000)}, name="portals")
    cache.store(cache_key("c"), {"x": np.ones(5)}, name="portals-photons")
    cache.store_chunk(cache_key("d"), 0, {"x": np.ones(3)}, name="portals-chunks", n_chunks=2)
    stray = tmp_path / "portals-0123456789abcdef0123456789abcdef.h5.tmp-1-abcd"
    stray.write_bytes(b"half a file")
    (tmp_path / "unrelated.txt").write_text("kept")
    _age(a, 100)
    listed = cache.entries()
    assert [(e.method, e.kind) for e in listed] == [
        ("interreflection", "entry"), ("portals", "entry"), ("portals-chunks", "parts"), ("portals-photons", "entry")]
    assert listed[0].path == a and listed[0].size_bytes == a.stat().st_size
    assert abs(listed[0].last_used - (time.time() - 100)) < 5
    assert listed[2].size_bytes == cache._chunk_path(cache_key("d"), "portals-chunks", 0).stat().st_size
    assert [e.method for e in cache.entries("portals")] == ["portals", "portals-chunks", "portals-photons"]
    assert cache.entries("portals-photons")[0].kind == "entry"
    assert cache.entries("interreflection")[0].path == a
    info = cache.info()
    assert info["root"] == str(tmp_path) and info["n_entries"] == 3 and info["n_parts"] == 1
    assert info["total_bytes"] == sum(e.size_bytes for e in listed)
    assert info["max_bytes"] == cache.max_bytes
    assert info["methods"]["portals"] == {"entries": 1, "parts": 0, "bytes": b.stat().st_size}
    assert info["methods"]["portals-chunks"]["parts"] == 1

    n, freed = cache.clear("interreflection")
    assert (n, freed) == (1, listed[0].size_bytes) and not a.exists() and b.exists()
    n, freed = cache.clear("portals")
    assert n == 4  # two entries, one part file, the stray temporary file
    assert freed == sum(e.size_bytes for e in listed[1:]) + len(b"half a file")
    assert cache.entries() == [] and not stray.exists() and (tmp_path / "unrelated.txt").exists()
    assert cache.info()["n_entries"] == 0 and cache.clear() == (0, 0)
    with pytest.raises(ValueError, match="method must be a non-empty string"):
        cache.entries("../x")


def test_missing_folder_is_an_empty_cache(tmp_path):
    cache = Cache(tmp_path / "nowhere")
    assert cache.entries() == [] and cache.info()["total_bytes"] == 0 and cache.clear() == (0, 0)
    assert not (tmp_path / "nowhere").exists()


def test_hits_and_misses_are_logged(cache, caplog):
    key = cache_key("log")
    with caplog.at_level(logging.INFO, logger="prtlab.cache"):
        cache.get_or_compute(key, lambda: {"x": np.ones(1)}, name="interreflection")
        cache.get_or_compute(key, lambda: {"x": np.ones(1)}, name="interreflection")
    path = str(cache.path(key, "interreflection"))
    assert [r.getMessage() for r in caplog.records] == [
        f"cache miss: interreflection {path}; computing", f"cache hit: interreflection {path}"]


def test_least_recently_used_entries_are_evicted(tmp_path, caplog):
    big = {"x": np.zeros(20000)}  # about 160 kB per entry
    cache = Cache(tmp_path, progress=False, max_bytes=10**9)
    paths = [cache.store(cache_key(k), big, name=k) for k in "abc"]
    size = paths[0].stat().st_size
    for p, ago in zip(paths, (300, 200, 100)):
        _age(p, ago)
    cache.get_or_compute(cache_key("a"), lambda: pytest.fail("recomputed"), name="a")  # a hit: 'a' is recent
    assert paths[0].stat().st_mtime > time.time() - 50
    cache.max_bytes = int(3.5 * size)
    with caplog.at_level(logging.INFO, logger="prtlab.cache"):
        d = cache.store(cache_key("d"), big, name="d")
    assert [p.exists() for p in paths] == [True, False, True] and d.exists()  # 'b' was the least recently used
    assert any(r.getMessage().startswith(f"cache evicted: b {paths[1]}") for r in caplog.records)


def test_the_entry_just_written_is_never_evicted(tmp_path):
    cache = Cache(tmp_path, progress=False, max_bytes=1)
    first = cache.store(cache_key("1"), {"x": np.ones(100)})
    second = cache.store(cache_key("2"), {"x": np.ones(100)})
    assert second.exists() and not first.exists()
    out = cache.get_or_compute(cache_key("3"), lambda: {"x": np.arange(4.0)})
    np.testing.assert_array_equal(out["x"], np.arange(4.0))
    assert [e.path.name[:1] for e in cache.entries()] == ["d"]
    out = cache.get_or_compute_chunks(cache_key("4"), 3, lambda i: {"x": np.full(2, i)})  # parts kept while needed
    np.testing.assert_array_equal(out["x"], [0, 0, 1, 1, 2, 2])


def test_size_cap_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.delenv("PRTLAB_CACHE_MAX_GB", raising=False)
    assert Cache(tmp_path).max_bytes == 4 * 10**9 == c.default_max_bytes()
    monkeypatch.setenv("PRTLAB_CACHE_MAX_GB", "0.5")
    assert Cache(tmp_path).max_bytes == 5 * 10**8
    assert Cache(tmp_path, max_bytes=1234).max_bytes == 1234  # an explicit cap wins
    for bad in ("four", "0", "-1", "nan", "inf", "1e400"):
        monkeypatch.setenv("PRTLAB_CACHE_MAX_GB", bad)
        with pytest.raises(ValueError, match=f"PRTLAB_CACHE_MAX_GB must be a positive number of gigabytes .*'{bad}'"):
            Cache(tmp_path)
    monkeypatch.delenv("PRTLAB_CACHE_MAX_GB")
    with pytest.raises(TypeError, match="max_bytes must be an int >= 1, got 1.5"):
        Cache(tmp_path, max_bytes=1.5)
    with pytest.raises(ValueError, match="max_bytes must be an int >= 1, got 0"):
        Cache(tmp_path, max_bytes=0)


# ----------------------------------------------------------------------------- writability


@pytest.fixture
def unwritable(tmp_path):
    """A cache whose folder cannot be created (its parent is a file): refused even for root."""
    (tmp_path / "file").write_text("")
    return Cache(tmp_path / "file" / "cache", progress=False)


def test_check_writable(unwritable, cache):
    pattern = r"^cache folder .*file/cache is not writable: .+; set PRTLAB_CACHE to a writable folder$"
    with pytest.raises(c.CacheNotWritableError, match=pattern) as info:
        unwritable.check_writable()
    assert isinstance(info.value, PermissionError) and "\n" not in str(info.value)
    cache.check_writable()
    assert list(cache.root.iterdir()) == []  # the probe is removed


def test_miss_on_an_unwritable_cache_is_refused_before_computing(unwritable):
    with pytest.raises(PermissionError, match="is not writable"):
        unwritable.get_or_compute(cache_key("w"), lambda: pytest.fail("computed before the refusal"))
    with pytest.raises(PermissionError, match="is not writable"):
        unwritable.get_or_compute_chunks(cache_key("w"), 3, lambda i: pytest.fail("computed before the refusal"))


def test_pipeline_on_an_unwritable_cache_is_refused_before_computing(unwritable):
    from prtlab.pipeline import Precomputation
    from prtlab.scene import Scene

    class Never(Precomputation):
        method = "never"

        @classmethod
        def compute(cls, scene, options, progress):
            pytest.fail("computed before the refusal")

    with pytest.raises(PermissionError, match="set PRTLAB_CACHE to a writable folder"):
        Never.precompute(Scene(objects=[]), cache=unwritable)


# ----------------------------------------------------------------------------- files removed under us


class Vanishing(Cache):
    """A cache whose files another process removes right after each write (as its eviction could)."""

    def _evict(self, protect):
        for path in protect:
            c._remove(path)


def test_entry_removed_right_after_writing_returns_the_computed_result(tmp_path, caplog):
    cache = Vanishing(tmp_path, progress=False)
    with caplog.at_level(logging.WARNING, logger="prtlab.cache"):
        out = cache.get_or_compute(cache_key("gone"), lambda: {"x": np.arange(3.0), "n": np.array(2), "g": {},
                                                               "attrs": {"a": (1, 2)}})
        chunked = cache.get_or_compute_chunks(cache_key("gone chunks"), 2, lambda i: {"x": np.full(2, i)})
    np.testing.assert_array_equal(out["x"], np.arange(3.0))
    assert out["n"] == 2 and out["g"] == {} and out["attrs"] == {"a": [1, 2]}  # as a read returns it
    np.testing.assert_array_equal(chunked["x"], [0, 0, 1, 1])
    assert any("was removed right after it was written" in r.getMessage() for r in caplog.records)


def test_chunk_that_cannot_be_stored_is_kept_in_memory(cache, monkeypatch, caplog):
    def parts_folder_removed(*args, **kwargs):
        raise FileNotFoundError("parts folder removed by another process")

    monkeypatch.setattr(cache, "store_chunk", parts_folder_removed)
    with caplog.at_level(logging.WARNING, logger="prtlab.cache"):
        out = cache.get_or_compute_chunks(cache_key("lost part"), 3, lambda i: {"x": np.full(2, i)})
    np.testing.assert_array_equal(out["x"], [0, 0, 1, 1, 2, 2])
    assert sum("could not be stored; keeping it in memory" in r.getMessage() for r in caplog.records) == 3
