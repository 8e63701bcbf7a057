"""Detecting a capture's pattern conventions from its frames (`slscan import`).

Keys a pattern set leaves out (scanner/conventions.py) are found from the evidence the
frames carry, on every 4th pixel; keys it gives are checked against the same evidence:

- frame layout (frame order, Gray-code position and variant, white/black references):
  every layout with the right frame count is scored and the best one kept. A Gray-code
  set scores by how well code and phase agree (the resultant length R of the phase's
  offset from the half period the code names, ~0.64 for a true layout, ~0 for a wrong
  one); a heterodyne set by how well its frequencies agree on one coordinate (R of each
  frequency's offset from the phase its beats predict, ~1 when true); others by the
  share of each phase block's temporal energy at the step frequency. Reference frames
  must be the brightest and darkest of every pixel.
- step sign: with a Gray code, the sign under which code and phase agree (under the other
  sign the phase runs against the code and R collapses). Without one, the frequencies agree
  under both signs (the two readings are mirror images, x → W − x): the sign is the one
  under which the coordinate increases in the direction the rig's geometry predicts (from
  the calibration), or, without a calibration, increases with the camera column (row for
  horizontal fringes), which holds for a projector that is not mirrored — reported as
  an assumption.
- phase offset: a Gray code's edges (the phase must wrap where the code's period changes)
  or the heterodyne beats (which cancel a common offset) show the phase's offset, the phase
  origin plus a rotation of every group's steps (2π·step_offset/N): both read alike, so a
  given origin leaves the rest to a detected rotation, and without one the offset is taken
  as the origin — snapped to the discrete values (multiples of π/2 or of a step) and refused
  when it lies between them. A Gray-code edge locates a period only to within its blur (a
  few hundredths of a radian on a real capture): it decides between discrete offsets, never
  a sub-pixel convention.
- pixel centre: never from the frames (it moves every coordinate alike by a fraction of a
  pixel); given by the description, or assumed (ours, 0.5) and said so.

Contradicting given keys or ambiguous evidence raise DecodeError naming them.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from scanner.conventions import CHOICES, NATIVE, Conventions, known
from scanner.decode import gray_phase_offset, phase_shift, read_complementary_code
from scanner.decode_checks import predicted_direction
from scanner.errors import DecodeError
from scanner.geometry import RigModel
from scanner.pattern_families import REFERENCES, FrameKind, temporal
from scanner.patterns import PatternSet
from scanner.pixel_code import read_pixel_code
from scanner.session import ConventionFinding

GRAY, GRAY_INVERSE = FrameKind.GRAY, FrameKind.GRAY_INVERSE

SUBSAMPLE = 4  # every 4th pixel on both axes
MIN_R = 0.3  # below this resultant length the code-phase agreement is no evidence
AMBIGUOUS = 0.85  # a runner-up scoring this fraction of the best is a tie


@dataclass(frozen=True)
class Finding:
    """How one convention key was settled: `source` given | detected | assumed."""

    key: str
    value: Any
    source: str
    evidence: str

    def line(self) -> str:
        return f"{self.key} = {self.value!r} ({self.source}: {self.evidence})"


@dataclass(eq=False)
class Detection:
    patterns: PatternSet  # with every convention known
    findings: list[Finding] = field(default_factory=list)

    def record(self) -> dict[str, ConventionFinding]:
        """The findings as an import's manifest records them (`ImportRecord.conventions`), by key."""
        return {f.key: ConventionFinding(value=f.value, source=f.source, evidence=f.evidence) for f in self.findings}


def _layouts(ps: PatternSet, n_frames: int, fixed: bool) -> list[PatternSet]:
    """Pattern sets for every frame layout the set's keys allow (`fixed`: only the given
    values of given keys) whose frame count is `n_frames`, distinct frame sequences only."""
    c = ps.conventions
    keys = ["references", *ps.kind.layout_keys(len(ps.fringes))]
    options = {k: ([getattr(c, k)] if fixed and getattr(c, k) is not None else list(CHOICES[k])) for k in keys}
    out, seen = [], set()
    for combo in itertools.product(*options.values()):
        conv = replace(c, **dict(zip(options, combo))).filled(NATIVE)
        cand = ps.with_conventions(conv)
        try:
            frames = tuple(cand.frames())
        except Exception:  # a layout that cannot be formed is no candidate
            continue
        if len(frames) == n_frames and frames not in seen:
            seen.add(frames)
            out.append(cand)
    return out


