"""Fringe pattern sets: description, validation and rendering for a projector.

Phase convention (ours; other tools' in scanner/conventions.py): along the coded axis (x for
vertical fringes, y for horizontal), a fringe of count f over an extent of W pixels has
absolute phase Φ(c) = 2π·f·(c + δ)/W at pixel coordinate c, δ = 0.5, so Φ runs over
[0, 2π·f) across the whole extent; step n adds δn = 2π·n/N and the displayed intensity is
0.5 + 0.5·cos(Φ + δn). A pattern set's `conventions` generalise this (phase origin, step
sign, δ, frame order, Gray-code variant, white/black reference frames).

Families: "heterodyne" and "hierarchical" (temporal phase unwrapping), "graycode" (phase
shift unwrapped by a Gray code) and "pixel_graycode" (OpenCV's GrayCodePattern alone: the
Gray code of every projector pixel, no phase shift; its frame count depends on the
projector size, so it is known only `for_projector`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, model_validator

from scanner import schema
from scanner.config import load_toml
from scanner.conventions import LAYOUT_KEYS, NATIVE, Conventions, ConventionsFile
from scanner.errors import ConfigError

FAMILIES = ("heterodyne", "hierarchical", "graycode", "pixel_graycode")
ORIENTATIONS = ("vertical", "horizontal")
KINDS = ("phase", "gray", "gray_inverse", "white", "black")


class PatternFile(schema.Schema):
    """A pattern-set TOML (and a manifest's `patterns`) as typed keys; `PatternSet.validate`
    adds the family's rules. `conventions` (scanner/conventions.py) and `projector_size`
    are optional; a pixel Gray code has no steps or fringes."""

    family: Literal[FAMILIES]
    steps: Annotated[int, Field(strict=True, ge=0, le=64)] = 0
    fringes: Annotated[list[Annotated[float, Field(strict=True, gt=0, le=10000)]], Field(max_length=8)] = []
    orientations: Annotated[list[Literal[ORIENTATIONS]], Field(min_length=1, max_length=2)] = ["vertical"]
    conventions: ConventionsFile = ConventionsFile()
    projector_size: Annotated[list[Annotated[int, Field(strict=True, ge=2, le=100000)]],
                              Field(min_length=2, max_length=2)] | None = None

    @model_validator(mode="after")
    def _phase_shift_keys(self) -> PatternFile:
        missing = [k for k in ("steps", "fringes") if k not in self.model_fields_set]
        if self.family != "pixel_graycode" and missing:
            raise ValueError(f"family '{self.family}' needs {' and '.join(missing)}")
        return self


@dataclass(frozen=True)
class FrameSpec:
    """What one frame of the sequence shows."""

    orientation: str  # vertical | horizontal (white and black: the first orientation)
    kind: str  # phase | gray | gray_inverse | white | black
    level: int  # phase: frequency index; gray: bit index (0 = most significant)
    step: int  # phase: step index n; otherwise 0


@dataclass(frozen=True)
class PatternSet:
    """A fringe pattern family with its parameters.

    `fringes`: fringe counts across the coded extent, one per frequency (graycode: the one
    phase-shift frequency; pixel_graycode: none). `steps`: phase steps N per frequency
    (>= 3; pixel_graycode: 0). `conventions`: how the frames were made (ours by default).
    `projector_size`: (width, height) px, needed only by OpenCV-style pixel Gray codes.
    """

    family: str
    steps: int
    fringes: tuple[float, ...]
    orientations: tuple[str, ...] = ("vertical",)
    conventions: Conventions = NATIVE
    projector_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        self.validate("pattern set")

    def validate(self, where: str | Path) -> None:
        if self.family not in FAMILIES:
            raise ConfigError(where, "family", f"'{self.family}' is not one of {FAMILIES}")
        if not self.orientations or any(o not in ORIENTATIONS for o in self.orientations) \
                or len(set(self.orientations)) != len(self.orientations):
            raise ConfigError(where, "orientations", f"{list(self.orientations)}: use one or both of {ORIENTATIONS}")
        if self.family == "pixel_graycode":
            if self.fringes or self.steps:
                raise ConfigError(where, "fringes", "pixel_graycode has no phase shift: leave out steps and fringes")
            return
        if self.steps < 3:
            raise ConfigError(where, "steps", f"N-step phase shift needs N >= 3, got {self.steps}")
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
    def from_dict(cls, d: Any, where: str | Path = "pattern set", prefix: str = "", detect: bool = False
                  ) -> PatternSet:
        """A pattern set described by `d` (a pattern TOML, or a manifest's `patterns`): keys
        known and typed (`PatternFile`), then the family's rules (`validate`). Convention keys
        left out take our own values, or with `detect` stay unknown (None) for
        `scanner.convention_detection` to find."""
        f = schema.parse(PatternFile, d, where, prefix)
        conventions = Conventions(**f.conventions.model_dump())
        ps = cls.__new__(cls)
        object.__setattr__(ps, "family", f.family)
        object.__setattr__(ps, "steps", f.steps)
        object.__setattr__(ps, "fringes", tuple(f.fringes))
        object.__setattr__(ps, "orientations", tuple(f.orientations))
        object.__setattr__(ps, "conventions", conventions if detect else conventions.filled(NATIVE))
        object.__setattr__(ps, "projector_size", None if f.projector_size is None else tuple(f.projector_size))
        ps.validate(where)
        return ps

    @classmethod
    def load(cls, path: str | Path, detect: bool = False) -> PatternSet:
        return cls.from_dict(load_toml(path), Path(path), detect=detect)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"family": self.family, "steps": self.steps, "fringes": list(self.fringes),
                             "orientations": list(self.orientations)}
        if self.conventions != NATIVE:
            d["conventions"] = self.conventions.to_dict()
        if self.projector_size is not None:
            d["projector_size"] = list(self.projector_size)
        return d

    def for_projector(self, size: tuple[int, int]) -> PatternSet:
        """This set on a projector of `size` = (width, height) px; with `period_rounding`
        "floor", its periods made whole pixels: floor(W/f) px each, so W/floor(W/f) of them."""
        out = replace(self, projector_size=(int(size[0]), int(size[1])))
        if self.conventions.period_rounding != "floor":
            return out
        if len(self.orientations) != 1:
            raise ConfigError("pattern set", "conventions.period_rounding", "whole-pixel periods along both "
                                                                             "orientations differ: give one")
        extent = size[0] if self.orientations[0] == "vertical" else size[1]
        fringes = tuple(extent / np.floor(extent / f) for f in self.fringes)
        return replace(out, fringes=fringes, conventions=replace(self.conventions, period_rounding="none"))

    def with_conventions(self, conventions: Conventions) -> PatternSet:
        return replace(self, conventions=conventions)

    @property
    def uses_pixel_code(self) -> bool:
        """Gray code of every projector pixel (OpenCV's layout) rather than of the periods."""
        return self.family == "pixel_graycode" or (self.family == "graycode" and self.conventions.gray_code == "opencv")

    def gray_bits(self, orientation: str = "vertical") -> int:
        """Gray-code bits per orientation: of the phase-shift periods (without the
        complementary bit), or of the projector pixels for a pixel code."""
        if self.uses_pixel_code:
            if self.projector_size is None:
                raise ConfigError("pattern set", "projector_size", "a pixel Gray code's frames depend on the "
                                                                   "projector size; give it (--projector-size)")
            extent = self.projector_size[0 if orientation == "vertical" else 1]
            return int(np.ceil(np.log2(extent)))
        return int(np.ceil(np.log2(self.fringes[0]))) if self.family == "graycode" else 0

    def _gray_block(self, o: str) -> list[FrameSpec]:
        if self.uses_pixel_code:
            return [FrameSpec(o, kind, b, 0) for b in range(self.gray_bits(o)) for kind in ("gray", "gray_inverse")]
        return [FrameSpec(o, "gray", b, 0) for b in range(self.gray_bits(o) + 1)]

    def frames(self) -> list[FrameSpec]:
        """The frame sequence in capture order (`conventions`): per orientation the phase
        frames (frequency- or step-major) and the Gray-code frames (after or before them),
        with the white and black reference frames first or last."""
        c = self.conventions
        unknown = [k for k in LAYOUT_KEYS if getattr(c, k) is None]
        if unknown:
            raise ConfigError("pattern set", "conventions", f"frame order unknown until {unknown} are given or "
                                                            f"detected")
        out: list[FrameSpec] = []
        levels, steps = range(len(self.fringes)), range(self.steps)
        for o in self.orientations:
            pairs = [(lv, n) for lv in levels for n in steps] if c.frame_order == "frequency-major" else \
                [(lv, n) for n in steps for lv in levels]
            phase = [FrameSpec(o, "phase", lv, n) for lv, n in pairs]
            gray = self._gray_block(o) if self.family in ("graycode", "pixel_graycode") else []
            out += phase + gray if c.gray_position == "after" else gray + phase
        refs = [FrameSpec(self.orientations[0], "white", 0, 0), FrameSpec(self.orientations[0], "black", 0, 0)]
        return refs + out if c.references == "first" else out + refs if c.references == "last" else out

    @property
    def n_frames(self) -> int:
        return len(self.frames())

    def render(self, width: int, height: int, gamma: float = 1.0) -> np.ndarray:
        """(n_frames, height, width) uint8 patterns, pre-compensated for a projector whose
        output is (command/255)^gamma so the displayed fringes are sinusoidal."""
        on_projector = self.for_projector((width, height))
        specs = on_projector.frames()
        out = np.empty((len(specs), height, width), dtype=np.uint8)
        for i, s in enumerate(specs):
            extent = width if s.orientation == "vertical" else height
            profile = on_projector.profile(s, extent)
            encoded = np.round(255.0 * np.clip(profile, 0.0, 1.0) ** (1.0 / gamma)).astype(np.uint8)
            out[i] = encoded[None, :] if s.orientation == "vertical" else encoded[:, None]
        return out

    def profile(self, s: FrameSpec, extent: int) -> np.ndarray:
        """Desired displayed intensity (0..1) along the coded axis."""
        c = np.arange(extent, dtype=np.float64)
        conv = self.conventions
        if s.kind == "phase":
            phase = 2.0 * np.pi * self.fringes[s.level] * (c + conv.pixel_centre) / extent
            phase += conv.first_phase(self.steps)
            return 0.5 + 0.5 * np.cos(phase + conv.step_sign * 2.0 * np.pi * s.step / self.steps)
        if s.kind in ("white", "black"):
            return np.full(extent, 1.0 if s.kind == "white" else 0.0)
        if self.uses_pixel_code:
            n_bits = int(np.ceil(np.log2(extent)))
            bit = ((gray_code(c.astype(np.int64)) >> (n_bits - 1 - s.level)) & 1).astype(np.float64)
            return bit if s.kind == "gray" else 1.0 - bit
        n_bits = int(np.ceil(np.log2(self.fringes[0])))
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
