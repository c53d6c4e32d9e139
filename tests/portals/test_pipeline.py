"""The portals pipeline end to end: precompute, shade, dispatch, errors, validity criteria."""

import warnings

import numpy as np
import pytest

from prtlab.pipeline import FrameState
from prtlab.portals import (
    Portals,
    PortalValidityWarning,
    check_interior_solid_angle,
    check_shell_distance,
    frosted,
    indirect_pass,
    shell_light,
    tint,
)
from prtlab.scene import Scene

from tests.conftest import two_numba_threads

from .conftest import window_box

QUICK = {"cube_resolution": 8, "direct_samples": 64, "n_photons": 20000, "gather_rays": 32, "order": 3, "bounces": 1}


@pytest.fixture(scope="module")
def pre():
    return Portals.precompute(window_box(cell=0.5), QUICK, cache=False, progress=False)


def test_shade_shapes_and_linearity(pre):
    res = pre.shade(bounces=1)
    n = pre.scene.objects[0].n_vertices
    for part in (res.direct, res.indirect, res.total):
        assert part["room"].shape == (n, 3)
        assert "window" not in part
    np.testing.assert_allclose(res.total["room"], res.direct["room"] + res.indirect["room"])
    assert res.direct["room"].max() > 0 and res.indirect["room"].max() > 0
    # the transfer is linear in the shell light: tinting scales each channel
    cube = shell_light(pre.scene.environment, 8)
    tinted = pre.shade_shells([tint(cube, [0.5, 1.0, 2.0])])
    np.testing.assert_allclose(tinted.total["room"], res.total["room"] * [0.5, 1.0, 2.0], rtol=1e-5, atol=1e-12)
    # a constant sky is unchanged by frosting
    np.testing.assert_allclose(pre.shade_shells([frosted(cube, 15.0)]).total["room"], res.total["room"], rtol=1e-6)
    assert np.all(pre.shade(bounces=0).indirect["room"] == 0)


def test_shade_frame_environment_changes(pre):
    state = FrameState.from_scene(pre.scene)
    brighter = window_box({"type": "environment", "constant": [2.0, 2.0, 2.0]}, cell=0.5)
    state.lights = list(brighter.lights)
    np.testing.assert_allclose(pre.shade(state).total["room"], 2 * pre.shade().total["room"], rtol=1e-6)


def test_shade_scene_entry_point():
    import prtlab.api
    from prtlab.portals import shade_scene

    opts = {k: v for k, v in QUICK.items() if k != "bounces"}
    scene = window_box(cell=0.5)
    res = shade_scene(scene, bounces=1, cache=False, progress=False, **opts)
    assert res.info["bounces"] == 1 and res.total["room"].shape == (scene.objects[0].n_vertices, 3)
    again = prtlab.api.shade(scene, method="portals", bounces=1, cache=False, progress=False, **opts)
    np.testing.assert_array_equal(again.total["room"], res.total["room"])


def test_errors(pre):
    with pytest.raises(ValueError, match="precomputed with bounces=1"):
        pre.shade(bounces=2)
    with pytest.raises(ValueError, match="one shell cubemap per portal"):
        pre.shade_shells([])
    with pytest.raises(ValueError, match="power of two"):
        Portals.make_options({"cube_resolution": 12})
    with pytest.raises(ValueError, match="option n_photons"):
        Portals.make_options({"n_photons": 0})
    with pytest.raises(ValueError, match="option direct_basis"):
        Portals.make_options({"direct_basis": "dct"})
    with pytest.raises(ValueError, match="option bounces"):
        Portals.make_options({"bounces": -1})
    state = FrameState.from_scene(pre.scene)
    state.lights = []
    with pytest.raises(ValueError, match="exactly one environment"):
        pre.shade(state)
    scene = window_box(cell=1.0)
    no_portal = Scene(objects=[scene.objects[0]], lights=scene.lights, camera=scene.camera)
    with pytest.raises(ValueError, match="no portal"):
        Portals.precompute(no_portal, QUICK, cache=False, progress=False)
    with pytest.raises(ValueError, match="bounces must be an int >= 0"):
        pre.shade_shells([shell_light(pre.scene.environment, 8)], bounces=-1)


