"""The inspection stage: a measured cloud and a CAD model in, a per-face report out.

    scan (camera frame, mm) --isolate the part--> register to the model (registration)
      --> assign every point to a CAD face (segmentation) --> per-face form, texture and
      deviations (form) --> report, optionally logged to a Rerun recording

A scan that does not match the model (another part, other units, too little in view)
ends in an exception, never in numbers: `RegistrationFailed`, `UnitMismatch`,
`CloudError`. A pose another pose explains as well (`Registration.status` "ambiguous")
measures nothing: every face row says "not measured: the pose is ambiguous ...", with the
alternatives in its registration record. A pose the view leaves a motion free in ("free")
measures every face that motion does not move; a motion fixed only to a U above the pose
tolerance moves none (form figures are blind to it, deviation figures carry its U).

Every figure carries its uncertainty (`inspection.uncertainty`): the scan's noise model
and calibration covariance (`ScanUncertainty`, per scan point, camera frame) are turned
into the model frame with the registration and passed to each face's evaluation; without
one the noise is estimated from the data. Each characteristic with a tolerance gets an
ISO 14253-1 verdict (`inspection.tolerances.decide`) under the tolerance file's rule.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from inspection.cad import CadModel
from inspection.errors import InspectionError
from inspection.figures import limited_by
from inspection.form import FORM_WORKERS, FaceForm, FormSettings, evaluate_face
from inspection.measured_cloud import ScanCloud, make_scan, part_mask
from inspection.pose_uncertainty import PoseUncertainty
from inspection.registration import ModelTarget, Registration, RegistrationSettings, transform_points
from inspection.registration.driver import AMBIGUOUS
from inspection.registration.evidence import SYMMETRY_ZERO, FreeMotion, moves
from inspection.registration.warm_start import register_with_prior
from inspection.report import FaceRow, InspectionReport
from inspection.segmentation import UNASSIGNED, Segmentation, assign_faces
from inspection.tolerances import GUARD_BANDED, NOT_MEASURED, Tolerances, decide
from inspection.uncertainty import ScanUncertainty
from scanner.native_threads import native_threads

_TARGETS: weakref.WeakKeyDictionary[CadModel, ModelTarget] = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class InspectionSettings:
    """`max_distance_mm` / `max_normal_deg`: a point further from a face, or with a normal
    turned further from it, is not that face's (segmentation)."""

    registration: RegistrationSettings = field(default_factory=RegistrationSettings)
    form: FormSettings = field(default_factory=FormSettings)
    max_distance_mm: float = 0.5
    max_normal_deg: float = 45.0


def prepare(model: CadModel) -> ModelTarget:
    """The model's registration target (samples, descriptors), made once per model."""
    target = _TARGETS.get(model)
    if target is None:
        target = _TARGETS[model] = ModelTarget.from_cad(model)
    return target


def inspect(scan: ScanCloud, model: CadModel, tolerances: Tolerances | None = None,
            *, settings: InspectionSettings = InspectionSettings(), recording: Any = None,
            prior: Registration | None = None, uncertainty: ScanUncertainty | None = None,
            on_verdict: Callable[[InspectionReport], None] | None = None,
            progress: Callable[[str, int, int], None] | None = None) -> InspectionReport:
    """Register `scan` to `model`, segment it by CAD face and evaluate every face seen.
    `recording`: a `scanner.session_recording.SessionRecording` to log the result into;
    `prior`: the previous part's registration on this station, tried first (warm start);
    `uncertainty`: the noise model and calibration of every scan point (None: the noise
    is estimated from the data and there is no calibration term). `on_verdict(report)`
    runs as soon as the verdict is known: the faces the tolerances ask for are evaluated
    first, and that report holds only them (and the faces they ask for that were not
    seen); the report returned has every face. Faces are evaluated two at a time
    (`FACE_WORKERS`). BLAS runs on one thread inside (restored after; a process-wide limit):
    its products here are thin and memory-bound, and a second BLAS thread busy-waits between
    calls on the core the faces' threads need (the demo part's registration and segmentation:
    1.45 -> 1.16 s CPU). `progress(stage, done, total)`: told as each stage starts (isolate,
    register, segment) and as each face's figures are done (faces, n of N)."""
    with native_threads(1):
        return _inspect(scan, model, tolerances, settings=settings, recording=recording, prior=prior,
                        uncertainty=uncertainty, on_verdict=on_verdict,
                        progress=progress or (lambda stage, done, total: None))


