"""Moving things in front of a simulated rig: a printed target through a sequence of
poses (the hand or robot of a bench calibration), a flat plate on a translation stage, and
calibration artefacts.

`show(rig, scene)` swaps what an open simulated rig looks at: the geometry is ray-cast once
for the new scene (a plane-only scene costs ~1 s at 1280 x 1024, no mesh ray casting) and
the camera renders from it from then on; the rig's ground truth follows. `SimBench` does
what an operator does during `slscan calibrate` (the `calibration.workflow.Bench`
protocol, met structurally: the simulator does not import the calibration package).

All poses map object-frame points to the rig's world frame (= the camera frame), in mm.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from scanner.geometry import RigModel
from scanner.rig import Rig
from sim.evaluate import GROUND_TRUTH_FILE, Truth
from sim.render import Renderer, project_points
from sim.scene import Scene, SceneObject

VISIBILITY_MARGIN = 0.03  # target points kept this fraction of the image size inside both images
OUTLINE_SAMPLES = 33  # points along each edge of the printed sheet (a lens bends its straight edges)


@dataclass(frozen=True, eq=False)
class Target:
    """A flat printed target: `texture` (H, W) reflectance 0..1 over a `size_mm` rectangle;
    the target frame's origin lies `origin_mm` from the texture's top-left corner (x along
    its columns, y down its rows, z into the target). `points` (N, 3): the points, in the
    target frame, that must stay visible to camera and projector when poses are planned."""

    texture: np.ndarray
    size_mm: tuple[float, float]
    origin_mm: tuple[float, float]
    points: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """The target's centre in its own frame."""
        return np.array([self.size_mm[0] / 2 - self.origin_mm[0], self.size_mm[1] / 2 - self.origin_mm[1], 0.0])

    @property
    def outline(self) -> np.ndarray:
        """(4 x OUTLINE_SAMPLES, 3) points along the printed sheet's four edges, in the target frame."""
        w, h = self.size_mm
        ox, oy = self.origin_mm
        corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]) - [ox, oy]
        t = np.linspace(0.0, 1.0, OUTLINE_SAMPLES, endpoint=False)[:, None]
        edges = np.concatenate([a + t * (b - a) for a, b in zip(corners, np.roll(corners, -1, axis=0))])
        return np.c_[edges, np.zeros(len(edges))]

    def scene_object(self, pose: np.ndarray, name: str = "target") -> SceneObject:
        """The target as a textured plane placed at `pose` (target frame -> world)."""
        centred = np.eye(4)
        centred[:3, 3] = self.centre
        return SceneObject(name=name, kind="plane", pose=pose @ centred, albedo=1.0, size_mm=self.size_mm,
                           texture=self.texture)


def show(rig: Rig, scene: Scene) -> None:
    """Make the simulated `rig` look at `scene` from now on (call between acquisitions)."""
    old: Renderer = rig.extras["renderer"]
    renderer = Renderer(old.model, scene, old.sensor, old.projector_blur_sigma_px)
    rig.camera.renderer = renderer  # type: ignore[attr-defined]  # a SimCamera
    truth = Truth.of(renderer.ground_truth)
    rig.extras.update(scene=scene, renderer=renderer, ground_truth=renderer.ground_truth,
                      session_files=[lambda root: truth.save(Path(root) / GROUND_TRUTH_FILE)])
    if "renderers" in rig.extras:  # a rig with several cameras: every one looks at the scene
        renderers = {name: renderer if rig.cameras[name] is rig.camera else
                     Renderer(r.model, scene, r.sensor, r.projector_blur_sigma_px)
                     for name, r in rig.extras["renderers"].items()}
        for name, r in renderers.items():
            rig.cameras[name].renderer = r  # type: ignore[attr-defined]  # SimCameras
        rig.extras.update(renderers=renderers, ground_truths={n: r.ground_truth for n, r in renderers.items()})


def rotation(tilt_x_deg: float, tilt_y_deg: float, spin_deg: float) -> np.ndarray:
    """Rz(spin)·Ry(tilt_y)·Rx(tilt_x), angles in degrees (human-facing parameters)."""
    rx, ry, rz = np.radians([tilt_x_deg, tilt_y_deg, spin_deg])
    Rx = cv2.Rodrigues(np.array([rx, 0.0, 0.0]))[0]
    Ry = cv2.Rodrigues(np.array([0.0, ry, 0.0]))[0]
    Rz = cv2.Rodrigues(np.array([0.0, 0.0, rz]))[0]
    return Rz @ Ry @ Rx


