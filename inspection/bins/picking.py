"""From part poses to what a robot cell reads: duplicates merged, pick order, the poses
file (JSON) and the Rerun view of the bin.

Pick order: parts with a pose and an estimated occlusion of at most `max_occlusion` less
`OCCLUSION_BOUND` (the estimate's measured error: a part offered is covered at most
`max_occlusion` in truth, where poses stay within a robot's 0.1 mm / 0.5 deg) are
pickable; they are ranked uncovered first (occlusion <= `free_occlusion`), then by how
high they lie (closest to the camera along its axis first), then by occlusion. Parts
without a pose, or covered more, are listed unranked with the reason.

Poses file (`POSES_FORMAT`, version 2): when it was made (`created`, UTC ISO 8601), what
from (`source`, `rig`: the rig's name, its calibration file or "nominal (uncalibrated)", the
session id), the frames and conventions (`frames`, `units`), and per part its id, pick
rank (1 = first; null: not pickable), position (mm) and orientation of the part frame
(quaternion w, x, y, z and rotation matrix) in the camera frame and in the rig's world
frame, the approach (unit vector from the part toward the gripper: the part file's, or the
up face's normal) and, when the part file names one, the grip point (mm) in both frames,
the side up, occlusion, fitness, RMSE, method, time (wall and CPU); failed parts carry
`status: "failed"` and the reason, and no pose. Without a rig (a cloud file and no
`--rig`) there is no world frame: `world_from_camera` and every `world` entry are null and
`frames.world` says so. Units: mm (quaternions, matrices, directions: none).

Rerun (the rig's world frame as the recording's rig logged it, scan timeline):
``world/pose/instances`` the instances' points coloured by part;
``world/pose/models/part_<id>`` each posed part mesh; ``world/pose/pick_order`` a labelled
point per pickable part ("#rank id side"); ``pose/table`` the table;
``metrics/pose/<name>`` counts and median time.
"""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from inspection.bins.instances import Instance
from inspection.bins.part_model import ThinPartModel
from inspection.bins.pose import PartPose
from inspection.bins.pose_settings import PoseSettings
from inspection.registration import pose_difference, transform_points

if TYPE_CHECKING:  # rerun, which the recording imports, only when a recording is made
    from scanner.session_recording import SessionRecording

POSES_FORMAT = "slscan-poses"
POSES_VERSION = 2
NO_RIG = "camera frame only: no rig (pass --rig for the world frame)"
INSTANCES = "world/pose/instances"
MODELS = "world/pose/models"
PICK_ORDER = "world/pose/pick_order"
TABLE = "pose/table"
METRICS = "pose"  # under the core's metrics/
# how much the occlusion estimate (`inspection.bins.pose`, face samples checked at their
# pixels) may fall short of the truth: the largest shortfall measured over the saved
# simulated bins (`slscan bench pose --sessions`, "occlusion estimate - truth"), rounded up:
# 0.045 over 77 poses of 10 fringe-scanned bins (seeds 0-9; the estimate exceeded the truth
# by up to 0.068). A small sample: re-measure over more bins before trusting the margin
OCCLUSION_BOUND = 0.05


def merge_duplicates(poses: list[PartPose], model: ThinPartModel | None = None, angle_deg: float = 2.0,
                     dist_mm: float = 0.5, max_overlap: float = 0.1) -> list[PartPose]:
    """Drop poses that repeat a pose of an instance with more points (one part split into
    pieces by a part lying across it gives the same pose twice). With the `model`, a pose
    whose part would share space with one kept before (more than `max_overlap` of its
    face samples inside the other, `_overlap`: two parts cannot) is reported failed: a
    piece of a part posed apart from its other piece, or a wrong pose."""
    kept: list[PartPose] = []
    for p in sorted(poses, key=lambda p: -p.points):
        if p.ok and any(k.ok and all(np.less(pose_difference(k.posed()[0], p.posed()[0]), (angle_deg, dist_mm)))
                        for k in kept):
            continue
        if p.ok and model is not None:
            other = next((k for k in kept if k.ok and _overlap(model, p, k) > max_overlap), None)
            if other is not None:
                p = replace(p, ok=False, pose=None, reason=(
                    f"its pose ({p.side} up) puts the part where instance {other.instance_id}'s pose puts one "
                    f"(they would share space): a piece of that part, or a wrong pose"))
        kept.append(p)
    return sorted(kept, key=lambda p: p.instance_id)


