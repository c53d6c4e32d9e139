"""Mitsuba 3 reference adapter: the same scene, rendered by an independent renderer.

:func:`to_mitsuba` translates a :class:`prtlab.Scene` into a ``mi.load_dict``
description; :func:`shade_mitsuba` estimates the per-vertex outgoing radiance
with Mitsuba's own ray tracer, emitter sampling and ``path`` integrator;
:func:`render_mitsuba` renders the scene camera.

Variant
-------
Per-vertex estimation traces millions of independent rays, which the JIT
variant ``llvm_ad_rgb`` runs as wide SIMD batches, orders of magnitude faster
than the per-ray Python loop the ``scalar_rgb`` variant needs. Dr.Jit's LLVM
backend must find an LLVM shared library it accepts; Debian's ``libllvm19``
works, so when it is present (and Dr.Jit is not imported yet) prtlab points
``DRJIT_LIBLLVM_PATH`` at it before importing Dr.Jit. If the user already set
``DRJIT_LIBLLVM_PATH``, that choice is kept. Otherwise prtlab falls back to
``scalar_rgb`` (slow but always available). ``PRTLAB_MITSUBA_VARIANT`` or the
``variant=`` argument force a variant. Without Mitsuba at all, every entry
point raises :class:`MitsubaUnavailable` saying what to install.
"""

from __future__ import annotations

import os
import sys
import time
import warnings

import numpy as np

from prtlab._validate import MemoryNeed, check_int, check_memory
from prtlab.scene import AreaLight, EnvironmentLight, PointLight, Scene, ShadeResult

from ._estimators import BYTES_PER_PATH

__all__ = [
    "MitsubaUnavailable",
    "mitsuba_variant",
    "to_mitsuba",
    "shade_mitsuba",
    "render_mitsuba",
]

#: LLVM libraries known to work with Dr.Jit (Debian's libllvm19), in order of preference.
LLVM_LIBRARIES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19",
)

_SUPPORTED_VARIANTS = ("llvm_ad_rgb", "scalar_rgb")


class MitsubaUnavailable(ImportError):
    """Mitsuba 3 (the optional ``[reference]`` extra) is not installed or cannot start."""


# --------------------------------------------------------------------------- variant selection


def _choose_variant(requested, environ, exists, drjit_imported: bool) -> tuple[str, str | None]:
    """Pick the Mitsuba variant and the LLVM library to announce to Dr.Jit.

    Pure logic (no imports, no side effects) so that both branches are unit tested.

    Parameters
    ----------
    requested : str or None
        ``variant=`` argument; falls back to ``environ["PRTLAB_MITSUBA_VARIANT"]``.
    environ : mapping
        The process environment.
    exists : callable
        ``exists(path) -> bool``.
    drjit_imported : bool
        Whether Dr.Jit is imported already (then ``DRJIT_LIBLLVM_PATH`` can no longer be set).

    Returns
    -------
    variant : str
        ``"llvm_ad_rgb"`` or ``"scalar_rgb"``.
    llvm_path : str or None
        Library to put in ``DRJIT_LIBLLVM_PATH`` before importing Dr.Jit (None: leave it alone).
    """
    requested = requested or environ.get("PRTLAB_MITSUBA_VARIANT") or None
    if requested is not None and requested not in _SUPPORTED_VARIANTS:
        raise ValueError(
            f"variant must be one of {_SUPPORTED_VARIANTS}, got {requested!r}; "
            "prtlab's adapter needs an RGB CPU variant"
        )
    user_path = environ.get("DRJIT_LIBLLVM_PATH")
    if user_path:
        # The user chose a library: trust it.
        return (requested or "llvm_ad_rgb"), None
    found = next((p for p in LLVM_LIBRARIES if exists(p)), None)
    if requested == "scalar_rgb":
        return "scalar_rgb", None
    if found is None or drjit_imported:
        if requested == "llvm_ad_rgb":
            raise MitsubaUnavailable(
                "variant 'llvm_ad_rgb' needs an LLVM library Dr.Jit accepts: install Debian's libllvm19 "
                "(apt-get install libllvm19) and set DRJIT_LIBLLVM_PATH before importing drjit, "
                "or use variant='scalar_rgb'"
            )
        return "scalar_rgb", None
    return "llvm_ad_rgb", found


def _announce_llvm() -> None:
    """Point ``DRJIT_LIBLLVM_PATH`` at a working LLVM if nobody did and Dr.Jit is not imported yet.

    Runs when :mod:`prtlab.reference` is imported (it only sets an environment
    variable; nothing is imported), so that Mitsuba imported later by the user
    or by a test's ``importorskip`` still gets the fast variant.
    """
    if "drjit" in sys.modules or os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    found = next((p for p in LLVM_LIBRARIES if os.path.exists(p)), None)
    if found is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = found


