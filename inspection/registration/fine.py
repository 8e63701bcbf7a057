"""The fine pose (paper 001 Eq. 27-29, with the point-to-plane metric): point-to-plane ICP
with normal-angle rejection on the dense scan (points seen at grazing incidence left out,
normal-space sampling so walls and holes weigh in) against dense model samples; then, for
STEP models, Gauss-Newton on the exact point-to-face distances with faces off as a whole
left out (`face_bias`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from inspection.measured_cloud import ScanCloud
from inspection.registration.clouds import normal_space_sample
from inspection.registration.evidence import PoseCovariance, free_motions, pose_covariance
from inspection.registration.face_bias import without_biased_faces, without_offset_face
from inspection.registration.gauss_newton import gauss_newton
from inspection.registration.point_to_plane import icp
from inspection.registration.rigid import transform_points
from inspection.registration.settings import RegistrationSettings
from inspection.registration.target import ModelTarget
from inspection.segmentation import assign_faces, project_to_faces


@dataclass(frozen=True)
class FinalFit:
    """The points the final pose rests on: `index` into the scan, and for a STEP model
    their faces (else they were fitted to the dense samples' tangent planes)."""

    index: np.ndarray
    face: np.ndarray | None = None


def fine_pose(scan: ScanCloud, target: ModelTarget, T: np.ndarray, settings: RegistrationSettings,
              rng: np.random.Generator) -> tuple[np.ndarray, FinalFit]:
    """(pose, the points it rests on): point-to-plane ICP on the dense scan (points seen more
    obliquely than `max_incidence_deg` left out, the rest drawn by normal-space sampling) on
    a quarter of the points; then, for a STEP model, `refine_exact`, else ICP on all of them.
    (Before the exact step a pass on all would add nothing: its threshold closes to 0.05
    voxel, within which only the ~5 % of points nearest a model sample pair up.)"""
    v = target.voxel_mm
    p, n = scan.points, scan.normals
    usable = np.arange(len(scan))
    if scan.viewpoint is not None:  # grazing views of a surface measure it worst: leave them out
        ray = scan.viewpoint - p
        grazing = (np.einsum("ij,ij->i", ray, n)
                   < np.cos(np.radians(settings.max_incidence_deg)) * np.linalg.norm(ray, axis=1))
        if (~grazing).sum() > 100:
            usable = np.flatnonzero(~grazing)
    sel = usable[normal_space_sample(n[usable], settings.max_points, rng)]
    first = sel[: max(len(sel) // 4, 1)]
    T = icp(p[first], n[first], target.dense, T, 1.5 * v, 0.1 * v, settings.max_normal_deg, 15,
            settings.tangential_weight)
    if target.model is None or target.model.kind != "step":
        T = icp(p[sel], n[sel], target.dense, T, 0.5 * v, 0.05 * v, settings.max_normal_deg, 10,
                settings.tangential_weight)
        d, _ = target.dense.tree.query(transform_points(T, p[sel]), distance_upper_bound=0.5 * v)
        return T, FinalFit(sel[np.isfinite(d)])
    sel = rng.choice(len(scan), size=min(settings.exact_points, len(scan)), replace=False)  # any point will do
    return refine_exact(scan, sel, T, target, 0.3 * v, settings, offset_limit_mm=0.5 * v)


def refine_exact(scan: ScanCloud, sel: np.ndarray, T: np.ndarray, target: ModelTarget, tol: float,
                 settings: RegistrationSettings, iterations: int = 10,
                 offset_limit_mm: float | None = None) -> tuple[np.ndarray, FinalFit]:
    """Gauss-Newton on the distances of the scan points `sel` to the exact CAD faces: the
    points are assigned to faces once (`segmentation.assign_faces`: within `tol` mm and
    `max_normal_deg`, inside the face), then each step projects them onto their face's
    surface (`gauss_newton`). Once converged, faces whose points sit off their surface as a
    group (median residual beyond `face_bias_sigma` times the spread of the faces' medians)
    are left out and the steps repeated; a large face off as a whole, by less than
    `offset_limit_mm`, is found by leaving faces out in turn (`face_bias.without_offset_face`).
    Leaving faces out is undone when it would leave a motion free that all of them fix (the
    one wall seen along a plate is not "off": it is all that places the plate)."""
    assert target.model is not None and target.samples is not None
    src, src_nrm = scan.points[sel], scan.normals[sel]
    seg = assign_faces(transform_points(T, src), src_nrm @ T[:3, :3].T, target.model, target.samples,
                       target.dense.tree, tol, settings.max_normal_deg)
    sel, face = sel[seg.assigned], seg.face[seg.assigned]
    if len(sel) < 6:
        return T, FinalFit(sel, face)
    src = scan.points[sel]
    T = gauss_newton(src, face, T, target.model, iterations)
    whole = (T, FinalFit(sel, face))
    keep, T = without_biased_faces(src, face, T, target.model, iterations, settings.face_bias_sigma)
    sel, src, face = sel[keep], src[keep], face[keep]
    if offset_limit_mm is not None:
        keep, T = without_offset_face(src, face, T, target.model, iterations, offset_limit_mm,
                                      settings.offset_noise_ratio, settings.big_face_fraction)
        sel, face = sel[keep], face[keep]
    if len(sel) == len(whole[1].index):
        return T, FinalFit(sel, face)
    loose = free_motions(fit_covariance(scan, target, T, FinalFit(sel, face)), settings.pose_tolerance_deg,
                         settings.pose_tolerance_mm)
    if loose and not free_motions(fit_covariance(scan, target, *whole), settings.pose_tolerance_deg,
                                  settings.pose_tolerance_mm):
        return whole
    return T, FinalFit(sel, face)


def fit_covariance(scan: ScanCloud, target: ModelTarget, T: np.ndarray, fit: FinalFit) -> PoseCovariance:
    """The covariance of pose T from the points of `fit` (`evidence.pose_covariance`): their
    residuals to their exact faces (or the dense samples' tangent planes), the residual
    field's correlation taken over the camera image (pixels) or, for a bare cloud, over the
    scan's point spacing."""
    q = transform_points(T, scan.points[fit.index])
    if fit.face is not None and target.model is not None:
        _, _, normal, r = project_to_faces(target.model, q, fit.face)
    else:
        _, j = target.dense.tree.query(q)
        normal = target.dense.normals[j]
        r = np.einsum("ij,ij->i", q - target.dense.points[j], normal)
    if scan.pixels is not None:
        return pose_covariance(q, normal, r, scan.pixels[fit.index].astype(np.float64), "px")
    where = scan.points[fit.index]
    spacing = float(np.median(cKDTree(where).query(where, k=2)[0][:, 1])) * np.sqrt(len(where) / len(scan))
    return pose_covariance(q, normal, r, where / max(spacing, 1e-9), f"x {spacing:.3g} mm")
