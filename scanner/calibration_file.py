"""The calibration file: versioned, human-readable JSON, with the phase-to-height reference
maps in an .npz beside it.

    {
      "format": "slscan-calibration", "version": 1,
      "created": ISO date, "software_version": ..., "rig": rig name,
      "image_sizes": {"camera": [w, h], "projector": [w, h]},
      "board": the board description,
      "rig_model": the rig geometry (`RigModel.to_dict`), projector gamma and the
                   phase-to-height coefficients included (their maps in the .npz),
      "rms_px": {"camera": ..., "projector": ..., "stereo": ...},
      "uncertainty": one-sigma of every parameter,
      "covariance": {"parameters": [24 names], "matrix": 24 x 24, "decoding_matrix": 24 x 24,
                   "noise_model": {...}}:
                   the covariance of the rig's parameters (both devices' intrinsics and
                   distortion, the extrinsic as a Rodrigues vector (rad) and a translation
                   (mm)), for the uncertainty of measurements (`inspection.uncertainty`),
                   the part of it the decoding's own error makes (the rest is the camera
                   corners'),
                   and the corners' error model it rests on: its statement, the one-sigma
                   of each noise group (px) with its degrees of freedom, how they were
                   estimated and what is assumed (`calibration.stereo.CornerErrorModel`),
      "views": per view: name, camera and projector RMS (px), points,
      "dropped_views": name -> reason,
      "separate": each device's own calibration before the joint refinement,
      "gamma", "phase_to_height", "validation", "stability": their reports (or null),
      "limits": the limits the calibration passed,
      "reference_maps": "<name>.npz" (when phase_to_height is present): the reference
                   phase and the per-pixel l and K maps (`PhaseToHeight.maps`)
    }

Loading checks the format, the version and the image sizes against the rig, and refuses a
mismatch (CalibrationFileError) rather than reconstructing with the wrong geometry. The
model loaded names its file (`RigModel.calibration`), so scans record which calibration
they used.
"""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from scanner import __version__, schema
from scanner.errors import CalibrationFileError, ConfigError
from scanner.file_checks import FileRefused, read_regular
from scanner.geometry import RigModel
from scanner.rig_schema import RigModelSchema, check_geometry
from scanner.session import write_json, write_npz

CALIBRATION_FORMAT = "slscan-calibration"
CALIBRATION_VERSION = 1


@dataclass(frozen=True, eq=False)
class CalibrationFile:
    """A calibration file read back: its JSON content and the rig model it describes."""

    path: Path
    data: dict[str, Any]
    model: RigModel

    @property
    def camera_size(self) -> tuple[int, int]:
        return tuple(self.data["image_sizes"]["camera"])

    @property
    def projector_size(self) -> tuple[int, int]:
        return tuple(self.data["image_sizes"]["projector"])


def maps_path(path: Path) -> Path:
    """The .npz of reference maps beside a calibration JSON."""
    return path.with_suffix(".npz")


def write_calibration(path: str | Path, model: RigModel, report: dict[str, Any], rig_name: str) -> Path:
    """Write the calibration JSON (and first the .npz of the phase-to-height maps, when the
    model has them); each file appears complete or not at all. Returns the JSON path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    extra: dict[str, Any] = {}
    if model.phase_to_height is not None:
        npz = maps_path(path)
        write_npz(npz, model.phase_to_height.maps())
        model = replace(model, phase_to_height=replace(model.phase_to_height, maps_file=npz.name))
        extra["reference_maps"] = npz.name
    data: dict[str, Any] = {
        "format": CALIBRATION_FORMAT, "version": CALIBRATION_VERSION,
        "created": dt.datetime.now(dt.UTC).isoformat(), "software_version": __version__, "rig": rig_name,
        "image_sizes": {"camera": list(model.camera.size), "projector": list(model.projector.size)},
        "rig_model": replace(model, calibration="").to_dict(), **report, **extra}
    write_json(path, data)
    return path


MAX_CALIBRATION_BYTES = 64 * 1024 ** 2  # a calibration's JSON (its maps are in the .npz beside it)

def load_calibration(path: str | Path, camera_size: tuple[int, int] | None = None,
                     projector_size: tuple[int, int] | None = None) -> CalibrationFile:
    """Read a calibration file; with sizes given, refuse one made for other image sizes."""
    path = Path(path)
    if not path.exists():
        raise CalibrationFileError(path, "calibration file not found; run `slscan calibrate` for this rig")
    try:
        data = json.loads(read_regular(path, limit=MAX_CALIBRATION_BYTES))
    except FileRefused as exc:
        raise CalibrationFileError(path, exc.problem) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise CalibrationFileError(path, f"unreadable calibration file: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != CALIBRATION_FORMAT:
        raise CalibrationFileError(path, f"not an slscan calibration file (format {data.get('format')!r})"
                                   if isinstance(data, dict) else "not an slscan calibration file")
    if data.get("version") != CALIBRATION_VERSION:
        raise CalibrationFileError(path, f"calibration file version {data.get('version')!r}; this slscan reads "
                                         f"version {CALIBRATION_VERSION}: calibrate again")
    try:
        sizes = {k: tuple(int(v) for v in data["image_sizes"][k]) for k in ("camera", "projector")}
        if any(len(v) != 2 for v in sizes.values()):
            raise ValueError("two numbers per device")
    except (KeyError, TypeError, ValueError, OverflowError):
        raise CalibrationFileError(path, "key 'image_sizes' missing or malformed") from None
    for device, expected in (("camera", camera_size), ("projector", projector_size)):
        if expected is not None and sizes[device] != tuple(expected):
            raise CalibrationFileError(path, f"made for a {device} of {sizes[device][0]} x {sizes[device][1]} px, "
                                             f"the rig's {device} is {expected[0]} x {expected[1]} px: calibrate "
                                             f"this rig, or name the right calibration file")
    try:
        schema.parse(RigModelSchema, data.get("rig_model"), path, "rig_model")
    except ConfigError as exc:
        raise CalibrationFileError(path, f"key '{exc.key}': {exc.problem}" if exc.key else exc.problem) from None
    described = dict(data["rig_model"])
    p2h = described.get("phase_to_height")
    if p2h and not p2h.get("maps_file"):  # files written before the model named its maps
        described["phase_to_height"] = {**p2h, "maps_file": data.get("reference_maps") or ""}
    try:
        model = RigModel.from_dict({**described, "calibration": str(path.resolve())}, f"{path}: rig_model",
                                   path.parent)
    except ConfigError as exc:
        raise CalibrationFileError(path, exc.problem if exc.key is None else f"key '{exc.key}': {exc.problem}") \
            from None
    if model.camera.size != sizes["camera"] or model.projector.size != sizes["projector"]:
        raise CalibrationFileError(path, "rig_model image sizes disagree with image_sizes")
    try:
        check_geometry(model, None, path, "rig_model")
    except ConfigError as exc:
        raise CalibrationFileError(path, f"key 'rig_model': {exc.problem}") from None
    return CalibrationFile(path, data, model)


def load_rig_model(path: str | Path, camera_size: tuple[int, int], projector_size: tuple[int, int]) -> RigModel:
    """The calibrated geometry for a rig of these image sizes (used by `scanner.rig`)."""
    return load_calibration(path, camera_size, projector_size).model
