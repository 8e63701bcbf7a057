"""`slscan verify`: the acceptance and reverification test of VDI/VDE 2634 Part 2 (optical
3D measuring systems with area scanning), what it implements: `inspection.acceptance`.

    slscan verify --rig RIG.toml --out DIR [--artefacts FILE] [--calibration FILE] [--json]

The rig file's [acceptance] table gives the measuring volume, the maximum permissible
errors and the decision rule; the artefact file their calibrated values (default: the
[acceptance] table's `artefacts`). On a simulated rig the simulator places each artefact
at each position and the test runs unattended; on a real bench the operator is told where
to put each artefact and presses Enter (s skips a position, q stops: the positions left
are not tested), as `slscan calibrate` guides its board poses. Each position is scanned
with the rig's geometry (its calibration file, or `--calibration`), measured, and logged to
DIR/recording.rrd (cloud, fitted spheres or plane, figures); the report goes to
DIR/verify.json and DIR/verify.html. Exit code 0 when the rig passes; 1 when it fails; 4
when a prescribed position was not tested (the result is then "incomplete": no verdict).

    slscan verify --leave-one-out DIR --out DIR [--layout opencv-graycode --projector-size WxH --board B]

checks a calibration on captured board poses instead (`slscan.board_check`).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from scanner.errors import ScannerError
from slscan.exit_codes import for_parts


class OperatorArtefactBench:
    """Tells a person at the bench where each artefact goes and waits for Enter."""

    def __init__(self, say: Callable[[str], None], ask: Callable[[str], str] = input) -> None:
        self.say = say
        self.ask = ask

    def place(self, position: Any) -> bool:
        """False when the operator skips the position; raises KeyboardInterrupt on q."""
        self.say(f"{position.name}: put the {position.description}")
        answer = self.ask("press Enter to scan, s and Enter to skip this position, q and Enter to stop: ")
        answer = answer.strip().lower()
        if answer == "q":
            raise KeyboardInterrupt
        return answer != "s"


def _out_folder(path: Path) -> Path:
    if path.exists() and any(path.iterdir()):
        raise ScannerError(f"{path}: output folder exists and is not empty; choose a new --out folder")
    path.mkdir(parents=True, exist_ok=True)
    return path


def _model(config: Any, calibration: Path | None) -> Any:
    """The geometry to measure with: `--calibration`, else the rig's own (its calibration
    file or its nominal geometry)."""
    if calibration is None:
        return config.model
    from scanner.calibration_file import load_rig_model

    nominal = config.nominal_model()
    return load_rig_model(calibration, nominal.camera.size, nominal.projector.size)


def _log_position(rec: Any, k: int, cloud: Any, model: Any, result: Any) -> None:
    import rerun as rr

    rec.log_cloud(cloud, model, scan=k)
    rec.log_event(f"{result.position.name}: {result.error or result.position.description}", scan=k,
                  level="WARN" if result.error else "INFO")
    if result.values:
        rec.log_metrics({f"verify_{p}_mm": v for p, v in result.values.items()}, scan=k)
    fit = result.detail.get("sphere") or result.detail.get("ball_bar") or {}
    spheres = fit.get("spheres", [fit] if "radius_mm" in fit else [])
    spheres = [s for s in spheres if s.get("radius_mm") is not None]
    if spheres:
        rec.stream.log("world/verify/fit", rr.Ellipsoids3D(centers=[s["centre_mm"] for s in spheres],
                                                            half_sizes=[[s["radius_mm"]] * 3 for s in spheres]),
                       strict=True)


def run(args: argparse.Namespace, say: Callable[[str], None]) -> Any:
    """Place, scan and measure every position; the AcceptanceReport."""
    from calibration.capture import capture_fringes
    from inspection.acceptance import Acceptance, AcceptanceReport, PositionResult, ScanData, evaluate, positions
    from inspection.artefact_file import DEFAULT_ARTEFACTS, load_artefacts
    from scanner.decode import decode
    from scanner.patterns import PatternSet
    from scanner.reconstruct import Triangulator, triangulate
    from scanner.rig import RigConfig, open_rig
    from scanner.session_recording import SessionRecording
    from slscan.measurement_model import rig_measurement

    config = RigConfig.load(args.rig)
    acceptance = Acceptance.for_rig(config)
    artefacts = load_artefacts(args.artefacts or acceptance.artefacts or DEFAULT_ARTEFACTS)
    plan = positions(acceptance, artefacts)
    model = _model(config, args.calibration)
    patterns = PatternSet.load(config.patterns_path)
    out = _out_folder(Path(args.out))
    stereo = config.stereo_model() if len(config.cameras) >= 2 else None
    geometry = (stereo.calibration if stereo is not None else model.calibration) or "nominal (no calibration file)"
    say(f"verifying rig {config.name} ({config.driver}) with {artefacts.name}: {len(plan)} positions in a "
        f"{' x '.join(f'{s:g}' for s in acceptance.size_mm)} mm measuring volume; geometry {geometry} -> {out}")
    results: list[PositionResult] = []
    sim = config.driver == "sim"
    options: dict[str, Any] = {"seed": args.seed} if sim else {}
    if sim:
        from sim.artefact_scenes import artefact_scene

        options["scene"] = artefact_scene(plan[0], artefacts)
    run_id = f"verify-{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    with SessionRecording(out / "recording.rrd", run_id) as rec, open_rig(config, **options) as rig:
        rig.model = model
        rec.log_rig(model)
        if sim:
            from sim.artefact_scenes import SimArtefactBench

            bench: Any = SimArtefactBench(rig, artefacts)
        else:
            bench = OperatorArtefactBench(say)
        measurement = rig_measurement(config.raw, model, patterns, rig.camera.bit_depth, config.path)
        tri = Triangulator(model)
        binocular = binocular_scanner(stereo) if stereo is not None else None
        for k, position in enumerate(plan):
            t0 = time.perf_counter()
            try:
                placed = bench.place(position)
            except KeyboardInterrupt:
                say(f"stopped at {position.name}: it and the {len(plan) - k - 1} positions after it are not tested")
                results.extend(PositionResult.not_tested(p) for p in plan[k:])
                break
            if placed is False:
                say(f"{position.name}: skipped (not tested: the test will be incomplete)")
                results.append(PositionResult.not_tested(position))
                continue
            if binocular is not None:
                cloud, data = binocular(rig, patterns, model.projector_gamma)
            else:
                stack = capture_fringes(rig, patterns, model.projector_gamma)
                decoded = decode(stack, patterns, rig.camera.bit_depth, model.projector.size)
                cloud = triangulate(decoded, tri)
                # the artefact fits leave the outlines out rather than remove the defocus bias (inspection.acceptance)
                data = ScanData(cloud.points, measurement.of_scan(decoded, model))
            result = evaluate(position, data, artefacts)
            results.append(result)
            _log_position(rec, k, cloud, model, result)
            figures = ", ".join(f"{p} {v * 1e3:.1f} µm" for p, v in result.values.items())
            say(f"{position.name} ({k + 1}/{len(plan)}, {time.perf_counter() - t0:.0f} s): "
                f"{figures or 'NOT MEASURED: ' + result.error}")
    notes = {"noise model": "decoder and sensor model" if measurement.sensor is not None else
             "none (the rig file has no [camera.sensor]): the fits' residuals stand in for it",
             "calibration uncertainty": measurement.calibration.source,
             "fringe error": f"{measurement.fringe.rms_px:.4f} projector px RMS (quantised patterns)"
                             if measurement.fringe is not None else "not modelled"}
    if stereo is not None:
        from slscan.commands.verify_binocular import binocular_calibration

        notes |= {"reconstruction": f"binocular: cameras {', '.join(config.camera_names[:2])} matched "
                                    f"(scanner/binocular.py); the projector's geometry unused",
                  "noise model": "both cameras' decoded phase noise", "calibration uncertainty":
                  binocular_calibration(stereo).source}
    return AcceptanceReport(config.name, f"geometry {geometry}",
                            acceptance, artefacts, tuple(results), notes)


def binocular_scanner(stereo: Any) -> Callable[[Any, Any, float], tuple[Any, Any]]:
    """For a rig with two cameras and their `stereo` model: a function scanning with all of them
    (patterns compensated for the projector's gamma) and returning the binocular cloud and its
    ScanData (slscan/commands/verify_binocular.py)."""
    from scanner.binocular import BinocularReconstructor
    from slscan.commands.verify_binocular import binocular_scan_data

    bino = BinocularReconstructor(stereo)
    return lambda rig, patterns, gamma: binocular_scan_data(rig, patterns, gamma, bino)


def leave_one_out(args: argparse.Namespace, say: Callable[[str], None]) -> int:
    """`--leave-one-out`: each pose of a capture checked by a calibration of the others
    (`slscan.board_check`); table on stdout (or JSON), DIR/leave_one_out.json."""
    import numpy as np

    from calibration.board import Board
    from calibration.graycode import GrayCodeLayout
    from calibration.store import CaptureSet, graycode_views
    from scanner.session import write_json
    from slscan.board_check import leave_one_out as check
    from slscan.board_check import pooled_summary

    if args.layout == "opencv-graycode":
        if args.projector_size is None or args.board is None:
            raise ScannerError("--layout opencv-graycode needs --projector-size WxH and --board BOARD.toml")
        views = graycode_views(args.leave_one_out, GrayCodeLayout(*args.projector_size), args.pose_folders)
        board, size = Board.load(args.board), args.projector_size
    else:
        capture = CaptureSet.open(args.leave_one_out)
        views, size = capture.views(), capture.projector_size
        board = Board.load(args.board) if args.board else capture.board
    out = _out_folder(Path(args.out))
    checks = check(views, board, size, say)
    rows = [c.summary(board.square_mm) for c in checks]
    pooled = pooled_summary(checks, board.square_mm)
    write_json(out / "leave_one_out.json", {"poses": rows, "summary": pooled})
    if args.json:
        print(json.dumps({"poses": rows, "summary": pooled}))
        return 0
    print(f"{'pose':<12} {'flatness (corners)':>20} {'plane RMS':>10} {'adjacent err RMS':>17} {'max':>7} "
          f"{'U (median)':>11} {'longest err ± U':>22} {'within U':>9}")
    for c, r in zip(checks, rows):
        longest = f"{np.mean(r['longest_error_mm']):+.3f} ± {np.median(r['longest_U_mm']):.3f}"
        print(f"{r['pose']:<12} {c.flatness.text(0).replace('µm', 'um'):>20} {r['plane_rms_mm']:10.3f} "
              f"{r['adjacent_error_rms_mm']:17.3f} {r['adjacent_error_max_mm']:7.3f} {r['adjacent_U_median_mm']:11.3f} "
              f"{longest:>22} {r['within_U']:9.0%}")
    print(f"mm (flatness in um); corner distances along rows and columns against multiples of {board.square_mm:g} mm; "
          f"'longest': the {rows[0]['longest_nominal_mm']:g} mm distances; U with k = 2; report "
          f"{out / 'leave_one_out.json'}")
    p = pooled
    print(f"{p['independent_poses']} independent poses ({p['distances']} distances, not independent: a pose's share "
          f"its "
          f"calibration and its board pose): {p['within_U']:.1%} of the distances within ±U, "
          f"{p['poses_with_95_percent_within_U']} of {p['independent_poses']} poses with 95 % or more; error / (U/2) "
          f"RMS {p['normalised_error_rms']:.2f} (1 when U is honest; per pose "
          f"{', '.join(f'{v:.2f}' for v in p['normalised_error_rms_per_pose'])}); adjacent corners: U median "
          f"{p['adjacent_U_median_mm']:.3f} mm, {p['adjacent_U_over_error_rms']:.1f} x the error's RMS "
          f"(2 for k = 2)")
    print("adjacent corners' U (median, mm) from the corners' noise | from the calibration: " + ", ".join(
        f"{r['pose']} {r['adjacent_U_noise_median_mm']:.3f} | {r['adjacent_U_calibration_median_mm']:.3f}"
        for r in rows))
    print(f"truth: {p['truth']}")
    return 0


def cmd_verify(args: argparse.Namespace) -> int:
    from scanner.session import write_atomic, write_json

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    if args.leave_one_out is not None:
        return leave_one_out(args, say)
    report = run(args, say)
    out = Path(args.out)
    data = report.as_dict()
    write_json(out / "verify.json", data)
    write_atomic(out / "verify.html", report.html().encode())
    if args.json:
        print(json.dumps(data))
    else:
        print(report.table())
        print(f"report    {out / 'verify.html'} (.json); recording {out / 'recording.rrd'}")
    return for_parts([report.status])  # pass 0, fail 1, incomplete 4 (no verdict)


def register(sub: Any) -> None:
    from scanner.config import DEFAULT_RIG
    from slscan.commands.calibrate import image_size

    v = sub.add_parser("verify")
    v.add_argument("--rig", type=Path, default=DEFAULT_RIG, help="rig TOML with an [acceptance] table (default: the "
                                                                 "simulated bench rig)")
    v.add_argument("--artefacts", type=Path, help="artefact TOML (default: the rig's [acceptance] artefacts)")
    v.add_argument("--calibration", type=Path, help="measure with this calibration file instead of the rig's own")
    v.add_argument("--out", type=Path, required=True, help="new folder for the report and the recording")
    v.add_argument("--seed", type=int, default=0, help="simulated rigs: noise seed")
    v.add_argument("--json", action="store_true", help="print the report as JSON")
    v.add_argument("--leave-one-out", type=Path, metavar="DIR",
                   help="instead: check a calibration on captured board poses, each left out of a calibration of the "
                        "others and measured by triangulation")
    v.add_argument("--layout", choices=("slscan", "opencv-graycode"), default="slscan",
                   help="--leave-one-out: how the captures are laid out (as slscan calibrate --from)")
    v.add_argument("--projector-size", type=image_size, help="--layout opencv-graycode: projector WIDTHxHEIGHT")
    v.add_argument("--board", type=Path, help="--leave-one-out: board TOML")
    v.add_argument("--pose-folders", default="*", metavar="GLOB", help="--layout opencv-graycode: one pose per folder")
    v.set_defaults(func=cmd_verify)
