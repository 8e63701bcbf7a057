"""Where the board's points have fallen so far, and which poses are still needed.

A calibration is only as good as its views: corners near every edge and corner of both
images pin down distortion and the principal point; boards tilted both ways about both
axes pin down the focal lengths. `Coverage` counts points on a grid over an image;
`needed_poses` turns the coverage of both devices and the tilts seen so far into advice.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

GRID = (8, 6)  # cells across, down
ZONES = (("top", "middle", "bottom"), ("left", "centre", "right"))
MIN_TILT_DEG = 15.0  # a view counts as tilted about an axis beyond this
ZONE_FILL = 0.5  # a zone of the image is covered when this fraction of its cells hold points


@dataclass(eq=False)
class Coverage:
    """Point counts on a GRID over an image of `size` = (width, height) px."""

    size: tuple[int, int]
    counts: np.ndarray = field(default_factory=lambda: np.zeros(GRID[::-1], dtype=np.int64))

    def add(self, points: np.ndarray) -> None:
        """Count points (N, 2) (pixels outside the image are ignored)."""
        w, h = self.size
        ix = np.floor(points[:, 0] / w * GRID[0]).astype(int)
        iy = np.floor(points[:, 1] / h * GRID[1]).astype(int)
        ok = (ix >= 0) & (ix < GRID[0]) & (iy >= 0) & (iy < GRID[1])
        np.add.at(self.counts, (iy[ok], ix[ok]), 1)

    @property
    def fraction(self) -> float:
        """Fraction of grid cells holding at least one point."""
        return float((self.counts > 0).mean())

    def empty_zones(self) -> list[str]:
        """Names of the 3 x 3 zones of the image ('top left', ...) not yet covered (fewer
        than ZONE_FILL of their cells hold points)."""
        out = []
        rows = np.array_split(np.arange(GRID[1]), 3)
        cols = np.array_split(np.arange(GRID[0]), 3)
        for i, r in enumerate(rows):
            for j, c in enumerate(cols):
                if (self.counts[np.ix_(r, c)] > 0).mean() < ZONE_FILL:
                    v, hz = ZONES[0][i], ZONES[1][j]
                    out.append("centre" if (v, hz) == ("middle", "centre") else
                               hz if v == "middle" else v if hz == "centre" else f"{v} {hz}")
        return out

    def image(self, scale: int = 16) -> np.ndarray:
        """The counts as an 8-bit heat map (cells `scale` px wide), 0 = empty."""
        c = self.counts.astype(np.float64)
        img = np.where(c > 0, 64 + 191 * c / max(c.max(), 1), 0).astype(np.uint8)
        return np.kron(img, np.ones((scale, scale), dtype=np.uint8))


def tilt_deg(board_to_camera: np.ndarray) -> tuple[float, float]:
    """Tilts (degrees) of a board about the camera's x and y axes: the angles of its normal
    (board z, pointing away from the camera) in the y-z and x-z planes. Negative about x:
    the top edge is farther away; negative about y: the right edge is farther away."""
    n = board_to_camera[:3, 2]
    n = n if n[2] > 0 else -n
    return float(np.degrees(np.arctan2(n[1], n[2]))), float(np.degrees(np.arctan2(n[0], n[2])))


_TILT_ADVICE = ((0, -1, "top edge"), (0, 1, "bottom edge"), (1, -1, "right edge"), (1, 1, "left edge"))


def needed_poses(camera: Coverage, projector: Coverage, tilts: list[tuple[float, float]], have: int,
                 want: int) -> list[str]:
    """Advice on the poses still needed (empty: the set is complete)."""
    out = []
    if have < want:
        out.append(f"{want - have} more pose(s)")
    for name, cov in (("camera", camera), ("projector", projector)):
        zones = cov.empty_zones()
        if zones:
            out.append(f"points in the {', '.join(zones)} of the {name} image")
    t = np.array(tilts).reshape(-1, 2)
    for col, sign, edge in _TILT_ADVICE:
        if not (sign * t[:, col] > MIN_TILT_DEG).any():
            out.append(f"a board turned with its {edge} away from the camera (> {MIN_TILT_DEG:.0f} degrees)")
    return out
