"""Each shipped tool description (config/patterns/) decodes that tool's own patterns to the
tool's own projector coordinate, and a wrong description is refused.

The patterns are generated here as each tool's public source generates them (read in
SLMaster's src/algorithm/cpuStructuredLight/ and opencv_contrib's modules/structured_light/src/;
written for this test, independently of scanner.patterns and sim.foreign_patterns), with the
tools' own 8-bit conversion (SLMaster truncates, OpenCV rounds). Each tool decodes to the
projector column k at pixel k's centre (SLMaster: wrapped + 2π·floor + π = 2π·k/p; OpenCV's
Gray code: the column index itself), so the truth is the analytic plane's projector coordinate
(OpenCV pixel centres). The camera is sim.foreign_patterns.capture (a linear camera with noise).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from scanner.convention_detection import detect
from scanner.decode import decode
from scanner.errors import DecodeError
from scanner.patterns import PatternSet
from sim.foreign_patterns import capture
from slscan.commands.bench.import_ import plane_coordinates, synthetic_rig

CONFIG = Path(__file__).resolve().parent.parent / "config" / "patterns"
RIG = synthetic_rig(camera=(320, 256))
PROJ = RIG.projector.size  # 1920 x 1080
DEPTH, UV = plane_coordinates(RIG)
U = UV[..., 0]
LIT = (UV[..., 1] > -0.5) & (UV[..., 1] < PROJ[1] - 0.5)


def slmaster_complementary(width: int, periods: int = 32, steps: int = 12) -> np.ndarray:
    """SinusCompleGrayCodePattern::generate: p = width / periods (int); phase frames
    uchar(127.5 + 127.5·cos((k % p)/p·2π − π + 2π/steps·i)); then log2(periods) + 1 frames of
    blocks width / len(seq) wide valued seq = {0, 255}, each time seq += reversed(seq)."""
    k = np.arange(width)
    p = width // periods
    rows = [np.trunc(127.5 + 127.5 * np.cos((k % p) / p * 2 * np.pi - np.pi + 2 * np.pi / steps * i))
            for i in range(steps)]
    seq = [0, 255]
    for _ in range(int(np.log2(periods)) + 1):
        block = width // len(seq)
        row = np.zeros(width)
        for j, v in enumerate(seq):
            row[j * block:(j + 1) * block] = v
        rows.append(row)
        seq = seq + seq[::-1]
    return np.array(rows).astype(np.uint8)


def slmaster_heterodyne(width: int, periods: int = 32, steps: int = 4) -> np.ndarray:
    """ThreeFrequencyHeterodynePattern::generate: for n, n − 6, n − 11 periods, p = width / n
    (float), frac = k/p − floor(k/p) in float, uchar(127.5 + 127.5·cos((2·frac − 1)·π + 2π/N·i))."""
    k = np.arange(width, dtype=np.float32)
    rows = []
    for n in (periods, periods - 6, periods - 11):
        p = np.float32(width) / np.float32(n)
        frac = k / p - np.floor(k / p)
        for i in range(steps):
            shift = np.float32(2 * np.pi / steps * i)
            rows.append(np.trunc(127.5 + 127.5 * np.cos((2 * frac - 1) * np.pi + shift)))
    return np.array(rows).astype(np.uint8)


def opencv_gray_rows(extent: int) -> list[np.ndarray]:
    """GrayCodePattern of one axis: for bit k of gray(j) (k from the most significant), the
    pattern and its inverse; getProjPixel reads bit 1 where the pattern is the brighter, as
    the procam captures of ../shared/data show (pattern 00 is dark on the left half)."""
    n = int(np.ceil(np.log2(extent)))
    j = np.arange(extent)
    gray = j ^ (j >> 1)
    rows = []
    for k in range(n - 1, -1, -1):
        bit = ((gray >> k) & 1) * 255
        rows += [bit, 255 - bit]
    return [r.astype(np.uint8) for r in rows]


def opencv_sinusoidal_with_gray(width: int, periods: int = 16) -> np.ndarray:
    """SinusoidalPattern::generate (3 patterns, shift 2π/3): period = width / periods (int),
    saturate_cast<uchar>(127.5 + 127.5·sin(2π·j/period + i·shift)); then the columns'
    GrayCodePattern and the white and black frames."""
    period = width // periods
    j = np.arange(width)
    shift = np.float32(2 * np.pi / 3)
    phase = [np.clip(np.rint(127.5 + 127.5 * np.sin(2 * np.pi * (1.0 / period) * j + i * shift)), 0, 255)
             for i in range(3)]
    rows = [r.astype(np.uint8) for r in phase] + opencv_gray_rows(width)
    return np.array(rows + [np.full(width, 255, np.uint8), np.zeros(width, np.uint8)])


TOOLS = {  # description file: (rows as the tool generates them)
    "slmaster_complementary_12x32.toml": lambda: slmaster_complementary(PROJ[0]),
    "slmaster_heterodyne_3x4.toml": lambda: slmaster_heterodyne(PROJ[0]),
    "opencv_sinusoidal_psp.toml": lambda: opencv_sinusoidal_with_gray(PROJ[0]),
}


def imported(stack: np.ndarray, ps: PatternSet) -> np.ndarray:
    """The projector coordinate map of an import: conventions settled against the frames,
    then the decode with its consistency checks (either refuses with DecodeError)."""
    det = detect(stack, ps, 8, PROJ, RIG)
    m = decode(stack, det.patterns, 8, PROJ).maps["vertical"]
    return np.where(m.valid, m.coordinate, np.nan)


@pytest.mark.parametrize("name", TOOLS)
def test_tool_patterns_decode_to_the_tools_own_coordinate(name: str) -> None:
    stack = capture(TOOLS[name](), U, lit=LIT, noise=0.002, seed=1)
    err = (imported(stack, PatternSet.load(CONFIG / name, detect=True)) - U)[LIT]
    err = err[np.isfinite(err)]
    median, p99 = float(np.median(err)), float(np.percentile(np.abs(err), 99))
    print(f"{name}: {err.size} px, median {median:+.4f} px, p99 |error| {p99:.3f} px")
    assert err.size > 0.8 * LIT.sum()
    assert abs(median) <= 0.01
    assert p99 < 0.3  # the tools' 8-bit patterns (SLMaster truncates: a periodic error of ~0.1 px)


WRONG = {  # a description with one key wrong: refused, by the frames' evidence or the decode's checks
    "phase origin +π/2": lambda c: replace(c, phase_origin=c.phase_origin + np.pi / 2),
    "steps reversed": lambda c: replace(c, step_sign=-c.step_sign),
    "rotated by one step": lambda c: replace(c, step_offset=1),
    "our origin (0)": lambda c: replace(c, phase_origin=0.0),
}


@pytest.mark.parametrize("wrong", WRONG)
@pytest.mark.parametrize("name", TOOLS)
def test_a_wrong_description_is_refused(name: str, wrong: str) -> None:
    stack = capture(TOOLS[name](), U, lit=LIT, noise=0.002, seed=2)
    right = PatternSet.load(CONFIG / name, detect=True)
    ps = right.with_conventions(WRONG[wrong](right.conventions))
    with pytest.raises(DecodeError):
        imported(stack, ps)


@pytest.mark.parametrize("name", TOOLS)
def test_a_wrong_period_count_is_refused(name: str) -> None:
    """One period more with the same frame count (SLMaster's heterodyne: every count + 1,
    still a heterodyne set; the Gray sets: the same number of Gray bits)."""
    stack = capture(TOOLS[name](), U, lit=LIT, noise=0.002, seed=3)
    right = PatternSet.load(CONFIG / name, detect=True)
    ps = replace(right, fringes=tuple(f + 1 for f in right.fringes))
    with pytest.raises(DecodeError):
        imported(stack, ps)


def test_a_wrong_pixel_centre_is_not_observable_and_said_so() -> None:
    """The one key the frames cannot show: a description giving pixel centre 0.5 for SLMaster's
    set decodes every coordinate 0.5 px further on (nothing refuses it), and the import says
    it was given; left out, it is assumed (ours) and said so."""
    stack = capture(TOOLS["slmaster_heterodyne_3x4.toml"](), U, lit=LIT, noise=0.002, seed=4)
    right = PatternSet.load(CONFIG / "slmaster_heterodyne_3x4.toml", detect=True)
    half = right.with_conventions(replace(right.conventions, pixel_centre=0.5))
    err = (imported(stack, half) - U)[LIT]
    assert np.nanmedian(err) == pytest.approx(-0.5, abs=0.02)
    found = {f.key: f for f in detect(stack, right.with_conventions(replace(right.conventions, pixel_centre=None)),
                                      8, PROJ, RIG).findings}
    assert found["pixel_centre"].source == "assumed" and "cannot show it" in found["pixel_centre"].evidence


@pytest.mark.parametrize("name", ["shifted_graycode", "four_level_intensity"])
def test_an_unsupported_family_is_refused_as_such(name: str, tmp_path: Path) -> None:
    from scanner.errors import ConfigError

    with pytest.raises(ConfigError, match=f"pattern family '{name}' is not supported \\(supported: heterodyne, "
                                          f"hierarchical, graycode, pixel_graycode\\)"):
        PatternSet.from_dict({"family": name, "steps": 4, "fringes": [16]}, tmp_path / "p.toml")