def _all_layouts(ps: PatternSet) -> list[PatternSet]:
    """Every layout the set's given keys allow, whatever its frame count."""
    c = ps.conventions
    keys = [k for k in ("references", "frame_order", "gray_position", "gray_code") if getattr(c, k) is None]
    out = []
    for combo in itertools.product(*(CHOICES[k] for k in keys)):
        layout: dict[str, Any] = dict(zip(keys, combo))  # str-valued keys of `Conventions`
        try:
            cand = ps.with_conventions(replace(c, **layout).filled(NATIVE))
            cand.frames()
        except Exception:  # a layout that cannot be formed is no candidate
            continue
        out.append(cand)
    return out


def _layout_name(ps: PatternSet) -> str:
    c = ps.conventions
    keys = ps.kind.layout_keys(len(ps.fringes))
    parts = [f"references {c.references}"]
    if "frame_order" in keys:
        parts.insert(0, known(c.frame_order, "frame_order"))
    if "gray_code" in keys:
        parts += [f"Gray code {c.gray_code} {c.gray_position} the phase"]
    return ", ".join(parts)


@dataclass(eq=False)
class _Evidence:
    """What one frame layout says about the frames (on the subsample)."""

    score: float
    sign_r: dict[int, float] = field(default_factory=dict)  # Gray sets: support per step sign (0..1)
    offset: dict[int, tuple[float, float]] = field(default_factory=dict)  # sign -> (ε rad, its std error)


def _circular(r: np.ndarray) -> tuple[float, float, float]:
    """(mean angle, resultant length R, standard error of the mean angle) of angles r."""
    z = np.mean(np.exp(1j * r.astype(np.float64))) if r.size else 0j
    R = float(abs(z))
    se = float(np.sqrt(max(-2.0 * np.log(max(R, 1e-9)), 0.0) / max(r.size, 1)))
    return float(np.angle(z)), R, se


def _refs_score(sub: np.ndarray, ps: PatternSet, usable: np.ndarray) -> float:
    """Share of usable pixels whose white frame is the brightest and black the darkest."""
    specs = ps.frames()
    kinds = [s.kind for s in specs]
    if FrameKind.WHITE not in kinds:
        return 1.0
    white = sub[kinds.index(FrameKind.WHITE)].astype(np.float32)
    black = sub[kinds.index(FrameKind.BLACK)].astype(np.float32)
    others = sub[[k for k, kind in enumerate(kinds) if kind not in REFERENCES]].astype(np.float32)
    slack = 0.05 * (white - black)
    ok = (white >= others.max(axis=0) - np.abs(slack)) & (black <= others.min(axis=0) + np.abs(slack))
    return float(ok[usable].mean()) if usable.any() else 0.0


