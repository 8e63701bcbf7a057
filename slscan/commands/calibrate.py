"""`slscan calibrate`: calibrate a projector-camera rig, guided on the bench or from
captures on disk (calibration/).

    slscan calibrate --rig RIG.toml --out DIR          capture on the rig, solve, validate, write
    slscan calibrate --from CAPTURE --out DIR          solve again from a capture made by slscan
    slscan calibrate --from DIR --layout opencv-graycode --projector-size 1024x768 --board BOARD.toml --out DIR
    slscan calibrate --stage-axis --rig RIG.toml --out DIR   the turntable's axis (slscan/commands/stage_axis.py)
    slscan calibrate --covariance-check N --seed S --out DIR   N independent simulated calibrations against the
                                                               true rig: is the reported covariance true?

On a simulated rig the simulator moves the board, the plate and the artefact, and the
report ends with the calibration's errors against the simulator's ground truth and a scan
compared with the ground-truth rig.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import re
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanner.errors import ScannerError
from slscan.exit_codes import Exit
from slscan.options import add_json
from slscan.simulated_calibration_bench import (
    PLATE_BEHIND_MM,
    SCAN_CHECK_SCENE,
    TEXELS_PER_PX,
    simulated_bench,
)

if TYPE_CHECKING:
    import numpy as np


def image_size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d+)x(\d+)", text)
    if not m:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 1024x768, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def _out_folder(path: Path) -> bool:
    """Make the empty output folder; True when this run created it (False: it was there, empty)."""
    if path.exists() and any(path.iterdir()):
        raise ScannerError(f"{path}: output folder exists and is not empty; choose a new --out folder")
    made = not path.exists()
    path.mkdir(parents=True, exist_ok=True)
    return made


@contextlib.contextmanager
def _undone_on_failure(out: Path, made: bool, undo: bool) -> Iterator[None]:
    """When `undo` and the body fails, leave `out` as it was before (absent, or empty), so
    the same command can be run again: solving from disk writes nothing worth keeping
    there before it succeeds (the captures stay where they are)."""
    try:
        yield
    except BaseException:
        if undo:
            shutil.rmtree(out, ignore_errors=True)
            if not made:
                out.mkdir(exist_ok=True)
            _say(f"nothing kept in {out}: fix the cause and run the same command again")
        raise


def _settings(args: argparse.Namespace, base: Any) -> Any:
    from dataclasses import replace

    changes = {k: v for k, v in (("max_camera_rms_px", args.max_camera_rms), ("max_projector_rms_px",
                                                                              args.max_projector_rms),
                                 ("max_validation_mm", args.max_validation), ("min_views", args.min_views),
                                 ("max_joint_camera_std", args.max_joint_camera_std))
               if v is not None}
    if args.fix_k3:
        changes["fix_k3"] = True
    if args.drop_outliers:
        changes["drop_outliers"] = True
    try:
        return replace(base, **changes)
    except ValueError as exc:
        raise ScannerError(f"slscan calibrate: {exc}") from None


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


RESULT_FILES = ("calibration.json", "stereo_calibration.json", "stage_axis.json")
"""What each kind of `slscan calibrate` writes into --out (projector-camera, two cameras, the
stage's axis): the result `--json` prints."""


def cmd_calibrate(args: argparse.Namespace) -> int:
    """The command; with `--json` (other than --covariance-check, whose summary is its result)
    the report goes to stderr and stdout gets one JSON document: the status, the file written
    and its content, or the refusal of a calibration its quality limits reject."""
    if not args.json or args.covariance_check is not None:
        return _calibrate(args)
    import json

    from calibration.errors import CalibrationRejected

    try:
        with contextlib.redirect_stdout(sys.stderr):
            code = _calibrate(args)
    except CalibrationRejected as exc:
        print(json.dumps({"status": "failed", "error": str(exc), "out": str(args.out)}))
        raise
    written = next(Path(args.out) / name for name in RESULT_FILES if (Path(args.out) / name).is_file())
    recording = Path(args.out) / "recording.rrd"
    print(json.dumps({"status": "ok", "file": str(written),
                      "recording": str(recording) if recording.is_file() else None,
                      "installed": bool(args.install), "result": json.loads(written.read_text())}))
    return code


def _calibrate(args: argparse.Namespace) -> int:
    if args.stage_axis:
        from slscan.commands.stage_axis import cmd_stage_axis

        return cmd_stage_axis(args)
    if args.covariance_check is not None:
        return _covariance_check(args)
    from calibration.calibration_recording import CalibrationRecording
    from calibration.errors import CalibrationRejected
    from calibration.workflow import write_result
    from scanner.session_recording import SessionRecording

    if args.source is not None and args.layout == "slscan":
        from calibration.stereo_capture import is_stereo_capture

        if is_stereo_capture(Path(args.source)):  # board poses of two cameras (calibrate_stereo writes them)
            from slscan.commands.calibrate_stereo import cmd_calibrate_stereo_from

            return cmd_calibrate_stereo_from(args, _say)
    if args.source is None:
        from scanner.rig import RigConfig

        config = RigConfig.load(args.rig)
        if len(config.cameras) >= 2:  # a rig with two cameras: they are calibrated together
            from slscan.commands.calibrate_stereo import cmd_calibrate_stereo

            return cmd_calibrate_stereo(args, config, _say, TEXELS_PER_PX)
    out = Path(args.out)
    made = _out_folder(out)
    run_id = f"calibration-{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    report_lines: list[str] = []
    try:
        with _undone_on_failure(out, made, undo=args.source is not None), \
                SessionRecording(out / "recording.rrd", run_id) as rec:
            log = CalibrationRecording(rec)

            def say(text: str) -> None:
                _say(text)
                log.event(text)

            if args.source:
                result, rig_path = _from_disk(args, say, log), None
            else:
                result, rig_path, report_lines = _on_rig(args, out, say, log)
            path = write_result(result, out / "calibration.json")
            log.metrics({"camera_rms_px": result.solution.stereo.camera_rms_px,
                         "projector_rms_px": result.solution.stereo.projector_rms_px,
                         "stereo_rms_px": result.solution.stereo.rms_px})
    except CalibrationRejected as exc:
        if args.source is None:  # on the rig: the capture and why it was refused stay in --out
            (out / "rejected.txt").write_text(f"{exc}\n")
        if (out / "capture").is_dir():
            _say(f"the capture is kept in {out / 'capture'}: solve it again with `slscan calibrate --from "
                 f"{out / 'capture'} --out NEW_FOLDER` (e.g. with --drop-outliers or corrected limits)")
        raise
    lines = result.lines() + report_lines
    (out / "report.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"calibration {path}")
    print(f"recording   {out / 'recording.rrd'}   (view: rerun {out / 'recording.rrd'})")
    if rig_path is not None:
        if args.install:
            _install(rig_path, path)
            print(f"installed   {rig_path} now names this calibration: every scan with it uses it")
        else:
            print(f"to use it   add  calibration = \"{path.resolve()}\"  under [rig] in {rig_path} (or rerun with "
                  f"--install)")
    return Exit.OK


def _covariance_check(args: argparse.Namespace) -> int:
    """`--covariance-check N`: the Mahalanobis check of the covariance (slscan/covariance_check.py);
    the report on stdout (or JSON) and in DIR/covariance_check.json."""
    import json

    from scanner.session import write_json
    from slscan.covariance_check import covariance_check

    if args.covariance_check < 1:
        raise ScannerError("--covariance-check: give the number of calibrations (>= 1; 30 or more to judge)")
    out = Path(args.out)
    _out_folder(out)
    try:
        check = covariance_check(args.rig, args.covariance_check, args.seed, args.poses, _say)
    except ValueError as exc:
        raise ScannerError(str(exc)) from None
    summary = check.summary()
    write_json(out / "covariance_check.json", summary)
    print(json.dumps({"status": "ok", **summary}) if args.json else "\n".join(check.lines()))
    return Exit.OK


def _from_disk(args: argparse.Namespace, say: Any, log: Any) -> Any:
    from calibration.board import Board
    from calibration.graycode import GrayCodeLayout
    from calibration.solve import CalibrationSettings
    from calibration.store import CaptureSet, graycode_views
    from calibration.workflow import calibrate_capture, calibrate_views

    strict = not args.skip_bad_views
    if args.layout == "opencv-graycode":
        if args.projector_size is None or args.board is None:
            raise ScannerError("--layout opencv-graycode needs --projector-size WxH and --board BOARD.toml")
        layout = GrayCodeLayout(*args.projector_size)
        say(f"reading OpenCV Gray-code captures for a {layout.width} x {layout.height} projector from {args.source}")
        views = graycode_views(args.source, layout, args.pose_folders)
        board = Board.load(args.board)
        return calibrate_views(board, views, args.projector_size, _settings(args, CalibrationSettings()), "from-disk",
                               say, recording=log, strict=strict)
    capture = CaptureSet.open(args.source)
    say(f"reading the slscan capture in {args.source} ({len(capture.pose_names)} poses)")
    return calibrate_capture(capture, _settings(args, CalibrationSettings()), capture.manifest.get("rig", "rig"),
                             say, recording=log, strict=strict, board=Board.load(args.board) if args.board else None)


def _on_rig(args: argparse.Namespace, out: Path, say: Any, log: Any) -> tuple[Any, Path, list[str]]:
    from dataclasses import replace

    from calibration.workflow import OperatorBench, Procedure, calibrate_rig
    from scanner.rig import RigConfig, open_rig

    config = RigConfig.load(args.rig)
    procedure = Procedure.for_rig(config, board=args.board, poses=args.poses)
    procedure = replace(procedure, settings=_settings(args, procedure.settings))
    say(f"calibrating rig {config.name} ({config.driver}) with {procedure.board.describe()}, "
        f"{procedure.poses} poses -> {out}")
    if config.driver != "sim":
        with open_rig(config) as rig:
            return calibrate_rig(rig, procedure, OperatorBench(say), out / "capture", say, log), config.path, []
    from calibration.compare import error_lines, model_errors
    from sim.calibration_bench import plate_scene

    truth = config.nominal_model()
    with open_rig(config, scene=plate_scene(config.working_distance_mm + PLATE_BEHIND_MM), seed=args.seed) as rig:
        result = calibrate_rig(rig, procedure, simulated_bench(rig, procedure, args.seed), out / "capture", say, log)
        lines = ["against the simulator's ground truth:", *("          " + x for x in
                                                           error_lines(model_errors(result.model, truth)))]
        lines += _scan_check(rig, result.model, truth, say)
        lines += [_calibration_depth_line(result.model, result.solution.stereo.covariance, truth, say)]
        if result.model.phase_to_height is not None:
            lines += _phase_height_check(rig, result.model, config.working_distance_mm + PLATE_BEHIND_MM,
                                         max(procedure.plate_heights_mm), say)
    return result, config.path, lines


def _scan_check(rig: Any, calibrated: Any, truth: Any, say: Any) -> list[str]:
    """One scan of the sphere-and-plane scene, reconstructed with the calibrated rig and with
    the ground-truth rig: depth errors against the simulator's truth."""
    from calibration.capture import capture_fringes
    from scanner.decode import decode
    from scanner.patterns import PatternSet
    from scanner.reconstruct import Triangulator, triangulate
    from sim.calibration_bench import show
    from sim.evaluate import Truth, evaluate
    from sim.scene import load_scene

    say("scan check: the sphere-and-plane scene with the calibrated and the ground-truth rig")
    show(rig, load_scene(SCAN_CHECK_SCENE))
    patterns = PatternSet.load(rig.config.patterns_path)
    stack = capture_fringes(rig, patterns, calibrated.projector_gamma)
    decoded = decode(stack, patterns, rig.camera.bit_depth, calibrated.projector.size)
    gt = Truth.of(rig.extras["ground_truth"])
    sensor = rig.extras["sensor"]
    acc = {name: evaluate(decoded, triangulate(decoded, Triangulator(m)), gt, sensor, Triangulator(m))
           for name, m in (("calibrated", calibrated), ("ground truth", truth))}
    c, t = acc["calibrated"], acc["ground truth"]
    return [f"scan check (sphere + plane, {patterns.family}): depth RMS {c.rms_mm * 1e3:.2f} um with the calibrated "
            f"rig, {t.rms_mm * 1e3:.2f} um with the ground-truth rig (ratio {c.rms_mm / t.rms_mm:.3f}); mean "
            f"{c.mean_mm * 1e3:+.2f} / {t.mean_mm * 1e3:+.2f} um"]


def _calibration_depth_line(calibrated: Any, covariance: np.ndarray, truth: Any, say: Any) -> str:
    """The calibration's own share of the scan check's mean depth error, and its one-sigma
    from the calibration's covariance (slscan/calibration_depth.py)."""
    from calibration.consistency import model_parameters
    from slscan.calibration_depth import calibration_depth_bias

    say("scan check: the calibration's own depth error and its sigma from the covariance")
    bias = calibration_depth_bias(truth, model_parameters(calibrated), covariance, SCAN_CHECK_SCENE)
    return "          " + bias.summary()


def _measuring_volume_scene(camera: Any, plate_mm: float, top_mm: float) -> Any:
    """A simulated scene filling the phase-to-height model's measuring volume: the plate at
    `plate_mm` (the reference plane), a ramp rising from 7 % to 93 % of `top_mm` in the left
    half of the view and a ball whose top is at 93 % of `top_mm` in the right half."""
    import cv2
    import numpy as np

    from sim.calibration_bench import plate_scene
    from sim.scene import Scene, SceneObject

    half = plate_mm * camera.width / 2.0 / camera.K[0, 0]  # half the field's width on the plate (mm)
    length = 0.55 * half
    tilt = float(np.arcsin(0.86 * top_mm / length))
    ramp = np.eye(4)
    ramp[:3, :3] = cv2.Rodrigues(np.array([0.0, tilt, 0.0]))[0]
    ramp[:3, 3] = (-0.45 * half, 0.0, plate_mm - 0.5 * top_mm)
    radius = 0.2 * half
    ball = np.eye(4)
    ball[:3, 3] = (0.5 * half, 0.0, plate_mm - 0.93 * top_mm + radius)
    return Scene(objects=(SceneObject("ramp", "plane", ramp, 0.7, size_mm=(length, 0.6 * half)),
                          SceneObject("ball", "sphere", ball, 0.7, radius_mm=radius)),
                 reference_plane=plate_scene(plate_mm).reference_plane, name="phase-to-height volume")


def _phase_height_check(rig: Any, calibrated: Any, plate_mm: float, top_mm: float, say: Any) -> list[str]:
    """A scan of `_measuring_volume_scene` reconstructed with the calibrated phase-to-height
    model (per pixel and global) and by triangulation: height errors against the
    simulator's truth over the measuring volume."""
    import numpy as np

    from calibration.capture import capture_fringes
    from calibration.phase_height import scan_height_errors
    from scanner.decode import decode
    from scanner.patterns import PatternSet
    from scanner.reconstruct import Triangulator, phase_to_height_cloud, triangulate
    from sim.calibration_bench import show
    from sim.evaluate import Truth, smooth_region

    say("phase-to-height check: a ramp and a ball within the calibrated heights")
    show(rig, _measuring_volume_scene(calibrated.camera, plate_mm, top_mm))
    patterns = PatternSet.load(rig.config.patterns_path)
    decoded = decode(capture_fringes(rig, patterns, calibrated.projector_gamma), patterns, rig.camera.bit_depth,
                     calibrated.projector.size)
    model, rays = calibrated.phase_to_height, calibrated.camera.ray_grid
    phase = np.where(decoded.valid, decoded.maps["vertical"].phase, np.nan)
    depths = {"per-pixel Eq. 17": phase_to_height_cloud(decoded, calibrated).points[..., 2],
              "global Eq. 17": model.depth(phase, rays, per_pixel=False),
              "triangulation": triangulate(decoded, Triangulator(calibrated), with_normals=False).points[..., 2]}
    gt = Truth.of(rig.extras["ground_truth"])
    errors, n = scan_height_errors(model, calibrated.camera, depths, gt.depth, smooth_region(gt), top_mm)
    return [f"phase-to-height check (ramp + ball, heights 0 .. {top_mm:g} mm, {n} px): height RMS "
            + ", ".join(f"{k} {rms * 1e3:.1f} um ({cover:.1%} measured)" for k, (rms, cover) in errors.items())]


def _install(rig_path: Path, calibration: Path) -> None:
    """Name `calibration` in the rig TOML's [rig] table (replacing an earlier one)."""
    from slscan.rig_install import name_in_rig

    name_in_rig(rig_path, "calibration", calibration)


def register(sub: Any) -> None:
    from scanner.config import DEFAULT_RIG

    c = sub.add_parser("calibrate")
    c.add_argument("--rig", type=Path, default=DEFAULT_RIG, help="rig TOML (default: the simulated bench rig)")
    c.add_argument("--out", type=Path, required=True, help="new folder for the capture, calibration and recording")
    c.add_argument("--board", type=Path, help="board TOML (default: the rig's [calibrate] board, or the bench board)")
    c.add_argument("--poses", type=int, help="board poses to capture (default: the rig's [calibrate] poses, or 12)")
    c.add_argument("--seed", type=int, default=0, help="simulated rigs: noise and pose jitter seed")
    c.add_argument("--from", dest="source", type=Path, help="solve from captures in this folder instead of capturing")
    c.add_argument("--layout", choices=("slscan", "opencv-graycode"), default="slscan",
                   help="--from: how the captures are laid out (default: a capture written by slscan calibrate, "
                        "one camera or two)")
    c.add_argument("--projector-size", type=image_size, help="--layout opencv-graycode: projector WIDTHxHEIGHT")
    c.add_argument("--pose-folders", default="*", metavar="GLOB",
                   help="--layout opencv-graycode: the sub-folders holding one pose each (default: all)")
    c.add_argument("--skip-bad-views", action="store_true",
                   help="--from: leave out views without the board or the projector pattern instead of failing")
    c.add_argument("--max-camera-rms", type=float, metavar="PX", help="refuse above this camera RMS (default 0.5)")
    c.add_argument("--max-projector-rms", type=float, metavar="PX",
                   help="refuse above this projector RMS (default 1.0)")
    c.add_argument("--max-validation", type=float, metavar="MM",
                   help="refuse above this artefact distance error (default 0.1)")
    c.add_argument("--min-views", type=int, help="fewest usable views (default 4)")
    c.add_argument("--max-joint-camera-std", type=float, metavar="FRACTION",
                   help="keep the camera's own intrinsics when the joint refinement determines its fx, fy, cx or cy "
                        "only to more than this fraction of the focal length (default 0.001)")
    c.add_argument("--fix-k3", action="store_true", help="keep the k3 distortion term at 0")
    c.add_argument("--drop-outliers", action="store_true", help="solve again without views whose error stands out")
    c.add_argument("--install", action="store_true", help="name the new calibration in the rig TOML")
    c.add_argument("--stage-axis", action="store_true", help="calibrate the rig's turntable axis from a board it turns "
                                                              "(writes stage_axis.json)")
    c.add_argument("--angles", metavar="DEG,DEG,...", help="--stage-axis: the stage angles (default -90..90 by 30)")
    c.add_argument("--covariance-check", type=int, metavar="N",
                   help="simulated rigs: N independent calibrations (seeds --seed, --seed + 1, ...), each against the "
                        "true rig: the Mahalanobis distance of the truth under the covariance each reports")
    add_json(c)
    c.set_defaults(func=cmd_calibrate)
