"""``prtlab reproduce``: execute the paper notebooks and gather their figures into one report.

The notebooks shipped in the package (``prtlab/notebooks/``, shown as
``notebooks/`` at the root of a clone) are the single source of every reproduced
figure and table (one per paper, plus the SH algebra and the ground truth).
This module executes each of them headless (``PRTLAB_QUICK=1`` in quick mode),
writes the executed notebook as a standalone HTML page, and writes
``index.html`` with, per notebook, its title, its figures and its printed
tables, linking to the full page. A notebook that fails is reported in the
index with its error, and makes the command exit non-zero.

Generated tables: a notebook records each table it prints with :func:`record_table`. When
``$PRTLAB_REPRODUCE_TABLES`` names a folder (``reproduce(..., write_docs=PATH)`` sets it to
``out_dir/tables``), the table is also written there as ``NAME.json``, and :func:`write_docs`
replaces the text between ``<!-- repro:begin NAME -->`` and ``<!-- repro:end NAME -->`` in a
Markdown file with the table rendered by :func:`render_table`, under one line saying the mode
(quick or full size), the date and the notebook. Everything outside the markers is kept as is.
"""

from __future__ import annotations

import html
import json
import math
import os
import re
import time
from pathlib import Path

from prtlab._shipped import clone_doc, shipped_folder

__all__ = ["reproduce", "notebook_dir", "record_table", "render_table", "write_docs", "default_docs_path"]

TABLES_ENV = "PRTLAB_REPRODUCE_TABLES"
NOTEBOOK_ENV = "PRTLAB_REPRODUCE_NOTEBOOK"
_NAME = re.compile(r"[a-z0-9][a-z0-9_.-]*\Z")
_MARKER = re.compile(r"<!-- repro:(begin|end) ([^ ]*) -->")


def notebook_dir() -> Path:
    """The folder of the paper notebooks: ``$PRTLAB_NOTEBOOKS`` if set, else the one shipped in the package."""
    return shipped_folder("PRTLAB_NOTEBOOKS", "notebooks", "notebook", "*.ipynb files")


def default_docs_path() -> Path:
    """``docs/REPRODUCTION.md`` of the clone this package runs from."""
    path = clone_doc("REPRODUCTION.md")
    if not path.is_file():
        raise FileNotFoundError(
            f"--write-docs: no {path} (prtlab is not run from a clone); give the Markdown file, --write-docs PATH"
        )
    return path


# --------------------------------------------------------------------------- recorded tables


def _cell(value, spec: str | None) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool) or isinstance(value, str):
        return str(value)
    if isinstance(value, (int, float)) or hasattr(value, "dtype"):
        value = value.item() if hasattr(value, "item") else value
        if isinstance(value, float) and math.isnan(value):
            return "n/a"
        if spec is not None:
            return format(value, spec)
        return str(value) if isinstance(value, int) else format(value, ".3g")
    raise TypeError(f"record_table: a cell must be a string or a number, got {type(value).__name__} {value!r}")


