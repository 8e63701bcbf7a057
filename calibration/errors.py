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


class PoseRefused(CalibrationError):
    """A board pose whose residuals the other poses' noise cannot explain (`calibration.pose_gate`):
    the capture is refused as input (a detection gone wrong), not saved as a calibration.

    `poses` lists the failing poses (indices into the capture), worst first."""

    def __init__(self, problem: str, poses: list[int]) -> None:
        super().__init__(problem)
        self.poses = list(poses)
