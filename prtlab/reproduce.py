"""``prtlab reproduce``: execute the paper notebooks and gather their figures into one report.

The notebooks shipped in the package (``prtlab/notebooks/``, shown as
``notebooks/`` at the root of a clone) are the single source of every reproduced
figure and table (one per paper, plus the SH algebra and the ground truth).
This module executes each of them headless (``PRTLAB_QUICK=1`` in quick mode),
writes the executed notebook as a standalone HTML page, and writes
``index.html`` with, per notebook, its title, its figures and its printed
tables, linking to the full page. A notebook that fails is reported in the
index with its error, and makes the command exit non-zero.
"""

from __future__ import annotations

import html
import os
import time
from pathlib import Path

__all__ = ["reproduce", "notebook_dir"]


def notebook_dir() -> Path:
    """The folder of the paper notebooks: ``$PRTLAB_NOTEBOOKS`` if set, else the one shipped in the package."""
    env = os.environ.get("PRTLAB_NOTEBOOKS")
    folder = Path(env) if env else Path(__file__).resolve().parent / "notebooks"
    if not folder.is_dir():
        where = "PRTLAB_NOTEBOOKS names" if env else "the installed prtlab package has"
        raise FileNotFoundError(
            f"no notebook folder at {folder} ({where} none); set PRTLAB_NOTEBOOKS to a folder of "
            "*.ipynb files or reinstall prtlab"
        )
    return folder


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


def _execute(path: Path, out_dir: Path, quick: bool) -> tuple[str, str, float, str | None]:
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(path, as_version=4)
    env_quick = os.environ.get("PRTLAB_QUICK")
    if quick:
        os.environ["PRTLAB_QUICK"] = "1"
    t0 = time.perf_counter()
    error = None
    try:
        NotebookClient(nb, timeout=1800, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}}).execute()
    except Exception as exc:  # report any notebook failure in the index, keep going
        error = f"{type(exc).__name__}: {exc}"
    finally:
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


def reproduce(out_dir="report", quick: bool = False, only: str | None = None, out=print) -> bool:
    """Execute every notebook and write ``out_dir/index.html``. Returns True if all succeeded."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    notebooks = sorted(p for p in notebook_dir().glob("*.ipynb") if only is None or only in p.name)
    if not notebooks:
        raise FileNotFoundError(f"no notebooks found in {notebook_dir()} (filter: {only!r})")
    sections, ok = [], True
    for path in notebooks:
        out(f"running {path.name} ...")
        title, body, seconds, error = _execute(path, out_dir, quick)
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
    return ok
