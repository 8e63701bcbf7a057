"""Issue 32: a session as a unit of integrity, run as users run slscan (separate processes).

Two writers on one session: the second is refused at once naming the first's PID, and the
outputs stay whole. Outputs go only inside the session's real folder (an `outputs` link is
refused, its target untouched); dead writers' temporary files are cleaned by the next
writer. A capture killed after its last frame is completed by `decode --recover`, every
frame checked; one with frames missing is refused naming how many it holds. Kills at random
moments of a scan leave a session that decodes, recovers or says to re-scan, never a
traceback. SIGTERM ends a scan as Ctrl-C does (exit 130, frames kept). A full disk (a small
tmpfs, when this process may mount one) ends scan, decode and export within seconds with
one line, exit code 2 and every captured frame kept."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hostile import campaign_seed
from session_support import SCENE, small_rig_toml

from scanner.session import MANIFEST, Session, sha256
from scanner.session_lock import session_lock

REPO = Path(__file__).resolve().parents[1]


def slscan(*argv: str, timeout_s: float = 120, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`python -m slscan ARGV` in a fresh process (this tree's code), with a timeout: a hang fails."""
    return subprocess.run([sys.executable, "-m", "slscan", *argv], capture_output=True, text=True, timeout=timeout_s,
                          cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})})


def error_line(proc: subprocess.CompletedProcess, command: str) -> str:
    """The one error line of a refused command (nothing else on stderr names an error)."""
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if "error" in ln.lower()]
    assert len(lines) == 1 and lines[0].startswith(f"slscan {command}: error: "), proc.stderr
    return lines[0]


@pytest.fixture
def session(clean_session: Path, tmp_path: Path) -> Path:
    out = tmp_path / "s"
    shutil.copytree(clean_session, out)
    return out


# ------------------------------------------------------------------ one writer at a time

def test_a_second_writer_is_refused_naming_the_first(session: Path) -> None:
    with session_lock(session, command="slscan decode (the test)"):
        t0 = time.perf_counter()
        proc = slscan("decode", str(session))
        assert time.perf_counter() - t0 < 60
    line = error_line(proc, "decode")
    assert proc.returncode == 2 and f"in use by PID {os.getpid()} (slscan decode (the test)" in line
    assert slscan("decode", str(session)).returncode == 0  # free again: the lock went with its holder


def test_two_decodes_at_once_leave_whole_outputs(session: Path) -> None:
    """Both started together: each either decodes or is refused as busy; whatever order,
    the outputs and the recording are complete and as a lone decode writes them."""
    procs = [subprocess.Popen([sys.executable, "-m", "slscan", "decode", str(session)], cwd=REPO, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              env={**os.environ, "PYTHONPATH": str(REPO)}) for _ in range(2)]
    results = [(p.wait(120), p.stderr.read()) for p in procs]  # type: ignore[union-attr]
    assert sorted(code for code, _ in results)[0] == 0
    for code, err in results:
        assert "Traceback" not in err and ".part: No such file" not in err
        assert code == 0 or (code == 2 and "in use by PID" in err), err
    assert not list(session.rglob("*.part*")), list(session.rglob("*.part*"))
    result = json.loads((session / "outputs" / "result.json").read_text())
    from scanner.pointcloud import read_ply_points
    from scanner.recording_reader import read_summary

    assert len(read_ply_points(session / "outputs" / "cloud.ply")) == result["points"] > 0
    assert read_summary(session / "recording.rrd").entities  # a complete recording opens (a truncated one is refused)


