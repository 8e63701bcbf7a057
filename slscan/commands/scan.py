"""`slscan scan`, `slscan decode` and `slscan demo`: capture a session, regenerate its
outputs from its raw frames, and the bundled demo (scan, then inspect against CAD)."""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Sequence

from scanner.config import CONFIG_DIR
from scanner.errors import ConfigError, ScannerError
from scanner.reconstruct import Triangulator
from scanner.rig import DEFAULT_RIG
from scanner.session import write_json
from scanner.stage_timer import StageTimer
from slscan.progress import ProgressLine

DEMO_SCENE = CONFIG_DIR / "scenes" / "demo.toml"
DEMO_CAD = CONFIG_DIR / "parts" / "demo_part.step"  # the demo scene's part as a STEP model
DEMO_TOLERANCES = CONFIG_DIR / "tolerances" / "demo_part.toml"


def _parse_faults(items: Sequence[str]) -> Any:
    from sim.virtual_devices import Faults

    table: dict[str, Any] = {}
    for item in items:
        key, _, value = item.partition("=")
        if not value:
            raise ConfigError("--fault", item, "expected NAME=VALUE, e.g. drop_frame=3")
        table[key] = float(value) if key == "delay_s" else int(value)
    return Faults.from_table(table, "--fault", prefix="--fault")


def _parse_stage_faults(items: Sequence[str]) -> Any:
    from sim.virtual_stage import StageFaults

    table: dict[str, Any] = {}
    for item in items:
        key, _, value = item.partition("=")
        if not value.isdigit():
            raise ConfigError("--stage-fault", item, "expected NAME=MOVE, e.g. alarm_at_move=3")
        table[key] = int(value)
    return StageFaults.from_table(table, "--stage-fault")


def cmd_scan(args: argparse.Namespace, then: Any = None) -> int:
    """`slscan scan`; `then(result, recording)` runs after processing, into the session's
    recording (`pipeline.scan`)."""
    from scanner.patterns import PatternSet
    from scanner.pipeline import scan
    from scanner.rig import RigConfig, open_rig

    config = RigConfig.load(args.rig)
    patterns = PatternSet.load(args.patterns or config.patterns_path)
    options: dict[str, Any] = {}
    stage_faults = getattr(args, "stage_fault", [])
    if config.driver == "sim":
        options = {"scene": args.scene or DEMO_SCENE, "seed": args.seed}
        if args.fault:
            options["faults"] = _parse_faults(args.fault)
        if stage_faults:
            options["stage_faults"] = _parse_stage_faults(stage_faults)
    elif args.scene or args.fault or stage_faults:
        raise ConfigError(config.path, "rig.driver", "--scene, --fault and --stage-fault apply to simulated rigs only")
    if getattr(args, "views", None) is not None or getattr(args, "angles", None) is not None:
        from slscan.commands.views import scan_views

        return scan_views(args, config, patterns, options)
    if getattr(args, "stage_axis", None) is not None:
        raise ScannerError("--stage-axis applies to multi-view scans only (--views or --angles)")
    out = Path(args.out)
    print(f"rig {config.name} ({config.driver}, {config.trigger} trigger), {patterns.family} "
          f"{patterns.n_frames} frames -> {out}", file=sys.stderr)
    with open_rig(config, **options) as rig:
        result = scan(rig, patterns, out, ProgressLine(), then, level=_level(args))
    report(result)
    return 0


def _level(args: argparse.Namespace) -> str | None:
    """The recording level asked on the command line (None: the rig's or session's own)."""
    return "full" if getattr(args, "full_recording", False) else None


def report(result: Any) -> None:
    """Print what a processed session holds, and its accuracy when ground truth is there."""
    s = result.session
    t = result.timings_s
    print(f"session   {s.root}")
    valid = f"{result.decoded.valid.mean() * 100:.1f} % of pixels valid"
    if result.cloud is None:
        print(f"maps      {s.outputs / 'maps.npz'}  ({valid}; no calibration, so no cloud)")
    else:
        print(f"cloud     {result.cloud_path}  ({len(result.cloud)} points, {valid})")
    rejected = result.decoded.rejected()  # per orientation, each pixel under its first reason
    print("rejected  " + ", ".join(f"{k} {v / result.decoded.valid.size * 100:.2f} %" for k, v in rejected.items()
                                   if v) + " of the pixels")
    if s.recording_path.exists():
        print(f"recording {s.recording_path}   (view: slscan review {s.root})")
    print(f"timings   decode {t['decode'] * 1e3:.0f} ms, reconstruct {t['reconstruct'] * 1e3:.0f} ms")
    if s.integrity != "sha256":
        print(f"warning   frame integrity {s.integrity}", file=sys.stderr)
    acc = sim_accuracy(result)
    if acc is not None:
        print(f"accuracy  {acc.summary()}")