_announce_llvm()


def _import_mitsuba(variant: str | None = None):
    """Import Mitsuba with the chosen variant set; return ``(mi, dr)``."""
    variant_arg = variant
    variant, llvm_path = _choose_variant(variant, os.environ, os.path.exists, "drjit" in sys.modules)
    if llvm_path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm_path
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - exercised only without mitsuba
        raise MitsubaUnavailable(
            "the Mitsuba reference needs Mitsuba 3: pip install 'prtlab[reference]' (or pip install mitsuba); "
            f"import failed with: {exc}"
        ) from exc
    if variant not in mi.variants():  # pragma: no cover - depends on the wheel
        raise MitsubaUnavailable(f"this Mitsuba build has no variant {variant!r}; it has {mi.variants()}")
    try:
        mi.set_variant(variant)
    except Exception as exc:  # pragma: no cover - only when the LLVM backend cannot start
        requested = variant_arg or os.environ.get("PRTLAB_MITSUBA_VARIANT")
        if variant != "llvm_ad_rgb" or requested:
            raise MitsubaUnavailable(f"Mitsuba variant {variant!r} failed to start: {exc}") from exc
        warnings.warn(f"Mitsuba's llvm_ad_rgb failed to start ({exc}); falling back to scalar_rgb (slow)",
                      RuntimeWarning, stacklevel=2)
        mi.set_variant("scalar_rgb")
    _register_phong(mi, dr)
    return mi, dr


def mitsuba_variant(variant: str | None = None) -> str:
    """The Mitsuba variant prtlab uses (importing Mitsuba if needed)."""
    mi, _ = _import_mitsuba(variant)
    return mi.variant()


# --------------------------------------------------------------------------- normalised Phong BSDF

_REGISTERED: set[str] = set()


def _register_phong(mi, dr) -> None:
    """Register ``prtlab_phong`` (the design's normalised Phong) in the current variant."""
    if mi.variant() in _REGISTERED:
        return

    class NormalisedPhong(mi.BSDF):
        """``f = kd/pi + ks (e+2)/(2 pi) max(0, reflect(wi) . wo)^e``, front side only.

        Sampling picks the diffuse lobe (cosine) or the Phong lobe about the
        mirror direction (pdf ``(e+1)/(2 pi) cos^e``) with probability
        proportional to the mean of ``kd`` and ``ks``.
        """

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            kd = props["kd"]
            ks = props["ks"]
            self.kd = mi.Color3f(kd[0], kd[1], kd[2])
            self.ks = mi.Color3f(ks[0], ks[1], ks[2])
            self.exponent = mi.Float(props["exponent"])
            wd = float(sum(kd)) / 3.0
            ws = float(sum(ks)) / 3.0
            self.p_spec = mi.Float(ws / (wd + ws) if wd + ws > 0 else 0.0)
            diffuse = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [diffuse, glossy]
            self.m_flags = diffuse | glossy

        def _lobe_pdf(self, wi, wo):
            r = mi.reflect(wi)
            c = dr.maximum(dr.dot(r, wo), 0.0)
            return (self.exponent + 1.0) * dr.inv_two_pi * dr.power(c, self.exponent), c

        def eval(self, ctx, si, wo, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            co = mi.Frame3f.cos_theta(wo)
            c = dr.maximum(dr.dot(mi.reflect(si.wi), wo), 0.0)
            f = self.kd * dr.inv_pi + self.ks * ((self.exponent + 2.0) * dr.inv_two_pi * dr.power(c, self.exponent))
            return dr.select(active & (ci > 0) & (co > 0), f * co, 0.0)

        def pdf(self, ctx, si, wo, active=True):
            ci = mi.Frame3f.cos_theta(si.wi)
            co = mi.Frame3f.cos_theta(wo)
            lobe, _ = self._lobe_pdf(si.wi, wo)
            p = (1.0 - self.p_spec) * dr.maximum(co, 0.0) * dr.inv_pi + self.p_spec * lobe
            return dr.select(active & (ci > 0) & (co > 0), p, 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            spec = sample1 < self.p_spec
            wo_diffuse = mi.warp.square_to_cosine_hemisphere(sample2)
            cos_a = dr.power(sample2.x, 1.0 / (self.exponent + 1.0))
            sin_a = dr.safe_sqrt(1.0 - cos_a * cos_a)
            sin_p, cos_p = dr.sincos(dr.two_pi * sample2.y)
            local = mi.Vector3f(sin_a * cos_p, sin_a * sin_p, cos_a)
            wo_spec = mi.Frame3f(mi.reflect(si.wi)).to_world(local)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = dr.select(spec, wo_spec, wo_diffuse)
            bs.eta = 1.0
            bs.sampled_component = dr.select(spec, mi.UInt32(1), mi.UInt32(0))
            bs.sampled_type = dr.select(
                spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection), mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            )
            value, bs.pdf = self.eval_pdf(ctx, si, bs.wo, active)
            ok = active & (bs.pdf > 0)
            return bs, dr.select(ok, value / dr.select(ok, bs.pdf, 1.0), 0.0)

        def traverse(self, callback):
            pass

        def to_string(self):
            return "NormalisedPhong[]"

    mi.register_bsdf("prtlab_phong", lambda props: NormalisedPhong(props))
    _REGISTERED.add(mi.variant())


# --------------------------------------------------------------------------- scene translation


def _check_scene(scene) -> None:
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a prtlab.Scene, got {type(scene).__name__}; build one with prtlab.load_scene")
    if not [obj for obj in scene.objects if not obj.portal]:
        raise ValueError("scene has no objects (other than portals): there is nothing to shade")


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(c) for c in np.asarray(value, dtype=np.float64).reshape(3)]}


