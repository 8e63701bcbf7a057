"""The acceptance-test artefacts in the simulator: scenes of a sphere, a ball bar and a flat
at a position of the measuring volume (`inspection.acceptance.Position`), exact primitives
made to their certificates; the bench that places them for `slscan verify` on a simulated
rig; and quick scans of them for repeat-scan studies (`studies.repeat_scans`).

A ball bar's bar is not modelled: its two spheres float at their certified distance (on
a bench the bar is behind the spheres and its points lie on neither sphere).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from inspection.acceptance import Position
from inspection.artefact_file import ArtefactSet
from scanner.decode import DecodeResult, decode
from scanner.geometry import Pinhole, RigModel
from scanner.patterns import PatternSet
from scanner.rig import Rig
from sim.calibration_bench import show
from sim.render import Renderer, project_points
from sim.scene import Scene, SceneObject


def _translated(pose: np.ndarray, offset: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = offset
    return pose @ T


def artefact_objects(position: Position, artefacts: ArtefactSet) -> tuple[SceneObject, ...]:
    """The artefact of `position` as exact primitives placed at its pose."""
    if position.kind == "sphere":
        s = artefacts.sphere
        assert s is not None
        return (SceneObject("sphere", "sphere", position.pose, s.albedo, radius_mm=s.radius_mm),)
    if position.kind == "ball_bar":
        b = artefacts.ball_bar
        assert b is not None
        return tuple(SceneObject(f"ball_{k}", "sphere",
                                 _translated(position.pose, np.array([sign * b.length_mm / 2, 0, 0])),
                                 b.albedo, radius_mm=b.radius_mm) for k, sign in enumerate((1.0, -1.0)))
    p = artefacts.plane
    assert p is not None
    return (SceneObject("flat", "plane", position.pose, p.albedo, size_mm=tuple(p.size_mm)),)


def artefact_scene(position: Position, artefacts: ArtefactSet) -> Scene:
    """A scene holding only the artefact of `position` (nothing behind it)."""
    return Scene(artefact_objects(position, artefacts), name=position.name)


def bounding_points(objects: tuple[SceneObject, ...]) -> np.ndarray:
    """Points (N, 3) whose projections enclose the objects' images (their box corners)."""
    out = []
    for o in objects:
        lo, hi = o.bounds()
        out.append(np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]))
    return np.concatenate(out)


def cropped_camera(camera: Pinhole, points: np.ndarray, margin_px: int = 6) -> Pinhole:
    """The camera's window (same pixels, same lens) around the images of `points` (N, 3)
    camera frame, `margin_px` wider on each side: a region of interest for quick scans."""
    uv = project_points(camera, points)
    lo = np.clip(np.floor(uv.min(axis=0)) - margin_px, 0, None).astype(int)
    hi = np.minimum(np.ceil(uv.max(axis=0)) + margin_px + 1, [camera.width, camera.height]).astype(int)
    K = camera.K.copy()
    K[0, 2] -= lo[0]
    K[1, 2] -= lo[1]
    return Pinhole(int(hi[0] - lo[0]), int(hi[1] - lo[1]), K, camera.dist)


class SimArtefactBench:
    """Places the artefacts on an open simulated rig for `slscan verify` (the simulator
    knows where they are: nothing to tell an operator)."""

    def __init__(self, rig: Rig, artefacts: ArtefactSet) -> None:
        self.rig = rig
        self.artefacts = artefacts

    def place(self, position: Position) -> None:
        show(self.rig, artefact_scene(position, self.artefacts))


def quick_scan(renderer: Renderer, patterns: PatternSet, gamma: float, exposure_s: float, bit_depth: int,
               rng: np.random.Generator) -> DecodeResult:
    """Render the pattern set (pre-compensated for `gamma`) on `renderer`'s scene with
    fresh noise and decode it: the scan without the acquisition's bookkeeping."""
    p = renderer.model.projector
    frames = np.stack([renderer.render(img, exposure_s, bit_depth, rng) for img in patterns.render(p.width, p.height,
                                                                                                   gamma)])
    return decode(frames, patterns, bit_depth, p.size)


def window_renderer(model: RigModel, objects: tuple[SceneObject, ...], sensor: object, projector_blur_px: float) \
        -> Renderer:
    """A renderer of `objects` on the camera window around them (`cropped_camera`)."""
    cam = cropped_camera(model.camera, bounding_points(objects))
    return Renderer(replace(model, camera=cam), Scene(objects, name="window"), sensor, projector_blur_px)  # type: ignore[arg-type]  # a window scene