def _evidence(stack: np.ndarray, ps: PatternSet, projector_size: tuple[int, int], bit_depth: int) -> _Evidence:
    """What the frames say under the layout of `ps` (judged on every SUBSAMPLE-th pixel)."""
    sub = stack[:, ::SUBSAMPLE, ::SUBSAMPLE]
    specs = ps.frames()
    index = {(s.orientation, s.kind, s.level, s.step): k for k, s in enumerate(specs)}
    o = ps.orientations[0]
    extent = projector_size[0] if o == "vertical" else projector_size[1]
    full = float(2 ** bit_depth - 1)
    if not ps.kind.has_phase:  # a pixel Gray code alone
        diffs = [sub[index[(o, GRAY, b, 0)]].astype(np.float32) - sub[index[(o, GRAY_INVERSE, b, 0)]]
                 for b in range(ps.gray_bits(o))]
        contrast = np.max(np.abs(diffs), axis=0)
        usable = contrast > 0.05 * full
        coordinate, _, readable = read_pixel_code(diffs, np.maximum(0.15 * contrast, 1.0), 0)
        inside = float((readable & (coordinate < extent))[usable].mean()) if usable.any() else 0.0
        return _Evidence(inside * _refs_score(sub, ps, usable))
    blocks = [[index[(o, FrameKind.PHASE, lv, n)] for n in range(ps.steps)] for lv in range(len(ps.fringes))]
    shifted = [phase_shift(sub[b], ps.steps, 0.0, 1) for b in blocks]
    wrapped = [w for w, _, _ in shifted]
    mod = [m for _, m, _ in shifted]
    background = sum((a for _, _, a in shifted), np.zeros_like(shifted[0][2])) / len(shifted)
    usable = (mod[-1] > 0.12 * background) & (mod[-1] > 0.005 * full) & (background < full)
    refs = _refs_score(sub, ps, usable)
    if not ps.unwrapping.by_frequencies:  # a Gray code unwraps the phase
        f = ps.fringes[0]
        if not ps.unwrapping.pixel_code:
            bits = [sub[index[(o, GRAY, b, 0)]] for b in range(ps.gray_bits() + 1)]
            half, unclear, half_unclear = read_complementary_code(bits, background, mod[0], 0.3)
            clear = (unclear == 0) & ~half_unclear
            reference = None
        else:
            diffs = [sub[index[(o, GRAY, b, 0)]].astype(np.float32) - sub[index[(o, GRAY_INVERSE, b, 0)]]
                     for b in range(ps.gray_bits(o))]
            coord, _, clear = read_pixel_code(diffs, np.maximum(0.3 * 2 * mod[0], 1.0), 0)
            reference = (coord + np.float32(0.5)) * np.float32(2 * np.pi * f / extent)
        sel = usable & clear
        ev = _Evidence(0.0)
        Rs: dict[int, float] = {}
        for sign in (1, -1):
            theta = wrapped[0] if sign == 1 else np.mod(-wrapped[0], np.float32(2 * np.pi))
            if reference is None:
                r = gray_phase_offset(theta, half)[sel]
            else:
                r = np.angle(np.exp(1j * (theta[sel] - reference[sel]).astype(np.float64)))
            eps, Rs[sign], se = _circular(r)
            ev.offset[sign] = (eps, se)
        if reference is None:  # the half-period test cannot tell a mirrored phase: ask the code's edges
            agree = _edge_agreement(stack, ps, bit_depth)
            ev.sign_r = {1: agree, -1: 1.0 - agree}
        else:
            ev.sign_r = {k: v / max(max(Rs.values()), 1e-9) for k, v in Rs.items()}
        ev.score = max(Rs.values()) * refs
        return ev
    beat = temporal(ps.kind).offset_free_phase(ps.fringes, wrapped)
    if beat is not None:  # each frequency's offset from the phase its beats predict
        phase, count = beat
        resultants: list[float] = []
        offsets: list[tuple[float, float]] = []
        for w, fi in zip(wrapped, ps.fringes):
            eps, R, se = _circular((w - phase * np.float32(fi / count))[usable])
            resultants.append(R)
            offsets.append((eps, se))
        ev = _Evidence(float(np.mean(resultants)) * refs)
        eps, R, se = _circular(np.array([e for e, _ in offsets]))
        ev.offset[1] = (eps, max(s for _, s in offsets))
        return ev
    # no beat (hierarchical): share of each block's temporal AC energy at the step frequency
    shares = []
    for b in blocks:
        spectrum = np.abs(np.fft.fft(sub[b].astype(np.float32), axis=0)) ** 2
        ac = spectrum[1:].sum(axis=0)
        fundamental = spectrum[1] + spectrum[-1]
        shares.append(np.median((fundamental / np.maximum(ac, 1e-9))[usable]) if usable.any() else 0.0)
    return _Evidence(float(np.mean(shares)) * refs)


