"""Gray codes of every projector pixel (OpenCV's `structured_light.GrayCodePattern` layout),
read from pattern/inverse pairs.

Bit k (most significant first) of projector pixel c is bit k of the reflected Gray code
c ^ (c >> 1). A camera pixel reads a bit as 1 where the pattern is brighter than its
inverse, and trusts it where |pattern − inverse| reaches a threshold. The finest stripes
are one projector pixel wide and blur first: where only the last `max_dropped_bits` bits are
unreadable, the leading bits still name a run of 2^k projector pixels (Gray-code prefixes
are contiguous ranges), and the pixel gets that run's centre (variance 4^k times a
one-pixel run's). Used by scan decoding and by calibration from other tools' captures.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from scanner.patterns import gray_to_binary


def read_pixel_code(diffs: Sequence[np.ndarray], min_bit_difference: float | np.ndarray,
                    max_dropped_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projector pixel coordinate per camera pixel from the per-bit differences pattern −
    inverse (most significant bit first). Returns (coordinate float32, the run's centre,
    NaN where more than `max_dropped_bits` trailing bits are unreadable; run length in
    projector pixels, int32; readable bool)."""
    n_bits = len(diffs)
    shape = diffs[0].shape
    code = np.zeros(shape, dtype=np.int32)
    readable = np.zeros(shape, dtype=np.int32)  # leading bits read reliably
    leading = np.ones(shape, dtype=bool)
    for diff in diffs:
        leading &= np.abs(diff) >= min_bit_difference
        readable += leading
        code <<= 1
        code |= diff > 0
    dropped = n_bits - readable
    ok = dropped <= max_dropped_bits
    run = np.left_shift(1, dropped).astype(np.int32)
    first = np.left_shift(gray_to_binary(np.right_shift(code, dropped), n_bits), dropped)
    coordinate = (first + (run - 1) * np.float32(0.5)).astype(np.float32)
    coordinate[~ok] = np.nan
    return coordinate, run, ok
