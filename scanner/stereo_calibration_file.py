"""Stereo calibrations of two cameras: ours (`stereo_calibration.json`, written by `slscan calibrate`
on a rig with two cameras) and other tools' OpenCV FileStorage files (YAML or XML), read into a
`scanner.binocular.StereoModel`.

The one place that says which matrix is which:

| file | left K, dist | right K, dist | extrinsics (X_right = R·X_left + T) | image size |
|---|---|---|---|---|
| slscan `stereo_calibration.json` | `stereo_model.left` | `stereo_model.right` | `right_from_left` | `image_sizes` |
| SLMaster `caliInfo.yml` (binocular) | `M1`, `D1` | `M2`, `D2` | `Rlr`, `Tlr` | `S` (w, h) |
| OpenCV stereo_calib sample (`intrinsics.yml` + `extrinsics.yml`) | `M1`, `D1` | `M2`, `D2` | `R`, `T` | none |

- Both tools' R, T come from OpenCV's `stereoCalibrate` with the left camera first, so they map
  left-camera points into the right camera's frame, our `right_from_left`.
- `R1`, `R2`, `P1`, `P2`, `Q` (`stereoRectify`'s outputs) are derived data: slscan rectifies
  again from the intrinsics and R, T (SLMaster computes them with the board's size passed as the
  image size, so its P1, P2, Q do not describe the images). When the file has `R1` and `R2`
  they must agree with R, T (R2·R = R1, and R2·T along x): a file whose rectification
  contradicts its extrinsics is refused.
- Lengths are in the board unit the user gave the tool (millimetres in both tools' examples):
  taken as mm, `unit_mm` scales them otherwise. Distortion is OpenCV's (k1, k2, p1, p2, k3);
  longer vectors with non-zero extra terms are refused.
- The image size comes from the frames; a file that states one (`S`) must agree with them.
- The files say nothing of a projector: a binocular import needs none.
- Ours holds the solve's covariance of the 24 parameters (`report.covariance`: parameters and
  matrix, `StereoModel.covariance`), which gives the points their calibration term
  (scanner/binocular.py); the other tools' files hold none: their points' calibration term is
  "not included".
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from scanner import schema
from scanner.binocular import StereoModel
from scanner.errors import CalibrationFileError, ConfigError
from scanner.geometry import Pinhole
from scanner.rig_schema import check_intrinsics

STEREO_CALIBRATION_VERSION = 1
RECTIFICATION_TOLERANCE = 1e-6  # of a rotation matrix's entries: stored doubles, rounded to ~1e-15 by writers


def write_stereo_calibration(path: str | Path, model: StereoModel, report: dict[str, Any]) -> Path:
    """Write ours (module docstring): the model, the image sizes and the solve's `report`; the
    model's covariance once, as the report's "covariance"."""
    from scanner.session import write_json

    path = Path(path)
    stereo = model.to_dict()
    covariance = stereo.pop("covariance", None)
    write_json(path, {"slscan_stereo_calibration": STEREO_CALIBRATION_VERSION, "stereo_model": stereo,
                      "image_sizes": {"left": list(model.left.size), "right": list(model.right.size)},
                      "report": report | ({"covariance": covariance} if covariance is not None else {})})
    return path


def _fs_matrix(fs: cv2.FileStorage, key: str, path: Path, size: int | None = None) -> np.ndarray | None:
    node = fs.getNode(key)
    if node.empty():
        return None
    m = node.mat()
    if m is None:
        raise CalibrationFileError(path, f"key '{key}' is not a matrix")
    m = np.asarray(m, dtype=np.float64).ravel()
    if size is not None and m.size != size:
        raise CalibrationFileError(path, f"key '{key}' has {m.size} values, expected {size}")
    if not np.isfinite(m).all():
        raise CalibrationFileError(path, f"key '{key}' holds a non-finite value")
    return m


def _needed(value: np.ndarray | None, key: str, path: Path, fmt: str) -> np.ndarray:
    if value is None:
        raise CalibrationFileError(path, f"key '{key}' missing ({fmt} stereo calibration)")
    return value


def _pinhole(K: np.ndarray, dist: np.ndarray, size: tuple[int, int], key: str, path: Path) -> Pinhole:
    if dist.size > 5 and np.any(dist[5:] != 0):
        raise CalibrationFileError(path, f"key '{key}' has {dist.size} distortion terms; slscan models OpenCV's "
                                         f"first five (k1, k2, p1, p2, k3)")
    K = K.reshape(3, 3)
    try:
        check_intrinsics(K, *size)
    except ValueError as exc:
        raise CalibrationFileError(path, f"{key}: {exc} (for {size[0]} x {size[1]} px frames)") from None
    return Pinhole(size[0], size[1], K, dist[:5])


def read_opencv_stereo(paths: list[Path], left_size: tuple[int, int], right_size: tuple[int, int],
                       unit_mm: float = 1.0) -> tuple[StereoModel, str]:
    """Another tool's stereo calibration, in one OpenCV FileStorage file or two (intrinsics and
    extrinsics, as OpenCV's stereo_calib sample writes them); (model, format name)."""
    values: dict[str, np.ndarray] = {}
    where: dict[str, Path] = {}
    for path in paths:
        try:
            fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except cv2.error:
            fs = None
        if fs is None or not fs.isOpened():
            raise CalibrationFileError(path, "not an OpenCV FileStorage file (YAML or XML)")
        try:
            for key, size in (("M1", 9), ("D1", None), ("M2", 9), ("D2", None), ("Rlr", 9), ("Tlr", 3), ("R", 9),
                              ("T", 3), ("R1", 9), ("R2", 9), ("S", 2)):
                m = _fs_matrix(fs, key, path, size)
                if m is not None:
                    if key in values:
                        raise CalibrationFileError(path, f"key '{key}' is also in {where[key]}")
                    values[key], where[key] = m, path
        finally:
            fs.release()
    first = paths[0]
    fmt = "slmaster" if "Rlr" in values else "opencv-stereo"
    if "Rlr" in values and "R" in values:
        raise CalibrationFileError(first, "both SLMaster's Rlr/Tlr and OpenCV's R/T extrinsics: which is meant?")
    r_key, t_key = ("Rlr", "Tlr") if fmt == "slmaster" else ("R", "T")
    if "M1" not in values and "Rlr" not in values and "R" not in values:
        raise CalibrationFileError(first, "an OpenCV FileStorage file, but none of a stereo calibration's keys "
                                          "(M1/D1, M2/D2, and Rlr/Tlr or R/T)")
    K1, D1 = (_needed(values.get(k), k, where.get(k, first), fmt) for k in ("M1", "D1"))
    K2, D2 = (_needed(values.get(k), k, where.get(k, first), fmt) for k in ("M2", "D2"))
    R = _needed(values.get(r_key), r_key, first, fmt).reshape(3, 3)
    T = _needed(values.get(t_key), t_key, first, fmt) * unit_mm
    if "S" in values and tuple(int(v) for v in values["S"]) != tuple(left_size):
        raise CalibrationFileError(where["S"], f"'S' says the images are {int(values['S'][0])} x "
                                               f"{int(values['S'][1])} px, the left frames are {left_size[0]} x "
                                               f"{left_size[1]} px")
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0):
        raise CalibrationFileError(where[r_key], f"'{r_key}' is not a rotation matrix")
    if "R1" in values and "R2" in values:
        R1, R2 = values["R1"].reshape(3, 3), values["R2"].reshape(3, 3)
        t = R2 @ T
        off = float(np.abs(R2 @ R - R1).max())
        if off > RECTIFICATION_TOLERANCE or np.hypot(t[1], t[2]) > 1e-6 * np.linalg.norm(T):
            raise CalibrationFileError(where["R1"], f"the file's rectification R1, R2 contradicts its extrinsics "
                                                   f"{r_key}, {t_key} (R2·R differs from R1 by {off:.2g}; R2·T = "
                                                   f"{np.round(t, 4).tolist()}): the keys come from different "
                                                   f"calibrations")
    T4 = np.eye(4)
    T4[:3, :3], T4[:3, 3] = R, T
    left = _pinhole(K1, D1, left_size, "M1/D1", where["M1"])
    right = _pinhole(K2, D2, right_size, "M2/D2", where["M2"])
    try:
        model = StereoModel(left, right, T4, calibration=", ".join(str(p.resolve()) for p in paths))
    except ValueError as exc:
        raise CalibrationFileError(first, str(exc)) from None
    return model, fmt


