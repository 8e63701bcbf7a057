"""The fine step's exact-face fit against blurred pixels (issue 26): a motion only points in
an outline band fix (a crease between two CAD faces, a depth step) is not turned by them.

The scenes are the demo part's own surface samples in the model frame (the true pose the
identity): its tops and the cone round the boss, which leave exactly one motion free, the
turn about the boss axis (the tops have no lever along it, the cone is coaxial), and a few
points of the x = -45 end wall, whose lever along that turn is their y (mm): wall points at
one y read b mm outside their face make the least-squares turn -b / y rad (closed form: the
turn alone zeroes their residuals at no cost to the rest), which is what the plain fit does
and the fix must not."""

from __future__ import annotations

import numpy as np
import pytest
from registration_support import STEP

from inspection.cad import load_cad
from inspection.measured_cloud import ScanCloud
from inspection.registration.fine import _inside_outline, mixed_pixels, mixing, off_outline
from inspection.registration.gauss_newton import gauss_newton, information
from inspection.registration.settings import RegistrationSettings
from inspection.registration.target import DEFAULT_TARGET_SETTINGS
from inspection.sampling import sample_model

SETTINGS = RegistrationSettings()
BOSS = np.array([20.0, 0.0, 0.0])  # a point on the boss axis (model frame, mm); the axis is z
NOISE_MM = 0.01
CREASE_Y = 20.0  # mm: the crease points' y, their lever along the turn about the boss axis


@pytest.fixture(scope="module")
def demo():
    """(model, samples, which faces by role): the demo part sampled at 1 mm."""
    model = load_cad(STEP)
    s = sample_model(model, 1.0, seed=0)
    mean_nz = np.array([s.normals[s.face == f, 2].mean() for f in range(len(model.faces))])
    tops = np.flatnonzero(mean_nz > 0.99)
    cone = np.flatnonzero((mean_nz > 0.5) & (mean_nz < 0.9))
    end = [f for f in range(len(model.faces)) if s.normals[s.face == f, 0].mean() < -0.99
           and s.points[s.face == f, 0].max() < -44.9]
    assert len(tops) >= 3 and len(cone) == 1 and len(end) == 1
    return model, s, tops, cone, end[0]


def _turn(T: np.ndarray) -> float:
    """The turn (rad) of pose T about z (the boss axis' direction)."""
    return float(np.arctan2(T[1, 0], T[0, 0]))


