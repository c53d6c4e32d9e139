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
