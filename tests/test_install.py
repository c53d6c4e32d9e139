"""A new user's first hour, as a test: the wheel installed into a fresh venv, used from outside the repo.

The wheel is built from a copy of the sources (``pip wheel --no-deps --no-build-isolation``,
offline) and installed with ``--no-deps`` into a new virtual environment in a temporary folder
outside the repository. The venv sees the dependencies that are already installed (those of the
interpreter running the tests, through a ``.pth`` file: ``venv --system-site-packages`` would show
the base interpreter's packages, not those of the venv that runs the tests), never the checkout:
``PYTHONPATH`` is unset, the working folder and ``PRTLAB_CACHE`` are temporary folders. Every
command runs as a user would type it, with small options so the whole test stays short.

The venv is made afresh on every run, at a fixed place per checkout (under the system's temporary
folder), and numba's disk cache of its kernels (``NUMBA_CACHE_DIR``) is kept beside it: each
installed module gets a modification time computed from its content, so numba, which keys its
cache on a source file's path, time and size, compiles a kernel again only when its source
changed. Only the first run after a change pays the compilation.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import re
import shutil
import site
import subprocess
import sys
import tempfile
import textwrap
import venv
import zipfile
from pathlib import Path

import pytest

# one venv for the module: its tests stay on one xdist worker (make test runs --dist loadgroup)
pytestmark = pytest.mark.xdist_group("install")

ROOT = Path(__file__).resolve().parents[1]
PIPE_SCENE = "tiny_ball_env"       # interreflection, spherelights and the references
PORTAL_SCENE = "tiny_window_room"  # portals (a window)
# small options per method (each a few seconds once compiled)
OPTIONS = {
    "reference": ["--samples", "8"],
    "mitsuba": ["--samples", "8"],
    "interreflection": ["-o", "n_radii=4", "-o", "resolution=4", "-o", "degree=7", "-o", "n_lights=16",
                        "-o", "n_basis=4"],
    "spherelights": ["-o", "n_spheres=2", "-o", "fit_resolution=12"],
    "portals": ["-o", "cube_resolution=8", "-o", "direct_samples=32", "-o", "n_photons=4000", "-o", "gather_rays=16",
                "-o", "order=3"],
}


def _has_mitsuba() -> bool:
    try:
        import mitsuba  # noqa: F401
    except ImportError:
        return False
    return True


def _run(cmd, env, cwd, timeout=300) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(c) for c in cmd], env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


def _install_root() -> Path:
    """A fixed folder per checkout, outside it: the venv is rebuilt in it, numba's cache is kept."""
    tag = hashlib.sha1(str(ROOT).encode()).hexdigest()[:12]
    return Path(tempfile.gettempdir()).resolve() / f"prtlab-install-test-{tag}"


@pytest.fixture(scope="module")
def installed():
    """(venv folder, python, prtlab script, environment, user folder, wheel) of a fresh install."""
    root = _install_root()
    assert not root.is_relative_to(ROOT), f"the install folder {root} must be outside the repository"
    root.mkdir(parents=True, exist_ok=True)
    with open(root / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one run per checkout at a time
        yield _install(root)


def _install(root: Path) -> dict:
    work = root / "run"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    # the sources as a user's clone would hold them, without build leftovers or caches
    src = work / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "prtlab", src / "prtlab",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc"))
    try:
        import wheel  # noqa: F401  (setuptools < 70.1 builds wheels through it)
    except ImportError:
        pytest.fail("building the wheel needs the 'wheel' package: pip install -e '.[test]'")
    dist = work / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
          "-w", dist, src], os.environ, work)
    (wheel_file,) = dist.glob("prtlab-*.whl")

    env_dir = work / "venv"
    venv.create(env_dir, with_pip=False, symlinks=True)
    python = env_dir / "bin" / "python"
    purelib = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    deps = [p for p in site.getsitepackages() + [site.getusersitepackages()] if Path(p).is_dir()]
    (purelib / "_prtlab_test_deps.pth").write_text("\n".join(deps) + "\n")
    _run([sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", wheel_file],
         os.environ, work)
    for source in (purelib / "prtlab").rglob("*.py"):  # a time from the content: numba's cache keys are stable
        stamp = 1.0e9 + int(hashlib.sha1(source.read_bytes()).hexdigest()[:12], 16) % 10**8
        os.utime(source, (stamp, stamp))

    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "NUMBA_CACHE_DIR") and not k.startswith("PRTLAB_")}
    env.update(PATH=f"{env_dir / 'bin'}{os.pathsep}{env.get('PATH', '')}", PRTLAB_CACHE=str(work / "cache"),
               PRTLAB_QUICK="1", MPLBACKEND="Agg", NUMBA_CACHE_DIR=str(root / "numba-cache"))
    shared = Path(sys.prefix) / "share" / "jupyter"  # the data files of those dependencies (nbconvert's templates)
    if shared.is_dir():
        env["JUPYTER_PATH"] = os.pathsep.join(filter(None, [env.get("JUPYTER_PATH"), str(shared)]))
    user = work / "user"
    user.mkdir()
    return {"dir": env_dir, "python": python, "prtlab": env_dir / "bin" / "prtlab", "env": env, "cwd": user,
            "wheel": wheel_file, "work": work}