def test_indirect_pass_tiers(rng):
    t = rng.normal(size=(30, 16, 3)).astype(np.float32)
    c = rng.normal(size=(16, 3))
    np.testing.assert_allclose(indirect_pass(t, c), indirect_pass(t, c, "reference"), rtol=1e-10, atol=1e-12)
    assert indirect_pass(t[:0], c).shape == (0, 3)
    with pytest.raises(ValueError, match=r"transfer must have shape \(V, n\*n, 3\)"):
        indirect_pass(t[..., 0], c)
    with pytest.raises(ValueError, match="light_sh must have shape"):
        indirect_pass(t, c[:4])
    with pytest.raises(ValueError, match="NaN"):
        indirect_pass(t, c * np.nan)
    with pytest.raises(ValueError, match="'numba' or 'reference'"):
        indirect_pass(t, c, "gpu")


def test_the_papers_options_turn_every_extension_off():
    """``PAPER_OPTIONS`` are options of the pipeline and select the paper's indirect transfer (photons and final
    gathers, no surface transfer) where the default takes the surface transfer (a diffuse interior), and the
    paper's view cubemaps for a glossy object (24 per glossy vertex at ``view_res=2``, none by default)."""
    import dataclasses

    from prtlab.portals import PAPER_OPTIONS, PortalsOptions

    assert set(PAPER_OPTIONS) <= {f.name for f in dataclasses.fields(PortalsOptions)}
    scene = window_box(cell=0.5)
    assert Portals.indirect_mode(scene, Portals.make_options(QUICK)) == "surface"
    paper = Portals.precompute(scene, {**QUICK, **PAPER_OPTIONS}, cache=False, progress=False)
    assert all(getattr(paper.options, k) == v for k, v in PAPER_OPTIONS.items())
    assert Portals.indirect_mode(scene, paper.options) == "paper" and "surface" not in paper.data
    assert np.all(np.isfinite(paper.shade(bounces=1).total["room"]))
    glossy = _glossy_box_scene()
    n_block = glossy.object("block").n_vertices
    for options, views in ((dict(QUICK, view_res=2), 0), (dict(QUICK, view_res=2, **PAPER_OPTIONS), 24)):
        pre = Portals.precompute(glossy, options, cache=False, progress=False)
        assert pre.direct_transfer(0, glossy=True).n_vertices == n_block * views


def test_validity_criteria():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_shell_distance(0.5, 3.0)          # the paper: 50 cm window, objects beyond 3 m, 5 deg
        assert check_interior_solid_angle(2.0, 2.9)    # the paper: 2 m^2 sedan, d > 2.8 m for R = 0.02
    with pytest.warns(PortalValidityWarning, match="split the portal"):
        assert not check_shell_distance(0.5, 2.0)
    with pytest.warns(PortalValidityWarning, match="not negligible"):
        assert not check_interior_solid_angle(2.0, 2.7)
    with pytest.raises(ValueError, match="distance must be a positive"):
        check_shell_distance(0.5, -1.0)
    with pytest.raises(ValueError, match="interior_area must be a positive"):
        check_interior_solid_angle(np.nan, 1.0)


