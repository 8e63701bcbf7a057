"""Capturing calibration frames on an open rig (real or simulated).

Fringe sequences go through the scanner's own acquisition (`scanner.acquisition.acquire`,
with its frame-order, timing and signature checks), rendered with the projector gamma
the calibration has measured so far. Flat images (white, black, grey levels) are shown and
grabbed in software-triggered lock-step, whatever the rig's trigger wiring, through the same
acquisition (`scanner.acquisition.acquire_images`) and its per-frame checks.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scanner.acquisition import AcquisitionSettings, acquire, acquire_images
from scanner.devices import TriggerMode, TriggerType
from scanner.patterns import PatternSet
from scanner.rig import Rig

WHITE, BLACK = 255, 0


@dataclass(frozen=True, eq=False)
class PoseFrames:
    """One board pose: the board under full white and under black, and the fringe stack."""

    white: np.ndarray
    black: np.ndarray
    fringes: np.ndarray


def show_images(rig: Rig, images: np.ndarray) -> np.ndarray:
    """One camera frame per projector image (N, Hp, Wp) uint8, software-triggered in
    lock-step; the camera's trigger setting is restored afterwards. Returns (N, H, W)."""
    cam = rig.camera
    saved = (cam.trigger_type, cam.trigger_mode)
    cam.set_trigger(TriggerType.SOFTWARE, TriggerMode.ONCE)
    try:
        return acquire_images(rig, images, AcquisitionSettings.for_rig(rig), wiring="software")
    finally:
        cam.set_trigger(*saved)


def capture_fringes(rig: Rig, patterns: PatternSet, gamma: float) -> np.ndarray:
    """The fringe stack of `patterns`, pre-compensated for a projector response `gamma`."""
    compensated = replace(rig, model=replace(rig.model, projector_gamma=gamma))
    return acquire(compensated, patterns, AcquisitionSettings.for_rig(rig), lambda k, frame: None)


def capture_uncompensated(rig: Rig, patterns: PatternSet) -> np.ndarray:
    """The fringe stack of `patterns` rendered for a linear projector (no gamma
    compensation), shown in lock-step: the acquisition's signature check would rightly
    refuse these non-sinusoidal fringes, and showing what they do is the point."""
    p = rig.projector
    return show_images(rig, patterns.render(p.width, p.height, 1.0))


def capture_pose(rig: Rig, patterns: PatternSet, gamma: float) -> PoseFrames:
    """White, black and the fringe stack of the board where it stands now."""
    p = rig.projector
    flats = show_images(rig, np.stack([np.full((p.height, p.width), v, np.uint8) for v in (WHITE, BLACK)]))
    return PoseFrames(flats[0], flats[1], capture_fringes(rig, patterns, gamma))
