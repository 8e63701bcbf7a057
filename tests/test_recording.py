"""Tests of the Rerun session recording (scanner/session_recording.py).

A whole session (rig, raw frames, decoded maps, cloud, metrics) is logged from a small
synthetic scan into a temporary `.rrd`, closed, and read back with `rerun.chunk.RrdReader`.
No viewer is ever started: the review command is only built, or run with a stand-in binary.
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from scanner import recording_reader as reader
from scanner import session_recording as R
from scanner.decode import DecodeResult, decode
from scanner.devices import Frame
from scanner.geometry import RigModel, look_at
from scanner.patterns import PatternSet
from scanner.pointcloud import OrganisedCloud
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import RigConfig
from sim.analytic_stack import synthetic_stack
from slscan import viewer

PATTERNS = PatternSet("heterodyne", 4, (64.0, 56.0, 49.0), ("vertical", "horizontal"))


@dataclass
class Scan:
    rig: RigModel
    patterns: PatternSet
    stack: np.ndarray
    decoded: DecodeResult
    cloud: OrganisedCloud


@pytest.fixture(scope="module")
def scan() -> Scan:
    rig = RigConfig.load().nominal_model().with_camera_size(160, 128)
    stack = synthetic_stack(rig, PATTERNS)
    decoded = decode(stack, PATTERNS, 12, rig.projector.size)
    return Scan(rig, PATTERNS, stack, decoded, triangulate(decoded, Triangulator(rig)))


def png_image(blob: np.ndarray) -> np.ndarray:
    """A logged frame's PNG bytes decoded by OpenCV, at their bit depth."""
    image = cv2.imdecode(np.asarray(blob, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None, "the logged frame is not a readable PNG"
    return image


def log_session(path: Path, s: Scan, session_id: str = "s-001", **kw: object) -> None:
    with R.SessionRecording(path, session_id, **kw) as rec:
        rec.log_rig(s.rig)
        for k, (img, spec) in enumerate(zip(s.stack, s.patterns.frames())):
            frame = Frame(img, k, k, 0.05 * k, 0.01, 12) if k % 2 else img  # both kinds of input
            rec.log_frame(k, frame, spec)
        rec.log_decode(s.decoded)
        rec.log_cloud(s.cloud, normals_step=20)
        rec.log_metrics({"decode_s": 0.25, "reconstruct_s": 0.125, "valid_fraction": float(s.decoded.valid.mean())})


@pytest.fixture(scope="module")
def session_file(scan: Scan, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / R.RECORDING_NAME
    log_session(path, scan)
    return path


@pytest.fixture(scope="module")
def summary(session_file: Path) -> reader.RecordingSummary:
    return reader.read_summary(session_file)


def test_closed_file_is_complete_with_its_blueprint(session_file: Path, summary: reader.RecordingSummary) -> None:
    assert session_file.is_file()
    assert not session_file.with_name(session_file.name + ".part").exists()
    # read_summary goes through RrdReader.store(), which refuses a file without its footer
    assert summary.application_id == R.APPLICATION_ID
    assert summary.recording_id == "s-001"
    assert summary.blueprints == 1
    assert {R.TIMELINE_PATTERN, R.TIMELINE_SCAN} <= summary.timelines


def test_expected_entity_paths(scan: Scan, summary: reader.RecordingSummary) -> None:
    expected = {R.WORLD, R.CAMERA, R.CAMERA_IMAGE, R.PROJECTOR, R.CLOUD, R.NORMALS, R.FRAME_SPEC, R.RIG_INFO,
                R.MAPS, R.MAP_TEXTURE, R.MAP_MASKS, "metrics/decode_s", "metrics/reconstruct_s",
                "metrics/valid_fraction"}
    for o in scan.patterns.orientations:
        expected |= {f"maps/{o}/coordinate", f"maps/{o}/phase", f"maps/{o}/background", f"maps/{o}/masks"}
        expected |= {f"maps/{o}/{kind}/{i}" for kind in ("wrapped", "modulation") for i in range(3)}
    assert expected <= set(summary.entity_paths), expected - set(summary.entity_paths)
    for static in (R.WORLD, R.CAMERA, R.PROJECTOR, R.RIG_INFO, R.MAPS):
        assert summary.entities[static].static_rows >= 1 and summary.entities[static].rows == 0
    assert "Pinhole:image_from_camera" in summary.entities[R.CAMERA].components
    assert "Transform3D:mat3x3" in summary.entities[R.PROJECTOR].components
    # the maps live outside the camera subtree
    assert not any(p.startswith(R.CAMERA + "/") and p != R.CAMERA_IMAGE for p in summary.entity_paths)


def test_one_image_per_frame_on_the_pattern_timeline(scan: Scan, session_file: Path,
                                                     summary: reader.RecordingSummary) -> None:
    n, _h, _w = scan.stack.shape
    image = summary.entities[R.CAMERA_IMAGE]
    assert image.rows == n
    assert {R.TIMELINE_PATTERN, R.TIMELINE_SCAN} <= image.timelines
    rows = reader.read_component(session_file, R.CAMERA_IMAGE, "EncodedImage:blob", R.TIMELINE_PATTERN)
    assert [t for t, _ in rows] == list(range(n))
    for k in (0, n - 1):  # lossless PNG at their bit depth: decoded, unchanged
        np.testing.assert_array_equal(png_image(rows[k][1]), scan.stack[k])
    texts = reader.read_component(session_file, R.FRAME_SPEC, "TextLog:text", R.TIMELINE_PATTERN)
    assert [str(a[0]) for _, a in texts] == [f"{k}: {R.spec_name(s)}" for k, s in enumerate(scan.patterns.frames())]


def test_cloud_points_and_colours(scan: Scan, session_file: Path, summary: reader.RecordingSummary) -> None:
    pts, grey, _ = scan.cloud.flat()
    assert len(pts) > 0
    assert summary.entities[R.CLOUD].rows == 1
    logged = reader.read_points(session_file)
    assert list(logged) == [0]
    assert logged[0].shape == (len(scan.cloud), 3)
    np.testing.assert_array_equal(logged[0], pts)  # the rig's world frame is the camera frame
    (_, colors), = reader.read_component(session_file, R.CLOUD, "Points3D:colors")
    np.testing.assert_array_equal(colors, grey.astype(np.uint32) * 0x01010100 + 0xFF)


def test_metrics_are_scalars_on_the_scan_timeline(session_file: Path, summary: reader.RecordingSummary) -> None:
    for name, value in (("decode_s", 0.25), ("reconstruct_s", 0.125)):
        e = summary.entities[R.metric_path(name)]
        assert e.rows == 1 and R.TIMELINE_SCAN in e.timelines and "Scalars:scalars" in e.components
        (t, v), = reader.read_component(session_file, R.metric_path(name), "Scalars:scalars")
        assert t == 0 and v.tolist() == [value]


def test_pinholes_and_poses(scan: Scan, session_file: Path) -> None:
    (_, k), = reader.read_component(session_file, R.CAMERA, "Pinhole:image_from_camera", None)
    K = k.reshape(3, 3).T  # Rerun stores 3x3 matrices column-major
    expected = scan.rig.camera.K.copy()
    expected[:2, 2] += 0.5  # OpenCV pixel centres at integers, Rerun's at +0.5
    np.testing.assert_allclose(K, expected, rtol=1e-6)
    (_, res), = reader.read_component(session_file, R.CAMERA, "Pinhole:resolution", None)
    assert res.tolist() == [160, 128]
    (_, t), = reader.read_component(session_file, R.PROJECTOR, "Transform3D:translation", None)
    np.testing.assert_allclose(t, scan.rig.cam_from_proj[:3, 3], atol=1e-4)


def test_maps_have_no_nan_and_masks_match_validity(scan: Scan, session_file: Path) -> None:
    h, w = scan.decoded.valid.shape
    (_, masks), = reader.read_component(session_file, R.MAP_MASKS, "SegmentationImage:buffer")
    masks = masks.reshape(h, w)
    np.testing.assert_array_equal(masks == R.VALID_CLASS, scan.decoded.valid)
    m = scan.decoded.maps["vertical"]
    (_, coord), = reader.read_component(session_file, "maps/vertical/coordinate", "DepthImage:buffer")
    coord = coord.view(np.float32).reshape(h, w)
    assert np.isfinite(coord).all()
    np.testing.assert_array_equal(coord[m.valid], m.coordinate[m.valid])
    assert (coord[~m.valid] == 0).all()
    (_, rng), = reader.read_component(session_file, "maps/vertical/coordinate", "DepthImage:depth_range")
    np.testing.assert_allclose(rng, [np.nanmin(m.coordinate), np.nanmax(m.coordinate)], rtol=1e-6)
    (_, per), = reader.read_component(session_file, "maps/vertical/masks", "SegmentationImage:buffer")
    per = per.reshape(h, w)
    np.testing.assert_array_equal(per == R.VALID_CLASS, m.valid)
    ids = R._reason_ids(list(m.masks))
    for name, mask in m.masks.items():  # every labelled pixel really has that reason
        assert mask[per == ids[name]].all(), name


def test_unclosed_recording_is_not_complete(scan: Scan, tmp_path: Path) -> None:
    path = tmp_path / R.RECORDING_NAME
    rec = R.SessionRecording(path, "open-one")
    try:
        rec.log_rig(scan.rig)
        rec.log_metrics({"decode_s": 1.0})
        rec.stream.flush()
        assert not path.exists() and rec.partial_path.exists()
        with pytest.raises(R.RecordingError, match="never closed"):
            reader.read_summary(path)
        with pytest.raises(R.RecordingError, match="footer"):  # the stream so far has no footer
            reader.read_summary(rec.partial_path)
    finally:
        rec.close()
    rec.close()  # idempotent
    assert "metrics/decode_s" in reader.entity_paths(path)
    with pytest.raises(R.RecordingError, match="closed"):
        rec.log_metrics({"x": 1.0})


def test_closed_on_exception_with_the_error_logged(scan: Scan, tmp_path: Path) -> None:
    path = tmp_path / "aborted.rrd"
    with pytest.raises(RuntimeError, match="camera vanished"), R.SessionRecording(path, "aborted") as rec:
        rec.log_rig(scan.rig)
        rec.log_frame(0, scan.stack[0], scan.patterns.frames()[0])
        raise RuntimeError("camera vanished")
    assert rec.closed
    (_, text), = reader.read_component(path, R.EVENTS, "TextLog:text")
    assert "camera vanished" in str(text[0])
    assert reader.read_summary(path).blueprints == 1  # the generic layout, sent at close


def test_two_sessions_in_one_process(scan: Scan, tmp_path: Path) -> None:
    a, b = tmp_path / "a.rrd", tmp_path / "b.rrd"
    with R.SessionRecording(a, "a") as ra, R.SessionRecording(b, "b") as rb:
        ra.log_metrics({"only_a": 1.0})
        rb.log_metrics({"only_b": 2.0})
        ra.log_cloud(scan.cloud, scan=3)
    sa, sb = reader.read_summary(a), reader.read_summary(b)
    assert (sa.recording_id, sb.recording_id) == ("a", "b")
    assert "metrics/only_a" in sa.entities and "metrics/only_a" not in sb.entities
    assert "metrics/only_b" in sb.entities and R.CLOUD not in sb.entities
    assert list(reader.read_points(a)) == [3]


def test_cloud_in_world_frame_and_projector_pose(scan: Scan, tmp_path: Path) -> None:
    world_from_cam = look_at(np.array([0.0, -250.0, 50.0]), np.array([0.0, 0.0, 400.0]))
    rig = replace(scan.rig, world_from_cam=world_from_cam)
    path = tmp_path / "world.rrd"
    with R.SessionRecording(path, "world") as rec:
        rec.log_rig(rig)
        rec.log_cloud(scan.cloud)
    pts = scan.cloud.flat()[0].astype(np.float64)
    expected = pts @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
    np.testing.assert_allclose(reader.read_points(path)[0], expected, atol=1e-3)
    (_, t), = reader.read_component(path, R.PROJECTOR, "Transform3D:translation", None)
    np.testing.assert_allclose(t, (world_from_cam @ rig.cam_from_proj)[:3, 3], atol=1e-3)


def test_bulk_frames_match_live_frames(scan: Scan, tmp_path: Path) -> None:
    path = tmp_path / "bulk.rrd"
    with R.SessionRecording(path, "bulk", patterns=scan.patterns) as rec:
        rec.log_frames(scan.stack, scan.patterns.frames(), scan=1)
        with pytest.raises(R.RecordingError, match="uint8 or uint16"):
            rec.log_frame(0, scan.stack[0].astype(np.float32))
        with pytest.raises(R.RecordingError, match="pattern specs"):
            rec.log_frames(scan.stack, scan.patterns.frames()[:3])
    s = reader.read_summary(path)
    assert s.entities[R.CAMERA_IMAGE].rows == len(scan.stack)
    assert s.entities[R.FRAME_SPEC].rows == len(scan.stack)
    rows = reader.read_component(path, R.CAMERA_IMAGE, "EncodedImage:blob", R.TIMELINE_PATTERN)
    assert [t for t, _ in rows] == list(range(len(scan.stack)))
    np.testing.assert_array_equal(png_image(rows[5][1]), scan.stack[5])
    assert s.blueprints == 1


def test_entity_path_helpers() -> None:
    assert R.map_path("wrapped", "vertical", 2) == "maps/vertical/wrapped/2"
    assert R.map_path("masks") == R.MAP_MASKS
    assert R.metric_path("/rms_px/") == "metrics/rms_px"
    with pytest.raises(ValueError):
        R.map_path("depth", "vertical")
    bp = R.blueprint(("vertical", "horizontal"), 3)
    assert bp is not None


# ---------------------------------------------------------------- review


def test_display_detection() -> None:
    assert viewer.has_display({"DISPLAY": ":0"})
    assert viewer.has_display({"WAYLAND_DISPLAY": "wayland-0"})
    assert not viewer.has_display({})
    assert not viewer.has_display({"DISPLAY": ""})


def test_review_command_with_a_display(tmp_path: Path) -> None:
    rrd = tmp_path / R.RECORDING_NAME
    cmd = viewer.review_command(rrd, display=True)
    assert cmd[-3:] == [str(rrd), "--port", str(viewer.DEFAULT_GRPC_PORT)]
    assert "--serve-web" not in cmd
    assert Path(cmd[0]).name.startswith("rerun") and Path(cmd[0]).exists()
    assert viewer.review_command(tmp_path, display=True)[-3] == str(rrd)  # a session folder names its .rrd


def test_review_command_headless(tmp_path: Path) -> None:
    rrd = tmp_path / "x.rrd"
    cmd = viewer.review_command(rrd, display=False, port=9191, grpc_port=9877)
    i = cmd.index("--serve-web")
    assert cmd[i + 1] == str(rrd)
    assert cmd[cmd.index("--web-viewer-port") + 1] == "9191"
    assert cmd[cmd.index("--port") + 1] == "9877"
    assert cmd[cmd.index("--bind") + 1] == "127.0.0.1"
    assert viewer.web_url(9191, 9877) == "http://localhost:9191?url=rerun%2Bhttp%3A%2F%2Flocalhost%3A9877%2Fproxy"
    text = viewer.review_instructions(9191, 9877)
    assert viewer.web_url(9191, 9877) in text
    assert "-L 9191:localhost:9191" in text and "-L 9877:localhost:9877" in text


def test_review_runs_the_command_and_waits(session_file: Path, monkeypatch: pytest.MonkeyPatch,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setenv("RERUN_CLI_PATH", "/bin/echo")  # stands in for the viewer binary
    proc = viewer.start_review(session_file.parent, display=False, port=9192, stdout=subprocess.PIPE, text=True)
    out, _ = proc.communicate(timeout=10)
    assert out.split() == ["--serve-web", str(session_file), "--bind", "127.0.0.1", "--web-viewer-port", "9192",
                           "--port", str(viewer.DEFAULT_GRPC_PORT)]
    assert "ssh -N -L 9192:localhost:9192" in capsys.readouterr().out
    assert viewer.review(session_file, display=True, stdout=subprocess.DEVNULL) == 0


def test_review_takes_a_free_port_when_the_default_is_taken(session_file: Path, monkeypatch: pytest.MonkeyPatch,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """A second `slscan review` beside a first: the gRPC port another holds is not reused (the
    viewer would exit 1); a port given on purpose and taken is refused naming it."""
    import socket

    monkeypatch.setenv("RERUN_CLI_PATH", "/bin/echo")
    with socket.socket() as first:
        first.bind(("127.0.0.1", 0))
        first.listen()
        held = first.getsockname()[1]
        monkeypatch.setattr(viewer, "DEFAULT_GRPC_PORT", held)
        proc = viewer.start_review(session_file, display=True, stdout=subprocess.PIPE, text=True)
        out, _ = proc.communicate(timeout=10)
        args = out.split()
        chosen = int(args[args.index("--port") + 1])
        assert chosen != held and chosen > 0
        with pytest.raises(R.RecordingError, match=f"port {held} on 127.0.0.1"):
            viewer.start_review(session_file, display=True, grpc_port=held)


def test_review_refuses_a_missing_or_unclosed_recording(tmp_path: Path) -> None:
    with pytest.raises(R.RecordingError, match="no recording"):
        viewer.start_review(tmp_path / "none.rrd", display=False)
    (tmp_path / "cut.rrd.part").write_bytes(b"")
    with pytest.raises(R.RecordingError, match="never closed"):
        viewer.start_review(tmp_path / "cut.rrd", display=False)
