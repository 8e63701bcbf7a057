"""Simulated parts for the bench station: the bundled demo part with known imposed defects.

Each `SimPart` is the demo part (`config/parts/demo_part.ply`, written by
`sim.make_demo_part`; part frame: mm, z up, base on z = 0) deformed by exact amounts, with
the true value of every characteristic of the demo part program
(`config/parts/demo_part.toml`, by characteristic name) so the station's verdicts have a
truth:

    high top bow        the high top face (z = 22, 35 x 60 mm) re-meshed on a ~1 mm grid and
                        lifted by b (1 - xi^2)(1 - eta^2) (xi, eta in -1..1 across the face):
                        zero on its edges, b at its centre. Flatness (minimum zone and least
                        squares: the shape is symmetric) = b.
    boss lobing         the boss's side (radius 12 mm) made 3-lobed, r = 12 + a cos(3 theta);
                        its edge rings move within their planes, so the neighbouring faces stay
                        flat. Cylindricity = 2a (the 128-gon's facets add at most 3.6 um).
    high top raised     the whole high section made d taller: the high top's signed deviation
                        from nominal is +d everywhere, so its profile zone (2 max|d|) = 2d while
                        its flatness stays 0.

Characteristics not deformed are true to nominal (value 0, to the tessellation's few um).
Every part lies on the reference plane like the demo scene's part, turned and shifted on
the plane by a small amount of its own (as an operator would place it), so registration
is never given the nominal pose.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cache
from typing import Any

import numpy as np

from .make_demo_part import BOSS_CENTER, BOSS_RADIUS, HIGH_TOP, PLATE_X, PLATE_Y, STEP_X
from .scene import DEFAULT_SCENE, Scene

TRUTH_FILE = "sim_part.json"  # written into every session of a simulated station part
BOW_GRID_MM = 1.0
LOBES = 3

# The characteristics every part's truth covers, by name: the demo part program's, and the
# boss's cylindricity, which a program on a STEP model of the part can check.
CHARACTERISTICS = ("high_top_flatness", "low_top_flatness", "boss_cylindricity", "high_top_profile", "high_top_sq")


@dataclass(frozen=True, eq=False)
class SimPart:
    """A simulated part: `imposed` the true value (mm) of each of `CHARACTERISTICS`;
    `vertices` (N, 3) mm and `triangles` (M, 3) its mesh in the part frame; `turn_rad` and
    `shift_mm` (x, y) how it is placed on the bench relative to the demo scene's pose."""

    name: str
    description: str
    imposed: dict[str, float]
    vertices: np.ndarray = field(repr=False)
    triangles: np.ndarray = field(repr=False)
    turn_rad: float = 0.0
    shift_mm: tuple[float, float] = (0.0, 0.0)

    def scene(self, view: int = 0, views: int = 1) -> Scene:
        """The demo scene with this part in place of the nominal one; view k of n turns it
        a further k/n of a revolution about the camera axis (the operator turns the part)."""
        base = demo_scene()
        part = base.objects[0]
        a = self.turn_rad + 2.0 * np.pi * view / views
        place = np.eye(4)
        place[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
        centre = part.pose[:3, 3]
        place[:3, 3] = centre - place[:3, :3] @ centre + np.array([*self.shift_mm, 0.0])
        obj = replace(part, name=f"demo_part-{self.name}", pose=place @ part.pose, vertices=self.vertices,
                      triangles=self.triangles, source=None)
        return Scene(objects=(obj,), reference_plane=base.reference_plane, name=f"station-{self.name}")

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "description": self.description, "imposed_mm": dict(self.imposed),
                "turn_rad": self.turn_rad, "shift_mm": list(self.shift_mm)}


@cache
def demo_scene() -> Scene:
    """The demo scene (`config/scenes/demo.toml`): the nominal part, its pose, the plane."""
    return Scene.load(DEFAULT_SCENE)


def _nominal_truth() -> dict[str, float]:
    return {name: 0.0 for name in CHARACTERISTICS}


