"""The one validator of scene data: every check of the scene format goes through here.

Each failure raises :class:`SceneError` with the source (file name, or
``<dict>``), the key path (``objects[2].material.albedo``) and what was
expected, e.g.::

    scene.yaml: objects[2].material.albedo: expected 3 non-negative finite numbers, got [0.5, nan, 1]
"""

from __future__ import annotations

import difflib
import math
from pathlib import Path
from typing import Any, Iterable

import numpy as np

__all__ = ["SceneError", "InwardNormalsWarning", "Validator", "child", "index", "show", "clip", "SHOW_LIMIT"]


class SceneError(ValueError):
    """A scene file or dict is invalid; the message names the file and the key path."""


class InwardNormalsWarning(UserWarning):
    """A closed mesh's faces point inward while the camera is outside it: it would shade black.

    Silence it for a scene where this is meant with
    ``warnings.filterwarnings("ignore", category=InwardNormalsWarning)``.
    """


def child(path: str, key: str) -> str:
    """Key path of ``key`` inside ``path`` (a long key is cut to :data:`SHOW_LIMIT` characters)."""
    key = clip(str(key))
    return f"{path}.{key}" if path else key


def index(path: str, i: int) -> str:
    """Key path of item ``i`` of the list at ``path``."""
    return f"{path}[{i}]"


#: Longest rendering of a value in a message; longer ones end in "...".
SHOW_LIMIT = 80


def show(value: Any, limit: int = SHOW_LIMIT) -> str:
    """Compact rendering of a YAML value for messages (``[0.5, nan, 1]``), at most ``limit`` characters.

    Containers are rendered lazily and cut at ``limit`` (ending in ``...``), so
    even a value with billions of shared leaves is shown at once.
    """
    pieces: list[str] = []
    size = 0
    for piece in _pieces(value):
        pieces.append(piece)
        size += len(piece)
        if size > limit:
            break
    return clip("".join(pieces), limit)


def clip(text: str, limit: int = SHOW_LIMIT) -> str:
    """``text`` cut to ``limit`` characters, ending in ``...`` when cut."""
    return text if len(text) <= limit else text[: max(limit - 3, 0)] + "..."


