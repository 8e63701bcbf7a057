"""What a scan is registered to, prepared once per model: dense samples, the voxel-grid
cloud, the sphere descriptors per radius, and a ray-casting scene of the CAD model."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from inspection.cad import CadModel
from inspection.measured_cloud import ScanCloud
from inspection.registration.clouds import Samples, voxel_grid
from inspection.registration.rigid import transform_points
from inspection.registration.settings import (
    DEFAULT_REGISTRATION_SETTINGS,
    DEFAULT_TARGET_SETTINGS,
    RegistrationSettings,
    TargetSettings,
)
from inspection.registration.spheres import SphereFeatures, describe, screen, sphere_radii
from inspection.sampling import LabelledCloud, sample_model

if TYPE_CHECKING:
    import open3d as o3d


class ModelTarget:
    """What a scan is registered to, prepared once: dense samples with normals (and CAD
    face labels), the voxel-grid cloud the descriptors are computed on, and the sphere
    descriptors per radius (computed when first needed, then kept)."""

    def __init__(self, points: np.ndarray, normals: np.ndarray, name: str, *, voxel_mm: float | None = None,
                 model: CadModel | None = None, samples: LabelledCloud | None = None,
                 settings: TargetSettings = DEFAULT_TARGET_SETTINGS) -> None:
        self.name = name
        self.model = model
        self.samples = samples  # CAD targets: the labelled samples `points`/`normals` come from
        self.settings = settings
        self.dense = Samples(points, normals)
        self.diagonal_mm = float(np.linalg.norm(np.ptp(points, axis=0)))
        self.voxel_mm = voxel_mm or self.diagonal_mm / settings.voxel_fraction
        self.coarse = Samples(*voxel_grid(points, normals, self.voxel_mm))
        self._features: dict[float, SphereFeatures] = {}
        self._mesh_scene: o3d.t.geometry.RaycastingScene | None = None  # built when first needed (`hidden`)

    @classmethod
    def from_cad(cls, model: CadModel, voxel_mm: float | None = None, seed: int = 0,
                 settings: TargetSettings = DEFAULT_TARGET_SETTINGS) -> ModelTarget:
        voxel = voxel_mm or model.diagonal_mm / settings.voxel_fraction
        s = sample_model(model, voxel / settings.dense_fraction, seed=seed)
        return cls(s.points, s.normals, str(model.path), voxel_mm=voxel, model=model, samples=s, settings=settings)

    @classmethod
    def from_cloud(cls, scan: ScanCloud, voxel_mm: float | None = None,
                   settings: TargetSettings = DEFAULT_TARGET_SETTINGS) -> ModelTarget:
        return cls(scan.points, scan.normals, scan.source, voxel_mm=voxel_mm, settings=settings)

    def describe(self, cloud: Samples, idx: np.ndarray, radius: float,
                 descriptors: tuple[str, ...]) -> dict[str, np.ndarray]:
        """Descriptors of spheres of `cloud` (a scan's or this model's) as this target's are made."""
        return describe(cloud, idx, radius, descriptors, self.settings.descriptor_nn)

    def descriptor_cloud(self, points: np.ndarray, normals: np.ndarray, radius: float) -> Samples:
        """The grid (`radius` / `descriptor_fraction`) that descriptors of `radius` are computed on."""
        return Samples(*voxel_grid(points, normals, radius / self.settings.descriptor_fraction))

    def features(self, radius: float, descriptors: tuple[str, ...]) -> SphereFeatures:
        """Sphere centres every radius/4 over the whole model and their descriptors."""
        f = self._features.get(radius)
        if f is None or any(d not in f.descriptors for d in descriptors):
            cloud = self.descriptor_cloud(self.coarse.points, self.coarse.normals, radius)
            centres, _ = voxel_grid(cloud.points, cloud.normals, radius / 4.0)
            _, idx = cloud.tree.query(centres)
            idx = screen(cloud, np.unique(idx), radius)
            f = SphereFeatures(cloud.points[idx], self.describe(cloud, idx, radius, descriptors))
            self._features[radius] = f
        return f

    def prepare(self, scan: ScanCloud, settings: RegistrationSettings = DEFAULT_REGISTRATION_SETTINGS) -> None:
        """Compute, ahead of registration, what `register` would compute for a scan like
        `scan` the first time: the sphere descriptors at its RSCS radii (a once-per-model
        cost, kept for every later scan of that size) and the ray-casting scene."""
        pts, _ = voxel_grid(scan.points, scan.normals, self.voxel_mm)
        if settings.coarse != "ndt" and len(pts) >= 50:
            for r in sphere_radii(pts, self.voxel_mm, settings.spheres)[1]:
                self.features(r, settings.descriptors)
        if scan.viewpoint is not None:
            self.hidden_fraction(np.eye(4), scan.points[:1], scan.viewpoint, 1.0)

    def hidden_fraction(self, T: np.ndarray, points: np.ndarray, viewpoint: np.ndarray, tol_mm: float) -> float:
        """Fraction of scan `points` (scan frame) that the model, posed by T (scan ->
        model), would hide from `viewpoint` (`hidden`)."""
        return float(np.mean(self.hidden(T, points, viewpoint, tol_mm)))

    def hidden(self, T: np.ndarray, points: np.ndarray, viewpoint: np.ndarray, tol_mm: float) -> np.ndarray:
        """Which scan `points` (scan frame) the model, posed by T (scan -> model), would hide
        from `viewpoint`: a model surface crossed more than `tol_mm` before the point on the
        ray from the sensor (all False for a target without a model)."""
        import open3d as o3d

        if self.model is None:
            return np.zeros(len(points), bool)
        cpu = o3d.core.Device("CPU:0")
        scene = self._mesh_scene
        if scene is None:
            tess = self.model.tessellation
            scene = self._mesh_scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(tess.vertices.astype(np.float32), o3d.core.float32, cpu),
                                o3d.core.Tensor(tess.triangles.astype(np.uint32), o3d.core.uint32, cpu))
        o = transform_points(T, viewpoint[None])[0]
        q = transform_points(T, points)
        d = q - o
        dist = np.linalg.norm(d, axis=1)
        rays = np.concatenate([np.broadcast_to(o, q.shape), d / dist[:, None]], axis=1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays, o3d.core.float32, cpu))["t_hit"].numpy()
        return t < dist - tol_mm