def _edge_agreement(stack: np.ndarray, ps: PatternSet, bit_depth: int) -> float:
    """Share of the complementary Gray code's half-period edges across which the phase moves
    the same way as the code (step sign +1): where the half-period index steps by ±1 between
    neighbouring camera pixels, the wrapped phase difference has that sign. Judged between
    direct neighbours (every 4th line, along both camera axes, the axis with more edges
    counting), since the phase may advance by most of a period over a few pixels."""
    o = ps.orientations[0]
    index = {(s.orientation, s.kind, s.level, s.step): k for k, s in enumerate(ps.frames())}
    block = [index[(o, FrameKind.PHASE, 0, n)] for n in range(ps.steps)]
    bits = [index[(o, GRAY, b, 0)] for b in range(ps.gray_bits() + 1)]
    full = float(2 ** bit_depth - 1)
    best = (0, 0.5)
    for axis, view in ((1, stack[:, ::SUBSAMPLE, :]), (0, stack[:, :, ::SUBSAMPLE])):
        theta, mod, background = phase_shift(view[block], ps.steps, 0.0, 1)
        half, unclear, half_unclear = read_complementary_code([view[b] for b in bits], background, mod, 0.3)
        sel = (unclear == 0) & ~half_unclear & (mod > 0.12 * background) & (mod > 0.005 * full)
        a, b = (np.s_[:, 1:], np.s_[:, :-1]) if axis == 1 else (np.s_[1:, :], np.s_[:-1, :])
        dh = half[a] - half[b]
        dt = theta[a] - theta[b]
        dt = dt - np.float32(2 * np.pi) * np.rint(dt / np.float32(2 * np.pi))
        ok = sel[a] & sel[b] & (np.abs(dh) == 1) & (np.abs(dt) < 0.5 * np.pi)
        n = int(ok.sum())
        if n > best[0]:
            best = (n, float((np.sign(dt[ok]) == np.sign(dh[ok])).mean()))
    return best[1]


def _geometric_sign(stack: np.ndarray, ps: PatternSet, projector_size: tuple[int, int], bit_depth: int,
                    rig: RigModel | None, origin_plus: float) -> tuple[int, str, str]:
    """Step sign of a phase-only set: the one under which the decoded coordinate runs the way
    the rig's geometry (or, without one, an unmirrored projector) says; `origin_plus` is the
    phase origin the frames show under sign +1. Returns (sign, source, evidence)."""
    from scanner.decode import DecodeSettings, decode

    o = ps.orientations[0]
    axis = 1 if o == "vertical" else 0  # camera image axis along which the coordinate runs
    expected, why = 1, "the coordinate increases with the camera " + ("column" if axis == 1 else "row") + \
        " (an unmirrored projector)"
    if rig is not None:
        predicted = predicted_direction(rig, o)
        if predicted != 0:
            expected, why = predicted, "from the calibration's geometry"
    settings = DecodeSettings(self_check=False, spatial_check=False)
    trial = replace(ps.conventions, step_sign=1, phase_origin=origin_plus).filled(NATIVE)
    lines = stack[:, ::SUBSAMPLE, :] if axis == 1 else stack[:, :, ::SUBSAMPLE]  # direct neighbours along axis
    d = decode(lines, ps.with_conventions(trial), bit_depth, projector_size, settings)
    c = d.maps[o].coordinate
    grad = np.diff(c, axis=axis)
    grad = grad[np.isfinite(grad) & (np.abs(grad) < 0.5 * d.maps[o].period_px)]
    if grad.size < 100:
        raise DecodeError("cannot tell the step sign: too few decoded pixels to see which way the coordinate runs")
    rising = float((grad > 0).mean())
    if 0.2 < rising < 0.8:
        raise DecodeError(f"cannot tell the step sign: the coordinate rises on {rising:.0%} of the pixels and falls "
                          f"on the rest; give conventions.step_sign")
    observed = 1 if rising >= 0.8 else -1
    sign = 1 if observed == expected else -1
    source = "detected" if rig is not None and why.startswith("from") else "assumed"
    return sign, source, f"{why}; under step sign +1 it {'rises' if observed > 0 else 'falls'} on " \
                         f"{max(rising, 1 - rising):.0%} of the pixels"


