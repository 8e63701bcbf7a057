"""Recording levels (scanner/session_recording.py): level "display" keeps the frames
lossless and logs the maps and the cloud decimated; the rig's `[recording] level` is
validated by the schema layer. Truth: the inputs themselves, sliced with numpy, and the
frames decoded by OpenCV."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from scanner import recording_reader as reader
from scanner import session_recording as R
from scanner.config import CONFIG_DIR, load_toml
from scanner.decode import decode
from scanner.errors import ConfigError
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import RigConfig
from sim.analytic_stack import synthetic_stack

PATTERNS = PatternSet("heterodyne", 4, (64.0, 56.0, 49.0), ("vertical",))


def test_display_level_decimates_maps_and_cloud_and_keeps_frames_lossless(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    rig = RigConfig.load().nominal_model().with_camera_size(160, 128)
    stack = synthetic_stack(rig, PATTERNS)
    decoded = decode(stack, PATTERNS, 12, rig.projector.size)
    cloud = triangulate(decoded, Triangulator(rig))
    monkeypatch.setattr(R, "DISPLAY_MAX_SIDE_PX", 60)  # 160 x 128 -> every 3rd row and column
    assert R.display_step(128, 160) == 3
    sizes = {}
    for level in ("full", "display"):
        path = tmp_path / f"{level}.rrd"
        with R.SessionRecording(path, level, level=level) as rec:
            rec.log_rig(rig)
            rec.log_frames(stack, PATTERNS.frames())
            rec.log_decode(decoded)
            logged = rec.log_cloud(cloud)
        sizes[level] = path.stat().st_size
        step = 3 if level == "display" else 1
        want = cloud.points[::step, ::step][~np.isnan(cloud.points[::step, ::step, 2])]
        assert logged == len(want)
        np.testing.assert_array_equal(reader.read_points(path)[0], want)
        m = decoded.maps["vertical"]
        (_, coord), = reader.read_component(path, "maps/vertical/coordinate", "DepthImage:buffer")
        v = m.valid[::step, ::step]
        coord = coord.view(np.float32).reshape(v.shape)
        np.testing.assert_array_equal(coord[v], m.coordinate[::step, ::step][v])
        rows = reader.read_component(path, R.CAMERA_IMAGE, "EncodedImage:blob", R.TIMELINE_PATTERN)
        assert len(rows) == len(stack)
        for k in (0, len(stack) - 1):
            np.testing.assert_array_equal(cv2.imdecode(rows[k][1].astype(np.uint8), cv2.IMREAD_UNCHANGED), stack[k])
    assert sizes["display"] < sizes["full"]


def test_recording_level_none_is_refused_by_the_recording() -> None:
    with pytest.raises(R.RecordingError, match="'none' makes no recording"):
        R.SessionRecording("/nonexistent/x.rrd", "x", level="none")


def test_rig_recording_level_is_validated(tmp_path: Path) -> None:
    src = CONFIG_DIR / "rigs" / "sim_bench.toml"
    assert RigConfig.load(src).recording_level == "display"  # the default
    text = src.read_text()
    assert "[recording]" not in text
    good = tmp_path / "good.toml"
    good.write_text(text + '\n[recording]\nlevel = "none"\n')
    assert load_toml(good)["recording"] == {"level": "none"}
    patterns = load_toml(src)["rig"].get("patterns")
    if patterns:  # relative to the rig file: keep it pointing at the bundled set
        good.write_text(good.read_text().replace(patterns, str((src.parent / patterns).resolve())))
    assert RigConfig.load(good).recording_level == "none"
    bad = tmp_path / "bad.toml"
    bad.write_text(good.read_text().replace('level = "none"', 'level = "some"'))
    with pytest.raises(ConfigError, match="recording.level"):
        RigConfig.load(bad)
