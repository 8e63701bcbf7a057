"""A view pair judged by what each sensor saw (inspection/views/sensor_view.py,
pair_evidence.py, pose_search.py, pair_registration.support_mask), against truth made here:
walls and plates seen by pinhole cameras whose rays are cut by hand, noise drawn with a
known sigma, poses built from rotations written out."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from inspection.measured_cloud import ScanCloud
from inspection.views.pair_evidence import K_SIGMA, P_AGREE, judge_in
from inspection.views.pair_registration import support_mask
from inspection.views.pose_search import normal_modes, rotations
from inspection.views.sensor_view import SensorView
from scanner.geometry import Pinhole
from scanner.stage_model import rotation_about

F, CX, CY = 500.0, 99.5, 49.5
CAMERA = Pinhole(200, 100, np.array([[F, 0, CX], [0, F, CY], [0, 0, 1]]))


def wall(z: float, columns: range, noise_mm: float, rng: np.random.Generator) -> ScanCloud:
    """A wall facing the camera at depth z (mm) over `columns` of CAMERA's image, each pixel's
    point on its ray, moved along it by Gaussian noise of `noise_mm`."""
    u, v = np.meshgrid(np.array(columns), np.arange(100))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    rays = np.column_stack([(pixels - [CX, CY]) / F, np.ones(len(pixels))])
    depth = z + rng.normal(0.0, noise_mm, len(rays))
    return ScanCloud(depth[:, None] * rays, np.tile([0.0, 0.0, -1.0], (len(rays), 1)), "wall", np.zeros(3), pixels,
                     (100, 200))


def on_rays(columns: np.ndarray, rows: np.ndarray, z: float) -> np.ndarray:
    uu, vv = np.meshgrid(columns, rows)
    return z * np.column_stack([(uu.ravel() - CX) / F, (vv.ravel() - CY) / F, np.ones(uu.size)])


def test_noise_is_estimated_from_the_views_own_points() -> None:
    """A wall with depth noise of 0.02 mm along the camera axis (its normal): the second
    differences give that sigma back."""
    rng = np.random.default_rng(1)
    view = SensorView.build(wall(400.0, range(200), 0.02, rng), CAMERA)
    assert view is not None and not view.virtual
    assert view.sigma_mm == pytest.approx(0.02, rel=0.06)
    assert view.smooth[1:-1, 1:-1].mean() > 0.99 and not view.smooth[0].any()  # the border has no 8 neighbours


def test_points_in_front_are_contradictions_behind_hidden_and_unseen_edges_no_evidence() -> None:
    """A wall 400 mm away over the left half of the image; the right half saw nothing.
    Points in front of its inside contradict it, points behind are hidden from it, points
    in front of its last column (a silhouette's near side may lie there) and points where it
    saw nothing are no evidence; points on it agree."""
    rng = np.random.default_rng(2)
    view = SensorView.build(wall(400.0, range(100), 0.01, rng), CAMERA)
    assert view is not None
    toward = np.tile([0.0, 0.0, -1.0], (80 * 80, 1))
    inside, rows = np.arange(10, 90), np.arange(10, 90)
    front = judge_in(on_rays(inside, rows, 380.0), toward, 0.01, view)
    assert front.front.mean() > 0.99 and not front.agree.any()  # a smooth pixel is refused at 1e-3 by chance
    behind = judge_in(on_rays(inside, rows, 420.0), toward, 0.01, view)
    assert behind.hidden.mean() > 0.99 and not behind.front.any()
    on = judge_in(on_rays(inside, rows, 400.0), toward, 0.01, view)
    assert on.agree.mean() > 0.99
    edge = judge_in(on_rays(np.array([99]), rows, 380.0), toward[:80], 0.01, view)
    assert not edge.comparable.any()
    unseen = judge_in(on_rays(np.arange(110, 190), rows, 380.0), toward, 0.01, view)
    assert not unseen.comparable.any() and not unseen.out.any()


def test_a_cloud_file_is_judged_on_a_virtual_camera_at_its_viewpoint() -> None:
    """The same wall as a cloud file (no camera: points in front of the origin): its
    virtual camera puts about one point on a pixel and judges as the real one does."""
    rng = np.random.default_rng(3)
    seen = wall(400.0, range(100), 0.01, rng)
    view = SensorView.build(ScanCloud(seen.points, seen.normals, "wall.ply", np.zeros(3)))
    assert view is not None and view.virtual
    assert 0.9 < (view.index >= 0).sum() / len(seen.points) <= 1.0
    toward = np.tile([0.0, 0.0, -1.0], (80 * 80, 1))
    assert judge_in(on_rays(np.arange(10, 90), np.arange(10, 90), 380.0), toward, 0.01, view).front.mean() > 0.95
    assert judge_in(on_rays(np.arange(10, 90), np.arange(10, 90), 420.0), toward, 0.01, view).hidden.mean() > 0.95
    assert SensorView.build(ScanCloud(seen.points - [0, 0, 500.0], seen.normals, "far.ply", None)) is None


def test_agreement_at_the_true_pose_follows_the_noise_model() -> None:
    """Two noisy measurements of one wall (sigma 0.02 mm each): the share of the second's
    points within K pair sigmas of the first is 2 Phi(K) - 1 (here about 0.9973), and their
    score's variance is what the class flips predict."""
    rng = np.random.default_rng(4)
    first = SensorView.build(wall(400.0, range(200), 0.02, rng), CAMERA)
    second = wall(400.0, range(200), 0.02, rng)
    assert first is not None
    judged = judge_in(second.points, second.normals, first.sigma_mm, first)
    share = judged.agree[judged.comparable].mean()
    n = judged.comparable.sum()
    assert pytest.approx(float(ndtr(K_SIGMA) - ndtr(-K_SIGMA))) == P_AGREE
    assert abs(share - P_AGREE) < 4.0 * np.sqrt(P_AGREE * (1 - P_AGREE) / n) + 0.002  # sigma estimated: +-6 %
    assert not judged.front.any() or judged.front.mean() < 0.005


def test_face_directions_give_back_a_turn_between_two_views() -> None:
    """A box corner's three faces seen in one view and, turned by a known rotation, in the
    other: the rotations from pairs of face directions include the true one."""
    rng = np.random.default_rng(5)
    normals = np.repeat(np.eye(3), 400, axis=0) + rng.normal(0.0, 0.01, (1200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    R = rotation_about(np.array([1.0, 2.0, 2.0]) / 3.0, 0.9)
    found = rotations(normal_modes(normals), normal_modes(normals @ R.T))
    errors = [np.degrees(np.arccos(np.clip((np.trace(R.T @ Q) - 1) / 2, -1, 1))) for Q, _ in found]
    assert min(errors) < 1.0


def test_support_is_the_plane_the_part_stands_on_in_any_frame() -> None:
    """A 40 x 30 x 10 mm block on a 200 mm table seen from 400 mm, and the same cloud moved
    rigidly (its viewpoint with it): the table goes either way; a block bigger than the
    table in view (its top the dominant plane) keeps everything."""
    rng = np.random.default_rng(6)

    def scene(block: float, table: float) -> ScanCloud:
        t = rng.uniform(-table / 2, table / 2, (40000, 2))
        t = t[(np.abs(t[:, 0]) > block / 2) | (np.abs(t[:, 1]) > 0.75 * block / 2)]
        top = rng.uniform(-0.5, 0.5, (20000, 2)) * [block, 0.75 * block]
        pts = np.vstack([np.column_stack([t, np.zeros(len(t))]), np.column_stack([top, np.full(len(top), 10.0)])])
        pts += rng.normal(0.0, 0.01, pts.shape)
        nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
        return ScanCloud(pts, nrm, "scene", np.array([0.0, -150.0, 400.0]))

    small = scene(40.0, 200.0)
    keep = support_mask(small)
    assert keep[len(keep) - 20000:].mean() > 0.99 and keep[:len(keep) - 20000].mean() < 0.01
    R, t = rotation_about(np.array([0.6, 0.0, 0.8]), 2.0), np.array([30.0, -70.0, 500.0])
    moved = ScanCloud(small.points @ R.T + t, small.normals @ R.T, "moved", R @ small.viewpoint + t)
    assert np.mean(support_mask(moved) == keep) > 0.999
    big = scene(190.0, 200.0)
    assert support_mask(big).all()


def valley(planes: list[tuple[np.ndarray, float]], noise_mm: float, rng: np.random.Generator) -> ScanCloud:
    """What CAMERA measures of the surface max(z) over `planes` (unit normal n toward the
    camera, offset d: n . x = d), its rays cut by hand, depth noise `noise_mm` along them."""
    u, v = np.meshgrid(np.arange(200), np.arange(100))
    pixels = np.column_stack([u.ravel(), v.ravel()])
    rays = np.column_stack([(pixels - [CX, CY]) / F, np.ones(len(pixels))])
    z = np.stack([d / (rays @ n) for n, d in planes], axis=1)  # each plane's depth on each ray
    k = np.argmax(z, axis=1)
    depth = z[np.arange(len(z)), k] + rng.normal(0.0, noise_mm, len(z))
    normals = np.stack([n for n, _ in planes])[k]
    return ScanCloud(depth[:, None] * rays, normals, "valley", np.zeros(3), pixels, (100, 200))


def test_projective_refinement_recovers_a_known_motion() -> None:
    """Three planes meeting in a valley, seen by CAMERA, and seen again after the camera
    moved by a known motion G (the planes re-expressed in its frame, the rays cut again):
    refined from a start 0.5 deg / 0.3 mm off, the pose is G within the noise."""
    from inspection.views.align import pose_error
    from inspection.views.projective import refine_projective

    rng = np.random.default_rng(7)
    planes = [(np.array([0.3, 0.0, -1.0]), -400.0), (np.array([-0.3, 0.2, -1.0]), -410.0),
              (np.array([0.0, -0.35, -1.0]), -395.0)]
    planes = [(n / np.linalg.norm(n), d / np.linalg.norm(n)) for n, d in planes]
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = rotation_about(np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2]), 0.04), \
        [2.0, -1.5, 3.0]
    moved = [(G[:3, :3] @ n, d + (G[:3, :3] @ n) @ G[:3, 3]) for n, d in planes]  # the planes in the moved frame
    a, b = valley(planes, 0.01, rng), valley(moved, 0.01, rng)
    va, vb = SensorView.build(a, CAMERA), SensorView.build(b, CAMERA)
    assert va is not None and vb is not None
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = rotation_about(np.array([0.0, 0.0, 1.0]), np.radians(0.5)), [0.3, 0.0, 0.0]
    T = refine_projective(start @ G, (a.points[::3], a.normals[::3], va), (b.points[::3], b.normals[::3], vb), 1.0)
    deg, mm = pose_error(G, T, a.points.mean(axis=0))
    assert deg < 0.01 and mm < 0.01
