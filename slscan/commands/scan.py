"""`slscan scan`, `slscan decode` and `slscan demo`: capture a session, regenerate its
outputs from its raw frames, and the bundled demo (scan, then inspect against CAD)."""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanner.config import CONFIG_DIR, DEFAULT_RIG
from scanner.errors import ConfigError, ScannerError
from scanner.stage_timer import StageTimer
from slscan.exit_codes import Exit, for_verdict
from slscan.options import add_json, add_paper, on_paper
from slscan.progress import ProgressLine

if TYPE_CHECKING:
    from scanner.pipeline import ScanResult
    from sim.evaluate import Accuracy

DEMO_SCENE = CONFIG_DIR / "scenes" / "demo.toml"
DEMO_PROGRAM = CONFIG_DIR / "parts" / "demo_part.toml"  # the demo part's program: its CAD, tolerances, face names
# the same part measured all round: the views a turntable turns it through, fused (what one view cannot see)
DEMO_TURNTABLE = (CONFIG_DIR / "parts" / "demo_part_turntable.toml", CONFIG_DIR / "station" / "sim_turntable.toml")


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
    from scanner.session import refuse_used_folder
    from scanner.session_lock import session_lock

    config = RigConfig.load(args.rig)
    patterns = PatternSet.load(args.patterns or config.patterns_path)
    options: dict[str, Any] = {}
    stage_faults = getattr(args, "stage_fault", [])
    truth = None
    if config.driver == "sim":
        options = {"scene": args.scene or DEMO_SCENE, "seed": args.seed}
        truth = _bin_scene(options, config)
        if args.fault:
            options["faults"] = _parse_faults(args.fault)
        if stage_faults:
            options["stage_faults"] = _parse_stage_faults(stage_faults)
    elif args.scene or args.fault or stage_faults:
        raise ConfigError(config.path, "rig.driver", "--scene, --fault and --stage-fault apply to simulated rigs only")
    exposure = None
    if getattr(args, "exposure", None):
        from scanner.exposure import ExposureRequest

        exposure = ExposureRequest.parse(args.exposure, args.exposure_roi)
    elif getattr(args, "exposure_roi", None):
        raise ConfigError("--exposure-roi", args.exposure_roi, "applies to --exposure auto or hdr only")
    if getattr(args, "views", None) is not None or getattr(args, "angles", None) is not None:
        from slscan.commands.views import scan_views

        if getattr(args, "json", False):
            raise ScannerError("--json applies to single-view scans (a multi-view scan writes its views' "
                               "result.json files)")
        return scan_views(args, config, patterns, options, exposure)
    if getattr(args, "stage_axis", None) is not None:
        raise ScannerError("--stage-axis applies to multi-view scans only (--views or --angles)")
    if len(config.cameras) >= 2:  # a binocular rig: every camera captured, points from matching two
        from slscan.commands.scan_binocular import cmd_scan_binocular

        return cmd_scan_binocular(args, config, patterns, options)
    out = Path(args.out)
    refuse_used_folder(out)  # before the rig opens
    print(f"rig {config.name} ({config.driver}, {config.trigger} trigger), {patterns.family} "
          f"{patterns.n_frames} frames -> {out}", file=sys.stderr)
    with open_rig(config, **options) as rig:
        if truth is not None:   # kept with the raw frames, as the simulator's ground truth is
            from sim.bins import BIN_TRUTH_FILE

            rig.extras["session_files"] = [*rig.extras.get("session_files", ()),
                                           lambda root: truth.save(Path(root) / BIN_TRUTH_FILE)]
        result = scan(rig, patterns, out, progress=ProgressLine(), then=then, level=_level(args), exposure=exposure)
    with session_lock(result.session.root, command="slscan scan"):  # accuracy.json: one writer
        report(result, as_json=getattr(args, "json", False))
    if truth is not None and not getattr(args, "json", False):
        print(f"bin truth {result.session.root / BIN_TRUTH_FILE}  ({len(truth.ids)} parts, seed {truth.seed}; "
              f"judge poses with: slscan bench pose --sessions {result.session.root})")
    return Exit.OK


def _level(args: argparse.Namespace) -> str | None:
    """The recording level asked on the command line (None: the rig's or session's own)."""
    return "full" if getattr(args, "full_recording", False) else None


