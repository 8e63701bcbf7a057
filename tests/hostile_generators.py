"""Generated hostile inputs with their truth (issue 32): each generator writes files into a
folder and returns `Case`s saying whether each must be refused and, if accepted, what it
must hold. Writers here are the test's own (PLY, STL, PCD, npz headers), independent of the
readers under test."""

from __future__ import annotations

import io
import math
import os
import re
import shutil
import struct
import tomllib
import unicodedata
import zipfile
from pathlib import Path

import numpy as np
from hostile import Case

from scanner.config import CONFIG_DIR

REPO = Path(__file__).resolve().parents[1]

# ------------------------------------------------------------------------------------- PLY

PLY_TYPES = {"f4": "float", "f8": "double", "u1": "uchar", "i4": "int", "u4": "uint", "i2": "short"}


def random_mesh(rng: np.random.Generator) -> tuple[np.ndarray, list[np.ndarray]]:
    """Vertices (N, 3) and polygons (3 or 4 vertices each) of a random mesh."""
    n = int(rng.integers(3, 1500))
    v = rng.normal(0, 50, (n, 3))
    m = int(rng.integers(1, 2500))
    sizes = rng.choice([3, 3, 3, 4], m) if rng.random() < 0.3 else np.full(m, 3)
    return v, [rng.integers(0, n, s) for s in sizes]


def _number(token: bytes) -> bool:
    try:
        float(token)
        return True
    except ValueError:
        return False


def write_ply(path: Path, v: np.ndarray, faces: list[np.ndarray] | None, fmt: str, vtype: str, itype: str,
              normals: bool) -> int:
    """A PLY written here (not by any reader's library); returns the byte offset of the data."""
    props = [("x", vtype), ("y", vtype), ("z", vtype)] + ([("nx", "f4"), ("ny", "f4"), ("nz", "f4")] if normals else [])
    head = ["ply", f"format {fmt} 1.0", "comment hostile test", f"element vertex {len(v)}"]
    head += [f"property {PLY_TYPES[t]} {n}" for n, t in props]
    if faces is not None:
        head += [f"element face {len(faces)}", f"property list uchar {PLY_TYPES[itype]} vertex_indices"]
    header = ("\n".join(head + ["end_header"]) + "\n").encode()
    nrm = v / np.linalg.norm(v, axis=1)[:, None] if normals else None
    if fmt == "ascii":
        rows = [" ".join([*(f"{x:.9g}" for x in p), *((f"{x:.6g}" for x in nrm[i]) if normals else ())])
                for i, p in enumerate(v)]
        rows += [" ".join([str(len(f)), *map(str, f)]) for f in (faces or [])]
        body = ("\n".join(rows) + "\n").encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        rec = np.empty(len(v), [(n, order + t) for n, t in props])
        for k, (n, _) in enumerate(props[:3]):
            rec[n] = v[:, k]
        if normals:
            for k, n in enumerate(("nx", "ny", "nz")):
                rec[n] = nrm[:, k]
        chunks = [rec.tobytes()]
        for f in faces or []:
            chunks.append(struct.pack("B", len(f)) + np.asarray(f, order + itype).tobytes())
        body = b"".join(chunks)
    path.write_bytes(header + body)
    return len(header)


