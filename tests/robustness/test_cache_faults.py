"""Cache faults: every damaged, foreign, stale or half-written cache file is detected, reported with a
CacheWarning naming the file, and recomputed (never silently used); bit flips anywhere; chunk parts of
another key, index or chunking; read-only folders; two writers at once; SIGKILL mid-write and mid-run."""

from __future__ import annotations

import ctypes
import os
import re
import signal
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

import prtlab.cache as c
from prtlab.cache import Cache, CacheWarning, cache_key

REPO = Path(__file__).resolve().parents[2]


def _result():
    """A small entry shaped like a pipeline's: nested objects, an empty group, a scalar, bools, attrs."""
    return {
        "centres": np.array([[0.1, 0.4, 0.2], [1.0, 2.0, 3.0]]),
        "radii": np.array([0.4, 0.25]),
        "n_spheres": np.array(2),
        "objects": {"ball": {"coeffs": np.arange(48.0).reshape(3, 16), "visible": np.array([True, False, True])},
                    "empty": {}},
        "attrs": {"seconds": 1.5, "order": 4},
    }


def _same(a, b) -> bool:
    """Equal structure, dtypes and bits."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if not isinstance(a, (np.ndarray, np.generic)):
        return a == b
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


class Counter:
    def __init__(self, make=_result):
        self.calls, self.make = 0, make

    def __call__(self):
        self.calls += 1
        return self.make()


@pytest.fixture
def cache(tmp_path):
    return Cache(tmp_path / "cache", progress=False)


@pytest.fixture
def stored(cache):
    """(key, path, compute function) of an entry already in the cache."""
    key, fn = cache_key("fault", 1), Counter()
    cache.get_or_compute(key, fn, name="spherelights")
    assert fn.calls == 1
    return key, cache.path(key, "spherelights"), fn


# ----------------------------------------------------------------------------- damaged entry files


def _restamped(edit):
    """A fault made through HDF5 itself, with a valid header re-stamped: only the inner checks can see it."""
    def fault(path, cache):
        with h5py.File(path, "r+") as f:
            edit(f)
        c._stamp(path)
    return fault


def _truncate(fraction=None, keep=None):
    def fault(path, cache):
        data = path.read_bytes()
        path.write_bytes(data[: keep if keep is not None else int(len(data) * fraction)])
    return fault


def _other_key(path, cache):
    other = cache_key("another result")
    cache.store(other, {"radii": np.array([0.2, 0.25])}, name="spherelights")
    cache.path(other, "spherelights").replace(path)


def _foreign_hdf5(path, cache):
    with h5py.File(path, "w") as f:
        f["radii"] = np.array([0.2, 0.25])


def _old_layout(path, cache):
    """An HDF5 file with every prtlab attribute but no header, as an older format wrote."""
    with h5py.File(path, "r") as f:
        attrs = dict(f.attrs)
        radii = f["radii"][()]
    path.unlink()
    with h5py.File(path, "w") as f:
        f.attrs.update(attrs)
        f["radii"] = radii


def _other_format_header(path, cache):
    data = bytearray(path.read_bytes())
    import hashlib

    digest = hashlib.blake2b(bytes(data[c._HEADER_SIZE:]), digest_size=32).hexdigest()
    data[: c._HEADER_SIZE] = c._header(digest, version=c.FORMAT_VERSION + 1)
    path.write_bytes(bytes(data))


def _poke(offset, value=None):
    def fault(path, cache):
        data = bytearray(path.read_bytes())
        data[offset] = value if value is not None else data[offset] ^ 0x10
        path.write_bytes(bytes(data))
    return fault


def _zero_block(path, cache):
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 1024] = bytes(len(data[mid : mid + 1024]))
    path.write_bytes(bytes(data))


def _set_dataset(f):
    f["radii"][0] = 0.2  # the radius 0.4 read as 0.2 of issue 13


def _rename_dataset(f):
    f.move("radii", "radius")


def _add_dataset(f):
    f["extra"] = np.ones(3)


def _string_dataset(f):
    f["label"] = "not a number"


def _set_attr(name, value):
    def edit(f):
        f.attrs[name] = value
    return edit


def _del(name, attrs=False):
    def edit(f):
        del (f.attrs if attrs else f)[name]
    return edit


ENTRY_FAULTS = {
    "empty file": (lambda p, cache: p.write_bytes(b""), "no prtlab cache header \\(0 bytes"),
    "text": (lambda p, cache: p.write_bytes(b"not an hdf5 file"), "no prtlab cache header"),
    "random bytes": (lambda p, cache: p.write_bytes(np.random.default_rng(1).bytes(5000)), "no prtlab cache header"),
    "truncated in the header": (_truncate(keep=100), "do not match their checksum"),
    "truncated before the magic": (_truncate(keep=5), "no prtlab cache header \\(5 bytes"),
    "truncated to the header": (_truncate(keep=c._HEADER_SIZE), "do not match their checksum"),
    "truncated to half": (_truncate(0.5), "do not match their checksum"),
    "truncated by one byte": (_truncate(keep=-1), "do not match their checksum"),
    "trailing garbage": (lambda p, cache: p.write_bytes(p.read_bytes() + b"\0junk"), "do not match their checksum"),
    "zeroed block": (_zero_block, "do not match their checksum"),
    "header magic bit": (_poke(3), "no prtlab cache header"),
    "header checksum digit": (_poke(40), "checksum"),
    "header padding byte": (_poke(c._HEADER_SIZE - 1, 1), "do not match their checksum"),
    "foreign hdf5 file": (_foreign_hdf5, "no prtlab cache header"),
    "older layout without header": (_old_layout, "no prtlab cache header"),
    "another format version": (_other_format_header, f"format version {c.FORMAT_VERSION + 1}, not"),
    "another key": (_other_key, "holds key"),
    "value rewritten": (_restamped(_set_dataset), "do not match its checksum"),
    "dataset renamed": (_restamped(_rename_dataset), "do not match its checksum"),
    "dataset added": (_restamped(_add_dataset), "do not match its checksum"),
    "dataset removed": (_restamped(_del("centres")), "do not match its checksum"),
    "empty group removed": (_restamped(_del("objects/empty")), "do not match its checksum"),
    "string dataset": (_restamped(_string_dataset), "non-numeric dtype"),
    "attrs json rewritten": (_restamped(_set_attr("prtlab_attrs", '{"order": 3, "seconds": 1.5}')),
                             "do not match its checksum"),
    "code fingerprint rewritten": (_restamped(_set_attr("prtlab_code", "0" * 64)), "do not match its checksum"),
    "format attribute rewritten": (_restamped(_set_attr("prtlab_format", c.FORMAT_VERSION + 1)), "format version"),
    "key attribute removed": (_restamped(_del("prtlab_key", attrs=True)), "no prtlab key"),
    "checksum attribute removed": (_restamped(_del("prtlab_checksum", attrs=True)), "no checksum"),
}


@pytest.mark.parametrize("fault", list(ENTRY_FAULTS))
def test_damaged_entry_is_reported_recomputed_and_replaced(cache, stored, fault):
    key, path, fn = stored
    damage, message = ENTRY_FAULTS[fault]
    damage(path, cache)
    with pytest.warns(CacheWarning, match=f"cache file '{re.escape(str(path))}' is unusable .*{message}"):
        out = cache.get_or_compute(key, fn, name="spherelights")
    assert fn.calls == 2 and _same(out, _result())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the bad file was replaced: a clean hit now
        assert _same(cache.get_or_compute(key, fn, name="spherelights"), _result())
    assert fn.calls == 2


def _payload_regions(path) -> list[tuple[int, int]]:
    """(offset, size) of every stored byte of every dataset and of the prtlab attributes."""
    regions = []
    with h5py.File(path, "r") as f:
        datasets = []
        f.visititems(lambda name, obj: datasets.append(obj) if isinstance(obj, h5py.Dataset) else None)
        for ds in datasets:
            if ds.chunks is None:
                regions.append((ds.id.get_offset(), ds.id.get_storage_size()))
            else:
                for j in range(ds.id.get_num_chunks()):
                    info = ds.id.get_chunk_info(j)
                    regions.append((info.byte_offset, info.size))
        attr_values = [str(v).encode() for k, v in f.attrs.items()]
    raw = path.read_bytes()
    for value in attr_values:
        at = raw.find(value)
        if at >= 0:
            regions.append((at, len(value)))
    return regions


@pytest.mark.parametrize("where", ["payload", "anywhere"])
def test_bit_flips_are_never_silent(cache, stored, where):
    """40 seeded trials of 4 flipped bits (in the datasets' stored bytes and the attributes, or anywhere
    in the file): each is detected, or reads back bit-identical. Never different data."""
    key, path, fn = stored
    good = path.read_bytes()
    regions = _payload_regions(path)
    assert len(regions) >= 5 and sum(size for _, size in regions) > 400
    rng = np.random.default_rng(13)
    detected = 0
    for trial in range(40):
        data = bytearray(good)
        for _ in range(4):
            if where == "payload":
                offset, size = regions[rng.integers(len(regions))]
                byte = offset + int(rng.integers(size))
            else:
                byte = int(rng.integers(len(data)))
            data[byte] ^= 1 << int(rng.integers(8))
        path.write_bytes(bytes(data))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            out = cache.load(key, "spherelights")
        if out is None:
            detected += 1
            assert any(issubclass(w.category, CacheWarning) and str(path) in str(w.message) for w in caught)
        else:
            assert _same(out, _result()), f"trial {trial}: a bit flip changed the data silently"
    assert detected >= 1  # the trials did corrupt something


def test_dangling_symlink_is_a_plain_miss(cache, stored):
    key, path, fn = stored
    path.unlink()
    path.symlink_to(path.with_name("gone.h5"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = cache.get_or_compute(key, fn, name="spherelights")
    assert fn.calls == 2 and _same(out, _result()) and path.is_file() and not path.is_symlink()


def test_stray_temporary_file_is_ignored_and_cleared(cache, stored):
    key, path, fn = stored
    stray = path.with_name(path.name + ".tmp-99999-deadbeef")
    stray.write_bytes(path.read_bytes()[:300])
    path.unlink()
    out = cache.get_or_compute(key, fn, name="spherelights")
    assert fn.calls == 2 and _same(out, _result())
    assert [e.path for e in cache.entries()] == [path]
    assert cache.clear("spherelights")[0] == 2 and not stray.exists()


# ----------------------------------------------------------------------------- damaged chunk parts


def _chunk(i):
    return {"v": np.arange(4.0) + 4 * i, "objects": {}}


def _part_of(index=1, key=None, **store):
    """Put in chunk 1's place an intact part of another index, key, chunk count or chunking."""
    def fault(cache, this_key, path):
        source_key = key or this_key
        written = cache.store_chunk(source_key, index, _chunk(index), **{"n_chunks": 4, **store})
        if written != path:
            path.write_bytes(written.read_bytes())
    return fault


