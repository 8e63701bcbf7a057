"""The whole part in a multi-view session's Rerun recording (a
`scanner.session_recording.SessionRecording` at the multi-view folder's recording.rrd,
written through its `.stream`). The 3D space `world` is the part frame (the stage frame).

=====================================  ================================================  ========
entity path                            content                                           timeline
=====================================  ================================================  ========
``world/views/<view>``                 Transform3D: the view's camera in the part frame  static
                                       (its refined pose), with its Pinhole
``world/priors/<view>``                Transform3D + Pinhole: where the stage put it     static
``world/views/<view>/cloud``           Points3D: the view's points (thinned), its frame  static
``world/merged``                       Points3D: the merged cloud, coloured by how many  static
                                       views each point fuses (grey 1, then hues)
``world/mesh``                         Mesh3D: the trimmed Poisson mesh                  static
``views/report``                       TextDocument: poses, pairs, mesh (markdown)       static
=====================================  ================================================  ========
"""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from inspection.views.pairwise import thin

VIEWS = "world/views"
PRIORS = "world/priors"
MERGED = "world/merged"
MESH = "world/mesh"
REPORT = "views/report"
VIEW_POINTS = 30000  # points shown per view
_HUES = np.array([[150, 150, 150], [66, 135, 245], [52, 199, 89], [255, 149, 0], [255, 59, 48], [175, 82, 222]],
                 np.uint8)


def log_whole_part(recording: Any, whole: Any) -> None:
    """Log a `inspection.views.whole.WholePart` (views, poses, merged cloud, mesh)."""
    stream = recording.stream
    stream.log("world", rr.ViewCoordinates.RDF, static=True, strict=True)
    for view, session_view, pose, prior in zip(whole.views, whole.session.views, whole.alignment.poses,
                                               whole.alignment.priors):
        model = session_view.session.rig_model()
        cam = model.camera
        pinhole = rr.Pinhole(image_from_camera=cam.K, width=cam.width, height=cam.height, image_plane_distance=60.0)
        path = f"{VIEWS}/{view.name}"
        for where, T in ((path, pose), (f"{PRIORS}/{view.name}", prior)):
            placed = T @ model.world_from_cam
            stream.log(where, rr.Transform3D(translation=placed[:3, 3], mat3x3=placed[:3, :3]), static=True,
                       strict=True)
            stream.log(where, pinhole, static=True, strict=True)
        keep = thin(view.points, 1.0)[:VIEW_POINTS]
        cam_from_world = np.linalg.inv(model.world_from_cam)
        pts = view.points[keep] @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        stream.log(f"{path}/cloud", rr.Points3D(pts.astype(np.float32), radii=0.1), static=True, strict=True)
    merged = whole.merged
    colours = _HUES[np.minimum(merged.views, len(_HUES)) - 1]
    stream.log(MERGED, rr.Points3D(merged.points.astype(np.float32), colors=colours, radii=0.08), static=True,
               strict=True)
    if whole.mesh is not None:
        stream.log(MESH, rr.Mesh3D(vertex_positions=whole.mesh.vertices.astype(np.float32),
                                   triangle_indices=whole.mesh.triangles.astype(np.uint32),
                                   albedo_factor=[0.8, 0.8, 0.85, 1.0]), static=True, strict=True)
    stream.log(REPORT, rr.TextDocument(report_markdown(whole), media_type=rr.MediaType.MARKDOWN), static=True,
               strict=True)


def report_markdown(whole: Any) -> str:
    """The alignment and the mesh, as a table for people."""
    a = whole.alignment
    rows = ["| view | correction of the stage pose |", "|---|---|"]
    rows += [f"| {n} | {d:.4f} deg, {m:.4f} mm |" for n, (d, m) in zip(a.names, a.corrections())]
    rows += ["", "| pair | overlap | RMS (mm) |", "|---|---|---|"]
    rows += [f"| {a.names[e.source]} - {a.names[e.target]} | {e.overlap:.0%} | {e.rmse_mm:.4f} |" for e in a.edges]
    rows += [f"| {a.names[s]} - {a.names[t]} | refused: {w} | |" for s, t, w in a.refused]
    if whole.mesh is not None:
        rows += ["", f"mesh: {whole.mesh.summary()}"]
    return "\n".join(rows)
