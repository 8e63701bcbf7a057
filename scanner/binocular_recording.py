"""A binocular scan in its session's Rerun recording, beside what `SessionRecording` logs for the
first camera (its rig, maps and cloud under the usual paths):

=========================================  ==========================================  ===============
entity path                                content                                      timelines
=========================================  ==========================================  ===============
``world/cameras/<name>``                   Transform3D (in the first camera's frame)    static
                                           + Pinhole of every camera
``world/cameras/<name>/image``             the camera's texture (mean intensity, DN)    scan
``world/cameras/<name>/image/matches``     Points2D: a subsample of the matched pixels, scan
                                           coloured by depth, the same colour in both
                                           cameras for one match; class id = the match
``metrics/binocular_<name>``               Scalars: the reconstruction's counts and     scan
                                           checks (BinocularResult.checks)
=========================================  ==========================================  ===============
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from scanner.binocular import BinocularResult
from scanner.decode import DecodeResult
from scanner.session_recording import SessionRecording, _rerun_pinhole, _transform

CAMERAS = "world/cameras"
MAX_MATCHES_SHOWN = 4000  # matched pixels drawn per camera: enough to see the correspondence, light to load


def camera_path(name: str) -> str:
    return f"{CAMERAS}/{name}"


def _depth_colours(z: np.ndarray) -> np.ndarray:
    """Packed RGBA colours from blue (near) to red (far) over the depths' 2-98 % range."""
    lo, hi = np.percentile(z, [2, 98]) if z.size else (0.0, 1.0)
    t = np.clip((z - lo) / max(hi - lo, 1e-9), 0, 1)
    r, b = (255 * t).astype(np.uint32), (255 * (1 - t)).astype(np.uint32)
    g = (255 * (1 - np.abs(2 * t - 1))).astype(np.uint32)
    return (r << 24) | (g << 16) | (b << 8) | np.uint32(0xFF)


def log_binocular(rec: SessionRecording, result: BinocularResult, decoded: dict[str, DecodeResult],
                  world_from_cam: dict[str, np.ndarray], *, scan: int = 0, seed: int = 0) -> None:
    """Both cameras (posed pinholes, textures), the cloud (through `rec.log_cloud`, in the first
    camera's frame) and a subsample of the matches drawn on both images."""
    s = rec.stream
    model = result.model
    for name, lens in zip(model.names, (model.left, model.right)):
        s.log(camera_path(name), _transform(world_from_cam[name]), _rerun_pinhole(lens, 100.0), static=True,
              strict=True)
    rec.at_scan(scan)
    for name, d in decoded.items():
        s.log(f"{camera_path(name)}/image", rr.Image(np.asarray(d.texture, dtype=np.float32)), strict=True)
    rec.log_cloud(result.cloud)
    idx, right_xy = result.right_pixels()
    if len(idx):
        pick = np.sort(np.random.default_rng(seed).choice(len(idx), min(MAX_MATCHES_SHOWN, len(idx)), replace=False))
        width = result.cloud.valid.shape[1]
        rows, cols = np.divmod(idx[pick], width)
        colours = _depth_colours(result.cloud.points.reshape(-1, 3)[idx[pick], 2])
        ids = np.arange(len(pick), dtype=np.uint16)
        a, b = model.names
        # Rerun puts pixel (0, 0)'s centre at (0.5, 0.5), OpenCV at (0, 0)
        s.log(f"{camera_path(a)}/image/matches", rr.Points2D(np.column_stack([cols, rows]) + 0.5, colors=colours,
                                                             class_ids=ids, radii=1.5), strict=True)
        s.log(f"{camera_path(b)}/image/matches", rr.Points2D(right_xy[pick] + 0.5, colors=colours, class_ids=ids,
                                                             radii=1.5), strict=True)
    rec.log_metrics({f"binocular_{k}": v for k, v in result.checks.items() if np.isfinite(v)}, scan=scan)


def log_scan(rec: SessionRecording, scan: Any) -> None:
    """A `scanner.binocular_pipeline.BinocularScan` into `rec` (the first camera's rig and maps too)."""
    from scanner.binocular_session import camera_model

    session = scan.session
    names = list(scan.decoded)
    rec.log_rig(camera_model(session, names[0]))
    rec.log_decode(scan.decoded[names[0]], detail=False)
    log_binocular(rec, scan.result, scan.decoded, {n: camera_model(session, n).world_from_cam for n in names})
