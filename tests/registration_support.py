"""Scenes the registration tests share: the demo part's STEP file, a plain block's (symmetric:
its half turn fits as well), and simulated views of a model, placed or from a random start;
and one registration and one set of face figures shared by the inspections of one cloud."""

from __future__ import annotations

import hashlib
import pickle
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from inspection import inspect_scan
from inspection.measured_cloud import ScanCloud, make_scan
from inspection.sampling import sample_model
from scanner.config import CONFIG_DIR
from sim.parts import lying_pose
from sim.parts_demo import write_step

STEP = CONFIG_DIR / "parts" / "demo_part.step"  # the demo part's model


_SAMPLES: dict[tuple[Any, ...], Any] = {}  # (model, spacing, seed) -> its samples: a model's are drawn once
_VIEWS: dict[tuple[Any, ...], ScanCloud] = {}  # a view's inputs -> the view: made once per process


def _model_key(model: Any) -> tuple[str, str]:
    """A model by its file and tessellation (a file loaded at another deflection is another key)."""
    tess = model.tessellation
    digest = hashlib.sha256()
    for a in (tess.vertices, tess.triangles, tess.face):
        digest.update(np.ascontiguousarray(a).tobytes())
    return str(model.path), digest.hexdigest()


def virtual_view(model, pose: np.ndarray, noise_mm: float = 0.014, spacing_mm: float = 0.25, seed: int = 0,
                 offsets: dict[str, float] | None = None) -> ScanCloud:
    """The model's surface seen from a camera at the origin (model placed by `pose`, part ->
    camera): visible samples, with noise along the viewing rays; normals estimated.
    `offsets`: faces (by label) moved as a whole along their outward normal (mm). A view
    asked for again (the same model, pose and options; here or in another module of the
    process) is a copy of the one made first (1-3 s a view)."""
    key = (_model_key(model), np.asarray(pose, float).tobytes(), noise_mm, spacing_mm, seed,
           tuple(sorted((offsets or {}).items())))
    if key not in _VIEWS:
        _VIEWS[key] = _render_view(model, pose, noise_mm, spacing_mm, seed, offsets or {})
    view = _VIEWS[key]
    return replace(view, points=view.points.copy(), normals=view.normals.copy())


def _render_view(model: Any, pose: np.ndarray, noise_mm: float, spacing_mm: float, seed: int,
                 offsets: dict[str, float]) -> ScanCloud:
    """`virtual_view`, made."""
    import open3d as o3d

    drawn = (_model_key(model), spacing_mm, seed)
    if drawn not in _SAMPLES:
        _SAMPLES[drawn] = sample_model(model, spacing_mm, seed=seed)
    s = _SAMPLES[drawn]
    points = s.points.copy()
    for label, mm in offsets.items():
        sel = s.face == model.by_label(label).index
        points[sel] += mm * s.normals[sel]
    p = points @ pose[:3, :3].T + pose[:3, 3]
    n = s.normals @ pose[:3, :3].T
    tess = model.tessellation
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((tess.vertices @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)),
                        o3d.core.Tensor(tess.triangles.astype(np.uint32)))
    dist = np.linalg.norm(p, axis=1)
    ray = p / dist[:, None]
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([np.zeros_like(p), ray], 1).astype(np.float32)))
    seen = (hit["t_hit"].numpy() > dist - 0.01) & (np.einsum("ij,ij->i", n, ray) < -0.1)
    rng = np.random.default_rng(seed)
    q = p[seen] + ray[seen] * rng.normal(0, noise_mm, seen.sum())[:, None]
    return make_scan(q, None, "virtual view", np.zeros(3))


def box_step(path: Path) -> Path:
    """A 60 x 40 x 15 mm block written as STEP to `path`."""
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.gp import gp_Pnt

    write_step(BRepPrimAPI_MakeBox(gp_Pnt(-30, -20, 0), gp_Pnt(30, 20, 15)).Shape(), path)
    return path


