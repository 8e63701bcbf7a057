"""Part files: the thin flat parts `slscan pose` finds in a bin, as a part file describes them.

  - `TabPart`: a parametric thin sheet-metal part like paper 001's nickel tab: a strip
    with one rounded end, a chamfered square end, a tongue on one side, a notch on the
    other and a hole near the rounded end; the outline is chiral (no rotation maps the
    part onto its mirror image), so front and back are distinguishable. Part frame (mm):
    the outline in xy, the back face on z = 0, the front face on z = thickness.
  - part files (`config/parts/nickel_tab.toml`): `PartFile`, a `[part]` table with the
    outline parameters of `TabPart` and, optionally, where a robot grips it
    (`grip_point_mm`, in-plane part coordinates) and from which direction (`approach`);
    `load_part_file` reads one.

The simulator drops the same parts into its bins (`sim.bins`). Units: mm.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import model_validator
from scipy.spatial import Delaunay

from scanner import schema
from scanner.errors import ConfigError


@dataclass(frozen=True)
class TabPart:
    """Outline parameters (mm) of the thin part; see the module docstring."""

    length_mm: float = 24.0        # square end to the centre of the rounded end
    width_mm: float = 8.0
    thickness_mm: float = 0.25
    tongue_mm: tuple[float, float, float] = (3.0, 6.0, 4.0)   # start x, width, depth (below y = 0)
    notch_mm: tuple[float, float, float] = (14.0, 3.0, 2.0)   # centre x, width, depth (from y = width)
    chamfer_mm: float = 2.0        # at the corner (0, width)
    hole_radius_mm: float = 1.5    # centred on the rounded end's centre
    mesh_step_mm: float = 0.5      # spacing of the mesh vertices (boundary and face grid)

    def __post_init__(self) -> None:
        t0, tw, td = self.tongue_mm
        nc, nw, nd = self.notch_mm
        ok = (self.length_mm > 0 and self.width_mm > 0 and 0 < self.thickness_mm < self.width_mm
              and t0 > 0 and t0 + tw < self.length_mm and td > 0 and 0 < nd < self.width_mm / 2
              and t0 + tw < nc - nw / 2 and nc + nw / 2 < self.length_mm and 0 <= self.chamfer_mm < t0
              and 0 <= self.hole_radius_mm < self.width_mm / 2 - self.mesh_step_mm and self.mesh_step_mm > 0)
        if not ok:
            raise ValueError(f"inconsistent tab part parameters: {self}")

    def outline(self) -> np.ndarray:
        """The outer boundary (K, 2), counter-clockwise, densified to `mesh_step_mm`."""
        L, W, c = self.length_mm, self.width_mm, self.chamfer_mm
        t0, tw, td = self.tongue_mm
        nc, nw, nd = self.notch_mm
        arc = np.linspace(-np.pi / 2, np.pi / 2, max(8, int(np.pi * W / 2 / self.mesh_step_mm)))
        corners = [(0.0, 0.0), (t0, 0.0), (t0, -td), (t0 + tw, -td), (t0 + tw, 0.0), (L, 0.0)]
        corners += [(L + W / 2 * np.cos(a), W / 2 + W / 2 * np.sin(a)) for a in arc[1:-1]]
        corners += [(L, W), (nc + nw / 2, W), (nc, W - nd), (nc - nw / 2, W), (c, W), (0.0, W - c)]
        return _densify(np.array(corners), self.mesh_step_mm)

    def hole(self) -> np.ndarray:
        """The hole's boundary (K, 2), clockwise."""
        n = max(8, int(2 * np.pi * self.hole_radius_mm / self.mesh_step_mm))
        a = -np.linspace(0, 2 * np.pi, n, endpoint=False)
        return np.stack([self.length_mm + self.hole_radius_mm * np.cos(a),
                         self.width_mm / 2 + self.hole_radius_mm * np.sin(a)], axis=1)

    def area_mm2(self) -> float:
        """Area of one face (outline minus hole)."""
        return _shoelace(self.outline()) + _shoelace(self.hole())

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (N, 3) float64 mm, triangles (M, 3) int32): a closed, outward-oriented
        solid: both faces triangulated over the outline with its hole, and the side walls."""
        outer, hole = self.outline(), self.hole()
        loops = [outer, hole] if self.hole_radius_mm > 0 else [outer]
        boundary = np.concatenate(loops)
        h = self.mesh_step_mm
        lo, hi = outer.min(axis=0), outer.max(axis=0)
        gx, gy = np.meshgrid(np.arange(lo[0] + h / 2, hi[0], h), np.arange(lo[1] + h / 2, hi[1], h))
        grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
        inside = inside_loops(grid, loops) & (distance_to_loops(grid, loops) > 0.4 * h)
        pts2 = np.concatenate([boundary, grid[inside]])
        tri = Delaunay(pts2).simplices
        centroid = pts2[tri].mean(axis=1)
        tri = tri[inside_loops(centroid, loops)]
        # counter-clockwise in xy (viewed from +z)
        a, b, c = (pts2[tri[:, k]] for k in range(3))
        cw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
        tri[cw] = tri[cw][:, [0, 2, 1]]
        n2 = len(pts2)
        t = self.thickness_mm
        vertices = np.concatenate([np.c_[pts2, np.zeros(n2)], np.c_[pts2, np.full(n2, t)]])
        faces = [tri[:, [0, 2, 1]], tri + n2]   # back face looks along -z, front face along +z
        start = 0
        for loop in loops:
            k = len(loop)
            i = start + np.arange(k)
            j = start + (np.arange(k) + 1) % k
            # walls: outward for a counter-clockwise outer loop and a clockwise hole
            faces += [np.stack([i, j, j + n2], axis=1), np.stack([i, j + n2, i + n2], axis=1)]
            start += k
        return vertices, np.concatenate(faces).astype(np.int32)


class PartTable(schema.Schema):
    """The `[part]` table of a part file: `kind = "tab"` (the only kind: a TabPart outline),
    its `name`, any TabPart parameter (left out: TabPart's default), and optionally where
    a robot grips it: `grip_point_mm` [x, y] in the part's outline plane (the point on
    whichever face is up) and `approach` [x, y, z], the direction (part frame, from the
    part toward the gripper) to come from when the front face is up (mirrored through the
    part's mid-plane, z negated, when the back is up; default the up face's normal)."""

    kind: Literal["tab"]
    name: schema.Str | None = None
    length_mm: schema.PositiveFloat | None = None
    width_mm: schema.PositiveFloat | None = None
    thickness_mm: schema.PositiveFloat | None = None
    tongue_mm: schema.Vector3 | None = None
    notch_mm: schema.Vector3 | None = None
    chamfer_mm: schema.NonNegativeFloat | None = None
    hole_radius_mm: schema.NonNegativeFloat | None = None
    mesh_step_mm: schema.PositiveFloat | None = None
    grip_point_mm: schema.Vector2 | None = None
    approach: schema.Vector3 | None = None

    @model_validator(mode="after")
    def _approach_is_a_direction(self) -> PartTable:
        if self.approach is not None and not (np.linalg.norm(self.approach) > 0 and self.approach[2] > 0):
            raise ValueError(f"approach {self.approach} must point away from the front face (z > 0)")
        return self


class PartFile(schema.Schema):
    """A part file (config/parts/nickel_tab.toml): one `[part]` table."""

    part: PartTable


@dataclass(frozen=True)
class PartSpec:
    """A part file read: the outline, its name, and the optional grip point (x, y mm, part
    frame) and unit approach direction for the front face up (part frame)."""

    part: TabPart
    name: str
    grip_point_mm: tuple[float, float] | None = None
    approach: tuple[float, float, float] | None = None


def load_part_file(path: Path) -> PartSpec:
    """The part file `path` validated (one ConfigError naming the file and key otherwise);
    the grip point must lie on the part (inside its outline, off its hole)."""
    path = Path(path)
    table = schema.load(PartFile, path).part
    params = {f.name: getattr(table, f.name) for f in fields(TabPart) if getattr(table, f.name) is not None}
    try:
        part = tab_part(params)
    except ValueError as exc:
        raise ConfigError(path, "part", str(exc)) from None
    grip = table.grip_point_mm
    if grip is not None and not inside_loops(np.array([grip]), outline_loops(part))[0]:
        raise ConfigError(path, "part.grip_point_mm", f"{grip} is not on the part (outside its outline or in its hole)")
    approach = None
    if table.approach is not None:
        a = np.asarray(table.approach, dtype=np.float64)
        approach = tuple(float(x) for x in a / np.linalg.norm(a))
    return PartSpec(part, table.name or path.stem, tuple(grip) if grip else None, approach)  # type: ignore[arg-type]  # 2-/3-tuples by the schema


def outline_loops(part: TabPart) -> list[np.ndarray]:
    """The part's outline and, if it has one, its hole."""
    return [part.outline(), part.hole()] if part.hole_radius_mm > 0 else [part.outline()]


