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
from typing import Any

from scanner.config import CONFIG_DIR, get, get_table, get_vector, load_toml
from scanner.errors import ConfigError

DEFAULT_ARTEFACTS = CONFIG_DIR / "artefacts" / "sim_bench.toml"
_KEYS = {"sphere": {"certificate", "diameter_mm", "diameter_u_mm", "form_mm", "albedo"},
         "ball_bar": {"certificate", "length_mm", "length_u_mm", "diameter_mm", "diameter_u_mm", "form_mm", "albedo"},
         "plane": {"certificate", "size_mm", "flatness_mm", "flatness_u_mm", "albedo"}}


@dataclass(frozen=True)
class Sphere:
    """A calibrated sphere (diameter, its U, its form deviation; mm)."""

    certificate: str
    diameter_mm: float
    diameter_u_mm: float
    form_mm: float
    albedo: float = 0.7

    @property
    def radius_mm(self) -> float:
        return self.diameter_mm / 2.0


@dataclass(frozen=True, kw_only=True)
class BallBar(Sphere):
    """Two spheres of the calibrated diameter whose centres are `length_mm` apart."""

    length_mm: float
    length_u_mm: float


@dataclass(frozen=True)
class Plane:
    certificate: str
    size_mm: tuple[float, float]
    flatness_mm: float
    flatness_u_mm: float
    albedo: float = 0.8


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
        from dataclasses import asdict

        return {"name": self.name, "path": str(self.path) if self.path else None,
                **{k: asdict(v) if v is not None else None for k, v in
                   (("sphere", self.sphere), ("ball_bar", self.ball_bar), ("plane", self.plane))}}


def load_artefacts(path: str | Path = DEFAULT_ARTEFACTS) -> ArtefactSet:
    """Read and check an artefact file; errors name the file and the key."""
    path = Path(path)
    raw = load_toml(path)
    unknown = set(raw) - {"name", *_KEYS}
    if unknown:
        raise ConfigError(path, sorted(unknown)[0], f"unknown key; expected name and the tables {sorted(_KEYS)}")
    tables = {}
    for kind, keys in _KEYS.items():
        if kind not in raw:
            continue
        t = get_table(raw, kind, path)
        for k in t:
            if k not in keys:
                raise ConfigError(path, f"{kind}.{k}", f"unknown key; expected one of {sorted(keys)}")
        values: dict[str, Any] = {"certificate": get(t, "certificate", str, path, prefix=kind)}
        for k in sorted(keys - {"certificate", "size_mm"}):
            values[k] = get(t, k, float, path, 0.7 if k == "albedo" else ..., prefix=kind)
            positive = k.endswith(("diameter_mm", "length_mm"))
            in_range = values[k] > 0 if positive else values[k] >= 0
            if not in_range or values[k] != values[k] or values[k] == float("inf"):
                raise ConfigError(path, f"{kind}.{k}", f"must be a finite number {'> 0' if positive else '>= 0'}, "
                                                       f"got {values[k]}")
        if "albedo" in values and values["albedo"] > 1.0:
            raise ConfigError(path, f"{kind}.albedo", f"{values['albedo']} outside 0..1")
        if kind == "plane":
            size = get_vector(t, "size_mm", 2, path, prefix=kind)
            if not all(s > 0 for s in size):
                raise ConfigError(path, "plane.size_mm", f"sizes must be > 0, got {size}")
            values["size_mm"] = tuple(size)
        tables[kind] = values
    if not tables:
        raise ConfigError(path, None, f"no artefact: give at least one of the tables {sorted(_KEYS)}")
    bar = tables.get("ball_bar")
    if bar is not None and bar["length_mm"] <= bar["diameter_mm"]:
        raise ConfigError(path, "ball_bar.length_mm", "the spheres would overlap: length_mm must exceed diameter_mm")
    return ArtefactSet(get(raw, "name", str, path, path.stem),
                       Sphere(**tables["sphere"]) if "sphere" in tables else None,
                       BallBar(**tables["ball_bar"]) if "ball_bar" in tables else None,
                       Plane(**tables["plane"]) if "plane" in tables else None, path)
