"""The scan as data: capture into a session, then decode and reconstruct from its raw
frames alone. Each stage takes arrays or small typed objects and returns the same."""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from scanner.acquisition import (
    AcquisitionSettings,
    acquire,
    acquire_exposures,
    acquire_images,
    at_exposure,
    settings_for_exposure,
)
from scanner.calibration_file import load_rig_model
from scanner.decode import DEFAULT_DECODE_SETTINGS, DecodeResult, DecodeSettings, NoiseModel, decode
from scanner.decode_checks import (
    FITTED_MODEL,
    FITTED_MODEL_ACCURACY,
    MIN_JUDGED,
    SENSOR_MODEL_ACCURACY,
    Check,
    ConsistencyError,
    Volume,
    direction,
    epipolar,
    failed,
    measurement_volume,
    not_judged,
    pattern_set_tie,
    rig_model_tie,
    sensor_noise_source,
    sensor_noise_terms,
)
from scanner.devices import Frame
from scanner.errors import DecodeError, ScannerError, SessionError
from scanner.exposure import ExposureRequest, FusedOrientationMaps, fuse, plan_exposures, probe_images
from scanner.geometry import RigModel
from scanner.native_threads import native_threads
from scanner.patterns import PatternSet
from scanner.pointcloud import OrganisedCloud, write_ply
from scanner.reconstruct import Triangulator, phase_to_height_cloud, triangulate
from scanner.rig import Rig
from scanner.rig_schema import check_patterns_fit
from scanner.session import (
    OUTPUTS_DIR,
    RECORDING,
    ExposureRecord,
    Provenance,
    Session,
    SessionWriter,
    ViewPlace,
    disk_problem,
    file_record,
    json_ready,
    rig_model_sha256,
    write_json,
    write_npz,
)
from scanner.session_lock import output_dir, session_lock
from scanner.stage_timer import StageTimer

if TYPE_CHECKING:  # Rerun takes ~0.3 s to import: only the commands that record load it
    from scanner.session_recording import SessionRecording

Progress = Callable[[str, int, int], None]  # (stage, done, total)
BLANK_FRAME_RANGE = 0.01  # of full scale: a frame whose pixels all lie within this range shows no pattern


def _quiet(stage: str, done: int, total: int) -> None:
    pass


@dataclass(eq=False)
class ScanResult:
    """What processing a session produced; figures in seconds and counts."""

    session: Session
    decoded: DecodeResult
    cloud: OrganisedCloud | None  # None: a session without a calibration (imported frames) has maps only
    timings_s: dict[str, float]
    checks: list[Check] = field(default_factory=list)  # the consistency checks it passed (decode_checks)
    written: Future[None] | None = None  # the outputs' write, when it runs behind (`process(write_behind=True)`)

    @property
    def cloud_path(self) -> Path:
        return self.session.outputs / "cloud.ply"

    def wait_written(self) -> None:
        """Wait until the outputs (cloud.ply, maps.npz, result.json) are on disk; raises the
        write's SessionError."""
        if self.written is not None:
            self.written.result()


AUTO_RANGE = (1 / 64, 16.0)  # auto exposure searches this range around the rig's exposure_s (factors)


def plan_for_rig(rig: Rig, patterns: PatternSet, request: ExposureRequest) -> ExposureRecord:
    """The exposures for `request` on this rig: "auto"/"hdr" pre-capture white, black and
    one fringe frame (`scanner.exposure`), searching AUTO_RANGE x the rig's exposure within
    the camera's range."""
    cam, proj = rig.camera, rig.projector
    lo, hi = cam.exposure_range_s
    base = cam.exposure_s
    search = (max(lo, base * AUTO_RANGE[0]), min(hi, base * AUTO_RANGE[1]))
    images = probe_images(patterns, proj.width, proj.height, rig.model.projector_gamma)
    settings = AcquisitionSettings.for_rig(rig)

    def capture_probe(t: float) -> np.ndarray:
        return at_exposure(rig, t, lambda: acquire_images(rig, images, settings_for_exposure(settings, t)))

    return plan_exposures(request, capture_probe, base, search if request.mode != "given" else (lo, hi),
                          float(2 ** cam.bit_depth - 1))


