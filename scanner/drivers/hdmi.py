"""An HDMI / DisplayPort projector: a fullscreen window on a chosen display, vsync-locked.

    pip install slscan[hdmi]        # pygame (SDL2)

Each present waits for the display's vertical sync, so a pattern is shown for a known
number of refresh periods. After a pattern's first present the window presents it
`latency_frames` more times before it counts as on display (the display chain's delay);
only then does `show` return or a sequence fire its trigger output.

Wirings: `software` (show, then the camera is triggered), and `projector`: the window
runs the sequence itself on a thread, holding each pattern round(period x refresh)
refreshes, and calls its trigger-output callbacks (`connect_trigger_out`, e.g. a camera's
software trigger) once each pattern is on display. The status `run_sequence` returns
finishes when the last pattern has been held and the window is dark again, or fails with
the error that ended the thread (a display that failed, a callback that raised): the
acquisition then reports that error rather than a camera that saw no frame. An HDMI
projector has no trigger input, so the `trigger_box` wiring is refused by the rig factory.

`HdmiDisplay` alone is also the video source of a LightCrafter in video-port mode.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Annotated, Any, Protocol

import numpy as np
from pydantic import Field

from scanner.devices import Projector
from scanner.drivers.registry import Driver, Triggers, register
from scanner.errors import ConfigError, DeviceError, ScannerError, UnsupportedSetting
from scanner.schema import Int, PositiveFloat, Schema
from scanner.status import Status

if TYPE_CHECKING:
    from scanner.rig import RigConfig

log = logging.getLogger(__name__)

VSYNC_TOLERANCE = 0.2  # measured refresh period may differ this much from the configured one
_CHECK_FRAMES = 12


class DisplayBackend(Protocol):
    """A fullscreen surface whose `present` returns after the vertical sync that shows it,
    with the time of that sync (monotonic s) as well as the backend knows it."""

    size: tuple[int, int]  # width, height in pixels

    def present(self, rgb: np.ndarray) -> float: ...

    def close(self) -> None: ...


class PygameBackend:
    """Fullscreen window on display `display` through pygame (SDL2) with vsync."""

    def __init__(self, name: str, display: int) -> None:
        try:
            import pygame
        except ImportError:
            raise DeviceError(name, "HDMI projectors need the optional extra: pip install slscan[hdmi]") from None
        self._pg = pygame
        pygame.display.init()
        sizes = pygame.display.get_desktop_sizes()
        if not 0 <= display < len(sizes):
            pygame.display.quit()
            raise DeviceError(name, f"display {display} not found; this desktop has {len(sizes)} "
                                    f"({', '.join(f'{w}x{h}' for w, h in sizes)}); `slscan devices` lists them")
        self.size = sizes[display]
        log.info("%s: fullscreen window on display %d (%dx%d)", name, display, *self.size)
        self._screen = pygame.display.set_mode(self.size, pygame.FULLSCREEN | pygame.SCALED | pygame.NOFRAME,
                                               display=display, vsync=1)
        pygame.mouse.set_visible(False)

    def present(self, rgb: np.ndarray) -> float:
        pg = self._pg
        pg.event.pump()  # keep the window responsive
        pg.surfarray.blit_array(self._screen, np.ascontiguousarray(rgb.transpose(1, 0, 2)))
        pg.display.flip()  # blocks until the vertical sync with vsync=1
        return time.monotonic()  # SDL gives no flip timestamp: the sync has just happened

    def close(self) -> None:
        self._pg.display.quit()


class HdmiDisplay:
    """A vsync-locked fullscreen output showing RGB frames (also a LightCrafter video source)."""

    def __init__(self, backend: DisplayBackend, name: str, refresh_hz: float, latency_frames: int = 2) -> None:
        self.backend = backend
        self.name = name
        self.refresh_hz = refresh_hz
        self.latency_frames = latency_frames
        self.check_vsync()

    def check_vsync(self) -> float:
        """Present black frames and check that presents really wait for the vertical sync
        at `refresh_hz` (a window without vsync would make every timing wrong)."""
        black = np.zeros((self.backend.size[1], self.backend.size[0], 3), np.uint8)
        stamps = [self.backend.present(black) for _ in range(_CHECK_FRAMES)]
        measured = float(np.median(np.diff(stamps)))
        if abs(measured * self.refresh_hz - 1.0) > VSYNC_TOLERANCE:
            raise DeviceError(self.name, f"presents take {measured * 1e3:.2f} ms, not one refresh of "
                                         f"{1e3 / self.refresh_hz:.2f} ms at {self.refresh_hz} Hz: vsync is not in "
                                         f"effect or projector.refresh_hz is wrong (check the display mode)")
        log.debug("%s: vsync checked, %.2f ms per refresh", self.name, measured * 1e3)
        return measured

    def show(self, rgb: np.ndarray, frames: int | None = None, stop: threading.Event | None = None) -> None:
        """Present `rgb` for 1 + latency_frames refreshes (or `frames`), returning once it is
        on display, or at the first refresh after `stop` is set."""
        for _ in range(1 + self.latency_frames if frames is None else frames):
            if stop is not None and stop.is_set():
                return
            self.backend.present(rgb)

    def close(self) -> None:
        self.backend.close()


class HdmiProjector(Projector):
    """8-bit patterns on an `HdmiDisplay` (see the module docstring)."""

    def __init__(self, display: HdmiDisplay, name: str = "hdmi-projector") -> None:
        width, height = display.backend.size
        super().__init__(name, width, height)
        self.display = display
        self._patterns: np.ndarray | None = None
        self._outputs: list[Callable[[], None]] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def connect_trigger_out(self, callback: Callable[[], None]) -> None:
        """Called once each pattern of a running sequence is on display."""
        self._outputs.append(callback)

    def _do_load_patterns(self, patterns: np.ndarray) -> None:
        self._do_stop_sequence()  # a thread outliving its status (past its deadline) stops too
        self._patterns = np.repeat(patterns[..., None], 3, axis=3)

    def _do_show(self, k: int) -> None:
        self._do_stop_sequence()
        assert self._patterns is not None
        self.display.show(self._patterns[k])

    def _do_blank(self) -> None:
        self._do_stop_sequence()
        self.display.show(np.zeros((self.height, self.width, 3), np.uint8))

    def _do_run_sequence(self, period_s: float, on_pattern: Callable[[int], None] | None, status: Status) -> None:
        frames = round(period_s * self.display.refresh_hz)
        if frames <= self.display.latency_frames:
            raise UnsupportedSetting(self.name, f"pattern period {period_s} s is {frames} refreshes at "
                                                f"{self.display.refresh_hz} Hz; it must exceed the display latency "
                                                f"of {self.display.latency_frames} refreshes")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(frames, on_pattern, self._stop, status),
                                        name=f"{self.name}-sequence", daemon=True)
        self._thread.start()

    def _run(self, frames: int, on_pattern: Callable[[int], None] | None, stop: threading.Event,
             status: Status) -> None:
        assert self._patterns is not None
        k = 0
        try:
            for k, image in enumerate(self._patterns):
                self.display.show(image, stop=stop)  # 1 + latency refreshes: now on display
                if stop.is_set():
                    return  # stopped: the base class fails the status
                for cb in self._outputs:
                    cb()
                if on_pattern is not None:
                    on_pattern(k)
                self.display.show(image, frames - 1 - self.display.latency_frames, stop)
            self.display.show(np.zeros_like(self._patterns[0]), 1, stop)
            if stop.is_set():
                return
        except ScannerError as exc:  # a device error (e.g. the camera a trigger output drives): as it is
            status.set_exception(exc)
        except Exception as exc:  # the display failed: say which projector and where
            error = DeviceError(self.name, f"pattern sequence failed at pattern {k}: {type(exc).__name__}: {exc}")
            error.__cause__ = exc
            status.set_exception(error)
        else:
            status.set_finished()

    def _do_stop_sequence(self) -> None:
        self._stop.set()
        thread, self._thread = self._thread, None
        if thread is not None and thread is not threading.current_thread():
            thread.join(5.0)

    def _do_shutdown(self) -> None:
        self._do_stop_sequence()
        self.display.close()
        log.info("%s: window closed", self.name)

    def describe(self) -> dict[str, object]:
        return {**super().describe(), "refresh_hz": self.display.refresh_hz,
                "latency_frames": self.display.latency_frames}


LatencyFrames = Annotated[int, Field(strict=True, ge=0)]


class HdmiSettings(Schema):
    """The [projector] keys of an HDMI projector: `display` its index among the desktop's
    displays, `refresh_hz` its refresh rate (Hz), `latency_frames` the refreshes between a
    present and the image being on screen."""

    display: Int = 1
    refresh_hz: PositiveFloat = 60.0
    latency_frames: LatencyFrames = 2


def open_display(index: int, refresh_hz: float, latency_frames: int, transports: Mapping[str, Any]) -> HdmiDisplay:
    """The fullscreen window on display `index`; transports["display"] replaces its backend."""
    backend = transports.get("display") or PygameBackend("hdmi-projector", index)
    return HdmiDisplay(backend, "hdmi-projector", refresh_hz, latency_frames)


def open_hdmi(config: RigConfig, settings: HdmiSettings, transports: Mapping[str, Any]) -> HdmiProjector:
    """The rig's HDMI projector, its display's mode checked against the rig's size."""
    lens = config.file.projector
    projector = HdmiProjector(open_display(settings.display, settings.refresh_hz, settings.latency_frames, transports),
                              "hdmi-projector")
    if (projector.width, projector.height) != (lens.width, lens.height):
        projector.shutdown()
        raise ConfigError(config.path, "projector.width", f"display {settings.display} is {projector.width}x"
                                                          f"{projector.height}, the rig says {lens.width}x"
                                                          f"{lens.height}; set the display mode or the TOML")
    return projector


DRIVER = register(Driver(
    "projector", "hdmi", "hardware", HdmiSettings, open_hdmi,
    triggers=lambda settings: Triggers(output="call", refusal="an HDMI projector has no trigger input; use "
                                                              "'software' or 'projector'")))
