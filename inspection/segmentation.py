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
from inspection.downsample import first_minimum_per_run
from inspection.errors import CadError
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


def by_face(face: np.ndarray, n_faces: int) -> list[tuple[int, np.ndarray]]:
    """(face index, positions in `face` holding it) for each of the `n_faces` faces that
    occurs in `face` (N,), positions ascending: one stable sort instead of a mask per face."""
    order = np.argsort(face, kind="stable")
    bounds = np.searchsorted(face[order], np.arange(n_faces + 1))
    return [(f, order[bounds[f]:bounds[f + 1]]) for f in range(n_faces) if bounds[f + 1] > bounds[f]]


def project_to_faces(model: CadModel, points: np.ndarray,
                     face: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(uv, foot, outward normal, signed distance mm) of each point projected onto the
    exact surface of its face `face[i]` (one vectorised call per face); u and v of a
    trimmed face are wrapped into its UV box (`Face.wrap`)."""
    n = len(points)
    uv, foot, normal, dist = np.zeros((n, 2)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n)
    for index, sel in by_face(face, len(model.faces)):  # one call per face
        f = model.faces[index]
        if f.surface is None:
            raise CadError(model.path, f"face {f.label} has no surface to project onto")
        u, p, nn, d = f.surface.project(points[sel])
        uv[sel], foot[sel], normal[sel], dist[sel] = u if f.domain is None else f.wrap(u), p, f.sense * nn, f.sense * d
    return uv, foot, normal, dist


def inside_faces(model: CadModel, uv: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Whether each (wrapped) parameter point uv (N, 2) lies in the trimmed domain of its
    face `face[i]` (untrimmed faces: everywhere)."""
    inside = np.ones(len(uv), bool)
    for index, sel in by_face(face, len(model.faces)):
        domain = model.faces[index].domain
        if domain is not None:
            inside[sel] = domain.contains(uv[sel])
    return inside


def assign_faces(points: np.ndarray, normals: np.ndarray, model: CadModel, samples: LabelledCloud,
                 *, tree: cKDTree | None = None, max_distance_mm: float = 0.5, max_normal_deg: float = 45.0,
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
    uv, foot, nrm, dist = project_to_faces(model, points[pid], fid)
    good = np.abs(dist) <= max_distance_mm
    good &= np.einsum("ij,ij->i", normals[pid], nrm) >= np.cos(np.radians(max_normal_deg))
    # the trimming test (the library's classifier near a face's edges) only where the others pass
    good[good] = inside_faces(model, uv[good], fid[good])
    # per point, the accepted candidate nearest its surface
    pid, fid, uv, foot, nrm, dist = pid[good], fid[good], uv[good], foot[good], nrm[good], dist[good]
    first = first_minimum_per_run(pid, np.abs(dist))  # per point, least |dist|, the first of equals
    face = np.full(n, UNASSIGNED, np.int32)
    dev = np.full(n, np.nan)
    out_foot, out_n, out_uv = np.full((n, 3), np.nan), np.full((n, 3), np.nan), np.full((n, 2), np.nan)
    p = pid[first]
    face[p], dev[p], out_foot[p], out_n[p], out_uv[p] = fid[first], dist[first], foot[first], nrm[first], uv[first]
    return Segmentation(face, dev, out_foot, out_n, out_uv)