def detect(stack: np.ndarray, patterns: PatternSet, bit_depth: int, projector_size: tuple[int, int],
           rig: RigModel | None = None) -> Detection:
    """Every convention of `patterns` settled (given keys checked, missing keys detected)
    from the frames `stack` (N, H, W); DecodeError naming a contradiction or ambiguity."""
    ps = patterns.for_projector(projector_size)
    given = ps.conventions
    n = stack.shape[0]
    candidates = _layouts(ps, n, fixed=True)
    if not candidates:
        every = _layouts(ps, n, fixed=False)
        hint = f"; with other frame-layout keys {len(every)} layout(s) would fit" if every else ""
        what = f"{ps.family} for a {projector_size[0]} x {projector_size[1]} projector" \
            if not ps.kind.has_phase else f"{ps.family}, fringes {list(ps.fringes)}, {ps.steps} steps"
        raise DecodeError(f"{n} frames, but the pattern set ({what}, {list(ps.orientations)}) with the given layout "
                          f"keys needs {_needed(ps)}: wrong frame count, fringe/period count or projector size{hint}")
    scored = sorted(((_evidence(stack, c, projector_size, bit_depth), c) for c in candidates),
                    key=lambda t: -t[0].score)
    best_ev, best = scored[0]
    findings: list[Finding] = []
    # given layout keys contradicted by a layout they exclude?
    free = sorted(((_evidence(stack, c, projector_size, bit_depth), c) for c in _layouts(ps, n, fixed=False)),
                  key=lambda t: -t[0].score)
    if free and free[0][1].frames() != best.frames() and free[0][0].score > max(1.5 * best_ev.score, 0.3):
        raise DecodeError(f"the given frame layout ({_layout_name(best)}, score {best_ev.score:.2f}) contradicts "
                          f"the frames: {_layout_name(free[0][1])} explains them (score {free[0][0].score:.2f})")
    if best_ev.score < 0.3:
        raise DecodeError(f"no frame layout explains the frames (best: {_layout_name(best)}, score "
                          f"{best_ev.score:.2f}): wrong frame order, fringe count or pattern family")
    if len(scored) > 1 and scored[1][0].score >= AMBIGUOUS * best_ev.score:
        raise DecodeError(f"ambiguous frame layout: {_layout_name(best)} (score {best_ev.score:.2f}) and "
                          f"{_layout_name(scored[1][1])} ({scored[1][0].score:.2f}) explain the frames alike; give "
                          f"the layout keys in [conventions]")
    layout_keys = [k for k in ("frame_order", "gray_position", "gray_code", "references")
                   if k in best.conventions.to_dict()]
    runner = f"; next best {scored[1][0].score:.2f}" if len(scored) > 1 else ""
    for k in layout_keys:
        v = getattr(best.conventions, k)
        if getattr(given, k) is not None:
            findings.append(Finding(k, v, "given", f"layout score {best_ev.score:.2f}{runner}"))
        elif k != "references" and k not in ps.kind.layout_keys(len(ps.fringes)):
            continue
        else:
            findings.append(Finding(k, v, "detected", f"layout score {best_ev.score:.2f} of {len(scored)} "
                                                      f"layout(s) with {n} frames{runner}"))
    conv = replace(given, **{k: getattr(best.conventions, k) for k in layout_keys})
    conv, more = _phase_keys(stack, ps.with_conventions(conv), best_ev, projector_size, bit_depth, rig)
    findings += more
    if ps.kind.has_phase:  # how long a period is: the description's (the frames show only its count)
        rounding = patterns.conventions.period_rounding
        extent = projector_size[0] if ps.orientations[0] == "vertical" else projector_size[1]
        periods = ", ".join(f"{extent / f:.3f}" for f in ps.fringes)
        findings.append(Finding("period_rounding", rounding or NATIVE.period_rounding,
                                "given" if rounding else "assumed", f"periods of {periods} px"))
    return Detection(ps.with_conventions(conv.filled(NATIVE)), findings)


def _needed(ps: PatternSet) -> str:
    counts = sorted({len(c.frames()) for c in _all_layouts(ps)})
    return "/".join(str(c) for c in counts) + " frames" if counts else "a frame count it cannot form"