def test_outputs_as_a_link_is_refused_and_its_target_untouched(session: Path, tmp_path: Path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.rmtree(session / "outputs")
    (session / "outputs").symlink_to(elsewhere)
    proc = slscan("decode", str(session))
    assert proc.returncode == 2 and "symbolic link" in error_line(proc, "decode")
    assert list(elsewhere.iterdir()) == []


def test_dead_writers_leftovers_are_cleaned_by_the_next(session: Path, tmp_path: Path) -> None:
    planted = [session / ".manifest.json.4242-deadbeef.part", session / "outputs" / ".cloud.ply.77-0a0b0c0d.part",
               session / "outputs" / "cloud.ply.part", session / "frames" / ".frame_003.png.9-00000000.part"]
    for p in planted:
        p.write_bytes(b"half a file")
    target = tmp_path / "victim"
    target.write_text("not to be written")
    (session / "recording.rrd.part").symlink_to(target)  # a planted link at the recording's temporary name
    assert slscan("decode", str(session)).returncode == 0
    assert not any(p.exists() or p.is_symlink() for p in planted + [session / "recording.rrd.part"])
    assert target.read_text() == "not to be written"


# ------------------------------------------------------------------ recovery

def test_recover_completes_a_capture_killed_before_its_manifest(session: Path) -> None:
    manifest = json.loads((session / MANIFEST).read_text())
    (session / MANIFEST).unlink()
    refused = slscan("decode", str(session))
    assert refused.returncode == 2 and "--recover" in error_line(refused, "decode")
    proc = slscan("decode", "--recover", str(session))
    assert proc.returncode == 0, proc.stderr
    rebuilt = json.loads((session / MANIFEST).read_text())
    assert rebuilt["frames"] == manifest["frames"] and rebuilt["rig_model"] == manifest["rig_model"]
    assert rebuilt["recovered"]["frames_checked"] == "sha256" and not rebuilt["recovered"]["assumed"]


def test_recover_refuses_a_capture_with_frames_missing(session: Path) -> None:
    (session / MANIFEST).unlink()
    lines = (session / "frames.jsonl").read_text().splitlines()
    (session / "frames.jsonl").write_text("\n".join(lines[:11]) + "\n" + lines[11][:37])  # the kill cut the last line
    proc = slscan("decode", "--recover", str(session))
    assert proc.returncode == 2 and "holds 11 of the 12 frames" in error_line(proc, "decode")
    assert not (session / MANIFEST).exists() and len(list((session / "frames").glob("*.png"))) == 12


@pytest.mark.parametrize("plan, words", [
    ("hdr", "capture.json, key 'exposure'"),
    ({"exposures_s": [0.016, 0.004], "mode": "given", "reason": "r"}, "capture.json, key 'exposure'"),
    ({"exposures_s": [0.004, 0.016], "mode": "given", "reason": "r"}, "holds 12 of the 24 frames"),
])
def test_recover_reads_the_capture_records_exposure_plan(session: Path, plan: object, words: str) -> None:
    """The plan in capture.json is read as the manifest's `exposure` is: a malformed one is
    refused in one line naming it; a two-exposure plan needs the pattern set twice."""
    (session / MANIFEST).unlink()
    record = json.loads((session / "capture.json").read_text())
    (session / "capture.json").write_text(json.dumps({**record, "exposure": plan}))
    proc = slscan("decode", "--recover", str(session))
    assert proc.returncode == 2 and words in error_line(proc, "decode")
    assert not (session / MANIFEST).exists()


def test_recover_refuses_a_frame_changed_since_it_was_logged(session: Path) -> None:
    (session / MANIFEST).unlink()
    f = session / "frames" / "frame_005.png"
    shutil.copy(session / "frames" / "frame_004.png", f)
    proc = slscan("decode", "--recover", str(session))
    assert proc.returncode == 2 and "frame 5 is not the one logged" in error_line(proc, "decode")


# ------------------------------------------------------------------ kills and signals

def test_sigterm_ends_a_scan_as_ctrl_c(tmp_path: Path) -> None:
    rig = small_rig_toml(tmp_path)
    out = tmp_path / "scan"
    proc = subprocess.Popen([sys.executable, "-m", "slscan", "scan", "--rig", str(rig), "--scene", str(SCENE), "--out",
                             str(out), "--fault", "delay_frame=6", "--fault", "delay_s=1.5"], cwd=REPO, text=True,
                            stderr=subprocess.PIPE, stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)})
    deadline = time.monotonic() + 90
    while not (out / "frames" / "frame_004.png").exists():
        assert time.monotonic() < deadline and proc.poll() is None, proc.stderr.read()  # type: ignore[union-attr]
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(30)
    err = proc.stderr.read()  # type: ignore[union-attr]
    assert code == 130 and "terminated (SIGTERM)" in err and "Traceback" not in err, err
    stored = json.loads((out / "error.json").read_text())["frames_stored"]
    assert stored >= 5 and len(list((out / "frames").glob("frame_*.png"))) == stored


