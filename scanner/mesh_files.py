"""Meshes and point clouds from files, each verified before it is used (one reader for every
command: `cad`, `inspect`, `register`, `segment`, `pose`, the simulator's scenes).

PLY is read by `scanner.ply_file` (counts checked against the file's bytes). A binary STL's
triangle count must match its size exactly (84 + 50 bytes per triangle). The other formats
(ASCII STL, OBJ, PCD, XYZ, PTS) are read by Open3D under `native_output`: a line Open3D writes
that says a read failed refuses the file (its reader gives no status), and a PCD header's
point count must fit the file. Every file is a regular file within the size cap; vertices
must be finite and triangle indices inside the vertex list.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scanner.file_checks import FileRefused, native_output, regular_size
from scanner.ply_file import face_triangles, read_ply, vertex_positions

FAILURE_WORDS = ("fail", "error", "unable", "cannot", "invalid")  # in a line Open3D writes while it reads


def _open3d_read(path: Path, read: str) -> object:
    """Open3D's `read` ("read_triangle_mesh" or "read_point_cloud") of `path`, its messages
    judged: a failure line refuses the file."""
    import open3d as o3d

    with native_output() as said:
        result = getattr(o3d.io, read)(str(path))
    failed = said.failures(*FAILURE_WORDS)
    if failed:
        raise FileRefused(path, f"unreadable ({failed[0].replace('[Open3D WARNING]', 'Open3D:').strip()[:160]})")
    return result


def _stl_binary_check(path: Path, size: int) -> None:
    """A binary STL (not starting with 'solid' followed by ASCII facets) holds exactly its
    declared triangle count."""
    with open(path, "rb") as f:
        start = f.read(4096)
    head = start[:84]
    if head[:5].lower() == b"solid" and b"facet" in start:
        return  # ASCII: Open3D parses it, its messages judged
    if len(head) < 84:
        raise FileRefused(path, f"not a usable STL file: {len(head)} bytes, a binary STL's header alone is 84")
    n = int(np.frombuffer(head, "<u4", 1, 80)[0])
    if size != 84 + 50 * n:
        raise FileRefused(path, f"not a usable STL file: its header declares {n} triangles ({84 + 50 * n} bytes), "
                                f"the file holds {size} bytes (cut short, or a header that lies)")


def _pcd_check(path: Path, size: int) -> None:
    """A PCD header's POINTS (or WIDTH x HEIGHT) must fit the bytes after it."""
    with open(path, "rb") as f:
        head = f.read(4096).decode("latin-1")
    fields: dict[str, list[str]] = {}
    for line in head.splitlines():
        words = line.split()
        if words and not words[0].startswith("#"):
            fields[words[0].upper()] = words[1:]
            if words[0].upper() == "DATA":
                break
    try:
        points = int(fields["POINTS"][0]) if "POINTS" in fields else int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
        counts = fields.get("COUNT", ["1"] * len(fields["SIZE"]))
        per_point = sum(int(s) * int(c) for s, c in zip(fields["SIZE"], counts))
        data = fields["DATA"][0].lower()
    except (KeyError, IndexError, ValueError):
        raise FileRefused(path, "not a usable PCD file: its header lacks POINTS/WIDTH, SIZE or DATA") from None
    least = points * (per_point if data == "binary" else 2 * len(fields["SIZE"]) if data == "ascii" else 0)
    if points < 0 or least > size:
        raise FileRefused(path, f"not a usable PCD file: its header declares {points} points, which need at least "
                                f"{least} bytes; the file holds {size} (cut short, or a header that lies)")


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float64, triangles (M, 3) int64) of a PLY, STL or OBJ mesh, verified
    (see the module docstring); FileRefused when the file cannot be trusted."""
    path = Path(path)
    size = regular_size(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        _, data = read_ply(path)
        if "vertex" not in data:
            raise FileRefused(path, "not a usable PLY mesh: no 'vertex' element")
        v = vertex_positions(path, data["vertex"])
        t = face_triangles(path, data["face"], len(v)) if "face" in data else np.empty((0, 3), np.int64)
        return v, t
    if suffix == ".stl":
        _stl_binary_check(path, size)
    mesh = _open3d_read(path, "read_triangle_mesh")
    v = np.asarray(mesh.vertices, dtype=np.float64)  # type: ignore[attr-defined]
    t = np.asarray(mesh.triangles, dtype=np.int64)  # type: ignore[attr-defined]
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise FileRefused(path, f"vertex {int(np.argmax(bad))} of {len(v)} has a non-finite coordinate")
    if len(t) and (t.min() < 0 or t.max() >= len(v)):
        raise FileRefused(path, f"a triangle names vertex {int(t.max() if t.max() >= len(v) else t.min())}, but the "
                                f"file has {len(v)} vertices")
    return v, t


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(points (N, 3) float64, normals (N, 3) or None) of a PLY, PCD, XYZ, XYZN or PTS
    cloud, verified (see the module docstring)."""
    path = Path(path)
    size = regular_size(path)
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
        _pcd_check(path, size)
    pc = _open3d_read(path, "read_point_cloud")
    points = np.asarray(pc.points, dtype=np.float64)  # type: ignore[attr-defined]
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise FileRefused(path, f"point {int(np.argmax(bad))} of {len(points)} has a non-finite coordinate")
    normals = np.asarray(pc.normals, dtype=np.float64) if pc.has_normals() else None  # type: ignore[attr-defined]
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
