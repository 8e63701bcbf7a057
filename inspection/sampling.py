"""Labelled point clouds of CAD models: area-uniform points on every face's exact surface.

STEP faces: a Poisson process of density 1/spacing^2 per mm^2 on the surface, made by
drawing parameters uniformly in the face's UV box at the density the largest area
Jacobian needs and keeping each with probability J(u, v)/J_max (so the kept points are
uniform per unit area), then keeping those inside the trimmed face (the library's
classification, `cad._Domain`). Points are evaluated on the exact surface, never on the
triangulation's chords. Mesh faces: uniform on their triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inspection.cad import CadModel, Face, MeshSurface
from inspection.errors import CadError
from inspection.surfaces import Surface


@dataclass(frozen=True, eq=False)
class LabelledCloud:
    """`points` (N, 3) mm, `normals` (N, 3) unit, pointing out of the material, `face`
    (N,) int32 index into the model's faces."""

    points: np.ndarray
    normals: np.ndarray
    face: np.ndarray

    def __len__(self) -> int:
        return len(self.points)

    def subset(self, mask: np.ndarray) -> LabelledCloud:
        return LabelledCloud(self.points[mask], self.normals[mask], self.face[mask])


def _sample_surface_face(face: Face, density: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    surface, domain = face.surface, face.domain
    if not isinstance(surface, Surface) or domain is None:
        raise CadError(f"face {face.label}", "not an exact surface with a trimmed domain: cannot sample it as one")
    u0, u1, v0, v1 = face.box
    jmax = surface.max_jacobian(face.box)
    n = rng.poisson((u1 - u0) * (v1 - v0) * jmax * density)
    uv = np.column_stack([rng.uniform(u0, u1, n), rng.uniform(v0, v1, n)])
    p, nrm, jac = surface.evaluate(uv)
    keep = rng.random(n) * jmax < jac
    uv, p, nrm = uv[keep], p[keep], nrm[keep]
    inside = domain.contains(uv)
    return p[inside], face.sense * nrm[inside]


def _sample_mesh_face(face: Face, density: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    ms = face.surface
    if not isinstance(ms, MeshSurface):
        raise CadError(f"face {face.label}", "has no triangles to sample")
    n = rng.poisson(face.area_mm2 * density)
    tri = rng.choice(len(ms.triangles), size=n, p=ms.areas / ms.areas.sum())
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    v = ms.vertices[ms.triangles[tri]]
    p = v[:, 0] + a[:, None] * (v[:, 1] - v[:, 0]) + b[:, None] * (v[:, 2] - v[:, 0])
    return p, ms.normals[tri]


def sample_model(model: CadModel, spacing_mm: float, seed: int = 0, faces: list[int] | None = None) -> LabelledCloud:
    """Area-uniform random points, one per `spacing_mm`^2 of surface on average, on every
    face (or on the faces listed by index), labelled by face, with outward normals."""
    if not spacing_mm > 0:
        raise CadError(model.path, f"sampling spacing must be > 0 mm, got {spacing_mm}")
    rng = np.random.default_rng(seed)
    density = 1.0 / spacing_mm ** 2
    pts, nrm, lab = [], [], []
    for face in (model.faces if faces is None else [model.faces[i] for i in faces]):
        sample = _sample_surface_face if face.domain is not None else _sample_mesh_face
        p, n = sample(face, density, rng)
        pts.append(p)
        nrm.append(n)
        lab.append(np.full(len(p), face.index, np.int32))
    return LabelledCloud(np.concatenate(pts), np.concatenate(nrm), np.concatenate(lab))


def spacing_for(model: CadModel, n_points: int) -> float:
    """The spacing (mm) that gives about `n_points` points over the whole model."""
    return float(np.sqrt(sum(f.area_mm2 for f in model.faces) / max(n_points, 1)))