def capture(rig: Rig, patterns: PatternSet, writer: SessionWriter, *, progress: Progress = _quiet,
            recording: SessionRecording | None = None, exposure: ExposureRequest | None = None,
            view: ViewPlace | None = None, keep: dict[int, np.ndarray] | None = None) -> Session:
    """Capture one scan into the writer's new session folder and return it, complete;
    `exposure` (None: the rig's) chooses or lists exposures, the pattern set captured once
    per exposure (HDR) with the plan and its reason in the manifest; `view`, for a view of a
    multi-view session, its place (the stage pose) in the manifest too; `keep`, if given,
    receives each frame stored (k -> image), for a decode that follows at once (not read
    back from the PNGs).

    On any failure the frames already captured stay on disk, `error.json` says what
    happened, the session has no manifest (so it is reported incomplete), and the error
    is raised again."""
    n = patterns.n_frames
    specs = patterns.frames()
    plan: ExposureRecord | None = None
    for save in rig.extras.get("session_files", ()):  # driver-specific data kept with the raw frames
        save(writer.root)

    def store(k: int, frame: Frame) -> None:
        writer.add_frame(k, frame)
        if keep is not None:
            keep[k] = frame.image
        if recording is not None:  # the PNG just written (in the page cache), not encoded again
            recording.log_frame(k, frame, specs[k % n], png=(writer.root / writer.frames[-1]["file"]).read_bytes())

    # frames are encoded (PNG) and written by one thread in arrival order while the next are
    # acquired; a store that failed stops the capture at the next frame. `progress` runs here,
    # in the acquisition's thread, so a progress callback that raises (an operator's abort)
    # stops the capture at once, every frame captured until then stored
    stored: list[Future[None]] = []

    def on_frame(k: int, frame: Frame) -> None:
        for f in stored:
            failure = f.exception() if f.done() else None
            if failure is not None:
                raise failure
        stored.append(pool.submit(store, k, replace(frame, image=frame.image.copy())))  # a driver may reuse its buffer
        progress("capture", k + 1, n * (len(plan.exposures_s) if plan else 1))

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    manifest_extra: dict[str, object] = {"rig_config_path": str(rig.config.path.resolve()),
                                         "provenance": provenance(rig, writer.root), "wiring": rig.config.trigger,
                                         **(view.manifest_keys() if view is not None else {})}

    def begin() -> None:
        if plan is not None:
            manifest_extra["exposure"] = plan
        writer.begin(rig.config.raw, rig.model, patterns, describe_devices(rig), manifest_extra)

    with ThreadPoolExecutor(1, thread_name_prefix="store frames") as pool:
        try:
            if exposure is None:
                begin()
                acquire(rig, patterns, AcquisitionSettings.for_rig(rig), on_frame)
            else:
                plan = plan_for_rig(rig, patterns, exposure)
                timings["exposure_plan"] = round(time.perf_counter() - t0, 4)
                begin()
                acquire_exposures(rig, patterns, AcquisitionSettings.for_rig(rig), plan.exposures_s, on_frame)
            for f in stored:
                f.result()
        except BaseException as exc:  # includes Ctrl-C: the capture is recorded as failed
            wait(stored)  # the frames already captured are kept
            writer.fail(exc, "capture")
            raise
    timings["capture"] = round(time.perf_counter() - t0, 4)
    writer.finish(rig.config.raw, rig.model, patterns, describe_devices(rig), timings, manifest_extra)
    return Session.open(writer.root)


def describe_devices(rig: Rig) -> dict[str, Any]:
    return {name: dev.describe() for name, dev in
            (("camera", rig.camera), ("projector", rig.projector), ("trigger", rig.trigger)) if dev is not None}