def _json_value(value):
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def record_table(name: str, rows, columns, note: str = "", formats=None, out=print) -> dict:
    """Print a table a notebook computed and, if ``$PRTLAB_REPRODUCE_TABLES`` is set, write it as JSON.

    Parameters
    ----------
    name : str
        The table's name: lower-case letters, digits, ``_``, ``.``, ``-``; the Markdown section
        ``<!-- repro:begin NAME -->`` of the docs that :func:`write_docs` fills with it.
    rows : sequence of sequences
        One row per line, each with one cell per column: a string or a number.
    columns : sequence of str
        The column headers.
    note : str
        One line printed under the table (units, what is left out).
    formats : {column: format spec}, optional
        How a number of that column is printed (default ``.3g`` for floats, ``str`` for ints).

    Returns
    -------
    dict
        The record written: ``name, columns, rows`` (the cells as printed), ``values`` (the
        numbers), ``note``, ``quick`` (``PRTLAB_QUICK=1``), ``date``, ``notebook``.
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"record_table: table name {name!r} must be lower-case letters, digits, '_', '.', '-'")
    columns = [str(c) for c in columns]
    formats = dict(formats or {})
    unknown = sorted(set(formats) - set(columns))
    if unknown:
        raise ValueError(f"record_table {name!r}: formats name columns {unknown} that are not among {columns}")
    specs = [formats.get(c) for c in columns]
    cells, values = [], []
    for i, row in enumerate(rows):
        row = list(row)
        if len(row) != len(columns):
            raise ValueError(f"record_table {name!r}: row {i} has {len(row)} cells for {len(columns)} columns {columns}")
        cells.append([_cell(v, spec) for v, spec in zip(row, specs)])
        values.append([_json_value(v) for v in row])
    record = {
        "name": name, "columns": columns, "rows": cells, "values": values, "note": str(note),
        "quick": os.environ.get("PRTLAB_QUICK", "0") == "1", "date": time.strftime("%Y-%m-%d"),
        "notebook": os.environ.get(NOTEBOOK_ENV) or None,
    }
    out(_markdown(record))
    folder = os.environ.get(TABLES_ENV)
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        with open(Path(folder) / f"{name}.json", "w", encoding="utf-8") as f:
            json.dump(record, f, indent=1)
    return record


def _markdown(record: dict) -> str:
    def line(cells):
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"

    lines = [line(record["columns"]), "|" + "---|" * len(record["columns"])]
    lines += [line(r) for r in record["rows"]]
    if record.get("note"):
        lines += ["", record["note"]]
    return "\n".join(lines)


def render_table(record: dict) -> str:
    """The Markdown of a recorded table: one line of provenance (mode, date, notebook), then the table."""
    source = f" by `notebooks/{record['notebook']}`" if record.get("notebook") else ""
    if record.get("quick"):
        mode = ("quick mode (`PRTLAB_QUICK=1`: reduced sizes and sample counts, what fits on the shared 2-core "
                "machine; a full-size run is `prtlab reproduce --write-docs`)")
        command = "prtlab reproduce --quick --write-docs"
    else:
        mode, command = "full size", "prtlab reproduce --write-docs"
    header = f"*Generated{source} on {record['date']} with `{command}`, {mode}.*"
    return header + "\n\n" + _markdown(record)


def _sections(text: str, path) -> list[tuple[str, int, int]]:
    """``(name, start, end)`` of every marked section: the text between its two markers."""
    sections, open_name, open_end, seen = [], None, 0, set()
    for m in _MARKER.finditer(text):
        kind, name = m.groups()
        line = text.count("\n", 0, m.start()) + 1
        if kind == "begin":
            if open_name is not None:
                raise ValueError(f"{path}:{line}: repro:begin {name} inside the open section {open_name!r}; "
                                 f"close it with <!-- repro:end {open_name} --> first")
            if name in seen:
                raise ValueError(f"{path}:{line}: section {name!r} is marked twice; give each table one section")
            open_name, open_end = name, m.end()
        else:
            if open_name != name:
                raise ValueError(f"{path}:{line}: repro:end {name} does not close "
                                 + (f"the open section {open_name!r}" if open_name else "an open section"))
            sections.append((name, open_end, m.start()))
            seen.add(name)
            open_name = None
    if open_name is not None:
        raise ValueError(f"{path}: section {open_name!r} has no <!-- repro:end {open_name} --> marker")
    return sections


def write_docs(path, tables) -> dict:
    """Replace each marked section of the Markdown file ``path`` with its recorded table.

    Parameters
    ----------
    path : path
        A Markdown file with sections ``<!-- repro:begin NAME -->`` ... ``<!-- repro:end NAME -->``.
    tables : path or iterable of paths
        A folder of ``NAME.json`` records (searched recursively) or the record files themselves.

    Returns
    -------
    dict
        ``written``: the sections replaced; ``missing``: marked sections without a record (left
        as they were); ``unused``: records without a section.
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    if isinstance(tables, (str, os.PathLike)):
        tables = sorted(Path(tables).rglob("*.json"))
    records = {}
    for file in tables:
        with open(file, encoding="utf-8") as f:
            record = json.load(f)
        records[record["name"]] = record
    pieces, last, written, missing = [], 0, [], []
    for name, start, end in _sections(text, path):
        if name not in records:
            missing.append(name)
            continue
        pieces += [text[last:start], "\n" + render_table(records[name]) + "\n"]
        last = end
        written.append(name)
    pieces.append(text[last:])
    path.write_text("".join(pieces), encoding="utf-8")
    marked = set(written) | set(missing)
    return {"written": written, "missing": missing, "unused": sorted(n for n in records if n not in marked)}


def _title(nb) -> str:
    for cell in nb.cells:
        if cell.cell_type == "markdown":
            for line in cell.source.splitlines():
                if line.startswith("#"):
                    return line.lstrip("#").strip()
    return "untitled notebook"


def _outputs_html(nb) -> str:
    """The figures (PNG/SVG) and printed text of an executed notebook, in order."""
    parts = []
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        for output in cell.get("outputs", []):
            data = output.get("data", {})
            if "image/png" in data:
                parts.append(f'<img src="data:image/png;base64,{data["image/png"]}">')
            elif "image/svg+xml" in data:
                parts.append(data["image/svg+xml"])
            elif output.get("output_type") == "stream" and output.get("name") == "stdout":
                parts.append(f"<pre>{html.escape(output['text'])}</pre>")
    return "\n".join(parts)


