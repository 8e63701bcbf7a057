"""`slscan bench`: decode + reconstruction time and peak memory for one fringe stack.

The stack is synthesised analytically (a tilted plane with a smooth bump, seen by a camera
of the requested size with the default rig's field of view, with shot and read noise), so
the figures do not depend on the simulator. Timing runs in a fresh child process whose
peak resident memory (VmHWM: interpreter, libraries, input stack and all working arrays)
is the reported peak.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from scanner.geometry import RigModel
from scanner.patterns import PatternSet
from scanner.rig import RigConfig
from sim.analytic_stack import synthetic_stack


def _vm_hwm_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _child(stack_path: str, rig_dict: dict, patterns_dict: dict, repeats: int, queue: mp.Queue) -> None:
    from scanner.decode import decode
    from scanner.reconstruct import Triangulator, triangulate

    stack = np.load(stack_path)
    rig = RigModel.from_dict(rig_dict)
    patterns = PatternSet.from_dict(patterns_dict)
    t0 = time.perf_counter()
    tri = Triangulator(rig)
    tri.prepare(patterns.orientations)
    setup = time.perf_counter() - t0
    dec, rec = [], []
    for _ in range(repeats + 1):  # the first run warms caches and is not counted
        t0 = time.perf_counter()
        d = decode(stack, patterns, 12, rig.projector.size)
        t1 = time.perf_counter()
        cloud = triangulate(d, tri)
        t2 = time.perf_counter()
        dec.append(t1 - t0)
        rec.append(t2 - t1)
    queue.put({"setup_s": setup, "decode_s": statistics.median(dec[1:]), "reconstruct_s": statistics.median(rec[1:]),
               "valid_fraction": float(d.valid.mean()), "points": len(cloud), "peak_mb": _vm_hwm_mb()})


def run_bench(width: int, height: int, patterns_path: Path | None = None, rig_path: Path | None = None,
              repeats: int = 5) -> dict:
    """Measure decode + reconstruction; returns the figures (seconds, MB)."""
    config = RigConfig.load(rig_path) if rig_path else RigConfig.load()
    patterns = PatternSet.load(patterns_path or config.patterns_path)
    rig = config.nominal_model().with_camera_size(width, height)
    stack = synthetic_stack(rig, patterns)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "stack.npy")
        np.save(path, stack)
        ctx = mp.get_context("spawn")
        queue = ctx.Queue()
        proc = ctx.Process(target=_child, args=(path, rig.to_dict(), patterns.to_dict(), repeats, queue))
        proc.start()
        result = queue.get(timeout=600)
        proc.join(timeout=60)
    return {"width": width, "height": height, "frames": patterns.n_frames, "patterns": patterns.family,
            "decode_s": round(result["decode_s"], 4), "reconstruct_s": round(result["reconstruct_s"], 4),
            "total_s": round(result["decode_s"] + result["reconstruct_s"], 4),
            "peak_mb": round(result["peak_mb"], 1), "setup_s": round(result["setup_s"], 3),
            "valid_fraction": round(result["valid_fraction"], 4), "points": result["points"],
            "repeats": repeats, "cores": os.cpu_count()}


def format_table(r: dict) -> str:
    rows = [("resolution", f"{r['width']} x {r['height']}"), ("pattern set", f"{r['patterns']}, {r['frames']} frames"),
            ("decode", f"{r['decode_s'] * 1e3:.0f} ms"), ("reconstruct", f"{r['reconstruct_s'] * 1e3:.0f} ms"),
            ("total", f"{r['total_s'] * 1e3:.0f} ms"), ("peak memory", f"{r['peak_mb']:.0f} MB (whole process)"),
            ("per-rig setup", f"{r['setup_s'] * 1e3:.0f} ms (once, cached)"),
            ("valid pixels", f"{r['valid_fraction'] * 100:.1f} %"), ("median of", f"{r['repeats']} runs, {r['cores']} cores")]
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


if __name__ == "__main__":
    print(json.dumps(run_bench(2448, 2048)))


def cmd_bench(args: argparse.Namespace) -> int:
    r = run_bench(args.width, args.height, Path(args.patterns) if args.patterns else None, repeats=args.repeats)
    print(json.dumps(r) if args.json else format_table(r))
    return 0


def register(sub: Any) -> None:
    b = sub.add_parser("bench", help="decode + reconstruction time and peak memory")
    b.add_argument("--width", type=int, default=2448)
    b.add_argument("--height", type=int, default=2048)
    b.add_argument("--patterns", help="pattern set TOML (default: 3 frequencies x 4 steps)")
    b.add_argument("--repeats", type=int, default=5)
    b.add_argument("--json", action="store_true", help="print a JSON object")
    b.set_defaults(func=cmd_bench)
