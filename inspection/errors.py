"""The inspection package's exception hierarchy.

Every message says what failed, where (file, face, stage) and what the user can do.
A measurement that cannot be trusted raises (or is reported as failed); it is never a number.
"""

from __future__ import annotations

from scanner.errors import ScannerError


class InspectionError(ScannerError):
    """Base of every error raised by the inspection stage."""


class CadError(InspectionError):
    """A CAD file (STEP or mesh) is missing, unreadable, empty or unusable."""

    def __init__(self, path: object, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


class CloudError(InspectionError):
    """A point cloud is missing, unreadable, empty or unusable (too few points, no part)."""

    def __init__(self, source: object, problem: str) -> None:
        super().__init__(f"{source}: {problem}")
        self.source = source
        self.problem = problem


class UnitMismatch(InspectionError):
    """The scan and the model differ in size by a factor that looks like a unit error."""


class RegistrationFailed(InspectionError):
    """No pose of the model explains the scan well enough: the scan is of another part, too
    little of the part is visible, or the model is in other units. `fitness` is the
    fraction of scan points within the inlier distance of the model at the best pose
    found, `rmse_mm` their RMS distance."""

    def __init__(self, problem: str, fitness: float = 0.0, rmse_mm: float = float("nan")) -> None:
        super().__init__(f"registration failed: {problem}")
        self.problem = problem
        self.fitness = fitness
        self.rmse_mm = rmse_mm


class ToleranceError(InspectionError):
    """A tolerance file is unreadable or names faces or keys the model does not have."""


class SegmentationError(InspectionError):
    """A cloud cannot be segmented or scored as asked (radius out of range, label arrays
    that do not match)."""


class MaskError(SegmentationError):
    """An instance mask or annotation is unreadable or does not match the camera image."""
