"""Benchmarks of prtlab.portals: one relighting frame of the window box at the paper's size (about 45k
vertices, Table 1: 70 fps), per pass and whole, and the memory of the 8-bit direct transfer.

Two frames: ``portals.frame.default_surface.45k`` is the default (``indirect="auto"``, which is ``"surface"`` for
this diffuse box: ``cube_resolution`` 64, 1,024 clusters; issue 17's goal: 14 ms on 2 cores); ``portals.frame.45k``
is the paper's mode (``PAPER_OPTIONS``, ``cube_resolution`` 32, order-4 SH; issue 20: at most 5 ms).

The transfer of the box scene (``data/scenes/box_window_sky.yaml``, 2,058 vertices) is precomputed with small
sample counts and its vertices are repeated to the paper's 44,763 (the per-frame cost depends on the vertex
count and on the stored entries per vertex, not on where the vertices are). Peers: the 8-bit direct transfer
decoded once (outside the timer) into a scipy.sparse CSR float64 matrix times the light's pulse and Haar
coefficients, and a numpy ``einsum`` of the stored float32 indirect transfer with the light's SH.
"""

from __future__ import annotations

import os
import time
from functools import lru_cache

import numpy as np

import prtlab.data
from prtlab.bench import case, check_same_work, floor, transfer_csr
from prtlab.wavelet import haar2d
from prtlab.portals import PAPER_OPTIONS, Portals, direct_pass, indirect_pass, shell_light, shell_sh
from prtlab.portals._surface import SurfaceTransfer, shade_surface
from prtlab.scene import load_scene
from prtlab.wavelet import SparseTransfer

PAPER_VERTICES = 44_763
SCENE = prtlab.data.scene_path("box_window_sky")


