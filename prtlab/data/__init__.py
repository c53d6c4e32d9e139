"""The assets and example scenes that ship inside the prtlab package.

The files live in this package's folder (``prtlab/data/``; a clone also shows
it as ``data/`` at the repository root), so they travel with a wheel and
resolve the same way from a clone, an editable install or an installed
package. Nothing is downloaded at run time. Sources and licences:
``prtlab/data/README.md``.

Layout::

    scenes/*.yaml         example scenes (``prtlab.load_scene("cornell_box")``)
    meshes/*.ply          the Stanford bunny and dragons
    meshes/cornell_box/   the Cornell box, one PLY per part
    envmaps/*.exr         light probes, 512 x 256 equirectangular
    tables/*.csv          numeric tables (teapot patches, sun spectrum)

Examples
--------
>>> import prtlab.data
>>> "cornell_box" in prtlab.data.scenes()
True
>>> prtlab.data.scene_path("cornell_box").name
'cornell_box.yaml'
>>> prtlab.data.path("envmaps", "courtyard.exr").is_file()
True
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["root", "path", "scene_path", "scenes", "meshes", "envmaps"]

_ROOT = Path(__file__).resolve().parent
_KINDS = {"scenes": ("*.yaml",), "meshes": ("*.ply", "*.obj"), "envmaps": ("*.exr",)}


def root() -> Path:
    """The folder holding the shipped assets (``scenes/``, ``meshes/``, ``envmaps/``)."""
    return _ROOT


def _listing(folder: Path) -> str:
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in folder.iterdir()
                   if not p.name.startswith(("_", ".")))
    return ", ".join(names) if names else "nothing"


def path(*parts) -> Path:
    """The shipped file or folder at ``root() / parts[0] / parts[1] / ...``.

    Parameters
    ----------
    *parts : str or path-like
        Path components relative to :func:`root`, e.g. ``("meshes", "bunny.ply")``;
        none gives :func:`root` itself.

    Returns
    -------
    Path
        An existing file or folder inside :func:`root`.

    Raises
    ------
    TypeError
        If a part is not a string or path-like.
    ValueError
        If the parts lead outside :func:`root` (an absolute part or ``..``).
    FileNotFoundError
        If nothing is shipped there; the message lists what the nearest existing
        folder holds.
    """
    for part in parts:
        if not isinstance(part, (str, os.PathLike)):
            raise TypeError(f"prtlab.data.path: parts must be strings, got {part!r}")
    relative = Path(*(os.fspath(p) for p in parts)) if parts else Path()
    target = (_ROOT / relative).resolve()
    if relative.is_absolute() or not target.is_relative_to(_ROOT):
        raise ValueError(
            f"prtlab.data.path: {relative.as_posix()!r} is outside the shipped data folder; "
            "give a path relative to it, e.g. path('scenes', 'cornell_box.yaml')"
        )
    if target.exists():
        return target
    folder = target.parent
    while not folder.is_dir():
        folder = folder.parent
    where = folder.relative_to(_ROOT).as_posix()
    where = "the data folder" if where == "." else f"{where}/"
    raise FileNotFoundError(
        f"prtlab.data: no shipped file {relative.as_posix()!r}; {where} holds: {_listing(folder)}"
    )


def _names(kind: str) -> list[str]:
    folder = _ROOT / kind
    if not folder.is_dir():
        return []
    found = {p.relative_to(folder).as_posix() for pattern in _KINDS[kind] for p in folder.rglob(pattern)}
    return sorted(found)


def scenes() -> list[str]:
    """Names (file stems) of the shipped example scenes, sorted, e.g. ``"cornell_box"``."""
    return sorted(Path(name).stem for name in _names("scenes") if "/" not in name)


def scene_path(name: str) -> Path:
    """The shipped scene file called ``name`` (its stem, e.g. ``"cornell_box"``; ``".yaml"`` optional).

    Raises
    ------
    TypeError
        If ``name`` is not a string.
    FileNotFoundError
        If no shipped scene has that name; the message lists the available names.
    """
    if not isinstance(name, str):
        raise TypeError(f"prtlab.data.scene_path: name must be a string such as 'cornell_box', got {name!r}")
    stem = name[: -len(".yaml")] if name.endswith(".yaml") else name
    if stem in scenes():
        return _ROOT / "scenes" / f"{stem}.yaml"
    raise FileNotFoundError(
        f"no shipped scene named {name!r}; available: {', '.join(scenes())} "
        "(or give the path of a scene file)"
    )


def meshes() -> list[str]:
    """The shipped mesh files, relative to ``meshes/``, e.g. ``"bunny.ply"``, ``"cornell_box/floor.ply"``.

    ``path("meshes", name)`` gives the file; ``prtlab.geometry.builtin_mesh`` reads them by name.
    """
    return _names("meshes")


def envmaps() -> list[str]:
    """The shipped light probes, relative to ``envmaps/``, e.g. ``"courtyard.exr"``.

    ``path("envmaps", name)`` gives the file (a scene refers to it by a path relative to the scene).
    """
    return _names("envmaps")
