"""Issue 15, items 1-5 and 8: sessions that cannot lie. Tampered frames and manifests are
refused naming the frame or key; frame paths stay in the session folder; a decode without
points fails; JSON holds no NaN; a full disk or a dead recording writer gives one line and
keeps every captured frame."""

from __future__ import annotations

import errno
import json
import shutil
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_support import run_cli
from recording_support import release_abandoned_recordings
from session_support import PATTERNS, SCENE, edit_manifest, frame, one_error_line, small_rig_toml

from scanner import session as session_module
from scanner.errors import ScannerError, SessionError
from scanner.pipeline import reprocess, scan
from scanner.rig import RigConfig, open_rig
from scanner.session import MANIFEST, Session, sha256, write_json
from scanner.session_recording import RecordingError, SessionRecording


@pytest.fixture
def copy(clean_session: Path, tmp_path: Path) -> Path:
    out = tmp_path / "s"
    shutil.copytree(clean_session, out)
    return out


def drop_checksums(root: Path) -> None:
    """The session as slscan wrote it before frames carried checksums."""
    edit_manifest(root, lambda m: [f.pop("sha256") for f in m["frames"]] and m)


# ------------------------------------------------------------------ item 2: frame integrity

def test_frames_carry_their_sha256(clean_session: Path) -> None:
    log = [json.loads(line) for line in (clean_session / "frames.jsonl").read_text().splitlines()]
    manifest = json.loads((clean_session / MANIFEST).read_text())
    for k, (entry, logged) in enumerate(zip(manifest["frames"], log)):
        assert entry["sha256"] == logged["sha256"] == sha256(frame(clean_session, k).read_bytes())
    assert Session.open(clean_session).integrity == "sha256"


def swap(root: Path, i: int, j: int) -> None:
    a, b = frame(root, i).read_bytes(), frame(root, j).read_bytes()
    frame(root, i).write_bytes(b)
    frame(root, j).write_bytes(a)


def repeat(root: Path, i: int, j: int) -> None:
    frame(root, j).write_bytes(frame(root, i).read_bytes())


def black(root: Path, i: int, j: int) -> None:
    cv2.imwrite(str(frame(root, i)), np.zeros((256, 320), np.uint16))


def foreign(root: Path, i: int, j: int) -> None:
    """Frame i from another scene: a shifted copy of itself (what another part would show)."""
    img = cv2.imread(str(frame(root, i)), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(frame(root, i)), np.roll(img, 9, axis=1))


TAMPERING = [(swap, 3, 7), (repeat, 5, 6), (swap, 0, 1), (black, 4, None), (foreign, 2, None)]


@pytest.mark.parametrize("tamper, i, j", TAMPERING, ids=["swap3-7", "repeat5-6", "swap0-1", "black4", "foreign2"])
def test_tampered_frames_are_refused_by_checksum(copy: Path, tamper, i: int, j: int | None) -> None:
    tamper(copy, i, j)
    code, err = run_cli("decode", str(copy))
    line = one_error_line(err)
    k = j if tamper is repeat else i  # the first frame whose bytes changed
    assert code == 2 and f"frame_{k:03d}.png: frame {k} has been altered or replaced" in line
    assert "error" not in json.loads((copy / "outputs" / "result.json").read_text())  # old outputs kept


@pytest.mark.parametrize("tamper, i, j", TAMPERING, ids=["swap3-7", "repeat5-6", "swap0-1", "black4", "foreign2"])
def test_tampered_frames_without_checksums_fail_the_signature(copy: Path, tamper, i: int, j: int | None) -> None:
    """Sessions written before checksums: the frames must still fit the patterns."""
    drop_checksums(copy)
    tamper(copy, i, j)
    code, err = run_cli("decode", str(copy))
    line = one_error_line(err)
    if tamper is repeat:  # a copy is named as one, with the frame it copies
        assert code == 2 and f"frame {j} (frame_{j:03d}.png) repeats frame {i} (frame_{i:03d}.png)" in line
        return
    assert code == 2 and "frame " in line and ("does not fit" in line or "do not follow" in line or "blank" in line)
    named = int(line.split("frame ")[1].split()[0])
    assert named // 4 in {i // 4, (j if j is not None else i) // 4}  # the frame, or one of its 4-step group