def _execute(path: Path, out_dir: Path, quick: bool, tables: Path | None = None) -> tuple[str, str, float, str | None]:
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    env_quick = os.environ.get("PRTLAB_QUICK")
    if quick:
        os.environ["PRTLAB_QUICK"] = "1"
    saved = {k: os.environ.get(k) for k in (TABLES_ENV, NOTEBOOK_ENV)}
    os.environ[NOTEBOOK_ENV] = path.name
    if tables is not None:
        os.environ[TABLES_ENV] = str(tables)
    else:
        os.environ.pop(TABLES_ENV, None)
    t0 = time.perf_counter()
    error = None
    try:
        NotebookClient(nb, timeout=1800, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}}).execute()
    except Exception as exc:  # report any notebook failure in the index, keep going
        error = f"{type(exc).__name__}: {exc}"
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        if quick:
            if env_quick is None:
                os.environ.pop("PRTLAB_QUICK", None)
            else:
                os.environ["PRTLAB_QUICK"] = env_quick
    seconds = time.perf_counter() - t0
    page = out_dir / f"{path.stem}.html"
    try:
        from nbconvert import HTMLExporter

        body, _ = HTMLExporter().from_notebook_node(nb)
        page.write_text(body)
    except ImportError:
        page.write_text(f"<html><body><h1>{html.escape(_title(nb))}</h1>{_outputs_html(nb)}</body></html>")
    return _title(nb), _outputs_html(nb), seconds, error


def reproduce(out_dir="report", quick: bool = False, only: str | None = None, out=print,
              write_docs_to=None) -> bool:
    """Execute every notebook and write ``out_dir/index.html``. Returns True if all succeeded.

    With ``write_docs_to`` (a Markdown file), the tables the notebooks record
    (:func:`record_table`) go to ``out_dir/tables/<notebook>/`` and replace the marked sections
    of that file (:func:`write_docs`); the tables of a notebook that failed are not written.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if write_docs_to is not None and not Path(write_docs_to).is_file():
        raise FileNotFoundError(f"--write-docs {write_docs_to}: no such file; give the Markdown file to update")
    notebooks = sorted(p for p in notebook_dir().glob("*.ipynb") if only is None or only in p.name)
    if not notebooks:
        raise FileNotFoundError(f"no notebooks found in {notebook_dir()} (filter: {only!r})")
    sections, ok, recorded = [], True, []
    for path in notebooks:
        out(f"running {path.name} ...")
        tables = None
        if write_docs_to is not None:
            tables = out_dir / "tables" / path.stem
            tables.mkdir(parents=True, exist_ok=True)
            for old in tables.glob("*.json"):  # only this run's tables
                old.unlink()
        title, body, seconds, error = _execute(path, out_dir, quick, tables)
        if tables is not None and error is None:
            recorded += sorted(tables.glob("*.json"))
        status = f"{seconds:.1f} s" if error is None else f'<span class="error">FAILED: {html.escape(error[:2000])}</span>'
        ok &= error is None
        out(f"  {title}: {'ok' if error is None else 'FAILED'} ({seconds:.1f} s)")
        sections.append(
            f'<section><h2>{html.escape(title)}</h2><p><a href="{path.stem}.html">full notebook</a> · '
            f"<code>{path.name}</code> · {status}</p>{body}</section>"
        )
    mode = "quick mode (PRTLAB_QUICK=1: reduced sizes)" if quick else "full size"
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>prtlab reproduction report</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;}} img{{max-width:100%;}}
section{{border-top:1px solid #ccc;margin-top:2em;}} .error{{color:#b00;}} pre{{background:#f6f6f6;padding:.5em;overflow-x:auto;}}</style>
</head><body><h1>prtlab reproduction report</h1>
<p>Generated {time.strftime('%Y-%m-%d %H:%M:%S')}, {mode}. Each section is one notebook of <code>notebooks/</code>;
see <code>docs/REPRODUCTION.md</code> for the paper's numbers next to ours.</p>
{''.join(sections)}</body></html>"""
    (out_dir / "index.html").write_text(page)
    out(f"wrote {out_dir / 'index.html'}")
    if write_docs_to is not None:
        done = write_docs(write_docs_to, recorded)
        out(f"wrote {len(done['written'])} tables into {write_docs_to}: {', '.join(done['written']) or 'none'}")
        if done["missing"]:
            out(f"  left as they were (no table recorded by this run): {', '.join(done['missing'])}")
        if done["unused"]:
            out(f"  recorded but not marked in {write_docs_to}: {', '.join(done['unused'])}")
    return ok


# --------------------------------------------------------------------------- command line


def add_arguments(parser) -> None:
    """The options of ``prtlab reproduce`` (also ``python -m prtlab.reproduce``)."""
    parser.add_argument("--quick", action="store_true", help="small sizes (PRTLAB_QUICK=1)")
    parser.add_argument("--out", type=Path, default=Path("report"), help="output folder (default report/)")
    parser.add_argument("--only", default=None, help="run only notebooks whose name contains this")
    parser.add_argument("--write-docs", nargs="?", const="", default=None, metavar="PATH",
                        help="replace the marked tables of PATH (default docs/REPRODUCTION.md) with this run's")


def run(args, out=print) -> int:
    """Run ``prtlab reproduce`` for parsed ``args``; the exit code."""
    docs = None
    if args.write_docs is not None:
        docs = Path(args.write_docs) if args.write_docs else default_docs_path()
    return 0 if reproduce(args.out, quick=args.quick, only=args.only, out=out, write_docs_to=docs) else 1


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m prtlab.reproduce",
                                     description="Run every notebook headless and gather their figures and tables.")
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
