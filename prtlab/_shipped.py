"""The folders shipped inside the package (notebooks, benchmarks) and the docs of the clone it runs from."""

from __future__ import annotations

import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def shipped_folder(env: str, name: str, kind: str, files: str) -> Path:
    """``$env`` if set, else the package's folder ``name``; ``FileNotFoundError`` saying what to set when it is
    not a folder (``kind`` names it, ``files`` says what it holds, e.g. ``"*.ipynb files"``)."""
    value = os.environ.get(env)
    folder = Path(value) if value else _PACKAGE / name
    if not folder.is_dir():
        where = f"{env} names" if value else "the installed prtlab package has"
        raise FileNotFoundError(
            f"no {kind} folder at {folder} ({where} none); set {env} to a folder of {files} or reinstall prtlab"
        )
    return folder


def clone_doc(name: str) -> Path:
    """``docs/<name>`` of the clone holding this package (it need not exist)."""
    return _PACKAGE.parent / "docs" / name
