"""Context-free segmentation (paper 002): downsampling, multi-scale features, region
growing, the α/β/η metrics, instances from masks and segments, and the CLI — each
against ground truth built into the synthetic data."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from inspection.bins.instances import (
    Instance,
    InstanceSegmenter,
    MaskPrediction,
    OnnxInstanceSegmenter,
    instances_from_label_image,
    instances_from_model,
    instances_from_segments,
    predictions_from_maskrcnn,
    read_label_image,
    read_labelme,
)
from inspection.downsample import density_voxel_size, downsample
from inspection.errors import CloudError, MaskError, SegmentationError
from inspection.regions.local_features import MultiScale
from inspection.regions.region_growing import DEFAULT_RADIUS_SPACINGS, default_radius, point_spacing, segment
from inspection.regions.segmetrics import NO_POINT, score
from scanner.pointcloud import OrganisedCloud
from slscan.cli import main


def _room(seed: int = 0, noise: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """A floor, a wall meeting it at 90°, a box standing on the floor (top and two sides
    seen) and a half pipe lying on the floor, uniformly sampled (~0.2 mm spacing); labels
    0..5 per surface."""
    rng = np.random.default_rng(seed)

    def u(lo: float, hi: float, n: int) -> np.ndarray:
        return rng.uniform(lo, hi, n)

    floor = np.c_[u(0, 40, 30000), u(0, 30, 30000), np.zeros(30000)]
    floor = floor[~((floor[:, 0] > 20) & (floor[:, 0] < 30) & (floor[:, 1] > 10) & (floor[:, 1] < 20))]
    wall = np.c_[np.zeros(12000), u(0, 30, 12000), u(0, 16, 12000)]
    top = np.c_[u(20, 30, 2500), u(10, 20, 2500), np.full(2500, 8.0)]
    side = np.c_[np.full(2000, 20.0), u(10, 20, 2000), u(0, 8, 2000)]
    side2 = np.c_[u(20, 30, 2000), np.full(2000, 10.0), u(0, 8, 2000)]
    th = u(0, np.pi, 8000)
    pipe = np.c_[10 + 4 * np.cos(th), u(4, 26, 8000), 4 + 4 * np.sin(th)]
    parts = [floor, wall, top, side, side2, pipe]
    labels = np.concatenate([np.full(len(p), i, np.int32) for i, p in enumerate(parts)])
    pts = np.concatenate(parts)
    return pts + noise * rng.standard_normal(pts.shape), labels


@pytest.fixture(scope="module")
def room() -> tuple[np.ndarray, np.ndarray]:
    return _room()


@pytest.fixture(scope="module")
def room_segmentation(room: tuple[np.ndarray, np.ndarray]) -> object:
    return segment(room[0], 2.0)


# ------------------------------------------------------------------- downsampling


def test_density_centre_keeps_one_input_point_per_voxel_nearest_its_centroid() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 10, (5000, 3))
    d = downsample(pts, 2.0, "density_centre")
    assert d.indices is not None and np.array_equal(d.points, pts[d.indices])
    cells = np.floor((pts - pts.min(axis=0)) / 2.0).astype(int)
    assert len(d) == len(np.unique(cells, axis=0))
    for k in range(len(d)):   # the kept point is the member nearest the cell's mean
        members = pts[d.inverse == k]
        centre = members.mean(axis=0)
        assert np.isclose(np.linalg.norm(d.points[k] - centre), np.linalg.norm(members - centre, axis=1).min())


def test_voxel_average_returns_centroids_and_inverse_map() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [5.2, 5.0, 5.0]])
    d = downsample(pts, 1.0, "average")
    assert len(d) == 2 and d.indices is None
    assert np.allclose(d.points[d.inverse[0]], [0.2, 0.1, 0.1])
    assert d.inverse[0] == d.inverse[1] != d.inverse[2]


def test_voxel_size_from_density_follows_eq13() -> None:
    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 1, (8000, 3)) * [40.0, 20.0, 10.0]
    ext = np.ptp(pts, axis=0) + 0.5
    expected = 2.0 * np.cbrt(3.0 * np.prod(ext) / len(pts))
    assert density_voxel_size(pts, alpha=2.0, scale=3.0, margin_mm=0.5) == pytest.approx(expected)
    assert downsample(pts, None, alpha=2.0, scale=3.0).voxel_mm == pytest.approx(
        density_voxel_size(pts, alpha=2.0, scale=3.0))


@pytest.mark.parametrize("pts, voxel", [(np.empty((0, 3)), 1.0), (np.array([[0, 0, np.nan]]), 1.0),
                                        (np.zeros((4, 3)), 0.0), (np.zeros((4, 2)), 1.0)])
def test_downsample_refuses_bad_input(pts: np.ndarray, voxel: float) -> None:
    with pytest.raises((CloudError, SegmentationError)):
        downsample(pts, voxel)


# ------------------------------------------------------------------------ features


def _features(points: np.ndarray, r: float) -> tuple[MultiScale, object]:
    sub = downsample(points, 0.1 * r, "density_centre")
    ms = MultiScale(points, sub.indices, sub.inverse, r, point_spacing(points))
    return ms, ms.features(np.arange(len(ms)))


def test_features_of_a_noisy_plane_cylinder_and_sphere_match_their_geometry() -> None:
    rng = np.random.default_rng(3)
    n, noise, r = 40000, 0.01, 3.0
    plane = np.c_[rng.uniform(0, 30, (n, 2)), noise * rng.standard_normal(n)]
    _, f = _features(plane, r)
    inner = np.flatnonzero(f.valid)
    assert f.valid.mean() > 0.99
    assert np.median(np.abs(f.normal[inner, 2])) > 0.999
    assert np.median(np.abs(f.k1[inner])) < 0.05            # flat: |k| well below 1/r
    assert 0.4 * noise < np.median(f.mu[inner]) < 1.2 * noise  # mean |residual| of N(0, noise) is 0.8 noise

    th, y = rng.uniform(0, np.pi, n), rng.uniform(0, 30, n)
    R = 8.0
    cyl = np.c_[R * np.cos(th), y, R * np.sin(th)] + noise * rng.standard_normal((n, 3))
    ms, f = _features(cyl, r)
    ok = f.valid
    assert ok.mean() > 0.95
    assert np.median(np.abs(f.k1[ok])) == pytest.approx(1 / R, rel=0.1)
    assert np.median(np.abs(f.k2[ok])) < 0.2 / R
    assert np.median(np.abs(f.k1_dir[ok, 1])) < 0.1          # max curvature across the axis (y)
    radial = (ms.points[ok] + ms.centre) * [1, 0, 1]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.median(np.abs(np.einsum("ij,ij->i", f.normal[ok], radial))) > 0.999

    u = rng.standard_normal((n, 3))
    sphere = 12.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    _, f = _features(sphere, r)
    ok = f.valid
    assert np.median(np.abs(f.k1[ok])) == pytest.approx(1 / 12.0, rel=0.15)
    assert np.median(np.abs(f.k2[ok])) == pytest.approx(1 / 12.0, rel=0.15)


# ------------------------------------------------------------------ region growing


def test_room_segments_match_ground_truth(room: tuple[np.ndarray, np.ndarray], room_segmentation: object) -> None:
    _, truth = room
    s = score(room_segmentation.labels, truth)
    assert s.mean_alpha <= 0.0005          # the paper: 0.03 % (one false point is 0.0037 % of this small cloud)
    assert s.mean_beta <= 0.08
    assert all(x.eta == 1 for x in s.segments)
    assert all(x.beta <= 0.15 for x in s.segments)   # small box faces lose a band along their edges
    # the subsample map: every point's label is its representative's
    seg = room_segmentation
    assert np.array_equal(seg.labels, seg.subsample_labels[seg.owner])


def test_rough_surface_points_far_off_their_neighbours_surfaces_still_join() -> None:
    """A rough floor (noise 2 % of r) with a box top above a hole in it: about 1 point in
    20 lies farther from its neighbours' fitted surfaces than their tolerance μ + 2σ. It
    must still join its surface (B' tests where it lies on its own fitted surface), not
    end as a segment of its own (0.8 % of both surfaces were lost so)."""
    rng = np.random.default_rng(4)
    floor = np.c_[rng.uniform(0, 50, (30000, 2)), np.zeros(30000)]
    hole = (np.abs(floor[:, 0] - 25) < 10) & (np.abs(floor[:, 1] - 25) < 10)
    floor = floor[~hole]
    top = np.c_[rng.uniform(15, 35, (hole.sum(), 2)), np.full(hole.sum(), 10.0)]
    pts = np.concatenate([floor, top])
    pts[:, 2] += 0.1 * rng.standard_normal(len(pts))
    truth = np.r_[np.zeros(len(floor), np.int32), np.ones(len(top), np.int32)]
    seg = segment(pts, 5.0)
    s = score(seg.labels, truth)
    assert all(x.eta == 1 and x.beta <= 0.003 and x.alpha == 0.0 for x in s.segments)
    labelled = seg.labels[seg.labels >= 0]
    assert (np.bincount(labelled)[labelled] < 10).mean() <= 0.001   # stranded points in crumbs: 0.76 % before


def test_segmentation_keeps_missing_points_unlabelled(room: tuple[np.ndarray, np.ndarray]) -> None:
    pts = room[0][::2].copy()
    pts[::50] = np.nan          # an organised scan's invalid pixels, flattened
    seg = segment(pts, 3.0)
    assert (seg.labels[::50] == -1).all()
    assert (seg.labels >= 0).mean() > 0.9


@pytest.mark.parametrize("r", [0.0, -1.0, np.nan, 0.05, 5000.0])
def test_radius_out_of_range_is_refused(room: tuple[np.ndarray, np.ndarray], r: float) -> None:
    with pytest.raises(SegmentationError, match="radius of interest"):
        segment(room[0][::10], r)


@pytest.mark.parametrize("spacing", [0.2, 0.7, 1.5])
def test_default_radius_is_a_fixed_number_of_point_spacings(spacing: float) -> None:
    """A square grid of pitch `spacing` (its nearest-neighbour distance, exactly) with NaN
    rows: the default radius is DEFAULT_RADIUS_SPACINGS pitches, to 0.1 mm."""
    u, v = np.meshgrid(np.arange(300) * spacing, np.arange(200) * spacing)
    pts = np.c_[u.ravel(), v.ravel(), 0.3 * u.ravel()]   # a tilted plane: pitch 1.044 x spacing along u
    pts[::97] = np.nan
    assert default_radius(pts) == pytest.approx(DEFAULT_RADIUS_SPACINGS * spacing, abs=0.051)
    with pytest.raises(CloudError, match="fewer than two points"):
        default_radius(np.full((5, 3), np.nan))


@pytest.mark.slow   # five rooms of ~0.8 M points: minutes each; run with -m slow
@pytest.mark.acceptance
def test_default_radius_meets_the_beta_target_on_the_simulated_rooms() -> None:
    """Issue 14: `slscan segment`'s default radius on the simulated rooms (sim.clutter,
    seeds 0..4, nominal spacing 1 mm): mean beta <= 8 % (the fixed 12 mm gave 13 %)."""
    from sim.clutter import clutter_cloud

    for seed in range(5):
        cloud = clutter_cloud(seed, 1.0, None)
        s = score(segment(cloud.points, cloud.radius_mm).labels, cloud.labels)
        assert s.mean_beta <= 0.08, (seed, cloud.radius_mm, s.mean_beta)


def test_empty_cloud_is_refused() -> None:
    with pytest.raises(CloudError, match="no points"):
        segment(np.full((10, 3), np.nan), 1.0)
    with pytest.raises(CloudError):
        segment(np.empty((0, 3)), 1.0)


# ------------------------------------------------------------------------- metrics


def test_metrics_follow_the_paper_definitions() -> None:
    truth = np.array([0] * 100 + [1] * 100 + [-1] * 20)
    test = np.array([5] * 60 + [6] * 36 + [7] * 4 + [6] * 10 + [8] * 90 + [-1] * 20)
    s = score(test, truth)
    g0, g1 = s.segments
    # G0: T5 (60) and T6 (36 of G0) qualify, T7 (4 < 5 %) does not; T6 also holds 10 of G1
    assert g0.members == (5, 6) and g0.eta == 2
    assert g0.beta == pytest.approx(4 / 100)
    assert g0.alpha == pytest.approx(10 / (220 - 100))
    # G1: T6 (10) and T8 (90) qualify; T6 brings 36 points of G0
    assert g1.members == (6, 8) and g1.beta == 0.0 and g1.alpha == pytest.approx(36 / 120)
    assert s.mean_eta == 2.0


def test_metrics_skip_pixels_without_points_and_check_shapes() -> None:
    truth = np.array([[0, 0, 1], [1, -1, 0]])
    test = np.array([[3, 3, 4], [4, NO_POINT, 3]])
    s = score(test, truth)
    assert [x.points for x in s.segments] == [3, 2]
    with pytest.raises(SegmentationError, match="shape"):
        score(test.ravel(), truth)
    with pytest.raises(SegmentationError, match="no segment"):
        score(test, np.full_like(truth, -1))


# ----------------------------------------------------------------------- instances


def _cloud(h: int = 20, w: int = 30) -> OrganisedCloud:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    pts = np.stack([xx, yy, np.full_like(xx, 100.0)], axis=-1)
    pts[0, 0] = np.nan
    normals = np.zeros_like(pts)
    normals[..., 2] = -1
    return OrganisedCloud(pts, np.zeros((h, w), np.uint8), normals)


def test_instances_from_label_images_lift_mask_pixels_to_their_points(tmp_path: Path) -> None:
    cloud = _cloud()
    lab = np.zeros((20, 30), np.int32)
    lab[0:3, 0:4] = 3      # holds the invalid pixel (0, 0)
    lab[10:15, 10:20] = 7
    inst = instances_from_label_image(lab, cloud)
    assert [(i.id, len(i)) for i in inst] == [(3, 11), (7, 50)]
    i7 = inst[1]
    assert i7.source == "label_image" and i7.mask is not None and i7.mask.sum() == 50
    assert np.array_equal(i7.points[:, :2], np.argwhere(lab == 7)[:, ::-1])   # x = col, y = row
    assert np.array_equal(i7.indices, np.flatnonzero(lab.ravel() == 7))
    colour = np.zeros((20, 30, 3), np.uint8)
    colour[lab == 3] = (0, 0, 255)
    colour[lab == 7] = (0, 255, 0)
    cv2.imwrite(str(tmp_path / "c.png"), colour)
    ids = read_label_image(tmp_path / "c.png")
    assert sorted(np.unique(ids, return_counts=True)[1]) == [12, 50, 538]
    with pytest.raises(MaskError, match="31x20, the camera image is 30x20"):
        instances_from_label_image(np.zeros((20, 31), np.int32), cloud)


def test_labelme_polygons_rectangles_circles_and_groups(tmp_path: Path) -> None:
    shapes = [{"label": "fs1", "points": [[2, 2], [8, 2], [8, 6], [2, 6]], "shape_type": "polygon"},
              {"label": "bs1", "points": [[20, 10], [24, 14]], "shape_type": "rectangle", "group_id": 4},
              {"label": "bs1", "points": [[26, 10], [28, 12]], "shape_type": "rectangle", "group_id": 4},
              {"label": "fs2", "points": [[6, 4], [6, 6]], "shape_type": "circle"},   # drawn over fs1
              {"label": "note", "points": [[1, 1]], "shape_type": "point"}]
    path = tmp_path / "a.json"
    path.write_text(json.dumps({"imageWidth": 30, "imageHeight": 20, "shapes": shapes}))
    ids, names = read_labelme(path, (30, 20))
    assert names == {1: "fs1", 2: "bs1", 3: "fs2"}
    assert (ids == 2).sum() == 25 + 9                      # both rectangles of group 4, corners inclusive
    assert ids[4, 6] == 3 and ids[2, 2] == 1                # the later circle covers the polygon
    inst = instances_from_label_image(ids, _cloud(), source="labelme", names=names)
    assert [i.label for i in inst] == ["fs1", "bs1", "fs2"]
    with pytest.raises(MaskError, match="30x20 image, the camera image is 40x20"):
        read_labelme(path, (40, 20))


class _Oracle:
    """A stand-in for a learned model: returns given masks."""

    name = "oracle"

    def __init__(self, preds: list[MaskPrediction]) -> None:
        self.preds = preds

    def predict(self, image: np.ndarray) -> list[MaskPrediction]:
        return self.preds


def test_model_masks_overlap_resolved_by_score_and_checked_for_size() -> None:
    a = np.zeros((20, 30), bool)
    a[5:10, 5:10] = True
    b = np.zeros((20, 30), bool)
    b[8:12, 8:12] = True
    model = _Oracle([MaskPrediction(a, "fs", 0.6), MaskPrediction(b, "bs", 0.9)])
    assert isinstance(model, InstanceSegmenter)
    inst = instances_from_model(model, np.zeros((20, 30), np.uint8), _cloud())
    assert [(i.label, len(i)) for i in inst] == [("fs", 25 - 4), ("bs", 16)]
    with pytest.raises(MaskError, match="camera image"):
        instances_from_model(_Oracle([MaskPrediction(a[:, :10], "fs", 1.0)]), np.zeros((20, 30)), _cloud())
    preds = predictions_from_maskrcnn(np.array([1, 2]), np.array([0.9, 0.3]), np.ones((2, 1, 20, 30)) * 0.7,
                                      (20, 30), {1: "fs"})
    assert [(p.label, p.score) for p in preds] == [("fs", 0.9)]
    with pytest.raises(MaskError, match="expected"):
        predictions_from_maskrcnn(np.array([1]), np.array([0.9]), np.ones((1, 1, 10, 30)), (20, 30), {})


def test_onnx_model_without_onnxruntime_names_the_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # as if not installed, whether it is or not
    with pytest.raises(MaskError, match="pip install onnxruntime"):
        OnnxInstanceSegmenter(tmp_path / "model.onnx")


def test_instances_from_segments_sorted_by_size_with_masks(room_segmentation: object) -> None:
    lab = np.array([[0, 0, 1], [1, 1, -1]])
    pts = np.arange(18, dtype=float).reshape(2, 3, 3)
    inst = instances_from_segments(lab, pts, min_points=2, exclude=())
    assert [(i.id, len(i)) for i in inst] == [(1, 3), (0, 2)]
    assert inst[0].mask is not None and inst[0].mask.sum() == 3 and isinstance(inst[0], Instance)
    assert instances_from_segments(lab, pts, exclude=(1,))[0].id == 0
    with pytest.raises(MaskError):
        instances_from_segments(lab, pts[:1])


# ----------------------------------------------------------------------------- CLI


def test_cli_segment_and_segscore(tmp_path: Path, room: tuple[np.ndarray, np.ndarray],
                                  capsys: pytest.CaptureFixture[str]) -> None:
    import open3d as o3d

    pts, truth = room
    sel = slice(None, None, 2)
    ply = tmp_path / "room.ply"
    o3d.io.write_point_cloud(str(ply), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts[sel])))
    np.save(tmp_path / "truth.npy", truth[sel])
    assert main(["segment", str(ply), "--radius", "3"]) == 0
    labels = np.load(tmp_path / "room.segments.npy")
    assert labels.shape == (len(truth[sel]),)
    from scanner.recording_reader import read_points

    logged = read_points(tmp_path / "room.segments.rrd", "world/segments")
    assert len(logged[0]) == len(labels)
    capsys.readouterr()
    assert main(["segscore", str(tmp_path / "room.segments.npy"), str(tmp_path / "truth.npy"), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    # a small cloud: one false point is 0.007 % here; accuracy itself is checked at full density above
    assert report["mean_alpha"] <= 0.001 and report["mean_beta"] <= 0.1 and report["mean_eta"] == 1.0
    assert main(["segment", str(ply), "--radius", "0.01"]) == 2
    assert "radius of interest" in capsys.readouterr().err
    assert main(["segscore", str(tmp_path / "room.segments.npy"), str(tmp_path / "missing.npy")]) == 2


# ---------------------------------------------------- acceptance on simulated clutter


@pytest.fixture(scope="module")
def clutter_scores() -> list[object]:
    """Seeds 0-2 of the simulated cluttered room (~0.78 M points each, planes, pipes of
    four diameters, boxes touching, roughness 0.05-0.4 mm, five scanner positions),
    segmented with r = 20 mm (as `slscan bench segment --seeds 0 1 2 --radius 20`)."""
    from sim.clutter import clutter_cloud

    out = []
    for seed in (0, 1, 2):
        c = clutter_cloud(seed, 1.0, 20.0)
        out.append(score(segment(c.points, 20.0).labels, c.labels))
    return out


@pytest.mark.acceptance
def test_clutter_false_positives_and_over_segmentation(clutter_scores: list[object]) -> None:
    assert np.mean([s.mean_alpha for s in clutter_scores]) <= 0.0003   # <= 0.03 %
    assert np.mean([s.mean_eta for s in clutter_scores]) <= 2.0


@pytest.mark.acceptance
def test_clutter_false_negatives(clutter_scores: list[object]) -> None:
    # 7.3 % (the paper 12 %); most of it from two box faces seen only at grazing angles
    # from far away (~4 mm spacing, r = 20 mm), which keep too few points for circle fits
    assert np.mean([s.mean_beta for s in clutter_scores]) <= 0.08
