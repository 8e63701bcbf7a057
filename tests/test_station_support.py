"""Shared pieces of the station tests (no tests here): a small simulated bench and a station
config around it, measuring with the simulator's truth (`measure.SimulatorTruth`) unless told."""

from __future__ import annotations

import json
import re
from pathlib import Path

from scanner.config import CONFIG_DIR
from scanner.rig import DEFAULT_RIG

DEMO_PROGRAM = CONFIG_DIR / "parts" / "demo_part.toml"
TRUTH_GAUGE = "simulator-truth"  # measures nothing: reports the simulated part's imposed defects


def small_rig(folder: Path, width: int = 320, height: int = 256, rig: Path = DEFAULT_RIG) -> Path:
    """The bench rig (or `rig`) with a smaller camera (same lens field of view), written into `folder`."""
    text = rig.read_text().replace("width = 1280", f"width = {width}").replace("height = 1024",
                                                                                       f"height = {height}")
    text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    path = folder / "rig.toml"
    path.write_text(text)
    return path


def station_config(folder: Path, database: str = "", measurement: str = TRUTH_GAUGE, rig: Path | None = None,
                   **station_keys: object) -> Path:
    """A station config in `folder`: the small rig, data in `folder/data`."""
    rig = rig or small_rig(folder)
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
