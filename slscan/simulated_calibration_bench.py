"""The simulated calibration bench `slscan calibrate` and its covariance check run on: the
board printed as a texture and moved through planned poses, the reference plate behind the
working distance, the sphere pair in front of it, and the scene the calibration's scan check
measures."""

from __future__ import annotations

from typing import Any

from scanner.config import CONFIG_DIR
from scanner.errors import ScannerError

SCAN_CHECK_SCENE = CONFIG_DIR / "scenes" / "sphere_plane.toml"
TEXELS_PER_PX = 4.0  # simulated board texture: texels per camera pixel at the working distance
PLATE_BEHIND_MM = 20.0  # simulated reference plate, beyond the working distance
ARTEFACT_BEFORE_MM = 10.0  # simulated sphere pair, nearer than the working distance


def simulated_bench(rig: Any, procedure: Any, seed: int = 0, jitter_deg: float = 2.0, *,
                    jitter_first: bool = False) -> Any:
    """The simulator's `Bench` for an open simulated rig: the procedure's board printed as
    a texture (TEXELS_PER_PX at the working distance), moved through planned poses (each
    but the first, or with `jitter_first` each, turned by up to `jitter_deg` about each
    axis, drawn from `seed`); the plate PLATE_BEHIND_MM behind the working distance; the
    sphere pair ARTEFACT_BEFORE_MM in front of it."""
    from sim.calibration_bench import SimBench, Target, plan_target_poses

    config, truth, board = rig.config, rig.config.nominal_model(), procedure.board
    footprint_mm = config.working_distance_mm / truth.camera.K[0, 0]
    target = Target(board.image(board.texture_density(TEXELS_PER_PX / footprint_mm)), board.size_mm,
                    board.image_origin_mm, board.object_points())
    try:
        poses = plan_target_poses(truth, target, procedure.poses, config.working_distance_mm, seed, jitter_deg,
                                  jitter_first=jitter_first)
    except ValueError as exc:
        raise ScannerError(f"simulated bench: {exc}") from None
    artefact = procedure.artefact
    return SimBench(rig, target, poses, plate_distance_mm=config.working_distance_mm + PLATE_BEHIND_MM,
                    sphere_radius_mm=artefact.radius_mm if artefact else 10.0,
                    sphere_distance_mm=artefact.distance_mm if artefact else 50.0,
                    artefact_distance_mm=config.working_distance_mm - ARTEFACT_BEFORE_MM)