def _overlap(model: ThinPartModel, p: PartPose, k: PartPose) -> float:
    """Fraction of pose p's up-face samples that pose k's part would hold: over k's
    outline (within 0.3 mm of its face samples, in plan) and within 0.7 thickness of k's
    up face, where a part lying on k (its up face one thickness above) or under it (one
    below) cannot be."""
    t = model.thickness_mm
    (p_pose, p_side), (k_pose, k_side) = p.posed(), k.posed()
    q = transform_points(np.linalg.inv(k_pose) @ p_pose, model.sides[p_side].interior)
    face = model.sides[k_side].face
    sign = 1.0 if k_side == "front" else -1.0
    level = float(np.median(face.points @ model.axis))
    h = sign * (q @ model.axis - level)
    plan = q - np.outer(q @ model.axis - level, model.axis)
    d, _ = face.tree.query(plan, distance_upper_bound=0.3)
    return float(np.mean(np.isfinite(d) & (np.abs(h) < 0.7 * t)))


def pick_order(poses: list[PartPose], max_occlusion: float = PoseSettings.max_occlusion,
               free_occlusion: float = 0.02) -> dict[int, int]:
    """{instance id: rank from 1} of the pickable parts (see the module docstring)."""
    pickable = [p for p in poses if p.ok and p.occlusion + OCCLUSION_BOUND <= max_occlusion]
    order = sorted(pickable, key=lambda p: (p.occlusion > free_occlusion, float(p.posed()[0][2, 3]), p.occlusion))
    return {p.instance_id: k for k, p in enumerate(order, start=1)}


def _frame(T: np.ndarray) -> dict[str, Any]:
    w_last = Rotation.from_matrix(T[:3, :3]).as_quat()   # scipy: x, y, z, w
    q = np.r_[w_last[3], w_last[:3]]
    q = q if q[0] >= 0 else -q
    return {"position_mm": [round(float(x), 5) for x in T[:3, 3]],
            "quaternion_wxyz": [round(float(x), 8) for x in q],
            "rotation": [[round(float(x), 8) for x in row] for row in T[:3, :3]]}


def poses_document(poses: list[PartPose], model: ThinPartModel, world_from_cam: np.ndarray | None, source: str,
                   *, rig: dict[str, Any] | None = None, max_occlusion: float = PoseSettings.max_occlusion,
                   message: str = "") -> dict[str, Any]:
    """The poses file's content (see the module docstring); `world_from_cam` None: no rig,
    camera frame only; `rig`: its name, calibration and session id as the file states them."""
    W = None if world_from_cam is None else np.asarray(world_from_cam, np.float64)
    ranks = pick_order(poses, max_occlusion)
    parts = []
    for p in sorted(poses, key=lambda p: (ranks.get(p.instance_id, 10 ** 9), p.instance_id)):
        row: dict[str, Any] = {"id": p.instance_id, "status": "ok" if p.ok else "failed",
                               "pick_rank": ranks.get(p.instance_id), "points": p.points, "method": p.method,
                               "time_ms": round(1000 * p.time_s, 1), "cpu_ms": round(1000 * p.cpu_s, 1)}
        if p.ok:
            pose, side = p.posed()
            grip, approach = model.up_face(side)
            a_cam = pose[:3, :3] @ approach
            row.update({"side_up": side, "occlusion": round(p.occlusion, 4), "fitness": round(p.fitness, 4),
                        "rmse_mm": round(p.rmse_mm, 5), "edge_fit": round(p.edge_fit, 4),
                        "side_margin": round(p.side_margin, 4),
                        "camera": _frame(pose), "world": None if W is None else _frame(W @ pose),
                        "approach": {"camera": _rounded(a_cam, 8),
                                     "world": None if W is None else _rounded(W[:3, :3] @ a_cam, 8)}})
            if grip is not None:
                g_cam = transform_points(pose, grip[None])[0]
                g_world = None if W is None else _rounded(transform_points(W, g_cam[None])[0], 5)
                row["grip_point_mm"] = {"camera": _rounded(g_cam, 5), "world": g_world}
            if p.instance_id not in ranks:
                row["reason"] = (f"occluded {p.occlusion:.0%} (limit {max_occlusion:.0%} less the estimate's "
                                 f"error bound {OCCLUSION_BOUND:.0%})")
        else:
            row["reason"] = p.reason
        if p.label:
            row["label"] = p.label
        parts.append(row)
    return {"format": POSES_FORMAT, "version": POSES_VERSION,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "source": source, "rig": rig, "part": model.name,
            "units": {"length": "mm", "angles": "none (quaternions, rotation matrices, unit vectors)"},
            "frames": {"pose": "part -> frame: a part-frame point p maps to R p + position",
                       "part": "the part file's frame: outline in x, y; back face on z = 0, front face toward +z",
                       "camera": "x right, y down (image rows), z along the optical axis away from the camera",
                       "world": NO_RIG if W is None else "the rig's world frame (world_from_camera)",
                       "quaternion": "w, x, y, z (Hamilton, unit, w >= 0)",
                       "approach": "unit vector from the part toward the gripper",
                       "side_up": "the part's face toward the camera (front: +z of the part frame)"},
            "world_from_camera": None if W is None else W.round(8).tolist(),
            "pick_rule": {"max_occlusion": max_occlusion, "occlusion_bound": OCCLUSION_BOUND},
            "message": message or f"{len(ranks)} of {len(poses)} parts pickable", "parts": parts}


