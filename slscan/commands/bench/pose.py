"""`slscan bench pose`: poses of thin parts in simulated bins, or in saved ones, against their
truth. It renders simulated bins (`sim.bins.bin_scene` + `scan_bin`: ray-cast
truth, depth noise, projector shadows), poses every part from the simulator's instance
masks with each method, and prints the acceptance figures against the true poses and the
four-case table of paper 001 (Tables 4-5). `slscan bench pose --sessions DIR...` judges
`slscan pose` on saved bins instead (`slscan scan --scene bin:SEED`); with `--rows FILE` it
writes one JSON line per bin, and `slscan bench pose --summary FILE...` prints the figures of
such rows files, so that a run over many bins can be done in pieces.
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

from slscan.commands.pose import POSE_METHODS, load_scene, one_thread, pose_scene
from slscan.exit_codes import Exit
from slscan.options import add_json, coarse_method

if TYPE_CHECKING:
    import numpy as np


def register(sub: Any) -> None:
    b = sub.add_parser("pose")
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
    b.set_defaults(func=cmd_pose_bench)


CASES = ("front up", "back up", "occluded front", "occluded back")


def cmd_pose_bench(args: argparse.Namespace) -> int:
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
                    if r.ok and r.pose is not None:
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


def saved_bins_bench(args: argparse.Namespace) -> dict[str, Any]:
    """`slscan bench pose --sessions`: `pose_scene` on every saved bin, judged by
    `studies.bin_judge` (wall and CPU time of every part's pose, and of each bin's instances and context);
    the figures: each bin's judgement, the summary lines, the load averages."""
    import numpy as np

    from inspection.bins.instances import instances_from_label_image
    from inspection.bins.picking import pick_order
    from inspection.bins.pose_settings import PoseSettings
    from sim.bins import BIN_TRUTH_FILE, BinTruth, TabPart
    from sim.evaluate import Truth
    from studies.bin_judge import PICK_DEG, PICK_MM, WRONG_DEG, WRONG_MM, judge

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


def rows_summary(args: argparse.Namespace) -> dict[str, Any]:
    """`slscan bench pose --summary ROWS...`: the saved-bins figures of rows files written by
    `--sessions --rows` runs (a long benchmark run in pieces, or stopped part way); the summary lines."""
    import numpy as np

    from studies.bin_judge import PICK_DEG, PICK_MM, WRONG_DEG, WRONG_MM, PoseVerdict

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

                raise ScannerError(f"{path}, line {n}: not a saved-bins row of `slscan bench pose --sessions --rows` "
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
