"""The inspection result in a session's Rerun recording (a `scanner.session_recording.SessionRecording`),
in the rig's world frame (the recording's `world_from_cam`, logged with its rig), on the
scan timeline:

=====================================  ================================================
entity path                            content
=====================================  ================================================
``world/inspection/cad``               Mesh3D: the CAD model at the registered pose
``world/inspection/deviation``         Points3D: the part's points coloured by the deviation
                                       their figures are taken from, on the tolerance-tied
                                       scale (`inspection.deviation_colours`; grey: none)
``world/inspection/deviation_legend``  Points3D: the scale's colour legend beside the part
                                       (right of it as the camera sees it), one labelled
                                       swatch per step (mm)
``world/inspection/faces``             Points3D: the part's points, class id = face
                                       index + 1 (0: on no face), labels = face names
``inspection/deviation_map``           Image: the deviation map (camera image layout), its
                                       colour legend drawn at its right
``inspection/report``                  TextDocument (markdown): the per-face table
``metrics/inspection/<name>``          Scalars: fitness, RMSE (mm), verdict counts
=====================================  ================================================
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from inspection.cad import CadModel
from inspection.deviation_colours import ColourScale, deviation_image, scale_of, shown_deviations
from inspection.measured_cloud import ScanCloud
from inspection.registration import transform_points
from inspection.registration.driver import AMBIGUOUS
from inspection.report import InspectionReport
from scanner.session_recording import SessionRecording

CAD = "world/inspection/cad"
DEVIATION = "world/inspection/deviation"
DEVIATION_LEGEND = "world/inspection/deviation_legend"
FACES = "world/inspection/faces"
DEVIATION_MAP = "inspection/deviation_map"
REPORT = "inspection/report"
METRICS = "inspection"  # under the core's metrics/


def log_inspection(recording: SessionRecording, report: InspectionReport, scan: ScanCloud, model: CadModel,
                   scan_index: int = 0) -> None:
    """Log `report` (of `scan`, camera frame, against `model`) into `recording` at scan
    `scan_index`, the geometry moved into the rig's world frame."""
    world_from_cam = recording.world_from_cam
    world_from_model = world_from_cam @ np.linalg.inv(report.registration.transform)  # transform: scan -> model
    tess = model.tessellation
    stream = recording.stream
    recording.at_scan(scan_index)
    if report.status != AMBIGUOUS:  # a pose another explains as well is not drawn as the part's; one with a
        # free motion is: the faces it measures do not depend on that motion
        stream.log(CAD, rr.Mesh3D(vertex_positions=transform_points(world_from_model, tess.vertices).astype(np.float32),
                                  triangle_indices=tess.triangles, albedo_factor=[0.75, 0.78, 0.85, 0.35]),
                   strict=True)
    part = transform_points(world_from_cam, scan.points[report.part_mask]).astype(np.float32)
    seg = report.segmentation
    scale = scale_of(report)
    rgb = scale.rgb(shown_deviations(report))
    stream.log(DEVIATION, rr.Points3D(part, colors=np.round(rgb * 255).astype(np.uint8)), strict=True)
    stream.log(DEVIATION_LEGEND, legend_points(scale, scan.points[report.part_mask], world_from_cam), strict=True)
    labels = [rr.AnnotationInfo(id=0, label="no face", color=(128, 128, 128))]
    names = {r.label: r.title for r in report.faces}  # "high top #657" where the part program names the face
    labels += [rr.AnnotationInfo(id=f.index + 1, label=f"{names.get(f.label, f.label)} {f.type}") for f in model.faces]
    stream.log(FACES, rr.AnnotationContext(labels), static=True, strict=True)
    stream.log(FACES, rr.Points3D(part, class_ids=(seg.face + 1).astype(np.uint16)), strict=True)
    stream.log(DEVIATION_MAP, rr.Image(deviation_image(report, scan, scale)), strict=True)
    stream.log(REPORT, rr.TextDocument("```\n" + report.table() + "\n```", media_type=rr.MediaType.MARKDOWN),
               strict=True)
    verdicts = [v for row in report.faces for _, v in row.verdicts.values()]
    metrics = {"fitness": report.fitness, "rmse_mm": report.rmse_mm,
               **{f"{w.replace('-', '_')}_count": float(verdicts.count(w))
                  for w in ("conforming", "non-conforming", "uncertain")}}
    recording.log_metrics({f"{METRICS}/{name}": value for name, value in metrics.items()}, scan=scan_index)


def legend_points(scale: ColourScale, part_cam: np.ndarray, world_from_cam: np.ndarray) -> rr.Points3D:
    """The colour scale as labelled swatches in a column beside the part, as the camera sees
    it (camera frame `part_cam`, mm: right of the part, from above nominal at the top of the
    image to below it at the bottom), moved into the world frame."""
    lo, hi = part_cam.min(axis=0), part_cam.max(axis=0)
    steps = scale.legend()[::-1]  # far above first: the top of the image
    size = float(np.linalg.norm(hi[:2] - lo[:2])) or 1.0
    gap = (hi[1] - lo[1]) / max(len(steps) - 1, 1)
    cam = np.array([[hi[0] + 0.08 * size, lo[1] + k * gap, float(np.median(part_cam[:, 2]))]
                    for k in range(len(steps))])
    rgb = scale.rgb(np.array([d for d, _ in steps]))
    labels = [text for _, text in steps]
    labels[len(labels) // 2] += f" ({scale.source})"
    return rr.Points3D(transform_points(world_from_cam, cam).astype(np.float32), radii=0.015 * size,
                       colors=np.round(rgb * 255).astype(np.uint8), labels=labels, show_labels=True)
