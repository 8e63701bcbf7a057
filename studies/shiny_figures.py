"""Figures of a simulated scan of a shiny part against its ground truth (issue 18's acceptance).

For the part (every scene object, not the reference plane) where the projector lights it:
valid coverage (valid / lit, saturated pixels included: what a user gets), depth error RMS
on its smooth region (`sim.evaluate.smooth_region`), projector-coordinate (phase) error of the
valid pixels, fringe-order errors (valid pixels off by half a period or more), pixels masked
per reason, and the session's exposures and capture time (the simulator's wall time, which is
mostly rendering, and the nominal time the rig's pattern period and exposures take).

    python -m studies.shiny_figures SESSION [--interreflection-off]

prints them as JSON (decoding the session's raw frames again; `--interreflection-off` decodes
without the interreflection mask, for the before/after comparison).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from scanner.acquisition import EXPOSURE_PERIOD_MARGIN_S
from scanner.decode import DecodeSettings
from scanner.pipeline import ScanResult, decode_session
from scanner.reconstruct import Triangulator, triangulate
from scanner.session import Session
from sim.evaluate import GROUND_TRUTH_FILE, Truth, smooth_region
from sim.scene import FIRST_OBJECT_ID


def part_figures(result: ScanResult, truth: Truth) -> dict[str, Any]:
    """The figures of the module docstring for a processed session of a simulated scene."""
    part = (truth.object_id >= FIRST_OBJECT_ID) & truth.lit
    (orientation, m), = result.decoded.maps.items()
    valid = result.decoded.valid & part
    if result.cloud is not None:
        valid &= result.cloud.valid
    smooth = smooth_region(truth) & valid
    depth_err = (result.cloud.points[..., 2] - truth.depth)[smooth] if result.cloud is not None else np.zeros(0)
    coord_err = (m.coordinate - truth.proj_uv[..., 0 if orientation == "vertical" else 1])[valid]
    manifest = result.session.manifest
    return {
        "session": str(result.session.root),
        "part_lit_pixels": int(part.sum()),
        "valid_coverage": round(float(valid.sum() / max(part.sum(), 1)), 5),
        "depth_rms_um": round(float(np.sqrt(np.mean(depth_err.astype(np.float64) ** 2)) * 1e3), 2)
        if depth_err.size else None,
        "depth_pixels": int(smooth.sum()),
        "phase_error_rms_px": round(float(np.sqrt(np.mean(coord_err.astype(np.float64) ** 2))), 4)
        if coord_err.size else None,
        "phase_error_p99_px": round(float(np.percentile(np.abs(coord_err), 99)), 4) if coord_err.size else None,
        "fringe_order_errors": int((np.abs(coord_err) >= m.period_px / 2).sum()),
        "masked_on_part": {k: int((v & part).sum()) for k, v in m.masks.items()},
        "exposures_s": list(result.session.exposures_s),
        "capture_s": manifest.timings_s.get("capture"),
        "nominal_capture_s": round(nominal_capture_s(result.session), 3),
        "exposure_reason": manifest.exposure.reason if manifest.exposure is not None else None,
    }


def nominal_capture_s(session: Session) -> float:
    """Capture time the rig's sequencing takes (s), the renderer's time left out: every frame
    (the probe's three per pre-capture included) holds a pattern for max(period, exposure +
    margin), as `scanner.acquisition.settings_for_exposure` sets it."""
    period = session.manifest.recorded_rig.rig.period_s
    n = session.patterns.n_frames
    record = session.manifest.exposure
    probe = 3 * (record.probe_captures if record is not None else 0) * period
    return probe + sum(n * max(period, t + EXPOSURE_PERIOD_MARGIN_S) for t in session.exposures_s)


def session_figures(path: str, interreflection: bool = True) -> dict[str, Any]:
    """Decode a session's raw frames again (its outputs left as they are) and measure it
    (`part_figures`). Without the interreflection mask the decode is the study's foil: its
    consistency checks (which the second paths fail: coordinates out of order) are kept, not
    enforced; with it, the decode must pass them as a scan does."""
    session = Session.open(path)
    decoded = decode_session(session, DecodeSettings(interreflection=interreflection, self_check=interreflection))
    result = ScanResult(session, decoded, triangulate(decoded, Triangulator(session.rig_model())), {})
    return part_figures(result, Truth.load(session.root / GROUND_TRUTH_FILE))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("session")
    ap.add_argument("--interreflection-off", action="store_true", help="decode without the interreflection mask")
    args = ap.parse_args(argv)
    print(json.dumps(session_figures(args.session, not args.interreflection_off), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
