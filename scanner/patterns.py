"""Fringe pattern sets: description, validation and rendering for a projector.

Phase convention: along the coded axis (x for vertical fringes, y for horizontal), a fringe
of count f over an extent of W pixels has absolute phase Φ(c) = 2π·f·(c + 0.5)/W at pixel
coordinate c, so Φ runs over [0, 2π·f) across the whole extent; step n adds δn = 2π·n/N and
the displayed intensity is 0.5 + 0.5·cos(Φ + δn).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field

from scanner import schema
from scanner.config import load_toml
from scanner.errors import ConfigError

FAMILIES = ("heterodyne", "hierarchical", "graycode")
ORIENTATIONS = ("vertical", "horizontal")


class PatternFile(schema.Schema):
    """A pattern-set TOML (and a manifest's `patterns`) as typed keys; `PatternSet.validate`
    adds the family's rules."""

    family: Literal[FAMILIES]
    steps: Annotated[int, Field(strict=True, ge=3, le=64)]
    fringes: Annotated[list[Annotated[float, Field(strict=True, gt=0, le=10000)]], Field(min_length=1, max_length=8)]
    orientations: Annotated[list[Literal[ORIENTATIONS]], Field(min_length=1, max_length=2)] = ["vertical"]


@dataclass(frozen=True)
class FrameSpec:
    """What one frame of the sequence shows."""

    orientation: str  # vertical | horizontal
    kind: str  # phase | gray
    level: int  # phase: frequency index; gray: bit index (0 = most significant)
    step: int  # phase: step index n; gray: 0


@dataclass(frozen=True)
class PatternSet:
    """A fringe pattern family with its parameters.

    `fringes`: fringe counts across the coded extent, one per frequency (graycode: the one
    phase-shift frequency). `steps`: phase steps N per frequency (>= 3).
    """

    family: str
    steps: int
    fringes: tuple[float, ...]
    orientations: tuple[str, ...] = ("vertical",)

    def __post_init__(self) -> None:
        self.validate("pattern set")

    def validate(self, where: str | Path) -> None:
        if self.family not in FAMILIES:
            raise ConfigError(where, "family", f"'{self.family}' is not one of {FAMILIES}")
        if self.steps < 3:
            raise ConfigError(where, "steps", f"N-step phase shift needs N >= 3, got {self.steps}")
        if not self.orientations or any(o not in ORIENTATIONS for o in self.orientations) \
                or len(set(self.orientations)) != len(self.orientations):
            raise ConfigError(where, "orientations", f"{list(self.orientations)}: use one or both of {ORIENTATIONS}")
        f = self.fringes
        if not f or any(x <= 0 for x in f):
            raise ConfigError(where, "fringes", "fringe counts must be positive")
        if self.family == "heterodyne":
            if len(f) != 3 or not f[0] > f[1] > f[2] or abs((f[0] - f[1]) - (f[1] - f[2]) - 1) > 1e-9:
                raise ConfigError(where, "fringes", f"three-frequency heterodyne needs f1 > f2 > f3 with "
                                                    f"(f1-f2)-(f2-f3) = 1, got {list(f)}")
        elif self.family == "hierarchical":
            if f[0] != 1 or any(b <= a for a, b in zip(f, f[1:])):
                raise ConfigError(where, "fringes", f"hierarchical counts must start at 1 and increase, got {list(f)}")
            if any(b / a > 16 for a, b in zip(f, f[1:])):
                raise ConfigError(where, "fringes", f"ratio between successive counts above 16 is not reliably "
                                                    f"unwrappable: {list(f)}")
        elif len(f) != 1:
            raise ConfigError(where, "fringes", f"graycode takes one phase-shift fringe count, got {list(f)}")

    @classmethod
    def from_dict(cls, d: Any, where: str | Path = "pattern set", prefix: str = "") -> PatternSet:
        """A pattern set described by `d` (a pattern TOML, or a manifest's `patterns`): keys
        known and typed (`PatternFile`), then the family's rules (`validate`)."""
        f = schema.parse(PatternFile, d, where, prefix)
        ps = cls.__new__(cls)
        object.__setattr__(ps, "family", f.family)
        object.__setattr__(ps, "steps", f.steps)
        object.__setattr__(ps, "fringes", tuple(f.fringes))
        object.__setattr__(ps, "orientations", tuple(f.orientations))
        ps.validate(where)
        return ps

    @classmethod
    def load(cls, path: str | Path) -> PatternSet:
        return cls.from_dict(load_toml(path), Path(path))

    def to_dict(self) -> dict[str, Any]:
        return {"family": self.family, "steps": self.steps, "fringes": list(self.fringes),
                "orientations": list(self.orientations)}

    def gray_bits(self) -> int:
        """Gray-code bits that number the phase-shift periods (without the complementary bit)."""
        return int(np.ceil(np.log2(self.fringes[0]))) if self.family == "graycode" else 0

    def frames(self) -> list[FrameSpec]:
        """The frame sequence: per orientation, every frequency's N steps, then Gray bits
        (the last one being the complementary half-period bit)."""
        out: list[FrameSpec] = []
        for o in self.orientations:
            for level in range(len(self.fringes)):
                out += [FrameSpec(o, "phase", level, n) for n in range(self.steps)]
            if self.family == "graycode":
                out += [FrameSpec(o, "gray", b, 0) for b in range(self.gray_bits() + 1)]
        return out

    @property
    def n_frames(self) -> int:
        return len(self.frames())

    def render(self, width: int, height: int, gamma: float = 1.0) -> np.ndarray:
        """(n_frames, height, width) uint8 patterns, pre-compensated for a projector whose
        output is (command/255)^gamma so the displayed fringes are sinusoidal."""
        specs = self.frames()
        out = np.empty((len(specs), height, width), dtype=np.uint8)
        for i, s in enumerate(specs):
            extent = width if s.orientation == "vertical" else height
            profile = self.profile(s, extent)
            encoded = np.round(255.0 * np.clip(profile, 0.0, 1.0) ** (1.0 / gamma)).astype(np.uint8)
            out[i] = encoded[None, :] if s.orientation == "vertical" else encoded[:, None]
        return out

    def profile(self, s: FrameSpec, extent: int) -> np.ndarray:
        """Desired displayed intensity (0..1) along the coded axis."""
        c = np.arange(extent, dtype=np.float64)
        if s.kind == "phase":
            phase = 2.0 * np.pi * self.fringes[s.level] * (c + 0.5) / extent
            return 0.5 + 0.5 * np.cos(phase + 2.0 * np.pi * s.step / self.steps)
        n_bits = self.gray_bits()
        period = extent / self.fringes[0]
        if s.level < n_bits:
            code = gray_code(np.floor((c + 0.5) / period).astype(np.int64))
            return ((code >> (n_bits - 1 - s.level)) & 1).astype(np.float64)
        # complementary bit: the least significant bit of a Gray code at half the period
        code = gray_code(np.floor((c + 0.5) / (period / 2.0)).astype(np.int64))
        return (code & 1).astype(np.float64)


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