def sim_accuracy(result: Any) -> Any:
    """Accuracy against the simulator's ground truth, if the session has it."""
    if "import" in result.session.manifest:
        return None  # another tool's frames carry no simulator truth (and the simulator takes ~0.3 s to import)
    from sim.evaluate import GROUND_TRUTH_FILE, Truth, evaluate
    from sim.render import SensorModel

    path = result.session.root / GROUND_TRUTH_FILE
    if not path.exists() or len(result.decoded.maps) != 1 or result.cloud is None:
        return None

    manifest = result.session.manifest
    sensor = SensorModel.from_table(manifest["rig_config"]["camera"]["sensor"], result.session.root / "manifest.json")
    acc = evaluate(result.decoded, result.cloud, Truth.load(path), sensor, Triangulator(result.session.rig_model()))
    write_json(result.session.outputs / "accuracy.json", acc.as_dict())
    return acc


def cmd_decode(args: argparse.Namespace) -> int:
    from scanner.multiview import is_multiview
    from scanner.pipeline import reprocess
    from scanner.session import Session

    if is_multiview(args.session):
        from slscan.commands.views import decode_views

        return decode_views(args)
    if args.stage_axis is not None:
        raise ScannerError(f"{args.session}: --stage-axis applies to multi-view sessions only")
    result = reprocess(Session.open(args.session), ProgressLine(), mode=args.mode, level=_level(args))
    report(result)
    return 0


def load_demo_part() -> tuple[Any, Any]:
    """The demo part's CAD model, registration target prepared, and its tolerances."""
    from inspection.inspect_scan import prepare
    from inspection.tolerances import load_tolerances
    from slscan.commands.inspect import _load_model

    model = _load_model(str(DEMO_CAD), "mm")
    prepare(model)  # the registration target, made once per model
    return model, load_tolerances(DEMO_TOLERANCES, {f.label: f.type for f in model.faces})


def inspect_verdict_first(result: Any, recording: Any, model: Any, tolerances: Any, seed: int = 0,
                          prior: Any = None, on_verdict: Callable[[Any], None] | None = None) -> tuple[Any, StageTimer]:
    """Inspect a processed scan against `model`, the verdict first: `on_verdict(report)`
    runs as soon as it is known; then the work that does not change it, the report files
    (JSON, CSV, HTML with the deviation map) and the inspection in `recording` (None: not
    recorded). The session is complete when this returns: until then outputs/ has no
    inspection.json and the recording is still `recording.rrd.part`. `prior`: the previous
    part's registration (warm start). Returns the report and the time of each stage."""
    from inspection.inspect_scan import InspectionSettings, inspect
    from inspection.measured_cloud import from_organised, load_session
    from inspection.registration import RegistrationSettings
    from inspection.report import deviation_image, png

    timer = StageTimer()
    with timer.stage("load_cloud"):  # the cloud in memory is the one in cloud.ply (same points, normals, pixels)
        scan = (from_organised(result.cloud, str(result.session.root)) if result.cloud is not None
                else load_session(result.session.root))
    with timer.stage("inspect"):
        report = inspect(scan, model, tolerances, InspectionSettings(registration=RegistrationSettings(seed=seed)),
                         prior=prior)
    if on_verdict is not None:
        on_verdict(report)
    with timer.stage("report_files"):
        report.write(result.session.outputs, deviation_png=png(deviation_image(report, scan)))
    if recording is not None:
        from inspection.inspection_recording import log_inspection

        with timer.stage("record_inspection"):
            log_inspection(recording, report, scan, model)
    return report, timer


