"""Measured clouds for inspection: reading them (session, PLY/PCD/XYZ), normals, and
isolating the part from the table it lies on.

A `ScanCloud` is in the scanner's camera frame (mm) when it comes from a session or an
slscan PLY: its `viewpoint` is then the camera centre (the origin), and `pixels` place
every point in the camera image, so deviation maps can be drawn as images.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from inspection.errors import CloudError, UnitMismatch
from scanner.pointcloud import OrganisedCloud

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".pts")
SUPPORT_EXTENT = 1.3  # a plane wider than this many model diagonals is the table, not the part
MIN_POINTS = 500
PIXEL_CHECK_POINTS = 2000  # a session's PLY: points projected to check the pixels it names
PIXEL_CHECK_PX = 1.0  # ... and how far they may land from them (triangulation residual, rounding)
_UNIT_FACTORS = {1000.0: "the model looks like metres and the scan millimetres (use --cad-unit m)",
                 25.4: "the model looks like inches and the scan millimetres (use --cad-unit in)",
                 10.0: "the model looks like centimetres and the scan millimetres (use --cad-unit cm)"}


@dataclass(frozen=True, eq=False)
class ScanCloud:
    """`points` (N, 3) mm and unit `normals` (N, 3) turned toward the sensor; `viewpoint`
    the sensor centre in the same frame (None if unknown); `pixels` (N, 2) int (column,
    row) in an `image_shape` (H, W) camera image, or None for unorganised clouds."""

    points: np.ndarray
    normals: np.ndarray
    source: str
    viewpoint: np.ndarray | None = None
    pixels: np.ndarray | None = None
    image_shape: tuple[int, int] | None = None

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, mask: np.ndarray) -> ScanCloud:
        return replace(self, points=self.points[mask], normals=self.normals[mask],
                       pixels=None if self.pixels is None else self.pixels[mask])


def estimate_normals(points: np.ndarray, query: np.ndarray | None = None, k: int = 16,
                     viewpoint: np.ndarray | None = None, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals (M, 3) at `points[query]` (default all) from the plane through their `k`
    nearest neighbours, turned toward `viewpoint` (default: the origin). The tree is built
    unbalanced (the same neighbours; on a 1.2 M-point scan 0.72 -> 0.21 s with the query of
    its 11.7 k border points, most of that the build)."""
    tree = cKDTree(points, balanced_tree=False, compact_nodes=False) if tree is None else tree
    q = points if query is None else points[query]
    _, idx = tree.query(q, k=min(k, len(points)), workers=-1)
    nb = points[idx]
    d = nb - nb.mean(axis=1, keepdims=True)
    _, vec = np.linalg.eigh(np.einsum("kni,knj->kij", d, d))
    n = vec[:, :, 0]
    toward = (np.zeros(3) if viewpoint is None else viewpoint) - q
    n[np.einsum("ij,ij->i", n, toward) < 0] *= -1.0
    return n


def from_organised(cloud: OrganisedCloud, source: str) -> ScanCloud:
    """The valid points of an organised scan (camera frame), with their pixels; normals the
    scanner could not compute (borders, holes) are estimated from neighbours."""
    pts, _, nrm = cloud.flat()
    rows, cols = np.nonzero(cloud.valid)
    return make_scan(pts.astype(np.float64), nrm.astype(np.float64), source, np.zeros(3),
                         np.stack([cols, rows], axis=1), cloud.points.shape[:2])