def _bsdf_dict(obj) -> dict:
    mat = obj.material
    if mat.type == "diffuse":
        inner = {"type": "diffuse", "reflectance": _rgb(mat.albedo)}
    elif mat.type == "phong":
        inner = {
            "type": "prtlab_phong",
            "kd": [float(c) for c in mat.kd],
            "ks": [float(c) for c in mat.ks],
            "exponent": float(mat.exponent),
        }
    else:
        raise NotImplementedError(
            f"object {obj.name!r}: material type {mat.type!r} has no Mitsuba translation (diffuse and phong do)"
        )
    return {"type": "twosided", "material": inner}


def _mesh(mi, obj, smooth_normals: bool):
    verts = np.ascontiguousarray(obj.world_vertices(), dtype=np.float32)
    faces = np.ascontiguousarray(np.asarray(obj.mesh.faces), dtype=np.uint32)
    if len(faces) == 0:
        raise ValueError(f"object {obj.name!r} has a mesh with no faces")
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf_dict(obj))
    mesh = mi.Mesh(obj.name, len(verts), len(faces), props=props, has_vertex_normals=smooth_normals)
    params = mi.traverse(mesh)
    params["vertex_positions"] = type(params["vertex_positions"])(verts.ravel())
    params["faces"] = type(params["faces"])(faces.ravel())
    if smooth_normals:
        normals = np.ascontiguousarray(obj.world_normals(), dtype=np.float32)
        params["vertex_normals"] = type(params["vertex_normals"])(normals.ravel())
    params.update()
    return mesh


def _rectangle_to_world(mi, light: AreaLight):
    """Affine map of Mitsuba's rectangle ([-1,1]^2 in local xy, normal +z) onto the parallelogram."""
    n = light.normal
    m = np.eye(4)
    m[:3, 0] = light.u
    m[:3, 1] = light.v
    m[:3, 2] = n
    m[:3, 3] = light.center
    return mi.ScalarTransform4f(m.tolist())


def _camera_to_world(mi, camera):
    return mi.ScalarTransform4f().look_at(
        origin=[float(c) for c in camera.position],
        target=[float(c) for c in camera.look_at],
        up=[float(c) for c in camera.up],
    )


def _max_depth(bounces: int, from_camera: bool) -> int:
    # Mitsuba's depth counts path segments from the sensor: depth 1 sees emitters directly.
    return int(bounces) + (2 if from_camera else 1)


