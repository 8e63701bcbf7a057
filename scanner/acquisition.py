"""Acquisition: show pattern k, trigger, grab, check that the frame is frame k, store it.

Three wirings (rig config `rig.trigger`): `software` (show, software-trigger, grab, per
pattern), `projector` (the projector runs the sequence and its trigger output exposes the
camera) and `trigger_box` (a pulse train advances the projector and exposes the camera).
A frame whose counter skips is a dropped frame; one that repeats an index or carries the
wrong pattern is out of order; either stops the scan rather than decoding a mixed
sequence. Every frame checked is stored before the next is awaited.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .devices import Frame
from .errors import FrameDropped, FrameError, FrameOutOfOrder
from .patterns import PatternSet
from .rig import Rig

FrameCallback = Callable[[int, Frame], None]


@dataclass(frozen=True)
class AcquisitionSettings:
    """`period_s`: pattern period for hardware-sequenced wirings; `timeout_s`: longest
    wait for any one frame."""

    period_s: float
    timeout_s: float

    @classmethod
    def for_rig(cls, rig: Rig) -> AcquisitionSettings:
        return cls(rig.config.period_s, rig.config.timeout_s)


def check_frame(k: int, frame: Frame, camera_name: str, shape: tuple[int, int], bit_depth: int) -> None:
    """Raise if `frame` is not a good frame k of this sequence."""
    if frame.index > k:
        raise FrameDropped(camera_name, f"frame {k} was dropped: the next frame arrived with index {frame.index}",
                           k, frame.index)
    if frame.index < k:
        raise FrameOutOfOrder(camera_name, f"expected frame {k}, got index {frame.index} again (stale buffer)",
                              k, frame.index)
    if frame.pattern_index is not None and frame.pattern_index != k:
        raise FrameOutOfOrder(camera_name, f"frame {k} was exposed under pattern {frame.pattern_index}, not {k}",
                              k, frame.index)
    if frame.image.shape != shape:
        raise FrameError(camera_name, f"frame {k} is {frame.image.shape[1]}x{frame.image.shape[0]}, the camera is "
                                      f"configured for {shape[1]}x{shape[0]}", k, frame.index)
    if frame.bit_depth != bit_depth or int(frame.image.max(initial=0)) >= 2 ** bit_depth:
        raise FrameError(camera_name, f"frame {k} does not hold {bit_depth}-bit data", k, frame.index)


def acquire(rig: Rig, patterns: PatternSet, settings: AcquisitionSettings, on_frame: FrameCallback) -> np.ndarray:
    """Capture every pattern of `patterns`; `on_frame(k, frame)` is called (to store and
    log it) as soon as frame k has been checked. Returns the (N, H, W) stack."""
    cam, proj = rig.camera, rig.projector
    images = patterns.render(proj.width, proj.height, rig.model.projector_gamma)
    n = len(images)
    proj.load_patterns(images)
    cam.arm(n)
    shape = (cam.height, cam.width)
    stack: np.ndarray | None = None
    wiring = rig.config.trigger
    try:
        if wiring == "projector":
            proj.run_sequence(settings.period_s)
        elif wiring == "trigger_box":
            if rig.trigger is None:
                raise FrameError(cam.name, "rig is wired for a trigger box but none is open", 0, None)
            rig.trigger.arm(n, settings.period_s)
            rig.trigger.start()
        for k in range(n):
            if wiring == "software":
                proj.show(k)
                cam.trigger()
            frame = cam.grab(settings.timeout_s)
            check_frame(k, frame, cam.name, shape, cam.bit_depth)
            if stack is None:
                stack = np.empty((n, *shape), dtype=frame.image.dtype)
            stack[k] = frame.image
            on_frame(k, frame)
    finally:
        proj.stop_sequence()
        if rig.trigger is not None:
            rig.trigger.stop()
        cam.disarm()
        if not proj.is_shut_down:
            proj.blank()
    assert stack is not None
    return stack
