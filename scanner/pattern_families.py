"""The pattern families slscan encodes and decodes: one object per family, the one registry
(`FAMILIES`) that pattern sets, the decoder and the convention detection ask.

Each family says what its frames are (the frame layout of its code block and the keys that
order its frames), how to draw each of them (`code_profile`; the phase frames are common to
all phase-shift families), how its fringe order is found (`unwrapping`, an `Unwrapping`:
temporal — the frequencies unwrap each other, their rules in `unwrap` and
`residual_variances` —, complementary — a Gray code of the periods with a half-period bit —,
pixel phase — OpenCV's Gray code of every projector pixel unwrapping one phase — or pixel
only), and which conventions its frames can determine (`determines`). A family not here is
refused by name with the list of those that are (`family`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, StrEnum
from itertools import pairwise
from typing import Any, ClassVar

import numpy as np

from scanner.errors import ConfigError

TWO_PI = np.float32(2.0 * np.pi)


class FrameKind(StrEnum):
    """What a frame shows; its value is the name sessions and pattern files write."""

    PHASE = "phase"  # one phase step of one fringe frequency
    GRAY = "gray"  # one bit of a Gray code
    GRAY_INVERSE = "gray_inverse"  # that bit inverted (a pixel Gray code's pair)
    WHITE = "white"  # the full-on reference
    BLACK = "black"  # the full-off reference


REFERENCES = (FrameKind.WHITE, FrameKind.BLACK)  # the frames a sequence's intensities are read against
PIXEL_CODE_PAIR = (FrameKind.GRAY, FrameKind.GRAY_INVERSE)  # each bit of a pixel Gray code, then its inverse


@dataclass(frozen=True)
class FrameSpec:
    """What one frame of the sequence shows."""

    orientation: str  # vertical | horizontal (white and black: the first orientation)
    kind: FrameKind
    level: int  # phase: frequency index; gray: bit index (0 = most significant)
    step: int  # phase: step index n; otherwise 0


class Unwrapping(Enum):
    """How a family finds its fringe order (module docstring): what the decoder and the
    convention detection dispatch on."""

    TEMPORAL = "temporal"
    COMPLEMENTARY = "complementary"
    PIXEL_PHASE = "pixel_phase"
    PIXEL_ONLY = "pixel_only"

    @property
    def by_frequencies(self) -> bool:
        """The phase-shift frequencies unwrap each other (no Gray code)."""
        return self is Unwrapping.TEMPORAL

    @property
    def pixel_code(self) -> bool:
        """A Gray code of every projector pixel (OpenCV's layout) rather than of the periods."""
        return self in (Unwrapping.PIXEL_PHASE, Unwrapping.PIXEL_ONLY)


def gray_code(n: np.ndarray) -> np.ndarray:
    return n ^ (n >> 1)


def gray_to_binary(g: np.ndarray, n_bits: int) -> np.ndarray:
    """Inverse of `gray_code` for codes of `n_bits` bits."""
    b = g.copy()
    shift = 1
    while shift < n_bits:
        b ^= b >> shift
        shift <<= 1
    return b


def unwrap_step(coarse: np.ndarray, ratio: float, fine_wrapped: np.ndarray, worst: np.ndarray) -> np.ndarray:
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


def wrap_positive(d: np.ndarray) -> np.ndarray:
    """Differences of two [0, 2π) phases mapped into [0, 2π), in place (2π added where negative)."""
    return np.add(d, TWO_PI, out=d, where=d < 0)


class PatternFamily:
    """One family (module docstring); the phase-shift families share the phase frames."""

    name: ClassVar[str]
    summary: ClassVar[str]
    determines: ClassVar[str]  # which conventions its frames determine, for people
    has_phase: ClassVar[bool] = True

    def check(self, fringes: tuple[float, ...], steps: int, where: Any) -> None:
        """Its rules for steps and fringe counts (ConfigError naming the key)."""
        if steps < 3:
            raise ConfigError(where, "steps", f"N-step phase shift needs N >= 3, got {steps}")
        if not fringes or any(x <= 0 for x in fringes):
            raise ConfigError(where, "fringes", "fringe counts must be positive")

    def unwrapping(self, gray_code_variant: str | None) -> Unwrapping:
        raise NotImplementedError

    def layout_keys(self, n_fringes: int) -> list[str]:
        """The convention keys that order its frames (beside `references`)."""
        return ["frame_order"] if n_fringes > 1 else []

    def gray_bits(self, fringes: tuple[float, ...], extent: int | None, pixel_code: bool) -> int:
        """Gray-code bits per orientation (0: no code)."""
        return 0

    def code_frames(self, orientation: str, bits: int, pixel_code: bool) -> list[FrameSpec]:
        return []

    def code_profile(self, spec: FrameSpec, extent: int, fringes: tuple[float, ...], pixel_code: bool) -> np.ndarray:
        raise NotImplementedError(f"{self.name} has no code frames")


class TemporalFamily(PatternFamily):
    """Several phase-shift frequencies that unwrap each other."""

    determines = ("the frame layout; the phase's offset (origin and step rotation) from the frequencies' beats; "
                  "the step sign only against a calibrated geometry")

    def unwrapping(self, gray_code_variant: str | None) -> Unwrapping:
        return Unwrapping.TEMPORAL

    def unwrap(self, fringes: tuple[float, ...], wrapped: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
        """Absolute phase per frequency and the worst unwrapping residual (fraction of π)."""
        raise NotImplementedError

    def residual_variances(self, fringes: tuple[float, ...], var: list[np.ndarray]) -> list[np.ndarray]:
        """The variance (rad²) of each unwrapping step's residual from each frequency's phase
        variance `var`, propagated through the steps."""
        raise NotImplementedError

    def offset_free_phase(self, fringes: tuple[float, ...], wrapped: list[np.ndarray]
                          ) -> tuple[np.ndarray, float] | None:
        """An absolute phase the frequencies' beats give, free of any offset common to every
        frequency (a phase origin, a rotation of the steps), and its fringe count; None when
        the family has no such beat."""
        return None


class Heterodyne(TemporalFamily):
    name = "heterodyne"
    summary = "three frequencies f1 > f2 > f3 with (f1 − f2) − (f2 − f3) = 1, unwrapped through their beats"

    def check(self, fringes: tuple[float, ...], steps: int, where: Any) -> None:
        super().check(fringes, steps, where)
        f = fringes
        if len(f) != 3 or not f[0] > f[1] > f[2] or abs((f[0] - f[1]) - (f[1] - f[2]) - 1) > 1e-9:
            raise ConfigError(where, "fringes", f"three-frequency heterodyne needs f1 > f2 > f3 with "
                                                f"(f1-f2)-(f2-f3) = 1, got {list(f)}")

    def unwrap(self, fringes: tuple[float, ...], wrapped: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
        f = fringes
        worst = np.zeros_like(wrapped[0])
        p12 = wrap_positive(wrapped[0] - wrapped[1])
        p23 = wrap_positive(wrapped[1] - wrapped[2])
        p123 = wrap_positive(p12 - p23)
        f12 = f[0] - f[1]
        a12 = unwrap_step(p123, f12, p12, worst)  # the f1-f2 beat is the finer one: unwrap all three from it
        return [unwrap_step(a12, f[i] / f12, wrapped[i], worst) for i in range(3)], worst

    def offset_free_phase(self, fringes: tuple[float, ...], wrapped: list[np.ndarray]
                          ) -> tuple[np.ndarray, float] | None:
        f = fringes
        p12 = wrap_positive(wrapped[0] - wrapped[1])
        p123 = wrap_positive(p12 - wrap_positive(wrapped[1] - wrapped[2]))
        return unwrap_step(p123, f[0] - f[1], p12, np.zeros_like(p12)), f[0] - f[1]

    def residual_variances(self, fringes: tuple[float, ...], var: list[np.ndarray]) -> list[np.ndarray]:
        f = fringes
        f12 = f[0] - f[1]
        v12 = var[0] + var[1]
        v123 = var[0] + 4 * var[1] + var[2]
        return [f12 ** 2 * v123 + v12] + [(f[i] / f12) ** 2 * v12 + var[i] for i in range(3)]


class Hierarchical(TemporalFamily):
    name = "hierarchical"
    summary = "increasing fringe counts from 1, each unwrapping the next"
    determines = "the frame layout; the step sign only against a calibrated geometry (no phase offset: assumed)"

    def check(self, fringes: tuple[float, ...], steps: int, where: Any) -> None:
        super().check(fringes, steps, where)
        f = fringes
        if f[0] != 1 or any(b <= a for a, b in pairwise(f)):
            raise ConfigError(where, "fringes", f"hierarchical counts must start at 1 and increase, got {list(f)}")
        if any(b / a > 16 for a, b in pairwise(f)):
            raise ConfigError(where, "fringes", f"ratio between successive counts above 16 is not reliably "
                                                f"unwrappable: {list(f)}")

    def unwrap(self, fringes: tuple[float, ...], wrapped: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
        worst = np.zeros_like(wrapped[0])
        absolute = [wrapped[0]]
        for i in range(1, len(fringes)):
            absolute.append(unwrap_step(absolute[-1], fringes[i] / fringes[i - 1], wrapped[i], worst))
        return absolute, worst

    def residual_variances(self, fringes: tuple[float, ...], var: list[np.ndarray]) -> list[np.ndarray]:
        f = fringes
        return [(f[i] / f[i - 1]) ** 2 * var[i - 1] + var[i] for i in range(1, len(f))]


class GrayCodePhase(PatternFamily):
    name = "graycode"
    summary = ("one phase-shift frequency unwrapped by a Gray code: of its periods with a half-period bit (Wu et al., "
               "gray_code 'complementary') or of every projector pixel (OpenCV's, gray_code 'opencv')")
    determines = "the frame layout; the step sign and the phase's offset (origin and step rotation) from the code"

    def check(self, fringes: tuple[float, ...], steps: int, where: Any) -> None:
        super().check(fringes, steps, where)
        if len(fringes) != 1:
            raise ConfigError(where, "fringes", f"graycode takes one phase-shift fringe count, got {list(fringes)}")

    def unwrapping(self, gray_code_variant: str | None) -> Unwrapping:
        return Unwrapping.PIXEL_PHASE if gray_code_variant == "opencv" else Unwrapping.COMPLEMENTARY

    def layout_keys(self, n_fringes: int) -> list[str]:
        return ["gray_position", "gray_code"]

    def gray_bits(self, fringes: tuple[float, ...], extent: int | None, pixel_code: bool) -> int:
        if pixel_code:
            return PixelGrayCode().gray_bits(fringes, extent, True)
        return int(np.ceil(np.log2(fringes[0])))

    def code_frames(self, orientation: str, bits: int, pixel_code: bool) -> list[FrameSpec]:
        if pixel_code:
            return PixelGrayCode().code_frames(orientation, bits, True)
        return [FrameSpec(orientation, FrameKind.GRAY, b, 0) for b in range(bits + 1)]

    def code_profile(self, spec: FrameSpec, extent: int, fringes: tuple[float, ...], pixel_code: bool) -> np.ndarray:
        if pixel_code:
            return PixelGrayCode().code_profile(spec, extent, fringes, True)
        c = np.arange(extent, dtype=np.float64)
        n_bits = int(np.ceil(np.log2(fringes[0])))
        period = extent / fringes[0]
        if spec.level < n_bits:
            code = gray_code(np.floor((c + 0.5) / period).astype(np.int64))
            return ((code >> (n_bits - 1 - spec.level)) & 1).astype(np.float64)
        # complementary bit: the least significant bit of a Gray code at half the period
        code = gray_code(np.floor((c + 0.5) / (period / 2.0)).astype(np.int64))
        return (code & 1).astype(np.float64)


class PixelGrayCode(PatternFamily):
    name = "pixel_graycode"
    summary = "OpenCV's GrayCodePattern alone: every projector pixel's Gray code, each bit with its inverse"
    determines = "the frame layout (references); whole projector pixels, nothing else to convene"
    has_phase = False

    def check(self, fringes: tuple[float, ...], steps: int, where: Any) -> None:
        if fringes or steps:
            raise ConfigError(where, "fringes", "pixel_graycode has no phase shift: leave out steps and fringes")

    def unwrapping(self, gray_code_variant: str | None) -> Unwrapping:
        return Unwrapping.PIXEL_ONLY

    def layout_keys(self, n_fringes: int) -> list[str]:
        return []

    def gray_bits(self, fringes: tuple[float, ...], extent: int | None, pixel_code: bool) -> int:
        if extent is None:
            raise ConfigError("pattern set", "projector_size", "a pixel Gray code's frames depend on the projector "
                                                               "size; give it (--projector-size)")
        return int(np.ceil(np.log2(extent)))

    def code_frames(self, orientation: str, bits: int, pixel_code: bool) -> list[FrameSpec]:
        return [FrameSpec(orientation, kind, b, 0) for b in range(bits) for kind in PIXEL_CODE_PAIR]

    def code_profile(self, spec: FrameSpec, extent: int, fringes: tuple[float, ...], pixel_code: bool) -> np.ndarray:
        n_bits = int(np.ceil(np.log2(extent)))
        bit = ((gray_code(np.arange(extent, dtype=np.int64)) >> (n_bits - 1 - spec.level)) & 1).astype(np.float64)
        return bit if spec.kind is FrameKind.GRAY else 1.0 - bit


FAMILIES: dict[str, PatternFamily] = {f.name: f for f in (Heterodyne(), Hierarchical(), GrayCodePhase(),
                                                          PixelGrayCode())}


def temporal(kind: PatternFamily) -> TemporalFamily:
    """`kind`, where the caller unwraps by its frequencies (`Unwrapping.TEMPORAL`): a
    ConfigError for a family whose fringe order a Gray code gives."""
    if not isinstance(kind, TemporalFamily):
        raise ConfigError("pattern set", "family", f"'{kind.name}' does not unwrap by its frequencies")
    return kind


def family(name: str, where: Any = "pattern set") -> PatternFamily:
    """The family called `name`; ConfigError naming it and the supported ones otherwise
    (shifted Gray codes, multi-level intensity codes and others are not decoded)."""
    try:
        return FAMILIES[name]
    except KeyError:
        raise ConfigError(where, "family", f"pattern family {name!r} is not supported (supported: "
                                           f"{', '.join(FAMILIES)})") from None
