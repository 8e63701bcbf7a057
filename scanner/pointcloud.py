"""Organised point clouds: (H, W, 3) points in mm with NaN where invalid, colours,
normals, and PLY output (the valid points with the pixel each came from)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from plyfile import PlyData, PlyElement

PLY_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("row", "<i4"), ("col", "<i4")])


def _offset(dtype: np.dtype, name: str) -> int:
    """The byte offset of field `name` in the structured `dtype`."""
    fields = dtype.fields
    if fields is None:
        raise TypeError(f"{dtype} is not a structured dtype")
    return int(fields[name][1])


_PLY_GROUPS = np.dtype({"names": ["position", "normal", "grey", "row", "col"],  # PLY_VERTEX's bytes, grouped
                        "formats": [("<f4", 3), ("<f4", 3), ("u1", 3), "<i4", "<i4"],
                        "offsets": [_offset(PLY_VERTEX, k) for k in ("x", "nx", "red", "row", "col")],
                        "itemsize": PLY_VERTEX.itemsize})


@dataclass(eq=False)
class OrganisedCloud:
    """Points (H, W, 3) float32 mm in the camera frame, NaN where invalid; colours (H, W)
    uint8 grey from the texture; normals (H, W, 3) unit vectors facing the camera."""

    points: np.ndarray
    colors: np.ndarray
    normals: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return ~np.isnan(self.points[..., 2])

    def __len__(self) -> int:
        return int(self.valid.sum())

    def flat(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M, 3) points, (M,) colours and (M, 3) normals of the valid pixels, row-major."""
        idx = self.valid_indices()
        return self.points.reshape(-1, 3)[idx], self.colors.reshape(-1)[idx], self.normals.reshape(-1, 3)[idx]

    def valid_indices(self) -> np.ndarray:
        """Row-major flat indices (row * W + col) of the valid pixels: one gather by index
        is ~3x cheaper than a boolean mask applied to each array."""
        return np.flatnonzero(self.valid)


NORMAL_BLOCK_ROWS = 16  # rows of normals computed together: their float32 temporaries stay in a core's L2 cache


def organised_normals(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) from central differences of an organised cloud given as
    coordinate planes (H, W) each, oriented toward the camera (negative z); NaN where a
    neighbour is missing and on the image border."""
    h, w = z.shape
    n = np.empty((h, w, 3), dtype=np.float32)
    n[0] = n[-1] = np.nan
    if h > 2:
        normals_into(x, y, z, n[1:-1])
    return n


def normals_into(x: np.ndarray, y: np.ndarray, z: np.ndarray, out: np.ndarray) -> None:
    """The normals (as `organised_normals`) of rows 1 .. k of coordinate planes (k + 2, W)
    into `out` (k, W, 3) float32, NaN in the first and last column. Computed
    NORMAL_BLOCK_ROWS rows at a time in reused buffers: the same float32 operations in the
    same order per pixel, without whole-band temporaries going through memory."""
    k, w = out.shape[0], out.shape[1]
    out[:, 0] = out[:, -1] = np.nan
    if k == 0 or w < 3:
        return
    block = min(NORMAL_BLOCK_ROWS, k)
    ux, uy, uz, vx, vy, vz, nx, ny, nz, tmp, scale = np.empty((11, block, w - 2), np.float32)
    for r0 in range(0, k, block):
        b = min(block, k - r0)
        centre = slice(r0 + 1, r0 + 1 + b)
        row, col = (centre, slice(2, None)), (centre, slice(None, -2))
        up, down = (slice(r0 + 2, r0 + 2 + b), slice(1, -1)), (slice(r0, r0 + b), slice(1, -1))
        bux, buy, buz, bvx, bvy, bvz, bnx, bny, bnz, btmp, bscale = (
            a[:b] for a in (ux, uy, uz, vx, vy, vz, nx, ny, nz, tmp, scale))
        for p, u, v in ((x, bux, bvx), (y, buy, bvy), (z, buz, bvz)):
            np.subtract(p[row], p[col], out=u)
            np.subtract(p[up], p[down], out=v)
        for n, (a, b_, c, d) in ((bnx, (buy, bvz, buz, bvy)), (bny, (buz, bvx, bux, bvz)),
                                 (bnz, (bux, bvy, buy, bvx))):
            np.multiply(a, b_, out=n)  # n = a·b − c·d, each product rounded as before
            np.multiply(c, d, out=btmp)
            n -= btmp
        np.square(bnx, out=bscale)
        bscale += np.square(bny, out=btmp)
        bscale += np.square(bnz, out=btmp)
        np.sqrt(bscale, out=bscale)
        np.divide(np.float32(1.0), bscale, out=bscale)
        np.negative(bnz, out=btmp)
        np.copysign(bscale, btmp, out=bscale)  # unit length, facing the camera (normal z < 0)
        for i, comp in enumerate((bnx, bny, bnz)):
            np.multiply(comp, bscale, out=out[r0:r0 + b, 1:-1, i])


def from_planes(x: np.ndarray, y: np.ndarray, z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Interleave coordinate planes (H, W) into points (H, W, 3), into `out` when given
    (OpenCV writes a C-contiguous float32 `out` of that shape in place: no second copy)."""
    merged = cv2.merge([x, y, z], dst=out)
    if out is None:
        return merged
    if merged is not out:  # OpenCV made a new array (an `out` it cannot write in place)
        out[...] = merged
    return out


