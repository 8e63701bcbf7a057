"""`slscan export` (issue 14, "Exports"): every format read back by an independent reader
(plyfile, numpy.loadtxt, pye57, Open3D for STL) and checked against the session's own cloud
and camera; `--aligned` against the simulator's true part pose; `--deviations` against the
distance to the part's mesh measured by Open3D; the grid mesh against a closed form.

One 640 x 512 scan of the demo part, inspected once for the module (~20 s CPU)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_support import run
from plyfile import PlyData
from session_support import small_rig_toml

from scanner.config import CONFIG_DIR
from scanner.exports import ExportCloud, write
from scanner.session import Session
from sim.scene import load_scene

DEMO_SCENE = CONFIG_DIR / "scenes" / "demo.toml"
STEP = CONFIG_DIR / "parts" / "demo_part.step"
MESH = CONFIG_DIR / "parts" / "demo_part.ply"


TILT_RAD = 0.4  # the demo part tilted about the camera's x axis: its walls fix the pose (from straight above
# the turn about the boss is free, tests/test_registration_proof.py), so the inspection proves it


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The demo scene with the part tilted by `TILT_RAD`."""
    from scipy.spatial.transform import Rotation

    part = next(o for o in load_scene(DEMO_SCENE).objects if o.name == "demo_part")
    tilted = Rotation.from_rotvec([TILT_RAD, 0.0, 0.0]) * Rotation.from_matrix(part.pose[:3, :3])
    text = DEMO_SCENE.read_text().replace('"../parts/', f'"{CONFIG_DIR}/parts/')
    head, tail = text.split("pose = { rotation_rad = [", 1)
    rv = ", ".join(repr(float(x)) for x in tilted.as_rotvec())
    path = tmp_path_factory.mktemp("scene") / "tilted_demo.toml"
    path.write_text(head + f"pose = {{ rotation_rad = [{rv}" + tail[tail.index("]"):])
    return path


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory, scene: Path) -> Path:
    tmp = tmp_path_factory.mktemp("export")
    rig = small_rig_toml(tmp, width=640, height=512)
    root = tmp / "demo"
    assert run("scan", "--rig", str(rig), "--scene", str(scene), "--out", str(root))[0] == 0
    code, _, err = run("inspect", str(root), "--cad", str(STEP))
    assert code == 0, err  # proven (no tolerances: nothing to judge)
    return root


def session_cloud(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """The session's points (N, 3) mm and their pixels (N, 2) row, col from its camera model."""
    v = PlyData.read(str(root / "outputs" / "cloud.ply"))["vertex"].data
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    cam = Session.open(root).rig_model().camera
    col_row = np.rint(cam.project(pts)).astype(np.int64)
    return pts, col_row[:, ::-1]


def true_cad_from_camera(scene: Path) -> np.ndarray:
    """The simulator's truth: the inverse of the demo part's pose in `scene` (camera = world)."""
    part = next(o for o in load_scene(scene).objects if o.name == "demo_part")
    return np.linalg.inv(part.pose)


def test_ply_holds_every_point_with_its_pixel(session: Path, tmp_path: Path) -> None:
    pts, pixels = session_cloud(session)
    assert run("export", str(session), "--format", "ply", "--out", str(tmp_path / "c.ply"))[0] == 0
    ply = PlyData.read(str(tmp_path / "c.ply"))
    v = ply["vertex"].data
    assert len(v) == len(pts) > 100_000
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], axis=1), pts, atol=1e-4)
    assert np.array_equal(np.stack([v["row"], v["col"]], axis=1), pixels)
    assert any("mm, camera frame" in c for c in ply.comments) and any("640 x 512" in c for c in ply.comments)