def to_mitsuba(scene, *, bounces: int | None = None, smooth_normals: bool = True, sensor: bool = True,
               spp: int = 16, variant: str | None = None) -> dict:
    """Translate a prtlab scene into a Mitsuba 3 ``load_dict`` description.

    Parameters
    ----------
    scene : prtlab.Scene
    bounces : int, optional
        Indirect bounces of the ``path`` integrator seen from the camera
        (``max_depth = bounces + 2``); None leaves Mitsuba's default (unbounded).
    smooth_normals : bool
        Give the Mitsuba meshes the scene's vertex normals as shading normals
        (barycentric interpolation, as prtlab's own estimators do at path
        vertices; default). False: flat triangles, the geometric normal.
    sensor : bool
        Include a perspective sensor matching ``scene.camera``.
    spp : int
        Samples per pixel of the sensor's sampler.
    variant : str, optional
        Mitsuba variant (see the module notes).

    Returns
    -------
    dict
        Ready for ``mi.load_dict``. Meshes are ``mi.Mesh`` objects in world
        space with the input vertex order and faces; every BSDF is wrapped
        ``twosided``; area lights are ``rectangle`` shapes with an ``area``
        emitter and a black BSDF (they reflect nothing).

    Notes
    -----
    The equirect environment maps directly to ``envmap`` with the identity
    ``to_world``: Mitsuba's lookup is ``u = atan2(x, -z) / (2 pi)``,
    ``v = acos(y) / pi`` with bilinear pixel samples, prtlab's convention
    exactly (tested texel by texel in ``tests/reference/test_mitsuba.py``).
    The rectangle's ``to_world`` has columns ``(u, v, n, center)`` with
    ``n = normalize(u x v)``, so it covers ``center + s u + t v`` and emits
    along ``n``. The sensor uses ``fov_axis = "y"``: prtlab's ``fov_deg`` is vertical.
    """
    _check_scene(scene)
    mi, _ = _import_mitsuba(variant)
    desc: dict = {"type": "scene"}
    desc["integrator"] = {"type": "path"}
    if bounces is not None:
        bounces = _check_bounces(bounces)
        desc["integrator"].update(max_depth=_max_depth(bounces, True), rr_depth=max(5, _max_depth(bounces, True)))
    for i, obj in enumerate(scene.objects):
        if obj.portal:  # an opening, not a surface
            continue
        desc[f"object_{i}"] = _mesh(mi, obj, smooth_normals)
    for i, light in enumerate(scene.lights):
        desc[f"light_{i}"] = _light(mi, i, light)
    if sensor:
        desc["sensor"] = _sensor(mi, scene.camera, spp)
    return desc


def _light(mi, i: int, light) -> dict:
    """The ``load_dict`` entry of scene light ``i``."""
    if isinstance(light, EnvironmentLight):
        if light.constant is not None:
            return {"type": "constant", "radiance": _rgb(light.constant)}
        image = np.ascontiguousarray(np.asarray(light.image, dtype=np.float32))
        return {"type": "envmap", "bitmap": mi.Bitmap(image)}
    if isinstance(light, AreaLight):
        return {
            "type": "rectangle",
            "to_world": _rectangle_to_world(mi, light),
            "bsdf": {"type": "diffuse", "reflectance": _rgb(np.zeros(3))},
            "emitter": {"type": "area", "radiance": _rgb(light.radiance)},
        }
    if isinstance(light, PointLight):
        return {"type": "point", "position": [float(c) for c in light.position], "intensity": _rgb(light.intensity)}
    raise NotImplementedError(f"light {i} of type {type(light).__name__} has no Mitsuba translation")


def _sensor(mi, cam, spp: int) -> dict:
    """A perspective sensor (vertical ``fov``) and box-filtered RGB film matching ``cam``."""
    width, height = (int(r) for r in cam.resolution)
    return {
        "type": "perspective",
        "fov": float(cam.fov_deg),
        "fov_axis": "y",
        "to_world": _camera_to_world(mi, cam),
        "sampler": {"type": "independent", "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
    }


def _load(mi, scene, **kwargs):
    return mi.load_dict(to_mitsuba(scene, variant=mi.variant(), **kwargs))


# --------------------------------------------------------------------------- per-vertex estimator


def _check_bounces(bounces) -> int:
    return check_int(bounces, "bounces", 0, meaning="indirect bounces; 0 = direct only")


def _shaded_objects(scene):
    """The objects that get radiance: every object except portals (openings, not surfaces)."""
    return [obj for obj in scene.objects if not obj.portal]


def _vertex_data(scene):
    """Concatenate every object's vertices, normals, view directions and material parameters."""
    cam = np.asarray(scene.camera.position, dtype=np.float64)
    pos, nrm, kd, ks, ex, counts = [], [], [], [], [], []
    for obj in _shaded_objects(scene):
        p = obj.world_shading_points()
        n = obj.world_normals()
        n = n / np.linalg.norm(n, axis=1, keepdims=True)
        m = obj.material
        k = len(p)
        pos.append(p)
        nrm.append(n)
        if m.type == "phong":
            kd.append(np.broadcast_to(m.kd, (k, 3)))
            ks.append(np.broadcast_to(m.ks, (k, 3)))
            ex.append(np.full(k, float(m.exponent)))
        elif m.type == "diffuse":
            kd.append(np.broadcast_to(m.albedo, (k, 3)))
            ks.append(np.zeros((k, 3)))
            ex.append(np.zeros(k))
        else:
            raise NotImplementedError(f"object {obj.name!r}: material type {m.type!r} is not supported")
        counts.append(k)
    pos = np.concatenate(pos)
    nrm = np.concatenate(nrm)
    if not np.all(np.isfinite(pos)) or not np.all(np.isfinite(nrm)):
        raise ValueError("scene vertices or normals contain NaN or inf; check the meshes and transforms")
    wo = cam - pos
    wo /= np.maximum(np.linalg.norm(wo, axis=1, keepdims=True), 1e-300)
    return pos, nrm, wo, np.concatenate(kd), np.concatenate(ks), np.concatenate(ex), counts


def _scene_extent(scene, pos) -> float:
    pts = [pos]
    for light in scene.area_lights:
        pts.append(np.stack([light.center + light.u + light.v, light.center - light.u - light.v]))
    allp = np.concatenate(pts)
    return float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0))) or 1.0