def write_ply(path: str | Path, cloud: OrganisedCloud, comments: list[str] | None = None) -> int:
    """Write the valid points as a binary little-endian PLY (through `plyfile`): position
    and normal (mm, camera frame), grey colour, and the camera pixel each point came from
    (`row`, `col`, so the organised layout can be rebuilt); the header says the file holds
    only the valid pixels of a W x H image, and `comments` add lines to it. Returns the number
    of points. The file appears complete or not at all."""
    idx = cloud.valid_indices()
    height, width = cloud.valid.shape
    rec = np.empty(len(idx), dtype=PLY_VERTEX)
    fields = rec.view(_PLY_GROUPS)  # the same bytes, the vertex's triples as (M, 3) columns
    np.take(cloud.points.reshape(-1, 3), idx, axis=0, out=fields["position"], mode="clip")  # gathered in place
    nrm = fields["normal"]
    np.take(cloud.normals.reshape(-1, 3), idx, axis=0, out=nrm, mode="clip")
    nrm[np.isnan(nrm)] = 0.0
    fields["grey"] = cloud.colors.reshape(-1)[idx][:, None]
    rec["row"], rec["col"] = np.divmod(idx, width)  # row-major, as `flat` orders the points
    comments = ["slscan cloud: mm, camera frame (x right, y down, z forward)",
                f"the valid pixels only of a {width} x {height} camera image; row, col: the pixel of each point",
                *(comments or [])]
    from scanner.session import open_new, temp_path

    path = Path(path)
    tmp = temp_path(path)
    try:
        with open_new(tmp) as f:
            PlyData([PlyElement.describe(rec, "vertex")], text=False, byte_order="<", comments=comments).write(f)
        tmp.replace(path)
    except BaseException:  # e.g. a full disk: no partial file left behind
        tmp.unlink(missing_ok=True)
        raise
    return len(idx)


@dataclass(frozen=True, eq=False)
class PlyPixels:
    """A PLY `write_ply` wrote: `points` (M, 3) mm, `normals` (M, 3), zero where the scanner
    had none, `pixels` (M, 2) int (column, row) of each point's camera pixel, and
    `image_shape` (H, W) as the header states it (None when it does not)."""

    points: np.ndarray
    normals: np.ndarray
    pixels: np.ndarray
    image_shape: tuple[int, int] | None

    def shape(self) -> tuple[int, int]:
        """The image (H, W): as the header states it, else the smallest holding the pixels."""
        return self.image_shape or (int(self.pixels[:, 1].max()) + 1, int(self.pixels[:, 0].max()) + 1)

    def is_image(self) -> bool:
        """Whether the pixels can be an image's: non-negative, inside the stated shape and
        one point per pixel (what a writer other than `write_ply` may not keep)."""
        px = self.pixels
        if len(px) == 0 or px.min() < 0:
            return False
        h, w = self.shape()
        if px[:, 0].max() >= w or px[:, 1].max() >= h:
            return False
        return len(np.unique(px[:, 1] * w + px[:, 0])) == len(px)


IMAGE_COMMENT = re.compile(r"the valid pixels only of a (\d+) x (\d+) camera image")


PIXEL_COLUMNS = frozenset({"col", "row", "nx", "ny", "nz"})  # the vertex columns `write_ply` adds to x, y, z


def read_ply_pixels(path: str | Path) -> PlyPixels | None:
    """The points, normals and camera pixels of a PLY `write_ply` wrote, verified
    (`scanner.ply_file`: counts against the file's bytes, finite points); None for a PLY
    without the pixel columns, known from its header alone (its body is not read)."""
    from scanner.ply_file import read_header, read_ply, vertex_positions

    spec = read_header(path).element("vertex")
    if spec is None or not PIXEL_COLUMNS.issubset(p.name for p in spec.properties if p.count_type is None):
        return None
    header, elements = read_ply(path)
    vertex = elements.get("vertex", {})
    columns = {k: v for k in PIXEL_COLUMNS if isinstance(v := vertex.get(k), np.ndarray)}
    size = next((m for m in map(IMAGE_COMMENT.search, header.comments) if m), None)
    return PlyPixels(vertex_positions(path, vertex), np.stack([columns["n" + k] for k in "xyz"], axis=1),
                     np.stack([columns["col"], columns["row"]], axis=1).astype(np.int64),
                     None if size is None else (int(size[2]), int(size[1])))


def read_ply_points(path: str | Path) -> np.ndarray:
    """The (M, 3) vertex positions of a PLY file, verified (`scanner.ply_file`)."""
    from scanner.ply_file import vertex_positions

    return vertex_positions(path, _vertex(path))


def _vertex(path: str | Path) -> dict:
    from scanner.file_checks import FileRefused
    from scanner.ply_file import read_ply

    _, elements = read_ply(path)
    if "vertex" not in elements:
        raise FileRefused(path, "not a usable PLY cloud: no 'vertex' element")
    return elements["vertex"]