CHUNK_FAULTS = {
    "empty part": (lambda cache, key, p: p.write_bytes(b""), "no prtlab cache header"),
    "garbage part": (lambda cache, key, p: p.write_bytes(b"garbage"), "no prtlab cache header"),
    "truncated part": (lambda cache, key, p: p.write_bytes(p.read_bytes()[:-10]), "do not match their checksum"),
    "bit flip in part": (lambda cache, key, p: _poke(-20)(p, cache), "do not match their checksum"),
    "part of another index": (_part_of(index=0), "prtlab_chunk is 0, not 1"),
    "part of another key": (_part_of(key=cache_key("other chunks")), "holds key"),
    "part of another chunk count": (_part_of(n_chunks=5), '"n_chunks": 5'),
    "part of another chunking": (_part_of(chunking={"vertices": 3}), '"vertices": 3'),
}


@pytest.mark.parametrize("fault", list(CHUNK_FAULTS))
def test_damaged_chunk_part_is_reported_and_recomputed(cache, fault):
    key = cache_key("chunk faults")

    def two_then_crash(fn, indices):
        for i in indices[:2]:
            yield i, fn(i)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cache.get_or_compute_chunks(key, 4, _chunk, map_fn=two_then_crash)
    part = cache._chunk_path(key, "data", 1)
    damage, message = CHUNK_FAULTS[fault]
    damage(cache, key, part)
    computed = []
    with pytest.warns(CacheWarning, match=f"cache chunk '{re.escape(str(part))}' is unusable .*{message}"):
        out = cache.get_or_compute_chunks(key, 4, lambda i: computed.append(i) or _chunk(i))
    assert computed == [1, 2, 3]  # chunk 0 was kept, the damaged chunk 1 recomputed
    np.testing.assert_array_equal(out["v"], np.arange(16.0))
    assert out["objects"] == {}