def _pieces(value: Any):
    """The rendering of ``value`` as a stream of short strings (depth-first, lazily)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        yield "["
        for k, item in enumerate(value):
            if k:
                yield ", "
            yield from _pieces(item)
        yield "]"
    elif isinstance(value, dict):
        yield "{"
        for k, (key, item) in enumerate(value.items()):
            yield (", " if k else "") + clip(str(key)) + ": "
            yield from _pieces(item)
        yield "}"
    elif isinstance(value, (float, np.floating)):
        yield repr(float(value))
    elif isinstance(value, np.integer):
        yield repr(int(value))
    elif isinstance(value, str):
        yield clip(repr(value))
    else:
        yield clip(str(value))


def _is_number(value: Any) -> bool:
    return not isinstance(value, (bool, np.bool_)) and isinstance(value, (int, float, np.integer, np.floating))


def _type_name(value: Any) -> str:
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, (list, tuple)):
        return "a list"
    if value is None:
        return "nothing (null)"
    return f"{type(value).__name__} {show(value)}"


class Validator:
    """Checks values of one scene source; every method raises :class:`SceneError` on failure.

    Parameters
    ----------
    source : str
        What the messages name first: the scene file's path, or ``<dict>``.
    """

    def __init__(self, source: str):
        self.source = source

    def error(self, path: str, message: str) -> SceneError:
        return SceneError(f"{self.source}: {path}: {message}" if path else f"{self.source}: {message}")

    # ------------------------------------------------------------------ structure

    def mapping(self, value: Any, path: str, allowed: Iterable[str], required: Iterable[str] = ()) -> dict:
        """A mapping with only ``allowed`` keys (suggesting the closest for a typo) and all ``required`` ones."""
        allowed = list(allowed)
        if not isinstance(value, dict):
            raise self.error(path, f"expected a mapping with keys {', '.join(allowed)}; got {_type_name(value)}")
        for key in value:
            if not isinstance(key, str):
                raise self.error(path, f"keys must be strings, got {show(key)}")
            if key not in allowed:
                close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
                hint = f"; did you mean '{close[0]}'?" if close else ""
                raise self.error(child(path, key), f"unknown key{hint} (valid keys: {', '.join(allowed)})")
        for key in required:
            if key not in value:
                raise self.error(path, f"missing required key '{key}'")
        return value

    def sequence(self, value: Any, path: str, *, nonempty: bool = False) -> list:
        if not isinstance(value, (list, tuple)):
            raise self.error(path, f"expected a list, got {_type_name(value)}")
        if nonempty and not value:
            raise self.error(path, "expected a non-empty list, got []")
        return list(value)

    def choice(self, value: Any, path: str, choices: Iterable[str], what: str) -> str:
        choices = list(choices)
        if not isinstance(value, str) or value not in choices:
            close = difflib.get_close_matches(str(value), choices, n=1, cutoff=0.6)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            raise self.error(path, f"unknown {what} {show(value)}{hint} (valid: {', '.join(choices)})")
        return value

    # ------------------------------------------------------------------ scalars

    def text(self, value: Any, path: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.error(path, f"expected a non-empty string, got {_type_name(value)}")
        return value

    def flag(self, value: Any, path: str) -> bool:
        if not isinstance(value, (bool, np.bool_)):
            raise self.error(path, f"expected true or false, got {_type_name(value)}")
        return bool(value)

    def number(
        self,
        value: Any,
        path: str,
        *,
        minimum: float | None = None,
        maximum: float | None = None,
        positive: bool = False,
    ) -> float:
        """A finite number; ``positive`` means > 0; ``minimum`` / ``maximum`` are inclusive bounds."""
        ok = _is_number(value) and math.isfinite(float(value))
        if ok and positive and not float(value) > 0.0:
            ok = False
        if ok and minimum is not None and float(value) < minimum:
            ok = False
        if ok and maximum is not None and float(value) > maximum:
            ok = False
        if not ok:
            raise self.error(path, f"expected {self._number_phrase(positive, minimum, maximum)}, got {show(value)}")
        return float(value)

    @staticmethod
    def _number_phrase(positive: bool, minimum, maximum) -> str:
        if positive:
            phrase = "a finite number > 0"
        else:
            phrase = "a finite number"
        if minimum is not None and maximum is not None:
            return f"{phrase} in [{show(minimum)}, {show(maximum)}]"
        if minimum is not None:
            return f"{phrase} >= {show(minimum)}"
        if maximum is not None:
            return f"{phrase} <= {show(maximum)}"
        return phrase

    def integer(self, value: Any, path: str, *, minimum: int = 0) -> int:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
            raise self.error(path, f"expected an integer >= {minimum}, got {show(value)}")
        return int(value)

    # ------------------------------------------------------------------ vectors

    def vector(self, value: Any, path: str, n: int = 3, *, nonnegative: bool = False) -> np.ndarray:
        """``n`` finite numbers (non-negative if asked) as a float64 array."""
        words = "non-negative finite numbers" if nonnegative else "finite numbers"
        ok = isinstance(value, (list, tuple, np.ndarray)) and len(value) == n and all(_is_number(v) for v in value)
        if ok:
            arr = np.asarray(value, dtype=np.float64)
            ok = bool(np.all(np.isfinite(arr))) and (not nonnegative or bool(np.all(arr >= 0.0)))
        if not ok:
            raise self.error(path, f"expected {n} {words}, got {show(value)}")
        return arr

    def colour(self, value: Any, path: str, *, at_most_one: bool = False) -> np.ndarray:
        """An RGB triple of non-negative finite numbers; reflectances must also be <= 1."""
        arr = self.vector(value, path, 3, nonnegative=True)
        if at_most_one and np.any(arr > 1.0):
            raise self.error(
                path,
                f"reflectance above 1 reflects more light than it receives (energy gain), got {show(value)}; "
                "use values in [0, 1]",
            )
        return arr

    def nonzero_vector(self, value: Any, path: str) -> np.ndarray:
        arr = self.vector(value, path, 3)
        if not np.linalg.norm(arr) > 0.0:
            raise self.error(path, f"expected a non-zero vector, got {show(value)}")
        return arr

    # ------------------------------------------------------------------ files

    def file(self, value: Any, path: str, base_dir: Path | None) -> Path:
        """An existing file; relative paths are relative to ``base_dir`` (the scene file's folder)."""
        name = self.text(value, path)
        p = Path(name).expanduser()
        if not p.is_absolute():
            p = (base_dir or Path.cwd()) / p
        if not p.is_file():
            where = f" (relative to {base_dir})" if base_dir is not None and not Path(name).is_absolute() else ""
            raise self.error(path, f"file not found: {clip(repr(name))}{where}")
        return p