def _frame(n):
    """Orthonormal tangent frames (t, b) for unit normals n (..., 3) (Duff et al. 2017)."""
    sign = np.where(n[..., 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t = np.stack([1.0 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]], axis=-1)
    bb = np.stack([b, sign + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    return t, bb


def _brdf_cos(wi, n, wo, kd, ks, ex):
    """Normalised Phong (ks = 0: Lambert) times max(0, cos) at the vertex; shapes (..., 3)."""
    cos_i = np.einsum("...k,...k->...", wi, n)
    r = 2.0 * cos_i[..., None] * n - wi
    c = np.maximum(np.einsum("...k,...k->...", r, wo), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        lobe = np.where(ks.any(axis=-1), (ex + 2.0) / (2.0 * np.pi) * np.power(c, ex), 0.0)
    f = kd / np.pi + ks * lobe[..., None]
    return f * np.maximum(cos_i, 0.0)[..., None]


def _spec_prob(kd, ks):
    wd = kd.mean(axis=-1)
    ws = ks.mean(axis=-1)
    tot = wd + ws
    return np.where(tot > 0, ws / np.where(tot > 0, tot, 1.0), 0.0)


def _bsdf_pdf(wi, n, wo, kd, ks, ex):
    cos_i = np.einsum("...k,...k->...", wi, n)
    ps = _spec_prob(kd, ks)
    r = 2.0 * np.einsum("...k,...k->...", wo, n)[..., None] * n - wo  # mirror of the view direction
    c = np.maximum(np.einsum("...k,...k->...", r, wi), 0.0)
    lobe = (ex + 1.0) / (2.0 * np.pi) * np.power(c, ex)
    p = (1.0 - ps) * np.maximum(cos_i, 0.0) / np.pi + ps * lobe
    return np.where(cos_i > 0, p, 0.0)


def _sample_bsdf(rng, n, wo, kd, ks, ex):
    """Directions from the vertex BRDF mixture: cosine lobe, or the Phong lobe about reflect(wo)."""
    shape = n.shape[:-1]
    u0, u1, u2 = rng.random(shape), rng.random(shape), rng.random(shape)
    ps = _spec_prob(kd, ks)
    spec = u0 < ps
    # cosine-weighted hemisphere about n
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    t, b = _frame(n)
    cz = np.sqrt(np.maximum(1.0 - u1, 0.0))
    wd = (r * np.cos(phi))[..., None] * t + (r * np.sin(phi))[..., None] * b + cz[..., None] * n
    # power-cosine lobe about the mirror direction of wo
    axis = 2.0 * np.einsum("...k,...k->...", wo, n)[..., None] * n - wo
    cos_a = np.power(u1, 1.0 / (ex + 1.0))
    sin_a = np.sqrt(np.maximum(1.0 - cos_a**2, 0.0))
    ta, ba = _frame(axis)
    ws = (sin_a * np.cos(phi))[..., None] * ta + (sin_a * np.sin(phi))[..., None] * ba + cos_a[..., None] * axis
    wi = np.where(spec[..., None], ws, wd)
    return wi / np.linalg.norm(wi, axis=-1, keepdims=True)


def _power_heuristic(pdf_a, pdf_b):
    """Veach's power heuristic (beta = 2): ``pa^2 / (pa^2 + pb^2)``, 0 where both pdfs vanish."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    total = a2 + b2
    return np.where(total > 0, a2 / np.where(total > 0, total, 1.0), 0.0)


def _to_vec(mi, cls, a):
    a = np.ascontiguousarray(np.asarray(a, dtype=np.float32).T)
    return cls(a[0], a[1], a[2])


def _np3(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float64).reshape(3, -1).T


def _trace_llvm(mi, dr, mscene, integrator, points, normals, offset, dirs, em_sample, max_depth, seed):
    """One wavefront: emitter sampling at the vertices, then BSDF rays and the path integrator."""
    count = len(points)
    ref = dr.zeros(mi.Interaction3f, count)
    ref.p = _to_vec(mi, mi.Point3f, points)
    ref.n = _to_vec(mi, mi.Normal3f, normals)
    ref.time = 0.0
    s2 = mi.Point2f(em_sample[:, 0].astype(np.float32), em_sample[:, 1].astype(np.float32))
    ds, em_weight = mscene.sample_emitter_direction(ref, s2, True)
    out = {
        "em_dir": _np3(ds.d),
        "em_weight": _np3(em_weight),
        "em_pdf": np.asarray(ds.pdf, dtype=np.float64),
        "em_delta": np.asarray(ds.delta, dtype=bool),
    }
    ray = mi.Ray3f(_to_vec(mi, mi.Point3f, points + offset * normals), _to_vec(mi, mi.Vector3f, dirs))
    si = mscene.ray_intersect(ray)
    emitter = si.emitter(mscene)
    has_em = emitter != None  # noqa: E711 (Dr.Jit pointer comparison)
    le = emitter.eval(si, has_em)
    ds_b = mi.DirectionSample3f(mscene, si, ref)
    out["bsdf_le"] = _np3(le)
    out["bsdf_em_pdf"] = np.asarray(mscene.pdf_emitter_direction(ref, ds_b, has_em), dtype=np.float64)
    surface = si.is_valid() & ~has_em
    out["surface"] = np.asarray(surface, dtype=bool)
    if max_depth > 1:
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(int(seed), count)
        radiance, _, _ = integrator.sample(mscene, sampler, mi.RayDifferential3f(ray), None, surface)
        out["indirect"] = np.where(out["surface"][:, None], _np3(radiance), 0.0)
    else:
        out["indirect"] = np.zeros((count, 3))
    return out


def _trace_scalar(mi, dr, mscene, integrator, points, normals, offset, dirs, em_sample, max_depth, seed):
    """The same as :func:`_trace_llvm`, one ray at a time (the ``scalar_rgb`` fallback)."""
    count = len(points)
    out = {
        "em_dir": np.zeros((count, 3)), "em_weight": np.zeros((count, 3)), "em_pdf": np.zeros(count),
        "em_delta": np.zeros(count, bool), "bsdf_le": np.zeros((count, 3)), "bsdf_em_pdf": np.zeros(count),
        "surface": np.zeros(count, bool), "indirect": np.zeros((count, 3)),
    }
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(int(seed))
    for k in range(count):
        ref = dr.zeros(mi.Interaction3f)
        ref.p = mi.Point3f(*(float(c) for c in points[k]))
        ref.n = mi.Normal3f(*(float(c) for c in normals[k]))
        ref.time = 0.0
        ds, w = mscene.sample_emitter_direction(ref, mi.Point2f(*(float(c) for c in em_sample[k])), True)
        out["em_dir"][k] = np.asarray(ds.d)
        out["em_weight"][k] = np.asarray(w)
        out["em_pdf"][k] = float(ds.pdf)
        out["em_delta"][k] = bool(ds.delta)
        origin = points[k] + offset * normals[k]
        ray = mi.Ray3f(mi.Point3f(*(float(c) for c in origin)), mi.Vector3f(*(float(c) for c in dirs[k])))
        si = mscene.ray_intersect(ray)
        emitter = si.emitter(mscene)
        if emitter is not None:
            out["bsdf_le"][k] = np.asarray(emitter.eval(si))
            out["bsdf_em_pdf"][k] = float(mscene.pdf_emitter_direction(ref, mi.DirectionSample3f(mscene, si, ref)))
        elif si.is_valid():
            out["surface"][k] = True
            if max_depth > 1:
                radiance, _, _ = integrator.sample(mscene, sampler, mi.RayDifferential3f(ray), None, True)
                out["indirect"][k] = np.asarray(radiance)
    return out


def shade_mitsuba(scene, bounces: int = 1, spp: int = 64, seed: int = 0, *, n_samples: int | None = None,
                  chunk_rays: int = 1 << 20, offset: float | None = None, variant: str | None = None,
                  progress: bool = False) -> ShadeResult:
    """Per-vertex outgoing radiance estimated with Mitsuba 3.

    (Long for the estimator's Notes; the code is 50 lines: validation, the chunk loop, the result.)

    Parameters
    ----------
    scene : prtlab.Scene
    bounces : int
        Indirect bounces (0 = direct light only).
    spp : int
        Samples per vertex (each: one emitter sample and one BRDF-sampled ray), >= 2.
    seed : int
        Seed of every random number used (numpy and Mitsuba's sampler).
    n_samples : int, optional
        Alias of ``spp`` (the name :func:`shade_reference` uses), so that
        ``prtlab.shade(scene, method=m, n_samples=n)`` works for both references.
    chunk_rays : int
        Rays per Dr.Jit wavefront (memory bound).
    offset : float, optional
        Ray-origin offset along the vertex normal; default ``1e-4`` times the scene diagonal.
    variant : str, optional
        ``"llvm_ad_rgb"`` or ``"scalar_rgb"`` (default: see the module notes).
    progress : bool
        Show a progress bar over the chunks.

    Returns
    -------
    ShadeResult
        ``direct``, ``indirect``, ``total`` ``(n_vertices, 3)`` per object and
        ``stderr[part][object]`` of the same shapes (standard error of the mean over the spp samples).

    Notes
    -----
    With ``n`` the vertex normal, ``wo`` the direction to the camera and
    ``f`` the material's BRDF (shaded on the side ``n`` points to)::

        L_o = int_{n . wi > 0} f(wi, wo) L_i(wi) (n . wi) dwi

    Direct light (emission arriving straight at the vertex: environment,
    area lights, point lights) is estimated by multiple importance sampling
    (power heuristic, Veach 1997 Sec. 9.2.4; why not the balance heuristic:
    ``docs/notes/reference.md``) of ``scene.sample_emitter_direction`` (with a
    visibility test) and the BRDF-sampled ray's emitter hit. Indirect light
    (>= 1 bounce) is, for BRDF rays that hit a non-emitting surface, the
    ``path`` integrator's radiance along that ray with ``max_depth =
    bounces + 1``. BRDF rays hitting an area light or the sky add nothing
    indirect, so ``total = direct + indirect`` counts every path once.

    The vertex BRDF is sampled as a mixture of the cosine lobe (probability
    ``1 - p``) and the Phong lobe ``(e+1)/(2 pi) cos^e`` about the mirror
    direction of ``wo`` (probability ``p = mean(ks) / (mean(kd) + mean(ks))``).
    """
    _check_scene(scene)
    bounces = _check_bounces(bounces)
    spp = check_int(spp if n_samples is None else n_samples, "spp (n_samples)", 2,
                    meaning="standard errors need two samples")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool):
        raise TypeError(f"seed must be an int, got {seed!r}")
    if int(chunk_rays) < 1:
        raise ValueError(f"chunk_rays must be >= 1, got {chunk_rays}")
    n_shaded = sum(o.n_vertices for o in scene.objects if not o.portal)
    per_chunk = max(1, int(chunk_rays) // spp)  # a chunk holds every sample of its vertices
    check_memory("mitsuba", {"n_samples": spp},
                 [MemoryNeed("the ray wavefront", float(min(n_shaded, per_chunk) * spp) * BYTES_PER_PATH,
                             ("n_samples",))], f"{n_shaded:,} vertices")
    mi, dr = _import_mitsuba(variant)
    start = time.perf_counter()
    pos, nrm, wo, kd, ks, ex, counts = _vertex_data(scene)
    if offset is None:
        offset = 1e-4 * _scene_extent(scene, pos)
    if not np.isfinite(offset) or offset < 0:
        raise ValueError(f"offset must be a finite float >= 0, got {offset}")
    tracer = _vertex_tracer(mi, dr, scene, bounces, offset)
    rng = np.random.default_rng(seed)
    n_vert = len(pos)
    means = {p: np.zeros((n_vert, 3)) for p in ("direct", "indirect", "total")}
    errors = {p: np.zeros((n_vert, 3)) for p in ("direct", "indirect", "total")}
    starts = range(0, n_vert, per_chunk)
    if progress:
        from tqdm.auto import tqdm

        starts = tqdm(starts, desc=f"mitsuba B={bounces}", unit="chunk")
    for chunk, lo in enumerate(starts):
        idx = np.arange(lo, min(n_vert, lo + per_chunk))
        samples = (np.repeat(a[idx], spp, axis=0) for a in (pos, nrm, wo, kd, ks, ex))
        chunk_seed = (int(seed) * 1_000_003 + chunk) & 0x7FFFFFFF
        direct, indirect = _chunk_samples(tracer, rng, *samples, chunk_seed=chunk_seed)
        for part, vals in (("direct", direct), ("indirect", indirect), ("total", direct + indirect)):
            # every sample of a vertex is in this chunk: two-pass mean and standard error
            vals = vals.reshape(len(idx), spp, 3)
            means[part][idx] = vals.mean(axis=1)
            errors[part][idx] = vals.std(axis=1, ddof=1) / np.sqrt(spp)

    result = ShadeResult.from_vertex_arrays([o.name for o in _shaded_objects(scene)], counts, means, errors)
    result.info.update(
        method="mitsuba", variant=mi.variant(), bounces=bounces, spp=spp, seed=int(seed),
        offset=float(offset), seconds=time.perf_counter() - start, mitsuba_version=mi.__version__,
    )
    return result


def _vertex_tracer(mi, dr, scene, bounces: int, offset: float):
    """``tracer(points, normals, dirs, em_sample, seed)``: one wavefront of :func:`_trace_llvm` (or
    :func:`_trace_scalar`) in the Mitsuba scene of ``scene`` with a ``path`` integrator for ``bounces``."""
    mscene = _load(mi, scene, sensor=False)
    max_depth = _max_depth(bounces, from_camera=False)
    integrator = mi.load_dict({"type": "path", "max_depth": max_depth, "rr_depth": max(5, max_depth)})
    trace = _trace_llvm if mi.variant().startswith("llvm") else _trace_scalar

    def tracer(points, normals, dirs, em_sample, chunk_seed):
        return trace(mi, dr, mscene, integrator, points, normals, offset, dirs, em_sample, max_depth, chunk_seed)

    return tracer


def _chunk_samples(tracer, rng, p, n, w, d_kd, d_ks, d_ex, chunk_seed):
    """Per-sample direct and indirect radiance ``(S, 3)`` of one wavefront of vertex samples.

    Direct: the BRDF-sampled ray's emitter hit and one emitter sample, combined by the power
    heuristic; indirect: the throughput times the path integrator's radiance along the BRDF ray.
    """
    wi = _sample_bsdf(rng, n, w, d_kd, d_ks, d_ex)
    pdf_b = _bsdf_pdf(wi, n, w, d_kd, d_ks, d_ex)
    fcos_b = _brdf_cos(wi, n, w, d_kd, d_ks, d_ex)
    with np.errstate(invalid="ignore", divide="ignore"):
        thr = np.where(pdf_b[:, None] > 0, fcos_b / np.where(pdf_b > 0, pdf_b, 1.0)[:, None], 0.0)
    em_sample = rng.random((len(p), 2))
    tr = tracer(p, n, wi, em_sample, chunk_seed)
    # BRDF-sampled ray hitting an emitter: MIS weight (power heuristic) against emitter sampling.
    w_b = _power_heuristic(pdf_b, tr["bsdf_em_pdf"])
    direct = thr * tr["bsdf_le"] * w_b[:, None]
    # Emitter sample.
    d_em = tr["em_dir"]
    ok = tr["em_pdf"] > 0
    fcos_e = _brdf_cos(d_em, n, w, d_kd, d_ks, d_ex)
    pdf_be = _bsdf_pdf(d_em, n, w, d_kd, d_ks, d_ex)
    w_e = np.where(tr["em_delta"], 1.0, np.where(ok, _power_heuristic(tr["em_pdf"], pdf_be), 0.0))
    direct = direct + np.where(ok[:, None], fcos_e * tr["em_weight"] * w_e[:, None], 0.0)
    return direct, thr * tr["indirect"]


# --------------------------------------------------------------------------- camera image


def render_mitsuba(scene, spp: int = 64, bounces: int = 1, seed: int = 0, *, variant: str | None = None) -> np.ndarray:
    """Render the scene camera with Mitsuba's ``path`` integrator.

    Parameters
    ----------
    scene : prtlab.Scene
    spp : int
        Samples per pixel.
    bounces : int
        Indirect bounces after the first visible surface (``max_depth = bounces + 2``).
    seed : int
    variant : str, optional

    Returns
    -------
    image : (h, w, 3) float64
        Linear RGB, box pixel filter; row 0 is the top of the image.
    """
    _check_scene(scene)
    bounces = _check_bounces(bounces)
    check_int(spp, "spp", 1)
    mi, _ = _import_mitsuba(variant)
    mscene = _load(mi, scene, bounces=bounces, spp=int(spp), sensor=True)
    image = mi.render(mscene, spp=int(spp), seed=int(seed))
    return np.asarray(image, dtype=np.float64)[..., :3].copy()