def _scene(demo, *, offset_mm: float, wall: str, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points, faces, band): tops and cone with noise along their normals; three end-wall
    points at its crease with the top (y = `CREASE_Y`, z 21.5-21.9 mm) read `offset_mm`
    outside their face, in the band; with `wall` "seen" also the wall's own samples, noisy
    and not in it."""
    _, s, tops, cone, end = demo
    rng = np.random.default_rng(seed)
    noisy = np.flatnonzero(np.isin(s.face, np.concatenate([tops, cone] + ([[end]] if wall == "seen" else []))))
    crease = np.array([[-45.0 - offset_mm, CREASE_Y, z] for z in (21.5, 21.7, 21.9)])
    p = np.concatenate([s.points[noisy] + s.normals[noisy] * rng.normal(0, NOISE_MM, len(noisy))[:, None], crease])
    face = np.concatenate([s.face[noisy], np.full(len(crease), end)])
    band = np.arange(len(p)) >= len(noisy)
    return p, face, band


def _pixels(p: np.ndarray) -> np.ndarray:
    """Image positions (px) of points `p` (mm) seen from 300 mm above the origin at a focal
    length of 1000 px (the bench's top-down view)."""
    return 1000.0 * p[:, :2] / (300.0 - p[:, 2:3])


def _mixed(demo, p: np.ndarray, band: np.ndarray):
    model = demo[0]
    voxel = model.diagonal_mm / DEFAULT_TARGET_SETTINGS.voxel_fraction
    return mixed_pixels(band, np.where(band, 0.3, 0.0), pixels=_pixels(p), voxel_mm=voxel, settings=SETTINGS)


def test_biased_crease_points_turn_the_plain_fit_but_not_the_bounded_one(demo) -> None:
    model = demo[0]
    b = 0.08  # mm: the crease pixels of scan 635461529/88 read 50-130 um off their face
    p, face, band = _scene(demo, offset_mm=b, wall="crease only")
    expected = -b / (CREASE_Y - BOSS[1])  # the turn that zeroes their residuals
    plain = gauss_newton(p, face, np.eye(4), model, 10)
    unbiased = gauss_newton(*_scene(demo, offset_mm=0.0, wall="crease only")[:2], np.eye(4), model, 10)
    # (the same noise with the crease read right: the noise's own shift of the cone taken out)
    assert _turn(plain) - _turn(unbiased) == pytest.approx(expected, rel=0.01)
    mixed = _mixed(demo, p, band)
    fixed = gauss_newton(p, face, np.eye(4), model, 10, mixed=mixed)
    assert abs(_turn(fixed)) < 0.02 * abs(expected)
    # the covariance's side: exactly that turn is the one only blurred points bound
    from inspection.segmentation import project_to_faces

    _, _, n, r = project_to_faces(model, p, face)
    info = information(p, n, r, mixed.effects(face))
    bounded, only_blurred = info.directions(mixed.tolerance_deg, mixed.tolerance_mm)
    assert only_blurred.shape[1] == 1 and bounded.shape[1] == 5
    omega, t = np.split(info.scale @ only_blurred[:, 0], 2)  # about info.centre
    assert abs(omega[2]) / np.linalg.norm(omega) > 0.999
    through = info.centre + np.cross(omega, t) / (omega @ omega)  # t = omega x (centre - axis point)
    assert np.hypot(*(through - BOSS)[:2]) < 0.5


def test_band_points_far_from_their_outline_bound_the_turn(demo) -> None:
    """The same three crease points, read right, with a share of light from beyond of 9e-5
    (2 px from an outline at a blur of 0.6 px): their face's offset variance, B^2/3 times
    (share / 0.5)^2, is below what the turn's tolerance needs, so they bound it as plain
    points do (3 points 20 mm from the axis, noise 10 um: sd 0.017 deg against 0.05), and the
    bounded fit's turn is the plain fit's; at a share of 0.3 (on the outline) they do not."""
    from inspection.segmentation import project_to_faces

    model = demo[0]
    p, face, band = _scene(demo, offset_mm=0.0, wall="crease only")
    _, _, n, r = project_to_faces(model, p, face)
    voxel = model.diagonal_mm / DEFAULT_TARGET_SETTINGS.voxel_fraction
    for share, free in ((9e-5, 0), (0.3, 1)):
        mixed = mixed_pixels(band, np.where(band, share, 0.0), pixels=_pixels(p), voxel_mm=voxel, settings=SETTINGS)
        info = information(p, n, r, mixed.effects(face))
        assert info.directions(mixed.tolerance_deg, mixed.tolerance_mm)[1].shape[1] == free
    far = mixed_pixels(band, np.where(band, 9e-5, 0.0), pixels=_pixels(p), voxel_mm=voxel, settings=SETTINGS)
    assert _turn(gauss_newton(p, face, np.eye(4), model, 10, mixed=far)) == pytest.approx(
        _turn(gauss_newton(p, face, np.eye(4), model, 10)), abs=1e-9)


def test_a_band_point_reads_the_offset_by_its_own_share(demo) -> None:
    """One band of three crease points: the first on the outline (share 0.3 of its light from
    beyond) reading `b` off its face, the other two 2 px in (share 9e-5) reading it right,
    as a wall's pixels read at the truth (outline pixels off, those two in within a few um).
    Each point takes its face's offset by its own share: the two inner ones bound the turn
    and the outline one hardly turns the part, where the plain (Huber) fit turns it by the
    capped pull of that point: more than 5 % of the turn that zeroes its residual (0.23 deg).
    (Taking the band at its mean share, 0.1, left the turn free.)"""
    from inspection.segmentation import project_to_faces

    model = demo[0]
    b = 0.08
    p, face, band = _scene(demo, offset_mm=0.0, wall="crease only")
    first = np.flatnonzero(band)[0]
    _, _, n, _ = project_to_faces(model, p, face)
    p[first] += b * n[first]
    share = np.where(band, 9e-5, 0.0)
    share[first] = 0.3
    voxel = model.diagonal_mm / DEFAULT_TARGET_SETTINGS.voxel_fraction
    mixed = mixed_pixels(band, share, pixels=_pixels(p), voxel_mm=voxel, settings=SETTINGS)
    _, _, n, r = project_to_faces(model, p, face)
    info = information(p, n, r, mixed.effects(face))
    assert info.directions(mixed.tolerance_deg, mixed.tolerance_mm)[1].shape[1] == 0
    unbiased = gauss_newton(*_scene(demo, offset_mm=0.0, wall="crease only")[:2], np.eye(4), model, 10)
    whole = -b / (CREASE_Y - BOSS[1])  # the turn that zeroes the outline point's residual
    plain = gauss_newton(p, face, np.eye(4), model, 10)
    pulled = abs(_turn(plain) - _turn(unbiased))
    assert pulled > 0.05 * abs(whole)
    fixed = gauss_newton(p, face, np.eye(4), model, 10, mixed=mixed)
    assert abs(_turn(fixed) - _turn(unbiased)) < 0.2 * pulled


def test_unbiased_crease_with_the_wall_seen_costs_no_precision(demo) -> None:
    """The wall well seen bounds the turn: the bounded fit, which estimates the three crease
    points' offset and trend with the pose (`band_effects`), turns the part as the plain fit
    does to within a tenth of the turn's sd (sd = sigma / sqrt(sum of the wall points' y^2):
    three points among the wall's hundreds weigh little either way) and lands within 3 sd of
    the truth; its translation agrees with the plain fit's to within a tenth of the noise."""
    model = demo[0]
    p, face, band = _scene(demo, offset_mm=0.0, wall="seen")
    plain = gauss_newton(p, face, np.eye(4), model, 10)
    fixed = gauss_newton(p, face, np.eye(4), model, 10, mixed=_mixed(demo, p, band))
    wall = face == demo[4]
    sd = NOISE_MM / np.sqrt(((p[wall, 1] - BOSS[1]) ** 2).sum())
    assert abs(_turn(fixed) - _turn(plain)) < 0.1 * sd
    assert np.abs(fixed[:3, 3] - plain[:3, 3]).max() < 0.1 * NOISE_MM
    assert abs(_turn(fixed)) < 3.0 * sd


def test_a_crease_is_an_outline_though_no_step_in_depth() -> None:
    """A flat organised grid whose left and right halves are two faces: without faces only the
    image's edge is outline; with them the columns within EDGE_MARGIN_PX of the crease too."""
    from inspection.acceptance import EDGE_MARGIN_PX

    rows, cols = np.mgrid[0:40, 0:40]
    pixels = np.stack([cols.ravel(), rows.ravel()], axis=1)
    points = np.stack([0.1 * cols.ravel(), 0.1 * rows.ravel(), np.zeros(pixels.shape[0])], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    scan = ScanCloud(points, normals, "grid", np.array([2.0, 2.0, 100.0]), pixels, (40, 40))
    face = (pixels[:, 0] >= 20).astype(int)
    plain = _inside_outline(scan, SETTINGS.max_incidence_deg)
    creased = _inside_outline(scan, SETTINGS.max_incidence_deg, face=face)
    middle = (pixels[:, 1] == 20)
    near = np.abs(pixels[:, 0] - 19.5) < EDGE_MARGIN_PX + 1
    assert plain[middle & (pixels[:, 0] > EDGE_MARGIN_PX) & (pixels[:, 0] < 39 - EDGE_MARGIN_PX)].all()
    assert not creased[middle & near].any()
    assert creased[middle & ~near & (pixels[:, 0] > EDGE_MARGIN_PX) & (pixels[:, 0] < 39 - EDGE_MARGIN_PX)].all()


def test_a_pixels_light_from_beyond_its_outline_is_the_blurred_edges() -> None:
    """The same creased grid with its top rows left empty: each pixel's share of light from
    beyond the nearest outline is the integral over its own square of a Gaussian-blurred
    step (sigma the camera's blur) at the outline pixel's far edge: Phi(-(d + 1/2) / s),
    s^2 = sigma^2 + 1/12, d its distance in pixels from the nearest outline pixel (the
    crease's two columns, the image's last row and column, the row below the empty ones),
    computed here from the grid's geometry alone."""
    from scipy.stats import norm

    rows, cols = np.mgrid[0:40, 0:40]
    keep = rows.ravel() >= 5
    pixels = np.stack([cols.ravel(), rows.ravel()], axis=1)[keep]
    points = np.stack([0.1 * pixels[:, 0], 0.1 * pixels[:, 1], np.zeros(len(pixels))], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    scan = ScanCloud(points, normals, "grid", np.array([2.0, 2.0, 100.0]), pixels, (40, 40))
    face = (pixels[:, 0] >= 20).astype(int)
    c, r = pixels[:, 0], pixels[:, 1]
    d = np.minimum.reduce([np.minimum(np.abs(c - 19), np.abs(c - 20)), c, 39 - c, r - 5, 39 - r])  # along rows/cols
    for sigma in (0.6, 1.0):
        share = mixing(scan, off_outline(scan, SETTINGS.max_incidence_deg, face=face), blur_px=sigma)
        expected = norm.cdf(-(d + 0.5) / np.sqrt(sigma ** 2 + 1.0 / 12.0))
        assert np.allclose(share, expected, rtol=1e-6, atol=1e-12)
    bare = ScanCloud(points, normals, "bare")
    assert off_outline(bare, 75.0, face=face) is None and np.allclose(mixing(bare, None, blur_px=1.0), 0.0)


def test_a_grazing_face_is_no_outline_along_itself() -> None:
    """A flat face (0.1 mm pixel gaps) beside a steep one whose neighbouring pixels lie 2 mm
    apart (seen near grazing: gaps beyond the flat's step / cos(max incidence)): without
    faces every steep pixel is a depth step; with them only the crease's and the image
    edge's pixels are outline, the steep face's own gaps being its slope."""
    from inspection.acceptance import EDGE_MARGIN_PX

    rows, cols = np.mgrid[0:40, 0:40]
    pixels = np.stack([cols.ravel(), rows.ravel()], axis=1)
    steep = pixels[:, 0] >= 20
    x = np.where(steep, 2.0, 0.1 * cols.ravel())
    z = np.where(steep, 2.0 * (cols.ravel() - 19), 0.0)
    points = np.stack([x, 0.1 * rows.ravel(), z], axis=1)
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    scan = ScanCloud(points, normals, "grid", np.array([2.0, 2.0, 100.0]), pixels, (40, 40))
    face = steep.astype(int)
    plain = _inside_outline(scan, SETTINGS.max_incidence_deg)
    faced = _inside_outline(scan, SETTINGS.max_incidence_deg, face=face)
    off_edge = (np.minimum(pixels, 39 - pixels) >= EDGE_MARGIN_PX).all(axis=1)
    off_crease = np.abs(pixels[:, 0] - 19.5) > EDGE_MARGIN_PX + 1
    assert not plain[steep].any()
    assert faced[off_edge & off_crease].all()
    assert not faced[np.abs(pixels[:, 0] - 19.5) < EDGE_MARGIN_PX].any()

def test_only_blurred_motions_join_the_unbounded_once() -> None:
    """`fit_covariance`'s side: a motion only blurred points bound is added to the covariance's
    unbounded motions (so `free_motions` names it free) unless it is one of them already."""
    from inspection.registration.evidence import PoseCovariance, ResidualCorrelation, free_motions
    from inspection.registration.fine import _with_unbounded

    radius = 30.0
    turn = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])  # (omega, t) about the centre
    shift = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    cov = PoseCovariance(1e-10 * np.eye(6), np.zeros(3), 0.01, 1000, ResidualCorrelation(0.0, 0.0, "px"), 1.0,
                         radius, unbounded=shift[None, :])
    out = _with_unbounded(cov, np.stack([turn, 3.0 * shift]))
    assert len(out.unbounded) == 2
    assert np.allclose(np.abs(out.unbounded[1]), turn)
    named = free_motions(out, SETTINGS.pose_tolerance_deg, SETTINGS.pose_tolerance_mm)
    assert [m.blurred for m in named] == [False, True]
    assert "not determined at all" in named[0].describe() and "only by blurred pixels" in named[1].describe()
    assert _with_unbounded(cov, np.zeros((0, 6))) is cov


def test_a_motion_moved_to_another_centre_moves_every_point_alike() -> None:
    """`Information.motions`: a direction in the fit's scaled coordinates about its centre,
    written about another centre, displaces any point by the same vector (omega x (p - c) + t,
    computed here for both centres)."""
    from inspection.registration.gauss_newton import Information

    rng = np.random.default_rng(7)
    radius, centre, other = 40.0, rng.normal(0, 50, 3), rng.normal(0, 50, 3)
    scale = np.diag([1.0 / radius] * 3 + [1.0] * 3)
    info = Information(centre, radius, scale, np.eye(6), np.zeros(6), 0.01)
    directions = np.linalg.qr(rng.normal(size=(6, 2)))[0]
    p = rng.normal(0, 80, (50, 3))
    for z, moved in zip(directions.T, info.motions(directions, other)):
        omega, t = np.split(scale @ z, 2)
        assert np.allclose(np.cross(omega, p - centre) + t, np.cross(moved[:3], p - other) + moved[3:])


@pytest.mark.parametrize("shape, high", [((5000, 2), 40), ((5000, 3), 12), ((300, 2), 10 ** 6), ((1, 3), 5)])
def test_block_labels_rank_the_distinct_blocks_as_a_sort_does(shape: tuple[int, int], high: int) -> None:
    """`_dense_labels` (no sort where the blocks span a small grid; a sort where they are
    sparse) against NumPy's sort-based `unique` of the rows, negative keys included."""
    from inspection.registration.evidence import _dense_labels

    keys = np.random.default_rng(sum(shape) + high).integers(-high, high, shape)
    assert np.array_equal(_dense_labels(keys), np.unique(keys, axis=0, return_inverse=True)[1].ravel())
    assert _dense_labels(np.zeros((0, 2), np.int64)).shape == (0,)