def provenance(rig: Rig, session_root: Path) -> Provenance:
    """manifest.json `provenance`: the rig TOML and its calibration file by absolute and
    session-relative path and SHA-256."""
    calibration = rig.config.calibration_path
    return Provenance(rig=file_record(rig.config.path, session_root),
                      calibration=file_record(calibration, session_root) if calibration is not None else None)


def process(session: Session, progress: Progress = _quiet, recording: SessionRecording | None = None,
            *, settings: DecodeSettings = DEFAULT_DECODE_SETTINGS, mode: str = "triangulation",
            frames: dict[int, np.ndarray] | None = None, write_behind: bool = False,
            rig_model: RigModel | None = None, rig_model_source: str | None = None) -> ScanResult:
    """Decode and reconstruct a complete session from its raw frames; write the outputs
    (cloud PLY, maps, result JSON) beside them. `frames`: the session's frames still in
    memory (k -> image, `capture(keep=)`: the images its PNGs were written from), else they
    are read back from disk and checked (`Session.load_stack`). `write_behind`: return
    once the cloud is made and write the outputs in a thread meanwhile (a verdict waits on
    the cloud, not on its files); `ScanResult.wait_written()` joins it and raises its error.
    `rig_model`: another model than the session's, given on purpose (named `rig_model_source`).
    Every decode is judged by its consistency checks (scanner.decode_checks): when one fails
    it raises ConsistencyError, result.json says which and why, and no cloud is written."""
    if mode not in ("triangulation", "phase_to_height"):
        raise ScannerError(f"unknown reconstruction mode '{mode}'; use triangulation or phase_to_height")
    with session_lock(session.root, command="slscan decode"):
        return _process(session, progress, recording, settings=settings, mode=mode, frames=frames,
                        write_behind=write_behind, rig_model=rig_model,
                        rig_model_source=rig_model_source)


def _process(session: Session, progress: Progress, recording: SessionRecording | None, *, settings: DecodeSettings,
             mode: str, frames: dict[int, np.ndarray] | None, write_behind: bool, rig_model: RigModel | None,
             rig_model_source: str | None) -> ScanResult:
    timer = StageTimer()
    progress("load", 0, 1)
    with timer.stage("load"):
        stack = session.load_stack() if frames is None else np.stack([frames[k] for k in range(len(frames))])
        model = rig_model or session.rig_model()
        stacks = exposure_stacks(session, stack, model)
    manifest = session.manifest
    used = model.to_dict() if rig_model is not None else manifest.recorded("rig_model")  # as checksummed
    named = manifest.rig_model.calibration
    tie = rig_model_tie(manifest.rig_model_sha256, used, rig_model_source,
                        (named, manifest.calibration_sha256) if named and manifest.calibration_sha256 else None,
                        holds_its_calibration(used, model))
    progress("decode", 0, 1)
    with timer.stage("decode"):
        decoded = decode_exposures(session, stacks, model, replace(settings, self_check=False))
    calibrated = manifest.calibrated
    progress("reconstruct", 0, 1)
    with timer.stage("reconstruct"):
        cloud = None
        if not calibrated:
            pass  # imported without a calibration: the maps are the result
        elif mode == "triangulation":
            cloud = triangulate(decoded, Triangulator(model))
        else:
            cloud = phase_to_height_cloud(decoded, model)
    described = pattern_set_tie(manifest.patterns_sha256, manifest.recorded("patterns"))
    checks = [tie, described, *decoded.checks, *rig_checks(session, decoded, cloud, model, calibrated)]
    progress("write", 0, 1)
    out = output_dir(session.root, OUTPUTS_DIR)
    n_points = len(cloud) if cloud is not None else 0
    stats = {"points": n_points, "valid_fraction": round(float(decoded.valid.mean()), 5),
             "rejected": decoded.rejected(), "consistency": [c.as_dict() for c in checks],
             "noise_source": sensor_noise_source(session.manifest.recorded_rig.sensor) or
             "the frames (fitted to their N-step residuals; the residual itself judged by their noise along the "
             "fringes)",
             "rig_model": rig_model_source or "the session's", "integrity": session.integrity}
    if settings.self_check and failed(checks):
        refusal = ConsistencyError(f"{session.root}: ", checks)
        write_json(out / "result.json", {"session_id": session.id, "mode": mode, "error": str(refusal), **stats})
        if recording is not None:
            log_checks(recording, checks)
        raise refusal
    if (cloud is not None and n_points == 0) or not decoded.valid.any():
        problem = no_points_reason(decoded)
        write_json(out / "result.json", {"session_id": session.id, "mode": mode, "error": problem, **stats})
        raise DecodeError(f"{session.root}: the scan yielded no points: {problem}")
    result = ScanResult(session, decoded, cloud, timer.rounded()[0], checks)
    head = {"session_id": session.id, "mode": mode}
    if write_behind:
        pool = ThreadPoolExecutor(1, thread_name_prefix="write outputs")
        result.written = pool.submit(_write_outputs, result, timer, {**head, **stats}, True)
        pool.shutdown(wait=False)  # the thread finishes the write; `ScanResult.wait_written` joins it
    else:
        _write_outputs(result, timer, {**head, **stats}, False)
    if recording is not None:
        log_result(recording, result, model)
    progress("done", 1, 1)
    return result


