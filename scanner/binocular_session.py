"""A session of a rig with several cameras (binocular): an ordinary session of the first camera
with every other camera's frames and the stereo geometry beside it.

    frames/<camera>/frame_000.png …   each camera's raw frames (the first camera's are the manifest's
                                      `frames`, so the folder is also that camera's own session)
    manifest.json                     the session's manifest (scanner/session.py) plus:
        cameras        [names]        in order; the first is the session's own camera (`rig_model`)
        camera_frames  {name: [...]}  every other camera's frame list, as `frames` (SHA-256 each)
        camera_models  {name: model}  every camera with the projector (RigModel.to_dict), in its own
                                      frame; `projector_calibrated` says whether the projector part
                                      was calibrated (else nominal: the three-ray check is skipped)
        stereo_model   {...}          the two cameras' geometry (StereoModel.to_dict): what points come from,
                                      with the calibration's covariance where it states one
    outputs/cloud.ply                 the binocular cloud, in the first camera's frame, mm
    outputs/binocular.json            the reconstruction's figures (matches, refusals, self-checks)
    outputs/<camera>/maps.npz         each camera's decoded maps

`camera_session(session, name)` is the session as that camera alone sees it: the frames and the
rig model of camera `name`, to decode (and, with a projector calibration, triangulate) on its own.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, model_validator

from scanner import schema
from scanner.binocular import StereoModel
from scanner.errors import ConfigError, SessionError
from scanner.geometry import RigModel
from scanner.rig_schema import PinholeSchema, RigModelSchema, is_rigid
from scanner.session import MANIFEST, FrameEntry, Session

CameraName = Annotated[str, Field(strict=True, min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")]


class StereoCovarianceSchema(schema.Schema):
    """`StereoModel.covariance` as `to_dict` writes it (its shape and names checked by `from_dict`)."""

    parameters: list[schema.Str]
    matrix: list[list[float]]


class StereoModelSchema(schema.Schema):
    """`StereoModel.to_dict` as written in manifests and stereo calibration files."""

    names: Annotated[list[CameraName], Field(min_length=2, max_length=2)]
    left: PinholeSchema
    right: PinholeSchema
    right_from_left: schema.Matrix4
    epipolar_sigma_px: schema.NonNegativeFloat = 0.0
    calibration: schema.Str = ""
    covariance: StereoCovarianceSchema | None = None

    @model_validator(mode="after")
    def _pose(self) -> StereoModelSchema:
        import numpy as np

        T = np.array(self.right_from_left)
        if not is_rigid(T):
            raise ValueError("right_from_left is not a rigid transform (orthonormal rotation, last row 0 0 0 1)")
        if not np.linalg.norm(T[:3, 3]) > 1.0:
            raise ValueError(f"the cameras are {np.linalg.norm(T[:3, 3]):.3g} mm apart: no baseline to triangulate")
        return self


class BinocularRecord(schema.Schema):
    """The keys a binocular session adds to its manifest (module docstring)."""

    cameras: Annotated[list[CameraName], Field(min_length=2, max_length=8)]
    camera_frames: dict[CameraName, Annotated[list[FrameEntry], Field(min_length=1)]]
    camera_models: dict[CameraName, RigModelSchema]
    projector_calibrated: schema.Bool = False
    stereo_model: StereoModelSchema

    @model_validator(mode="after")
    def _consistent(self) -> BinocularRecord:
        if len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"camera names {self.cameras} repeat")
        if sorted(self.camera_frames) != sorted(self.cameras[1:]):
            raise ValueError(f"camera_frames holds {sorted(self.camera_frames)}, the cameras after the first are "
                             f"{self.cameras[1:]}")
        if sorted(self.camera_models) != sorted(self.cameras):
            raise ValueError(f"camera_models holds {sorted(self.camera_models)}, the cameras are {self.cameras}")
        if self.stereo_model.names != self.cameras[:2]:
            raise ValueError(f"stereo_model names {self.stereo_model.names}, the first two cameras are "
                             f"{self.cameras[:2]}")
        for name, frames in self.camera_frames.items():
            lens = self.camera_models[name].camera
            for k, f in enumerate(frames):
                if f.k != k:
                    raise ValueError(f"camera_frames.{name}[{k}] is numbered k = {f.k}")
                if tuple(f.shape[:2]) != (lens.height, lens.width):
                    raise ValueError(f"camera_frames.{name}[{k}] is {f.shape[1]} x {f.shape[0]} px, the camera "
                                     f"{lens.width} x {lens.height} px")
        return self


def is_binocular(session: Session) -> bool:
    return "stereo_model" in (session.manifest.model_extra or {})


def record(session: Session) -> BinocularRecord:
    """The session's binocular keys, validated (SessionError naming the manifest and key)."""
    keys = ("cameras", "camera_frames", "camera_models", "projector_calibrated", "stereo_model")
    recorded = session.manifest.as_recorded()
    data = {k: recorded[k] for k in keys if k in recorded}
    try:
        rec = schema.parse(BinocularRecord, data, session.root / MANIFEST)
    except ConfigError as exc:
        raise SessionError(str(exc)) from None
    first = session.manifest.frames
    for name, frames in rec.camera_frames.items():
        if len(frames) != len(first):
            raise SessionError(f"{session.root / MANIFEST}: camera '{name}' has {len(frames)} frames, camera "
                               f"'{rec.cameras[0]}' {len(first)}: an incomplete frame set")
    return rec


def stereo_model(session: Session) -> StereoModel:
    return StereoModel.from_dict(session.manifest.recorded("stereo_model"), f"{session.root / MANIFEST}: stereo_model")


def camera_model(session: Session, name: str) -> RigModel:
    return RigModel.from_dict(session.manifest.recorded("camera_models")[name],
                              f"{session.root / MANIFEST}: camera_models")


def camera_session(session: Session, name: str) -> Session:
    """The session as camera `name` alone sees it: its frames and rig model (see the module docstring)."""
    rec = record(session)
    if name not in rec.cameras:
        raise SessionError(f"{session.root}: no camera '{name}' (cameras: {', '.join(rec.cameras)})")
    if name == rec.cameras[0]:
        return session
    return session.replaced(frames=session.manifest.recorded("camera_frames")[name],
                            rig_model=session.manifest.recorded("camera_models")[name])
