"""Tests of the stored basis radiance fields (``StoredBasisRadiance``, option ``storage``; issue 20).

Bounds come from the formats: float32 rounds a value with relative error at most ``u = 2^-24``; the int16
storage rounds ``S / scale`` to an integer, ``|S - scale q| <= scale / 2`` with ``scale`` the block's
``max |S| / 32767`` rounded up to float32. Eq. 13 is linear in ``S`` with non-negative interpolation
weights, so the basis irradiance errs by at most the same interpolation of the per-value error dotted with
``|transfer|``; the float64 kernel arithmetic adds at most ``1e-12`` of the sum of ``|terms|``.
"""

from __future__ import annotations

import numpy as np
import pytest

import prtlab.interreflection._pipeline as pipeline_module
from prtlab import sh
from prtlab.geometry import builtin_mesh
from prtlab.interreflection import Interreflection, basis_irradiance, fit_weights, outgoing_radiance
from prtlab.interreflection._fields import StoredBasisRadiance, store_basis_radiance
from prtlab.pipeline import FrameState
from prtlab.scene import Scene
from prtlab.shadowfields import sphere_grid

U32 = 2.0**-24
#: float64 rounding of the kernels' sums, relative to the sum of |terms| (16-64 terms of float64 products)
ARITHMETIC = 1e-12
GRID = sphere_grid(builtin_mesh("icosphere", subdivisions=1), n_radii=3, resolution=4)


def _field(rng, n_k=2, n_b=3, n2=16):
    """A random field with whole sample points at 0 (as behind a flat source) and blocks of mixed scales."""
    field = rng.normal(size=GRID.shape + (n_k, n_b, n2)) * 10.0 ** rng.uniform(-6, 1, GRID.shape + (n_k, n_b, 1))
    field[rng.random(GRID.shape) < 0.4] = 0.0
    field[0, 0, 0, 0, 0, 0] = 0.0  # a zero block at a stored point
    return field


def _per_value_error(stored: StoredBasisRadiance, dense64) -> np.ndarray:
    """The format's bound on ``|S - stored|`` per value (dense shape)."""
    if stored.storage == "float64":
        return np.zeros(stored.shape)
    if stored.storage == "float32":
        return U32 * np.abs(dense64)
    half = np.zeros((int(np.prod(stored.shape[:4])),) + stored.values.shape[1:])
    at = stored.rows.ravel()
    half[at >= 0] = 0.5 * stored.scale[at[at >= 0]].astype(np.float64)[..., None]
    return half.reshape(stored.shape)


@pytest.mark.parametrize("storage", ["float64", "float32", "int16"])
def test_stored_values_within_the_format_bound_and_zero_points_dropped(rng, storage):
    field = _field(rng)
    stored = store_basis_radiance(field, storage)
    zero = np.all(field.reshape(GRID.shape + (-1,)) == 0.0, axis=-1)
    np.testing.assert_array_equal(stored.rows < 0, zero)
    assert stored.storage == storage and len(stored.values) == np.count_nonzero(~zero)
    back = stored.dense()
    assert back.dtype == np.float64 and back.shape == field.shape
    err = np.abs(back - field)
    assert np.all(err <= _per_value_error(stored, field)), np.max(err - _per_value_error(stored, field))
    if storage == "int16":  # the step is the block's largest |S| over 32767, rounded up by at most one ulp
        peak = np.max(np.abs(field.reshape(-1, 6, 16)[stored.rows.ravel() >= 0]), axis=2)
        step = stored.scale.astype(np.float64)
        assert np.all(step >= peak / 32767) and np.all(step <= peak / 32767 * (1 + 2 * U32))
        assert stored.values.dtype == np.int16 and np.abs(stored.values).max() <= 32767
    again = StoredBasisRadiance.from_arrays(stored.to_arrays())
    np.testing.assert_array_equal(again.dense(), back)
    cut = stored.truncated(2, 3)
    np.testing.assert_array_equal(cut.dense(), back[..., :2, :9])


def test_storage_refuses_unknown_formats_and_shapes():
    with pytest.raises(ValueError, match=r"storage must be one of 'float64', 'float32', 'int16', got 'float16'"):
        store_basis_radiance(np.zeros(GRID.shape + (1, 1, 4)), "float16")
    with pytest.raises(ValueError, match=r"field must be \(n_r, 6, res, res, K, N, n\*n\), got shape \(2, 3\)"):
        store_basis_radiance(np.zeros((2, 3)), "int16")
    with pytest.raises(ValueError, match=r"not a stored basis radiance field"):
        StoredBasisRadiance.from_arrays({"shape": np.array([2, 3]), "rows": np.zeros(1), "values": np.zeros((1, 1, 1)),
                                         "scale": np.zeros((0, 1))})
    with pytest.raises(ValueError, match=r"option storage must be one of 'float64', 'float32', 'int16'"):
        pipeline_module.InterreflectionOptions(storage="float16")