# --------------------------------------------------------------------------- packaging


def test_wheel_carries_the_data(installed):
    names = set(zipfile.ZipFile(installed["wheel"]).namelist())
    shipped = [p for kind in ("scenes", "meshes", "envmaps", "tables") for p in (ROOT / "prtlab" / "data" / kind).rglob("*")
               if p.is_file()]
    shipped += list((ROOT / "prtlab" / "notebooks").glob("*.ipynb"))
    shipped += list((ROOT / "prtlab" / "benchmarks").glob("bench_*.py"))
    shipped += [ROOT / "prtlab" / "data" / "README.md", ROOT / "prtlab" / "sh" / "_explog_tables.npz"]
    assert len(shipped) > 30
    missing = [p.relative_to(ROOT).as_posix() for p in shipped if p.relative_to(ROOT).as_posix() not in names]
    assert not missing, f"files missing from the wheel: {missing}"


def test_the_venv_imports_the_installed_package(installed):
    code = textwrap.dedent("""
        import prtlab, prtlab.data, prtlab.reproduce, prtlab.bench
        print(prtlab.__file__)
        print(prtlab.data.scene_path("cornell_box"))
        print(prtlab.reproduce.notebook_dir())
        print(prtlab.bench.benchmark_dir())
        print(len(prtlab.data.scenes()), len(prtlab.data.meshes()), len(prtlab.data.envmaps()))
        for name in ("cornell_box", "spheres_on_plane_env", "bunny_floor_arealight"):
            scene = prtlab.load_scene(prtlab.data.scene_path(name))
            print(name, sum(o.n_vertices for o in scene.objects))
    """)
    out = _run([installed["python"], "-c", code], installed["env"], installed["cwd"]).stdout.splitlines()
    package = Path(out[0]).parent
    assert package.is_relative_to(installed["dir"]), f"prtlab imported from {package}, not from the venv"
    for line in out[1:4]:
        assert Path(line).is_relative_to(package), line
    assert out[4] == f"{len(list((ROOT / 'prtlab/data/scenes').glob('*.yaml')))} 11 3"
    assert [line.split()[0] for line in out[5:]] == ["cornell_box", "spheres_on_plane_env", "bunny_floor_arealight"]


def test_readme_python_block_runs(installed):
    from tests.test_docs import code_blocks

    (block,) = [code for code, _ in code_blocks(ROOT / "README.md")]
    script = installed["cwd"] / "readme_block.py"
    script.write_text(block)
    _run([installed["python"], script], installed["env"], installed["cwd"])


# --------------------------------------------------------------------------- the command line


def test_version(installed):
    out = _run([installed["prtlab"], "--version"], installed["env"], installed["cwd"]).stdout
    version = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    assert out.strip() == f"prtlab {version}"


@pytest.mark.parametrize("method", ["reference", "mitsuba", "interreflection", "spherelights", "portals"])
def test_shade_every_method(installed, method):
    if method == "mitsuba" and not _has_mitsuba():
        pytest.skip("Mitsuba 3 is not installed (the 'reference' extra)")
    scene = PORTAL_SCENE if method == "portals" else PIPE_SCENE
    out = installed["cwd"] / f"{method}.npz"
    _run([installed["prtlab"], "shade", scene, "--method", method, *OPTIONS[method], "--out", out],
         installed["env"], installed["cwd"])
    import numpy as np

    with np.load(out) as radiance:
        totals = {k: radiance[k] for k in radiance.files if k.endswith("/total")}
    assert totals and all(v.ndim == 2 and v.shape[1] == 3 and np.all(np.isfinite(v)) for v in totals.values())
    assert all(v.max() > 0 for v in totals.values())


