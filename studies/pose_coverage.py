"""Does the registration's pose uncertainty cover? Repeat scans of one part, each at a fresh
random placement on the table (so the fringe systematics, fixed for one placement, are drawn
anew) with fresh noise, through the whole fringe chain; each registered (the part isolated
by the scanner's truth: the question here is the pose's U, not the table's removal) and its
error against the simulator's true pose set beside the covariance the registration states.

    python -m studies.pose_coverage OUT [--part demo|SEED] [--scans 100] [--seed S]

Each scan's cloud and truth are kept in OUT (`scan_K.npz`); run again with the same seed,
the scans are read back instead of taken (a change to the registration re-measured on the
same scans).

Coverage figures (target 95 % +- 3 %): the share of scans whose rotation error is within
the stated 95 % bound of the rotation angle (`rotation_u_deg`), whose displacement of the
fit's centre is within `translation_u_mm`, and whose error lies inside the covariance's
95 % ellipsoid (Mahalanobis distance squared below the chi-square 95 % point, 6 degrees of
freedom). A seed not given is drawn fresh and printed.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np


def placements(seed: int, n: int, rig_scale: float) -> list[Any]:
    """`n` random placements of a part on the table (turn, tilt 10-35 deg, offset within
    20 mm of the axis), the rig at `rig_scale`."""
    from sim.random_parts import Placement

    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a, tilt = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(10.0, 35.0))
        tilts = (float(tilt * np.cos(a)), float(tilt * np.sin(a)))
        out.append(Placement(seed + k, float(rng.uniform(0, 2 * np.pi)), tilts,
                             tuple(float(x) for x in rng.uniform(-20.0, 20.0, 2)), rig_scale))
    return out


def run(out: Path, part: str, scans: int, seed: int, command: bool = False) -> dict[str, Any]:
    """Scan and register `scans` times (module docstring); rows in `out`/coverage_SEED.jsonl.
    `command`: each scan written as the scanner writes its cloud (table in view, a PLY) and
    registered by `python -m slscan register CLOUD STEP --json` in its own process, the
    pose and its covariance read from that JSON (the command a user runs, table removal
    included)."""
    from scipy.stats import chi2

    from inspection.cad import load_cad
    from scanner.config import CONFIG_DIR
    from sim.random_parts import placement_for, random_part

    out.mkdir(parents=True, exist_ok=True)
    if part == "demo":
        step, scale = CONFIG_DIR / "parts" / "demo_part.step", 1.0
    else:
        p = random_part(int(part))
        step = p.write(out / f"part_{part}.step")
        scale = placement_for(float(np.hypot(p.length_mm, p.width_mm)), seed).rig_scale
    model = load_cad(step)
    fine = load_cad(step, deflection_mm=1e-3 * max(1.0, model.diagonal_mm / 100.0))
    measure = _by_command(step) if command else _in_process(model)
    rng = np.random.default_rng(seed)
    rows = []
    with (out / f"coverage_{seed}.jsonl").open("w") as log:
        for k, placement in enumerate(placements(seed, scans, scale)):
            noise = int(rng.integers(0, 2 ** 31))
            t0 = time.perf_counter()
            cloud = _scan(out / f"scan_{seed}_{k}", fine, placement, noise, command)
            status, T, cov, centre, inflation = measure(cloud, k)
            truth = np.load(out / f"scan_{seed}_{k}.npz")["truth"]
            row = {"scan": k, "placement_seed": placement.seed, "noise_seed": noise, "status": status,
                   "seconds": round(time.perf_counter() - t0, 1), "load": os.getloadavg()[0]}
            if cov is not None:
                row.update(_errors(truth, T, cov, centre), inflation=inflation)
            rows.append(row)
            log.write(json.dumps(row) + "\n")
            log.flush()
            print(f"{k:3d} {status}" + ("" if cov is None else
                  f" rot {row['rotation_deg']:.5f} (U {row['rotation_u_deg']:.5f}) deg, shift "
                  f"{row['translation_mm']:.5f} (U {row['translation_u_mm']:.5f}) mm, d2 {row['mahalanobis2']:.1f}, "
                  f"inflation {inflation:.2f}") + f", {row['seconds']} s", flush=True)
    result = coverage(rows, chi2.ppf(0.95, 6))
    print(json.dumps(result))
    return result


def _scan(stem: Path, fine: Any, placement: Any, noise: int, command: bool) -> Path:
    """The scan at `placement` with noise seed `noise`, taken once and kept: `stem`.npz (the
    part's points, pixels and the truth) and, for the command, `stem`.ply (the whole cloud as
    the scanner writes it)."""
    from scanner.pointcloud import write_ply
    from sim.random_parts import scan_part

    cache, ply = stem.with_suffix(".npz"), stem.with_suffix(".ply")
    if not cache.exists() or (command and not ply.exists()):
        s = scan_part(fine, placement, noise)
        on = s.true_face >= 0
        np.savez(cache, points=s.scan.points[on], normals=s.scan.normals[on], pixels=s.scan.pixels[on],
                 truth=s.truth, shape=np.array(s.scan.image_shape))
        if command:
            write_ply(ply, s.cloud)
    return ply if command else cache


def _in_process(model: Any) -> Any:
    """Register a cached scan's part (isolated by the simulator's truth) in this process:
    (status, pose, covariance, its centre, inflation)."""
    from inspection.measured_cloud import ScanCloud
    from inspection.registration import ModelTarget, RegistrationSettings, register
    from scanner.native_threads import native_threads

    target = ModelTarget.from_cad(model)

    def measure(cache: Path, k: int) -> tuple[str, np.ndarray, Any, Any, float]:
        d = np.load(cache)
        scan = ScanCloud(d["points"], d["normals"], str(cache), np.zeros(3), d["pixels"],
                         tuple(int(x) for x in d["shape"]))
        with native_threads(1):
            reg = register(scan, target, RegistrationSettings(seed=k))
        c = reg.covariance
        return reg.status, reg.transform, c.covariance, c.centre, c.inflation

    return measure


def _by_command(step: Path) -> Any:
    """Register a cloud by `python -m slscan register CLOUD STEP --json --seed K`, this
    checkout's code: (status, pose (the best unproven one when not proven), covariance
    (None when the command gave none), its centre, inflation)."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}

    def measure(ply: Path, k: int) -> tuple[str, Any, Any, Any, float]:
        done = subprocess.run([sys.executable, "-m", "slscan", "register", str(ply), str(step), "--json",
                               "--seed", str(k)], capture_output=True, text=True, env=env, cwd=root,
                              check=False)
        try:
            r = json.loads(done.stdout)
        except json.JSONDecodeError:
            return f"exit {done.returncode}: {done.stderr.strip()[-200:]}", None, None, None, 0.0
        T = r["transform"] if r["transform"] is not None else r["best_unproven"]
        if r.get("pose_covariance") is None:
            return r["status"], np.array(T), None, None, 0.0
        return (r["status"], np.array(T), np.array(r["pose_covariance"]), np.array(r["pose_centre_mm"]),
                float(r.get("correlation_inflation") or 0.0))

    return measure


