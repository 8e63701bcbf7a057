"""The inspection result in a session's Rerun recording (a `scanner.session_recording.SessionRecording`,
written through its `.stream`), in the world (camera) frame of the scan:

=====================================  ================================================  ========
entity path                            content                                           timeline
=====================================  ================================================  ========
``world/inspection/cad``               Mesh3D: the CAD model at the registered pose      scan
``world/inspection/deviation``         Points3D: the part's points coloured by signed    scan
                                       deviation (blue inside, red outside, grey: none)
``world/inspection/faces``             Points3D: the part's points, class id = face      scan
                                       index + 1 (0: on no face), labels = face names
``inspection/deviation_map``           Image: the deviation map (camera image layout)    scan
``inspection/report``                  TextDocument (markdown): the per-face table       scan
``metrics/inspection_<name>``          Scalars: fitness, RMSE (mm), verdict counts       scan
=====================================  ================================================  ========
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from inspection.cad import CadModel
from inspection.measured_cloud import ScanCloud
from inspection.report import InspectionReport, colour_limit, deviation_colours, deviation_image

CAD = "world/inspection/cad"
DEVIATION = "world/inspection/deviation"
FACES = "world/inspection/faces"
DEVIATION_MAP = "inspection/deviation_map"
REPORT = "inspection/report"


def log_inspection(recording: Any, report: InspectionReport, scan: ScanCloud, model: CadModel, scan_index: int = 0) -> None:
    """Log `report` (of `scan` against `model`) into `recording` on the scan timeline."""
    stream = recording.stream
    stream.reset_time()
    stream.set_time("scan", sequence=scan_index)
    to_scan = np.linalg.inv(report.registration.transform)  # model -> scan (camera) frame
    tess = model.tessellation
    v = tess.vertices @ to_scan[:3, :3].T + to_scan[:3, 3]
    stream.log(CAD, rr.Mesh3D(vertex_positions=v.astype(np.float32), triangle_indices=tess.triangles,
                              albedo_factor=[0.75, 0.78, 0.85, 0.35]), strict=True)
    part = scan.points[report.part_mask].astype(np.float32)
    seg = report.segmentation
    rgb = deviation_colours(seg.deviation_mm, colour_limit(report))
    stream.log(DEVIATION, rr.Points3D(part, colors=np.round(rgb * 255).astype(np.uint8)), strict=True)
    labels = [rr.AnnotationInfo(id=0, label="no face", color=(128, 128, 128))]
    names = {r.label: r.title for r in report.faces}  # "high top #657" where the part program names the face
    labels += [rr.AnnotationInfo(id=f.index + 1, label=f"{names.get(f.label, f.label)} {f.type}") for f in model.faces]
    stream.log(FACES, rr.AnnotationContext(labels), static=True, strict=True)
    stream.log(FACES, rr.Points3D(part, class_ids=(seg.face + 1).astype(np.uint16)), strict=True)
    stream.log(DEVIATION_MAP, rr.Image(deviation_image(report, scan)), strict=True)
    stream.log(REPORT, rr.TextDocument("```\n" + report.table() + "\n```", media_type=rr.MediaType.MARKDOWN),
               strict=True)
    verdicts = [v for row in report.faces for _, v in row.verdicts.values()]
    metrics = {"fitness": report.fitness, "rmse_mm": report.rmse_mm,
               **{f"{w.replace('-', '_')}_count": float(verdicts.count(w))
                  for w in ("conforming", "non-conforming", "uncertain")}}
    for name, value in metrics.items():
        stream.log(f"metrics/inspection_{name}", rr.Scalars(float(value)), strict=True)
