"""`slscan bench views`: issue 13's acceptance figures on the simulated turntable.

    slscan bench views --out DIR [--views 8] [--width 1280 --height 1024] [--session DIR] [--json]

Scans the demo part all round (or takes an existing multi-view `--session` of the turntable
scene), then prints, against the simulator's truth (each view's true stage pose, and the
part's true pose in the stage frame from the scene):
  - view alignment error (rotation, translation at the part) with the stage prior exact,
    with the axis miscalibrated (tilted `--axis-error-deg`, moved `--axis-error-mm`), and
    with the axis `slscan calibrate --stage-axis` finds on the same simulated rig (its own
    error against the simulator's axis beside it);
  - the share of the part's CAD surface area the merged cloud covers (sampled area within
    0.5 mm of a merged point);
  - the merged cloud's noise against a single view's: RMS distance to the true high top
    face (#657), every view sees it;
  - the form of the boss (#17, cylindricity) and the cone (#105) and of the single-view
    faces, from `slscan inspect` of the merged cloud;
  - view-to-view registration (`slscan register` with a view as target) on the pairs 45,
    90 and 135 degrees apart, beside Open3D's FPFH + RANSAC + ICP on the same pairs:
    found (within 1 deg and 1 mm at the part), refused, wrong;
  - time to merge and mesh, with the load average and a peer (a fixed SVD) timed in the
    same run (indicative).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanner.config import CONFIG_DIR
from slscan.exit_codes import Exit

if TYPE_CHECKING:
    import numpy as np

TURNTABLE = CONFIG_DIR / "rigs" / "sim_turntable.toml"
SCENE = CONFIG_DIR / "scenes" / "turntable_demo.toml"
CAD = CONFIG_DIR / "parts" / "demo_part.step"
PROGRAM = CONFIG_DIR / "parts" / "demo_part.toml"  # the demo part's program: its tolerances and face names
STEP_DIR = Path(__file__).resolve().parents[4] / "shared" / "data" / "step"
NIST = {"ctc01": ("nist_ctc_01_asme1_rd.stp", 0.12, (0.0, 0.0, 1.0)),  # as studies/nist_registration.py,
        "ftc06": ("nist_ftc_06_asme1_rd.stp", 0.3, (0.0, 1.0, 0.0))}  # a little smaller to fit the platter


def register(sub: Any) -> None:
    b = sub.add_parser("views")
    b.add_argument("--out", type=Path, required=True, help="new folder for the scan and the figures")
    b.add_argument("--session", type=Path, help="an existing multi-view scan of the turntable scene")
    b.add_argument("--views", type=int, default=8, help="views equally spaced over a turn (default 8)")
    b.add_argument("--width", type=int, default=1280, help="simulated camera width, px (default 1280)")
    b.add_argument("--height", type=int, default=1024, help="simulated camera height, px (default 1024)")
    b.add_argument("--axis-error-deg", type=float, default=0.5, help="the miscalibrated axis's tilt, deg (default 0.5)")
    b.add_argument("--axis-error-mm", type=float, default=0.5, help="the miscalibrated axis's shift, mm (default 0.5)")
    b.add_argument("--no-pairs", action="store_true", help="leave out the view-pair registrations")
    b.add_argument("--pairs-only", action="store_true", help="only the view-pair registrations")
    b.add_argument("--part", choices=sorted(NIST), help="view pairs of a NIST part (../shared/data/step) on the "
                                                       "turntable instead of the demo part (pairs only)")
    b.add_argument("--json", action="store_true", help="print the figures as JSON (always written to "
                                                       "OUT/viewbench.json)")
    b.set_defaults(func=cmd_viewbench)


def peer_s() -> float:
    """A fixed CPU task timed beside the figures: the SVD of a 1200 x 1200 matrix (s)."""
    import numpy as np

    a = np.random.default_rng(0).standard_normal((1200, 1200))
    t0 = time.perf_counter()
    np.linalg.svd(a)
    return time.perf_counter() - t0


def cmd_viewbench(args: argparse.Namespace) -> int:
    """The figures (below), also in --out/viewbench.json; with --json the scan's and the
    stage axis's lines go to stderr and stdout gets the figures alone."""
    document = sys.stdout
    with contextlib.redirect_stdout(sys.stderr) if args.json else contextlib.nullcontext():
        figures, text = _viewbench(args)
    print(json.dumps(figures, default=float) if args.json else text, file=document)
    return Exit.OK