def test_xyz_and_csv_read_back_with_numpy(session: Path, tmp_path: Path) -> None:
    pts, pixels = session_cloud(session)
    assert run("export", str(session), "--out", str(tmp_path / "c.xyz"))[0] == 0  # the format from the suffix
    xyz = np.loadtxt(tmp_path / "c.xyz")
    assert xyz.shape == pts.shape
    np.testing.assert_allclose(xyz, pts, atol=1e-4)
    code, out, _ = run("export", str(session), "--format", "csv", "--out", str(tmp_path / "c.csv"), "--json")
    assert code == 0 and json.loads(out)["file"] == str(tmp_path / "c.csv")
    header = (tmp_path / "c.csv").read_text().split("\n", 1)[0]
    assert header == "x_mm,y_mm,z_mm,row,col"
    table = np.loadtxt(tmp_path / "c.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(table[:, :3], pts, atol=1e-4)
    assert np.array_equal(table[:, 3:].astype(np.int64), pixels)


def test_e57_reads_back_with_pye57_in_metres(session: Path, tmp_path: Path) -> None:
    import pye57

    pts, pixels = session_cloud(session)
    assert run("export", str(session), "--format", "e57", "--out", str(tmp_path / "c.e57"))[0] == 0
    e57 = pye57.E57(str(tmp_path / "c.e57"))
    assert e57.scan_count == 1
    data = e57.read_scan_raw(0)
    got = np.stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]], axis=1) * 1000.0
    np.testing.assert_allclose(got, pts, atol=1e-3)  # single-precision metres: ~0.03 um at 0.5 m
    assert np.array_equal(np.stack([data["rowIndex"], data["columnIndex"]], axis=1), pixels)
    assert "metres" in e57.get_header(0).node["name"].value()


