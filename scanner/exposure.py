"""Exposure for shiny and dark parts: automatic choice from a short pre-capture, and the
per-pixel fusion of a pattern set captured at several exposures (HDR).

Automatic exposure. A pre-capture of three frames (full white, black, and one fringe frame of
the pattern set's finest frequency) at a probe exposure t0 gives, per pixel of the region of
interest (ROI: pixels the projector lights, white − black above `ROI_MIN_CONTRAST` of full
scale, inside the optional rectangle), the projector's light W − K and the fringes' contrast
(the fringe frame's mean |F − mid| against (W − K)/2, times π/2, over the ROI). A camera is
linear in exposure, so at exposure t a pixel peaks at W·t/t0 and has modulation
B(t) = c·(W − K)/2·t/t0: the saturation and modulation histograms at any t follow from the
probe. A pixel is *covered* at t when it stays below `SATURATION_LEVEL` of full scale and its
B reaches `GOOD_MODULATION` of full scale: three-frequency heterodyne unwrapping amplifies the
phase noise ~15x (beat of 6 fringes), so a rare order error needs B ≳ 35 σ_I; for a 10 ke
full-well sensor at 12 bits (shot-noise σ_I ≈ 14 DN at 500 DN) that is ~10 % of full scale.
When the probe itself saturates more than `PROBE_MAX_SATURATED` of the ROI, it is repeated
at t0/8 (at most `PROBE_TRIES`).
  - `auto`: the one exposure (of a half-stop grid within the camera's range) that covers the
    most ROI pixels, the longest of those within 0.2 % of the best (less noise);
  - `hdr`: exposures chosen greedily, each covering the most pixels not yet covered, until one
    adds less than `HDR_MIN_GAIN` of the ROI or `HDR_MAX_EXPOSURES` are chosen.
The choice and its reason (coverages, what saturates, what is too dark) go into the manifest.
Projector brightness is not adjusted: no projector interface in slscan exposes it, so the
reason says so.

Fusion. Each exposure's stack is decoded on its own (`scanner.decode`: its masks, noise model
and predicted phase noise), then every pixel takes all its maps from the exposure whose phase
is valid with the least predicted noise (the best unsaturated exposure with the most
modulation relative to its noise); a pixel valid in none keeps the reasons of the longest
exposure that does not saturate it (else the shortest). The fused phase noise per pixel is
that exposure's prediction, kept in `phase_sigma` (maps.npz) for the uncertainty work; the
chosen exposure index per pixel is `exposure_index`. Texture is scaled to the shortest
exposure so it stays within full scale.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from scanner.decode import DecodeResult, OrientationMaps
from scanner.errors import ConfigError
from scanner.pattern_families import FrameKind
from scanner.patterns import PatternSet
from scanner.session import ExposureMode, ExposureRecord

ROI_MIN_CONTRAST = 0.01  # of full scale at the probe exposure: a pixel the projector lights
SATURATION_LEVEL = 0.98  # of full scale: brighter than this at the peak counts as saturated
GOOD_MODULATION = 0.1  # of full scale: modulation B whose phase survives temporal unwrapping (see below)
PROBE_MAX_SATURATED = 0.005  # of the ROI: a probe brighter than this is repeated shorter
PROBE_TRIES = 3
PROBE_SHORTEN = 8.0
GRID_STEP = np.sqrt(2.0)  # candidate exposures a half stop apart
AUTO_TIE = 0.002  # of the ROI: coverages this close to the best count as equal
HDR_MIN_GAIN = 0.005  # of the ROI: an exposure adding less is not worth its capture time
HDR_MAX_EXPOSURES = 4


@dataclass(frozen=True)
class ExposureRequest:
    """What the user asked for: `mode` "auto" (one exposure chosen), "hdr" (several chosen)
    or "given" (`exposures_s` as listed); `roi` (x, y, width, height) camera pixels or None
    (every lit pixel)."""

    mode: ExposureMode
    exposures_s: tuple[float, ...] = ()
    roi: tuple[int, int, int, int] | None = None

    @classmethod
    def parse(cls, text: str, roi: str | None = None, where: str = "--exposure") -> ExposureRequest:
        """From the command line: "auto", "hdr", or exposures in seconds "0.004,0.016,0.064"."""
        box: tuple[int, int, int, int] | None = None
        if roi is not None:
            try:
                parts = tuple(int(v) for v in roi.split(","))
            except ValueError:
                parts = ()
            if len(parts) != 4 or parts[2] <= 0 or parts[3] <= 0 or min(parts[:2]) < 0:
                raise ConfigError("--exposure-roi", roi, "expected x,y,width,height in camera pixels (width, "
                                                         "height > 0)")
            x, y, w, h = parts
            box = (x, y, w, h)
        match text:
            case "auto" | "hdr":
                return cls(text, (), box)
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if not values or not all(np.isfinite(v) and v > 0 for v in values):
            raise ConfigError(where, text, "expected auto, hdr, or exposures in seconds, e.g. 0.004,0.016,0.064")
        if len(set(values)) != len(values):
            raise ConfigError(where, text, "an exposure is listed twice")
        return cls("given", tuple(sorted(values)), box)


@dataclass(frozen=True)
class Probe:
    """The pre-capture: white, black and fringe frames (H, W) float32 in DN at `exposure_s`."""

    white: np.ndarray
    black: np.ndarray
    fringe: np.ndarray
    exposure_s: float
    full_scale: float

    def roi(self, box: tuple[int, int, int, int] | None) -> np.ndarray:
        """Pixels the projector lights (inside `box`, if given)."""
        lit = (self.white - self.black) > ROI_MIN_CONTRAST * self.full_scale
        if box is not None:
            x, y, w, h = box
            inside = np.zeros_like(lit)
            inside[y:y + h, x:x + w] = True
            lit &= inside
        return lit

    def saturated_fraction(self, roi: np.ndarray) -> float:
        return float((self.white[roi] >= SATURATION_LEVEL * self.full_scale).mean()) if roi.any() else 0.0


def fringe_contrast(probe: Probe, roi: np.ndarray) -> float:
    """The displayed fringes' contrast at the camera (0..1): mean |F − mid|/half·π/2 over the
    ROI's unsaturated pixels (1 for a sharp sinusoid, less through defocus)."""
    ok = roi & (probe.white < SATURATION_LEVEL * probe.full_scale)
    if not ok.any():
        return 1.0
    half = (probe.white[ok] - probe.black[ok]) / 2
    mid = probe.black[ok] + half
    return float(np.clip(np.mean(np.abs(probe.fringe[ok] - mid) / half) * np.pi / 2, 0.05, 1.0))


