"""The views of a multi-view session as clouds: points, normals, each point's expected
precision, where the sensor was, and the stage pose that places the view in the part frame.

Every view's cloud is given in the rig's world frame (the session's `world_from_cam`
applied), as the stage's axes are. `prior` is the view's pose in the part frame as the
stage says it (`part_from_view = inv(world_from_stage(q))`); `viewpoint` the camera centre,
both in that world frame. Units mm.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from inspection.errors import CloudError
from inspection.measured_cloud import load_session
from inspection.views.precision import depth_sigma, ray_sigma
from scanner.multiview import MultiViewSession, View
from scanner.stage_model import StageModel


@dataclass(frozen=True, eq=False)
class ViewCloud:
    """One view (see the module docstring): `points`, `normals` (N, 3) world frame, normals
    toward the sensor; `sigma` (N,) each point's expected (relative) noise, mm."""

    index: int
    name: str
    points: np.ndarray
    normals: np.ndarray
    sigma: np.ndarray
    viewpoint: np.ndarray
    prior: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, mask: np.ndarray) -> ViewCloud:
        return replace(self, points=self.points[mask], normals=self.normals[mask], sigma=self.sigma[mask])

    def moved(self, T: np.ndarray) -> ViewCloud:
        """The view with points, normals and viewpoint mapped by T (4x4)."""
        R, t = T[:3, :3], T[:3, 3]
        return replace(self, points=self.points @ R.T + t, normals=self.normals @ R.T, viewpoint=R @ self.viewpoint + t)


def load_view(view: View, stage_model: StageModel | None = None) -> ViewCloud:
    """A view of a multi-view session with each point's expected precision; its prior
    from `stage_model` at the view's stage position when given (a stage-axis calibration
    made after the scan), else the pose recorded at capture."""
    scan = load_session(view.session.root)
    assert scan.pixels is not None
    sigma_z = depth_sigma(view.session)[scan.pixels[:, 1], scan.pixels[:, 0]]
    sigma = ray_sigma(sigma_z, scan.points)
    ok = np.isfinite(sigma)
    if ok.sum() < 0.5 * len(scan):
        raise CloudError(view.session.root, f"only {ok.sum()} of {len(scan)} points have a decoded precision: "
                                            f"outputs/maps.npz is not this cloud's; run `slscan decode` again")
    world_from_cam = view.session.rig_model().world_from_cam
    world_from_stage = view.world_from_stage if stage_model is None else stage_model.world_from_stage(view.position)
    cam = ViewCloud(view.index, view.name, scan.points[ok], scan.normals[ok], sigma[ok], np.zeros(3),
                    np.linalg.inv(world_from_stage))
    return cam.moved(world_from_cam)


def load_views(session: MultiViewSession, stage_model: StageModel | None = None) -> list[ViewCloud]:
    """Every complete view of `session` (at least two), priors as `load_view`."""
    if len(session.views) < 2:
        raise CloudError(session.root, f"{len(session.views)} complete view(s): aligning views needs at least two")
    return [load_view(v, stage_model) for v in session.views]