def _write_outputs(result: ScanResult, timer: StageTimer, summary: dict[str, Any], behind: bool) -> None:
    """cloud.ply, maps.npz, then result.json with `summary` and the stage times. `behind`:
    in a thread of its own while the caller goes on (the PLY and the maps one after the
    other; the write's CPU is that thread's), else the maps beside the PLY."""
    session, out = result.session, result.session.outputs
    try:
        with timer.stage("write", clock=time.thread_time if behind else time.process_time), \
                ThreadPoolExecutor(1, thread_name_prefix="write maps") as pool:
            maps = None if behind else pool.submit(save_maps, out / "maps.npz", result.decoded)  # beside the PLY
            if result.cloud is not None:
                write_ply(out / "cloud.ply", result.cloud)
            if maps is None:
                save_maps(out / "maps.npz", result.decoded)
            else:
                maps.result()
    except OSError as exc:  # the frames and manifest are already safe: say so, and how to finish
        raise SessionError(f"{session.root}: cannot write the outputs: {disk_problem(exc)}; the frames and manifest "
                           f"are kept: `slscan decode {session.root}` writes the outputs again") from None
    timings, cpu = timer.rounded()
    result.timings_s.update(timings)
    write_json(out / "result.json", {**summary, "timings_s": timings, "cpu_s": cpu})


def holds_its_calibration(used: dict[str, Any], model: RigModel) -> bool:
    """Whether a rig model description is exactly the model the calibration file it names
    holds now (by the SHA-256 of both descriptions): a session re-decoded with its rig's new
    calibration (`slscan batch --rig`) rather than a model edited by hand."""
    path = used.get("calibration")
    if not path:
        return False
    try:
        held = load_rig_model(path, model.camera.size, model.projector.size)
    except ScannerError:
        return False
    return rig_model_sha256(json_ready(held.to_dict())) == rig_model_sha256(json_ready(used))