def coverage_table(probe: Probe, roi: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """(n_candidates, n_roi) bool: ROI pixel covered (unsaturated, modulation good) at each
    candidate exposure, predicted linearly from the probe."""
    scale = candidates[:, None] / probe.exposure_s
    white = probe.white[roi][None, :]
    b = fringe_contrast(probe, roi) * (probe.white[roi] - probe.black[roi])[None, :] / 2
    return (white * scale < SATURATION_LEVEL * probe.full_scale) & (b * scale >= GOOD_MODULATION * probe.full_scale)


def candidate_exposures(lo_s: float, hi_s: float) -> np.ndarray:
    """Half-stop grid from `lo_s` to `hi_s` (s)."""
    n = int(np.floor(np.log(hi_s / lo_s) / np.log(GRID_STEP) + 1e-9)) + 1
    return lo_s * GRID_STEP ** np.arange(max(n, 1))


def choose_exposures(probe: Probe, mode: ExposureMode, exposure_range_s: tuple[float, float],
                     box: tuple[int, int, int, int] | None = None) -> ExposureRecord:
    """The plan for `mode` "auto" or "hdr" from a probe (see the module docstring)."""
    roi = probe.roi(box)
    n_roi = int(roi.sum())
    if n_roi == 0:
        raise ConfigError("--exposure", mode, "the pre-capture found no pixel the projector lights in the region of "
                                              "interest; check the projector, the part's placement and --exposure-roi")
    grid = candidate_exposures(*exposure_range_s)
    table = coverage_table(probe, roi, grid)
    coverage = table.mean(axis=1)
    best_single = int(np.flatnonzero(coverage >= coverage.max() - AUTO_TIE).max())
    if mode == "auto":
        chosen = [best_single]
    else:
        chosen, covered = [], np.zeros(n_roi, bool)
        while len(chosen) < HDR_MAX_EXPOSURES:
            gain = (table & ~covered).sum(axis=1)
            k = int(np.argmax(gain))
            if chosen and gain[k] < HDR_MIN_GAIN * n_roi:
                break
            chosen.append(k)
            covered |= table[k]
    chosen = sorted(chosen)
    total = float(np.logical_or.reduce(table[chosen]).mean())
    saturating = float((probe.white[roi] * grid[chosen[0]] / probe.exposure_s >= SATURATION_LEVEL * probe.full_scale
                        ).mean())
    dark = float(np.logical_not(np.logical_or.reduce(table[chosen]) |
                                (probe.white[roi] * grid[chosen[-1]] / probe.exposure_s
                                 >= SATURATION_LEVEL * probe.full_scale)).mean())
    exposures = [float(round(grid[k], 6)) for k in chosen]
    names = ", ".join(f"{t * 1e3:.3g}" for t in exposures)
    reason = (f"{mode}: {'exposures' if len(exposures) > 1 else 'exposure'} {names} ms predicted to cover "
              f"{total:.1%} of the {n_roi} lit ROI pixels (unsaturated, modulation >= {GOOD_MODULATION:.0%} of full "
              f"scale); the best single exposure ({grid[best_single] * 1e3:.3g} ms) covers "
              f"{coverage[best_single]:.1%}; {saturating:.1%} saturate even at the shortest chosen and {dark:.1%} "
              f"stay too dark at the longest; fringe contrast {fringe_contrast(probe, roi):.2f}; projector brightness "
              f"not adjusted (its interface offers no brightness control)")
    return ExposureRecord(exposures_s=exposures, mode=mode, reason=reason, probe_exposure_s=probe.exposure_s,
                          roi_pixels=n_roi, roi_box=list(box) if box else None, predicted_coverage=round(total, 5),
                          best_single_exposure_s=float(round(grid[best_single], 6)),
                          best_single_coverage=round(float(coverage[best_single]), 5),
                          fringe_contrast=round(fringe_contrast(probe, roi), 4))


def probe_images(patterns: PatternSet, width: int, height: int, gamma: float) -> np.ndarray:
    """(3, height, width) uint8: white, black and the first frame of the finest fringes."""
    specs = patterns.frames()
    finest = max(patterns.fringes) if patterns.fringes else None
    k = next((i for i, s in enumerate(specs) if s.kind is FrameKind.PHASE and patterns.fringes[s.level] == finest), 0)
    fringe = patterns.render(width, height, gamma)[k]
    return np.stack([np.full((height, width), 255, np.uint8), np.zeros((height, width), np.uint8), fringe])


def plan_exposures(request: ExposureRequest, capture_probe: Callable[[float], np.ndarray], start_s: float,
                   exposure_range_s: tuple[float, float], full_scale: float) -> ExposureRecord:
    """The exposures for `request`; "auto" and "hdr" pre-capture with `capture_probe(t)`
    (returns the three probe frames at exposure t), shortened while the probe saturates."""
    lo, hi = exposure_range_s
    if request.mode == "given":
        bad = [t for t in request.exposures_s if not lo <= t <= hi]
        if bad:
            raise ConfigError("--exposure", ",".join(map(str, request.exposures_s)),
                              f"{bad[0] * 1e3:.4g} ms is outside the camera's range {lo * 1e3:.4g}..{hi * 1e3:.4g} ms")
        return ExposureRecord(exposures_s=list(request.exposures_s), mode="given",
                              reason=f"given: {len(request.exposures_s)} exposure(s) as listed")
    t = float(np.clip(start_s, lo, hi))
    probes = 0
    while True:
        frames = capture_probe(t).astype(np.float32)
        probes += 1
        probe = Probe(frames[0], frames[1], frames[2], t, full_scale)
        if probe.saturated_fraction(probe.roi(request.roi)) <= PROBE_MAX_SATURATED or probes >= PROBE_TRIES \
                or t / PROBE_SHORTEN < lo:
            break
        t /= PROBE_SHORTEN
    plan = choose_exposures(probe, request.mode, exposure_range_s, request.roi)
    return plan.model_copy(update={"probe_captures": probes})


@dataclass(eq=False)
class FusedOrientationMaps(OrientationMaps):
    """One orientation's maps fused from several exposures: every array per pixel from the
    exposure `exposure_index` names; `fused_sigma` the chosen exposure's predicted phase
    noise (rad), NaN where invalid."""

    exposure_index: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.uint8))
    fused_sigma: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))

    @cached_property
    def phase_sigma(self) -> np.ndarray:
        return self.fused_sigma


