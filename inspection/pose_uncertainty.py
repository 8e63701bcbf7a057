"""The registration pose's uncertainty as an inspection reports it: the fit's covariance
(`registration.evidence.PoseCovariance`) plus the calibration's share, the 95 % bounds of
their sum, and none at all where the view leaves a motion free."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from inspection.form import FaceForm
from inspection.registration.evidence import FreeMotion, PoseCovariance, jacobian
from inspection.segmentation import Segmentation
from inspection.uncertainty import ScanUncertainty

POSE_CALIBRATION_POINTS = 50_000  # points the calibration's pose term is computed on (a smooth sum: a subset will do)


@dataclass(frozen=True)
class PoseUncertainty:
    """The registration pose's covariance (`evidence.PoseCovariance`, from the residuals
    and the Jacobian of the final fit, the residual field's correlation included; None: not
    known) and how the fit follows a calibration error (`following`, (D, 6); None: no
    calibration term): each principal one-sigma calibration error moves every point of the
    scan (`ScanUncertainty.shifts`), and the fit moves the pose to follow. The reported U
    and `pose_covariance` are the fit's covariance plus the calibration's share. The fit's
    own part moves each face's points along its normal as a whole, so it is added to the
    deviation figures (not to form, which it cannot change); the calibration's part is not:
    each figure carries its own points' calibration moves less the pose's following of
    them (`followed`), which is what their deviations from the registered model change by."""

    covariance: PoseCovariance | None
    following: np.ndarray | None = None  # (D, 6): rad about the centre, mm; model frame
    unbounded: tuple[FreeMotion, ...] = ()

    @classmethod
    def of(cls, covariance: PoseCovariance | None, camera_points: np.ndarray, points: np.ndarray,
           seg: Segmentation, *, R: np.ndarray, uncertainty: ScanUncertainty | None,
           unbounded: tuple[FreeMotion, ...] = ()) -> PoseUncertainty:
        """The pose's uncertainty of a scan whose camera-frame `camera_points` (N, 3) lie at
        model-frame `points` (`R` camera -> model) with faces `seg`: the fit's `covariance`
        and the fit's following of the calibration's errors (`calibration_following`) when
        `uncertainty` has one;
        `unbounded` the motions the view does not fix at all (`Registration.unbounded`):
        the pose's U is then not bounded, and not reported."""
        if covariance is None or uncertainty is None or uncertainty.calibration.is_zero:
            return cls(covariance, unbounded=unbounded)
        idx = np.flatnonzero(seg.assigned)
        idx = idx[:: max(1, len(idx) // POSE_CALIBRATION_POINTS)]
        moves = uncertainty.subset(idx).shifts(camera_points[idx])
        if moves is None:
            return cls(covariance, unbounded=unbounded)
        return cls(covariance, calibration_following(points[idx], seg.normal[idx], covariance.centre, moves @ R.T),
                   unbounded)

    @property
    def calibration(self) -> np.ndarray | None:
        """The calibration's share of the pose covariance (6, 6): Σ_d ξ_d ξ_dᵀ over the
        principal directions (None: no calibration term)."""
        return None if self.following is None else self.following.T @ self.following

    def followed(self, moves: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Model-frame `points`' (N, 3) calibration `moves` (D, N, 3) mm, one per principal
        direction, with the fit's following motion ξ_d = (ω_d, t_d) added: a point moves by
        move_d + ω_d × (p − c) + t_d relative to the registered model (unchanged without a
        calibration term)."""
        if self.following is None or self.covariance is None:
            return moves
        w, t = self.following[:, None, :3], self.following[:, None, 3:]
        return moves + np.cross(w, points - self.covariance.centre) + t

    def total(self) -> np.ndarray | None:
        """The pose's covariance (6, 6) with the calibration's share; None when not known
        or not bounded (`unbounded`: it says nothing of the motions the view leaves free)."""
        if self.covariance is None or self.unbounded:
            return None
        return self.covariance.covariance if self.calibration is None else self.covariance.covariance + self.calibration

    def bounds(self) -> tuple[float, float] | None:
        """(rotation deg, displacement of the centre mm) the pose's error stays within with
        95 % probability (`PoseCovariance.bounds_of` of `total`); None when not bounded."""
        total = self.total()
        return None if total is None else PoseCovariance.bounds_of(total)

    def note(self) -> str:
        """The motions that leave the pose's U unbounded, named ("" none)."""
        return "not bounded: " + "; ".join(m.describe() for m in self.unbounded) if self.unbounded else ""

    def text(self) -> str:
        """"pose U …" for a report's line."""
        bounds = self.bounds()
        if bounds is None:
            return f"pose U {self.note() or 'not known'}"
        return f"pose U {bounds[1] * 1e3:.2f} um, {bounds[0]:.5f} deg"

    def as_dict(self) -> dict[str, Any]:
        """The report's pose fields (JSON): the 95 % bounds, the covariance with the
        calibration's share, and how it was made ({} when not known)."""
        if self.covariance is None:
            return {}
        total, bounds = self.total(), self.bounds()
        out: dict[str, Any] = {**self.covariance.as_dict(),
                               "pose_u_calibration": "not included (no calibration covariance)"
                               if self.calibration is None else "included",
                               "rotation_u_deg": None if bounds is None else bounds[0],
                               "translation_u_mm": None if bounds is None else bounds[1],
                               "pose_covariance": None if total is None else total.tolist()}
        if self.unbounded:
            out["pose_u_note"] = self.note()
        elif self.calibration is not None:
            out["pose_covariance_calibration"] = self.calibration.tolist()
        return out

    def added_to(self, form: FaceForm, points: np.ndarray, normals: np.ndarray, *, face: int) -> FaceForm:
        """The face's deviation figures with the fit's pose uncertainty added (the mean move
        of the face along its normals; twice that for the profile zone 2 max|d|): j C j (j the
        points' mean Jacobian row, C the fit's covariance) and the part of CAD face `face`'s own
        offset the fit did not take from it (`FaceOffsets.kept_variance`). j C j holds the part it
        took; a face with little say in the fit keeps nearly all of its offset, which j C j alone
        understated (Monte Carlo: small faces' spread stated at a median 0.6 of the truth). An
        upper bound: the fit's following of the face is not subtracted, since on the demo part
        the subtraction the covariance's linear model gives left faces the fit rests on at a U of
        0.03-0.12 um against errors of 0.1-0.7 um (the fit's weights and the face's area-weighted
        mean are not the model's), so a face the fit rests on is stated wider than it reads."""
        if form.status != "ok" or self.covariance is None:
            return form
        j = jacobian(points, normals, self.covariance.centre).mean(axis=0)
        kept = 0.0 if self.covariance.offsets is None else self.covariance.offsets.kept_variance(face, j)
        u = float(np.sqrt(max(j @ self.covariance.covariance @ j + kept, 0.0)))
        changes: dict[str, Any] = {}  # FaceForm's figure fields by name: replace() cannot check them
        for name, scale in (("deviation_min", 1.0), ("deviation_max", 1.0), ("deviation_mean", 1.0),
                            ("profile", 2.0)):
            e = form.figure(name)
            if e is not None:
                changes[name] = replace(e, u=float(np.hypot(e.u, scale * u)))
        return replace(form, **changes)


def calibration_following(points: np.ndarray, normals: np.ndarray, centre: np.ndarray,
                          moves: np.ndarray) -> np.ndarray:
    """How the pose follows the calibration's errors (D, 6; rotation rad about `centre`,
    translation mm, model frame): model-frame `points` (N, 3) on faces with `normals` move
    by `moves` (D, N, 3) mm along each principal one-sigma direction of the calibration's
    covariance, and the point-to-plane fit follows each move with the motion
    ξ_d = −(JᵀJ)⁻¹ Jᵀ (n·move_d) (J the fit's Jacobian, `evidence.jacobian`). The
    directions are independent: the pose's covariance from the calibration is Σ_d ξ_d ξ_dᵀ.
    Motions the points do not fix (a turn about a ring's axis) take no share (the
    least-norm solution)."""
    J = jacobian(points, normals, centre)
    along = np.einsum("dni,ni->nd", moves, normals)
    return -np.linalg.lstsq(J, along, rcond=None)[0].T