def read_stereo_calibration(paths: list[str | Path], left_size: tuple[int, int], right_size: tuple[int, int],
                            unit_mm: float = 1.0) -> tuple[StereoModel, str]:
    """A stereo calibration for frames of `left_size`, `right_size` (w, h): ours (JSON) or another
    tool's OpenCV file(s); (model, format: "slscan", "slmaster" or "opencv-stereo")."""
    files = [Path(p) for p in paths]
    for p in files:
        if not p.is_file():
            raise CalibrationFileError(p, "no such file")
    if files[0].suffix.lower() == ".json":
        if len(files) > 1:
            raise CalibrationFileError(files[1], "slscan's stereo calibration is one file")
        return _read_ours(files[0], left_size, right_size), "slscan"
    return read_opencv_stereo(files, left_size, right_size, unit_mm)


def _read_ours(path: Path, left_size: tuple[int, int], right_size: tuple[int, int]) -> StereoModel:
    from scanner.binocular_session import StereoCovarianceSchema, StereoModelSchema

    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationFileError(path, f"unreadable: {exc}") from None
    if not isinstance(data, dict) or data.get("slscan_stereo_calibration") != STEREO_CALIBRATION_VERSION:
        raise CalibrationFileError(path, f"not an slscan stereo calibration (version "
                                         f"{STEREO_CALIBRATION_VERSION})")
    report = data.get("report")
    covariance = report.get("covariance") if isinstance(report, dict) else None
    try:
        schema.parse(StereoModelSchema, data.get("stereo_model"), path, prefix="stereo_model")
        if covariance is not None:
            schema.parse(StereoCovarianceSchema, covariance, path, prefix="report.covariance")
        model = StereoModel.from_dict(data["stereo_model"] | ({"covariance": covariance} if covariance else {}),
                                      str(path))
    except ConfigError as exc:
        raise CalibrationFileError(path, str(exc)) from None
    for name, lens, size in (("left", model.left, left_size), ("right", model.right, right_size)):
        if lens.size != tuple(size):
            raise CalibrationFileError(path, f"the {name} camera is calibrated at {lens.width} x {lens.height} px, "
                                             f"its frames are {size[0]} x {size[1]} px")
    return replace(model, calibration=str(path.resolve()))