def _pick(arrays: list[np.ndarray], choice: np.ndarray) -> np.ndarray:
    return np.take_along_axis(np.stack(arrays), choice[None].astype(np.intp), axis=0)[0]


def fuse_orientation(maps: list[OrientationMaps]) -> FusedOrientationMaps:
    """Per pixel, the exposure (maps in ascending exposure order) with a valid phase of the
    least predicted noise; invalid everywhere: the longest exposure not saturating it.

    A pixel any exposure masks as "interreflection" is masked so in the fused maps, taken
    from the longest exposure that saw the second path: a second path is a property of the
    scene's light, not of the exposure, and the frequency and modulation-ratio tests judge it
    against each exposure's own noise, so a shorter, noisier exposure may pass what a longer
    one resolves (on the polished aluminium demo part such pixels, kept only by the 2.5 ms
    exposure, were most of HDR's fringe-order errors)."""
    second = np.stack([m.masks.get("interreflection", np.zeros_like(m.valid)) for m in maps])
    seen = second.any(axis=0)
    sigma = [np.where(m.valid & ~seen, m.phase_sigma, np.inf) for m in maps]
    best = np.argmin(np.stack(sigma), axis=0)
    unsaturated = np.stack([~m.masks["saturated"] for m in maps])
    fallback = np.where(unsaturated.any(axis=0), len(maps) - 1 - np.argmax(unsaturated[::-1], axis=0), 0)
    fallback = np.where(seen, len(maps) - 1 - np.argmax(second[::-1], axis=0), fallback)
    choice = np.where(np.logical_or.reduce([m.valid for m in maps]) & ~seen, best, fallback).astype(np.uint8)
    reasons = list(dict.fromkeys(k for m in maps for k in m.masks))  # decode's order of reasons
    masks = {k: _pick([m.masks.get(k, np.zeros_like(m.valid)) for m in maps], choice) for k in reasons}
    first = maps[0]
    n_freq = len(first.modulation)
    return FusedOrientationMaps(
        orientation=first.orientation, coordinate=_pick([m.coordinate for m in maps], choice),
        phase=_pick([m.phase for m in maps], choice),
        wrapped=[_pick([m.wrapped[i] for m in maps], choice) for i in range(len(first.wrapped))],
        modulation=[_pick([m.modulation[i] for m in maps], choice) for i in range(n_freq)],
        background=_pick([m.background for m in maps], choice), phase_weight=_pick([m.phase_weight for m in maps],
                                                                                    choice),
        masks=masks, valid=_pick([m.valid for m in maps], choice), fringes=first.fringes, extent_px=first.extent_px,
        noise=first.noise, steps=first.steps, exposure_index=choice,
        fused_sigma=_pick([m.phase_sigma for m in maps], choice))


def fuse(results: list[DecodeResult], exposures_s: tuple[float, ...]) -> DecodeResult:
    """One decode from the decodes of the same pattern set at `exposures_s` (ascending)."""
    if len(results) != len(exposures_s) or not results:
        raise ValueError("one decode per exposure is needed")
    if len(results) == 1:
        return results[0]
    fused = {o: fuse_orientation([r.maps[o] for r in results]) for o in results[0].maps}
    scale = [np.float32(exposures_s[0] / t) for t in exposures_s]
    first = next(iter(fused.values()))
    texture = _pick([r.texture * s for r, s in zip(results, scale)], first.exposure_index)
    valid = np.logical_and.reduce([m.valid for m in fused.values()])
    checks = [replace(c, scope=f"{c.scope}, exposure {i}") for i, r in enumerate(results) for c in r.checks]
    maps: dict[str, OrientationMaps] = dict(fused)  # as the base type DecodeResult holds
    return DecodeResult(results[0].patterns, results[0].bit_depth, maps, texture, valid, checks)
