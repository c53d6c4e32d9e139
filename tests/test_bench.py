"""The benchmark runner: report shape, peers, peak measured in the same run."""

import json
import subprocess
import sys
import textwrap

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
    assert {"cpu", "cores", "peak_gflops"} <= set(machine) and machine["peak_gflops"] > 0
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
