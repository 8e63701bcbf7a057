"""`slscan review` opens anything slscan writes (issue 14, "Review"): a scan session (with its
inspection), a station part folder, a calibration folder, a multi-view folder, poses.rrd, any
folder with recordings; a folder it does not know is refused in one line. The viewer is a
stand-in script (RERUN_CLI_PATH) that records what it was asked to open, so the test sees
exactly the files and the blueprint the real viewer would get."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from cli_support import run
from rerun.chunk import RrdReader
from session_support import small_rig_toml

from scanner.config import CONFIG_DIR
from scanner.recording_reader import entity_paths
from slscan.review_target import find_target

SCENE = CONFIG_DIR / "scenes" / "sphere_plane.toml"


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real 320 x 256 scan session (sphere and plane)."""
    tmp = tmp_path_factory.mktemp("review")
    rig = small_rig_toml(tmp)
    assert run("scan", "--rig", str(rig), "--scene", str(SCENE), "--out", str(tmp / "s"))[0] == 0
    return tmp / "s"


@pytest.fixture
def viewer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A stand-in viewer: writes its arguments to args.txt and keeps any .rbl it was given."""
    log = tmp_path / "viewer"
    log.mkdir()
    script = log / "rerun"
    script.write_text(f'#!/bin/sh\nfor a in "$@"; do echo "$a" >> {log}/args.txt; case "$a" in *.rbl) '
                      f'cp "$a" {log}/blueprint.rbl;; esac; done\n')
    script.chmod(0o755)
    monkeypatch.setenv("RERUN_CLI_PATH", str(script))
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    return log


def opened(log: Path) -> list[str]:
    args = (log / "args.txt").read_text().split()
    return args[1: args.index("--bind")]  # after --serve-web, before the server options


def views(blueprint_file: Path) -> bool:
    entries = RrdReader(str(blueprint_file)).blueprints()
    return len(entries) == 1 and entries[0].application_id == "slscan"


def origins(target) -> set[str]:
    """Every view's origin in a target's blueprint."""
    found, todo = set(), [target.blueprint.root_container]
    while todo:
        item = todo.pop()
        if hasattr(item, "origin"):
            found.add(str(item.origin))
        todo.extend(getattr(item, "contents", None) or [] if not hasattr(item, "origin") else [])
    return found


def three_d_contents(target) -> set[str]:
    """The entity filter of the blueprint's one 3D view: the part alone, not the rig's frusta
    (with them the part was a small patch in a corner of the web viewer's view)."""
    views, todo = [], [target.blueprint.root_container]
    while todo:
        item = todo.pop()
        views += [item] if type(item).__name__ == "Spatial3DView" else []
        todo.extend([] if hasattr(item, "origin") else getattr(item, "contents", None) or [])
    assert len(views) == 1
    return set(views[0].contents)


def small_recording(path: Path, entity: str) -> Path:
    """A closed .rrd with one entity, written by rerun itself."""
    path.parent.mkdir(parents=True, exist_ok=True)
    stream = rr.RecordingStream("slscan")
    stream.save(str(path))
    stream.log(entity, rr.Points3D(np.zeros((3, 3))))
    stream.flush()
    stream.disconnect()
    return path


def test_a_scan_session_opens_its_recording(session: Path, viewer: Path) -> None:
    code, _, err = run("review", str(session))
    assert code == 0 and "scan session" in err
    assert opened(viewer) == [str(session / "recording.rrd")]  # a session alone keeps its own blueprint
    assert "world/scan/cloud" in entity_paths(session / "recording.rrd")


def test_an_inspected_session_opens_the_inspection_with_its_views(session: Path, viewer: Path,
                                                                  tmp_path: Path) -> None:
    copy = tmp_path / "inspected"
    shutil.copytree(session, copy, symlinks=True)
    small_recording(copy / "outputs" / "inspection.rrd", "world/inspection/deviation")
    (copy / "outputs" / "inspection.json").write_text(json.dumps({"status": "ok"}))
    code, _, _ = run("review", str(copy))
    files = opened(viewer)
    assert code == 0 and files[:2] == [str(copy / "recording.rrd"), str(copy / "outputs" / "inspection.rrd")]
    assert files[2].endswith(".rbl") and views(viewer / "blueprint.rbl")
    assert {"inspection/deviation_map", "inspection/report", "world"} <= origins(find_target(copy))
    assert three_d_contents(find_target(copy)) == {"+ world/inspection/cad", "+ world/inspection/deviation",
                                                   "+ world/inspection/deviation_legend"}
    assert not Path(files[2]).exists()  # the temporary blueprint is gone once the viewer ends


def test_a_posed_bin_session_opens_with_the_poses_views(session: Path, viewer: Path, tmp_path: Path) -> None:
    """`slscan pose SESSION` writes outputs/poses.rrd: reviewing the session shows the poses'
    views (it showed the recording's own automatic layout, the poses table in a narrow pane)."""
    copy = tmp_path / "bin"
    shutil.copytree(session, copy, symlinks=True)
    small_recording(copy / "outputs" / "poses.rrd", "world/pose/instances")
    code, _, _ = run("review", str(copy))
    files = opened(viewer)
    assert code == 0 and files[:2] == [str(copy / "recording.rrd"), str(copy / "outputs" / "poses.rrd")]
    assert files[2].endswith(".rbl") and views(viewer / "blueprint.rbl")
    assert {"world", "pose/table"} <= origins(find_target(copy))


def test_a_station_part_folder_opens_each_view_session(session: Path, viewer: Path, tmp_path: Path) -> None:
    part = tmp_path / "parts" / "demo" / "SN-1-20261201"
    part.mkdir(parents=True)
    shutil.copytree(session, part / "view0", symlinks=True)
    (part / "part.json").write_text(json.dumps({"status": "pass", "sessions": [str(part / "view0")]}))
    code, _, err = run("review", str(part))
    assert code == 0 and "station part" in err
    assert opened(viewer) == [str(part / "view0" / "recording.rrd")]


def test_a_calibration_folder_shows_its_coverage(viewer: Path, tmp_path: Path) -> None:
    cal = tmp_path / "cal"
    small_recording(cal / "recording.rrd", "calibration/camera/coverage")
    (cal / "calibration.json").write_text("{}")
    code, _, err = run("review", str(cal))
    assert code == 0 and "calibration folder" in err
    files = opened(viewer)
    assert files[0] == str(cal / "recording.rrd") and files[1].endswith(".rbl") and views(viewer / "blueprint.rbl")
    assert {"calibration/camera/coverage", "calibration/projector/coverage"} <= origins(find_target(cal))


def test_poses_and_other_recordings(viewer: Path, tmp_path: Path) -> None:
    poses = small_recording(tmp_path / "bin" / "outputs" / "poses.rrd", "world/pose/instances")
    code, _, _ = run("review", str(poses))
    assert code == 0 and opened(viewer)[0] == str(poses) and views(viewer / "blueprint.rbl")
    assert {"world", "pose/table"} <= origins(find_target(poses))
    assert three_d_contents(find_target(poses)) == {"+ world/pose/instances", "+ world/pose/models/**",
                                                   "+ world/pose/pick_order"}
    verify = tmp_path / "verify"
    a = small_recording(verify / "verify.rrd", "world/artefact")
    os.remove(viewer / "args.txt")
    assert run("review", str(verify))[0] == 0 and opened(viewer) == [str(a)]


def test_a_multiview_folder_opens_its_views(session: Path, viewer: Path, tmp_path: Path) -> None:
    mv = tmp_path / "mv"
    mv.mkdir()
    (mv / "views.json").write_text("{}")
    for k in range(2):
        shutil.copytree(session, mv / f"view_{k:03d}", symlinks=True)
    code, _, err = run("review", str(mv))
    assert code == 0 and "multi-view folder" in err
    assert opened(viewer) == [str(mv / f"view_{k:03d}" / "recording.rrd") for k in range(2)]
    small_recording(mv / "recording.rrd", "world/merged")  # once aligned: the merged recording
    assert find_target(mv).recordings == (mv / "recording.rrd",)


def test_unknown_and_incomplete_folders_are_refused_in_one_line(viewer: Path, tmp_path: Path) -> None:
    (tmp_path / "stuff").mkdir()
    (tmp_path / "stuff" / "notes.txt").write_text("x")
    code, _, err = run("review", str(tmp_path / "stuff"))
    assert code == 2 and "nothing slscan wrote to review here" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "cut" / "frames").mkdir(parents=True)
    code, _, err = run("review", str(tmp_path / "cut"))
    assert code == 2 and "incomplete session" in err
    code, _, err = run("review", str(tmp_path / "stuff" / "notes.txt"))
    assert code == 2 and "not a Rerun recording" in err
    assert not (viewer / "args.txt").exists()
