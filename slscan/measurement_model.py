"""The measurement model of a scan taken by slscan: what `inspection.uncertainty` needs to
give every figure its uncertainty, read from the session and its rig.

  - the noise: the session's raw frames decoded again (the same decoder and settings as
    its cloud, an HDR session's exposures fused as for its cloud: each pixel's noise is
    its chosen exposure's), with the camera's sensor model from the rig config
    ([camera.sensor]); without one, no noise model (the figures then estimate the noise
    from the data);
  - the fringe error of the projector's quantised patterns (pattern set, gamma, the
    projector's blur when the rig file gives it);
  - the calibration's covariance, from the calibration file the session's rig model
    names; a rig without one uses its nominal geometry: exact on the simulator, unknown
    (and said to be not in U) on a real rig;
  - the camera's defocus ([camera.sensor] blur_sigma_px; 0 without it), whose depth bias
    an inspection removes from the surfaces it measures (`inspection.uncertainty.defocus_bias`).

`recorded_measurement` is the one place this is put together, from the rig config read
through its typed tables (`scanner.rig_schema.RecordedRig`: a session's recorded one, or a
rig TOML's by `rig_measurement`): `scan`, `inspect`, `verify` and `slscan coverage` (the
repeat-scan studies) all take it from there.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from inspection.uncertainty import (
    CalibrationUncertainty,
    FringeError,
    MeasurementModel,
    ScanUncertainty,
    SensorNoise,
    fringe_error,
)
from scanner.camera_noise import CameraNoise
from scanner.decode import DecodeResult
from scanner.geometry import RigModel
from scanner.patterns import PatternSet
from scanner.pipeline import decode_session
from scanner.rig_schema import RecordedRig


def sensor_noise(sensor: CameraNoise | None, bit_depth: int) -> SensorNoise | None:
    """The camera's intensity noise (DN) as a function of its mean signal, from a rig
    config's [camera.sensor] table (None without one)."""
    if sensor is None:
        return None
    return lambda mean: sensor.noise_sigma_dn(mean, bit_depth)


def projector_fringe_error(patterns: PatternSet, model: RigModel, blur_px: float) -> FringeError:
    """The fringe error of the rig's projector showing `patterns`, blurred by `blur_px`
    (Gaussian sigma, projector px; the rig config's projector.blur_sigma_px, 0 when not given)."""
    extent = model.projector.width if "vertical" in patterns.orientations else model.projector.height
    return fringe_error(patterns, extent, model.projector_gamma, blur_px)


def calibration_uncertainty(model: RigModel, driver: str) -> CalibrationUncertainty:
    """The covariance of the calibration `model` was loaded from; without one, none, with
    what that means for this driver."""
    if model.calibration:
        path = Path(model.calibration)
        return CalibrationUncertainty.from_report(json.loads(path.read_text()))
    if driver == "sim":
        return CalibrationUncertainty.none("none: the simulator's nominal geometry is its truth")
    return CalibrationUncertainty.none("not known: the rig has no calibration file (nominal geometry); its error is "
                                       "not in U")


def rig_measurement(rig_config: Mapping[str, object], model: RigModel, patterns: PatternSet, bit_depth: int,
                    where: object) -> MeasurementModel:
    """The measurement model of a rig (its TOML's content, from the file `where`) measuring with `model`."""
    return recorded_measurement(RecordedRig(rig_config, str(where), key=""), model, patterns, bit_depth)


def recorded_measurement(rig: RecordedRig, model: RigModel, patterns: PatternSet, bit_depth: int) -> MeasurementModel:
    """The measurement model of a rig config read through its typed tables (a session's
    recorded one, or a rig TOML's): ConfigError for a table they need that is malformed.
    The camera's defocus is [camera.sensor] blur_sigma_px (0 without the table)."""
    sensor = rig.sensor
    return MeasurementModel(sensor_noise(sensor, bit_depth),
                            projector_fringe_error(patterns, model, rig.projector.blur_sigma_px),
                            calibration_uncertainty(model, rig.rig.driver or ""),
                            sensor.blur_sigma_px if sensor is not None else 0.0)


def session_uncertainty(session: Any, decoded: DecodeResult | None = None) -> Callable[[np.ndarray], ScanUncertainty]:
    """For a `scanner.session.Session`: a function giving the ScanUncertainty of the
    points at camera pixels (N, 2) (column, row) of its cloud, with the camera defocus's
    depth bias per point for the inspection to remove. `decoded`: the session's decode
    when it is at hand (a scan just processed: `ScanResult.decoded`), else its frames are
    decoded again."""
    model = session.rig_model()
    if decoded is None:
        decoded = decode_session(session)
    measurement = recorded_measurement(session.manifest.recorded_rig, model, session.patterns, session.bit_depth)
    return measurement.of_scan(decoded, model, defocus=True)