def _bin_scene(options: dict[str, Any], config: Any) -> Any:
    """For `--scene bin:SEED[:N_PARTS]`: the simulated bin put in `options` as the scene,
    and its truth (`sim.bins.BinTruth`) to save in the session; None for other scenes
    (without importing `sim.bins`: its part files load SciPy's spatial module, ~0.3 s)."""
    from sim.scene import BIN_SCENE_PREFIX

    if not str(options["scene"]).startswith(BIN_SCENE_PREFIX):
        return None
    from sim.bins import BinTruth, bin_scene, bin_spec

    spec = bin_spec(str(options["scene"]))
    if spec is None:
        return None
    seed, parts = spec
    b = bin_scene(parts, seed=seed)
    options["scene"] = b.scene
    return BinTruth.of(b, config.nominal_model().world_from_cam)


def report(result: Any, *, as_json: bool = False) -> None:
    """Print what a processed session holds, and its accuracy when ground truth is there
    (`as_json`: one JSON document, `result_record`)."""
    if as_json:
        print(json.dumps(result_record(result), default=str))
        return
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
    if s.manifest.exposure is not None:
        print(f"exposure  {s.manifest.exposure.reason}")
    print(f"timings   decode {t['decode'] * 1e3:.0f} ms, reconstruct {t['reconstruct'] * 1e3:.0f} ms")
    print("checks    " + "\n          ".join(c.line() for c in result.checks))
    if s.integrity != "sha256":
        print(f"warning   frame integrity {s.integrity}", file=sys.stderr)
    acc = sim_accuracy(result)
    if acc is not None:
        print(f"accuracy  {acc.summary()}")


def result_record(result: Any) -> dict[str, Any]:
    """What `slscan scan/decode/import --json` print: the session, its outputs, the checks that
    judged the decode and the accuracy against the simulator's truth (None without it)."""
    s, decoded = result.session, result.decoded
    acc = sim_accuracy(result)
    return {"status": "ok", "session": str(s.root), "session_id": s.id,
            "cloud": str(result.cloud_path) if result.cloud is not None else None,
            "maps": str(s.outputs / "maps.npz"), "points": len(result.cloud) if result.cloud is not None else 0,
            "valid_fraction": float(decoded.valid.mean()),
            "rejected_fraction": {k: v / decoded.valid.size for k, v in decoded.rejected().items()},
            "recording": str(s.recording_path) if s.recording_path.exists() else None,
            "exposure": s.manifest.exposure.reason if s.manifest.exposure is not None else None,
            "frame_integrity": s.integrity,
            "timings_s": result.timings_s, "checks": [c.as_dict() for c in result.checks],
            "accuracy": acc.as_dict() if acc is not None else None}


def sim_accuracy(result: ScanResult) -> Accuracy | None:
    """Accuracy against the simulator's ground truth, if the session has it."""
    from scanner.reconstruct import Triangulator
    from scanner.session import write_json

    if result.session.manifest.imported is not None:
        return None  # another tool's frames carry no simulator truth (and the simulator takes ~0.3 s to import)
    from sim.evaluate import GROUND_TRUTH_FILE, Truth, evaluate
    from sim.render import SensorModel

    path = result.session.root / GROUND_TRUTH_FILE
    if not path.exists() or len(result.decoded.maps) != 1 or result.cloud is None:
        return None

    sensor = SensorModel.of(result.session.manifest.recorded_rig.sensor)  # none stated: rendered with the defaults
    acc = evaluate(result.decoded, result.cloud, Truth.load(path), sensor, Triangulator(result.session.rig_model()))
    write_json(result.session.outputs / "accuracy.json", acc.as_dict())
    return acc


def cmd_decode(args: argparse.Namespace) -> int:
    from scanner.multiview import is_multiview
    from scanner.pipeline import reprocess
    from scanner.session import Session
    from scanner.session_lock import session_lock

    if is_multiview(args.session):
        from slscan.commands.views import decode_views

        return decode_views(args)
    if args.stage_axis is not None:
        raise ScannerError(f"{args.session}: --stage-axis applies to multi-view sessions only")
    if args.recover:
        _recover(args)
    elif args.rig is not None or args.patterns is not None:
        raise ScannerError("--rig and --patterns apply to `slscan decode --recover` only")
    with session_lock(args.session, command="slscan decode"):  # the outputs and accuracy.json: one writer
        session = Session.open(args.session)
        from scanner.binocular_session import is_binocular

        if is_binocular(session):
            from slscan.commands.scan_binocular import cmd_decode_binocular

            return cmd_decode_binocular(args, session)
        model = rig_model_file(Path(args.rig_model), session.rig_model()) if args.rig_model else None
        result = reprocess(session, ProgressLine(), mode=args.mode, level=_level(args), rig_model=model,
                           rig_model_source=args.rig_model)
        report(result, as_json=args.json)
    return Exit.OK


