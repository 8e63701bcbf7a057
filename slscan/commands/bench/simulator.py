"""`slscan bench sim`: how fast the simulator makes frames and how well it keeps a
sequence's period, on the default bench rig (the timings the tests no longer assert).

    frame     one full-resolution frame: rendering a pattern not seen before, and one seen
              before (its projector sampling cached); median of --repeats
    peer      the sensor model alone (shot and read noise, digitisation) on a flat image of
              the same size, timed in the same run: the part of a frame no scene can save.
              frame / peer moves less with the machine's load than either figure
    sequence  the simulated projector's trigger-output times over a sequence of the rig's
              pattern set at its period: mean period and worst deviation from it

Wall times on a shared machine: the load average before and after is printed beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import threading
import time
from typing import Any

from slscan.exit_codes import Exit


def _timed(fn: Any, *args: Any) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


def run_simbench(repeats: int = 5) -> dict[str, Any]:
    """Measure frame rendering, its peer and the sequence period; returns the figures (s)."""
    import numpy as np

    from scanner.patterns import PatternSet
    from scanner.rig import RigConfig
    from sim.virtual_devices import SimProjector
    from sim.virtual_rig import open_sim_rig

    config = RigConfig.load()
    load_before = os.getloadavg()
    with open_sim_rig(config) as rig:
        renderer, sensor, cam, proj = rig.extras["renderer"], rig.extras["sensor"], rig.camera, rig.projector
        patterns = PatternSet.load(config.patterns_path).render(proj.width, proj.height, rig.model.projector_gamma)
        exposure, bits = cam.exposure_s, cam.bit_depth
        rng = np.random.default_rng(0)
        flat = np.full((cam.height, cam.width), 0.5 * sensor.full_well_e, np.float32)
        new, seen, peer = [], [], []
        for i in range(repeats + 1):  # the first round warms caches and is not counted
            pattern = np.roll(patterns[i % len(patterns)], 7 * (i + 1), axis=1)  # never rendered before
            new.append(_timed(renderer.render, pattern, exposure, bits, rng))
            seen.append(_timed(renderer.render, pattern, exposure, bits, rng))
            peer.append(_timed(sensor.expose, flat, bits, rng))
        stamps: list[float] = []
        lock = threading.Lock()

        def stamp() -> None:
            with lock:
                stamps.append(time.monotonic())

        assert isinstance(proj, SimProjector)  # open_sim_rig's projector
        proj.connect_trigger_out(stamp)
        proj.load_patterns(patterns)
        proj.run_sequence(config.period_s).wait(10 * len(patterns) * config.period_s + 10.0)
    spacing = np.diff(stamps)
    frame_new, frame_seen, peer_s = (statistics.median(x[1:]) for x in (new, seen, peer))
    return {"width": cam.width, "height": cam.height, "bit_depth": bits, "repeats": repeats,
            "frame_new_pattern_s": round(frame_new, 4), "frame_seen_pattern_s": round(frame_seen, 4),
            "peer_sensor_s": round(peer_s, 4), "frame_new_over_peer": round(frame_new / peer_s, 2),
            "frame_seen_over_peer": round(frame_seen / peer_s, 2), "sequence_patterns": len(stamps),
            "period_s": config.period_s, "mean_period_s": round(float(spacing.mean()), 5),
            "worst_period_deviation_s": round(float(np.abs(spacing - config.period_s).max()), 5),
            "load_before": [round(x, 2) for x in load_before],
            "load_after": [round(x, 2) for x in os.getloadavg()], "cores": os.cpu_count()}


def format_table(r: dict[str, Any]) -> str:
    ms = 1e3
    rows = [("camera", f"{r['width']} x {r['height']}, {r['bit_depth']} bits (default bench rig)"),
            ("frame, new pattern",
             f"{r['frame_new_pattern_s'] * ms:.0f} ms  ({r['frame_new_over_peer']:.2f} x peer)"),
            ("frame, seen pattern",
             f"{r['frame_seen_pattern_s'] * ms:.0f} ms  ({r['frame_seen_over_peer']:.2f} x peer)"),
            ("peer: sensor model", f"{r['peer_sensor_s'] * ms:.0f} ms"),
            ("sequence period", f"mean {r['mean_period_s'] * ms:.2f} ms for {r['period_s'] * ms:.0f} ms configured, "
                                f"worst deviation {r['worst_period_deviation_s'] * ms:.2f} ms over "
                                f"{r['sequence_patterns']} patterns"),
            ("median of", f"{r['repeats']} runs, {r['cores']} cores"),
            ("load average", f"before {' '.join(f'{x:.2f}' for x in r['load_before'])}, after "
                             f"{' '.join(f'{x:.2f}' for x in r['load_after'])}")]
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


def cmd_simbench(args: argparse.Namespace) -> int:
    r = run_simbench(args.repeats)
    print(json.dumps(r) if args.json else format_table(r))
    return Exit.OK


def register(sub: Any) -> None:
    b = sub.add_parser("sim")
    b.add_argument("--repeats", type=int, default=5, help="frames timed per figure (median)")
    b.add_argument("--json", action="store_true", help="print a JSON object")
    b.set_defaults(func=cmd_simbench)
