"""Multi-view scanning on the simulated turntable: the multi-view folder, durability view by
view, alignment against the simulator's truth (the stage's true pose of every view), the
fused cloud (closed form on synthetic views), the mesh (read back by trimesh and Open3D),
the recording, the stage-axis calibration and view-to-view registration (judged by what each
sensor saw: tests/test_pair_evidence.py). Quick versions on
a small camera run by default; the acceptance figures are in tests/test_multiview_acceptance.py."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from session_support import edit_manifest

from calibration.stage_axis import StageAxisError, solve_stage_axis
from inspection.views.align import pose_error
from inspection.views.merge import fuse
from inspection.views.view_clouds import ViewCloud
from scanner.config import CONFIG_DIR
from scanner.errors import IncompleteSession, ScannerError, SessionError
from scanner.multiview import MULTIVIEW, PLAN, MultiViewSession, plan_views, view_name
from scanner.rig import RigConfig
from scanner.session import MANIFEST, write_json
from scanner.stage import AxisKind
from scanner.stage_model import AxisGeometry, StageModel, rotation_about
from slscan import cli
from slscan.exit_codes import Exit

TURNTABLE = CONFIG_DIR / "rigs" / "sim_turntable.toml"
SCENE = CONFIG_DIR / "scenes" / "turntable_demo.toml"


def turntable_rig(tmp: Path, width: int = 320, height: int = 256) -> Path:
    text = TURNTABLE.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    text = text.replace("width = 1280", f"width = {width}").replace("height = 1024", f"height = {height}")
    text = text.replace("speed_deg_s = 90.0", "speed_deg_s = 720.0").replace("settle_s = 0.2", "settle_s = 0.0")
    path = tmp / f"turntable_{width}.toml"
    path.write_text(text)
    return path


def truth_pose(view: Path) -> np.ndarray:
    """part_from_view as the simulator placed the part (its true stage pose)."""
    return np.linalg.inv(np.array(json.loads((view / "ground_truth_stage.json").read_text())["world_from_stage"]))


@pytest.fixture(scope="module")
def four_views(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 640 x 512 turntable scan of the demo part, four views 45 degrees apart."""
    tmp = tmp_path_factory.mktemp("mv")
    out = tmp / "mv"
    assert cli.main(["scan", "--rig", str(turntable_rig(tmp, 640, 512)), "--scene", str(SCENE),
                     "--angles", "0,45,90,135", "--out", str(out)]) == 0
    return out


def test_multiview_folder_records_each_views_stage_pose(four_views: Path) -> None:
    session = MultiViewSession.open(four_views)
    assert (four_views / PLAN).is_file() and (four_views / MULTIVIEW).is_file() and session.complete
    assert [v.name for v in session.views] == [view_name(k) for k in range(4)]
    for view, deg in zip(session.views, (0, 45, 90, 135)):
        assert math.degrees(view.position["turntable"]) == pytest.approx(deg, abs=1e-6)
        # the recorded pose is the stage model's (here the simulator's own axis: equal to the truth)
        assert pose_error(np.linalg.inv(view.world_from_stage), truth_pose(view.session.root),
                          np.array([0.0, 0.0, 400.0])) < (1e-6, 1e-6)


def test_views_align_to_the_simulators_truth(four_views: Path) -> None:
    from inspection.views.align import align_views
    from inspection.views.view_clouds import load_views

    session = MultiViewSession.open(four_views)
    alignment = align_views(load_views(session))
    for k, view in enumerate(session.views):
        deg, mm = pose_error(truth_pose(view.session.root), alignment.poses[k], alignment.centre)
        assert deg < 0.05 and mm < 0.1, (view.name, deg, mm)


def test_merged_cloud_mesh_and_recording(four_views: Path) -> None:
    import open3d as o3d
    import trimesh

    from scanner.recording_reader import read_summary

    out = four_views / "outputs"
    figures = json.loads((out / "views.json").read_text())
    assert figures["views"] == 4 and figures["fused_points"] > 0.2 * figures["points"]
    stl = trimesh.load(out / "mesh.stl")
    ply = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    assert len(stl.faces) == len(ply.triangles) == figures["mesh"]["triangles"] > 1000
    assert stl.is_watertight == figures["mesh"]["watertight"]  # trimesh's own edge count agrees with ours
    entities = set(read_summary(four_views / "recording.rrd").entity_paths)
    assert {"world/merged", "world/mesh", "world/views/view_000", "world/priors/view_003", "views/report"} <= entities


