"""Where a rig's stage is, and its `[stage]` table: stage positions become poses of the part.

Geometry (`StageModel`): the axes as screws in the rig's world frame with every axis at 0,
listed from the base of the stack to the top (a linear slide carrying a turntable: the
slide first). A rotary axis turns by its position q (rad, right-handed) about the line
through `point_mm` along `direction`; a linear one slides by q (mm) along `direction`.
The pose of whatever the stage carries, mapping points fixed on the stage (the stage
frame: the world frame with every axis at 0) into the world, is the product of the axes'
motions from base to top (the product-of-exponentials form):

    world_from_stage(q) = M_1(q_1) M_2(q_2) ... M_n(q_n)

so a view's cloud, taken at positions q, goes back into the stage (part) frame by
inv(world_from_stage(q)).

The rig TOML (`[stage]`, optional; lengths mm, angles in degrees where the key says so):

    [stage]
    driver = "sim"                     # a stage driver of the rig's driver: sim (simulated
                                       #   rigs) | grbl (hardware rigs); absent: the only one
    settle_s = 0.3                     # wait after each move before a view is captured
    calibration = "stage_axis.json"    # optional: the calibrated axes (`slscan calibrate
                                       # --stage-axis`), replacing direction and point_mm
    home = true                        # the controller homes (it then refuses moves until
                                       #   homed); sim: the same, simulated
    port = "/dev/ttyUSB0"              # the driver's own keys (scanner/drivers/grbl.py):
    boot_timeout_s = 5.0               #   the controller's serial port, how long it may take
    timeout_s = 1.0                    #   to answer after opening, and to answer a command

    [[stage.axes]]                     # base first
    name = "turntable"
    kind = "rotary"                    # rotary | linear
    direction = [0.0, -0.766, -0.643]  # unit vector, rig world frame (normalised on load)
    point_mm = [0.0, 0.0, 400.0]       # rotary: a point on the axis
    limits_deg = [-400.0, 400.0]       # rotary travel (default endless); linear: limits_mm
    speed_deg_s = 30.0                 # nominal speed (linear: speed_mm_s)
    tolerance_deg = 0.01               # reported position must be this close (linear: tolerance_mm)
    letter = "X"                       # the driver's own keys (grbl: the controller axis driving
    units_per_turn = 360.0             #   it; rotary: controller units per turn)

The calibration file (`stage_axis.json`, written by `calibration.stage_axis`): JSON with
`slscan_stage_axis` (format version), `axes` (name, kind, direction, point_mm as above),
and the solve's figures (`residual_mm`, `views`, ...). Loading checks that its axes are the
rig's, by name and kind, and refuses another version.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import ConfigDict, Field, ValidationInfo, field_validator

from scanner.config import resolve
from scanner.drivers.registry import lookup, own_settings
from scanner.errors import ConfigError
from scanner.schema import Bool, Float, Schema, Str, Vector2, Vector3
from scanner.stage import Axis, AxisKind

STAGE_AXIS_VERSION = 1


def rotation_about(direction: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by `angle` (rad, right-handed) about the unit vector `direction`."""
    d = np.asarray(direction, float)
    K = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


@dataclass(frozen=True, eq=False)
class AxisGeometry:
    """One axis in the world frame with every axis at 0 (see the module docstring)."""

    name: str
    kind: AxisKind
    direction: np.ndarray
    point_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, float)
        n = float(np.linalg.norm(d))
        if d.shape != (3,) or not np.isfinite(d).all() or n < 1e-9:
            raise ValueError(f"axis {self.name}: direction must be a non-zero 3-vector, got {self.direction}")
        p = np.asarray(self.point_mm, float)
        if p.shape != (3,) or not np.isfinite(p).all():
            raise ValueError(f"axis {self.name}: point_mm must be a finite 3-vector, got {self.point_mm}")
        object.__setattr__(self, "direction", d / n)
        object.__setattr__(self, "point_mm", p)

    def motion(self, q: float) -> np.ndarray:
        """4x4 world-frame motion of the axis at position q (rad or mm)."""
        T = np.eye(4)
        if self.kind is AxisKind.LINEAR:
            T[:3, 3] = q * self.direction
            return T
        R = rotation_about(self.direction, q)
        T[:3, :3] = R
        T[:3, 3] = self.point_mm - R @ self.point_mm
        return T

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "kind": self.kind.value, "direction": self.direction.tolist(),
                "point_mm": self.point_mm.tolist()}


