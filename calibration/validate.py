"""Validation of a solved rig on a known artefact: a pair of spheres at a certified
centre distance in front of a flat plate (a ball bar).

The artefact is scanned and triangulated with the calibrated rig. The plate is the largest
plane in the cloud (RANSAC, then least squares); what stands in front of it splits into
connected regions, the two largest being the spheres, each fitted by least squares (centre
and radius free). Reported: the centre distance and its error against the certificate (the
validation error judged against the limit), each sphere's radius error and form RMS, and
the plate's flatness RMS (a wavy plate betrays an uncompensated projector response).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from calibration.errors import CalibrationError
from calibration.fit import fit_sphere, plane_rms
from scanner import schema
from scanner.rig_schema import SpherePairTable

PLANE_TOLERANCE_MM = 1.0  # points this close to the plate belong to it
EDGE_MARGIN_PX = 3  # sphere pixels this close to the silhouette are left out (mixed pixels)
MIN_SPHERE_POINTS = 200


@dataclass(frozen=True)
class Artefact:
    """Two spheres of `radius_mm` (nominal), centres `distance_mm` apart (certified)."""

    radius_mm: float
    distance_mm: float

    @classmethod
    def of(cls, table: SpherePairTable) -> Artefact:
        return cls(table.radius_mm, table.distance_mm)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str | Path = "artefact", prefix: str = "") -> Artefact:
        """From `to_dict` (a capture's manifest); errors name `where` and the key."""
        return cls.of(schema.parse(SpherePairTable, d, where, prefix))

    def to_dict(self) -> dict[str, Any]:
        return {"type": "sphere_pair", "radius_mm": self.radius_mm, "distance_mm": self.distance_mm}


@dataclass(frozen=True)
class Validation:
    """Artefact measurement (mm): centre distance and its error, radius errors and form RMS
    of the two spheres, flatness RMS of the plate."""

    distance_mm: float
    distance_error_mm: float
    radius_error_mm: tuple[float, float]
    sphere_rms_mm: tuple[float, float]
    plate_rms_mm: float
    points: tuple[int, int]

    @property
    def error_mm(self) -> float:
        """The figure judged against the limit: |centre distance error|."""
        return abs(self.distance_error_mm)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def summary(self) -> str:
        return (f"sphere distance {self.distance_mm:.4f} mm (error {self.distance_error_mm * 1e3:+.1f} um), radius "
                f"errors {self.radius_error_mm[0] * 1e3:+.1f} / {self.radius_error_mm[1] * 1e3:+.1f} um, sphere form "
                f"RMS {self.sphere_rms_mm[0] * 1e3:.1f} / {self.sphere_rms_mm[1] * 1e3:.1f} um, plate flatness RMS "
                f"{self.plate_rms_mm * 1e3:.1f} um")


def plane_ransac(points: np.ndarray, tolerance_mm: float, iterations: int = 200, seed: int = 0) -> np.ndarray:
    """Inlier mask of the plane with the most points within `tolerance_mm`."""
    rng = np.random.default_rng(seed)
    sample = points[rng.choice(len(points), size=min(len(points), 20000), replace=False)]
    triples = rng.integers(0, len(sample), size=(iterations, 3))
    p0, p1, p2 = sample[triples[:, 0]], sample[triples[:, 1]], sample[triples[:, 2]]
    normals = np.cross(p1 - p0, p2 - p0)
    norm = np.linalg.norm(normals, axis=1)
    good = norm > 1e-9
    normals = normals[good] / norm[good, None]
    offsets = -np.einsum("ij,ij->i", normals, p0[good])
    counts = (np.abs(sample @ normals.T + offsets) < tolerance_mm).sum(axis=0)
    k = int(np.argmax(counts))
    return np.abs(points @ normals[k] + offsets[k]) < tolerance_mm


def measure_sphere_pair(points: np.ndarray, artefact: Artefact) -> Validation:
    """Measure the artefact in an organised cloud `points` (H, W, 3), NaN where invalid."""
    valid = np.isfinite(points).all(axis=2)
    pts = points[valid].astype(np.float64)
    if len(pts) < 3 * MIN_SPHERE_POINTS:
        raise CalibrationError(f"validation: only {len(pts)} points in the artefact scan; is the artefact in view?")
    on_plate = plane_ransac(pts, PLANE_TOLERANCE_MM)
    plate_rms = plane_rms(pts[on_plate])
    front = np.zeros(valid.shape, dtype=np.uint8)
    front[valid] = ~on_plate
    front = cv2.erode(front, np.ones((2 * EDGE_MARGIN_PX + 1,) * 2, np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(front, connectivity=8)
    order = np.argsort(stats[1:, cv2.CC_STAT_AREA])[::-1][:2] + 1
    if n < 3 or stats[order[-1], cv2.CC_STAT_AREA] < MIN_SPHERE_POINTS:
        raise CalibrationError(f"validation: two spheres of {MIN_SPHERE_POINTS}+ points in front of the plate were "
                               f"not found ({n - 1} region(s)); place the sphere pair in view, in front of a plate")
    fits = [(*fit_sphere(points[labels == k].astype(np.float64)), int(stats[k, cv2.CC_STAT_AREA])) for k in order]
    fits.sort(key=lambda f: f[0][0])  # left, right
    (c1, r1, e1, n1), (c2, r2, e2, n2) = fits
    dist = float(np.linalg.norm(c2 - c1))
    return Validation(dist, dist - artefact.distance_mm, (r1 - artefact.radius_mm, r2 - artefact.radius_mm), (e1, e2),
                      plate_rms, (n1, n2))
