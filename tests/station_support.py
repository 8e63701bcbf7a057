"""Shared pieces of the station tests: a station config around the small simulated bench
(`session_support.small_rig_toml`), measuring with the simulator's truth (`measure.SimulatorTruth`) unless told."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from session_support import small_rig_toml

from scanner.config import CONFIG_DIR

DEMO_PROGRAM = CONFIG_DIR / "parts" / "demo_part.toml"
TRUTH_GAUGE = "simulator-truth"  # measures nothing: reports the simulated part's imposed defects


def station_config(folder: Path, database: str = "", measurement: str = TRUTH_GAUGE, rig: Path | None = None,
                   **station_keys: object) -> Path:
    """A station config in `folder`: the small rig, data in `folder/data`."""
    rig = rig or small_rig_toml(folder)
    lines = ["[station]", 'name = "test-bench"', f'rig = "{rig}"', f'data_dir = "{folder / "data"}"',
             f'database = "{database}"', f'measurement = "{measurement}"']
    lines += [f"{k} = {json.dumps(v)}" for k, v in station_keys.items()]
    path = folder / "station.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def program_copy(folder: Path, edit: tuple[str, str] | None = None, **subs: str) -> Path:
    """The demo program copied into `folder` (CAD and patterns still pointing at config/),
    with `edit` = (old, new) applied once (it must occur)."""
    text = DEMO_PROGRAM.read_text()
    text = text.replace('cad = "demo_part.step"', f'cad = "{CONFIG_DIR / "parts" / "demo_part.step"}"')
    text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    if edit is not None:
        assert edit[0] in text, edit[0]
        text = text.replace(edit[0], edit[1], 1)
    for key, value in subs.items():
        text = re.sub(rf"^{key} = .*$", f"{key} = {value}", text, count=1, flags=re.M)
    path = folder / "program.toml"
    path.write_text(text)
    return path


def face_row(label: str, points: int, note: str = "", status: str = "ok", **figures: Any) -> dict[str, Any]:
    """One face of an inspection report as the station reads it (`inspection.report.FaceRow`
    by its label): `figures` by name (`inspection.figures`), each an `Estimate`, a value in
    mm (U 0) or None (not measured)."""
    from inspection.form import FaceForm
    from inspection.report import FaceRow
    from inspection.uncertainty import Estimate

    estimates = {k: Estimate(v, 0.0) if isinstance(v, float) else v for k, v in figures.items()}
    return {label: FaceRow(label, None, "plane", FaceForm(points, status, note, **estimates))}