def ply_cases(folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    cases = []
    for i in range(n):
        v, faces = random_mesh(rng)
        mesh = rng.random() < 0.7
        fmt = str(rng.choice(["binary_little_endian", "binary_big_endian", "ascii"]))
        path = folder / f"m{i}.ply"
        start = write_ply(path, v, faces if mesh else None, fmt, str(rng.choice(["f4", "f8"])),
                          str(rng.choice(["i4", "u4"])), bool(rng.random() < 0.4))
        data = path.read_bytes()
        tri = sum(len(f) - 2 for f in faces) if mesh else 0
        target = "hostile_cases:mesh_counts" if mesh else "hostile_cases:point_count"
        good = (len(v), tri) if mesh else len(v)
        what = rng.choice(["intact", "truncate", "truncate", "count lie", "junk", "index lie", "nan", "header line"])
        refuse = True
        if what == "intact" or (not mesh and what == "index lie"):
            what, refuse = "intact", False
        elif what == "truncate":
            cut = int(rng.integers(1, len(data)))
            path.write_bytes(data[:cut])
            what = f"truncated at {cut} of {len(data)} ({fmt})"
            kept = data[start:cut].split() if cut > start else []
            if fmt == "ascii" and len(kept) == len(data[start:].split()) and _number(kept[-1]):
                refuse = False  # only white space, or the last number's last digits, were cut: nothing says so
        elif what == "count lie":
            element = "face" if mesh and rng.random() < 0.5 else "vertex"
            true = len(faces) if element == "face" else len(v)
            lie = int(rng.choice([true + int(rng.integers(1, 1000)), max(true - int(rng.integers(1, 3)), 0),
                                  10 ** 9, 2 ** 31 - 1, 2 ** 32 + true, 10 ** 18, 2 ** 64 + true]))
            lie = lie if lie != true else true + 1
            path.write_bytes(data.replace(f"element {element} {true}\n".encode(),
                                          f"element {element} {lie}\n".encode()))
            what = f"{element} count {true} -> {lie} ({fmt})"
        elif what == "junk":
            junk = rng.integers(33, 127, int(rng.integers(1, 2000)), dtype=np.uint8).tobytes()
            path.write_bytes(data + junk)
            what = f"{len(junk)} bytes appended ({fmt})"
        elif what == "index lie":
            k = int(rng.integers(0, len(faces)))
            bad = int(rng.choice([len(v), len(v) + int(rng.integers(1, 10 ** 6)), -1, -int(rng.integers(2, 10 ** 6)),
                                  99999999]))
            faces = [f.copy() for f in faces]
            faces[k][int(rng.integers(0, len(faces[k])))] = bad
            write_ply(path, v, faces, fmt, "f8", "i4", False)
            what = f"face {k} names vertex {bad} of {len(v)} ({fmt})"
        elif what == "nan":
            v = v.copy()
            v[int(rng.integers(0, len(v))), int(rng.integers(0, 3))] = rng.choice([np.nan, np.inf, -np.inf])
            write_ply(path, v, faces if mesh else None, fmt, "f8", "i4", False)
            what = f"a non-finite vertex ({fmt})"
        else:
            lines = data[:start].split(b"\n")
            k = int(rng.integers(1, len(lines) - 1))
            line = rng.choice([b"element", b"property float", b"format ascii 2.0", b"elemnt vertex 3",
                               b"property list float float x", rng.integers(33, 127, 12, dtype=np.uint8).tobytes()])
            path.write_bytes(b"\n".join(lines[:k] + [line] + lines[k:]) + data[start:])
            what = f"header line {line[:20]!r} inserted ({fmt})"
        cases.append(Case("PLY meshes" if mesh else "PLY clouds", target, (str(path),), refuse, what,
                          None if refuse else good))
    return cases


# ------------------------------------------------------------------------------------- STL, PCD, OBJ

def write_stl(path: Path, v: np.ndarray, tris: np.ndarray, ascii_: bool) -> None:
    if ascii_:
        rows = ["solid t"] + [" facet normal 0 0 1\n  outer loop\n" + "".join(
            f"   vertex {v[i, 0]:.9g} {v[i, 1]:.9g} {v[i, 2]:.9g}\n" for i in t) + "  endloop\n endfacet" for t in tris]
        path.write_text("\n".join(rows + ["endsolid t"]) + "\n")
        return
    rec = np.zeros(len(tris), [("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = v[tris]
    path.write_bytes(b"hostile".ljust(80, b" ") + struct.pack("<I", len(tris)) + rec.tobytes())


def other_mesh_cases(folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    cases = []
    for i in range(n):
        kind = str(rng.choice(["stl-binary", "stl-ascii", "pcd", "obj"]))
        v, _faces = random_mesh(rng)
        v = np.unique(np.round(v, 3), axis=0).astype(np.float32).astype(np.float64)  # distinct, exact in float32
        tris = rng.integers(0, len(v), (int(rng.integers(1, 800)), 3))
        tris = tris[(tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2])]
        if len(tris) == 0:
            tris = np.array([[0, 1, 2]])
        used = len(np.unique(tris))
        what = str(rng.choice(["intact", "truncate", "count lie", "index lie"]))
        if kind.startswith("stl"):
            path = folder / f"o{i}.stl"
            write_stl(path, v, tris, kind == "stl-ascii")
            data = path.read_bytes()
            target, good, area = "hostile_cases:mesh_counts", (used, len(tris)), "STL meshes"
            if what == "truncate":
                cut = int(rng.integers(1, len(data)))
                path.write_bytes(data[:cut])
                refuse = kind == "stl-binary" or cut < data.rindex(b"endsolid") + len(b"endsolid")
            elif what == "count lie" and kind == "stl-binary":
                lie = int(rng.choice([len(tris) + 1, len(tris) - 1, 2 ** 32 - 1, 10 ** 9]))
                path.write_bytes(data[:80] + struct.pack("<I", lie) + data[84:])
                refuse = True
            else:
                what, refuse = "intact", False
        elif kind == "pcd":
            path = folder / f"o{i}.pcd"
            binary = rng.random() < 0.5
            head = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {len(v)}\n"
                    f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(v)}\nDATA {'binary' if binary else 'ascii'}\n")
            body = v.astype("<f4").tobytes() if binary else "".join(f"{a:.6f} {b:.6f} {c:.6f}\n"
                                                                      for a, b, c in v).encode()
            data = head.encode() + body
            path.write_bytes(data)
            target, good, area = "hostile_cases:point_count", len(v), "PCD clouds"
            if what == "truncate":
                cut = int(rng.integers(len(head) + 1, len(data)))
                path.write_bytes(data[:cut])
                refuse = binary or len(data[len(head):cut].split()) < 3 * len(v)
            elif what == "count lie":
                lie = int(rng.choice([len(v) + 1, len(v) * 2, 10 ** 9, max(len(v) - 1, 1)]))
                lie = lie if lie != len(v) else len(v) + 1
                path.write_bytes(data.replace(f"WIDTH {len(v)}\n".encode(), f"WIDTH {lie}\n".encode())
                                 .replace(f"POINTS {len(v)}\n".encode(), f"POINTS {lie}\n".encode()))
                refuse = True
            else:
                what, refuse = "intact", False
        else:
            path = folder / f"o{i}.obj"
            bad = what == "index lie"
            if bad:
                tris = tris.copy()
                tris[int(rng.integers(0, len(tris))), int(rng.integers(0, 3))] = int(
                    rng.choice([len(v), 99999998, -len(v) - 5]))
            path.write_text("".join(f"v {a:.9g} {b:.9g} {c:.9g}\n" for a, b, c in v)
                            + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in tris))
            target, good, area = "hostile_cases:mesh_counts", None, "OBJ meshes"
            what, refuse = ("index lie", True) if bad else ("intact", False)
        cases.append(Case(area, target, (str(path),), refuse, f"{kind} {what}", None if refuse else good))
    return cases


# ------------------------------------------------------------------------------------- STEP

STEP_REF = re.compile(r"#(\d+)")


def step_cases(folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    """The demo part's STEP file with an entity removed that a face, shell or loop names
    (refuse), cut at a random offset (refuse unless the cut falls after the last entity),
    or intact (13 faces)."""
    text = (CONFIG_DIR / "parts" / "demo_part.step").read_text()
    records = {int(m.group(1)): m for m in re.finditer(r"^#(\d+)\s*=\s*([A-Z_]+)[^;]*;", text, flags=re.M)}
    referenced = sorted({int(r) for m in records.values() if m.group(2) in (
        "ADVANCED_FACE", "CLOSED_SHELL", "EDGE_LOOP", "FACE_BOUND", "FACE_OUTER_BOUND", "ORIENTED_EDGE")
        for r in STEP_REF.findall(m.group(0)[m.group(0).index("=") + 1:]) if int(r) in records})
    last = max(m.end() for m in records.values())
    cases = []
    for i in range(n):
        path = folder / f"s{i}.step"
        what = str(rng.choice(["intact", "entity removed", "entity removed", "truncate"]))
        if what == "entity removed":
            k = int(rng.choice(referenced))
            m = records[k]
            path.write_text(text[:m.start()] + text[m.end() + 1:])
            cases.append(Case("STEP models", "hostile_cases:cad_faces", (str(path),), True,
                              f"#{k} ({m.group(2)}) removed"))
        elif what == "truncate":
            cut = int(rng.integers(1, len(text)))
            path.write_text(text[:cut])
            cases.append(Case("STEP models", "hostile_cases:cad_faces", (str(path),), cut < last,
                              f"truncated at {cut} of {len(text)}", None if cut < last else 13))
        else:
            path.write_text(text)
            cases.append(Case("STEP models", "hostile_cases:cad_faces", (str(path),), False, "intact", 13))
    return cases


# ------------------------------------------------------------------------------------- ground truth .npz

def _npz(path: Path, arrays: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w") as z:
        for name, data in arrays.items():
            z.writestr(f"{name}.npy", data)


def _npy(a: np.ndarray, shape_lie: tuple[int, ...] | None = None) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, a, allow_pickle=True)
    data = buf.getvalue()
    if shape_lie is not None:
        data = data.replace(repr(a.shape).encode(), repr(shape_lie).encode().ljust(len(repr(a.shape))), 1)
    return data


def truth_cases(folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    cases = []
    for i in range(n):
        h, w = int(rng.integers(2, 60)), int(rng.integers(2, 60))
        arrays = {"depth": rng.random((h, w)).astype(np.float32), "object_id": rng.integers(0, 5, (h, w), np.int32),
                  "proj_uv": rng.random((h, w, 2)).astype(np.float32)}
        path = folder / f"t{i}.npz"
        what = str(rng.choice(["intact", "truncate", "shape lie", "objects", "missing", "garbage", "shapes differ"]))
        members = {k: _npy(a) for k, a in arrays.items()}
        refuse = True
        if what == "shape lie":
            k = str(rng.choice(list(arrays)))
            lie = tuple(int(x) for x in rng.choice([10 ** 5, 10 ** 6, 46341, 3], arrays[k].ndim))
            members[k] = _npy(arrays[k], lie)
            what = f"{k} header says {lie}"
        elif what == "objects":
            members["depth"] = _npy(np.array([{"a": 1}] * 4, dtype=object))
        elif what == "missing":
            del members[str(rng.choice(list(members)))]
        elif what == "shapes differ":
            members["object_id"] = _npy(rng.integers(0, 5, (h + 1, w), np.int32))
        elif what == "intact":
            refuse = False
        _npz(path, members)
        if what == "truncate":
            data = path.read_bytes()
            path.write_bytes(data[:int(rng.integers(0, len(data)))])
        elif what == "garbage":
            path.write_bytes(rng.integers(0, 256, int(rng.integers(0, 5000)), dtype=np.uint8).tobytes())
        cases.append(Case("ground_truth.npz", "hostile_cases:truth_shapes", (str(path),), refuse, what,
                          None if refuse else ((h, w), (h, w), (h, w, 2))))
    return cases


# ------------------------------------------------------------------------------------- session frames

def frame_cases(clean: Path, folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    """A small clean session with one frame replaced by a FIFO, a folder, a link to a
    device or out of the session, a sparse file past the size bound, a PNG whose header
    claims a huge image, or cut short: each refused quickly; the clean copy accepted."""
    cases = []
    for i in range(n):
        root = folder / f"f{i}"
        shutil.copytree(clean, root)
        k = int(rng.integers(0, 12))
        f = root / "frames" / f"frame_{k:03d}.png"
        what = str(rng.choice(["intact", "fifo", "folder", "device link", "outside link", "sparse", "png size lie",
                               "truncate"]))
        refuse = what != "intact"
        if what == "fifo":
            f.unlink()
            os.mkfifo(f)
        elif what == "folder":
            f.unlink()
            f.mkdir()
        elif what == "device link":
            f.unlink()
            f.symlink_to("/dev/zero")
        elif what == "outside link":
            outside = folder / f"outside{i}.png"
            shutil.copy(f, outside)
            f.unlink()
            f.symlink_to(outside)
        elif what == "sparse":
            with open(f, "r+b") as h:
                h.truncate(int(rng.integers(2, 64)) * 1024 ** 3)
        elif what == "png size lie":
            data = bytearray(f.read_bytes())
            data[16:24] = struct.pack(">II", int(rng.integers(10 ** 4, 65535)), int(rng.integers(10 ** 4, 65535)))
            f.write_bytes(bytes(data))
        elif what == "truncate":
            data = f.read_bytes()
            f.write_bytes(data[:int(rng.integers(0, len(data)))])
        cases.append(Case("session frames", "hostile_cases:session_frames", (str(root),), refuse,
                          f"frame {k}: {what}", None if refuse else (12, 256, 320)))
    return cases


# ------------------------------------------------------------------------------------- config values

SENSOR_RANGES = {"full_well_e": (1e3, 1e6), "read_noise_e": (0.0, 100.0), "flux_e_per_s": (1e2, 1e10),
                 "ambient": (0.0, 1.0), "blur_sigma_px": (0.0, 10.0)}


def draw_value(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A value across and beyond [lo, hi]: uniform over three times the range around it,
    log-uniform over 1e-30 .. 1e30 either sign, or an edge (the bounds, just past them, 0)."""
    kind = rng.integers(0, 4)
    if kind == 0:
        span = hi - lo
        return float(rng.uniform(lo - span, hi + span))
    if kind == 1:
        return float(rng.choice([-1, 1]) * 10 ** rng.uniform(-30, 30))
    if kind == 2:
        return float(rng.choice([lo, hi, np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf), 0.0, -0.0]))
    return float(lo + (hi - lo) * rng.random())


def toml_float(x: float) -> str:
    return repr(float(x)) if math.isfinite(x) else ("nan" if math.isnan(x) else "inf" if x > 0 else "-inf")


def rig_text(edits: dict[tuple[str, str], str]) -> str:
    """The simulated bench rig with `edits` ((table, key) -> TOML value), paths absolute."""
    text = (CONFIG_DIR / "rigs" / "sim_bench.toml").read_text().replace('"../', f'"{CONFIG_DIR}/')
    table = ""
    out = []
    done = set()
    for line in text.splitlines():
        if line.startswith("["):
            for (t, k), v in edits.items():
                if t == table and (t, k) not in done:
                    out.append(f"{k} = {v}")
                    done.add((t, k))
            table = line[1:line.index("]")]
            out.append(line)
            continue
        key = line.split("=")[0].strip()
        if (table, key) in edits:
            out.append(f"{key} = {edits[table, key]}")
            done.add((table, key))
        else:
            out.append(line)
    out += [f"{k} = {v}" for (t, k), v in edits.items() if (t, k) not in done and t == table]
    return "\n".join(out) + "\n"


def config_cases(folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    """Random values across and beyond each documented range of the rig's sensor table, the
    projector's blur, the fault delay and the image sizes: refused iff outside the range."""
    cases = []
    keys = [("camera.sensor", k) for k in SENSOR_RANGES] + [("projector", "blur_sigma_px"), ("camera", "size"),
                                                          ("projector", "size")]
    for i in range(n):
        table, key = keys[int(rng.integers(0, len(keys)))]
        path = folder / f"rig{i}.toml"
        if key == "size":  # both sides by one factor: the same field of view (the rig's geometry check holds)
            unit = (5, 4) if table == "camera" else (4, 5)  # 1280 x 1024, 912 x 1140 ~ 4 x 5
            k = int(rng.choice([rng.integers(-3, 20000), 10 ** int(rng.integers(0, 10)), 0, 1, 13107, 13108,
                                1095, 1096]))
            w, h = unit[0] * k, unit[1] * k
            value = f"{w} x {h}"
            refuse = not (1 <= w <= 65536 and 1 <= h <= 65536) or (table == "camera" and w * h > 24_000_000)
            text = rig_text({(table, "width"): str(w), (table, "height"): str(h)})
        else:
            lo, hi = SENSOR_RANGES.get(key, (0.0, 10.0))
            value = draw_value(rng, lo, hi)
            refuse = not lo <= value <= hi
            text = rig_text({(table, key): toml_float(value)})
        path.write_text(text)
        cases.append(Case("rig config values", "hostile_cases:rig_loads", (str(path),), refuse,
                          f"{table}.{key} = {value!r}", None if refuse else "ok"))
    return cases


def projector_fit_cases(folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    """Projector sizes against the rig's heterodyne 70/64/59 fringes: a scan is refused before
    its session when the finest fringe has fewer than 2 projector pixels per period."""
    cases = []
    for i in range(n):
        w = int(rng.choice([rng.integers(1, 300), rng.integers(1, 4000), 139, 140, 141]))
        path = folder / f"proj{i}.toml"
        path.write_text(rig_text({("projector", "width"): str(w)}))
        cases.append(Case("projector size", "hostile_cases:patterns_fit", (str(path),), w / 70 < 2,
                          f"projector width {w}", None if w / 70 < 2 else "ok"))
    return cases


def scene_cases(folder: Path, rng: np.random.Generator, n: int, rig: Path) -> list[Case]:
    """A sphere anywhere around the camera (behind it, beside its view, in it) of any radius,
    a reference plane at any distance: refused iff a length is outside [1e-3, 1e5] mm or the
    sphere cannot be seen. Whether it can be seen is decided here as a rendering samples it:
    by casting the ray of every pixel's centre of the 1280 x 1024 camera at the sphere, not
    by the check under test."""
    from scanner.rig import RigConfig

    cam = RigConfig.load(rig).nominal_model().camera
    u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
    rays = np.column_stack([cam.normalized(np.stack([u.ravel(), v.ravel()], 1)), np.ones(u.size)])
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    cases = []
    for i in range(n):
        r = float(draw_value(rng, 1e-3, 1e5) if rng.random() < 0.3 else 10 ** rng.uniform(-1, 3))
        c = rng.normal(0, 1, 3) * 10 ** rng.uniform(0, 4)
        distance = float(draw_value(rng, 1e-3, 1e5)) if rng.random() < 0.3 else 900.0
        path = folder / f"scene{i}.toml"
        path.write_text(f"[reference_plane]\ndistance_mm = {toml_float(distance)}\n\n[[objects]]\n"
                        f"sphere = {{ radius_mm = {toml_float(r)}, "
                        f"center_mm = [{', '.join(toml_float(x) for x in c)}] }}\n")
        lengths_ok = 1e-3 <= r <= 1e5 and 1e-3 <= distance <= 1e5 and np.abs(c).max() <= 1e5
        # a ray t d (unit d) meets the sphere where |t d - c| = r: t = d.c +- sqrt(r^2 - (|c|^2 - (d.c)^2)),
        # in front of the camera when the farther root is > 0
        t = rays @ c
        gap = r * r - (c @ c - t * t)
        seen = bool(np.any((gap >= 0) & (t + np.sqrt(np.maximum(gap, 0.0)) > 0)))
        refuse = not lengths_ok or not seen
        cases.append(Case("scene values", "hostile_cases:scene_opens", (str(path), str(rig)), refuse,
                          f"sphere r {r:.3g} at {np.round(c, 1).tolist()}, plane at {distance:.3g}",
                          None if refuse else "ok"))
    return cases


# ------------------------------------------------------------------------------------- free text

NOT_TEXT = {"Cc", "Cf", "Cs", "Zl", "Zp"}  # the categories the spec refuses (scanner.schema.plain_text's docstring)


def random_text(rng: np.random.Generator) -> str:
    """Random bytes decoded as the command line decodes them (undecodable bytes become lone
    surrogates), or random code points of any plane, or plain words with one control
    character, or a formula."""
    kind = rng.integers(0, 5)
    if kind == 0:
        return rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes().decode("utf-8",
                                                                                             "surrogateescape")
    if kind == 1:
        return "".join(chr(int(x)) for x in rng.integers(1, 0x10FFFF, int(rng.integers(1, 20))))
    if kind == 2:
        word = "SN-" + "".join(chr(int(x)) for x in rng.integers(48, 123, 8))
        k = int(rng.integers(0, len(word)))
        return word[:k] + chr(int(rng.choice([0, 9, 10, 13, 27, 127, 0x85, 0x200B, 0x202E, 0x2028, 0xFEFF, 0xAD,
                                               0xE0041]))) + word[k:]
    if kind == 3:
        return str(rng.choice(["=HYPERLINK(\"http://x\",\"y\")", "+1+1", "-2", "@SUM(A1)", "naïve Ωmega 名前",
                               "SN 0001", "O'Brien"]))
    return "".join(chr(int(x)) for x in rng.integers(32, 127, int(rng.integers(1, 30))))


def is_text(s: str) -> bool:
    return 0 < len(s) <= 4096 and not any(unicodedata.category(c) in NOT_TEXT for c in s)


def text_cases(folder: Path, rng: np.random.Generator, n: int) -> list[Case]:
    """Random strings into every free-text field: the station's serial (database and CSV),
    `--operator`/`--serial` on the command line, a station config's operator, a part
    program's name: refused iff they hold a character of a refused category."""
    cases = []
    program = (CONFIG_DIR / "parts" / "demo_part.toml").read_text().replace(
        'cad = "demo_part.step"', f'cad = "{CONFIG_DIR / "parts" / "demo_part.step"}"').replace(
        '"../patterns/', f'"{CONFIG_DIR}/patterns/')
    station = (CONFIG_DIR / "station" / "sim_bench.toml").read_text().replace('"../', f'"{CONFIG_DIR}/')
    parsed = tomllib.loads(program)
    for i in range(n):
        s = random_text(rng)
        ok = is_text(s)
        field = str(rng.choice(["serial", "--operator", "--serial", "station operator", "program name", "face name",
                                "characteristic name"]))
        shown = f"{field} {s[:40]!r}"
        if field == "serial":
            s = s.strip() or "x"  # the station strips a serial and asks again for a blank one
            ok = is_text(s)
            formula = s.startswith(("=", "+", "-", "@"))
            cases.append(Case("free text", "hostile_cases:stored_serial", (str(folder / f"db{i}.sqlite"), s), not ok,
                              shown, None if not ok else (True, "'" + s if formula else s)))
        elif field.startswith("--"):
            argv = (["inspect", "x.ply", "--tolerances", "t.toml", f"{field}={s}"] if field == "--serial" else
                    ["station", "p.toml", f"{field}={s}"])
            cases.append(Case("free text", "hostile_cases:cli_args", (argv,), not ok, shown, None if not ok else "ok"))
        else:
            encoded = _toml_string(s)
            if field == "station operator":
                path = folder / f"station{i}.toml"
                path.write_bytes(station.encode().replace(b'operator = ""', b"operator = " + encoded, 1))
                target = "hostile_cases:station_config_loads"
            else:
                taken = {"face name": set(parsed["faces"].values()) - {"high top"},
                         "characteristic name": {c["name"] for c in parsed["characteristic"][1:]}}.get(field, set())
                ok = ok and bool(s.strip()) and s not in taken  # a name is not blank, nor another face's or check's
                path = folder / f"program{i}.toml"
                which, old = {"program name": ("name", b'name = "demo-part"'),
                              "face name": ("face", b'"#657" = "high top"'),
                              "characteristic name": ("characteristic", b'name = "high_top_flatness"')}[field]
                path.write_bytes(program.encode().replace(old, old.split(b"=")[0] + b"= " + encoded, 1))
                cases.append(Case("free text", "hostile_cases:program_text", (str(path), which), not ok, shown,
                                  None if not ok else s))
                continue
            cases.append(Case("free text", target, (str(path),), not ok, shown, None if not ok else s))
    return cases


def _toml_string(s: str) -> bytes:
    """`s` as a TOML basic string: backslash, quote and control characters escaped, the rest
    as UTF-8 (a lone surrogate stays an undecodable byte: the file is then not UTF-8)."""
    out = []
    for c in s:
        if c in '"\\':
            out.append("\\" + c)
        elif ord(c) < 32 or ord(c) == 127:
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    return b'"' + "".join(out).encode("utf-8", "surrogatepass") + b'"'

