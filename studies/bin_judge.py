"""Poses found in a saved simulated bin judged against its truth (`sim.bins.BinTruth` and
the simulator's per-pixel object ids).

Each instance is matched to the true part most of its pixels show (`truth_of_instance`:
the tray or nothing when most of them are not a part: a phantom); each reported pose is
compared with its instance's true part (`pose_difference`: rotation in degrees and the
translation of the part-frame origin in mm) and side. A pose is *wrong* when it is off
by more than `WRONG_MM` / `WRONG_DEG` or on the wrong side, or belongs to a phantom; a
*pick* (a pose offered for picking) must be within the robot's tolerance,
`PICK_MM` / `PICK_DEG`. Units: mm, degrees (human-facing figures).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from inspection.registration import pose_difference
from sim.bins import BinTruth

PICK_MM, PICK_DEG = 0.1, 0.5     # a pick offered must be this close to the truth
WRONG_MM, WRONG_DEG = 0.5, 2.0   # a pose reported ok farther off than this (or flipped) is wrong
MIN_VISIBLE_PX = 200             # a part showing fewer pixels cannot be found (the pose step's minimum)


@dataclass(frozen=True)
class PoseVerdict:
    """One reported pose judged: its instance id, the true part index (drop order) or -1
    for a phantom, rotation (deg) and translation (mm) errors, side right, pickable,
    estimated and true occlusion."""

    instance_id: int
    part: int
    rot_deg: float
    trans_mm: float
    side_ok: bool
    picked: bool
    occlusion: float
    true_occlusion: float

    @property
    def wrong(self) -> bool:
        return self.part < 0 or not (self.side_ok and self.rot_deg <= WRONG_DEG and self.trans_mm <= WRONG_MM)

    @property
    def within_pick_tolerance(self) -> bool:
        return self.part >= 0 and self.side_ok and self.rot_deg <= PICK_DEG and self.trans_mm <= PICK_MM


def truth_of_instance(indices: np.ndarray, object_id: np.ndarray, truth: BinTruth) -> tuple[int, float]:
    """(index of the true part most of the instance's pixels show, or -1 when most show the
    tray or nothing; the fraction of its pixels on that part)."""
    ids = object_id.ravel()[indices]
    values, counts = np.unique(ids, return_counts=True)
    top = values[np.argmax(counts)]
    share = float(counts.max() / max(len(ids), 1))
    where = np.flatnonzero(truth.ids == top)
    return (int(where[0]) if len(where) else -1), share


def judge(truth: BinTruth, object_id: np.ndarray, instances: list[Any], poses: list[Any],
          ranks: dict[int, int]) -> dict[str, Any]:
    """The figures of one bin: parts (visible ones: at least MIN_VISIBLE_PX pixels),
    instances, instances per true part, phantoms (instances mostly off every part), and
    per ok pose its `PoseVerdict` (`ranks`: pick rank of the pickable instances)."""
    match = {i.id: truth_of_instance(i.indices, object_id, truth) for i in instances}
    visible = np.array([(object_id == i).sum() for i in truth.ids])
    verdicts = []
    for p in poses:
        if not p.ok:
            continue
        k, _ = match.get(p.instance_id, (-1, 0.0))
        if k >= 0:
            rot, trans = pose_difference(truth.camera_from_part[k], p.pose)
            side_ok = (p.side == "front") == bool(truth.front_up[k])
            true_occ = float(truth.occlusion[k])
        else:
            rot, trans, side_ok, true_occ = float("inf"), float("inf"), False, float("nan")
        verdicts.append(PoseVerdict(p.instance_id, k, float(rot), float(trans), side_ok, p.instance_id in ranks,
                                    float(p.occlusion), true_occ))
    found = {v.part for v in verdicts if v.part >= 0 and not v.wrong}
    return {"parts": len(truth.ids), "visible_parts": int((visible >= MIN_VISIBLE_PX).sum()),
            "instances": len(instances), "phantom_instances": sum(k < 0 for k, _ in match.values()),
            "parts_with_instance": len({k for k, _ in match.values() if k >= 0}),
            "parts_posed": len(found), "verdicts": verdicts,
            "pickable_true": [int(k) for k in range(len(truth.ids)) if k in found]}
