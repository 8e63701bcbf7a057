"""Status objects: the outcome of a long device action that runs on after the call returns.

Modelled on ophyd's `StatusBase`: a projector's pattern sequence or a trigger box's pulse
train is started by a call that returns at once with a `Status`; the device completes it
later, from whatever thread runs the action, with `set_finished()` or `set_exception(exc)`
(the first outcome wins, later ones are ignored). The caller may poll `done`/`success`,
add callbacks, or `wait(timeout_s)`, which raises

  - the action's own exception if it failed (e.g. the error that ended an HDMI projector's
    sequence thread), so it surfaces as itself rather than as a camera that saw no frame;
  - `WaitTimeout` if the caller's `timeout_s` passed first (the action may still finish).

A status made with a `deadline_s` fails by itself with `DeviceTimeout` if the action has not
finished by then: the device was detected to time out, whoever is waiting.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from scanner.errors import DeviceTimeout, WaitTimeout

log = logging.getLogger(__name__)

StatusCallback = Callable[["Status"], None]


class Status:
    """The completion of `action` on `device` (names used in every message)."""

    def __init__(self, device: str, action: str, deadline_s: float | None = None) -> None:
        self.device = device
        self.action = action
        self._lock = threading.Lock()
        self._event = threading.Event()
        self._exception: BaseException | None = None
        self._callbacks: list[StatusCallback] = []
        self._deadline: threading.Timer | None = None
        if deadline_s is not None:
            self._deadline = threading.Timer(deadline_s, self._expire, args=(deadline_s,))
            self._deadline.daemon = True
            self._deadline.start()

    def __repr__(self) -> str:
        state = "running" if not self.done else "finished" if self.success else f"failed ({self._exception})"
        return f"Status({self.device}: {self.action}, {state})"

    @property
    def done(self) -> bool:
        """True once the action has finished, successfully or not."""
        return self._event.is_set()

    @property
    def success(self) -> bool:
        """True once the action has finished without error."""
        return self._event.is_set() and self._exception is None

    def exception(self) -> BaseException | None:
        """The error the action failed with; None while running or after success."""
        return self._exception

    def wait(self, timeout_s: float) -> None:
        """Wait at most `timeout_s` for the action to finish; raise its error if it failed,
        `WaitTimeout` (naming the device and the action) if it is still running."""
        if not timeout_s > 0:
            raise ValueError("timeout_s must be > 0: waits are always finite")
        if not self._event.wait(timeout_s):
            raise WaitTimeout(self.device, self.action, timeout_s, "it is still running")
        if self._exception is not None:
            raise self._exception

    def add_callback(self, callback: StatusCallback) -> None:
        """Call `callback(status)` once when the action finishes (at once if it has)."""
        with self._lock:
            if not self._event.is_set():
                self._callbacks.append(callback)
                return
        self._run(callback)

    def set_finished(self) -> None:
        """The action completed successfully (for the device that runs it)."""
        self._finish(None)

    def set_exception(self, exc: BaseException) -> None:
        """The action failed with `exc` (for the device that runs it)."""
        self._finish(exc)

    def _finish(self, exc: BaseException | None) -> None:
        with self._lock:
            if self._event.is_set():
                return  # the first outcome wins
            self._exception = exc
            self._event.set()
            callbacks, self._callbacks = self._callbacks, []
        if self._deadline is not None:
            self._deadline.cancel()
        if exc is None:
            log.debug("%s: %s finished", self.device, self.action)
        else:
            log.debug("%s: %s failed: %s", self.device, self.action, exc)
        for callback in callbacks:
            self._run(callback)

    def _run(self, callback: StatusCallback) -> None:
        try:
            callback(self)
        except Exception:  # a listener's bug must not break the device thread completing the status
            log.warning("%s: a callback on '%s' raised; ignored", self.device, self.action, exc_info=True)

    def _expire(self, deadline_s: float) -> None:
        self.set_exception(DeviceTimeout(self.device, f"{self.action} not finished", deadline_s,
                                         "the device stopped advancing it"))
