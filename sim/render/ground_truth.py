"""The exact ground truth of what the simulated camera sees, per pixel.

For every camera pixel's hit point (`raytrace`), a ray from the projector centre:
something hit first (more than `OCCLUSION_TOL_MM` before the point) means a cast shadow;
a surface facing away from the projector is an attached shadow; a point outside the
projector image is not lit. The projector pixel (u, v) that lights each camera pixel is
`projector.project` of the point in the projector frame (with the projector's distortion).

Textured planes (`SceneObject.texture`): a camera sees a texture through its defocus and
its pixel areas before the image is sampled, so the texture is blurred on the plane by a
Gaussian of sigma = sqrt(blur^2 + 1/12) camera pixels (the camera blur and a pixel-wide
box), mapped onto the plane with the median pixel footprint of the object, and then
sampled bilinearly where each pixel's ray hits. Edges of the texture therefore land at
sub-pixel positions in the image without aliasing; sampling the sharp texture at pixel
centres and blurring afterwards would not (it makes periodic edge-position errors of
~0.1 px). The camera blur is applied again to the whole image, as to everything else, so a
texture ends up blurred by ~sqrt(2) x the camera blur: a slightly softer board, never a
biased one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from scanner.geometry import Pinhole, RigModel
from scanner.native_threads import native_threads
from sim.render.projection import project_points, projector_field
from sim.render.raytrace import Tracer, camera_rays
from sim.scene import BACKGROUND_ID, REFERENCE_PLANE_ID, Scene, SceneObject

OCCLUSION_TOL_MM = 1e-3  # a projector ray hitting something this much before the point is blocked


@dataclass(frozen=True, eq=False)
class GroundTruth:
    """What the simulated camera sees, per pixel, in the camera frame (mm).

    `points` (H, W, 3) and `depth` (H, W, z) are NaN where nothing is hit; `object_id`
    (H, W) int32 follows `sim.scene` (0 nothing, 1 reference plane, 2.. objects);
    `normal` (H, W, 3) unit, turned toward the camera, NaN where nothing; `proj_uv`
    (H, W, 2) the projector pixel lighting the point (OpenCV pixel coordinates, projector
    distortion included), NaN where the point is not lit; `shadow` (H, W) surface seen by
    the camera but not lit by the projector (cast shadow, facing away, or outside the
    projector image); `occluded`: the cast-shadow part of it (something else is hit first
    on the ray from the projector); `albedo` (0 where nothing); `cos_incidence` of the
    projector light (0 where not lit). `model` is the rig the truth was computed with."""

    model: RigModel
    points: np.ndarray
    depth: np.ndarray
    object_id: np.ndarray
    normal: np.ndarray
    proj_uv: np.ndarray
    shadow: np.ndarray
    occluded: np.ndarray
    albedo: np.ndarray
    cos_incidence: np.ndarray
    names: dict[int, str] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        h, w = self.depth.shape
        return h, w

    @property
    def hit(self) -> np.ndarray:
        """Pixels that see a surface."""
        return self.object_id != BACKGROUND_ID

    @property
    def lit(self) -> np.ndarray:
        """Pixels that see a surface lit by the projector (finite `proj_uv`)."""
        return np.isfinite(self.proj_uv[..., 0])

    def mask(self, obj: int | str) -> np.ndarray:
        """Pixels seeing object `obj` (id or name)."""
        if isinstance(obj, str):
            ids = [i for i, n in self.names.items() if n == obj]
            if not ids:
                raise KeyError(f"no object named {obj!r}; names: {sorted(self.names.values())}")
            obj = ids[0]
        return self.object_id == obj


def texture_albedo(obj: SceneObject, cam_from_obj: np.ndarray, points: np.ndarray, camera: Pinhole,
                   blur_px: float = 0.0) -> np.ndarray:
    """The texture of plane `obj` (N,) at camera-frame `points` on it, averaged over the
    camera pixel's footprint and blurred by `blur_px` (see the module docstring)."""
    tex = obj.texture
    assert tex is not None and obj.size_mm is not None
    R, p = cam_from_obj[:3, :3], cam_from_obj[:3, 3]
    local = (points - p) @ R
    w, h = obj.size_mm
    th, tw = tex.shape
    sx, sy = tw / w, th / h  # texels per mm
    # footprint area of one pixel on the plane: z^2/(fx fy) on the z = const plane through the
    # point, divided by the plane's obliquity to the ray (relative to that z plane)
    ray = points / np.linalg.norm(points, axis=1, keepdims=True)
    area = points[:, 2] ** 2 / (camera.K[0, 0] * camera.K[1, 1]) * np.abs(ray[:, 2]) / np.abs(ray @ R[:, 2])
    sigma_mm = float(np.sqrt(np.median(area) * (1.0 / 12.0 + blur_px ** 2)))
    if sigma_mm * min(sx, sy) > 0.3:
        tex = cv2.GaussianBlur(np.asarray(tex), (0, 0), sigmaX=sigma_mm * sx, sigmaY=sigma_mm * sy,
                               borderType=cv2.BORDER_REPLICATE)
    u = (local[:, 0] + w / 2) * sx - 0.5
    v = (local[:, 1] + h / 2) * sy - 0.5
    return ndimage.map_coordinates(np.asarray(tex, dtype=np.float32), [v, u], order=1, mode="nearest")


