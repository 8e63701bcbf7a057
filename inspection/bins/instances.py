"""Part instances in a scan: from 2D instance masks aligned with the camera image (label
images, Labelme polygons, or a learned model behind `InstanceSegmenter`), or from the
3D segmentation; each lifted to the 3D points it covers.

Lifting (paper 001, Eq. 6-8): a mask pixel (c_x, c_y) with depth d maps to
P = (d·(c_x - u)/f_x, d·(c_y - v)/f_y, d) in the camera frame. The scanner's organised
cloud already holds that point for every pixel (triangulated, distortion included), so a
mask selects its points by pixel: instance points = cloud.points[mask & cloud.valid].
A mask must have exactly the camera image's size; pixels without a 3D point are left out.

Instances are what pose estimation consumes: `Instance` carries its id, the flat pixel
indices (row * width + col) or point rows it covers, the points (mm, camera frame) and
normals, its 2D mask when it has one, and where it came from.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from inspection.errors import MaskError
from inspection.measured_cloud import fit_plane
from scanner.pointcloud import OrganisedCloud

SOURCES = ("label_image", "labelme", "model", "segmentation")
MAX_COORDINATE_PX = 1 << 20  # Labelme vertices beyond this cannot be drawn (1/16 px fixed point in int32)


@dataclass(frozen=True, eq=False)
class Instance:
    """One part instance.

    `indices` (M,) int64: for an organised cloud, flat pixel indices row * width + col
    into the camera image; for an unordered cloud, rows of its point array. `points`
    (M, 3) float64 mm and `normals` (M, 3) (NaN where unknown) in the cloud's frame.
    `mask` (H, W) bool for instances from 2D masks or organised clouds, else None.
    `source` is one of `SOURCES`; `label` the annotation's class text (Labelme, e.g.
    "fs1" front side, "bs2" back side in paper 001's scheme) or the model's class, if any;
    `score` the model's confidence, if any."""

    id: int
    indices: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    source: str
    mask: np.ndarray | None = field(default=None, repr=False)
    label: str | None = None
    score: float | None = None

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"instance source {self.source!r} is not one of {SOURCES}")
        if not (len(self.indices) == len(self.points) == len(self.normals)):
            raise ValueError(f"instance {self.id}: {len(self.indices)} indices, {len(self.points)} points, "
                             f"{len(self.normals)} normals")

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def centroid(self) -> np.ndarray:
        return self.points.mean(axis=0)


@dataclass(frozen=True)
class MaskPrediction:
    """One instance a 2D model found: `mask` (H, W) bool, its class `label` and `score`."""

    mask: np.ndarray
    label: str
    score: float


@runtime_checkable
class InstanceSegmenter(Protocol):
    """A learned 2D instance segmentation model: given the camera image (H, W) or
    (H, W, 3) uint8/uint16, the instances it finds, masks of the image's size."""

    name: str

    def predict(self, image: np.ndarray) -> list[MaskPrediction]: ...


# ------------------------------------------------------------------------ from masks


def instances_from_label_image(labels: np.ndarray, cloud: OrganisedCloud, source: str = "label_image",
                               min_points: int = 1, names: dict[int, str] | None = None) -> list[Instance]:
    """One instance per non-zero id of an integer label image (H, W) aligned with the
    cloud; instances with fewer than `min_points` 3D points are dropped."""
    lab = _check_shape(np.asarray(labels), cloud, "label image")
    if not np.issubdtype(lab.dtype, np.integer):
        raise MaskError(f"label image must hold integer instance ids, got {lab.dtype}")
    h, w = lab.shape
    valid = cloud.valid.ravel()
    flat = lab.ravel()
    out = []
    for i in np.unique(flat[flat > 0]):
        mask = (flat == i)
        idx = np.flatnonzero(mask & valid)
        if len(idx) < min_points:
            continue
        out.append(_instance(int(i), idx, cloud, source, mask.reshape(h, w), (names or {}).get(int(i))))
    return out


def read_label_image(path: str | Path) -> np.ndarray:
    """An instance label PNG as an int32 (H, W) id image: single-channel 8/16-bit ids as
    they are (0 = background), or a colour image with one colour per instance (black =
    background), numbered in colour order from 1."""
    from scanner.file_checks import MAX_IMAGE_BYTES, FileRefused, decode_image, read_regular

    path = Path(path)
    try:
        img, said = decode_image(read_regular(path, limit=MAX_IMAGE_BYTES))
    except FileRefused as exc:
        raise MaskError(str(exc)) from None
    if img is None:
        raise MaskError(f"{path}: not a readable image" + (f" ({said})" if said else ""))
    if img.dtype not in (np.uint8, np.uint16):
        raise MaskError(f"{path}: a label image holds 8- or 16-bit integer ids, not {img.dtype}")
    if img.ndim == 2:
        return img.astype(np.int32)
    colours = img[..., :3].reshape(-1, 3)
    uniq, inv = np.unique(colours, axis=0, return_inverse=True)
    colour = (uniq != 0).any(axis=1)
    ids = (np.cumsum(colour) * colour).astype(np.int32)
    return ids[inv.ravel()].reshape(img.shape[:2])


