"""Fringe patterns as other tools make them, written from their published formulas and
independently of `scanner.patterns` (whose conventions they test), and analytic captures of
them: what a camera sees of a surface whose projector coordinates per pixel are known.

- `slmaster_heterodyne` / `slmaster_complementary`: SLMaster's ThreeFrequencyHeterodynePattern
  and SinusCompleGrayCodePattern (github.com/Practice3DVision/SLMaster, cpuStructuredLight/):
  127.5 + 127.5·cos(ψ + 2π·i/N) truncated to 8 bits, ψ running from −π at the start of each period
  (at a pixel's centre), periods n, n−6, n−11 (heterodyne) or n with integer pixels per period and
  log2(n) + 1 block-Gray-code frames after the phase frames (complementary).
- `fringe_rows`: a phase-shift set in any combination of conventions (phase origin, step sign,
  pixel centre δ in 2π·f·(c + δ)/W, frequency- or step-major order, complementary or OpenCV pixel
  Gray code before or after the phase, white/black references first or last).
- `opencv_graycode`: OpenCV's GrayCodePattern: pixel Gray code of columns then rows, each bit and
  its inverse, then white and black.

Rows are (n_frames, extent) floats in 0..1 along the coded axis (or uint8 where the tool rounds).
"""

from __future__ import annotations

import numpy as np


def _gray(n: np.ndarray) -> np.ndarray:
    return n ^ (n >> 1)


def slmaster_heterodyne(width: int, periods: int = 32, steps: int = 4) -> np.ndarray:
    """(3·steps, width) uint8 rows, frequency by frequency."""
    k = np.arange(width, dtype=np.float64)
    rows = []
    for f in (periods, periods - 6, periods - 11):
        p = width / f
        psi = (2 * (k / p - np.floor(k / p)) - 1) * np.pi
        rows += [(127.5 + 127.5 * np.cos(psi + 2 * np.pi / steps * i)).astype(np.uint8) for i in range(steps)]
    return np.array(rows)


def slmaster_complementary(width: int, periods: int = 32, steps: int = 12) -> np.ndarray:
    """(steps + log2(periods) + 1, width) uint8 rows: phase frames, then the block Gray code
    (each frame splits the previous blocks in two, the last at half a period)."""
    k = np.arange(width)
    p = width // periods
    rows = [(127.5 + 127.5 * np.cos((k % p) / p * 2 * np.pi - np.pi + 2 * np.pi / steps * i)).astype(np.uint8)
            for i in range(steps)]
    sequence = [0, 255]
    for _ in range(int(np.log2(periods)) + 1):
        block = width // len(sequence)
        row = np.zeros(width, np.uint8)
        for j, value in enumerate(sequence):
            row[j * block:(j + 1) * block] = value
        rows.append(row)
        sequence = sequence + sequence[::-1]
    return np.array(rows)


def _pixel_code_rows(extent: int) -> list[np.ndarray]:
    n_bits = int(np.ceil(np.log2(extent)))
    code = _gray(np.arange(extent))
    out = []
    for b in range(n_bits):
        bit = ((code >> (n_bits - 1 - b)) & 1).astype(np.float64)
        out += [bit, 1.0 - bit]
    return out


def opencv_graycode(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV GrayCodePattern as (column rows, row rows) plus white and black at the end of
    the second: frames 0..2·ceil(log2 W)−1 vary along x, the next 2·ceil(log2 H) along y."""
    cols = np.array(_pixel_code_rows(width))
    rows = np.array(_pixel_code_rows(height) + [np.ones(height), np.zeros(height)])
    return cols, rows


def fringe_rows(extent: int, fringes: list[float], steps: int, *, origin: float = 0.0, sign: int = 1,
                delta: float = 0.5, order: str = "frequency-major", gray: str | None = None,
                gray_position: str = "after", references: str = "none") -> np.ndarray:
    """(n_frames, extent) rows in 0..1 of a phase-shift set in the given conventions (module
    docstring); `gray` "complementary" codes periods of fringes[0] (Wu et al.), "opencv" pixels."""
    c = np.arange(extent, dtype=np.float64)
    pairs = [(f, n) for f in fringes for n in range(steps)] if order == "frequency-major" else \
        [(f, n) for n in range(steps) for f in fringes]
    phase = [0.5 + 0.5 * np.cos(2 * np.pi * f * (c + delta) / extent + origin + sign * 2 * np.pi * n / steps)
             for f, n in pairs]
    code: list[np.ndarray] = []
    if gray == "complementary":
        n_bits = int(np.ceil(np.log2(fringes[0])))
        period = extent / fringes[0]
        index = _gray(np.floor(c / period).astype(np.int64))  # period k covers pixels [k·p, (k+1)·p)
        code = [((index >> (n_bits - 1 - b)) & 1).astype(np.float64) for b in range(n_bits)]
        code.append((_gray(np.floor(c / (period / 2)).astype(np.int64)) & 1).astype(np.float64))
    elif gray == "opencv":
        code = _pixel_code_rows(extent)
    body = phase + code if gray_position == "after" else code + phase
    refs = [np.ones(extent), np.zeros(extent)]
    rows = refs + body if references == "first" else body + refs if references == "last" else body
    return np.array(rows)


def capture(rows: np.ndarray, coordinate: np.ndarray, *, bits: int = 8, dark: float = 0.08, bright: float = 0.85,
            noise: float = 0.004, seed: int = 0, lit: np.ndarray | None = None) -> np.ndarray:
    """Frames a camera takes of rows shown along the coded axis, each pixel seeing projector
    coordinate `coordinate` (H, W; OpenCV pixel centres, NaN: not lit; the rows interpolated
    linearly between pixel centres, as a slightly defocused projector shows them; `lit`: where
    the projector's light reaches at all, e.g. its other coordinate inside its image): intensity
    linear between `dark` and `bright` of full scale, Gaussian noise `noise` of full scale."""
    rng = np.random.default_rng(seed)
    full = 2 ** bits - 1
    levels = rows.astype(np.float64) / (255.0 if rows.dtype == np.uint8 else 1.0)
    extent = rows.shape[1]
    x = np.nan_to_num(coordinate, nan=-10.0)
    lit = (x > -0.5) & (x < extent - 0.5) & (True if lit is None else lit)
    grid = np.arange(extent, dtype=np.float64)
    out = np.empty((len(rows), *coordinate.shape), dtype=np.uint8 if bits == 8 else np.uint16)
    for k, row in enumerate(levels):
        shown = np.where(lit, np.interp(x, grid, row), 0.0)
        img = full * (dark + (bright - dark) * shown + rng.normal(0.0, noise, coordinate.shape))
        out[k] = np.clip(np.rint(img), 0, full)
    return out
