"""The fine pose (paper 001 Eq. 27-29, with the point-to-plane metric): point-to-plane ICP
with normal-angle rejection on the dense scan (points seen at grazing incidence left out,
normal-space sampling so walls and holes weigh in) against dense model samples; then, for
STEP models, Gauss-Newton on the exact point-to-face distances with faces off as a whole
left out (`face_bias`)."""

from __future__ import annotations

import numpy as np

from inspection.measured_cloud import ScanCloud
from inspection.registration.clouds import normal_space_sample
from inspection.registration.face_bias import without_biased_faces, without_offset_face
from inspection.registration.gauss_newton import gauss_newton
from inspection.registration.point_to_plane import icp
from inspection.registration.rigid import transform_points
from inspection.registration.settings import RegistrationSettings
from inspection.registration.target import ModelTarget
from inspection.segmentation import assign_faces


def fine_pose(scan: ScanCloud, target: ModelTarget, T: np.ndarray, settings: RegistrationSettings,
              rng: np.random.Generator) -> np.ndarray:
    """Point-to-plane ICP on the dense scan (points seen more obliquely than
    `max_incidence_deg` left out, the rest drawn by normal-space sampling) on a quarter of
    the points; then, for a STEP model, `refine_exact`, else ICP on all of them. (Before
    the exact step a pass on all would add nothing: its threshold closes to 0.05 voxel,
    within which only the ~5 % of points nearest a model sample pair up.)"""
    v = target.voxel_mm
    p, n = scan.points, scan.normals
    if scan.viewpoint is not None:  # grazing views of a surface measure it worst: leave them out
        ray = scan.viewpoint - p
        grazing = (np.einsum("ij,ij->i", ray, n)
                   < np.cos(np.radians(settings.max_incidence_deg)) * np.linalg.norm(ray, axis=1))
        if (~grazing).sum() > 100:
            p, n = p[~grazing], n[~grazing]
    sel = normal_space_sample(n, settings.max_points, rng)
    first = sel[: max(len(sel) // 4, 1)]
    T = icp(p[first], n[first], target.dense, T, 1.5 * v, 0.1 * v, settings.max_normal_deg, 15,
            settings.tangential_weight)
    if target.model is None or target.model.kind != "step":
        return icp(p[sel], n[sel], target.dense, T, 0.5 * v, 0.05 * v, settings.max_normal_deg, 10,
                   settings.tangential_weight)
    sel = rng.choice(len(scan), size=min(settings.exact_points, len(scan)), replace=False)  # any point will do
    return refine_exact(scan.points[sel], scan.normals[sel], T, target, 0.3 * v, settings, offset_limit_mm=0.5 * v)


def refine_exact(src: np.ndarray, src_nrm: np.ndarray, T: np.ndarray, target: ModelTarget, tol: float,
                 settings: RegistrationSettings, iterations: int = 6,
                 offset_limit_mm: float | None = None) -> np.ndarray:
    """Gauss-Newton on the distances to the exact CAD faces: the points are assigned to
    faces once (`segmentation.assign_faces`: within `tol` mm and `max_normal_deg`, inside
    the face), then each step projects them onto their face's surface (`gauss_newton`).
    Once converged, faces whose points sit off their surface as a group (median residual
    beyond `face_bias_sigma` times the spread of the faces' medians) are left out and the
    steps repeated. Last, a large face off as a whole, by less than `offset_limit_mm`, is
    found by leaving faces out in turn (`face_bias.without_offset_face`)."""
    assert target.model is not None and target.samples is not None
    seg = assign_faces(transform_points(T, src), src_nrm @ T[:3, :3].T, target.model, target.samples,
                       target.dense.tree, tol, settings.max_normal_deg)
    src, face = src[seg.assigned], seg.face[seg.assigned]
    if len(src) < 6:
        return T
    T = gauss_newton(src, face, T, target.model, iterations)
    src, face, T = without_biased_faces(src, face, T, target.model, iterations, settings.face_bias_sigma)
    if offset_limit_mm is None:
        return T
    return without_offset_face(src, face, T, target.model, iterations, offset_limit_mm, settings.offset_noise_ratio,
                               settings.big_face_fraction)
