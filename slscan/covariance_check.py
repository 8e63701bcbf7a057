"""Is a calibration's covariance true? Independent simulated calibrations, each against the
simulator's true rig: the Mahalanobis distance d² of the true parameters under the
covariance the calibration reports (`calibration.consistency`).

Each calibration is a fresh draw: its own seed for the sensor noise and for the board
poses (every pose, the frontal first one too, turned by up to JITTER_DEG about each axis:
a pose the same in every draw would repeat its detection errors in all of them),
captured, decoded and solved as `slscan calibrate` does on the simulated rig (the board
poses only: no plate, no artefact, no leave-one-out). A true covariance gives a mean d²
equal to its degrees of freedom and 95 % of the calibrations under the chi-square 95 %
point; the figures come with their own sampling spread (the mean's standard error, the
fraction's binomial interval), so a campaign of 30 says what 30 can say. What the
covariance means for a scan: each calibration's own mean depth error on the scan check's
sphere-and-plane scene over its one-sigma from the covariance (`slscan.calibration_depth`),
a standard normal value over the draws when the covariance is true.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from calibration.consistency import Distance, mahalanobis, model_parameters, rig_parameters
from calibration.stereo import RIG_PARAMETERS
from slscan.calibration_depth import DepthBias, calibration_depth_bias

JITTER_DEG = 6.0  # board poses turned by up to this about each axis, per calibration


@dataclass(frozen=True)
class Draw:
    """One simulated calibration: its seed, the distance of the truth under its
    covariance, its parameters' errors (`estimate` minus the truth, RIG_PARAMETERS' units)
    and covariance, its mean depth error on the scan check's scene, the corners' noise it
    estimated, and its seconds."""

    seed: int
    distance: Distance
    error: np.ndarray
    covariance: np.ndarray
    depth: DepthBias
    noise: dict[str, Any]
    seconds: float

    def line(self) -> str:
        worst = ", ".join(f"{n} {z:+.1f}σ" for n, z in self.distance.worst())
        return (f"seed {self.seed}: d² {self.distance.d2:.1f} on {self.distance.dof} dof; worst {worst}; depth "
                f"{self.depth.error_um:+.2f} ± {self.depth.sigma_um:.2f} um (z {self.depth.z:+.2f}) "
                f"({self.seconds:.0f} s)")

    def to_dict(self) -> dict[str, Any]:
        return {"seed": self.seed, "d2": self.distance.d2, "dof": self.distance.dof,
                "z": dict(zip(RIG_PARAMETERS, self.distance.z.tolist())),
                "error": dict(zip(RIG_PARAMETERS, self.error.tolist())), "covariance": self.covariance.tolist(),
                "depth": self.depth.to_dict(), "noise": self.noise, "seconds": self.seconds}


@dataclass(frozen=True)
class CovarianceCheck:
    """The campaign's draws and what they say about the covariance."""

    rig: str
    poses: int
    draws: list[Draw] = field(default_factory=list)
    failed: dict[int, str] = field(default_factory=dict)  # seed -> why (a device fault: no draw, not a refusal)

    @property
    def dof(self) -> int:
        return max(d.distance.dof for d in self.draws)

    def summary(self) -> dict[str, Any]:
        from scipy.stats import beta, chi2

        d2 = np.array([d.distance.d2 for d in self.draws])
        dof = np.array([d.distance.dof for d in self.draws])
        n = len(d2)
        under = int(np.sum(d2 <= chi2.ppf(0.95, dof)))
        lo = float(beta.ppf(0.025, under, n - under + 1)) if under else 0.0
        hi = float(beta.ppf(0.975, under + 1, n - under)) if under < n else 1.0
        z = np.array([d.distance.z for d in self.draws])
        depth_z = np.array([d.depth.z for d in self.draws])
        ratio = d2 / dof
        return {"rig": self.rig, "poses": self.poses, "calibrations": n, "seeds": [d.seed for d in self.draws],
                "dof": int(self.dof), "d2": d2.tolist(), "mean_d2_over_dof": float(ratio.mean()),
                # for a true covariance d²/dof has variance 2/dof: the mean's standard error
                "mean_d2_over_dof_expected_sd": float(np.sqrt(2.0 / self.dof / n)),
                "under_chi2_95": under / n, "under_chi2_95_interval": [lo, hi],
                "z_mean": dict(zip(RIG_PARAMETERS, np.nanmean(z, axis=0).tolist())),
                "z_sd": dict(zip(RIG_PARAMETERS, np.nanstd(z, axis=0).tolist())),
                # the calibration's mean depth error on the scan check's scene over its sigma
                "depth_z_mean": float(depth_z.mean()), "depth_z_sd": float(depth_z.std()),
                "depth_within_2_sigma": float(np.mean(np.abs(depth_z) <= 1.96)),
                "draws": [d.to_dict() for d in self.draws], "failed": {str(k): v for k, v in self.failed.items()}}

    def lines(self) -> list[str]:
        s = self.summary()
        lo, hi = s["under_chi2_95_interval"]
        z_sd = sorted(s["z_sd"].items(), key=lambda kv: -kv[1])[:4]
        return [f"{s['calibrations']} independent simulated calibrations of {self.rig} ({self.poses} board poses "
                f"each), seeds {s['seeds'][0]}..{s['seeds'][-1]}: the true rig's Mahalanobis distance under each "
                f"calibration's covariance",
                f"mean d²/dof {s['mean_d2_over_dof']:.2f} (1 for a true covariance, "
                f"± {s['mean_d2_over_dof_expected_sd']:.2f} for {s['calibrations']} draws); "
                f"{s['under_chi2_95']:.0%} under the chi-square 95 % point "
                f"(95 % interval {lo:.0%}..{hi:.0%}; 95 % for a true covariance)",
                "largest spread of a parameter's error in its own sigmas (1 for a true covariance): "
                + ", ".join(f"{k} {v:.2f}" for k, v in z_sd),
                f"the calibration's mean depth error on the scan check's scene in its own sigmas: mean "
                f"{s['depth_z_mean']:+.2f}, spread {s['depth_z_sd']:.2f} (0 and 1 for a true covariance), "
                f"{s['depth_within_2_sigma']:.0%} within ± 1.96 (95 %)"]


