"""`slscan calibrate` on a rig with two cameras ([[cameras]]): both cameras' intrinsics and their
relative pose from board poses both see (calibration/stereo_cameras.py), written as
DIR/stereo_calibration.json (scanner/stereo_calibration_file.py) with DIR/report.txt; the board
frames stay in DIR/capture/pose_NNN/<camera>.png.

    slscan calibrate --rig RIG.toml --out DIR [--board B.toml] [--poses N] [--install] [--drop-outliers]
    slscan calibrate --from DIR/capture --out DIR2   (the same solve from the frames on disk)

The report gives each camera's reprojection RMS (alone and in the joint solve), the stereo RMS, the
epipolar error (rectified row difference of every corner both cameras found: what binocular
matching relies on), the baseline, and every parameter's one-sigma from the covariance (saved
whole in the file). A solve whose stereo RMS exceeds --max-camera-rms (default 0.5 px) is refused.
Every pose both cameras saw must pass `calibration.pose_gate` (its residuals against the other poses'
noise; a calibration whose poses all follow the model is refused with probability 0.1 %): a pose that
fails is named with its figures and the capture refused (exit 2), or with --drop-outliers left out
and the rig solved again without it, said so. On a simulated rig the simulator moves the board and
the report ends with the errors against its ground truth. The projector is not calibrated here
(binocular scans do not need it).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from scanner.errors import ConfigError
from slscan.exit_codes import Exit


def _truth_lines(cal: Any, truth: Any) -> list[str]:
    """The solve's errors against the simulator's truth (px, mm, arcsec)."""
    model, report = cal.model, cal.report()
    lines = ["against the simulator's ground truth:"]
    for name, got, true in (("left", model.left, truth.left), ("right", model.right, truth.right)):
        parts = []
        for i, j, p in ((0, 0, "fx"), (1, 1, "fy"), (0, 2, "cx"), (1, 2, "cy")):
            parts.append(f"{p} {got.K[i, j] - true.K[i, j]:+.3f} (sigma {report['std'][f'{name}.{p}']:.3f})")
        lines.append(f"          {name}: " + ", ".join(parts) + " px")
    T, Tt = model.right_from_left, truth.right_from_left
    angle = float(np.degrees(np.linalg.norm(cv2.Rodrigues(T[:3, :3] @ Tt[:3, :3].T)[0])))
    lines.append(f"          right_from_left: translation {np.linalg.norm(T[:3, 3] - Tt[:3, 3]) * 1e3:.1f} um "
                 f"(sigma {report['std']['extrinsic.translation_mm'] * 1e3:.1f}), rotation {angle * 3600:.1f} arcsec "
                 f"(sigma {report['std']['extrinsic.rotation_deg'] * 3600:.1f}); baseline "
                 f"{np.linalg.norm(T[:3, 3]) - np.linalg.norm(Tt[:3, 3]):+.4f} mm")
    return lines


def report_lines(cal: Any) -> list[str]:
    r = cal.report()
    a, b = cal.names
    rms = r["rms_px"]
    turned = (f"; {b}'s board labels turned to agree with {a}'s in pose(s) {', '.join(map(str, r['turned_poses']))}"
              if r["turned_poses"] else "")
    return [f"views     {len(r['views'])} board poses seen by both cameras{turned}",
            f"RMS       {a} {rms[a]:.4f} px ({rms[f'{a}_alone']:.4f} alone), {b} {rms[b]:.4f} px "
            f"({rms[f'{b}_alone']:.4f} alone), stereo {rms['stereo']:.4f} px",
            f"epipolar  {r['epipolar_rms_px']:.4f} px RMS, {r['epipolar_max_px']:.4f} px max (rectified rows)",
            f"baseline  {r['baseline_mm']:.3f} mm ± {r['std']['extrinsic.translation_mm'] * 1e3:.1f} um, rotation ± "
            f"{r['std']['extrinsic.rotation_deg'] * 3600:.1f} arcsec",
            *(f"{n:<9} " + ", ".join(f"{p} {c.K[i, j]:.2f} ± {r['std'][f'{n}.{p}']:.3f}" for i, j, p in
                                     ((0, 0, "fx"), (1, 1, "fy"), (0, 2, "cx"), (1, 2, "cy"))) + " px"
              for n, c in ((a, cal.model.left), (b, cal.model.right)))]


def _out(args: argparse.Namespace) -> Path:
    out = Path(args.out)
    if out.exists() and any(out.iterdir()):
        raise ConfigError("--out", "", f"{out}: output folder exists and is not empty; choose a new --out folder")
    out.mkdir(parents=True, exist_ok=True)
    return out


def cmd_calibrate_stereo(args: argparse.Namespace, config: Any, say: Any, texels_per_px: float) -> int:
    """The command (module docstring); `texels_per_px`: the simulated board's print resolution at the
    working distance (slscan/commands/calibrate.py's)."""
    from calibration.stereo_capture import capture_board_views
    from calibration.workflow import OperatorBench, Procedure
    from scanner.rig import open_rig

    out = _out(args)
    procedure = Procedure.for_rig(config, board=args.board, poses=args.poses)
    names = config.camera_names[:2]
    sizes = tuple(m.camera.size for m in list(config.camera_models().values())[:2])
    say(f"calibrating the cameras {names[0]} and {names[1]} of rig {config.name} ({config.driver}) with "
        f"{procedure.board.describe()}, {procedure.poses} poses -> {out}")
    if config.driver == "sim":
        from sim.calibration_bench import Target, plate_scene
        from sim.stereo_bench import StereoSimBench, plan_stereo_poses

        board, left = procedure.board, config.camera_models()[names[0]].camera
        footprint = config.working_distance_mm / left.K[0, 0]
        target = Target(board.image(board.texture_density(texels_per_px / footprint)), board.size_mm,
                        board.image_origin_mm, board.object_points())
        poses = plan_stereo_poses(config, target, procedure.poses, args.seed)
        with open_rig(config, scene=plate_scene(config.working_distance_mm + 200.0), seed=args.seed) as rig:
            views = capture_board_views(rig, StereoSimBench(rig, target, poses), board, len(poses), out / "capture",
                                        say)
    else:
        with open_rig(config) as rig:
            views = capture_board_views(rig, OperatorBench(say), procedure.board, procedure.poses, out / "capture",
                                        say)
    truth = config.stereo_model(nominal=True) if config.driver == "sim" else None
    return _solve_and_write(args, views, sizes, names=names, board=procedure.board, out=out, say=say, truth=truth,
                            rig_path=config.path)


def cmd_calibrate_stereo_from(args: argparse.Namespace, say: Any) -> int:
    """`slscan calibrate --from DIR` on a capture of board poses seen by two cameras
    (`calibration.stereo_capture`: as this command writes it under DIR/capture): the same solve,
    gate and files as on the rig. A folder without its manifest needs --board and a --rig whose
    [[cameras]] name its cameras (the first the rig's frame)."""
    from calibration.board import Board
    from calibration.stereo_capture import STEREO_CAPTURE_FILE, open_stereo_capture, read_board_views
    from scanner.rig import RigConfig

    source = Path(args.source)
    names = board = None
    if not (source / STEREO_CAPTURE_FILE).is_file():
        config = RigConfig.load(args.rig)
        names = tuple(config.camera_names) if len(config.cameras) >= 2 else None
        board = Board.load(args.board) if args.board else None
    capture = open_stereo_capture(source, board=board, names=names)
    if len(capture.names) < 2:
        raise ConfigError("--from", "", f"{source}: frames of one camera only; a stereo calibration needs two")
    out = _out(args)
    say(f"reading the stereo capture in {source} ({len(capture.poses)} poses, cameras {', '.join(capture.names)}) "
        f"with {capture.board.describe()} -> {out}")
    views = [v[:2] for v in read_board_views(capture, say)]
    return _solve_and_write(args, views, capture.sizes[:2], names=capture.names[:2], board=capture.board, out=out,
                            say=say,
                            truth=None, rig_path=None, frames=source)


def _solve_and_write(args: argparse.Namespace, views: list[Any], sizes: Any, *, names: Any, board: Any, out: Path,
                     say: Any, truth: Any, rig_path: Path | None, frames: Path | None = None) -> int:
    """The gate, the solve, the limit and the files (module docstring); `truth` the simulator's
    stereo model (the report ends with the errors against it), `frames` where the board frames are."""
    from calibration.errors import CalibrationRejected, PoseRefused
    from calibration.stereo_cameras import gated_stereo_calibration
    from scanner.stereo_calibration_file import write_stereo_calibration

    frames = frames or out / "capture"
    gate, cal = gated_stereo_calibration(views, sizes, names, fix_k3=args.fix_k3, symmetries=board.symmetries())
    dropped: list[str] = []
    if gate.failures:
        figures = "; ".join(f.describe(f"pose {f.pose}") for f in gate.failures)
        one = len(gate.failures) == 1
        if not args.drop_outliers:
            (out / "rejected.txt").write_text(f"{figures}\n{gate.model()}\n")
            raise PoseRefused(f"{figures}: the board likely found wrong in {'that pose' if one else 'those poses'} (a "
                              f"corner off, blur, glare, the board cut by the image edge); re-take "
                              f"{'it' if one else 'them'} or solve with --drop-outliers (frames kept in {frames})",
                              gate.poses)
        say(f"dropped {figures}; solved again without {'it' if one else 'them'} (--drop-outliers)")
        dropped = [f"dropped   {figures} ({gate.model()})"]
    limit = args.max_camera_rms if args.max_camera_rms is not None else 0.5
    if cal.joint.rms_px > limit:
        (out / "rejected.txt").write_text(f"stereo RMS {cal.joint.rms_px:.3f} px above {limit} px\n")
        raise CalibrationRejected(f"stereo RMS {cal.joint.rms_px:.3f} px exceeds --max-camera-rms {limit} px; the "
                                  f"board frames are kept in {frames}")
    path = write_stereo_calibration(out / "stereo_calibration.json", cal.model, cal.report())
    lines = report_lines(cal) + dropped
    if truth is not None:
        lines += _truth_lines(cal, truth)
    (out / "report.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"calibration {path}")
    if rig_path is None:
        return Exit.OK
    if args.install:
        from slscan.rig_install import name_in_rig

        name_in_rig(rig_path, "stereo_calibration", path)
        print(f"installed   {rig_path} now names this stereo calibration: every binocular scan with it uses it")
    else:
        print(f"to use it   add  stereo_calibration = \"{path.resolve()}\"  under [rig] in {rig_path} (or rerun "
              f"with --install)")
    return Exit.OK
