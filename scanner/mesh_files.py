"""Meshes and point clouds from files, each verified before it is used (one reader for every
command: `cad`, `inspect`, `register`, `segment`, `pose`, the simulator's scenes).

PLY is read by `scanner.ply_file` (counts checked against the file's bytes); STL here (a
binary STL's triangle count must match its size exactly, 84 + 50 bytes per triangle; an
ASCII STL's every facet must be complete and the file end with `endsolid`). The other formats
(OBJ, PCD, XYZ, PTS) are read by Open3D under `native_output`: a line Open3D writes that says
a read failed refuses the file (its reader gives no status), and a PCD must hold the points
its header declares. Every file is a regular file within the size cap; vertices
must be finite and triangle indices inside the vertex list.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from scanner.file_checks import FileRefused, ascii_numbers, native_output, read_regular, regular_size
from scanner.ply_file import face_triangles, read_ply, vertex_positions

FAILURE_WORDS = ("fail", "error", "unable", "cannot", "invalid")  # in a line Open3D writes while it reads

T = TypeVar("T")


def _open3d_read(path: Path, read: Callable[[Path], T]) -> T:
    """Open3D's reader `read` (o3d.io.read_triangle_mesh or read_point_cloud) of `path`, its
    messages judged: a failure line refuses the file."""
    with native_output() as said:
        result = read(path)
    failed = said.failures(*FAILURE_WORDS)
    if failed:
        raise FileRefused(path, f"unreadable ({failed[0].replace('[Open3D WARNING]', 'Open3D:').strip()[:160]})")
    return result


STL_TRIANGLE = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
_ASCII_FACET = re.compile(rb"facet\s+normal\s+\S+\s+\S+\s+\S+\s+outer\s+loop\s+vertex\s+(\S+)\s+(\S+)\s+(\S+)"
                          rb"\s+vertex\s+(\S+)\s+(\S+)\s+(\S+)\s+vertex\s+(\S+)\s+(\S+)\s+(\S+)\s+endloop\s+endfacet")


def read_stl(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) of a binary STL (exactly its declared count of 50-byte records
    after the 84-byte header) or an ASCII STL (every `facet` complete, then `endsolid`);
    vertices shared between triangles merged."""
    data = read_regular(path)
    if (data[:5].lower() == b"solid" and b"facet" in data[:4096]) or data.strip() == b"solid":
        corners = _ascii_stl(path, data)
    else:
        if len(data) < 84:
            raise FileRefused(path, f"not a usable STL file: {len(data)} bytes, a binary STL's header alone is 84")
        n = int(np.frombuffer(data, "<u4", 1, 80)[0])
        if len(data) != 84 + STL_TRIANGLE.itemsize * n:
            raise FileRefused(path, f"not a usable STL file: its header declares {n} triangles ({84 + 50 * n} "
                                    f"bytes), the file holds {len(data)} bytes (cut short, or a header that lies)")
        corners = np.frombuffer(data, STL_TRIANGLE, n, 84)["vertices"].reshape(-1, 3).astype(np.float64)
    vertices, index = np.unique(corners, axis=0, return_inverse=True)
    return vertices, index.reshape(-1, 3).astype(np.int64)


def _ascii_stl(path: Path, data: bytes) -> np.ndarray:
    """The (3 M, 3) corners of an ASCII STL's facets, each facet checked complete."""
    if not re.search(rb"\bendsolid\b[^\n]*\s*$", data):
        raise FileRefused(path, "not a usable STL file: no 'endsolid' line at its end (cut short)")
    facets = _ASCII_FACET.findall(data)
    started = len(re.findall(rb"\bfacet\b", data))
    if not len(facets) == started == data.count(b"endfacet"):
        raise FileRefused(path, f"not a usable STL file: {started} facets begin, {len(facets)} of them are complete "
                                f"(a facet cut short or malformed)")
    try:
        return np.array(facets, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        raise FileRefused(path, "not a usable STL file: a vertex coordinate is not a number") from None


PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8",
             ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}