def cmd_demo(args: argparse.Namespace) -> int:
    """Scan the bundled part on the simulated rig, then (unless --no-inspect) inspect the
    session against the part's STEP model and tolerances: registration, per-face
    segmentation, form table; the verdict is shown as soon as it is known, then the report
    files go to the session's outputs/ and the inspection into its recording. The CAD
    model is loaded while the part is scanned. Exit 1 when a tolerance fails."""
    out = args.out or f"sessions/demo-{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    ns = argparse.Namespace(rig=DEFAULT_RIG, scene=DEMO_SCENE, out=out, patterns=None, seed=args.seed, fault=[],
                            full_recording=args.full_recording)
    if args.no_inspect:
        return cmd_scan(ns)
    done: dict[str, Any] = {}
    t0 = time.perf_counter()

    def show(report: Any) -> None:
        print(f"verdict   {report.verdict} ({time.perf_counter() - t0:.1f} s after the demo started; report "
              f"files and recording follow)", file=sys.stderr)

    with ThreadPoolExecutor(1, thread_name_prefix="load CAD") as pool:
        part = pool.submit(load_demo_part)  # OpenCASCADE and the model's descriptors while the part is scanned

        def inspect_scan(result: Any, recording: Any) -> None:
            print(f"inspect   {result.session.root} against {DEMO_CAD.name} ({DEMO_TOLERANCES.name})", file=sys.stderr)
            model, tolerances = part.result()
            t1, c1 = time.perf_counter(), time.process_time()
            done["report"], done["timer"] = inspect_verdict_first(result, recording, model, tolerances, args.seed,
                                                                  on_verdict=show)
            done["seconds"], done["cpu"] = time.perf_counter() - t1, time.process_time() - c1

        cmd_scan(ns, inspect_scan)
    rep, outputs = done["report"], Path(out) / "outputs"
    print(rep.table())
    print(f"report    {outputs / 'inspection.html'} (.json, .csv); inspection in the recording under "
          f"world/inspection/ and inspection/")
    stages = ", ".join(f"{k} {v:.1f}" for k, v in rep.timings_s.items())
    print(f"time      inspection {done['seconds']:.1f} s wall, {done['cpu']:.1f} s CPU ({stages} s); demo "
          f"{time.perf_counter() - t0:.1f} s wall")
    return 1 if rep.verdict == "fail" else 0


def _add_full_recording(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--full-recording", action="store_true",
                        help="record every map pixel and point in the Rerun recording (default: the rig's "
                             "[recording] level; 'display' decimates maps and cloud for viewing; frames are "
                             "always lossless)")


def register(sub: Any) -> None:
    s = sub.add_parser("scan", help="scan a part into a session folder (raw frames, cloud PLY, Rerun recording)")
    s.add_argument("--rig", type=Path, default=DEFAULT_RIG, help="rig TOML (default: the simulated bench rig)")
    s.add_argument("--scene", help="simulated rigs: scene TOML or a mesh file (PLY/STL/OBJ)")
    s.add_argument("--out", required=True, help="new session folder")
    s.add_argument("--patterns", help="pattern set TOML (default: the rig's)")
    s.add_argument("--seed", type=int, default=0, help="simulated rigs: noise seed")
    s.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE",
                   help="simulated rigs: inject a fault (drop_frame=K, delay_frame=K, delay_s=S, "
                        "disconnect_after=N, stale_frame=K)")
    s.add_argument("--views", type=int, metavar="N", help="multi-view: N views equally spaced over a turn of the "
                                                         "rig's stage, into one multi-view folder")
    s.add_argument("--angles", metavar="DEG,DEG,...", help="multi-view: the stage angles of the views, in degrees")
    s.add_argument("--no-merge", action="store_true", help="multi-view: capture only (no alignment, merge or mesh)")
    s.add_argument("--stage-axis", metavar="FILE", help="multi-view: the stage-axis calibration (slscan calibrate "
                                                        "--stage-axis) to record and align the views with, in place "
                                                        "of the rig's [stage] calibration")
    s.add_argument("--stage-fault", action="append", default=[], metavar="NAME=MOVE",
                   help="simulated rigs: a stage fault (alarm_at_move=K, disconnect_at_move=K, silent_at_move=K)")
    _add_full_recording(s)
    s.set_defaults(func=cmd_scan)

    d = sub.add_parser("decode", help="regenerate every output of a session from its raw frames")
    d.add_argument("session")
    d.add_argument("--mode", choices=("triangulation", "phase_to_height"), default="triangulation")
    d.add_argument("--stage-axis", metavar="FILE", help="multi-view: align the views again from this stage-axis "
                                                        "calibration (slscan calibrate --stage-axis)")
    _add_full_recording(d)
    d.set_defaults(func=cmd_decode)

    m = sub.add_parser("demo", help="scan the bundled part on the default simulated rig and inspect it against "
                                    "its STEP model")
    m.add_argument("--out", help="session folder (default: sessions/demo-<time>)")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--no-inspect", action="store_true", help="scan only (no inspection against the STEP model)")
    _add_full_recording(m)
    m.set_defaults(func=cmd_demo)