def _cache_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.h5")) if folder.is_dir() else []


def test_render_precomputes_once(installed):
    """``render --frames 3`` of a moving ball stores what one ``shade`` stores: one precomputation."""
    env, cwd = dict(installed["env"]), installed["cwd"]
    one = installed["work"] / "cache-shade-once"
    env["PRTLAB_CACHE"] = str(one)
    _run([installed["prtlab"], "shade", PIPE_SCENE, "--method", "interreflection", *OPTIONS["interreflection"],
          "--out", cwd / "once.npz"], env, cwd)
    frames = installed["work"] / "cache-render"
    env["PRTLAB_CACHE"] = str(frames)
    _run([installed["prtlab"], "render", PIPE_SCENE, "--method", "interreflection", *OPTIONS["interreflection"],
          "--frames", "3", "--out", cwd / "frames"], env, cwd)
    assert sorted(p.name for p in (cwd / "frames").glob("*.png")) == [f"frame_{i:04d}.png" for i in range(3)]
    assert len(_cache_files(one)) >= 1
    assert len(_cache_files(frames)) == len(_cache_files(one))


def test_compare_prints_the_table(installed):
    out = _run([installed["prtlab"], "compare", PIPE_SCENE, "--methods", "spherelights", "--reference", "reference",
                "--samples", "8", "-o", "spherelights.n_spheres=2", "-o", "spherelights.fit_resolution=12",
                "--out", installed["cwd"] / "compare"], installed["env"], installed["cwd"]).stdout
    assert "rel_rms" in out and "ball" in out and "ground" in out
    assert (installed["cwd"] / "compare" / "compare.json").is_file()


def test_cache_info(installed):
    env = dict(installed["env"], PRTLAB_CACHE=str(installed["work"] / "cache-info"))
    _run([installed["prtlab"], "shade", PORTAL_SCENE, "--method", "portals", *OPTIONS["portals"],
          "--out", installed["cwd"] / "info.npz"], env, installed["cwd"])
    out = _run([installed["prtlab"], "cache", "info"], env, installed["cwd"]).stdout
    assert env["PRTLAB_CACHE"] in out and "portals" in out


def test_bench_and_reproduce_run_from_the_package(installed):
    """The benchmark cases and the notebooks ship in the wheel: both commands work outside a clone."""
    import json

    env, cwd = installed["env"], installed["cwd"]
    _run([installed["prtlab"], "bench", "--quick", "--select", "brdf.phong.eval", "--json", cwd / "bench.json"],
         env, cwd)
    report = json.loads((cwd / "bench.json").read_text())
    assert [case["name"] for case in report["cases"]] == ["brdf.phong.eval.1M"]
    _run([installed["prtlab"], "reproduce", "--quick", "--only", "00_sh_algebra", "--out", cwd / "report"], env, cwd)
    index = (cwd / "report" / "index.html").read_text()
    assert "00_sh_algebra.ipynb" in index and "FAILED" not in index


def test_missing_notebook_and_benchmark_folders_say_what_to_set(tmp_path, monkeypatch):
    from prtlab import bench, reproduce

    monkeypatch.setenv("PRTLAB_NOTEBOOKS", str(tmp_path / "none"))
    with pytest.raises(FileNotFoundError, match=r"no notebook folder at .*none \(PRTLAB_NOTEBOOKS names none\); "
                                                r"set PRTLAB_NOTEBOOKS to a folder of \*\.ipynb files"):
        reproduce.notebook_dir()
    monkeypatch.setenv("PRTLAB_BENCHMARKS", str(tmp_path / "none"))
    with pytest.raises(FileNotFoundError, match=r"no benchmark folder at .*none \(PRTLAB_BENCHMARKS names none\); "
                                                r"set PRTLAB_BENCHMARKS to a folder of bench_\*\.py files"):
        bench.benchmark_dir()
    monkeypatch.delenv("PRTLAB_NOTEBOOKS")
    monkeypatch.delenv("PRTLAB_BENCHMARKS")
    assert reproduce.notebook_dir() == Path(reproduce.__file__).resolve().parent / "notebooks"
    assert bench.benchmark_dir() == Path(bench.__file__).resolve().parent / "benchmarks"
