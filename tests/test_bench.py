"""The benchmark runner: report shape, peers, peak measured in the same run, threads, fresh state per repeat,
the generated tables of docs/BENCHMARKS.md."""

import json
import re
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from prtlab import bench


@pytest.fixture
def bench_folder(tmp_path, monkeypatch):
    (tmp_path / "bench_toy.py").write_text(
        textwrap.dedent(
            """
            import numpy as np
            from prtlab.bench import case

            @case("toy.matmul")
            def toy(quick):
                a = np.ones((64, 64))
                return {"run": lambda: a @ a, "gflop": 2 * 64**3 / 1e9, "items": 64,
                        "peer": ("einsum", lambda: np.einsum("ij,jk->ik", a, a))}
            """
        )
    )
    monkeypatch.setenv("PRTLAB_BENCHMARKS", str(tmp_path))
    return tmp_path


def test_report_has_design_shape(bench_folder, tmp_path):
    out = tmp_path / "bench.json"
    report = bench.run_benchmarks(quick=True, select="toy", json_path=out, out=lambda *a: None)
    assert json.loads(out.read_text()) == report
    machine = report["machine"]
    assert {"cpu", "cores", "threads", "peak_gflops"} <= set(machine) and machine["peak_gflops"] > 0
    assert report["quick"] is True and re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC", report["started"])
    assert len(report["load_at_start"]) == 3
    (entry,) = report["cases"]
    assert entry["name"] == "toy.matmul" and entry["seconds_median"] > 0
    assert entry["peer"]["name"] == "einsum" and entry["peer"]["seconds_median"] > 0
    assert 0 < entry["share_of_peak"]
    assert entry["items_per_second"] > 0


def test_unknown_selection_is_an_error(bench_folder):
    with pytest.raises(ValueError, match="no benchmark case matches 'nothing-like-this'"):
        bench.run_benchmarks(quick=True, select="nothing-like-this", out=lambda *a: None)


def test_missing_folder_is_an_error(tmp_path, monkeypatch):
    monkeypatch.setenv("PRTLAB_BENCHMARKS", str(tmp_path / "absent"))
    with pytest.raises(FileNotFoundError, match="no benchmark folder"):
        bench.benchmark_dir()


def test_cli_bench_writes_json(bench_folder, tmp_path):
    out = tmp_path / "cli.json"
    proc = subprocess.run(
        [sys.executable, "-m", "prtlab.cli", "bench", "--quick", "--select", "toy", "--json", str(out)],
        capture_output=True, text=True,
    )
    assert proc.returncode == 0, proc.stderr
    assert json.loads(out.read_text())["cases"][0]["name"] == "toy.matmul"


def test_repeats_and_info_are_kept(tmp_path, monkeypatch):
    """A long case may ask for fewer repeats (never more) and no warm-up, and its ``info`` figures reach the
    report."""
    (tmp_path / "bench_slow.py").write_text(textwrap.dedent(
        """
        from prtlab.bench import case
        CALLS = []

        @case("toy.precompute")
        def slow(quick):
            return {"run": lambda: CALLS.append(1), "repeats": 1, "warmup": False,
                    "info": {"bytes": 1234, "seconds_first": 0.5}}
        """))
    monkeypatch.setenv("PRTLAB_BENCHMARKS", str(tmp_path))
    lines = []
    report = bench.run_benchmarks(quick=True, select="toy.precompute", out=lines.append)
    (entry,) = report["cases"]
    assert entry["info"] == {"bytes": 1234, "seconds_first": 0.5}
    assert "bytes=1234" in lines[1] and "seconds_first=0.5" in lines[1]
    assert len(sys.modules["prtlab_benchmarks.bench_slow"].CALLS) == 1  # no warm-up, 1 repeat


def test_setup_runs_before_every_call_outside_the_timer(tmp_path, monkeypatch):
    """``setup`` runs before the warm-up and every repeat of ours and of the peer (interleaved), and its time is not
    counted."""
    (tmp_path / "bench_fresh.py").write_text(textwrap.dedent(
        """
        import time
        from prtlab.bench import case
        LOG = []

        @case("toy.fresh")
        def fresh(quick):
            def setup():
                time.sleep(0.2)
                LOG.append("setup")
            return {"run": lambda: LOG.append("run"), "setup": setup,
                    "peer": ("same", lambda: LOG.append("peer"))}
        """))
    monkeypatch.setenv("PRTLAB_BENCHMARKS", str(tmp_path))
    report = bench.run_benchmarks(quick=True, select="toy.fresh", out=lambda *a: None)
    (entry,) = report["cases"]
    log = sys.modules["prtlab_benchmarks.bench_fresh"].LOG
    assert log == ["setup", "run", "setup", "peer"] * 4  # warm-up + 3 repeats each
    assert entry["seconds_median"] < 0.1 and entry["peer"]["seconds_median"] < 0.1


