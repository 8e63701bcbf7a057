"""A binocular scan as data: every camera captured together into one session
(scanner/binocular_session.py), each camera decoded on its own (the monocular decoder, unchanged),
the first two matched and triangulated (scanner/binocular.py).

Where the projector's calibration is known (`projector_calibrated`), the camera-projector rays
must meet the binocular point: `three_ray_check` reports how far apart they are, per scan.

outputs/binocular.json states the points' noise (`depth_sigma_median_mm`) and, apart, the stereo
calibration's term ("calibration": `BinocularResult.calibration_figures`, one error common to the
whole scan), or that it is not included (a calibration stating no covariance).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scanner.acquisition import AcquisitionSettings, acquire_all
from scanner.binocular import BinocularResult, reconstructor_for
from scanner.binocular_session import camera_model, camera_session, record, stereo_model
from scanner.decode import DEFAULT_DECODE_SETTINGS, DecodeResult, DecodeSettings
from scanner.devices import Frame
from scanner.errors import DecodeError
from scanner.geometry import RigModel
from scanner.patterns import PatternSet
from scanner.pipeline import Progress, _quiet, decode_exposures, exposure_stacks, save_maps
from scanner.pointcloud import write_ply
from scanner.reconstruct import Triangulator
from scanner.rig import Rig
from scanner.session import OUTPUTS_DIR, Session, SessionWriter, write_json

PLY_COMMENT = "binocular: points from two cameras' matched projector coordinates; the projector's calibration unused"


@dataclass(eq=False)
class BinocularScan:
    """A processed binocular session: each camera's decode by name, the reconstruction, the
    three-ray self-check (None without a projector calibration) and the stage times (s)."""

    session: Session
    decoded: dict[str, DecodeResult]
    result: BinocularResult
    three_rays: dict[str, float] | None
    timings_s: dict[str, float]

    @property
    def cloud_path(self) -> Path:
        return self.session.outputs / "cloud.ply"


def capture_binocular(rig: Rig, patterns: PatternSet, writer: SessionWriter, progress: Progress = _quiet,
                      calibrated: bool = False, keep: dict[str, dict[int, np.ndarray]] | None = None) -> Session:
    """Capture one scan with every camera of the rig into the writer's new session, complete only
    when every camera's frame of every pattern is stored; `calibrated`: the rig's
    camera-projector models are calibrated (the three-ray check applies). On a failure the frames
    stored stay, error.json says why, and the error is raised again."""
    names = list(rig.cameras)
    if len(names) < 2:
        raise DecodeError(f"rig {rig.config.name} has one camera: a binocular scan needs a [[cameras]] list of two")
    for save in rig.extras.get("session_files", ()):
        save(writer.root)
    n = patterns.n_frames

    def on_frame(name: str, k: int, frame: Frame) -> None:
        writer.add_frame(k, frame, camera=name)
        if keep is not None:
            keep.setdefault(name, {})[k] = frame.image.copy()
        progress("capture", k + 1, n)

    t0 = time.perf_counter()
    try:
        acquire_all(rig, patterns, AcquisitionSettings.for_rig(rig), on_frame)
    except BaseException as exc:
        writer.fail(exc, "capture")
        raise
    timings = {"capture": round(time.perf_counter() - t0, 4)}
    writer.frames = writer.camera_frames.pop(names[0])
    models = rig.config.camera_models()
    stereo = rig.extras.get("stereo_model") or rig.config.stereo_model()
    devices = {"projector": rig.projector.describe(), **{f"camera {n}": c.describe() for n, c in rig.cameras.items()}}
    extra = {"rig_config_path": str(rig.config.path), "wiring": rig.config.trigger, "cameras": names,
             "camera_frames": writer.camera_frames, "camera_models": {k: m.to_dict() for k, m in models.items()},
             "projector_calibrated": calibrated, "stereo_model": stereo.to_dict()}
    writer.finish(rig.config.raw, models[names[0]], patterns, devices, timings, extra)
    return Session.open(writer.root)


def decode_camera(session: Session, name: str, frames: dict[int, np.ndarray] | None = None,
                  settings: DecodeSettings = DEFAULT_DECODE_SETTINGS) -> DecodeResult:
    """Camera `name`'s decode of a binocular session, from its frames in memory or on disk."""
    view = camera_session(session, name)
    model = view.rig_model()
    stack = view.load_stack() if frames is None else np.stack([frames[k] for k in range(len(frames))])
    return decode_exposures(view, exposure_stacks(view, stack, model), model, settings)