def rig_checks(session: Session, decoded: DecodeResult, cloud: OrganisedCloud | None, model: RigModel,
               calibrated: bool) -> list[Check]:
    """The checks that need the rig: each orientation's direction against the geometry's
    and the cloud's measuring volume (scanner.decode_checks)."""
    out = []
    for o in decoded.maps:
        ordering_check = next((c for c in decoded.checks if c.name == "ordering" and c.scope.startswith(o)), None)
        if ordering_check is not None:
            out.append(direction(ordering_check, model, o, calibrated))
    if cloud is not None and len(cloud):
        volume = Volume.of_recorded(session.manifest.recorded_rig)
        out.append(measurement_volume(cloud.points, model, volume, tuple(decoded.maps)))
    if calibrated and set(decoded.maps) == {"vertical", "horizontal"}:
        accuracy = model_accuracy_px(session, model)
        out.append(not_judged("epipolar", "cloud", "x noise", "the rig model's error on a new view is not known (a "
                              "calibration states its RMS on its own views only)") if accuracy is None else
                   epipolar_check(decoded, model, sensor_noise_source(session.manifest.recorded_rig.sensor),
                                  accuracy))
    return out


def model_accuracy_px(session: Session, model: RigModel) -> float | None:
    """How well the rig model places a point (px, one sigma), when that is known: 0 for a
    simulated rig's nominal geometry (the simulator's truth). A calibration file states its
    reprojection RMS on its own views only, not its error on a new one (on the real procam
    capture the epipolar distance is twice that RMS allows), and a nominal hardware geometry
    states nothing: None, the epipolar check is then not judged."""
    imported = session.manifest.imported
    calibrated_elsewhere = imported is not None and imported.calibration is not None
    driver = session.manifest.recorded_rig.rig.driver
    return 0.0 if driver == "sim" and not model.calibration and not calibrated_elsewhere else None


def epipolar_check(decoded: DecodeResult, model: RigModel, sensor: str | None, model_px: float) -> Check:
    """`decode_checks.epipolar` on every 4th pixel of every 4th row valid in both orientations:
    the depth from the orientation that fixes it best (the smaller |dz/dcoordinate|, along the
    baseline), the other coordinate that depth predicts through the rig, and the same from a
    coordinate half a pixel further; `model_px` the rig model's own reprojection error (px);
    `sensor` the sensor model the noise comes from (`decode_checks.sensor_noise_source`; None:
    the noise fitted to the frames)."""
    sample = np.zeros(decoded.valid.shape, bool)
    sample[::4, ::4] = True
    sample &= decoded.valid
    if sample.sum() < MIN_JUDGED:
        return not_judged("epipolar", "cloud", "x noise", f"{int(sample.sum())} pixels valid in both orientations")
    tri = Triangulator(model)
    with np.errstate(divide="ignore", invalid="ignore"):  # rays parallel to a plane a wrong model makes: no depth
        dz = {o: tri.depth_scale(np.where(sample, decoded.maps[o].coordinate, np.nan), o, True)[1][sample]
              for o in ("vertical", "horizontal")}
    dz = {o: d[np.isfinite(d)] for o, d in dz.items()}  # pixels no depth reaches are left out
    if min(d.size for d in dz.values()) < MIN_JUDGED:
        return not_judged("epipolar", "cloud", "x noise", "too few pixels the rig places in both orientations")
    source = min(dz, key=lambda o: float(np.median(dz[o])))
    other = "horizontal" if source == "vertical" else "vertical"
    rays = model.camera.ray_grid[sample].astype(np.float64)
    predicted = []
    for shift in (0.0, 0.5):
        with np.errstate(divide="ignore", invalid="ignore"):
            z = tri.depth_scale(np.where(sample, decoded.maps[source].coordinate + np.float32(shift), np.nan), source)
        in_projector = (rays * z[sample][:, None]) @ model.proj_from_cam[:3, :3].T + model.proj_from_cam[:3, 3]
        predicted.append(model.projector.project(in_projector)[:, 1 if other == "horizontal" else 0])
    accuracy = SENSOR_MODEL_ACCURACY if sensor else FITTED_MODEL_ACCURACY
    measured, given = decoded.maps[other], decoded.maps[source]
    return epipolar(measured.coordinate[sample].astype(np.float64),
                    measured.coordinate_sigma[sample].astype(np.float64), predicted[0], v_from_u_shifted=predicted[1],
                    u_sigma=given.coordinate_sigma[sample].astype(np.float64), shift_px=0.5, accuracy=accuracy,
                    noise_source=sensor or FITTED_MODEL, model_px=model_px)