def _viewbench(args: argparse.Namespace) -> tuple[dict[str, Any], str]:
    """The figures of the benchmark asked, and their text."""
    from inspection.views.align import align_views
    from inspection.views.whole import whole_part
    from scanner.multiview import MultiViewSession

    args.out.mkdir(parents=True, exist_ok=True)
    root = args.session or _scan(args)
    session = MultiViewSession.open(root)
    if args.part or args.pairs_only:
        truths = [_truth(v.session.root) for v in session.views]
        part, pairs = args.part or "demo", _pairs(session, truths)
        doc = {"part": part, "views": len(session.views), "camera": _camera(session), "pairs": pairs}
        (args.out / "viewbench.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
        return doc, "\n".join(f"{part} pairs {k} apart: ours {p['ours']}; Open3D "
                               f"{p['open3d_fpfh_ransac_icp']}" for k, p in pairs.items())
    figures: dict[str, Any] = {"views": len(session.views), "camera": _camera(session)}
    load0, peer0 = os.getloadavg()[0], peer_s()
    whole = whole_part(session)
    figures["time"] = {**whole.timings_s, "load_average": load0, "peer_svd_s": peer0, "peer_svd_after_s": peer_s()}
    truths = [_truth(v.session.root) for v in session.views]
    figures["alignment"] = _errors(whole.alignment, truths)
    wrong = _miscalibrated(session, args.axis_error_deg, args.axis_error_mm)
    figures["alignment_axis_error"] = {"axis_error": [args.axis_error_deg, args.axis_error_mm],
                                       **_errors(align_views(_with_priors(whole.views, session, wrong)), truths)}
    calibrated = _calibrated_axis(session, args.out / "stage_axis")
    figures["alignment_calibrated_axis"] = {"axis_error": _axis_error(calibrated, session.stage_model),
                                            **_errors(align_views(_with_priors(whole.views, session, calibrated)),
                                                      truths)}
    figures["coverage"], figures["noise"] = _coverage_and_noise(whole, session)
    figures["form"] = _form(root)
    if not args.no_pairs:
        figures["pairs"] = _pairs(session, truths)
    (args.out / "viewbench.json").write_text(json.dumps(figures, indent=2, default=float) + "\n")
    return figures, _text(figures)


def _scan(args: argparse.Namespace) -> Path:
    from slscan.commands.scan import cmd_scan

    text = TURNTABLE.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    text = text.replace("width = 1280", f"width = {args.width}").replace("height = 1024", f"height = {args.height}")
    rig = args.out / "turntable.toml"
    rig.write_text(text)
    out = args.out / "scan"
    scene = SCENE if args.part is None else _nist_scene(args.part, rig, args.out)
    cmd_scan(argparse.Namespace(rig=rig, scene=scene, out=out, patterns=None, seed=0, fault=[], stage_fault=[],
                                views=args.views, angles=None, no_merge=True, stage_axis=None))
    return out


def _nist_scene(part: str, rig: Path, out: Path) -> Path:
    """The NIST part standing on the turntable, written as a mesh scene (PLY + TOML)."""
    import open3d as o3d

    from inspection.cad import load_cad
    from scanner.errors import ScannerError
    from scanner.rig import RigConfig
    from sim.stage_bench import part_on_stage

    file, scale, up = NIST[part]
    if not (STEP_DIR / file).is_file():
        raise ScannerError(f"{STEP_DIR / file}: the NIST STEP files are not here")
    tess = load_cad(STEP_DIR / file, scale=scale, deflection_mm=0.01).tessellation
    stage = RigConfig.load(rig).stage
    if stage is None:
        raise ScannerError(f"{rig}: the rig has no [stage] to stand the part on")
    scene = part_on_stage(tess.vertices, tess.triangles, tess.face, up, stage.nominal)
    lines = [f'name = "{part} on the turntable"']
    for obj in scene.objects:
        if obj.kind == "mesh" and obj.triangles is not None:
            mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(obj.world_vertices()),
                                             o3d.utility.Vector3iVector(obj.triangles))
            o3d.io.write_triangle_mesh(out / f"{obj.name}.ply", mesh)
            lines += ["[[objects]]", f'name = "{obj.name}"', f'mesh = "{obj.name}.ply"']
        else:
            lines += ["[[objects]]", f'name = "{obj.name}"', f"plane = {{ size_mm = {list(obj.size_mm or ())} }}",
                      f"albedo = {obj.albedo}", f"pose = {{ matrix = {obj.pose.tolist()} }}"]
    path = out / "scene.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def _camera(session: Any) -> str:
    cam = session.views[0].session.rig_model().camera
    return f"{cam.width}x{cam.height}"


