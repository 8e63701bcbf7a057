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
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from inspection.cad import CadModel
from inspection.errors import InspectionError
from inspection.figures import limited_by
from inspection.form import FORM_WORKERS, FaceForm, FormSettings, evaluate_face
from inspection.measured_cloud import ScanCloud, make_scan, part_mask
from inspection.registration import ModelTarget, Registration, RegistrationSettings, transform_points
from inspection.registration.driver import AMBIGUOUS
from inspection.registration.evidence import SYMMETRY_ZERO, FreeMotion, PoseCovariance, jacobian, moves
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
    unbounded = [m for m in reg.free if not m.symmetry and not np.isfinite(m.u)]
    pose = PoseUncertainty.of(reg.covariance, part.points, q, seg, R=R, uncertainty=unc,
                              unbounded="; ".join(m.describe() for m in unbounded))
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
                            settings=settings.form)
        form = pose.added_to(form, q[sel], seg.normal[sel])
        return _face_row(face, form, tolerances, rule)

    def report_of(done: dict[int, FaceRow]) -> InspectionReport:
        return InspectionReport(
            model=str(model.path), unit=model.unit, source=scan.source, scan_points=len(scan), part_points=len(part),
            assigned_points=int(seg.assigned.sum()), registration=reg, faces=tuple(done[k] for k in sorted(done)),
            form_settings=settings.form, timings_s={k: round(v, 4) for k, v in times.items()},
            part_mask=mask, segmentation=seg, decision_rule=rule, pose_u=pose.as_dict(),
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
                 settings: FormSettings) -> FaceForm:
    """One face's figures (`inspection.form.evaluate_face`) from its points in the camera
    frame (N, 3) and, registered (rotation `R` camera -> model), in the model frame, their
    deviations, surface parameters and the face's normals there, with the scan's
    uncertainty of these points (None: estimated from the data) turned into the model
    frame. What `inspect` and the plate's repeat scans (`studies.repeat_scans`) both call."""
    noise, shifts = None, None
    if uncertainty is not None:
        noise = None if uncertainty.noise is None else uncertainty.noise.rotated(R)
        moves = uncertainty.shifts(camera_points)
        shifts = None if moves is None else moves @ R.T
    return evaluate_face(face, points, deviation, uv=uv, settings=settings, noise=noise, normals=normals, shifts=shifts)


POSE_CALIBRATION_POINTS = 50_000  # points the calibration's pose term is computed on (a smooth sum: a subset will do)


@dataclass(frozen=True)
class PoseUncertainty:
    """The registration pose's covariance (`evidence.PoseCovariance`, from the residuals
    and the Jacobian of the final fit, the residual field's correlation included; None: not
    known) and the calibration's share (6, 6; None: no calibration term): one calibration
    error moves every point of the scan (`ScanUncertainty.shifts`), and the fit moves the
    pose to follow. The reported U and `pose_covariance` are their sum. The fit's own part
    moves each face's points along its normal as a whole, so it is added to the deviation
    figures (not to form, which it cannot change); the calibration's part is not, as each
    figure carries the calibration's moves of its own points already."""

    covariance: PoseCovariance | None
    calibration: np.ndarray | None = None
    unbounded: str = ""

    @classmethod
    def of(cls, covariance: PoseCovariance | None, camera_points: np.ndarray, points: np.ndarray,
           seg: Segmentation, *, R: np.ndarray, uncertainty: ScanUncertainty | None,
           unbounded: str = "") -> PoseUncertainty:
        """The pose's uncertainty of a scan whose camera-frame `camera_points` (N, 3) lie at
        model-frame `points` (`R` camera -> model) with faces `seg`: the fit's `covariance`
        and the calibration's term (`calibration_covariance`) when `uncertainty` has one;
        `unbounded` the motions the view does not fix at all, described ("" none): the
        pose's U is then not bounded, and not reported."""
        if covariance is None or uncertainty is None or uncertainty.calibration.is_zero:
            return cls(covariance, unbounded=unbounded)
        idx = np.flatnonzero(seg.assigned)
        idx = idx[:: max(1, len(idx) // POSE_CALIBRATION_POINTS)]
        moves = uncertainty.subset(idx).shifts(camera_points[idx])
        if moves is None:
            return cls(covariance, unbounded=unbounded)
        return cls(covariance, calibration_covariance(points[idx], seg.normal[idx], covariance.centre, moves @ R.T),
                   unbounded)

    def total(self) -> np.ndarray | None:
        """The pose's covariance (6, 6) with the calibration's share."""
        if self.covariance is None:
            return None
        return self.covariance.covariance if self.calibration is None else self.covariance.covariance + self.calibration

    def as_dict(self) -> dict[str, Any]:
        total = self.total()
        if self.covariance is None or total is None:
            return {}
        out: dict[str, Any] = {**self.covariance.as_dict(),
                               "pose_u_calibration": "not included (no calibration covariance)"
                               if self.calibration is None else "included"}
        if self.unbounded:  # the covariance says nothing of the motions the view leaves free
            return {**out, "rotation_u_deg": None, "translation_u_mm": None, "pose_covariance": None,
                    "pose_u_note": f"not bounded: {self.unbounded}"}
        rot, shift = PoseCovariance.bounds_of(total)
        out.update(rotation_u_deg=rot, translation_u_mm=shift, pose_covariance=total.tolist())
        if self.calibration is not None:
            out["pose_covariance_calibration"] = self.calibration.tolist()
        return out

    def added_to(self, form: FaceForm, points: np.ndarray, normals: np.ndarray) -> FaceForm:
        """The face's deviation figures with the fit's pose uncertainty added (the mean move
        of the face along its normals; twice that for the profile zone 2 max|d|)."""
        if form.status != "ok" or self.covariance is None:
            return form
        m = jacobian(points, normals, self.covariance.centre).mean(axis=0)
        u = float(np.sqrt(max(m @ self.covariance.covariance @ m, 0.0)))
        changes: dict[str, Any] = {}  # FaceForm's figure fields by name: replace() cannot check them
        for name, scale in (("deviation_min", 1.0), ("deviation_max", 1.0), ("deviation_mean", 1.0),
                            ("profile", 2.0)):
            e = form.figure(name)
            if e is not None:
                changes[name] = replace(e, u=float(np.hypot(e.u, scale * u)))
        return replace(form, **changes)


def calibration_covariance(points: np.ndarray, normals: np.ndarray, centre: np.ndarray,
                           moves: np.ndarray) -> np.ndarray:
    """The pose's covariance (6, 6; rotation rad about `centre`, translation mm, model
    frame) from the calibration's: model-frame `points` (N, 3) on faces with `normals`
    move by `moves` (D, N, 3) mm along each principal one-sigma direction of the
    calibration's covariance; the point-to-plane fit follows each move with the motion
    ξ_d = −(JᵀJ)⁻¹ Jᵀ (n·move_d) (J the fit's Jacobian, `evidence.jacobian`), and the
    directions are independent: Σ = Σ_d ξ_d ξ_dᵀ. Motions the points do not fix (a
    turn about a ring's axis) take no share (the least-norm solution)."""
    J = jacobian(points, normals, centre)
    along = np.einsum("dni,ni->nd", moves, normals)
    xi = -np.linalg.lstsq(J, along, rcond=None)[0].T
    return xi.T @ xi


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
        pose_u={}, calibration=uncertainty.calibration.source if uncertainty is not None
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
