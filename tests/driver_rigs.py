"""Example hardware rigs driven by emulators: the LightCrafter + UVC + trigger box example's
config, edited copies of a rig file, and the emulated transports its drivers open."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scanner.config import CONFIG_DIR
from scanner.drivers.testing import Dlpc350Emulator, FakeAcquirer, FakeCapture, TriggerBoxEmulator
from scanner.rig import RigConfig

LCR = CONFIG_DIR / "rigs" / "lightcrafter_uvc_box.toml"


def variant(tmp: Path, source: Path, *edits: tuple[str, str]) -> RigConfig:
    """`source` copied into `tmp` (patterns still pointing at config/), each edit (old, new)
    applied (it must occur)."""
    text = source.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp / source.name
    path.write_text(text)
    return RigConfig.load(path)


def lcr_transports(acq: FakeAcquirer | None = None) -> dict:
    """The LightCrafter rig's transports, emulated: a 1280 x 720 black camera unless `acq`."""
    cam = (lambda: (acq, acq.close)) if acq else (lambda: FakeCapture(lambda t: np.zeros((720, 1280, 3), np.uint8)))
    return {"projector": Dlpc350Emulator, "camera": cam, "trigger_box": TriggerBoxEmulator}