def _errors(truth: np.ndarray, T: np.ndarray, cov: np.ndarray, centre: np.ndarray) -> dict[str, Any]:
    """The pose's error against the truth beside its stated covariance: the angle and the
    centre's displacement with their 95 % bounds, and the Mahalanobis distance squared."""
    from inspection.registration.evidence import PoseCovariance, twist

    x = twist(truth, T, centre)
    rot_u, shift_u = PoseCovariance.bounds_of(cov)
    return {"rotation_deg": float(np.degrees(np.linalg.norm(x[:3]))), "rotation_u_deg": rot_u,
            "translation_mm": float(np.linalg.norm(x[3:])), "translation_u_mm": shift_u,
            "mahalanobis2": float(x @ np.linalg.pinv(cov) @ x), "error": x.tolist()}


def coverage(rows: list[dict[str, Any]], ellipsoid: float) -> dict[str, Any]:
    """The three coverage figures (module docstring) of `rows`, with their count."""
    statuses = {s: sum(r["status"] == s for r in rows) for s in sorted({r["status"] for r in rows})}
    rows = [r for r in rows if r["status"] == "ok" and "mahalanobis2" in r]  # a pose stated with its U
    return {"scans": len(rows), "statuses": statuses,
            "rotation": float(np.mean([r["rotation_deg"] <= r["rotation_u_deg"] for r in rows])),
            "translation": float(np.mean([r["translation_mm"] <= r["translation_u_mm"] for r in rows])),
            "ellipsoid": float(np.mean([r["mahalanobis2"] <= ellipsoid for r in rows])),
            "median_rotation_u_deg": float(np.median([r["rotation_u_deg"] for r in rows])),
            "median_translation_u_mm": float(np.median([r["translation_u_mm"] for r in rows])),
            "median_inflation": float(np.median([r["inflation"] for r in rows]))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.pose_coverage", description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("--part", default="demo", help="demo, or the seed of a random part")
    p.add_argument("--scans", type=int, default=100)
    p.add_argument("--seed", type=int, default=None, help="default: drawn fresh and printed")
    p.add_argument("--command", action="store_true", help="register by `slscan register CLOUD STEP --json`, the "
                   "whole cloud (table in view) as the scanner writes it")
    args = p.parse_args(argv)
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2 ** 31)
    print(f"pose coverage: part {args.part}, seed {seed}", flush=True)
    run(args.out, args.part, args.scans, seed, args.command)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
