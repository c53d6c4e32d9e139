"""prtlab reproduce: notebooks executed headless, figures gathered into report/index.html."""

import nbformat
import pytest

from prtlab.reproduce import reproduce


def _write_notebook(path, code):
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_markdown_cell("# Toy figure\nA test notebook."), nbformat.v4.new_code_cell(code)]
    nbformat.write(nb, path)


@pytest.fixture
def notebook_folder(tmp_path, monkeypatch):
    folder = tmp_path / "nbs"
    folder.mkdir()
    monkeypatch.setenv("PRTLAB_NOTEBOOKS", str(folder))
    return folder


def test_report_gathers_outputs(notebook_folder, tmp_path):
    _write_notebook(notebook_folder / "00_toy.ipynb", "import os\nprint('quick =', os.environ.get('PRTLAB_QUICK'))")
    out = tmp_path / "report"
    assert reproduce(out, quick=True, out=lambda *a: None)
    index = (out / "index.html").read_text()
    assert "Toy figure" in index and "quick = 1" in index
    assert (out / "00_toy.html").exists()


def test_failing_notebook_is_reported(notebook_folder, tmp_path):
    _write_notebook(notebook_folder / "00_bad.ipynb", "raise RuntimeError('boom')")
    out = tmp_path / "report"
    assert not reproduce(out, quick=True, out=lambda *a: None)
    assert "FAILED" in (out / "index.html").read_text()


def test_no_notebooks_is_an_error(notebook_folder, tmp_path):
    with pytest.raises(FileNotFoundError, match="no notebooks found"):
        reproduce(tmp_path / "report", only="nothing")


# --------------------------------------------------------------------------- generated tables

import json  # noqa: E402
import re  # noqa: E402
from pathlib import Path  # noqa: E402

from prtlab.reproduce import (NOTEBOOK_ENV, TABLES_ENV, notebook_dir, record_table, render_table,  # noqa: E402
                              write_docs)

DOC = """# Title

Prose before, with a number 0.5 that stays.

<!-- repro:begin alpha -->
old alpha table
<!-- repro:end alpha -->

Prose between.

<!-- repro:begin beta -->
old beta table
<!-- repro:end beta -->

Prose after.
"""


@pytest.fixture
def tables_env(tmp_path, monkeypatch):
    folder = tmp_path / "tables"
    monkeypatch.setenv(TABLES_ENV, str(folder))
    monkeypatch.setenv(NOTEBOOK_ENV, "07_toy.ipynb")
    monkeypatch.setenv("PRTLAB_QUICK", "1")
    return folder


def test_record_table_prints_and_writes_json(tables_env):
    printed = []
    record = record_table("alpha", [("a|b", 0.123456, 3), ("c", float("nan"), None)], ["name", "err", "n"],
                          note="a note", formats={"err": ".2f"}, out=printed.append)
    stored = json.loads((tables_env / "alpha.json").read_text())
    assert stored == record
    assert stored["rows"] == [["a|b", "0.12", "3"], ["c", "n/a", "—"]]
    assert stored["values"] == [["a|b", 0.123456, 3], ["c", None, None]]
    assert stored["quick"] is True and stored["notebook"] == "07_toy.ipynb"
    assert printed == ["| name | err | n |\n|---|---|---|\n| a\\|b | 0.12 | 3 |\n| c | n/a | — |\n\na note"]