def test_old_session_decodes_and_says_it_was_not_checked(copy: Path) -> None:
    drop_checksums(copy)
    result = reprocess(Session.open(copy))
    assert len(result.cloud) > 0.5 * 320 * 256
    assert json.loads((copy / "outputs" / "result.json").read_text())["integrity"].startswith("not checked")
    code, err = run_cli("decode", str(copy))
    assert code == 0 and "frame integrity not checked" in err and "cannot be detected" in err


# ------------------------------------------------------------------ item 3: frame paths confined to the session

@pytest.mark.parametrize("path", ["ABS", "../../elsewhere/frames/frame_002.png", "../../../../../etc/passwd",
                                  "frames/../../s2/frames/frame_002.png"])
def test_frame_paths_outside_the_session_are_refused(copy: Path, path: str) -> None:
    target = str(frame(copy, 2).resolve()) if path == "ABS" else path
    edit_manifest(copy, lambda m: m["frames"][2].__setitem__("file", target))
    code, err = run_cli("decode", str(copy))
    assert code == 2 and "frames[2].file" in one_error_line(err) and "leaves the session folder" in err


def test_frame_symlinked_out_of_the_session_is_refused(copy: Path, tmp_path: Path) -> None:
    outside = tmp_path / "outside.png"
    shutil.copy(frame(copy, 2), outside)
    frame(copy, 2).unlink()
    frame(copy, 2).symlink_to(outside)
    code, err = run_cli("decode", str(copy))
    assert code == 2 and "outside the session folder" in one_error_line(err)


# ------------------------------------------------------------------ item 4: no points is a failure, JSON never NaN

@pytest.mark.parametrize("edit, words", [
    (lambda m: m["rig_model"]["camera"]["K"][0].__setitem__(0, float("nan")), "finite"),
    (lambda m: m["rig_model"]["camera"].__setitem__("K", [[0, 0, 0], [0, 0, 0], [0, 0, 1]]), "focal lengths"),
    (lambda m: m["rig_model"].__setitem__("cam_from_proj", [[0.0] * 4] * 4), "rigid"),
    (lambda m: [row.__setitem__(3, 0.0) for row in m["rig_model"]["cam_from_proj"][:3]], "baseline"),
    (lambda m: [f.__setitem__("bit_depth", 8) for f in m["frames"]], "8-bit"),
])
def test_inputs_that_yield_no_points_are_refused(copy: Path, edit, words: str) -> None:
    edit_manifest(copy, edit)
    code, err = run_cli("decode", str(copy))
    assert code == 2 and words in one_error_line(err)


def test_all_white_frames_fail_instead_of_exit_0(copy: Path) -> None:
    drop_checksums(copy)
    for k in range(12):
        cv2.imwrite(str(frame(copy, k)), np.full((256, 320), 4095, np.uint16))
    code, err = run_cli("decode", str(copy))
    assert code == 2 and "blank" in one_error_line(err)


