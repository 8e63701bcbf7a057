"""View-to-view registration where two views only partly overlap.

`refine_pair` starts from a pose (the stage prior) and refines it with the project's
point-to-plane ICP (`inspection.registration.icp`: normal-angle rejection, a partner
distance shrinking from `max_distance_mm` to three robust sigmas of the residuals, but
never below the target's sample spacing): the source view thinned to one measured point
per voxel, against the target view at full density, so a partner lies within the noise of
its surface rather than half a voxel away. The partner distance is a point-to-point one
while the sigmas are of point-to-plane residuals: a right partner lies up to about one
sample spacing beside the source point, so a floor below the spacing (0.12 mm at 1280 x
1024 on the simulated turntable, residual sigmas 0.014 mm) keeps only the points that
happen to lie over a target sample, a fifth of the overlap, and the pose slides (views
45 degrees apart: 0.0135 deg off the truth from an exact start, 0.0044 with the floor).
A point without a partner near enough (the part of a view the other never saw), or whose
normal disagrees (a point of a face the other view did not see, near a view's rim, finding
the neighbouring face), does not pull on the pose.

How well the pose is supported is judged on the overlap only (`PairFit`): `overlap` is the
share of the source's points with a partner within one voxel and agreeing normals;
`rmse_mm` the RMS point-to-plane distance of the partners within three robust sigmas;
`information` the pose's 6x6 information matrix for the pose graph (rotation first, then
translation, as Open3D orders them): sum J^T J over those partners with J = [p x n, n]
(p the moved source point, n the target's normal), over the RMS squared. Two views
sharing only parallel planes and a cylinder (90 degrees apart on a turntable) leave the
turn about the cylinder's axis free, and this information says so, where a point-to-point
information would claim it known and let a slid pair pull the whole graph. Transforms are
4x4 mapping SOURCE points into the TARGET's frame; mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inspection.downsample import voxel_cells
from inspection.registration import Samples, icp, transform_points
from inspection.views.view_clouds import ViewCloud


@dataclass(frozen=True)
class PairSettings:
    """`voxel_mm`: sources are thinned to one point per voxel; ICP partners start within
    `max_distance_mm` (the stage prior's error must be below it) and shrink to no less than
    `min_distance_mm` or, with `spacing_floor`, the target's sample spacing, whichever is
    larger; normals more than `max_normal_deg` apart are no partners."""

    voxel_mm: float = 1.0
    max_distance_mm: float = 2.0
    min_distance_mm: float = 0.02
    max_normal_deg: float = 30.0
    iterations: int = 40
    spacing_floor: bool = True

    def __post_init__(self) -> None:
        if not (0 < self.min_distance_mm < self.max_distance_mm and self.voxel_mm > 0 and self.iterations > 0
                and 0 < self.max_normal_deg < 90):
            raise ValueError(f"pair settings out of range: {self}")


@dataclass(frozen=True, eq=False)
class PairView:
    """A view ready for pairing: `points`, `normals` thinned (a source), `dense` the whole
    view with its KD-tree (a target) and `spacing_mm` its sample spacing."""

    points: np.ndarray
    normals: np.ndarray
    dense: Samples
    spacing_mm: float


@dataclass(frozen=True, eq=False)
class PairFit:
    """A refined pair (see the module docstring): `transform` source -> target."""

    source: int
    target: int
    transform: np.ndarray
    overlap: float
    rmse_mm: float
    information: np.ndarray
    correspondences: int


def thin(points: np.ndarray, voxel_mm: float) -> np.ndarray:
    """Indices of one of the points per voxel (the first in order): measured points, never
    averages across an edge, which would lie off both faces."""
    cell, _ = voxel_cells(points, voxel_mm)
    _, first = np.unique(cell, return_index=True)
    return first


def pair_view(view: ViewCloud, voxel_mm: float) -> PairView:
    keep = thin(view.points, voxel_mm)
    return paired(view.points, view.normals, keep)


def paired(points: np.ndarray, normals: np.ndarray, keep: np.ndarray) -> PairView:
    """A PairView of a cloud whose source points are `keep` (indices)."""
    dense = Samples(points, normals)
    return PairView(points[keep], normals[keep], dense, sample_spacing(dense))


def sample_spacing(samples: Samples, probes: int = 2000) -> float:
    """The median distance from a sample to its nearest neighbour (mm), on up to `probes`
    samples spread through the cloud."""
    at = np.linspace(0, len(samples.points) - 1, min(probes, len(samples.points))).astype(np.int64)
    d, _ = samples.tree.query(samples.points[at], k=2)
    return float(np.median(d[:, 1]))


def refine_pair(source: PairView, target: PairView, init: np.ndarray, settings: PairSettings,
                ids: tuple[int, int] = (0, 1)) -> PairFit:
    """Refine the pose `init` of `source` in `target` (see the module docstring)."""
    spacing = target.spacing_mm if settings.spacing_floor else 0.0
    floor = min(max(settings.min_distance_mm, spacing), settings.max_distance_mm)
    T = icp(source.points, source.normals, target.dense, T=np.asarray(init, float), max_dist=settings.max_distance_mm,
            min_dist=floor, max_normal_deg=settings.max_normal_deg, iterations=settings.iterations, tangential=0.0)
    q = transform_points(T, source.points)
    n = source.normals @ T[:3, :3].T
    d, j = target.dense.tree.query(q, distance_upper_bound=settings.voxel_mm, workers=-1)
    ok = np.isfinite(d)
    j = np.where(ok, j, 0)
    tn = target.dense.normals[j]
    ok &= np.einsum("ij,ij->i", n, tn) > np.cos(np.radians(settings.max_normal_deg))
    r = np.einsum("ij,ij->i", q - target.dense.points[j], tn)
    sigma = 1.4826 * float(np.median(np.abs(r[ok]))) if ok.any() else np.inf
    tight = ok & (np.abs(r) <= max(3.0 * sigma, settings.min_distance_mm))
    rmse = float(np.sqrt(np.mean(r[tight] ** 2))) if tight.any() else np.inf
    info = point_to_plane_information(q[tight], tn[tight], max(rmse, 1e-3))
    return PairFit(ids[0], ids[1], T, float(ok.mean()), rmse, info, int(tight.sum()))


def point_to_plane_information(points: np.ndarray, normals: np.ndarray, sigma_mm: float) -> np.ndarray:
    """6x6 information of a pose from point-to-plane partners (points on the target's
    planes with its normals), residuals of `sigma_mm`: sum J^T J / sigma^2, J = [p x n, n]."""
    J = np.hstack([np.cross(points, normals), normals])
    return J.T @ J / sigma_mm ** 2
