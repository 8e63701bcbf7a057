"""`slscan bench segment`: region growing (`slscan segment`) on simulated cluttered clouds
(`sim.clutter.clutter_cloud`): per seed the time of the segmentation alone and its α, β, η
against the clouds' ground truth, then the means over seeds."""

from __future__ import annotations

import argparse
import json
import os
from typing import Any

from slscan.exit_codes import Exit
from slscan.options import add_json


def cmd_segment_bench(args: argparse.Namespace) -> int:
    """Per seed: build the cloud, segment it (wall-clock and process CPU time of the
    segmentation alone), score it; then the means over seeds."""
    import time

    import numpy as np

    from inspection.regions.region_growing import segment
    from inspection.regions.segmetrics import score
    from sim.clutter import clutter_cloud

    rows = []
    for seed in args.seeds:
        cloud = clutter_cloud(seed, args.spacing, args.radius)   # None: slscan segment's default radius
        radius = cloud.radius_mm
        wall, cpu = time.perf_counter(), time.process_time()
        seg = segment(cloud.points, radius)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        sc = score(seg.labels, cloud.labels)
        rows.append({"seed": seed, "radius_mm": radius, "points": len(cloud.points), "subsampled": len(seg.subsample),
                     "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "stages_s": seg.timings_s,
                     "truth_segments": len(sc.segments), "mean_alpha": sc.mean_alpha, "mean_beta": sc.mean_beta,
                     "mean_eta": sc.mean_eta})
        if not args.json:
            print(f"seed {seed}: {len(cloud.points)} points ({len(seg.subsample)} subsampled), r = {radius:g} mm: "
                  f"{wall:.1f} s wall, {cpu:.1f} s CPU; {len(sc.segments)} true segments: "
                  f"alpha {100 * sc.mean_alpha:.4f} %, beta {100 * sc.mean_beta:.2f} %, eta {sc.mean_eta:.2f}",
                  flush=True)
    means = {k: float(np.mean([r[k] for r in rows]))
             for k in ("mean_alpha", "mean_beta", "mean_eta", "wall_s", "cpu_s")}
    load = [round(x, 2) for x in os.getloadavg()]   # wall time depends on what else runs: report it
    if args.json:
        print(json.dumps({"radius_mm": args.radius or "default", "spacing_mm": args.spacing, "runs": rows,
                          "means": means, "load_average": load}, indent=2))
    else:
        print(f"mean over {len(rows)}: alpha {100 * means['mean_alpha']:.4f} %, beta {100 * means['mean_beta']:.2f} %, "
              f"eta {means['mean_eta']:.2f}; {means['wall_s']:.1f} s wall, {means['cpu_s']:.1f} s CPU per cloud; "
              f"load average {load[0]} {load[1]} {load[2]} on {os.cpu_count()} CPUs")
    return Exit.OK


def register(sub: Any) -> None:
    b = sub.add_parser("segment")
    b.add_argument("--seeds", type=int, nargs="+", default=[0], help="scene seeds (default: 0)")
    b.add_argument("--spacing", type=float, default=1.0, metavar="MM", help="nearest scanner's point spacing")
    b.add_argument("--radius", "-r", type=float, metavar="MM",
                   help="radius of interest r (default: slscan segment's, 35 point spacings of each cloud)")
    add_json(b)
    b.set_defaults(func=cmd_segment_bench)