def sensor_noise(session: Session) -> NoiseModel | None:
    """The camera's intensity noise from the session's rig file ([camera.sensor]), or None."""
    terms = sensor_noise_terms(session.manifest.recorded_rig.sensor, session.bit_depth)
    return NoiseModel(*terms) if terms is not None else None


def log_checks(recording: SessionRecording, checks: list[Check]) -> None:
    """Each check's statistic and threshold as metrics (`consistency/<name>/<scope>/...`) and
    its line in the event log (a failure at level ERROR)."""
    values: dict[str, float] = {}
    for c in checks:
        key = f"consistency/{c.name}/{c.scope.replace(', ', '/').replace(' ', '_')}"
        if c.statistic is not None and c.threshold is not None:
            values[f"{key}/statistic"] = c.statistic
            values[f"{key}/threshold"] = c.threshold
        recording.log_event(c.line() if c.passed is not False else c.refusal(),
                            level="ERROR" if c.passed is False else "INFO")
    if values:
        recording.log_metrics(values)


def log_result(recording: SessionRecording, result: ScanResult, model: RigModel) -> None:
    """A processed scan's maps, cloud and figures (stage timings, valid fraction, points)
    and its consistency checks into its recording."""
    log_checks(recording, result.checks)
    recording.log_decode(result.decoded)
    if result.cloud is not None:
        recording.log_cloud(result.cloud, model)
    recording.log_metrics({**{f"{k}_s": v for k, v in result.timings_s.items()},
                           "valid_fraction": round(float(result.decoded.valid.mean()), 5),
                           "points": len(result.cloud) if result.cloud is not None else 0})


def exposure_stacks(session: Session, stack: np.ndarray, model: RigModel) -> list[np.ndarray]:
    """The session's raw frames `stack` as one pattern set per exposure (ascending; one for a
    plain session), each checked against the session's patterns (`check_frames_fit`)."""
    stacks = np.split(stack, len(session.exposures_s))
    for i, stack in enumerate(stacks):
        check_frames_fit(session, stack, model, i * session.patterns.n_frames)
    return stacks


def decode_exposures(session: Session, stacks: list[np.ndarray], model: RigModel,
                     settings: DecodeSettings = DEFAULT_DECODE_SETTINGS) -> DecodeResult:
    """One decode of a session: each exposure's pattern set decoded on its own, fused per
    pixel (`scanner.exposure.fuse`; a single exposure's decode as it is), judged against the
    noise of the session's sensor model when its rig file has one."""
    patterns, noise = session.patterns, sensor_noise(session)
    return fuse([decode(s, patterns, session.bit_depth, model.projector.size, settings, noise) for s in stacks],
                session.exposures_s)


def decode_session(session: Session, settings: DecodeSettings = DEFAULT_DECODE_SETTINGS) -> DecodeResult:
    """A session's raw frames checked and decoded again, every exposure fused: the decode its
    outputs come from (`process`), for whatever needs it beside them (uncertainty, figures)."""
    stack = session.load_stack()
    model = session.rig_model()
    return decode_exposures(session, exposure_stacks(session, stack, model), model, settings)


