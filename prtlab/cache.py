"""Content-addressed HDF5 cache of precomputed data (``../shared/DESIGN.md``, "Caching and data safety").

A cache entry is one HDF5 file of plain numeric datasets, named by a hash of
every input that made it (:func:`cache_key`). Guarantees:

- **Atomic writes.** An entry is written to a temporary file in the same
  folder and renamed into place with :func:`os.replace`, so a reader never
  sees half a file, and a crash leaves at worst a stray ``*.tmp-*`` file.
- **Checked reads.** The key is stored inside the file (attribute
  ``prtlab_key``) with the format version; a file that fails to open, lacks
  the key, or holds another key is reported with :class:`CacheWarning` and
  recomputed, never silently used.
- **No code on load.** Only numeric/boolean datasets and a JSON string of
  attributes are stored; nothing is pickled, so loading executes nothing.
- **Resumable chunks.** :meth:`Cache.get_or_compute_chunks` stores every
  finished chunk as its own part file and assembles them at the end, so an
  interrupted precomputation resumes from its finished chunks (and chunks
  can be computed elsewhere, e.g. on Dask workers, then stored with
  :meth:`Cache.store_chunk`).

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
import os
import shutil
import uuid
import warnings
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from prtlab._validate import check_int

__all__ = ["FORMAT_VERSION", "Cache", "CacheWarning", "cache_key", "default_cache_root"]

#: Bump when the layout of cached data changes: every old entry then misses.
FORMAT_VERSION = 1

_KEY_ATTR = "prtlab_key"
_FORMAT_ATTR = "prtlab_format"
_ATTRS_ATTR = "prtlab_attrs"
_CHUNK_ATTR = "prtlab_chunk"
_ATTRS = "attrs"  # the reserved entry of a result dict holding JSON metadata


class CacheWarning(UserWarning):
    """A cache file was unusable (unreadable, wrong key, wrong format) and is being recomputed."""


def default_cache_root() -> Path:
    """``$PRTLAB_CACHE`` if set, else ``~/.cache/prtlab``."""
    env = os.environ.get("PRTLAB_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "prtlab"


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
        cache :data:`FORMAT_VERSION` is always included.

    Returns
    -------
    key : str
        64 hex characters. Equal inputs give equal keys on every machine;
        ``1`` and ``1.0`` and ``"1"`` differ (types are tagged).
    """
    h = hashlib.sha256()
    _feed(h, ("prtlab-cache", FORMAT_VERSION))
    for part in parts:
        _feed(h, part)
    return h.hexdigest()


def _check_key(key: Any) -> str:
    if not isinstance(key, str) or len(key) < 16 or not all(c in "0123456789abcdef" for c in key):
        raise ValueError(f"key must be a hex digest from cache_key(...), got {key!r}")
    return key


def _check_name(name: Any) -> str:
    if not isinstance(name, str) or not name or not all(c.isalnum() or c in "-_." for c in name):
        raise ValueError(f"name must be a non-empty string of letters, digits, '-', '_', '.', got {name!r}")
    return name


# --------------------------------------------------------------------------- HDF5 I/O


def _flatten(result: Mapping, prefix: str = "") -> dict[str, np.ndarray]:
    out = {}
    for k, value in result.items():
        if not isinstance(k, str) or not k or "/" in k:
            raise ValueError(f"result keys must be non-empty strings without '/', got {k!r}")
        name = f"{prefix}{k}"
        if prefix == "" and k == _ATTRS:
            continue
        if isinstance(value, Mapping):
            out.update(_flatten(value, name + "/"))
            continue
        arr = np.asarray(value)
        if arr.dtype.kind not in "biufc":
            raise TypeError(
                f"result entry {name!r} has dtype {arr.dtype}; the cache stores numeric or boolean arrays "
                "only (no objects, no pickle)"
            )
        out[name] = arr
    return out


def _unflatten(flat: dict[str, np.ndarray]) -> dict:
    out: dict = {}
    for name, arr in flat.items():
        parts = name.split("/")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = arr
    return out


