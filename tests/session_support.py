"""A small simulated bench and the sessions it scans, shared by the session, input and
station tests: the bench rig with a smaller camera (same lens field of view), one small scan
of the sphere-and-plane scene, and ways to edit a stored session."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from scanner.config import CONFIG_DIR
from scanner.patterns import PatternSet
from scanner.pipeline import scan
from scanner.rig import DEFAULT_RIG, RigConfig, open_rig
from scanner.session import MANIFEST

SCENE = CONFIG_DIR / "scenes" / "sphere_plane.toml"
PATTERNS = PatternSet.load(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml")


def small_rig_toml(folder: Path, *, width: int = 320, height: int = 256, source: Path = DEFAULT_RIG,
                   **rig_keys: object) -> Path:
    """`source` (default the bench rig) with a `width` x `height` camera (same lens field of
    view) and extra or changed [rig] keys, written to `folder`/rig.toml."""
    text = source.read_text().replace("width = 1280", f"width = {width}").replace("height = 1024",
                                                                                   f"height = {height}")
    text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    for key, value in rig_keys.items():
        line = f"{key} = {json.dumps(value)}"
        text, n = re.subn(rf"^{key} = .*$", line, text, count=1, flags=re.M)
        if not n:
            text = text.replace("[rig]\n", f"[rig]\n{line}\n", 1)
    path = folder / "rig.toml"
    path.write_text(text)
    return path


def scan_small_session(folder: Path, **scan_options: Any) -> Path:
    """One scan of the sphere-and-plane scene on the small rig (320 x 256, 12 frames) into
    `folder`/s, with `scan`'s options (e.g. level="none")."""
    with open_rig(RigConfig.load(small_rig_toml(folder)), scene=SCENE) as rig:
        scan(rig, PATTERNS, folder / "s", **scan_options)
    return folder / "s"


def edit_manifest(root: Path, edit: Callable[[dict], Any]) -> None:
    """`edit` changes the manifest in place (or returns what to write instead: a JSON list)."""
    m = json.loads((root / MANIFEST).read_text())
    out = edit(m)
    (root / MANIFEST).write_text(json.dumps(out if isinstance(out, list) and out == [m] else m))


def frame(root: Path, k: int) -> Path:
    """The session's frame number `k`."""
    return root / "frames" / f"frame_{k:03d}.png"


def one_error_line(stderr: str) -> str:
    """The one `slscan decode: error` line of `stderr` (no traceback allowed)."""
    lines = [ln for ln in stderr.splitlines() if ln.strip() and "slscan decode: error" in ln]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]
