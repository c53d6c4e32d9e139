"""Content-addressed HDF5 cache of precomputed data.

A cache entry is one HDF5 file of plain numeric datasets, named by a hash of
every input that made it (:func:`cache_key`). Guarantees:

- **Keys cover the code.** Every key includes :func:`code_fingerprint`, a
  hash of the source of every ``.py`` file of the installed ``prtlab``
  package, so a result computed by other code is never read.
- **Atomic writes.** An entry is written to a temporary file in the same
  folder and renamed into place with :func:`os.replace`, so a reader never
  sees half a file, two processes writing the same entry leave one whole
  entry, and a crash leaves at worst a stray ``*.tmp-*`` file.
- **Checked reads.** Every file starts with a 512-byte header (the HDF5
  user block) holding the format version and a BLAKE2b checksum of every
  byte after it, verified before HDF5 parses the file; inside, the key, the
  format version and a checksum of every dataset, group and attribute are
  stored, and every chunked dataset carries HDF5's ``fletcher32`` checksum.
  A file that is empty, truncated, corrupt in any bit, holds another key, or
  has another format is reported with :class:`CacheWarning` naming the file
  and recomputed (the bad file is replaced), never silently used.
- **No code on load.** Only numeric/boolean datasets, groups and a JSON
  string of attributes are stored; nothing is pickled, so loading executes
  nothing.
- **Resumable chunks.** :meth:`Cache.get_or_compute_chunks` stores every
  finished chunk as its own part file, tagged with the chunking it belongs
  to, and assembles them at the end, so an interrupted precomputation resumes
  from its finished chunks, and parts of another chunking are recomputed,
  never assembled.
- **Bounded and visible.** The folder is kept under a size cap by evicting
  the least recently used entries (:class:`Cache` ``max_bytes``); hits,
  misses and evictions are logged on the ``"prtlab.cache"`` logger at INFO;
  :meth:`Cache.entries`, :meth:`Cache.info` and :meth:`Cache.clear` list,
  sum and remove entries.
- **Refused before work.** A miss checks that the folder is writable
  (:meth:`Cache.check_writable`) before computing anything.

Example
-------
>>> import numpy as np, tempfile
>>> cache = Cache(tempfile.mkdtemp())
>>> key = cache_key("transfer", np.arange(3.0), {"order": 4})
>>> out = cache.get_or_compute(key, lambda: {"coeffs": np.ones((3, 16))}, name="transfer")
>>> out["coeffs"].shape
(3, 16)
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
import shutil
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from prtlab._validate import check_int

__all__ = [
    "FORMAT_VERSION", "Cache", "CacheEntry", "CacheNotWritableError", "CacheWarning", "cache_key",
    "code_fingerprint", "default_cache_root", "default_max_bytes",
]

#: Bump when the layout of cached data changes: every old entry then misses.
FORMAT_VERSION = 2

#: The size cap when neither ``max_bytes`` nor ``$PRTLAB_CACHE_MAX_GB`` is given.
DEFAULT_MAX_GB = 4.0

_KEY_ATTR = "prtlab_key"
_FORMAT_ATTR = "prtlab_format"
_ATTRS_ATTR = "prtlab_attrs"
_CODE_ATTR = "prtlab_code"
_CHECKSUM_ATTR = "prtlab_checksum"
_CHUNK_ATTR = "prtlab_chunk"
_CHUNKING_ATTR = "prtlab_chunking"
_ATTRS = "attrs"  # the reserved entry of a result dict holding JSON metadata

_HEADER_SIZE = 512  # the HDF5 user block: magic, format version, checksum of every byte after it
_MAGIC = b"prtlab-cache\n"
_ENTRY_RE = re.compile(r"^(?P<name>[A-Za-z0-9_.-]+)-(?P<key>[0-9a-f]{32})\.(?P<ext>h5|parts)$")
_TMP_MARK = ".tmp-"

log = logging.getLogger("prtlab.cache")


class CacheWarning(UserWarning):
    """A cache file was unusable (unreadable, wrong key, wrong format, corrupt) and is being recomputed."""


class CacheNotWritableError(PermissionError):
    """The cache folder cannot be written (raised before any computation)."""


def default_cache_root() -> Path:
    """``$PRTLAB_CACHE`` if set, else ``~/.cache/prtlab``."""
    env = os.environ.get("PRTLAB_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "prtlab"


def default_max_bytes() -> int:
    """The size cap in bytes: ``$PRTLAB_CACHE_MAX_GB`` (gigabytes of 10**9 bytes) if set, else 4 GB."""
    env = os.environ.get("PRTLAB_CACHE_MAX_GB")
    if env is None or env.strip() == "":
        return int(DEFAULT_MAX_GB * 1e9)
    try:
        gb = float(env)
    except ValueError:
        gb = math.nan
    if not math.isfinite(gb) or gb <= 0:
        raise ValueError(f"PRTLAB_CACHE_MAX_GB must be a positive number of gigabytes (e.g. 4 or 0.5), got {env!r}")
    return max(1, int(gb * 1e9))


# --------------------------------------------------------------------------- the code fingerprint

_CODE_FINGERPRINT: str | None = None  # computed once per process by code_fingerprint()


def _fingerprint_of(package_dir: Path) -> str:
    """SHA-256 over every ``.py`` file under ``package_dir``: relative path and bytes, sorted by path."""
    h = hashlib.sha256()
    files = sorted((p.relative_to(package_dir).as_posix(), p) for p in package_dir.rglob("*.py") if p.is_file())
    for rel, p in files:
        data = p.read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode() + data)
    return h.hexdigest()


def code_fingerprint() -> str:
    """SHA-256 hex digest of the source of the ``prtlab`` package (every ``.py`` file under it).

    Every :func:`cache_key` includes it, so any change to the code a
    precomputation can run gives new keys, and no result computed by other
    code is ever read. It is computed once per process, on first use, and
    kept in a module global: editing the source of a running process does
    not change its keys until it restarts. Data files the code reads are not
    part of it (callers key the data they pass in).
    """
    global _CODE_FINGERPRINT
    if _CODE_FINGERPRINT is None:
        _CODE_FINGERPRINT = _fingerprint_of(Path(__file__).resolve().parent)
    return _CODE_FINGERPRINT


# --------------------------------------------------------------------------- keys


def _feed(h, part: Any) -> None:
    """Feed a canonical, type-tagged encoding of ``part`` into the hash ``h``."""
    if part is None or isinstance(part, (bool, np.bool_)):
        h.update(b"J" + json.dumps(None if part is None else bool(part)).encode())
    elif isinstance(part, (int, np.integer)):
        h.update(b"I" + str(int(part)).encode() + b";")
    elif isinstance(part, (float, np.floating)):
        h.update(b"F" + float(part).hex().encode() + b";")
    elif isinstance(part, str):
        data = part.encode("utf-8")
        h.update(b"S" + str(len(data)).encode() + b":" + data)
    elif isinstance(part, bytes):
        h.update(b"B" + str(len(part)).encode() + b":" + part)
    elif isinstance(part, np.ndarray):
        if part.dtype.kind not in "biufc":
            raise TypeError(f"cache_key: arrays must be numeric or boolean, got dtype {part.dtype}")
        arr = np.ascontiguousarray(part)
        header = f"A{arr.dtype.str}{arr.shape}".encode()
        h.update(header + b":" + arr.tobytes())
    elif hasattr(part, "vertices") and hasattr(part, "faces"):  # a mesh: geometry and connectivity
        h.update(b"M")
        _feed(h, np.asarray(part.vertices, dtype=np.float64))
        _feed(h, np.asarray(part.faces, dtype=np.int64))
    elif isinstance(part, Mapping):
        keys = list(part)
        if not all(isinstance(k, str) for k in keys):
            raise TypeError(f"cache_key: dict keys must be strings, got {keys!r}")
        h.update(b"D" + str(len(keys)).encode() + b"{")
        for k in sorted(keys):
            _feed(h, k)
            _feed(h, part[k])
        h.update(b"}")
    elif isinstance(part, (list, tuple)):
        h.update(b"L" + str(len(part)).encode() + b"[")
        for item in part:
            _feed(h, item)
        h.update(b"]")
    elif hasattr(part, "to_dict"):  # scene dataclasses (Material, Transform, ...)
        h.update(b"O" + type(part).__name__.encode())
        _feed(h, part.to_dict())
    else:
        raise TypeError(
            f"cache_key: cannot hash a {type(part).__name__}; pass arrays, meshes, numbers, strings, "
            "or lists/dicts of them"
        )


def cache_key(*parts: Any) -> str:
    """SHA-256 hex digest of every input that determines a cached result.

    Parameters
    ----------
    *parts
        Arrays (hashed with dtype, shape and bytes), meshes (vertex and face
        arrays), dicts of options (canonically: sorted keys, exact float bits),
        lists, numbers, strings, bytes, and objects with ``to_dict()``. The
        cache :data:`FORMAT_VERSION` and the :func:`code_fingerprint` are
        always included.

    Returns
    -------
    key : str
        64 hex characters. Equal inputs and equal code give equal keys on
        every machine; ``1`` and ``1.0`` and ``"1"`` differ (types are tagged).
    """
    h = hashlib.sha256()
    _feed(h, ("prtlab-cache", FORMAT_VERSION, code_fingerprint()))
    for part in parts:
        _feed(h, part)
    return h.hexdigest()


def _check_key(key: Any) -> str:
    if not isinstance(key, str) or len(key) < 32 or not all(c in "0123456789abcdef" for c in key):
        raise ValueError(f"key must be a hex digest from cache_key(...), got {key!r}")
    return key


def _check_name(name: Any, what: str = "name") -> str:
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "-_." for c in name):
        raise ValueError(f"{what} must be a non-empty string of letters, digits, '-', '_', '.', got {name!r}")
    return name


def _chunking_id(n_chunks: int, chunking: Any) -> str:
    """The identity of a chunking: the chunk count and the caller's descriptor, as canonical JSON."""
    try:
        return json.dumps({"n_chunks": n_chunks, "chunking": chunking}, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise TypeError(
            f"chunking must be JSON-serialisable (numbers, strings, lists, dicts), got {chunking!r}: {err}"
        ) from None


# --------------------------------------------------------------------------- HDF5 I/O


def _flatten(result: Mapping, prefix: str = "") -> tuple[dict[str, np.ndarray], list[str]]:
    """``(arrays, groups)``: the arrays by slash-joined path, and the path of every nested dict."""
    arrays: dict[str, np.ndarray] = {}
    groups: list[str] = []
    for k, value in result.items():
        if not isinstance(k, str) or not k or "/" in k:
            raise ValueError(f"result keys must be non-empty strings without '/', got {k!r}")
        name = f"{prefix}{k}"
        if prefix == "" and k == _ATTRS:
            continue
        if isinstance(value, Mapping):
            groups.append(name)
            sub_arrays, sub_groups = _flatten(value, name + "/")
            arrays.update(sub_arrays)
            groups += sub_groups
            continue
        arr = np.asarray(value)
        if arr.dtype.kind not in "biufc":
            raise TypeError(
                f"result entry {name!r} has dtype {arr.dtype}; the cache stores numeric or boolean arrays "
                "only (no objects, no pickle)"
            )
        arrays[name] = arr
    return arrays, groups


def _unflatten(arrays: Mapping[str, Any], groups: Iterable[str] = ()) -> dict:
    out: dict = {}
    for name in sorted(groups):
        node = out
        for p in name.split("/"):
            node = node.setdefault(p, {})
    for name, arr in arrays.items():
        parts = name.split("/")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = arr
    return out


def _attr_value(value: Any) -> Any:
    """An HDF5 attribute as a plain Python str or int (what the cache writes)."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if isinstance(value, (np.integer, int)) and not isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, str):
        return str(value)
    return repr(value)


def _checksum(attrs: Mapping[str, Any], groups: Iterable[str], arrays: Mapping[str, Any]) -> str:
    """BLAKE2b over the attributes, group paths and arrays (name, kind, size, shape, little-endian bytes)."""
    h = hashlib.blake2b(digest_size=32)
    h.update(json.dumps({k: _attr_value(v) for k, v in attrs.items()}, sort_keys=True).encode())
    h.update(json.dumps(sorted(groups)).encode())
    for name in sorted(arrays):
        arr = np.asarray(arrays[name])
        canonical = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<")) if arr.dtype.kind != "b" else (
            np.ascontiguousarray(arr, dtype=np.uint8))
        h.update(f"\0{name}\0{arr.dtype.kind}{arr.dtype.itemsize}\0{arr.shape}\0".encode())
        h.update(canonical.tobytes())
    return h.hexdigest()


def _file_digest(f) -> str:
    """BLAKE2b of the rest of the open binary file ``f``, read in blocks."""
    h = hashlib.blake2b(digest_size=32)
    while block := f.read(1 << 20):
        h.update(block)
    return h.hexdigest()


def _header(digest: str, version: int | None = None) -> bytes:
    """The HDF5 user block of an entry: magic, format version, checksum of the bytes after it, zeros."""
    version = FORMAT_VERSION if version is None else version
    return (_MAGIC + f"format {version}\nblake2b {digest}\n".encode()).ljust(_HEADER_SIZE, b"\0")


def _stamp(path: Path) -> None:
    """Write the header of a finished HDF5 file (made with ``userblock_size=_HEADER_SIZE``)."""
    with open(path, "r+b") as f:
        f.seek(_HEADER_SIZE)
        digest = _file_digest(f)
        f.seek(0)
        f.write(_header(digest))


def _verify_bytes(path: Path) -> None:
    """Raise ``ValueError`` unless ``path`` starts with an entry header whose checksum matches the rest."""
    with open(path, "rb") as f:
        head = f.read(_HEADER_SIZE)
        if not head.startswith(_MAGIC):
            size = os.fstat(f.fileno()).st_size
            raise ValueError(f"it has no prtlab cache header ({size} bytes; empty, truncated, or not a cache file)")
        digest = _file_digest(f)
    if head == _header(digest):
        return
    version = head[len(_MAGIC):].split(b"\n", 1)[0]
    if version != f"format {FORMAT_VERSION}".encode() and head.rstrip(b"\0").count(b"\n") == 3:
        raise ValueError(f"it has format version {version.decode('ascii', 'replace')[7:]}, not {FORMAT_VERSION}")
    raise ValueError("its bytes do not match their checksum (the file is corrupt or truncated)")


def _as_read(result: Mapping) -> dict:
    """``result`` in the form a read returns: numpy arrays (scalars as numpy scalars), attrs through JSON."""
    arrays, groups = _flatten(result)
    out = _unflatten({n: (a[()] if a.ndim == 0 else np.array(a)) for n, a in arrays.items()}, groups)
    attrs = dict(result.get(_ATTRS, {}) or {})
    if attrs:
        out[_ATTRS] = json.loads(json.dumps(attrs, sort_keys=True, allow_nan=True))
    return out


def _write_h5(path: Path, result: Mapping, key: str, extra: dict | None = None) -> None:
    """Write ``result`` atomically: a temporary file next to ``path``, then ``os.replace``."""
    import h5py

    arrays, groups = _flatten(result)
    attrs = {
        _KEY_ATTR: key,
        _FORMAT_ATTR: FORMAT_VERSION,
        _ATTRS_ATTR: json.dumps(dict(result.get(_ATTRS, {}) or {}), sort_keys=True, allow_nan=True),
        _CODE_ATTR: code_fingerprint(),
        **(extra or {}),
    }
    checksum = _checksum(attrs, groups, arrays)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}{_TMP_MARK}{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        with h5py.File(tmp, "w", userblock_size=_HEADER_SIZE) as f:
            for k, v in attrs.items():
                f.attrs[k] = v
            f.attrs[_CHECKSUM_ATTR] = checksum
            for name in groups:
                f.require_group(name)
            for name, arr in arrays.items():
                if arr.ndim == 0:  # HDF5 cannot chunk (so cannot fletcher32) a scalar: the checksum covers it
                    f.create_dataset(name, data=arr)
                else:
                    f.create_dataset(name, data=arr, fletcher32=True,
                                     compression="gzip" if arr.nbytes > 1 << 16 else None)
        _stamp(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _read_h5(path: Path, key: str, extra: dict | None = None) -> dict:
    """Read a cache file; raise ``ValueError`` naming the problem if it is not an intact entry for ``key``."""
    import h5py

    _verify_bytes(path)  # before HDF5 parses a byte of it: corrupt metadata can make HDF5 loop forever
    with h5py.File(path, "r") as f:
        attrs = {k: _attr_value(f.attrs[k]) for k in f.attrs}
        stored = attrs.get(_KEY_ATTR)
        if stored is None:
            raise ValueError("it has no prtlab key (not a prtlab cache file)")
        if stored != key:
            raise ValueError(f"it holds key {str(stored)[:16]}..., not {key[:16]}...")
        version = attrs.get(_FORMAT_ATTR)
        if version != FORMAT_VERSION:
            raise ValueError(f"it has format version {version}, not {FORMAT_VERSION}")
        for k, v in (extra or {}).items():
            if attrs.get(k) != v:
                raise ValueError(f"its attribute {k} is {attrs.get(k)!r}, not {v!r}")
        checksum = attrs.pop(_CHECKSUM_ATTR, None)
        if checksum is None:
            raise ValueError("it has no checksum")
        arrays: dict[str, Any] = {}
        groups: list[str] = []

        def visit(name, obj):
            if isinstance(obj, h5py.Group):
                groups.append(name)
            elif isinstance(obj, h5py.Dataset):
                if obj.dtype.kind not in "biufc":
                    raise ValueError(f"dataset {name!r} has non-numeric dtype {obj.dtype}")
                arrays[name] = obj[()]
            else:  # pragma: no cover - h5py yields only groups and datasets
                raise ValueError(f"object {name!r} is neither a group nor a dataset")

        f.visititems(visit)
    if _checksum(attrs, groups, arrays) != checksum:
        raise ValueError("its contents do not match its checksum (the file is corrupt)")
    out = _unflatten(arrays, groups)
    user_attrs = json.loads(attrs.get(_ATTRS_ATTR, "{}"))
    if user_attrs:
        out[_ATTRS] = user_attrs
    return out


def _tree_stats(path: Path) -> tuple[int, float, int]:
    """``(bytes, newest mtime, n_files)`` of a file or of every file under a folder."""
    if path.is_dir():
        size, newest, n = 0, path.stat().st_mtime, 0
        for p in path.rglob("*"):
            try:
                st = p.stat()
            except FileNotFoundError:
                continue
            if p.is_file():
                size, n = size + st.st_size, n + 1
            newest = max(newest, st.st_mtime)
        return size, newest, n
    st = path.stat()
    return st.st_size, st.st_mtime, 1


def _remove(path: Path) -> tuple[int, int]:
    """Remove a file or a folder tree; ``(files removed, bytes freed)``, ``(0, 0)`` if it is already gone."""
    try:
        size, _, n = _tree_stats(path)
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink()
    except FileNotFoundError:
        return 0, 0
    return n, size


# --------------------------------------------------------------------------- the cache


@dataclass(frozen=True)
class CacheEntry:
    """One item of a cache folder, as listed by :meth:`Cache.entries`.

    ``method`` is the name the entry was stored under (the file-name prefix,
    e.g. ``"interreflection"`` or ``"portals-photons"``); ``kind`` is
    ``"entry"`` (a finished result) or ``"parts"`` (the stored chunks of an
    unfinished chunked result); ``last_used`` is the time of the last write
    or hit (seconds since the epoch).
    """

    path: Path
    method: str
    size_bytes: int
    last_used: float
    kind: str


class Cache:
    """A folder of content-addressed HDF5 entries.

    Parameters
    ----------
    root : path-like, optional
        Folder of the cache (created on first write). Default:
        :func:`default_cache_root` (``$PRTLAB_CACHE`` or ``~/.cache/prtlab``).
    progress : bool
        Show a tqdm progress bar in :meth:`get_or_compute_chunks`.
    max_bytes : int, optional
        Size cap of the folder. After each write, the least recently used
        entries (and parts of unfinished chunked results) are removed until
        the folder is under the cap; the entry just written is never removed.
        Default: :func:`default_max_bytes` (``$PRTLAB_CACHE_MAX_GB``, else 4 GB).

    Notes
    -----
    Entry ``key`` of name ``name`` lives in ``root/<name>-<key[:32]>.h5``
    (the full key is stored inside and checked); its unfinished chunks in
    ``root/<name>-<key[:32]>.parts/chunk-00000.h5``, ...

    A result is a dict of numeric arrays (nested dicts become HDF5 groups,
    empty ones included) plus an optional ``"attrs"`` entry: a dict of
    JSON-serialisable metadata (timings, options). Reads return the same
    structure (0-d arrays come back as numpy scalars).

    A hit sets the entry's modification time to now: that time is its last
    use, for eviction. Hits, misses and evictions are logged on the
    ``"prtlab.cache"`` logger at INFO.
    """

    def __init__(self, root=None, progress: bool = True, max_bytes: int | None = None):
        self.root = Path(os.fspath(root)).expanduser() if root is not None else default_cache_root()
        self.progress = bool(progress)
        self.max_bytes = default_max_bytes() if max_bytes is None else check_int(max_bytes, "max_bytes", 1)

    def __repr__(self) -> str:
        return f"Cache({str(self.root)!r}, max_bytes={self.max_bytes})"

    # ------------------------------------------------------------------ paths

    def path(self, key: str, name: str = "data") -> Path:
        """Path of the entry file for ``key``."""
        return self.root / f"{_check_name(name)}-{_check_key(key)[:32]}.h5"

    def _parts_dir(self, key: str, name: str) -> Path:
        return self.root / f"{_check_name(name)}-{_check_key(key)[:32]}.parts"

    def _chunk_path(self, key: str, name: str, i: int) -> Path:
        return self._parts_dir(key, name) / f"chunk-{i:05d}.h5"

    # ------------------------------------------------------------------ writability

    def check_writable(self) -> None:
        """Create the folder if needed and write (then remove) a probe file in it.

        Raises
        ------
        CacheNotWritableError
            (a ``PermissionError``) naming the folder and the reason, if it
            cannot be created or written.
        """
        probe = self.root / f"write-check{_TMP_MARK}{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            os.close(fd)
            probe.unlink()
        except OSError as err:
            reason = err.strerror or str(err)
            raise CacheNotWritableError(
                f"cache folder {self.root} is not writable: {reason}; set PRTLAB_CACHE to a writable folder"
            ) from None

    # ------------------------------------------------------------------ reading and writing files

    def _load_file(self, path: Path, key: str, what: str, extra: dict | None = None, quiet: bool = False):
        if not path.exists():
            return None
        try:
            out = _read_h5(path, key, extra)
        except FileNotFoundError:  # removed (evicted, or assembled by another process) since the check
            return None
        except Exception as err:  # h5py raises OSError for corrupt files, KeyError or ValueError for odd ones
            if not quiet:
                warnings.warn(
                    f"cache {what} {str(path)!r} is unusable ({type(err).__name__}: {err}); recomputing it",
                    CacheWarning,
                    stacklevel=4,
                )
            return None
        try:
            os.utime(path)  # its last use, for eviction
        except OSError:  # a read-only cache: still readable
            pass
        return out

    # ------------------------------------------------------------------ single entries

    def load(self, key: str, name: str = "data") -> dict | None:
        """The stored result for ``key``, or ``None`` if absent or unusable (then a :class:`CacheWarning`)."""
        return self._load_file(self.path(key, name), key, "file")

    def store(self, key: str, result: Mapping, name: str = "data") -> Path:
        """Write ``result`` (dict of arrays, optional ``"attrs"``) as the entry for ``key``, then evict
        least recently used entries to stay under :attr:`max_bytes` (never this one)."""
        _check_key(key)
        if not isinstance(result, Mapping):
            raise TypeError(f"result must be a dict of arrays, got {type(result).__name__}")
        path = self.path(key, name)
        _write_h5(path, result, key)
        self._evict(protect={path})
        return path

    def get_or_compute(self, key: str, compute_fn: Callable[[], Mapping], name: str = "data") -> dict:
        """The cached result for ``key``, computing and storing it on a miss.

        Parameters
        ----------
        key : str
            From :func:`cache_key` over every input of ``compute_fn``.
        compute_fn : callable
            ``compute_fn() -> dict`` of numeric arrays (plus optional ``"attrs"``).
        name : str
            A readable prefix of the file name (letters, digits, ``-_.``).

        Returns
        -------
        dict
            What ``compute_fn`` returned, as read back from the file (arrays
            as numpy arrays, ``"attrs"`` as JSON-decoded values), so hits and
            misses return the same thing.

        Raises
        ------
        CacheNotWritableError
            On a miss, before ``compute_fn`` runs, if the folder is not writable.
        """
        path = self.path(key, name)
        cached = self.load(key, name)
        if cached is not None:
            log.info("cache hit: %s %s", name, path)
            return cached
        log.info("cache miss: %s %s; computing", name, path)
        self.check_writable()
        result = compute_fn()
        if not isinstance(result, Mapping):
            raise TypeError(f"result must be a dict of arrays, got {type(result).__name__}")
        self.store(key, result, name)
        fresh = self.load(key, name)
        if fresh is None:  # removed by another process between the write and the read-back
            log.warning("cache entry %s was removed right after it was written; using the computed result", path)
            return _as_read(result)
        return fresh

    # ------------------------------------------------------------------ chunked entries

    def _chunk_extra(self, i: int, n_chunks: int, chunking: Any) -> dict:
        n_chunks = check_int(n_chunks, "n_chunks", 1)
        i = check_int(i, "chunk index", 0)
        if i >= n_chunks:
            raise ValueError(f"chunk index must be < n_chunks = {n_chunks}, got {i}")
        return {_CHUNK_ATTR: i, _CHUNKING_ATTR: _chunking_id(n_chunks, chunking)}

    def finished_chunks(self, key: str, n_chunks: int, name: str = "data", chunking: Any = None) -> list[int]:
        """Indices of the chunks already stored (and valid, of this chunking) for ``key``."""
        n_chunks = check_int(n_chunks, "n_chunks", 1)
        return [i for i in range(n_chunks)
                if self.load_chunk(key, i, name, quiet=True, n_chunks=n_chunks, chunking=chunking) is not None]

    def missing_chunks(self, key: str, n_chunks: int, name: str = "data", chunking: Any = None) -> list[int]:
        """Indices of the chunks still to compute (e.g. to submit to Dask workers)."""
        done = set(self.finished_chunks(key, n_chunks, name, chunking))
        return [i for i in range(n_chunks) if i not in done]

    def store_chunk(self, key: str, i: int, result: Mapping, name: str = "data", *, n_chunks: int,
                    chunking: Any = None) -> Path:
        """Store chunk ``i`` of ``n_chunks`` of entry ``key`` as its own part file (atomic).

        ``n_chunks`` and ``chunking`` (any JSON-serialisable description of
        how the work was split, e.g. ``{"vertices": 2048}``) are stored with
        the part: a part is only ever used by a run of the same chunking.
        """
        _check_key(key)
        extra = self._chunk_extra(i, n_chunks, chunking)
        if not isinstance(result, Mapping):
            raise TypeError(f"chunk result must be a dict of arrays, got {type(result).__name__}")
        path = self._chunk_path(key, name, int(i))
        _write_h5(path, result, key, extra)
        self._evict(protect={self._parts_dir(key, name)})
        return path

    def load_chunk(self, key: str, i: int, name: str = "data", quiet: bool = False, *, n_chunks: int,
                   chunking: Any = None) -> dict | None:
        """Chunk ``i`` of ``n_chunks`` of entry ``key``, or ``None`` if absent, of another chunking, or
        unusable (warned unless ``quiet``)."""
        extra = self._chunk_extra(i, n_chunks, chunking)
        return self._load_file(self._chunk_path(key, name, int(i)), key, "chunk", extra, quiet)

    def get_or_compute_chunks(
        self,
        key: str,
        n_chunks: int,
        chunk_fn: Callable[[int], Mapping],
        name: str = "data",
        assemble: Callable[[list[dict]], Mapping] | None = None,
        map_fn: Callable[[Callable[[int], Mapping], list[int]], Iterable[tuple[int, Mapping]]] | None = None,
        chunking: Any = None,
    ) -> dict:
        """A result computed in ``n_chunks`` resumable pieces.

        Each finished chunk is stored as its own part file at once; on a later
        call (after a crash or an interrupt) only the missing chunks are
        computed. When all are present they are assembled into the entry for
        ``key`` and the part files are removed. A stored part made for another
        ``n_chunks`` or ``chunking`` is reported (:class:`CacheWarning`) and
        recomputed, never assembled.

        Parameters
        ----------
        key : str
            Identifies the assembled result: it must cover every input the
            result depends on (the chunking too, if the result depends on it).
        n_chunks : int
        chunk_fn : callable
            ``chunk_fn(i) -> dict`` of arrays for chunk ``i``.
        name : str
        assemble : callable, optional
            ``assemble(chunks) -> dict`` from the list of chunk dicts in order.
            Default: concatenate every array along axis 0 (chunks by
            vertices or sample points); ``"attrs"`` of the first chunk are kept.
        map_fn : callable, optional
            ``map_fn(chunk_fn, indices)`` yielding ``(i, result)`` pairs as
            chunks finish, in any order: plug in a parallel executor (e.g.
            ``dask.distributed``'s ``as_completed``). Default: one by one.
        chunking : JSON-serialisable, optional
            How the work is split beyond the count (e.g. ``{"vertices": 16}``);
            stored with every part with ``n_chunks``.

        Returns
        -------
        dict
            The assembled result, as read back from the entry file.

        Raises
        ------
        CacheNotWritableError
            On a miss, before any chunk is computed, if the folder is not writable.
        """
        n_chunks = check_int(n_chunks, "n_chunks", 1)
        _chunking_id(n_chunks, chunking)  # refuse a chunking that cannot be stored before any work
        path = self.path(key, name)
        cached = self.load(key, name)
        if cached is not None:
            log.info("cache hit: %s %s", name, path)
            return cached
        self.check_writable()
        # read every stored chunk once (warning about unusable ones), then compute the rest
        stored = {i: self.load_chunk(key, i, name, n_chunks=n_chunks, chunking=chunking) for i in range(n_chunks)}
        todo = [i for i, chunk in stored.items() if chunk is None]
        log.info("cache miss: %s %s; computing %d of %d chunks", name, path, len(todo), n_chunks)
        if todo:
            self._compute_chunks(key, name, todo, chunk_fn, map_fn, stored, n_chunks, chunking)
        missing = [i for i, chunk in stored.items() if chunk is None]
        if missing:
            raise RuntimeError(f"chunks {missing} of {name!r} are missing after computing them (map_fn skipped them?)")
        chunks = [stored[i] for i in range(n_chunks)]
        result = (assemble or _concatenate)(chunks)
        self.store(key, result, name)
        shutil.rmtree(self._parts_dir(key, name), ignore_errors=True)
        fresh = self.load(key, name)
        if fresh is None:  # removed by another process between the write and the read-back
            log.warning("cache entry %s was removed right after it was written; using the computed result", path)
            return _as_read(result)
        return fresh

    def _compute_chunks(self, key, name, todo, chunk_fn, map_fn, stored: dict, n_chunks: int, chunking) -> None:
        """Compute the chunks ``todo`` (by ``map_fn``), store each as it finishes and put it in ``stored``."""
        from tqdm.auto import tqdm

        runner = map_fn or (lambda fn, indices: ((i, fn(i)) for i in indices))
        with tqdm(
            total=n_chunks, initial=n_chunks - len(todo), desc=name, unit="chunk", disable=not self.progress
        ) as bar:
            for i, result in runner(chunk_fn, todo):
                try:
                    self.store_chunk(key, i, result, name, n_chunks=n_chunks, chunking=chunking)
                except FileNotFoundError:  # the parts folder was removed under us: keep it in memory
                    log.warning("cache chunk %d of %s could not be stored; keeping it in memory", i,
                                self.path(key, name))
                stored[int(i)] = _as_read(result)
                bar.update(1)

    # ------------------------------------------------------------------ listing, size cap, clearing

    def entries(self, method: str | None = None) -> list[CacheEntry]:
        """Every entry and unfinished-parts folder in the cache, sorted by name, kind and path.

        ``method``: only those stored under that name or under a name that
        starts with ``method + "-"`` (``"portals"`` lists ``portals``,
        ``portals-photons`` and ``portals-chunks``).
        """
        if method is not None:
            _check_name(method, "method")
        if not self.root.is_dir():
            return []
        out = []
        for p in self.root.iterdir():
            m = _ENTRY_RE.match(p.name)
            if m is None:
                continue
            name = m.group("name")
            if method is not None and name != method and not name.startswith(method + "-"):
                continue
            kind = "entry" if m.group("ext") == "h5" else "parts"
            if (kind == "entry") != p.is_file():
                continue
            try:
                size, last_used, _ = _tree_stats(p)
            except FileNotFoundError:  # removed while listing
                continue
            out.append(CacheEntry(path=p, method=name, size_bytes=size, last_used=last_used, kind=kind))
        return sorted(out, key=lambda e: (e.method, e.kind, e.path.name))

    def info(self) -> dict:
        """A summary: ``root``, ``n_entries``, ``n_parts`` (unfinished chunked results),
        ``total_bytes``, ``max_bytes`` and per name ``methods[name] = {"entries", "parts", "bytes"}``."""
        listed = self.entries()
        methods: dict[str, dict[str, int]] = {}
        for e in listed:
            m = methods.setdefault(e.method, {"entries": 0, "parts": 0, "bytes": 0})
            m["entries" if e.kind == "entry" else "parts"] += 1
            m["bytes"] += e.size_bytes
        return {
            "root": str(self.root),
            "n_entries": sum(e.kind == "entry" for e in listed),
            "n_parts": sum(e.kind == "parts" for e in listed),
            "total_bytes": sum(e.size_bytes for e in listed),
            "max_bytes": self.max_bytes,
            "methods": dict(sorted(methods.items())),
        }

    def clear(self, method: str | None = None) -> tuple[int, int]:
        """Remove every entry and parts folder (of ``method``, as in :meth:`entries`) and stray
        temporary files; ``(files removed, bytes freed)``. Do not run while a precomputation
        writes to this cache: its temporary files are removed too."""
        removed = freed = 0
        for e in self.entries(method):
            n, size = _remove(e.path)
            removed, freed = removed + n, freed + size
        if self.root.is_dir():
            for p in self.root.iterdir():
                if _TMP_MARK not in p.name or not p.is_file():
                    continue
                stem = p.name.split(_TMP_MARK)[0]
                m = _ENTRY_RE.match(stem)
                if method is not None and (m is None or not (m.group("name") == method
                                                             or m.group("name").startswith(method + "-"))):
                    continue
                n, size = _remove(p)
                removed, freed = removed + n, freed + size
        log.info("cache cleared: %d files, %d bytes from %s%s", removed, freed, self.root,
                 f" (method {method})" if method else "")
        return removed, freed

    def _evict(self, protect: set[Path]) -> None:
        """Remove least recently used entries until the folder is under :attr:`max_bytes`."""
        listed = self.entries()
        total = sum(e.size_bytes for e in listed)
        if total <= self.max_bytes:
            return
        for e in sorted(listed, key=lambda e: e.last_used):
            if total <= self.max_bytes:
                break
            if e.path in protect:
                continue
            _, size = _remove(e.path)
            total -= size
            log.info("cache evicted: %s %s (%d bytes, last used %s) to stay under %d bytes", e.method, e.path,
                     e.size_bytes, time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(e.last_used)), self.max_bytes)
        if total > self.max_bytes:
            log.info("cache %s holds %d bytes, over its cap of %d: the entry just written is kept", self.root,
                     total, self.max_bytes)


def _concatenate(chunks: list[dict]) -> dict:
    """Default assembly: every array concatenated along axis 0 across chunks (nested dicts too)."""
    flat = [_flatten(c) for c in chunks]
    names = sorted(flat[0][0])
    for i, (arrays, _) in enumerate(flat[1:], start=1):
        if sorted(arrays) != names:
            raise ValueError(f"chunk {i} has arrays {sorted(arrays)}, chunk 0 has {sorted(names)}; they must match")
    out = _unflatten({n: np.concatenate([f[0][n] for f in flat], axis=0) for n in names}, flat[0][1])
    if chunks[0].get(_ATTRS):
        out[_ATTRS] = chunks[0][_ATTRS]
    return out