def test_ours_and_peer_run_with_the_same_threads(tmp_path, monkeypatch):
    """BLAS and numba are limited to ``threads`` for ours and the peer alike, and restored afterwards."""
    numba = pytest.importorskip("numba")
    (tmp_path / "bench_threads.py").write_text(textwrap.dedent(
        """
        import numba
        from threadpoolctl import threadpool_info
        from prtlab.bench import case
        SEEN = []

        def look():
            SEEN.append((numba.get_num_threads(), max(p["num_threads"] for p in threadpool_info())))

        @case("toy.threads")
        def threads(quick):
            return {"run": look, "peer": ("look", look)}
        """))
    monkeypatch.setenv("PRTLAB_BENCHMARKS", str(tmp_path))
    before = numba.get_num_threads()
    report = bench.run_benchmarks(quick=True, select="toy.threads", out=lambda *a: None, threads=1)
    assert report["machine"]["threads"] == 1
    assert set(sys.modules["prtlab_benchmarks.bench_threads"].SEEN) == {(1, 1)}
    assert numba.get_num_threads() == before


@pytest.mark.parametrize("threads", [0, 1.0, True])
def test_bad_thread_count_is_an_error(bench_folder, threads):
    with pytest.raises(ValueError, match=r"threads must be an int >= 1, got"):
        bench.run_benchmarks(quick=True, select="toy", out=lambda *a: None, threads=threads)


def test_transfer_csr_is_the_sparse_dot():
    """The CSR peer of the 8-bit transfer (pulse and Haar vertices) gives ``SparseTransfer.dot``."""
    from prtlab.wavelet import encode_transfer, haar2d

    rng = np.random.default_rng(0)
    transfer = np.where(rng.random((12, 6, 4, 4)) < 0.3, rng.normal(size=(12, 6, 4, 4)), 0.0)
    transfer[:4] = rng.normal(size=(4, 6, 4, 4))  # dense rows: stored in the Haar basis
    sparse = encode_transfer(transfer)
    assert set(sparse.basis) == {sparse.PULSE, sparse.HAAR}
    light = rng.random((6, 4, 4, 3))
    stacked = np.concatenate([light.reshape(-1, 3), haar2d(light, channels=True).reshape(-1, 3)])
    np.testing.assert_allclose(bench.transfer_csr(sparse) @ stacked, sparse.dot(light), rtol=1e-12, atol=1e-14)


def test_check_same_work_refuses_a_peer_that_differs():
    bench.check_same_work(np.ones(3), np.ones(3), "toy")
    with pytest.raises(RuntimeError, match=r"benchmark toy: the peer's result differs from ours"):
        bench.check_same_work(np.ones(3), np.full(3, 2.0), "toy")
    with pytest.raises(RuntimeError, match=r"shapes \(3,\) / \(2,\)"):
        bench.check_same_work(np.ones(3), np.ones(2), "toy")


DOC = """# Title

Prose that stays, with its own words.

<!-- bench:begin machine -->
old header
<!-- bench:end machine -->

Between the tables.

<!-- bench:begin toy -->
| old | table |
<!-- bench:end toy -->

<!-- bench:begin other -->
a section no case of this run belongs to
<!-- bench:end other -->

Closing prose.
"""


def _prose(text):
    return re.sub(r"<!-- bench:begin (\S+) -->\n.*?<!-- bench:end \1 -->", "<\\1>", text, flags=re.S)


def test_write_docs_fills_the_marked_sections_only(bench_folder, tmp_path):
    """A tiny selection run from the command line writes its sections; the prose and the sections the run has no
    case for stay; each written table is what the writer makes of the JSON results."""
    doc, out = tmp_path / "BENCH.md", tmp_path / "bench.json"
    doc.write_text(DOC)
    proc = subprocess.run(
        [sys.executable, "-m", "prtlab.bench", "--quick", "--select", "toy", "--json", str(out), "--write-docs",
         str(doc)], capture_output=True, text=True,
    )
    assert proc.returncode == 0, proc.stderr
    text = doc.read_text()
    assert _prose(text) == _prose(DOC)
    sections = bench.doc_sections(text)
    assert sections["other"] == bench.doc_sections(DOC)["other"]
    report = json.loads(out.read_text())
    assert sections["toy"] == bench.render_section(report, "toy")
    assert sections["machine"] == bench.render_section(report, "machine")
    assert "`toy.matmul`" in sections["toy"] and "| einsum |" in sections["toy"]
    assert report["started"] in sections["toy"] and "quick sizes" in sections["toy"]


def test_write_docs_errors(tmp_path):
    report = {"cases": []}
    with pytest.raises(FileNotFoundError, match=r"--write-docs .*absent.md: no such file"):
        bench.write_docs(report, tmp_path / "absent.md")
    plain = tmp_path / "plain.md"
    plain.write_text("# no markers\n")
    with pytest.raises(ValueError, match=r"--write-docs .*plain.md: no <!-- bench:begin NAME -->"):
        bench.write_docs(report, plain)


def test_benchmarks_doc_has_no_hand_written_numbers():
    """docs/BENCHMARKS.md: every number is inside a generated section (code spans and names such as float64
    aside)."""
    text = bench.default_docs_path().read_text()
    sections = bench.doc_sections(text)
    assert {"machine", "sh", "wavelet", "portals", "interreflection", "spherelights"} <= set(sections)
    prose = re.sub(r"`[^`]*`", "", _prose(text))
    assert re.findall(r"(?<![\w.^-])\d[\d.,]*(?![\w])", prose) == []
