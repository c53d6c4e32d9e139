"""The documents: every Python block runs, nothing points outside the repository, every shipped scene loads.

A fenced block marked ``python`` in ``README.md`` or ``docs/*.md`` is executed as written (in a
temporary folder, ``PRTLAB_QUICK=1``, a temporary cache); a block that is not meant to run is
fenced as ``text`` or ``console``, so nothing is skipped silently.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import prtlab.data
from prtlab.scene import load_scene

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "prtlab" / "data" / "README.md"]
# written split so that this file does not match itself
FORBIDDEN = ("../" + "shared", "DESIGN" + ".md")
_FENCE = re.compile(r"^(\s*)```(.*)$")


def code_blocks(path: Path, language: str = "python") -> list[tuple[str, int]]:
    """``(code, first line number)`` of every fenced block of ``path`` marked ``language``."""
    blocks, lines, current, start = [], path.read_text(encoding="utf-8").splitlines(), None, 0
    for number, line in enumerate(lines, 1):
        match = _FENCE.match(line)
        if not match:
            if current is not None:
                current.append(line)
            continue
        if current is None:
            current, start, tag = [], number + 1, match.group(2).strip()
        else:
            if tag == language:
                blocks.append(("\n".join(current) + "\n", start))
            current = None
    if current is not None:
        raise ValueError(f"{path.name}: the code block opened at line {start - 1} is never closed")
    return blocks


def _python_blocks():
    return [pytest.param(doc, code, id=f"{doc.name}:{line}")
            for doc in DOCUMENTS for code, line in code_blocks(doc)]


def test_readme_has_a_python_block():
    assert code_blocks(ROOT / "README.md"), "README.md lost its Python example"


@pytest.mark.parametrize("doc, code", _python_blocks())
def test_python_block_runs(doc, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PRTLAB_QUICK", "1")
    monkeypatch.setenv("PRTLAB_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("MPLBACKEND", "Agg")
    exec(compile(code, f"{doc.name} (python block)", "exec"), {"__name__": "__main__"})


@pytest.mark.parametrize("doc", DOCUMENTS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_block_says_its_language(doc):
    """A bare fence would be neither run nor marked as not runnable."""
    opened, bare = False, []
    for number, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1):
        match = _FENCE.match(line)
        if match:
            if not opened and not match.group(2).strip():
                bare.append(number)
            opened = not opened
    assert not bare, f"{doc.name}: fenced blocks without a language (python, text, console, yaml) at lines {bare}"


@pytest.mark.parametrize("doc", DOCUMENTS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_links_stay_in_the_repository(doc):
    """Every relative Markdown link names a file or folder of the repository."""
    text = doc.read_text(encoding="utf-8")
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue
        path = (doc.parent / target.split("#")[0]).resolve()
        if not path.is_relative_to(ROOT.resolve()) or not path.exists():
            broken.append(target)
    assert not broken, f"{doc.name}: links to nothing in the repository: {broken}"


def _repository_files():
    folders = ("prtlab", "tests", "docs", "tools", ".ci")  # prtlab/ holds the notebooks and benchmarks
    files = [ROOT / name for name in ("README.md", "Makefile", "pyproject.toml")]
    for folder in folders:
        files += [p for p in (ROOT / folder).rglob("*") if p.is_file() and "__pycache__" not in p.parts
                  and p.suffix in (".py", ".md", ".ipynb", ".yaml", ".txt", ".toml", ".cfg", ".sh", "")]
    return files


def test_nothing_refers_outside_the_repository():
    found = []
    for path in _repository_files():
        for number, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if any(word in line for word in FORBIDDEN):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not found, "references to files outside the repository:\n" + "\n".join(found)


def test_no_document_names_a_scratch_path():
    """The documents (README, docs/ and its notes) name no file outside the repository by an absolute scratch path
    (a script a session left in ``/tmp`` is gone for every reader)."""
    found = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if re.search(r"(?<![\w.])/(tmp|work|root|home)/", line):
                found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not found, "scratch paths in the documents:\n" + "\n".join(found)

@pytest.mark.parametrize("name", prtlab.data.scenes())
def test_every_shipped_scene_loads(name):
    scene = load_scene(prtlab.data.scene_path(name))
    assert scene.objects and all(o.n_vertices > 0 for o in scene.objects)
    assert scene.lights


def test_prtlab_data_without_importing_it():
    """``import prtlab`` then ``prtlab.data.scenes()``, as README shows, in a fresh interpreter."""
    import subprocess
    import sys

    code = "import prtlab; print(len(prtlab.data.scenes()))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout) == len(prtlab.data.scenes())


def test_data_api_errors():
    with pytest.raises(FileNotFoundError, match=r"no shipped scene named 'no_such_scene'; available: .*cornell_box"):
        prtlab.data.scene_path("no_such_scene")
    with pytest.raises(TypeError, match="name must be a string"):
        prtlab.data.scene_path(3)
    with pytest.raises(FileNotFoundError, match=r"no shipped file 'meshes/teapot.ply'; meshes/ holds: .*bunny.ply"):
        prtlab.data.path("meshes", "teapot.ply")
    with pytest.raises(FileNotFoundError, match=r"no shipped file 'nothing/here'; the data folder holds: .*scenes/"):
        prtlab.data.path("nothing", "here")
    with pytest.raises(ValueError, match=r"'../cli.py' is outside the shipped data folder"):
        prtlab.data.path("..", "cli.py")
    with pytest.raises(TypeError, match="parts must be strings"):
        prtlab.data.path("scenes", 3)


def test_data_api_lists_what_ships():
    assert prtlab.data.scene_path("cornell_box") == prtlab.data.scene_path("cornell_box.yaml")
    assert prtlab.data.scene_path("cornell_box").is_file()
    assert {"bunny.ply", "cornell_box/floor.ply", "dragon_5k.ply"} <= set(prtlab.data.meshes())
    assert prtlab.data.envmaps() == ["courtyard.exr", "interior.exr", "sunset.exr"]
    for kind, names in (("meshes", prtlab.data.meshes()), ("envmaps", prtlab.data.envmaps())):
        assert all(prtlab.data.path(kind, n).is_file() for n in names)
    assert prtlab.data.path() == prtlab.data.root()
    assert set(prtlab.data.scenes()) == {p.stem for p in prtlab.data.path("scenes").glob("*.yaml")}


def _capabilities_tool():
    import importlib.util

    spec = importlib.util.spec_from_file_location("capabilities", ROOT / "tools" / "capabilities.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_capability_table_is_the_tools():
    """README's table was written by tools/capabilities.py from its current capability columns."""
    tool = _capabilities_tool()
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert tool.BEGIN in text and tool.END in text
    rows = [line for line in text.split(tool.BEGIN, 1)[1].split(tool.END, 1)[0].splitlines()
            if line.startswith("| ") and not line.startswith("| method")]
    assert [row.split(" | ")[0][2:] for row in rows] == list(tool.RUNS)
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split(" | ")]
        assert tuple(cells[1:6]) == tool.CAPABILITIES[cells[0]], f"README's row of {cells[0]} is stale: rerun the tool"


