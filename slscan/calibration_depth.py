"""What a calibration's error does to depth on a simulated scene, and whether its covariance
says so.

The calibration's own share of a scan's mean depth error: the scene's true projector
coordinates (the simulator's ground truth, no decoding noise) triangulated with the
calibrated rig, minus the true depth, averaged over the smooth lit pixels (`sim.evaluate.
smooth_region`, the pixels the scan check judges). Its one-sigma under the calibration's
covariance Σ is propagated through the same triangulation: Σ's correlation matrix is split
into its eigenvectors, the rig is moved by one sigma along each in turn (both ways) and the
mean's changes add in quadrature. A true covariance makes error / sigma a standard normal
value over independent calibrations; a mean depth error far outside its sigma is a
calibration error the covariance does not carry.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.consistency import parameters_model
from scanner.geometry import RigModel
from scanner.reconstruct import Triangulator
from sim.evaluate import Truth, smooth_region
from sim.render import compute_ground_truth
from sim.scene import load_scene


@dataclass(frozen=True)
class DepthBias:
    """The calibration's mean depth error on the scene (µm), its one-sigma from the
    calibration's covariance (µm), over `pixels` camera pixels."""

    error_um: float
    sigma_um: float
    pixels: int

    @property
    def z(self) -> float:
        return self.error_um / self.sigma_um if self.sigma_um > 0 else float("nan")

    def to_dict(self) -> dict[str, float | int]:
        return {"error_um": self.error_um, "sigma_um": self.sigma_um, "z": self.z, "pixels": self.pixels}

    def summary(self) -> str:
        return (f"the calibration's own mean depth error (the true projector coordinates triangulated with it, "
                f"{self.pixels} px) {self.error_um:+.2f} um, one sigma {self.sigma_um:.2f} um from its covariance "
                f"(z {self.z:+.2f})")


def calibration_depth_bias(truth: RigModel, estimate: np.ndarray, covariance: np.ndarray, scene_path: Path, *,
                           orientation: str = "vertical") -> DepthBias:
    """The calibration (`estimate` (24,) in the order of `calibration.consistency.rig_parameters`,
    its `covariance` (24, 24)) against the simulator's `truth`, on the scene at `scene_path`,
    triangulating the `orientation` fringes' coordinate (module docstring)."""
    gt = Truth.of(compute_ground_truth(truth, load_scene(scene_path)))
    region = smooth_region(gt)
    coord = np.where(region, gt.proj_uv[..., 0 if orientation == "vertical" else 1], np.nan).astype(np.float32)
    depth = gt.depth[region].astype(np.float64)

    def mean_error_mm(parameters: np.ndarray) -> float:
        z = Triangulator(parameters_model(parameters, truth)).depth_scale(coord, orientation)
        return float(np.mean(np.asarray(z, dtype=np.float64)[region] - depth))

    sd = np.sqrt(np.maximum(np.diag(covariance), 0.0))
    free = np.flatnonzero(sd > 0)
    correlation = covariance[np.ix_(free, free)] / np.outer(sd[free], sd[free])
    values, vectors = np.linalg.eigh(correlation)
    changes = []
    for value, vector in zip(values, vectors.T):
        step = np.zeros(len(estimate))
        step[free] = sd[free] * vector * np.sqrt(max(value, 0.0))
        changes.append((mean_error_mm(estimate + step) - mean_error_mm(estimate - step)) / 2.0)
    sigma = float(np.sqrt(np.sum(np.square(changes))))
    return DepthBias(mean_error_mm(estimate) * 1e3, sigma * 1e3, int(region.sum()))
