"""Each scan point's signed deviation from CAD as the inspection measured it, kept beside
the report (`outputs/inspection_points.npz`) so exports can carry it as a scalar field.

The file holds, over the inspected cloud's points in their file order: `deviation_mm`
(float32, NaN for points that are not the part or on no face) and, for organised scans,
`pixels` (uint16 (N, 2), row and column of each point's camera pixel), with which a reader
checks the cloud is still the one inspected."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from inspection.errors import InspectionError
from scanner.file_checks import ArraySpec, FileRefused, load_npz
from scanner.session import open_new, temp_path

POINTS_FILE = "inspection_points.npz"


def write_point_deviations(folder: str | Path, scan: Any, report: Any) -> Path:
    """Write the per-point deviations of `report` (an InspectionReport of `scan`)."""
    dev = np.full(len(scan), np.nan, dtype=np.float32)
    dev[report.part_mask] = report.segmentation.deviation_mm
    arrays = {"deviation_mm": dev}
    if scan.pixels is not None:  # ScanCloud pixels are (column, row)
        arrays["pixels"] = scan.pixels[:, ::-1].astype(np.uint16)
    path = Path(folder) / POINTS_FILE
    tmp = temp_path(path, ".npz")
    try:
        with open_new(tmp) as f:
            np.savez_compressed(f, allow_pickle=False, **arrays)  # numeric arrays: nothing to pickle
        tmp.replace(path)
    except BaseException:  # e.g. a full disk: no partial file left behind
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_point_deviations(folder: str | Path, pixels: np.ndarray | None) -> np.ndarray:
    """The (N,) deviations (mm, NaN off the part) saved in `folder`, checked against the
    cloud's `pixels` ((N, 2) row, col) when both have them."""
    path = Path(folder) / POINTS_FILE
    if not path.is_file():
        raise InspectionError(f"{path}: no per-point deviations; inspect the session again (`slscan inspect`)")
    try:
        data = load_npz(path, {"deviation_mm": ArraySpec("f", 1), "pixels": ArraySpec("iu", 2)},
                        what="per-point deviations file", optional=("pixels",))
    except FileRefused as exc:
        raise InspectionError(f"{exc}; inspect the session again (`slscan inspect`)") from None
    dev, saved = data["deviation_mm"], data.get("pixels")
    if pixels is not None and (len(pixels) != len(dev) or (saved is not None and not np.array_equal(saved, pixels))):
        raise InspectionError(f"{path}: inspected a different cloud than the session's (decoded again since?); "
                              f"inspect the session again")
    return dev
