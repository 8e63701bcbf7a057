"""`slscan pose` and `slscan posebench`: poses of thin flat parts in a bin for a robot cell
(paper 001), and their benchmark on simulated bins.

`slscan pose SESSION|CLOUD --part FILE [--masks PATH] [--method sacia|ndt]` finds the part
instances (from instance masks aligned with the camera image — label PNGs or Labelme JSON
— or, without masks, by removing the tray plane and splitting the rest at depth steps),
estimates each instance's pose (`inspection.bins.pose`), ranks the pickable ones
(`inspection.bins.picking`), writes the poses file (`<session>/outputs/poses.json`, or
`<cloud stem>.poses.json` beside a cloud file), prints the table and logs the bin to a
Rerun recording beside the poses file. A cloud file is placed on the camera image of the
rig (`--rig`, default the simulated bench rig), as slscan's own clouds are in its camera
frame. The part file is a TOML `[part]` table (`kind = "tab"`: the parameters of
`sim.bins.TabPart`, see config/parts/nickel_tab.toml) or a mesh (PLY, STL, OBJ, OFF; mm).
Exit code 0 when at least one part is pickable, 1 when none is (the file is written anyway).

`slscan posebench` renders simulated bins (`sim.bins.bin_scene` + `scan_bin`: ray-cast
truth, depth noise, projector shadows), poses every part from the simulator's instance
masks with each method, and prints the acceptance figures against the true poses and the
four-case table of paper 001 (Tables 4-5).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

MESH_SUFFIXES = (".ply", ".stl", ".obj", ".off")


def register(sub: Any) -> None:
    from scanner.rig import DEFAULT_RIG

    p = sub.add_parser("pose", help="poses and pick order of thin flat parts in a bin (poses JSON for a robot cell)")
    p.add_argument("input", help="a session folder or a point cloud file in the camera frame")
    p.add_argument("--part", required=True, help="part file: TOML with a [part] table (kind = \"tab\") or a mesh (mm)")
    p.add_argument("--masks", help="instance masks aligned with the camera image: a label PNG, a Labelme JSON, or "
                                   "a folder of them (default: tray removal + depth-step components)")
    p.add_argument("--method", choices=("sacia", "ndt"), default="sacia",
                   help="coarse registration: FPFH + SAC-IA with the Huber score (default) or NDT")
    p.add_argument("--max-occlusion", type=float, default=0.3, metavar="FRACTION",
                   help="parts covered more than this are not offered for picking (default 0.3)")
    p.add_argument("--rig", type=Path, default=DEFAULT_RIG, help="rig TOML for a cloud file (camera, world frame)")
    p.add_argument("--out", help="poses file (.json); default <session>/outputs/poses.json or <cloud>.poses.json")
    p.add_argument("--no-log", action="store_true", help="do not write the Rerun recording")
    p.set_defaults(func=cmd_pose)

    b = sub.add_parser("posebench", help="pose parts in simulated bins and score them against the truth "
                                         "(both methods, paper 001's four cases)")
    b.add_argument("--seeds", type=int, nargs="+", default=list(range(50)), help="bin seeds (default 0..49)")
    b.add_argument("--methods", nargs="+", choices=("sacia", "ndt"), default=["sacia", "ndt"])
    b.add_argument("--size", type=int, nargs=2, default=(1280, 1024), metavar=("W", "H"),
                   help="camera resolution of the rig the bins are rendered with (default the rig's 1280 x 1024)")
    b.add_argument("--noise", type=float, default=0.01, metavar="MM", help="depth noise along the camera rays")
    b.add_argument("--fringe", action="store_true",
                   help="scan each bin through the whole simulated chain (fringes rendered, decoded, triangulated) "
                        "on the default rig instead of the quick ray-cast scan (--size and --noise then do not apply)")
    b.add_argument("--rows", help="append every part's row to this file (JSON lines, bin by bin)")
    b.set_defaults(func=cmd_posebench)


# ------------------------------------------------------------------------------ inputs


def load_part(path: str | Path) -> Any:
    """The `inspection.bins.part_model.ThinPartModel` of a part file (see the module docstring)."""
    import tomllib
    from dataclasses import fields

    from inspection.bins.part_model import ThinPartModel
    from inspection.errors import CadError

    path = Path(path)
    if not path.is_file():
        raise CadError(path, "no such part file")
    suffix = path.suffix.lower()
    if suffix == ".toml":
        from sim.bins import TabPart

        try:
            doc = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise CadError(path, f"not a readable TOML file: {exc}") from None
        table = doc.get("part")
        if not isinstance(table, dict):
            raise CadError(path, "no [part] table; see config/parts/nickel_tab.toml")
        params = dict(table)
        kind, name = params.pop("kind", None), str(params.pop("name", path.stem))
        if kind != "tab":
            raise CadError(path, f"[part] kind = {kind!r}: only \"tab\" (a sim.bins.TabPart outline) is known; "
                                 "give a mesh file for other parts")
        known = {f.name for f in fields(TabPart)}
        unknown = sorted(set(params) - known)
        if unknown:
            raise CadError(path, f"[part] has unknown keys {unknown}; known: {sorted(known | {'kind', 'name'})}")
        try:
            part = TabPart(**{k: tuple(v) if isinstance(v, list) else v for k, v in params.items()})
            vertices, triangles = part.mesh()
        except (TypeError, ValueError) as exc:
            raise CadError(path, f"[part]: {exc}") from None
        return ThinPartModel.from_mesh(vertices, triangles, name)
    if suffix in MESH_SUFFIXES:
        import open3d as o3d

        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles) == 0:
            raise CadError(path, "no triangles could be read (unreadable or empty mesh)")
        return ThinPartModel.from_mesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), path.stem)
    raise CadError(path, f"unsupported part file: expected .toml or a mesh ({', '.join(MESH_SUFFIXES)})")


def _organise(points: np.ndarray, normals: np.ndarray | None, camera: Any, where: str) -> Any:
    """An organised cloud on `camera`'s image from camera-frame points (nearest point per
    pixel), with normals from the organised points where none are given."""
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


def load_scene(path: Path, rig: Path) -> tuple[Any, Any, Any]:
    """(organised cloud, rig model, session or None) of a session or a cloud file (placed
    on the camera of the rig TOML `rig`)."""
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
    if not path.is_file():
        raise CloudError(path, "no such cloud file or session folder")
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(path))
    points = np.asarray(pc.points, dtype=np.float64)
    if len(points) == 0:
        raise CloudError(path, "no points could be read (unreadable or empty cloud)")
    model = RigConfig.load(rig).nominal_model()
    normals = np.asarray(pc.normals, dtype=np.float64) if pc.has_normals() else None
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


def cmd_pose(args: argparse.Namespace) -> int:
    from inspection.bins.instances import instances_from_depth_steps
    from inspection.bins.picking import merge_duplicates, poses_document, table, write_poses
    from inspection.bins.pose import estimate_poses
    from inspection.bins.pose_settings import PoseSettings

    model = load_part(args.part)
    src = Path(args.input)
    cloud, rig_model, session = load_scene(src, args.rig)
    world_from_cam = np.asarray(rig_model.world_from_cam, np.float64)
    if session is not None:
        out = Path(args.out) if args.out else session.outputs / "poses.json"
    else:
        out = Path(args.out) if args.out else src.with_name(src.stem + ".poses.json")
    if out.suffix != ".json":
        from scanner.errors import ScannerError

        raise ScannerError(f"{out}: the poses file must end in .json")
    if args.masks:
        instances = load_masks(Path(args.masks), cloud)
        how = f"masks {args.masks}"
    else:
        instances = instances_from_depth_steps(cloud, step_mm=0.4 * model.thickness_mm,
                                               tray_tol_mm=0.3 * model.thickness_mm)
        how = "tray removal + depth-step components"
    print(f"{len(instances)} instances in {src} ({how}); part {model.name}, method {args.method}", file=sys.stderr)
    settings = PoseSettings(method=args.method, max_occlusion=args.max_occlusion)
    poses = merge_duplicates(estimate_poses(instances, model, cloud.points[cloud.valid], settings))
    message = ""
    if not instances:
        message = (f"no parts found in {src}: no instance in the masks" if args.masks else
                   f"no parts found in {src}: nothing stands above the tray plane")
    elif not any(p.ok for p in poses):
        message = f"no part recognised in {src}: none of the {len(poses)} instances fits {model.name}"
    doc = poses_document(poses, model, world_from_cam, str(src), args.max_occlusion, message)
    write_poses(out, doc)
    print(table(doc))
    print(f"poses     {out}")
    if not args.no_log:
        from inspection.bins.picking import log_poses
        from scanner.session_recording import SessionRecording

        rrd = out.with_name(out.stem + ".rrd")
        with SessionRecording(rrd, session.id if session is not None else src.stem, send_blueprint=False) as rec:
            rec.log_rig(rig_model)
            rec.log_cloud(cloud)
            log_poses(rec, doc, poses, instances, model)
        print(f"recording {rrd}")
    return 0 if any(r["pick_rank"] is not None for r in doc["parts"]) else 1


# ------------------------------------------------------------------------- benchmark


CASES = ("front up", "back up", "occluded front", "occluded back")


def cmd_posebench(args: argparse.Namespace) -> int:
    """Per bin: render, lift the simulator's instance masks, pose every part with each
    method (wall and process CPU time per part), compare with the true poses."""
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
        context = SceneContext(cloud.points[cloud.valid])
        for method in args.methods:
            settings = PoseSettings(method=method)
            for k in range(n):
                inst = instances.get(k + 2)
                row = {"seed": seed, "part": k, "method": method, "occlusion": float(truth_occ[k]),
                       "front_up": bool(b.front_up[k]), "points": len(inst) if inst else 0, "found": False}
                if inst is not None:
                    cpu = time.process_time()
                    r = estimate_pose(inst, models[method], context, settings)
                    row["cpu_s"] = time.process_time() - cpu
                    row["wall_s"] = r.time_s
                    row["found"] = r.ok
                    row["reason"] = r.reason
                    if r.ok:
                        rot, trans = pose_difference(b.poses[k], r.pose)
                        row.update(rot_deg=rot, trans_mm=trans, trans_centre_mm=pose_difference(b.poses[k], r.pose, centre)[1],
                                   side_ok=(r.side == "front") == bool(b.front_up[k]), est_occlusion=r.occlusion)
                rows.append(row)
        done = [r for r in rows if r["seed"] == seed]
        if args.rows:   # one JSON line per part, written as each bin is done
            with open(args.rows, "a") as f:
                f.writelines(json.dumps(r) + "\n" for r in done)
        print(f"bin {seed}: {n} parts; " + "; ".join(
            f"{m} {sum(r['found'] for r in done if r['method'] == m)} posed" for m in args.methods), flush=True)
    load1 = os.getloadavg()
    print(summary(rows, args.methods))
    print(f"load average at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    return 0


def _case(r: dict[str, Any]) -> str:
    side = "front" if r["front_up"] else "back"
    return f"occluded {side}" if r["occlusion"] >= 0.02 else f"{side} up"


def summary(rows: list[dict[str, Any]], methods: list[str], trans_tol: float = 0.1, rot_tol: float = 0.5) -> str:
    """Acceptance figures per method over the parts less than 30 % occluded, and the
    four-case table (success: a pose within the tolerances with the right side)."""
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
        out.append(f"  front/back correct           {np.mean([r['side_ok'] for r in found]) if found else float('nan'):.2%}")
        out.append(f"  time per part                median {1000 * np.median([r['wall_s'] for r in timed]):.0f} ms wall, "
                   f"{1000 * np.median([r['cpu_s'] for r in timed]):.0f} ms CPU (mean {1000 * np.mean([r['wall_s'] for r in timed]):.0f} ms wall)")
        out.append(f"  >= 30 % occluded             {sum(r['found'] for r in heavy)}/{len(heavy)} posed; "
                   f"poses outside the tolerances or on the wrong side, all parts: {len(wrong)}")
    out.append("")
    out.append("paper 001 Tables 4-5: success = pose within %.1f mm / %.1f deg, right side (parts < 30 %% occluded; "
               "occluded: >= 2 %%)" % (trans_tol, rot_tol))
    out.append(f"{'method':<12} {'case':<16} {'parts':>5} {'success':>8} {'trans mm':>9} {'rot deg':>8} {'ms wall':>8} {'ms CPU':>7}")
    for m in methods:
        for case in CASES:
            rs = [r for r in rows if r["method"] == m and r["occlusion"] < 0.3 and _case(r) == case]
            ok = [r for r in rs if r["found"] and r["trans_mm"] <= trans_tol and r["rot_deg"] <= rot_tol and r["side_ok"]]
            f = [r for r in rs if r["found"]]
            t = [r for r in rs if "wall_s" in r]
            out.append(f"{m + ' + ICP':<12} {case:<16} {len(rs):>5} {len(ok) / max(len(rs), 1):>8.1%} "
                       f"{np.mean([r['trans_mm'] for r in f]) if f else float('nan'):>9.4f} "
                       f"{np.mean([r['rot_deg'] for r in f]) if f else float('nan'):>8.4f} "
                       f"{1000 * np.mean([r['wall_s'] for r in t]) if t else float('nan'):>8.0f} "
                       f"{1000 * np.mean([r['cpu_s'] for r in t]) if t else float('nan'):>7.0f}")
    return "\n".join(out)