def test_chunked_cache_resumes(tmp_path, monkeypatch):
    from prtlab.cache import Cache

    scene = window_box(cell=0.5)
    monkeypatch.setattr(Portals, "chunk_vertices", 40)
    fresh = Portals.precompute(scene, QUICK, cache=False, progress=False)
    store = Cache(tmp_path, progress=False)
    calls = []

    def interrupted(fn, indices):
        for i in indices[:2]:
            calls.append(i)
            yield i, fn(i)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        Portals.precompute(scene, QUICK, cache=store, progress=False, map_fn=interrupted)

    def counting(fn, indices):
        for i in indices:
            calls.append(i)
            yield i, fn(i)

    resumed = Portals.precompute(scene, QUICK, cache=store, progress=False, map_fn=counting)
    n_chunks = -(-scene.objects[0].n_vertices // 40)
    assert sorted(calls) == list(range(n_chunks))  # the two finished chunks were not recomputed
    for name in ("indptr", "indices", "codes", "scale", "basis", "source_codes"):
        np.testing.assert_array_equal(resumed.data["portal0"][name], fresh.data["portal0"][name])
    np.testing.assert_array_equal(resumed.data["surface"]["gather_codes"], fresh.data["surface"]["gather_codes"])
    again = Portals.precompute(scene, QUICK, cache=store, progress=False, map_fn=counting)
    assert len(calls) == n_chunks  # a hit: nothing recomputed
    np.testing.assert_array_equal(again.shade().total["room"], fresh.shade().total["room"])


def test_merge_portals():
    base = window_box(cell=0.5)
    d = {"objects": [o.to_dict() for o in base.objects], "lights": [{"type": "environment", "constant": [1, 1, 1]}],
         "camera": base.camera.to_dict()}
    second = dict(d["objects"][1], name="window2")
    d["objects"].append(second)  # the same opening twice: two portals, or one merged portal of twice the area
    scene = Scene.from_dict(d)
    opts = dict(QUICK, bounces=0)
    separate = Portals.precompute(scene, opts, cache=False, progress=False)
    merged = Portals.precompute(scene, dict(opts, merge_portals=True), cache=False, progress=False)
    assert separate.n_portals == 2 and merged.n_portals == 1
    with pytest.raises(TypeError, match="option merge_portals must be True or False"):
        Portals.make_options({"merge_portals": "yes"})


def test_parallel_chunks_match_serial(tmp_path, monkeypatch):
    """Chunks run by a thread pool (any map_fn, e.g. Dask's) give the serial result: per-chunk seeds."""
    from concurrent.futures import ThreadPoolExecutor, as_completed

    from prtlab.cache import Cache

    scene = window_box(cell=0.5)
    monkeypatch.setattr(Portals, "chunk_vertices", 50)
    serial = Portals.precompute(scene, QUICK, cache=False, progress=False)

    def pool_map(fn, indices):
        with ThreadPoolExecutor(2) as pool:
            futures = {pool.submit(fn, i): i for i in indices}
            for f in as_completed(futures):
                yield futures[f], f.result()

    parallel = Portals.precompute(scene, QUICK, cache=Cache(tmp_path, progress=False), progress=False,
                                  map_fn=pool_map)
    for name in ("indptr", "codes", "source_codes"):
        np.testing.assert_array_equal(parallel.data["portal0"][name], serial.data["portal0"][name])
    np.testing.assert_array_equal(parallel.data["surface"]["gather_codes"], serial.data["surface"]["gather_codes"])


def _glossy_box_scene():
    base = window_box(cell=0.5)
    d = {"objects": [o.to_dict() for o in base.objects] + [{
        "name": "block", "mesh": {"builtin": "box"}, "transform": {"translate": [0.3, 0.4, 0.2], "scale": 0.8},
        "material": {"type": "phong", "kd": [0.3, 0.3, 0.3], "ks": [0.4, 0.5, 0.6], "exponent": 10}}],
        "lights": [{"type": "environment", "constant": [1.0, 1.0, 1.0]}], "camera": base.camera.to_dict()}
    return Scene.from_dict(d)


@pytest.mark.parametrize("glossy_direct", ["views", "lobe"])
def test_glossy_and_per_bounce_shading(glossy_direct):
    scene = _glossy_box_scene()
    pre = Portals.precompute(scene, dict(QUICK, bounces=2, view_res=2, glossy_direct=glossy_direct), cache=False,
                             progress=False)
    n_block = scene.object("block").n_vertices
    assert pre.data["glossy"].sum() == n_block
    if glossy_direct == "views":
        assert pre.direct_transfer(0, glossy=True).n_vertices == n_block * 24
    else:  # no view cubemaps: one float32 row of visible texels per glossy vertex
        assert pre.direct_transfer(0, glossy=True).n_vertices == 0
        assert len(pre.data["portal0"]["lobe_indptr"]) == n_block + 1
        assert pre.data["portal0"]["lobe_values"].dtype == np.float32
    assert pre.indirect_transfer(0, 2, glossy=True).shape == (n_block, 9, 9, 3)
    res = [pre.shade(bounces=b) for b in range(3)]
    for name in ("room", "block"):
        np.testing.assert_array_equal(res[0].direct[name], res[2].direct[name])
        assert np.all(res[0].indirect[name] == 0)
        # constant sky: each bounce adds non-negative light (band 0 only)
        assert np.all(res[2].indirect[name] >= res[1].indirect[name] - 1e-12)
        assert res[2].indirect[name].sum() > res[1].indirect[name].sum() > 0
    cube = shell_light(scene.environment, 8)
    ref = pre.shade_shells([cube], 2, method="reference")
    for name in ("room", "block"):
        np.testing.assert_allclose(res[2].total[name], ref.total[name], rtol=1e-5, atol=1e-9)
    # the camera moves: only the glossy block changes, and its ks-coloured highlight with it
    from prtlab.scene import Camera

    moved = pre.shade_shells([cube], 2, camera=Camera(position=np.array([-1.2, 2.0, -1.0])))
    np.testing.assert_array_equal(moved.total["room"], res[2].total["room"])
    assert np.abs(moved.total["block"] - res[2].total["block"]).max() > 1e-3
    with pytest.raises(ValueError, match=r"precomputed with bounces=2; shade with bounces <= 2"):
        pre.shade(bounces=3)
    with pytest.raises(ValueError, match="option view_res"):
        Portals.make_options({"view_res": 0})
    with pytest.raises(ValueError, match="option glossy_order"):
        Portals.make_options({"glossy_order": -1})
    with pytest.raises(ValueError, match="option glossy_direct"):
        Portals.make_options({"glossy_direct": "exact"})
    wider = Portals.precompute(scene, dict(QUICK, bounces=1, view_res=1, glossy_order=5), cache=False, progress=False)
    assert wider.indirect_transfer(0, glossy=True).shape == (n_block, 25, 9, 3)
    assert np.all(np.isfinite(wider.shade(bounces=1).total["block"]))
    with pytest.raises(ValueError, match="camera sits on a glossy vertex"):
        pre.view_directions(Camera(position=pre.scene.object("block").world_shading_points()[0]))


@pytest.mark.slow  # a LocalCluster of 2 processes: 10 s on an idle machine, 35 s on a busy one
def test_dask_workers_match_serial(tmp_path, monkeypatch):
    """``prtlab.api.precompute(scene, method="portals", workers=2)`` (``prtlab precompute --workers 2``): chunks
    on a Dask LocalCluster give the serial data."""
    pytest.importorskip("dask.distributed")
    import prtlab.api

    monkeypatch.setenv("PRTLAB_CACHE", str(tmp_path))
    monkeypatch.setattr(Portals, "chunk_vertices", 60)  # several chunks (the workers import the class unpatched:
    scene = _glossy_box_scene()                          # chunk sizes are fixed before chunk_fn is shipped)
    opts = dict(QUICK, bounces=2, view_res=2)
    serial = Portals.precompute(scene, opts, cache=False, progress=False)
    try:
        distributed = prtlab.api.precompute(scene, method="portals", workers=2, progress=False, **opts)
    finally:
        from dask.distributed import default_client

        try:
            client = default_client()
        except ValueError:
            client = None
        if client is not None:
            cluster = client.cluster
            client.close()
            if cluster is not None:
                cluster.close()
    for name in ("indptr", "codes", "indirect", "glossy_indptr", "glossy_codes", "glossy_matrix"):
        np.testing.assert_array_equal(distributed.data["portal0"][name], serial.data["portal0"][name])
    np.testing.assert_array_equal(distributed.shade(bounces=2).total["block"], serial.shade(bounces=2).total["block"])


# ------------------------------------------------------------------ objects moved after the precomputation (issue 17)


def test_an_object_moved_after_the_precomputation_is_refused_not_ignored():
    """The interior is baked: a pose given in the frame state, or the scene's own object moved in place (its
    transform replaced or its arrays edited) after the precomputation, is refused in one line by ``shade`` and by
    ``shade_shells``; put back, it shades as before."""
    from prtlab.scene import Transform
    from tests.robustness.test_pipelines import TINY_PORTALS, _room_with_box

    aside = Transform(translate=np.array([1.0, 0.3, 1.0]))
    blocking = Transform(translate=np.array([0.0, 1.4, -1.2]))
    scene = _room_with_box(aside)
    pre = Portals.precompute(scene, TINY_PORTALS, cache=False, progress=False)
    before = pre.shade(bounces=1).total["room"]
    cube = shell_light(scene.environment, 4)
    state = FrameState.from_scene(scene)
    state.transforms["box"] = blocking
    with pytest.raises(ValueError, match="^the portals method precomputes the interior: object 'box' moved; keep it"):
        pre.shade(state, bounces=1)
    scene.object("box").transform = blocking  # the scene edited in place
    with pytest.raises(ValueError, match="^the portals method precomputes the interior: object 'box' moved; keep it"):
        pre.shade(bounces=1)
    with pytest.raises(ValueError, match="^the portals method precomputes the interior: object 'box' moved after "
                                         r"the precomputation; put it back or re-precompute at the new pose"):
        pre.shade_shells([cube], 1)
    scene.object("box").transform = Transform(translate=np.array([1.0, 0.3, 1.0]))
    np.testing.assert_array_equal(pre.shade(bounces=1).total["room"], before)
    scene.object("box").transform.translate[1] += 0.5  # an in-place edit of the pose's arrays
    with pytest.raises(ValueError, match="object 'box' moved after the precomputation"):
        pre.shade_shells([cube], 1)
    scene.object("box").transform.translate[1] -= 0.5
    np.testing.assert_array_equal(pre.shade_shells([cube], 1).total["room"], before)
    assert pre.moved_objects(FrameState()) == []


# ------------------------------------------------------------------ the default frame's tiers


def test_surface_frame_numba_tier_within_its_float32_bound_of_the_float64_reference():
    """``indirect="surface"``: the numba frame (shell light coefficients once, the source operator ``Pbar diag(rho)
    T_src``, float32 sums) against the float64 reference tier (per-vertex source pass, patch mean, float64
    products). The source light agrees to float64 roundoff (1e-12 of the sums of absolute terms); the indirect light
    within the float32 sums' forward error bound ``2 (C + 2) eps_32`` times the same products of absolute values; the
    direct light within its float32 bound (``direct_float32_bound``)."""
    scene = window_box(cell=0.5)
    pre = Portals.precompute(scene, {**QUICK, "bounces": 2, "indirect": "surface", "clusters": 24}, cache=False,
                             progress=False)
    surface = pre.surface_transfer()
    assert surface.n_patches == 24 and not surface.identity
    from prtlab.bench import transfer_csr
    from prtlab.portals._shade import shell_coefficients

    cube = shell_light(scene.environment, 8)
    albedo = np.asarray(pre.data["albedo"], dtype=np.float64)
    source_t = pre.direct_transfer(0, source=True)
    from prtlab.portals import direct_pass

    s_ref = surface.patch_source(direct_pass(source_t, albedo, cube, method="reference"))
    light = shell_coefficients(cube)
    s_abs = surface.patch_source((abs(transfer_csr(source_t)) @ np.abs(light)) * albedo)  # sums of |terms|
    s = pre.source_operator(0).apply(light)
    assert np.all(np.abs(s - s_ref) <= 1e-12 * s_abs)
    ours, ref = surface.frame(s, 2), surface.frame(s_ref, 2, method="reference")
    sums = np.abs(surface.bounce_sum(2).astype(np.float64))
    bound_light = np.einsum("cdk,dk->ck", sums, np.abs(s_ref))
    gather = surface.codes.astype(np.float64) * surface.scale.astype(np.float64)[:, None]
    bound = 2 * (surface.n_patches + 2) * np.finfo(np.float32).eps * albedo * (gather @ bound_light)
    assert np.all(np.abs(ours - ref) <= bound)
    numba_frame, ref_frame = pre.shade(bounces=2), pre.shade_shells([cube], 2, method="reference")
    from .test_shade import direct_float32_bound

    assert np.all(np.abs(numba_frame.direct["room"] - ref_frame.direct["room"])
                  <= direct_float32_bound(pre.direct_transfer(0), albedo, cube))
    assert np.all(np.abs(numba_frame.indirect["room"] - ref_frame.indirect["room"]) <= bound)
    with pytest.raises(ValueError, match="method must be 'numba' or 'reference', got 'fast'"):
        pre.shade_shells([cube], 2, method="fast")
    with pytest.raises(ValueError, match="method must be 'numba' or 'reference', got 'fast'"):
        surface.frame(s, 2, method="fast")


def test_cube_resolution_resolved_per_glossy_direct():
    """``cube_resolution=0``: 32 only where a cubemap per view direction is stored (``glossy_direct="views"`` with a
    glossy object), else 64."""
    glossy, diffuse = _glossy_box_scene(), window_box(cell=0.5)
    res = {(name, gd): Portals.resolved(scene, Portals.make_options({"glossy_direct": gd})).cube_resolution
           for name, scene in (("glossy", glossy), ("diffuse", diffuse)) for gd in ("lobe", "views")}
    assert res == {("glossy", "lobe"): 64, ("glossy", "views"): 32, ("diffuse", "lobe"): 64,
                   ("diffuse", "views"): 64}


@pytest.mark.parametrize("clusters", [24, 4096])
def test_task_frames_equal_serial_frames(monkeypatch, clusters):
    """``shade_shells`` of the default frame (one portal, ``indirect="surface"``) with :data:`prtlab._tasks.TASKS` (the
    direct pass and the surface indirect light as tasks on Python threads, :func:`shade_surface`) equals the frame
    with its passes one after another, bit for bit: clusters (near reads of patches) and the vertices as patches
    (the limited projection of the direct term), 1 and 2 bounces, two skies."""
    from prtlab import _tasks

    two_numba_threads()
    scene = window_box(cell=0.5)
    pre = Portals.precompute(scene, {**QUICK, "bounces": 2, "indirect": "surface", "clusters": clusters},
                             cache=False, progress=False)
    surface = pre.surface_transfer()
    assert surface.near is not None and len(surface.partners)
    assert surface.identity == (clusters > len(surface.patch))
    cubes = [shell_light(scene.environment, 8), tint(shell_light(scene.environment, 8), [1.0, 0.5, 0.2])]
    for bounces in (1, 2):
        for cube in cubes:
            frames = {}
            for tasks in (False, True):
                monkeypatch.setattr(_tasks, "TASKS", tasks)
                frames[tasks] = pre.shade_shells([cube], bounces)
            assert ("direct_and_indirect" in frames[True].info["timings"]) and \
                ("direct_and_indirect" not in frames[False].info["timings"])
            for part in ("direct", "indirect", "total"):
                a, b = getattr(frames[False], part)["room"], getattr(frames[True], part)["room"]
                np.testing.assert_array_equal(a.view(np.uint64), b.view(np.uint64))