def _rounded(v: np.ndarray, digits: int) -> list[float]:
    return [round(float(x), digits) for x in v]


def table(doc: dict[str, Any]) -> str:
    """The poses as a fixed-width text table (degrees for the tilt, human-facing)."""
    lines = [f"{'rank':>4} {'id':>4} {'status':<7} {'side':<5} {'x mm':>9} {'y mm':>9} {'z mm':>9} "
             f"{'tilt°':>6} {'occl':>5} {'fit':>5} {'rmse mm':>8} {'ms':>6}  note"]
    for r in doc["parts"]:
        rank = str(r["pick_rank"]) if r["pick_rank"] is not None else "-"
        if r["status"] == "ok":
            x, y, z = r["camera"]["position_mm"]
            R = np.asarray(r["camera"]["rotation"])
            tilt = np.degrees(np.arccos(min(1.0, abs(R[2, 2]))))
            lines.append(f"{rank:>4} {r['id']:>4} {'ok':<7} {r['side_up']:<5} {x:9.3f} {y:9.3f} {z:9.3f} {tilt:6.2f} "
                         f"{r['occlusion']:5.2f} {r['fitness']:5.3f} {r['rmse_mm']:8.4f} {r['time_ms']:6.0f}  "
                         f"{r.get('reason', '')}")
        else:
            lines.append(f"{rank:>4} {r['id']:>4} {'failed':<7} {'':<5} {'':>9} {'':>9} {'':>9} {'':>6} {'':>5} "
                         f"{'':>5} {'':>8} {r['time_ms']:6.0f}  {r['reason']}")
    lines.append(doc["message"])
    return "\n".join(lines)


def log_poses(recording: SessionRecording, doc: dict[str, Any], poses: list[PartPose], instances: list[Instance],
              model: ThinPartModel, scan_index: int = 0) -> None:
    """Log the bin's instances, posed models, pick order and table into `recording` at scan
    `scan_index`, in its rig's world frame (`world_from_cam`; see the module docstring)."""
    import rerun as rr

    W = recording.world_from_cam
    stream = recording.stream
    recording.at_scan(scan_index)
    if instances:
        pts = transform_points(W, np.concatenate([i.points for i in instances]))
        ids = np.concatenate([np.full(len(i), i.id) for i in instances])
        stream.log(INSTANCES, rr.Points3D(pts.astype(np.float32), class_ids=(ids % 65535).astype(np.uint16)),
                   strict=True)
    ranks = {r["id"]: r["pick_rank"] for r in doc["parts"]}
    anchors, labels = [], []
    for p in poses:
        if not p.ok:
            continue
        v = transform_points(W @ p.pose, model.vertices)
        rank = ranks.get(p.instance_id)
        colour = [0.2, 0.8, 0.3, 0.6] if rank is not None else [0.9, 0.4, 0.2, 0.6]
        stream.log(f"{MODELS}/part_{p.instance_id}", rr.Mesh3D(vertex_positions=v.astype(np.float32),
                                                               triangle_indices=model.triangles.astype(np.uint32),
                                                               albedo_factor=colour), strict=True)
        if rank is not None:
            anchors.append(v.mean(axis=0))
            labels.append(f"#{rank} id {p.instance_id} {p.side}")
    if anchors:
        stream.log(PICK_ORDER, rr.Points3D(np.array(anchors, np.float32), labels=labels, radii=0.5), strict=True)
    stream.log(TABLE, rr.TextDocument("```\n" + table(doc) + "\n```", media_type=rr.MediaType.MARKDOWN), strict=True)
    ok = [p for p in poses if p.ok]
    metrics = {"parts": float(len(poses)), "posed": float(len(ok)),
               "pickable": float(sum(r["pick_rank"] is not None for r in doc["parts"])),
               "median_time_ms": float(np.median([1000 * p.time_s for p in poses])) if poses else 0.0}
    recording.log_metrics({f"{METRICS}/{name}": value for name, value in metrics.items()}, scan=scan_index)


def write_poses(path: Any, doc: dict[str, Any]) -> None:
    """Write the poses file atomically (a robot cell polling it never reads half a file)."""
    from pathlib import Path

    from scanner.session import write_json

    write_json(Path(path), doc)

