"""The session cloud's PLY file (`scanner.pointcloud.write_ply`), read back with Open3D's
own reader (another implementation than the writer's `plyfile`): every valid pixel's point,
normal and grey level, and the pixel it came from, so the organised layout is rebuilt
exactly; the header claims nothing the file does not hold."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from scanner.pointcloud import OrganisedCloud, write_ply


def _cloud(height: int = 24, width: int = 31) -> OrganisedCloud:
    rng = np.random.default_rng(4)
    points = rng.normal(0.0, 20.0, (height, width, 3)).astype(np.float32)
    points[..., 2] += 400.0
    invalid = rng.random((height, width)) < 0.3
    invalid[0, 0] = invalid[-1, -1] = True
    points[invalid] = np.nan
    normals = rng.normal(size=(height, width, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    normals[~invalid & (rng.random((height, width)) < 0.1)] = np.nan   # a valid point without a normal
    return OrganisedCloud(points, rng.integers(0, 256, (height, width)).astype(np.uint8), normals)


def test_ply_holds_every_valid_point_with_its_pixel(tmp_path: Path) -> None:
    cloud = _cloud()
    path = tmp_path / "cloud.ply"
    n = write_ply(path, cloud)
    valid = ~np.isnan(cloud.points[..., 2])
    assert n == valid.sum() and not (tmp_path / "cloud.ply.part").exists()
    pc = o3d.t.io.read_point_cloud(str(path)).point
    row, col = pc.row.numpy()[:, 0], pc.col.numpy()[:, 0]
    assert len(row) == n and valid[row, col].all()
    assert len(set(zip(row.tolist(), col.tolist()))) == n   # each valid pixel once
    rebuilt = np.full(cloud.points.shape, np.nan, np.float32)
    rebuilt[row, col] = pc.positions.numpy()
    assert np.array_equal(rebuilt, cloud.points, equal_nan=True)
    assert np.array_equal(pc.normals.numpy(), np.nan_to_num(cloud.normals[row, col]))
    grey = pc.colors.numpy()
    assert np.array_equal(grey, np.repeat(cloud.colors[row, col][:, None], 3, axis=1))


def test_ply_header_is_honest(tmp_path: Path) -> None:
    cloud = _cloud(10, 16)
    path = tmp_path / "cloud.ply"
    n = write_ply(path, cloud)
    header = path.read_bytes().split(b"end_header\n")[0].decode("ascii")
    assert "format binary_little_endian 1.0" in header and f"element vertex {n}\n" in header
    assert "16 x 10" in header and "valid pixels only" in header
    assert "organised" not in header.lower() and "obj_info" not in header
    assert "property int row" in header and "property int col" in header


def test_ply_of_a_cloud_without_valid_points(tmp_path: Path) -> None:
    cloud = OrganisedCloud(np.full((4, 5, 3), np.nan, np.float32), np.zeros((4, 5), np.uint8),
                           np.full((4, 5, 3), np.nan, np.float32))
    path = tmp_path / "empty.ply"
    assert write_ply(path, cloud) == 0
    assert b"element vertex 0\n" in path.read_bytes()