def _write_h5(path: Path, arrays: dict[str, np.ndarray], attrs: dict, key: str, extra: dict | None = None) -> None:
    """Write atomically: a temporary file next to ``path``, then ``os.replace``."""
    import h5py

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs[_KEY_ATTR] = key
            f.attrs[_FORMAT_ATTR] = FORMAT_VERSION
            f.attrs[_ATTRS_ATTR] = json.dumps(attrs, sort_keys=True, allow_nan=True)
            for k, v in (extra or {}).items():
                f.attrs[k] = v
            for name, arr in arrays.items():
                f.create_dataset(name, data=arr, compression="gzip" if arr.nbytes > 1 << 16 else None)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _read_h5(path: Path, key: str, extra: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
    """Read a cache file; raise ``ValueError`` naming the problem if it is not the entry for ``key``."""
    import h5py

    with h5py.File(path, "r") as f:
        stored = f.attrs.get(_KEY_ATTR)
        if isinstance(stored, bytes):
            stored = stored.decode()
        if stored != key:
            raise ValueError(f"it holds key {str(stored)[:16]}..., not {key[:16]}...")
        version = f.attrs.get(_FORMAT_ATTR)
        if version != FORMAT_VERSION:
            raise ValueError(f"it has format version {version}, not {FORMAT_VERSION}")
        for k, v in (extra or {}).items():
            if f.attrs.get(k) != v:
                raise ValueError(f"its attribute {k} is {f.attrs.get(k)!r}, not {v!r}")
        attrs = json.loads(f.attrs.get(_ATTRS_ATTR, "{}"))
        arrays: dict[str, np.ndarray] = {}

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                if obj.dtype.kind not in "biufc":
                    raise ValueError(f"dataset {name!r} has non-numeric dtype {obj.dtype}")
                arrays[name] = obj[()]

        f.visititems(visit)
    return arrays, attrs


# --------------------------------------------------------------------------- the cache


class Cache:
    """A folder of content-addressed HDF5 entries.

    Parameters
    ----------
    root : path-like, optional
        Folder of the cache (created on first write). Default:
        :func:`default_cache_root` (``$PRTLAB_CACHE`` or ``~/.cache/prtlab``).
    progress : bool
        Show a tqdm progress bar in :meth:`get_or_compute_chunks`.

    Notes
    -----
    Entry ``key`` of name ``name`` lives in ``root/<name>-<key[:32]>.h5``
    (the full key is stored inside and checked); its unfinished chunks in
    ``root/<name>-<key[:32]>.parts/chunk-00000.h5``, ...

    A result is a dict of numeric arrays (nested dicts become HDF5 groups)
    plus an optional ``"attrs"`` entry: a dict of JSON-serialisable metadata
    (timings, options). Reads return the same structure.
    """

    def __init__(self, root=None, progress: bool = True):
        self.root = Path(os.fspath(root)).expanduser() if root is not None else default_cache_root()
        self.progress = bool(progress)

    def __repr__(self) -> str:
        return f"Cache({str(self.root)!r})"

    # ------------------------------------------------------------------ paths

    def path(self, key: str, name: str = "data") -> Path:
        """Path of the entry file for ``key``."""
        return self.root / f"{_check_name(name)}-{_check_key(key)[:32]}.h5"

    def _parts_dir(self, key: str, name: str) -> Path:
        return self.root / f"{_check_name(name)}-{_check_key(key)[:32]}.parts"

    def _chunk_path(self, key: str, name: str, i: int) -> Path:
        return self._parts_dir(key, name) / f"chunk-{i:05d}.h5"

    # ------------------------------------------------------------------ single entries

    def load(self, key: str, name: str = "data") -> dict | None:
        """The stored result for ``key``, or ``None`` if absent or unusable (then a :class:`CacheWarning`)."""
        path = self.path(key, name)
        if not path.exists():
            return None
        try:
            arrays, attrs = _read_h5(path, key)
        except Exception as err:  # h5py raises OSError for corrupt files, KeyError for odd ones
            warnings.warn(
                f"cache file {str(path)!r} is unusable ({type(err).__name__}: {err}); recomputing it",
                CacheWarning,
                stacklevel=3,
            )
            return None
        out = _unflatten(arrays)
        if attrs:
            out[_ATTRS] = attrs
        return out

    def store(self, key: str, result: Mapping, name: str = "data") -> Path:
        """Write ``result`` (dict of arrays, optional ``"attrs"``) as the entry for ``key``."""
        _check_key(key)
        if not isinstance(result, Mapping):
            raise TypeError(f"result must be a dict of arrays, got {type(result).__name__}")
        arrays = _flatten(result)
        attrs = dict(result.get(_ATTRS, {}) or {})
        path = self.path(key, name)
        _write_h5(path, arrays, attrs, key)
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
        """
        cached = self.load(key, name)
        if cached is not None:
            return cached
        self.store(key, compute_fn(), name)
        fresh = self.load(key, name)
        if fresh is None:  # pragma: no cover - only if the file system loses the write
            raise OSError(f"cache entry {self.path(key, name)} vanished right after writing it")
        return fresh

    # ------------------------------------------------------------------ chunked entries

    def finished_chunks(self, key: str, n_chunks: int, name: str = "data") -> list[int]:
        """Indices of the chunks already stored (and valid) for ``key``."""
        n_chunks = check_int(n_chunks, "n_chunks", 1)
        return [i for i in range(n_chunks) if self.load_chunk(key, i, name, quiet=True) is not None]

    def missing_chunks(self, key: str, n_chunks: int, name: str = "data") -> list[int]:
        """Indices of the chunks still to compute (e.g. to submit to Dask workers)."""
        done = set(self.finished_chunks(key, n_chunks, name))
        return [i for i in range(n_chunks) if i not in done]

    def store_chunk(self, key: str, i: int, result: Mapping, name: str = "data") -> Path:
        """Store chunk ``i`` of entry ``key`` as its own part file (atomic)."""
        _check_key(key)
        if not isinstance(result, Mapping):
            raise TypeError(f"chunk result must be a dict of arrays, got {type(result).__name__}")
        path = self._chunk_path(key, name, int(i))
        _write_h5(path, _flatten(result), dict(result.get(_ATTRS, {}) or {}), key, {_CHUNK_ATTR: int(i)})
        return path

    def load_chunk(self, key: str, i: int, name: str = "data", quiet: bool = False) -> dict | None:
        """Chunk ``i`` of entry ``key``, or ``None`` if absent or unusable (warned unless ``quiet``)."""
        path = self._chunk_path(key, name, int(i))
        if not path.exists():
            return None
        try:
            arrays, attrs = _read_h5(path, key, {_CHUNK_ATTR: int(i)})
        except Exception as err:
            if not quiet:
                warnings.warn(
                    f"cache chunk {str(path)!r} is unusable ({type(err).__name__}: {err}); recomputing it",
                    CacheWarning,
                    stacklevel=3,
                )
            return None
        out = _unflatten(arrays)
        if attrs:
            out[_ATTRS] = attrs
        return out

    def get_or_compute_chunks(
        self,
        key: str,
        n_chunks: int,
        chunk_fn: Callable[[int], Mapping],
        name: str = "data",
        assemble: Callable[[list[dict]], Mapping] | None = None,
        map_fn: Callable[[Callable[[int], Mapping], list[int]], Iterable[tuple[int, Mapping]]] | None = None,
    ) -> dict:
        """A result computed in ``n_chunks`` resumable pieces.

        Each finished chunk is stored as its own part file at once; on a later
        call (after a crash or an interrupt) only the missing chunks are
        computed. When all are present they are assembled into the entry for
        ``key`` and the part files are removed.

        Parameters
        ----------
        key : str
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

        Returns
        -------
        dict
            The assembled result, as read back from the entry file.
        """
        n_chunks = check_int(n_chunks, "n_chunks", 1)
        cached = self.load(key, name)
        if cached is not None:
            return cached
        # read every stored chunk once (warning about unusable ones), then compute the rest
        stored = {i: self.load_chunk(key, i, name) for i in range(n_chunks)}
        todo = [i for i, chunk in stored.items() if chunk is None]
        if todo:
            from tqdm.auto import tqdm

            runner = map_fn or (lambda fn, indices: ((i, fn(i)) for i in indices))
            with tqdm(
                total=n_chunks, initial=n_chunks - len(todo), desc=name, unit="chunk", disable=not self.progress
            ) as bar:
                for i, result in runner(chunk_fn, todo):
                    self.store_chunk(key, i, result, name)
                    stored[i] = self.load_chunk(key, i, name)
                    bar.update(1)
        missing = [i for i, chunk in stored.items() if chunk is None]
        if missing:
            raise RuntimeError(f"chunks {missing} of {name!r} are missing after computing them (map_fn skipped them?)")
        chunks = [stored[i] for i in range(n_chunks)]
        result = (assemble or _concatenate)(chunks)
        self.store(key, result, name)
        shutil.rmtree(self._parts_dir(key, name), ignore_errors=True)
        return self.load(key, name)


def _concatenate(chunks: list[dict]) -> dict:
    """Default assembly: every array concatenated along axis 0 across chunks (nested dicts too)."""
    flat = [_flatten(c) for c in chunks]
    names = list(flat[0])
    for i, f in enumerate(flat[1:], start=1):
        if list(f) != names:
            raise ValueError(f"chunk {i} has arrays {sorted(f)}, chunk 0 has {sorted(names)}; they must match")
    out = _unflatten({n: np.concatenate([f[n] for f in flat], axis=0) for n in names})
    if chunks[0].get(_ATTRS):
        out[_ATTRS] = chunks[0][_ATTRS]
    return out