def three_ray_check(result: BinocularResult, decoded: DecodeResult, model: RigModel) -> dict[str, float]:
    """How far the first camera's camera-projector triangulation lands from the binocular
    points (the three rays meeting): the projector coordinate the binocular point projects to
    minus the one decoded (projector px), and the monocular depth minus the binocular one (mm),
    as median and RMS over the points."""
    o = result.orientation
    valid = result.cloud.valid
    X = result.cloud.points[valid].astype(np.float64)
    P = model.proj_from_cam
    uv = model.projector.project(X @ P[:3, :3].T + P[:3, 3])
    axis = 0 if o == "vertical" else 1
    r = uv[:, axis] - decoded.maps[o].coordinate[valid]
    z_mono = Triangulator(model).depth_scale(np.where(valid, decoded.maps[o].coordinate, np.nan), o)[valid]
    dz = (z_mono - result.cloud.points[..., 2][valid]).astype(np.float64)
    ok, okz = np.isfinite(r), np.isfinite(dz)
    return {"projector_residual_median_px": float(np.median(r[ok])), "projector_residual_rms_px":
            float(np.sqrt(np.mean(r[ok] ** 2))), "mono_minus_binocular_median_mm": float(np.median(dz[okz])),
            "mono_minus_binocular_rms_mm": float(np.sqrt(np.mean(dz[okz] ** 2))), "points": float(ok.sum())}


def process_binocular(session: Session, progress: Progress = _quiet,
                      frames: dict[str, dict[int, np.ndarray]] | None = None,
                      settings: DecodeSettings = DEFAULT_DECODE_SETTINGS) -> BinocularScan:
    """Decode every camera of a binocular session (two at once), match the first two and
    triangulate; write outputs/cloud.ply (first camera's frame, mm), each camera's maps and
    outputs/binocular.json."""
    rec = record(session)
    names = rec.cameras[:2]
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    progress("decode", 0, len(names))
    with ThreadPoolExecutor(len(names), thread_name_prefix="decode camera") as pool:
        futures = {n: pool.submit(decode_camera, session, n, None if frames is None else frames[n], settings)
                   for n in names}
        decoded = {n: f.result() for n, f in futures.items()}
    timings["decode"] = round(time.perf_counter() - t0, 4)
    progress("match", 0, 1)
    t0 = time.perf_counter()
    model = stereo_model(session)
    result = reconstructor_for(model).reconstruct(decoded[names[0]], decoded[names[1]])
    timings["match"] = round(time.perf_counter() - t0, 4)
    if not result.cloud.valid.any():
        raise DecodeError(f"{session.root}: no left pixel found a unique match in camera '{names[1]}': "
                          f"{ {k: int(v) for k, v in result.checks.items()} }")
    three = three_ray_check(result, decoded[names[0]], camera_model(session, names[0])) \
        if rec.projector_calibrated else None
    progress("write", 0, 1)
    t0 = time.perf_counter()
    out = session.root / OUTPUTS_DIR
    out.mkdir(exist_ok=True)
    write_ply(out / "cloud.ply", result.cloud, comments=[PLY_COMMENT, f"frame: camera '{names[0]}', unit: mm"])
    for n in names:
        (out / n).mkdir(exist_ok=True)
        save_maps(out / n / "maps.npz", decoded[n])
    timings["write"] = round(time.perf_counter() - t0, 4)
    write_json(out / "binocular.json", {
        "session_id": session.id, "cameras": names, "orientation": result.orientation,
        "points": len(result.cloud), "checks": result.checks, "three_ray_check": three,
        "depth_sigma_median_mm": float(np.nanmedian(result.depth_sigma_mm)),
        "calibration": result.calibration_figures(), "timings_s": timings,
        "consistency": {n: [c.as_dict() for c in d.checks] for n, d in decoded.items()},
        "integrity": session.integrity})
    progress("done", 1, 1)
    return BinocularScan(session, decoded, result, three, timings)


def scan_binocular(rig: Rig, patterns: PatternSet, out_dir: str | Path, progress: Progress = _quiet,
                   calibrated: bool = False) -> BinocularScan:
    """Capture, decode and reconstruct one binocular scan (the frames decoded from memory)."""
    writer = SessionWriter.create(out_dir)
    frames: dict[str, dict[int, np.ndarray]] = {}
    session = capture_binocular(rig, patterns, writer, progress, calibrated, keep=frames)
    return process_binocular(session, progress, frames)


def summary(scan: BinocularScan) -> dict[str, Any]:
    """The figures a person reads first."""
    c = scan.result.checks
    return {"points": int(c["points"]), "of_pixels": int(c["pixels_with_coordinate"]),
            "not_unique": int(c["not_unique"]), "low_gradient": int(c["low_gradient"]),
            **({"epipolar_offset_median_px": round(c["epipolar_offset_median_px"], 4)}
               if "epipolar_offset_median_px" in c else {}), "three_ray_check": scan.three_rays,
            "timings_s": scan.timings_s}

