"""Write the bundled demo part: its CAD model `config/parts/demo_part.step` (built with
OpenCASCADE) and its tessellation `config/parts/demo_part.ply` (what the simulator scans).

Part frame (mm, z up, the base on z = 0): a 90 x 60 mm plate with a step (the left
35 mm are 22 mm high, the rest 10 mm high), and on the low section a cylindrical boss
(radius 12 mm, top at z = 35 mm, 1.5 mm top chamfer) with a blind bore (radius 5 mm,
10 mm deep, flat bottom).

The tessellation is OpenCASCADE's own, with a chord tolerance of `CHORD_MM` (0.25 um), so
the simulator scans a surface that departs from the CAD model by far less than the
scanner can see (a coarser mesh would show up as a fake form error on the cylinders);
vertices shared by faces are merged, so the mesh is watertight.

Run:  python -m sim.parts_demo [output.step]      (the .ply is written beside it)
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

OUTPUT = Path(__file__).resolve().parent.parent / "config" / "parts" / "demo_part.ply"
STEP_OUTPUT = OUTPUT.with_suffix(".step")

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
CHORD_MM = 2.5e-4


def build_demo_shape() -> Any:
    """The demo part as an OpenCASCADE solid (TopoDS_Shape)."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Cut, BRepAlgoAPI_Fuse
    from OCP.BRepFilletAPI import BRepFilletAPI_MakeChamfer
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox, BRepPrimAPI_MakeCylinder
    from OCP.GeomAbs import GeomAbs_Circle
    from OCP.gp import gp_Ax2, gp_Dir, gp_Pnt
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    (x0, x1), (y0, y1) = PLATE_X, PLATE_Y
    plate = BRepPrimAPI_MakeBox(gp_Pnt(x0, y0, 0.0), gp_Pnt(x1, y1, HIGH_TOP)).Shape()
    step = BRepPrimAPI_MakeBox(gp_Pnt(STEP_X, y0 - 1, LOW_TOP), gp_Pnt(x1 + 1, y1 + 1, HIGH_TOP + 1)).Shape()
    body = BRepAlgoAPI_Cut(plate, step).Shape()
    axis = gp_Ax2(gp_Pnt(*BOSS_CENTER, LOW_TOP - 1.0), gp_Dir(0, 0, 1))
    boss = BRepPrimAPI_MakeCylinder(axis, BOSS_RADIUS, BOSS_TOP - LOW_TOP + 1.0).Shape()
    body = BRepAlgoAPI_Fuse(body, boss).Shape()
    chamfer = BRepFilletAPI_MakeChamfer(body)
    exp = TopExp_Explorer(body, TopAbs_EDGE)
    while exp.More():
        e = TopoDS.Edge(exp.Current())
        c = BRepAdaptor_Curve(e)
        if c.GetType() == GeomAbs_Circle and abs(c.Circle().Radius() - BOSS_RADIUS) < 1e-9 \
                and abs(c.Circle().Location().Z() - BOSS_TOP) < 1e-9:
            chamfer.Add(CHAMFER, e)
        exp.Next()
    body = chamfer.Shape()
    bore_axis = gp_Ax2(gp_Pnt(*BOSS_CENTER, BOSS_TOP - BORE_DEPTH), gp_Dir(0, 0, 1))
    bore = BRepPrimAPI_MakeCylinder(bore_axis, BORE_RADIUS, BORE_DEPTH + 1.0).Shape()
    return BRepAlgoAPI_Cut(body, bore).Shape()


def write_step(shape: Any, path: Path) -> None:
    """An AP214 STEP file in millimetres."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer

    Interface_Static.SetCVal_s("write.step.schema", "AP214IS")
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    writer = STEPControl_Writer()
    writer.Transfer(shape, STEPControl_AsIs)
    if writer.Write(str(path)) != IFSelect_RetDone:
        raise SystemExit(f"could not write {path}")


def merged_mesh(vertices: np.ndarray, triangles: np.ndarray, decimals: int = 7) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, triangles) with vertices equal to `decimals` places merged (faces of a
    tessellation each carry their own copy of the edge points they share)."""
    key = np.round(vertices, decimals)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep the first occurrence order: deterministic output
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return vertices[first[order]], rank[inverse.ravel()][triangles].astype(np.int32)


def build_demo_part(step_path: Path = STEP_OUTPUT) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float64 mm, triangles (M, 3) int32) of the demo part's STEP model,
    tessellated to `CHORD_MM` by OpenCASCADE."""
    from inspection.cad import load_cad

    tess = load_cad(step_path, deflection_mm=CHORD_MM).tessellation
    return merged_mesh(tess.vertices, tess.triangles)


def main(argv: list[str] | None = None) -> int:
    import open3d as o3d

    argv = sys.argv[1:] if argv is None else argv
    step_path = Path(argv[0]) if argv else STEP_OUTPUT
    step_path.parent.mkdir(parents=True, exist_ok=True)
    write_step(build_demo_shape(), step_path)
    v, t = build_demo_part(step_path)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t))
    if not (mesh.is_watertight() and mesh.is_orientable()):
        raise SystemExit("demo part mesh is not watertight: this is a bug in sim/parts_demo.py")
    mesh.compute_triangle_normals()
    out = step_path.with_suffix(".ply")
    if not o3d.io.write_triangle_mesh(out, mesh, write_ascii=False, write_vertex_normals=False):
        raise SystemExit(f"could not write {out}")
    lo, hi = v.min(axis=0), v.max(axis=0)
    print(f"wrote {step_path} and {out}: {len(v)} vertices, {len(t)} triangles, volume {mesh.get_volume():.1f} mm^3, "
          f"bounds {lo.round(3).tolist()} .. {hi.round(3).tolist()} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