def bow_high_top(vertices: np.ndarray, triangles: np.ndarray, bow_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The high top face replaced by a grid lifted by `bow_mm` at its centre, 0 on its edges."""
    top = np.all(np.isclose(vertices[triangles][:, :, 2], HIGH_TOP), axis=1)
    keep = triangles[~top]
    x0, x1 = PLATE_X[0], STEP_X
    y0, y1 = PLATE_Y
    nx = 2 * int(np.ceil((x1 - x0) / BOW_GRID_MM / 2))  # even: a grid line through the centre
    ny = 2 * int(np.ceil((y1 - y0) / BOW_GRID_MM / 2))
    xi, eta = np.meshgrid(np.linspace(-1.0, 1.0, nx + 1), np.linspace(-1.0, 1.0, ny + 1), indexing="ij")
    x = (x0 + x1) / 2 + xi * (x1 - x0) / 2
    y = (y0 + y1) / 2 + eta * (y1 - y0) / 2
    z = HIGH_TOP + bow_mm * (1 - xi ** 2) * (1 - eta ** 2)
    grid = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    idx = np.arange(len(grid)).reshape(nx + 1, ny + 1) + len(vertices)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    quads = np.stack([a, b, c, d], axis=-1).reshape(-1, 4)
    tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])  # counter-clockwise from above: +z
    return np.concatenate([vertices, grid]), np.concatenate([keep, tris]).astype(np.int32)


def lobe_boss(vertices: np.ndarray, lobe_mm: float) -> np.ndarray:
    """The boss's side made `LOBES`-lobed: radius 12 + lobe_mm cos(LOBES theta)."""
    v = vertices.copy()
    d = v[:, :2] - np.asarray(BOSS_CENTER)
    r = np.hypot(d[:, 0], d[:, 1])
    ring = np.isclose(r, BOSS_RADIUS)
    theta = np.arctan2(d[ring, 1], d[ring, 0])
    v[ring, :2] = np.asarray(BOSS_CENTER) + d[ring] * ((BOSS_RADIUS + lobe_mm * np.cos(LOBES * theta)) / BOSS_RADIUS)[:, None]
    return v


def raise_high_top(vertices: np.ndarray, raise_mm: float) -> np.ndarray:
    """The high section made `raise_mm` taller (every vertex on z = HIGH_TOP moves up)."""
    v = vertices.copy()
    v[np.isclose(v[:, 2], HIGH_TOP), 2] += raise_mm
    return v


def make_part(name: str, bow_mm: float = 0.0, lobe_mm: float = 0.0, raise_mm: float = 0.0,
              turn_rad: float = 0.0, shift_mm: tuple[float, float] = (0.0, 0.0)) -> SimPart:
    """The demo part (the demo scene's mesh, `config/parts/demo_part.ply`) with the given
    defects (mm), and its truth."""
    nominal = demo_scene().objects[0]
    v, t = nominal.vertices, nominal.triangles
    truth = _nominal_truth()
    said = []
    if bow_mm:
        v, t = bow_high_top(v, t, bow_mm)
        truth["high_top_flatness"] = abs(bow_mm)
        said.append(f"high top bowed {bow_mm * 1e3:.0f} um")
    if lobe_mm:
        v = lobe_boss(v, lobe_mm)
        truth["boss_cylindricity"] = 2 * abs(lobe_mm)
        said.append(f"boss {LOBES}-lobed +-{lobe_mm * 1e3:.0f} um")
    if raise_mm:
        v = raise_high_top(v, raise_mm)
        truth["high_top_profile"] = 2 * abs(raise_mm)
        said.append(f"high top raised {raise_mm * 1e3:.0f} um")
    return SimPart(name, ", ".join(said) or "nominal", truth, v, t, turn_rad, shift_mm)


def lineup() -> tuple[SimPart, ...]:
    """The parts that come to the simulated bench, in order (part k is lineup()[k % 6]).
    Against the demo program's tolerances (flatness 0.05 mm, profile zone 0.4 mm) parts 0,
    2 and 4 conform and 1 and 3 do not, each by a wide margin; part 5's lobed boss is out of
    a 0.05 mm cylindricity tolerance, which a program on a STEP model of the part can check."""
    return (
        make_part("nominal", turn_rad=0.00, shift_mm=(0.0, 0.0)),
        make_part("bow150", bow_mm=0.150, turn_rad=0.12, shift_mm=(3.0, -2.0)),
        make_part("raised50", raise_mm=0.050, turn_rad=-0.10, shift_mm=(-2.5, 1.5)),
        make_part("raised500", raise_mm=0.500, turn_rad=-0.15, shift_mm=(-3.0, -2.5)),
        make_part("bow20", bow_mm=0.020, turn_rad=0.09, shift_mm=(2.0, 2.0)),
        make_part("lobe75", lobe_mm=0.075, turn_rad=0.06, shift_mm=(1.5, 3.0)),
    )
