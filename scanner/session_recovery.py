"""Completing a session whose capture finished but whose manifest was never written (the
process was killed between its last frame and the manifest): `slscan decode --recover`.

The manifest is rebuilt from what the session itself holds, every part checked:
`capture.json` (written before the first frame: rig, rig model, patterns, devices,
provenance, exposure plan) and `frames.jsonl` (one line per stored frame with its SHA-256).
Each listed frame must exist with the recorded checksum, the frames must be numbered
0..n-1 without gaps, and there must be as many as the pattern set (times the exposures)
needs; a last line of frames.jsonl cut by the kill is dropped (its frame was not complete
either, since a frame is named before it is logged). A session of fewer frames is refused,
naming how many it holds: the capture did not finish and only a re-scan completes it.

A session written before capture.json existed can be recovered only with the rig (and
pattern set) given by the user; the manifest then says they were assumed, not recorded.
The manifest's `recovered` record says what it was rebuilt from and when.
"""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

from scanner import schema
from scanner.errors import ScannerError, SessionError
from scanner.file_checks import FileRefused, read_regular
from scanner.patterns import PatternSet
from scanner.session import (
    CAPTURE,
    ERROR,
    FRAME_LOG,
    MANIFEST,
    ExposureRecord,
    FrameEntry,
    Session,
    confined_frame_path,
    manifest_record,
    sha256,
    write_json,
)
from scanner.session_lock import session_lock

MAX_LOG_BYTES = 64 * 1024 ** 2


def _read_json(path: Path) -> Any:
    try:
        return json.loads(read_regular(path, limit=MAX_LOG_BYTES))
    except FileRefused as exc:
        raise SessionError(str(exc)) from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise SessionError(f"{path}: unreadable: {exc}") from None


def logged_frames(root: Path) -> tuple[list[dict[str, Any]], str]:
    """The frame entries of frames.jsonl, each validated (`FrameEntry`), and a note on a
    last line cut short (dropped) or "" when there was none."""
    path = root / FRAME_LOG
    try:
        lines = read_regular(path, limit=MAX_LOG_BYTES).decode("utf-8", errors="replace").splitlines()
    except FileRefused as exc:
        raise SessionError(f"{exc}; no frame was logged, nothing to recover") from None
    entries, note = [], ""
    for n, line in enumerate(lines, 1):
        try:
            entry = json.loads(line)
            FrameEntry.model_validate(entry)
        except (ValueError, RecursionError) as exc:
            if n == len(lines):
                note = f"the last line of {FRAME_LOG} was cut short and is dropped"
                break
            raise SessionError(f"{path}, line {n}: not a frame record ({str(exc).splitlines()[0][:100]})") from None
        entries.append(entry)
    return entries, note


def capture_progress(root: Path) -> tuple[int, int | None]:
    """(frames logged, frames the capture needs or None without capture.json) of a session
    without a manifest, from its records alone (no frame read): what a restarted station
    says of it."""
    try:
        entries, _ = logged_frames(root)
    except SessionError:
        entries = []
    try:
        record, _ = _capture_record(root, None, None)
        pattern_set = PatternSet.from_dict(record["patterns"], root / CAPTURE, "patterns")
        needed = pattern_set.n_frames * _exposures(root, record)
    except ScannerError:
        needed = None
    return len(entries), needed


def recover_manifest(root: str | Path, *, rig: Any = None, patterns: PatternSet | None = None) -> Path:
    """Write the manifest of a session whose capture finished without one (module
    docstring); `rig` (a RigConfig) and `patterns` stand in for a missing capture.json.
    Returns the manifest's path; SessionError naming what is missing otherwise."""
    root = Path(root)
    with session_lock(root, command="slscan decode --recover"):
        if (root / MANIFEST).exists():
            raise SessionError(f"{root}: already has a {MANIFEST}: nothing to recover (decode it without --recover)")
        record, assumed = _capture_record(root, rig, patterns)
        entries, note = logged_frames(root)
        pattern_set = PatternSet.from_dict(record["patterns"], root / CAPTURE, "patterns")
        needed = pattern_set.n_frames * _exposures(root, record)
        for k, e in enumerate(entries):
            if e["k"] != k:
                raise SessionError(f"{root / FRAME_LOG}: frame {k} is missing (the log goes on with frame {e['k']})")
            _check_frame(root, k, e)
        if len(entries) != needed:
            raise SessionError(f"{root}: holds {len(entries)} of the {needed} frames the pattern set needs: the "
                               f"capture did not finish; re-scan the part (the frames are kept)")
        error = _read_json(root / ERROR) if (root / ERROR).exists() else None
        manifest = {**record, "timings_s": record.get("timings_s", {}), "frames": entries,
                    "recovered": {"time": dt.datetime.now(dt.UTC).isoformat(),
                                  "from": [FRAME_LOG] + ([] if assumed else [CAPTURE]),
                                  "assumed": assumed, "frames_checked": "sha256" if entries[0].get("sha256") else
                                  "not checked (no checksums logged)", "note": note, "error_json": error}}
        path = root / MANIFEST
        write_json(path, manifest)
        try:
            Session.open(root)
        except ScannerError:
            path.unlink(missing_ok=True)  # what was rebuilt does not hold: leave the session as it was
            raise
        return path


def _capture_record(root: Path, rig: Any, patterns: PatternSet | None) -> tuple[dict[str, Any], str]:
    """(the manifest-to-be, "" or what was assumed in its place)."""
    if (root / CAPTURE).exists():
        record = _read_json(root / CAPTURE)
        if not isinstance(record, dict) or "patterns" not in record or "rig_model" not in record:
            raise SessionError(f"{root / CAPTURE}: not a capture record")
        return record, ""
    if rig is None:
        raise SessionError(f"{root}: no {CAPTURE} (written by slscan since this release, before the first frame): "
                           f"give the rig the session was captured with, `--rig RIG.toml` (and `--patterns` if the "
                           f"scan used other patterns); the manifest will say they were assumed")
    patterns = patterns or PatternSet.load(rig.patterns_path)
    started = dt.datetime.fromtimestamp((root / FRAME_LOG).stat().st_mtime, dt.UTC)
    record = manifest_record(root, root.name, started, rig_config=rig.raw, model=rig.model, patterns=patterns,
                             devices={},
                             extra={"rig_config_path": str(rig.path.resolve())})
    return record, f"rig {rig.path} and patterns {patterns.family} given on the command line, not recorded"


def _exposures(root: Path, record: dict[str, Any]) -> int:
    """How many times the capture record's exposure plan (`ExposureRecord`) takes the pattern
    set: once without a plan."""
    plan = record.get("exposure")
    return 1 if plan is None else len(schema.parse(ExposureRecord, plan, root / CAPTURE, "exposure").exposures_s)


def _check_frame(root: Path, k: int, entry: dict[str, Any]) -> None:
    path = confined_frame_path(root, entry["file"], k, f"{root / FRAME_LOG}, frame {k}")
    try:
        data = read_regular(path)
    except FileRefused as exc:
        raise SessionError(f"{exc}: frame {k} is logged but not stored; re-scan the part") from None
    if entry.get("sha256") and sha256(data) != entry["sha256"]:
        raise SessionError(f"{path}: frame {k} is not the one logged (its SHA-256 differs); re-scan the part")