def read_pcd(path: Path) -> tuple[np.ndarray, np.ndarray | None] | None:
    """(points, normals or None) of an ASCII or binary PCD, its data exactly the points its
    header declares (POINTS, else WIDTH x HEIGHT) of the fields it lists; None for a
    binary_compressed PCD (left to Open3D, its count checked by the caller)."""
    data = read_regular(path)
    fields: dict[str, list[str]] = {}
    at = 0
    while "DATA" not in fields:
        end = data.find(b"\n", at)
        if end < 0 or at > 65536:
            raise FileRefused(path, "not a usable PCD file: no DATA line ends its header")
        words = data[at:end].decode("latin-1").split()
        at = end + 1
        if words and not words[0].startswith("#"):
            fields[words[0].upper()] = words[1:]
    try:
        names, sizes, types = fields["FIELDS"], [int(s) for s in fields["SIZE"]], fields["TYPE"]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(names))]
        n = int(fields["POINTS"][0]) if "POINTS" in fields else int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
        kind = fields["DATA"][0].lower()
        dtype = np.dtype([(f"{name}#{k}", "<" + PCD_TYPES[t.upper(), s]) for name, s, t, c in
                          zip(names, sizes, types, counts, strict=True) for k in range(c)])
    except (KeyError, IndexError, ValueError):
        raise FileRefused(path, "not a usable PCD file: its header's FIELDS, SIZE, TYPE, COUNT, POINTS or DATA "
                                "are missing or do not agree") from None
    if kind == "binary_compressed":
        return None
    body = data[at:]
    columns = dtype.names or ()  # "name#k": item k of field `name`
    if kind == "binary":
        if n < 0 or len(body) != n * dtype.itemsize:
            raise FileRefused(path, f"not a usable PCD file: its header declares {n} points of {dtype.itemsize} "
                                    f"bytes, {len(body)} bytes follow it (cut short, or a header that lies)")
        table = np.frombuffer(body, dtype, n)
        column = {name: table[name].astype(np.float64) for name in columns}
    elif kind == "ascii":
        tokens = ascii_numbers(path, body, "PCD file")
        if n < 0 or len(tokens) != n * len(columns):
            raise FileRefused(path, f"not a usable PCD file: its header declares {n} points of {len(columns)} "
                                    f"values, {len(tokens)} numbers follow it (cut short, or a header that lies)")
        rows = tokens.reshape(n, -1)
        column = {name: rows[:, k] for k, name in enumerate(columns)}
    else:
        raise FileRefused(path, f"not a usable PCD file: DATA {kind!r} is not ascii, binary or binary_compressed")
    if not {"x#0", "y#0", "z#0"} <= column.keys():
        raise FileRefused(path, "not a usable PCD file: no x, y, z fields")
    points = np.stack([column[f"{k}#0"] for k in "xyz"], axis=1)
    normal_keys = [f"normal_{k}#0" for k in "xyz"]
    normals = np.stack([column[k] for k in normal_keys], axis=1) if all(k in column for k in normal_keys) else None
    return points, normals


def _obj_counts(path: Path, vertices: int, triangles: int) -> None:
    """An OBJ must give at least a triangle per `f` line (polygons fan into more) and no more
    vertices than its `v` lines (Open3D keeps only the vertices faces use): Open3D drops
    what it cannot use (a face naming a vertex the file does not have) without failing."""
    text = b"\n" + read_regular(path)
    v_lines, f_lines = text.count(b"\nv "), text.count(b"\nf ")
    if vertices > v_lines or triangles < f_lines:
        raise FileRefused(path, f"not a usable OBJ file: {v_lines} vertex and {f_lines} face lines, {vertices} "
                                f"vertices and {triangles} triangles read (a face names a vertex the file does not "
                                f"have, or a line is malformed)")


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float64, triangles (M, 3) int64) of a PLY, STL or OBJ mesh, verified
    (see the module docstring); FileRefused when the file cannot be trusted."""
    path = Path(path)
    regular_size(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        _, data = read_ply(path)
        if "vertex" not in data:
            raise FileRefused(path, "not a usable PLY mesh: no 'vertex' element")
        v = vertex_positions(path, data["vertex"])
        t = face_triangles(path, data["face"], len(v)) if "face" in data else np.empty((0, 3), np.int64)
        return v, t
    if suffix == ".stl":
        v, t = read_stl(path)
    else:
        import open3d as o3d

        mesh = _open3d_read(path, o3d.io.read_triangle_mesh)
        v = np.asarray(mesh.vertices, dtype=np.float64)
        t = np.asarray(mesh.triangles, dtype=np.int64)
        if suffix == ".obj":
            _obj_counts(path, len(v), len(t))
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise FileRefused(path, f"vertex {int(np.argmax(bad))} of {len(v)} has a non-finite coordinate")
    if len(t) and (t.min() < 0 or t.max() >= len(v)):
        raise FileRefused(path, f"a triangle names vertex {int(t.max() if t.max() >= len(v) else t.min())}, but the "
                                f"file has {len(v)} vertices")
    return v, t


def _finite(path: Path, points: np.ndarray) -> None:
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise FileRefused(path, f"point {int(np.argmax(bad))} of {len(points)} has a non-finite coordinate")


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(points (N, 3) float64, normals (N, 3) or None) of a PLY, PCD, XYZ, XYZN or PTS
    cloud, verified (see the module docstring)."""
    path = Path(path)
    regular_size(path)
    if path.suffix.lower() == ".ply":
        _, data = read_ply(path)
        if "vertex" not in data:
            raise FileRefused(path, "not a usable PLY cloud: no 'vertex' element")
        vertex = data["vertex"]
        points = vertex_positions(path, vertex)
        normals = None
        if all(isinstance(vertex.get(k), np.ndarray) for k in ("nx", "ny", "nz")):
            normals = np.stack([np.asarray(vertex[k], np.float64) for k in ("nx", "ny", "nz")], axis=1)
        return points, normals
    if path.suffix.lower() == ".pcd":
        read = read_pcd(path)
        if read is not None:
            points, normals = read
            _finite(path, points)
            return points, normals
    import open3d as o3d

    pc = _open3d_read(path, o3d.io.read_point_cloud)
    points = np.asarray(pc.points, dtype=np.float64)
    _finite(path, points)
    normals = np.asarray(pc.normals, dtype=np.float64) if pc.has_normals() else None
    return points, normals


def triangle_count(path: str | Path) -> int:
    """How many faces a mesh file declares (a PLY's header alone; other formats read): 0 for
    a cloud. Tells a mesh target from a cloud without reading a large cloud twice."""
    path = Path(path)
    if path.suffix.lower() == ".ply":
        from scanner.ply_file import read_header

        face = read_header(path).element("face")
        return face.count if face is not None else 0
    return len(read_mesh(path)[1])