def _kill_at(argv: list[str], root: Path, after_s: float) -> float:
    """Start `slscan ARGV` writing the session `root`; SIGKILL it `after_s` seconds after the
    session folder appears (the start-up, imports and the simulator's rendering, a few to
    tens of seconds on a loaded machine, are not what a kill tests). Returns how long it had
    run since the folder appeared (it may have finished first)."""
    proc = subprocess.Popen([sys.executable, "-m", "slscan", *argv], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, env={**os.environ, "PYTHONPATH": str(REPO)})
    deadline = time.monotonic() + 300
    while not root.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    t0 = time.monotonic()
    try:
        proc.wait(after_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(30)
    return time.monotonic() - t0


def check_after_kill(root: Path) -> str:
    """What a session left by a killed scan is, checked against what it holds: complete (it
    decodes), completable (--recover then decodes) or to re-scan (refused, frames kept)."""
    if not root.exists():
        return "no folder"
    frames = sorted((root / "frames").glob("frame_*.png")) if (root / "frames").exists() else []
    logged = [json.loads(x) for x in (root / "frames.jsonl").read_text().splitlines() if x.endswith("}")] \
        if (root / "frames.jsonl").exists() else []
    for entry in logged:  # every logged frame is stored whole
        assert sha256((root / entry["file"]).read_bytes()) == entry["sha256"]
    if (root / MANIFEST).exists():
        Session.open(root)
        proc = slscan("decode", str(root))
        assert proc.returncode == 0, proc.stderr
        return "complete"
    proc = slscan("decode", "--recover", str(root))
    if len(logged) == 12 and (root / "capture.json").exists():
        assert proc.returncode == 0, proc.stderr
        return "recovered"
    assert proc.returncode == 2, proc.stderr
    error_line(proc, "decode")
    assert len(list((root / "frames").glob("frame_*.png"))) == len(frames)  # nothing lost by trying
    return "re-scan"


def test_a_scan_killed_at_a_random_moment_leaves_a_truthful_session(tmp_path: Path, capsys) -> None:
    rig = small_rig_toml(tmp_path)
    rng = np.random.default_rng(seed := campaign_seed())
    after = float(rng.uniform(0.0, 3.0))
    root = tmp_path / "k"
    _kill_at(["scan", "--rig", str(rig), "--scene", str(SCENE), "--out", str(root)], root, after)
    state = check_after_kill(root)
    with capsys.disabled():
        print(f"\nkilled {after:.2f} s after its session folder appeared (seed {seed}): {state}")


@pytest.mark.slow
def test_scans_killed_at_every_stage_leave_truthful_sessions(tmp_path: Path, capsys) -> None:
    """SIGKILL at 40 moments spread over a scan's life from its session folder's creation
    to its end (a first, unkilled scan measures that span here), with jitter."""
    rig = small_rig_toml(tmp_path)
    argv = ["scan", "--rig", str(rig), "--scene", str(SCENE), "--out"]
    span = _kill_at(argv + [str(tmp_path / "whole")], tmp_path / "whole", 300.0)
    rng = np.random.default_rng(seed := campaign_seed())
    states: dict[str, int] = {}
    for k, u in enumerate((np.arange(40) + rng.uniform(0, 1, 40)) / 40):
        root = tmp_path / f"k{k}"
        _kill_at(argv + [str(root)], root, float(u * span))
        state = check_after_kill(root)
        states[state] = states.get(state, 0) + 1
    with capsys.disabled():
        print(f"\nscans killed at 40 moments over their {span:.1f} s (seed {seed}): {states}")


# ------------------------------------------------------------------ a full disk

@pytest.fixture
def small_disk(tmp_path: Path):
    """A tmpfs of a size the test sets (`mount(MB)`), unmounted afterwards; skipped when
    this process may not mount one."""
    mounts: list[Path] = []

    def mount(mb: float) -> Path:
        point = tmp_path / f"disk{len(mounts)}"
        point.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={int(mb * 1024)}k", "tmpfs", str(point)],
                              capture_output=True)
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({done.stderr.decode().strip()})")
        mounts.append(point)
        return point

    yield mount
    for point in mounts:
        subprocess.run(["umount", "-l", str(point)], capture_output=True)


def test_scan_on_a_full_disk(tmp_path: Path, small_disk) -> None:
    disk = small_disk(1.0)
    rig = small_rig_toml(tmp_path)
    t0 = time.perf_counter()
    proc = slscan("scan", "--rig", str(rig), "--scene", str(SCENE), "--out", str(disk / "s"), timeout_s=120)
    line = error_line(proc, "scan")
    assert proc.returncode == 2 and "No space left on device" in line and time.perf_counter() - t0 < 60
    assert "kept" in line  # says where the frames stored are
    log = [json.loads(x) for x in (disk / "s" / "frames.jsonl").read_text().splitlines()]
    for entry in log:  # every frame logged is stored whole
        assert sha256((disk / "s" / entry["file"]).read_bytes()) == entry["sha256"]


def test_decode_on_a_full_disk_keeps_the_session(session: Path, small_disk) -> None:
    frames = sum(f.stat().st_size for f in session.rglob("*") if f.is_file() and "outputs" not in f.parts
                 and f.name != "recording.rrd")
    disk = small_disk(frames / 2 ** 20 + 0.5)
    root = disk / "s"
    shutil.copytree(session, root, ignore=shutil.ignore_patterns("outputs", "recording.rrd"))
    t0 = time.perf_counter()
    proc = slscan("decode", str(root), timeout_s=120)
    line = error_line(proc, "decode")
    assert proc.returncode == 2 and "No space left on device" in line and time.perf_counter() - t0 < 60
    Session.open(root).load_stack()  # the frames and manifest are intact
    partial = [p for p in root.rglob("*.part*") if p.name != "recording.rrd.part"]  # that one says "interrupted"
    assert not partial, partial


def test_export_to_a_full_disk(session: Path, small_disk) -> None:
    disk = small_disk(0.1)
    proc = slscan("export", str(session), "--format", "csv", "--out", str(disk / "cloud.csv"))
    line = error_line(proc, "export")
    assert proc.returncode == 2 and "No space left on device" in line
    assert list(disk.iterdir()) == []  # no partial file
