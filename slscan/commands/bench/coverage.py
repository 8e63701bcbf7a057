"""`slscan coverage`: how often the truth lies within ±U, measured on the simulated bench
with the product's own measurement path (`studies.repeat_scans`), so anyone can rerun a
published coverage figure (a user's command, not a bench; its module is here, beside the
benches, because it runs a study):

    slscan coverage --case plate-flatness|plate-sq|sphere-radius|ball-bar|pose|face-position|smooth-flatness|
                    smooth-sq|near-limit-flatness|near-limit-sq --scans N --seed S
                    [--calibrated --out DIR [--calibrations K]] [--processes P] [--json]

prints {"case", "scans", "inside", "coverage", "error_mean_mm", "error_sd_mm",
"median_U_mm", "seconds"} per case (`--case` may be given more than once: the plate's
cases share their scans, as do the demo part's: its pose and a plane face's mean deviation,
"face-position"; several cases print a JSON list). The smooth-plate cases measure
a perfectly flat, smooth plate (truth 0): their "detected" is how many scans reported a
value (false detections; the stated rate is 5 %). The near-limit cases measure a smooth plate
whose bow (`studies.repeat_scans.NEAR_LIMIT`) puts its flatness near the detection limit, where
a zone is reported in some scans and "< L" in the others.

`--calibrated`: each scan is reconstructed with the result of an independent simulated
calibration (`slscan calibrate --seed 1000·S + j --out DIR/calibration-<seed>`, j <
K; made once, then reused from DIR; their captures are deleted once solved) and its U
holds that calibration's covariance; scan k uses calibration k mod K. Without it the
rig's exact geometry is used (no calibration term). Each calibration's Mahalanobis d² of
the true rig under its own covariance is printed beside the figures ("calibration_d2",
"calibration_dof", "calibration_d2_95": the chi-square 95 % point): the coverage measures
U only as far as the calibrations are representative (a calibration above its 95 % point,
or one made by older code and reused from DIR, says its covariance is not).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from scanner.errors import ScannerError

CASES = ("plate-flatness", "plate-sq", "sphere-radius", "ball-bar", "pose", "face-position", "smooth-flatness",
         "smooth-sq", "near-limit-flatness", "near-limit-sq")


def calibrations(rig: Path, out: Path, seed: int, count: int, say: Callable[[str], None]) -> list[Path]:
    """`count` independent simulated calibrations of `rig` in `out` (seeds 1000·seed + j),
    each by `slscan calibrate` in its own process (its output in DIR/calibration-<seed>.log);
    one already there is reused."""
    done = []
    for j in range(count):
        s = 1000 * seed + j
        folder = out / f"calibration-{s}"
        result = folder / "calibration.json"
        if not result.exists():
            say(f"calibration {j + 1} of {count} (seed {s}) -> {folder}")
            t0 = time.perf_counter()
            with open(out / f"calibration-{s}.log", "w") as log:
                code = subprocess.call([sys.executable, "-m", "slscan", "calibrate", "--rig", str(rig), "--seed",
                                        str(s), "--out", str(folder)], stdout=log, stderr=subprocess.STDOUT)
            if code != 0 or not result.exists():
                raise ScannerError(f"simulated calibration seed {s} failed (exit {code}); "
                                   f"see {out}/calibration-{s}.log")
            import shutil

            shutil.rmtree(folder / "capture", ignore_errors=True)  # 0.8 GB of frames, not needed once solved
            say(f"calibration seed {s}: {time.perf_counter() - t0:.0f} s")
        done.append(result)
    return done


def cmd_coverage(args: argparse.Namespace) -> int:
    from scipy.stats import chi2

    from calibration.consistency import mahalanobis, model_parameters
    from inspection.artefact_file import DEFAULT_ARTEFACTS, load_artefacts
    from scanner.patterns import PatternSet
    from scanner.rig import RigConfig
    from slscan.measurement_model import rig_measurement
    from studies import repeat_scans as rs

    def say(text: str) -> None:
        print(f"{time.strftime('%H:%M:%S')} {text} (load {os.getloadavg()[0]:.1f})", file=sys.stderr, flush=True)

    cases = args.case or []
    if not cases:
        raise ScannerError(f"give --case: one or more of {', '.join(CASES)}")
    for option in ("scans", "processes", "calibrations"):
        if getattr(args, option) < 1:
            raise ScannerError(f"--{option} {getattr(args, option)}: must be at least 1")
    config = RigConfig.load(args.rig)
    if config.driver != "sim":
        raise ScannerError(f"{config.path}: coverage is measured on a simulated rig (driver sim), not {config.driver}")
    model = config.nominal_model()
    measurement = rig_measurement(config.raw, model, PatternSet.load(config.patterns_path),
                                  config.camera.bit_depth or 12, config.path)
    bench = rs.Bench.of(config, measurement)
    rigs: tuple[Any, ...] = ()
    if args.calibrated:
        if args.out is None:
            raise ScannerError("--calibrated needs --out DIR for the simulated calibrations")
        args.out.mkdir(parents=True, exist_ok=True)
        rigs = tuple(rs.MeasuringRig.from_calibration(p, bench)
                     for p in calibrations(config.path, args.out, args.seed, args.calibrations, say))
    distances = [mahalanobis(model_parameters(r.model), model_parameters(model), r.calibration.covariance)
                 for r in rigs]
    for j, d in enumerate(distances):
        say(f"calibration seed {1000 * args.seed + j}: d² of the true rig {d.d2:.1f} on {d.dof} dof "
            f"(95 % point {chi2.ppf(0.95, d.dof):.1f})")
    common = dict(seed=args.seed, rigs=rigs, processes=args.processes, progress=say)
    results: dict[str, Any] = {}
    for name, plate in (("plate", rs.Plate()), ("smooth", rs.SMOOTH), ("near-limit", rs.NEAR_LIMIT)):
        if {f"{name}-flatness", f"{name}-sq"} & set(cases):
            results[f"{name}-flatness"], results[f"{name}-sq"] = rs.plate_figures(bench, args.scans, plate=plate,
                                                                                   **common)
    if "sphere-radius" in cases:
        results["sphere-radius"] = rs.sphere_radius(bench, load_artefacts(DEFAULT_ARTEFACTS), args.scans, **common)[0]
    if "ball-bar" in cases:
        results["ball-bar"] = rs.ball_bar_length(bench, load_artefacts(DEFAULT_ARTEFACTS), args.scans, **common)[0]
    demo = tuple(c for c in rs.DEMO_PART_FIGURES if c in cases)  # one inspection per scan serves both
    if demo:
        results.update(zip(demo, rs.demo_part_coverage(bench, args.scans, demo, **common)))
    rows = []
    for case in cases:
        r = results[case]
        row = r.as_json(case)
        row.update(seed=args.seed, calibrated=bool(rigs), calibrations=len(rigs))
        if distances:
            row.update(calibration_seeds=[1000 * args.seed + j for j in range(len(rigs))],
                       calibration_d2=[d.d2 for d in distances], calibration_dof=distances[0].dof,
                       calibration_d2_95=float(chi2.ppf(0.95, distances[0].dof)))
        if case.startswith("smooth"):
            row.update(detected=row["reported"], false_detection_rate=row["reported"] / row["scans"])
        if case == "pose" and r.trials:
            n = len(r.trials)
            row.update(rotation_error_deg_mean=float(sum(t.rotation_error_deg for t in r.trials) / n),
                       median_rotation_U_deg=sorted(t.rotation_u_deg for t in r.trials)[n // 2],
                       rotation_coverage=sum(t.rotation_inside for t in r.trials) / n,
                       translation_coverage=sum(t.translation_inside for t in r.trials) / n)
        rows.append(row)
        if not args.json:
            print(r.summary())
    if args.json:
        print(json.dumps(rows[0] if len(rows) == 1 else rows))
    return 0


def register(sub: Any) -> None:
    from scanner.config import DEFAULT_RIG

    c = sub.add_parser("coverage")
    c.add_argument("--case", action="append", choices=CASES, help="the figure (repeatable)")
    c.add_argument("--scans", type=int, default=200, help="repeat scans (default 200)")
    c.add_argument("--seed", type=int, required=True, help="seed of the placements and noise")
    c.add_argument("--calibrated", action="store_true",
                   help="reconstruct with independent simulated calibrations (their covariance in U)")
    c.add_argument("--calibrations", type=int, default=10, help="--calibrated: how many calibrations (default 10)")
    c.add_argument("--out", type=Path, help="--calibrated: folder for the calibrations (reused when present)")
    c.add_argument("--rig", type=Path, default=DEFAULT_RIG, help="simulated rig TOML (default: the bench rig)")
    c.add_argument("--processes", type=int, default=1, help="forked workers sharing the scans out")
    c.add_argument("--json", action="store_true", help="print the figures as JSON")
    c.set_defaults(func=cmd_coverage)
