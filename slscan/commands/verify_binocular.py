"""`slscan verify` on a rig with two cameras: each position scanned by every camera at once and
measured on the binocular cloud (scanner/binocular.py), its points' noise the binocular
prediction from both cameras' phase noise, and the stereo calibration's covariance carried into
every figure through each point's ∂X/∂θ from the matcher (`BinocularResult.calibration_jacobian`:
one error common to the scan, added over a figure's points before squaring). A stereo model
stating no covariance (the rig file's nominal geometry, another tool's file) leaves that term
out, and the report says so."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from scanner.binocular import BinocularReconstructor


def binocular_scan_data(rig: Any, patterns: Any, gamma: float, bino: BinocularReconstructor) -> tuple[Any, Any]:
    """(the binocular cloud, its `inspection.acceptance.ScanData`) of one scan of `rig`."""
    from inspection.acceptance import ScanData
    from inspection.uncertainty import PointJacobian, PointNoise, ScanUncertainty
    from scanner.acquisition import AcquisitionSettings, acquire_all
    from scanner.decode import decode

    compensated = replace(rig, model=replace(rig.model, projector_gamma=gamma))
    stacks = acquire_all(compensated, patterns, AcquisitionSettings.for_rig(rig), lambda *a: None)
    names = list(stacks)[:2]
    decoded = [decode(stacks[n], patterns, rig.cameras[n].bit_depth, rig.model.projector.size) for n in names]
    result = bino.reconstruct(decoded[0], decoded[1])
    rays = bino.model.left.ray_grid
    calibration = binocular_calibration(bino.model)
    width = rays.shape[1]

    def uncertainty(px: np.ndarray) -> Any:
        cols, rows = px[:, 0], px[:, 1]
        noise = PointNoise(result.depth_sigma_mm[rows, cols].astype(np.float64),
                           rays[rows, cols].astype(np.float64), source="binocular: both cameras' decoded phase noise")
        return ScanUncertainty(noise, calibration, jacobian=PointJacobian(result.calibration_jacobian,
                                                                          rows.astype(np.int64) * width + cols))

    return result.cloud, ScanData(result.cloud.points, uncertainty)


def binocular_calibration(model: Any) -> Any:
    """The stereo calibration's covariance as `inspection.uncertainty.CalibrationUncertainty` (its
    24 parameters in `scanner.binocular.parameter_names` order, the right camera where a
    monocular rig has its projector), or none, saying why."""
    from inspection.uncertainty import CalibrationUncertainty

    if model.covariance is None:
        return CalibrationUncertainty.none("not included: the stereo model states no covariance (the rig file's "
                                           "nominal geometry or another tool's file)")
    return CalibrationUncertainty(model.covariance, f"the stereo calibration's covariance ({model.calibration})")