def _truth(view: Path) -> np.ndarray:
    import numpy as np

    return np.linalg.inv(np.array(json.loads((view / "ground_truth_stage.json").read_text())["world_from_stage"]))


def _errors(alignment: Any, truths: list[np.ndarray]) -> dict[str, Any]:
    import numpy as np

    from inspection.views.align import pose_error

    e = np.array([pose_error(t, p, alignment.centre) for t, p in zip(truths, alignment.poses)])
    prior = np.array([pose_error(t, p, alignment.centre) for t, p in zip(truths, alignment.priors)])
    return {"max_deg": float(e[:, 0].max()), "max_mm": float(e[:, 1].max()), "median_deg": float(np.median(e[:, 0])),
            "median_mm": float(np.median(e[:, 1])), "prior_max_deg": float(prior[:, 0].max()),
            "prior_max_mm": float(prior[:, 1].max()), "pairs": len(alignment.edges), "refused": len(alignment.refused)}


def _miscalibrated(session: Any, tilt_deg: float, shift_mm: float) -> Any:
    """The stage model with the axis tilted and moved (what a miscalibration gives)."""
    import numpy as np

    from scanner.stage_model import AxisGeometry, StageModel, rotation_about

    a = session.stage_model.axes[0]
    side = np.cross(a.direction, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    return StageModel((AxisGeometry(a.name, a.kind, rotation_about(side, np.radians(tilt_deg)) @ a.direction,
                                    a.point_mm + shift_mm * np.array([1.0, 0.0, 0.0])),))


def _calibrated_axis(session: Any, out: Path) -> Any:
    """The stage model `slscan calibrate --stage-axis` finds on the rig the views were
    scanned with (the simulator turns a board on the same turntable)."""
    from slscan.commands.stage_axis import cmd_stage_axis

    rig = Path(session.plan["rig_config_path"])
    cmd_stage_axis(argparse.Namespace(rig=rig, out=out, angles=None, board=None, seed=0))
    return session.stage_axis_file(out / "stage_axis.json")


def _axis_error(model: Any, truth: Any) -> list[float]:
    """[tilt deg, distance mm from the true axis point to the line of `model`'s axis]."""
    import numpy as np

    a, t = model.axes[0], truth.axes[0]
    off = a.point_mm - t.point_mm
    off -= a.direction * (a.direction @ off)
    return [float(np.degrees(np.arccos(min(1.0, float(a.direction @ t.direction))))), float(np.linalg.norm(off))]


def _with_priors(views: list[Any], session: Any, model: Any) -> list[Any]:
    """The views with their priors from `model` at their recorded stage positions."""
    from dataclasses import replace

    import numpy as np

    return [replace(v, prior=np.linalg.inv(model.world_from_stage(s.position))) for v, s in zip(views, session.views)]


def _part_from_cad() -> np.ndarray:
    from sim.scene import load_scene

    return load_scene(SCENE).objects[0].pose  # the part at stage 0: CAD frame -> part (stage) frame


def _coverage_and_noise(whole: Any, session: Any) -> tuple[dict[str, float], dict[str, float]]:
    import numpy as np
    from scipy.spatial import cKDTree

    from inspection.cad import load_cad
    from inspection.sampling import sample_model
    from inspection.views.merge import fuse

    model = load_cad(CAD)
    samples = sample_model(model, 0.3, seed=0)
    T = _part_from_cad()
    pts = samples.points @ T[:3, :3].T + T[:3, 3]
    d, _ = cKDTree(whole.merged.points).query(pts, workers=-1)
    faces = {f.label: f.index for f in model.faces}
    covered = d < 0.5
    per_face = {label: float(covered[samples.face == i].mean()) for label, i in faces.items()}
    coverage = {"area_share": float(covered.mean()), **{f"face {k}": v for k, v in per_face.items()}}
    # noise on the high top (#657, z = 22 in the CAD frame): distance to its true plane
    n = T[:3, 2]
    c = T[:3, :3] @ np.array([-27.5, 0.0, 22.0]) + T[:3, 3]

    def rms_on_top(points: np.ndarray, normals: np.ndarray) -> float:
        h = (points - c) @ n
        local = points - c - np.outer(h, n)
        inside = (np.abs(h) < 0.2) & (normals @ n > 0.95) & (np.linalg.norm(local, axis=1) < 12.0)
        return float(np.sqrt(np.mean(h[inside] ** 2)))

    first = whole.views[0].moved(whole.alignment.poses[0])
    alone = fuse([whole.views[0]], [whole.alignment.poses[0]], whole.merged.cell_mm)
    noise = {"merged_rms_mm": rms_on_top(whole.merged.points, whole.merged.normals),
             "single_view_rms_mm": rms_on_top(first.points, first.normals),
             "single_view_same_cells_rms_mm": rms_on_top(alone.points, alone.normals)}
    return coverage, noise


def _form(root: Path) -> dict[str, Any]:
    """`slscan inspect` of the merged cloud (every face's row), and the narrow faces again
    with a 0.3 mm edge margin: the demo part's cone (#105) is a 1.5 mm chamfer, which the
    default 1 mm margin on both of its borders leaves empty."""
    from inspection.cad import load_cad
    from inspection.form import FormSettings
    from inspection.inspect_scan import InspectionSettings, inspect
    from inspection.views.whole import load_merged
    from scanner.multiview import MultiViewSession
    from slscan.commands.inspect import inspect_source

    def rows(report: Any) -> dict[str, Any]:
        keys = ("type", "points", "status", "flatness_mz_mm", "cylindricity_mz_mm", "profile_mm", "noise_mm",
                "sq_mm", "verdicts")
        return {row.get("label", "?"): {k: row.get(k) for k in keys if k in row} for row in report.as_dict()["faces"]}

    report = inspect_source(root, CAD, tolerances=PROGRAM)
    narrow = inspect(load_merged(MultiViewSession.open(root)), load_cad(CAD),
                     settings=InspectionSettings(form=FormSettings(edge_margin_mm=0.3)))
    return {"verdict": report.verdict, "faces": rows(report),
            "narrow_margin_0.3mm": {k: v for k, v in rows(narrow).items() if k in ("#17", "#105", "#270", "#602")}}


def _pairs(session: Any, truths: list[np.ndarray]) -> dict[str, Any]:
    import numpy as np

    from inspection.errors import RegistrationFailed
    from inspection.measured_cloud import load_source
    from inspection.views.align import pose_error
    from inspection.views.pair_registration import register_view_pair, without_support
    from studies.pair_bench import open3d_pair

    views = [without_support(load_source(v.session.root)) for v in session.views]
    n = len(views)
    step = 360.0 / n
    out: dict[str, Any] = {}
    for apart in (45, 90, 135):
        k = round(apart / step)
        if k < 1 or abs(k * step - apart) > 1e-6:
            continue
        ours: list[tuple[float, float] | None] = []
        theirs: list[tuple[float, float] | None] = []
        for i in range(n):
            j = (i + k) % n
            truth = np.linalg.inv(truths[j]) @ truths[i]
            centre = views[i].points.mean(axis=0)
            try:
                found = register_view_pair(views[i], views[j]).transform
                ours.append(pose_error(truth, found, centre))
            except RegistrationFailed:
                ours.append(None)
            theirs.append(pose_error(truth, open3d_pair(views[i], views[j], 0), centre))
        out[f"{apart} deg"] = {"ours": _rates(ours), "open3d_fpfh_ransac_icp": _rates(theirs)}
    return out


def _rates(errors: list[tuple[float, float] | None]) -> dict[str, Any]:
    import numpy as np

    found = [e for e in errors if e is not None and e[0] <= 1.0 and e[1] <= 1.0]
    wrong = [e for e in errors if e is not None and not (e[0] <= 1.0 and e[1] <= 1.0)]
    return {"pairs": len(errors), "found": len(found), "refused": sum(e is None for e in errors),
            "wrong": len(wrong), "median_found_deg": float(np.median([e[0] for e in found])) if found else None,
            "median_found_mm": float(np.median([e[1] for e in found])) if found else None}


def _text(f: dict[str, Any]) -> str:
    a, b, c = f["alignment"], f["alignment_axis_error"], f["alignment_calibrated_axis"]
    lines = [f"{f['views']} views, camera {f['camera']}",
             f"alignment, exact stage prior:     max {a['max_deg']:.4f} deg / {a['max_mm']:.4f} mm at the part "
             f"(median {a['median_deg']:.4f} / {a['median_mm']:.4f}); {a['pairs']} pairs, {a['refused']} refused",
             f"alignment, axis off {b['axis_error'][0]} deg / {b['axis_error'][1]} mm (prior up to "
             f"{b['prior_max_deg']:.3f} deg / {b['prior_max_mm']:.3f} mm): max {b['max_deg']:.4f} deg / "
             f"{b['max_mm']:.4f} mm (median {b['median_deg']:.4f} / {b['median_mm']:.4f})",
             f"alignment, axis from slscan calibrate --stage-axis (off {c['axis_error'][0]:.4f} deg / "
             f"{c['axis_error'][1]:.4f} mm; prior up to {c['prior_max_deg']:.3f} deg / {c['prior_max_mm']:.3f} mm): "
             f"max {c['max_deg']:.4f} deg / {c['max_mm']:.4f} mm (median {c['median_deg']:.4f} / "
             f"{c['median_mm']:.4f})",
             f"coverage of the CAD surface: {f['coverage']['area_share']:.1%} of its area within 0.5 mm of the merged "
             "cloud; per face: " + ", ".join(f"{k[5:]} {v:.0%}" for k, v in f["coverage"].items()
                                             if k != "area_share"),
             f"noise on the high top (#657) against its true plane: merged {f['noise']['merged_rms_mm'] * 1e3:.1f} um "
             f"RMS, one view {f['noise']['single_view_rms_mm'] * 1e3:.1f} um (on the same cells "
             f"{f['noise']['single_view_same_cells_rms_mm'] * 1e3:.1f} um)",
             f"inspection of the merged cloud: verdict {f['form']['verdict']}"]
    for label, row in f["form"]["faces"].items():
        lines.append(f"  {label:>6} {row}")
    lines.append("narrow faces with a 0.3 mm edge margin:")
    for label, row in f["form"]["narrow_margin_0.3mm"].items():
        lines.append(f"  {label:>6} {row}")
    for apart, p in f.get("pairs", {}).items():
        lines.append(f"pairs {apart} apart: ours {p['ours']}; Open3D {p['open3d_fpfh_ransac_icp']}")
    t = f["time"]
    lines.append(f"time: load views {t['load']:.1f} s, align {t['align']:.1f} s, merge {t['merge']:.1f} s, mesh "
                 f"{t.get('mesh', 0):.1f} s; load average {t['load_average']:.1f}, peer SVD {t['peer_svd_s']:.2f} s "
                 f"before, {t['peer_svd_after_s']:.2f} s after (indicative)")
    return "\n".join(lines)


