"""`slscan pose` and `slscan posebench`: poses of thin flat parts in a bin for a robot cell
(paper 001), and their benchmark on simulated bins.

`slscan pose SESSION|CLOUD --part FILE [--masks PATH] [--method sac-ia|ndt]` finds the part
instances (from instance masks aligned with the camera image — label PNGs or Labelme JSON
— or, without masks, the flat patches above the tray: `inspection.bins.flat_patches`),
estimates each instance's pose (`inspection.bins.pose`), ranks the pickable ones
(`inspection.bins.picking`), writes the poses file (`<session>/outputs/poses.json`, or
`<cloud stem>.poses.json` beside a cloud file), prints the table and logs the bin to a
Rerun recording beside the poses file. A cloud file is placed on the camera image of the
rig (`--rig`, default the simulated bench rig), as slscan's own clouds are in its camera
frame; without `--rig` the poses file has no world frame (camera frame only), so a robot
cell never reads an identity it did not ask for. The part file is a TOML `[part]` table
(`kind = "tab"`: the parameters of `sim.bins.TabPart`, see config/parts/nickel_tab.toml) or
a mesh (PLY, STL, OBJ, OFF; mm).
Exit code 0 when at least one part is pickable, 1 when none is (the file is written anyway).

`slscan posebench` renders simulated bins (`sim.bins.bin_scene` + `scan_bin`: ray-cast
truth, depth noise, projector shadows), poses every part from the simulator's instance
masks with each method, and prints the acceptance figures against the true poses and the
four-case table of paper 001 (Tables 4-5). `slscan posebench --sessions DIR...` judges
`slscan pose` on saved bins instead (`slscan scan --scene bin:SEED`); with `--rows FILE` it
writes one JSON line per bin, and `slscan posebench --summary FILE...` prints the figures of
such rows files, so that a run over many bins can be done in pieces.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slscan.exit_codes import Exit
from slscan.options import add_json, coarse_method

if TYPE_CHECKING:
    import numpy as np

MESH_SUFFIXES = (".ply", ".stl", ".obj", ".off")
POSE_METHODS = {"sac-ia": "sacia", "ndt": "ndt"}  # the command line's spelling -> inspection.bins' name


def register(sub: Any) -> None:
    p = sub.add_parser("pose")
    p.add_argument("input", help="a session folder or a point cloud file in the camera frame")
    p.add_argument("--part", required=True, help="part file: TOML with a [part] table (kind = \"tab\") or a mesh (mm)")
    p.add_argument("--masks", help="instance masks aligned with the camera image: a label PNG, a Labelme JSON, or "
                                   "a folder of them (default: the flat patches above the tray)")
    p.add_argument("--method", type=coarse_method, choices=tuple(POSE_METHODS), default="sac-ia",
                   help="coarse registration: FPFH + SAC-IA with the Huber score (default) or NDT")
    p.add_argument("--max-occlusion", type=float, default=0.15, metavar="FRACTION",
                   help="the most a part offered for picking may be covered: its occlusion estimate plus the "
                        "estimate's error bound (0.05) at most this (default 0.15)")
    p.add_argument("--rig", type=Path, help="rig TOML for a cloud file: its camera image and world frame (default: "
                                            "the simulated bench rig's camera, and no world frame: poses in the "
                                            "camera frame only)")
    p.add_argument("--out", help="poses file (.json); default <session>/outputs/poses.json or <cloud>.poses.json")
    p.add_argument("--no-log", action="store_true", help="do not write the Rerun recording")
    add_json(p)
    p.set_defaults(func=cmd_pose)

    b = sub.add_parser("posebench")
    b.add_argument("--seeds", type=int, nargs="+", default=list(range(50)), help="bin seeds (default 0..49)")
    b.add_argument("--methods", nargs="+", type=coarse_method, choices=tuple(POSE_METHODS), default=["sac-ia", "ndt"],
                   help="coarse registration methods to compare (default both)")
    b.add_argument("--size", type=int, nargs=2, default=(1280, 1024), metavar=("W", "H"),
                   help="camera resolution of the rig the bins are rendered with (default the rig's 1280 x 1024)")
    b.add_argument("--noise", type=float, default=0.01, metavar="MM", help="depth noise along the camera rays")
    b.add_argument("--fringe", action="store_true",
                   help="scan each bin through the whole simulated chain (fringes rendered, decoded, triangulated) "
                        "on the default rig instead of the quick ray-cast scan (--size and --noise then do not apply)")
    b.add_argument("--rows", help="append every part's row to this file (JSON lines, bin by bin; with --sessions one "
                                  "line per bin: its judged poses and pose times, for --summary)")
    b.add_argument("--sessions", nargs="+", type=Path, metavar="SESSION",
                   help="judge `slscan pose` on saved bins instead (sessions of `slscan scan --scene bin:SEED`, or "
                        "folders holding them): instances without masks, as `slscan pose` finds them, judged against "
                        "each session's bin_truth.json and instance ids (--methods: the first one)")
    b.add_argument("--truth-masks", action="store_true",
                   help="with --sessions: take the instances from the simulator's instance ids instead")
    b.add_argument("--summary", nargs="+", type=Path, metavar="ROWS",
                   help="print the saved-bins figures of rows files written by `--sessions --rows` runs (a long "
                        "run done in pieces) instead of posing anything")
    add_json(b)
    b.set_defaults(func=cmd_posebench)


# ------------------------------------------------------------------------------ inputs


def load_part(path: str | Path) -> Any:
    """The `inspection.bins.part_model.ThinPartModel` of a part file (see the module
    docstring), with the grip point and approach a TOML part file names."""
    from dataclasses import replace

    from inspection.bins.part_model import ThinPartModel
    from inspection.errors import CadError

    path = Path(path)
    if not path.is_file():
        raise CadError(path, "no such part file")
    suffix = path.suffix.lower()
    if suffix == ".toml":
        from sim.bins import load_part_file

        spec = load_part_file(path)
        model = ThinPartModel.from_mesh(*spec.part.mesh(), spec.name)
        return replace(model, grip_point_mm=spec.grip_point_mm, approach=spec.approach)
    if suffix in MESH_SUFFIXES:
        from scanner.mesh_files import read_mesh

        vertices, triangles = read_mesh(path)
        if len(triangles) == 0:
            raise CadError(path, "no triangles could be read (unreadable or empty mesh)")
        return ThinPartModel.from_mesh(vertices, triangles, path.stem)
    raise CadError(path, f"unsupported part file: expected .toml or a mesh ({', '.join(MESH_SUFFIXES)})")


def _organise(points: np.ndarray, normals: np.ndarray | None, camera: Any, where: str) -> Any:
    """An organised cloud on `camera`'s image from camera-frame points (nearest point per
    pixel), with normals from the organised points where none are given."""
    import numpy as np

    from inspection.errors import CloudError
    from scanner.pointcloud import OrganisedCloud, organised_normals

    px = np.rint(camera.project(points)).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < camera.width) & (px[:, 1] >= 0) & (px[:, 1] < camera.height)
    if not inside.any():
        raise CloudError(where, "no point projects into the rig's camera image: not a cloud in this rig's camera frame")
    order = np.argsort(-points[inside, 2])   # farthest first: the nearest point of a pixel is written last
    sel = np.flatnonzero(inside)[order]
    grid = np.full((camera.height, camera.width, 3), np.nan, np.float32)
    grid[px[sel, 1], px[sel, 0]] = points[sel]
    nrm = organised_normals(grid[..., 0], grid[..., 1], grid[..., 2])
    if normals is not None:
        nrm[px[sel, 1], px[sel, 0]] = normals[sel]
    return OrganisedCloud(grid, np.zeros(grid.shape[:2], np.uint8), nrm)


def load_scene(path: Path, rig: Path | None) -> tuple[Any, Any, Any]:
    """(organised cloud, rig model, session or None) of a session or a cloud file (placed
    on the camera of the rig TOML `rig`, default the simulated bench rig)."""
    import numpy as np

    from inspection.errors import CloudError
    from scanner.rig import RigConfig

    if path.is_dir():
        from scanner.pointcloud import OrganisedCloud, organised_normals
        from scanner.session import Session
        from slscan.commands.segment import _session_points

        session = Session.open(path)
        points, valid = _session_points(session)
        grid = np.full(valid.shape + (3,), np.nan, np.float32)
        grid[valid] = points
        cloud = OrganisedCloud(grid, np.zeros(valid.shape, np.uint8),
                               organised_normals(grid[..., 0], grid[..., 1], grid[..., 2]))
        return cloud, session.rig_model(), session
    if not path.exists():
        raise CloudError(path, "no such cloud file or session folder")
    from scanner.mesh_files import read_points

    points, normals = read_points(path)
    if len(points) == 0:
        raise CloudError(path, "no points could be read (unreadable or empty cloud)")
    model = RigConfig.load(rig).model if rig is not None else RigConfig.load().nominal_model()
    return _organise(points, normals, model.camera, str(path)), model, None


def load_masks(path: Path, cloud: Any) -> list[Any]:
    """Instances from a label PNG, a Labelme JSON, or a folder of them (ids numbered on
    across files)."""
    from inspection.bins.instances import instances_from_label_image, read_label_image, read_labelme
    from inspection.errors import MaskError

    files = sorted(f for f in path.iterdir() if f.suffix.lower() in (".png", ".json")) if path.is_dir() else [path]
    if not path.exists():
        raise MaskError(f"{path}: no such mask file or folder")
    if not files:
        raise MaskError(f"{path}: no label PNG or Labelme JSON files in the folder")
    h, w = cloud.valid.shape
    out: list[Any] = []
    for f in files:
        if f.suffix.lower() == ".json":
            ids, names = read_labelme(f, (w, h))
        elif f.suffix.lower() == ".png":
            ids, names = read_label_image(f), None
        else:
            raise MaskError(f"{f}: not a label PNG or a Labelme JSON file")
        try:
            found = instances_from_label_image(ids, cloud, names=names)
        except MaskError as exc:
            raise MaskError(f"{f}: {exc}") from None
        base = max((i.id for i in out), default=0)
        out += [type(i)(i.id + base, i.indices, i.points, i.normals, i.source, i.mask, i.label, i.score) for i in found]
    return out


# ------------------------------------------------------------------------------ pose


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """One BLAS and one OpenCV thread inside (restored after): the per-part matrices and
    grids are small, and a second thread costs more CPU than it saves (its start-up and
    waits are CPU time too), most of all on a busy machine. Results do not change. Both
    limits are process-wide: for the command line, not for a thread beside others."""
    from scanner.native_threads import native_threads, opencv_threads

    with opencv_threads(1), native_threads(1, openmp=True):
        yield


def pose_scene(cloud: Any, camera: Any, model: Any, settings: Any, instances: list[Any] | None = None) -> tuple:
    """(instances, poses) of a scanned bin, as `slscan pose` finds them: the given
    instances (from masks), or else the flat patches above the tray; each posed with the
    organised scan as context (`camera` projects camera-frame points onto its image), in
    `one_thread`."""
    from inspection.bins.flat_patches import instances_from_flat_patches
    from inspection.bins.instance_plane import SceneContext
    from inspection.bins.picking import merge_duplicates
    from inspection.bins.pose import estimate_poses

    with one_thread():
        if instances is None:
            instances = instances_from_flat_patches(cloud, model.thickness_mm)
        context = SceneContext.of_cloud(cloud, camera)
        return instances, merge_duplicates(estimate_poses(instances, model, context, settings), model)


def rig_of(rig_model: Any, session: Any, rig_file: Path | None) -> tuple[np.ndarray | None, dict[str, Any] | None]:
    """(world_from_camera, the poses file's `rig` entry) of a session (its rig), or of a
    cloud file with `--rig` (that rig); a cloud file without one has no world frame (None, None)."""
    import numpy as np

    calibration = rig_model.calibration or "nominal (uncalibrated)"
    if session is not None:
        conf = session.manifest.rig_config.get("rig", {})
        name = conf.get("name") if isinstance(conf, dict) else None
        return (np.asarray(rig_model.world_from_cam, np.float64),
                {"name": name, "calibration": calibration, "session": session.id})
    if rig_file is None:
        return None, None
    from scanner.rig import RigConfig

    return (np.asarray(rig_model.world_from_cam, np.float64),
            {"name": RigConfig.load(rig_file).name, "calibration": calibration, "file": str(rig_file)})


def cmd_pose(args: argparse.Namespace) -> int:
    from inspection.bins.picking import poses_document, table, write_poses
    from inspection.bins.pose_settings import PoseSettings

    model = load_part(args.part)
    src = Path(args.input)
    cloud, rig_model, session = load_scene(src, args.rig)
    world_from_cam, rig = rig_of(rig_model, session, args.rig)
    if session is not None:
        out = Path(args.out) if args.out else session.outputs / "poses.json"
    else:
        out = Path(args.out) if args.out else src.with_name(src.stem + ".poses.json")
    if out.suffix != ".json":
        from scanner.errors import ScannerError

        raise ScannerError(f"{out}: the poses file must end in .json")
    masks = load_masks(Path(args.masks), cloud) if args.masks else None
    how = f"masks {args.masks}" if args.masks else "flat patches above the tray"
    settings = PoseSettings(method=POSE_METHODS[args.method], max_occlusion=args.max_occlusion)
    instances, poses = pose_scene(cloud, rig_model.camera, model, settings, masks)
    print(f"{len(instances)} instances in {src} ({how}); part {model.name}, method {args.method}", file=sys.stderr)
    message = ""
    if not instances:
        message = (f"no parts found in {src}: no instance in the masks" if args.masks else
                   f"no parts found in {src}: nothing stands above the tray plane")
    elif not any(p.ok for p in poses):
        message = f"no part recognised in {src}: none of the {len(poses)} instances fits {model.name}"
    doc = poses_document(poses, model, world_from_cam, str(src), rig, args.max_occlusion, message)
    write_poses(out, doc)
    text = sys.stderr if args.json else sys.stdout  # --json: the document alone on stdout
    print(table(doc), file=text)
    print(f"poses     {out}", file=text)
    if not args.no_log:
        from inspection.bins.picking import log_poses
        from scanner.session_recording import SessionRecording

        rrd = out.with_name(out.stem + ".rrd")
        with SessionRecording(rrd, session.id if session is not None else src.stem, send_blueprint=False) as rec:
            rec.log_rig(rig_model)
            rec.log_cloud(cloud)
            log_poses(rec, doc, poses, instances, model)
        print(f"recording {rrd}", file=text)
    if args.json:
        print(json.dumps(doc, default=str))
    return Exit.OK if any(r["pick_rank"] is not None for r in doc["parts"]) else Exit.FAILED


# ------------------------------------------------------------------------- benchmark


CASES = ("front up", "back up", "occluded front", "occluded back")


def cmd_posebench(args: argparse.Namespace) -> int:
    """The benchmark asked (simulated bins, `--sessions` or `--summary`): its lines on stdout,
    or with `--json` on stderr and its figures as one JSON document on stdout."""
    run = rows_summary if args.summary else saved_bins_bench if args.sessions else simulated_bins_bench
    if not args.json:
        run(args)
        return Exit.OK
    with contextlib.redirect_stdout(sys.stderr):
        figures = run(args)
    print(json.dumps({"status": "ok", **figures}, default=float))
    return Exit.OK


def simulated_bins_bench(args: argparse.Namespace) -> dict[str, Any]:
    """Per bin: render, lift the simulator's instance masks, pose every part with each
    method (wall and process CPU time per part), compare with the true poses; the rows."""
    import numpy as np

    from inspection.bins.instance_plane import SceneContext
    from inspection.bins.instances import instances_from_label_image
    from inspection.bins.part_model import ThinPartModel
    from inspection.bins.pose import estimate_pose
    from inspection.bins.pose_settings import PoseSettings
    from inspection.registration import pose_difference
    from scanner.rig import RigConfig
    from sim.bins import TabPart, bin_scene, fringe_scan_bin, scan_bin

    rig = RigConfig.load().nominal_model().with_camera_size(*args.size)
    part = TabPart()
    centre = np.r_[(part.outline().min(axis=0) + part.outline().max(axis=0)) / 2, part.thickness_mm / 2]
    models = {m: ThinPartModel.from_mesh(*part.mesh(), "tab") for m in args.methods}
    load0 = os.getloadavg()
    scanned = "fringe scans on the default rig" if args.fringe else \
        f"quick scans, rig {args.size[0]}x{args.size[1]}, depth noise {args.noise} mm"
    print(f"{scanned}; load average {load0[0]:.2f} "
          f"{load0[1]:.2f} {load0[2]:.2f}", flush=True)
    rows: list[dict[str, Any]] = []
    for seed in args.seeds:
        n = 5 + seed % 16
        b = bin_scene(n, seed=seed, part=part)
        cloud, ids = fringe_scan_bin(b, seed) if args.fringe else scan_bin(b, rig, args.noise, seed)
        truth_occ = b.occlusion()
        instances = {i.id: i for i in instances_from_label_image(np.where(ids >= 2, ids, 0), cloud)}
        camera = rig.camera if not args.fringe else RigConfig.load().nominal_model().camera
        context = SceneContext.of_cloud(cloud, camera)
        for method in args.methods:
            settings = PoseSettings(method=POSE_METHODS[method])
            for k in range(n):
                inst = instances.get(k + 2)
                row = {"seed": seed, "part": k, "method": method, "occlusion": float(truth_occ[k]),
                       "front_up": bool(b.front_up[k]), "points": len(inst) if inst else 0, "found": False}
                if inst is not None:
                    with one_thread():
                        r = estimate_pose(inst, models[method], context, settings)
                    row["cpu_s"] = r.cpu_s
                    row["wall_s"] = r.time_s
                    row["found"] = r.ok
                    row["reason"] = r.reason
                    if r.ok:
                        rot, trans = pose_difference(b.poses[k], r.pose)
                        row.update(rot_deg=rot, trans_mm=trans,
                                   trans_centre_mm=pose_difference(b.poses[k], r.pose, centre)[1],
                                   side_ok=(r.side == "front") == bool(b.front_up[k]), est_occlusion=r.occlusion)
                rows.append(row)
        done = [r for r in rows if r["seed"] == seed]
        if args.rows:   # one JSON line per part, written as each bin is done
            with open(args.rows, "a") as f:
                f.writelines(json.dumps(r) + "\n" for r in done)
        print(f"bin {seed}: {n} parts; " + "; ".join(
            f"{m} {sum(r['found'] for r in done if r['method'] == m)} posed" for m in args.methods), flush=True)
    load1 = os.getloadavg()
    text = summary(rows, args.methods)
    print(text)
    print(f"load average at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    return {"bench": "simulated bins", "scans": scanned, "methods": args.methods, "rows": rows,
            "summary": text.splitlines(), "load_average": {"start": load0, "end": load1}}


def bin_sessions(paths: list[Path]) -> list[Path]:
    """The session folders with a bin truth among `paths` (each one, or the folders in it)."""
    from scanner.errors import SessionError
    from sim.bins import BIN_TRUTH_FILE

    out = []
    for p in paths:
        found = [p] if (p / BIN_TRUTH_FILE).is_file() else sorted(q.parent for q in p.glob(f"*/{BIN_TRUTH_FILE}"))
        if not found:
            raise SessionError(f"{p}: no saved bin ({BIN_TRUTH_FILE}) here or in its folders; "
                               "save one with `slscan scan --scene bin:SEED --out DIR`")
        out += found
    return out


def saved_bins_bench(args: argparse.Namespace) -> int:
    """`slscan posebench --sessions`: `pose_scene` on every saved bin, judged by
    `sim.bin_judge` (wall and CPU time of every part's pose, and of each bin's instances and context);
    the figures: each bin's judgement, the summary lines, the load averages."""
    import numpy as np

    from inspection.bins.instances import instances_from_label_image
    from inspection.bins.picking import pick_order
    from inspection.bins.pose_settings import PoseSettings
    from sim.bin_judge import PICK_DEG, PICK_MM, WRONG_DEG, WRONG_MM, judge
    from sim.bins import BIN_TRUTH_FILE, BinTruth, TabPart
    from sim.evaluate import Truth

    sessions = bin_sessions(args.sessions)
    settings = PoseSettings(method=POSE_METHODS[args.methods[0]])
    models: dict[TabPart, Any] = {}
    load0 = os.getloadavg()
    print(f"{len(sessions)} saved bins, {settings.method}, instances from "
          f"{'the simulator ids' if args.truth_masks else 'flat patches (no masks)'}; "
          f"load average {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}", flush=True)
    bins, times, steps, records = [], [], [], []
    for path in sessions:
        truth = BinTruth.load(path / BIN_TRUTH_FILE)
        if truth.part not in models:
            from inspection.bins.part_model import ThinPartModel

            models[truth.part] = ThinPartModel.from_mesh(*truth.part.mesh(), "tab")
        cloud, rig_model, _ = load_scene(path, None)
        object_id = Truth.load(path / "ground_truth.npz").object_id
        masks = instances_from_label_image(np.where(object_id >= 2, object_id, 0), cloud) if args.truth_masks else None
        wall, cpu = time.perf_counter(), time.process_time()
        instances, poses = pose_scene(cloud, rig_model.camera, models[truth.part], settings, masks)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        times += [(p.time_s, p.cpu_s) for p in poses]
        scene_wall, scene_cpu = wall - sum(p.time_s for p in poses), cpu - sum(p.cpu_s for p in poses)
        steps.append((scene_wall, scene_cpu))
        j = judge(truth, object_id, instances, poses, pick_order(poses, settings.max_occlusion))
        bins.append(j)
        v = j["verdicts"]
        print(f"{path.name}: {j['parts']} parts ({j['visible_parts']} visible), {j['instances']} instances "
              f"({j['phantom_instances']} phantom), {len(v)} ok poses ({sum(x.wrong for x in v)} wrong), "
              f"{sum(x.picked for x in v)} picks ({sum(x.picked and not x.within_pick_tolerance for x in v)} out of "
              f"tolerance); pose step {1000 * wall:.0f} ms wall, {1000 * cpu:.0f} ms CPU, of which instances and "
              f"scene context {1000 * scene_wall:.0f} ms wall, {1000 * scene_cpu:.0f} ms CPU",
              flush=True)
        records.append({"session": str(path), **{k: x for k, x in j.items() if k != "verdicts"},
                        "verdicts": [vars(x) for x in v], "pose_times_s": [[p.time_s, p.cpu_s] for p in poses],
                        "bin_step_s": [scene_wall, scene_cpu]})
        if args.rows:   # one JSON line per bin: what `--summary` needs
            with open(args.rows, "a") as f:
                f.write(json.dumps(records[-1], default=float) + "\n")
    text = saved_bins_summary(bins, np.array(times), (PICK_MM, PICK_DEG), (WRONG_MM, WRONG_DEG), np.array(steps))
    print(text)
    load1 = os.getloadavg()
    print(f"load average at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    return {"bench": "saved bins", "method": settings.method, "bins": records, "summary": text.splitlines(),
            "load_average": {"start": load0, "end": load1}}


def rows_summary(args: argparse.Namespace) -> int:
    """`slscan posebench --summary ROWS...`: the saved-bins figures of rows files written by
    `--sessions --rows` runs (a long benchmark run in pieces, or stopped part way); the summary lines."""
    import numpy as np

    from sim.bin_judge import PICK_DEG, PICK_MM, WRONG_DEG, WRONG_MM, PoseVerdict

    bins, times, steps = [], [], []
    for path in args.summary:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            try:
                doc = json.loads(line)
                bins.append({**doc, "verdicts": [PoseVerdict(**v) for v in doc["verdicts"]]})
                times += doc["pose_times_s"]
                steps.append(doc.get("bin_step_s"))   # rows written before it was recorded lack it
            except (ValueError, KeyError, TypeError) as exc:
                from scanner.errors import ScannerError

                raise ScannerError(f"{path}, line {n}: not a saved-bins row of `slscan posebench --sessions --rows` "
                                   f"({exc})") from None
    print(f"{len(bins)} saved bins from {len(args.summary)} rows file(s)")
    known = None if any(x is None for x in steps) else np.array(steps, dtype=float).reshape(-1, 2)
    text = saved_bins_summary(bins, np.array(times).reshape(-1, 2), (PICK_MM, PICK_DEG), (WRONG_MM, WRONG_DEG), known)
    print(text)
    return {"bench": "summary of saved bins", "rows_files": [str(p) for p in args.summary], "bins": len(bins),
            "summary": text.splitlines()}


def saved_bins_summary(bins: list[dict[str, Any]], times: np.ndarray, pick: tuple[float, float],
                       wrong: tuple[float, float], steps: np.ndarray | None = None) -> str:
    """The acceptance figures over saved bins (see `saved_bins_bench`); `times` (parts, 2)
    each part's pose (wall, CPU s), `steps` (bins, 2) each bin's instances and scene
    context (None: not recorded). The time per part with its share of the bin step (all
    bin steps and part poses over the instances posed) is what a robot cell waits per part."""
    import numpy as np

    v = [x for b in bins for x in b["verdicts"]]
    picks = [x for x in v if x.picked]
    occ = np.array([x.occlusion - x.true_occlusion for x in v if x.part >= 0])
    te = np.array([x.trans_mm for x in v if not x.wrong] or [np.nan])
    re = np.array([x.rot_deg for x in v if not x.wrong] or [np.nan])
    tot = lambda k: sum(b[k] for b in bins)  # noqa: E731
    lines = [
        f"bins                          {len(bins)}",
        f"true parts                    {tot('parts')} ({tot('visible_parts')} showing >= 200 pixels)",
        f"instances found               {tot('instances')} ({tot('phantom_instances')} mostly off every part); "
        f"parts with an instance {tot('parts_with_instance')}",
        f"poses reported ok             {len(v)}: right (side, <= {wrong[0]} mm / {wrong[1]} deg) "
        f"{len(v) - sum(x.wrong for x in v)}, "
        f"wrong {sum(x.wrong for x in v)}; parts posed {tot('parts_posed')} of {tot('visible_parts')} visible",
        f"  error of the right ones     translation median {np.median(te):.4f} mm, max {np.max(te):.4f}; "
        f"rotation median {np.median(re):.3f} deg, max {np.max(re):.3f}",
        f"  within {pick[0]} mm / {pick[1]} deg   {sum(x.within_pick_tolerance for x in v)}",
        f"picks offered                 {len(picks)}: outside {pick[0]} mm / {pick[1]} deg "
        f"{sum(not x.within_pick_tolerance for x in picks)}",
        "occlusion estimate - truth    " + (f"median {np.median(occ):+.3f}, min {occ.min():+.3f}, max {occ.max():+.3f} "
                                           f"over {len(occ)} poses" if len(occ) else "no poses"),
        f"time per part pose            median {1000 * np.median(times[:, 0]):.0f} ms wall, "
        f"{1000 * np.median(times[:, 1]):.0f} ms CPU; 90 % {1000 * np.percentile(times[:, 0], 90):.0f} ms wall, "
        f"{1000 * np.percentile(times[:, 1], 90):.0f} ms CPU (one BLAS and one OpenCV thread)"]
    if steps is not None and len(steps) and len(times):
        share = (steps.sum(axis=0) + times.sum(axis=0)) / len(times)
        lines += [f"time per bin, instances and scene context   median {1000 * np.median(steps[:, 0]):.0f} ms wall, "
                  f"{1000 * np.median(steps[:, 1]):.0f} ms CPU; max {1000 * steps[:, 0].max():.0f} ms wall, "
                  f"{1000 * steps[:, 1].max():.0f} ms CPU",
                  f"time per part, bin step shared              mean {1000 * share[0]:.0f} ms wall, "
                  f"{1000 * share[1]:.0f} ms CPU ((bin steps + poses) / {len(times)} instances posed)"]
    return "\n".join(lines)


def _case(r: dict[str, Any]) -> str:
    side = "front" if r["front_up"] else "back"
    return f"occluded {side}" if r["occlusion"] >= 0.02 else f"{side} up"


def summary(rows: list[dict[str, Any]], methods: list[str], trans_tol: float = 0.1, rot_tol: float = 0.5) -> str:
    """Acceptance figures per method over the parts less than 30 % occluded, and the
    four-case table (success: a pose within the tolerances with the right side)."""
    import numpy as np

    out = []
    for m in methods:
        rs = [r for r in rows if r["method"] == m]
        acc = [r for r in rs if r["occlusion"] < 0.3]
        found = [r for r in acc if r["found"]]
        heavy = [r for r in rs if r["occlusion"] >= 0.3]
        wrong = [r for r in rs if r["found"] and not (r["trans_mm"] <= trans_tol and r["rot_deg"] <= rot_tol
                                                      and r["side_ok"])]
        timed = [r for r in rs if "wall_s" in r]
        te = np.array([r["trans_mm"] for r in found]) if found else np.array([np.nan])
        re = np.array([r["rot_deg"] for r in found]) if found else np.array([np.nan])
        out.append(f"== {m} + ICP: {len(rs)} parts, {len(acc)} less than 30 % occluded")
        out.append(f"  found (pose reported)        {len(found)}/{len(acc)} = {len(found) / max(len(acc), 1):.1%}")
        out.append(f"  translation error (origin)   median {np.median(te):.4f} mm, 95 % {np.percentile(te, 95):.4f}, "
                   f"max {te.max():.4f}; within {trans_tol} mm: {np.mean(te <= trans_tol):.1%}")
        out.append(f"  rotation error               median {np.median(re):.4f} deg, 95 % {np.percentile(re, 95):.4f}, "
                   f"max {re.max():.4f}; within {rot_tol} deg: {np.mean(re <= rot_tol):.1%}")
        side_ok = np.mean([r["side_ok"] for r in found]) if found else float("nan")
        out.append(f"  front/back correct           {side_ok:.2%}")
        wall, cpu = [r["wall_s"] for r in timed], [r["cpu_s"] for r in timed]
        out.append(f"  time per part                median {1000 * np.median(wall):.0f} ms wall, "
                   f"{1000 * np.median(cpu):.0f} ms CPU (mean {1000 * np.mean(wall):.0f} ms wall)")
        out.append(f"  >= 30 % occluded             {sum(r['found'] for r in heavy)}/{len(heavy)} posed; "
                   f"poses outside the tolerances or on the wrong side, all parts: {len(wrong)}")
    out.append("")
    out.append(f"paper 001 Tables 4-5: success = pose within {trans_tol:.1f} mm / {rot_tol:.1f} deg, right side "
               "(parts < 30 % occluded; occluded: >= 2 %)")
    out.append(f"{'method':<12} {'case':<16} {'parts':>5} {'success':>8} {'trans mm':>9} {'rot deg':>8} "
               f"{'ms wall':>8} {'ms CPU':>7}")
    for m in methods:
        for case in CASES:
            rs = [r for r in rows if r["method"] == m and r["occlusion"] < 0.3 and _case(r) == case]
            ok = [r for r in rs
                  if r["found"] and r["trans_mm"] <= trans_tol and r["rot_deg"] <= rot_tol and r["side_ok"]]
            f = [r for r in rs if r["found"]]
            t = [r for r in rs if "wall_s" in r]
            out.append(f"{m + ' + ICP':<12} {case:<16} {len(rs):>5} {len(ok) / max(len(rs), 1):>8.1%} "
                       f"{np.mean([r['trans_mm'] for r in f]) if f else float('nan'):>9.4f} "
                       f"{np.mean([r['rot_deg'] for r in f]) if f else float('nan'):>8.4f} "
                       f"{1000 * np.mean([r['wall_s'] for r in t]) if t else float('nan'):>8.0f} "
                       f"{1000 * np.mean([r['cpu_s'] for r in t]) if t else float('nan'):>7.0f}")
    return "\n".join(out)
