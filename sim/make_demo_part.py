"""Write the bundled demo part, `config/parts/demo_part.ply`: a machined-looking block.

Part frame (mm, z up, the base on z = 0): a 90 x 60 mm plate with a step (the left
35 mm are 22 mm high, the rest 10 mm high), and on the low section a cylindrical boss
(radius 12 mm, top at z = 35 mm, 1.5 mm top chamfer) with a blind bore (radius 5 mm,
10 mm deep). The mesh is built face by face with shared vertices, so it is watertight
and consistently oriented (outward normals); no CAD kernel is needed.

Run:  python -m sim.make_demo_part [output.ply]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

OUTPUT = Path(__file__).resolve().parent.parent / "config" / "parts" / "demo_part.ply"

PLATE_X = (-45.0, 45.0)
PLATE_Y = (-30.0, 30.0)
LOW_TOP = 10.0
HIGH_TOP = 22.0
STEP_X = -10.0
BOSS_CENTER = (20.0, 0.0)
BOSS_RADIUS = 12.0
BOSS_TOP = 35.0
CHAMFER = 1.5
BORE_RADIUS = 5.0
BORE_DEPTH = 10.0
SEGMENTS = 128


class _MeshBuilder:
    """Vertices shared by exact coordinates; triangles oriented by an outward hint."""

    def __init__(self) -> None:
        self.vertices: list[tuple[float, float, float]] = []
        self.lookup: dict[tuple[float, float, float], int] = {}
        self.triangles: list[tuple[int, int, int]] = []

    def vertex(self, p: object) -> int:
        key = tuple(round(float(c), 9) for c in p)  # type: ignore[union-attr]
        if key not in self.lookup:
            self.lookup[key] = len(self.vertices)
            self.vertices.append(key)
        return self.lookup[key]

    def triangle(self, a: object, b: object, c: object, outward: object) -> None:
        ia, ib, ic = self.vertex(a), self.vertex(b), self.vertex(c)
        pa, pb, pc = (np.array(self.vertices[i]) for i in (ia, ib, ic))
        if np.dot(np.cross(pb - pa, pc - pa), np.asarray(outward, float)) < 0:
            ib, ic = ic, ib
        self.triangles.append((ia, ib, ic))

    def quad(self, a: object, b: object, c: object, d: object, outward: object) -> None:
        """A planar (or nearly) quad a-b-c-d, given in order around its edge."""
        self.triangle(a, b, c, outward)
        self.triangle(a, c, d, outward)


def _ring(radius: float, z: float) -> np.ndarray:
    ang = 2.0 * np.pi * np.arange(SEGMENTS) / SEGMENTS
    return np.stack([BOSS_CENTER[0] + radius * np.cos(ang), BOSS_CENTER[1] + radius * np.sin(ang),
                     np.full(SEGMENTS, z)], axis=1)


def _plate_with_hole(mb: _MeshBuilder, ring: np.ndarray) -> None:
    """The low top face (z = LOW_TOP, x in [STEP_X, x1]) with the boss footprint cut out.

    Each arc edge is fanned to the rectangle corner on its side of the nearest side's
    foot point, and each side closes with one triangle to the arc vertex at that foot;
    every fan segment is visible from its corner because the circle clears every side."""
    x0, x1 = STEP_X, PLATE_X[1]
    y0, y1 = PLATE_Y
    corners = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])  # counter-clockwise from above
    cx, cy = BOSS_CENTER
    z = LOW_TOP
    up = (0.0, 0.0, 1.0)
    corner_ang = np.arctan2(corners[:, 1] - cy, corners[:, 0] - cx)
    # side k runs from corner k to corner k+1; its outward normal angle (foot direction)
    foot_ang = np.array([-np.pi / 2, 0.0, np.pi / 2, np.pi])
    arc_ang = 2.0 * np.pi * np.arange(SEGMENTS) / SEGMENTS

    def ccw_between(a: float, lo: float, hi: float) -> bool:
        return (a - lo) % (2 * np.pi) < (hi - lo) % (2 * np.pi)

    def p3(xy: np.ndarray) -> tuple[float, float, float]:
        return (float(xy[0]), float(xy[1]), z)

    split = []  # per side: index of the arc vertex nearest its foot
    for k in range(4):
        d = np.abs((arc_ang - foot_ang[k] + np.pi) % (2 * np.pi) - np.pi)
        split.append(int(np.argmin(d)))
    for i in range(SEGMENTS):
        j = (i + 1) % SEGMENTS
        mid = arc_ang[i] + np.pi / SEGMENTS
        for k in range(4):
            lo, hi = corner_ang[k], corner_ang[(k + 1) % 4]
            if ccw_between(mid, lo, hi):
                # arc vertices before the split fan to corner k, after it to corner k+1
                before = ccw_between(mid, lo, arc_ang[split[k]])
                c = corners[k] if before else corners[(k + 1) % 4]
                mb.triangle(p3(c), ring[i], ring[j], up)
                break
    for k in range(4):
        mb.triangle(p3(corners[k]), p3(corners[(k + 1) % 4]), ring[split[k]], up)


def build_demo_part() -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float64 mm, triangles (M, 3) int32) of the demo part."""
    mb = _MeshBuilder()
    y0, y1 = PLATE_Y
    # stepped profile in the x-z plane, counter-clockwise (x right, z up)
    prof = [(PLATE_X[0], 0.0), (PLATE_X[1], 0.0), (PLATE_X[1], LOW_TOP), (STEP_X, LOW_TOP),
            (STEP_X, HIGH_TOP), (PLATE_X[0], HIGH_TOP)]
    for y, out in ((y0, (0, -1, 0)), (y1, (0, 1, 0))):  # end caps: fan from the bottom-left corner
        for k in range(1, len(prof) - 1):
            a, b, c = prof[0], prof[k], prof[k + 1]
            mb.triangle((a[0], y, a[1]), (b[0], y, b[1]), (c[0], y, c[1]), out)
    for k in range(len(prof)):
        (ax, az), (bx, bz) = prof[k], prof[(k + 1) % len(prof)]
        if (ax, az, bx, bz) == (PLATE_X[1], LOW_TOP, STEP_X, LOW_TOP):
            continue  # the low top face carries the boss: built below
        out = (bz - az, 0.0, -(bx - ax))
        mb.quad((ax, y0, az), (bx, y0, bz), (bx, y1, bz), (ax, y1, az), out)
    base = _ring(BOSS_RADIUS, LOW_TOP)
    _plate_with_hole(mb, base)
    rings = [base, _ring(BOSS_RADIUS, BOSS_TOP - CHAMFER), _ring(BOSS_RADIUS - CHAMFER, BOSS_TOP),
             _ring(BORE_RADIUS, BOSS_TOP), _ring(BORE_RADIUS, BOSS_TOP - BORE_DEPTH)]
    centre = np.array([*BOSS_CENTER, 0.0])
    for i in range(SEGMENTS):
        j = (i + 1) % SEGMENTS
        radial = (rings[0][i] + rings[0][j]) / 2 - centre
        radial[2] = 0.0
        hints = [radial, radial + np.array([0, 0, np.linalg.norm(radial)]), (0, 0, 1), -radial]
        for r in range(4):
            mb.quad(rings[r][i], rings[r][j], rings[r + 1][j], rings[r + 1][i], hints[r])
        mb.triangle((*BOSS_CENTER, BOSS_TOP - BORE_DEPTH), rings[4][i], rings[4][j], (0, 0, 1))
    return np.array(mb.vertices, dtype=np.float64), np.array(mb.triangles, dtype=np.int32)


def main(argv: list[str] | None = None) -> int:
    import open3d as o3d

    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else OUTPUT
    v, t = build_demo_part()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    if not (mesh.is_watertight() and mesh.is_orientable()):
        raise SystemExit("demo part mesh is not watertight: this is a bug in sim/make_demo_part.py")
    mesh.compute_triangle_normals()
    out.parent.mkdir(parents=True, exist_ok=True)
    if not o3d.io.write_triangle_mesh(str(out), mesh, write_ascii=False, write_vertex_normals=False):
        raise SystemExit(f"could not write {out}")
    lo, hi = v.min(axis=0), v.max(axis=0)
    print(f"wrote {out}: {len(v)} vertices, {len(t)} triangles, volume {mesh.get_volume():.1f} mm^3, "
          f"bounds {lo.round(3).tolist()} .. {hi.round(3).tolist()} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