def target_pose(target: Target, R: np.ndarray, centre_world: np.ndarray) -> np.ndarray:
    """The pose that turns the target by R (about its centre) and puts its centre at `centre_world`."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre_world - R @ target.centre
    return T


def visible(model: RigModel, target: Target, pose: np.ndarray, margin: float = VISIBILITY_MARGIN, *,
            whole_sheet: bool = False) -> bool:
    """Every target point is in front of both devices, inside both images by `margin` (a
    fraction of the image size), and the target faces the camera and the projector at less
    than 70 degrees; `whole_sheet`: the printed sheet's outline (`Target.outline`: the pattern
    and its white border) inside both images too, in front of both."""
    R, t = pose[:3, :3], pose[:3, 3]
    X = (np.concatenate([target.points, target.outline]) if whole_sheet else target.points) @ R.T + t
    Xp = X @ model.proj_from_cam[:3, :3].T + model.proj_from_cam[:3, 3]
    inset = np.where(np.arange(len(X)) < len(target.points), margin, 0.0)[:, None]  # the outline: none
    for pts, centre, dev in ((X, np.zeros(3), model.camera), (Xp, model.cam_from_proj[:3, 3], model.projector)):
        if (pts[:, 2] <= 0).any():
            return False
        uv = project_points(dev, pts)
        size = np.array(dev.size)
        if not ((uv >= inset * size).all() and (uv <= size - 1 - inset * size).all()):
            return False
        view = t - centre
        if abs(view @ R[:, 2]) / np.linalg.norm(view) < np.cos(np.radians(70)):
            return False
    return True


# (tilt about x, tilt about y, spin about the normal) in degrees, and the direction the
# target is pushed from the centre of the field (fractions of the room there is), and the
# change of distance (fraction of +-15 % of the working distance)
_POSE_TEMPLATES = (
    (0, 0, 0, 0.0, 0.0, 0.0),
    (28, 0, 4, 0.0, -1.0, -0.5),
    (-28, 0, -4, 0.0, 1.0, 0.5),
    (0, 28, 0, -1.0, 0.0, 0.3),
    (0, -28, 3, 1.0, 0.0, -0.3),
    (20, 20, 12, -1.0, -1.0, -1.0),
    (20, -20, -12, 1.0, -1.0, 1.0),
    (-20, 20, 15, -1.0, 1.0, 1.0),
    (-20, -20, -15, 1.0, 1.0, -1.0),
    (12, -8, 35, 0.0, 0.0, 0.8),
    (-10, 25, -30, -0.6, 0.5, -0.8),
    (25, 12, -20, 0.6, -0.5, 0.6),
    (-25, -12, 25, 0.5, 0.8, 0.0),
    (8, 30, 8, -0.3, -0.8, 0.4),
    (-30, -5, -8, 0.8, 0.3, -0.6),
)
MAX_POSES = len(_POSE_TEMPLATES)


def plan_target_poses(model: RigModel, target: Target, n: int, distance_mm: float, seed: int = 0,
                      jitter_deg: float = 2.0, *, jitter_first: bool = False, whole_sheet: bool = False,
                      also: tuple[RigModel, ...] = ()) -> list[np.ndarray]:
    """`n` (<= MAX_POSES) poses of `target` that the camera and the projector both see whole
    (`visible`, with `whole_sheet`), and so does each device pair in `also`: frontal, tilted up
    to ~30 degrees each way, spun, pushed toward each side of the field as far as visibility
    allows, and nearer and farther. `seed` turns every pose but the first (frontal) by up to
    `jitter_deg` about each axis; `jitter_first`: the first too (independent draws: a pose the
    same in every draw repeats its detection errors)."""
    if not 1 <= n <= MAX_POSES:
        raise ValueError(f"between 1 and {MAX_POSES} target poses can be planned, not {n}")
    rng = np.random.default_rng(seed)

    def seen(pose: np.ndarray) -> bool:
        return all(visible(m, target, pose, whole_sheet=whole_sheet) for m in (model, *also))

    poses = []
    for k, (tx, ty, spin, fx, fy, fz) in enumerate(_POSE_TEMPLATES[:n]):
        jitter = rng.uniform(-jitter_deg, jitter_deg, 3) if k or jitter_first else np.zeros(3)
        R = rotation(tx + jitter[0], ty + jitter[1], spin + jitter[2])
        placed = None
        for shrink in (1.0, 0.7, 0.5, 0.3):  # pull in tilt and distance change until a placement exists
            Rk = rotation((tx + jitter[0]) * shrink, (ty + jitter[1]) * shrink, spin + jitter[2]) if shrink < 1 else R
            z = distance_mm * (1.0 + 0.15 * fz * shrink)
            centre = np.array([0.0, 0.0, z])
            if not seen(target_pose(target, Rk, centre)):
                continue
            lo, hi = 0.0, 0.5 * z  # bisect the push toward (fx, fy) that still keeps everything visible
            direction = np.array([fx, fy, 0.0])
            for _ in range(20):
                mid = (lo + hi) / 2
                ok = seen(target_pose(target, Rk, centre + mid * direction))
                lo, hi = (mid, hi) if ok else (lo, mid)
            placed = target_pose(target, Rk, centre + lo * direction)
            break
        if placed is None:
            raise ValueError(f"target pose {k}: the target does not fit in the common field of the rig's devices at "
                             f"{distance_mm:.0f} mm; use a smaller target")
        poses.append(placed)
    return poses


def plate_scene(distance_mm: float, height_mm: float = 0.0, size_mm: float = 1000.0, albedo: float = 0.8) -> Scene:
    """A flat plate facing the camera at `distance_mm`, raised `height_mm` toward the camera
    (a reference plane on a translation stage)."""
    pose = np.eye(4)
    pose[2, 3] = distance_mm - height_mm
    plate = SceneObject(name="reference_plane", kind="plane", pose=pose, albedo=albedo, size_mm=(size_mm, size_mm))
    return Scene(objects=(), reference_plane=plate, name=f"plate at {height_mm:g} mm")


def sphere_pair_scene(radius_mm: float, separation_mm: float, distance_mm: float, backing_mm: float,
                      tilt_deg: float = 30.0, albedo: float = 0.7) -> Scene:
    """Two spheres of `radius_mm`, centres `separation_mm` apart, centred on the camera axis
    at `distance_mm`, the bar between them turned `tilt_deg` out of the image plane (so the
    distance measures depth as well as width), in front of a plate at `backing_mm`."""
    spheres = []
    t = np.radians(tilt_deg)
    for name, sign in (("sphere_left", -1.0), ("sphere_right", 1.0)):
        pose = np.eye(4)
        pose[:3, 3] = [sign * separation_mm / 2 * np.cos(t), 0.0, distance_mm + sign * separation_mm / 2 * np.sin(t)]
        spheres.append(SceneObject(name=name, kind="sphere", pose=pose, albedo=albedo, radius_mm=radius_mm))
    plate = plate_scene(backing_mm).reference_plane
    return Scene(objects=tuple(spheres), reference_plane=plate, name="sphere pair")


class SimBench:
    """What an operator does at the bench during a calibration, done in the simulator
    (`calibration.workflow.Bench`): the target moves through `poses`, the plate stands
    `plate_distance_mm` from the camera on a stage that raises it toward the camera, and
    the artefact is a sphere pair centred on the camera axis in front of the plate."""

    def __init__(self, rig: Rig, target: Target, poses: list[np.ndarray], *, plate_distance_mm: float,
                 sphere_radius_mm: float, sphere_distance_mm: float, artefact_distance_mm: float) -> None:
        self.rig = rig
        self.target = target
        self.poses = poses
        self.plate_distance_mm = plate_distance_mm
        self.artefact = (sphere_radius_mm, sphere_distance_mm, artefact_distance_mm)

    def place_board(self, index: int, needed: list[str]) -> bool:
        if index >= len(self.poses):
            return False
        show(self.rig, Scene(objects=(self.target.scene_object(self.poses[index]),), name=f"target pose {index}"))
        return True

    def place_plate(self, height_mm: float) -> None:
        show(self.rig, plate_scene(self.plate_distance_mm, height_mm))

    def place_artefact(self) -> None:
        radius, distance, depth = self.artefact
        show(self.rig, sphere_pair_scene(radius, distance, depth, self.plate_distance_mm))
