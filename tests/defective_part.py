"""The demo part with known form defects, scanned on the simulated rig and inspected, and the
truth of its form figures from the simulator's noise-free surface points (the default run's
test_inspection_sim.py checks one such part, test_inspection_form_acceptance.py several)."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
from form_truth import cylinder_min_zone, inside_margin, plane_frame, plane_min_zone, raster, roughness_sq
from registration_support import STEP
from scipy import ndimage

from inspection.cad import load_cad
from inspection.inspect_scan import inspect
from inspection.measured_cloud import from_organised
from inspection.registration import transform_points
from scanner.patterns import PatternSet
from scanner.pipeline import scan
from scanner.rig import RigConfig, open_rig
from sim.parts import Lobing, PlaneBow, Roughness, Taper, deform, lying_pose, part_scene
from sim.parts_demo import BOSS_CENTER

EDGE_MARGIN_MM = 1.0  # inspection's default edge margin: the truth leaves out the same band
CUTOFF_MM = 8.0  # the form and roughness filters' nesting index (inspection's default)


def defective_run(out: Path, bow: float, lobes: float, taper: float, texture: float, seed: int = 5,
                  turn: float = 0.3) -> SimpleNamespace:
    """The demo part with a bow on the low top, lobing and a taper on the boss and a texture
    on the high top (mm), scanned into session `out` and inspected; with the truth."""
    fine = load_cad(STEP, deflection_mm=2.5e-4)
    low, top, boss = fine.by_label("#158"), fine.by_label("#657"), fine.by_label("#17")
    defects = [PlaneBow(low.index, (17.5, 0.0, 10.0), (0.0, 0.0, 1.0), bow, float(np.hypot(27.5, 30.0)),
                        max_edge_mm=4.0),
               Lobing(boss.index, (20.0, 0.0, 0.0), (0.0, 0.0, 1.0), 1, lobes=3, amplitude_mm=lobes),
               Taper(boss.index, (20.0, 0.0, 22.0), (0.0, 0.0, 1.0), 1, per_mm=taper),
               Roughness(top.index, (-27.5, 0.0, 22.0), (0.0, 0.0, 1.0), texture, (2.0, 4.0), max_edge_mm=0.15)]
    tess = fine.tessellation
    v, t, f = deform(tess.vertices, tess.triangles, tess.face, defects)
    pose = lying_pose(v, turn, 400.0, (0.6, 0.0))  # tilted 34 degrees: the boss's side is in view
    scene, face_of_id = part_scene(v, t, f, pose)
    config = RigConfig.load()
    patterns = PatternSet.load(config.patterns_path)
    with open_rig(config, scene=scene, seed=seed) as rig:
        result = scan(rig, patterns, out)
        gt = rig.extras["ground_truth"]
    model = load_cad(STEP)
    cloud = from_organised(result.cloud, str(out))
    report = inspect(cloud, model)
    return SimpleNamespace(model=model, pose=pose, gt=gt, face_of_id=face_of_id, cloud=cloud, report=report,
                           session=out, defects=defects, valid=result.cloud.valid)


def part_points(run: SimpleNamespace) -> np.ndarray:
    """The simulator's noise-free surface point of every pixel (H, W, 3) in the part frame."""
    return transform_points(np.linalg.inv(run.pose), run.gt.points.reshape(-1, 3)).reshape(run.gt.points.shape)


def measured_region(on: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Pixels (H, W) a face's truth is taken over: `on` (the face's pixels where the scan
    has a point), single-pixel gaps closed, at least the edge margin from the region's
    border (`points` (H, W, 3): the true surface points)."""
    closed = ndimage.binary_closing(on, np.ones((3, 3)), border_value=0) | on
    return inside_margin(closed, points, EDGE_MARGIN_MM) & on


def face_region(run: SimpleNamespace, label: str) -> np.ndarray:
    """The region measured of a face whose pixels the simulator's face ids give."""
    on = (run.face_of_id[run.gt.object_id] == run.model.by_label(label).index) & run.valid
    return measured_region(on, part_points(run))


def true_form(run: SimpleNamespace, label: str) -> SimpleNamespace:
    """The face's figures over the region measured, from the simulator's noise-free surface
    points there: minimum zones by LP on every point (the boss's about its design axis),
    Sq of the imposed defects' analytic heights on a 0.15 mm grid through the Gaussian
    L-filter. (The form filter keeps these defects: bow and taper exactly, 3-lobe lobing on
    the boss, 25 mm long, to 0.2 %.)"""
    face = run.model.by_label(label)
    q = part_points(run)[face_region(run, label)]
    truth = SimpleNamespace(points=len(q), flatness_mz_mm=None, cylindricity_mz_mm=None, sq_mm=None)
    if face.type == "plane":
        truth.flatness_mz_mm = plane_min_zone(q)
        centre, axes = plane_frame(q)
        spacing = 0.15
        mask, cells, _ = raster((q - centre) @ axes[:2].T, spacing)
        at = (centre + cells[..., :1] * axes[0] + cells[..., 1:] * axes[1]).reshape(-1, 3)
        heights = sum((d.height(at) for d in run.defects if d.face == face.index), np.zeros(len(at)))
        truth.sq_mm = roughness_sq(heights.reshape(mask.shape), mask, CUTOFF_MM, spacing)
    elif face.type == "cylinder":
        truth.cylindricity_mz_mm = cylinder_min_zone(q, np.array([*BOSS_CENTER, 0.0]), np.array([0.0, 0.0, 1.0]))
    return truth


def form_row(run: SimpleNamespace, label: str) -> object:
    """The inspection report's form figures of the face `label`."""
    return next(r.form for r in run.report.faces if r.label == label)
