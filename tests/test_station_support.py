"""Shared pieces of the station tests (no tests here): a small simulated bench, a station
config around it, and a test double of the measuring step."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Sequence

from scanner.config import CONFIG_DIR
from scanner.rig import DEFAULT_RIG
from scanner.session import Session
from scanner.station.measure import MeasuredValue, MeasurementResult
from scanner.station.program import PartProgram
from sim.station_parts import TRUTH_FILE

DEMO_PROGRAM = CONFIG_DIR / "parts" / "demo_part.toml"
TRUTH_GAUGE = "test_station_support:TruthGauge"


class TruthGauge:
    """Test double of the measuring step: returns the simulated part's imposed defects
    (`sim_part.json`, written into each session by the simulated bench) as if measured.
    It measures nothing, so tests using it check the station's loop, storage, views and
    verdict logic, never a measurement; measured verdicts are tested through the inspection
    adapter."""

    name = "truth-gauge (test double)"

    def unavailable(self) -> str | None:
        return None

    def measure(self, sessions: Sequence[Session], program: PartProgram) -> MeasurementResult:
        truth = json.loads((sessions[0].root / TRUTH_FILE).read_text())["imposed_mm"]
        points = json.loads((sessions[0].outputs / "result.json").read_text())["points"]
        return MeasurementResult(True, tuple(MeasuredValue(c.name, truth[c.name], points) for c in program.characteristics))


def small_rig(folder: Path, width: int = 320, height: int = 256) -> Path:
    """The bench rig with a smaller camera (same lens field of view), written into `folder`."""
    text = DEFAULT_RIG.read_text().replace("width = 1280", f"width = {width}").replace("height = 1024",
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
