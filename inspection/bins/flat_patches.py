"""Part instances in an organised scan of a bin without masks: the flat patches standing
above the tray.

A thin part lying on the tray or on other parts is a flat patch; where one part lies on
another, or on the tray, its edge is a depth step of at least its thickness. A fringe
scan blurs that step over a few pixels (a pixel straddling an edge decodes to a depth
mixed from both sides), so a threshold on neighbouring depths alone leaks across it
wherever the ramp's single steps stay small. Here:

1. the tray is the dominant plane (RANSAC within `tray_tol_mm`); pixels more than that
   above it (toward the camera) are candidates;
2. each candidate's `window` x `window` neighbourhood gets a least-squares plane (in
   pixel coordinates, z along the camera axis, from box filters: no loop over pixels);
   its RMS residual is the camera noise (~0.015 mm) on a flat part and several times that
   where the window straddles a step. Pixels below `max_residual_mm` form the cores;
   connected cores (4-neighbours with depths within `step_mm`) are the patches, each
   split by planes where pieces of it lie more than `step_mm` off its dominant plane
   (two parts meeting at the same depth along a line, one tilted, leave no step);
3. every patch gets its plane (robust fit), and grows back into the band of rejected
   pixels around it, a pixel joining a neighbouring patch when it lies within
   `join_mm` of that patch's plane: the band's pixels on a part's own surface come back,
   those mixed with a lower or higher surface stay out (their depth is neither).

Patches smaller than `min_points` are dropped; ids 1.. by size. A part split in two by a
part lying across it gives two patches (the pose step judges whether one pose explains
both); two parts touching edge to edge at the same height give one (the pose step finds
that one pose explains only part of it). Units: mm.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from inspection.bins.instances import Instance
from inspection.measured_cloud import fit_plane
from scanner.pointcloud import OrganisedCloud

MIN_CORE = 20   # core pixels a patch needs to fit its plane and grow back


def tray_plane(cloud: OrganisedCloud, tol_mm: float, seed: int = 0) -> tuple[np.ndarray, float]:
    """(unit normal n, offset d) of the dominant plane of the scan (RANSAC within `tol_mm`
    on up to 50 000 points), signed so that n·p + d grows toward the camera at the origin."""
    pts = cloud.points.reshape(-1, 3).astype(np.float64)
    idx = np.flatnonzero(cloud.valid.ravel())
    rng = np.random.default_rng(seed)
    sub = pts[rng.choice(idx, size=min(50000, len(idx)), replace=False)]
    plane, _ = fit_plane(sub, tol_mm, seed)
    n, d = np.asarray(plane[:3], dtype=np.float64), float(plane[3])
    return (-n, -d) if d < 0 else (n, d)


def local_plane_residual(z: np.ndarray, window: int) -> np.ndarray:
    """RMS residual (H, W) of the least-squares plane z = a + b·col + c·row through the
    finite values of each `window` x `window` neighbourhood (inf where fewer than 60 % of
    them are finite, or at a non-finite pixel)."""
    finite = np.isfinite(z)
    w = finite.astype(np.float64)
    zz = np.where(finite, z, 0.0).astype(np.float64)
    rows, cols = np.mgrid[0:z.shape[0], 0:z.shape[1]].astype(np.float64)
    rows -= rows.mean()
    cols -= cols.mean()

    def box(a: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(a, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)

    n = box(w)
    safe = np.maximum(n, 1.0)
    mu, mv, mz = box(w * cols) / safe, box(w * rows) / safe, box(zz) / safe
    cuu = box(w * cols * cols) - n * mu * mu
    cvv = box(w * rows * rows) - n * mv * mv
    cuv = box(w * cols * rows) - n * mu * mv
    cuz = box(zz * cols) - n * mu * mz
    cvz = box(zz * rows) - n * mv * mz
    czz = box(zz * zz) - n * mz * mz
    det = cuu * cvv - cuv * cuv
    ok = finite & (n >= 0.6 * window * window) & (det > 1e-9)
    det = np.where(ok, det, 1.0)
    b = (cvv * cuz - cuv * cvz) / det
    c = (cuu * cvz - cuv * cuz) / det
    rss = np.maximum(czz - b * cuz - c * cvz, 0.0)
    return np.where(ok, np.sqrt(rss / safe), np.inf)


def _plane_of(points: np.ndarray) -> np.ndarray:
    """(n, d) of a robust plane through points (N, 3): SVD, refitted twice to the points
    within 3 robust sigma."""
    keep = np.ones(len(points), bool)
    for _ in range(3):
        c = points[keep].mean(axis=0)
        n = np.linalg.svd(points[keep][:: max(1, keep.sum() // 5000)] - c, full_matrices=False)[2][2]
        r = (points - c) @ n
        keep = np.abs(r) < max(3.0 * 1.4826 * float(np.median(np.abs(r[keep]))), 1e-3)
    return np.r_[n, -n @ c]


def instances_from_flat_patches(cloud: OrganisedCloud, thickness_mm: float, window: int = 7,
                                max_residual_mm: float = 0.035, min_points: int = 200,
                                seed: int = 0) -> list[Instance]:
    """The flat patches above the tray as instances (see the module docstring): tolerances
    from the part's `thickness_mm` (tray and depth steps 0.3 and 0.4 of it, re-joining
    within 0.2 of it)."""
    valid = cloud.valid
    if valid.sum() < 3:
        return []
    tray_tol, step, join = 0.3 * thickness_mm, 0.4 * thickness_mm, 0.2 * thickness_mm
    n, d = tray_plane(cloud, tray_tol, seed)
    pts = cloud.points.astype(np.float64)
    above = valid & (np.where(valid[..., None], pts, 0.0) @ n + d > tray_tol)
    if not above.any():
        return []
    rows, cols = np.nonzero(above)
    r0, r1 = max(rows.min() - window, 0), rows.max() + window + 1
    c0, c1 = max(cols.min() - window, 0), cols.max() + window + 1
    crop = (slice(r0, r1), slice(c0, c1))
    sub, p = above[crop], pts[crop]
    z = np.where(sub, p[..., 2], np.nan)
    core = sub & (local_plane_residual(z, window) < max_residual_mm)
    labels = _components(core, z, step)
    sizes = np.bincount(labels.ravel())
    labels = np.where(sizes[labels] >= MIN_CORE, labels, 0)   # crumbs: no plane to grow back with
    kept = np.flatnonzero(np.bincount(labels.ravel()))
    rank = np.zeros(kept[-1] + 1, np.intp)
    rank[kept] = np.arange(len(kept))
    labels = _one_plane_each(rank[labels], p, step)   # numbered 0, 1, ... in the order of their labels
    labels = _grow_back(labels, sub, p, join, window)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    order = [c for c in np.argsort(-sizes, kind="stable") if sizes[c] >= min_points]
    # each patch's pixels in raster order from one stable sort of the crop's labels (crop
    # raster order is the image's), as image pixel indices
    by_label = np.argsort(labels.ravel(), kind="stable")
    starts = np.searchsorted(labels.ravel()[by_label], np.arange(len(sizes) + 1))
    out = []
    for k, c in enumerate(order, start=1):
        at = by_label[starts[c]:starts[c + 1]]
        idx = (at // sub.shape[1] + r0) * valid.shape[1] + at % sub.shape[1] + c0
        mask = np.zeros(valid.shape, bool)
        mask.ravel()[idx] = True
        out.append(Instance(k, idx, pts.reshape(-1, 3)[idx], cloud.normals.reshape(-1, 3)[idx].astype(np.float64),
                            "segmentation", mask))
    return out


def _components(core: np.ndarray, z: np.ndarray, step_mm: float) -> np.ndarray:
    """Labels (0: none) of the 4-connected components of `core`, less its pixels that
    differ by `step_mm` or more from a core 4-neighbour (so no component crosses a step)."""
    keep = core.copy()
    for axis in (0, 1):
        a = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        b = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))
        jump = core[a] & core[b] & ~(np.abs(z[a] - z[b]) < step_mm)
        keep[a] &= ~jump
        keep[b] &= ~jump
    return ndimage.label(keep)[0]


def _dominant_plane(points: np.ndarray, tol_mm: float, seed: int = 0) -> np.ndarray:
    """Indices of the points within `tol_mm` of the plane most of them lie on (RANSAC on up
    to 20 000 of them)."""
    sub = np.random.default_rng(seed).choice(len(points), size=min(20000, len(points)), replace=False)
    plane, _ = fit_plane(points[sub], tol_mm, seed, iterations=200)
    return np.flatnonzero(np.abs(points @ np.asarray(plane[:3]) + plane[3]) < tol_mm)


def _one_plane_each(labels: np.ndarray, points: np.ndarray, off_mm: float) -> np.ndarray:
    """`labels` with each component split by planes: the pieces of it farther than
    `off_mm` from its dominant plane (RANSAC) get planes of their own, and every pixel of
    the component goes to the nearest of these planes. Two parts whose surfaces meet at
    the same depth along a line (one tilted under the other's edge) leave no step to
    split on, but each lies in its own plane."""
    out = labels.copy()
    top = int(labels.max())   # the largest label in `out` so far
    for c, box in enumerate(ndimage.find_objects(labels), start=1):   # a handful of components
        if box is None:
            continue
        mask = labels[box] == c   # the component's bounding box: its pixels in the same (raster) order
        if mask.sum() < MIN_CORE:
            continue
        pts = points[box][mask].astype(np.float64)
        plane = _plane_of(pts[_dominant_plane(pts, off_mm / 2)])
        off = np.abs(pts @ plane[:3] + plane[3]) > off_mm
        off_image = np.zeros_like(mask)
        off_image[mask] = off
        pieces, k = ndimage.label(off_image)
        sizes = np.bincount(pieces[mask], minlength=k + 1)
        planes = [plane] + [_plane_of(pts[pieces[mask] == j]) for j in range(1, k + 1) if sizes[j] >= MIN_CORE]
        if len(planes) == 1:
            continue
        nearest = np.argmin(np.abs(pts @ np.array(planes)[:, :3].T + np.array(planes)[:, 3]), axis=1)
        out[box][mask] = np.where(nearest == 0, c, top + nearest)
        top += int(nearest.max())
    return out


def _grow_back(labels: np.ndarray, candidates: np.ndarray, points: np.ndarray, join_mm: float,
               steps: int) -> np.ndarray:
    """`labels` grown into the unlabelled `candidates` pixels, one ring per step: a pixel
    takes the label of a 4-neighbour whose patch plane it lies within `join_mm` of (the
    nearest plane when several do)."""
    n_lab = int(labels.max())
    if n_lab == 0:
        return labels
    h, w = labels.shape
    flat = labels.ravel().copy()
    pts = points.reshape(-1, 3)
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(n_lab + 2))
    planes = np.zeros((n_lab + 1, 4))
    for c in range(1, n_lab + 1):   # one robust fit per patch (a handful of patches)
        planes[c] = _plane_of(pts[order[bounds[c]:bounds[c + 1]]])
    free = np.flatnonzero(candidates.ravel() & (flat == 0))
    row, col = free // w, free % w
    hom = np.c_[pts[free], np.ones(len(free))]
    neighbours = [(free - w, row > 0), (free + w, row < h - 1), (free - 1, col > 0), (free + 1, col < w - 1)]
    for _ in range(steps):
        best = np.full(len(free), np.inf)
        take = np.zeros(len(free), np.int64)
        for nb, inside in neighbours:
            lab = np.where(inside, flat[np.where(inside, nb, 0)], 0)
            dist = np.abs(np.einsum("ij,ij->i", hom, planes[lab]))
            better = (lab > 0) & (flat[free] == 0) & (dist < join_mm) & (dist < best)
            best[better] = dist[better]
            take[better] = lab[better]
        if not take.any():
            break
        flat[free[take > 0]] = take[take > 0]
    return flat.reshape(h, w)