def make_scan(points: np.ndarray, normals: np.ndarray | None, source: str, viewpoint: np.ndarray | None,
              pixels: np.ndarray | None = None, shape: tuple[int, int] | None = None) -> ScanCloud:
    """A checked ScanCloud; missing or invalid normals are estimated from neighbours."""
    if len(points) < MIN_POINTS:
        raise CloudError(source, f"only {len(points)} points; a scan of a part needs at least {MIN_POINTS}")
    if not np.isfinite(points).all():
        raise CloudError(source, "non-finite point coordinates")
    spread = np.linalg.svd(points[:: max(1, len(points) // 20000)] - points.mean(axis=0), compute_uv=False)
    if not spread[1] > 1e-6 * max(spread[0], 1e-12):
        raise CloudError(source, "the points lie on a line (or on one point): not a scan of a surface")
    if normals is None:
        normals = np.full_like(points, np.nan)
    length = np.linalg.norm(normals, axis=1)  # once: it both finds the bad normals and scales the good ones
    bad = ~(np.isfinite(normals).all(axis=1) & (length > 0.5))
    if bad.any():
        normals = normals.copy()
        normals[bad] = estimate_normals(points, np.flatnonzero(bad), viewpoint=viewpoint)
        length[bad] = np.linalg.norm(normals[bad], axis=1)
    normals = normals / length[:, None]
    return ScanCloud(points, normals, source, viewpoint, pixels, shape)


def read_cloud(path: str | Path) -> ScanCloud:
    """A PLY, PCD or XYZ cloud in mm. A cloud lying in front of the origin (z > 0, as
    scans in a camera frame do) is taken as seen from the origin."""
    from scanner.file_checks import FileRefused
    from scanner.mesh_files import read_points

    path = Path(path)
    if not path.exists():
        raise CloudError(path, "no such file")
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise CloudError(path, f"not a point cloud: expected one of {', '.join(CLOUD_SUFFIXES)}")
    try:
        pts, nrm = read_points(path)
    except FileRefused as exc:
        raise CloudError(path, exc.problem) from None
    if len(pts) == 0:
        raise CloudError(path, "no points could be read (unreadable or empty cloud)")
    viewpoint = np.zeros(3) if np.all(pts[:, 2] > 0) else None
    return make_scan(pts, nrm, str(path), viewpoint)


def load_session(path: str | Path) -> ScanCloud:
    """The cloud of an slscan session (outputs/cloud.ply), placed back on its camera pixels:
    the pixels the PLY names (checked on a sample: those points must project onto them),
    else each point's projection."""
    from scanner.file_checks import FileRefused
    from scanner.pointcloud import read_ply_pixels
    from scanner.session import Session

    session = Session.open(path)
    ply = session.outputs / "cloud.ply"
    if not ply.exists():
        raise CloudError(session.root, f"no {ply.name}; run `slscan decode {session.root}` to make it")
    cam = session.rig_model().camera
    try:
        stored = read_ply_pixels(ply)
    except FileRefused as exc:
        raise CloudError(ply, exc.problem) from None
    if stored is None:  # another writer's PLY: place every point by projecting it
        scan = read_cloud(ply)
        px = np.rint(cam.project(scan.points)).astype(np.int64)
    else:
        points, normals, px = stored
        scan = make_scan(points.astype(np.float64), normals.astype(np.float64), str(ply), np.zeros(3))
        sample = np.linspace(0, len(px) - 1, min(len(px), PIXEL_CHECK_POINTS)).astype(np.int64)
        off = np.abs(cam.project(scan.points[sample]) - px[sample]).max(initial=0.0)
        if not off <= PIXEL_CHECK_PX:
            raise CloudError(ply, f"points lie up to {off:.1f} px from the pixels the file names in this session's "
                                  f"camera: not this session's cloud")
    inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    if not inside.all():
        raise CloudError(ply, "points do not project into the session's camera: not this session's cloud")
    return replace(scan, source=str(session.root), viewpoint=np.zeros(3), pixels=px, image_shape=(cam.height, cam.width))


def load_source(path: str | Path) -> ScanCloud:
    """A session folder or a cloud file."""
    path = Path(path)
    return load_session(path) if path.is_dir() else read_cloud(path)


def fit_plane(points: np.ndarray, threshold: float, seed: int, iterations: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """(plane (a, b, c, d) with unit normal, inlier mask) by Open3D's RANSAC, on one thread:
    on two its draws reach the iterations in a varying order and a seeded fit still changed
    from call to call (13 422-13 433 inliers of 20 000 on a turntable view), so results
    depended on what ran before."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        o3d.utility.random.seed(seed)
        plane, inl = pc.segment_plane(threshold, 3, iterations)
    finally:
        o3d.utility.set_max_threads(threads)
    mask = np.zeros(len(points), bool)
    mask[np.asarray(inl, dtype=np.int64)] = True
    return np.asarray(plane), mask


def isolate_part(scan: ScanCloud, model_diagonal_mm: float, seed: int = 0) -> ScanCloud:
    """The scan's points that belong to the part (`part_mask`)."""
    return scan.subset(part_mask(scan, model_diagonal_mm, seed))


def part_mask(scan: ScanCloud, model_diagonal_mm: float, seed: int = 0) -> np.ndarray:
    """Which points are the part: the table it lies on (a plane much wider than the
    model) and what lies behind it are removed, then the largest connected piece (with
    pieces near it) is kept. Raises UnitMismatch when what is left cannot be the model
    at its units."""
    pts = scan.points
    extent = float(np.linalg.norm(np.ptp(pts, axis=0)))
    voxel = extent / 300.0
    keep = np.ones(len(pts), bool)
    remaining = np.random.default_rng(seed).choice(len(pts), size=min(20000, len(pts)), replace=False)
    for attempt in range(3):  # the largest plane may be the part's own top: look further
        if len(remaining) < 100:
            break
        plane, inl = fit_plane(pts[remaining], 2.0 * voxel, seed + attempt)
        support = pts[remaining[inl]]
        if np.linalg.norm(np.ptp(support, axis=0)) > SUPPORT_EXTENT * model_diagonal_mm:
            d = pts @ plane[:3] + plane[3]
            front = np.sign(np.median(d[np.abs(d) > 2.0 * voxel])) if np.any(np.abs(d) > 2.0 * voxel) else 1.0
            if scan.viewpoint is not None:
                front = np.sign(scan.viewpoint @ plane[:3] + plane[3]) or front
            keep &= d * front > 2.0 * voxel
            break
        remaining = remaining[~inl]
    if keep.sum() < MIN_POINTS:
        raise CloudError(scan.source, "nothing but the table in view: no part found in the scan")
    # connected pieces on a voxel grid; keep the largest and those near it
    part = np.flatnonzero(keep)
    cell = np.floor((pts[part] - pts[part].min(axis=0)) / (2.0 * voxel)).astype(np.int64)
    grid = np.zeros(cell.max(axis=0) + 1, bool)
    grid[tuple(cell.T)] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
    lab = labels[tuple(cell.T)]
    sizes = np.bincount(lab, minlength=n + 1)
    sizes[0] = 0
    big = np.argmax(sizes)
    centre = pts[part[lab == big]].mean(axis=0)
    centres = np.stack([np.bincount(lab, weights=pts[part, i], minlength=n + 1) for i in range(3)], 1) / np.maximum(sizes, 1)[:, None]
    near = (np.linalg.norm(centres - centre, axis=1) < 0.75 * max(model_diagonal_mm, voxel)) & (sizes >= 0.002 * sizes[big])
    near[big] = True
    mask = np.zeros(len(pts), bool)
    mask[part[near[lab]]] = True
    check_units(scan.subset(mask), model_diagonal_mm)
    return mask


def check_units(scan: ScanCloud, model_diagonal_mm: float) -> None:
    """Raise UnitMismatch when the isolated part is far too large or small for the model."""
    size = float(np.linalg.norm(np.ptp(scan.points, axis=0)))
    ratio = size / model_diagonal_mm
    if 1.0 / 40.0 < ratio < 1.5:
        return
    factor = ratio if ratio > 1 else 1.0 / ratio
    hint = next((text for f, text in _UNIT_FACTORS.items() if 0.5 * f < factor < 2.0 * f and ratio > 1), None)
    raise UnitMismatch(f"{scan.source}: the scanned part ({size:.3g} mm across) is {factor:.3g} times "
                       f"{'larger' if ratio > 1 else 'smaller'} than the model ({model_diagonal_mm:.3g} mm across)"
                       + (f"; {hint}" if hint else "; check the units of both files, or that this is the right part"))
