"""Errors of segmentation, instance extraction and their inputs (radius, labels, masks).

They extend the inspection hierarchy (`inspection.errors`); an empty or unusable cloud is
that module's `CloudError`. Every message says what was wrong with which input and, where
it can, what value would work.
"""

from __future__ import annotations

from .errors import InspectionError


class SegmentationError(InspectionError):
    """A cloud cannot be segmented or scored as asked (radius out of range, label arrays
    that do not match)."""


class MaskError(SegmentationError):
    """An instance mask or annotation is unreadable or does not match the camera image."""
