"""STEP-guided segmentation: every measured point (in the model frame, after
registration) is assigned to the CAD face it belongs to, or left unassigned.

A point's candidate faces are those of its nearest dense model samples. For each
candidate the point is projected onto the face's exact surface; the candidate is
accepted when the point lies within `max_distance_mm` of the surface, its normal agrees
with the face's outward normal within `max_normal_deg`, and the foot of the projection
is inside the trimmed face (the library's classification, `cad._Domain`). Of the
accepted candidates the nearest surface wins; a point with none stays unassigned (-1):
noise between faces, spikes, fixtures, or parts of something else.

Signed deviations are along the outward normal: positive where the point lies outside
the material (excess material), negative inside.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from inspection.cad import CadModel
from inspection.sampling import LabelledCloud

UNASSIGNED = -1


@dataclass(frozen=True, eq=False)
class Segmentation:
    """Per point (model frame): `face` index (-1 unassigned), signed `deviation_mm` from
    the assigned face's nominal surface (NaN unassigned), the `foot` point and outward
    `normal` there, and the surface parameters `uv` of the foot."""

    face: np.ndarray
    deviation_mm: np.ndarray
    foot: np.ndarray
    normal: np.ndarray
    uv: np.ndarray

    @property
    def assigned(self) -> np.ndarray:
        return self.face != UNASSIGNED

    def counts(self, n_faces: int) -> np.ndarray:
        return np.bincount(self.face[self.assigned], minlength=n_faces)


def project_to_faces(model: CadModel, points: np.ndarray, face: np.ndarray,
                     check_inside: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(uv, foot, outward normal, signed distance, inside) of each point projected onto
    the exact surface of its face `face[i]` (one vectorised call per face)."""
    n = len(points)
    uv, foot, normal = np.zeros((n, 2)), np.zeros((n, 3)), np.zeros((n, 3))
    dist, inside = np.zeros(n), np.ones(n, bool)
    order = np.argsort(face, kind="stable")
    bounds = np.searchsorted(face[order], np.arange(len(model.faces) + 1))
    for f in model.faces:  # one call per face
        sel = order[bounds[f.index]:bounds[f.index + 1]]
        if not sel.size:
            continue
        u, p, nn, d = f.surface.project(points[sel])  # type: ignore[union-attr]
        if f.domain is not None:
            u = f.wrap(u)
            if check_inside:
                inside[sel] = f.domain.contains(u)
        uv[sel], foot[sel], normal[sel], dist[sel] = u, p, f.sense * nn, f.sense * d
    return uv, foot, normal, dist, inside


def assign_faces(points: np.ndarray, normals: np.ndarray, model: CadModel, samples: LabelledCloud,
                 tree: cKDTree | None = None, max_distance_mm: float = 0.5, max_normal_deg: float = 45.0,
                 k: int = 8) -> Segmentation:
    """Assign each point (N, 3), with its unit normal, to a face of `model` (see the
    module docstring); `samples` are dense labelled samples of the model (and `tree`
    their KD-tree, built if not given)."""
    tree = cKDTree(samples.points) if tree is None else tree
    n = len(points)
    reach = max_distance_mm + 4.0 * float(np.sqrt(sum(f.area_mm2 for f in model.faces) / max(len(samples), 1)))
    d, j = tree.query(points, k=k, distance_upper_bound=reach, workers=-1)
    ok = np.isfinite(d)
    cand = np.where(ok, samples.face[np.where(ok, j, 0)], -1)
    # unique (point, face) candidate pairs, by point then face: each row's k candidates sorted,
    # repeats dropped (a sort of k per row, not of all n * k pairs: ~40x less time than np.unique)
    cand.sort(axis=1)
    keep = cand >= 0
    keep[:, 1:] &= cand[:, 1:] != cand[:, :-1]
    pid, fid = np.nonzero(keep)[0], cand[keep].astype(np.int64)
    uv, foot, nrm, dist, inside = project_to_faces(model, points[pid], fid, check_inside=True)
    good = inside & (np.abs(dist) <= max_distance_mm)
    good &= np.einsum("ij,ij->i", normals[pid], nrm) >= np.cos(np.radians(max_normal_deg))
    # per point, the accepted candidate nearest its surface
    pid, fid, uv, foot, nrm, dist = pid[good], fid[good], uv[good], foot[good], nrm[good], dist[good]
    order = np.lexsort((np.abs(dist), pid))
    first = order[np.r_[True, pid[order][1:] != pid[order][:-1]]] if len(order) else order
    face = np.full(n, UNASSIGNED, np.int32)
    dev = np.full(n, np.nan)
    out_foot, out_n, out_uv = np.full((n, 3), np.nan), np.full((n, 3), np.nan), np.full((n, 2), np.nan)
    p = pid[first]
    face[p], dev[p], out_foot[p], out_n[p], out_uv[p] = fid[first], dist[first], foot[first], nrm[first], uv[first]
    return Segmentation(face, dev, out_foot, out_n, out_uv)