def rig_model_file(path: Path, recorded: Any) -> Any:
    """The rig model in `path`, given on purpose instead of a session's (`recorded`, whose
    image sizes it must fit): a JSON rig model as a manifest holds it (`cam_from_proj` at its
    top), our calibration.json, or another tool's calibration (scanner/foreign_calibration.py)."""
    import json

    from scanner.foreign_calibration import read_calibration
    from scanner.geometry import RigModel

    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ScannerError(f"{path}: unreadable rig model: {exc}") from None
        if isinstance(data, dict) and "cam_from_proj" in data:
            model = RigModel.from_dict(data, str(path))
            if model.camera.size != recorded.camera.size or model.projector.size != recorded.projector.size:
                raise ScannerError(f"{path}: the rig model is for a {model.camera.size} camera and a "
                                   f"{model.projector.size} projector; the session's are {recorded.camera.size} and "
                                   f"{recorded.projector.size}")
            return model
    return read_calibration(path, recorded.camera.size, recorded.projector.size)[0]


def _recover(args: argparse.Namespace) -> None:
    """`decode --recover`: the manifest rebuilt from capture.json and frames.jsonl (or the
    given rig and patterns, said to be assumed), each frame checked (`scanner.session_recovery`)."""
    from scanner.patterns import PatternSet
    from scanner.rig import RigConfig
    from scanner.session_recovery import recover_manifest

    rig = RigConfig.load(args.rig) if args.rig is not None else None
    patterns = PatternSet.load(args.patterns) if args.patterns is not None else None
    path = recover_manifest(args.session, rig=rig, patterns=patterns)
    print(f"recovered {path} from the session's own records; every frame checked", file=sys.stderr)


def load_demo_part() -> tuple[Any, Any, Any]:
    """The demo part's CAD model (registration target prepared), its tolerances and its
    part program (`DEMO_PROGRAM`: the one source of its tolerances and face names)."""
    from inspection.inspect_scan import prepare
    from slscan.commands.inspect import _load_model, load_tolerance_source
    from slscan.station.program import load_program

    model = _load_model(str(load_program(DEMO_PROGRAM).cad_path), "mm")
    prepare(model)  # the registration target, made once per model
    tolerances, program = load_tolerance_source(DEMO_PROGRAM, {f.label: f.type for f in model.faces})
    return model, tolerances, program


