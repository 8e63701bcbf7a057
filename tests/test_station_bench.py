"""The bench's start input on hardware: the foot switch on the trigger box's input (protocol
2), read through the driver over an emulated serial line; a box or rig without it leaves the
keyboard as the only start and says why. (The simulated bench's switch: test_station_loop.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scanner.config import CONFIG_DIR
from scanner.drivers.testing import Dlpc350Emulator, FakeAcquirer, FakeCapture, TriggerBoxEmulator
from scanner.rig import RigConfig
from slscan.station.hardware_bench import Bench

LCR = CONFIG_DIR / "rigs" / "lightcrafter_uvc_box.toml"


def _rig(tmp_path: Path, trigger: str) -> RigConfig:
    text = LCR.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    text = text.replace('trigger = "software"', f'trigger = "{trigger}"')
    if trigger == "trigger_box":
        text = text.replace('driver = "uvc"', 'driver = "genicam"\ncti = "/x.cti"')
    path = tmp_path / "rig.toml"
    path.write_text(text)
    return RigConfig.load(path)


def _transports(box: TriggerBoxEmulator) -> dict:
    acq = FakeAcquirer(lambda t: np.zeros((720, 1280), np.uint8), 1280, 720)
    return {"projector": Dlpc350Emulator, "camera": lambda: (acq, acq.close), "trigger_box": lambda: box}


def test_foot_switch_on_the_rigs_trigger_box_starts_once_per_press(tmp_path: Path) -> None:
    box = TriggerBoxEmulator()
    box.pressed = 3  # pressed before the station was ready: not a start
    with Bench(_rig(tmp_path, "trigger_box"), transports=_transports(box)) as bench:
        assert not bench.start_pressed() and bench.input_problem == ""
        box.pressed += 1
        assert bench.start_pressed() and not bench.start_pressed()
        box.pressed += 2  # two presses between polls: one start
        assert bench.start_pressed() and not bench.start_pressed()
    assert box.lines.count("PRESSES?") == 6


def test_protocol_1_box_or_no_box_leaves_the_keyboard_and_says_why(tmp_path: Path) -> None:
    old = TriggerBoxEmulator(protocol=1)  # firmware without the input
    with Bench(_rig(tmp_path, "trigger_box"), transports=_transports(old)) as bench:
        assert not bench.start_pressed() and not bench.start_pressed()
        assert bench.input_problem.startswith("foot switch not read: ") and "firmware protocol 1 has no input" \
            in bench.input_problem and "flash firmware/triggerbox" in bench.input_problem
    assert "PRESSES?" not in old.lines
    uvc = {"projector": Dlpc350Emulator, "camera": lambda: FakeCapture(lambda t: np.zeros((720, 1280, 3), np.uint8))}
    with Bench(_rig(tmp_path, "software"), transports=uvc) as bench:
        assert not bench.start_pressed()
        assert bench.input_problem == "rig lightcrafter-uvc-box has no trigger box: no foot switch"