def read_labelme(path: str | Path, image_size: tuple[int, int]) -> tuple[np.ndarray, dict[int, str]]:
    """Rasterise a Labelme JSON file into an instance id image (H, W) int32 and the id ->
    label text map. `image_size` is the camera's (width, height); the file's
    imageWidth/imageHeight must match it. Area shapes (polygon, rectangle, circle, mask)
    are drawn in file order, later shapes over earlier ones (as Labelme's own label
    export does); shapes sharing a group_id form one instance; point and line shapes
    carry no area and are skipped. Polygon vertices are pixel coordinates (pixel centres
    at integers, as in OpenCV)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise MaskError(f"{path}: not a readable Labelme JSON file: {exc}") from None
    if not isinstance(doc, dict):
        raise MaskError(f"{path}: not a Labelme file (a JSON {type(doc).__name__}, not an object with 'shapes')")
    w, h = image_size
    fw, fh = doc.get("imageWidth"), doc.get("imageHeight")
    if (fw, fh) != (w, h):
        raise MaskError(f"{path}: annotations are for a {fw}x{fh} image, the camera image is {w}x{h}; "
                        "annotate the scan's own camera image (uncropped, unscaled)")
    shapes = doc.get("shapes")
    if not isinstance(shapes, list):
        raise MaskError(f"{path}: no 'shapes' list")
    ids = np.zeros((h, w), dtype=np.int32)
    names: dict[int, str] = {}
    groups: dict[object, int] = {}
    for k, shape in enumerate(shapes):
        if not isinstance(shape, dict):
            raise MaskError(f"{path}: shapes[{k}] is a {type(shape).__name__}, not a shape object")
        kind = shape.get("shape_type") or "polygon"
        if kind in ("point", "line", "linestrip", "points"):
            continue
        group = shape.get("group_id")
        if not isinstance(group, (int, str, type(None))):
            raise MaskError(f"{path}: shapes[{k}].group_id must be a number, a string or null, got {group!r}")
        key = ("group", group) if group is not None else ("shape", k)
        if key not in groups:
            groups[key] = len(groups) + 1
        i = groups[key]
        names.setdefault(i, str(shape.get("label", "")))
        ids[_shape_mask(shape, kind, (h, w), f"{path}: shapes[{k}]")] = i
    return ids, names


def _shape_mask(shape: dict[str, object], kind: str, size: tuple[int, int], where: str) -> np.ndarray:
    h, w = size
    try:
        pts = np.asarray(shape.get("points"), dtype=np.float64).reshape(-1, 2)
    except (TypeError, ValueError):
        raise MaskError(f"{where}: 'points' must be a list of [x, y]") from None
    if not np.all(np.abs(pts) <= MAX_COORDINATE_PX):  # NaN fails too
        raise MaskError(f"{where}: point coordinates must be finite and within +-{MAX_COORDINATE_PX} px")
    canvas = np.zeros((h, w), dtype=np.uint8)
    shift = 4   # sub-pixel vertices: 1/16 px
    fixed = lambda p: np.round(p * (1 << shift)).astype(np.int32)  # noqa: E731
    if kind == "polygon":
        if len(pts) < 3:
            raise MaskError(f"{where}: a polygon needs at least 3 points, got {len(pts)}")
        cv2.fillPoly(canvas, [fixed(pts)], 1, lineType=cv2.LINE_8, shift=shift)
    elif kind == "rectangle":
        if len(pts) != 2:
            raise MaskError(f"{where}: a rectangle needs 2 points, got {len(pts)}")
        (x0, y0), (x1, y1) = pts.min(axis=0), pts.max(axis=0)
        cv2.fillPoly(canvas, [fixed(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))], 1, shift=shift)
    elif kind == "circle":
        if len(pts) != 2:
            raise MaskError(f"{where}: a circle needs its centre and a point on it, got {len(pts)} points")
        radius = float(np.linalg.norm(pts[1] - pts[0]))
        cv2.circle(canvas, tuple(int(v) for v in fixed(pts[0])), round(radius * (1 << shift)), 1, -1, shift=shift)
    elif kind == "mask":
        if len(pts) < 1 or not shape.get("mask"):
            raise MaskError(f"{where}: a mask shape needs its top-left point and base64 PNG 'mask'")
        data = np.frombuffer(base64.b64decode(str(shape["mask"])), dtype=np.uint8)
        sub = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)
        if sub is None:
            raise MaskError(f"{where}: the 'mask' is not a readable PNG")
        x0, y0 = (round(v) for v in pts[0])
        ys, xs = np.nonzero(sub)
        ys, xs = ys + y0, xs + x0
        keep = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
        canvas[ys[keep], xs[keep]] = 1
    else:
        raise MaskError(f"{where}: unsupported shape_type {kind!r} (polygon, rectangle, circle, mask)")
    return canvas.astype(bool)


def instances_from_model(model: InstanceSegmenter, image: np.ndarray, cloud: OrganisedCloud,
                         min_points: int = 1) -> list[Instance]:
    """Run a 2D model on the camera image and lift its masks; where masks overlap, each
    pixel goes to the most confident instance (a pixel sees one surface)."""
    preds = model.predict(image)
    owner = np.zeros(cloud.valid.shape, dtype=np.int32)
    best = np.full(cloud.valid.shape, -np.inf)
    for k, p in enumerate(preds):
        m = _check_shape(np.asarray(p.mask), cloud, f"{model.name} mask {k}").astype(bool)
        take = m & (p.score > best)
        owner[take] = k + 1
        best[take] = p.score
    out = []
    valid = cloud.valid.ravel()
    for k, p in enumerate(preds):
        mask = owner == k + 1
        idx = np.flatnonzero(mask.ravel() & valid)
        if len(idx) >= min_points:
            out.append(_instance(k + 1, idx, cloud, "model", mask, p.label, score=float(p.score)))
    return out


# ------------------------------------------------------------------ learned models


class OnnxInstanceSegmenter:
    """A Mask R-CNN-style instance segmentation model in an ONNX file, run with
    onnxruntime (not a dependency of slscan: install it to use this).

    Expected interface (torchvision's Mask R-CNN export): one input, the image as float32
    (3, H, W) in 0..1 (grey images are repeated to 3 channels); outputs boxes (N, 4),
    labels (N,) int, scores (N,), masks (N, 1, H, W) float in 0..1. `classes` names the
    label ids; instances below `min_score` are dropped, masks cut at `mask_threshold`."""

    def __init__(self, path: str | Path, classes: dict[int, str] | None = None, min_score: float = 0.5,
                 mask_threshold: float = 0.5) -> None:
        self.path = Path(path)
        self.name = self.path.name
        self.classes = classes or {}
        self.min_score = min_score
        self.mask_threshold = mask_threshold
        try:
            import onnxruntime  # type: ignore[import-not-found]  # optional, not installed: no stubs to find
        except ImportError:
            raise MaskError(f"{self.path}: running an ONNX instance segmentation model needs the 'onnxruntime' "
                            "package, which slscan does not install: pip install onnxruntime") from None
        if not self.path.is_file():
            raise MaskError(f"{self.path}: model file not found")
        self.session = onnxruntime.InferenceSession(str(self.path), providers=["CPUExecutionProvider"])

    def predict(self, image: np.ndarray) -> list[MaskPrediction]:
        img = np.asarray(image)
        scale = 255.0 if img.dtype == np.uint8 else float(np.iinfo(img.dtype).max) if img.dtype.kind == "u" else 1.0
        x = (img.astype(np.float32) / scale)
        x = np.repeat(x[None], 3, axis=0) if x.ndim == 2 else np.transpose(x[..., :3], (2, 0, 1))
        name = self.session.get_inputs()[0].name
        _, labels, scores, masks = self.session.run(None, {name: x})[:4]
        return predictions_from_maskrcnn(labels, scores, masks, img.shape[:2], self.classes, min_score=self.min_score,
                                         mask_threshold=self.mask_threshold)


def predictions_from_maskrcnn(labels: np.ndarray, scores: np.ndarray, masks: np.ndarray, image_shape: tuple[int, int],
                              classes: dict[int, str], *, min_score: float = 0.5,
                              mask_threshold: float = 0.5) -> list[MaskPrediction]:
    """`MaskPrediction`s from Mask R-CNN outputs: labels (N,), scores (N,), soft masks
    (N, 1, H, W) or (N, H, W) at the image's size."""
    m = np.asarray(masks)
    if m.ndim == 4:
        m = m[:, 0]
    if m.ndim != 3 or m.shape[1:] != tuple(image_shape):
        raise MaskError(f"model masks have shape {m.shape}, expected (N, {image_shape[0]}, {image_shape[1]}) "
                        "for the camera image")
    out = []
    for lab, sc, mk in zip(np.asarray(labels).ravel(), np.asarray(scores).ravel(), m):
        if sc >= min_score:
            out.append(MaskPrediction(mk >= mask_threshold, classes.get(int(lab), str(int(lab))), float(sc)))
    return out


# ----------------------------------------------------------------- from segmentation


def instances_from_segments(labels: np.ndarray, points: np.ndarray, normals: np.ndarray | None = None,
                            min_points: int = 1, exclude: tuple[int, ...] = (),
                            image_shape: tuple[int, int] | None = None) -> list[Instance]:
    """One instance per segment of a 3D segmentation: `labels` (N,) per point of `points`
    (N, 3) (-1: unsegmented), or an (H, W) label image over an organised cloud's points
    (H, W, 3). Segments in `exclude` (e.g. the tray) or smaller than `min_points` are
    left out. With an image, instances carry their masks and pixel indices."""
    lab = np.asarray(labels)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if lab.size != len(pts):
        raise MaskError(f"{lab.size} labels for {len(pts)} points")
    nrm = np.full_like(pts, np.nan) if normals is None else np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    shape = lab.shape if lab.ndim == 2 else image_shape
    flat = lab.ravel()
    ids, counts = np.unique(flat[flat >= 0], return_counts=True)
    order = np.argsort(-counts, kind="stable")
    out = []
    for i in ids[order]:
        if int(i) in exclude:
            continue
        idx = np.flatnonzero(flat == i)
        if len(idx) < min_points:
            continue
        mask = None
        if shape is not None and int(np.prod(shape)) == len(flat):
            mask = (flat == i).reshape(shape)
        out.append(Instance(int(i), idx, pts[idx], nrm[idx], "segmentation", mask))
    return out


# ------------------------------------------------------------------------- helpers


def _check_shape(mask: np.ndarray, cloud: OrganisedCloud, what: str) -> np.ndarray:
    h, w = cloud.valid.shape
    if mask.ndim != 2 or mask.shape != (h, w):
        got = f"{mask.shape[1]}x{mask.shape[0]}" if mask.ndim == 2 else f"shape {mask.shape}"
        raise MaskError(f"{what} is {got}, the camera image is {w}x{h}: masks must be aligned with the scan's "
                        "camera image (same size, uncropped, unscaled)")
    return mask


def _instance(i: int, idx: np.ndarray, cloud: OrganisedCloud, source: str, mask: np.ndarray, label: str | None,
              *, score: float | None = None) -> Instance:
    pts = cloud.points.reshape(-1, 3)[idx].astype(np.float64)
    nrm = cloud.normals.reshape(-1, 3)[idx].astype(np.float64)
    return Instance(i, idx.astype(np.int64), pts, nrm, source, mask, label, score)


# ------------------------------------------------------------------- from depth steps


def instances_from_depth_steps(cloud: OrganisedCloud, step_mm: float = 0.1, tray_tol_mm: float = 0.08,
                               min_points: int = 200, seed: int = 0) -> list[Instance]:
    """Parts lying on a tray, from an organised scan without masks: the tray (the dominant
    plane, RANSAC within `tray_tol_mm`) removed, the remaining pixels split into connected
    regions where 4-neighbours join only if their depths differ by less than `step_mm` (a
    part lying on another is at least its thickness above it, so the step at its edge
    separates them). Regions of fewer than `min_points` are dropped; ids 1.. by size."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    valid = cloud.valid
    if valid.sum() < 3:
        return []
    pts = cloud.points.reshape(-1, 3).astype(np.float64)
    idx = np.flatnonzero(valid.ravel())
    rng = np.random.default_rng(seed)
    sub = pts[rng.choice(idx, size=min(50000, len(idx)), replace=False)]
    plane, _ = fit_plane(sub, tray_tol_mm, seed)
    n = np.asarray(plane[:3])
    d = float(plane[3])
    if n @ np.zeros(3) + d < 0:   # signed distance positive toward the camera (origin)
        n, d = -n, -d
    above = np.zeros(valid.size, bool)
    above[idx] = (pts[idx] @ n + d) > tray_tol_mm
    h, w = valid.shape
    z = cloud.points[..., 2].reshape(-1)
    grid = np.arange(h * w).reshape(h, w)
    edges = []
    for a, b in ((grid[:, :-1], grid[:, 1:]), (grid[:-1, :], grid[1:, :])):
        a, b = a.ravel(), b.ravel()
        join = above[a] & above[b] & (np.abs(z[a] - z[b]) < step_mm)
        edges.append((a[join], b[join]))
    rows = np.concatenate([e[0] for e in edges])
    cols = np.concatenate([e[1] for e in edges])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(h * w, h * w))
    _, comp = connected_components(graph, directed=False)
    comp = np.where(above, comp, -1)
    ids, counts = np.unique(comp[comp >= 0], return_counts=True)
    big = ids[counts >= min_points][np.argsort(-counts[counts >= min_points], kind="stable")]
    out = []
    for k, c in enumerate(big, start=1):
        mask = comp == c
        out.append(_instance(k, np.flatnonzero(mask), cloud, "segmentation", mask.reshape(h, w), None))
    return out
