"""A stored session decoded with a fault (`slscan decode`): refused with exit 2 by the check
the fault breaks, naming the figure and the likely cause, no cloud written, the frames kept,
result.json holding every check; the rig model tied to the one recorded at capture."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_support import run_cli
from session_support import edit_manifest, frame, one_error_line, scan_small_session

from scanner.recording_reader import entity_paths
from scanner.session import MANIFEST


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small scan, unrecorded (level "none"): the tests decode it again."""
    return scan_small_session(tmp_path_factory.mktemp("refusals"), level="none")


@pytest.fixture
def copy(clean: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "s"
    shutil.copytree(clean, dst, ignore=shutil.ignore_patterns("outputs"))
    return dst


def refused(root: Path) -> tuple[str, dict]:
    code, err = run_cli("decode", str(root))
    line = one_error_line(err)
    assert code == 2 and not (root / "outputs" / "cloud.ply").exists()
    assert len(list((root / "frames").iterdir())) == len(json.loads((root / MANIFEST).read_text())["frames"])
    result = json.loads((root / "outputs" / "result.json").read_text())
    assert result["error"] and {c["name"] for c in result["consistency"]} >= {"rig_model", "phase_residual"}
    return line, {c["name"]: c for c in result["consistency"]}


def test_clean_session_passes_every_check(clean: Path) -> None:
    result = json.loads((clean / "outputs" / "result.json").read_text())
    assert all(c["passed"] is not False for c in result["consistency"])
    assert result["noise_source"] == "sensor model"


def test_steps_in_reverse_order_refused_as_such(copy: Path) -> None:
    def reverse(m: dict) -> None:
        frames = m["frames"]
        m["frames"] = [dict(frames[g + 3 - i], k=g + i) for g in (0, 4, 8) for i in range(4)]

    edit_manifest(copy, reverse)
    line, checks = refused(copy)
    assert "direction (vertical) failed" in line and "most likely: phase steps in reverse order" in line
    assert checks["direction"]["statistic"] < 0.1 and checks["direction"]["threshold"] == 0.5
    paths = entity_paths(copy / "recording.rrd")  # the refusal's figures in the recording too
    assert {"metrics/consistency/direction/vertical/statistic", "metrics/consistency/direction/vertical/threshold",
            "events"} <= set(paths)


def test_edited_rig_model_refused_unless_given_on_purpose(copy: Path, tmp_path: Path) -> None:
    def edit(m: dict) -> None:
        m["rig_model"]["camera"]["K"][0][0] *= 1.01

    edit_manifest(copy, edit)
    line, _checks = refused(copy)
    assert "rig_model (session) failed" in line and "--rig-model" in line
    model = tmp_path / "model.json"
    model.write_text(json.dumps(json.loads((copy / MANIFEST).read_text())["rig_model"]))
    code, err = run_cli("decode", str(copy), "--rig-model", str(model))
    assert code == 0, err
    result = json.loads((copy / "outputs" / "result.json").read_text())
    tie = next(c for c in result["consistency"] if c["name"] == "rig_model")
    assert result["rig_model"] == str(model) and tie["passed"] is None and "on purpose" in tie["note"]


def test_a_frame_in_another_steps_place_fails_the_residual_naming_its_group(copy: Path) -> None:
    """Frame 2's pattern captured again (fresh camera noise: not a pixel-for-pixel copy, which
    is refused as such before any decode) where frame 6 belongs."""
    image = cv2.imread(str(frame(copy, 2)), cv2.IMREAD_UNCHANGED)
    noise = np.random.default_rng(5).integers(-2, 3, image.shape)
    again = np.clip(image.astype(np.int64) + noise, 0, np.iinfo(image.dtype).max).astype(image.dtype)
    cv2.imwrite(str(frame(copy, 6)), again)

    def repeat(m: dict) -> None:
        m["frames"][6]["sha256"] = hashlib.sha256(frame(copy, 6).read_bytes()).hexdigest()

    edit_manifest(copy, repeat)
    line, checks = refused(copy)
    assert "phase_residual (vertical) failed" in line and "frame 4 (step group 4..7) fits worst" in line
    assert checks["phase_residual"]["statistic"] > 5 * checks["phase_residual"]["threshold"]
