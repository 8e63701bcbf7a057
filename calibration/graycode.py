"""Decoding OpenCV's Gray-code pattern layout (`structured_light.GrayCodePattern`), which
other calibration tools capture with, without OpenCV's structured_light module.

Layout for a W x H projector: ceil(log2 W) column bits then ceil(log2 H) row bits, most
significant first, each as a pattern and its inverse (2·(Nc + Nr) images), optionally
followed by an all-white and an all-black image. Bit k of column c is bit k of the
reflected Gray code c ^ (c >> 1). A camera pixel reads bit k as 1 where the pattern is
brighter than its inverse; a bit is trusted where |pattern − inverse| reaches
`min_bit_difference`, a pixel where white − black reaches `min_contrast` (both in DN, as
OpenCV's white and black thresholds).

The bits are read by `scanner.pixel_code.read_pixel_code`: where only the last
`max_dropped_bits` bits are unreadable (the finest stripes blur first: a tilted board,
defocus) the pixel gets the centre of the run of 2^k projector pixels the leading bits name,
with weight 4^-k. OpenCV's decoder drops such pixels; keeping them keeps corners of tilted
boards usable.

The result is the projector pixel (column, row) each camera pixel sees (NaN where not
decoded), with those weights: sub-pixel precision comes from fitting many such pixels, in
local fits (`calibration.correspond`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.errors import DetectionError
from scanner.pixel_code import read_pixel_code


@dataclass(frozen=True)
class GrayCodeLayout:
    """OpenCV's Gray-code sequence for a projector of `width` x `height` pixels;
    `white_black`: the sequence ends with an all-white and an all-black image."""

    width: int
    height: int
    white_black: bool = True

    @property
    def column_bits(self) -> int:
        return int(np.ceil(np.log2(self.width)))

    @property
    def row_bits(self) -> int:
        return int(np.ceil(np.log2(self.height)))

    @property
    def n_frames(self) -> int:
        return 2 * (self.column_bits + self.row_bits) + (2 if self.white_black else 0)

    @property
    def white_index(self) -> int | None:
        return self.n_frames - 2 if self.white_black else None

    def patterns(self) -> np.ndarray:
        """(n_frames, height, width) uint8: the images the projector shows."""
        out = np.empty((self.n_frames, self.height, self.width), dtype=np.uint8)
        for axis, n_bits, start in ((0, self.column_bits, 0), (1, self.row_bits, 2 * self.column_bits)):
            coord = np.arange(self.width if axis == 0 else self.height)
            gray = coord ^ (coord >> 1)
            for k in range(n_bits):
                bit = ((gray >> (n_bits - 1 - k)) & 1).astype(np.uint8) * 255
                img = bit[None, :] if axis == 0 else bit[:, None]
                out[start + 2 * k] = img
                out[start + 2 * k + 1] = 255 - img
        if self.white_black:
            out[-2], out[-1] = 255, 0
        return out


@dataclass(frozen=True, eq=False)
class GrayCodeMaps:
    """Decoded projector columns `u` and rows `v` (H, W) float32, NaN where not decoded,
    and their weights (4^-k for k dropped bits)."""

    u: np.ndarray
    v: np.ndarray
    weight_u: np.ndarray
    weight_v: np.ndarray
    valid: np.ndarray
    contrast: np.ndarray  # white − black (DN)


def decode_graycode(stack: np.ndarray, layout: GrayCodeLayout, min_contrast: float, min_bit_difference: float,
                    view: int | str = 0, max_dropped_bits: int = 2) -> GrayCodeMaps:
    """Projector coordinates per camera pixel from an (n_frames, H, W) capture of `layout`;
    without white and black images the contrast test uses the bit pairs alone."""
    if stack.ndim != 3 or stack.shape[0] != layout.n_frames:
        got = stack.shape[0] if stack.ndim == 3 else stack.shape
        raise DetectionError(view, f"OpenCV Gray code for a {layout.width} x {layout.height} projector needs "
                                   f"{layout.n_frames} images, got {got}")
    frames = stack.astype(np.int16 if stack.dtype == np.uint8 else np.int32)
    shape = frames.shape[1:]
    valid = np.ones(shape, dtype=bool)
    if layout.white_black:
        contrast = frames[-2] - frames[-1]
        valid &= contrast >= min_contrast
    else:
        contrast = np.zeros(shape, dtype=frames.dtype)
    coords, weights = [], []
    for n_bits, start in ((layout.column_bits, 0), (layout.row_bits, 2 * layout.column_bits)):
        diffs = [frames[start + 2 * k] - frames[start + 2 * k + 1] for k in range(n_bits)]
        coordinate, run, readable = read_pixel_code(diffs, min_bit_difference, max_dropped_bits)
        valid &= readable
        coords.append(coordinate)
        weights.append(np.float32(1.0) / np.square(run, dtype=np.float32))
    (col, row), (wu, wv) = coords, weights
    valid &= (col < layout.width) & (row < layout.height)
    u = np.where(valid, col, np.float32(np.nan)).astype(np.float32)
    v = np.where(valid, row, np.float32(np.nan)).astype(np.float32)
    return GrayCodeMaps(u, v, wu, wv, valid, contrast.astype(np.float32))