def test_a_decode_without_points_fails_naming_why(copy: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Frames that fit the patterns but a geometry that places nothing: the decode fails."""
    import scanner.pipeline as pipeline

    monkeypatch.setattr(pipeline, "triangulate", lambda decoded, tri: type(
        "Empty", (), {"__len__": lambda self: 0})())
    code, err = run_cli("decode", str(copy))
    line = one_error_line(err)
    assert code == 2 and "yielded no points" in line and "none triangulated" in line
    assert json.loads((copy / "outputs" / "result.json").read_text())["points"] == 0


def test_json_never_holds_nan(tmp_path: Path) -> None:
    write_json(tmp_path / "a.json", {"rms_mm": float("nan"), "x": [np.float32("inf"), 1.5], "n": np.int64(3)})
    text = (tmp_path / "a.json").read_text()
    assert json.loads(text) == {"rms_mm": None, "x": [None, 1.5], "n": 3}
    assert "NaN" not in text and "Infinity" not in text


def test_accuracy_without_pixels_is_null_with_a_note() -> None:
    from sim.evaluate import Accuracy

    d = Accuracy(0, float("nan"), float("nan"), float("nan"), float("nan"), 0.0, 0, 0).as_dict()
    assert d["rms_mm"] is None and d["pixels"] == 0 and "null" in d["note"]
    json.dumps(d, allow_nan=False)


# ------------------------------------------------------------------ item 5: malformed manifests, one line each

MALFORMED = {
    "a JSON list": (lambda m: [m], "not an object"),
    "no frames": (lambda m: m.pop("frames") and m, "key 'frames'"),
    "no rig_model": (lambda m: m.pop("rig_model") and m, "key 'rig_model'"),
    "no patterns": (lambda m: m.pop("patterns") and m, "key 'patterns'"),
    "no session_id": (lambda m: m.pop("session_id") and m, "key 'session_id'"),
    "no frames[3].file": (lambda m: m["frames"][3].pop("file") and m, "key 'frames[3].file'"),
    "bit_depth 0": (lambda m: [f.__setitem__("bit_depth", 0) for f in m["frames"]] and m, "frames[0].bit_depth"),
    "bit_depth twelve": (lambda m: [f.__setitem__("bit_depth", "twelve") for f in m["frames"]] and m,
                         "frames[0].bit_depth"),
    "bit_depth 16": (lambda m: [f.__setitem__("bit_depth", 16) for f in m["frames"]] and m, "camera.bit_depth is 12"),
    "projector_gamma 0": (lambda m: m["rig_model"].__setitem__("projector_gamma", 0) or m, "projector_gamma"),
    "stage pose 3x3": (lambda m: m.update(stage={"position": {"turntable": 0.0}, "stage_model": {},
                                                 "world_from_stage": np.eye(3).tolist()}) or m,
                       "key 'stage.world_from_stage[0]'"),
    "import hard_linked -1": (lambda m: m.update({"import": {"hard_linked": -1}}) or m, "key 'import."),
    "exposure coverage 1.5": (lambda m: m.update(exposure={"exposures_s": [0.01], "mode": "auto", "reason": "r",
                                                           "predicted_coverage": 1.5}) or m,
                              "key 'exposure.predicted_coverage'"),
    "exposure roi_box of 3": (lambda m: m.update(exposure={"exposures_s": [0.01], "mode": "hdr", "reason": "r",
                                                           "roi_box": [0, 0, 10]}) or m, "key 'exposure.roi_box'"),
    "exposure unknown key": (lambda m: m.update(exposure={"exposures_s": [0.01], "mode": "given", "reason": "r",
                                                          "coverage": 0.9}) or m, "exposure.coverage"),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_manifest_gives_one_line(copy: Path, case: str) -> None:
    edit, words = MALFORMED[case]
    edit_manifest(copy, edit)
    code, err = run_cli("decode", str(copy))
    line = one_error_line(err)
    assert code == 2 and words in line and "manifest.json" in line


def test_an_import_record_from_before_sources_still_opens(copy: Path) -> None:
    """`import` as the first `slscan import` wrote it (no `sources`), read as typed."""
    record = {"source_folder": "/data/capture_0", "frames_glob": None, "patterns_file": "opencv_graycode.toml",
              "projector_size": [1024, 768], "bit_depth": 8, "hard_linked": 40, "copied": 2,
              "calibration": {"file": "/data/calibration_result.xml", "format": "procam", "projector_scale": 2.0},
              "conventions": {"pixel_centre": {"value": 0.0, "source": "assumed", "evidence": "not observable"}}}
    edit_manifest(copy, lambda m: m.update({"import": record}))
    imported = Session.open(copy).manifest.imported
    assert imported is not None and imported.sources is None and imported.hard_linked == 40
    assert imported.calibration is not None and imported.calibration.projector_scale == 2.0
    assert imported.conventions["pixel_centre"].source == "assumed"


def test_three_channel_frame_message_says_channels(copy: Path) -> None:
    drop_checksums(copy)
    img = cv2.imread(str(frame(copy, 1)), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(frame(copy, 1)), np.dstack([img] * 3))
    with pytest.raises(SessionError, match="frame 1 is uint16 320x256, 3 channels, expected uint16 320x256 "
                                           "single-channel"):
        Session.open(copy).load_stack()


# ------------------------------------------------- items 1 and 8: full disk, read-only folder, dead writer

def scan_within_bound(tmp_path: Path, out: Path, bound_s: float = 300.0) -> list[BaseException]:
    """Scan the small rig into `out` in a thread; fail if it has not ended within `bound_s`
    (a hang); return what it raised."""
    done = threading.Event()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            with open_rig(RigConfig.load(small_rig_toml(tmp_path)), scene=SCENE) as rig:
                scan(rig, PATTERNS, out)
        except BaseException as exc:  # returned to the test
            errors.append(exc)
        done.set()

    threading.Thread(target=run, daemon=True).start()
    assert done.wait(bound_s), "the scan hung on a full disk"
    return errors


def test_disk_full_during_capture_keeps_every_frame(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A write wrapper that raises ENOSPC once 7 frames are stored: one SessionError, the 7
    frames intact (their checksums in frames.jsonl), the recording closed, no hang."""
    real = session_module.write_atomic
    stored: list[Path] = []

    def filling(path: Path, data: bytes) -> None:
        if path.parent.name == "frames" and len(stored) == 7:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, data)
        if path.parent.name == "frames":
            stored.append(path)

    monkeypatch.setattr(session_module, "write_atomic", filling)
    errors = scan_within_bound(tmp_path, tmp_path / "s")
    assert len(errors) == 1 and isinstance(errors[0], SessionError)
    message = str(errors[0])
    assert "cannot store frame 7" in message and "No space left" in message and "\n" not in message
    log = [json.loads(line) for line in (tmp_path / "s" / "frames.jsonl").read_text().splitlines()]
    assert [e["k"] for e in log] == list(range(7))
    for e in log:
        assert sha256((tmp_path / "s" / e["file"]).read_bytes()) == e["sha256"]
    assert not list((tmp_path / "s" / "frames").glob(".*part"))
    assert json.loads((tmp_path / "s" / "error.json").read_text())["frames_stored"] == 7


