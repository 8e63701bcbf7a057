"""Calibrations made by other tools, read into our rig model (`slscan import --calibration`).

The one place that says which matrix is which, in what unit and which way:

| | slscan `calibration.json` | SLMaster `caliInfo.yml` | procam `calibration_result.xml` |
|---|---|---|---|
| camera K, dist | `rig_model.camera` | `M1`, `D1` | `cam_int`, `cam_dist` |
| projector K, dist | `rig_model.projector` | `M4`, `D4` | `proj_int`, `proj_dist` |
| extrinsics | `cam_from_proj` | `Rlp`, `Tlp` | `roration`, `translation` |
| camera size | `image_sizes` | `S` (w, h) | `img_shape` (h, w) |

(both foreign files are OpenCV FileStorage, YAML and XML; ours is described in
scanner/calibration_file.py.)

(procam is kamino410's procam-calibration; `roration` is its spelling.)

- Both foreign extrinsics map camera-frame points into the projector frame, X_p = R·X_c + T
  (OpenCV stereoCalibrate with the camera first), so our `cam_from_proj` is their inverse.
- Lengths are in the unit of the calibration board's square size as the user typed it into
  the tool: millimetres for both tools' examples (SLMaster's boards, procam's `75`); we take
  them as mm (`unit_mm` scales them otherwise).
- Intrinsics are in pixels with OpenCV's convention (pixel centres at integers); distortion
  is OpenCV's (k1, k2, p1, p2, k3); longer vectors are refused rather than truncated.
- `projector_scale`: projector coordinates in the file are this many times ours. procam's
  `graycode_step` multiplies every decoded projector pixel by the step before calibrating, so
  its file describes a projector `step` times larger; with scale s the projector's fx, fy,
  cx, cy are divided by s (x_file = s·x_ours: no half-pixel shift, the tool multiplies the
  integer pixel index). Nothing in the file says which step was used: it is the user's to give.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from scanner.calibration_file import load_calibration
from scanner.errors import CalibrationFileError
from scanner.geometry import Pinhole, RigModel

FORMATS = {
    "slmaster": {"camera": ("M1", "D1"), "projector": ("M4", "D4"), "extrinsics": ("Rlp", "Tlp")},
    "procam": {"camera": ("cam_int", "cam_dist"), "projector": ("proj_int", "proj_dist"),
               "extrinsics": ("roration", "translation")},
}


def _matrix(fs: cv2.FileStorage, key: str, path: Path, shape: tuple[int, ...] | None = None) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty():
        raise CalibrationFileError(path, f"key '{key}' missing")
    m = node.mat()
    if m is None:
        raise CalibrationFileError(path, f"key '{key}' is not a matrix")
    m = np.asarray(m, dtype=np.float64)
    if shape is not None and m.size != int(np.prod(shape)):
        raise CalibrationFileError(path, f"key '{key}' has {m.size} values, expected {int(np.prod(shape))}")
    if not np.all(np.isfinite(m)):
        raise CalibrationFileError(path, f"key '{key}' holds a non-finite value")
    return m.reshape(shape) if shape is not None else m


def _distortion(fs: cv2.FileStorage, key: str, path: Path) -> np.ndarray:
    d = _matrix(fs, key, path).ravel()
    if d.size > 5 and np.any(d[5:] != 0):
        raise CalibrationFileError(path, f"key '{key}' has {d.size} distortion terms; slscan models OpenCV's first "
                                         f"five (k1, k2, p1, p2, k3)")
    return d[:5]


def _format(fs: cv2.FileStorage, path: Path) -> str:
    for name, keys in FORMATS.items():
        if not fs.getNode(keys["camera"][0]).empty():
            return name
    raise CalibrationFileError(path, "an OpenCV FileStorage file, but neither SLMaster's (M1/D1, M4/D4, Rlp/Tlp) nor "
                                     "procam's (cam_int, proj_int, roration, translation) keys are in it")


def read_opencv_calibration(path: str | Path, camera_size: tuple[int, int], projector_size: tuple[int, int],
                            projector_scale: float = 1.0, unit_mm: float = 1.0) -> tuple[RigModel, str]:
    """The rig model in an SLMaster or procam FileStorage file (module docstring), for a
    camera of `camera_size` and a projector of `projector_size` (w, h, px). Returns the model
    and the format's name."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(path, "calibration file not found")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CalibrationFileError(path, f"not a readable OpenCV FileStorage file: {exc.err}") from None
    try:
        if not fs.isOpened():
            raise CalibrationFileError(path, "not a readable OpenCV FileStorage file")
        name = _format(fs, path)
        keys = FORMATS[name]
        K_cam = _matrix(fs, keys["camera"][0], path, (3, 3))
        K_proj = _matrix(fs, keys["projector"][0], path, (3, 3)).copy()
        d_cam, d_proj = _distortion(fs, keys["camera"][1], path), _distortion(fs, keys["projector"][1], path)
        R = _matrix(fs, keys["extrinsics"][0], path, (3, 3))
        T = _matrix(fs, keys["extrinsics"][1], path, (3,)) * unit_mm
        stored = _stored_camera_size(fs, name, path)
    finally:
        fs.release()
    if stored is not None and tuple(stored) != tuple(camera_size):
        raise CalibrationFileError(path, f"made for a camera of {stored[0]} x {stored[1]} px, the frames are "
                                         f"{camera_size[0]} x {camera_size[1]} px")
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or np.abs(R @ R.T - np.eye(3)).max() > 1e-3:
        raise CalibrationFileError(path, f"'{keys['extrinsics'][0]}' is not a rotation matrix")
    if projector_scale <= 0:
        raise CalibrationFileError(path, f"projector scale must be positive, got {projector_scale}")
    K_proj[:2] /= projector_scale
    for label, K, size in (("camera", K_cam, camera_size), ("projector", K_proj, projector_size)):
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise CalibrationFileError(path, f"{label} focal lengths must be positive, got {K[0, 0]}, {K[1, 1]}")
        if not (-0.5 * size[0] < K[0, 2] < 1.5 * size[0] and -0.5 * size[1] < K[1, 2] < 1.5 * size[1]):
            hint = " (is the projector size right, or does the file need a projector scale?)" \
                if label == "projector" else ""
            raise CalibrationFileError(path, f"{label} principal point ({K[0, 2]:.0f}, {K[1, 2]:.0f}) px lies far "
                                             f"outside its {size[0]} x {size[1]} image{hint}")
    proj_from_cam = np.eye(4)
    proj_from_cam[:3, :3], proj_from_cam[:3, 3] = R, T
    model = RigModel(Pinhole(*camera_size, K_cam, d_cam), Pinhole(*projector_size, K_proj, d_proj),
                     np.linalg.inv(proj_from_cam), calibration=str(path.resolve()))
    return model, name


