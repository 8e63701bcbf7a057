"""`slscan bench`: decode + reconstruction time and peak memory for one fringe stack.

The stack is synthesised analytically (a tilted plane with a smooth bump, seen by a camera
of the requested size with the default rig's field of view, with shot and read noise), so
the figures do not depend on the simulator. Timing runs in a fresh child process whose
peak resident memory (VmHWM: interpreter, libraries, input stack and all working arrays)
is the reported peak.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .geometry import Pinhole, RigModel
from .patterns import PatternSet
from .rig import RigConfig


def scaled_rig(base: RigModel, width: int, height: int) -> RigModel:
    """The rig with its camera resampled to width x height at the same field of view."""
    cam = base.camera
    sx, sy = width / cam.width, height / cam.height
    K = cam.K.copy()
    K[0] *= sx
    K[1] *= sy
    K[0, 2] = (cam.K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (cam.K[1, 2] + 0.5) * sy - 0.5
    return replace(base, camera=Pinhole(width, height, K, cam.dist))


def synthetic_stack(rig: RigModel, patterns: PatternSet, bit_depth: int = 12, seed: int = 0) -> np.ndarray:
    """(N, H, W) frames of a tilted plane with a bump at the rig's working distance."""
    rays = rig.camera.ray_grid.astype(np.float64)
    n = np.array([0.15, -0.1, 1.0])
    n /= np.linalg.norm(n)
    z = 400.0 / (rays @ n)
    x, y = rays[..., 0] * z, rays[..., 1] * z
    z -= 8.0 * np.exp(-(x ** 2 + y ** 2) / (2 * 25.0 ** 2))
    pts = rays * z[..., None]
    p = (pts.reshape(-1, 3) - rig.cam_from_proj[:3, 3]) @ rig.cam_from_proj[:3, :3]
    uv = rig.projector.project(p).reshape(*z.shape, 2)
    rng = np.random.default_rng(seed)
    full = 2 ** bit_depth - 1
    specs = patterns.frames()
    out = np.empty((len(specs), *z.shape), dtype=np.uint16)
    size = (rig.projector.width, rig.projector.height)
    for i, s in enumerate(specs):
        axis = 0 if s.orientation == "vertical" else 1
        profile = patterns.profile(s, size[axis])
        c = np.clip(uv[..., axis], 0, size[axis] - 1)
        shown = np.interp(c, np.arange(size[axis]), profile)
        electrons = 400.0 + 7000.0 * shown
        frame = rng.poisson(electrons).astype(np.float64) + rng.normal(0.0, 6.0, z.shape)
        out[i] = np.clip(np.rint(frame / (10500.0 / full)), 0, full)
    return out


def _vm_hwm_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _child(stack_path: str, rig_dict: dict, patterns_dict: dict, repeats: int, queue: mp.Queue) -> None:
    from .decode import decode
    from .reconstruct import Triangulator, triangulate

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
    rig = scaled_rig(config.nominal_model(), width, height)
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
