"""Importing a real capture made by another tool: the kamino410 procam-calibration sample
(OpenCV Gray code, 1280 x 1024 camera, 1024 x 768 projector, a flat 9 x 7 chessboard with
75 mm squares) with the tool's own calibration_result.xml (projector scale 2, its
graycode_step). The board is flat and its squares are known: the truth."""

from __future__ import annotations

from pathlib import Path

import pytest

from slscan.commands.bench.import_ import OPENCV_GRAYCODE, board_figures
from slscan.commands.import_ import import_frames, list_frames, read_frames

PROCAM = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam-graycode"

pytestmark = pytest.mark.skipif(not PROCAM.is_dir(), reason="../shared/data/procam-graycode is not here (real data)")


def _pose(name: str, tmp_path: Path) -> dict:
    pose = PROCAM / name
    result, detection = import_frames(pose, OPENCV_GRAYCODE, (1024, 768), tmp_path / name,
                                      calibration=PROCAM / "calibration_result.xml", projector_scale=2.0)
    assert {f.key: f.value for f in detection.findings} == {"references": "last"}
    stack, _ = read_frames(list_frames(pose, None))
    return board_figures(tmp_path / name, stack[-2], result.session.rig_model(), 75.0)


@pytest.mark.acceptance
def test_procam_pose_0_board_is_flat_and_to_scale(tmp_path: Path) -> None:
    """Whole-pixel Gray codes at 3.6 m: one projector pixel is ~9 mm of depth on this rig's
    ~0.68 m baseline, so the plane RMS is that quantisation (2-4 mm), while the corner
    distances (rays through the 63 corners meeting the fitted plane) test the scale."""
    f = _pose("capture_0", tmp_path)
    assert f["board_points"] > 20000
    assert f["plane_rms_mm"] < 5.0
    assert abs(f["corner_error_mean_mm"]) < 0.5 and f["corner_error_rms_mm"] < 0.5


@pytest.mark.slow
@pytest.mark.acceptance
@pytest.mark.parametrize("pose", ["capture_1", "capture_2", "capture_3", "capture_4"])
def test_procam_other_poses(pose: str, tmp_path: Path) -> None:
    f = _pose(pose, tmp_path)
    assert f["plane_rms_mm"] < 5.0
    assert abs(f["corner_error_mean_mm"]) < 1.0 and f["corner_error_rms_mm"] < 2.0