def test_record_table_without_folder_only_prints(tmp_path, monkeypatch):
    monkeypatch.delenv(TABLES_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    printed = []
    record_table("alpha", [(1,)], ["n"], out=printed.append)
    assert printed and not list(tmp_path.iterdir())


@pytest.mark.parametrize("kwargs, match", [
    (dict(name="Bad Name", rows=[], columns=["a"]), "table name 'Bad Name' must be lower-case"),
    (dict(name="t", rows=[(1, 2)], columns=["a"]), "row 0 has 2 cells for 1 columns"),
    (dict(name="t", rows=[(1,)], columns=["a"], formats={"b": ".2f"}), r"formats name columns \['b'\]"),
    (dict(name="t", rows=[([1],)], columns=["a"]), "a cell must be a string or a number, got list"),
])
def test_record_table_refuses(kwargs, match, tables_env):
    with pytest.raises((ValueError, TypeError), match=match):
        record_table(out=lambda *a: None, **kwargs)
    assert not tables_env.exists()


def _section(text, name):
    return re.search(rf"<!-- repro:begin {re.escape(name)} -->(.*?)<!-- repro:end {re.escape(name)} -->",
                     text, re.S).group(1)


def test_write_docs_replaces_only_marked_sections(tables_env, tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text(DOC)
    record_table("alpha", [("x", 1.5)], ["k", "v"], out=lambda *a: None)
    record_table("gamma", [("y", 2)], ["k", "v"], out=lambda *a: None)
    done = write_docs(doc, tables_env)
    assert done == {"written": ["alpha"], "missing": ["beta"], "unused": ["gamma"]}
    text = doc.read_text()
    record = json.loads((tables_env / "alpha.json").read_text())
    assert _section(text, "alpha") == "\n" + render_table(record) + "\n"  # the marked table is the writer's
    assert "| x | 1.5 |" in text and "old alpha table" not in text
    assert _section(text, "beta") == "\nold beta table\n"  # no record: left as it was
    # everything outside the markers is unchanged
    outside = re.sub(r"(<!-- repro:begin (\S+) -->).*?(<!-- repro:end \2 -->)", r"\1\3", text, flags=re.S)
    assert outside == re.sub(r"(<!-- repro:begin (\S+) -->).*?(<!-- repro:end \2 -->)", r"\1\3", DOC, flags=re.S)
    # writing again with the same record changes nothing
    write_docs(doc, tables_env)
    assert doc.read_text() == text


def test_rendered_header_says_mode_and_date(tables_env):
    record = record_table("alpha", [(1,)], ["n"], out=lambda *a: None)
    header = render_table(record).splitlines()[0]
    assert "quick mode" in header and record["date"] in header and "notebooks/07_toy.ipynb" in header
    assert "full size" in render_table(dict(record, quick=False)).splitlines()[0]


@pytest.mark.parametrize("text, match", [
    ("<!-- repro:begin a -->\n<!-- repro:begin b -->\n", r"doc.md:2: repro:begin b inside the open section 'a'"),
    ("<!-- repro:end a -->\n", r"doc.md:1: repro:end a does not close an open section"),
    ("<!-- repro:begin a -->\n", r"section 'a' has no <!-- repro:end a --> marker"),
    ("<!-- repro:begin a -->\n<!-- repro:end a -->\n<!-- repro:begin a -->\n<!-- repro:end a -->\n",
     r"doc.md:3: section 'a' is marked twice"),
])
def test_write_docs_refuses_bad_markers(text, match, tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text(text)
    with pytest.raises(ValueError, match=match):
        write_docs(doc, [])
    assert doc.read_text() == text


def test_reproduce_writes_docs_from_the_notebooks_tables(notebook_folder, tmp_path):
    _write_notebook(notebook_folder / "00_alpha.ipynb",
                    "from prtlab.reproduce import record_table\nrecord_table('alpha', [('x', 0.25)], ['k', 'v'])")
    _write_notebook(notebook_folder / "01_beta.ipynb",
                    "from prtlab.reproduce import record_table\nrecord_table('beta', [('y', 1)], ['k', 'v'])\n"
                    "raise RuntimeError('after the table')")
    doc = tmp_path / "doc.md"
    doc.write_text(DOC)
    out = tmp_path / "report"
    assert not reproduce(out, quick=True, out=lambda *a: None, write_docs_to=doc)
    text = doc.read_text()
    record = json.loads((out / "tables" / "00_alpha" / "alpha.json").read_text())
    assert record["notebook"] == "00_alpha.ipynb" and record["quick"] is True
    assert _section(text, "alpha") == "\n" + render_table(record) + "\n"
    assert _section(text, "beta") == "\nold beta table\n"  # its notebook failed: its table is not written


def test_reproduce_refuses_a_missing_docs_file(notebook_folder, tmp_path):
    with pytest.raises(FileNotFoundError, match=r"--write-docs .*nope.md: no such file"):
        reproduce(tmp_path / "report", write_docs_to=tmp_path / "nope.md")


def test_shipped_docs_sections_are_recorded_by_a_notebook():
    """Every marked section of docs/REPRODUCTION.md names a table that a shipped notebook records."""
    doc = Path(__file__).resolve().parent.parent / "docs" / "REPRODUCTION.md"
    names = re.findall(r"<!-- repro:begin (\S+) -->", doc.read_text())
    sources = "".join(p.read_text() for p in notebook_dir().glob("*.ipynb"))
    recorded = set(re.findall(r'record_table\(\\"([a-z0-9_.-]+)\\"', sources))
    assert names and sorted(set(names) - recorded) == []


def test_command_line_write_docs(notebook_folder, tmp_path):
    from prtlab.reproduce import main

    _write_notebook(notebook_folder / "00_alpha.ipynb",
                    "from prtlab.reproduce import record_table\nrecord_table('alpha', [('x', 0.25)], ['k', 'v'])")
    doc = tmp_path / "doc.md"
    doc.write_text(DOC)
    assert main(["--quick", "--out", str(tmp_path / "report"), "--write-docs", str(doc)]) == 0
    assert "| x | 0.25 |" in _section(doc.read_text(), "alpha")


def test_default_docs_path(monkeypatch, tmp_path):
    import prtlab.reproduce as module

    assert module.default_docs_path() == Path(__file__).resolve().parent.parent / "docs" / "REPRODUCTION.md"
    monkeypatch.setattr("prtlab._shipped._PACKAGE", tmp_path / "site" / "prtlab")
    with pytest.raises(FileNotFoundError, match=r"--write-docs: no .*REPRODUCTION.md .*give the Markdown file"):
        module.default_docs_path()
