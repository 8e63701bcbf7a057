"""Inspection and bin picking log their geometry in the rig's world frame, on a rig whose
world frame is not its camera frame: every point and mesh vertex read back from the `.rrd`
is the camera-frame geometry mapped by the rig's `world_from_cam`, computed here in numpy
from the known poses (the simulated view's true pose, a pose set by hand), never from the
code under test. Metrics go under the core's `metrics/` helper paths."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from registration_support import virtual_view
from scipy.spatial.transform import Rotation

from inspection.bins.instances import Instance
from inspection.bins.part_file import TabPart
from inspection.bins.part_model import ThinPartModel
from inspection.bins.picking import INSTANCES, MODELS, log_poses, poses_document
from inspection.bins.pose import PartPose
from inspection.cad import load_cad
from inspection.inspect_scan import inspect
from inspection.inspection_recording import CAD, DEVIATION, FACES
from scanner.config import CONFIG_DIR
from scanner.recording_reader import entity_paths, read_component, read_points
from scanner.rig import RigConfig
from scanner.session_recording import SessionRecording
from sim.parts import lying_pose

STEP = CONFIG_DIR / "parts" / "demo_part.step"


@pytest.fixture(scope="module")
def world_from_cam() -> np.ndarray:
    """A camera 35 degrees off the world's axes and 0.5 m from its origin."""
    W = np.eye(4)
    W[:3, :3] = Rotation.from_rotvec(np.radians(35.0) * np.array([0.6, -0.8, 0.0])).as_matrix()
    W[:3, 3] = [120.0, -340.0, 350.0]
    return W


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.einsum("ij,nj->ni", T[:3, :3], p) + T[:3, 3]


def _recording(path: Path, world_from_cam: np.ndarray) -> SessionRecording:
    rec = SessionRecording(path, path.stem, send_blueprint=False)
    rec.log_rig(replace(RigConfig.load().nominal_model(), world_from_cam=world_from_cam))
    return rec


def test_inspection_is_logged_in_the_rigs_world_frame(world_from_cam: np.ndarray, tmp_path: Path) -> None:
    model = load_cad(STEP)
    pose = lying_pose(model.tessellation.vertices, 0.35, 400.0, (0.3, 0.1))   # part -> camera, the truth
    view = virtual_view(model, pose)
    path = tmp_path / "inspection.rrd"
    heard: list[tuple[str, int, int]] = []
    with _recording(path, world_from_cam) as rec:
        report = inspect(view, model, recording=rec, progress=lambda *told: heard.append(told))
    # the long inspection is told as it goes: each stage, then each face seen, one by one
    assert [s for s, _, _ in heard[:3]] == ["isolate", "register", "segment"]
    seen = sum(r.form.points > 0 and r.form.status != "not seen" for r in report.faces)
    assert [d for s, d, _ in heard if s == "faces"] == list(range(seen + 1)) and heard[-1][2] == seen
    expected = _apply(world_from_cam, view.points[report.part_mask])
    for entity in (DEVIATION, FACES):
        assert np.allclose(read_points(path, entity)[0], expected, atol=1e-3)
    cad = read_component(path, CAD, "Mesh3D:vertex_positions")[0][1].reshape(-1, 3)
    truth = _apply(world_from_cam @ pose, model.tessellation.vertices)
    assert np.abs(cad - truth).max() < 0.05   # the registered pose is within 0.02 mm / 0.02 deg of the truth
    assert np.abs(cad - _apply(pose, model.tessellation.vertices)).max() > 100.0   # not the camera frame
    paths = entity_paths(path)
    assert {"metrics/inspection/fitness", "metrics/inspection/rmse_mm",
            "metrics/inspection/non_conforming_count"} <= set(paths)
    assert not [p for p in paths if p.startswith("metrics/inspection_")]


def test_bin_poses_are_logged_in_the_rigs_world_frame(world_from_cam: np.ndarray, tmp_path: Path) -> None:
    part = ThinPartModel.from_mesh(*TabPart().mesh(), "tab")
    pose = np.eye(4)   # part -> camera, set by hand
    pose[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 1.3]).as_matrix()
    pose[:3, 3] = [4.0, -7.0, 395.0]
    points = _apply(pose, part.vertices[:50])
    instance = Instance(3, np.arange(50), points, np.zeros_like(points), "segmentation")
    poses = [PartPose(3, True, "", "sacia+icp", 50, pose, "front", 0.99, 0.01, 0.0, 0.5, 0.01, edge_fit=1.0),
             PartPose(4, False, "no coarse pose", "sacia", 10)]
    doc = poses_document(poses, part, world_from_cam, "hand-made")
    path = tmp_path / "poses.rrd"
    with _recording(path, world_from_cam) as rec:
        log_poses(rec, doc, poses, [instance], part)
    assert np.allclose(read_points(path, INSTANCES)[0], _apply(world_from_cam, points), atol=1e-3)
    mesh = read_component(path, f"{MODELS}/part_3", "Mesh3D:vertex_positions")[0][1].reshape(-1, 3)
    assert np.allclose(mesh, _apply(world_from_cam @ pose, part.vertices), atol=1e-3)
    assert np.allclose(doc["parts"][0]["world"]["position_mm"], _apply(world_from_cam, pose[None, :3, 3])[0],
                       atol=1e-4)
    paths = entity_paths(path)
    assert {"metrics/pose/parts", "metrics/pose/posed", "metrics/pose/pickable"} <= set(paths)
    assert not [p for p in paths if p.startswith("metrics/pose_")]
