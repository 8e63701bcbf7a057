"""A rig: its configuration (TOML), its nominal geometry, and its open devices.

The factory picks drivers by name and imports them lazily, so the scanner core does not
depend on the simulator or on hardware libraries.

A rig TOML may name its calibration file (`[rig] calibration = "path.json"`, relative to
the TOML): the rig then reconstructs with the calibrated geometry (`RigConfig.model`,
`Rig.model` of an opened rig) instead of the nominal one written in the TOML. The file is
read by `scanner.calibration_file`, which checks its version and its image sizes against
this rig's devices and refuses a mismatch.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from scanner.calibration_file import load_rig_model
from scanner.config import CONFIG_DIR, get, get_table, get_vector, load_toml, resolve
from scanner.devices import Camera, Projector, TriggerSource
from scanner.errors import ConfigError, ScannerError
from scanner.geometry import Pinhole, RigModel, look_at
from scanner.stage import Stage
from scanner.stage_model import StageConfig

DEFAULT_RIG = CONFIG_DIR / "rigs" / "sim_bench.toml"
TRIGGER_WIRINGS = ("software", "projector", "trigger_box")

# driver name -> "module:function" returning a Rig; imported only when used
DRIVERS = {"sim": "sim.virtual_rig:open_sim_rig", "hardware": "scanner.drivers.hardware_rig:open_hardware_rig"}


@dataclass(frozen=True, eq=False)
class RigConfig:
    """A parsed, validated rig TOML. `raw` keeps the whole file for the session manifest."""

    path: Path
    name: str
    driver: str
    trigger: str
    timeout_s: float
    period_s: float
    working_distance_mm: float
    patterns_path: Path
    camera: dict[str, Any]
    projector: dict[str, Any]
    raw: dict[str, Any] = field(repr=False)
    calibration_path: Path | None = None

    @classmethod
    def load(cls, path: str | Path = DEFAULT_RIG) -> RigConfig:
        path = Path(path)
        raw = load_toml(path)
        rig = get_table(raw, "rig", path)
        trigger = get(rig, "trigger", str, path, "software", "rig")
        if trigger not in TRIGGER_WIRINGS:
            raise ConfigError(path, "rig.trigger", f"'{trigger}' is not one of {TRIGGER_WIRINGS}")
        driver = get(rig, "driver", str, path, prefix="rig")
        if driver not in DRIVERS:
            raise ConfigError(path, "rig.driver", f"unknown driver '{driver}'; known: {sorted(DRIVERS)}")
        timeout = get(rig, "timeout_s", float, path, 2.0, "rig")
        if not timeout > 0:
            raise ConfigError(path, "rig.timeout_s", "must be > 0: every wait is finite")
        period = get(rig, "period_s", float, path, 0.05, "rig")
        if not 0 < period < timeout:
            raise ConfigError(path, "rig.period_s", f"pattern period {period} s must be > 0 and below timeout_s")
        patterns = resolve(path, get(rig, "patterns", str, path, "../patterns/heterodyne_3x4.toml", "rig"))
        calibration = get(rig, "calibration", str, path, None, "rig")
        cfg = cls(path=path, name=get(rig, "name", str, path, path.stem, "rig"), driver=driver, trigger=trigger,
                  timeout_s=timeout, period_s=period, working_distance_mm=get(rig, "working_distance_mm", float, path, 400.0, "rig"),
                  patterns_path=patterns, camera=get_table(raw, "camera", path),
                  projector=get_table(raw, "projector", path), raw=raw,
                  calibration_path=resolve(path, calibration) if calibration else None)
        cfg.nominal_model()  # validates the geometry keys now, naming the file
        _ = cfg.model  # and the calibration file, if any
        _ = cfg.stage  # and the stage table, if any
        return cfg

    def _pinhole(self, table: dict[str, Any], prefix: str) -> Pinhole:
        p = self.path
        width = get(table, "width", int, p, prefix=prefix)
        height = get(table, "height", int, p, prefix=prefix)
        if width < 1 or height < 1:
            raise ConfigError(p, f"{prefix}.width", f"image size must be positive, got {width} x {height}")
        dist = np.array(get_vector(table, "dist", 5, p, [0.0] * 5, prefix))
        if "K" in table:
            K = np.array(get(table, "K", list, p, prefix=prefix), dtype=float)
            if K.shape != (3, 3):
                raise ConfigError(p, f"{prefix}.K", "expected a 3x3 matrix")
            return Pinhole(width, height, K, dist)
        hfov = get(table, "hfov_deg", float, p, prefix=prefix)
        if not 1.0 < hfov < 170.0:
            raise ConfigError(p, f"{prefix}.hfov_deg", f"{hfov} is not a plausible field of view")
        aspect = get(table, "pixel_aspect", float, p, 1.0, prefix)
        return Pinhole.from_fov(width, height, hfov, aspect, dist=dist)

    @cached_property
    def model(self) -> RigModel:
        """The geometry to reconstruct with: the calibration file's when the rig names one
        (checked against this rig's image sizes), else the nominal one."""
        nominal = self.nominal_model()
        if self.calibration_path is None:
            return nominal
        try:
            return load_rig_model(self.calibration_path, nominal.camera.size, nominal.projector.size)
        except ScannerError as exc:
            raise ConfigError(self.path, "rig.calibration", str(exc)) from None

    @cached_property
    def stage(self) -> StageConfig | None:
        """The motion stage of a `[stage]` table, checked (`scanner.stage_model`); None without one."""
        return StageConfig.from_rig(self.raw, self.path)

    def nominal_model(self) -> RigModel:
        """The rig geometry written in the config (for the simulator: its ground truth)."""
        p = self.path
        pos = np.array(get_vector(self.projector, "position_mm", 3, p, prefix="projector"))
        target = np.array(get_vector(self.projector, "look_at_mm", 3, p, [0.0, 0.0, self.working_distance_mm],
                                     "projector"))
        if np.linalg.norm(target - pos) < 1e-6:
            raise ConfigError(p, "projector.look_at_mm", "projector looks at its own position")
        gamma = get(self.projector, "gamma", float, p, 1.0, "projector")
        if not 0.2 < gamma < 5.0:
            raise ConfigError(p, "projector.gamma", f"{gamma} is not a plausible projector gamma")
        return RigModel(camera=self._pinhole(self.camera, "camera"), projector=self._pinhole(self.projector, "projector"),
                        cam_from_proj=look_at(pos, target), projector_gamma=gamma)


@dataclass(eq=False)
class Rig:
    """Open devices plus the geometry used to reconstruct with them."""

    config: RigConfig
    camera: Camera
    projector: Projector
    trigger: TriggerSource | None
    model: RigModel
    extras: dict[str, Any] = field(default_factory=dict)  # driver-specific (the simulator's ground truth)
    stage: Stage | None = None  # the motion stage carrying the part, when the rig TOML has a [stage]

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def shutdown(self) -> None:
        for dev in (self.camera, self.projector, self.trigger, self.stage):
            if dev is not None:
                dev.shutdown()


def open_rig(config: RigConfig, **driver_options: Any) -> Rig:
    """Open the devices named by `config` (driver options, e.g. the simulator's scene, pass through)."""
    module_name, func = DRIVERS[config.driver].split(":")
    factory = getattr(importlib.import_module(module_name), func)
    rig = factory(config, **driver_options)
    if config.calibration_path is not None:
        rig.model = config.model  # reconstruct with the calibrated geometry
    return rig
