"""`slscan bench demo`: scan-to-verdict of the demo part as a station runs it, stage by stage.

The station's one-time work (the CAD model read and its registration target prepared)
is timed apart; then `--parts` parts are scanned on the simulated rig, one after another,
each inspected verdict first (`scan.inspect_verdict_first`) with the previous part's
registration as the prior (the warm start; the first part has none), and every stage
printed: the simulator opening the rig (it renders the scene's ground truth: simulator
cost, not the scanner's), capture (the simulator renders each frame), load, decode,
reconstruct, write, the inspection's own stages, the verdict (seconds from the start of
the scan, and from the capture's end, i.e. when processing starts: on a real bench the
capture is the camera's time, here the simulator's rendering; with the CPU seconds of every
thread from the capture's end to the verdict, the figure a loaded machine distorts least;
the outputs are written behind the inspection), then the report files and the
Rerun recording written after it, and the session complete. Wall and CPU seconds side by
side, with the load average and a peer measured in the same run (a fixed numpy workload: a
256 MB memory copy and a 1024 x 1024 float64 matrix product), so a figure from a busy
machine can be scaled.

Timings depend on the machine's load; no test asserts them.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from scanner.config import DEFAULT_RIG
from scanner.stage_timer import StageTimer
from slscan.commands.scan import DEMO_SCENE, inspect_verdict_first, load_demo_part
from slscan.exit_codes import Exit


def numpy_peer(repeats: int = 3) -> dict[str, float]:
    """The fixed numpy workload (best of `repeats`): seconds of a 256 MB float32 copy and of
    a 1024 x 1024 float64 matrix product."""
    import numpy as np

    src = np.ones(64 * 2 ** 20, np.float32)
    dst = np.empty_like(src)
    a = np.random.default_rng(0).random((1024, 1024))
    copy, matmul = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        copy.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        a @ a
        matmul.append(time.perf_counter() - t0)
    return {"copy_256mb_s": min(copy), "matmul_1024_s": min(matmul)}


def run_part(k: int, workdir: Path, model: Any, tolerances: Any, prior: Any, full_recording: bool) -> dict[str, Any]:
    """Scan and inspect part `k` (noise seed k); its stage times (s), verdict and pose."""
    from scanner.patterns import PatternSet
    from scanner.pipeline import scan
    from scanner.rig import RigConfig, open_rig

    config = RigConfig.load(DEFAULT_RIG)
    patterns = PatternSet.load(config.patterns_path)
    outer = StageTimer()
    marks: dict[str, float] = {}
    done: dict[str, Any] = {}

    def verdict(report: Any) -> None:
        marks.setdefault("verdict", time.perf_counter())
        marks.setdefault("verdict_cpu", time.process_time())

    def progress(stage: str, done: int, total: int) -> None:
        if stage == "load":  # processing starts: the capture is complete (frames stored, manifest written)
            marks.setdefault("captured", time.perf_counter())
            marks.setdefault("captured_cpu", time.process_time())

    def inspect(result: Any, recording: Any) -> None:
        done["report"], done["timer"] = inspect_verdict_first(result, recording, model, tolerances, seed=0,
                                                              prior=prior, on_verdict=verdict)

    with outer.stage("sim_open_rig"):  # the simulator's scene set-up, timed alone
        rig = open_rig(config, scene=DEMO_SCENE, seed=k)
    with rig:
        t0 = time.perf_counter()
        with outer.stage("scan_to_complete"):
            result = scan(rig, patterns, workdir / f"part-{k}", progress=progress, then=inspect,
                          level="full" if full_recording else None)
        complete = time.perf_counter()
    report, inner = done["report"], done["timer"]
    processed = json.loads((result.session.outputs / "result.json").read_text())
    capture = result.session.manifest.timings_s["capture"]
    rrd = result.session.recording_path
    return {"part": k, "verdict": report.verdict, "method": report.registration.method,
            "fitness": report.registration.fitness, "transform": report.registration.transform.tolist(),
            "capture_s": capture, "process_s": processed["timings_s"], "process_cpu_s": processed.get("cpu_s", {}),
            "inspection_s": report.timings_s, "registration_s": report.registration.timings_s,
            "after_scan_s": inner.rounded()[0], "after_scan_cpu_s": inner.rounded()[1],
            "verdict_after_s": marks["verdict"] - t0, "verdict_after_capture_s": marks["verdict"] - marks["captured"],
            "verdict_cpu_after_capture_s": marks["verdict_cpu"] - marks["captured_cpu"],  # every thread's
            "before_capture_s": marks["captured"] - t0 - capture,
            "complete_after_s": complete - t0,
            "sim_open_rig_s": outer.wall_s["sim_open_rig"], "registration": report.registration,
            "sizes_mb": {"recording": rrd.stat().st_size / 1e6 if rrd.exists() else 0.0,
                         "cloud_ply": (result.session.outputs / "cloud.ply").stat().st_size / 1e6,
                         "maps_npz": (result.session.outputs / "maps.npz").stat().st_size / 1e6,
                         "frames": sum(p.stat().st_size for p in (result.session.root / "frames").iterdir()) / 1e6}}


def cmd_demobench(args: argparse.Namespace) -> int:
    report: dict[str, Any] = {"load_average_start": os.getloadavg(), "peer": numpy_peer()}
    t0, c0 = time.perf_counter(), time.process_time()
    model, tolerances, _ = load_demo_part()
    report["setup_s"] = {"cad_and_target_wall": time.perf_counter() - t0,
                         "cad_and_target_cpu": time.process_time() - c0}
    parts = []
    prior = None
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.parts):
            row = run_part(k, Path(args.out) if args.out else Path(tmp), model, tolerances,
                           prior if not args.cold else None, args.full_recording)
            prior = row.pop("registration")
            parts.append(row)
    report["parts"] = parts
    report["peer_end"] = numpy_peer()
    report["load_average_end"] = os.getloadavg()
    print(json.dumps(report, indent=1, default=float) if args.json else format_report(report))
    return Exit.OK


def format_report(r: dict[str, Any]) -> str:
    def loads(x: Any) -> str:
        return " ".join(f"{v:.2f}" for v in x)

    p, q = r["peer"], r["peer_end"]
    lines = [f"load average {loads(r['load_average_start'])} (start), {loads(r['load_average_end'])} (end); numpy "
             f"peer: 256 MB copy {p['copy_256mb_s'] * 1e3:.0f} / {q['copy_256mb_s'] * 1e3:.0f} ms, 1024^2 matmul "
             f"{p['matmul_1024_s'] * 1e3:.0f} / {q['matmul_1024_s'] * 1e3:.0f} ms (start / end)",
             f"station set-up (once): CAD model and registration target {r['setup_s']['cad_and_target_wall']:.2f} s "
             f"wall, {r['setup_s']['cad_and_target_cpu']:.2f} s CPU"]
    for row in r["parts"]:
        proc = ", ".join(f"{k} {v:.2f}" for k, v in row["process_s"].items())
        cpu = ", ".join(f"{k} {v:.2f}" for k, v in row["process_cpu_s"].items())
        insp = ", ".join(f"{k} {v:.2f}" for k, v in row["inspection_s"].items())
        reg = ", ".join(f"{k} {v:.2f}" for k, v in row["registration_s"].items())
        after = ", ".join(f"{k} {v:.2f} ({row['after_scan_cpu_s'][k]:.2f} CPU)" for k, v in row["after_scan_s"].items())
        sizes = ", ".join(f"{k} {v:.1f}" for k, v in row["sizes_mb"].items())
        lines += [f"part {row['part']}: verdict {row['verdict']} after {row['verdict_after_s']:.2f} s "
                  f"({row['verdict_after_capture_s']:.2f} s after the capture, "
                  f"{row['verdict_cpu_after_capture_s']:.2f} s CPU), session "
                  f"complete after {row['complete_after_s']:.2f} s (registration {row['method']}, fitness "
                  f"{row['fitness']:.4f}); simulator opening the rig {row['sim_open_rig_s']:.2f} s (not counted)",
                  f"  before the capture (session folder, recording opened) {row['before_capture_s']:.2f} s; capture "
                  f"{row['capture_s']:.2f} s (simulated frames rendered); processing wall {proc} s; "
                  f"CPU {cpu} s (the write behind the inspection, its own thread's CPU)",
                  f"  after the scan: {after} s; inspection stages {insp} s; registration {reg} s",
                  f"  sizes MB: {sizes}"]
    return "\n".join(lines)


def register(sub: Any) -> None:
    b = sub.add_parser("demo")
    b.add_argument("--parts", type=int, default=2, help="parts scanned one after another (default 2: cold, warm)")
    b.add_argument("--cold", action="store_true", help="no warm start: every part registered by the global search")
    b.add_argument("--full-recording", action="store_true", help="record every map pixel and point")
    b.add_argument("--out", help="keep the sessions in this folder (default: a temporary one)")
    b.add_argument("--json", action="store_true", help="print the figures as JSON")
    b.set_defaults(func=cmd_demobench)
