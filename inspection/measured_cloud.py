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
from scipy.spatial import Delaunay, cKDTree

from inspection.errors import CloudError, UnitMismatch
from scanner.pointcloud import OrganisedCloud, PlyPixels

CLOUD_SUFFIXES = (".ply", ".pcd", ".xyz", ".xyzn", ".pts")
MIN_POINTS = 500
SUPPORT_CANDIDATES = 4  # planes tried for the table, largest first: the part's own faces come before it
SUPPORT_SAMPLE = 20000  # points the table search samples
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

    def camera_pixels(self) -> np.ndarray:
        """`pixels`, for a step that needs each point's camera pixel (the noise model's maps)."""
        if self.pixels is None:
            raise CloudError(self.source, "the cloud has no camera pixels (an unorganised cloud), "
                                          "so its noise cannot be read off the session's maps")
        return self.pixels

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
    scans in a camera frame do) is taken as seen from the origin. A PLY the scanner wrote
    keeps each point's camera pixel (`read_ply_pixels`), so a cloud file carries the same
    evidence as its session (the image's outlines and blocks of neighbouring pixels)."""
    from scanner.file_checks import FileRefused
    from scanner.pointcloud import read_ply_pixels

    path = Path(path)
    if not path.exists():
        raise CloudError(path, "no such file")
    if path.suffix.lower() not in CLOUD_SUFFIXES:
        raise CloudError(path, f"not a point cloud: expected one of {', '.join(CLOUD_SUFFIXES)}")
    try:
        return _cloud_of(path, read_ply_pixels(path) if path.suffix.lower() == ".ply" else None)
    except FileRefused as exc:
        raise CloudError(path, exc.problem) from None


def _cloud_of(path: Path, organised: PlyPixels | None) -> ScanCloud:
    """`read_cloud`'s scan of `path`, from the PLY already read with its pixels (`organised`;
    the pixels kept when they form an image), else read as a bare cloud."""
    from scanner.mesh_files import read_points

    nrm: np.ndarray | None
    pixels, shape = None, None
    if organised is None:
        pts, nrm = read_points(path)
    else:
        pts, nrm = organised.points.astype(np.float64), organised.normals.astype(np.float64)
        if organised.is_image():
            pixels, shape = organised.pixels, organised.shape()
    if len(pts) == 0:
        raise CloudError(path, "no points could be read (unreadable or empty cloud)")
    viewpoint = np.zeros(3) if np.all(pts[:, 2] > 0) else None
    return make_scan(pts, nrm, str(path), viewpoint, pixels, shape)


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
        scan = (_cloud_of(ply, None) if stored is None else
                make_scan(stored.points.astype(np.float64), stored.normals.astype(np.float64), str(ply), np.zeros(3)))
    except FileRefused as exc:
        raise CloudError(ply, exc.problem) from None
    if stored is None:  # another writer's PLY: place every point by projecting it
        px = np.rint(cam.project(scan.points)).astype(np.int64)
    else:
        px = stored.pixels
        sample = np.linspace(0, len(px) - 1, min(len(px), PIXEL_CHECK_POINTS)).astype(np.int64)
        off = np.abs(cam.project(scan.points[sample]) - px[sample]).max(initial=0.0)
        if not off <= PIXEL_CHECK_PX:
            raise CloudError(ply, f"points lie up to {off:.1f} px from the pixels the file names in this session's "
                                  f"camera: not this session's cloud")
    inside = (px[:, 0] >= 0) & (px[:, 0] < cam.width) & (px[:, 1] >= 0) & (px[:, 1] < cam.height)
    if not inside.all():
        raise CloudError(ply, "points do not project into the session's camera: not this session's cloud")
    return replace(scan, source=str(session.root), viewpoint=np.zeros(3), pixels=px,
                   image_shape=(cam.height, cam.width))


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


@dataclass(frozen=True)
class Support:
    """The plane the part stands on: `plane` (a, b, c, d) with unit normal pointing to the
    side the part is on, `band_mm` the distance within which a point is the plane's (4
    robust sigma of its points about it)."""

    plane: np.ndarray
    band_mm: float

    def above(self, points: np.ndarray) -> np.ndarray:
        """Which points lie on the part's side of the plane, beyond its band."""
        return points @ self.plane[:3] + self.plane[3] > self.band_mm


def find_support(scan: ScanCloud, seed: int = 0) -> Support | None:
    """The table the part stands on, or None when the scan shows none. The largest planes
    (RANSAC, `SUPPORT_CANDIDATES` of them, each found among the points the ones before left)
    are tried in turn; a plane is the support when the part stands on it: more of the points
    off it (beyond its band) lie on the sensor's side of it than behind it (the table is
    seen from the part's side: the part's own top has the rest of the part and the table
    behind it), and more than half of those project, along the plane's normal, inside the
    plane's own points (the part stands within the table, not beside it: a lower step of
    the part has the higher section beside it). Without a known sensor position the part's
    side is the side most of the points are on, and the plane must also spread wider than
    what stands on it. All of it is independent of the part's size and of the cloud's frame
    (distances scale with the scan's own point spacing and noise)."""
    pts = scan.points
    rng = np.random.default_rng(seed)
    sample = rng.choice(len(pts), size=min(SUPPORT_SAMPLE, len(pts)), replace=False)
    sp, sn = pts[sample], scan.normals[sample]
    spacing = point_spacing(sp, len(pts))
    remaining = np.arange(len(sp))
    for _ in range(SUPPORT_CANDIDATES):
        if len(remaining) < 100:
            return None
        plane, inl = dominant_plane(sp[remaining], sn[remaining], 3.0 * spacing, rng)
        on = remaining[inl]
        support = _support_from(sp, on, plane, scan.viewpoint)
        if support is not None:
            return support
        remaining = remaining[~inl]
    return None


def point_spacing(sample: np.ndarray, n: int) -> float:
    """The spacing (mm) of a scanned surface of `n` points from a random `sample` of them:
    the median nearest-neighbour distance of a sample of density rho on a surface is
    sqrt(ln 2 / (pi rho)) (a Poisson process), the spacing of all n points 1 / sqrt(rho n / m)."""
    nn = float(np.median(cKDTree(sample).query(sample, k=2)[0][:, 1]))
    return nn * np.sqrt(np.pi / np.log(2.0)) * np.sqrt(len(sample) / n)


def dominant_plane(points: np.ndarray, normals: np.ndarray, threshold_mm: float, rng: np.random.Generator,
                   hypotheses: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """(plane (a, b, c, d), inlier mask) of the plane holding the most points within
    `threshold_mm` whose normals lie nearer its normal than its tangent (within 45 deg:
    the strips where walls cross the plane are not its points), by RANSAC over `hypotheses`
    random triplets, scored on at most 5000 points at once (one matrix product)."""
    tri = points[rng.integers(0, len(points), size=(hypotheses, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-12
    n = n[ok] / norm[ok, None]
    planes = np.concatenate([n, -np.einsum("ij,ij->i", n, tri[ok, 0])[:, None]], axis=1)
    pick = rng.choice(len(points), size=min(5000, len(points)), replace=False)
    homo = np.concatenate([points[pick], np.ones((len(pick), 1))], axis=1)
    near = (np.abs(planes @ homo.T) < threshold_mm) & (np.abs(planes[:, :3] @ normals[pick].T) > np.sqrt(0.5))
    best = planes[int(np.argmax(near.sum(axis=1)))]
    inliers = ((np.abs(points @ best[:3] + best[3]) < threshold_mm)
               & (np.abs(normals @ best[:3]) > np.sqrt(0.5)))
    return best, inliers


def _support_from(sp: np.ndarray, on: np.ndarray, plane: np.ndarray, viewpoint: np.ndarray | None) -> Support | None:
    """The plane through the sample points `on` as the support, if the rest of `sp` stands
    on it (`find_support`); None otherwise."""
    c = sp[on].mean(axis=0)
    _, _, vt = np.linalg.svd(sp[on] - c, full_matrices=False)  # least squares through its points
    n = vt[2] if vt[2] @ plane[:3] >= 0 else -vt[2]
    d = (sp - c) @ n
    band = 4.0 * float(1.4826 * np.median(np.abs(d[on])))
    off = np.ones(len(sp), bool)
    off[on] = False
    off &= np.abs(d) > band
    if off.sum() < MIN_POINTS // 10:
        return None
    side = np.sign(float((viewpoint - c) @ n)) if viewpoint is not None else np.sign(np.median(d[off]))
    side = side or 1.0
    n, d = side * n, side * d
    front = off & (d > 0)
    if front.sum() <= (off & (d < 0)).sum():
        return None
    u = vt[0]
    v = np.cross(n, u)
    flat = np.stack([(sp - c) @ u, (sp - c) @ v], axis=1)
    hull = Delaunay(flat[on][:: max(1, on.size // 4000)])
    inside = hull.find_simplex(flat[front]) >= 0
    if inside.mean() <= 0.5:
        return None
    if viewpoint is None and _area(flat[on]) <= _area(flat[front]):
        return None
    return Support(np.append(n, -float(n @ c)), band)


def _area(xy: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return float(ConvexHull(xy[:: max(1, len(xy) // 4000)]).volume) if len(xy) >= 3 else 0.0


def part_mask(scan: ScanCloud, model_diagonal_mm: float, seed: int = 0) -> np.ndarray:
    """Which points are the part: the table it stands on (`find_support`) and what lies
    behind it are removed, then the largest piece left is kept: in an organised scan the
    largest region of the image that no table pixel crosses (the part's faces at different
    heights, and the shadows between them, are one region; stray points beyond the table,
    one), else the largest piece connected in space, with the pieces near it. Raises
    UnitMismatch when what is left cannot be the model at its units."""
    pts = scan.points
    support = find_support(scan, seed)
    keep = _off_support(scan, support) if support is not None else np.ones(len(pts), bool)
    if keep.sum() < MIN_POINTS:
        raise CloudError(scan.source, "nothing but the table in view: no part found in the scan")
    if scan.pixels is not None and scan.image_shape is not None and support is not None:
        mask = _largest_image_region(scan, keep, model_diagonal_mm)
    else:
        mask = _largest_piece(pts, keep, model_diagonal_mm, seed)
    check_units(scan.subset(mask), model_diagonal_mm)
    return mask


def _largest_image_region(scan: ScanCloud, keep: np.ndarray, model_diagonal_mm: float) -> np.ndarray:
    """The kept points in the largest (by kept points) 8-connected image region of kept
    pixels and pixels without a point, with the regions near it (`_near_pieces`), table
    pixels being the walls between regions; so are pixels without a point that reach the
    image's border (outside the field or beyond the table, not a shadow among the part's
    faces). A step's wall in its own shadow can join such pixels along the part's outline
    and cut the part in two (the demo part at random placements: its raised block, half
    the part, was left out). Of the regions, only the pieces of kept
    pixels (8-connected among themselves) that are surfaces: at least one pixel with all
    eight neighbours kept. The border of the part's shadow on the table is a line of mixed
    pixels one or two wide, read up to 0.7 mm above the table's plane (far beyond its
    noise band) and joined to the part across the shadow: a random part filling the view
    (campaign 1273036622 part_056) had such a line along its shadow, 80 px from the part,
    and was refused as 1.5 times larger than its model."""
    from scipy.ndimage import binary_erosion, label

    assert scan.pixels is not None and scan.image_shape is not None
    wall = np.ones(scan.image_shape, bool)  # no point ...
    wall[scan.pixels[:, 1], scan.pixels[:, 0]] = False
    empty, _ = label(wall, structure=np.ones((3, 3)))
    border = np.unique(np.concatenate([empty[0], empty[-1], empty[:, 0], empty[:, -1]]))
    wall = np.isin(empty, border[border > 0])  # ... reaching the border
    wall[scan.pixels[~keep, 1], scan.pixels[~keep, 0]] = True  # and the table
    regions, _ = label(~wall, structure=np.ones((3, 3)))
    of_point = regions[scan.pixels[:, 1], scan.pixels[:, 0]]
    part = np.flatnonzero(keep)
    near = _near_pieces(scan.points[part], of_point[part], model_diagonal_mm)
    kept = np.zeros(scan.image_shape, bool)
    kept[scan.pixels[keep, 1], scan.pixels[keep, 0]] = True
    pieces, count = label(kept, structure=np.ones((3, 3)))
    solid = np.zeros(count + 1, bool)
    solid[pieces[binary_erosion(kept, structure=np.ones((3, 3)))]] = True
    return keep & near[of_point] & solid[pieces[scan.pixels[:, 1], scan.pixels[:, 0]]]


def _largest_piece(pts: np.ndarray, keep: np.ndarray, model_diagonal_mm: float, seed: int) -> np.ndarray:
    """The kept points of the largest piece connected in space (on a grid of 4 point
    spacings), with the pieces whose centres lie within 0.75 model diagonals of it."""
    part = np.flatnonzero(keep)
    sample = pts[np.random.default_rng(seed).choice(part, size=min(SUPPORT_SAMPLE, len(part)), replace=False)]
    step = 4.0 * point_spacing(sample, len(part))
    cell = np.floor((pts[part] - pts[part].min(axis=0)) / step).astype(np.int64)
    dims = cell.max(axis=0) + 1
    codes, lab = np.unique((cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2], return_inverse=True)
    cells = np.stack([codes // (dims[1] * dims[2]), codes // dims[2] % dims[1], codes % dims[2]], axis=1)
    lab = _connected(cells, lab.ravel())
    mask = np.zeros(len(pts), bool)
    mask[part[_near_pieces(pts[part], lab, max(model_diagonal_mm, step))[lab]]] = True
    return mask


def _near_pieces(points: np.ndarray, piece: np.ndarray, model_diagonal_mm: float) -> np.ndarray:
    """Which pieces (bool per label of `piece`, one per point of `points`) are the part: the
    largest, and those of at least 0.2 % of its points whose centres lie within 0.75 model
    diagonals of its centre."""
    sizes = np.bincount(piece)
    big = int(np.argmax(sizes))
    centres = (np.stack([np.bincount(piece, weights=points[:, i], minlength=len(sizes)) for i in range(3)], 1)
               / np.maximum(sizes, 1)[:, None])
    near = (np.linalg.norm(centres - centres[big], axis=1) < 0.75 * model_diagonal_mm) & (sizes >= 0.002 * sizes[big])
    near[big] = True
    return near


def _off_support(scan: ScanCloud, support: Support, k: int = 8) -> np.ndarray:
    """The points on the part's side of the support, beyond its band, whose neighbours are
    mostly so too (the 3 x 3 pixels about them in an organised scan, else the `k` nearest):
    the table's own outliers (its noise has longer tails than its band) are surrounded by
    table points and stay with the table."""
    above = support.above(scan.points)
    if scan.pixels is not None and scan.image_shape is not None:
        from scipy.ndimage import uniform_filter

        up, seen = np.zeros(scan.image_shape), np.zeros(scan.image_shape)
        up[scan.pixels[:, 1], scan.pixels[:, 0]] = above
        seen[scan.pixels[:, 1], scan.pixels[:, 0]] = 1.0
        share = uniform_filter(up, 3) / np.maximum(uniform_filter(seen, 3), 1e-9)
        return above & (share[scan.pixels[:, 1], scan.pixels[:, 0]] > 0.5)
    tree = cKDTree(scan.points, balanced_tree=False, compact_nodes=False)
    idx = np.flatnonzero(above)
    _, nb = tree.query(scan.points[idx], k=k + 1)
    keep = np.zeros(len(above), bool)
    keep[idx] = above[nb[:, 1:]].mean(axis=1) > 0.5
    return keep


def _connected(cells: np.ndarray, of_point: np.ndarray) -> np.ndarray:
    """Label per point of the 26-connected pieces formed by the occupied grid `cells` (K, 3)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tree = cKDTree(cells)
    pairs = tree.query_pairs(np.sqrt(3.0) + 1e-6, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(cells), len(cells)))
    _, labels = connected_components(graph, directed=False)
    return labels[of_point]


def principal_diagonal(points: np.ndarray) -> float:
    """The diagonal (mm) of the points' bounding box along their principal axes: the same in
    any frame (an axis-aligned box grows when the points turn)."""
    sample = points[:: max(1, len(points) // 20000)]
    c = sample.mean(axis=0)
    _, _, vt = np.linalg.svd(sample - c, full_matrices=False)
    return float(np.linalg.norm(np.ptp((points - c) @ vt.T, axis=0)))


def check_units(scan: ScanCloud, model_diagonal_mm: float) -> None:
    """Raise UnitMismatch when the isolated part is far too large or small for the model
    (the part's size: the diagonal of its box along its principal axes, whatever the frame)."""
    size = principal_diagonal(scan.points)
    ratio = size / model_diagonal_mm
    if 1.0 / 40.0 < ratio < 1.5:
        return
    factor = ratio if ratio > 1 else 1.0 / ratio
    hint = next((text for f, text in _UNIT_FACTORS.items() if 0.5 * f < factor < 2.0 * f and ratio > 1), None)
    raise UnitMismatch(f"{scan.source}: the scanned part ({size:.3g} mm across) is {factor:.3g} times "
                       f"{'larger' if ratio > 1 else 'smaller'} than the model ({model_diagonal_mm:.3g} mm across)"
                       + (f"; {hint}" if hint else "; check the units of both files, or that this is the right part"))
