"""How far a calibration lies from a known rig in units of its own covariance: the
Mahalanobis distance d² = δᵀ Σ⁻¹ δ of the parameter differences δ (`RIG_PARAMETERS`).

When the covariance is true, d² over many independent calibrations follows a chi-square
distribution with as many degrees of freedom as the covariance has free directions: its
mean is that number and 95 % of the calibrations fall below its 95 % point. The check runs
where the truth is known (the simulator, `slscan calibrate --covariance-check`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from calibration.stereo import RIG_PARAMETERS
from scanner.geometry import Pinhole, RigModel


def rig_parameters(camera: Pinhole, projector: Pinhole, proj_from_cam: np.ndarray) -> np.ndarray:
    """The rig's parameters (P,) in the order of `RIG_PARAMETERS` (px, unitless distortion,
    rad, mm): each device's fx, fy, cx, cy, k1, k2, p1, p2, k3, then proj_from_cam as a
    Rodrigues vector and a translation."""
    out = []
    for device in (camera, projector):
        K = device.K
        out += [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *np.asarray(device.dist, dtype=np.float64)[:5]]
    out += [*cv2.Rodrigues(np.asarray(proj_from_cam[:3, :3], dtype=np.float64))[0].ravel(), *proj_from_cam[:3, 3]]
    return np.array(out, dtype=np.float64)


def model_parameters(model: RigModel) -> np.ndarray:
    """`rig_parameters` of a rig model."""
    return rig_parameters(model.camera, model.projector, model.proj_from_cam)


def parameters_model(parameters: np.ndarray, like: RigModel) -> RigModel:
    """The rig `like` (its device sizes, world pose, gamma) with the geometry `parameters`
    (P,) in the order of `rig_parameters`: its inverse."""
    p = np.asarray(parameters, dtype=np.float64)

    def device(old: Pinhole, q: np.ndarray) -> Pinhole:
        K = np.array([[q[0], 0.0, q[2]], [0.0, q[1], q[3]], [0.0, 0.0, 1.0]])
        return Pinhole(old.width, old.height, K, q[4:9].copy())

    proj_from_cam = np.eye(4)
    proj_from_cam[:3, :3] = cv2.Rodrigues(p[18:21])[0]
    proj_from_cam[:3, 3] = p[21:24]
    return replace(like, camera=device(like.camera, p[:9]), projector=device(like.projector, p[9:18]),
                   cam_from_proj=np.linalg.inv(proj_from_cam), phase_to_height=None)


@dataclass(frozen=True)
class Distance:
    """`d2` the Mahalanobis distance of a calibration from the truth on `dof` degrees of
    freedom (the parameters with a non-zero variance), and `z` (P,) each parameter's error
    over its one-sigma (NaN where the parameter was held fixed)."""

    d2: float
    dof: int
    z: np.ndarray

    def worst(self, n: int = 3) -> list[tuple[str, float]]:
        """The `n` parameters furthest from the truth in their own sigmas, worst first."""
        order = np.argsort(-np.nan_to_num(np.abs(self.z), nan=-1.0))[:n]
        return [(RIG_PARAMETERS[i], float(self.z[i])) for i in order]


def mahalanobis(estimate: np.ndarray, truth: np.ndarray, covariance: np.ndarray) -> Distance:
    """d² of `estimate` from `truth` (P,) under `covariance` (P, P), solved on the
    correlation matrix (the parameters span ten orders of magnitude) over the parameters
    with a variance."""
    delta = np.asarray(estimate, dtype=np.float64) - np.asarray(truth, dtype=np.float64)
    sd = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    free = sd > 0
    corr = covariance[np.ix_(free, free)] / np.outer(sd[free], sd[free])
    scaled = delta[free] / sd[free]
    z = np.full(len(delta), np.nan)
    z[free] = scaled
    return Distance(float(scaled @ np.linalg.solve(corr, scaled)), int(free.sum()), z)