def test_stl_mesh_joins_neighbouring_pixels_facing_the_camera(session: Path, tmp_path: Path) -> None:
    import open3d as o3d

    pts, pixels = session_cloud(session)
    assert run("export", str(session), "--format", "stl", "--max-jump", "2", "--out", str(tmp_path / "m.stl"))[0] == 0
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "m.stl"))
    tri_v = np.asarray(mesh.vertices)[np.asarray(mesh.triangles)]  # (T, 3, 3)
    assert len(tri_v) > len(pts)  # about two per valid 2 x 2 cell
    lookup = {tuple(np.round(p, 3)): k for k, p in enumerate(pts.astype(np.float32).astype(np.float64))}
    sample = tri_v[:: max(1, len(tri_v) // 2000)]
    for tri in sample:  # the corners are the session's points, from three pixels of one 2 x 2 cell
        px = pixels[[lookup[tuple(np.round(p, 3))] for p in tri]]
        assert np.ptp(px[:, 0]) == 1 and np.ptp(px[:, 1]) == 1 and len({tuple(p) for p in px}) == 3
    normals = np.cross(sample[:, 1] - sample[:, 0], sample[:, 2] - sample[:, 0])
    assert (np.einsum("ij,ij->i", normals, sample.mean(axis=1)) < 0).all()  # facing the camera at the origin
    depth = np.linalg.norm(tri_v, axis=2)
    assert (np.ptp(depth, axis=1) <= 2.0 + 1e-3).all()


def test_grid_mesh_leaves_a_depth_step_open() -> None:
    """A 6 x 8 grid of a plane at 500 mm with a 10 mm step between columns 3 and 4: every
    cell is two triangles except the five cells straddling the step."""
    h, w = 6, 8
    rows, cols = np.mgrid[0:h, 0:w]
    pts = np.stack([cols * 1.0, rows * 1.0, 500.0 + 10.0 * (cols >= 4)], axis=-1).reshape(-1, 3)
    cloud = ExportCloud(pts, np.stack([rows.ravel(), cols.ravel()], axis=1), (h, w), np.zeros(h * w, np.uint8),
                        None, "camera frame", "test")
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        summary = write(cloud, Path(d) / "g.stl", "stl", max_jump_mm=3.0)
        data = (Path(d) / "g.stl").read_bytes()
    n = int(np.frombuffer(data[80:84], "<u4")[0])
    assert n == 2 * (h - 1) * (w - 1 - 1) and f"{n} triangles" in summary
    assert len(data) == 84 + 50 * n


def test_aligned_cloud_lies_where_the_simulator_put_the_part(session: Path, scene: Path, tmp_path: Path) -> None:
    """The export applies the inspection's registration exactly; that pose is checked against
    the simulator's (a pose the inspection proved; the bounds are the ones this test held
    when the part lay flat and its registration was 0.66 deg off, before poses needed proof)."""
    import cv2

    pts, _ = session_cloud(session)
    assert run("export", str(session), "--format", "ply", "--aligned", "--out", str(tmp_path / "a.ply"))[0] == 0
    ply = PlyData.read(str(tmp_path / "a.ply"))
    v = ply["vertex"].data
    got = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    assert len(got) == len(pts) and any("CAD frame of demo_part.step" in c for c in ply.comments)
    import json

    pose = np.array(json.loads((session / "outputs" / "inspection.json").read_text())["registration"]["transform"])
    np.testing.assert_allclose(got, pts @ pose[:3, :3].T + pose[:3, 3], atol=1e-4)  # float32 file
    truth = true_cad_from_camera(scene)
    off = pose @ np.linalg.inv(truth)  # identity for a perfect registration
    assert np.degrees(np.linalg.norm(cv2.Rodrigues(off[:3, :3])[0])) < 1.0 and np.linalg.norm(off[:3, 3]) < 0.5
    err = np.linalg.norm(got - (pts @ truth[:3, :3].T + truth[:3, 3]), axis=1)
    on_part = np.linalg.norm(got[:, :2], axis=1) < 55.0  # the part's footprint (90 x 60 mm) and a margin
    assert np.percentile(err[on_part], 95) < 1.0


def test_an_unproven_pose_gives_no_aligned_cloud(session: Path, tmp_path: Path) -> None:
    """An inspection whose pose its evidence leaves ambiguous (its JSON says so): `export
    --aligned` exits 1, one line naming why, and writes nothing."""
    import json
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(session, copy)
    path = copy / "outputs" / "inspection.json"
    report = json.loads(path.read_text())
    report.update(pose_status="ambiguous", status_note="not measured: the pose is ambiguous between the best pose "
                                                       "and 1 other pose(s)")
    path.write_text(json.dumps(report))
    code, _out, err = run("export", str(copy), "--aligned", "--out", str(tmp_path / "a.ply"))
    assert code == 1 and not (tmp_path / "a.ply").exists()
    assert len(err.strip().splitlines()) == 1 and "pose is not proven (ambiguous" in err


def test_deviations_match_the_distance_to_the_part(session: Path, tmp_path: Path) -> None:
    import open3d as o3d
    import pye57

    code, _, err = run("export", str(session), "--aligned", "--deviations", "--out", str(tmp_path / "d.ply"))
    assert code == 0 and "deviations for" in err
    v = PlyData.read(str(tmp_path / "d.ply"))["vertex"].data
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32)
    dev = np.asarray(v["deviation"], dtype=np.float64)
    assert 10_000 < len(v) < len(session_cloud(session)[0]) and np.isfinite(dev).all()
    mesh = o3d.t.geometry.TriangleMesh.from_legacy(o3d.io.read_triangle_mesh(str(MESH)))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    distance = scene.compute_distance(o3d.core.Tensor(pts)).numpy()
    away = np.abs(np.abs(dev) - distance)
    assert np.median(away) < 0.002 and np.percentile(away, 90) < 0.01  # mm; edges may pick another face
    assert np.median(np.abs(dev)) < 0.03  # a nominal part: deviations are the scanner's noise
    assert run("export", str(session), "--aligned", "--deviations", "--out", str(tmp_path / "d.e57"))[0] == 0
    data = pye57.E57(str(tmp_path / "d.e57")).read_scan_raw(0)
    np.testing.assert_allclose(data["intensity"], dev, atol=1e-5)


def test_refusals_are_one_line(session: Path, tmp_path: Path) -> None:
    code, _, err = run("export", str(session), "--format", "stl", "--deviations")
    assert code == 2 and "STL mesh holds no per-point values" in err
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("manifest.json", "frames.jsonl"):
        (bare / name).write_bytes((session / name).read_bytes())
    (bare / "frames").symlink_to(session / "frames")
    (bare / "outputs").mkdir()
    (bare / "outputs" / "cloud.ply").symlink_to(session / "outputs" / "cloud.ply")
    code, _, err = run("export", str(bare), "--format", "ply", "--aligned", "--out", str(tmp_path / "x.ply"))
    assert code == 2 and "has none (inspection.json missing): run `slscan inspect" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "x.ply").exists()
    code, _, err = run("export", str(session), "--out", str(tmp_path / "x.obj"))
    assert code == 2 and "give --format" in err