def _densify(corners: np.ndarray, step: float) -> np.ndarray:
    """A closed polygon with extra vertices so no edge is longer than `step`."""
    out = []
    for p, q in zip(corners, np.roll(corners, -1, axis=0)):
        n = max(1, int(np.ceil(np.linalg.norm(q - p) / step)))
        out.append(p + (q - p) * (np.arange(n) / n)[:, None])
    return np.concatenate(out)


def _shoelace(loop: np.ndarray) -> float:
    x, y = loop[:, 0], loop[:, 1]
    return float(0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def inside_loops(points: np.ndarray, loops: list[np.ndarray]) -> np.ndarray:
    """Even-odd rule over all loops (an outline and its holes)."""
    odd = np.zeros(len(points), dtype=bool)
    x, y = points[:, 0:1], points[:, 1:2]
    for loop in loops:
        p, q = loop, np.roll(loop, -1, axis=0)
        crosses = (p[:, 1] > y) != (q[:, 1] > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = p[:, 0] + (y - p[:, 1]) * (q[:, 0] - p[:, 0]) / (q[:, 1] - p[:, 1])
        odd ^= (crosses & (x < xs)).sum(axis=1) % 2 == 1
    return odd


def distance_to_loops(points: np.ndarray, loops: list[np.ndarray]) -> np.ndarray:
    """Distance from each point to the nearest boundary segment."""
    best = np.full(len(points), np.inf)
    for loop in loops:
        p, q = loop, np.roll(loop, -1, axis=0)
        d = q - p
        t = np.clip(((points[:, None, :] - p) * d).sum(-1) / (d * d).sum(-1), 0, 1)
        best = np.minimum(best, np.linalg.norm(points[:, None, :] - (p + t[..., None] * d), axis=-1).min(axis=1))
    return best


def tab_part(params: Mapping[str, object]) -> TabPart:
    """A TabPart from its parameters as a file holds them (lists for the tuples)."""
    return TabPart(**{k: tuple(v) if isinstance(v, list) else v for k, v in params.items()})  # type: ignore[arg-type]  # the file's schema types
