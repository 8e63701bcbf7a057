"""From one captured board pose to correspondences: board points, their camera pixels and
their projector pixels.

A `View` is what a pose yields whatever captured it: the camera image of the board under
uniform light and, per camera pixel, the decoded projector coordinates (phase shift in both
orientations with their precision weights, or Gray code). `correspond` finds the board and
each corner's projector pixel (local fits of the decoded coordinates) and refuses a view that does not show
the board or the projector pattern, saying which.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.board import Board
from calibration.correspond import ProjectorCorners, local_projector_points
from calibration.detect import Detection, corner_spacing_px, detect
from calibration.errors import DetectionError
from calibration.intrinsics import ViewPoints

FIT_WINDOW = 0.6  # local fit window radius, as a fraction of the corner spacing
MAX_FIT_WINDOW_PX = 60.0
MIN_PROJECTOR_FRACTION = 0.5  # of the detected corners; below this the projector pattern is missing


@dataclass(frozen=True, eq=False)
class View:
    """One board pose: `image` (H, W) under uniform light, projector coordinate maps `u`, `v`
    (H, W, projector pixels, NaN where not decoded) and optional precision weights."""

    name: str
    image: np.ndarray
    u: np.ndarray
    v: np.ndarray
    weight_u: np.ndarray | None = None
    weight_v: np.ndarray | None = None

    @property
    def size(self) -> tuple[int, int]:
        return (self.image.shape[1], self.image.shape[0])


@dataclass(frozen=True, eq=False)
class Correspondence:
    """The board points seen in one view: by the camera (every detected corner) and by the
    projector (the corners whose projector pixel was found)."""

    name: str
    detection: Detection
    camera: ViewPoints
    projector: ViewPoints
    projector_corners: ProjectorCorners


def correspond(board: Board, view: View, index: int) -> Correspondence:
    """Detect the board in `view` and find its corners' projector pixels; DetectionError
    (naming the view) when the board or the projector pattern is missing."""
    where = f"{index} ({view.name})"
    if view.u.shape != view.image.shape or view.v.shape != view.image.shape:
        raise DetectionError(where, f"projector maps {view.u.shape} do not match the image {view.image.shape}")
    found = detect(board, view.image)
    if found is None:
        raise DetectionError(where, f"{board.describe()} not found in the camera image; check that the whole board "
                                    f"is in view and lit, and that the board description matches the printed board "
                                    f"(count its inner corners)")
    radius = min(FIT_WINDOW * corner_spacing_px(found.image_points), MAX_FIT_WINDOW_PX)
    pc = local_projector_points(found.image_points, view.u, view.v, radius, view.weight_u, view.weight_v)
    if pc.found.sum() < MIN_PROJECTOR_FRACTION * len(found):
        raise DetectionError(where, f"the projector pattern is missing on the board: {int(pc.found.sum())} of "
                                    f"{len(found)} corners have decoded projector coordinates around them; check "
                                    f"that the projector lights the whole board and that the capture holds every "
                                    f"pattern frame")
    obj = board.object_points()[found.ids]
    return Correspondence(view.name, found, ViewPoints(obj, found.image_points),
                          ViewPoints(obj[pc.found], pc.points[pc.found]), pc)
