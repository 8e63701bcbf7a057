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
from typing import Any

import numpy as np

from scanner.config import get, get_vector, resolve
from scanner.drivers.registry import lookup, own_settings
from scanner.errors import ConfigError
from scanner.stage import Axis, AxisKind

STAGE_AXIS_VERSION = 1
_STAGE_KEYS = {"driver", "settle_s", "calibration", "home", "axes"}  # and the driver's `settings`
_AXIS_KEYS = {"name", "kind", "direction", "point_mm", "limits_deg", "limits_mm", "speed_deg_s", "speed_mm_s",
              "tolerance_deg", "tolerance_mm"}  # and the driver's `axis_settings`


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
    table: dict[str, Any] = field(repr=False)
    axis_tables: tuple[dict[str, Any], ...] = field(repr=False, default=())
    settings: Any = None
    axis_settings: tuple[Any, ...] = ()

    @classmethod
    def from_rig(cls, raw: dict[str, Any], path: Path) -> StageConfig | None:
        """The `[stage]` table of a rig TOML's contents `raw` (None when it has none), its
        driver one the rig's driver (`[rig] driver`) opens."""
        if "stage" not in raw:
            return None
        table = get(raw, "stage", dict, path)
        name = get(table, "driver", str, path, None, "stage")
        driver = lookup("stage", name, get(get(raw, "rig", dict, path), "driver", str, path, prefix="rig"), path,
                        "stage.driver")
        settings = own_settings(driver, table, _STAGE_KEYS, path, "stage")
        settle = get(table, "settle_s", float, path, 0.0, "stage")
        if not 0 <= settle <= 60:
            raise ConfigError(path, "stage.settle_s", f"must be 0..60 s, got {settle}")
        home = get(table, "home", bool, path, False, "stage")
        entries = get(table, "axes", list, path, prefix="stage")
        if not entries:
            raise ConfigError(path, "stage.axes", "a stage needs at least one [[stage.axes]] table")
        axes, geometry, own = [], [], []
        for i, t in enumerate(entries):
            axis, geo = _axis(t, path, f"stage.axes[{i}]", home)
            axes.append(axis)
            geometry.append(geo)
            own.append(own_settings(driver, t, _AXIS_KEYS, path, f"stage.axes[{i}]", axis=True))
        names = [a.name for a in axes]
        if len(set(names)) != len(names):
            raise ConfigError(path, "stage.axes", f"axis names must be unique, got {names}")
        nominal = StageModel(tuple(geometry))
        model = nominal
        calibration = get(table, "calibration", str, path, None, "stage")
        if calibration is not None:
            model = load_stage_model(resolve(path, calibration), nominal, path)
        return cls(path, driver.name, settle, home, tuple(axes), nominal, model, table, tuple(entries), settings,
                   tuple(own))


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


def _axis(t: Any, path: Path, pre: str, home: bool) -> tuple[Axis, AxisGeometry]:
    if not isinstance(t, dict):
        raise ConfigError(path, pre, "expected a table ([[stage.axes]])")
    name = get(t, "name", str, path, prefix=pre)
    kind_text = get(t, "kind", str, path, prefix=pre)
    try:
        kind = AxisKind(kind_text)
    except ValueError:
        raise ConfigError(path, f"{pre}.kind", f"'{kind_text}' is not one of {[k.value for k in AxisKind]}") from None
    rotary = kind is AxisKind.ROTARY
    unit, scale = ("deg", math.radians(1.0)) if rotary else ("mm", 1.0)
    wrong = "mm" if rotary else "deg"
    for k in (f"limits_{wrong}", f"speed_{wrong}_s", f"tolerance_{wrong}"):
        if k in t:
            raise ConfigError(path, f"{pre}.{k}",
                              f"a {kind.value} axis gives this in {unit} ({k.replace(wrong, unit)})")
    if not rotary and ("point_mm" in t or "units_per_turn" in t):
        raise ConfigError(path, pre, "a linear axis has no point_mm or units_per_turn")
    limits = get_vector(t, f"limits_{unit}", 2, path, prefix=pre) if f"limits_{unit}" in t else [-math.inf, math.inf]
    speed = get(t, f"speed_{unit}_s", float, path, 30.0 if rotary else 10.0, pre)
    tolerance = get(t, f"tolerance_{unit}", float, path, 0.01, pre)
    direction = np.array(get_vector(t, "direction", 3, path, prefix=pre))
    point = np.array(get_vector(t, "point_mm", 3, path, [0.0, 0.0, 0.0], pre))
    try:
        axis = Axis(name, kind, (limits[0] * scale, limits[1] * scale), speed * scale, tolerance * scale, home)
        geometry = AxisGeometry(name, kind, direction, point)
    except ValueError as exc:
        raise ConfigError(path, pre, str(exc)) from None
    return axis, geometry