@dataclass(frozen=True, eq=False)
class StageModel:
    """The stage's axes, base first; `calibration` names the file they came from ("":
    the rig TOML's nominal axes)."""

    axes: tuple[AxisGeometry, ...]
    calibration: str = ""

    def world_from_stage(self, positions: Mapping[str, float]) -> np.ndarray:
        """4x4 pose of the stage frame in the world at `positions` (axes not named: at 0)."""
        unknown = set(positions) - {a.name for a in self.axes}
        if unknown:
            raise ValueError(f"no stage axis named {sorted(unknown)}; axes: {[a.name for a in self.axes]}")
        T = np.eye(4)
        for axis in self.axes:
            T = T @ axis.motion(float(positions.get(axis.name, 0.0)))
        return T

    def to_dict(self) -> dict[str, Any]:
        return {"axes": [a.to_dict() for a in self.axes], "calibration": self.calibration}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: object) -> StageModel:
        """From `to_dict` (a manifest, a calibration file); errors name `where`."""
        try:
            axes = tuple(AxisGeometry(str(a["name"]), AxisKind(a["kind"]), np.array(a["direction"], float),
                                      np.array(a.get("point_mm", [0.0, 0.0, 0.0]), float)) for a in d["axes"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(where, "axes", f"not a stage model: {exc}") from None
        if not axes:
            raise ConfigError(where, "axes", "a stage model needs at least one axis")
        return cls(axes, str(d.get("calibration", "")))


class AxisTable(Schema):
    """One [[stage.axes]] table: the keys every axis has, in the axis's unit (rotary: deg,
    linear: mm); every other key is the stage driver's (`axis_settings`)."""

    model_config = ConfigDict(extra="allow")

    name: Str
    kind: Literal["rotary", "linear"]
    direction: Vector3
    point_mm: Vector3 | None = None
    limits_deg: Vector2 | None = None
    limits_mm: Vector2 | None = None
    speed_deg_s: Float | None = None
    speed_mm_s: Float | None = None
    tolerance_deg: Float | None = None
    tolerance_mm: Float | None = None

    @field_validator("limits_mm", "speed_mm_s", "tolerance_mm", "limits_deg", "speed_deg_s", "tolerance_deg")
    @classmethod
    def _in_its_unit(cls, value: Any, info: ValidationInfo) -> Any:
        kind, key = info.data.get("kind"), str(info.field_name)
        unit, wrong = ("deg", "mm") if kind == "rotary" else ("mm", "deg")
        if kind is not None and wrong in key.split("_"):
            raise ValueError(f"a {kind} axis gives this in {unit} ({key.replace(wrong, unit)})")
        return value

    @field_validator("point_mm")
    @classmethod
    def _rotary_only(cls, value: Any, info: ValidationInfo) -> Any:
        if info.data.get("kind") == "linear":
            raise ValueError("a linear axis has no point_mm")
        return value


class StageTable(Schema):
    """A rig TOML's [stage] table (see the module docstring): the keys every stage has and
    `driver`; every other key is the stage driver's (`settings`)."""

    model_config = ConfigDict(extra="allow")

    driver: Str | None = None
    settle_s: Annotated[float, Field(strict=True, ge=0.0, le=60.0)] = 0.0
    calibration: Str | None = None
    home: Bool = False
    axes: list[AxisTable]

    @field_validator("axes")
    @classmethod
    def _axes(cls, axes: list[AxisTable]) -> list[AxisTable]:
        if not axes:
            raise ValueError("a stage needs at least one [[stage.axes]] table")
        names = [a.name for a in axes]
        if len(set(names)) != len(names):
            raise ValueError(f"axis names must be unique, got {names}")
        return axes


@dataclass(frozen=True, eq=False)
class StageConfig:
    """A rig TOML's `[stage]` table, checked: the axes the driver moves, their geometry
    (calibrated when the table names a calibration file), and the driver's own keys
    (`settings`, and `axis_settings` per axis: instances of its declared schemas)."""

    path: Path
    driver: str
    settle_s: float
    home: bool
    axes: tuple[Axis, ...]
    nominal: StageModel
    model: StageModel
    settings: Any = None
    axis_settings: tuple[Any, ...] = ()

    @classmethod
    def from_table(cls, table: StageTable, rig_driver: str, path: Path) -> StageConfig:
        """The stage of a rig file's `[stage]` table, its driver one the rig's driver opens
        and the driver's keys validated by its schemas."""
        driver = lookup("stage", table.driver, rig_driver, path, "stage.driver")
        settings = own_settings(driver, table.model_extra or {}, StageTable.model_fields, path, "stage")
        axes, geometry, own = [], [], []
        for i, t in enumerate(table.axes):
            pre = f"stage.axes[{i}]"
            axis, geo = _axis(t, path, pre, table.home)
            axes.append(axis)
            geometry.append(geo)
            own.append(own_settings(driver, t.model_extra or {}, AxisTable.model_fields, path, pre, axis=True))
        nominal = StageModel(tuple(geometry))
        model = nominal
        if table.calibration is not None:
            model = load_stage_model(resolve(path, table.calibration), nominal, path)
        return cls(path, driver.name, table.settle_s, table.home, tuple(axes), nominal, model, settings, tuple(own))


def load_stage_model(file: Path, nominal: StageModel, rig_path: object, key: str = "stage.calibration") -> StageModel:
    """The calibrated axes of `file`, checked against the rig's (names, kinds, order);
    errors name `rig_path` and `key` (where the file was given)."""
    try:
        d = json.loads(file.read_text())
    except FileNotFoundError:
        raise ConfigError(rig_path, key, f"{file}: no such stage-axis calibration file; run `slscan calibrate "
                                         f"--stage-axis`") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(rig_path, key, f"{file}: unreadable: {exc}") from None
    if not isinstance(d, dict) or d.get("slscan_stage_axis") != STAGE_AXIS_VERSION:
        version = d.get("slscan_stage_axis") if isinstance(d, dict) else None
        raise ConfigError(rig_path, key, f"{file}: stage-axis file version {version!r}, this slscan reads "
                                         f"{STAGE_AXIS_VERSION}")
    model = StageModel.from_dict(d, file)
    want = [(a.name, a.kind) for a in nominal.axes]
    got = [(a.name, a.kind) for a in model.axes]
    if got != want:
        raise ConfigError(rig_path, key, f"{file}: calibrated axes {[(n, k.value) for n, k in got]} are not the "
                                         f"rig's {[(n, k.value) for n, k in want]}")
    return StageModel(model.axes, str(file))


def _axis(t: AxisTable, path: Path, pre: str, home: bool) -> tuple[Axis, AxisGeometry]:
    kind = AxisKind(t.kind)
    rotary = kind is AxisKind.ROTARY
    scale = math.radians(1.0) if rotary else 1.0
    limits, speed, tolerance = (t.limits_deg, t.speed_deg_s, t.tolerance_deg) if rotary else \
        (t.limits_mm, t.speed_mm_s, t.tolerance_mm)
    limits = [-math.inf, math.inf] if limits is None else limits
    speed = (30.0 if rotary else 10.0) if speed is None else speed
    tolerance = 0.01 if tolerance is None else tolerance
    try:
        axis = Axis(t.name, kind, (limits[0] * scale, limits[1] * scale), speed * scale, tolerance * scale, home)
        geometry = AxisGeometry(t.name, kind, np.array(t.direction), np.array(t.point_mm or [0.0, 0.0, 0.0]))
    except ValueError as exc:
        raise ConfigError(path, pre, str(exc)) from None
    return axis, geometry
