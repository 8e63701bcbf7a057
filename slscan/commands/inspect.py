"""`slscan cad`, `slscan register` and `slscan inspect`: inspection against CAD (issue 5).

    slscan cad FILE [--json] [--sample N]            faces by STEP id and surface type, counts per type;
                                                     --sample: time to sample N labelled points
    slscan cadbench FILE [--copies 1,4,16]           STEP reading time of files holding copies of FILE
    slscan register SOURCE TARGET [--json]           4x4 transform taking SOURCE onto TARGET, fitness, RMSE;
                                                     a cloud or session TARGET is another view of the part
                                                     (partial overlap, fitness on the overlap, --overlap)
    slscan inspect SESSION|CLOUD --cad FILE [--tolerances FILE]
                                                     register, segment by CAD face, per-face form table

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
        return 0
    if args.json:
        s = model.summary()
        print(json.dumps({"path": s["path"], "unit": s["unit"], "faces": s["faces"], "counts": s["counts"]}))
        return 0
    print(f"{model.path}: {len(model)} faces, unit {model.unit}, {model.kind}")
    for f in model.faces:
        params = ", ".join(f"{k} {_short(v)}" for k, v in f.params().items())
        print(f"  {f.label:>8}  {f.type:<9} {f.area_mm2:12.3f} mm^2  {params}")
    print("counts: " + ", ".join(f"{n} {t}" for t, n in model.counts.items()))
    for line in model.skipped:
        print(f"  skipped {line}")
    return 0


def cmd_cadbench(args: argparse.Namespace) -> int:
    """STEP reading time for files holding 1, 4, 16 ... copies of one part, each read by
    `slscan cad` in a fresh process: wall and CPU s, peak memory, faces, and the time per
    face against the one-copy file (its peer in the same run), with the load average."""
    import os
    import subprocess
    import tempfile
    import time

    from OCP.Message import Message, Message_Gravity

    from inspection.cad import write_copies

    for printer in Message.DefaultMessenger_s().Printers():  # the STEP writer's statistics are not ours to print
        printer.SetTraceLevel(Message_Gravity.Message_Fail)
    counts = [int(c) for c in args.copies.split(",")]
    print(f"{'copies':>6} {'MB':>6} {'faces':>6} {'wall s':>7} {'CPU s':>7} {'peak MB':>7} "
          f"{'CPU ms/face':>11} {'marginal':>8}  load average (1, 5, 15 min) before")
    first: tuple[int, float] | None = None
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            path = write_copies(args.file, n, Path(tmp) / f"copies_{n}.stp")
            load = os.getloadavg()
            t0 = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-m", "slscan", "cad", str(path), "--json"],
                                    stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
            out = proc.stdout.read()  # type: ignore[union-attr]
            _, status, usage = os.wait4(proc.pid, 0)
            wall = time.perf_counter() - t0
            if status != 0:
                print(f"{n:>6}: slscan cad failed (wait status {status})")
                return 1
            faces = len(json.loads(out)["faces"])
            cpu = usage.ru_utime + usage.ru_stime
            first = first or (faces, cpu)
            marginal = f"{1e3 * (cpu - first[1]) / (faces - first[0]):8.2f}" if faces > first[0] else f"{'':>8}"
            print(f"{n:>6} {path.stat().st_size / 1e6:6.1f} {faces:>6} {wall:7.2f} {cpu:7.2f} "
                  f"{usage.ru_maxrss / 1024:7.0f} {1e3 * cpu / faces:11.2f} {marginal}  "
                  + " ".join(f"{x:.2f}" for x in load), flush=True)
    print("marginal: CPU ms per face added over the first file (the fixed start-up of ~2 s excluded); "
          "a constant marginal cost is linear growth")
    print("load average after " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    return 0


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
    import open3d as o3d

    return len(o3d.io.read_triangle_mesh(path).triangles) > 0


def cmd_register(args: argparse.Namespace) -> int:
    import numpy as np

    from inspection.measured_cloud import isolate_part, load_source
    from inspection.registration import RegistrationSettings, register

    settings = RegistrationSettings(descriptors=tuple(args.descriptors.split(",")), coarse=args.coarse, seed=args.seed)
    if not _is_model(args.target):
        return _register_views(args, settings)
    from inspection.registration import ModelTarget

    target = ModelTarget.from_cad(_load_model(args.target, args.cad_unit))
    scan = load_source(args.source)
    if not args.no_isolate:
        scan = isolate_part(scan, target.diagonal_mm)
    reg = register(scan, target, settings)
    if args.json:
        print(json.dumps({"transform": reg.transform.tolist(), "fitness": reg.fitness, "rmse": reg.rmse_mm,
                          "ambiguous": reg.ambiguous, "method": reg.method}))
        return 0
    with np.printoptions(precision=6, suppress=True, floatmode="fixed"):
        print(f"transform taking {args.source} onto {args.target} (mm):")
        print(reg.transform)
    print(f"fitness {reg.fitness:.4f} (points within {reg.inlier_mm:.3g} mm), RMSE {reg.rmse_mm:.4f} mm, "
          f"{reg.method}, {reg.timings_s.get('total', 0):.2f} s" + ("; AMBIGUOUS: another pose fits as well"
                                                                    if reg.ambiguous else ""))
    return 0


def _register_views(args: argparse.Namespace, settings: Any) -> int:
    """A cloud (or session) target is another view of the part: partial overlap, judged on
    the overlap (`inspection.views.pair_registration`)."""
    import numpy as np

    from inspection.measured_cloud import load_source
    from inspection.views.pair_registration import register_view_pair, without_support

    scan, target = load_source(args.source), load_source(args.target)
    if not args.no_isolate:
        scan, target = without_support(scan, args.seed), without_support(target, args.seed)
    reg = register_view_pair(scan, target, args.overlap, settings)
    if args.json:
        print(json.dumps({"transform": reg.transform.tolist(), "fitness": reg.fitness, "rmse": reg.rmse_mm,
                          "overlap": reg.overlap, "overlap_given": reg.overlap_given, "ambiguous": reg.ambiguous,
                          "method": reg.method}))
        return 0
    with np.printoptions(precision=6, suppress=True, floatmode="fixed"):
        print(f"transform taking {args.source} onto {args.target} (mm):")
        print(reg.transform)
    print(f"overlap {reg.overlap:.0%} of the scan ({'given' if reg.overlap_given else 'estimated'}); fitness on the "
          f"overlap {reg.fitness:.4f} (points within {reg.inlier_mm:.3g} mm), RMSE {reg.rmse_mm:.4f} mm, {reg.method}"
          + ("; AMBIGUOUS: another pose fits as well" if reg.ambiguous else ""))
    return 0


def inspect_source(source: str | Path, cad: str | Path, tolerances: str | Path | None = None,
                   out: str | Path | None = None, cad_unit: str = "mm", seed: int = 0,
                   recording: Any = None) -> Any:
    """Inspect a session folder or cloud file against a CAD file; write the report files
    (and, for a session without a `recording` given, outputs/inspection.rrd); return the
    report. `slscan demo` can call this after its scan."""
    from inspection.inspect_scan import InspectionSettings, inspect
    from inspection.measured_cloud import load_source
    from inspection.registration import RegistrationSettings
    from inspection.report import deviation_image, png
    from inspection.tolerances import load_tolerances
    from scanner.multiview import MultiViewSession, is_multiview

    model = _load_model(str(cad), cad_unit)
    tol = load_tolerances(tolerances, {f.label: f.type for f in model.faces}) if tolerances else None
    multiview = MultiViewSession.open(source) if is_multiview(source) else None
    if multiview is not None:  # the whole part: the views' merged cloud
        from inspection.views.whole import load_merged

        scan = load_merged(multiview)
    else:
        scan = load_source(source)
    source = Path(source)
    folder = Path(out) if out else (source / "outputs" if source.is_dir() else source.parent)
    settings = InspectionSettings(registration=RegistrationSettings(seed=seed))
    own = None
    if recording is None and source.is_dir():
        from scanner.session import Session
        from scanner.session_recording import SessionRecording

        folder.mkdir(parents=True, exist_ok=True)
        session = multiview.views[0].session if multiview is not None else Session.open(source)  # its rig's world
        run_id = multiview.id if multiview is not None else session.id  # frame: the part frame at stage 0
        own = recording = SessionRecording(folder / "inspection.rrd", run_id, send_blueprint=False)
    try:
        if own is not None:  # the session's rig: its world frame is the recording's `world`
            own.log_rig(session.rig_model())
        report = inspect(scan, model, tol, settings, recording)
    finally:
        if own is not None:
            own.close()
    report.write(folder, deviation_png=png(deviation_image(report, scan)))
    return report


def cmd_inspect(args: argparse.Namespace) -> int:
    report = inspect_source(args.source, args.cad, args.tolerances, args.out, args.cad_unit, args.seed)
    if args.json:
        print(json.dumps(report.as_dict(), default=str))
    else:
        print(report.table())
        folder = Path(args.out) if args.out else (Path(args.source) / "outputs" if Path(args.source).is_dir()
                                                  else Path(args.source).parent)
        print(f"report    {folder / 'inspection.html'} (.json, .csv)", file=sys.stderr)
    return 1 if report.verdict == "fail" else 0


def register(sub: Any) -> None:
    c = sub.add_parser("cad", help="list a CAD model's faces by STEP id and surface type")
    c.add_argument("file", help="STEP (.step/.stp) or mesh (.stl/.ply/.obj)")
    c.add_argument("--cad-unit", choices=CAD_UNITS, default="mm", help="unit of a mesh file (STEP files say theirs)")
    c.add_argument("--json", action="store_true", help="print {faces: [...], counts: {...}}")
    c.add_argument("--sample", type=int, metavar="N", help="benchmark: time sampling N labelled points")
    c.add_argument("--repeats", type=int, default=5, help="with --sample: timed runs after a warm-up")
    c.set_defaults(func=cmd_cad)

    cb = sub.add_parser("cadbench", help="benchmark: STEP reading time for files of 1, 4, 16 copies of a part")
    cb.add_argument("file", help="STEP file of one part (e.g. ../shared/data/step/nist_ctc_01_asme1_rd.stp)")
    cb.add_argument("--copies", default="1,4,16", help="comma-separated copy counts (default 1,4,16)")
    cb.set_defaults(func=cmd_cadbench)

    r = sub.add_parser("register", help="register a cloud to a CAD model, a mesh or another cloud")
    r.add_argument("source", help="cloud (PLY/PCD/XYZ) or session folder")
    r.add_argument("target", help="STEP, mesh (STL/PLY/OBJ with triangles), or a cloud or session: another view")
    r.add_argument("--cad-unit", choices=CAD_UNITS, default="mm", help="unit of a mesh target")
    r.add_argument("--coarse", choices=("sac-ia", "ransac", "ndt"), default="sac-ia", help="coarse method")
    r.add_argument("--descriptors", default="fpfh,shot", help="fpfh, shot or fpfh,shot (multivariate)")
    r.add_argument("--no-isolate", action="store_true", help="keep every source point (no table removal)")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--overlap", type=float, metavar="SHARE", help="cloud targets: the share of SOURCE the target "
                                                                   "also saw (default: estimated)")
    r.add_argument("--json", action="store_true", help="print {transform, fitness, rmse}")
    r.set_defaults(func=cmd_register)

    i = sub.add_parser("inspect", help="register a scan to CAD, segment it by face, report form errors per face")
    i.add_argument("source", help="session folder or cloud file (PLY/PCD/XYZ, mm, camera frame)")
    i.add_argument("--cad", required=True, help="STEP or mesh of the part")
    i.add_argument("--tolerances", help="tolerance TOML (see config/tolerances/)")
    i.add_argument("--cad-unit", choices=CAD_UNITS, default="mm", help="unit of a mesh CAD file")
    i.add_argument("--out", help="folder for inspection.json/.csv/.html (default: beside the data)")
    i.add_argument("--seed", type=int, default=0)
    i.add_argument("--json", action="store_true", help="print the report as JSON")
    i.set_defaults(func=cmd_inspect)