def moved_view(model: Any, tilt: tuple[float, float], seed: int) -> tuple[Any, np.ndarray]:
    """A view of `model` from a random start: (scan, the true moved-scan -> model pose)."""
    pose = lying_pose(model.tessellation.vertices, 0.4, 400.0, tilt)
    view = virtual_view(model, pose, seed=seed)
    G = np.eye(4)
    G[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    G[:3, 3] = [80.0, -120.0, 60.0]
    moved = ScanCloud(view.points @ G[:3, :3].T + G[:3, 3], view.normals @ G[:3, :3].T, "moved view", G[:3, 3].copy())
    return moved, np.linalg.inv(pose) @ np.linalg.inv(G)


def write_ply(scan: Any, path: Path) -> Path:
    """`scan`'s points and normals as a PLY cloud at `path`."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scan.points))
    pc.normals = o3d.utility.Vector3dVector(scan.normals)
    o3d.io.write_point_cloud(str(path), pc)
    return path


def _digest(*parts: Any) -> str | None:
    """A key of `parts` by their content (pickled: arrays by dtype, shape and bytes); None
    when one cannot be pickled (then nothing is shared). Equal objects may pickle apart
    (a repeated object is pickled once): a key missed, never a wrong one shared."""
    try:
        return hashlib.sha256(pickle.dumps(parts, protocol=pickle.HIGHEST_PROTOCOL)).hexdigest()
    except (pickle.PicklingError, TypeError, AttributeError):
        return None


@contextmanager
def shared_inspections() -> Iterator[None]:
    """Inside, `inspection.inspect_scan.inspect` registers a part cloud once and measures a
    face once: its global registration (no prior) is kept by its inputs (the part's points
    and normals, the target's samples, the settings), and each face's figures
    (`measure_face`) by theirs (the face's surface and every point, noise, pose and setting
    given), and given again to an inspection of the same inputs, e.g. `slscan inspect` of
    one session with other tolerances (the verdicts are still decided each time). Both are
    repeatable bit for bit (test_inspection_sim.py's inspections of one session: the same
    transform, fitness, covariance and free motions, and the same inspection.json). A
    session's noise model (`session_uncertainty`, its frames decoded again) is kept by the
    session (its folder and id: a recorded session is never rewritten)."""
    from slscan import measurement_model

    register, measure = inspect_scan.register_with_prior, inspect_scan.measure_face
    uncertainty = measurement_model.session_uncertainty
    registered: dict[tuple[str, str], Any] = {}
    measured: dict[str, Any] = {}
    modelled: dict[tuple[str, str], Any] = {}

    def register_once(scan: ScanCloud, target: Any, prior: Any, settings: Any) -> Any:
        if prior is not None:
            return register(scan, target, prior, settings)
        digest = hashlib.sha256()
        for a in (scan.points, scan.normals, target.dense.points, target.dense.normals):
            digest.update(np.ascontiguousarray(a).tobytes())
        key = (digest.hexdigest(), repr(settings))
        if key not in registered:
            registered[key] = register(scan, target, prior, settings)
        return registered[key]

    def measure_once(face: Any, *args: Any, **kw: Any) -> Any:
        key = _digest(face.index, face.step_id, face.type, face.sense, face.box, face.surface, args, kw)
        if key is None:
            return measure(face, *args, **kw)
        if key not in measured:
            measured[key] = measure(face, *args, **kw)
        return measured[key]

    def uncertainty_once(session: Any, decoded: Any = None) -> Any:
        if decoded is not None:
            return uncertainty(session, decoded)
        key = (str(Path(session.root).resolve()), session.id)
        if key not in modelled:
            modelled[key] = uncertainty(session)
        return modelled[key]

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(inspect_scan, "register_with_prior", register_once)
        patch.setattr(inspect_scan, "measure_face", measure_once)
        patch.setattr(measurement_model, "session_uncertainty", uncertainty_once)
        yield
