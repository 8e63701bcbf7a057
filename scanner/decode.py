"""Fringe decoding: wrapped phase, modulation and background, temporal unwrapping, masks.

Input: an (N, H, W) stack of camera frames in the order of `PatternSet.frames()`, at its
bit depth. Output per fringe orientation: the projector pixel coordinate each camera
pixel sees along the coded axis (NaN where invalid), with the maps behind it and the
reasons pixels were rejected. Everything is whole-array numpy/OpenCV work.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scanner.errors import DecodeError
from scanner.patterns import PatternSet, gray_to_binary

TWO_PI = np.float32(2.0 * np.pi)


@dataclass(frozen=True)
class DecodeSettings:
    """Thresholds for rejecting pixels.

    `min_modulation`: modulation B below this fraction of full scale is too weak for a
    precise phase. `min_contrast`: B/A below this means no fringe reaches the pixel
    (projector shadow or outside the projected area). `order_tolerance`: an unwrapping
    residual above this fraction of π marks a fringe-order error. `spatial_check`: also
    cut the map where neighbours jump by more than half a fringe period and reject the
    regions between cuts smaller than `min_region_fraction` of the image (clustered
    order errors, which no per-pixel test sees). `gray_certainty`: a Gray-code bit reads
    clearly when |I − A| exceeds this fraction of the fringe modulation B.
    """

    min_modulation: float = 0.005
    min_contrast: float = 0.12
    order_tolerance: float = 0.5
    spatial_check: bool = True
    min_region_fraction: float = 1e-4
    gray_certainty: float = 0.3


@dataclass(eq=False)
class OrientationMaps:
    """Decoded maps for one fringe orientation (float32 unless stated)."""

    orientation: str
    coordinate: np.ndarray  # projector pixel coordinate along the coded axis, NaN invalid
    phase: np.ndarray  # absolute phase in units of the finest fringe (rad), NaN invalid
    wrapped: list[np.ndarray]  # wrapped phase per frequency, [0, 2π)
    modulation: list[np.ndarray]  # B per frequency (DN)
    background: np.ndarray  # A (DN), mean of all phase frames
    phase_weight: np.ndarray  # Σ_i (B_i·f_i/f_max)², the precision of `phase` up to the noise σ_I²·2/N
    masks: dict[str, np.ndarray]  # bool reasons for rejection
    valid: np.ndarray  # bool
    fringes: float  # finest fringe count across `extent_px`
    extent_px: int  # projector pixels along the coded axis

    @property
    def period_px(self) -> float:
        """Finest fringe period in projector pixels."""
        return self.extent_px / self.fringes


@dataclass(eq=False)
class DecodeResult:
    """Everything decoded from one stack. `texture` is the mean intensity (DN)."""

    patterns: PatternSet
    bit_depth: int
    maps: dict[str, OrientationMaps]
    texture: np.ndarray
    valid: np.ndarray  # bool: valid in every orientation

    def coordinate(self, orientation: str) -> np.ndarray:
        return self.maps[orientation].coordinate


def _wrap_positive(d: np.ndarray) -> np.ndarray:
    """Map differences of two [0, 2π) phases into [0, 2π), in place."""
    d += TWO_PI * (d < 0)
    return d


def _phase_shift(block: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wrapped phase [0, 2π), modulation B and background A of one N-step block (N, H, W)."""
    n, h, w = block.shape
    delta = 2.0 * np.pi * np.arange(steps) / steps
    weights = np.stack([np.cos(delta), -np.sin(delta), np.full(steps, 1.0)]).astype(np.float32)
    weights[:2] *= 2.0 / steps
    weights[2] /= steps
    flat = block.reshape(n, h * w).astype(np.float32)
    c, s, a = weights @ flat  # B·cos φ, B·sin φ, A
    c, s = c.reshape(h, w), s.reshape(h, w)
    return cv2.phase(c, s), cv2.magnitude(c, s), a.reshape(h, w)


def _unwrap_step(coarse: np.ndarray, ratio: float, fine_wrapped: np.ndarray,
                 worst: np.ndarray) -> np.ndarray:
    """Absolute fine phase from an absolute coarse phase; raises `worst` to the unwrapping
    residual (fraction of π) where it is larger."""
    predicted = coarse * np.float32(ratio)
    fine = np.subtract(predicted, fine_wrapped)
    fine *= np.float32(1.0 / TWO_PI)
    np.rint(fine, out=fine)
    fine *= TWO_PI
    fine += fine_wrapped
    predicted -= fine
    np.abs(predicted, out=predicted)
    predicted *= np.float32(1.0 / np.pi)
    np.maximum(worst, predicted, out=worst)
    return fine