def test_recording_close_is_bounded_when_the_writer_hangs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import scanner.session_recording as sr

    monkeypatch.setattr(sr, "CLOSE_TIMEOUT_S", 0.5)
    rec = SessionRecording(tmp_path / "recording.rrd", "hang")
    release = threading.Event()
    monkeypatch.setattr(rec.stream, "flush", lambda **kw: release.wait(120))
    finished = threading.Event()
    raised: list[BaseException] = []

    def close() -> None:
        try:
            rec.close()
        except RecordingError as exc:
            raised.append(exc)
        finished.set()

    threading.Thread(target=close, daemon=True).start()
    assert finished.wait(30), "close() waited on the writer without a timeout"
    release.set()
    assert raised and "did not finish within 1 s" in str(raised[0])
    # the writer released, the close's own worker goes on to disconnect the stream: let it end before
    # the abandoned stream is disconnected again after the test (two at once can deadlock Rerun)
    for worker in [t for t in threading.enumerate() if t.name == "close recording.rrd"]:
        worker.join(30)
        assert not worker.is_alive(), "the released writer's close did not end"


def test_recording_writer_that_died_gives_one_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rec = SessionRecording(tmp_path / "recording.rrd", "dead")

    def dead(**kw: object) -> None:
        raise RuntimeError("File-writer thread shut down prematurely")

    monkeypatch.setattr(rec.stream, "flush", dead)
    with pytest.raises(RecordingError, match="could not be finished .*File-writer thread"):
        rec.close()


@pytest.mark.skipif(shutil.os.geteuid() == 0, reason="root writes into read-only folders: needs an unprivileged user")
def test_read_only_output_folder_gives_one_line(tmp_path: Path) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    code, err = run_cli("scan", "--out", str(ro / "s"))
    assert code == 2 and "cannot create the session folder" in err and "Traceback" not in err


def test_unwritable_output_folder_gives_one_line(tmp_path: Path) -> None:
    """Independent of the user: a file where a folder must be created."""
    (tmp_path / "file").write_text("")
    code, err = run_cli("scan", "--out", str(tmp_path / "file" / "s"))
    assert code == 2 and "cannot create the session folder" in err and "Traceback" not in err


