"""Pattern conventions: how another structured-light tool's fringes differ from ours.

A pattern set's `[conventions]` table (all keys optional) says how its frames were made:

    phase_origin    rad   the phase of the displayed cosine at the start of a period
                          (ours 0; SLMaster's −π; OpenCV SinusoidalPattern's −π/2, a sine)
    step_sign       ±1    +1: step n adds +2πn/N to the phase (ours); −1: subtracts it
    pixel_centre    px    δ in Φ(c) = 2π·f·(c + δ)/W at projector pixel c (ours 0.5, so a
                          period starts at a pixel's left edge; 0: at a pixel's centre)
    frame_order           "frequency-major" (every step of frequency 1, then 2 …; ours) or
                          "step-major" (step 1 of every frequency, then step 2 …)
    gray_position         "after" the phase frames (ours) or "before" them
    gray_code             "complementary": ceil(log2 f) bits of the period index plus one
                          half-period bit (Wu et al.; ours, SLMaster) or "opencv": the Gray
                          code of every projector pixel, each bit followed by its inverse
                          (OpenCV structured_light.GrayCodePattern)
    references            "none", "first" or "last": an all-white and an all-black frame
                          (in that order) before or after everything else
    step_offset     int   the step the first frame of every group shows (ours 0; k: the
                          groups' frames rotated by k, as a trigger k patterns out of step)
    period_rounding       "none": a period is W/f pixels (ours, SLMaster's heterodyne);
                          "floor": floor(W/f) whole pixels (SLMaster's complementary set,
                          OpenCV's SinusoidalPattern), so the set has W/floor(W/f) periods

So the displayed intensity of phase step n is 0.5 + 0.5·cos(Φ(c) + phase_origin +
step_sign·2π(n + step_offset)/N), and a decoded phase becomes the OpenCV projector
coordinate (pixel centres at integers) x = (Φ − phase_origin)·W/(2π·f) − pixel_centre.

What frames can determine and what they cannot: the step sign (against a Gray code, or the
rig's calibrated geometry), the frame layout, and the phase's offset from a Gray code or
between frequencies — phase_origin + 2π·step_offset/N, one value that both readings decode
alike — to a discrete value (a multiple of π/2 or of a step). The pixel centre moves every
coordinate alike by a fraction of a pixel: a Gray-code edge locates a period boundary only
to within its blur, so it comes from the description or the user ("assumed" otherwise).

A key left out is None: `slscan import` detects what the frames determine and assumes the
rest, saying so (scanner.convention_detection); a pattern set used for scanning has every
key, our own values by default (NATIVE).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Annotated, Any, Literal, TypeVar, get_args

import numpy as np
from pydantic import Field, Strict, field_validator

from scanner import schema
from scanner.errors import ConfigError

FrameOrder = Literal["frequency-major", "step-major"]
GrayPosition = Literal["after", "before"]
GrayCode = Literal["complementary", "opencv"]
References = Literal["none", "first", "last"]
PeriodRounding = Literal["none", "floor"]
FRAME_ORDERS: tuple[str, ...] = get_args(FrameOrder)
GRAY_POSITIONS: tuple[str, ...] = get_args(GrayPosition)
GRAY_CODES: tuple[str, ...] = get_args(GrayCode)
REFERENCES: tuple[str, ...] = get_args(References)
PERIOD_ROUNDINGS: tuple[str, ...] = get_args(PeriodRounding)
LAYOUT_KEYS = ("frame_order", "gray_position", "gray_code", "references")  # the keys that order the frames
CHOICES: dict[str, tuple[str, ...]] = {"frame_order": FRAME_ORDERS, "gray_position": GRAY_POSITIONS,
                                       "gray_code": GRAY_CODES, "references": REFERENCES}


@dataclass(frozen=True)
class Conventions:
    """The conventions of one pattern set (module docstring); None: not known yet."""

    phase_origin: float | None = None
    step_sign: int | None = None
    pixel_centre: float | None = None
    frame_order: str | None = None
    gray_position: str | None = None
    gray_code: str | None = None
    references: str | None = None
    step_offset: int | None = None
    period_rounding: str | None = None

    def first_phase(self, steps: int) -> float:
        """The phase (rad) the first frame of every group adds: the origin and the groups'
        rotation (`step_offset` steps)."""
        origin = known(self.phase_origin, "phase_origin")
        sign, offset = known(self.step_sign, "step_sign"), known(self.step_offset, "step_offset")
        return float(origin) + sign * 2.0 * np.pi * offset / steps

    def missing(self) -> list[str]:
        """Names of the keys not known yet."""
        return [f.name for f in fields(self) if getattr(self, f.name) is None]

    @property
    def complete(self) -> bool:
        return not self.missing()

    def filled(self, defaults: Conventions) -> Conventions:
        """These conventions with every unknown key taken from `defaults`."""
        return replace(self, **{k: getattr(defaults, k) for k in self.missing()})

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}


T = TypeVar("T")


def known(value: T | None, key: str) -> T:
    """`value`, the convention `key`, where the caller needs it known: a ConfigError naming
    the key while it is None (neither given nor detected yet)."""
    if value is None:
        raise ConfigError("pattern set", f"conventions.{key}", "not known until it is given or detected")
    return value


class ConventionsFile(schema.Schema):
    """The `[conventions]` table as typed keys (module docstring); every key optional."""

    phase_origin: schema.Float | None = None
    step_sign: Annotated[int, Strict(), Field(ge=-1, le=1)] | None = None
    pixel_centre: Annotated[float, Strict(), Field(ge=0.0, lt=1.0)] | None = None
    frame_order: FrameOrder | None = None
    gray_position: GrayPosition | None = None
    gray_code: GrayCode | None = None
    references: References | None = None
    step_offset: Annotated[int, Strict(), Field(ge=0, le=63)] | None = None
    period_rounding: PeriodRounding | None = None

    @field_validator("step_sign")
    @classmethod
    def _sign(cls, v: int | None) -> int | None:
        if v == 0:
            raise ValueError("step_sign is 1 or -1")
        return v


NATIVE = Conventions(phase_origin=0.0, step_sign=1, pixel_centre=0.5, frame_order="frequency-major",
                     gray_position="after", gray_code="complementary", references="none", step_offset=0,
                     period_rounding="none")
