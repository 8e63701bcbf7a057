"""What pose estimation of thin flat parts can be tuned by (`PoseSettings`), and its error."""

from __future__ import annotations

from dataclasses import dataclass

from inspection.errors import InspectionError

METHODS = ("sacia", "ndt")


class PoseError(InspectionError):
    """A part model or pose-estimation input is unusable (not a thin flat part, bad settings)."""


@dataclass(frozen=True)
class PoseSettings:
    """`method`: coarse step, "sacia" or "ndt"; `extrude_mm` / `wall_levels`: depth and
    levels of the walls dropped from outlines; `voxel_mm`: the coarse clouds' voxel;
    `max_normal_deg`: ICP's normal-angle rejection; `min_fitness`: fraction of the
    instance's points on the posed face (within `inlier_mm`) below which the pose fails;
    `min_edge_fit`: the same for the instance's true outline points on the part's outline;
    `ambiguity_margin`: a distinct pose (or the other side) judged within it of the best
    makes the instance ambiguous (failed); `max_spill`: fraction of the posed face
    allowed where a lower surface is seen;
    `max_plane_rms_mm`, `min_plane_fraction`: an instance with a larger robust RMS
    distance to its plane, or a smaller fraction of its points within that distance, is
    not one flat part;
    `max_pose_occlusion`: a pose of a part estimated covered more than this is reported
    failed (its fragment is too small to rule out the part turned over: on saved
    simulated bins the only wrong poses reported were of parts ~70 % covered);
    `max_occlusion`: the most a part offered for picking may be covered (in truth: the
    estimate plus its error bound, `inspection.bins.picking.OCCLUSION_BOUND`; poses of parts
    covered more stray beyond 0.1 mm on the saved simulated bins); `visible_occlusion`:
    below it an instance counts as mostly visible (its other side's coarse search may be
    skipped); `mirror_occlusion`: from
    this estimated occlusion up, the best pose is also flipped over about lines through
    the visible fragment every `mirror_step_deg` (a fragment symmetric about a line is
    explained as well by the other side up: that rival must be judged); `min_points`: smaller
    instances are not posed; `hypotheses`: SAC-IA triplets scored (`prescored`: the best by
    a pre-score on a fifth of the points scored on all); `verify`: its distinct
    coarse poses refined per side; `attempts`: SAC-IA runs (fresh samples) before an
    instance is reported as failed; `judge_icp_stride`, `judge_icp_iterations`: the ICP of
    every judged pose runs its first iterations (threshold shrinking from 6 voxels) on
    every `judge_icp_stride`-th point, its last ones on all (on saved simulated bins, 4 + 2
    iterations this way judged as 15 on all points did, in a third of the time)."""

    method: str = "sacia"
    extrude_mm: float = 1.5
    wall_levels: int = 3
    voxel_mm: float = 0.3
    max_normal_deg: float = 30.0
    min_fitness: float = 0.9
    min_edge_fit: float = 0.8
    inlier_mm: float = 0.15
    max_spill: float = 0.05
    ambiguity_margin: float = 0.1
    max_plane_rms_mm: float = 0.1
    min_plane_fraction: float = 0.8
    max_occlusion: float = 0.15
    max_pose_occlusion: float = 0.5
    visible_occlusion: float = 0.3
    mirror_occlusion: float = 0.2
    mirror_step_deg: float = 15.0
    min_points: int = 200
    hypotheses: int = 100
    prescored: int = 25
    verify: int = 2
    attempts: int = 3
    judge_icp_stride: int = 3
    judge_icp_iterations: tuple[int, int] = (4, 2)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise PoseError(f"unknown pose method {self.method!r}; use one of {METHODS}")
        if not (self.extrude_mm > 0 and self.wall_levels >= 1 and self.voxel_mm > 0 and 0 < self.min_fitness <= 1):
            raise PoseError(f"inconsistent pose settings: {self}")


DEFAULT_POSE_SETTINGS = PoseSettings()  # the defaults, shared (frozen): the functions' default argument