def inspect_verdict_first(result: Any, recording: Any, model: Any, tolerances: Any, *, seed: int = 0,
                          prior: Any = None, on_verdict: Callable[[Any], None] | None = None,
                          program: Any = None, pdf: bool = True,
                          progress: Callable[[str, int, int], None] | None = None) -> tuple[Any, StageTimer]:
    """Inspect a processed scan against `model`, the verdict first: `on_verdict(report)`
    runs as soon as it is known (a report of the faces the tolerances ask for,
    `inspection.inspect_scan.inspect`); then the work that does not change it, the other
    faces' figures, the report files
    (JSON, CSV, HTML with the deviation map) and the inspection in `recording` (None: not
    recorded). The session is complete when this returns: until then outputs/ has no
    inspection.json and the recording is still `recording.rrd.part`. `prior`: the previous
    part's registration (warm start); `program` names the part in the report's header, `pdf`
    prints inspection.pdf; `progress(stage, done, total)` hears the inspection's stages and
    faces. Returns the report and the time of each stage."""
    from inspection.inspect_scan import InspectionSettings, inspect
    from inspection.measured_cloud import from_organised, load_session
    from inspection.registration import RegistrationSettings
    from slscan.commands.inspect import write_report_files
    from slscan.measurement_model import session_uncertainty

    timer = StageTimer()
    with timer.stage("load_cloud"):  # the cloud in memory is the one in cloud.ply (same points, normals, pixels)
        scan = (from_organised(result.cloud, str(result.session.root)) if result.cloud is not None
                else load_session(result.session.root))
    with timer.stage("inspect"):
        # the decoder's noise model and calibration, from the decode the scan was made of
        uncertainty = session_uncertainty(result.session, result.decoded)(scan.camera_pixels())
        report = inspect(scan, model, tolerances,
                         settings=InspectionSettings(registration=RegistrationSettings(seed=seed)),
                         prior=prior, uncertainty=uncertainty, on_verdict=on_verdict, progress=progress)
    with timer.stage("report_files"):
        report = write_report_files(report, scan, result.session.outputs, result.session.root, program=program, pdf=pdf)
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
    model is loaded while the part is scanned. Exit by the verdict (`for_verdict`: 1 when a
    characteristic is non-conforming, 4 when one is not measured or uncertain)."""
    from scanner.session import refuse_used_folder

    out = args.out or f"sessions/demo-{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    refuse_used_folder(Path(out))  # before the CAD and the libraries load (seconds)
    ns = argparse.Namespace(rig=DEFAULT_RIG, scene=DEMO_SCENE, out=out, patterns=None, seed=args.seed, fault=[],
                            full_recording=args.full_recording, json=args.json and args.no_inspect)
    if args.no_inspect:
        return cmd_scan(ns)
    done: dict[str, Any] = {}
    t0 = time.perf_counter()

    def show(report: Any) -> None:
        print(f"verdict   {report.verdict} ({time.perf_counter() - t0:.1f} s after the demo started; report "
              f"files and recording follow)", file=sys.stderr)

    import open3d  # noqa: F401  here, before the CAD thread starts: open3d's __init__ iterates sys.modules,
    # which an import on another thread changes under it ("dictionary changed size during iteration")
    with ThreadPoolExecutor(1, thread_name_prefix="load CAD") as pool:
        part = pool.submit(load_demo_part)  # OpenCASCADE and the model's descriptors while the part is scanned

        def inspect_scan(result: Any, recording: Any) -> None:
            print(f"inspect   {result.session.root} against the part program {DEMO_PROGRAM}", file=sys.stderr)
            model, tolerances, program = part.result()
            t1, c1 = time.perf_counter(), time.process_time()
            with on_paper(args.paper):
                done["report"], done["timer"] = inspect_verdict_first(result, recording, model, tolerances,
                                                                      seed=args.seed, on_verdict=show, program=program,
                                                                      progress=ProgressLine())
            done["seconds"], done["cpu"] = time.perf_counter() - t1, time.process_time() - c1

        with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
            cmd_scan(ns, inspect_scan)  # the scan's own lines: on stderr beside the JSON
    rep, outputs = done["report"], Path(out) / "outputs"
    if args.json:
        from inspection.tolerances import DECISION_STATUS

        print(json.dumps({"status": DECISION_STATUS[rep.verdict], "verdict": rep.verdict, "session": str(out),
                          "conclusion": demo_conclusion(rep, Path(out)), "report": str(outputs / "inspection.html"),
                          "inspection": rep.as_dict()}, default=str))
        return for_verdict(rep.verdict)
    print(rep.table())
    print(f"report    {outputs / 'inspection.html'} (.json, .csv, .pdf); inspection in the recording under "
          f"world/inspection/ and inspection/")
    stages = ", ".join(f"{k} {v:.1f}" for k, v in rep.timings_s.items())
    print(f"time      inspection {done['seconds']:.1f} s wall, {done['cpu']:.1f} s CPU ({stages} s); demo "
          f"{time.perf_counter() - t0:.1f} s wall")
    print(demo_conclusion(rep, Path(out)))
    return for_verdict(rep.verdict)


def _shown(path: Path) -> str:
    """A path as the user would type it: relative to the working folder when inside it."""
    import os

    rel = os.path.relpath(path)
    return rel if not rel.startswith("..") else str(path)


def _value(e: Any) -> str:
    if e is None or (e.value is None and e.limit is None):
        return "not measured"
    return f"< {e.limit:.4f} mm" if e.value is None else f"{e.value:.4f} ± {e.U:.4f} mm"


def demo_conclusion(report: Any, session: Path) -> str:
    """The demo's last line: the verdict, why, and the command to run next."""
    from inspection.figures import limited_by
    from inspection.tolerances import CONFORMING, NON_CONFORMING, NOT_MEASURED, UNCERTAIN

    def items(verdict: str) -> list[tuple[Any, str, float]]:
        return [(row, key, tol) for row in report.faces for key, (tol, v) in row.verdicts.items() if v == verdict]

    def named(row: Any, key: str) -> str:
        return f"{row.title} {key.removesuffix('_mm').replace('_ls', ' (least squares)')}"

    def figure(row: Any, key: str) -> Any:
        return row.form.figure(limited_by(key).name) if row.form.status == "ok" else None

    html = _shown(session / "outputs" / "inspection.html")
    verdict = report.verdict
    if verdict == NON_CONFORMING:
        why = "; ".join(f"{named(r, k)} {_value(figure(r, k))} > {t:.3f} mm" for r, k, t in items(NON_CONFORMING))
        step = f"open {html} (the views show where)"
    elif verdict == NOT_MEASURED:
        why = "; ".join(f"{named(r, k)} not measured: {r.form.points} points from the demo's one view "
                        f"({r.form.note or r.form.status})" for r, k, _ in items(NOT_MEASURED))
        program, station = (_shown(p) for p in DEMO_TURNTABLE)
        why += "; the turntable program measures the part all round"
        step = f"slscan station {program} --config {station} --auto --parts 1"
    elif verdict == UNCERTAIN:
        why = "; ".join(f"{named(r, k)} {_value(figure(r, k))} is within its U of {t:.3f} mm (ISO 14253-1)"
                        for r, k, t in items(UNCERTAIN))
        step = f"re-measure: slscan demo --seed 1 --out {_shown(session)}-2"
    elif verdict == CONFORMING:
        why = f"all {len(items(CONFORMING))} characteristics within tolerance, their uncertainty allowed for"
        step = f"slscan review {_shown(session)} (or open {html})"
    else:
        why, step = "no tolerances to judge", f"open {html}"
    return f"RESULT    {verdict.upper()}: {why}. Next: {step}"