# ----------------------------------------------------------------------------- other processes


def _child(code: str, *args, drop_write_permission: bool = False, wait: bool = True):
    """Run ``code`` in a fresh interpreter on this checkout (``args`` in ``sys.argv[1:]``)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    preexec = None
    if drop_write_permission and os.geteuid() == 0:
        preexec = _drop_dac_override
    cmd = [sys.executable, "-c", textwrap.dedent(code), *map(str, args)]
    if not wait:
        return subprocess.Popen(cmd, env=env, cwd=str(REPO), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return subprocess.run(cmd, env=env, cwd=str(REPO), capture_output=True, text=True, timeout=120,
                          preexec_fn=preexec)


def _drop_dac_override():
    """In the child, before exec: drop root's power to ignore file permissions (CAP_DAC_OVERRIDE, _READ_SEARCH)."""
    libc = ctypes.CDLL(None, use_errno=True)
    for cap in (1, 2):
        if libc.prctl(24, cap, 0, 0, 0) != 0:  # PR_CAPBSET_DROP
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP) failed")


def _wait_for(predicate, what: str, timeout: float = 60.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


READ_ONLY_CHILD = """
    import sys
    import numpy as np
    from prtlab.cache import Cache, CacheNotWritableError
    root, key, other = sys.argv[1:4]
    cache = Cache(root, progress=False)
    out = cache.get_or_compute(key, lambda: sys.exit("recomputed a valid entry"), name="ro")  # a hit works
    assert np.array_equal(out["x"], np.arange(5.0)), out
    for run in (lambda: cache.get_or_compute(other, lambda: sys.exit("computed before the refusal"), name="ro"),
                lambda: cache.get_or_compute_chunks(other, 3, lambda i: sys.exit("computed a chunk"), name="ro")):
        try:
            run()
        except CacheNotWritableError as err:
            print(err)
        else:
            sys.exit("a miss on a read-only cache was not refused")
"""


def test_read_only_cache_reads_hits_and_refuses_misses_before_computing(tmp_path):
    root = tmp_path / "ro"
    cache = Cache(root, progress=False)
    key, other = cache_key("ro"), cache_key("ro", "other")
    cache.store(key, {"x": np.arange(5.0)}, name="ro")
    os.chmod(cache.path(key, "ro"), 0o444)
    os.chmod(root, 0o555)
    try:
        try:
            proc = _child(READ_ONLY_CHILD, root, key, other, drop_write_permission=True)
        except subprocess.SubprocessError as err:  # no CAP_SETPCAP to drop root's override
            pytest.skip(f"cannot make a folder read-only for this user: {err}")
    finally:
        os.chmod(root, 0o755)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 2
    for line in lines:
        assert re.fullmatch(f"cache folder {re.escape(str(root))} is not writable: Permission denied; "
                            "set PRTLAB_CACHE to a writable folder", line), line
    assert [e.path for e in cache.entries()] == [cache.path(key, "ro")]


RACE_CHILD = """
    import os, sys, time
    from pathlib import Path
    import numpy as np
    from prtlab.cache import Cache
    root, key, sync, chunked = sys.argv[1:5]
    sync = Path(sync)
    cache = Cache(root, progress=False)
    (sync / f"ready-{os.getpid()}").touch()
    while not (sync / "go").exists():
        time.sleep(0.01)

    def both_computing():  # hold until the other process computes too: the two really overlap
        (sync / f"computing-{os.getpid()}").touch()
        deadline = time.monotonic() + 60
        while len(list(sync.glob("computing-*"))) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)

    if chunked == "1":
        def chunk(i):
            if i == 0:
                both_computing()
            time.sleep(0.02)
            return {"x": np.arange(10000.0) + 10000 * i, "g": {}}
        out = cache.get_or_compute_chunks(key, 6, chunk, name="race")
        expected = np.arange(60000.0)
    else:
        def compute():
            both_computing()
            return {"x": np.arange(60000.0), "g": {}, "attrs": {"n": 1}}
        out = cache.get_or_compute(key, compute, name="race")
        assert out["attrs"] == {"n": 1}
    assert np.array_equal(out["x"], expected if chunked == "1" else np.arange(60000.0)) and out["g"] == {}
    print("ok")
"""


@pytest.mark.parametrize("chunked", [False, True], ids=["entry", "chunks"])
def test_two_processes_computing_one_key_leave_one_valid_entry(tmp_path, chunked):
    root, sync = tmp_path / "cache", tmp_path / "sync"
    sync.mkdir()
    key = cache_key("race", chunked)
    procs = [_child(RACE_CHILD, root, key, sync, int(chunked), wait=False) for _ in range(2)]
    try:
        _wait_for(lambda: len(list(sync.glob("ready-*"))) == 2, "both processes to start")
        (sync / "go").touch()
        outs = [p.communicate(timeout=120) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0 and out.strip() == "ok", err
    assert len(list(sync.glob("computing-*"))) == 2  # both missed and computed at once
    cache = Cache(root, progress=False)
    assert [(e.kind, e.path) for e in cache.entries()] == [("entry", cache.path(key, "race"))]
    assert not list(root.rglob("*.tmp-*"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = cache.get_or_compute(key, lambda: pytest.fail("recomputed"), name="race")
    np.testing.assert_array_equal(out["x"], np.arange(60000.0))


KILLED_CHUNKS_CHILD = """
    import sys, time
    from pathlib import Path
    import numpy as np
    from prtlab.cache import Cache
    root, key, marker = sys.argv[1:4]

    def chunk(i):
        if i == 3:
            Path(marker).touch()
            time.sleep(120)  # killed here, with chunks 0-2 stored
        return {"v": np.arange(5.0) + 5 * i}

    Cache(root, progress=False).get_or_compute_chunks(key, 8, chunk, name="killed")
"""


def test_sigkill_mid_chunks_keeps_the_finished_chunks(tmp_path):
    root, marker, key = tmp_path / "cache", tmp_path / "at-chunk-3", cache_key("killed")
    proc = _child(KILLED_CHUNKS_CHILD, root, key, marker, wait=False)
    try:
        _wait_for(marker.exists, "the child to reach chunk 3")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    cache = Cache(root, progress=False)
    assert cache.finished_chunks(key, 8, name="killed") == [0, 1, 2]
    assert cache.load(key, "killed") is None
    computed = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = cache.get_or_compute_chunks(key, 8, lambda i: computed.append(i) or {"v": np.arange(5.0) + 5 * i},
                                          name="killed")
    assert computed == [3, 4, 5, 6, 7]
    np.testing.assert_array_equal(out["v"], np.arange(40.0))


KILLED_WRITE_CHILD = """
    import sys, time
    from pathlib import Path
    import numpy as np
    import prtlab.cache as c
    root, key, marker = sys.argv[1:4]
    stamp = c._stamp

    def stamp_then_hang(path):
        stamp(path)
        Path(marker).touch()
        time.sleep(120)  # killed here: the file is whole but not yet renamed into place

    c._stamp = stamp_then_hang
    c.Cache(root, progress=False).get_or_compute(key, lambda: {"x": np.arange(30000.0)}, name="killed")
"""


def test_sigkill_mid_write_leaves_no_entry_and_a_stray_file_that_clear_removes(tmp_path):
    root, marker, key = tmp_path / "cache", tmp_path / "writing", cache_key("killed write")
    proc = _child(KILLED_WRITE_CHILD, root, key, marker, wait=False)
    try:
        _wait_for(marker.exists, "the child to write")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=30)
    cache = Cache(root, progress=False)
    strays = list(root.glob("*.tmp-*"))
    assert len(strays) == 1 and not cache.path(key, "killed").exists() and cache.entries() == []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = cache.get_or_compute(key, lambda: {"x": np.arange(30000.0)}, name="killed")
    np.testing.assert_array_equal(out["x"], np.arange(30000.0))
    size = sum(p.stat().st_size for p in [*strays, cache.path(key, "killed")])
    assert cache.clear() == (2, size) and not list(root.iterdir())
