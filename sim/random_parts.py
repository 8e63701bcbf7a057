"""Random prismatic test parts, placed at random on the simulated table and scanned, so that
registration is measured on parts nobody chose (issue 26).

A part is a plate (largest side 20-400 mm, log-uniform) built by OpenCASCADE booleans: its
vertical corners filleted or chamfered at random, then 2-5 features at random places (a
rectangular pocket, a round or square boss, a through or blind hole, a step cut off one end,
a chamfered top edge), each feature kept only when its boolean gives a valid solid. Features
at random places make a generic part asymmetric; nothing here forces it, so a rare part may
be (nearly) symmetric, and registration must then say so.

A placement lays the part on its base on the table, turned at random about the vertical, put
anywhere in the field, and views it from a camera tilted 10-35 degrees off the table's normal.
The bench rig (`config/rigs/sim_bench.toml`, ~160 x 128 mm at 400 mm) is scaled about its
camera (working distance and projector position times `rig_scale`) so that the part fills
55-80 % of the field's height: a bigger part is scanned by a bigger rig, whose depth noise
grows with it. The scan is the scanner's whole cloud, table in view (`ScanCloud` from the
organised cloud the decoder writes), with the simulator's true camera -> part pose.

Everything is seeded: `random_part(seed)`, `random_placement(part, seed)`, the scan's noise
by its own seed; a measurement draws new seeds each time and prints them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

SIZE_RANGE_MM = (20.0, 400.0)  # the plate's longest side, drawn log-uniform
FEATURE_KINDS = ("pocket", "boss", "square boss", "hole", "blind hole", "step", "top chamfer")
BENCH_FIELD_HEIGHT_MM = 128.0  # the bench rig's field height at its working distance (400 mm)
FILL = (0.55, 0.8)  # the part's extent over the field's height


@dataclass(frozen=True)
class RandomPart:
    """A generated part: `shape` the OpenCASCADE solid (part frame: base on z = 0, the plate
    over x in [0, length], y in [0, width]); `features` what was built, for people."""

    seed: int
    length_mm: float
    width_mm: float
    height_mm: float
    features: tuple[str, ...]
    shape: Any = field(repr=False, compare=False)

    @property
    def diagonal_mm(self) -> float:
        return math.sqrt(self.length_mm ** 2 + self.width_mm ** 2 + self.height_mm ** 2)

    def write(self, path: str | Path) -> Path:
        """The part as an AP214 STEP file in millimetres (the writer's statistics not printed)."""
        from OCP.Message import Message, Message_Gravity

        from sim.parts_demo import write_step

        for printer in Message.DefaultMessenger_s().Printers():
            printer.SetTraceLevel(Message_Gravity.Message_Fail)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_step(self.shape, path)
        return path


def _valid(shape: Any) -> bool:
    from OCP.BRepCheck import BRepCheck_Analyzer

    return shape is not None and not shape.IsNull() and BRepCheck_Analyzer(shape).IsValid()


def _edges(shape: Any) -> list[Any]:
    """Each edge of `shape` once (an explorer visits an edge once per face it bounds)."""
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    out: list[Any] = []
    exp = TopExp_Explorer(shape, TopAbs_EDGE)
    while exp.More():  # a plate's few dozen edges
        e = TopoDS.Edge(exp.Current())
        if not any(e.IsSame(o) for o in out):
            out.append(e)
        exp.Next()
    return out


def _edge_ends(edge: Any) -> tuple[np.ndarray, np.ndarray]:
    from OCP.BRep import BRep_Tool
    from OCP.TopExp import TopExp

    a, b = TopExp.FirstVertex_s(edge), TopExp.LastVertex_s(edge)
    pa, pb = BRep_Tool.Pnt_s(a), BRep_Tool.Pnt_s(b)
    return np.array([pa.X(), pa.Y(), pa.Z()]), np.array([pb.X(), pb.Y(), pb.Z()])


def _round_corners(shape: Any, rng: np.random.Generator, size: float) -> tuple[Any, str | None]:
    """Some vertical corner edges of the plate filleted or chamfered (one radius)."""
    from OCP.BRepFilletAPI import BRepFilletAPI_MakeChamfer, BRepFilletAPI_MakeFillet

    def is_vertical(edge: Any) -> bool:
        a, b = _edge_ends(edge)
        return bool(np.allclose(a[:2], b[:2]))

    vertical = [e for e in _edges(shape) if is_vertical(e)]
    chosen = [e for e in vertical if rng.random() < 0.6]
    if not chosen:
        return shape, None
    kind = "fillet" if rng.random() < 0.6 else "chamfer"
    r = float(rng.uniform(0.04, 0.15) * size)
    maker = BRepFilletAPI_MakeFillet(shape) if kind == "fillet" else BRepFilletAPI_MakeChamfer(shape)
    for e in chosen:
        maker.Add(r, e)
    maker.Build()
    if not maker.IsDone() or not _valid(maker.Shape()):
        return shape, None
    return maker.Shape(), f"{len(chosen)} corner {kind}(s) r {r:.2f} mm"


def _top_chamfer(shape: Any, rng: np.random.Generator, height: float, size: float) -> tuple[Any, str | None]:
    """One straight outer edge of the plate's top chamfered."""
    from OCP.BRepFilletAPI import BRepFilletAPI_MakeChamfer

    top = [e for e in _edges(shape) if all(abs(p[2] - height) < 1e-6 for p in _edge_ends(e))
           and np.linalg.norm(np.subtract(*_edge_ends(e))) > 0.3 * size]
    if not top:
        return shape, None
    e = top[int(rng.integers(len(top)))]
    d = float(rng.uniform(0.1, 0.35) * height)
    maker = BRepFilletAPI_MakeChamfer(shape)
    maker.Add(d, e)
    maker.Build()
    if not maker.IsDone() or not _valid(maker.Shape()):
        return shape, None
    return maker.Shape(), f"top edge chamfer {d:.2f} mm"


def _feature(kind: str, rng: np.random.Generator, L: float, W: float, H: float) -> tuple[Any, bool, str]:
    """(tool solid, cut (else fuse), description) of one feature at a random place."""
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox, BRepPrimAPI_MakeCylinder
    from OCP.gp import gp_Ax2, gp_Dir, gp_Pnt

    small = min(L, W)
    if kind in ("hole", "blind hole"):
        r = float(rng.uniform(0.04, 0.14) * small)
        x, y = rng.uniform(r + 0.05 * small, L - r - 0.05 * small), rng.uniform(r + 0.05 * small, W - r - 0.05 * small)
        depth = H + 2.0 if kind == "hole" else float(rng.uniform(0.3, 0.8) * H)
        z0 = -1.0 if kind == "hole" else H - depth
        tool = BRepPrimAPI_MakeCylinder(gp_Ax2(gp_Pnt(x, y, z0), gp_Dir(0, 0, 1)), r, depth + 1.0).Shape()
        return tool, True, f"{kind} r {r:.2f} at ({x:.1f}, {y:.1f}), depth {min(depth, H):.2f}"
    if kind == "boss":
        r = float(rng.uniform(0.05, 0.16) * small)
        x, y = rng.uniform(r, L - r), rng.uniform(r, W - r)
        h = float(rng.uniform(0.2, 0.9) * H)
        tool = BRepPrimAPI_MakeCylinder(gp_Ax2(gp_Pnt(x, y, H - 0.5), gp_Dir(0, 0, 1)), r, h + 0.5).Shape()
        return tool, False, f"boss r {r:.2f} h {h:.2f} at ({x:.1f}, {y:.1f})"
    if kind == "square boss":
        a, b = rng.uniform(0.08, 0.25, 2) * np.array([L, W])
        x, y = rng.uniform(0, L - a), rng.uniform(0, W - b)
        h = float(rng.uniform(0.2, 0.9) * H)
        tool = BRepPrimAPI_MakeBox(gp_Pnt(x, y, H - 0.5), gp_Pnt(x + a, y + b, H + h)).Shape()
        return tool, False, f"square boss {a:.1f} x {b:.1f} h {h:.2f} at ({x:.1f}, {y:.1f})"
    if kind == "pocket":
        a, b = rng.uniform(0.12, 0.4, 2) * np.array([L, W])
        x, y = rng.uniform(0.05 * L, 0.95 * L - a), rng.uniform(0.05 * W, 0.95 * W - b)
        d = float(rng.uniform(0.2, 0.65) * H)
        tool = BRepPrimAPI_MakeBox(gp_Pnt(x, y, H - d), gp_Pnt(x + a, y + b, H + 1.0)).Shape()
        return tool, True, f"pocket {a:.1f} x {b:.1f} depth {d:.2f} at ({x:.1f}, {y:.1f})"
    # a step: one end of the plate cut down
    a = float(rng.uniform(0.15, 0.4) * L)
    d = float(rng.uniform(0.25, 0.6) * H)
    x0 = -1.0 if rng.random() < 0.5 else L - a
    tool = BRepPrimAPI_MakeBox(gp_Pnt(x0, -1.0, H - d), gp_Pnt(x0 + a + 1.0, W + 1.0, H + 1.0)).Shape()
    return tool, True, f"step {a:.1f} long, {d:.2f} deep at the {'left' if x0 < 0 else 'right'} end"


def random_part(seed: int) -> RandomPart:
    """A random prismatic part (module docstring), the same for the same seed."""
    from OCP.BRepAlgoAPI import BRepAlgoAPI_Cut, BRepAlgoAPI_Fuse
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.gp import gp_Pnt

    rng = np.random.default_rng(seed)
    L = float(np.exp(rng.uniform(*np.log(SIZE_RANGE_MM))))
    W = float(L * rng.uniform(0.45, 0.95))
    H = float(max(3.0, min(L, W) * rng.uniform(0.12, 0.45)))
    shape = BRepPrimAPI_MakeBox(gp_Pnt(0, 0, 0), gp_Pnt(L, W, H)).Shape()
    built = []
    shape, what = _round_corners(shape, rng, min(L, W))
    if what:
        built.append(what)
    if rng.random() < 0.4:
        shape, what = _top_chamfer(shape, rng, H, min(L, W))
        if what:
            built.append(what)
    kinds = [k for k in FEATURE_KINDS if k != "top chamfer"]
    for _ in range(int(rng.integers(2, 6))):
        kind = kinds[int(rng.integers(len(kinds)))]
        tool, cut, what = _feature(kind, rng, L, W, H)
        op = BRepAlgoAPI_Cut(shape, tool) if cut else BRepAlgoAPI_Fuse(shape, tool)
        if op.IsDone() and _valid(op.Shape()):
            shape = op.Shape()
            built.append(what)
    return RandomPart(seed, L, W, H, tuple(built), shape)


@dataclass(frozen=True)
class Placement:
    """Where a part lies in front of the rig: turned by `turn_rad` about the table's
    normal, the camera tilted by `tilt_rad` (about its x and y axes), the part's centre
    `offset_mm` (x, y in the camera frame) off the camera axis, the rig scaled by
    `rig_scale` (working distance 400 mm x it)."""

    seed: int
    turn_rad: float
    tilt_rad: tuple[float, float]
    offset_mm: tuple[float, float]
    rig_scale: float

    @property
    def distance_mm(self) -> float:
        return 400.0 * self.rig_scale


def random_placement(part: RandomPart, seed: int) -> Placement:
    """A random placement of `part` (module docstring): the rig scaled so the part fills
    `FILL` of the field's height, the part anywhere it stays in the field."""
    return placement_for(math.hypot(part.length_mm, part.width_mm), seed)


def placement_for(extent: float, seed: int) -> Placement:
    """A random placement of a part `extent` mm across its footprint (`random_placement`)."""
    rng = np.random.default_rng(seed)
    scale = max(0.5, extent / (BENCH_FIELD_HEIGHT_MM * rng.uniform(*FILL)))
    tilt = np.radians(rng.uniform(10.0, 35.0))
    a = rng.uniform(0.0, 2.0 * np.pi)
    room = np.array([160.0, 128.0]) * scale - extent  # the field's width and height less the part
    offset = rng.uniform(-0.4, 0.4, 2) * np.maximum(room, 0.0)
    return Placement(seed, float(rng.uniform(0.0, 2.0 * np.pi)), (float(tilt * np.cos(a)), float(tilt * np.sin(a))),
                     (float(offset[0]), float(offset[1])), float(scale))


def scaled_rig(config: Any, scale: float) -> Any:
    """`config` (a `scanner.rig.RigConfig`) with its working distance and projector position
    and aim times `scale`: the same camera and projector seeing a field `scale` times wider."""
    raw = {**config.raw, "rig": {**config.raw["rig"]}, "projector": {**config.raw["projector"]}}
    raw["rig"]["working_distance_mm"] = config.working_distance_mm * scale
    for key in ("position_mm", "look_at_mm"):
        if key in raw["projector"]:
            raw["projector"][key] = [float(x) * scale for x in raw["projector"][key]]
    raw.pop("acceptance", None)  # its measuring volume is the unscaled rig's
    return type(config).from_toml(raw, config.path)  # validated again, as the rig file it stands for


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """A scan as the scanner writes it (`cloud`: the organised cloud, table in view; `scan`
    its ScanCloud), the true pose taking camera points onto the part (`truth`, 4x4), the
    rig it was taken with, and the true CAD face per valid pixel (-1: table)."""

    cloud: Any
    scan: Any
    truth: np.ndarray
    rig: Any
    true_face: np.ndarray


def part_pose(vertices: np.ndarray, placement: Placement,
              up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Part -> camera pose of a part with vertices `vertices` (part frame, its base
    perpendicular to `up`) at `placement`."""
    from sim.parts import lying_pose

    pose = lying_pose(vertices, placement.turn_rad, placement.distance_mm, placement.tilt_rad, up)
    pose[:2, 3] += placement.offset_mm
    return pose


def scan_part(model: Any, placement: Placement, seed: int, config: Any = None,
              up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> SimulatedScan:
    """Scan `model` (an `inspection.cad.CadModel` of the part, tessellated finely enough that
    its chords are far below the noise) at `placement` on the table (its base perpendicular
    to `up`), with noise seed `seed`, through the whole fringe chain (acquire, decode,
    triangulate)."""
    from inspection.measured_cloud import from_organised
    from scanner.acquisition import AcquisitionSettings, acquire
    from scanner.decode import decode
    from scanner.native_threads import native_threads
    from scanner.patterns import PatternSet
    from scanner.reconstruct import Triangulator, triangulate
    from scanner.rig import RigConfig, open_rig
    from sim.parts import part_scene

    config = scaled_rig(config or RigConfig.load(), placement.rig_scale)
    tess = model.tessellation
    pose = part_pose(tess.vertices, placement, up)
    scene, face_of_id = part_scene(tess.vertices, tess.triangles, tess.face, pose, up=up)
    patterns = PatternSet.load(config.patterns_path)
    with native_threads(1), open_rig(config, scene=scene, seed=seed) as rig:
        stack = acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda i, f: None)
        cloud = triangulate(decode(stack, patterns, rig.camera.bit_depth, rig.model.projector.size),
                            Triangulator(rig.model))
        gt = rig.extras["ground_truth"]
    scan = from_organised(cloud, f"part {model.path.name} placement {placement.seed} noise {seed}")
    px = scan.camera_pixels()
    true_face = face_of_id[gt.object_id[px[:, 1], px[:, 0]]]
    return SimulatedScan(cloud, scan, np.linalg.inv(pose), config, true_face)
