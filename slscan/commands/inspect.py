"""`slscan cad`, `slscan register` and `slscan inspect`: inspection against CAD (issue 5).

    slscan cad FILE [--json] [--sample N]            faces by STEP id and surface type, counts per type;
                                                     --sample: time to sample N labelled points
    slscan register SOURCE TARGET [--json]           4x4 transform taking SOURCE onto TARGET, fitness, RMSE,
                                                     pose U; exit 1 when the evidence does not prove the
                                                     pose (another fits as well, a motion left free);
                                                     a cloud or session TARGET is another view of the part
                                                     (partial overlap, fitness on the overlap, --overlap)
    slscan inspect SESSION|MULTIVIEW|CLOUD [--cad FILE] --tolerances PROGRAM|FILE
                                                     register, segment by CAD face, per-face form table

`--json` prints JSON alone on stdout (whatever the libraries print goes to stderr).
`inspect` writes inspection.json/.csv/.html beside the data (a session's outputs/, or the
cloud's folder, or --out) and, for a session, outputs/inspection.rrd: a Rerun recording
with the session's recording id, so the viewer shows it together with recording.rrd
(`rerun recording.rrd outputs/inspection.rrd`). OpenCASCADE and Open3D are imported
inside the command functions.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from scanner.errors import ConfigError
from slscan.exit_codes import Exit, for_verdict
from slscan.options import COARSE_METHODS, add_paper, coarse_method, on_paper, plain_text_arg

CAD_UNITS = ("mm", "cm", "m", "in")


def _load_model(path: str, unit: str) -> Any:
    from inspection.cad import load_cad
    from slscan.progress import ProgressLine

    return load_cad(path, mesh_unit=unit, progress=ProgressLine())


def cmd_cad(args: argparse.Namespace) -> int:
    import time

    t0 = time.perf_counter()
    model = _load_model(args.file, args.cad_unit)
    load_s = time.perf_counter() - t0
    if args.sample:
        bench = sample_benchmark(model, args.sample, args.repeats, load_s)
        print(json.dumps(bench) if args.json else _sample_text(bench))
        return Exit.OK
    if args.json:
        s = model.summary()
        print(json.dumps({"path": s["path"], "unit": s["unit"], "faces": s["faces"], "counts": s["counts"]}))
        return Exit.OK
    print(f"{model.path}: {len(model)} faces, unit {model.unit}, {model.kind}")
    for f in model.faces:
        params = ", ".join(f"{k} {_short(v)}" for k, v in f.params().items())
        print(f"  {f.label:>8}  {f.type:<9} {f.area_mm2:12.3f} mm^2  {params}")
    print("counts: " + ", ".join(f"{n} {t}" for t, n in model.counts.items()))
    for line in model.skipped:
        print(f"  skipped {line}")
    return Exit.OK


def sample_benchmark(model: Any, n_points: int, repeats: int, load_s: float) -> dict[str, Any]:
    """Time to sample about `n_points` labelled points on `model` (after one warm-up run,
    which builds the faces' trimming classifiers): wall and CPU seconds of each of
    `repeats` runs, the machine's load average, the points drawn."""
    import os
    import time

    from inspection.sampling import sample_model, spacing_for

    spacing = spacing_for(model, n_points)
    t0, c0 = time.perf_counter(), time.process_time()
    sample_model(model, spacing, seed=0)
    warm = (time.perf_counter() - t0, time.process_time() - c0)
    runs = []
    for k in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        cloud = sample_model(model, spacing, seed=k + 1)
        runs.append((time.perf_counter() - t0, time.process_time() - c0, len(cloud)))
    wall, cpu, points = (list(x) for x in zip(*runs))
    return {"path": str(model.path), "faces": len(model), "counts": model.counts, "load_s": load_s,
            "spacing_mm": spacing, "points": points, "warm_up_wall_s": warm[0], "warm_up_cpu_s": warm[1],
            "wall_s": wall, "cpu_s": cpu, "median_wall_s": float(sorted(wall)[len(wall) // 2]),
            "median_cpu_s": float(sorted(cpu)[len(cpu) // 2]), "load_average": os.getloadavg()}


def _sample_text(b: dict[str, Any]) -> str:
    return (f"{b['path']}: {b['faces']} faces ({', '.join(f'{n} {t}' for t, n in b['counts'].items())}), "
            f"loaded in {b['load_s']:.2f} s\n"
            f"sampling ~{b['points'][0]} labelled points (spacing {b['spacing_mm']:.4g} mm): median "
            f"{b['median_wall_s']:.3f} s wall, {b['median_cpu_s']:.3f} s CPU over {len(b['wall_s'])} runs "
            f"(runs {', '.join(f'{x:.3f}' for x in b['wall_s'])} s; first run with classifier set-up "
            f"{b['warm_up_wall_s']:.2f} s); load average {', '.join(f'{x:.2f}' for x in b['load_average'])}")


def _short(v: Any) -> str:
    if isinstance(v, list):
        return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"
    return f"{v:.6g}" if isinstance(v, float) else str(v)


def _is_model(path: str) -> bool:
    """Whether `path` is a CAD model or a mesh (a registration target), not a cloud or a session."""
    from inspection.cad import MESH_SUFFIXES, STEP_SUFFIXES

    suffix = Path(path).suffix.lower()
    return suffix in STEP_SUFFIXES or (suffix in MESH_SUFFIXES and _has_triangles(path))


def _has_triangles(path: str) -> bool:
    from scanner.mesh_files import triangle_count

    return triangle_count(path) > 0


def cmd_register(args: argparse.Namespace) -> int:
    if not args.json:
        return _register(args)
    out: dict[str, Any] = {}
    code = _register(args, out)
    print(json.dumps(out))
    return code


def registration_record(reg: Any) -> dict[str, Any]:
    """What `register --json` prints for a CAD target: the pose only when it is proven
    (`transform` null otherwise), what the evidence says, the alternatives and free motions;
    the pose's U only when every motion is bounded (`pose_u_note` names the others)."""
    from inspection.pose_uncertainty import PoseUncertainty

    d = reg.as_dict()
    pose = PoseUncertainty(reg.covariance, unbounded=reg.unbounded)
    u = pose.as_dict()
    return {"status": reg.status, "transform": reg.transform.tolist() if reg.proven else None,
            "best_unproven": None if reg.proven else reg.transform.tolist(), "reason": reg.reason,
            "fitness": reg.fitness, "rmse": reg.rmse_mm, "ambiguous": reg.ambiguous, "method": reg.method,
            "alternatives": d["alternatives"], "rejected_alternatives": d["rejected_alternatives"],
            "free_motions": d["free_motions"], "rotation_u_deg": u.get("rotation_u_deg"),
            "translation_u_mm": u.get("translation_u_mm"), "pose_covariance": u.get("pose_covariance"),
            "pose_centre_mm": u.get("pose_centre_mm"), "correlation_inflation": u.get("correlation_inflation"),
            "pose_u_note": pose.note() or None,
            "timings_s": reg.timings_s}


def registration_exit(reg: Any) -> int:
    """Exit.OK for a proven pose, Exit.FAILED for one the evidence leaves ambiguous."""
    return Exit.OK if reg.proven else Exit.FAILED


def _register(args: argparse.Namespace, json_out: dict[str, Any] | None = None) -> int:
    import numpy as np

    from inspection.measured_cloud import isolate_part, load_source
    from inspection.registration import RegistrationSettings, register

    blur = {} if args.camera_blur_px is None else {"camera_blur_px": args.camera_blur_px}
    settings = RegistrationSettings(descriptors=tuple(args.descriptors.split(",")), coarse=args.coarse, seed=args.seed,
                                    **blur)
    if not _is_model(args.target):
        return _register_views(args, settings, json_out)
    from inspection.registration import ModelTarget

    target = ModelTarget.from_cad(_load_model(args.target, args.cad_unit))
    from scanner.native_threads import native_threads

    scan = load_source(args.source)
    with native_threads(1):  # thin, memory-bound products: a second BLAS thread only spins
        if not args.no_isolate:
            scan = isolate_part(scan, target.diagonal_mm)
        reg = register(scan, target, settings)
    if json_out is not None:
        json_out.update(registration_record(reg), camera_blur_px=settings.camera_blur_px,
                        camera_blur="given" if blur else "assumed")
        return registration_exit(reg)
    if not reg.proven:
        print(f"{args.source}: not registered: {reg.reason}", file=sys.stderr)
        return registration_exit(reg)
    with np.printoptions(precision=6, suppress=True, floatmode="fixed"):
        print(f"transform taking {args.source} onto {args.target} (mm):")
        print(reg.transform)
    u = reg.covariance.bounds() if reg.covariance is not None else None
    print(f"fitness {reg.fitness:.4f} (points within {reg.inlier_mm:.3g} mm), RMSE {reg.rmse_mm:.4f} mm, "
          f"{reg.method}, {reg.timings_s.get('total', 0):.2f} s"
          + (f"; pose U {u[0]:.4f} deg, {u[1]:.4f} mm (95 %)" if u else "")
          + "".join(f"; free: {m.describe()}" for m in reg.free)
          + ("" if blur else f"; camera blur {settings.camera_blur_px:g} px assumed"))
    return registration_exit(reg)


def _register_views(args: argparse.Namespace, settings: Any, json_out: dict[str, Any] | None = None) -> int:
    """A cloud (or session) target is another view of the part: partial overlap, judged on
    the overlap (`inspection.views.pair_registration`). The pose only when its evidence
    proves it (exit 0); otherwise why not, the best pose and the alternatives (exit 1)."""
    from inspection.measured_cloud import load_source
    from inspection.views.pair_registration import weigh_view_pair, without_support

    scan, target = load_source(args.source), load_source(args.target)
    if not args.no_isolate:
        scan, target = without_support(scan, args.seed), without_support(target, args.seed)
    pair = weigh_view_pair(scan, target, args.overlap, settings)
    if json_out is not None:
        d = pair.as_dict()
        json_out.update({**d, "status": "ok" if pair.proven else "refused",
                         "transform": d["transform"] if pair.proven else None,
                         "best_unproven": None if pair.proven else d["transform"]})
    else:
        print(pair.text(args.source, args.target), file=sys.stdout if pair.proven else sys.stderr)
    return Exit.OK if pair.proven else Exit.FAILED


def is_program(path: str | Path) -> bool:
    """Whether a TOML is a part program (it has a [program] table); False for anything
    unreadable, which the tolerance loader then names."""
    import tomllib

    try:
        return "program" in tomllib.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


def load_tolerance_source(path: str | Path, labels: dict[str, str]) -> tuple[Any, Any]:
    """(Tolerances, PartProgram or None) from `--tolerances`: a part program (a TOML with a
    [program] table, `config/parts/*.toml`: the one source of a part's tolerances and face
    names) or a tolerance file (`inspection.tolerances`, for a model without a program).
    `labels`: the model's faces (label -> surface type), which every face named must be."""
    from inspection.tolerances import load_tolerances

    if not is_program(path):
        return load_tolerances(path, labels), None
    from slscan.station.program import load_program, program_tolerances

    program = load_program(path, faces=lambda _: labels)
    return program_tolerances(program), program


def report_header(source: Path, program: Any, operator: str | None, serial: str | None) -> Any:
    """The report's header: the part and program (with the program file's SHA-256), the
    serial (default: the session id), the operator (default: the login name), now (UTC),
    and for a session (or a multi-view folder: its first view's) its rig and the
    calibration it used (`station.calib.rig_calibration`)."""
    import datetime as dt
    import getpass

    from inspection.report_header import ReportHeader, file_sha256
    from scanner import __version__

    rig = cal_id = cal_date = ""
    session_id = ""
    if source.is_dir():
        from scanner.multiview import MultiViewSession, is_multiview
        from scanner.rig import RigConfig
        from scanner.session import Session
        from slscan.station.calib import rig_calibration

        multiview = MultiViewSession.open(source) if is_multiview(source) else None
        session = multiview.views[0].session if multiview is not None else Session.open(source)  # the views' rig
        session_id = multiview.id if multiview is not None else session.id
        rig = session.manifest.recorded_rig.rig.name or ""
        rig_path, problem = recorded_rig(session)
        if rig_path is not None:
            info = rig_calibration(RigConfig.load(rig_path))
            cal_id, cal_date = info.id or f"none ({info.problem})", str(info.date or "undated (factory geometry)")
            rig = f"{rig} ({rig_path})"
        else:
            cal_id = f"not known: {problem}"
    return ReportHeader(
        part=f"{program.name} — {program.description}" if program is not None and program.description
        else (program.name if program is not None else ""),
        serial=serial or session_id, program=f"{program.path} (version {program.version})" if program else "",
        program_sha256=file_sha256(program.path) if program is not None else "",
        operator=operator if operator is not None else getpass.getuser(),
        date=dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S"), rig=rig, calibration_id=cal_id,
        calibration_date=cal_date, software_version=f"slscan {__version__}")


def recorded_rig(session: Any) -> tuple[Path | None, str]:
    """The rig TOML a session was captured with, found by its provenance (absolute path, then
    relative to the session, each only with the recorded SHA-256; and its calibration file
    likewise), or by the absolute `rig_config_path` of a session recorded before provenance:
    (path or None, why not, for people)."""
    from scanner.session import find_recorded

    record = session.manifest.provenance
    if record is None:
        path = Path(session.manifest.rig_config_path or "")
        if path.is_absolute() and path.is_file():
            return path, ""
        return None, f"the session's rig file {path} is not found (recorded before sessions kept their provenance)"
    rig, found = find_recorded(record.rig, session.root)
    if rig is None:
        return None, f"the session's rig file {found}"
    if record.calibration is not None:
        calibration, found = find_recorded(record.calibration, session.root)
        if calibration is None:
            return None, f"the session's calibration file {found}"
    return rig, ""


def write_report_files(report: Any, scan: Any, folder: Path, source: Path, *, program: Any = None,
                       operator: str | None = None, serial: str | None = None, pdf: bool = True) -> Any:
    """The report with its header (`report_header`) written to `folder` (JSON, CSV, HTML with
    the deviation map, PDF when `pdf`) with the per-point deviations `slscan export
    --deviations` reads; returns the report with its header."""
    from dataclasses import replace

    from inspection.point_deviations import write_point_deviations
    from inspection.report import deviation_image, png

    report = replace(report, header=report_header(source, program, operator, serial))
    report.write(folder, deviation_png=png(deviation_image(report, scan)), pdf=pdf)
    write_point_deviations(folder, scan, report)
    return report


def inspect_source(source: str | Path, cad: str | Path | None, *, tolerances: str | Path | None = None,
                   out: str | Path | None = None, cad_unit: str = "mm", seed: int = 0,
                   recording: Any = None, operator: str | None = None, serial: str | None = None,
                   pdf: bool = True) -> Any:
    """Inspect a session folder, a multi-view folder (its merged cloud) or a cloud file
    against a CAD file (None: the part program's, when `tolerances` is one); write the
    report files (and, for a session without a `recording` given, outputs/inspection.rrd);
    return the report. `slscan demo` calls this after its scan with the demo part's program.
    A session or multi-view folder is held (`session_lock`) while its outputs are written."""
    from scanner.session_lock import session_lock

    if not Path(source).is_dir():
        return _inspect_source(source, cad, tolerances, out=out, cad_unit=cad_unit, seed=seed, recording=recording,
                               operator=operator, serial=serial, pdf=pdf)
    with session_lock(source, command="slscan inspect"):
        return _inspect_source(source, cad, tolerances, out=out, cad_unit=cad_unit, seed=seed, recording=recording,
                               operator=operator, serial=serial, pdf=pdf)


def _inspect_source(source: str | Path, cad: str | Path | None, tolerances: str | Path | None, *,
                    out: str | Path | None,
                    cad_unit: str, seed: int, recording: Any, operator: str | None, serial: str | None,
                    pdf: bool) -> Any:
    from dataclasses import replace

    from inspection.inspect_scan import InspectionSettings, inspect
    from inspection.measured_cloud import load_source
    from inspection.registration import RegistrationSettings
    from scanner.multiview import MultiViewSession, is_multiview
    from scanner.session_lock import output_dir

    program = None
    if cad is None:
        if tolerances is None or not is_program(tolerances):
            raise ConfigError("--cad", "", "give --cad FILE, or a part program as --tolerances (it names its CAD)")
        from slscan.station.program import load_program

        cad = load_program(tolerances).cad_path
    model = _load_model(str(cad), cad_unit)
    tol = None
    if tolerances:
        tol, program = load_tolerance_source(tolerances, {f.label: f.type for f in model.faces})
    multiview = MultiViewSession.open(source) if is_multiview(source) else None
    if multiview is not None:  # the whole part: the views' merged cloud
        from inspection.views.whole import load_merged

        scan = load_merged(multiview)
    else:
        scan = load_source(source)
    source = Path(source)
    folder = Path(out) if out else (output_dir(source, "outputs") if source.is_dir() else source.parent)
    settings = InspectionSettings(registration=RegistrationSettings(seed=seed))
    if program is not None:  # the program's edge margin (a narrow face, e.g. a chamfer, needs less than the default)
        settings = replace(settings, form=program.form_settings())
    own = None
    uncertainty = None
    if source.is_dir():
        from scanner.session import Session
        from slscan.measurement_model import session_uncertainty

        # a multi-view folder: its first view's rig, whose world frame is the part frame at stage 0;
        # the merged cloud has no one camera's pixels, so its figures estimate their noise from the data
        session = multiview.views[0].session if multiview is not None else Session.open(source)
        if multiview is None:
            uncertainty = session_uncertainty(session)(scan.camera_pixels())
        if recording is None:
            from scanner.session_recording import SessionRecording

            folder.mkdir(parents=True, exist_ok=True)
            own = recording = SessionRecording(folder / "inspection.rrd", multiview.id if multiview is not None
                                               else session.id, send_blueprint=False)
    try:
        if own is not None:  # the session's rig: its world frame is the recording's `world`
            own.log_rig(session.rig_model())
        from slscan.progress import ProgressLine

        report = inspect(scan, model, tol, settings=settings, recording=recording, uncertainty=uncertainty,
                         progress=ProgressLine())
    finally:
        if own is not None:
            own.close()
    return write_report_files(report, scan, folder, source, program=program, operator=operator, serial=serial, pdf=pdf)


def cmd_inspect(args: argparse.Namespace) -> int:
    with on_paper(args.paper):
        report = inspect_source(args.source, args.cad, tolerances=args.tolerances, out=args.out, cad_unit=args.cad_unit,
                                seed=args.seed, operator=args.operator, serial=args.serial, pdf=not args.no_pdf)
    if args.json:
        print(json.dumps(report.as_dict(), default=str))
    else:
        print(report.table())
        folder = Path(args.out) if args.out else (Path(args.source) / "outputs" if Path(args.source).is_dir()
                                                  else Path(args.source).parent)
        print(f"report    {folder / 'inspection.html'} (.json, .csv{'' if args.no_pdf else ', .pdf'})", file=sys.stderr)
    return for_verdict(report.verdict)


def register(sub: Any) -> None:
    c = sub.add_parser("cad")
    c.add_argument("file", help="STEP (.step/.stp) or mesh (.stl/.ply/.obj)")
    c.add_argument("--cad-unit", choices=CAD_UNITS, default="mm", help="unit of a mesh file (STEP files say theirs)")
    c.add_argument("--json", action="store_true", help="print {faces: [...], counts: {...}}")
    c.add_argument("--sample", type=int, metavar="N", help="benchmark: time sampling N labelled points")
    c.add_argument("--repeats", type=int, default=5, help="with --sample: timed runs after a warm-up")
    c.set_defaults(func=cmd_cad)

    r = sub.add_parser("register")
    r.add_argument("source", help="cloud (PLY/PCD/XYZ) or session folder")
    r.add_argument("target", help="STEP, mesh (STL/PLY/OBJ with triangles), or a cloud or session: another view")
    r.add_argument("--cad-unit", choices=CAD_UNITS, default="mm", help="unit of a mesh target")
    r.add_argument("--coarse", type=coarse_method, choices=COARSE_METHODS, default="sac-ia",
                   help="coarse method (default sac-ia)")
    r.add_argument("--descriptors", default="fpfh,shot", help="fpfh, shot or fpfh,shot (multivariate)")
    r.add_argument("--no-isolate", action="store_true", help="keep every source point (no table removal)")
    r.add_argument("--seed", type=int, default=0, help="random seed of the coarse search (default 0)")
    r.add_argument("--camera-blur-px", type=float, metavar="SIGMA",
                   help="the camera's blur (Gaussian sigma, px), for how far a face's points near its outline may "
                        "read off (default: 1 px, assumed)")
    r.add_argument("--overlap", type=float, metavar="SHARE", help="cloud targets: the share of SOURCE the target "
                                                                   "also saw (default: estimated)")
    r.add_argument("--json", action="store_true", help="print {status, transform (null unless proven), fitness, "
                                                        "rmse, alternatives, free_motions, pose U}")
    r.set_defaults(func=cmd_register)

    i = sub.add_parser("inspect")
    i.add_argument("source", help="session folder or cloud file (PLY/PCD/XYZ, mm, camera frame)")
    i.add_argument("--cad", help="STEP or mesh of the part (default: the one --tolerances PROGRAM names)")
    i.add_argument("--tolerances", help="the part program (config/parts/*.toml: tolerances and face names), or a "
                                        "tolerance file of a model without one (format: inspection/tolerances.py)")
    i.add_argument("--operator", type=plain_text_arg,
                   help="operator named in the report header (default: the login name)")
    i.add_argument("--serial", type=plain_text_arg,
                   help="part serial number in the report header (default: the session id)")
    i.add_argument("--no-pdf", action="store_true", help="no inspection.pdf (made with headless Chromium)")
    add_paper(i)
    i.add_argument("--cad-unit", choices=CAD_UNITS, default="mm", help="unit of a mesh CAD file")
    i.add_argument("--out", help="folder for inspection.json/.csv/.html (default: beside the data)")
    i.add_argument("--seed", type=int, default=0, help="random seed of the registration (default 0)")
    i.add_argument("--json", action="store_true", help="print the report as JSON")
    i.set_defaults(func=cmd_inspect)