def simulated_draw(rig_toml: Path, seed: int, poses: int | None, jitter_deg: float = JITTER_DEG) -> Draw:
    """One simulated calibration of the rig `rig_toml` (a simulated rig) from `seed`."""
    from calibration.solve import solve
    from calibration.workflow import Procedure, capture_board_poses
    from scanner.rig import RigConfig, open_rig
    from sim.calibration_bench import plate_scene
    from slscan.simulated_calibration_bench import PLATE_BEHIND_MM, SCAN_CHECK_SCENE, simulated_bench

    t0 = time.perf_counter()
    config = RigConfig.load(rig_toml)
    procedure = Procedure.for_rig(config, poses=poses)
    truth = config.nominal_model()
    with open_rig(config, scene=plate_scene(config.working_distance_mm + PLATE_BEHIND_MM), seed=seed) as rig:
        bench = simulated_bench(rig, procedure, seed, jitter_deg, jitter_first=True)
        _, views, _ = capture_board_poses(rig, procedure, bench, lambda text: None)
        sizes = (rig.camera.width, rig.camera.height), (rig.projector.width, rig.projector.height)
    s = solve(views, *sizes, procedure.settings).stereo
    estimate = rig_parameters(s.camera, s.projector, s.proj_from_cam)
    distance = mahalanobis(estimate, model_parameters(truth), s.covariance)
    depth = calibration_depth_bias(truth, estimate, s.covariance, SCAN_CHECK_SCENE)
    return Draw(seed, distance, estimate - model_parameters(truth), s.covariance, depth, s.noise.to_dict(),
                time.perf_counter() - t0)


def covariance_check(rig_toml: Path, calibrations: int, seed: int, poses: int | None,
                     say: Callable[[str], None], jitter_deg: float = JITTER_DEG) -> CovarianceCheck:
    """`calibrations` independent simulated calibrations, seeds `seed`, `seed` + 1, ..."""
    from calibration.workflow import Procedure
    from scanner.rig import RigConfig

    config = RigConfig.load(rig_toml)
    if config.driver != "sim":
        raise ValueError(f"{rig_toml}: the covariance check needs a simulated rig (its truth), not a "
                         f"{config.driver} one")
    from scanner.errors import DeviceError

    check = CovarianceCheck(config.name, Procedure.for_rig(config, poses=poses).poses)
    for k in range(calibrations):
        try:
            draw = simulated_draw(rig_toml, seed + k, poses, jitter_deg)
        except DeviceError as exc:  # the simulated devices time out on an overloaded machine: that seed has no draw
            check.failed[seed + k] = str(exc)
            say(f"[{k + 1}/{calibrations}] seed {seed + k}: no calibration ({exc})")
            continue
        check.draws.append(draw)
        say(f"[{k + 1}/{calibrations}] {draw.line()}")
    if not check.draws:
        raise DeviceError("simulated calibration",
                          f"none of the {calibrations} simulated calibrations completed: {check.failed}")
    return check
