"""The fine pose (paper 001 Eq. 27-29, with the point-to-plane metric): point-to-plane ICP
with normal-angle rejection on the dense scan (points seen at grazing incidence left out,
normal-space sampling so walls and holes weigh in) against dense model samples; then, for
STEP models, Gauss-Newton on the exact point-to-face distances with faces off as a whole
left out (`face_bias`), stepping only along the motions that points other than blurred ones
(`blurred`: near a depth step or a crease) bound (`gauss_newton.MixedPixels`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from inspection.measured_cloud import ScanCloud, point_spacing
from inspection.registration.clouds import normal_space_sample
from inspection.registration.evidence import PoseCovariance, free_motions, pose_covariance
from inspection.registration.face_bias import without_biased_faces, without_offset_face
from inspection.registration.gauss_newton import MixedPixels, gauss_newton, information
from inspection.registration.point_to_plane import icp
from inspection.registration.rigid import transform_points
from inspection.registration.settings import RegistrationSettings
from inspection.registration.target import ModelTarget
from inspection.segmentation import assign_faces, project_to_faces

ASSIGN_VOXELS = 0.3  # scan points within this many voxels of a CAD face are assigned to it (the exact fit)

@dataclass(frozen=True)
class FinalFit:
    """The points the final pose rests on: `index` into the scan, and for a STEP model
    their faces (else they were fitted to the dense samples' tangent planes)."""

    index: np.ndarray
    face: np.ndarray | None = None
    left_out: np.ndarray | None = None  # points assigned to faces but left out as off (`refine_exact`)
    left_out_face: np.ndarray | None = None
    unseen: np.ndarray | None = None  # points on faces the fit has none of and left none out (`with_the_rest`)
    unseen_face: np.ndarray | None = None
    claimed: np.ndarray | None = None  # the pose refitted on these points and the unseen together (`with_claims`)
    mixed: MixedPixels | None = None  # the exact fit's blurred-pixel model, one entry per scan point (`blurred`)


def fine_pose(scan: ScanCloud, target: ModelTarget, T: np.ndarray, settings: RegistrationSettings,
              rng: np.random.Generator) -> tuple[np.ndarray, FinalFit]:
    """(pose, the points it rests on): point-to-plane ICP on the dense scan (points seen more
    obliquely than `max_incidence_deg` left out, the rest drawn by normal-space sampling) on
    a quarter of the points; then, for a STEP model, `refine_exact` on the points well seen
    (`well_seen`: neither grazing nor in an outline band), or, when those leave a motion
    free, on all but the grazing ones, or then on all; else ICP on all of them. The exact
    fit steps only along the motions its points bound once the blurred ones (`blurred`, at
    the ICP pose) may be off by a common offset per face (`mixed_pixels`).
    (Before the exact step a pass on all would add nothing: its threshold closes to 0.05
    voxel, within which only the ~5 % of points nearest a model sample pair up.)"""
    v = target.voxel_mm
    p, n = scan.points, scan.normals
    usable = well_seen(scan, settings.max_incidence_deg, outline=False)
    sel = usable[normal_space_sample(n[usable], settings.max_points, rng)]
    first = sel[: max(len(sel) // 4, 1)]
    T = icp(p[first], n[first], target.dense, T=T, max_dist=1.5 * v, min_dist=0.1 * v,
            max_normal_deg=settings.max_normal_deg, iterations=15,
            tangential=settings.tangential_weight)
    if target.model is None or target.model.kind != "step":
        T = icp(p[sel], n[sel], target.dense, T=T, max_dist=0.5 * v, min_dist=0.05 * v,
                max_normal_deg=settings.max_normal_deg, iterations=10,
                tangential=settings.tangential_weight)
        d, _ = target.dense.tree.query(transform_points(T, p[sel]), distance_upper_bound=0.5 * v)
        return T, FinalFit(sel[np.isfinite(d)])
    fit = None
    faces = assigned_faces(scan, target, T, settings)
    surface = off_outline(scan, settings.max_incidence_deg, face=faces)  # one outline for the band and the shares
    mixed = mixed_pixels(blurred(scan, surface), mixing(scan, surface, blur_px=settings.camera_blur_px),
                         pixels=scan.pixels, voxel_mm=v, settings=settings)
    for points in _from_best_seen(scan, settings.max_incidence_deg):  # the best measured first
        sel = rng.choice(points, size=min(settings.exact_points, len(points)), replace=False)  # any will do
        fit = refine_exact(scan, sel, T, target=target, faces=faces, settings=settings, offset_limit_mm=0.5 * v,
                           mixed=mixed)
        if not _frees(scan, target, *fit, settings):
            break
    assert fit is not None
    return fit[0], with_claims(scan, target, fit[0], with_the_rest(scan, target, *fit, settings, rng))


def with_the_rest(scan: ScanCloud, target: ModelTarget, T: np.ndarray, fit: FinalFit, settings: RegistrationSettings,
                  rng: np.random.Generator) -> FinalFit:
    """`fit` with its `unseen`: points the fit does not rest on whose faces' offsets as a whole
    tell how far the scanner may measure a face off (`evidence.pose_covariance`): a sample of
    the scan's other points (outline bands, grazing: up to `exact_points` of them) on CAD
    faces at pose T that the fit has no point of, and the faces it left out as off that lie
    mostly in outline bands (`edge_faces`). A pose a few tenths of a degree off that the
    points it rests on cannot tell shows there, as walls tens of um off. A face left out as
    off that is measured mostly away from any outline is not among them: the scanner's
    face-level error comes from the camera's blur mixing a surface with what lies beyond
    its outline (`well_seen`), so such a face's offset is the part's own (what the
    inspection measures), not the scanner's."""
    assert target.model is not None and target.samples is not None
    known = np.zeros(len(scan), bool)
    known[fit.index] = True
    if fit.left_out is not None:
        known[fit.left_out] = True
    rest = np.flatnonzero(~known)
    rest = rng.choice(rest, size=min(settings.exact_points, len(rest)), replace=False)
    seg = assign_faces(transform_points(T, scan.points[rest]), scan.normals[rest] @ T[:3, :3].T, target.model,
                       target.samples, tree=target.dense.tree, max_distance_mm=ASSIGN_VOXELS * target.voxel_mm,
                       max_normal_deg=settings.max_normal_deg)
    used = np.concatenate([fit.face if fit.face is not None else [], fit.left_out_face
                           if fit.left_out_face is not None else []])
    new = seg.assigned & ~np.isin(seg.face, used)
    index, face = rest[new], seg.face[new]
    if fit.left_out is not None and fit.left_out_face is not None and len(fit.left_out):
        edge = np.isin(fit.left_out_face, edge_faces(scan, fit.left_out, fit.left_out_face, settings.max_incidence_deg))
        index = np.concatenate([index, fit.left_out[edge]])
        face = np.concatenate([face, fit.left_out_face[edge]])
    return replace(fit, unseen=index, unseen_face=face)


def with_claims(scan: ScanCloud, target: ModelTarget, T: np.ndarray, fit: FinalFit) -> FinalFit:
    """`fit` with `claimed`: pose T refitted (`gauss_newton`) on the points it rests on and its
    `unseen` together, every face the pose claims. Where the two differ by more than the pose
    tolerance, the faces the fit rests on and the others place the part differently, and the
    motion between them is not proven (`driver.refine`): a pose trapped a few tenths of a
    degree off by the faces it rests on (random part campaign 1458621907 part_007: 0.26 deg
    off, resting on three tops and one 145-point wall, its U 0.03 deg; the walls it claims
    but did not rest on 77-101 um off as a whole)."""
    assert target.model is not None
    if fit.unseen is None or fit.face is None or len(fit.unseen) == 0:
        return fit
    index, face = np.concatenate([fit.index, fit.unseen]), np.concatenate([fit.face, fit.unseen_face])
    mixed = None if fit.mixed is None else fit.mixed.subset(index)
    return replace(fit, claimed=gauss_newton(scan.points[index], face, T, target.model, 10, mixed=mixed))


def edge_faces(scan: ScanCloud, index: np.ndarray, face: np.ndarray, max_incidence_deg: float) -> np.ndarray:
    """The faces (ids of `face`, one per scan point `index`) whose points lie mostly within
    `EDGE_MARGIN_PX` of their surface's outline in the image (`_inside_outline`); none for
    a bare cloud, which has no image to tell an outline by."""
    if scan.pixels is None or scan.image_shape is None or len(index) == 0:
        return np.zeros(0, face.dtype)
    outer = ~_inside_outline(scan, max_incidence_deg)[index]
    ids, which = np.unique(face, return_inverse=True)
    share = np.bincount(which.ravel(), weights=outer) / np.bincount(which.ravel())
    return ids[share > 0.5]


def _from_best_seen(scan: ScanCloud, max_incidence_deg: float) -> list[np.ndarray]:
    """The point sets the exact fit tries, best measured first, each only if it adds points:
    the well seen (`well_seen`), then those not grazing, then all (a part seen from straight
    above has its walls only at grazing incidence, and they are what fixes its turn)."""
    sets = [well_seen(scan, max_incidence_deg, outline=True), well_seen(scan, max_incidence_deg, outline=False),
            np.arange(len(scan))]
    return [x for k, x in enumerate(sets) if k == 0 or len(x) > len(sets[k - 1])]


def _frees(scan: ScanCloud, target: ModelTarget, T: np.ndarray, fit: FinalFit,
           settings: RegistrationSettings) -> bool:
    """Whether the fit of pose T on `fit`'s points leaves a motion free (`evidence.free_motions`)."""
    if len(fit.index) < 6:
        return True
    cov = fit_covariance(scan, target, T, fit, max_incidence_deg=settings.max_incidence_deg)
    return bool(free_motions(cov, settings.pose_tolerance_deg, settings.pose_tolerance_mm))


def well_seen(scan: ScanCloud, max_incidence_deg: float, outline: bool) -> np.ndarray:
    """Indices of the points measured well enough to rest a pose on: not seen more
    obliquely than `max_incidence_deg` (grazing views measure a surface worst), and, with
    `outline`, in an organised scan, not within `EDGE_MARGIN_PX` of the outline of the surface they lie on
    (the image's edge of the points, or a step in depth: two neighbouring pixels farther
    apart than one surface seen at that incidence puts them), where the camera's blur mixes
    the surface's fringes with what lies beyond (`inspection.acceptance.inner_pixels`: on
    the simulated bench a 12 mm step wall of the demo part read 34 um inside the material,
    enough to turn the part 0.025 deg about its axis). All points when fewer than 100 remain."""
    keep = np.ones(len(scan), bool)
    if scan.viewpoint is not None:
        ray = scan.viewpoint - scan.points
        keep &= (np.einsum("ij,ij->i", ray, scan.normals)
                 >= np.cos(np.radians(max_incidence_deg)) * np.linalg.norm(ray, axis=1))
    if outline and scan.pixels is not None and scan.image_shape is not None:
        keep &= _inside_outline(scan, max_incidence_deg)
    return np.flatnonzero(keep) if keep.sum() >= 100 else np.arange(len(scan))


def assigned_faces(scan: ScanCloud, target: ModelTarget, T: np.ndarray, settings: RegistrationSettings) -> np.ndarray:
    """The CAD face of every scan point at pose T (-1: none), as the exact fit assigns them
    (`segmentation.assign_faces` within `ASSIGN_VOXELS` voxels and `max_normal_deg`)."""
    assert target.model is not None and target.samples is not None
    seg = assign_faces(transform_points(T, scan.points), scan.normals @ T[:3, :3].T, target.model, target.samples,
                       tree=target.dense.tree, max_distance_mm=ASSIGN_VOXELS * target.voxel_mm,
                       max_normal_deg=settings.max_normal_deg)
    return np.where(seg.assigned, seg.face, -1)


def blurred(scan: ScanCloud, surface: np.ndarray | None) -> np.ndarray:
    """Which points of the scan (bool per point) the camera's blur mixes with another
    surface: within `EDGE_MARGIN_PX` of their surface's outline in the image (`surface`,
    `off_outline` with the points' CAD faces: a depth step or a crease, two neighbouring
    pixels on different faces). A convex crease is no step in depth, yet its pixels read a
    mix of both faces (on top-down views of the demo part 50-130 um off their face). None
    for a bare cloud (no image to tell it by)."""
    if surface is None:
        return np.zeros(len(scan), bool)
    return ~_inner(scan, surface)


def mixed_pixels(band: np.ndarray, share: np.ndarray, *, pixels: np.ndarray | None, voxel_mm: float,
                 settings: RegistrationSettings) -> MixedPixels:
    """The exact fit's blurred-pixel model (`gauss_newton.MixedPixels`) for the scan points
    `band` flags (`blurred`) at image positions `pixels` (N, 2; None for a bare cloud, which
    has no band): each face's band points off by a common offset and a trend across the
    image (`band_effects`), the offset uniform within
    the assignment bound (`ASSIGN_VOXELS` voxels of `voxel_mm`: a point farther off is not
    assigned) for a band half of whose light came from beyond, tau^2 = bound^2 / 3, scaled
    by the band's mean `share` of light from beyond (`mixing`); steps bounded to the pose
    tolerance of `settings`."""
    where = np.zeros((len(band), 2)) if pixels is None else pixels.astype(np.float64)
    return MixedPixels(band, (ASSIGN_VOXELS * voxel_mm) ** 2 / 3.0, settings.pose_tolerance_deg,
                       settings.pose_tolerance_mm, share, where)


def _inside_outline(scan: ScanCloud, max_incidence_deg: float, *, face: np.ndarray | None = None) -> np.ndarray:
    """Which points of an organised scan lie at least `EDGE_MARGIN_PX` inside the outline
    of their surface (`well_seen`, `off_outline`)."""
    surface = off_outline(scan, max_incidence_deg, face=face)
    assert surface is not None
    return _inner(scan, surface)


def _inner(scan: ScanCloud, surface: np.ndarray) -> np.ndarray:
    """Which points of an organised scan lie at least `EDGE_MARGIN_PX` inside `surface`
    (`off_outline`)."""
    import cv2

    from inspection.acceptance import EDGE_MARGIN_PX

    assert scan.pixels is not None
    kernel = np.ones((2 * EDGE_MARGIN_PX + 1,) * 2, np.uint8)
    inner = cv2.erode(surface.view(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    return inner[scan.pixels[:, 1], scan.pixels[:, 0]]


def off_outline(scan: ScanCloud, max_incidence_deg: float, *, face: np.ndarray | None = None) -> np.ndarray | None:
    """The image (H, W) bool of an organised scan's points that are not on an outline of
    their surface (None for a bare cloud): neighbours further apart than the image's median step at
    `max_incidence_deg` are a depth step, both pixels on it. With `face` (one CAD face id per
    point, -1 none), a crease between two faces counts as outline too, and two neighbours on
    one face are no step however far apart: that gap is the face's slope, seen near grazing
    (`blurred`; such points read their face to a few um at the true pose, where points
    within the margin of a crease read tens)."""
    if scan.pixels is None or scan.image_shape is None:
        return None
    col, row = scan.pixels[:, 0], scan.pixels[:, 1]
    grid = np.full(scan.image_shape + (3,), np.nan)
    grid[row, col] = scan.points
    surface = np.zeros(scan.image_shape, bool)
    surface[row, col] = True
    gaps = [np.linalg.norm(np.diff(grid, axis=a), axis=2) for a in (0, 1)]
    step = np.nanmedian(np.concatenate([g[np.isfinite(g)] for g in gaps]))
    limit = step / np.cos(np.radians(max_incidence_deg))
    with np.errstate(invalid="ignore"):
        jump0, jump1 = gaps[0] > limit, gaps[1] > limit
    if face is not None:  # a crease: neighbours on two faces; a gap within one face is its slope, not a step
        label = np.full(scan.image_shape, -1)
        label[row, col] = face
        for a, jump in ((0, jump0), (1, jump1)):
            lo, hi = np.delete(label, -1, axis=a), np.delete(label, 0, axis=a)
            both = (lo >= 0) & (hi >= 0)
            jump &= ~(both & (lo == hi))
            jump |= both & (lo != hi)
    surface[:-1] &= ~jump0
    surface[1:] &= ~jump0
    surface[:, :-1] &= ~jump1
    surface[:, 1:] &= ~jump1
    return surface


def mixing(scan: ScanCloud, surface: np.ndarray | None, *, blur_px: float) -> np.ndarray:
    """The share of each point's light (0 to 1/2) that comes from beyond its surface's
    outline (`surface`, `off_outline`: a depth step or a crease, as for `blurred`): a pixel whose
    centre lies d + 1/2 px from the outline (d the distance in pixels from the nearest outline
    pixel, 0 on it) sees the far side through the camera's blur, a Gaussian of sigma
    `blur_px`, integrated over its own square (variance 1/12 px^2): Phi(-(d + 1/2) / s),
    s^2 = `blur_px`^2 + 1/12. A face's offset as a whole grows with its points' mean share
    (`evidence._face_offsets`). Zeros for a bare cloud (no image to tell outlines by)."""
    import cv2
    from scipy.special import ndtr

    if surface is None:
        return np.zeros(len(scan))
    assert scan.pixels is not None
    col, row = scan.pixels[:, 0], scan.pixels[:, 1]
    present = np.zeros(surface.shape, bool)
    present[row, col] = True
    whole = cv2.erode(present.view(np.uint8), np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8),
                      borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    outline = present & ~(surface & whole)  # on a step or crease, or beside a pixel with no point
    d = cv2.distanceTransform((~outline).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[row, col]
    return ndtr(-(d + 0.5) / np.sqrt(blur_px ** 2 + 1.0 / 12.0))


def refine_exact(scan: ScanCloud, sel: np.ndarray, T: np.ndarray, *, target: ModelTarget, faces: np.ndarray,
                 settings: RegistrationSettings, iterations: int = 10,
                 offset_limit_mm: float | None = None, mixed: MixedPixels | None = None) -> tuple[np.ndarray, FinalFit]:
    """Gauss-Newton on the distances of the scan points `sel` to the exact CAD faces: the
    points keep the faces `faces` gives every scan point at T (`assigned_faces`; -1: none,
    left out), then each step projects them onto their face's
    surface (`gauss_newton`). Once converged, faces whose points sit off their surface as a
    group (median residual beyond `face_bias_sigma` times the spread of the faces' medians)
    are left out and the steps repeated; a large face off as a whole, by less than
    `offset_limit_mm`, is found by leaving faces out in turn (`face_bias.without_offset_face`).
    A motion that only the faces left out fix is then free: the data call the one face that
    would place the part along it off, so the pose along it is not proven (taking such a
    face back in had placed random part seed 1458621907/part_000 0.136 mm off, exit 0).
    `mixed` (one entry per scan point): every step only along the motions the points bound
    with their blurred ones' offsets allowed for (`gauss_newton.MixedPixels`; None: plain)."""
    assert target.model is not None
    faces_sel = faces[sel]
    sel, face = sel[faces_sel >= 0], faces_sel[faces_sel >= 0]
    if len(sel) < 6:
        return T, FinalFit(sel, face, mixed=mixed)
    src = scan.points[sel]
    own = None if mixed is None else mixed.subset(sel)
    T = gauss_newton(src, face, T, target.model, iterations, mixed=own)
    whole = (T, FinalFit(sel, face))
    keep, T = without_biased_faces(src, face, T, target.model, iterations, settings.face_bias_sigma, mixed=own)
    sel, src, face = sel[keep], src[keep], face[keep]
    if offset_limit_mm is not None:
        own = None if mixed is None else mixed.subset(sel)
        keep, T = without_offset_face(src, face, T, model=target.model, iterations=iterations, limit_mm=offset_limit_mm,
                                      noise_ratio=settings.offset_noise_ratio, big_fraction=settings.big_face_fraction,
                                      mixed=own)
        sel, face = sel[keep], face[keep]
    return T, FinalFit(sel, face, *_left_out(whole[1], sel), mixed=mixed)


def _left_out(whole: FinalFit, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(points, faces) of `whole` not among `kept`."""
    out = ~np.isin(whole.index, kept)
    assert whole.face is not None
    return whole.index[out], whole.face[out]


def fit_covariance(scan: ScanCloud, target: ModelTarget, T: np.ndarray, fit: FinalFit, *,
                   max_incidence_deg: float) -> PoseCovariance:
    """The covariance of pose T from the points of `fit` (`evidence.pose_covariance`): their
    residuals to their exact faces (or the dense samples' tangent planes), the residual
    field's correlation taken over the camera image (pixels) or, for a bare cloud, over the
    scan's point spacing; the faces the fit never saw (`with_the_rest`) are evidence of how
    far a face's measurement may be off as a whole (in the face offsets' variance, not the fit),
    faces mostly in outline bands (`_inside_outline` at `max_incidence_deg`) apart from the rest.
    With the fit's blurred-pixel model (`FinalFit.mixed`), the motions the exact fit would not
    step along (`gauss_newton.MixedPixels`: only blurred points bound them) are named
    unbounded (`_with_unbounded`), so a pose is never proven along a motion the fit left
    where the stage before it (ICP) put it."""
    index, face = fit.index, fit.face
    if fit.unseen is not None and len(fit.unseen) and face is not None:
        index, face = np.concatenate([index, fit.unseen]), np.concatenate([face, fit.unseen_face])
    in_fit = np.arange(len(index)) < len(fit.index)
    q = transform_points(T, scan.points[index])
    if face is not None and target.model is not None:
        _, _, normal, r = project_to_faces(target.model, q, face)
    else:
        _, j = target.dense.tree.query(q)
        normal = target.dense.normals[j]
        r = np.einsum("ij,ij->i", q - target.dense.points[j], normal)
    effects = None if fit.mixed is None or face is None else fit.mixed.subset(index).effects(face, within=in_fit)
    if scan.pixels is not None:
        share = None if fit.mixed is None else fit.mixed.mixing[index]
        cov = pose_covariance(q, normal, r, scan.pixels[index].astype(np.float64), "px", face, in_fit=in_fit,
                              mixing=share, offset_bound_mm=ASSIGN_VOXELS * target.voxel_mm, band=effects)
    else:
        where = scan.points[index]
        spacing = point_spacing(scan.points[fit.index], len(scan))
        cov = pose_covariance(q, normal, r, where / max(spacing, 1e-9), f"x {spacing:.3g} mm", face, in_fit=in_fit,
                              offset_bound_mm=ASSIGN_VOXELS * target.voxel_mm)
    if fit.mixed is None or effects is None:
        return cov
    info = information(q[in_fit], normal[in_fit], r[in_fit], effects.subset(in_fit))
    _, only_blurred = info.directions(fit.mixed.tolerance_deg, fit.mixed.tolerance_mm)
    return _with_unbounded(cov, info.motions(only_blurred, cov.centre))


def _with_unbounded(cov: PoseCovariance, motions: np.ndarray) -> PoseCovariance:
    """`cov` with `motions` (rows (omega rad, t mm) about `cov.centre`) among its unbounded
    ones (`free_motions` names them free), each whose part outside their span is over 1/2
    in `cov`'s scaled coordinates (rotations as mm at `cov.radius_mm`; the rest is in the
    span already). Its covariance along them stays what the points, blurred ones included,
    say: the fit did not move the pose there."""
    if len(motions) == 0:
        return cov
    S = np.diag([1.0 / cov.radius_mm] * 3 + [1.0] * 3)
    known = np.linalg.solve(S, cov.unbounded.T)
    basis = np.linalg.qr(known)[0] if known.shape[1] else known
    directions = np.linalg.solve(S, motions.T)
    directions /= np.linalg.norm(directions, axis=0, keepdims=True)
    rest = directions - basis @ (basis.T @ directions)
    new = (S @ rest[:, np.linalg.norm(rest, axis=0) > 0.5]).T
    new /= np.linalg.norm(new, axis=1, keepdims=True)
    return replace(cov, unbounded=np.concatenate([cov.unbounded, new]), blurred=cov.blurred + len(new))