def _phase_keys(stack: np.ndarray, ps: PatternSet, ev: _Evidence, projector_size: tuple[int, int], bit_depth: int,
                rig: RigModel | None) -> tuple[Conventions, list[Finding]]:
    """Step sign, phase offset (origin and step rotation) and pixel centre: given, detected
    where the frames determine them, else assumed (module docstring)."""
    c = ps.conventions
    findings: list[Finding] = []
    if not ps.kind.has_phase:
        return c, findings
    o = ps.orientations[0]
    extent = projector_size[0] if o == "vertical" else projector_size[1]
    coded = ps.gray_bits(o) > 0
    f = ps.fringes[0] if coded else max(ps.fringes)
    eps: float | None  # the phase's offset the frames show (rad); None: nothing measures it
    if coded:
        sign = _gray_sign(c, ev, findings)
        eps, se = ev.offset[sign]
    else:
        eps_plus, se = ev.offset.get(1, (None, 0.0))
        origin_plus = _discrete(eps_plus, ps.steps)[0] if eps_plus is not None else 0.0
        sign = _phase_only_sign(stack, ps, c, projector_size=projector_size, bit_depth=bit_depth, rig=rig,
                                origin_plus=origin_plus, findings=findings)
        eps = None if eps_plus is None else (-eps_plus if sign == -1 else eps_plus)  # the beats' offsets mirror
    c = replace(c, step_sign=sign)
    if c.pixel_centre is None:
        findings.append(Finding("pixel_centre", NATIVE.pixel_centre, "assumed",
                                "a fraction of a pixel that moves every coordinate alike: the frames cannot show it "
                                "(a Gray-code edge locates a period only to within its blur); ours, 0.5 — give the "
                                "tool's description (config/patterns/) or conventions.pixel_centre"))
        c = replace(c, pixel_centre=NATIVE.pixel_centre)
    else:
        findings.append(Finding("pixel_centre", c.pixel_centre, "given", "not observable in the frames"))
    if eps is None:  # hierarchical: nothing measures the phase's offset
        for key, native in (("phase_origin", 0.0), ("step_offset", 0)):
            if getattr(c, key) is None:
                findings.append(Finding(key, native, "assumed", "a hierarchical set carries no evidence of it; ours"))
            else:
                findings.append(Finding(key, getattr(c, key), "given", "not checked (no evidence in the frames)"))
        return c.filled(NATIVE), findings
    # the phase's offset the frames show, less what the pixel centre accounts for (Gray code:
    # ε = first phase + 2π·f·(δ − 0.5)/W; heterodyne: the beats cancel δ, ε = first phase)
    rad_per_px = 2 * np.pi * f / extent
    measured = _wrap(eps - (known(c.pixel_centre, "pixel_centre") - 0.5) * rad_per_px) if coded else eps
    against = "the Gray code's edges" if coded else "its frequencies' beats"
    evidence = f"the phase sits {measured:+.3f} ± {se:.3f} rad from {against}"
    step = 2 * np.pi / ps.steps
    if c.phase_origin is not None:  # given: the frames must show it (and the given rotation, if any)
        k = c.step_offset or 0
        d = _wrap(measured - c.phase_origin - sign * k * step)
        if abs(d) > max(step / 4, 3 * se):
            steps_off = round(d / step * sign) % ps.steps
            rotated = (f"; {steps_off} whole step(s): every group's frames rotated by {steps_off} (set "
                       f"conventions.step_offset = {(k + steps_off) % ps.steps} if so), or not this description's "
                       f"patterns") if abs(_wrap(d - sign * steps_off * step)) <= max(step / 4, 3 * se) else \
                "; not a whole number of steps: a wrong phase origin or pixel centre"
            raise DecodeError(f"conventions.phase_origin = {c.phase_origin:.3f}{f' with step_offset {k}' if k else ''}"
                              f" contradicts the frames: {evidence}, {d:+.3f} rad from what they give{rotated}")
        findings.append(Finding("phase_origin", c.phase_origin, "given", f"{evidence} (agrees: {d:+.3f} rad)"))
        findings.append(Finding("step_offset", k, "given" if c.step_offset is not None else "detected",
                                f"{evidence}: the groups' first frames show step {k}"))
        return replace(c, step_offset=k), findings
    offset, spacing = _discrete(measured, ps.steps)
    if abs(_wrap(measured - offset)) > max(spacing / 4, 3 * se):
        raise DecodeError(f"cannot tell the phase origin: {evidence}, between the discrete offsets a phase origin "
                          f"(a multiple of π/2) or a rotation of the steps (of {step:.3f} rad) make; give "
                          f"conventions.phase_origin (and pixel_centre), or the tool's description")
    k = c.step_offset if c.step_offset is not None else 0
    origin = -np.pi if abs(abs(_wrap(offset - sign * k * step)) - np.pi) < 1e-9 else _wrap(offset - sign * k * step)
    findings.append(Finding("phase_origin", round(origin, 6), "detected",
                            f"{evidence}; an origin of {origin:.3f} rad and the steps rotated by {k} read alike"))
    findings.append(Finding("step_offset", k, "given" if c.step_offset is not None else "assumed",
                            "the phase origin takes the whole offset (a rotation of the steps reads the same)"))
    return replace(c, phase_origin=origin, step_offset=k), findings


