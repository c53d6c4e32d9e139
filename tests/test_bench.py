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


def test_write_docs_keeps_the_rows_a_selection_did_not_run(tmp_path):
    """A selection's table heads its section; the earlier rows it did not repeat stay below with their own run
    line, and a row of a case no longer registered goes."""
    old_run = "Run of 2000-01-01 00:00 UTC, an earlier run."
    head = "\n".join(bench._TABLE_HEAD)
    doc = tmp_path / "BENCH.md"
    doc.write_text(f"<!-- bench:begin toy -->\n{head}\n| `toy.a` | 1 ms |\n| `toy.b` | 2 ms |\n| `toy.gone` | 3 ms |\n\n"
                   f"{old_run}\n<!-- bench:end toy -->\n")
    report = {"machine": {"cpu": "cpu", "cores": 2, "threads": 2, "peak_gflops": 1.0, "numpy": "x", "python": "y"},
              "quick": True, "started": "2001-01-01 00:00 UTC", "load_at_start": None,
              "registered": ["toy.a", "toy.b"], "cases": [{"name": "toy.a", "seconds_median": 0.5}]}
    assert bench.write_docs(report, doc) == ["toy"]
    body = bench.doc_sections(doc.read_text())["toy"]
    new, earlier = body.split("\n\n| case", 1)[0], body.split(bench._run_line(report), 1)[1]
    assert "`toy.a` | 500 ms" in new and "`toy.b`" not in new
    assert earlier == f"\n\n{head}\n| `toy.b` | 2 ms |\n\n{old_run}\n"
    assert "toy.gone" not in body
    # run again: the kept block stays once, the new table is replaced
    bench.write_docs(report, doc)
    assert bench.doc_sections(doc.read_text())["toy"] == body


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


# --------------------------------------------------------------------------- floors


def _bench_module(name):
    bench._discover()
    return sys.modules[f"prtlab_benchmarks.{name}"]


def test_floor_of_a_dense_matvec_reaches_the_report(tmp_path, monkeypatch):
    """A case's floor (a dense matvec n x m: 2 n m flops, 8 (n m + n + m) bytes) reaches the JSON with its shares of
    the peak, of the bandwidth and of the roofline, computed from the run's own peak and triad bandwidth; the
    table shows the floor's columns and the stored size."""
    (tmp_path / "bench_matvec.py").write_text(textwrap.dedent(
        """
        import numpy as np
        from prtlab.bench import case, floor

        @case("toy.matvec")
        def matvec(quick):
            n, m = 300, 200
            a, x = np.ones((n, m)), np.ones(m)
            return {"run": lambda: a @ x, "floor": floor(2 * n * m, 8 * (n * m + n + m), "2 n m; 8 (n m + n + m)"),
                    "stored_bytes": a.nbytes}
        """))
    monkeypatch.setenv("PRTLAB_BENCHMARKS", str(tmp_path))
    out = tmp_path / "bench.json"
    report = bench.run_benchmarks(quick=True, select="toy.matvec", json_path=out, out=lambda *a: None)
    assert json.loads(out.read_text()) == report
    machine = report["machine"]
    assert machine["bandwidth_gbs"] > 0 and machine["peak_gflops"] > 0
    (entry,) = report["cases"]
    f, t = entry["floor"], entry["seconds_median"]
    assert f["gflop"] == 2 * 300 * 200 / 1e9 and f["bytes"] == 8 * (300 * 200 + 300 + 200)
    assert f["formula"] == "2 n m; 8 (n m + n + m)"
    assert f["share_of_peak"] == pytest.approx(f["gflop"] / t / machine["peak_gflops"], rel=1e-12)
    assert f["share_of_bandwidth"] == pytest.approx(f["bytes"] / 1e9 / t / machine["bandwidth_gbs"], rel=1e-12)
    assert f["share_of_roofline"] == pytest.approx(max(f["share_of_peak"], f["share_of_bandwidth"]), rel=1e-12)
    assert entry["stored_bytes"] == 300 * 200 * 8
    table = bench.render_section(report, "toy")
    assert "floor: GFLOP, MB" in table and "| 0.00012, 0.484 |" in table and "| 0.48 MB |" in table
    assert "GB/s (STREAM triad)" in bench.render_section(report, "machine")


def test_floor_shares_are_the_roofline():
    """1 GFLOP and 2 GB in 1 s on a 10 GFLOP/s, 4 GB/s machine: 10% of peak, 50% of bandwidth, 50% of roofline;
    a floor without bytes has no bandwidth share."""
    shares = bench.floor_shares({"gflop": 1.0, "bytes": 2e9}, 1.0, 10.0, 4.0)
    assert shares == pytest.approx({"share_of_peak": 0.1, "share_of_bandwidth": 0.5, "share_of_roofline": 0.5})
    assert bench.floor_shares({"gflop": 1.0}, 0.5, 10.0, 4.0) == pytest.approx(
        {"share_of_peak": 0.2, "share_of_roofline": 0.2})


