"""Calibration targets: their description (TOML), model points and printable image.

Three kinds, all planar with their points on the board's z = 0 plane (mm):

    chessboard          `inner_corners = [C, R]`: C x R inner corners of a board of
                        (C+1) x (R+1) squares of `square_mm`; found with OpenCV's
                        sector-based detector. Point (c, r) is at (c·s, r·s).
    charuco             a chessboard of the same inner corners with ArUco markers of
                        `marker_mm` in its white squares (`dictionary`, e.g. "DICT_5X5_100"):
                        every corner is identified, so partial views are usable.
    circles_asymmetric  `inner_corners = [C, R]`: R rows of C dark circles of `circle_mm`,
                        odd rows shifted by half a step; point (c, r) is at ((2c + r mod 2)·s, r·s)
                        with s = `square_mm` (OpenCV's convention).

Board TOML (every length in mm):

    name = "sim-chess-9x7"
    type = "chessboard"          # chessboard | charuco | circles_asymmetric
    inner_corners = [9, 7]       # columns x rows of points
    square_mm = 8.0
    margin_mm = 8.0              # white border around the pattern (image and simulated board)
    # marker_mm = 6.0            # charuco only
    # dictionary = "DICT_5X5_100"  # charuco only
    # circle_mm = 4.0            # circles_asymmetric only

The board frame: x along a row of points, y down the rows, z into the board (OpenCV's
convention, so a board facing the camera has z roughly along the camera's z). The printed
image puts the board frame's origin at `image_origin_mm` from its top-left corner.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np
from pydantic import field_validator

from calibration.errors import BoardError
from scanner import schema
from scanner.config import load_toml

BoardKind = Literal["chessboard", "charuco", "circles_asymmetric"]
KINDS: tuple[str, ...] = get_args(BoardKind)
BLACK_ALBEDO = 0.05  # printed black and white, as reflectance
WHITE_ALBEDO = 0.85


class BoardFile(schema.Schema):
    """A board TOML as typed keys (lengths in mm); `Board.validate` adds the printing rules."""

    name: schema.Str = "board"
    type: BoardKind
    inner_corners: schema.Vector2
    square_mm: schema.PositiveFloat
    margin_mm: schema.NonNegativeFloat = 0.0
    marker_mm: schema.PositiveFloat | None = None
    dictionary: schema.Str | None = None
    circle_mm: schema.PositiveFloat | None = None

    @field_validator("inner_corners")
    @classmethod
    def _whole(cls, v: list[float]) -> list[float]:
        if any(x != int(x) or not 2 <= x <= 1000 for x in v):
            raise ValueError(f"expected two whole numbers of points from 2 to 1000, got {v}")
        return v


@dataclass(frozen=True)
class Board:
    """A planar calibration target (see the module docstring)."""

    kind: str
    columns: int
    rows: int
    square_mm: float
    margin_mm: float = 0.0
    marker_mm: float | None = None
    dictionary: str | None = None
    circle_mm: float | None = None
    name: str = "board"

    def __post_init__(self) -> None:
        self.validate("board")

    def validate(self, where: object) -> None:
        if self.kind not in KINDS:
            raise BoardError(f"{where}: type '{self.kind}' is not one of {KINDS}")
        if self.columns < 2 or self.rows < 2:
            raise BoardError(f"{where}: inner_corners must be at least [2, 2], got [{self.columns}, {self.rows}]")
        if not self.square_mm > 0 or self.margin_mm < 0:
            raise BoardError(f"{where}: square_mm must be > 0 and margin_mm >= 0")
        if self.kind == "charuco":
            if self.marker_mm is None or not 0 < self.marker_mm < self.square_mm:
                raise BoardError(f"{where}: a charuco board needs 0 < marker_mm < square_mm, got {self.marker_mm}")
            if self.dictionary is None or not hasattr(cv2.aruco, self.dictionary):
                raise BoardError(f"{where}: a charuco board needs dictionary = one of OpenCV's DICT_* names, "
                                 f"got {self.dictionary!r}")
        if self.kind == "circles_asymmetric" and (self.circle_mm is None or not 0 < self.circle_mm < self.square_mm):
            raise BoardError(f"{where}: circles need 0 < circle_mm < square_mm (the spacing), got {self.circle_mm}")

    # ------------------------------------------------------------------ description

    @classmethod
    def from_dict(cls, d: Any, where: str | Path = "board") -> Board:
        """A board described by `d` (a board TOML, a capture's board): keys known and typed
        (`BoardFile`), then the printing rules (`validate`)."""
        f = schema.parse(BoardFile, d, where)
        board = cls.__new__(cls)
        values = dict(kind=f.type, columns=int(f.inner_corners[0]), rows=int(f.inner_corners[1]),
                      square_mm=f.square_mm, margin_mm=f.margin_mm, marker_mm=f.marker_mm, dictionary=f.dictionary,
                      circle_mm=f.circle_mm, name=f.name)
        for k, v in values.items():
            object.__setattr__(board, k, v)
        board.validate(where)
        return board

    @classmethod
    def load(cls, path: str | Path) -> Board:
        path = Path(path)
        d = load_toml(path)
        d.setdefault("name", path.stem)
        return cls.from_dict(d, path)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "type": self.kind, "inner_corners": [self.columns, self.rows],
                             "square_mm": self.square_mm, "margin_mm": self.margin_mm}
        for k in ("marker_mm", "dictionary", "circle_mm"):
            if getattr(self, k) is not None:
                d[k] = getattr(self, k)
        return d

    def describe(self) -> str:
        return (f"{self.kind} '{self.name}', {self.columns} x {self.rows} points, "
                f"{'spacing' if self.kind == 'circles_asymmetric' else 'squares'} {self.square_mm:g} mm")

    # ------------------------------------------------------------------ geometry

    @property
    def n_points(self) -> int:
        return self.columns * self.rows

    def _circle_mm(self) -> float:
        """The circles' diameter (mm); `validate` makes sure a circles board has one."""
        if self.circle_mm is None:
            raise BoardError(f"board '{self.name}' ({self.kind}) has no circle_mm")
        return self.circle_mm

    def object_points(self) -> np.ndarray:
        """(N, 3) float64 model points in the board frame (mm), point id = r·C + c."""
        r, c = np.divmod(np.arange(self.n_points), self.columns)
        x = (2 * c + r % 2) if self.kind == "circles_asymmetric" else c
        return np.stack([x * self.square_mm, r * self.square_mm, np.zeros(self.n_points)], axis=1)

    @property
    def pattern_extent_mm(self) -> tuple[float, float, float, float]:
        """(x0, y0, x1, y1): the printed pattern's outline in the board frame, without margin."""
        s = self.square_mm
        if self.kind == "circles_asymmetric":
            r = self._circle_mm() / 2
            return (-r, -r, (2 * self.columns - 1) * s + r, (self.rows - 1) * s + r)
        return (-s, -s, self.columns * s, self.rows * s)

    @property
    def size_mm(self) -> tuple[float, float]:
        """Outer size (width, height) of the printed board, margin included."""
        x0, y0, x1, y1 = self.pattern_extent_mm
        return (x1 - x0 + 2 * self.margin_mm, y1 - y0 + 2 * self.margin_mm)

    @property
    def image_origin_mm(self) -> tuple[float, float]:
        """Position of the board frame's origin from the printed board's top-left corner."""
        x0, y0, _, _ = self.pattern_extent_mm
        return (self.margin_mm - x0, self.margin_mm - y0)

    @property
    def centre_mm(self) -> np.ndarray:
        """Centre of the printed board in the board frame (mm, z = 0)."""
        w, h = self.size_mm
        ox, oy = self.image_origin_mm
        return np.array([w / 2 - ox, h / 2 - oy, 0.0])

    def symmetries(self) -> list[np.ndarray]:
        """The in-plane turns (4, 4, board frame) other than the identity that map the printed
        pattern onto itself: a detector that finds such a board cannot tell which of these
        labellings it saw (OpenCV orders the points by how they lie in the image), so two
        cameras may label one pose differently. A chessboard has a half turn when C + R is even
        (its corner squares' colours then repeat), quarter turns when also square and the turn
        keeps the colours; a circle grid when its points map onto themselves; ChArUco none."""
        if self.kind == "charuco":
            return []
        points = self.object_points()[:, :2]
        centre = (points.min(axis=0) + points.max(axis=0)) / 2
        squares = (np.arange(self.rows + 1)[:, None] + np.arange(self.columns + 1)[None, :]) % 2
        keys = {tuple(k) for k in np.round(points, 6)}
        out = []
        for k in (1, 2, 3):
            c, s = np.round(np.cos(k * np.pi / 2)), np.round(np.sin(k * np.pi / 2))
            R = np.array([[c, -s], [s, c]])
            turned = (points - centre) @ R.T + centre
            if {tuple(p) for p in np.round(turned, 6)} != keys:
                continue
            if self.kind == "chessboard" and not np.array_equal(np.rot90(squares, k), squares):
                continue
            T = np.eye(4)
            T[:2, :2], T[:2, 3] = R, centre - R @ centre
            out.append(T)
        return out

    # ------------------------------------------------------------------ image

    def image(self, px_per_mm: float, black: float = BLACK_ALBEDO, white: float = WHITE_ALBEDO) -> np.ndarray:
        """The printed board as a reflectance image (H, W) float32, `px_per_mm` texels per mm.

        Chessboard and ChArUco squares fall on texel boundaries when square and margin are
        whole numbers of texels (BoardError otherwise), so edges are exact; circles are
        area-sampled 4 x 4 per texel."""
        w_mm, h_mm = self.size_mm
        W, H = round(w_mm * px_per_mm), round(h_mm * px_per_mm)
        ox, oy = self.image_origin_mm
        if self.kind == "circles_asymmetric":
            ss = 4
            u = (np.arange(W * ss) + 0.5) / (ss * px_per_mm) - ox
            v = (np.arange(H * ss) + 0.5) / (ss * px_per_mm) - oy
            dark = np.zeros((H * ss, W * ss), dtype=bool)
            circle = self._circle_mm()
            r2 = (circle / 2) ** 2
            for x, y, _ in self.object_points():  # a loop over the board's circles, each on its own window
                cols = np.flatnonzero(np.abs(u - x) <= circle)
                rows = np.flatnonzero(np.abs(v - y) <= circle)
                dark[np.ix_(rows, cols)] |= ((u[cols][None, :] - x) ** 2 + (v[rows][:, None] - y) ** 2) <= r2
            cover = dark.reshape(H, ss, W, ss).mean(axis=(1, 3))
            return (white + (black - white) * cover).astype(np.float32)
        step = self.square_mm * px_per_mm
        margin = self.margin_mm * px_per_mm
        if abs(step - round(step)) > 1e-6 or abs(margin - round(margin)) > 1e-6:
            raise BoardError(f"board '{self.name}': square {self.square_mm} mm and margin {self.margin_mm} mm must be "
                             f"whole numbers of texels at {px_per_mm} px/mm for exact edges; choose another density")
        step, margin = round(step), round(margin)
        if self.kind == "charuco":
            board = self.opencv_charuco()
            img = board.generateImage((W, H), marginSize=margin, borderBits=1)
            return (black + (white - black) * (img.astype(np.float32) / 255.0)).astype(np.float32)
        nx, ny = self.columns + 1, self.rows + 1
        squares = ((np.arange(ny)[:, None] + np.arange(nx)[None, :]) % 2 == 0)
        img = np.full((H, W), white, dtype=np.float32)
        block = np.where(np.kron(squares, np.ones((step, step), dtype=bool)), black, white)
        img[margin:margin + ny * step, margin:margin + nx * step] = block
        return img

    def texture_density(self, min_px_per_mm: float) -> float:
        """The smallest texel density (px/mm) of at least `min_px_per_mm` at which squares and
        margin are whole numbers of texels (for `image`)."""
        for ppm in range(max(1, int(np.ceil(min_px_per_mm))), int(np.ceil(min_px_per_mm)) + 1000):
            if all(abs(v * ppm - round(v * ppm)) < 1e-6 for v in (self.square_mm, self.margin_mm)):
                return float(ppm)
        raise BoardError(f"board '{self.name}': no texel density near {min_px_per_mm:.1f} px/mm makes square "
                         f"{self.square_mm} mm and margin {self.margin_mm} mm whole numbers of texels")

    def opencv_charuco(self) -> Any:
        """The matching `cv2.aruco.CharucoBoard` (charuco boards only)."""
        if self.kind != "charuco":
            raise BoardError(f"board '{self.name}' is a {self.kind}, not a charuco board")
        if self.marker_mm is None or self.dictionary is None:  # `validate` makes sure a charuco board has both
            raise BoardError(f"board '{self.name}' (charuco) needs marker_mm and dictionary")
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.columns + 1, self.rows + 1), self.square_mm, self.marker_mm, dictionary)