def _discrete(angle: float, steps: int) -> tuple[float, float]:
    """The discrete phase offset nearest `angle` (rad): a multiple of π/2 (a phase origin) or
    of 2π/steps (a rotation of the steps), and the least spacing between such offsets."""
    candidates = np.unique(np.round(np.r_[np.arange(4) * np.pi / 2, np.arange(steps) * 2 * np.pi / steps], 12))
    gaps = np.diff(np.r_[candidates, candidates[0] + 2 * np.pi])
    distance = np.abs(np.angle(np.exp(1j * (angle - candidates))))
    return _wrap(float(candidates[int(np.argmin(distance))])), float(gaps.min())


def _gray_sign(c: Conventions, ev: _Evidence, findings: list[Finding]) -> int:
    """The step sign from how Gray code and phase agree under each sign."""
    r_plus, r_minus = ev.sign_r[1], ev.sign_r[-1]
    best = 1 if r_plus >= r_minus else -1
    strong, weak = max(r_plus, r_minus), min(r_plus, r_minus)
    if strong < MIN_R or weak > 0.5 * strong:
        raise DecodeError(f"cannot tell the step sign: Gray code and phase agree alike under both (R {r_plus:.2f} "
                          f"for +1, {r_minus:.2f} for -1); check the Gray-code frames and the fringe count")
    evidence = f"Gray code and phase agree {strong:.2f} under {best:+d}, {weak:.2f} under {-best:+d}"
    if c.step_sign is not None and c.step_sign != best:
        raise DecodeError(f"conventions.step_sign = {c.step_sign:+d} contradicts the frames: {evidence}")
    findings.append(Finding("step_sign", best, "given" if c.step_sign is not None else "detected", evidence))
    return best


def _phase_only_sign(stack: np.ndarray, ps: PatternSet, c: Conventions, *, projector_size: tuple[int, int],
                     bit_depth: int, rig: RigModel | None, origin_plus: float, findings: list[Finding]) -> int:
    """The step sign of a set without a Gray code: given, or from the rig's geometry, or assumed."""
    o = ps.orientations[0]
    if c.step_sign is None:
        sign, source, evidence = _geometric_sign(stack, ps, projector_size, bit_depth, rig, origin_plus)
    else:
        sign, source, evidence = c.step_sign, "given", "not checked against the frames (no Gray code)"
        if rig is not None and predicted_direction(rig, o) != 0:
            detected, _, evidence = _geometric_sign(stack, ps, projector_size, bit_depth, rig, origin_plus)
            if detected != sign:
                raise DecodeError(f"conventions.step_sign = {sign:+d} contradicts the frames and the calibration: "
                                  f"{evidence}")
    findings.append(Finding("step_sign", sign, source, evidence))
    return sign


def _wrap(angle: float) -> float:
    """An angle (rad) in (−π, π]."""
    return float(np.angle(np.exp(1j * angle)))