def check_frames_fit(session: Session, stack: np.ndarray, model: RigModel, first: int = 0) -> None:
    """Refuse blank frames (every pixel within BLANK_FRAME_RANGE of full scale: no pattern),
    naming the frame. `stack` is one pattern set's frames, the session's frames `first`..
    (one exposure of an HDR session). Whether the frames follow the patterns (swapped,
    repeated, foreign ones) is the consistency checks' judgement (scanner.decode_checks)."""
    where = str(session.root)
    full = 2 ** session.bit_depth - 1
    flat = stack.reshape(len(stack), -1)
    lo, hi = flat.min(axis=1), flat.max(axis=1)
    for blank in np.flatnonzero(hi - lo <= BLANK_FRAME_RANGE * full):
        k = first + int(blank)
        raise DecodeError(f"{where}: frame {k} ({session.frame_path(k).name}) is blank (every pixel "
                          f"{int(lo[blank])}..{int(hi[blank])} DN): it cannot be a fringe image; re-scan")
    seen: dict[bytes, int] = {}
    for i, image in enumerate(stack):  # a frame copied over another: named as such, not blamed on a third
        digest = hashlib.sha256(image.tobytes()).digest()
        if digest in seen:
            k, j = first + i, first + seen[digest]
            raise DecodeError(f"{where}: frame {k} ({session.frame_path(k).name}) repeats frame {j} "
                              f"({session.frame_path(j).name}) pixel for pixel: two patterns cannot give the same "
                              f"image with camera noise; the frames were copied or the capture repeated a frame; "
                              f"re-scan")
        seen[digest] = i


def no_points_reason(decoded: DecodeResult) -> str:
    """Why a decode gave no points, for people."""
    valid = float(decoded.valid.mean())
    if valid == 0:
        return ("no pixel decoded (every pixel rejected: " + ", ".join(
            f"{o}/{k} {int(v.sum())}" for o, m in decoded.maps.items() for k, v in m.masks.items() if v.any())
            + ")")
    return (f"{valid:.1%} of pixels decoded but none triangulated: the rig model cannot place them (check the "
            f"camera and projector intrinsics and cam_from_proj in the manifest or calibration)")


def save_maps(path: Path, decoded: DecodeResult) -> None:
    """The decoded maps as an npz (float32 maps stored as they are, bool masks deflated;
    `write_npz`), for later analysis."""
    arrays: dict[str, np.ndarray] = {"texture": decoded.texture, "valid": decoded.valid}
    for o, m in decoded.maps.items():
        arrays[f"{o}/coordinate"] = m.coordinate
        arrays[f"{o}/phase"] = m.phase
        if m.wrapped:  # phase-shift sets: the finest modulation and the predicted phase noise (rad)
            arrays[f"{o}/modulation"] = m.modulation[int(np.argmax(decoded.patterns.fringes))]
            arrays[f"{o}/phase_sigma"] = m.phase_sigma
        for name, mask in m.masks.items():
            arrays[f"{o}/mask/{name}"] = mask
        if isinstance(m, FusedOrientationMaps):  # HDR: which exposure (index, ascending) each pixel came from
            arrays[f"{o}/exposure_index"] = m.exposure_index
    write_npz(path, arrays, deflate_floats=False)


def recording_level(session: Session) -> str:
    """The recording level the session was captured with (its rig's `[recording] level`;
    "display" when the rig said nothing, or for imported frames; ConfigError for a level
    that is none of them)."""
    return session.manifest.recorded_rig.recording.level


def reprocess(session: Session, progress: Progress = _quiet, mode: str = "triangulation",
              level: str | None = None, *, rig_model: RigModel | None = None,
              rig_model_source: str | None = None) -> ScanResult:
    """Regenerate every output of a session, its Rerun recording included (at `level`,
    default the session's own: `recording_level`), from the raw frames and manifest alone
    (`rig_model`: another model given on purpose, as for `process`).
    The recording is started in a thread while the session is decoded (importing Rerun,
    ~0.8 s, and logging the rig and the raw frames), and gets the results once both are
    done; a processing error (with the consistency checks of a refused decode) is logged
    into it before it is closed and raised."""
    level = level or recording_level(session)
    given: dict[str, Any] = {"rig_model": rig_model, "rig_model_source": rig_model_source}  # for `process`
    with session_lock(session.root, command="slscan decode"):
        if level == "none":
            session.recording_path.unlink(missing_ok=True)  # an older recording would not match the new outputs
            return process(session, progress, mode=mode, **given)
        return _reprocess_recorded(session, progress, mode, level, given)