def test_cli_turns_scanner_errors_and_os_errors_into_one_line(tmp_path: Path) -> None:
    for argv in (["decode", str(tmp_path / "missing")], ["scan", "--rig", str(tmp_path), "--out", str(tmp_path / "o")]):
        code, err = run_cli(*argv)
        assert code == 2 and len([ln for ln in err.splitlines() if ln.strip()]) == 1, err
    assert issubclass(SessionError, ScannerError)


@pytest.fixture
def small_disk(tmp_path: Path):
    """A 3 MiB tmpfs (root only): a real full disk for the Rerun writer too."""
    import subprocess

    mount = tmp_path / "disk"
    mount.mkdir()
    if shutil.os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mount)],
                                                  capture_output=True).returncode != 0:
        pytest.skip("mounting a small tmpfs needs root (a real full disk); the ENOSPC wrapper test covers the rest")
    try:
        yield mount
    finally:  # the recording the full disk stopped is let go while its disk is still there, with room again
        subprocess.run(["mount", "-o", "remount,size=64m", str(mount)], capture_output=True)
        try:
            release_abandoned_recordings()
        finally:
            subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def test_real_full_disk_gives_one_error_and_keeps_every_frame(small_disk: Path, tmp_path: Path) -> None:
    """12 frames of ~107 kB, the ground truth and the recording do not fit in 3 MiB: the scan
    stops with one SessionError naming the frame, within its bound, every stored frame intact."""
    errors = scan_within_bound(tmp_path, small_disk / "s")
    assert len(errors) == 1 and isinstance(errors[0], ScannerError), errors
    assert "No space left" in str(errors[0]) and "\n" not in str(errors[0])
    log = [json.loads(line) for line in (small_disk / "s" / "frames.jsonl").read_text().splitlines()]
    assert len(log) >= 1
    for e in log:
        assert sha256((small_disk / "s" / e["file"]).read_bytes()) == e["sha256"]
    assert not list((small_disk / "s" / "frames").glob(".*part"))


def test_full_disk_while_writing_the_outputs_keeps_the_frames_and_decode_finishes(clean_session: Path,
                                                                                  tmp_path: Path) -> None:
    """A real disk (tmpfs) that holds the frames and manifest but not the outputs: decoding
    stops with one SessionError naming the session and `slscan decode`, leaves no partial file
    and every frame intact; once there is space, decoding the same session writes its cloud."""
    import subprocess

    mount = tmp_path / "disk"
    mount.mkdir()
    kept = [p for p in clean_session.rglob("*") if p.is_file() and p.parent.name != "outputs" and p.suffix != ".rrd"]
    size_kib = sum(p.stat().st_size for p in kept) // 1024 + 16 * len(kept) + 256  # the outputs need ~3.8 MB
    if shutil.os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kib}k", "tmpfs",
                                                   str(mount)], capture_output=True).returncode != 0:
        pytest.skip("mounting a small tmpfs needs root (a real full disk); the ENOSPC wrapper tests cover the rest")
    try:
        session_dir = mount / "s"
        for p in kept:
            (session_dir / p.relative_to(clean_session)).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(p, session_dir / p.relative_to(clean_session))
        with pytest.raises(SessionError) as raised:
            reprocess(Session.open(session_dir), level="none")
        message = str(raised.value)
        assert str(session_dir) in message and "slscan decode" in message and "\n" not in message, message
        assert not [p for p in session_dir.rglob("*") if ".part" in p.name], "a partial output was left behind"
        for e in (json.loads(line) for line in (session_dir / "frames.jsonl").read_text().splitlines()):
            assert sha256((session_dir / e["file"]).read_bytes()) == e["sha256"], e["file"]
        assert subprocess.run(["mount", "-o", "remount,size=64m", str(mount)], capture_output=True).returncode == 0
        result = reprocess(Session.open(session_dir), level="none")
        assert result.cloud is not None and len(result.cloud) > 1000
        assert (session_dir / "outputs" / "cloud.ply").stat().st_size > 0
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)