def test_capabilities_tool_errors(tmp_path, capsys):
    tool = _capabilities_tool()
    readme = tmp_path / "README.md"
    readme.write_text("# no table here\n")
    with pytest.raises(ValueError, match="the markers <!-- capabilities:begin --> and <!-- capabilities:end --> are "
                                         "missing"):
        tool.write_readme("| table |", readme)
    readme.write_text(f"before\n{tool.BEGIN}\nold\n{tool.END}\nafter\n")
    tool.write_readme("new", readme)
    assert readme.read_text() == f"before\n{tool.BEGIN}\nnew\n{tool.END}\nafter\n"
    with pytest.raises(SystemExit):
        tool.main(["--methods", "nothing"])
    assert "--methods: unknown method(s) ['nothing']; choose from reference, mitsuba" in capsys.readouterr().err


def test_fidelity_table_names_existing_tests():
    """docs/FIDELITY.md's generated table (tests/fidelity/conftest.py writes it) names tests that still exist."""
    text = (ROOT / "docs" / "FIDELITY.md").read_text(encoding="utf-8")
    begin, end = "<!-- fidelity:begin -->", "<!-- fidelity:end -->"
    assert text.count(begin) == 1 and text.count(end) == 1
    rows = [line for line in text.split(begin, 1)[1].split(end, 1)[0].splitlines()
            if line.startswith("| ") and not line.startswith("| test ")]
    for row in rows:
        module, _, test = row[2:].split(" | ", 1)[0].partition(": ")
        source = (ROOT / "tests" / "fidelity" / f"test_{module}.py").read_text(encoding="utf-8")
        assert f"def {test.split('[', 1)[0]}(" in source, f"docs/FIDELITY.md names a test that is gone: {row[:80]}"
