"""Triangulation and the Eq. 17 phase-to-height mode against analytic geometry."""

from __future__ import annotations

import numpy as np
import pytest
from fringe_frames import fringe_stack

from scanner.decode import decode
from scanner.errors import DecodeError
from scanner.geometry import PhaseToHeight, Pinhole, RigModel
from scanner.patterns import PatternSet
from scanner.pointcloud import read_ply_points, write_ply
from scanner.reconstruct import Triangulator, phase_to_height_cloud, triangulate

HET = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0))


def plane_view(rig: RigModel, normal: np.ndarray, dist: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) of the plane n·X = dist seen by the rig camera, and the projector (u, v)
    of each point (distortion included)."""
    rays = rig.camera.ray_grid.astype(np.float64)
    n = normal / np.linalg.norm(normal)
    z = dist / (rays @ n)
    pts = rays * z[..., None]
    p = (pts.reshape(-1, 3) - rig.cam_from_proj[:3, 3]) @ rig.cam_from_proj[:3, :3]
    return z, rig.projector.project(p).reshape(*z.shape, 2)


@pytest.mark.parametrize("orientation", ["vertical", "horizontal"])
def test_triangulation_is_exact_with_distortion(bench_model: RigModel, orientation: str) -> None:
    rig = bench_model
    assert rig.projector.dist.any() and rig.camera.dist.any()
    z, uv = plane_view(rig, np.array([0.1, -0.2, 1.0]), 410.0)
    inside = (uv[..., 0] > 1) & (uv[..., 0] < 910) & (uv[..., 1] > 1) & (uv[..., 1] < 1138)
    axis = 0 if orientation == "vertical" else 1
    tri = Triangulator(rig)
    zt, dz = tri.depth_scale(uv[..., axis].astype(np.float32), orientation, sensitivity=True)
    err = np.abs(zt - z)[inside]
    # float32 arithmetic: within 0.1 um plus 2e-4 projector px times the depth sensitivity
    # (horizontal fringes on this horizontal baseline are ill-conditioned: dz/dc ~ 7 mm/px)
    assert np.all(err <= 1e-4 + 2e-4 * dz[inside])


def test_triangulated_cloud_and_normals(small_rig: RigModel) -> None:
    normal = np.array([0.0, 0.3, 1.0])
    z, uv = plane_view(small_rig, normal, 400.0)
    d = decode(fringe_stack(uv[..., 0], HET, 912), HET, 12, small_rig.projector.size)
    cloud = triangulate(d, Triangulator(small_rig))
    assert cloud.valid.mean() > 0.95
    assert np.nanmax(np.abs(cloud.points[..., 2] - z)) < 0.05
    n_expected = -normal / np.linalg.norm(normal)
    inner = cloud.normals[5:-5, 5:-5][cloud.valid[5:-5, 5:-5]]
    inner = inner[~np.isnan(inner[:, 0])]
    assert np.degrees(np.arccos(np.clip(inner @ n_expected, -1, 1))).max() < 0.5


def test_camera_size_mismatch_is_refused(small_rig: RigModel, bench_model: RigModel) -> None:
    _z, uv = plane_view(small_rig, np.array([0, 0, 1.0]), 400.0)
    d = decode(fringe_stack(uv[..., 0], HET, 912), HET, 12, small_rig.projector.size)
    with pytest.raises(DecodeError, match="rig camera is"):
        triangulate(d, Triangulator(bench_model))


def parallel_rig(d_mm: float) -> RigModel:
    """Camera and projector with parallel optical axes, centres at the same height: the
    geometry in which Eq. 17 is exact."""
    cam = Pinhole.from_fov(320, 256, 22.6)
    proj = Pinhole(912, 1140, np.array([[1975.0, 0, 800.0], [0, 3950.0, 569.5], [0, 0, 1]]))  # off-axis
    T = np.eye(4)
    T[0, 3] = d_mm
    return RigModel(cam, proj, T)


def test_phase_to_height_eq17_recovers_heights() -> None:
    l_mm, d_mm = 450.0, 80.0
    rig = parallel_rig(d_mm)
    period_px = 912 / HET.fringes[0]
    pitch_mm = period_px * l_mm / rig.projector.K[0, 0]  # λ0: fringe pitch on the reference plane

    def phase_of(height_map: np.ndarray) -> np.ndarray:
        z = l_mm - height_map
        rays = rig.camera.ray_grid.astype(np.float64)
        x = rays[..., 0] * z
        u = rig.projector.K[0, 0] * (x - d_mm) / z + rig.projector.K[0, 2]
        d = decode(fringe_stack(u, HET, 912, noise=2.0), HET, 12, rig.projector.size)
        return d, u

    ref, _ = phase_of(np.zeros((256, 320)))
    yy, xx = np.mgrid[0:256, 0:320]
    heights = 5.0 + 10.0 * np.exp(-((xx - 160) ** 2 + (yy - 128) ** 2) / (2 * 50.0 ** 2))
    obj, _ = phase_of(heights)
    plane = np.array([0.0, 0.0, -1.0, l_mm])  # n·X + c = 0 with n toward the camera
    model = PhaseToHeight(l_mm, d_mm, pitch_mm, ref.maps["vertical"].phase, plane)
    rig = RigModel(rig.camera, rig.projector, rig.cam_from_proj, phase_to_height=model)
    cloud = phase_to_height_cloud(obj, rig)
    ok = cloud.valid
    assert ok.mean() > 0.98
    err = cloud.points[..., 2][ok] - (l_mm - heights[ok])
    # the residual is the test stack's own (linearly interpolated, integer-DN fringes): ~4 um RMS
    assert np.sqrt(np.mean(err ** 2)) < 0.01 and abs(err.mean()) < 0.001 and np.abs(err).max() < 0.05
    # and it agrees with full triangulation on the same scan
    tri = triangulate(obj, Triangulator(rig))
    both = ok & tri.valid
    assert np.abs(tri.points[..., 2][both] - cloud.points[..., 2][both]).max() < 0.05


def test_phase_to_height_needs_calibration(small_rig: RigModel) -> None:
    _z, uv = plane_view(small_rig, np.array([0, 0, 1.0]), 400.0)
    d = decode(fringe_stack(uv[..., 0], HET, 912), HET, 12, small_rig.projector.size)
    with pytest.raises(DecodeError, match="phase-to-height"):
        phase_to_height_cloud(d, small_rig)


def test_ply_roundtrip(small_rig: RigModel, tmp_path) -> None:
    _z, uv = plane_view(small_rig, np.array([0, 0, 1.0]), 400.0)
    d = decode(fringe_stack(uv[..., 0], HET, 912), HET, 12, small_rig.projector.size)
    cloud = triangulate(d, Triangulator(small_rig))
    n = write_ply(tmp_path / "c.ply", cloud)
    pts = read_ply_points(tmp_path / "c.ply")
    assert n == len(cloud) == len(pts)
    assert np.allclose(pts, cloud.flat()[0], atol=1e-4)
    assert not list(tmp_path.glob("*.part"))
