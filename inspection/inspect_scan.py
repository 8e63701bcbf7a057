"""The inspection stage: a measured cloud and a CAD model in, a per-face report out.

    scan (camera frame, mm) --isolate the part--> register to the model (registration)
      --> assign every point to a CAD face (segmentation) --> per-face form, texture and
      deviations (form) --> report, optionally logged to a Rerun recording

A scan that does not match the model (another part, other units, too little in view)
ends in an exception, never in numbers: `RegistrationFailed`, `UnitMismatch`,
`CloudError`.
"""

from __future__ import annotations

import time
import weakref
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from inspection.cad import CadModel
from inspection.errors import InspectionError
from inspection.form import FormSettings, evaluate_face
from inspection.measured_cloud import ScanCloud, make_scan, part_mask
from inspection.registration import ModelTarget, Registration, RegistrationSettings, transform_points
from inspection.registration.warm_start import register_with_prior
from inspection.report import FaceRow, InspectionReport
from inspection.segmentation import assign_faces
from inspection.tolerances import Tolerances, verdict

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
            settings: InspectionSettings = InspectionSettings(), recording: Any = None,
            prior: Registration | None = None) -> InspectionReport:
    """Register `scan` to `model`, segment it by CAD face and evaluate every face seen.
    `recording`: a `scanner.session_recording.SessionRecording` to log the result into;
    `prior`: the previous part's registration on this station, tried first (warm start)."""
    times: dict[str, float] = {}
    t0 = time.perf_counter()
    mask = part_mask(scan, model.diagonal_mm)
    part = scan.subset(mask)
    times["isolate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    target = prepare(model)
    times["model"] = time.perf_counter() - t0
    reg = register_with_prior(part, target, prior, settings.registration)
    times["register"] = reg.timings_s.get("total", 0.0)
    t0 = time.perf_counter()
    q = transform_points(reg.transform, part.points)
    qn = part.normals @ reg.transform[:3, :3].T
    assert target.samples is not None
    seg = assign_faces(q, qn, model, target.samples, target.dense.tree, settings.max_distance_mm,
                       settings.max_normal_deg)
    times["segment"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rows = []
    for face in model.faces:  # one evaluation per face seen
        sel = seg.face == face.index
        if not sel.any():
            continue
        form = evaluate_face(face, q[sel], seg.deviation_mm[sel], seg.uv[sel], settings.form)
        rows.append(FaceRow.of(face, form, _verdicts(face.label, form, tolerances)))
    times["form"] = time.perf_counter() - t0
    report = InspectionReport(
        model=str(model.path), unit=model.unit, source=scan.source, scan_points=len(scan), part_points=len(part),
        assigned_points=int(seg.assigned.sum()), registration=reg, faces=tuple(rows),
        form_settings=settings.form, timings_s={k: round(v, 4) for k, v in times.items()},
        part_mask=mask, segmentation=seg)
    if recording is not None:
        from inspection.inspection_recording import log_inspection

        log_inspection(recording, report, scan, model)
    return report


def _verdicts(label: str, form: Any, tolerances: Tolerances | None) -> dict[str, tuple[float, str]]:
    """characteristic -> (limit, verdict) for the limits that apply to this face."""
    if tolerances is None:
        return {}
    out = {}
    floor = form.noise_floor_mm or 0.0
    own = tolerances.faces.get(label, {})
    for key, limit in tolerances.for_face(label).items():
        if form.status != "ok" and key not in own:
            continue  # a default limit does not ask for a face seen too little to measure
        if key == "flatness_mm":
            out[key] = (limit, verdict(form.flatness_mz_mm, limit, floor))
        elif key == "cylindricity_mm":
            out[key] = (limit, verdict(form.cylindricity_mz_mm, limit, floor))
        elif key == "sq_mm":
            unc = abs((form.sq_raw_mm or 0.0) - (form.sq_mm or 0.0))
            out[key] = (limit, verdict(form.sq_mm, limit, unc))
        elif key == "profile_mm":
            out[key] = (limit, verdict(form.profile_mm, limit, _profile_uncertainty(form)))
    return out


def _profile_uncertainty(form: Any) -> float:
    """What noise can add to a profile zone (mm): the filtered noise's zone (noise floor)
    on the form surface; on raw points, twice the expected largest of `points` normal
    deviates of the estimated noise, sigma sqrt(2 ln N)."""
    if form.deviation_source == "form surface":
        return form.noise_floor_mm or 0.0
    return 2.0 * (form.noise_mm or 0.0) * float(np.sqrt(2.0 * np.log(max(form.points, 2))))


def inspect_points(points: np.ndarray, model: CadModel, **kw: Any) -> InspectionReport:
    """`inspect` for bare points (N, 3) mm in a camera frame (normals estimated)."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InspectionError(f"expected points (N, 3) in mm, got shape {pts.shape}")
    viewpoint = np.zeros(3) if len(pts) and np.all(pts[:, 2] > 0) else None
    return inspect(make_scan(pts, None, "points", viewpoint), model, **kw)
