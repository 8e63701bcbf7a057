"""Foreign captures of a plane on a synthetic rig (320 x 256 camera), as the import tests
shoot them: what the camera sees of a pattern's rows, and frames written as files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from scanner.config import CONFIG_DIR
from sim.foreign_patterns import capture
from slscan.commands.bench.import_ import plane_coordinates, synthetic_rig

CONFIG = CONFIG_DIR / "patterns"  # the shipped pattern descriptions
RIG = synthetic_rig(camera=(320, 256))
PROJ = RIG.projector.size
DEPTH, UV = plane_coordinates(RIG)
U = UV[..., 0]
LIT = (UV[..., 1] > -0.5) & (UV[..., 1] < PROJ[1] - 0.5)  # the projector's rows reach these pixels


def shoot(rows: np.ndarray, coordinate: np.ndarray = U, **kwargs) -> np.ndarray:
    """What the camera sees of `rows` on the plane."""
    return capture(rows, coordinate, lit=LIT, **kwargs)


def write_frames(folder: Path, stack: np.ndarray, names: list[str]) -> None:
    """`stack`'s frames as image files `names` in a new `folder` (the format from each name)."""
    folder.mkdir()
    for img, name in zip(stack, names):
        assert cv2.imwrite(str(folder / name), img)
