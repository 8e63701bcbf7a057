"""`slscan scan` on a rig with two cameras and `slscan decode` of a binocular session: every camera
captured together (scanner/binocular_pipeline.py), the cloud from matching the first two, the
session's Rerun recording with both cameras, their images and the matched points
(scanner/binocular_recording.py). On a simulated rig the report adds the depth error against the
simulator's truth where both cameras see the surface, beside the predicted noise.

The three-ray self-check (the camera-projector triangulation meeting the binocular points) runs
where the projector's geometry is known: on a simulated rig (its nominal geometry is its truth)
or when the rig names a camera-projector calibration; otherwise it is reported as not checked."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from scanner.session import RECORDING
from slscan.exit_codes import Exit
from slscan.progress import ProgressLine


def _recorded(session: Any, scan: Any) -> None:
    from scanner.binocular_recording import log_scan
    from scanner.session_recording import SessionRecording

    with SessionRecording(session.root / RECORDING, session.id, level="display") as rec:
        log_scan(rec, scan)


def sim_depth_error(scan: Any) -> dict[str, float] | None:
    """Depth error against the simulator's truth saved with the frames (the first camera's), over
    its smooth lit pixels with a point; None without a truth file."""
    from sim.evaluate import GROUND_TRUTH_FILE, Truth, smooth_region

    path = scan.session.root / GROUND_TRUTH_FILE
    if not path.exists():
        return None
    gt = Truth.load(path)
    cloud, sigma = scan.result.cloud, scan.result.depth_sigma_mm
    sel = smooth_region(gt) & cloud.valid
    err = (cloud.points[..., 2] - gt.depth)[sel].astype(np.float64)
    if not err.size:
        return None
    beyond = cloud.valid & ~(np.abs(cloud.points[..., 2] - gt.depth) <= 5 * sigma)
    return {"rms_mm": float(np.sqrt(np.mean(err ** 2))), "mean_mm": float(err.mean()),
            "bound_mm": float(np.sqrt(np.mean(sigma[sel].astype(np.float64) ** 2))), "pixels": int(sel.sum()),
            "beyond_5_sigma": int(beyond.sum())}


def report(scan: Any) -> None:
    from scanner.binocular_pipeline import summary

    s = summary(scan)
    root = scan.session.root
    print(f"session   {root}  (cameras {', '.join(scan.decoded)})")
    print(f"cloud     {scan.cloud_path}  ({s['points']} points of {s['of_pixels']} left pixels with a coordinate; "
          f"first camera's frame, mm)")
    print(f"refused   {s['not_unique']} ambiguous, {s['low_gradient']} too little phase change along the epipolar "
          f"line" + (f"; epipolar offset {s['epipolar_offset_median_px']:+.4f} px" if "epipolar_offset_median_px" in s
                     else ""))
    three = scan.three_rays
    if three:
        median, rms = three["mono_minus_binocular_median_mm"] * 1e3, three["mono_minus_binocular_rms_mm"] * 1e3
        print(f"3 rays    camera-projector depth minus binocular: median {median:+.2f} um, RMS {rms:.2f} um; "
              f"projector residual RMS {three['projector_residual_rms_px']:.4f} px")
    else:
        print("3 rays    not checked (no calibration of the projector)")
    t = scan.timings_s
    print(f"timings   decode {t['decode'] * 1e3:.0f} ms (both cameras), match + triangulate {t['match'] * 1e3:.0f} ms")
    if (root / RECORDING).exists():
        print(f"recording {root / RECORDING}   (view: slscan review {root})")
    acc = sim_depth_error(scan)
    if acc is not None:
        print(f"accuracy  depth error RMS {acc['rms_mm'] * 1e3:.1f} um (predicted {acc['bound_mm'] * 1e3:.1f} um), "
              f"mean {acc['mean_mm'] * 1e3:+.2f} um over {acc['pixels']} px; {acc['beyond_5_sigma']} points beyond "
              f"5 sigma")


def cmd_scan_binocular(args: argparse.Namespace, config: Any, patterns: Any, options: dict[str, Any]) -> int:
    from scanner.binocular_pipeline import scan_binocular
    from scanner.rig import open_rig

    out = Path(args.out)
    print(f"rig {config.name} ({config.driver}, {config.trigger} trigger, cameras {', '.join(config.camera_names)}), "
          f"{patterns.family} {patterns.n_frames} frames -> {out}", file=sys.stderr)
    calibrated = config.driver == "sim" or config.calibration_path is not None
    with open_rig(config, **options) as rig:
        rig.extras["stereo_model"] = config.stereo_model()
        scan = scan_binocular(rig, patterns, out, ProgressLine(), calibrated=calibrated)
    if config.recording_level != "none":
        _recorded(scan.session, scan)
    report(scan)
    return Exit.OK


def cmd_decode_binocular(args: argparse.Namespace, session: Any) -> int:
    from scanner.binocular_pipeline import process_binocular

    scan = process_binocular(session, ProgressLine())
    (session.root / RECORDING).unlink(missing_ok=True)  # the recording follows the outputs it shows
    _recorded(session, scan)
    report(scan)
    return Exit.OK