def projector_view(model: RigModel, tracer: Tracer, X: np.ndarray, normal: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The projector's view of camera-frame points `X` (N, 3) with unit `normal`s turned
    toward the viewer: (uv (N, 2) projector pixel, NaN where not lit; lit (N,); occluded
    (N,) cast shadow; cos_incidence (N,) of the projector ray)."""
    proj = model.projector
    Cp = model.cam_from_proj[:3, 3]
    dp = X - Cp
    dist = np.linalg.norm(dp, axis=1)
    tp, _, _ = tracer.first_hit(Cp, dp, t_min=1e-9)
    occluded = tp * dist < dist - OCCLUSION_TOL_MM
    cos_inc = -np.einsum("ij,ij->i", normal, dp) / dist
    P = model.proj_from_cam
    Xp = X @ P[:3, :3].T + P[:3, 3]
    lo, hi = projector_field(proj)
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = Xp[:, :2] / Xp[:, 2:3]
    in_front = (Xp[:, 2] > 0) & np.all((xy >= lo) & (xy <= hi), axis=1)
    uv = np.full((len(X), 2), np.nan)
    if in_front.any():
        uv[in_front] = project_points(proj, Xp[in_front])
    in_image = (in_front & (uv[:, 0] >= -0.5) & (uv[:, 0] <= proj.width - 0.5)
                & (uv[:, 1] >= -0.5) & (uv[:, 1] <= proj.height - 0.5))
    lit = in_image & ~occluded & (cos_inc > 0)
    uv[~lit] = np.nan
    return uv, lit, occluded, cos_inc


def compute_ground_truth(model: RigModel, scene: Scene, texture_blur_px: float = 0.0) -> GroundTruth:
    """Ray-cast the scene from the camera and the projector (see the module docstring);
    textures are blurred by `texture_blur_px` (camera pixels) before they are sampled.
    BLAS runs on one thread inside (restored after; a process-wide limit): its products are
    thin, (rays, 3) @ (3, 3), and OpenBLAS threads them badly on busy cores (1.3 M rows:
    0.21 s on two threads against 0.02 s on one, load 4 on 2 cores)."""
    cam = model.camera
    H, W = cam.height, cam.width
    cam_from_world = np.linalg.inv(model.world_from_cam)
    with native_threads(1):
        tracer = Tracer(scene, cam_from_world)
        dirs = camera_rays(cam).reshape(-1, 3)
        t, oid, nrm = tracer.first_hit(np.zeros(3), dirs)
        hit = np.flatnonzero(np.isfinite(t))
        X = dirs[hit] * t[hit, None]
        nh = nrm[hit]
        nh[np.einsum("ij,ij->i", nh, dirs[hit]) > 0] *= -1.0  # toward the camera

        uv, lit, occluded, cos_inc = projector_view(model, tracer, X, nh)

        albedo_of = np.zeros(max([REFERENCE_PLANE_ID, *scene.by_id()]) + 1)
        for i, o in scene.by_id().items():
            albedo_of[i] = o.albedo
        albedo = albedo_of[oid[hit]]
        for i, o in scene.by_id().items():
            on = oid[hit] == i
            if o.texture is not None and on.any():
                albedo[on] *= texture_albedo(o, cam_from_world @ o.pose, X[on], cam, texture_blur_px)

    def full(shape_tail: tuple[int, ...], fill: float, values: np.ndarray, dtype: Any = np.float64) -> np.ndarray:
        a = np.full((H * W, *shape_tail), fill, dtype=dtype)
        a[hit] = values
        a = a.reshape(H, W, *shape_tail)
        a.setflags(write=False)
        return a

    ids = oid.reshape(H, W).copy()
    ids.setflags(write=False)
    return GroundTruth(
        model=model,
        points=full((3,), np.nan, X),
        depth=full((), np.nan, X[:, 2]),
        object_id=ids,
        normal=full((3,), np.nan, nh),
        proj_uv=full((2,), np.nan, uv),
        shadow=full((), False, ~lit, bool),
        occluded=full((), False, occluded, bool),
        albedo=full((), 0.0, albedo),
        cos_incidence=full((), 0.0, np.where(lit, cos_inc, 0.0)),
        names=scene.names,
    )
