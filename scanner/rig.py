"""A rig: its configuration (TOML), its nominal geometry, and its open devices.

`open_rig` opens the rig driver the TOML names (`[rig] driver`), found in the registry of
drivers (`scanner.drivers.registry`: each driver module declares itself there), which
imports hardware libraries and the simulator only when a rig opens.

A rig TOML may name its calibration file (`[rig] calibration = "path.json"`, relative to
the TOML): the rig then reconstructs with the calibrated geometry (`RigConfig.model`,
`Rig.model` of an opened rig) instead of the nominal one written in the TOML. The file is
read by `scanner.calibration_file`, which checks its version and its image sizes against
this rig's devices and refuses a mismatch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from scanner.calibration_file import load_rig_model
from scanner.config import DEFAULT_RIG, load_toml, resolve
from scanner.devices import Camera, Projector, TriggerSource
from scanner.errors import ConfigError, ScannerError
from scanner.geometry import Pinhole, RigModel, look_at
from scanner.rig_schema import (
    CameraEntry,
    CameraTable,
    DriverSettings,
    Lens,
    ProjectorTable,
    RigFile,
    check_geometry,
    device_settings,
    parse_rig_file,
)
from scanner.stage import Stage
from scanner.stage_model import StageConfig

if TYPE_CHECKING:
    from scanner.binocular import StereoModel


@dataclass(frozen=True, eq=False)
class RigConfig:
    """A parsed, validated rig TOML: `file` is its record (`scanner.rig_schema.RigFile`),
    every table typed; `raw` the file as written, for the session manifest; `camera` (the
    first camera), `projector` and `cameras` ([[cameras]]) its device tables; `devices`
    their drivers and the drivers' settings (`scanner.rig_schema.device_settings`: "rig",
    "camera", "projector", "trigger_box", "cameras.<name>"); `stage` its [stage], checked."""

    path: Path
    name: str
    driver: str
    trigger: str
    timeout_s: float
    period_s: float
    working_distance_mm: float
    patterns_path: Path
    file: RigFile = field(repr=False)
    raw: dict[str, Any] = field(repr=False)
    calibration_path: Path | None = None
    recording_level: str = "display"  # [recording] level: "full", "display" or "none"
    devices: dict[str, DriverSettings] = field(default_factory=dict, repr=False)
    stage: StageConfig | None = None  # the motion stage of a `[stage]` table (`scanner.stage_model`)

    @classmethod
    def load(cls, path: str | Path = DEFAULT_RIG) -> RigConfig:
        """Read and validate a rig TOML: every key known, typed, in range and finite, and the
        nominal geometry able to triangulate (a common field of view at the working distance)."""
        path = Path(path)
        return cls.from_toml(load_toml(path), path)

    @classmethod
    def from_toml(cls, raw: dict[str, Any], path: Path) -> RigConfig:
        """A rig TOML's contents `raw`, validated as `load` does (relative paths from `path`)."""
        file = parse_rig_file(raw, path)
        rig = file.rig
        stage = StageConfig.from_table(file.stage, rig.driver, path) if file.stage is not None else None
        cfg = cls(path=path, name=rig.name or path.stem, driver=rig.driver, trigger=rig.trigger,
                  timeout_s=rig.timeout_s, period_s=rig.period_s, working_distance_mm=rig.working_distance_mm,
                  patterns_path=resolve(path, rig.patterns), file=file, raw=raw,
                  calibration_path=resolve(path, rig.calibration) if rig.calibration else None,
                  recording_level=file.recording.level, devices=device_settings(file, raw, path), stage=stage)
        check_geometry(cfg.nominal_model(), cfg.working_distance_mm, path, "projector")
        for name, model in list(cfg.camera_models().items())[1:]:
            check_geometry(model, cfg.working_distance_mm, path, f"cameras.{name}")
        if cfg.calibration_path is not None:
            check_geometry(cfg.model, cfg.working_distance_mm, path, "rig.calibration")
        return cfg

    @property
    def camera(self) -> CameraTable:
        """The rig's camera table ([camera], or the first of [[cameras]])."""
        return self.file.first_camera

    @property
    def projector(self) -> ProjectorTable:
        return self.file.projector

    @property
    def cameras(self) -> tuple[CameraEntry, ...]:
        """Each [[cameras]] table of a rig with several cameras (else empty)."""
        return tuple(self.file.cameras or ())

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

    def nominal_model(self) -> RigModel:
        """The rig geometry written in the config (for the simulator: its ground truth)."""
        file = self.file
        pos = np.array(file.projector.position_mm)
        look = file.projector.look_at_mm
        target = np.array(look) if look is not None else np.array([0.0, 0.0, self.working_distance_mm])
        if np.linalg.norm(target - pos) < 1e-6:
            raise ConfigError(self.path, "projector.look_at_mm", "projector looks at its own position")
        return RigModel(camera=_pinhole(file.first_camera), projector=_pinhole(file.projector),
                        cam_from_proj=look_at(pos, target), projector_gamma=file.projector.gamma)

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The cameras' names ([[cameras]]); a one-camera rig's is ("camera",)."""
        return tuple(c.name for c in self.cameras) or ("camera",)

    def camera_models(self) -> dict[str, RigModel]:
        """Per camera (by name) its nominal rig model with the projector: the camera placed in
        the first camera's frame (`world_from_cam`), `cam_from_proj` from its own frame."""
        first = self.nominal_model()
        if not self.cameras:
            return {"camera": first}
        file = self.file
        out = {}
        for entry in file.cameras or []:
            pose = np.eye(4)
            if entry.position_mm is not None:
                pos = np.array(entry.position_mm)
                look = entry.look_at_mm
                target = np.array(look) if look is not None else np.array([0.0, 0.0, self.working_distance_mm])
                if np.linalg.norm(target - pos) < 1e-6:
                    raise ConfigError(self.path, f"cameras.{entry.name}.look_at_mm", "camera looks at its own position")
                pose = look_at(pos, target)
            out[entry.name] = replace(first, camera=_pinhole(entry), world_from_cam=pose,
                                      cam_from_proj=np.linalg.inv(pose) @ first.cam_from_proj)
        return out

    def stereo_model(self, nominal: bool = False) -> StereoModel:
        """The stereo model of the first two cameras of a [[cameras]] rig: the [rig]
        stereo_calibration file's (its sizes checked against the cameras'), or with `nominal`
        (or without one) the geometry written in the rig file."""
        from scanner.binocular import StereoModel
        from scanner.stereo_calibration_file import read_stereo_calibration

        models = self.camera_models()
        if len(models) < 2:
            raise ConfigError(self.path, "cameras", "binocular reconstruction needs a [[cameras]] list of two cameras")
        (a, left), (b, right) = list(models.items())[:2]
        file = self.file.rig.stereo_calibration
        if file and not nominal:
            try:
                model, _ = read_stereo_calibration([resolve(self.path, file)], left.camera.size, right.camera.size)
            except ScannerError as exc:
                raise ConfigError(self.path, "rig.stereo_calibration", str(exc)) from None
            return replace(model, names=(a, b))
        return StereoModel(left.camera, right.camera, np.linalg.inv(right.world_from_cam) @ left.world_from_cam,
                           (a, b))


def _pinhole(lens: Lens) -> Pinhole:
    if lens.K is not None:
        return Pinhole(lens.width, lens.height, np.array(lens.K), np.array(lens.dist))
    assert lens.hfov_deg is not None  # the schema gives either K or hfov_deg
    return Pinhole.from_fov(lens.width, lens.height, lens.hfov_deg, lens.pixel_aspect, dist=np.array(lens.dist))


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
    cameras: dict[str, Camera] = field(default_factory=dict)  # every camera by name, the first being `camera`

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def shutdown(self) -> None:
        for dev in (self.camera, *[c for c in self.cameras.values() if c is not self.camera], self.projector,
                    self.trigger, self.stage):
            if dev is not None:
                dev.shutdown()


def open_rig(config: RigConfig, **driver_options: Any) -> Rig:
    """Open the devices named by `config` with its rig driver (driver options, e.g. the
    simulator's scene, pass through)."""
    rig: Rig = config.devices["rig"].driver.opener()(config, **driver_options)
    if config.calibration_path is not None:
        rig.model = config.model  # reconstruct with the calibrated geometry
    return rig
