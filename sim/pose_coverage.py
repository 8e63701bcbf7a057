"""Does the registration's pose uncertainty cover? Repeat scans of one part, each at a fresh
random placement on the table (so the fringe systematics, fixed for one placement, are drawn
anew) with fresh noise, through the whole fringe chain; each registered (the part isolated
by the scanner's truth: the question here is the pose's U, not the table's removal) and its
error against the simulator's true pose set beside the covariance the registration states.

    python -m sim.pose_coverage OUT [--part demo|SEED] [--scans 100] [--seed S]

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


def run(out: Path, part: str, scans: int, seed: int) -> dict[str, Any]:
    """Scan and register `scans` times (module docstring); rows in `out`/coverage_SEED.jsonl."""
    from scipy.stats import chi2

    from inspection.cad import load_cad
    from inspection.measured_cloud import ScanCloud
    from inspection.registration import ModelTarget, RegistrationSettings, register
    from inspection.registration.evidence import twist
    from scanner.config import CONFIG_DIR
    from scanner.native_threads import native_threads
    from sim.random_parts import placement_for, random_part, scan_part

    out.mkdir(parents=True, exist_ok=True)
    if part == "demo":
        step, scale = CONFIG_DIR / "parts" / "demo_part.step", 1.0
    else:
        p = random_part(int(part))
        step = p.write(out / f"part_{part}.step")
        scale = placement_for(float(np.hypot(p.length_mm, p.width_mm)), seed).rig_scale
    model = load_cad(step)
    fine = load_cad(step, deflection_mm=1e-3 * max(1.0, model.diagonal_mm / 100.0))
    target = ModelTarget.from_cad(model)
    rng = np.random.default_rng(seed)
    rows = []
    with (out / f"coverage_{seed}.jsonl").open("w") as log:
        for k, placement in enumerate(placements(seed, scans, scale)):
            noise = int(rng.integers(0, 2 ** 31))
            t0 = time.perf_counter()
            cache = out / f"scan_{seed}_{k}.npz"
            if not cache.exists():
                s = scan_part(fine, placement, noise)
                on = s.true_face >= 0
                np.savez(cache, points=s.scan.points[on], normals=s.scan.normals[on], pixels=s.scan.pixels[on],
                         truth=s.truth, shape=np.array(s.scan.image_shape))
            d = np.load(cache)
            scan = ScanCloud(d["points"], d["normals"], str(cache), np.zeros(3), d["pixels"],
                             tuple(int(x) for x in d["shape"]))
            with native_threads(1):
                reg = register(scan, target, RegistrationSettings(seed=k))
            cov = reg.covariance
            x = twist(d["truth"], reg.transform, cov.centre)
            rot_u, shift_u = cov.bounds()
            d2 = float(x @ np.linalg.pinv(cov.covariance) @ x)
            row = {"scan": k, "placement_seed": placement.seed, "noise_seed": noise, "status": reg.status,
                   "rotation_deg": float(np.degrees(np.linalg.norm(x[:3]))), "rotation_u_deg": rot_u,
                   "translation_mm": float(np.linalg.norm(x[3:])), "translation_u_mm": shift_u, "mahalanobis2": d2,
                   "inflation": cov.inflation, "block": cov.correlation.block, "error": x.tolist(),
                   "seconds": round(time.perf_counter() - t0, 1), "load": os.getloadavg()[0]}
            rows.append(row)
            log.write(json.dumps(row) + "\n")
            log.flush()
            print(f"{k:3d} rot {row['rotation_deg']:.5f} (U {rot_u:.5f}) deg, shift {row['translation_mm']:.5f} "
                  f"(U {shift_u:.5f}) mm, d2 {d2:.1f}, inflation {cov.inflation:.2f}, {reg.status}, "
                  f"{row['seconds']} s", flush=True)
    result = coverage(rows, chi2.ppf(0.95, 6))
    print(json.dumps(result))
    return result


def coverage(rows: list[dict[str, Any]], ellipsoid: float) -> dict[str, Any]:
    """The three coverage figures (module docstring) of `rows`, with their count."""
    return {"scans": len(rows),
            "rotation": float(np.mean([r["rotation_deg"] <= r["rotation_u_deg"] for r in rows])),
            "translation": float(np.mean([r["translation_mm"] <= r["translation_u_mm"] for r in rows])),
            "ellipsoid": float(np.mean([r["mahalanobis2"] <= ellipsoid for r in rows])),
            "median_rotation_u_deg": float(np.median([r["rotation_u_deg"] for r in rows])),
            "median_translation_u_mm": float(np.median([r["translation_u_mm"] for r in rows])),
            "median_inflation": float(np.median([r["inflation"] for r in rows]))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m sim.pose_coverage", description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("--part", default="demo", help="demo, or the seed of a random part")
    p.add_argument("--scans", type=int, default=100)
    p.add_argument("--seed", type=int, default=None, help="default: drawn fresh and printed")
    args = p.parse_args(argv)
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2 ** 31)
    print(f"pose coverage: part {args.part}, seed {seed}", flush=True)
    run(args.out, args.part, args.scans, seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
