"""Fringe pattern sets: description, validation and rendering for a projector.

Phase convention (ours; other tools' in scanner/conventions.py): along the coded axis (x for
vertical fringes, y for horizontal), a fringe of count f over an extent of W pixels has
absolute phase Φ(c) = 2π·f·(c + δ)/W at pixel coordinate c, δ = 0.5, so Φ runs over
[0, 2π·f) across the whole extent; step n adds δn = 2π·n/N and the displayed intensity is
0.5 + 0.5·cos(Φ + δn). A pattern set's `conventions` generalise this (phase origin, step
sign, δ, frame order, Gray-code variant, white/black reference frames).

Families (the registry: scanner/pattern_families.py): "heterodyne" and "hierarchical"
(temporal phase unwrapping), "graycode" (phase shift unwrapped by a Gray code) and
"pixel_graycode" (OpenCV's GrayCodePattern alone: the Gray code of every projector pixel, no
phase shift; its frame count depends on the projector size, so it is known only
`for_projector`). Any other family is refused as not supported, naming those that are.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import numpy as np
from pydantic import Field, field_validator, model_validator

from scanner import schema
from scanner.config import load_toml
from scanner.conventions import LAYOUT_KEYS, NATIVE, Conventions, ConventionsFile, known
from scanner.errors import ConfigError
from scanner.pattern_families import (
    FAMILIES,
    REFERENCES,
    FrameKind,
    FrameSpec,
    PatternFamily,
    Unwrapping,
    family,
    gray_code,
    gray_to_binary,
)

__all__ = ["FAMILIES", "FrameSpec", "PatternFile", "PatternSet", "gray_code", "gray_to_binary"]

Orientation = Literal["vertical", "horizontal"]
ORIENTATIONS: tuple[str, ...] = get_args(Orientation)


class PatternFile(schema.Schema):
    """A pattern-set TOML (and a manifest's `patterns`) as typed keys; `PatternSet.validate`
    adds the family's rules. `conventions` (scanner/conventions.py) and `projector_size`
    are optional; a pixel Gray code has no steps or fringes."""

    family: schema.Str
    steps: Annotated[int, Field(strict=True, ge=0, le=64)] = 0
    fringes: Annotated[list[Annotated[float, Field(strict=True, gt=0, le=10000)]],
                       Field(max_length=8)] = Field(default_factory=list)
    orientations: Annotated[list[Orientation], Field(min_length=1, max_length=2)] = Field(default=["vertical"])
    conventions: ConventionsFile = ConventionsFile()
    projector_size: Annotated[list[Annotated[int, Field(strict=True, ge=2, le=100000)]],
                              Field(min_length=2, max_length=2)] | None = None

    @field_validator("family")
    @classmethod
    def _supported(cls, name: str) -> str:
        if name not in FAMILIES:
            raise ValueError(f"pattern family {name!r} is not supported (supported: {', '.join(FAMILIES)})")
        return name

    @model_validator(mode="after")
    def _phase_shift_keys(self) -> PatternFile:
        missing = [k for k in ("steps", "fringes") if k not in self.model_fields_set]
        if FAMILIES[self.family].has_phase and missing:
            raise ValueError(f"family '{self.family}' needs {' and '.join(missing)}")
        return self


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
        kind = family(self.family, where)
        if not self.orientations or any(o not in ORIENTATIONS for o in self.orientations) \
                or len(set(self.orientations)) != len(self.orientations):
            raise ConfigError(where, "orientations", f"{list(self.orientations)}: use one or both of {ORIENTATIONS}")
        kind.check(self.fringes, self.steps, where)

    @property
    def kind(self) -> PatternFamily:
        """This set's family (scanner.pattern_families)."""
        return FAMILIES[self.family]

    @property
    def unwrapping(self) -> Unwrapping:
        """How its fringe order is found (`PatternFamily.unwrapping`)."""
        return self.kind.unwrapping(self.conventions.gray_code)

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
        return self.unwrapping.pixel_code

    def gray_bits(self, orientation: str = "vertical") -> int:
        """Gray-code bits per orientation: of the phase-shift periods (without the
        complementary bit), or of the projector pixels for a pixel code (0: no code)."""
        extent = None if self.projector_size is None else self.projector_size[0 if orientation == "vertical" else 1]
        return self.kind.gray_bits(self.fringes, extent, self.uses_pixel_code)

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
            phase = [FrameSpec(o, FrameKind.PHASE, lv, n) for lv, n in pairs]
            gray = self.kind.code_frames(o, self.gray_bits(o), self.uses_pixel_code)
            out += phase + gray if c.gray_position == "after" else gray + phase
        refs = [FrameSpec(self.orientations[0], kind, 0, 0) for kind in REFERENCES]
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
        if s.kind is FrameKind.PHASE:
            centre, sign = known(conv.pixel_centre, "pixel_centre"), known(conv.step_sign, "step_sign")
            phase = 2.0 * np.pi * self.fringes[s.level] * (c + centre) / extent
            phase += conv.first_phase(self.steps)
            return 0.5 + 0.5 * np.cos(phase + sign * 2.0 * np.pi * s.step / self.steps)
        if s.kind in REFERENCES:
            return np.full(extent, 1.0 if s.kind is FrameKind.WHITE else 0.0)
        return self.kind.code_profile(s, extent, self.fringes, self.uses_pixel_code)