@pytest.mark.parametrize("kwargs, match", [({}, "floor needs flop or nbytes"),
                                           ({"flop": -1.0}, "floor flop must be a finite number >= 0"),
                                           ({"nbytes": float("nan")}, "floor nbytes must be a finite number >= 0"),
                                           ({"flop": True}, "floor flop must be a finite number >= 0")])
def test_bad_floor_is_an_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        bench.floor(**kwargs)


def _tiny_sparse():
    """Two vertices of a 2 x 2 cube (T = 24 texels): 3 and 1 stored entries."""
    from prtlab.wavelet import encode_transfer

    transfer = np.zeros((2, 6, 2, 2))
    transfer[0, 0, 0, 0], transfer[0, 1, 1, 1], transfer[0, 3, 0, 1] = 0.5, 0.25, 0.125
    transfer[1, 2, 1, 0] = 1.0
    return encode_transfer(transfer)


def test_portals_floors_by_hand():
    """Direct pass: 6 flops an entry and 6 a vertex, the stored bytes + 48 V + 2 T 3 8; indirect: 2 V n^2 3 flops,
    V n^2 3 4 + 24 V bytes (float32 transfer); glossy: by hand for two vertices blending two rows each."""
    module = _bench_module("bench_portals")
    sparse = _tiny_sparse()
    e = len(sparse.codes)
    assert e == 4
    flop, nbytes = module._direct_floor(sparse, 2)
    assert flop == 6 * 4 + 6 * 2 and nbytes == sparse.nbytes + 48 * 2 + 2 * 24 * 3 * 8
    flop, nbytes = module._indirect_floor(np.zeros((5, 4, 3), np.float32))
    assert flop == 2 * 5 * 4 * 3 and nbytes == 5 * 4 * 3 * 4 + 24 * 5
    rows = np.array([[0, 1], [1, 1]])  # entries 3 + 1, 1 + 1: 6 read
    matrix = np.zeros((2, 4, 4, 3), np.float32)
    flop, nbytes = module._glossy_floor(sparse, rows, matrix)
    assert flop == 6 * 6 + 6 * 4 + 2 * 2 * 16 * 3 + 6 * 4 * 2
    per_entry = sparse.codes.itemsize + sparse.indices.itemsize
    per_row = 2 * sparse.indptr.itemsize + sparse.scale.itemsize + sparse.basis.itemsize
    assert nbytes == 6 * per_entry + 4 * per_row + matrix.nbytes + 16 * 4 + 72 * 2


def _tiny_interreflection(self_interreflection=True):
    """Two objects (a: 10 vertices, K 1, N 2 at 4 samples; b: 6 vertices, K 2, N 3 at 5 samples), order 2, no
    frame run yet (M from the sizes), b's field reaching 4 of a's points, a's field 2 of b's."""
    from types import SimpleNamespace as NS

    objects = [NS(name="a", n_vertices=10), NS(name="b", n_vertices=6)]
    seps = {"a": NS(K=1), "b": NS(K=2)}
    bases = {"a": NS(n_basis=2, samples=np.arange(4)), "b": NS(n_basis=3, samples=np.arange(5))}
    xa = np.zeros((10, 3))
    xa[4:] = 10.0
    xb = np.zeros((6, 3))
    xb[2:] = 10.0
    geometry = {"a": (None, {"x": xa, "center": np.zeros(3), "reach": 1.0}),
                "b": (None, {"x": xb, "center": np.zeros(3), "reach": 1.0})}
    return NS(objects=objects, seps=seps, bases=bases,
              options=NS(order=2, self_interreflection=self_interreflection),
              reuse=NS(stacked={}, geometry=geometry))