def _points_and_transfer(rng, n=300, n_kp=2):
    points = GRID.center + rng.normal(size=(n, 3)) * GRID.radii[-1] * 0.6  # some beyond the outermost sphere
    return points, rng.normal(size=(n, n_kp, 16))


@pytest.mark.parametrize("storage", ["float64", "float32", "int16"])
def test_kernel_on_stored_fields_is_the_reference_tier(rng, storage):
    """The numba kernel on a stored field equals the float64 tier on its dense form (float64 rounding)."""
    stored = store_basis_radiance(_field(rng), storage)
    points, transfer = _points_and_transfer(rng)
    fast = basis_irradiance(stored, GRID, points, transfer)
    ref = basis_irradiance(stored.dense(), GRID, points, transfer, method="reference")
    terms = basis_irradiance(np.abs(stored.dense()), GRID, points, np.abs(transfer), method="reference")
    assert np.all(np.abs(fast - ref) <= ARITHMETIC * terms + 1e-300)


@pytest.mark.parametrize("storage", ["float32", "int16"])
def test_basis_irradiance_from_compact_storage_within_the_format_bound(rng, storage):
    field = _field(rng)
    stored = store_basis_radiance(field, storage)
    points, transfer = _points_and_transfer(rng)
    exact = basis_irradiance(field, GRID, points, transfer)
    compact = basis_irradiance(stored, GRID, points, transfer)
    bound = basis_irradiance(_per_value_error(stored, field), GRID, points, np.abs(transfer))
    terms = basis_irradiance(np.abs(field), GRID, points, np.abs(transfer))
    assert np.all(np.abs(compact - exact) <= bound + ARITHMETIC * terms)
    assert np.any(compact != exact)  # the formats do round


def _scene():
    return Scene.from_dict({
        "objects": [{"name": "floor", "mesh": {"builtin": "plane", "size": [4, 4], "resolution": [8, 8]},
                     "material": {"type": "diffuse", "albedo": [0.8, 0.3, 0.3]}},
                    {"name": "ball", "mesh": {"builtin": "icosphere", "radius": 0.5, "subdivisions": 2},
                     "transform": {"translate": [0, 0.7, 0]}, "material": {"type": "diffuse", "albedo": [0.7] * 3}}],
        "lights": [{"type": "environment", "sky": {"sun_elevation_deg": 40, "sun_azimuth_deg": 30, "turbidity": 3},
                    "scale": 0.1},
                   {"type": "area", "center": [0, 3, 0], "u": [0.4, 0, 0], "v": [0, 0, 0.4],
                    "radiance": [10.0, 10.0, 10.0]}],
        "camera": {"position": [0, 3, 6], "look_at": [0, 0, 0]},
    })


QUICK = dict(n_radii=6, resolution=6, degree=23, n_lights=32, n_basis=6, near_field=0.0, residual_rays=0)


def test_shaded_result_with_int16_storage_within_the_bound_of_float64_storage(monkeypatch):
    """One bounce on a ball over a floor: the direct light is the same (the other arrays are kept in float64),
    and ``|indirect_int16 - indirect_float64| <= sum_k' |h colour| sum_s sum_m B^s_m |w^s_m|`` with ``B^s`` the
    Eq. 13 bound of each pair (half a step per value, interpolated, dotted with ``|R^T transfer|``; the clamp
    ``max(0, .)`` and the fit are the same on both sides), plus float64 rounding."""
    scene = _scene()
    pre64 = Interreflection.precompute(scene, dict(QUICK, storage="float64"), cache=False, progress=False)
    pre16 = Interreflection.precompute(scene, dict(QUICK, storage="int16"), cache=False, progress=False)
    assert all(pre16.radiance[o.name].storage == "int16" for o in pre16.objects)
    state = FrameState.from_scene(scene)
    r64, r16 = pre64.shade(state, bounces=1), pre16.shade(state, bounces=1)

    bounds = {}
    original = pipeline_module.basis_irradiance

    def recording(field, grid, points, transfer, source_transform=None, method="numba"):
        value = original(field, grid, points, transfer, source_transform, method)
        R = np.asarray(source_transform.rotation, float)
        local = ((points - source_transform.translate) @ R) / float(source_transform.scale)
        t_obj = np.abs(sh.rotate(transfer, R.T, channels=False))
        err = _per_value_error(field, None)
        bounds[id(value)] = (original(err, grid, local, t_obj),
                             original(np.abs(field.dense()), grid, local, t_obj))
        return value

    monkeypatch.setattr(pipeline_module, "basis_irradiance", recording)
    pre16.reuse = type(pre16.reuse)()  # recompute the pairs under the recorder
    geo = pre16._frame_geometry(state)
    occ = pre16._occlusion(geo)
    phi, _ = pre16.basis_irradiance_step(geo, occ)
    light_k, _ = pre16.direct_step(state, geo, pre16.direct_transfer(geo, occ, state.lights))
    weights = {o.name: fit_weights(pre16.bases[o.name], light_k[o.name], pre16.seps[o.name].colour)
               for o in pre16.objects}
    for o in pre16.objects:
        name = o.name
        np.testing.assert_array_equal(r16.direct[name], r64.direct[name])
        bound_lk = np.zeros(light_k[name].shape)
        terms_lk = np.zeros(light_k[name].shape)
        for s, value in phi[name].items():
            b, t = bounds[id(value)]
            w = np.abs(weights[s]).reshape(-1, 3)
            bound_lk += b.reshape(len(b), b.shape[1], -1) @ w
            terms_lk += t.reshape(len(t), t.shape[1], -1) @ w
        h, colour = np.abs(geo[name]["h"]), np.abs(pre16.seps[name].colour)
        bound = outgoing_radiance(bound_lk, h, colour)
        slack = ARITHMETIC * (outgoing_radiance(terms_lk, h, colour) + np.abs(r64.indirect[name]))
        diff = np.abs(r16.indirect[name] - r64.indirect[name])
        assert np.all(diff <= bound + slack), (name, np.max(diff - bound - slack))
        assert np.max(diff) > 0.0