def _stored_camera_size(fs: cv2.FileStorage, name: str, path: Path) -> tuple[int, int] | None:
    """The camera image size the file names, if any (SLMaster's S is (w, h), procam's
    img_shape (rows, cols))."""
    key = "S" if name == "slmaster" else "img_shape"
    node = fs.getNode(key)
    if node.empty():
        return None
    if node.isSeq():
        v = np.array([node.at(i).real() for i in range(node.size())])
    else:
        m = node.mat()
        v = np.asarray(m, dtype=np.float64).ravel() if m is not None else np.zeros(0)
    if v.size != 2:
        return None
    w, h = (v[0], v[1]) if name == "slmaster" else (v[1], v[0])
    return round(w), round(h)


def read_calibration(path: str | Path, camera_size: tuple[int, int], projector_size: tuple[int, int],
                     projector_scale: float = 1.0) -> tuple[RigModel, str]:
    """Our calibration.json, or another tool's FileStorage YAML/XML; (model, format name).
    Our own file names its image sizes and is refused for other ones."""
    path = Path(path)
    if path.suffix.lower() == ".json":
        if projector_scale != 1.0:
            raise CalibrationFileError(path, "a projector scale applies to other tools' files, not to slscan's")
        return load_calibration(path, camera_size, projector_size).model, "slscan"
    return read_opencv_calibration(path, camera_size, projector_size, projector_scale)