def _temporal_unwrap(ps: PatternSet, wrapped: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """Absolute phase per frequency and the worst unwrapping residual (fraction of π)."""
    f = ps.fringes
    worst = np.zeros_like(wrapped[0])
    if ps.family == "hierarchical":
        absolute = [wrapped[0]]
        for i in range(1, len(f)):
            absolute.append(_unwrap_step(absolute[-1], f[i] / f[i - 1], wrapped[i], worst))
        return absolute, worst
    # three-frequency heterodyne: beat phases with f1-f2 and f2-f3 fringes, and their beat with 1
    p12 = _wrap_positive(wrapped[0] - wrapped[1])
    p23 = _wrap_positive(wrapped[1] - wrapped[2])
    p123 = _wrap_positive(p12 - p23)
    f12 = f[0] - f[1]
    a12 = _unwrap_step(p123, f12, p12, worst)  # the f1-f2 beat is the finer one: unwrap all three from it
    return [_unwrap_step(a12, f[i] / f12, wrapped[i], worst) for i in range(3)], worst


def _graycode_unwrap(ps: PatternSet, wrapped: np.ndarray, bits: np.ndarray, background: np.ndarray,
                     modulation: np.ndarray, certainty: float) -> tuple[np.ndarray, np.ndarray]:
    """Absolute phase from complementary Gray code (Wu et al.), and where it is unreliable.

    The extra half-period bit picks the fringe order that is safe at the code boundaries:
    away from a period boundary (π/2 < φ < 3π/2) every regular bit must read clearly, and
    near one only the single bit that changes there may be ambiguous; the complementary bit
    must read clearly wherever it is used. A bit reads clearly when |I − A| exceeds
    `certainty`·B; blur wider than a quarter period breaks this, and those pixels are
    returned as order errors instead of being unwrapped by a guess."""
    n_bits = ps.gray_bits()
    code = np.zeros(wrapped.shape, dtype=np.int32)
    unclear = np.zeros(wrapped.shape, dtype=np.int32)  # regular bits read ambiguously
    margin = np.float32(certainty) * modulation
    for b in range(n_bits + 1):
        diff = bits[b].astype(np.float32) - background
        code = (code << 1) | (diff > 0)
        ambiguous = np.abs(diff) < margin
        if b < n_bits:
            unclear += ambiguous
        else:
            complementary_unclear = ambiguous
    k1 = gray_to_binary(code >> 1, n_bits)
    k2 = (gray_to_binary(code, n_bits + 1) + 1) >> 1
    quarter = np.float32(np.pi / 2)
    near_boundary = (wrapped <= quarter) | (wrapped >= 3 * quarter)
    order = np.where(wrapped <= quarter, k2, np.where(wrapped >= 3 * quarter, k2 - 1, k1))
    unreliable = np.where(near_boundary, complementary_unclear | (unclear > 1), unclear > 0)
    return wrapped + TWO_PI * order.astype(np.float32), unreliable


def _typical_step(diff: np.ndarray) -> np.float32:
    """Median |difference| between neighbours, from every 16th line (cheap, robust)."""
    sample = np.abs(diff[::16])
    sample = sample[~np.isnan(sample)]
    return np.float32(np.median(sample)) if sample.size else np.float32(0.0)


def _unreliable_regions(coordinate: np.ndarray, valid: np.ndarray, period_px: float,
                        min_region_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Fringe-order errors that came in clusters, found spatially.

    The coordinate map is cut wherever neighbours differ by more than half a fringe period
    beyond the map's typical neighbour step (a depth step or an order error), both pixels of
    the pair being rejected as possibly mixed; regions
    smaller than `min_region_px` left between the cuts are order-error islands.
    Returns (islands, cut pixels)."""
    c = coordinate  # NaN where not valid
    half = np.float32(period_px / 2.0)
    cut = np.zeros(valid.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        dx = np.abs(c[:, 1:] - c[:, :-1])
        jump = dx > half + _typical_step(dx)
        cut[:, :-1] |= jump  # both pixels of a jump: at a depth edge either may be a mixed pixel
        cut[:, 1:] |= jump
        dy = np.abs(c[1:, :] - c[:-1, :])
        jump = dy > half + _typical_step(dy.T)
        cut[:-1, :] |= jump
        cut[1:, :] |= jump
    cut &= valid
    _, labels, stats, _ = cv2.connectedComponentsWithStats((valid & ~cut).view(np.uint8), connectivity=4,
                                                           ltype=cv2.CV_32S)
    small = stats[:, cv2.CC_STAT_AREA] < min_region_px
    small[0] = False  # label 0: invalid or cut pixels
    return small[labels], cut


def decode(stack: np.ndarray, patterns: PatternSet, bit_depth: int, projector_size: tuple[int, int],
           settings: DecodeSettings = DecodeSettings()) -> DecodeResult:
    """Decode an (N, H, W) fringe stack taken with `patterns` on a projector of
    `projector_size` = (width, height) pixels."""
    specs = patterns.frames()
    if stack.ndim != 3 or stack.shape[0] != len(specs):
        raise DecodeError(f"pattern set '{patterns.family}' needs {len(specs)} frames of one size; "
                          f"got an array of shape {stack.shape}")
    if not np.issubdtype(stack.dtype, np.integer):
        raise DecodeError(f"frames must be integer images at their bit depth, got {stack.dtype}")
    full_scale = float(2 ** bit_depth - 1)
    saturated = stack[0].copy()
    for frame in stack[1:]:
        cv2.max(saturated, frame, dst=saturated)
    saturated = saturated >= full_scale

    maps: dict[str, OrientationMaps] = {}
    start = 0
    backgrounds = []
    for orientation in patterns.orientations:
        extent = projector_size[0] if orientation == "vertical" else projector_size[1]
        n_freq = len(patterns.fringes)
        wrapped, modulation, background = [], [], None
        for level in range(n_freq):
            phi, b, a = _phase_shift(stack[start:start + patterns.steps], patterns.steps)
            start += patterns.steps
            wrapped.append(phi)
            modulation.append(b)
            background = a if background is None else background + a
        background /= np.float32(n_freq)
        masks = {"saturated": saturated}
        f_max = max(patterns.fringes)
        finest = patterns.fringes.index(f_max)
        if patterns.family == "graycode":
            n_bits = patterns.gray_bits() + 1
            phase, masks["order_error"] = _graycode_unwrap(patterns, wrapped[0], stack[start:start + n_bits],
                                                           background, modulation[0], settings.gray_certainty)
            start += n_bits
            weight = modulation[0] ** 2
        else:
            absolute, residual = _temporal_unwrap(patterns, wrapped)
            masks["order_error"] = residual > settings.order_tolerance
            # inverse-variance combination of all frequencies, in units of the finest fringe
            phase = np.zeros_like(background)
            weight = np.zeros_like(background)
            for phi_abs, b, fi in zip(absolute, modulation, patterns.fringes):
                w = np.square(b)
                w *= np.float32((fi / f_max) ** 2)
                weight += w
                w *= phi_abs
                phase += np.multiply(w, np.float32(f_max / fi), out=w)
            phase /= np.maximum(weight, np.float32(1e-12))
        b_fine = modulation[finest]
        masks["shadow"] = b_fine < settings.min_contrast * np.maximum(background, 1e-6)
        masks["low_modulation"] = ~masks["shadow"] & (b_fine < settings.min_modulation * full_scale)
        valid = ~(masks["saturated"] | masks["shadow"] | masks["low_modulation"])
        masks["order_error"] &= valid  # reasons stay distinct: an order error is judged on a usable phase
        valid &= ~masks["order_error"]
        coordinate = phase * np.float32(extent / (2.0 * np.pi * f_max))
        coordinate -= np.float32(0.5)
        np.copyto(coordinate, np.float32(np.nan), where=~valid)
        if settings.spatial_check:
            min_region = max(1, int(settings.min_region_fraction * valid.size))
            islands, masks["discontinuity"] = _unreliable_regions(coordinate, valid, extent / f_max, min_region)
            masks["order_error"] |= islands
            valid &= ~(islands | masks["discontinuity"])
        invalid = ~valid
        np.copyto(coordinate, np.float32(np.nan), where=invalid)
        np.copyto(phase, np.float32(np.nan), where=invalid)
        maps[orientation] = OrientationMaps(orientation, coordinate, phase, wrapped, modulation, background, weight,
                                            masks, valid, f_max, extent)
        backgrounds.append(background)
    texture = backgrounds[0] if len(backgrounds) == 1 else (backgrounds[0] + backgrounds[1]) / 2
    valid_all = np.logical_and.reduce([m.valid for m in maps.values()])
    return DecodeResult(patterns, bit_depth, maps, texture, valid_all)
