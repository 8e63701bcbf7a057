"""Part-in-whole registration measured on parts nobody chose (issue 26): random prismatic
parts (`sim.random_parts`) and the NIST STEP files, each at a random placement on the
simulated table, scanned through the whole fringe chain as the scanner writes the cloud
(table in view), then registered from a random start exactly as `slscan register` does
(`isolate_part`, `register`, exit 0 only for a proven pose), with Open3D's FPFH + RANSAC +
ICP on the same isolated clouds beside it.

    python -m studies.registration_bench scan OUT --parts 60 [--seed S]     scans into OUT (seeds printed)
    python -m studies.registration_bench evaluate OUT [--shard K/N]           registers them, prints the table
    python -m studies.registration_bench summary OUT                          the table of every shard's results

A seed not given is drawn from the operating system and printed: every measurement runs on
new parts. Outcomes per scan: "success" (proven, within 0.05 deg and 0.05 mm of the truth at
the part's centroid), "wrong" (proven, exit 0, beyond that), "refused" (exit 1: ambiguous;
exit 2: registration failed, with the reason). Times: wall seconds of isolation plus
registration per scan, the model prepared once per part (sampling and sphere descriptors,
reported apart), with the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from inspection.registration.settings import RegistrationSettings

# a success is a pose within the tolerance the proof proves poses to (deg, mm)
SUCCESS_DEG, SUCCESS_MM = RegistrationSettings.pose_tolerance_deg, RegistrationSettings.pose_tolerance_mm
NIST = {"nist_ctc_01_asme1_rd.stp": (0.16, (0.0, 0.0, 1.0)), "nist_ctc_01_asme1_ap242-e1.stp": (0.16, (0.0, 0.0, 1.0)),
        "nist_ftc_06_asme1_rd.stp": (0.4, (0.0, 1.0, 0.0))}  # scale models that fit the bench, as in the NIST test
NIST_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "step"


@dataclass(frozen=True)
class Case:
    """One scan of a campaign: the STEP file, its scale and up axis, the seeds."""

    name: str
    step: str
    scale: float
    up: tuple[float, float, float]
    part_seed: int | None
    placement_seed: int
    noise_seed: int
    start_seed: int


def scan_cases(out: Path, parts: int, seed: int, nist_placements: int = 2) -> list[Case]:
    """Generate `parts` random parts and scan each once, and each NIST file
    `nist_placements` times, into `out` (npz per scan and cases.json)."""
    from sim.random_parts import random_part

    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    cases = []
    for i in range(parts):
        ps, ls, ns, ss = (int(x) for x in rng.integers(0, 2 ** 31, 4))
        part = random_part(ps)
        step = part.write(out / f"part_{i:03d}.step")
        cases.append(Case(f"part_{i:03d}", str(step), 1.0, (0.0, 0.0, 1.0), ps, ls, ns, ss))
    if NIST_DIR.is_dir():
        for file, (scale, up) in NIST.items():
            for k in range(nist_placements):
                ls, ns, ss = (int(x) for x in rng.integers(0, 2 ** 31, 3))
                cases.append(Case(f"{Path(file).stem}_{k}", str(NIST_DIR / file), scale, up, None, ls, ns, ss))
    (out / "cases.json").write_text(json.dumps([asdict(c) for c in cases], indent=1))
    scan_saved(out, cases)
    return cases


def scan_saved(out: Path, cases: list[Case]) -> None:
    """Scan every case of `out` not scanned yet (a campaign cut short goes on where it was)."""
    import gc

    from inspection.cad import load_cad
    from sim.random_parts import placement_for, scan_part

    for c in cases:
        if (out / f"{c.name}.npz").exists():
            continue
        t0 = time.perf_counter()
        model = load_cad(c.step, scale=c.scale)
        fine = load_cad(c.step, scale=c.scale, deflection_mm=1e-3 * max(1.0, model.diagonal_mm / 100.0))
        lo, hi = fine.tessellation.vertices.min(axis=0), fine.tessellation.vertices.max(axis=0)
        footprint = float(np.linalg.norm((hi - lo)[np.abs(np.asarray(c.up)) < 0.5]))
        placement = placement_for(footprint, c.placement_seed)
        s = scan_part(fine, placement, c.noise_seed, up=c.up)
        np.savez(out / f"{c.name}.npz", points=s.scan.points.astype(np.float32),
                 normals=s.scan.normals.astype(np.float32), pixels=s.scan.pixels.astype(np.int16), truth=s.truth,
                 face=s.true_face.astype(np.int16), shape=np.array(s.scan.image_shape))
        print(f"scanned {c.name} ({Path(c.step).name}, scale {c.scale}, rig x{placement.rig_scale:.2f}): "
              f"{len(s.scan)} points, {time.perf_counter() - t0:.1f} s", flush=True)
        del s, model, fine
        gc.collect()  # the fine tessellations and the simulator's buffers: one part's at a time


def random_start(seed: int) -> np.ndarray:
    """A random rigid motion: rotation uniform on SO(3), translation within 300 mm."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    G = np.eye(4)
    G[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    G[:3, 3] = rng.uniform(-300.0, 300.0, 3)
    return G


def open3d_baseline(points: np.ndarray, normals: np.ndarray, target: Any, voxel: float) -> np.ndarray:
    """Open3D's own pipeline, single start: FPFH on both voxel clouds, RANSAC on feature
    matches (mutual filter), then point-to-plane ICP against the dense model samples."""
    import open3d as o3d

    reg = o3d.pipelines.registration

    def cloud(p: np.ndarray, n: np.ndarray) -> Any:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
        pc.normals = o3d.utility.Vector3dVector(n)
        return pc

    src = cloud(points, normals).voxel_down_sample(voxel)
    dst = cloud(target.coarse.points, target.coarse.normals)
    param = o3d.geometry.KDTreeSearchParamHybrid(5 * voxel, 100)
    fs, fd = reg.compute_fpfh_feature(src, param), reg.compute_fpfh_feature(dst, param)
    ransac = reg.registration_ransac_based_on_feature_matching(
        src, dst, fs, fd, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    icp = reg.registration_icp(cloud(points, normals).voxel_down_sample(voxel / 4),
                               cloud(target.dense.points, target.dense.normals), voxel, ransac.transformation,
                               reg.TransformationEstimationPointToPlane())
    return np.asarray(icp.transformation)


def evaluate(out: Path, open3d: bool = True, ours: bool = True, shard: tuple[int, int] = (0, 1)) -> list[dict]:
    """Register every scan of `out` from its random start (module docstring), ours and/or
    Open3D's, or, with `shard` (k, n), every n-th from the k-th (processes sharing the
    cases); cases another run already wrote a result for are skipped. One JSON line per scan
    in `out`/results_<what>_k_n.jsonl; the table printed."""
    from inspection.cad import load_cad
    from inspection.errors import InspectionError
    from inspection.measured_cloud import ScanCloud, isolate_part
    from inspection.registration import ModelTarget, pose_difference
    from scanner.native_threads import native_threads

    cases = [Case(**{**c, "up": tuple(c["up"])}) for c in json.loads((out / "cases.json").read_text())]
    done = merged(out)
    what = "both" if ours and open3d else "ours" if ours else "open3d"
    rows = []
    with (out / f"results_{what}_{shard[0]}_{shard[1]}.jsonl").open("a") as log, native_threads(1):
        for c in cases[shard[0]::shard[1]]:
            have = done.get(c.name, {})
            todo_ours, todo_o3d = ours and "outcome" not in have, open3d and "open3d_success" not in have
            if not (out / f"{c.name}.npz").exists() or not (todo_ours or todo_o3d):
                continue
            d = np.load(out / f"{c.name}.npz")
            model = load_cad(c.step, scale=c.scale)
            t0 = time.perf_counter()
            target = ModelTarget.from_cad(model)
            G = random_start(c.start_seed)
            scan = ScanCloud(d["points"].astype(np.float64) @ G[:3, :3].T + G[:3, 3],
                             d["normals"].astype(np.float64) @ G[:3, :3].T, c.name, G[:3, 3].copy(),
                             d["pixels"].astype(np.int64), tuple(int(x) for x in d["shape"]))
            truth = d["truth"] @ np.linalg.inv(G)  # moved scan -> model
            row: dict[str, Any] = {"case": c.name, "step": Path(c.step).name, "part_seed": c.part_seed,
                                   "placement_seed": c.placement_seed, "noise_seed": c.noise_seed,
                                   "start_seed": c.start_seed, "faces": len(model), "diagonal_mm": model.diagonal_mm}
            try:
                t1 = time.perf_counter()
                part = isolate_part(scan, target.diagonal_mm)
                isolate_s = time.perf_counter() - t1
            except InspectionError as exc:
                part, isolate_s = None, time.perf_counter() - t1
                if todo_ours:
                    row.update(exit=2, reason=str(exc), seconds=round(isolate_s, 2))
            if todo_ours and part is not None:
                row.update(_ours(part, target, truth, c.start_seed, isolate_s, t0))
            if todo_ours:
                good = row.get("angle_deg", np.inf) <= SUCCESS_DEG and row.get("shift_mm", np.inf) <= SUCCESS_MM
                row["outcome"] = ("success" if row["exit"] == 0 and good else "wrong" if row["exit"] == 0
                                  else "refused")
                row["right_but_refused"] = bool(row["exit"] == 1 and good)
            if todo_o3d and part is not None:
                t1 = time.perf_counter()
                T = open3d_baseline(part.points, part.normals, target, target.voxel_mm)
                a, s = pose_difference(T, truth, part.points.mean(axis=0))
                row.update(open3d_angle_deg=a, open3d_shift_mm=s, open3d_seconds=round(time.perf_counter() - t1, 2),
                           open3d_success=bool(a <= SUCCESS_DEG and s <= SUCCESS_MM))
            row["load"] = os.getloadavg()[0]
            rows.append(row)
            log.write(json.dumps(row, default=float) + "\n")
            log.flush()
            print(_line(row), flush=True)
    print(summary(list(merged(out).values())))
    return rows


def _ours(part: Any, target: Any, truth: np.ndarray, seed: int, isolate_s: float, t0: float) -> dict[str, Any]:
    """Our registration of the isolated `part` as `slscan register` runs it: the figures of
    one row (`evaluate`); `t0` when the model's preparation began."""
    from inspection.errors import InspectionError
    from inspection.registration import RegistrationSettings, pose_difference, register

    row: dict[str, Any] = {}
    target.prepare(part)  # the model's once-per-part cost, apart
    row["model_s"] = round(time.perf_counter() - t0 - isolate_s, 2)
    t1 = time.perf_counter()
    try:
        reg = register(part, target, RegistrationSettings(seed=seed))
    except InspectionError as exc:
        return {**row, "exit": 2, "reason": str(exc), "seconds": round(isolate_s + time.perf_counter() - t1, 2)}
    angle, shift = pose_difference(reg.transform, truth, part.points.mean(axis=0))
    return {**row, "seconds": round(isolate_s + time.perf_counter() - t1, 2), "exit": 0 if reg.proven else 1,
            "status": reg.status, "angle_deg": angle, "shift_mm": shift, "reason": reg.reason,
            "free": [m.describe() for m in reg.free], "fitness": reg.fitness, "alternatives": len(reg.alternatives),
            "u": reg.covariance.bounds() if reg.covariance is not None else None}


def merged(out: Path) -> dict[str, dict[str, Any]]:
    """Every result row written in `out`, ours and Open3D's merged per case."""
    cases: dict[str, dict[str, Any]] = {}
    for f in sorted(out.glob("results_*.jsonl")):
        for line in f.open():
            r = json.loads(line)
            cases.setdefault(r["case"], {}).update(r)
    return cases


def _line(r: dict[str, Any]) -> str:
    err = f"{r['angle_deg']:.4f} deg {r['shift_mm']:.4f} mm" if "angle_deg" in r else "-"
    o3d = (f"; open3d {r['open3d_angle_deg']:.3f} deg {r['open3d_shift_mm']:.3f} mm"
           if "open3d_angle_deg" in r else "")
    return (f"{r['case']:<34} exit {r.get('exit', '-')} {r.get('outcome', '-'):<8} {err} {r.get('seconds', 0):6.1f} s"
            f"{o3d}{'; ' + r['reason'][:160] if r.get('reason') else ''}")


def summary(rows: list[dict[str, Any]]) -> str:
    """The campaign's figures as text."""
    o3d = [r for r in rows if "open3d_success" in r]
    rows = [r for r in rows if "outcome" in r]
    n = len(rows)
    if not n:
        return "no scans"
    count = {k: sum(r["outcome"] == k for r in rows) for k in ("success", "wrong", "refused")}
    secs = [r["seconds"] for r in rows if r["exit"] != 2]
    lines = [f"{n} scans: success {count['success']} ({count['success'] / n:.1%}), wrong with exit 0 "
             f"{count['wrong']}, refused {count['refused']} (of which the best pose was right: "
             f"{sum(r['right_but_refused'] for r in rows)})",
             f"Open3D FPFH+RANSAC+ICP on the same clouds: {sum(r['open3d_success'] for r in o3d)} of {len(o3d)} "
             f"within {SUCCESS_DEG} deg / {SUCCESS_MM} mm",
             f"time per scan (isolation + registration, model prepared once): median "
             f"{np.median(secs) if secs else float('nan'):.1f} s; Open3D median "
             f"{np.median([r['open3d_seconds'] for r in o3d]) if o3d else float('nan'):.1f} s; load average "
             f"{np.median([r['load'] for r in rows]):.1f}"]
    lines += [f"  refused: {r['case']} exit {r['exit']}: {r['reason']}" for r in rows if r["outcome"] == "refused"]
    lines += [f"  WRONG: {r['case']} {r['angle_deg']:.3f} deg {r['shift_mm']:.3f} mm" for r in rows
              if r["outcome"] == "wrong"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.registration_bench", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    s = sub.add_parser("scan", help="new cases (a fresh seed) or, with --resume, the rest of OUT's")
    s.add_argument("out", type=Path)
    s.add_argument("--resume", action="store_true", help="scan the cases of OUT/cases.json not scanned yet")
    s.add_argument("--parts", type=int, default=60)
    s.add_argument("--nist-placements", type=int, default=2)
    s.add_argument("--seed", type=int, default=None, help="default: drawn fresh and printed")
    e = sub.add_parser("evaluate")
    e.add_argument("out", type=Path)
    e.add_argument("--no-open3d", action="store_true", help="ours only")
    e.add_argument("--open3d-only", action="store_true", help="Open3D's only")
    e.add_argument("--shard", default="0/1", help="K/N: every N-th case from the K-th (default all)")
    t = sub.add_parser("summary")
    t.add_argument("out", type=Path)
    args = p.parse_args(argv)
    if args.what == "scan" and args.resume:
        cases = [Case(**{**c, "up": tuple(c["up"])}) for c in json.loads((args.out / "cases.json").read_text())]
        scan_saved(args.out, cases)
    elif args.what == "scan":
        seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2 ** 31)
        print(f"campaign seed {seed}", flush=True)
        scan_cases(args.out, args.parts, seed, args.nist_placements)
    elif args.what == "evaluate":
        k, n = (int(x) for x in args.shard.split("/"))
        evaluate(args.out, open3d=not args.no_open3d, ours=not args.open3d_only, shard=(k, n))
    else:
        print(summary(list(merged(args.out).values())))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