def test_interreflection_floors_by_hand():
    """A relighting frame and a pose change counted by hand on two tiny objects (order 2: n^2 = 4)."""
    module = _bench_module("bench_interreflection")
    pre = _tiny_interreflection()
    # M: a's sources b (K N = 6) and a itself (2): 8; b's: a (2) and b (6): 8
    flop, nbytes = module.frame_floor(pre, bounces=3, lights=2)
    flop_a = 2 * 10 * 1 * 4 * 3 * 2 + 3 * (2 * 10 * 1 * 8 * 3 + 2 * 2 * 4 * 1 * 3) + 4 * 2 * 10 * 1 * 3
    flop_b = 2 * 6 * 2 * 4 * 3 * 2 + 3 * (2 * 6 * 2 * 8 * 3 + 2 * 3 * 5 * 2 * 3) + 4 * 2 * 6 * 2 * 3
    assert flop == flop_a + flop_b
    assert nbytes == (10 * 4 + 3 * 10 * 8) * 8 + 80 + 720 + (12 * 4 + 3 * 12 * 8) * 8 + 96 + 432
    # with a's residual gather: 2 segments of starts over its 10 points, 5 + 2 terms used (of 9 stored: the rest
    # room), uint16 rows and float32 weights, 4 residual rows named
    from types import SimpleNamespace as NS

    starts = np.zeros((2, 11), np.int64)
    starts[0, 1:], starts[1] = 5, np.r_[6, np.full(10, 8)]
    packed = NS(arrays=lambda: (starts, np.zeros((9, 3), np.uint16), np.zeros((9, 3), np.float32), np.arange(4)))
    pre.reuse.residual_hits = {"a": {"packed": packed}}
    flop_g, nbytes_g = module.frame_floor(pre, bounces=3, lights=2)
    assert flop_g == flop + 3 * 18 * 7
    assert nbytes_g == nbytes + 3 * (7 * 18 + 2 * 11 * 8 + 4 * 32)
    # b moves: a's 4 points in b's reach look b up and redo their transfer; b's 2 points in a's reach look a up,
    # all of b's transfers redone; pairs (a, b) and (b, a) recomputed at every vertex (no third occluder)
    p = module._product_flop(2)
    flop, nbytes = module.pose_floor(pre, "b")
    lookups = 4 * (16 * 4 + p + 1 * p) + 2 * (16 * 4 + p) + 6 * 2 * p
    # Eq. 13 a point and basis function: min(interpolate then contract n^2 (16 + 2 K'), contract at the 8 corners
    # then interpolate K' (16 n^2 + 16)): K' = 1: min(72, 80); K' = 2: min(80, 160)
    assert (module.eq13_flop(1, 4), module.eq13_flop(2, 4), module.eq13_flop(1, 16)) == (72, 80, 272)
    pair_ab = 10 * 6 * 72 + 10 * 1 * p
    pair_ba = 6 * 2 * 80 + 6 * 2 * p
    assert flop == lookups + pair_ab + pair_ba
    assert nbytes == 8 * 10 * 1 * 6 + 8 * 6 * 2 * 2


def test_spherelights_floor_by_hand():
    """Two receivers (normals up) and two lights: one above both receivers' horizons (live twice), one below both
    (culled): the shadows-only floor is 2 (2 31 3 n^2 + 3 n^2 + 6 n^2) + 4 n^2 2 flops (OL), 192 bytes."""
    module = _bench_module("bench_spherelights")
    n2 = 16
    a = {"points": np.array([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]]), "normals": np.array([[0.0, 1.0, 0.0]] * 2),
         "centres": np.array([[0.0, 2.0, 0.0], [50.0, -2.0, 0.0]]), "radii": np.array([0.5, 0.5]),
         "sl_object": np.array([0, 1]), "inter": np.zeros((2, 2), bool)}
    from prtlab.spherelights import accumulate_blockers

    theta = accumulate_blockers(a["points"], a["normals"], a["centres"], a["radii"], a["sl_object"], a["inter"], 4,
                                blocking="object")[2]
    assert (theta >= 0).tolist() == [[True, False], [True, False]]
    flop, nbytes = module.frame_floor(a, "object", indirect=False, exp_method="ol")
    assert flop == 2 * (2 * 31 * 3 * n2 + 3 * n2 + 6 * n2) + 4 * n2 * 2 and nbytes == 192


def test_spherelights_frame_floors_are_below_the_counted_work():
    """Every spherelights frame case carries a floor, at most the work its kernels are counted to do (``gflop``:
    every lane of a block, culled pairs included) and at least a tenth of it."""
    module = _bench_module("bench_spherelights")
    names = [n for n in bench._CASES if n.startswith("spherelights.frame.")]
    assert len(names) >= 4
    for name in names:
        spec = bench._CASES[name](True)
        assert 0.1 * spec["gflop"] <= spec["floor"]["gflop"] <= spec["gflop"], name
        assert spec["floor"]["bytes"] == 96 * module._n(True) and spec["floor"]["formula"] == module.FLOOR_FORMULA


def test_long_times_read_in_minutes():
    assert bench._ms(1486.87) == "24.8 min" and bench._ms(0.0624) == "62.4 ms" and bench._ms(0.167) == "167 ms"