def test_view_pair_registration_45_degrees_apart(four_views: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Proven, within the noise of the truth, and --json prints JSON alone on stdout (file
    descriptor 1: Open3D's C++ prints would land there)."""
    capfd.readouterr()
    assert cli.main(["register", str(four_views / "view_001"), str(four_views / "view_000"), "--json"]) == 0
    found = json.loads(capfd.readouterr().out)
    truth = np.linalg.inv(truth_pose(four_views / "view_000")) @ truth_pose(four_views / "view_001")
    deg, mm = pose_error(truth, np.array(found["transform"]), np.array([0.0, 0.0, 400.0]))
    assert deg < 0.05 and mm < 0.1 and not found["overlap_given"] and 0.3 < found["overlap"] < 1.0


@pytest.mark.parametrize(("fault", "stopped"), [
    (["--stage-fault", "alarm_at_move=2"], "move: StageAlarm"),
    (["--fault", "disconnect_after=30"], "capture: DeviceDisconnected")])  # the camera goes at view 2's 7th frame
def test_interrupted_run_keeps_every_finished_view(tmp_path: Path, capsys: pytest.CaptureFixture[str], fault: list[str],
                                                   stopped: str) -> None:
    out = tmp_path / "mv"
    code = cli.main(["scan", "--rig", str(turntable_rig(tmp_path)), "--scene", str(SCENE), "--views", "4", *fault,
                     "--out", str(out)])
    assert code == Exit.DEVICE  # a stage or camera fault: README "Exit codes"
    err = capsys.readouterr().err
    assert f"2 of 4 views complete (view_000, view_001); stopped at view 2 during {stopped}" in err
    with pytest.raises(IncompleteSession, match="2 of 4 views complete"):
        MultiViewSession.open(out)
    partial = MultiViewSession.open(out, partial=True)
    assert [v.name for v in partial.views] == ["view_000", "view_001"] and not partial.complete
    assert len(partial.views[1].session.load_stack()) == 12  # the finished views are whole


def one_view_folder(clean_session: Path, out: Path, stage: dict) -> Path:
    """A complete multi-view folder of one view (a copy of `clean_session`) whose manifest
    records `stage`; the view's manifest path."""
    shutil.copytree(clean_session, out / view_name(0))
    write_json(out / PLAN, {"slscan_multiview": 1, "multiview_id": "mv-test",
                            "views": [{"target": {"turntable": 0.5}}]})
    write_json(out / MULTIVIEW, {"slscan_multiview": 1, "multiview_id": "mv-test", "views": []})
    edit_manifest(out / view_name(0), lambda m: m.update(stage=stage, view=0, multiview_id="mv-test"))
    return out / view_name(0) / MANIFEST


TURNED = [[0.0, -1.0, 0.0, 10.0], [1.0, 0.0, 0.0, -20.0], [0.0, 0.0, 1.0, 30.0], [0.0, 0.0, 0.0, 1.0]]  # 90 deg about z
STAGE = {"position": {"turntable": 0.5}, "world_from_stage": TURNED,
         "stage_model": {"axes": [{"name": "turntable", "kind": "rotary", "direction": [0.0, 0.0, 1.0],
                                   "point_mm": [0.0, 0.0, 400.0]}], "calibration": ""}}


def test_a_views_stage_record_is_read_as_written(clean_session: Path, tmp_path: Path) -> None:
    one_view_folder(clean_session, tmp_path / "mv", STAGE)
    view = MultiViewSession.open(tmp_path / "mv").views[0]
    assert view.position == {"turntable": 0.5} and np.array_equal(view.world_from_stage, np.array(TURNED))


@pytest.mark.parametrize(("edit", "words"), [
    (lambda s: s.pop("position"), "key 'stage.position': required key is missing"),
    (lambda s: s["position"].update(turntable="half a turn"), "key 'stage.position.turntable': expected a number"),
    (lambda s: s.update(world_from_stage=[row[:3] for row in TURNED[:3]]),
     "key 'stage.world_from_stage[0]': expected a list of 4 values"),
    (lambda s: s.update(world_from_stage=[[2.0 * v for v in row[:3]] + row[3:] for row in TURNED[:3]] + TURNED[3:]),
     "key 'stage.world_from_stage': not a rigid motion"),
    (lambda s: s["stage_model"]["axes"][0].update(kind="spiral"), "key 'stage.stage_model': not a stage model"),
], ids=["no position", "position not a number", "pose 3x3", "pose scaled", "unknown axis kind"])
def test_a_malformed_stage_record_is_refused_naming_the_manifest(clean_session: Path, tmp_path: Path, edit,
                                                                 words: str) -> None:
    stage = json.loads(json.dumps(STAGE))
    edit(stage)
    manifest = one_view_folder(clean_session, tmp_path / "mv", stage)
    with pytest.raises(SessionError) as refused:
        MultiViewSession.open(tmp_path / "mv")
    message = str(refused.value)
    assert message.startswith(f"{manifest}, ") and words in message and "\n" not in message, message


def test_plan_views_and_its_refusals(tmp_path: Path) -> None:
    stage = RigConfig.load(turntable_rig(tmp_path)).stage
    assert [round(math.degrees(q["turntable"]), 6) for q in plan_views(stage, 8)] == [45.0 * k for k in range(8)]
    assert [round(math.degrees(q["turntable"]), 6) for q in plan_views(stage, angles_deg=[0, 30])] == [0.0, 30.0]
    with pytest.raises(ScannerError, match="either a number of views or a list of angles"):
        plan_views(stage, 4, [0.0])
    with pytest.raises(ScannerError, match="no rotary stage axis named 'tilt'"):
        plan_views(stage, 4, axis="tilt")


def test_fusion_is_the_inverse_variance_mean() -> None:
    # two views of the plane z = 0, one sample per 0.5 mm; view a at z = +0.01 (sigma 0.01),
    # view b at z = -0.02 (sigma 0.02): fused z = (0.01/0.01^2 - 0.02/0.02^2) / (1/0.01^2 + 1/0.02^2) = 0.004
    g = (np.stack(np.meshgrid(np.arange(20), np.arange(20)), -1).reshape(-1, 2) + 0.5) * 0.5
    n = np.tile([0.0, 0.0, 1.0], (len(g), 1))

    def view(k: int, z: float, sigma: float) -> ViewCloud:
        pts = np.column_stack([g, np.full(len(g), z)])
        return ViewCloud(k, f"v{k}", pts, n, np.full(len(g), sigma), np.array([0, 0, 100.0]), np.eye(4))

    merged = fuse([view(0, 0.01, 0.01), view(1, -0.02, 0.02)], [np.eye(4), np.eye(4)], 0.5)
    assert len(merged) == len(g) and np.all(merged.views == 2)
    assert np.allclose(merged.points[:, 2], 0.004)
    assert np.allclose(merged.sigma, 1.0 / math.sqrt(1 / 0.01 ** 2 + 1 / 0.02 ** 2))


def test_stage_axis_solved_from_exact_board_poses() -> None:
    d = np.array([0.1, -0.7, -0.7])
    d /= np.linalg.norm(d)
    p = np.array([3.0, 10.0, 410.0])
    B = np.eye(4)
    B[:3, 3] = [20.0, 5.0, 405.0]
    board = np.array([[x, y, 0.0] for x in range(0, 60, 10) for y in range(0, 40, 10)], float)
    angles = np.radians([-60, -20, 10, 50])
    poses = []
    for q in angles:
        M = np.eye(4)
        M[:3, :3] = rotation_about(d, q)
        M[:3, 3] = p - M[:3, :3] @ p
        poses.append(M @ B)
    solution = solve_stage_axis(poses, list(angles), [board] * 4)
    assert np.allclose(solution.direction, d, atol=1e-9)
    foot = solution.point_mm - p
    assert np.linalg.norm(foot - d * (d @ foot)) < 1e-6  # on the same line
    assert solution.residual_mm < 1e-6 and max(abs(a) for a in solution.angle_residuals_deg) < 1e-6
    with pytest.raises(StageAxisError, match="span 4.0 deg"):
        solve_stage_axis(poses[:3], [0.0, 0.03, 0.07], [board] * 3)


def test_stage_axis_calibration_on_the_simulated_turntable(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rig = turntable_rig(tmp_path, 640, 512)
    assert cli.main(["calibrate", "--stage-axis", "--rig", str(rig), "--out", str(tmp_path / "axis")]) == 0
    written = json.loads((tmp_path / "axis" / "stage_axis.json").read_text())
    axis = StageModel.from_dict(written, "stage_axis.json").axes[0]
    truth = RigConfig.load(rig).stage.nominal.axes[0]
    assert math.degrees(math.acos(min(1.0, axis.direction @ truth.direction))) < 0.05
    off = axis.point_mm - truth.point_mm
    assert np.linalg.norm(off - truth.direction * (truth.direction @ off)) < 0.1
    # the rig then takes it: its stage model is the calibrated one
    axis = tmp_path / "axis" / "stage_axis.json"
    text = rig.read_text().replace("settle_s = 0.0", f'settle_s = 0.0\ncalibration = "{axis}"')
    rig.write_text(text)
    assert RigConfig.load(rig).stage.model.calibration.endswith("stage_axis.json")


def test_axis_geometry_refuses_a_zero_direction() -> None:
    with pytest.raises(ValueError, match="direction must be a non-zero 3-vector"):
        AxisGeometry("t", AxisKind.ROTARY, np.zeros(3))


def tilted_axis_file(path: Path, nominal: StageModel, tilt_deg: float, shift_mm: float) -> Path:
    """A stage-axis calibration file whose turntable axis is off the truth by `tilt_deg`
    (about the camera's x axis) and `shift_mm` (along x): what a poor calibration gives."""
    a = nominal.axes[0]
    c, s = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    tilted = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]) @ a.direction
    path.write_text(json.dumps({"slscan_stage_axis": 1, "axes": [
        {"name": a.name, "kind": "rotary", "direction": tilted.tolist(),
         "point_mm": (a.point_mm + [shift_mm, 0.0, 0.0]).tolist()}]}))
    return path


def test_views_realigned_from_a_stage_axis_file(four_views: Path, tmp_path: Path) -> None:
    from inspection.views.align import align_views
    from inspection.views.view_clouds import load_views

    session = MultiViewSession.open(four_views)
    file = tilted_axis_file(tmp_path / "stage_axis.json", session.stage_model, 0.5, 0.5)
    model = session.stage_axis_file(file)
    views = load_views(session, model)
    a = json.loads(file.read_text())["axes"][0]
    d, p = np.array(a["direction"]) / np.linalg.norm(a["direction"]), np.array(a["point_mm"])
    for view, deg in zip(views, (0, 45, 90, 135)):
        # independently: world_from_stage turns about the file's line (Rodrigues), the prior is its inverse
        R = rotation_about(d, math.radians(deg))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, p - R @ p
        assert np.allclose(view.prior, np.linalg.inv(T), atol=1e-9)
    assert max(pose_error(truth_pose(v.session.root), w.prior, np.array([0.0, 0.0, 400.0]))[0]
               for v, w in zip(session.views, views)) > 0.5  # the priors are off ...
    alignment = align_views(views)
    for k, view in enumerate(session.views):  # ... and the refinement brings every view back to the truth
        deg, mm = pose_error(truth_pose(view.session.root), alignment.poses[k], alignment.centre)
        assert deg < 0.05 and mm < 0.1, (view.name, deg, mm)


def test_stage_axis_file_of_another_stage_is_refused_by_name(four_views: Path, tmp_path: Path) -> None:
    file = tmp_path / "other.json"
    file.write_text(json.dumps({"slscan_stage_axis": 1, "axes": [
        {"name": "tilt", "kind": "rotary", "direction": [1.0, 0.0, 0.0], "point_mm": [0.0, 0.0, 0.0]}]}))
    with pytest.raises(ScannerError, match=r"views.json, key '--stage-axis': .*other.json: calibrated axes "
                                           r"\[\('tilt', 'rotary'\)\] are not the rig's \[\('turntable', 'rotary'\)\]"):
        MultiViewSession.open(four_views).stage_axis_file(file)
    assert cli.main(["decode", str(four_views), "--stage-axis", str(tmp_path / "missing.json")]) == 2


def test_scan_records_the_views_with_the_given_stage_axis(tmp_path: Path) -> None:
    rig = turntable_rig(tmp_path)
    nominal = RigConfig.load(rig).stage.nominal
    file = tilted_axis_file(tmp_path / "stage_axis.json", nominal, 0.3, 0.2)
    out = tmp_path / "mv"
    assert cli.main(["scan", "--rig", str(rig), "--scene", str(SCENE), "--angles", "0,60", "--no-merge",
                     "--stage-axis", str(file), "--out", str(out)]) == 0
    session = MultiViewSession.open(out)
    assert session.stage_model.calibration == str(file)
    believed = StageModel.from_dict(json.loads(file.read_text()), file)
    for view in session.views:  # recorded with the file's axis; the simulator turned the part about its own
        assert np.allclose(view.world_from_stage, believed.world_from_stage(view.position), atol=1e-9)
        assert np.allclose(np.linalg.inv(truth_pose(view.session.root)), nominal.world_from_stage(view.position),
                           atol=1e-9)
    assert cli.main(["scan", "--rig", str(rig), "--scene", str(SCENE), "--stage-axis", str(file),
                     "--out", str(tmp_path / "single")]) == 2
