"""A closed-form two-camera scene for the binocular tests: a tilted plane with a sphere in front,
seen by two cameras and lit by one projector; for every camera pixel the exact point and the
projector coordinates it sees, computed here by ray-plane and ray-sphere intersection (not by
the simulator's ray tracer, nor by the code under test)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from scanner.binocular import CameraPhase
from scanner.geometry import Pinhole, look_at

PLANE_NORMAL = np.array([0.1, -0.05, -1.0]) / np.linalg.norm([0.1, -0.05, -1.0])  # facing the cameras
PLANE_POINT = np.array([0.0, 0.0, 430.0])
SPHERE_CENTRE = np.array([10.0, 5.0, 395.0])
SPHERE_RADIUS = 22.0


@dataclass(frozen=True)
class View:
    """What one camera sees: depth (H, W) z in its frame, points (H, W, 3) in the world
    (= left camera) frame, projector coordinates (H, W, 2), NaN where nothing or unlit."""

    depth: np.ndarray
    points: np.ndarray
    proj_uv: np.ndarray


def _rays(camera: Pinhole) -> np.ndarray:
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height, dtype=float))
    xy = camera.normalized(np.stack([u.ravel(), v.ravel()], 1))
    return np.column_stack([xy, np.ones(len(xy))])


def _hits(o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest positive ray parameter t (inf on a miss) and which surface (0 plane, 1 sphere)."""
    t_plane = ((PLANE_POINT - o) @ PLANE_NORMAL) / (d @ PLANE_NORMAL)
    t_plane = np.where(t_plane > 1e-9, t_plane, np.inf)
    oc = o - SPHERE_CENTRE
    a = np.einsum("ij,ij->i", d, d)
    b = d @ oc if oc.ndim == 1 else np.einsum("ij,ij->i", d, oc)
    cq = (oc @ oc if oc.ndim == 1 else np.einsum("ij,ij->i", oc, oc)) - SPHERE_RADIUS ** 2
    disc = b * b - a * cq
    with np.errstate(invalid="ignore"):
        t_s = (-b - np.sqrt(disc)) / a
    t_s = np.where((disc >= 0) & (t_s > 1e-9), t_s, np.inf)
    which = (t_s < t_plane).astype(int)
    return np.minimum(t_plane, t_s), which


def view(camera: Pinhole, world_from_cam: np.ndarray, projector: Pinhole, world_from_proj: np.ndarray) -> View:
    """The exact view of `camera` placed by `world_from_cam` (see `View`)."""
    d_cam = _rays(camera)
    R, o = world_from_cam[:3, :3], world_from_cam[:3, 3]
    d = d_cam @ R.T
    t, which = _hits(o, d)
    X = o + d * t[:, None]
    normal = np.where(which[:, None] == 1, (X - SPHERE_CENTRE) / SPHERE_RADIUS, PLANE_NORMAL)
    Cp = world_from_proj[:3, 3]
    to_point = X - Cp
    tp, _ = _hits(Cp, to_point)
    lit = np.isfinite(t) & (tp > 1 - 1e-9) & (np.einsum("ij,ij->i", normal, -to_point) > 0)
    Xp = (X - Cp) @ world_from_proj[:3, :3]
    uv = np.full((len(X), 2), np.nan)
    ahead = lit & (Xp[:, 2] > 0)
    uv[ahead] = projector.project(Xp[ahead])
    inside = ahead & (uv[:, 0] > -0.5) & (uv[:, 0] < projector.width - 0.5) & (uv[:, 1] > -0.5) & \
        (uv[:, 1] < projector.height - 0.5)
    uv[~inside] = np.nan
    X[~inside] = np.nan
    h, w = camera.height, camera.width
    depth = ((X - o) @ R)[:, 2]
    return View(depth.reshape(h, w), X.reshape(h, w, 3), uv.reshape(h, w, 2))


@dataclass(frozen=True)
class TwoCameraRig:
    left: Pinhole
    right: Pinhole
    projector: Pinhole
    world_from_right: np.ndarray
    world_from_proj: np.ndarray

    @property
    def right_from_left(self) -> np.ndarray:
        return np.linalg.inv(self.world_from_right)


def rig(scale: float = 0.5, baseline_mm: float = 200.0) -> TwoCameraRig:
    """Two 1280 x 1024 cameras (times `scale`) `baseline_mm` apart aimed at the scene, the bench
    projector between them; the world frame is the left camera's."""
    w, h = int(1280 * scale), int(1024 * scale)
    left = Pinhole.from_fov(w, h, 26.0, dist=np.array([-0.08, 0.10, 0.0005, -0.0003, 0.0]))
    right = Pinhole.from_fov(w, h, 25.0, principal=(w / 2 + 7.3, h / 2 - 4.1),
                             dist=np.array([-0.05, 0.04, 0.0, 0.0004, 0.0]))
    projector = Pinhole.from_fov(912, 1140, 30.0, pixel_aspect=2.0, dist=np.array([0.02, 0.0, 0.0, 0.0, 0.0]))
    target = np.array([0.0, 0.0, 410.0])
    left_pose = look_at(np.zeros(3), target)
    world_from_right = look_at(np.array([baseline_mm, 3.0, 8.0]), target + [0.0, 0.0, 0.0])
    world_from_right = np.linalg.inv(left_pose) @ world_from_right
    world_from_proj = look_at(np.array([baseline_mm / 2, -40.0, 0.0]), target)
    return TwoCameraRig(left, right, projector, world_from_right, world_from_proj)


def camera_phase(view: View, sigma: float, *, rng: np.random.Generator | None = None,
                 orientations: tuple[str, ...] = ("vertical", "horizontal")) -> CameraPhase:
    """The view's projector coordinates as a camera's decode gives them, with a stated noise of
    `sigma` projector px; with `rng`, that noise drawn and added (per orientation, in order)."""
    axes = {"vertical": 0, "horizontal": 1}
    c = {o: (view.proj_uv[..., axes[o]] + (0.0 if rng is None else rng.normal(0, sigma, view.depth.shape))
             ).astype(np.float32) for o in orientations}
    s = {o: np.where(np.isfinite(c[o]), np.float32(sigma), np.float32(np.nan)) for o in orientations}
    return CameraPhase(c, s, np.full(view.depth.shape, 2000.0, np.float32), 12)


def depth_edges(depth: np.ndarray, px: int, *, step_mm: float) -> np.ndarray:
    """Pixels within `px` of a depth step above `step_mm` inside a 3 x 3 neighbourhood (nothing
    seen counts as depth 0)."""
    d = np.nan_to_num(depth, nan=0.0).astype(np.float32)
    k = np.ones((3, 3), np.uint8)
    edge = ((cv2.dilate(d, k) - cv2.erode(d, k)) > step_mm).astype(np.uint8)
    return cv2.dilate(edge, np.ones((2 * px + 1, 2 * px + 1), np.uint8)) > 0