def _add_full_recording(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--full-recording", action="store_true",
                        help="record every map pixel and point in the Rerun recording (default: the rig's "
                             "[recording] level; 'display' decimates maps and cloud for viewing; frames are "
                             "always lossless)")


def register(sub: Any) -> None:
    s = sub.add_parser("scan")
    s.add_argument("--rig", type=Path, default=DEFAULT_RIG, help="rig TOML (default: the simulated bench rig)")
    s.add_argument("--scene", help="simulated rigs: scene TOML, a mesh file (PLY/STL/OBJ), or bin:SEED[:N_PARTS] for a "
                                   "bin of thin parts (default 5 + SEED %% 16 parts) saved with its true poses, "
                                   "instance ids and occlusion (bin_truth.json)")
    s.add_argument("--out", required=True, help="new session folder")
    s.add_argument("--patterns", help="pattern set TOML (default: the rig's)")
    s.add_argument("--seed", type=int, default=0, help="simulated rigs: noise seed")
    s.add_argument("--exposure", help="auto (one exposure chosen from a white/black/fringe pre-capture), hdr "
                                      "(several chosen, fused per pixel), or exposures in seconds, e.g. "
                                      "0.004,0.016,0.064 (default: the rig's exposure_s)")
    s.add_argument("--exposure-roi", metavar="X,Y,W,H", help="with --exposure auto/hdr: judge only this camera "
                                                              "rectangle (default: every lit pixel)")
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
    add_json(s)
    s.set_defaults(func=cmd_scan)

    d = sub.add_parser("decode")
    d.add_argument("session", help="session or multi-view folder (its raw frames and manifest)")
    d.add_argument("--mode", choices=("triangulation", "phase_to_height"), default="triangulation",
                   help="reconstruction: triangulation with the rig model (default) or Eq. 17 phase-to-height "
                        "for rigs calibrated with the reference-plane model")
    d.add_argument("--stage-axis", metavar="FILE", help="multi-view: align the views again from this stage-axis "
                                                        "calibration (slscan calibrate --stage-axis)")
    d.add_argument("--rig-model", metavar="FILE", help="decode with this rig model instead of the one recorded at "
                                                       "capture, on purpose: a JSON rig model (as a manifest holds "
                                                       "it) or a calibration file")
    d.add_argument("--recover", action="store_true",
                   help="a session whose capture finished but whose manifest was not written (a killed scan): "
                        "rebuild the manifest from its capture.json and frames.jsonl, every frame checked, then "
                        "decode it")
    d.add_argument("--rig", type=Path, help="--recover of a session without capture.json: the rig it was captured "
                                            "with (recorded in the manifest as assumed)")
    d.add_argument("--patterns", type=Path, help="--recover without capture.json: the pattern set, if not the rig's")
    _add_full_recording(d)
    add_json(d)
    d.set_defaults(func=cmd_decode)

    m = sub.add_parser("demo")
    m.add_argument("--out", help="session folder (default: sessions/demo-<time>)")
    m.add_argument("--seed", type=int, default=0, help="simulated rig: noise seed (default 0)")
    m.add_argument("--no-inspect", action="store_true", help="scan only (no inspection against the STEP model)")
    add_paper(m)
    _add_full_recording(m)
    add_json(m)
    m.set_defaults(func=cmd_demo)