def _inspect(scan: ScanCloud, model: CadModel, tolerances: Tolerances | None, *, settings: InspectionSettings,
             recording: Any, prior: Registration | None, uncertainty: ScanUncertainty | None,
             on_verdict: Callable[[InspectionReport], None] | None,
             progress: Callable[[str, int, int], None]) -> InspectionReport:
    times: dict[str, float] = {}
    progress("isolate", 0, 1)
    t0 = time.perf_counter()
    mask = part_mask(scan, model.diagonal_mm)
    part = scan.subset(mask)
    times["isolate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    target = prepare(model)
    times["model"] = time.perf_counter() - t0
    progress("register", 0, 1)
    reg = register_with_prior(part, target, prior, settings.registration)
    times["register"] = reg.timings_s.get("total", 0.0)
    if reg.status == AMBIGUOUS:
        report = _ambiguous_report(scan, part, model, reg=reg, tolerances=tolerances, settings=settings, mask=mask,
                                   times=times, uncertainty=uncertainty)
        if on_verdict is not None:
            on_verdict(report)
        if recording is not None:
            from inspection.inspection_recording import log_inspection

            log_inspection(recording, report, scan, model)
        return report
    progress("segment", 0, 1)
    t0 = time.perf_counter()
    q = transform_points(reg.transform, part.points)
    qn = part.normals @ reg.transform[:3, :3].T
    assert target.samples is not None
    seg = assign_faces(q, qn, model, target.samples, tree=target.dense.tree, max_distance_mm=settings.max_distance_mm,
                       max_normal_deg=settings.max_normal_deg)
    times["segment"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    R = reg.transform[:3, :3]
    unc = None if uncertainty is None else uncertainty.subset(mask)
    unbounded = list(reg.unbounded)
    pose = PoseUncertainty.of(reg.covariance, part.points, q, seg, R=R, uncertainty=unc, unbounded=reg.unbounded)
    rule = tolerances.decision_rule if tolerances is not None else GUARD_BANDED
    rows: dict[int, FaceRow] = {}
    seen = []
    for face in model.faces:
        if (seg.face == face.index).any():
            seen.append(face)
        elif tolerances is not None and face.label in tolerances.faces:  # asked for, not seen: said so
            unseen = FaceForm(0, "not seen", "no scan point on this face")
            rows[face.index] = _face_row(face, unseen, tolerances, rule)

    # a motion the view leaves free is a symmetry (nothing depends on it), bounded (its U,
    # in the pose covariance, is carried by every deviation figure as any pose U is; form
    # figures are blind to a rigid motion) or unbounded (`unbounded`): the faces it moves are
    # not measured, and neither is the pose's U

    def row(face: Any) -> FaceRow:  # one face's figures and verdicts
        sel = seg.face == face.index
        moved = _moved_by(unbounded, q[sel], seg.normal[sel], reg)
        if moved:
            unfixed = FaceForm(int(sel.sum()), NOT_MEASURED, f"depends on the {moved}, which the view does not fix")
            return _face_row(face, unfixed, tolerances, rule)
        form = measure_face(face, part.points[sel], None if unc is None else unc.subset(sel), R=R, points=q[sel],
                            deviation=seg.deviation_mm[sel], uv=seg.uv[sel], normals=seg.normal[sel],
                            settings=settings.form, pose=pose)
        form = pose.added_to(form, q[sel], seg.normal[sel], face=face.index)
        return _face_row(face, form, tolerances, rule)

    def report_of(done: dict[int, FaceRow]) -> InspectionReport:
        return InspectionReport(
            model=str(model.path), unit=model.unit, source=scan.source, scan_points=len(scan), part_points=len(part),
            assigned_points=int(seg.assigned.sum()), registration=reg, faces=tuple(done[k] for k in sorted(done)),
            form_settings=settings.form, timings_s={k: round(v, 4) for k, v in times.items()},
            part_mask=mask, segmentation=seg, decision_rule=rule, pose_u=pose,
            calibration=(uncertainty.calibration.source if uncertainty is not None
                         else "not known (a bare cloud): not in U"),
            cad=model, status=reg.status, status_note=_free_note(reg, unbounded))

    # the faces the tolerances ask for first: the verdict needs only them; the others' figures follow
    asked = [f for f in seen if tolerances is not None and tolerances.for_face(f.label)]
    done, lock = [0], threading.Lock()

    def counted(face: Any) -> FaceRow:  # one face's row, told to `progress` (faces, n of N)
        figures = row(face)
        with lock:
            done[0] += 1
            progress("faces", done[0], len(seen))
        return figures

    progress("faces", 0, len(seen))
    rows.update(_each_face(counted, asked, seg))
    times["form"] = time.perf_counter() - t0
    if on_verdict is not None:
        on_verdict(report_of(rows))
    t0 = time.perf_counter()
    rows.update(_each_face(counted, [f for f in seen if f not in asked], seg))
    times["form_after_verdict"] = time.perf_counter() - t0
    report = report_of(rows)
    if recording is not None:
        from inspection.inspection_recording import log_inspection

        log_inspection(recording, report, scan, model)
    return report


def measure_face(face: Any, camera_points: np.ndarray, uncertainty: ScanUncertainty | None, *, R: np.ndarray,
                 points: np.ndarray, deviation: np.ndarray, uv: np.ndarray, normals: np.ndarray,
                 settings: FormSettings, pose: PoseUncertainty | None = None) -> FaceForm:
    """One face's figures (`inspection.form.evaluate_face`) from its points in the camera
    frame (N, 3) and, registered (rotation `R` camera -> model), in the model frame, their
    deviations, surface parameters and the face's normals there, with the scan's
    uncertainty of these points (None: estimated from the data) turned into the model
    frame; `pose` the registration's, whose following of a calibration error takes its
    share off the points' calibration moves (None: the model frame is not fitted to the
    scan). What `inspect` and the plate's repeat scans (`studies.repeat_scans`) both call."""
    noise, shifts = None, None
    if uncertainty is not None:
        noise = None if uncertainty.noise is None else uncertainty.noise.rotated(R)
        moves = uncertainty.shifts(camera_points)
        shifts = None if moves is None else moves @ R.T
        if shifts is not None and pose is not None:
            shifts = pose.followed(shifts, points)
    return evaluate_face(face, points, deviation, uv=uv, settings=settings, noise=noise, normals=normals, shifts=shifts)


def _free_note(reg: Registration, unbounded: list[FreeMotion]) -> str:
    """What a report says of a pose with free motions (none: "")."""
    loose = [m for m in reg.free if not m.symmetry]
    if not loose:
        return ""
    if unbounded:
        return f"the view does not fix the pose: {reg.reason}; the faces that depend on it are not measured"
    return (f"the view fixes the pose only within its U: {reg.reason}; the deviation and profile figures carry it "
            f"(form figures do not depend on the pose)")


def _moved_by(unbounded: list[FreeMotion], points: np.ndarray, normals: np.ndarray, reg: Registration) -> str:
    """The unbounded free motions (not symmetries of the part) that move a face's points
    along their normals by more than a numerical zero, described; "" when none does."""
    if not unbounded or reg.covariance is None or not len(points):
        return ""
    centre, radius = reg.covariance.centre, reg.covariance.radius_mm
    return "; ".join(m.describe() for m in unbounded
                     if moves(m, points, normals, centre) > SYMMETRY_ZERO * (radius if m.kind == "rotation" else 1.0))


def ambiguity_note(reg: Registration) -> str:
    """"the pose is ambiguous between ...": what a report says in place of figures."""
    return f"the pose is {reg.reason}"


def _ambiguous_report(scan: ScanCloud, part: ScanCloud, model: CadModel, *, reg: Registration,
                      tolerances: Tolerances | None, settings: InspectionSettings, mask: np.ndarray,
                      times: dict[str, float], uncertainty: ScanUncertainty | None) -> InspectionReport:
    """The report of a scan whose pose is not proven: every face of the model "not
    measured" with the reason, every characteristic asked for "not measured"."""
    note = ambiguity_note(reg)
    unmeasured = FaceForm(0, NOT_MEASURED, note)
    rule = tolerances.decision_rule if tolerances is not None else GUARD_BANDED
    rows = tuple(_face_row(face, unmeasured, tolerances, rule) for face in model.faces)
    n = len(part)
    seg = Segmentation(np.full(n, UNASSIGNED, np.int32), np.full(n, np.nan), np.full((n, 3), np.nan),
                       np.full((n, 3), np.nan), np.full((n, 2), np.nan))
    return InspectionReport(
        model=str(model.path), unit=model.unit, source=scan.source, scan_points=len(scan), part_points=n,
        assigned_points=0, registration=reg, faces=rows, form_settings=settings.form,
        timings_s={k: round(v, 4) for k, v in times.items()}, part_mask=mask, segmentation=seg, decision_rule=rule,
        pose_u=None, calibration=uncertainty.calibration.source if uncertainty is not None
        else "not known (a bare cloud): not in U", cad=model, status=reg.status, status_note=f"not measured: {note}")


FACE_WORKERS = 2  # faces evaluated at once: threads, the form's numpy and FFT work releasing the GIL


def _each_face(row: Callable[[Any], FaceRow], faces: list[Any], seg: Any) -> dict[int, FaceRow]:
    """face index -> `row(face)` for `faces`, the largest first, `FACE_WORKERS` at a time
    (each face's figures depend on its own points and seed only: the same in any order)."""
    faces = sorted(faces, key=lambda f: -int(np.count_nonzero(seg.face == f.index)))
    if len(faces) < 2:
        return {f.index: row(f) for f in faces}

    def beside(face: Any) -> FaceRow:  # the cores are the faces': one thread of FFTs each
        FORM_WORKERS.set(1)
        return row(face)

    with ThreadPoolExecutor(FACE_WORKERS, thread_name_prefix="face form") as pool:
        return {f.index: r for f, r in zip(faces, pool.map(beside, faces))}


def _face_row(face: Any, form: FaceForm, tolerances: Tolerances | None, rule: str) -> FaceRow:
    """One face's row: its figures, their verdicts and the face's name in the tolerances."""
    return FaceRow.of(face, form, _verdicts(face.label, form, tolerances, rule),
                      tolerances.name(face.label) if tolerances is not None else "")


def _verdicts(label: str, form: Any, tolerances: Tolerances | None, rule: str) -> dict[str, tuple[float, str]]:
    """characteristic -> (limit, verdict) for the limits that apply to this face."""
    if tolerances is None:
        return {}
    out = {}
    own = tolerances.faces.get(label, {})
    for key, limit in tolerances.for_face(label).items():
        if form.status != "ok" and key not in own:
            continue  # a default limit does not ask for a face seen too little to measure
        e = form.figure(limited_by(key).name) if form.status == "ok" else None
        out[key] = (limit, NOT_MEASURED if e is None else decide(e.value, e.U, limit, None, rule, e.limit))
    return out


def inspect_points(points: np.ndarray, model: CadModel, **kw: Any) -> InspectionReport:
    """`inspect` for bare points (N, 3) mm in a camera frame (normals estimated)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InspectionError(f"expected points (N, 3) in mm, got shape {pts.shape}")
    viewpoint = np.zeros(3) if len(pts) and np.all(pts[:, 2] > 0) else None
    return inspect(make_scan(pts, None, "points", viewpoint), model, **kw)
