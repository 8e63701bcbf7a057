"""The scanner's exception hierarchy.

Every message says what failed, where (file, key, device, frame index) and, where it can,
what the user can do about it.
"""

from __future__ import annotations


class ScannerError(Exception):
    """Base of every error raised by the scanner core."""


class ConfigError(ScannerError):
    """A rig, scene or pattern configuration is missing, unreadable or invalid."""

    def __init__(self, path: object, key: str | None, problem: str) -> None:
        where = f"{path}" + (f", key '{key}'" if key else "")
        super().__init__(f"{where}: {problem}")
        self.path = path
        self.key = key
        self.problem = problem


class DeviceError(ScannerError):
    """A device failed or refused an operation."""

    def __init__(self, device: str, problem: str) -> None:
        super().__init__(f"{device}: {problem}")
        self.device = device


def _timeout_message(what: str, timeout_s: float | None, hint: str) -> str:
    return what + (f" after {timeout_s:.3g} s" if timeout_s is not None else "") + (f"; {hint}" if hint else "")


class WaitTimeout(DeviceError):
    """The caller stopped waiting: `awaited` (a frame, the end of a sequence) had not happened
    within the caller's `timeout_s`. Nothing is known to be wrong with the device and the
    awaited event may still come: a later wait can succeed."""

    def __init__(self, device: str, awaited: str, timeout_s: float, hint: str = "") -> None:
        super().__init__(device, _timeout_message(f"stopped waiting for {awaited}", timeout_s, hint))
        self.awaited = awaited
        self.timeout_s = timeout_s
        self.hint = hint


class DeviceTimeout(DeviceError):
    """The device timed out: it did not answer, or did not finish `awaited`, within the time it
    must (a command's reply, a validation, a sequence's deadline); the operation failed and the
    driver has reset what it must (a link out of step is reopened at the next call).
    `timeout_s` is None where the device reported the timeout without saying how long."""

    def __init__(self, device: str, awaited: str, timeout_s: float | None, hint: str = "") -> None:
        super().__init__(device, _timeout_message(f"device timeout: {awaited}", timeout_s, hint))
        self.awaited = awaited
        self.timeout_s = timeout_s
        self.hint = hint


class DeviceDisconnected(DeviceError):
    """The device is gone (unplugged, powered off, or shut down)."""


class UnsupportedSetting(DeviceError):
    """The device cannot take the requested setting (value out of range or feature absent)."""


class OutOfTravel(UnsupportedSetting):
    """A stage move was refused: its target lies outside an axis's travel (nothing moved)."""


class NotHomed(DeviceError):
    """A stage axis that must be homed first was asked to move before its homing cycle."""


class StageAlarm(DeviceError):
    """A stage controller raised an alarm (a limit switch hit, a failed homing): it stopped
    and locks out motion until it is homed or unlocked."""


class FrameError(DeviceError):
    """A frame arrived wrong: the sequence can no longer be trusted."""

    def __init__(self, device: str, problem: str, expected_index: int, got_index: int | None) -> None:
        super().__init__(device, problem)
        self.expected_index = expected_index
        self.got_index = got_index


class FrameDropped(FrameError):
    """A frame of the sequence never arrived; a later one did."""


class FrameOutOfOrder(FrameError):
    """A frame arrived with the wrong index or pattern (including a repeated stale frame)."""


class DecodeError(ScannerError):
    """Fringe images cannot be decoded (wrong count, wrong size, inconsistent pattern set)."""


class SessionError(ScannerError):
    """A session folder is missing, unreadable or inconsistent."""


class IncompleteSession(SessionError):
    """A session has no complete manifest: the scan was interrupted or failed."""


class CalibrationFileError(ScannerError):
    """A calibration file is unreadable, of another version, or made for another rig."""

    def __init__(self, path: object, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path


class Terminated(KeyboardInterrupt):
    """The process was asked to stop (SIGTERM): handled everywhere as Ctrl-C is (the cycle
    or capture ends as interrupted, what was captured is kept, exit code 130)."""

    def __init__(self, signal_name: str = "SIGTERM") -> None:
        super().__init__(f"terminated ({signal_name})")
