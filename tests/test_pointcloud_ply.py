"""The session cloud's PLY file (`scanner.pointcloud.write_ply`), read back with Open3D's
own reader (another implementation than the writer's `plyfile`): every valid pixel's point,
normal and grey level, and the pixel it came from, so the organised layout is rebuilt
exactly; the header claims nothing the file does not hold. And the organised normals and
banded cloud the PLY carries, against their rule written out on whole images."""

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



def test_a_cloud_file_the_scanner_wrote_keeps_its_pixels(tmp_path: Path) -> None:
    """`slscan register CLOUD.ply` reads the same organised scan its session gives: each
    point on the pixel it came from (the valid pixels of the image, row-major, found here
    from the cloud itself) in the image the header names. The same points with two on one
    pixel (no image's) are read as a bare cloud."""
    from plyfile import PlyData, PlyElement

    from inspection.measured_cloud import read_cloud

    cloud = _cloud(40, 31)
    path = tmp_path / "cloud.ply"
    write_ply(path, cloud)
    scan = read_cloud(path)
    row, col = np.nonzero(~np.isnan(cloud.points[..., 2]))
    assert scan.image_shape == (40, 31)
    assert scan.pixels is not None and np.array_equal(scan.pixels, np.stack([col, row], axis=1))
    assert np.array_equal(scan.points, cloud.points[row, col].astype(np.float64))
    vertex = PlyData.read(str(path))["vertex"].data.copy()
    vertex["row"][1], vertex["col"][1] = vertex["row"][0], vertex["col"][0]
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(tmp_path / "twice.ply"))
    bare = read_cloud(tmp_path / "twice.ply")
    assert bare.pixels is None and bare.image_shape is None and len(bare) == len(scan)

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


def _normals_written_out(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The organised normals' rule on whole images, one float32 operation at a time: the cross
    product of the central differences along a row and down a column, unit length, facing
    the camera; NaN on the border."""
    p = np.stack([x, y, z], axis=-1)
    u = p[1:-1, 2:] - p[1:-1, :-2]
    v = p[2:, 1:-1] - p[:-2, 1:-1]
    n = np.stack([u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1], u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2],
                  u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]], axis=-1)
    length = np.sqrt(n[..., 0] * n[..., 0] + n[..., 1] * n[..., 1] + n[..., 2] * n[..., 2])
    scale = np.copysign(np.float32(1.0) / length, -n[..., 2])
    out = np.full(p.shape, np.nan, np.float32)
    out[1:-1, 1:-1] = n * scale[..., None]
    return out


def test_normals_and_cloud_match_the_rule_on_whole_images() -> None:
    """Normals computed a few rows at a time in reused buffers, and the cloud built in bands
    (normals across band edges from each band's neighbour rows), equal the rule written out
    on the whole image bit for bit, holes and borders included; a tilted plane's normals
    are its normal, facing the camera."""
    from scanner.pointcloud import NORMAL_BLOCK_ROWS, organised_normals
    from scanner.reconstruct import cloud_from_depth

    rng = np.random.default_rng(5)
    h, w = 3 * NORMAL_BLOCK_ROWS + 300 + 5, 173  # several blocks and in_bands' bands, ragged ends
    ray_x = np.broadcast_to(np.linspace(-0.4, 0.4, w, dtype=np.float32), (h, w)).copy()
    ray_y = np.broadcast_to(np.linspace(-0.3, 0.3, h, dtype=np.float32)[:, None], (h, w)).copy()
    normal = np.array([0.2, -0.1, 1.0])
    z = (500.0 / (normal[0] * ray_x + normal[1] * ray_y + normal[2])).astype(np.float32)
    bumpy = z + rng.normal(0.0, 0.5, z.shape).astype(np.float32)
    bumpy[rng.random(z.shape) < 0.03] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        for depth in (z, bumpy):
            x, y = ray_x * depth, ray_y * depth
            expected = _normals_written_out(x, y, depth)
            assert np.array_equal(organised_normals(x, y, depth), expected, equal_nan=True)
            cloud = cloud_from_depth(depth, ray_x, ray_y, np.zeros((h, w), np.uint8))
            assert np.array_equal(cloud.normals, expected, equal_nan=True)
            assert np.array_equal(cloud.points, np.stack([x, y, depth], axis=-1), equal_nan=True)
        flat = organised_normals(ray_x * z, ray_y * z, z)[1:-1, 1:-1].reshape(-1, 3)
    assert np.allclose(flat, -normal / np.linalg.norm(normal), atol=1e-3)
    assert np.isnan(organised_normals(ray_x[:2] * z[:2], ray_y[:2] * z[:2], z[:2])).all()