def _reprocess_recorded(session: Session, progress: Progress, mode: str, level: str,
                        given: dict[str, Any]) -> ScanResult:
    rig_model = given["rig_model"]
    with ThreadPoolExecutor(1, thread_name_prefix="record frames") as pool:
        started = pool.submit(record_session_frames, session, level)
        try:
            result = process(session, progress, mode=mode, **given)
        except BaseException as exc:
            if started.exception() is None:  # waits for it; then logs the error and closes it
                with started.result() as rec:
                    if isinstance(exc, ConsistencyError):
                        log_checks(rec, exc.checks)
                    raise
            raise
        with started.result() as rec:
            log_result(rec, result, rig_model or session.rig_model())
    return result


def record_session_frames(session: Session, level: str) -> SessionRecording:
    """A new recording of `session` at `level` (its recording.rrd) holding the rig and the
    raw frames; the caller closes it (on an error here it is closed, the error raised)."""
    from scanner.session_recording import SessionRecording

    rec = SessionRecording(session.recording_path, session.id, level=level)
    with ExitStack() as on_error:
        on_error.push(rec)  # closes the recording (logging the error) only if logging fails
        rec.log_rig(session.rig_model())
        log_session_frames(rec, session)
        on_error.pop_all()
    return rec


def log_session_frames(recording: SessionRecording, session: Session) -> None:
    """The session's raw frames into `recording` as PNG: the files' own bytes, or frames in
    another lossless format (an import's BMP or TIFF) re-encoded."""
    from scanner.session_recording import png_bytes

    specs = session.patterns.frames()
    for k in range(len(session.manifest.frames)):  # every exposure's frames (HDR: the pattern set per exposure)
        spec = specs[k % len(specs)]
        path = session.frame_path(k)
        data = path.read_bytes()
        if path.suffix.lower() != ".png":
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise SessionError(f"{path}: frame {k} is not a readable image")
            data = png_bytes(image)
        recording.log_png_frame(k, data, spec)


def scan(rig: Rig, patterns: PatternSet, out_dir: str | Path, *, progress: Progress = _quiet,
         then: Callable[[ScanResult, SessionRecording | None], None] | None = None,
         level: str | None = None, exposure: ExposureRequest | None = None,
         view: ViewPlace | None = None) -> ScanResult:
    """Capture, decode and reconstruct one scan, recording every stage to the session's
    Rerun file at `level` (default the rig's `[recording] level`; "none": no recording, and
    `then` gets None). `then(result, recording)`, if given, runs a later stage (`slscan
    demo`'s inspection) into the same recording before it is closed, while the outputs are
    written behind it; `exposure` and `view` as for `capture`. Returns once every file is
    on disk."""
    from scanner.session_recording import SessionRecording

    level = level or rig.config.recording_level
    check_patterns_fit(patterns, rig.model.projector, rig.config.path)
    writer = SessionWriter.create(out_dir)
    frames: dict[int, np.ndarray] = {}  # decoded from memory, not read back from the PNGs just written
    with ExitStack() as stack:
        stack.enter_context(session_lock(writer.root, command="slscan scan"))
        rec = None if level == "none" else stack.enter_context(
            SessionRecording(writer.root / RECORDING, writer.id, level=level))
        if rec is not None:
            rec.log_rig(rig.model)
        session = capture(rig, patterns, writer, progress=progress, recording=rec, exposure=exposure, view=view,
                          keep=frames)
        if then is not None:  # BLAS on one thread: the stages' parallelism is their own threads', and an idle
            stack.enter_context(native_threads(1))  # BLAS thread spins, taking a core from them
        result = process(session, progress, rec, frames=frames, write_behind=then is not None)
        frames.clear()  # decoded: the memory goes back before the inspection
        try:
            if then is not None:
                then(result, rec)  # meanwhile the outputs are written
        finally:
            result.wait_written()
        return result
