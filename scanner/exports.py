"""A scan's cloud written for other tools: PLY, XYZ, CSV, E57 (ASTM E57, through pye57) and
STL (a mesh from the camera grid, `scanner.grid_mesh`).

Every format says what it holds: the frame (the camera's, or the CAD model's of the
session's inspection), units, and each point's camera pixel (`row`, `col`) where the
format has room for it (PLY, CSV, E57 rowIndex/columnIndex; XYZ has no header beyond a
`#` comment line and holds coordinates only). Per-point signed deviations from CAD
(mm, positive = excess material) go in a PLY property `deviation`, a CSV column
`deviation_mm`, an XYZ fourth column, and E57 `intensity` (the standard has no other scalar
field pye57 writes; the scan's name says so). Units: mm, except E57, which stores metres
as its standard requires. Files appear complete or not at all.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from scanner.grid_mesh import JUMP_SPACINGS, grid_triangles, neighbour_spacing

FORMATS = ("ply", "xyz", "csv", "e57", "stl")
E57_METRES_PER_MM = 1e-3
STL_RECORD = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])


@dataclass(frozen=True, eq=False)
class ExportCloud:
    """Points (N, 3) mm in `frame`; `pixels` (N, 2) int (row, col) in an `image_shape`
    (H, W) camera image; `grey` (N,) uint8; `normals` (N, 3) or None; `deviation_mm` (N,)
    signed deviation from CAD or None; `source` names where the points came from;
    `camera_centre` (3,) mm the camera's centre in `frame` (depths are measured from it)."""

    points: np.ndarray
    pixels: np.ndarray
    image_shape: tuple[int, int]
    grey: np.ndarray
    normals: np.ndarray | None
    frame: str
    source: str
    deviation_mm: np.ndarray | None = None
    camera_centre: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __len__(self) -> int:
        return len(self.points)

    def transformed(self, transform: np.ndarray, frame: str) -> ExportCloud:
        """The cloud mapped by a 4x4 rigid `transform` into `frame`."""
        r, t = transform[:3, :3], transform[:3, 3]
        normals = None if self.normals is None else self.normals @ r.T
        return replace(self, points=self.points @ r.T + t, normals=normals, frame=frame,
                       camera_centre=r @ self.camera_centre + t)

    def subset(self, keep: np.ndarray) -> ExportCloud:
        def pick(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[keep]

        return replace(self, points=self.points[keep], pixels=self.pixels[keep], grey=self.grey[keep],
                       normals=pick(self.normals), deviation_mm=pick(self.deviation_mm))

    def describe(self) -> str:
        h, w = self.image_shape
        return (f"slscan cloud from {self.source}: mm, {self.frame}; {len(self)} points, the valid pixels of a "
                f"{w} x {h} camera image")


def write(cloud: ExportCloud, path: str | Path, fmt: str, max_jump_mm: float | None = None) -> str:
    """Write `cloud` as `fmt` (one of FORMATS) to `path`; a one-line summary of what was
    written. `max_jump_mm`: STL only, the depth-jump limit (default JUMP_SPACINGS x the
    median neighbour spacing)."""
    from scanner.session import temp_path

    path = Path(path)
    tmp = temp_path(path)
    try:
        if fmt == "stl":
            summary = write_stl(cloud, tmp, max_jump_mm)
        else:
            {"ply": write_ply, "xyz": write_xyz, "csv": write_csv, "e57": write_e57}[fmt](cloud, tmp)
            summary = f"{len(cloud)} points"
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)
    return summary


def write_ply(cloud: ExportCloud, path: Path) -> None:
    """Binary PLY: x y z (mm), normals, grey as red/green/blue, row, col, and `deviation`
    (mm) when the cloud has deviations."""
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")] if cloud.normals is not None else []
    fields += [("red", "u1"), ("green", "u1"), ("blue", "u1"), ("row", "<i4"), ("col", "<i4")]
    fields += [("deviation", "<f4")] if cloud.deviation_mm is not None else []
    rec = np.empty(len(cloud), dtype=fields)
    for i, k in enumerate("xyz"):
        rec[k] = cloud.points[:, i]
        if cloud.normals is not None:
            rec["n" + k] = np.nan_to_num(cloud.normals[:, i])
    rec["red"] = rec["green"] = rec["blue"] = cloud.grey
    rec["row"], rec["col"] = cloud.pixels[:, 0], cloud.pixels[:, 1]
    comments = [cloud.describe(), "row, col: the camera pixel of each point"]
    if cloud.deviation_mm is not None:
        rec["deviation"] = cloud.deviation_mm
        comments.append("deviation: signed distance from the CAD surface, mm, positive = excess material")
    PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<", comments=comments).write(str(path))


def write_xyz(cloud: ExportCloud, path: Path) -> None:
    """Text, one point per line: x y z (mm) [deviation_mm]; a `#` comment line first."""
    dev = cloud.deviation_mm
    data = np.hstack([cloud.points] + ([dev[:, None]] if dev is not None else []))
    names = "x y z" + (" deviation_mm" if dev is not None else "")
    _write_text(path, f"# {cloud.describe()}; columns: {names}; no pixel index\n", data, ["%.5f"] * data.shape[1],
                " ")


def write_csv(cloud: ExportCloud, path: Path) -> None:
    """CSV with a header row: x_mm, y_mm, z_mm, row, col[, deviation_mm]."""
    dev = cloud.deviation_mm
    names = ["x_mm", "y_mm", "z_mm", "row", "col"] + (["deviation_mm"] if dev is not None else [])
    data = np.hstack([cloud.points, cloud.pixels] + ([dev[:, None]] if dev is not None else []))
    _write_text(path, ",".join(names) + "\n", data, ["%.5f"] * 3 + ["%d"] * 2 + (["%.5f"] if dev is not None else []),
                ",")


