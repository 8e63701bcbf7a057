"""Fringe decoding: wrapped phase, modulation and background, unwrapping, masks, self-check.

Input: an (N, H, W) stack of camera frames in the order of `PatternSet.frames()` (which
follows the set's conventions: frame order, reference frames, Gray-code variant), at its
bit depth. Output per fringe orientation: the projector pixel coordinate each camera pixel
sees along the coded axis (OpenCV convention, pixel centres at integers; NaN where
invalid), with the maps behind it and the reasons pixels were rejected.

Every decode checks itself against the physics of its frames (scanner.decode_checks,
docs/consistency.md): the N-step fit residual against the sensor's noise, the frequencies'
agreement, the Gray code's agreement with the phase, the projector's range, the fringe
orders and the coordinate's order along each line, each with its statistic, threshold and
false-refusal rate in `DecodeResult.checks`. Everything is whole-array numpy/OpenCV work.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from itertools import pairwise
from typing import Any

import cv2
import numpy as np

from scanner.conventions import known
from scanner.decode_checks import (
    ALPHA,
    FITTED_MODEL,
    FITTED_MODEL_ACCURACY,
    MIN_JUDGED,
    PATTERN_ERROR,
    SENSOR_MODEL,
    SENSOR_MODEL_ACCURACY,
    Check,
    ConsistencyError,
    failed,
    majority_check,
    normal_isf,
    not_judged,
    offset_check,
    ordering,
    poisson_quantile,
    scale_check,
)
from scanner.errors import DecodeError
from scanner.pattern_families import PIXEL_CODE_PAIR, TWO_PI, FrameKind, Unwrapping, temporal, unwrap_step
from scanner.patterns import FrameSpec, PatternSet, gray_to_binary
from scanner.pixel_code import read_pixel_code

CHUNK_ROWS = 128  # rows decoded together (a band's float32 maps fit in cache)
SAMPLE_STEP = 4  # the consistency checks judge every 4th pixel of every 4th row
SPATIAL_MODEL = "frames' noise along the fringes (an upper bound)"


@dataclass(frozen=True)
class DecodeSettings:
    """Thresholds for rejecting pixels.

    `min_modulation`: modulation B below this fraction of full scale is too weak for a
    precise phase. `min_contrast`: B/A below this means no fringe reaches the pixel
    (projector shadow or outside the projected area). `order_tolerance` (fraction of π)
    is the least unwrapping residual ever called a fringe-order error; above it a pixel is
    one when its residual comes within `order_sigmas` of its own predicted residual noise
    (from its modulation and the stack's intensity-noise model) of the ambiguity at π, the
    tolerance never above `order_tolerance_max`. `spatial_check`: also cut the map where
    neighbours jump by more than half a fringe period and reject the regions between cuts
    smaller than `min_region_fraction` of the image (clustered order errors, which no
    per-pixel test sees). `gray_certainty`: a Gray-code bit reads clearly when |I − A|
    exceeds this fraction of the fringe modulation B (complementary code); a pixel-code bit
    when |pattern − inverse| exceeds `code_certainty` times the white − black contrast (a
    pair read against each other is robust; up to `max_dropped_bits` of the finest bits may
    be unreadable). `self_check`: refuse the decode when any of its consistency checks
    fails (`scanner.decode_checks`, docs/consistency.md; off: recorded only).
    `interreflection` (multi-frequency phase-shift sets): mask, as "interreflection", pixels
    whose phase a second light path corrupts: their frequencies' absolute phases disagree
    (beyond the image's median, systematic, disagreement) by more than
    `interreflection_min_rad` (finest fringe) and `interreflection_sigmas` of their
    predicted noise though short of an order error, or their
    finest/coarsest modulation ratio departs from the image's median by more than
    `interreflection_ratio` (relative) and `interreflection_sigmas` of its noise
    (`_SecondPaths`). A second path whose phase shift is about the same at every
    frequency (nearby points: the last few pixels at a concave fold) or that outshines the
    direct light is not seen by either test; where it outshines it, what is left valid
    among the masked pixels are slivers (1-2 px wide), so valid pixels narrower than
    `sliver_px` + 1 within `sliver_px` of an interreflection-masked pixel are masked too
    (`interreflection_slivers`; on the simulated concave corner they were every one of the
    fringe-order errors the tests let through).
    """

    min_modulation: float = 0.005
    min_contrast: float = 0.12
    order_tolerance: float = 0.5
    order_tolerance_max: float = 0.9
    order_sigmas: float = 4.0
    spatial_check: bool = True
    min_region_fraction: float = 1e-4
    gray_certainty: float = 0.3
    code_certainty: float = 0.1
    max_dropped_bits: int = 2
    self_check: bool = True
    interreflection: bool = True
    interreflection_sigmas: float = 5.0
    interreflection_min_rad: float = 0.2
    interreflection_ratio: float = 0.15
    sliver_px: int = 2


DEFAULT_DECODE_SETTINGS = DecodeSettings()  # the defaults every decode entry point takes


@dataclass(frozen=True)
class NoiseModel:
    """Camera intensity noise variance σ_I² = read + shot·A (DN², A in DN), fitted to the
    residuals of the phase-shift fit (or, with 3 steps, to the background's fine texture)."""

    read: float
    shot: float

    def sigma(self, background: np.ndarray) -> np.ndarray:
        """σ_I (DN) for a background A (DN)."""
        return np.sqrt(np.float32(self.read) + np.float32(self.shot) * np.maximum(background, 0))


@dataclass(eq=False)
class OrientationMaps:
    """Decoded maps for one fringe orientation (float32 unless stated)."""

    orientation: str
    coordinate: np.ndarray  # projector pixel coordinate along the coded axis, NaN invalid
    phase: np.ndarray  # absolute phase in units of the finest fringe (rad), NaN invalid
    wrapped: list[np.ndarray]  # wrapped phase per frequency, [0, 2π), phase origin removed
    modulation: list[np.ndarray]  # B per frequency (DN)
    background: np.ndarray  # A (DN), mean of all phase frames
    phase_weight: np.ndarray  # Σ_i (B_i·f_i/f_max)², the precision of `phase` up to the noise σ_I²·2/N
    masks: dict[str, np.ndarray]  # bool reasons for rejection
    valid: np.ndarray  # bool
    fringes: float  # finest fringe count across `extent_px`
    extent_px: int  # projector pixels along the coded axis
    noise: NoiseModel
    steps: int

    @property
    def period_px(self) -> float:
        """Finest fringe period in projector pixels."""
        return self.extent_px / self.fringes

    @cached_property
    def phase_sigma(self) -> np.ndarray:
        """Predicted one-sigma noise of `phase` (rad, finest fringe) per pixel:
        sqrt(2/N)·σ_I(A)/sqrt(phase_weight); NaN where invalid."""
        s = self.noise.sigma(self.background) * np.float32(np.sqrt(2.0 / self.steps))
        s /= np.sqrt(np.maximum(self.phase_weight, np.float32(1e-12)))
        s[~self.valid] = np.nan
        return s

    @property
    def coordinate_sigma(self) -> np.ndarray:
        """Predicted one-sigma noise of `coordinate` (projector px)."""
        return self.phase_sigma * np.float32(self.period_px / (2 * np.pi))


@dataclass(eq=False)
class DecodeResult:
    """Everything decoded from one stack. `texture` is the mean intensity (DN)."""

    patterns: PatternSet
    bit_depth: int
    maps: dict[str, OrientationMaps]
    texture: np.ndarray
    valid: np.ndarray  # bool: valid in every orientation
    checks: list[Check]  # the consistency checks the maps support (scanner.decode_checks)

    def coordinate(self, orientation: str) -> np.ndarray:
        return self.maps[orientation].coordinate

    def rejected(self) -> dict[str, int]:
        """Pixels rejected per orientation and reason (a pixel counts under its first reason)."""
        return {f"{o}/{k}": int(v.sum()) for o, m in self.maps.items() for k, v in m.masks.items()}


def _weighted_sum(frames: list[np.ndarray], weights: np.ndarray) -> np.ndarray:
    """Σ w_k·I_k as float32, straight from the frames at their bit depth: pairs of frames by
    cv2.addWeighted (one pass each, no float copy of the frames), zero weights skipped."""
    terms = [(f, float(w)) for f, w in zip(frames, weights) if abs(w) > 1e-9]
    acc = None
    for i in range(0, len(terms), 2):
        if i + 1 < len(terms):
            (f1, w1), (f2, w2) = terms[i], terms[i + 1]
            t: np.ndarray = cv2.addWeighted(f1, w1, f2, w2, 0.0, dtype=cv2.CV_32F)
        else:
            t = terms[i][0].astype(np.float32)
            t *= np.float32(terms[i][1])
        acc = t if acc is None else cv2.add(acc, t, dst=acc)
    return acc if acc is not None else np.zeros(frames[0].shape, np.float32)


def phase_shift(block: np.ndarray | list[np.ndarray], steps: int, origin: float, sign: int,
                out: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wrapped phase [0, 2π) with the phase origin removed, modulation B and background A
    of one N-step block (N frames of (H, W)) whose step n adds sign·2πn/N to the displayed
    phase; `out`: arrays to write the phase and modulation into."""
    frames = [block[k] for k in range(steps)]
    angle = sign * 2.0 * np.pi * np.arange(steps) / steps + origin
    c = _weighted_sum(frames, np.cos(angle) * (2.0 / steps))  # B·cos φ
    s = _weighted_sum(frames, -np.sin(angle) * (2.0 / steps))  # B·sin φ
    a = _weighted_sum(frames, np.full(steps, 1.0 / steps))  # A
    if out is None:
        return cv2.phase(c, s), _magnitude(c, s), a
    cv2.phase(c, s, angle=out[0])
    _magnitude(c, s, out[1])
    return out[0], out[1], a


def _magnitude(c: np.ndarray, s: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """sqrt(c² + s²) in float32 by numpy, squaring `s` in place (the caller's scratch array):
    cv2.magnitude's result depends on its buffers' memory alignment (last-ulp differences
    between runs), and a session must decode bit-identically."""
    m = np.multiply(c, c, out=out)
    m += np.multiply(s, s, out=s)
    return np.sqrt(m, out=m)


def _residual_sigma(ps: PatternSet, phase_sigmas: list[np.ndarray]) -> np.ndarray:
    """Predicted one-sigma of the largest unwrapping residual (fraction of π) from each
    frequency's phase noise (rad), propagated through the family's unwrapping steps."""
    steps = temporal(ps.kind).residual_variances(ps.fringes, [s * s for s in phase_sigmas])
    return np.sqrt(np.maximum.reduce(steps)) / np.float32(np.pi)


def _order_errors(residual: np.ndarray, candidates_sigma: Callable[[np.ndarray], np.ndarray],
                  settings: DecodeSettings) -> np.ndarray:
    """Pixels whose unwrapping residual (fraction of π) marks a fringe-order error: above
    `order_tolerance` and within `order_sigmas` predicted sigmas of the ambiguity at 1."""
    errors = residual > np.float32(settings.order_tolerance)
    idx = np.flatnonzero(errors)
    if idx.size:
        sigma = candidates_sigma(idx)
        tol = np.clip(1.0 - settings.order_sigmas * sigma, settings.order_tolerance, settings.order_tolerance_max)
        errors.flat[idx] = ~(residual.flat[idx] <= tol)  # NaN sigma: an error
    return errors


class _SecondPaths:
    """The interreflection tests (see DecodeSettings), on every core in bands after the
    per-pixel decode, with outputs equal to judging the whole image at once.

    Frequency consistency: among the candidates (usable, no order error), pixels whose
    frequencies' absolute phases, scaled to the finest fringe, disagree pairwise beyond the
    image's median disagreement of that pair (a systematic offset between frequencies is no
    second path) by more than `interreflection_min_rad` and `interreflection_sigmas` of the
    pair's predicted noise (each frequency's phase noise, no beat amplification): one light
    path gives every frequency the same coordinate; a second path of another coordinate
    shifts each frequency's phase differently. Modulation ratio: usable pixels whose
    finest/coarsest modulation ratio departs from the image's median ratio (the optics'
    transfer ratio, the same for every directly lit pixel) by more than `interreflection_ratio`
    and `interreflection_sigmas` of its noise: two paths of different phase add up to different
    amplitudes at different frequencies. Each median is taken over every k-th judged pixel in
    raster order (k = judged // MEDIAN_SAMPLE), gathered band by band."""

    MEDIAN_SAMPLE = 200000

    def __init__(self, fringes: tuple[float, ...], scaled: list[np.ndarray], modulation: list[np.ndarray],
                 *, background: np.ndarray, noise: NoiseModel, steps: int, settings: DecodeSettings) -> None:
        self.fringes, self.scaled, self.modulation = list(fringes), scaled, modulation
        self.background, self.noise, self.settings = background, noise, settings
        self.sqrt_2n = np.float32(np.sqrt(2.0 / steps))
        self.pairs = [(i, j) for i in range(len(fringes)) for j in range(i + 1, len(fringes))]
        self.fine, self.coarse = int(np.argmax(fringes)), int(np.argmin(fringes))

    def _pair_devs(self, rows: slice, at: np.ndarray | None = None) -> list[np.ndarray]:
        """Per pair, the difference of the scaled absolute phases on `rows` (at the band's flat
        indices `at`, when given)."""
        pick = (lambda a: a[rows]) if at is None else (lambda a: a[rows].ravel()[at])
        return [pick(self.scaled[i]) - pick(self.scaled[j]) for i, j in self.pairs]

    def _log_ratio(self, rows: slice, at: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(log of the finest/coarsest modulation ratio, the finest and coarsest B floored at
        1e-6) on `rows` (at `at`, when given)."""
        pick = (lambda a: a[rows]) if at is None else (lambda a: a[rows].ravel()[at])
        bf = np.maximum(pick(self.modulation[self.fine]), np.float32(1e-6))
        bc = np.maximum(pick(self.modulation[self.coarse]), np.float32(1e-6))
        return np.log(bf / bc), bf, bc

    def _medians(self, judged: list[np.ndarray], value: Callable[[slice, np.ndarray], list[np.ndarray]]
                 ) -> list[np.float32] | None:
        """Medians of `value(rows, at)` over every k-th pixel of `judged` (one bool array per
        band of `band_slices`) in raster order; None when fewer than MIN_JUDGED are judged."""
        counts = [int(np.count_nonzero(j)) for j in judged]
        total = sum(counts)
        if total < MIN_JUDGED:
            return None
        step = max(1, total // self.MEDIAN_SAMPLE)
        starts = np.cumsum([0] + counts[:-1])

        def sample(rows: slice) -> list[np.ndarray]:
            k = rows.start // CHUNK_ROWS
            return value(rows, np.flatnonzero(judged[k])[(-int(starts[k])) % step:: step])

        parts = in_bands(self.background.shape[0], sample)
        return [np.float32(np.median(np.concatenate([p[n] for p in parts]))) for n in range(len(parts[0]))]

    def _sigma_b(self, rows: slice, at: np.ndarray) -> np.ndarray:
        """σ of the modulation B (DN) at the band's flat indices `at`."""
        return self.noise.sigma(self.background[rows].ravel()[at]) * self.sqrt_2n

    def _pair_bound(self, rows: slice, at: np.ndarray, i: int, j: int) -> np.ndarray:
        """The disagreement (rad, finest fringe) frequencies i and j may show at `at` without a
        second path: `interreflection_sigmas` of the pair's predicted noise, at least
        `interreflection_min_rad`."""
        f_max, sigma_b = max(self.fringes), self._sigma_b(rows, at)
        noise = [sigma_b / np.maximum(self.modulation[n][rows].ravel()[at], np.float32(1e-6))
                 * np.float32(f_max / self.fringes[n]) for n in (i, j)]
        bound = np.hypot(*noise)
        bound *= np.float32(self.settings.interreflection_sigmas)
        return np.maximum(bound, np.float32(self.settings.interreflection_min_rad), out=bound)

    def mask(self, usable: np.ndarray, order_error: np.ndarray) -> np.ndarray:
        """The pixels masked as "interreflection"; removes them from `usable` and
        `order_error` (in place): one reason per corrupted pixel, its own."""
        s = self.settings
        bands = band_slices(usable.shape[0])
        candidates = [usable[b] & ~order_error[b] for b in bands]
        pair_medians = self._medians(candidates, self._pair_devs)
        ratio_medians = self._medians([usable[b] for b in bands], lambda rows, at: [self._log_ratio(rows, at)[0]])
        ratio_median = ratio_medians[0] if ratio_medians is not None else None
        out = np.zeros(usable.shape, bool)
        min_rad = np.float32(s.interreflection_min_rad)
        ratio_limit = np.float32(np.log1p(s.interreflection_ratio))
        if ratio_median is not None:  # ratios surely within the limit (1e-4 spares log's rounding)
            inside = (np.exp(float(ratio_median) - float(ratio_limit)) * (1 + 1e-4),
                      np.exp(float(ratio_median) + float(ratio_limit)) * (1 - 1e-4))

        def band(rows: slice) -> None:
            k = rows.start // CHUNK_ROWS
            hit = out[rows].ravel()
            if pair_medians is not None:  # a pixel within min_rad of a pair's median needs no noise bound
                for (i, j), dev, median in zip(self.pairs, self._pair_devs(rows), pair_medians):
                    dev -= median
                    np.abs(dev, out=dev)
                    at = np.flatnonzero(candidates[k] & (dev > min_rad))
                    hit[at] |= dev.ravel()[at] > self._pair_bound(rows, at, i, j)
            if ratio_median is not None:  # the log and the noise only for ratios near or past the limit
                ratio = np.maximum(self.modulation[self.fine][rows], np.float32(1e-6))
                ratio /= np.maximum(self.modulation[self.coarse][rows], np.float32(1e-6))
                at = np.flatnonzero(usable[rows] & ~((ratio > inside[0]) & (ratio < inside[1])))
                departure, bf, bc = self._log_ratio(rows, at)
                departure -= ratio_median
                np.abs(departure, out=departure)
                sigma = self._sigma_b(rows, at) * np.sqrt(1.0 / bf ** 2 + 1.0 / bc ** 2)
                hit[at] |= (departure > ratio_limit) & (departure > np.float32(s.interreflection_sigmas) * sigma)
            order_error[rows] &= ~out[rows]
            usable[rows] &= ~out[rows]

        in_bands(usable.shape[0], band)
        return out


def read_complementary_code(bits: list[np.ndarray], background: np.ndarray, modulation: np.ndarray,
                            certainty: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read a complementary Gray code (n regular bits, then the half-period bit), each bit
    against the background A. Returns (the half-period index the whole code names, the
    count of regular bits read ambiguously, whether the half-period bit is ambiguous); a
    bit reads clearly when |I − A| exceeds `certainty`·B."""
    code = np.zeros(background.shape, dtype=np.int32)
    unclear = np.zeros(background.shape, dtype=np.int32)
    margin = np.float32(certainty) * modulation
    for b, frame in enumerate(bits):
        diff = frame.astype(np.float32) - background
        code = (code << 1) | (diff > 0)
        ambiguous = np.abs(diff) < margin
        if b < len(bits) - 1:
            unclear += ambiguous
    return gray_to_binary(code, len(bits)), unclear, ambiguous


def _graycode_unwrap(wrapped: np.ndarray, bits: list[np.ndarray], background: np.ndarray,
                     modulation: np.ndarray, certainty: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Absolute phase from complementary Gray code (Wu et al.), where it is unreliable, the
    half-period index the code names and where every bit of it reads clearly (for the checks).

    The extra half-period bit picks the fringe order that is safe at the code boundaries:
    away from a period boundary (π/2 < φ < 3π/2) every regular bit must read clearly, and
    near one only the single bit that changes there may be ambiguous; the complementary bit
    must read clearly wherever it is used. Blur wider than a quarter period breaks this, and
    those pixels are returned as order errors instead of being unwrapped by a guess."""
    half, unclear, complementary_unclear = read_complementary_code(bits, background, modulation, certainty)
    k1 = half >> 1  # the regular bits' period index (a Gray prefix names the same range)
    k2 = (half + 1) >> 1
    quarter = np.float32(np.pi / 2)
    near_boundary = (wrapped <= quarter) | (wrapped >= 3 * quarter)
    order = np.where(wrapped <= quarter, k2, np.where(wrapped >= 3 * quarter, k2 - 1, k1))
    unreliable = np.where(near_boundary, complementary_unclear | (unclear > 1), unclear > 0)
    clear = (unclear == 0) & ~complementary_unclear
    return wrapped + TWO_PI * order.astype(np.float32), unreliable, half, clear


def gray_phase_offset(wrapped: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Per pixel, how far (rad, (−π, π]) the wrapped phase sits from the centre of the
    half period its Gray code names: within ±π/2 when code and phase agree."""
    r = wrapped - np.float32(np.pi) * ((half & 1).astype(np.float32) + np.float32(0.5))
    r -= TWO_PI * np.rint(r / TWO_PI)
    return r


def _typical_step(sample: np.ndarray) -> np.float32:
    """Median of the |differences| between neighbours in `sample` (every 16th line of the
    map: cheap, robust), NaN left out."""
    sample = np.abs(sample[~np.isnan(sample)])
    return np.float32(np.median(sample)) if sample.size else np.float32(0.0)


def interreflection_slivers(valid: np.ndarray, interreflection: np.ndarray, reach_px: int) -> np.ndarray:
    """Valid pixels (H, W) in strips narrower than `reach_px` + 1 (those a (reach_px + 1)²
    opening of `valid` removes) within `reach_px` pixels of an `interreflection` pixel:
    what a second path that outshines the direct light leaves among the pixels it corrupts."""
    size = reach_px + 1
    opened = cv2.morphologyEx(valid.view(np.uint8), cv2.MORPH_OPEN, np.ones((size, size), np.uint8))
    near = cv2.dilate(interreflection.view(np.uint8), np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8))
    return valid & ~opened.view(bool) & near.view(bool)


def band_slices(height: int) -> list[slice]:
    """The bands of CHUNK_ROWS rows (the last one shorter) that `in_bands` works on."""
    return [slice(r, min(r + CHUNK_ROWS, height)) for r in range(0, height, CHUNK_ROWS)]


_BAND_THREAD = "slscan-band"
_band_pool: ThreadPoolExecutor | None = None


def _forget_band_pool() -> None:
    global _band_pool
    _band_pool = None  # a forked child has none of the parent's threads


os.register_at_fork(after_in_child=_forget_band_pool)


def in_bands(height: int, work: Callable[[slice], Any]) -> list[Any]:
    """`work(rows)` for the bands of `band_slices` on every core, in order: on one pool of
    threads kept for the process (starting two threads per call cost 0.4 ms, 8 ms under
    load, and a decode + reconstruction makes 13 calls); inline when called from a band."""
    global _band_pool
    bands = band_slices(height)
    if threading.current_thread().name.startswith(_BAND_THREAD):  # a nested call would wait on its own pool
        return [work(b) for b in bands]
    if _band_pool is None:
        _band_pool = ThreadPoolExecutor(max_workers=os.cpu_count() or 1, thread_name_prefix=_BAND_THREAD)
    return list(_band_pool.map(work, bands))


def _unreliable_regions(coordinate: np.ndarray, valid: np.ndarray, period_px: float,
                        min_region_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Fringe-order errors that came in clusters, found spatially.

    The coordinate map is cut wherever neighbours differ by more than half a fringe period
    beyond the map's typical neighbour step (a depth step or an order error), both pixels of
    the pair being rejected as possibly mixed; regions
    smaller than `min_region_px` left between the cuts are order-error islands.
    Returns (islands, cut pixels)."""
    c = coordinate  # NaN where not valid
    h = c.shape[0]
    half = np.float32(period_px / 2.0)
    with np.errstate(invalid="ignore"):
        limit_x = half + _typical_step(c[::16, 1:] - c[::16, :-1])
        limit_y = half + _typical_step(c[1:, ::16] - c[:-1, ::16])
    cut = np.empty(valid.shape, dtype=bool)

    def cuts(rows: slice) -> None:
        a, b = rows.start, rows.stop
        top, bottom = max(a - 1, 0), min(b + 1, h)
        own = c[a:b]
        band = np.zeros(own.shape, dtype=bool)
        with np.errstate(invalid="ignore"):
            jump = np.abs(own[:, 1:] - own[:, :-1]) > limit_x
            band[:, :-1] |= jump  # both pixels of a jump: at a depth edge either may be a mixed pixel
            band[:, 1:] |= jump
            ext = c[top:bottom]
            jump = np.abs(ext[1:] - ext[:-1]) > limit_y  # pair p joins rows top + p and top + p + 1
        off = a - top
        band[max(0, 1 - off):] |= jump[max(0, off - 1):off - 1 + (b - a)]  # with the row above
        below = jump[off:off + (b - a)]
        band[:len(below)] |= below  # with the row below
        cut[rows] = band & valid[rows]

    in_bands(h, cuts)
    return small_regions(valid & ~cut, min_region_px), cut


def small_regions(foreground: np.ndarray, min_px: int) -> np.ndarray:
    """Pixels of the 4-connected regions of `foreground` smaller than `min_px` pixels:
    labelled band by band on every core (OpenCV), the bands' labels joined where a region
    crosses from one band's last row into the next band's first row."""
    h = foreground.shape[0]

    def label(rows: slice) -> tuple[np.ndarray, np.ndarray]:
        # areas by bincount: OpenCV's stats (boxes, centroids too) cost 4x the labelling
        n, labels = cv2.connectedComponents(foreground[rows].view(np.uint8), connectivity=4, ltype=cv2.CV_32S)
        return labels, np.bincount(labels.ravel(), minlength=n)

    parts = in_bands(h, label)
    offsets = np.cumsum([0] + [len(area) for _, area in parts[:-1]])
    area = np.concatenate([area for _, area in parts])
    area[offsets] = 0  # each band's label 0: background
    a, b = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]  # label pairs joined across band edges
    for k in range(len(parts) - 1):
        u, v = offsets[k] + parts[k][0][-1], offsets[k + 1] + parts[k + 1][0][0]
        both = (u > offsets[k]) & (v > offsets[k + 1])  # foreground above and below the edge
        a.append(u[both])
        b.append(v[both])
    root = _joined(len(area), np.concatenate(a), np.concatenate(b))
    small = np.bincount(root, weights=area, minlength=len(area))[root] < min_px
    small[offsets] = False
    islands = np.empty(foreground.shape, dtype=bool)

    def lookup(rows: slice) -> None:
        k = rows.start // CHUNK_ROWS
        labels, area = parts[k]
        band_small = small[offsets[k]:offsets[k] + len(area)]  # by the band's own labels
        if band_small.any():
            np.take(band_small, labels, out=islands[rows])
        else:
            islands[rows] = False

    in_bands(h, lookup)
    return islands


def _joined(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For nodes 0 … n−1 joined by the edges (a[i], b[i]): each node's representative (the
    least node of its connected set), by hooking roots onto the lesser root and pointer
    jumping until every edge joins equal roots."""
    root = np.arange(n)
    while a.size:
        ra, rb = root[a], root[b]
        unmet = ra != rb
        if not unmet.any():
            break
        ra, rb = ra[unmet], rb[unmet]
        least = np.minimum(ra, rb)
        np.minimum.at(root, ra, least)
        np.minimum.at(root, rb, least)
        while True:
            up = root[root]
            if np.array_equal(up, root):
                break
            root = up
    return root


_CHI2_MEDIAN = (0.4549, 0.6931, 0.7887, 0.8392, 0.8703, 0.8914, 0.9066, 0.9180, 0.9270, 0.9342)  # median(χ²_k)/k


def harmonic_basis(delta: np.ndarray) -> np.ndarray:
    """(N, 1 + 2K): the background and the fringe's harmonics 1..K at the N phase steps
    `delta` (rad). A projector's gamma puts harmonics 2..K in every pixel (the 2nd at ~30 % of
    the fundamental without gamma compensation); an N-step phase is blind to them all but
    N ± 1, so they are part of what the frames should be, not noise or a fault. K is the
    largest leaving N − 1 − 2K ≥ 3 degrees of freedom in the residual (K = 4 for 12 steps, 1
    below 8 steps: the residual then holds whatever harmonics there are)."""
    steps = len(delta)
    harmonics = range(1, max(1, (steps - 4) // 2) + 1)
    return np.stack([np.ones(steps)] + [f(k * delta) for k in harmonics for f in (np.cos, np.sin)], axis=1)


def residual_dof(steps: int) -> int:
    """Degrees of freedom of an N-step fit's residual about `harmonic_basis`."""
    return steps - 1 - 2 * max(1, (steps - 4) // 2)


def fit_noise(stack: np.ndarray, blocks: list[list[int]], steps: int, sign: int, full_scale: float) -> NoiseModel:
    """The intensity-noise model of a stack, from ~20 000 of its pixels (32 rows): the
    residual of the N-step fit per pixel regressed on the background; with 3 steps, the
    background's fine texture (Immerkær's Laplacian estimate, an upper bound where the scene
    has texture).

    The fit holds the fringe's harmonics (`harmonic_basis`): left in the residual they would
    read as intensity noise (15 DN for 1.2 DN in an uncompensated 8-bit 12-step capture)."""
    h, w = stack.shape[1:]
    rs, cs = max(1, h // 32), max(1, w // 640)
    sub = [stack[k, ::rs, ::cs].astype(np.float64) for k in blocks[0]]
    if steps > 3:
        a_all, v_all = [], []
        basis = harmonic_basis(sign * 2.0 * np.pi * np.arange(steps) / steps)
        projector = np.eye(steps) - basis @ np.linalg.pinv(basis)
        for block in blocks:
            frames = np.stack([stack[k, ::rs, ::cs] for k in block]).reshape(steps, -1).astype(np.float64)
            ok = (frames.max(axis=0) < full_scale) & (frames.min(axis=0) > 0)
            res = projector @ frames[:, ok]
            a_all.append(frames[:, ok].mean(axis=0))
            v_all.append((res ** 2).sum(axis=0) / (steps - basis.shape[1]))
        a, v = np.concatenate(a_all), np.concatenate(v_all)
    else:
        mean = np.mean(sub, axis=0)
        lap = cv2.filter2D(mean, -1, np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64))[1:-1, 1:-1]
        a = mean[1:-1, 1:-1].ravel()
        v = (lap.ravel() ** 2) * (np.pi / 2) / 36.0 * steps  # σ_A² per pixel, back to one frame's σ_I²
    if a.size < 50:
        return NoiseModel(1.0, 0.0)
    # median variance in background bins (unbiased for the χ² of the residuals), then a line
    # through them with non-negative read and shot terms
    dof = residual_dof(steps) if steps > 3 else 1
    return _noise_line(a, v, _CHI2_MEDIAN[dof - 1] if dof <= len(_CHI2_MEDIAN) else (1 - 2 / (9 * dof)) ** 3)


def spatial_noise(stack: np.ndarray, block: list[int], orientation: str, full_scale: float) -> NoiseModel:
    """The intensity-noise model of a stack from its frames alone, without the N-step fit
    residual (which it can then judge): along the fringes (camera columns for vertical
    fringes, rows for horizontal) a frame varies only with the scene, so the second
    difference of neighbours, I[i−1] − 2I[i] + I[i+1], has variance 6·σ_I² plus the scene's
    fine texture and the fringes' tilt: an upper bound of the noise, from every 8th line of
    the phase frames of `block`, medians in background bins (χ²_1 unbiased)."""
    lines = stack[block, :, ::8] if orientation == "vertical" else np.swapaxes(stack[block, ::8, :], 1, 2)
    f = lines.astype(np.float64)  # (frames, along the fringes, across)
    d2 = f[:, :-2] - 2.0 * f[:, 1:-1] + f[:, 2:]
    inside = (f.max(axis=0) < full_scale) & (f.min(axis=0) > 0)  # not clipped in any frame
    ok = inside[:-2] & inside[1:-1] & inside[2:]
    if ok.sum() < 50:
        return NoiseModel(1.0, 0.0)
    return _noise_line(lines[:, 1:-1][:, ok].ravel(), (d2[:, ok] ** 2 / 6.0).ravel(), _CHI2_MEDIAN[0])


def _noise_line(a: np.ndarray, v: np.ndarray, unbias: float) -> NoiseModel:
    """σ_I² = read + shot·A through per-pixel variance samples `v` at levels `a`: the median
    of each of 8 level bins (divided by `unbias`, the median of the samples' χ² over its
    mean), a line with non-negative terms, read at least the quantisation 1/12 DN². The
    samples are put in order of level once (a radix sort where the levels are the frames'
    integers), so each bin is a slice."""
    order = np.argsort(a, kind="stable")
    a = a.take(order).astype(np.float64)
    v = v.take(order)
    edges = np.quantile(a, np.linspace(0, 1, 9))
    centres, medians = [], []
    for lo, hi in pairwise(edges):
        i0, i1 = np.searchsorted(a, lo, side="left"), np.searchsorted(a, hi, side="right")  # lo <= a <= hi
        if i1 - i0 >= 10:
            centres.append(np.median(a[i0:i1]))
            medians.append(np.median(v[i0:i1]) / unbias)
    c, m = np.array(centres), np.array(medians)
    shot, read = np.polyfit(c, m, 1) if len(c) >= 2 and np.ptp(c) > 0.05 * max(c.max(), 1.0) else (0.0, np.mean(m))
    if shot < 0:  # no shot noise visible: a constant
        shot, read = 0.0, float(np.mean(m))
    if read < 1.0 / 12.0:  # at least the quantisation noise; the shot term through the rest
        read = 1.0 / 12.0
        shot = max(float(np.sum((m - read) * c) / max(np.sum(c * c), 1e-12)), 0.0)
    return NoiseModel(float(read), float(shot))


def _rotation_cause(steps_off: float, steps: int) -> str:
    """The likely cause of a common phase offset of `steps_off` phase steps (of `steps`)."""
    k = round(steps_off) % steps
    if k and abs(steps_off - round(steps_off)) < 0.25:
        return (f"phase steps rotated by {k} of {steps} in every group (each frame showing the step {k} after its "
                f"own: a trigger out of step), or a phase origin {2 * np.pi * k / steps:.2f} rad off?")
    return "a wrong phase origin, or phase steps rotated within every group?"


def _frequency_samples(ps: PatternSet, extent: int, absolute: list[np.ndarray], modulation: list[np.ndarray],
                       sigma_b: np.ndarray, idx: np.ndarray) -> dict[str, np.ndarray]:
    """At the band's flat indices `idx`: each frequency's projector coordinate (px) from its
    absolute phase, its predicted noise (σ_I·sqrt(2/N)/B_i, with the patterns' own error
    `PATTERN_ERROR`, times P_i/(2π); `sigma_b` = σ_I·sqrt(2/N) there), and from them `q`,
    the weighted squared spread of the coordinates about their inverse-variance mean (χ² with
    F − 1 degrees of freedom when the frequencies agree), and `d`, the finest frequency's
    coordinate less the coarsest's (px)."""
    xs, ws = [], []
    pattern = 2.0 / ps.steps * PATTERN_ERROR ** 2  # rad²: the 8-bit patterns' own error
    for phi, b, fi in zip(absolute, modulation, ps.fringes):
        scale = extent / (2.0 * np.pi * fi)
        xs.append(phi.flat[idx].astype(np.float64) * scale)
        var = np.square(sigma_b / np.maximum(b.flat[idx], np.float32(1e-6)), dtype=np.float64) + pattern
        ws.append(1.0 / (var * scale ** 2))
    x, w = np.array(xs), np.array(ws)
    mean = (x * w).sum(axis=0) / w.sum(axis=0)
    fine, coarse = int(np.argmax(ps.fringes)), int(np.argmin(ps.fringes))
    return {"q": (np.square(x - mean) * w).sum(axis=0), "d": x[fine] - x[coarse]}


def _saturated(stack: np.ndarray, frames: list[int], full_scale: float) -> np.ndarray:
    """Pixels where any of the stack's `frames` reaches `full_scale`, in bands on every core."""
    out = np.empty(stack.shape[1:], dtype=bool)

    def band(rows: slice) -> None:
        peak = stack[frames[0], rows].copy()
        for k in frames[1:]:
            cv2.max(peak, stack[k, rows], dst=peak)
        out[rows] = peak >= full_scale

    in_bands(stack.shape[1], band)
    return out


def _frame_indices(specs: list[FrameSpec]) -> dict[tuple[str, FrameKind, int, int], int]:
    return {(s.orientation, s.kind, s.level, s.step): k for k, s in enumerate(specs)}


def decode(stack: np.ndarray, patterns: PatternSet, bit_depth: int, projector_size: tuple[int, int],
           settings: DecodeSettings = DEFAULT_DECODE_SETTINGS, sensor_noise: NoiseModel | None = None) -> DecodeResult:
    """Decode an (N, H, W) fringe stack taken with `patterns` on a projector of
    `projector_size` = (width, height) pixels. `sensor_noise`: the camera's intensity noise
    from its sensor model, when known; the consistency checks then judge the fit residual
    against it (else the noise is fitted to the frames, which cannot judge that residual).
    With `settings.self_check` a failed check raises `ConsistencyError`; without, the
    checks are only recorded (`DecodeResult.checks`) for the caller to judge with more."""
    patterns = patterns.for_projector(projector_size)
    specs = patterns.frames()
    if stack.ndim != 3 or stack.shape[0] != len(specs):
        raise DecodeError(f"pattern set '{patterns.family}' needs {len(specs)} frames of one size; "
                          f"got an array of shape {stack.shape}")
    if not np.issubdtype(stack.dtype, np.integer):
        raise DecodeError(f"frames must be integer images at their bit depth, got {stack.dtype}")
    index = _frame_indices(specs)
    conv = patterns.conventions
    full_scale = float(2 ** bit_depth - 1)
    phase_blocks = {o: [[index[(o, FrameKind.PHASE, lv, n)] for n in range(patterns.steps)]
                        for lv in range(len(patterns.fringes))] for o in patterns.orientations}
    all_phase = [k for o in patterns.orientations for block in phase_blocks[o] for k in block]
    saturated = np.zeros(stack.shape[1:], dtype=bool)
    if all_phase:  # judged on the frames that carry the measurement: a clipped binary frame still reads
        saturated = _saturated(stack, all_phase, full_scale)
        noise = fit_noise(stack, phase_blocks[patterns.orientations[0]], patterns.steps,
                          known(conv.step_sign, "step_sign"), full_scale)
    else:
        noise = NoiseModel(1.0, 0.0)
    refs = (stack[index[(patterns.orientations[0], FrameKind.WHITE, 0, 0)]].astype(np.float32),
            stack[index[(patterns.orientations[0], FrameKind.BLACK, 0, 0)]].astype(np.float32)) \
        if conv.references != "none" else None

    maps: dict[str, OrientationMaps] = {}
    checks: list[Check] = []
    check_noise, source = (sensor_noise, SENSOR_MODEL) if sensor_noise is not None else (noise, FITTED_MODEL)
    residual_noise = sensor_noise if sensor_noise is not None or patterns.steps < 4 else spatial_noise(
        stack, phase_blocks[patterns.orientations[0]][0], patterns.orientations[0], full_scale)
    for orientation in patterns.orientations:
        extent = projector_size[0] if orientation == "vertical" else projector_size[1]
        decoder = _OrientationDecoder(stack, patterns, orientation, extent, index, phase_blocks[orientation],
                                      saturated, refs, noise, full_scale, settings, check_noise, source,
                                      residual_noise)
        maps[orientation], found = decoder.run()
        checks += found
    if settings.self_check and failed(checks):
        raise ConsistencyError("", checks)
    backgrounds = [m.background for m in maps.values()]
    texture = backgrounds[0] if len(backgrounds) == 1 else (backgrounds[0] + backgrounds[1]) / 2
    valid_all = np.logical_and.reduce([m.valid for m in maps.values()])
    return DecodeResult(patterns, bit_depth, maps, texture, valid_all, checks)


@dataclass(eq=False)
class _OrientationDecoder:
    """Decoding of one fringe orientation (`decode` strings these together)."""

    stack: np.ndarray
    patterns: PatternSet
    orientation: str
    extent: int
    index: dict[tuple[str, FrameKind, int, int], int]
    blocks: list[list[int]]
    saturated: np.ndarray
    refs: tuple[np.ndarray, np.ndarray] | None
    noise: NoiseModel
    full_scale: float
    settings: DecodeSettings
    check_noise: NoiseModel  # the intensity noise the checks judge by (`noise_source`)
    noise_source: str
    residual_noise: NoiseModel | None  # the noise the fit residual is judged by: not fitted to it (None: not judged)

    def _frame(self, kind: FrameKind, level: int) -> np.ndarray:
        return self.stack[self.index[(self.orientation, kind, level, 0)]]

    def _pixel_code(self, frame: Callable[[FrameKind, int], np.ndarray],
                    contrast: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(coordinate, run length, readable, beyond the projector) from this orientation's
        pixel-code frames (`frame(kind, bit)`)."""
        ps = self.patterns
        diffs = [frame(FrameKind.GRAY, b).astype(np.float32) - frame(FrameKind.GRAY_INVERSE, b)
                 for b in range(ps.gray_bits(self.orientation))]
        threshold = np.float32(self.settings.code_certainty) * contrast
        coordinate, run, readable = read_pixel_code(diffs, np.maximum(threshold, np.float32(1.0)),
                                                    self.settings.max_dropped_bits)
        beyond = readable & ~(coordinate < self.extent)
        readable &= ~beyond
        return coordinate, run, readable, beyond

    def run(self) -> tuple[OrientationMaps, list[Check]]:
        """Per-pixel decoding in bands of CHUNK_ROWS rows on every core (the arrays of a band
        stay in cache; numpy and OpenCV release the GIL), then the spatial check on the whole
        map and the consistency checks (`scanner.decode_checks`) from every band's samples."""
        ps, s = self.patterns, self.settings
        if not ps.kind.has_phase:
            return self._pixel_graycode_only({"saturated": self.saturated})
        h, w = self.stack.shape[1:]
        n_freq = len(self.blocks)
        out = {name: np.empty((h, w), np.float32) for name in ("background", "phase", "weight", "coordinate")}
        wrapped = [np.empty((h, w), np.float32) for _ in range(n_freq)]
        modulation = [np.empty((h, w), np.float32) for _ in range(n_freq)]
        # each frequency's absolute phase scaled to the finest fringe, for the second-path test
        scaled = [np.empty((h, w), np.float32) for _ in range(n_freq)] if self._judges_paths else None
        reasons = ("shadow", "low_modulation", "order_error")
        masks = {"saturated": self.saturated, **{k: np.empty((h, w), bool) for k in reasons}}
        usable = np.empty((h, w), bool)
        beyond = np.empty((h, w), bool)

        def band(rows: slice) -> dict[str, Any]:
            b = self._band(rows, [(wrapped[i][rows], modulation[i][rows]) for i in range(n_freq)],
                           {name: out[name][rows] for name in out},
                           [a[rows] for a in scaled] if scaled is not None else None)
            for k in reasons:
                masks[k][rows] = b["masks"][k]
            usable[rows] = b["usable"]
            beyond[rows] = b["beyond"]
            return b["sums"]

        sums = in_bands(h, band)
        if scaled is not None:
            masks["interreflection"] = _SecondPaths(ps.fringes, scaled, modulation, background=out["background"],
                                                    noise=self.noise,
                                                    steps=ps.steps, settings=s).mask(usable, masks["order_error"])
        f_max = max(ps.fringes)
        maps = self._finish(masks, usable, out["coordinate"], phase=out["phase"], wrapped=wrapped,
                            modulation=modulation, background=out["background"],
                            weight=out["weight"], fringes=f_max)
        coded = [self._range(beyond, sum(b["readable"] for b in sums))] if ps.gray_bits(self.orientation) else []
        return maps, self._map_checks(sums, masks.get("interreflection")) + coded + self._ordering(maps)

    def _band(self, rows: slice, dest: list[tuple[np.ndarray, np.ndarray]], maps: dict[str, np.ndarray],
              scaled: list[np.ndarray] | None) -> dict[str, Any]:
        """The per-pixel work on rows `rows`: phases and modulations (written into `dest`, per
        frequency), masks, unwrapping (the family's, `_UNWRAP`), and the background, phase,
        weight and coordinate (written into `maps`' views of those rows), each frequency's
        absolute phase in units of the finest fringe (into `scaled`, when given); returns the
        masks and, in `sums`, the counts and the samples (every SAMPLE_STEP-th row and column)
        the checks judge."""
        ps, s, conv = self.patterns, self.settings, self.patterns.conventions
        stack = self.stack[:, rows]
        wrapped, modulation = [], []
        background = maps["background"]
        background.fill(0.0)
        for block, out in zip(self.blocks, dest):
            phi, b, a = phase_shift([stack[k] for k in block], ps.steps, conv.first_phase(ps.steps),
                                    known(conv.step_sign, "step_sign"), out)
            wrapped.append(phi)
            modulation.append(b)
            background += a
        saturated = self.saturated[rows]
        background /= np.float32(len(self.blocks))
        b_fine = modulation[ps.fringes.index(max(ps.fringes))]
        shadow = b_fine < s.min_contrast * np.maximum(background, 1e-6)
        masks = {"shadow": shadow, "low_modulation": ~shadow & (b_fine < s.min_modulation * self.full_scale)}
        usable = ~(saturated | masks["shadow"] | masks["low_modulation"])
        band = _Band(self, rows, stack, wrapped, modulation, background, usable, masks, {}, maps, scaled)
        _UNWRAP[ps.unwrapping](self, band)
        sums = band.sums
        sums["usable"], sums["order_bad"] = int(usable.sum()), int((masks["order_error"] & usable).sum())
        if self.judges_residual:
            sums["residual_z2"] = self._residual_z2(stack, band.at_samples())
        coordinate = np.multiply(maps["phase"], np.float32(self.extent / (2.0 * np.pi * band.f_max)),
                                 out=maps["coordinate"])
        coordinate -= np.float32(known(conv.pixel_centre, "pixel_centre"))
        if band.beyond is None:  # a fringe order beyond the projector's pixels is an order error
            band.beyond = self._beyond(coordinate, usable & ~masks["order_error"], band.sigma_of(band.finest))
            masks["order_error"] |= band.beyond
            sums["readable"] = sums["usable"]
        return {"masks": masks, "usable": usable, "sums": sums, "beyond": band.beyond}

    def _unwrap_complementary(self, band: _Band) -> None:
        """Phase unwrapped by a complementary Gray code of the periods (Wu et al.)."""
        masks, sums, maps, background, modulation = band.masks, band.sums, band.maps, band.background, band.modulation
        bits = [band.frame(FrameKind.GRAY, b) for b in range(self.patterns.gray_bits() + 1)]
        phase, masks["order_error"], half, clear = _graycode_unwrap(band.wrapped[0], bits, background,
                                                                    modulation[0], self.settings.gray_certainty)
        idx = band.at_samples()
        idx = idx[clear.flat[idx]]  # the code's edges judged where every bit reads clearly
        sums["gray_offset"] = gray_phase_offset(band.wrapped[0].flat[idx], half.flat[idx])
        sums["phase_sigma"] = np.hypot(self.check_noise.sigma(background.flat[idx]) / np.maximum(
            modulation[0].flat[idx], np.float32(1e-6)), np.float32(PATTERN_ERROR)) * band.sqrt_2n
        maps["phase"][...] = phase
        np.square(modulation[0], out=maps["weight"])

    def _unwrap_pixel_phase(self, band: _Band) -> None:
        """Phase unwrapped by OpenCV's Gray code of every projector pixel."""
        masks, sums, maps, usable, rows = band.masks, band.sums, band.maps, band.usable, band.rows
        conv, f_max, wrapped = self.patterns.conventions, band.f_max, band.wrapped
        contrast = self.refs[0][rows] - self.refs[1][rows] if self.refs is not None else \
            np.float32(2.0) * band.modulation[band.finest]
        coordinate_g, run, readable, beyond = self._pixel_code(band.frame, contrast)
        beyond &= usable
        band.beyond = beyond
        sums["readable"] = int(((readable | beyond) & usable).sum())
        predicted = (coordinate_g + np.float32(known(conv.pixel_centre, "pixel_centre"))) \
            * np.float32(2 * np.pi * f_max / self.extent)
        worst = np.zeros_like(band.background)
        phase = unwrap_step(predicted, 1.0, wrapped[0], worst)
        quant = np.float32(2 * np.pi * f_max / self.extent / np.sqrt(12.0) / np.pi)

        def code_sigma(idx: np.ndarray) -> np.ndarray:
            return np.hypot(band.sigma_of(0)(idx) / np.float32(np.pi), quant * run.flat[idx])

        masks["order_error"] = ~readable | _order_errors(worst, code_sigma, self.settings)
        idx = band.at_samples()
        sums["gray_offset"] = np.angle(np.exp(1j * (wrapped[0].flat[idx] - predicted.flat[idx])))
        maps["phase"][...] = phase
        np.square(band.modulation[0], out=maps["weight"])

    def _unwrap_temporal(self, band: _Band) -> None:
        """The frequencies unwrap each other (the family's `unwrap`); the phase is their
        inverse-variance combination."""
        ps, masks, sums, maps, f_max = self.patterns, band.masks, band.sums, band.maps, band.f_max
        absolute, residual = temporal(ps.kind).unwrap(ps.fringes, band.wrapped)

        def residual_sigma(idx: np.ndarray) -> np.ndarray:
            return _residual_sigma(ps, [band.sigma_of(lv)(idx) for lv in range(len(ps.fringes))])

        masks["order_error"] = _order_errors(residual, residual_sigma, self.settings)
        idx = band.at_samples()
        sums["frequencies"] = _frequency_samples(ps, self.extent, absolute, band.modulation,
                                                 self.check_noise.sigma(band.background.flat[idx]) * band.sqrt_2n, idx)
        sums["frequencies"]["at"] = idx + band.rows.start * band.usable.shape[1]  # flat in the image
        if band.scaled is not None:
            for phi_abs, fi, dst in zip(absolute, ps.fringes, band.scaled):
                np.multiply(phi_abs, np.float32(f_max / fi), out=dst)
        # inverse-variance combination of all frequencies, in units of the finest fringe
        phase, weight = maps["phase"], maps["weight"]
        phase.fill(0.0)
        weight.fill(0.0)
        for phi_abs, b, fi in zip(absolute, band.modulation, ps.fringes):
            w = np.square(b)
            w *= np.float32((fi / f_max) ** 2)
            weight += w
            w *= phi_abs
            phase += np.multiply(w, np.float32(f_max / fi), out=w)
        phase /= np.maximum(weight, np.float32(1e-12))

    def _beyond(self, coordinate: np.ndarray, judged: np.ndarray, phase_sigma: Callable[[np.ndarray], np.ndarray]
                ) -> np.ndarray:
        """The judged pixels whose coordinate lies beyond the projector's light (its pixels
        −0.5 .. W − 0.5, and one pixel more its lens blurs the edge pixels' light into) by more
        than 5 σ of its noise (`phase_sigma` per flat index, rad of the finest fringe)."""
        half = np.float32(1.5)
        idx = np.flatnonzero(judged & ~((coordinate > -half) & (coordinate < np.float32(self.extent) - half)))
        out = np.zeros(judged.shape, bool)
        if idx.size:
            c = coordinate.flat[idx]
            tol = np.float32(5.0 * self.extent / (2.0 * np.pi * max(self.patterns.fringes))) * phase_sigma(idx)
            out.flat[idx] = (c < -half - tol) | (c > np.float32(self.extent) - half + tol)
        return out

    def _residual_z2(self, stack: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Per step group (row) and sample pixel (flat indices `idx` of the band `stack`), the
        N-step fit's residual sum of squares (about the background and the fringe's harmonics,
        `harmonic_basis`) in units of each frame's predicted variance (the sensor model's σ_I²
        at the group's mean, and the patterns' own error): χ² with `residual_dof(N)` degrees of
        freedom when the frames are what the pattern set says."""
        ps, conv, noise = self.patterns, self.patterns.conventions, self.residual_noise
        if noise is None:
            raise DecodeError("the fit residual is judged only against a noise model (`judges_residual`)")
        sign = known(conv.step_sign, "step_sign")
        delta = conv.first_phase(ps.steps) + sign * 2.0 * np.pi * np.arange(ps.steps) / ps.steps
        basis = harmonic_basis(delta)
        residual = np.eye(ps.steps) - basis @ np.linalg.pinv(basis)  # (N, N): the fit's residual projector
        cos_sin = np.linalg.pinv(basis)[1:3]  # (2, N): B·cos and B·sin of the fit's fundamental
        z2 = np.zeros((len(self.blocks), idx.size))
        for g, block in enumerate(self.blocks):
            frames = stack[block].reshape(ps.steps, -1)[:, idx].astype(np.float64)
            res = residual @ frames
            b2 = np.square(cos_sin @ frames).sum(axis=0)
            var = np.square(noise.sigma(frames.mean(axis=0)), dtype=np.float64) + PATTERN_ERROR ** 2 * b2
            z2[g] = (res * res).sum(axis=0) / var
        return z2

    @property
    def judges_residual(self) -> bool:
        """Whether this decode judges the N-step fit's residual: N >= 4 (three steps fit any
        three values) against a noise model that did not come from that residual (the sensor
        model, or the frames' spatial noise along the fringes: `spatial_noise`)."""
        return self.patterns.steps >= 4 and self.residual_noise is not None

    def _map_checks(self, sums: list[dict[str, Any]], second: np.ndarray | None) -> list[Check]:
        """The checks this orientation's maps support (docs/consistency.md), from the bands'
        samples. `second`: the pixels masked as a second light path (interreflection), whose
        frequencies disagree by physics the model of one path does not cover: left out of the
        frequencies' checks (the mask takes what departs from the image's median disagreement,
        so a common offset or a disagreement that grows across the image is still judged on
        the pixels it leaves). When it takes most of them, the median it departs from is not
        one path's (a projector's uncompensated gamma moves every pixel): all are judged."""
        ps, o = self.patterns, self.orientation
        total = {k: sum(b.get(k, 0) for b in sums) for k in ("usable", "order_bad")}
        joined = {k: np.concatenate([b[k] for b in sums], axis=-1) for k in ("residual_z2", "gray_offset",
                                                                           "phase_sigma") if k in sums[0]}
        accuracy = SENSOR_MODEL_ACCURACY if self.noise_source == SENSOR_MODEL else FITTED_MODEL_ACCURACY
        out: list[Check] = []
        if ps.steps >= 3:
            if "residual_z2" in joined:
                z2 = joined["residual_z2"]
                worst = self.blocks[int(np.argmax(np.median(z2, axis=1)))] if z2.shape[1] else [0]
                spatial = self.noise_source != SENSOR_MODEL
                out.append(scale_check("phase_residual", o, z2.sum(axis=0),
                                       dof=len(self.blocks) * residual_dof(ps.steps),
                                       accuracy=FITTED_MODEL_ACCURACY if spatial else SENSOR_MODEL_ACCURACY,
                                       noise_source=SPATIAL_MODEL if spatial else self.noise_source,
                                       cause=f"the frames do not follow the patterns: frame {worst[0]} (step group "
                                             f"{worst[0]}..{worst[-1]}) fits worst; frames swapped, repeated or from "
                                             f"another scan?", what="each pixel's N-step fit residual"))
            else:
                out.append(not_judged("phase_residual", o, "x noise", "three steps leave no residual"))
        if "frequencies" in sums[0]:
            at = np.concatenate([b["frequencies"]["at"] for b in sums])
            one_path = ~second.ravel()[at] if second is not None else np.ones(at.size, bool)
            if one_path.size and one_path.mean() < 0.5:
                # the mask's premise (most pixels on one path) fails: judge them all
                one_path[:] = True
            q = np.concatenate([b["frequencies"]["q"] for b in sums])[one_path]
            d = np.concatenate([b["frequencies"]["d"] for b in sums])[one_path]
            out.append(scale_check("frequency_agreement", o, q, dof=len(ps.fringes) - 1, accuracy=accuracy,
                                   noise_source=self.noise_source,
                                   cause="a wrong fringe count, frames from another scan, or frequencies out of order?",
                                   what="the frequencies' spread about their mean coordinate"))
            out.append(self._frequency_offset(d))
        if "gray_offset" in joined:
            out.append(self._gray_offset(joined["gray_offset"]))
        if "phase_sigma" in joined:
            out.append(self._gray_edges(joined["gray_offset"], joined["phase_sigma"]))
        out.append(majority_check("fringe_orders", o, total["order_bad"] / max(total["usable"], 1),
                                  judged=total["usable"],
                                  unit="of usable pixels",
                                  expected="a fringe order consistent with the noise on most pixels",
                                  cause="wrong fringe counts, frame order or projector size, or phase steps rotated by "
                                        "half a group (every phase half a period off: no order fits)?"))
        return out

    def _frequency_offset(self, d: np.ndarray) -> Check:
        """The finest frequency's coordinate less the coarsest's, at its median: 0 when the
        frames follow the set; a common phase offset ε (a step rotation 2π·k/N, a wrong phase
        origin) shifts each frequency's coordinate by ε·P_i/(2π), so this by ε·(P_f − P_c)/(2π)."""
        ps = self.patterns
        fault = self.extent * (1 / max(ps.fringes) - 1 / min(ps.fringes)) / ps.steps  # one step's rotation (px)
        if d.size < MIN_JUDGED:
            return not_judged("frequency_offset", self.orientation, "px", f"{d.size} pixels")
        se = 1.2533 * float(np.std(d)) / np.sqrt(d.size)  # standard error of a median
        offset = float(np.median(d))
        return offset_check("frequency_offset", self.orientation, offset, standard_error=se, fault=fault, unit="px",
                            what="the median of the finest less the coarsest frequency's coordinate",
                            cause=_rotation_cause(offset / fault if fault else 0.0, ps.steps), judged=int(d.size))

    def _gray_offset(self, r: np.ndarray) -> Check:
        """The phase's common offset from where the Gray code says it is (rad, circular mean):
        0 when they agree; a rotation of the steps by k adds 2π·k/N, a wrong origin a
        multiple of π/2."""
        if r.size < MIN_JUDGED:
            return not_judged("gray_offset", self.orientation, "rad", f"{r.size} pixels")
        z = np.mean(np.exp(1j * r.astype(np.float64)))
        spread = np.sqrt(max(-2.0 * np.log(max(abs(z), 1e-9)), 0.0))
        steps = self.patterns.steps
        fault = min(2.0 * np.pi / steps, np.pi / 2)
        offset = float(np.angle(z))
        return offset_check("gray_offset", self.orientation, offset, standard_error=spread / np.sqrt(r.size),
                            fault=fault, unit="rad",
                            what="the phase's mean offset from the Gray code's period",
                            cause=_rotation_cause(offset * steps / (2 * np.pi), steps), judged=int(r.size))

    def _gray_edges(self, r: np.ndarray, phase_sigma: np.ndarray) -> Check:
        """Where the complementary Gray code, read clearly, and the phase disagree: a phase
        outside the half period the code names (|r| > π/2) by more than z σ_φ (z for a
        one-sided 1e-3) plus one projector pixel of phase. A code's edge lies between two
        projector pixels while the phase's period may start anywhere within a pixel of it
        (the pixel-centre convention, the 8-bit patterns, blur), so no noise or convention
        carries a pixel further, and noise does so to at most 1e-3 of the pixels wherever in
        the half period they lie: the count is at most Poisson(1e-3·n). A wrong period count
        or a step rotation moves whole stretches of the map across."""
        name, o = "gray_edges", self.orientation
        if r.size < MIN_JUDGED:
            return not_judged(name, o, "pixels", f"{r.size} pixels")
        per_pixel = 1e-3
        accuracy = SENSOR_MODEL_ACCURACY if self.noise_source == SENSOR_MODEL else FITTED_MODEL_ACCURACY
        z = normal_isf(per_pixel) * (1.0 + accuracy)
        pixel = 2.0 * np.pi * self.patterns.fringes[0] / self.extent  # rad per projector pixel
        observed = int(np.count_nonzero(np.abs(r) - np.pi / 2 > z * phase_sigma + pixel))
        threshold = poisson_quantile(1.0 - ALPHA, per_pixel * r.size)
        return Check(name, o, float(observed), threshold, "pixels",
                     f"only noise puts the phase more than a projector pixel outside the half period the code "
                     f"names (at most {per_pixel:g} of {r.size})", observed <= threshold,
                     "a wrong period count, or phase steps rotated?",
                     f"{ALPHA:g} (Poisson bound, the noise model within ±{accuracy:.0%} in σ)", int(r.size))

    def _range(self, beyond: np.ndarray, readable: int) -> Check:
        """A Gray code names a period or pixel the projector may not have: each such pixel is
        masked (an order error). A misread code lands there at isolated pixels (the spatial
        check's `min_region_fraction` removes such islands from any map); a wrong projector
        size or period count puts whole regions there, which refuses the decode. (Phase-only
        sets unwrap within the projector's extent: their pixels beyond are masked, not judged.)"""
        name, o = "projector_range", self.orientation
        if readable < MIN_JUDGED:
            return not_judged(name, o, "of decoded pixels", f"{readable} decoded pixels")
        coherent = int(np.count_nonzero(beyond & ~small_regions(beyond, self.min_region)))
        return Check(name, o, coherent / readable, 0.0, "of decoded pixels",
                     f"no region of {self.min_region} px or more decodes beyond the projector's {self.extent} pixels",
                     coherent == 0, "a wrong projector size or period count?",
                     "0 under the model (misreads are isolated pixels)", readable,
                     figures={"beyond_pixels": int(np.count_nonzero(beyond)), "in_regions": coherent})

    @property
    def min_region(self) -> int:
        """The least area (px) of a region the spatial check keeps (`min_region_fraction`)."""
        return max(1, int(self.settings.min_region_fraction * self.stack.shape[1] * self.stack.shape[2]))

    def _ordering(self, maps: OrientationMaps) -> list[Check]:
        return [ordering(maps.coordinate, maps.valid, maps.coordinate_sigma, maps.period_px, self.orientation,
                         SAMPLE_STEP)]

    @property
    def _judges_paths(self) -> bool:
        """Whether this decode looks for second light paths (several phase-shift frequencies)."""
        return (self.settings.interreflection and self.patterns.unwrapping.by_frequencies
                and len(self.patterns.fringes) > 1)

    def _pixel_graycode_only(self, masks: dict[str, np.ndarray]) -> tuple[OrientationMaps, list[Check]]:
        """OpenCV's GrayCodePattern alone: the coordinate is the pixel (run) the code names."""
        s = self.settings
        if self.refs is not None:
            white, black = self.refs
            background = (white + black) * np.float32(0.5)
            contrast = white - black
        else:
            pairs = [tuple(self._frame(kind, b).astype(np.float32) for kind in PIXEL_CODE_PAIR)
                     for b in range(self.patterns.gray_bits(self.orientation))]
            background = sum(p + q for p, q in pairs) * np.float32(0.5 / len(pairs))
            contrast = np.max([np.abs(p - q) for p, q in pairs], axis=0)
        b = contrast * np.float32(0.5)
        masks["shadow"] = b < s.min_contrast * np.maximum(background, 1e-6)
        masks["low_modulation"] = ~masks["shadow"] & (b < s.min_modulation * self.full_scale)
        usable = ~(masks["shadow"] | masks["low_modulation"])
        coordinate, run, readable, beyond = self._pixel_code(self._frame, contrast)
        masks["order_error"] = ~readable
        weight = np.float32(12.0) / np.square(run, dtype=np.float32)  # 1 / variance of a uniform run (px⁻²)
        phase = (coordinate + np.float32(0.5)) * TWO_PI  # one "fringe" per projector pixel
        maps = self._finish(masks, usable, coordinate, phase=phase, wrapped=[], modulation=[b], background=background,
                            weight=weight, fringes=float(self.extent))
        return maps, [self._range(beyond & usable, int(((readable | beyond) & usable).sum()))] + self._ordering(maps)

    def _finish(self, masks: dict[str, np.ndarray], usable: np.ndarray, coordinate: np.ndarray, *, phase: np.ndarray,
                wrapped: list[np.ndarray], modulation: list[np.ndarray], background: np.ndarray,
                weight: np.ndarray, fringes: float) -> OrientationMaps:
        s = self.settings
        valid = np.empty_like(usable)
        order_error = masks["order_error"]
        nan = np.float32(np.nan)

        def prepare(rows: slice) -> None:
            order_error[rows] &= usable[rows]  # reasons stay distinct: an order error is judged on a usable phase
            np.logical_and(usable[rows], ~order_error[rows], out=valid[rows])
            np.copyto(coordinate[rows], nan, where=~valid[rows])

        in_bands(valid.shape[0], prepare)
        islands = None
        if s.spatial_check:
            islands, masks["discontinuity"] = _unreliable_regions(coordinate, valid, self.extent / fringes,
                                                                  self.min_region)

        def finish(rows: slice) -> None:
            if islands is not None:
                order_error[rows] |= islands[rows]
                valid[rows] &= ~(islands[rows] | masks["discontinuity"][rows])
            invalid = ~valid[rows]
            np.copyto(coordinate[rows], nan, where=invalid)
            np.copyto(phase[rows], nan, where=invalid)

        in_bands(valid.shape[0], finish)
        if "interreflection" in masks and masks["interreflection"].any():  # no slivers near no masked pixel
            slivers = interreflection_slivers(valid, masks["interreflection"], s.sliver_px)
            masks["interreflection"] |= slivers
            valid &= ~slivers
            coordinate[slivers] = nan
            phase[slivers] = nan
        return OrientationMaps(self.orientation, coordinate, phase, wrapped, modulation, background, weight, masks,
                               valid, fringes, self.extent, self.noise, max(self.patterns.steps, 1))


_UNWRAP: dict[Unwrapping, Callable[[_OrientationDecoder, _Band], None]] = {
    Unwrapping.COMPLEMENTARY: _OrientationDecoder._unwrap_complementary,
    Unwrapping.PIXEL_PHASE: _OrientationDecoder._unwrap_pixel_phase,
    Unwrapping.TEMPORAL: _OrientationDecoder._unwrap_temporal,
}  # how a band's fringe order is found, per the family's unwrapping (pixel only: `_pixel_graycode_only`)


@dataclass(eq=False)
class _Band:
    """One band of rows in `_OrientationDecoder._band`: its frames (`stack`), each frequency's
    wrapped phase and modulation B, the background A (DN), the usable pixels, and what the
    unwrapping writes: the masks, the checks' samples (`sums`), the maps' views of these rows
    and, for the second-path test, each frequency's absolute phase scaled to the finest
    (`scaled`); `beyond`: the pixels a code names beyond the projector (None: judged after)."""

    decoder: _OrientationDecoder
    rows: slice
    stack: np.ndarray
    wrapped: list[np.ndarray]
    modulation: list[np.ndarray]
    background: np.ndarray
    usable: np.ndarray
    masks: dict[str, np.ndarray]
    sums: dict[str, Any]
    maps: dict[str, np.ndarray]
    scaled: list[np.ndarray] | None
    beyond: np.ndarray | None = None

    @property
    def f_max(self) -> float:
        return max(self.decoder.patterns.fringes)

    @property
    def finest(self) -> int:
        """The index of the finest frequency."""
        return self.decoder.patterns.fringes.index(self.f_max)

    @property
    def sqrt_2n(self) -> np.float32:
        return np.float32(np.sqrt(2.0 / self.decoder.patterns.steps))

    def sigma_of(self, level: int) -> Callable[[np.ndarray], np.ndarray]:
        """The phase noise (rad) of frequency `level` at flat indices of the band."""
        d = self.decoder
        return lambda idx: d.noise.sigma(self.background.flat[idx]) * self.sqrt_2n / np.maximum(
            self.modulation[level].flat[idx], np.float32(1e-6))

    def frame(self, kind: FrameKind, level: int) -> np.ndarray:
        d = self.decoder
        return self.stack[d.index[(d.orientation, kind, level, 0)]]

    def at_samples(self) -> np.ndarray:
        """Flat indices (in the band) of the judged sample pixels: usable, no order error."""
        grid = np.zeros(self.usable.shape, bool)
        grid[(-self.rows.start) % SAMPLE_STEP::SAMPLE_STEP, ::SAMPLE_STEP] = True
        return np.flatnonzero(grid & self.usable & ~self.masks["order_error"])