def test_cache_keys_tell_the_formats_apart():
    """A cache file of another storage, or of the dense float64 layout before format 4, is never read as this one."""
    from prtlab.cache import cache_key

    scene = _scene()
    keys = {storage: cache_key(*Interreflection.cache_key_parts(
        scene, pipeline_module.InterreflectionOptions(**dict(QUICK, storage=storage))))
        for storage in ("float64", "float32", "int16")}
    assert len(set(keys.values())) == 3
    assert Interreflection.format_version >= 4
    parts = Interreflection.cache_key_parts(scene, pipeline_module.InterreflectionOptions())
    assert Interreflection.format_version in parts and parts[-1]["storage"] == "int16"


def test_objects_of_one_mesh_share_one_entry_and_shade_as_when_stored_apart():
    """Two balls of one mesh and different albedos: one stored entry (``same_as``) holding what the second ball
    computes alone, and the same shading as with each ball's entry stored apart."""
    d = _scene().to_dict()
    ball2 = dict(d["objects"][1], name="ball2", transform={"translate": [1.2, 0.7, 0.3]},
                 material={"type": "diffuse", "albedo": [0.2, 0.6, 0.9]})
    scene = Scene.from_dict({**d, "objects": d["objects"] + [ball2]})
    pre = Interreflection.precompute(scene, dict(QUICK, storage="float64"), cache=False, progress=False)
    assert set(pre.data["ball2"]) == {"same_as"} and int(pre.data["ball2"]["same_as"]) == 1
    assert pre.radiance["ball2"] is pre.radiance["ball"] and pre.entries["ball2"] is pre.data["ball"]
    alone = Interreflection.compute(Scene.from_dict({**d, "objects": [ball2]}), pre.options, progress=False)["ball2"]
    for key in ("pca_basis", "self_visibility", "self_irradiance"):
        np.testing.assert_array_equal(alone[key], pre.data["ball"][key])
    np.testing.assert_array_equal(alone["basis_radiance"]["values"], pre.data["ball"]["basis_radiance"]["values"])
    apart = Interreflection(scene, pre.options, {**pre.data, "ball2": alone})
    a, b = pre.shade(bounces=1), apart.shade(bounces=1)
    for name in ("floor", "ball", "ball2"):
        np.testing.assert_array_equal(a.total[name], b.total[name])


def test_stored_fields_read_back_from_the_cache_shade_the_same(tmp_path):
    from prtlab.cache import Cache

    cache = Cache(tmp_path, progress=False)
    d = _scene().to_dict()
    scene = Scene.from_dict({**d, "objects": d["objects"] + [dict(d["objects"][1], name="ball2",
                                                                   transform={"translate": [1.2, 0.7, 0.3]})]})
    made = Interreflection.precompute(scene, QUICK, cache=cache, progress=False)
    read = Interreflection.precompute(scene, QUICK, cache=cache, progress=False)
    stored = read.radiance["ball"]
    assert stored.storage == "int16" and stored.values.dtype == np.int16 and stored.rows.dtype == np.int32
    assert read.radiance["ball2"] is stored
    a, b = made.shade(bounces=1), read.shade(bounces=1)
    for name in ("floor", "ball", "ball2"):
        np.testing.assert_array_equal(a.total[name], b.total[name])
