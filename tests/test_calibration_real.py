"""Calibration from a real projector-camera capture made by another tool: the public
procam-graycode sample (kamino410/procam-calibration; ../shared/data/procam-graycode): five
board poses, OpenCV Gray code for a 1024 x 768 projector, 9 x 7 corners of 75 mm, camera
1280 x 1024. Published result: camera fx 3452.39, fy 3449.92, cx 587.17, cy 521.45, stereo
RMS 0.857 px."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from scanner.config import CONFIG_DIR
from slscan import cli

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam-graycode"
BOARD = CONFIG_DIR / "boards" / "procam_chess_9x7_75mm.toml"
PUBLISHED_K = {"fx": 3452.39, "fy": 3449.92, "cx": 587.17, "cy": 521.45}
PUBLISHED_STEREO_RMS = 0.857

pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data/procam-graycode not present (real data is "
                                                          "only in CI and on the bench)")


def graycode_args(source: Path, out: Path, *extra: str) -> list[str]:
    return ["calibrate", "--from", str(source), "--layout", "opencv-graycode", "--projector-size", "1024x768",
            "--board", str(BOARD), "--pose-folders", "capture_*", "--out", str(out), *extra]


def test_real_graycode_capture_calibrates(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert cli.main(graycode_args(DATA, tmp_path / "cal")) == 0
    printed = capsys.readouterr().out
    data = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    assert data["image_sizes"] == {"camera": [1280, 1024], "projector": [1024, 768]}
    assert [v["name"] for v in data["views"]] == [f"capture_{i}" for i in range(5)]
    assert all(v["camera_points"] == 63 and v["projector_points"] >= 50 for v in data["views"])
    # five poses do not pin the camera in the joint refinement (its cx is known to ~10 px
    # there): the saved camera keeps its own views' intrinsics, and says so
    choice = data["camera_intrinsics"]
    assert choice["source"] == "camera views" and max(choice["joint_std"].values()) > choice["limit_px"]
    assert "intrinsics from the camera views: the joint refinement determines the camera's" in printed
    # the saved camera matrix (the one scans use) agrees with the published one within 0.5 %
    K = np.array(data["rig_model"]["camera"]["K"])
    assert np.allclose(K, data["separate"]["camera"]["K"])
    for name, value in zip(("fx", "fy", "cx", "cy"), (K[0, 0], K[1, 1], K[0, 2], K[1, 2])):
        assert abs(value / PUBLISHED_K[name] - 1.0) < 0.005, name
    assert data["rms_px"]["stereo"] <= PUBLISHED_STEREO_RMS
    # the report shows how stable the projector is when each pose is left out in turn
    loo = data["stability"]["leave_one_out"]
    for name in ("projector.fx", "projector.fy"):
        lo, hi, _ = loo[name]
        assert (hi - lo) / data["stability"]["values"][name] < 0.01, name
    assert "stability (leave one view out)" in printed and "projector.fx" in printed
    assert "gamma     not measured" in printed and "validate  no artefact scanned" in printed


def test_real_view_without_the_projector_pattern_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A pose whose Gray-code frames show nothing (the projector was off): a clear error
    naming the view, and no calibration file."""
    pose = tmp_path / "captures" / "capture_0"
    pose.mkdir(parents=True)
    for k in range(42):
        source = DATA / "capture_0" / f"graycode_{41 if k < 40 else k:02d}.png"  # every pattern frame is black
        shutil.copy(source, pose / f"graycode_{k:02d}.png")
    assert cli.main(graycode_args(tmp_path / "captures", tmp_path / "cal")) == 2
    err = capsys.readouterr().err
    assert "view 0 (capture_0): the projector pattern is missing on the board" in err
    assert not (tmp_path / "cal" / "calibration.json").exists()