def _tile(sparse: SparseTransfer, n: int) -> SparseTransfer:
    reps = -(-n // sparse.n_vertices)
    counts = np.tile(np.diff(sparse.indptr), reps)[:n]
    indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    e = int(indptr[-1])
    return SparseTransfer(indptr, np.tile(sparse.indices, reps)[:e], np.tile(sparse.codes, reps)[:e],
                          np.tile(sparse.scale, reps)[:n], np.tile(sparse.basis, reps)[:n], sparse.res)


@lru_cache(maxsize=1)
def _frame_data():
    scene = load_scene(SCENE)
    pre = Portals.precompute(scene, {"direct_samples": 256, "n_photons": 50_000, "gather_rays": 32, "order": 4,
                                     "cube_resolution": 32, **PAPER_OPTIONS}, progress=False)
    reps = -(-PAPER_VERTICES // len(pre.data["albedo"]))
    sparse = _tile(pre.direct_transfer(0), PAPER_VERTICES)
    transfer = np.ascontiguousarray(np.tile(pre.indirect_transfer(0), (reps, 1, 1))[:PAPER_VERTICES])
    albedo = np.tile(pre.data["albedo"], (reps, 1))[:PAPER_VERTICES]
    return scene, sparse, transfer, albedo


@lru_cache(maxsize=1)
def _direct_csr():
    return transfer_csr(_frame_data()[1])


def _csr_direct(csr, albedo, cube):
    """The direct pass as a user would write it with scipy: CSR (decoded once) @ [pulse; Haar] light, albedo."""
    light = np.concatenate([cube.reshape(-1, 3), haar2d(cube, channels=True).reshape(-1, 3)])
    return (csr @ light) * albedo


def _einsum_indirect(transfer, c):
    """The indirect pass with numpy: ``t_v . c`` per channel from the stored float32 transfer."""
    return np.einsum("vic,ic->vc", transfer, c)


# Floors (``prtlab.bench.floor``): V vertices, E stored 8-bit entries, T = 6 r^2 texels of the shell cube, n^2 SH
# coefficients, 3 colours, float64 outputs. Direct pass: 2 x 3 flops an entry (the 8-bit code times the light, per
# colour; the vertex's scale and albedo folded in once: 2 x 3 V), bytes: the stored transfer read once
# (``SparseTransfer.nbytes``), albedo read and radiance written (2 x 24 V), the light (2 T x 3 x 8: pulse and
# Haar). Indirect pass: 2 x 3 n^2 V flops, bytes: the stored transfer (V n^2 3 x its itemsize) and 24 V written.


def _direct_floor(sparse, res: int) -> tuple[float, float]:
    """(flop, bytes) of the direct pass's floor."""
    v, e, t = sparse.n_vertices, len(sparse.codes), 6 * res * res
    return 6.0 * e + 6.0 * v, sparse.nbytes + 48.0 * v + 2 * t * 3 * 8


def _indirect_floor(transfer) -> tuple[float, float]:
    """(flop, bytes) of the indirect pass's floor: ``transfer`` (V, n^2, 3)."""
    return 2.0 * transfer.size, transfer.nbytes + 24.0 * transfer.shape[0]


DIRECT_FORMULA = "6 E + 6 V flops; SparseTransfer.nbytes + 48 V + 144 T bytes"
INDIRECT_FORMULA = "6 n^2 V flops; V n^2 3 itemsize + 24 V bytes"


@case("portals.frame.45k")
def frame(quick: bool) -> dict:
    """The paper's mode (``prtlab.portals.PAPER_OPTIONS``, ``cube_resolution=32``, order 4): not the default frame."""
    scene, sparse, transfer, albedo = _frame_data()
    env = scene.environment
    csr = _direct_csr()

    def run():
        cube = shell_light(env, 32)
        return direct_pass(sparse, albedo, cube) + indirect_pass(transfer, shell_sh(cube, 4))

    def peer():
        cube = shell_light(env, 32)
        return _csr_direct(csr, albedo, cube) + _einsum_indirect(transfer, shell_sh(cube, 4))

    check_same_work(run(), peer(), "portals.frame", rtol=1e-6)
    entries = len(sparse.codes)
    # floor: both passes with one radiance written (24 V less), and the light's SH (2 T n^2 3 flops)
    (fd, bd), (fi, bi) = _direct_floor(sparse, 32), _indirect_floor(transfer)
    n2 = transfer.shape[1]
    return {"run": run, "gflop": (2 * entries * 3 + 2 * transfer.size) / 1e9, "items": PAPER_VERTICES,
            "peer": ("scipy.sparse CSR direct + numpy einsum indirect", peer),
            "floor": floor(fd + fi + 2 * 6 * 32**2 * n2 * 3, bd + bi - 24 * PAPER_VERTICES,
                           f"direct ({DIRECT_FORMULA}) + indirect ({INDIRECT_FORMULA}) + 6 T n^2 flops - 24 V bytes"),
            "stored_bytes": sparse.nbytes + transfer.nbytes + albedo.nbytes}


@case("portals.direct_pass.45k")
def direct(quick: bool) -> dict:
    scene, sparse, _, albedo = _frame_data()
    cube = shell_light(scene.environment, 32)
    csr = _direct_csr()
    ours = direct_pass(sparse, albedo, cube)  # float32 sums of the pulse rows: agreement to float32 rounding
    check_same_work(ours, _csr_direct(csr, albedo, cube), "portals.direct_pass", rtol=1e-5,
                    atol=1e-6 * float(np.max(ours)))
    return {"run": lambda: direct_pass(sparse, albedo, cube), "gflop": 2 * len(sparse.codes) * 3 / 1e9,
            "items": PAPER_VERTICES, "peer": ("scipy.sparse CSR float64 (decoded once) @ light",
                                              lambda: _csr_direct(csr, albedo, cube)),
            "floor": floor(*_direct_floor(sparse, 32), DIRECT_FORMULA), "stored_bytes": sparse.nbytes}


@case("portals.indirect_pass.45k")
def indirect(quick: bool) -> dict:
    scene, _, transfer, _ = _frame_data()
    c = shell_sh(shell_light(scene.environment, 32), 4)
    check_same_work(indirect_pass(transfer, c), _einsum_indirect(transfer, c), "portals.indirect_pass", rtol=1e-6)
    return {"run": lambda: indirect_pass(transfer, c), "gflop": 2 * transfer.size / 1e9, "items": PAPER_VERTICES,
            "peer": ("numpy einsum (float32 transfer, float64 light)", lambda: _einsum_indirect(transfer, c)),
            "floor": floor(*_indirect_floor(transfer), INDIRECT_FORMULA), "stored_bytes": transfer.nbytes}


# ------------------------------------------------------------------ the default frame: indirect="surface"


@lru_cache(maxsize=1)
def _surface_frame_data():
    """The default frame's data at 44,763 vertices: direct and hat-averaged source transfers (res 64, 4096 portal
    samples: their entries per vertex are the defaults'), the interior gather over 1,024 clusters, rows tiled.
    ``gather_rays`` is lowered for the precomputation's sake: the frame reads the dense (V, C) gather whatever its
    ray count. The source operator ``Pbar diag(rho) T_src`` is built from the tiled rows (tiled copies fall in the
    same clusters, so it is the untiled box's: a cluster's entries are the union over its region, set by the
    cluster's extent, not by how many vertices sample it)."""
    scene = load_scene(SCENE)
    pre = Portals.precompute(scene, {"indirect": "surface", "gather_rays": 64}, progress=False)
    n0 = len(pre.data["albedo"])
    reps = -(-PAPER_VERTICES // n0)

    def tile(a):
        return np.ascontiguousarray(np.tile(a, (reps,) + (1,) * (np.ndim(a) - 1))[:PAPER_VERTICES])

    e, st = pre.data["surface"], pre.surface_transfer()
    albedo = tile(pre.data["albedo"])
    near = None if st.near is None else (_tile_rows(st.near[0], reps, 0), _tile_rows(st.near[1], reps, n0))
    surface = SurfaceTransfer((tile(st.codes), tile(st.scale)), tile(st.patch), tile(e["areas"]), albedo,
                              e["operator"], {pre.options.bounces: e["sum"]}, near=near)
    direct = _tile(pre.direct_transfer(0), PAPER_VERTICES)
    source = _tile(pre.direct_transfer(0, source=True), PAPER_VERTICES)
    return scene, direct, source, surface, surface.source_operator(source), albedo, pre.options


def _tile_rows(m, reps: int, column_step: int):
    """A sparse ``(n0, k)`` matrix's rows repeated ``reps`` times, copy ``r``'s columns moved by ``r column_step``
    (near point reads name vertices, near patch reads clusters: step 0), cut to :data:`PAPER_VERTICES` rows and
    columns."""
    import scipy.sparse

    m = m.tocoo()
    n0 = m.shape[0]
    rows = np.concatenate([m.row + r * n0 for r in range(reps)])
    cols = np.concatenate([m.col + r * column_step for r in range(reps)])
    keep = (rows < PAPER_VERTICES) & (cols < (PAPER_VERTICES if column_step else m.shape[1]))
    shape = (PAPER_VERTICES, PAPER_VERTICES if column_step else m.shape[1])
    return scipy.sparse.csr_matrix((np.tile(m.data, reps)[keep], (rows[keep], cols[keep])), shape=shape)


def surface_frame(env, direct, source_operator, surface, albedo, res: int, bounces: int) -> np.ndarray:
    """One default frame as :meth:`Portals.shade_shells` runs it (numba tiers, :func:`shade_surface`): the shell
    light, its pulse and Haar coefficients once, the direct pass, the patches' source light ``G L``, then ``rho F
    S_B s`` with the near rays' point reads; total radiance."""
    radiance, indirect = shade_surface(direct, albedo, shell_light(env, res), source_operator, surface, bounces)
    return radiance + indirect


@lru_cache(maxsize=1)
def _surface_peer_data():
    """The peer's operands, decoded once: CSR float64 direct and source transfers, the patch mean as a CSR matrix,
    the gather as float32 ``(V, C)`` (codes times their row scale), ``S_B`` float32 per channel."""
    import scipy.sparse

    _, direct, source, surface, _, _, options = _surface_frame_data()
    mean = scipy.sparse.csr_matrix((surface.mean_weight, (surface.patch, np.arange(len(surface.patch)))),
                                   shape=(surface.n_patches, len(surface.patch)))
    gather = surface.codes.astype(np.float32) * surface.scale[:, None]
    sums = [np.ascontiguousarray(surface.bounce_sum(b).transpose(2, 0, 1)) for b in (options.bounces,
                                                                                     options.bounces - 1)]
    return transfer_csr(direct), transfer_csr(source), mean, gather, sums, surface.near, surface.partners


def _peer_surface_frame(env, res, albedo):
    """The default frame as a user would write it with scipy and numpy from the transfers decoded once, the near
    rays' point reads included (:meth:`SurfaceTransfer.near_correction`)."""
    direct_csr, source_csr, mean, gather, sums, (near_patch, near_point), partners = _surface_peer_data()
    cube = shell_light(env, res)
    light = np.concatenate([cube.reshape(-1, 3), haar2d(cube, channels=True).reshape(-1, 3)])
    s = (mean @ ((source_csr @ light) * albedo)).astype(np.float32)
    u, previous = (np.stack([m[ch] @ s[:, ch] for ch in range(3)], axis=1) for m in sums)
    direct = (direct_csr @ light) * albedo
    point = direct.copy()
    point[partners] += albedo[partners] * (gather[partners] @ previous)
    return direct + (gather @ u + near_point @ point - near_patch @ u) * albedo


# The default frame's floor: V vertices, E direct entries, T texels, C clusters, E_G entries of the source operator
# (3 float64 values and a 4-byte column each), N near-read entries (float64 and a 4-byte column), P vertices read
# by near rays, 3 colours. Flops: the direct pass (6 E + 6 V), the source light (6 E_G), the bounce sums S_B s and
# S_(B-1) s (12 C^2), the gather (6 V C; scale and albedo 6 V), the partners' rows (6 P C) and the near reads
# (6 N). Bytes: the direct transfer (``SparseTransfer.nbytes``) and the light (2 x 2 T x 24: written, read), the
# source operator (28 E_G), both sums (24 C^2), the 16-bit gather and its scales (2 V C + 4 V), the partners' rows
# (2 P C), the near reads (12 N), albedo read (24 V) and the radiance written (24 V).
SURFACE_FORMULA = ("6 E + 12 V + 6 E_G + 12 C^2 + 6 V C + 6 P C + 6 N flops; SparseTransfer.nbytes + 96 T + 28 E_G "
                   "+ 24 C^2 + 2 V C + 2 P C + 12 N + 52 V bytes")


def _surface_floor(direct, source_operator, surface) -> tuple[float, float]:
    v, e, t = direct.n_vertices, len(direct.codes), 6 * direct.res**2
    e_g, c = len(source_operator.columns), surface.n_patches
    n = sum(m.nnz for m in surface.near) if surface.near is not None else 0
    p = len(surface.partners) if surface.near is not None else 0
    flop = 6.0 * e + 12.0 * v + 6.0 * e_g + 12.0 * c * c + 6.0 * v * c + 6.0 * p * c + 6.0 * n
    nbytes = direct.nbytes + 96.0 * t + 28.0 * e_g + 24.0 * c * c + 2.0 * v * c + 2.0 * p * c + 12.0 * n + 52.0 * v
    return flop, nbytes


def _idle_blas_threads(seconds: float = 0.25) -> None:
    """Wait (untimed) until the peer's BLAS threads have parked: after a call they busy-wait for up to about 0.1 s,
    and on 2 cores they take the core that the next call's second thread needs (the frame right after the peer took
    about 2x its time alone; ``docs/notes/portals.md``)."""
    time.sleep(seconds)


@case("portals.frame.default_surface.45k")
def frame_default_surface(quick: bool) -> dict:
    """The default frame (``indirect="surface"``, res 64, 1,024 clusters) at 44,763 vertices; issue 17: 14 ms."""
    scene, direct, source, surface, source_operator, albedo, options = _surface_frame_data()
    env, res, bounces = scene.environment, direct.res, options.bounces

    def run():
        return surface_frame(env, direct, source_operator, surface, albedo, res, bounces)

    def peer():
        return _peer_surface_frame(env, res, albedo)

    ours = run()
    check_same_work(ours, peer(), "portals.frame.default_surface", rtol=1e-4, atol=1e-6 * float(np.max(ours)))
    return {"run": run, "setup": _idle_blas_threads,
            "gflop": _surface_floor(direct, source_operator, surface)[0] / 1e9, "items": PAPER_VERTICES,
            "peer": ("scipy.sparse CSR direct and source + float32 BLAS gather (all decoded once)", peer),
            "floor": floor(*_surface_floor(direct, source_operator, surface), SURFACE_FORMULA),
            "stored_bytes": direct.nbytes + source.nbytes + surface.codes.nbytes + surface.scale.nbytes
            + surface.bounce_sum(bounces).nbytes + sum(m.data.nbytes + m.indices.nbytes for m in surface.near),
            "info": {"direct_entries_per_vertex": len(direct.codes) / PAPER_VERTICES,
                     "source_operator_entries": len(source_operator.columns), "clusters": surface.n_patches,
                     "source_operator_mb": source_operator.nbytes / 1e6,
                     "near_entries": sum(m.nnz for m in surface.near), "near_partners": len(surface.partners)}}


def direct_transfer_memory() -> dict:
    """Bytes of the 8-bit direct transfer at the paper's vertex count (and per vertex)."""
    _, sparse, transfer, _ = _frame_data()
    return {"direct_bytes": sparse.nbytes, "direct_bytes_per_vertex": sparse.nbytes / sparse.n_vertices,
            "entries_per_vertex": len(sparse.codes) / sparse.n_vertices, "indirect_bytes_float32": transfer.nbytes}


@lru_cache(maxsize=1)
def _precompute_inputs():
    from prtlab.geometry import RayCaster
    from prtlab.portals import find_portals, radiance_estimate, trace_photons

    scene = load_scene(SCENE)
    room = scene.object("room")
    caster = RayCaster(scene)
    (portal,) = find_portals(scene)
    points, normals = room.world_vertices(), room.world_normals()
    albedo = np.tile(room.material.albedo, (len(points), 1))
    photons = trace_photons(caster, albedo[:1], portal, 100_000, 3, np.random.default_rng(0))
    exitance = radiance_estimate(photons, points, normals, albedo, 4)
    return caster, portal, points, normals, albedo, exitance


def _sample_vertices(quick: bool):
    """64 (quick: 16) of the room's vertices, the same for every precomputation case: ``(inputs, sel)``."""
    inputs = _precompute_inputs()
    points = inputs[2]
    return inputs, np.random.default_rng(1).choice(len(points), 16 if quick else 64, replace=False)


@case("portals.precompute.direct.4096rays")
def precompute_direct(quick: bool) -> dict:
    """Direct transfer of 64 (quick: 16) vertices at the paper's 4096 portal samples; x 44,763 / items = Table 1."""
    from prtlab.portals import direct_transfer

    (caster, portal, points, normals, _, _), sel = _sample_vertices(quick)
    rng = np.random.default_rng(2)
    return {"run": lambda: direct_transfer(caster, points[sel], normals[sel], portal, 4096, 32, rng),
            "gflop": None, "items": len(sel), "peer": None}


@case("portals.precompute.gather.4096rays")
def precompute_gather(quick: bool) -> dict:
    """Final gathering of 64 (quick: 16) vertices at the paper's 4096 rays, order 4."""
    from prtlab.portals import final_gather

    (caster, _, points, normals, albedo, exitance), sel = _sample_vertices(quick)
    rng = np.random.default_rng(3)
    offsets = np.array([0, len(points)])
    return {"run": lambda: final_gather(caster, points[sel], normals[sel], albedo[sel], exitance, offsets, normals,
                                        4096, rng),
            "gflop": None, "items": len(sel), "peer": None}


@case("portals.precompute.photons.200k")
def precompute_photons(quick: bool) -> dict:
    """Photon tracing from the window (3 bounces) for all SH bases at once: 200k (quick: 50k) photons."""
    from prtlab.portals import trace_photons

    caster, portal, _, _, albedo, _ = _precompute_inputs()
    n = 50_000 if quick else 200_000
    rng = np.random.default_rng(4)
    return {"run": lambda: trace_photons(caster, albedo[:1], portal, n, 3, rng), "gflop": None, "items": n,
            "peer": None}


# ------------------------------------------------------------------ the whole precomputation at the paper's counts

#: Table 1's counts: 4096 direct samples and final-gather rays per vertex, 9 bounces; photons: 2M per SH basis in the
#: paper, here 2M shared by all 16 bases (each photon carries every basis's value: per basis as many photons as the
#: paper's, 16 times fewer traced)
PAPER_COUNTS = {"direct_samples": 4096, "gather_rays": 4096, "bounces": 9}
#: the room's cell size that gives the shipped box 44,476 vertices (the paper's box: 44,763)
PAPER_CELL = 0.0405


def paper_box(quick: bool = False):
    """The shipped window box (``box_window_sky``, 2,058 vertices) remeshed at the paper's size: the room's grid
    cell 0.2 m -> 0.0405 m, 44,476 vertices (quick: as shipped)."""
    import yaml

    from prtlab.scene import Scene

    spec = yaml.safe_load(SCENE.read_text())
    if not quick:
        spec["objects"][0]["mesh"]["cell_size"] = PAPER_CELL
    return Scene.from_dict(spec)


def _peak_rss(fn):
    """``fn()`` and the peak resident memory of this process while it ran (``/proc/self/status`` VmRSS, sampled
    every 0.2 s; bytes; None where unavailable)."""
    import threading

    def rss():
        try:
            for line in open("/proc/self/status"):
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
        except OSError:
            return None

    peak, done = [rss()], threading.Event()

    def watch():
        while not done.wait(0.2):
            peak.append(rss())

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        out = fn()
    finally:
        done.set()
        watcher.join()
    peak = [p for p in peak if p is not None]
    return out, (max(peak) if peak else None)


def _data_bytes(data) -> int:
    """Bytes of a precomputation's stored arrays (nested dicts)."""
    if isinstance(data, dict):
        return sum(_data_bytes(v) for v in data.values())
    return int(np.asarray(data).nbytes)


def _paper_counts_case(quick: bool, indirect: str) -> dict:
    """The whole precomputation (``cache=False``, one process, chunks in order) of the paper-size box at Table 1's
    counts, once (no warm-up: numba's compilation is in the figure, a few seconds)."""
    scene = paper_box(quick)
    options = dict(PAPER_COUNTS, indirect=indirect)
    if indirect == "paper":
        options.update(n_photons=2_000_000, cube_resolution=32)  # the paper's shell resolution
    if quick:
        options.update(direct_samples=256, gather_rays=64, n_photons=50_000, bounces=3)
    # filled by the run, read after it; cpu_s: the process's CPU time (all threads), the load-proof figure
    info = {"cpu_s": None, "gather_rays": None, "indirect_noise": None, "peak_rss_gb": None, "load_1min": None}
    stored = []

    def run():
        cpu = time.process_time()
        pre, peak = _peak_rss(lambda: Portals.precompute(scene, options, cache=False, progress=False))
        noise = pre.data["gather_noise"]
        info.update(cpu_s=time.process_time() - cpu, gather_rays=int(noise["gather_rays"]),
                    indirect_noise=float(noise["noise"]), peak_rss_gb=None if peak is None else peak / 1e9,
                    load_1min=os.getloadavg()[0] if hasattr(os, "getloadavg") else None)
        stored.append(_data_bytes(pre.data))

    n_vertices = sum(o.n_vertices for o in scene.objects if not o.portal)
    return {"run": run, "repeats": 1, "warmup": False, "gflop": None, "items": n_vertices, "peer": None,
            "info": info, "stored_bytes": lambda: stored[-1]}


@case("portals.precompute.paper_counts.45k")
def precompute_paper_counts(quick: bool) -> dict:
    """The default precomputation (``indirect="surface"``, res 64, 1,024 clusters) of the 44,476-vertex box at the
    paper's counts (Table 1; issue 17: within 23 minutes on 2 cores, goal 10)."""
    return _paper_counts_case(quick, "surface")


@case("portals.precompute.paper_counts.paper_mode.45k")
def precompute_paper_counts_paper(quick: bool) -> dict:
    """The paper's mode (``indirect="paper"``, res 32, order 4, 2M photons shared by the 16 SH bases) of the
    44,476-vertex box at the paper's counts."""
    return _paper_counts_case(quick, "paper")


@case("portals.glossy_passes.bunny")
def glossy_passes(quick: bool) -> dict:
    """The glossy passes of Fig. 11's bunny (1,839 vertices): the direct pass blends 4 of the 96 per-direction 8-bit
    rows toward the camera, the indirect pass is the SH->SH matrix-vector product then the evaluation at the view
    (Eq. 6). Rows are the box's direct transfers (the cost depends on entries per row, not on their values)."""
    from prtlab.portals import glossy_direct_pass, glossy_indirect_pass, view_interpolation

    scene, sparse, transfer, _ = _frame_data()
    n_glossy, view_res = 1839, 4
    n_views = 6 * view_res**2
    rows_sparse = _tile(sparse, n_glossy * n_views)
    rng = np.random.default_rng(0)
    view = rng.normal(size=(n_glossy, 3))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    rows, weights = view_interpolation(view, view_res)
    rows += (np.arange(n_glossy) * n_views)[:, None]
    ks = np.full((n_glossy, 3), 0.5)
    matrix = rng.normal(size=(n_glossy, 16, 16, 3)).astype(np.float32)
    cube = shell_light(scene.environment, 32)
    c = shell_sh(cube, 4)

    def run(method="numba"):
        return glossy_direct_pass(rows_sparse, rows, weights, ks, cube, method) + glossy_indirect_pass(matrix, c, view,
                                                                                                      method)

    entries = int(sum(rows_sparse.indptr[r + 1] - rows_sparse.indptr[r] for r in rows.ravel()))
    return {"run": run, "gflop": (2 * entries * 3 + 2 * matrix.size + 2 * 16 * 3 * n_glossy) / 1e9,
            "items": n_glossy, "peer": ("float64 reference tiers", lambda: run("reference")),
            "floor": floor(*_glossy_floor(rows_sparse, rows, matrix), GLOSSY_FORMULA),
            "stored_bytes": rows_sparse.nbytes + matrix.nbytes}


# The glossy passes' floor: V_g vertices blending Q rows of E_q 8-bit entries in all, the (V_g, n^2, n^2, 3)
# matrices. Flops: 2 x 3 an entry read (its weight folded per row, 2 x 3 Q V_g), the matrix-vector products
# (2 x its size) and the evaluation at the view (2 n^2 3 V_g; the view's SH basis not counted). Bytes: the blended
# rows' entries (code and index) and their rows' pointers, scale and basis; the matrices; rows and weights, ks,
# views read and radiance written (Q V_g 16 + 3 x 24 V_g).
GLOSSY_FORMULA = ("6 E_q + 6 Q V_g + 2 V_g n^4 3 + 6 n^2 V_g flops; E_q (code + index bytes) + Q V_g (indptr 16 + "
                  "scale + basis bytes) + matrix bytes + 16 Q V_g + 72 V_g bytes")


def _glossy_floor(sparse, rows, matrix) -> tuple[float, float]:
    n_glossy, q = rows.shape
    entries = float(sum(sparse.indptr[r + 1] - sparse.indptr[r] for r in rows.ravel()))
    n2 = matrix.shape[2]
    flop = 6 * entries + 6 * q * n_glossy + 2 * matrix.size + 6 * n2 * n_glossy
    per_row = 2 * sparse.indptr.itemsize + sparse.scale.itemsize + sparse.basis.itemsize
    nbytes = (entries * (sparse.codes.itemsize + sparse.indices.itemsize) + rows.size * per_row + matrix.nbytes
              + 16 * rows.size + 72 * n_glossy)
    return flop, nbytes


if __name__ == "__main__":  # pragma: no cover
    print(direct_transfer_memory())