def _write_text(path: Path, header: str, data: np.ndarray, formats: list[str], sep: str,
                rows_per_block: int = 65536) -> None:
    """`header`, then one line per row of `data` (N, k) with `formats`: a block of rows is
    formatted by one string operation (about 3x faster than numpy.savetxt's row loop)."""
    line = sep.join(formats) + "\n"
    with open(path, "w") as f:
        f.write(header)
        for start in range(0, len(data), rows_per_block):
            block = data[start:start + rows_per_block]
            f.write((line * len(block)) % tuple(block.ravel().tolist()))


def write_e57(cloud: ExportCloud, path: Path) -> None:
    """ASTM E57 through pye57: one scan, cartesian coordinates in metres, rowIndex and
    columnIndex the camera pixel, intensity the grey level (0..255) or, with deviations,
    the signed deviation in mm (the scan's name says which)."""
    import pye57

    if cloud.image_shape[0] > 65535 or cloud.image_shape[1] > 65535:
        raise ValueError("E57 export: pixel indices above 65535 do not fit pye57's 16-bit row/column fields")
    xyz = cloud.points * E57_METRES_PER_MM
    data = {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2],
            "rowIndex": cloud.pixels[:, 0].astype(np.uint16), "columnIndex": cloud.pixels[:, 1].astype(np.uint16)}
    if cloud.deviation_mm is not None:
        data["intensity"] = cloud.deviation_mm.astype(np.float64)
        what = "intensity = signed deviation from CAD (mm, + excess material)"
    else:
        data["intensity"] = cloud.grey.astype(np.float64)
        what = "intensity = grey level 0..255"
    e57 = pye57.E57(str(path), mode="w")
    try:
        e57.write_scan_raw(data, name=f"{cloud.describe()}; coordinates in metres; {what}")
    finally:
        e57.close()


def write_stl(cloud: ExportCloud, path: Path, max_jump_mm: float | None = None) -> str:
    """Binary STL of the camera grid's triangles (`grid_triangles`), mm; the header names
    the frame. Returns a summary with the triangle count and the jump limit used."""
    h, w = cloud.image_shape
    index = np.full((h, w), -1, dtype=np.int64)
    index[cloud.pixels[:, 0], cloud.pixels[:, 1]] = np.arange(len(cloud))
    if max_jump_mm is None:
        max_jump_mm = JUMP_SPACINGS * neighbour_spacing(index, cloud.points)
    depth = np.linalg.norm(cloud.points - cloud.camera_centre, axis=1)  # the same in any frame
    tris = grid_triangles(index, depth, max_jump_mm)
    v = cloud.points[tris].astype(np.float32)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    rec = np.zeros(len(tris), dtype=STL_RECORD)
    rec["normal"], rec["vertices"] = n, v
    header = f"slscan mesh, mm, {cloud.frame}".encode()[:80].ljust(80, b" ")
    with open(path, "wb") as f:
        f.write(header)
        f.write(np.uint32(len(tris)).tobytes())
        f.write(rec.tobytes())
    return f"{len(tris)} triangles on {len(cloud)} points (depth-jump limit {max_jump_mm:.3g} mm)"



def read_session_cloud(path: str | Path, source: str) -> ExportCloud:
    """A session's `outputs/cloud.ply` (written by `scanner.pointcloud.write_ply`, camera
    frame, with each point's pixel) as an ExportCloud."""
    from scanner.errors import SessionError
    from scanner.ply_file import read_ply, vertex_positions

    header, elements = read_ply(path)
    v = elements.get("vertex", {})
    scalar = {k: a for k, a in v.items() if isinstance(a, np.ndarray)}  # the properties that are not lists
    if not {"row", "col"} <= scalar.keys():
        raise SessionError(f"{path}: the cloud has no pixel index (row, col); run `slscan decode` on the session "
                           f"to write it again")
    size = next((c.split(" of a ")[1].split(" camera")[0] for c in header.comments if " of a " in c), None)
    if size is None:
        raise SessionError(f"{path}: the header does not say the camera image size; run `slscan decode` again")
    try:
        w, h = (int(x) for x in size.split(" x "))
    except ValueError:
        raise SessionError(f"{path}: the header's camera image size {size!r} is not W x H; run `slscan decode` "
                           f"again") from None
    points = vertex_positions(path, v)
    normals = np.stack([scalar["nx"], scalar["ny"], scalar["nz"]], axis=1).astype(np.float64) \
        if "nx" in scalar else None
    grey = scalar["red"].astype(np.uint8) if "red" in scalar else np.zeros(len(points), np.uint8)
    pixels = np.stack([scalar["row"], scalar["col"]], axis=1).astype(np.int64)
    outside = (pixels < 0).any(axis=1) | (pixels[:, 0] >= h) | (pixels[:, 1] >= w)
    if not 0 < w <= 65536 or not 0 < h <= 65536 or outside.any():
        raise SessionError(f"{path}: point {int(np.argmax(outside))} names pixel {pixels[np.argmax(outside)].tolist()} "
                           f"outside the {w} x {h} image its header gives; run `slscan decode` again")
    return ExportCloud(points, pixels, (h, w), grey, normals,
                       "camera frame (x right, y down, z forward)", source)
