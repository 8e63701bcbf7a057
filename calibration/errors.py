"""The calibration package's exceptions: every message says what failed, where (file,
view index, key) and what the user can do about it."""

from __future__ import annotations

from scanner.errors import ScannerError


class CalibrationError(ScannerError):
    """Base of every error raised by `calibration`."""


class BoardError(CalibrationError):
    """A board description is missing, invalid, or does not match what the images show."""


class DetectionError(CalibrationError):
    """A view does not show the pattern it should (board not found, projector pattern missing)."""

    def __init__(self, view: int | str, problem: str) -> None:
        super().__init__(f"view {view}: {problem}")
        self.view = view


class NotEnoughData(CalibrationError):
    """Too few usable views or points to solve for the parameters asked for."""


class CalibrationRejected(CalibrationError):
    """A solved calibration fails a quality limit; it is not saved.

    `blame` lists the views (indices) most responsible, worst first."""

    def __init__(self, problem: str, blame: list[int] | None = None) -> None:
        super().__init__(problem)
        self.blame = list(blame or [])
