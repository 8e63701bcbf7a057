"""Sessions, acquisition faults, config errors and the CLI on a small simulated rig."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from session_support import PATTERNS, SCENE, small_rig_toml

from scanner.errors import (
    ConfigError,
    DeviceDisconnected,
    FrameDropped,
    FrameOutOfOrder,
    IncompleteSession,
    ScannerError,
    SessionError,
    WaitTimeout,
)
from scanner.pipeline import reprocess, scan
from scanner.pointcloud import read_ply_points
from scanner.recording_reader import read_component, read_points, read_summary
from scanner.rig import RigConfig, open_rig
from scanner.session import ERROR, MANIFEST, Session
from sim.virtual_devices import Faults
from slscan import cli


@pytest.fixture
def small_config(tmp_path: Path) -> RigConfig:
    return RigConfig.load(small_rig_toml(tmp_path, timeout_s=0.5))


@pytest.mark.parametrize("wiring", ["software", "projector", "trigger_box"])
def test_scan_writes_complete_session(tmp_path: Path, wiring: str) -> None:
    config = RigConfig.load(small_rig_toml(tmp_path, trigger=wiring))
    with open_rig(config, scene=SCENE) as rig:
        result = scan(rig, PATTERNS, tmp_path / "s")
    s = Session.open(tmp_path / "s")
    assert len(s.manifest.frames) == 12 and s.manifest.recorded("wiring") == wiring
    assert s.manifest.rig_model.camera.width == 320
    stack = s.load_stack()
    assert stack.dtype == np.uint16 and stack.shape == (12, 256, 320) and stack.max() < 4096
    assert result.cloud_path.exists() and len(result.cloud) > 0.8 * 320 * 256
    assert (tmp_path / "s" / "ground_truth.npz").exists()
    rec = read_summary(s.recording_path)  # closed, with its footer, holding the whole scan
    assert rec.recording_id == s.id
    assert rec.entities["world/camera/image"].rows == 12 and "pattern" in rec.entities["world/camera/image"].timelines
    assert {"world/camera", "world/projector", "world/scan/cloud", "maps/vertical/phase", "maps/masks",
            "metrics/decode_s"} <= set(rec.entity_paths)
    assert len(read_points(s.recording_path)[0]) == len(result.cloud)


def test_decode_regenerates_outputs_from_raw_frames(tmp_path: Path, small_config: RigConfig) -> None:
    with open_rig(small_config, scene=SCENE) as rig:
        first = scan(rig, PATTERNS, tmp_path / "s")
    (tmp_path / "s" / "outputs" / "cloud.ply").unlink()
    again = reprocess(Session.open(tmp_path / "s"))
    assert again.cloud_path.exists()
    # the recording, started beside the decode, is closed and holds the frames and the results
    rec = read_summary(tmp_path / "s" / "recording.rrd")
    assert rec.entities["world/camera/image"].rows == 12
    assert {"world/camera", "world/scan/cloud", "maps/vertical/phase", "metrics/decode_s"} <= set(rec.entity_paths)
    assert len(read_points(tmp_path / "s" / "recording.rrd")[0]) == len(again.cloud)
    # the scan decoded its frames from memory, the decode reads them back from the PNGs: the same cloud
    assert np.array_equal(np.isnan(first.cloud.points), np.isnan(again.cloud.points))
    assert np.nanmax(np.abs(first.cloud.points - again.cloud.points)) == 0.0

    with zipfile.ZipFile(tmp_path / "s" / "outputs" / "maps.npz") as z:  # float maps stored, masks deflated
        kinds = {i.filename: i.compress_type for i in z.infolist()}
        dated = {i.date_time for i in z.infolist()}
    assert dated == {(1980, 1, 1, 0, 0, 0)}  # no clock time inside: the same maps give the same file
    assert kinds["vertical/coordinate.npy"] == kinds["texture.npy"] == zipfile.ZIP_STORED
    assert kinds["valid.npy"] == kinds["vertical/mask/shadow.npy"] == zipfile.ZIP_DEFLATED
    with np.load(tmp_path / "s" / "outputs" / "maps.npz") as m:
        assert np.array_equal(m["vertical/coordinate"], again.decoded.maps["vertical"].coordinate, equal_nan=True)
        assert np.array_equal(m["valid"], again.decoded.valid)
        maps = {k: m[k] for k in m.files}
    # an older session's maps.npz (every member deflated) still reads the same
    np.savez_compressed(tmp_path / "old.npz", **maps)
    with np.load(tmp_path / "old.npz") as old:
        assert set(old.files) == set(maps) and all(np.array_equal(old[k], maps[k], equal_nan=True) for k in maps)


def test_outputs_are_written_behind_a_later_stage(tmp_path: Path, small_config: RigConfig,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """With a later stage (`then`, the demo's inspection), the cloud reaches it at once and
    the outputs are written meanwhile: all on disk when `scan` returns, the PLY holding the
    cloud; a write that fails is raised after the stage, which kept its cloud, and the frames
    and manifest stay."""
    seen: dict[str, int] = {}

    def then(result: object, recording: object) -> None:
        seen["points"] = len(result.cloud)  # type: ignore[attr-defined]

    with open_rig(small_config, scene=SCENE) as rig:
        result = scan(rig, PATTERNS, tmp_path / "s", then=then)
    out = tmp_path / "s" / "outputs"
    summary = json.loads((out / "result.json").read_text())
    assert summary["points"] == len(result.cloud) == seen["points"] > 0
    assert summary["timings_s"]["write"] > 0 and summary["cpu_s"]["write"] >= 0
    assert len(read_ply_points(out / "cloud.ply")) == len(result.cloud)
    with np.load(out / "maps.npz") as m:
        assert np.array_equal(m["valid"], result.decoded.valid)

    def full_disk(*args: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("scanner.pipeline.write_ply", full_disk)
    seen.clear()
    with open_rig(small_config, scene=SCENE) as rig, pytest.raises(SessionError, match="cannot write the outputs"):
        scan(rig, PATTERNS, tmp_path / "t", then=then)
    assert seen["points"] > 0
    assert len(Session.open(tmp_path / "t").load_stack()) == 12


def test_decode_error_is_logged_into_a_closed_recording(tmp_path: Path, small_config: RigConfig) -> None:
    """A session whose processing fails (here a frame damaged after the capture) leaves its
    recording closed, with the raw frames and the error, and raises the processing error."""
    with open_rig(small_config, scene=SCENE) as rig:
        scan(rig, PATTERNS, tmp_path / "s")
    session = Session.open(tmp_path / "s")
    cv2.imwrite(str(session.frame_path(3)), np.zeros((256, 320), np.uint16))
    with pytest.raises(ScannerError, match="frame"):
        reprocess(session)
    rec = read_summary(session.recording_path)
    assert rec.entities["world/camera/image"].rows == 12
    events = [str(t) for _, text in read_component(session.recording_path, "events", "TextLog:text", None)
              for t in text]
    assert any("session aborted" in e and "frame" in e for e in events), events


FAULTS = [
    (Faults(drop_frame=4), "projector", FrameDropped, 4),
    (Faults(stale_frame=5), "projector", FrameOutOfOrder, 5),
    (Faults(delay_frame=3, delay_s=2.0), "projector", WaitTimeout, 3),
    (Faults(disconnect_after=6), "projector", DeviceDisconnected, 6),
    (Faults(delay_frame=2, delay_s=2.0), "software", WaitTimeout, 2),
    (Faults(drop_frame=7), "trigger_box", FrameDropped, 7),
]


@pytest.mark.parametrize("faults, wiring, error, stored", FAULTS,
                         ids=[f"{e.__name__}-{w}" for _, w, e, _ in FAULTS])
def test_fault_gives_named_error_and_keeps_frames(tmp_path: Path, faults: Faults, wiring: str, error: type,
                                                  stored: int) -> None:
    config = RigConfig.load(small_rig_toml(tmp_path, trigger=wiring, timeout_s=0.5))
    out = tmp_path / "s"
    with open_rig(config, scene=SCENE, faults=faults) as rig, pytest.raises(error) as exc:
        scan(rig, PATTERNS, out)
    assert "sim-camera" in str(exc.value)
    frames = sorted((out / "frames").glob("frame_*.png"))
    assert [f.name for f in frames] == [f"frame_{k:03d}.png" for k in range(stored)]
    assert all(cv2.imread(str(f), cv2.IMREAD_UNCHANGED).shape == (256, 320) for f in frames)
    assert not (out / MANIFEST).exists()
    err = json.loads((out / ERROR).read_text())
    assert err["error"] == error.__name__ and err["frames_stored"] == stored
    with pytest.raises(IncompleteSession, match=f"{stored} raw frame"):
        Session.open(out)
    assert (out / "recording.rrd").stat().st_size > 0


def test_rig_reconnects_after_fault(tmp_path: Path, small_config: RigConfig) -> None:
    """A fault in one scan does not poison the next (faults fire once by default)."""
    with open_rig(small_config, scene=SCENE, faults=Faults(drop_frame=2)) as rig:
        with pytest.raises(FrameDropped):
            scan(rig, PATTERNS, tmp_path / "a")
        result = scan(rig, PATTERNS, tmp_path / "b")
    assert len(result.cloud) > 0


def test_damaged_session_is_refused_with_file_named(tmp_path: Path, small_config: RigConfig) -> None:
    with open_rig(small_config, scene=SCENE) as rig:
        scan(rig, PATTERNS, tmp_path / "s")
    frame = tmp_path / "s" / "frames" / "frame_005.png"
    cv2.imwrite(str(frame), np.zeros((100, 100), np.uint16))
    with pytest.raises(SessionError, match="frame_005.png: frame 5 has been altered or replaced"):
        Session.open(tmp_path / "s").load_stack()  # its SHA-256 no longer matches the manifest's
    frame.unlink()
    with pytest.raises(SessionError, match="frame_005.png: frame 5 missing"):
        Session.open(tmp_path / "s").load_stack()


def test_existing_output_folder_is_not_overwritten(tmp_path: Path, small_config: RigConfig) -> None:
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "keep.txt").write_text("earlier work")
    with open_rig(small_config, scene=SCENE) as rig, pytest.raises(SessionError, match="not empty"):
        scan(rig, PATTERNS, tmp_path / "s")
    assert (tmp_path / "s" / "keep.txt").read_text() == "earlier work"


@pytest.mark.parametrize("edit, key", [
    (("trigger = \"projector\"", "trigger = \"laser\""), "rig.trigger"),
    (("hfov_deg = 22.6", "hfov_deg = \"wide\""), "camera.hfov_deg"),
    (("width = 912\n", ""), "projector.width"),
    (("gamma = 2.2", "gamma = 22.0"), "projector.gamma"),
    (("timeout_s = 0.5", "timeout_s = 0"), "rig.timeout_s"),
    (("position_mm = [145.6, 0.0, 0.0]", "position_mm = [145.6, 0.0]"), "projector.position_mm"),
])
def test_broken_rig_toml_names_file_and_key(tmp_path: Path, edit: tuple[str, str], key: str) -> None:
    path = small_rig_toml(tmp_path, timeout_s=0.5)
    text = path.read_text()
    assert edit[0] in text
    path.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(ConfigError) as exc:
        RigConfig.load(path)
    assert exc.value.key == key and str(path) in str(exc.value)


def test_unparsable_toml_names_file(tmp_path: Path) -> None:
    path = tmp_path / "rig.toml"
    path.write_text("[rig\nname = ")
    with pytest.raises(ConfigError, match="rig.toml: not valid TOML"):
        RigConfig.load(path)


def test_cli_scan_decode_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    rig = small_rig_toml(tmp_path)
    assert cli.main(["scan", "--rig", str(rig), "--scene", str(SCENE), "--out", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    assert "cloud.ply" in out and "accuracy" in out and "fringe-order errors 0 (smooth)" in out
    acc = json.loads((tmp_path / "s" / "outputs" / "accuracy.json").read_text())
    # the noise-bound ratio is asserted at full resolution in test_scan_accuracy; this 320 x 256
    # camera sees ~5 px per fringe, where camera blur over curved phase adds a real bias
    assert acc["order_errors"] == 0 and acc["coverage"] > 0.97 and 0 < acc["rms_mm"] < 0.1
    assert cli.main(["decode", str(tmp_path / "s")]) == 0
    # a device fault: named error, exit code 3 (slscan.exit_codes), incomplete session reported by decode
    assert cli.main(["scan", "--rig", str(rig), "--scene", str(SCENE), "--out", str(tmp_path / "f"),
                     "--fault", "drop_frame=3"]) == 3
    assert "FrameDropped" not in capsys.readouterr().err  # the message, not a traceback
    assert cli.main(["decode", str(tmp_path / "f")]) == 2
    err = capsys.readouterr().err
    assert "incomplete session" in err and "3 raw frame(s)" in err and "frame 3 was dropped" in err
    bad = tmp_path / "bad.toml"
    bad.write_text("[rig]\nname = 'x'\n")
    assert cli.main(["scan", "--rig", str(bad), "--out", str(tmp_path / "x")]) == 2
    assert "bad.toml, key 'rig.driver': required key is missing" in capsys.readouterr().err


def test_cli_bench_json(capsys: pytest.CaptureFixture) -> None:
    assert cli.main(["bench", "decode", "--width", "320", "--height", "256", "--repeats", "1", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert {"width", "height", "frames", "decode_s", "reconstruct_s", "total_s", "peak_mb"} <= set(r)
    assert r["width"] == 320 and r["frames"] == 12 and r["valid_fraction"] > 0.95
    assert r["total_s"] == pytest.approx(r["decode_s"] + r["reconstruct_s"], abs=2e-4)
