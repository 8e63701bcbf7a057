"""The rig TOML and the rig model description as schemas, and the physics a rig must obey.

`RigFile` is every table a rig TOML may hold (see `config/rigs/`): of each device table
([camera], [[cameras]], [projector], [trigger_box]) the keys every device of its kind has
and `driver`; every other key of the table belongs to that driver, which declares them
(`scanner.drivers.registry`, docs/drivers.md) and validates them (`device_settings`), as
the rig driver does the top-level table named after it (`[sim]`). So a typo is refused at
load instead of being silently ignored. The tables read by the layers above the core are
typed here too, so the whole file is checked at load: `[calibrate]` (`CalibrateTable`, read
by `calibration.workflow.Procedure`), `[acceptance]` (`AcceptanceTable`, read by
`inspection.acceptance.Acceptance`), `[stage]` (`scanner.stage_model.StageTable`).

`RecordedRig` reads the copy of a rig TOML a session recorded (manifest.json `rig_config`)
through typed tables of the keys read after the capture, each when first asked for: an
imported session records a stand-in without tables, an older one tables this schema may
now refuse, and both must read as they did.

`RigModelSchema` is the geometry as `RigModel.to_dict` writes it (session manifests,
calibration files). `check_geometry` refuses a rig that cannot measure anything: a camera
and projector without a common field of view at the working distance, a projector looking
away, a projector at the camera (no baseline, no triangulation).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
from pydantic import ConfigDict, Field, field_validator, model_validator

from scanner import schema
from scanner.camera_noise import CameraNoise
from scanner.drivers.registry import Driver, Kind, lookup, own_settings
from scanner.errors import ConfigError
from scanner.geometry import RigModel
from scanner.schema import (
    Bool,
    Float,
    Int,
    Matrix3,
    Matrix4,
    PositiveFloat,
    PositiveInt,
    Schema,
    Str,
    Vector3,
    Vector4,
)
from scanner.stage_model import StageTable

T = TypeVar("T", bound=Schema)

ImageSide = Annotated[int, Field(strict=True, ge=1, le=65536)]
Distortion = Annotated[list[Float], Field(min_length=5, max_length=5)]
Gamma = Annotated[float, Field(strict=True, gt=0.2, lt=5.0)]
FieldOfView = Annotated[float, Field(strict=True, gt=1.0, lt=170.0)]
PixelAspect = Annotated[float, Field(strict=True, ge=0.1, le=10.0)]


class DeviceTable(Schema):
    """A device's table: the keys the core reads, `driver` (absent: the one driver of its
    kind the rig driver opens), and the driver's own keys, kept as given (`model_extra`)
    for `device_settings` to validate with the driver's schema."""

    model_config = ConfigDict(extra="allow")

    driver: Str | None = None


class Lens(DeviceTable):
    """What camera and projector share: image size and intrinsics (K, or hfov_deg and pixel_aspect)."""

    width: ImageSide
    height: ImageSide
    hfov_deg: FieldOfView | None = None
    pixel_aspect: PixelAspect = 1.0
    K: Matrix3 | None = None
    dist: Distortion = [0.0] * 5

    @model_validator(mode="after")
    def _intrinsics(self) -> Lens:
        if (self.K is None) == (self.hfov_deg is None):
            raise ValueError("give the intrinsics as either 'K' or 'hfov_deg' (with 'pixel_aspect'), one of them")
        if self.K is not None:
            check_intrinsics(np.array(self.K), self.width, self.height)
        return self


MAX_CAMERA_PIXELS = 24_000_000
"""The largest camera image decoded here: decoding and reconstruction peak at about 170 bytes
per camera pixel (`slscan bench --width 1224 --height 1024`: 359 MB for the whole process, of
which ~150 MB are the interpreter and its libraries), so 24 MP fill the ~4 GB a process may use."""


class CameraTable(Lens):
    bit_depth: Annotated[int, Field(strict=True, ge=1, le=16)] | None = None
    exposure_s: Annotated[float, Field(strict=True, gt=0, le=60)] | None = None

    @model_validator(mode="after")
    def _pixels(self) -> CameraTable:
        if self.width * self.height > MAX_CAMERA_PIXELS:
            raise ValueError(f"a {self.width} x {self.height} camera ({self.width * self.height / 1e6:.0f} MP) is "
                             f"more than the {MAX_CAMERA_PIXELS / 1e6:.0f} MP decoded within a process's memory")
        return self


