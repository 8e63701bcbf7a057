"""Calibrated artefacts for the acceptance test (`slscan verify`), described in TOML with
their calibration certificates (`config/artefacts/`). Lengths in mm; every `*_u_mm` is an
expanded uncertainty (k = 2) as certificates state them.

    name = "bench artefact set"

    [sphere]                      # probing errors PF, PS
    certificate = "S-0421"        # the certificate's number, copied into the report
    diameter_mm = 25.4003         # calibrated diameter
    diameter_u_mm = 0.0010
    form_mm = 0.0008              # calibrated form deviation (sphericity)
    albedo = 0.7                  # simulator only: the surface's reflectance (0..1)

    [ball_bar]                    # sphere-spacing error SD, length measurement error E
    certificate = "BB-117"
    length_mm = 100.0021          # calibrated distance between the sphere centres
    length_u_mm = 0.0015
    diameter_mm = 20.0004         # both spheres (calibrated)
    diameter_u_mm = 0.0010
    form_mm = 0.0008
    albedo = 0.7

    [plane]                       # flatness measurement error F
    certificate = "P-0032"
    size_mm = [120.0, 40.0]       # the measured face (length, width)
    flatness_mm = 0.0010          # calibrated flatness
    flatness_u_mm = 0.0005
    albedo = 0.8
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, ValidationInfo, field_validator, model_validator

from scanner import schema
from scanner.config import CONFIG_DIR
from scanner.schema import NonNegativeFloat, PositiveFloat, Schema, Str

DEFAULT_ARTEFACTS = CONFIG_DIR / "artefacts" / "sim_bench.toml"
Albedo = Annotated[float, Field(strict=True, ge=0.0, le=1.0)]  # simulator only: the surface's reflectance


class Sphere(Schema):
    """A calibrated sphere (diameter, its U, its form deviation; mm)."""

    certificate: Str
    diameter_mm: PositiveFloat
    diameter_u_mm: NonNegativeFloat
    form_mm: NonNegativeFloat
    albedo: Albedo = 0.7

    @property
    def radius_mm(self) -> float:
        return self.diameter_mm / 2.0


class BallBar(Sphere):
    """Two spheres of the calibrated diameter whose centres are `length_mm` apart."""

    length_mm: PositiveFloat
    length_u_mm: NonNegativeFloat

    @field_validator("length_mm")
    @classmethod
    def _apart(cls, length: float, info: ValidationInfo) -> float:
        if length <= info.data.get("diameter_mm", 0.0):
            raise ValueError("the spheres would overlap: length_mm must exceed diameter_mm")
        return length


class Plane(Schema):
    """A calibrated flat: its measured face (length, width) and flatness with its U (mm)."""

    certificate: Str
    size_mm: Annotated[list[PositiveFloat], Field(min_length=2, max_length=2)]  # length, width
    flatness_mm: NonNegativeFloat
    flatness_u_mm: NonNegativeFloat
    albedo: Albedo = 0.8


class ArtefactFile(Schema):
    """An artefact TOML (see the module docstring): at least one artefact."""

    name: Str | None = None
    sphere: Sphere | None = None
    ball_bar: BallBar | None = None
    plane: Plane | None = None

    @model_validator(mode="after")
    def _some(self) -> ArtefactFile:
        if self.sphere is None and self.ball_bar is None and self.plane is None:
            raise ValueError("no artefact: give at least one of the tables ['ball_bar', 'plane', 'sphere']")
        return self


@dataclass(frozen=True)
class ArtefactSet:
    """The artefacts of one acceptance test (each may be absent: its figures are then not
    measured) and the file they came from."""

    name: str
    sphere: Sphere | None
    ball_bar: BallBar | None
    plane: Plane | None
    path: Path | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "path": str(self.path) if self.path else None,
                **{k: v.model_dump() if v is not None else None for k, v in
                   (("sphere", self.sphere), ("ball_bar", self.ball_bar), ("plane", self.plane))}}


def load_artefacts(path: str | Path = DEFAULT_ARTEFACTS) -> ArtefactSet:
    """Read and check an artefact file; errors name the file and the key."""
    path = Path(path)
    file = schema.load(ArtefactFile, path)
    return ArtefactSet(file.name or path.stem, file.sphere, file.ball_bar, file.plane, path)