class CameraEntry(CameraTable):
    """One camera of a rig with several (`[[cameras]]`): named; every camera after the first
    is placed in the first one's frame (which is the rig's camera frame) by `position_mm` and
    `look_at_mm`, as the projector is."""

    name: Annotated[str, Field(strict=True, min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")]
    position_mm: Vector3 | None = None
    look_at_mm: Vector3 | None = None


class ProjectorTable(Lens):
    gamma: Gamma = 1.0
    position_mm: Vector3
    look_at_mm: Vector3 | None = None


PERIOD_S = 0.05  # the pattern period (s) of a rig file that states none


class RigTable(Schema):
    name: Str | None = None
    driver: Str  # a rig driver: "sim", "hardware" (scanner.drivers.registry)
    trigger: Literal["software", "projector", "trigger_box"] = "software"
    timeout_s: Annotated[float, Field(strict=True, gt=0, le=3600)] = 2.0
    period_s: PositiveFloat = PERIOD_S
    working_distance_mm: Annotated[float, Field(strict=True, ge=10.0, le=100_000.0)] = 400.0  # 1 cm .. 100 m
    patterns: Str = "../patterns/heterodyne_3x4.toml"
    calibration: Str | None = None
    stereo_calibration: Str | None = None  # a [[cameras]] rig: the first two cameras' (stereo_calibration.json)

    @model_validator(mode="after")
    def _period(self) -> RigTable:
        if not self.period_s < self.timeout_s:
            raise ValueError(f"pattern period_s {self.period_s} s must be below timeout_s {self.timeout_s} s")
        return self


RecordingLevel = Literal["full", "display", "none"]  # see scanner.session_recording


class RecordingTable(Schema):
    """[recording]: how much of each scan its Rerun recording keeps (the raw frames and the
    cloud PLY are always on disk): "full" every map and point, "display" (default) maps and
    cloud decimated for viewing, "none" no recording."""

    level: RecordingLevel = "display"


class TriggerBoxTable(DeviceTable):
    """[trigger_box]: the driver's keys only (the port, ...)."""


class SpherePairTable(Schema):
    """A validation artefact ([calibrate] artefact, a calibration capture's): two spheres of
    `radius_mm` (nominal), centres `distance_mm` apart (certified)."""

    type: Literal["sphere_pair"] = "sphere_pair"
    radius_mm: PositiveFloat
    distance_mm: PositiveFloat

    @model_validator(mode="after")
    def _apart(self) -> SpherePairTable:
        if not self.distance_mm > 2 * self.radius_mm:
            raise ValueError(f"need distance_mm > 2 x radius_mm, got {self.radius_mm}, {self.distance_mm}")
        return self


class CalibrateTable(Schema):
    """[calibrate]: how `slscan calibrate` runs on this rig (`calibration.workflow.Procedure`,
    which holds the defaults: a key left out keeps the procedure's). `board` is relative to
    the rig TOML; the limits are those of `calibration.solve.CalibrationSettings`."""

    board: Str | None = None
    poses: PositiveInt | None = None
    plate_heights_mm: list[Float] | None = None  # first = the reference plane, 0
    artefact: SpherePairTable | None = None
    fix_k3: Bool | None = None
    drop_outliers: Bool | None = None
    min_views: Int | None = None
    max_camera_rms_px: Float | None = None
    max_projector_rms_px: Float | None = None
    max_validation_mm: Float | None = None
    max_joint_camera_std: Float | None = None


class MpeTable(Schema):
    """[acceptance.mpe]: the maximum permissible errors (mm) of the parameters of
    `inspection.acceptance` (a parameter left out has no MPE)."""

    PF_mm: PositiveFloat | None = None
    PS_mm: PositiveFloat | None = None
    SD_mm: PositiveFloat | None = None
    F_mm: PositiveFloat | None = None
    OL_mm: PositiveFloat | None = None
    E_mm: Any = None  # refused, with why (`_no_E`)

    @field_validator("E_mm")
    @classmethod
    def _no_E(cls, value: Any) -> Any:
        raise ValueError("VDI/VDE 2634-2 has no length measurement error E for one view; the ball bar's "
                         "outer-length error (SD plus both spheres' size errors) is OL_mm")


class AcceptanceTable(Schema):
    """[acceptance]: the measuring volume (mm: width, height, depth about the working
    distance), the artefact file (relative to the rig TOML), the decision rule (one of
    `inspection.tolerances.DECISION_RULES`) and the MPEs (see `inspection.acceptance`)."""

    volume_mm: Annotated[list[PositiveFloat], Field(min_length=3, max_length=3)]
    artefacts: Str | None = None
    decision_rule: Str = "guard-banded"
    mpe: MpeTable | None = None  # required by `slscan verify`


class RigFile(Schema):
    """A rig TOML: [rig], [camera], [projector], and the optional tables (the rig driver's
    own table, named after it, is set aside by `parse_rig_file`)."""

    rig: RigTable
    camera: CameraTable | None = None
    cameras: Annotated[list[CameraEntry], Field(min_length=1, max_length=8)] | None = None  # or several, named
    projector: ProjectorTable
    trigger_box: TriggerBoxTable | None = None
    recording: RecordingTable = RecordingTable()
    calibrate: CalibrateTable = CalibrateTable()
    acceptance: AcceptanceTable | None = None
    stage: StageTable | None = None

    @model_validator(mode="after")
    def _cameras(self) -> RigFile:
        if (self.camera is None) == (self.cameras is None):
            raise ValueError("give one [camera] table or a [[cameras]] list, one of them")
        if self.cameras is not None:
            names = [c.name for c in self.cameras]
            if len(set(names)) != len(names):
                raise ValueError(f"camera names {names} repeat")
            first = self.cameras[0]
            if first.position_mm is not None or first.look_at_mm is not None:
                raise ValueError(f"the first camera ('{first.name}') is the rig's frame: it takes no position_mm "
                                 f"or look_at_mm")
            placed = [c.name for c in self.cameras[1:] if c.position_mm is None]
            if placed:
                raise ValueError(f"camera(s) {placed} need position_mm (in the first camera's frame, mm)")
        return self

    @property
    def first_camera(self) -> CameraTable:
        """The rig's camera ([camera], or the first of [[cameras]]): the frame of its geometry."""
        if self.camera is not None:
            return self.camera
        if not self.cameras:
            raise ValueError("a rig file has a [camera] table or a [[cameras]] list")  # the validator refuses it first
        return self.cameras[0]


class RecordedTable(Schema):
    """A table of a rig config as a session recorded it (manifest.json `rig_config`: the rig
    TOML at capture, or the stand-in `slscan import` writes), typed for the readers after the
    capture: only the keys they read, without the file schema's ranges and cross-key rules
    (the config was judged at capture, by the schema of its day); the other keys are ignored,
    so an older session's tables read as before. A key left out reads as None, or its default."""

    model_config = ConfigDict(extra="ignore")


class RecordedRigTable(RecordedTable):
    name: Str | None = None
    driver: Str | None = None
    working_distance_mm: Float | None = None
    period_s: Float = PERIOD_S  # left out: the capture sequenced at the default


class RecordedCameraTable(RecordedTable):
    bit_depth: Int | None = None  # [camera.sensor]: `RecordedRig.sensor`


class RecordedProjectorTable(RecordedTable):
    blur_sigma_px: Float = 0.0  # the simulator's projector defocus (Gaussian sigma, px); 0: none stated


class RecordedRecordingTable(RecordedTable):
    level: RecordingLevel = "display"


class RecordedAcceptanceTable(RecordedTable):
    volume_mm: Annotated[list[Float], Field(min_length=3, max_length=3)] | None = None


@dataclass(frozen=True, eq=False)
class RecordedRig:
    """A session's recorded rig config read through typed tables, each validated when first
    read and kept: a table or key left out reads as its default, one present but malformed
    (a table that is not one, a value of the wrong type) raises ConfigError naming it.
    `key` is where `config` sits in the file at `path` ("rig_config" in a manifest, "" for a
    rig TOML read as recorded)."""

    config: Mapping[str, object]
    path: str | Path
    key: str = "rig_config"

    @cached_property
    def rig(self) -> RecordedRigTable:
        return self._table(RecordedRigTable, "rig")

    @cached_property
    def camera(self) -> RecordedCameraTable:
        return self._table(RecordedCameraTable, "camera")

    @cached_property
    def projector(self) -> RecordedProjectorTable:
        return self._table(RecordedProjectorTable, "projector")

    @cached_property
    def recording(self) -> RecordedRecordingTable:
        return self._table(RecordedRecordingTable, "recording")

    @cached_property
    def acceptance(self) -> RecordedAcceptanceTable:
        return self._table(RecordedAcceptanceTable, "acceptance")

    @cached_property
    def sensor(self) -> CameraNoise | None:
        """[camera.sensor] as the camera's noise model (the simulator's `SensorTable`, its
        ranges too), read apart from [camera] so that a sensor table the current schema
        refuses stops only its readers. None when absent or empty (an empty table states no
        sensor to the readers after capture; the simulator renders it with the defaults)."""
        table = self._mapping("camera").get("sensor")
        return schema.parse(CameraNoise, table, self.path, self._dotted("camera.sensor")) if table else None

    def _table(self, table: type[T], key: str) -> T:
        return schema.parse(table, self._mapping(key), self.path, self._dotted(key))

    def _mapping(self, key: str) -> Mapping[str, object]:
        """The recorded table `key` as written ({} when absent or null)."""
        value = self.config.get(key)
        if value is None:
            return {}
        if not isinstance(value, Mapping):
            raise ConfigError(self.path, self._dotted(key), f"expected a table, got {value!r:.60}")
        return value

    def _dotted(self, key: str) -> str:
        return f"{self.key}.{key}" if self.key else key


@dataclass(frozen=True, eq=False)
class DriverSettings:
    """A table's driver and its keys validated by the driver's schema."""

    driver: Driver
    settings: Any  # an instance of driver.settings


def parse_rig_file(raw: dict[str, Any], path: str | Path) -> RigFile:
    """`raw` (a rig TOML's contents) validated as a RigFile, the top-level table named after
    the rig driver set aside (its keys are the driver's: `device_settings` checks them)."""
    rig = raw.get("rig")
    name = rig.get("driver") if isinstance(rig, dict) else None
    return schema.parse(RigFile, {k: v for k, v in raw.items() if k != name or k in RigFile.model_fields}, path)


def device_settings(file: RigFile, raw: dict[str, Any], path: str | Path) -> dict[str, DriverSettings]:
    """The driver of each device table of `file` (parsed from `raw`) with its settings: keys
    "rig" (the rig driver, its settings the top-level table named after it), "camera" (the first camera),
    "cameras.<name>" (each of [[cameras]]), "projector" and "trigger_box" (when present).
    ConfigError naming the key for an unknown driver, one another rig driver opens, or a
    key no driver of its kind knows (`scanner.drivers.registry.own_settings`)."""
    rig = lookup("rig", file.rig.driver, None, path, "rig.driver")
    out = {"rig": DriverSettings(rig, schema.parse(rig.settings, raw.get(rig.name, {}), path, rig.name))}
    tables: list[tuple[str, Kind, str, DeviceTable]] = []
    if file.camera is not None:
        tables.append(("camera", "camera", "camera", file.camera))
    for i, entry in enumerate(file.cameras or []):
        tables.append((f"cameras.{entry.name}", "camera", f"cameras[{i}]", entry))
    tables.append(("projector", "projector", "projector", file.projector))
    if file.trigger_box is not None:
        tables.append(("trigger_box", "trigger_box", "trigger_box", file.trigger_box))
    for name, kind, prefix, table in tables:
        out[name] = _device(kind, table, rig.name, path, prefix)
    if file.cameras:
        out["camera"] = out[f"cameras.{file.cameras[0].name}"]
    return out


def _device(kind: Kind, table: DeviceTable, rig: str, path: str | Path, prefix: str) -> DriverSettings:
    driver = lookup(kind, table.driver, rig, path, f"{prefix}.driver")
    return DriverSettings(driver, own_settings(driver, table.model_extra or {}, type(table).model_fields, path, prefix))


# ---------------------------------------------------------------- the model description


class PinholeSchema(Schema):
    width: ImageSide
    height: ImageSide
    K: Matrix3
    dist: Annotated[list[Float], Field(min_length=0, max_length=5)] = [0.0] * 5

    @model_validator(mode="after")
    def _intrinsics(self) -> PinholeSchema:
        check_intrinsics(np.array(self.K), self.width, self.height)
        return self


class PhaseToHeightSchema(Schema):
    l_mm: PositiveFloat
    d_mm: PositiveFloat
    pitch_mm: PositiveFloat
    plane: Vector4
    per_pixel: Bool = False
    maps_file: Str = ""


class RigModelSchema(Schema):
    """`RigModel.to_dict` as written in manifests and calibration files."""

    camera: PinholeSchema
    projector: PinholeSchema
    cam_from_proj: Matrix4
    world_from_cam: Matrix4 = np.eye(4).tolist()
    projector_gamma: Gamma = 1.0
    phase_to_height: PhaseToHeightSchema | None = None
    calibration: Str = ""

    @model_validator(mode="after")
    def _poses(self) -> RigModelSchema:
        for name in ("cam_from_proj", "world_from_cam"):
            if not is_rigid(np.array(getattr(self, name))):
                raise ValueError(f"{name} is not a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        return self


def is_rigid(T: np.ndarray) -> bool:
    R = T[:3, :3]
    return bool(np.isfinite(T).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
                and np.allclose(T[3], [0, 0, 0, 1]))


def check_intrinsics(K: np.ndarray, width: int, height: int) -> None:
    """ValueError unless K is a pinhole's: positive focal lengths, last row 0 0 1, the
    principal point within an image's size of the image."""
    if not np.isfinite(K).all():
        raise ValueError("K holds a non-finite value")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"focal lengths must be > 0 px, got fx {K[0, 0]:g}, fy {K[1, 1]:g}")
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise ValueError("K must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
    if not (-width <= K[0, 2] <= 2 * width and -height <= K[1, 2] <= 2 * height):
        raise ValueError(f"principal point ({K[0, 2]:g}, {K[1, 2]:g}) px lies far outside the "
                         f"{width} x {height} image")


NYQUIST_PX = 2.0  # a sampled sinusoid needs more than two pixels per period to keep its phase


def check_patterns_fit(patterns: Any, projector: Any, path: object) -> None:
    """ConfigError naming the rig's projector size unless `patterns` (a PatternSet) can be
    shown on `projector` (a Pinhole): its finest fringe at least NYQUIST_PX projector pixels
    per period along each coded orientation (a pixel Gray code needs 2 pixels), so a 1 x 1
    projector is refused here instead of scanning a blank and blaming the exposure."""
    finest = max(patterns.fringes, default=1.0)
    for orientation in patterns.orientations:
        key, extent = ("width", projector.width) if orientation == "vertical" else ("height", projector.height)
        if extent / finest < NYQUIST_PX:
            raise ConfigError(path, f"projector.{key}", f"{extent} px cannot show the pattern set's finest fringe "
                                                        f"({finest:g} across it: {extent / finest:.3g} px per period; "
                                                        f"at least {NYQUIST_PX:g} needed)")


MIN_COMMON_VIEW = 0.01  # of the camera's image lit by the projector at the working distance
MIN_BASELINE_MM = 1.0


def common_view(model: RigModel, distance_mm: float, grid: int = 24) -> float:
    """The fraction of the camera's image whose rays, at depth `distance_mm` (camera frame),
    land inside the projector's image in front of the projector."""
    cam, proj = model.camera, model.projector
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, grid), np.linspace(0, cam.height - 1, grid))
    xy = cam.normalized(np.stack([u.ravel(), v.ravel()], axis=1))
    points = np.column_stack([xy * distance_mm, np.full(len(xy), distance_mm)])
    T = model.proj_from_cam
    in_proj = points @ T[:3, :3].T + T[:3, 3]
    ahead = in_proj[:, 2] > 1e-6
    if not ahead.any():
        return 0.0
    px = proj.project(in_proj[ahead])
    inside = (px[:, 0] >= -0.5) & (px[:, 0] <= proj.width - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= proj.height - 0.5)
    return float(inside.sum() / len(points))


def check_geometry(model: RigModel, distance_mm: float | None, path: object, key: str | None) -> None:
    """ConfigError naming `path`/`key` unless camera and projector can triangulate: a
    baseline, and a common field of view at `distance_mm` (None: at any of 50 mm .. 5 m)."""
    if model.baseline_mm < MIN_BASELINE_MM:
        raise ConfigError(path, key, f"the projector sits {model.baseline_mm:.3g} mm from the camera: without a "
                                     f"baseline nothing can be triangulated")
    distances = [distance_mm] if distance_mm is not None else [50.0 * 2 ** i for i in range(7)]
    shared = max(common_view(model, d) for d in distances)
    if shared >= MIN_COMMON_VIEW:
        return
    axis_in_proj = (model.proj_from_cam[:3, :3] @ np.array([0.0, 0.0, 1.0]))[2]
    at = f"at the working distance {distance_mm:g} mm" if distance_mm is not None else "at any distance up to 3.2 m"
    why = ("the projector looks away from the camera's view" if axis_in_proj <= 0
           else "check the projector's position_mm and look_at_mm (or the calibration's cam_from_proj)")
    raise ConfigError(path, key, f"camera and projector share no field of view {at} (the projector lights "
                                 f"{shared:.0%} of the camera's image): {why}")
