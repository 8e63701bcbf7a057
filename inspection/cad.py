"""CAD models for inspection: STEP B-reps (through OpenCASCADE) and triangle meshes.

A `CadModel` is a list of `Face`s in the model frame (mm). A STEP face keeps its
`ADVANCED_FACE` entity id (`#n` in the file), its exact surface (`inspection.surfaces`),
its orientation and its trimmed parameter domain, classified by OpenCASCADE itself
(`IntTools_FClass2d`; a raster of the library's own triangulation answers for points
clearly inside or outside, the classifier for the rest; built when the face is first
asked). A tessellated STEP face (AP242 `TRIANGULATED_FACE`, `COMPLEX_TRIANGULATED_FACE`:
triangles, no surface) is read as a mesh face with its entity id. A face OpenCASCADE
cannot evaluate (no surface and no triangles, or a failing evaluation) is left out and
named in `CadModel.skipped`; no method is ever called on a null handle. A mesh model
(STL/PLY/OBJ) is split into faces at sharp edges; a mesh face is its triangles.

Reading time grows about linearly with the file: the STEP ids of the faces are found
from the file's records in one pass (`_face_entity_ids`), not by a search per face.

Units: STEP lengths are converted to mm by OpenCASCADE from the file's declared unit
(kept in `CadModel.unit`); a mesh file has no unit, so the caller states it (`mesh_unit`).

OpenCASCADE costs ~1 s and ~265 MB to import, so it is imported inside the functions that
need it.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from inspection.errors import CadError
from inspection.surfaces import BSpline, Cone, Cylinder, Plane, Sphere, Surface, Torus
from scanner.file_checks import FileRefused, regular_size
from scanner.mesh_files import read_mesh

STEP_SUFFIXES = (".step", ".stp")
MESH_SUFFIXES = (".stl", ".ply", ".obj")
SURFACE_TYPES = ("plane", "cylinder", "cone", "sphere", "torus", "bspline", "mesh")
MESH_UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4, "inch": 25.4}
SHARP_EDGE_DEG = 25.0  # mesh models: faces are split where neighbouring triangles turn by more
DEFLECTION_FRACTION = 10000.0  # default triangulation chord tolerance: the model's diagonal / this
RASTER_CELLS = 512  # classification raster: cells along the longer side of a face's UV box
_OUT, _IN, _UNSURE = 0, 1, 2
Progress = Callable[[str, int, int], None]  # (stage, done, total), as scanner.pipeline's


@dataclass(frozen=True, eq=False)
class Tessellation:
    """Triangles of a model, per face: `vertices` (N, 3) mm, `triangles` (M, 3) int32
    wound so that normals point out of the material, `face` (M,) int32 the model face of
    each triangle. Vertices are not shared between faces."""

    vertices: np.ndarray
    triangles: np.ndarray
    face: np.ndarray

    def face_mesh(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(vertices, triangles) of one face, re-indexed."""
        tri = self.triangles[self.face == index]
        used, inverse = np.unique(tri, return_inverse=True)
        return self.vertices[used], inverse.reshape(-1, 3).astype(np.int32)


# what `_Domain._raster` builds a face's raster from: UV box, mm per unit of u and v, the
# triangulation's UV points and triangles, and its deflection (mm)
_RasterInputs = tuple[tuple[float, float, float, float], tuple[float, float], np.ndarray, np.ndarray, float]


class _Domain:
    """The trimmed parameter domain of a STEP face: a raster over the UV box marks cells
    certainly inside or outside (from the library's triangulation in UV); points in the
    remaining cells, near the trimming curves, are classified by `IntTools_FClass2d`.
    The raster (up to RASTER_CELLS^2 bytes) is built on the first `contains`, so a large
    model holds rasters only for the faces a scan actually reaches."""

    def __init__(self, face: Any, box: tuple[float, float, float, float], scale: tuple[float, float],
                 uv: np.ndarray, triangles: np.ndarray, deflection_mm: float) -> None:
        self._face = face
        self._classifier: Any = None
        self._args: _RasterInputs | None = (box, scale, uv, triangles, deflection_mm)  # dropped once it is built
        self._state: np.ndarray | None = None

    @property
    def state(self) -> np.ndarray:
        """Per raster cell (one cell of margin all round): _OUT, _IN or _UNSURE."""
        if self._state is None:
            if self._args is None:
                raise RuntimeError("a face domain's raster inputs are gone but no raster was built")
            self._state = self._raster(*self._args)
            self._args = None
        return self._state

    def _raster(self, box: tuple[float, float, float, float], scale: tuple[float, float], uv: np.ndarray,
                triangles: np.ndarray, deflection_mm: float) -> np.ndarray:
        import cv2

        u0, u1, v0, v1 = box
        span = np.array([max(u1 - u0, 1e-12) * scale[0], max(v1 - v0, 1e-12) * scale[1]])
        n = np.maximum(np.round(RASTER_CELLS * span / span.max()), 8).astype(int)
        self.origin = np.array([u0, v0])
        self.cell = np.array([u1 - u0, v1 - v0]) / n
        self.cell = np.where(self.cell > 0, self.cell, 1.0)
        filled = np.zeros((n[1] + 2, n[0] + 2), np.uint8)  # one cell of margin all round
        if len(triangles):
            pix = np.round(((uv - self.origin) / self.cell + 0.5) * 16.0).astype(np.int32)  # 4 fractional bits
            cv2.fillPoly(filled, list(pix[triangles]), 1, lineType=cv2.LINE_8, shift=4)
            edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
            e, count = np.unique(edges, axis=0, return_counts=True)
            boundary = np.zeros_like(filled)
            cv2.polylines(boundary, list(pix[e[count == 1]]), False, 1, thickness=1, lineType=cv2.LINE_8, shift=4)
        else:
            boundary = np.ones_like(filled)
        # the triangulation's boundary is within `deflection_mm` of the trimming curves
        cell_mm = self.cell * np.asarray(scale)
        band = (np.ceil(deflection_mm / cell_mm).astype(int) + 1).clip(1, 64)
        k = np.ones((2 * band[1] + 1, 2 * band[0] + 1), np.uint8)
        k3 = np.ones((3, 3), np.uint8)
        # uint8 masks (OpenCV's stubs say any numeric array, which `~` does not take)
        near_boundary: np.ndarray = cv2.dilate(boundary, k)
        grown: np.ndarray = cv2.dilate(filled, k3)
        shrunk: np.ndarray = cv2.erode(filled, k3)
        unsure = near_boundary | (grown & ~shrunk & 1)
        return np.where(unsure > 0, _UNSURE, np.where(filled > 0, _IN, _OUT)).astype(np.uint8)

    def contains(self, uv: np.ndarray) -> np.ndarray:
        """Whether each parameter point (N, 2) lies in the face (on its boundary counts)."""
        from OCP.gp import gp_Pnt2d
        from OCP.TopAbs import TopAbs_OUT

        state_map = self.state  # builds the raster (and origin, cell) on first use
        ij = np.floor((uv - self.origin) / self.cell).astype(np.int64) + 1
        h, w = state_map.shape
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        state = np.full(len(uv), _OUT, np.uint8)
        state[ok] = state_map[ij[ok, 1], ij[ok, 0]]
        inside = state == _IN
        ask = np.flatnonzero(state == _UNSURE)
        if ask.size:
            if self._classifier is None:
                from OCP.BRep import BRep_Tool
                from OCP.IntTools import IntTools_FClass2d

                self._classifier = IntTools_FClass2d(self._face, BRep_Tool.Tolerance_s(self._face))
            perform = self._classifier.Perform
            inside[ask] = [perform(gp_Pnt2d(u, v)) != TopAbs_OUT for u, v in uv[ask].tolist()]
        return inside


@dataclass(frozen=True, eq=False)
class Face:
    """One face of a model. `index` is its position in `CadModel.faces`; `step_id` the STEP
    face entity id (`ADVANCED_FACE`, or a tessellated face; None for mesh files); `type` one
    of `SURFACE_TYPES`; `mesh` its triangles (vertices mm, triangles) as in the tessellation; `sense`
    +1 when the surface's natural normal points out of the material, -1 when reversed;
    `box` the UV bounding box; `area_mm2` its area."""

    index: int
    step_id: int | None
    type: str
    area_mm2: float
    surface: Surface | MeshSurface | None = field(default=None, repr=False)
    sense: int = 1
    box: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    domain: _Domain | None = field(default=None, repr=False)
    mesh: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    @property
    def label(self) -> str:
        """How reports name the face: `#<STEP id>` or `F<index>` for mesh faces."""
        return f"#{self.step_id}" if self.step_id is not None else f"F{self.index}"

    def params(self) -> dict[str, Any]:
        """Nominal parameters (mm, rad) as plain values; outward normals for planes."""
        if self.surface is None:
            return {}
        p = self.surface.params()
        if "normal" in p:
            p["normal"] = (self.sense * np.asarray(p["normal"])).tolist()
        return p

    def wrap(self, uv: np.ndarray) -> np.ndarray:
        """Parameters moved by whole periods into the face's UV box where possible."""
        uv = np.array(uv, dtype=np.float64)
        s = self.surface
        for k, period in ((0, getattr(s, "u_period", None)), (1, getattr(s, "v_period", None))):
            if period:
                lo = self.box[2 * k]
                uv[:, k] = lo + np.mod(uv[:, k] - lo, period)
        return uv


@dataclass(frozen=True, eq=False)
class CadModel:
    """Faces of a part in the model frame (mm). `unit` is the length unit the file declared
    (STEP) or the caller stated (mesh); `kind` "step" or "mesh"; `skipped` one line per
    face of the file that OpenCASCADE could not evaluate (left out of `faces`)."""

    path: Path
    kind: str
    unit: str
    faces: tuple[Face, ...]
    tessellation: Tessellation = field(repr=False)
    skipped: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.faces)

    @property
    def counts(self) -> dict[str, int]:
        """Faces per surface type, in `SURFACE_TYPES` order."""
        c = Counter(f.type for f in self.faces)
        return {t: c[t] for t in SURFACE_TYPES if c[t]}

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        v = self.tessellation.vertices
        return v.min(axis=0), v.max(axis=0)

    @property
    def diagonal_mm(self) -> float:
        lo, hi = self.bounds
        return float(np.linalg.norm(hi - lo))

    def by_label(self, label: str) -> Face:
        """The face named `#<STEP id>` (or `F<index>`)."""
        for f in self.faces:
            if f.label == label:
                return f
        raise KeyError(f"{self.path}: no face {label}; faces are {self.faces[0].label} .. {self.faces[-1].label}")

    def summary(self) -> dict[str, Any]:
        """The model as plain data: faces (STEP id, type, area, parameters) and counts."""
        return {"path": str(self.path), "kind": self.kind, "unit": self.unit,
                "bounds_mm": [b.tolist() for b in self.bounds],
                "faces": [{"index": f.index, "id": f.step_id, "label": f.label, "type": f.type,
                           "area_mm2": round(f.area_mm2, 6), "params": f.params()} for f in self.faces],
                "counts": self.counts}


def load_cad(path: str | Path, mesh_unit: str = "mm", deflection_mm: float | None = None,
             scale: float = 1.0, progress: Progress | None = None) -> CadModel:
    """A STEP (.step/.stp: AP203, AP214, AP242, B-rep or tessellated) or mesh (.stl/.ply/.obj)
    model. `deflection_mm` is the chord tolerance of the STEP triangulation (default: the
    model's diagonal / DEFLECTION_FRACTION); `mesh_unit` the unit a mesh file is written in;
    `scale` makes a scale model of a STEP part (every length multiplied, about the origin);
    `progress(stage, done, total)` hears how a STEP file's reading goes."""
    path = Path(path)
    if not path.exists():
        raise CadError(path, "no such file")
    try:
        regular_size(path)
    except FileRefused as exc:
        raise CadError(path, exc.problem) from None
    suffix = path.suffix.lower()
    if not scale > 0:
        raise CadError(path, f"scale must be > 0, got {scale}")
    if suffix in STEP_SUFFIXES:
        return _load_step(path, deflection_mm, scale, progress or _quiet)
    if suffix in MESH_SUFFIXES:
        if mesh_unit not in MESH_UNITS_MM:
            raise CadError(path, f"unknown mesh unit {mesh_unit!r}; use one of {sorted(MESH_UNITS_MM)}")
        return _load_mesh(path, mesh_unit)
    raise CadError(path, f"not a CAD file: expected STEP ({', '.join(STEP_SUFFIXES)}) or a mesh "
                         f"({', '.join(MESH_SUFFIXES)})")


def _quiet(stage: str, done: int, total: int) -> None:
    pass


# ------------------------------------------------------------------------------- STEP

# STEP entities OpenCASCADE turns into faces: B-rep faces (a surface and its bounds) and
# AP242 tessellated faces (triangles only)
FACE_ENTITIES = ("ADVANCED_FACE", "FACE_SURFACE", "TRIANGULATED_FACE", "COMPLEX_TRIANGULATED_FACE")
_RECORD = re.compile(r"^\s*#(\d+)\s*=\s*([A-Za-z0-9_]*)", flags=re.M)


def _face_records(path: Path) -> list[tuple[int, int]]:
    """(record number in the file's DATA section, 1-based; entity id) of every face record,
    in one pass over the text. OpenCASCADE numbers a STEP model's entities in this order."""
    text = path.read_text(errors="replace")
    data = re.search(r"^\s*DATA\b", text, flags=re.M)
    records = _RECORD.findall(text, data.end() if data else 0)
    return [(k, int(ident)) for k, (ident, kind) in enumerate(records, 1) if kind.upper() in FACE_ENTITIES]


def _vec(d: Any) -> np.ndarray:
    return np.array([d.X(), d.Y(), d.Z()], dtype=np.float64)


def _placement(ax3: Any) -> dict[str, np.ndarray]:
    return {"origin": _vec(ax3.Location()), "x": _vec(ax3.XDirection()), "y": _vec(ax3.YDirection()),
            "z": _vec(ax3.Direction())}


def _bspline(handle: Any) -> BSpline:
    """A non-periodic copy of an OpenCASCADE B-spline surface as a `BSpline`."""
    s = handle.Copy()
    s.SetUNotPeriodic()
    s.SetVNotPeriodic()
    nu, nv = s.NbUPoles(), s.NbVPoles()
    ctrl = np.empty((nu, nv, 4))
    for i in range(1, nu + 1):
        for j in range(1, nv + 1):
            w = s.Weight(i, j)
            ctrl[i - 1, j - 1] = (*(w * _vec(s.Pole(i, j))), w)
    tu = np.array([s.UKnotSequence().Value(i) for i in range(1, s.UKnotSequence().Length() + 1)])
    tv = np.array([s.VKnotSequence().Value(i) for i in range(1, s.VKnotSequence().Length() + 1)])
    o = np.zeros(3)
    return BSpline(o, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]),
                   knots=(tu, tv), degrees=(s.UDegree(), s.VDegree()), control=ctrl)


def _is_null(handle: Any) -> bool:
    """Whether an OpenCASCADE handle or shape is null (OCP gives a null handle as None; a
    shape answers IsNull): calling anything on a null one kills the process."""
    return handle is None or bool(getattr(handle, "IsNull", lambda: False)())


def _surface(face: Any) -> Surface | None:
    """The face's exact surface, or None when it has none (a tessellated face)."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepAdaptor import BRepAdaptor_Surface
    from OCP.GeomAbs import (
        GeomAbs_BSplineSurface,
        GeomAbs_Cone,
        GeomAbs_Cylinder,
        GeomAbs_Plane,
        GeomAbs_Sphere,
        GeomAbs_Torus,
    )
    from OCP.GeomConvert import GeomConvert
    from OCP.TopLoc import TopLoc_Location

    handle = BRep_Tool.Surface_s(face, TopLoc_Location())
    if _is_null(handle):
        return None
    a = BRepAdaptor_Surface(face, True)
    t = a.GetType()
    if t == GeomAbs_Plane:
        return Plane(**_placement(a.Plane().Position()))
    if t == GeomAbs_Cylinder:
        c = a.Cylinder()
        return Cylinder(**_placement(c.Position()), radius=c.Radius())
    if t == GeomAbs_Cone:
        c = a.Cone()
        return Cone(**_placement(c.Position()), ref_radius=c.RefRadius(), semi_angle=c.SemiAngle())
    if t == GeomAbs_Sphere:
        c = a.Sphere()
        return Sphere(**_placement(c.Position()), radius=c.Radius())
    if t == GeomAbs_Torus:
        c = a.Torus()
        return Torus(**_placement(c.Position()), major_radius=c.MajorRadius(), minor_radius=c.MinorRadius())
    if t == GeomAbs_BSplineSurface:
        return _bspline(a.BSpline())
    # Bezier, revolution, extrusion, offset, ...: their exact B-spline form
    converted = GeomConvert.SurfaceToBSplineSurface_s(BRep_Tool.Surface_s(face))
    if _is_null(converted):
        raise CadError("surface", f"OpenCASCADE gives no B-spline form of its {t.name} surface")
    return _bspline(converted)


def _read_step(path: Path) -> tuple[Any, Any, str]:
    """(shape, reader, declared length unit); raises CadError when unreadable or empty."""
    from OCP.collections import Sequence_TCollection_AsciiString
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_Reader

    _silence_opencascade()  # its messages go to stdout (a --json stream); its check list is read below instead
    reader = STEPControl_Reader()
    status = reader.ReadFile(str(path))
    if status != IFSelect_RetDone:
        raise CadError(path, f"unreadable STEP file (OpenCASCADE: {status.name}); check that it is an ISO 10303-21 "
                             f"file and not truncated")
    if reader.StepModel().NbEntities() == 0:
        raise CadError(path, "the STEP file holds no shape that can be transferred (its DATA section is empty)")
    problem = _step_load_failure(reader)
    if problem:
        raise CadError(path, f"damaged STEP file: {problem}; the part's geometry would be read incomplete")
    if reader.TransferRoots() == 0:
        raise CadError(path, "the STEP file holds no shape that can be transferred (no solid, shell or face)")
    shape = reader.OneShape()
    if _is_null(shape):
        raise CadError(path, "the STEP file holds no geometry")
    units = Sequence_TCollection_AsciiString()
    reader.FileUnits(units, Sequence_TCollection_AsciiString(), Sequence_TCollection_AsciiString())
    names = sorted({units.Value(i).ToCString().lower() for i in range(1, units.Length() + 1)})
    return shape, reader, ",".join(names) or "unknown"


def _silence_opencascade() -> None:
    """Remove OpenCASCADE's default printer (stdout) from its messenger, once: what it reports
    of a STEP file is read from the reader's check list (`_step_load_failure`)."""
    from OCP.Message import Message, Message_PrinterOStream

    Message.DefaultMessenger_s().RemovePrinters(Message_PrinterOStream.get_type_descriptor_s())


STEP_GEOMETRY_CLASSES = ("StepShape_", "StepGeom_")  # the entities the shape is made of (topology, geometry)


def _step_load_failure(reader: Any) -> str | None:
    """What OpenCASCADE's load check found wrong with the file's geometry, or None: a
    failure of the whole file (an unresolved reference: an entity named but not there) or of
    an entity the shape is made of (a shell whose face is missing or of the wrong type).
    Failures in presentation and PMI entities (styles, annotations) do not change the
    geometry and are not counted: the NIST AP242 files hold 53 of them."""
    model = reader.StepModel()
    check = model.GlobalCheck()
    if check.NbFails():
        return f"{check.CFail(1)} (OpenCASCADE's load check, {check.NbFails()} in all)"
    checks = reader.WS().ModelCheckList()
    checks.Start()
    while checks.More():
        k, entity_check = checks.Number(), checks.Value()
        if entity_check.HasFailed():
            if k == 0:
                return f"{entity_check.CFail(1)} (OpenCASCADE's load check)"
            kind = model.Value(k).DynamicType().Name()
            if kind.startswith(STEP_GEOMETRY_CLASSES):
                ident = model.IdentLabel(model.Value(k))
                return f"entity #{ident} ({kind.split('_', 1)[1]}): {entity_check.CFail(1)}"
        checks.Next()
    return None


def _load_step(path: Path, deflection_mm: float | None, scale: float, progress: Progress) -> CadModel:
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS

    progress("read STEP", 0, 1)
    shape, reader, unit = _read_step(path)
    fmap = IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher()
    TopExp.MapShapes_s(shape, TopAbs_FACE, fmap)
    occ_faces = [TopoDS.Face(fmap.FindKey(i)) for i in range(1, fmap.Extent() + 1)]
    if not occ_faces:
        raise CadError(path, "the STEP file holds no faces")
    step_ids = _face_entity_ids(path, reader, occ_faces)
    progress("read STEP", 1, 1)
    if scale != 1.0:  # a scaled copy: its faces, in the same order, keep their ids
        from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
        from OCP.gp import gp_Pnt, gp_Trsf

        trsf = gp_Trsf()
        trsf.SetScale(gp_Pnt(0.0, 0.0, 0.0), scale)
        shape = BRepBuilderAPI_Transform(shape, trsf, True).Shape()
        fmap = IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher()
        TopExp.MapShapes_s(shape, TopAbs_FACE, fmap)  # the copy is explored in the same order
        occ_faces = [TopoDS.Face(fmap.FindKey(i)) for i in range(1, fmap.Extent() + 1)]
        unit = f"{unit} x {scale:g}"

    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    bb = Bnd_Box()
    BRepBndLib.Add_s(shape, bb)
    if bb.IsVoid():
        raise CadError(path, "the model has no extent")
    diag = float(np.linalg.norm(_vec(bb.CornerMax()) - _vec(bb.CornerMin())))
    if not diag > 0:
        raise CadError(path, "the model has no extent")
    defl = deflection_mm if deflection_mm is not None else diag / DEFLECTION_FRACTION
    progress("triangulate", 0, 1)
    BRepMesh_IncrementalMesh(shape, defl, False, 0.2, True)  # faces without a surface keep their triangles
    progress("triangulate", 1, 1)

    faces: list[Face] = []
    skipped: list[str] = []
    for i, f in enumerate(occ_faces):
        name = f"face #{step_ids[i]}" if step_ids[i] is not None else f"face {i + 1} (no STEP id)"
        try:
            face = _step_face(f, len(faces), step_ids[i], defl)
        except Exception as exc:  # OpenCASCADE's own failures on one face (Standard_Failure)
            face, why = None, f"{type(exc).__name__}: {exc}"
        else:
            why = "no surface and no triangles"
        if face is None:
            skipped.append(f"{name}: OpenCASCADE cannot evaluate it ({why})")
        else:
            faces.append(face)
        progress("faces", i + 1, len(occ_faces))
    if not faces:
        raise CadError(path, f"none of its {len(occ_faces)} faces can be evaluated: {skipped[0]}")
    return CadModel(path=path, kind="step", unit=unit, faces=tuple(faces), tessellation=_tessellation(faces),
                    skipped=tuple(skipped))


def _step_face(f: Any, index: int, step_id: int | None, deflection_mm: float) -> Face | None:
    """One STEP face: exact surface and trimmed domain, or, for a tessellated face, its
    triangles as a mesh face; None when it has neither."""
    from OCP.BRepGProp import BRepGProp
    from OCP.BRepTools import BRepTools
    from OCP.GProp import GProp_GProps
    from OCP.TopAbs import TopAbs_REVERSED

    sense = -1 if f.Orientation() == TopAbs_REVERSED else 1
    surf = _surface(f)
    if surf is None:
        mesh = _face_mesh(f, sense)
        return None if mesh is None else _mesh_face(index, step_id, *mesh)
    u0, u1, v0, v1 = BRepTools.UVBounds_s(f)
    box = (float(u0), float(u1), float(v0), float(v1))
    props = GProp_GProps()
    BRepGProp.SurfaceProperties_s(f, props)
    v, uv, t = _face_triangulation(f, surf, sense)
    return Face(index=index, step_id=step_id, type=surf.kind, area_mm2=float(props.Mass()), surface=surf,
                sense=sense, box=box, domain=_Domain(f, box, surf.metric_scale(box), uv, t, deflection_mm),
                mesh=(v, t))


def _tessellation(faces: list[Face]) -> Tessellation:
    """The faces' triangles in one array (vertices not shared between faces)."""
    meshes = [f.mesh for f in faces if f.mesh is not None]
    if len(meshes) != len(faces):
        raise ValueError("the tessellation needs every face's triangles; a face has none")
    verts = [v for v, _ in meshes]
    tris = [t for _, t in meshes]
    offsets = np.cumsum([0] + [len(v) for v in verts[:-1]])
    return Tessellation(np.concatenate(verts), np.concatenate([t + o for t, o in zip(tris, offsets)]).astype(np.int32),
                        np.repeat(np.arange(len(faces), dtype=np.int32), [len(t) for t in tris]))


def write_copies(source: str | Path, copies: int, out: str | Path, spacing_mm: float | None = None) -> Path:
    """A STEP file holding `copies` translated copies of `source`'s shape, on a grid with
    `spacing_mm` between origins (default: 1.5 x the part's diagonal), each copy with its
    own faces: a large real file for timing the reader (`slscan bench cad`)."""
    from OCP.Bnd import Bnd_Box
    from OCP.BRep import BRep_Builder
    from OCP.BRepBndLib import BRepBndLib
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
    from OCP.gp import gp_Trsf, gp_Vec
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer
    from OCP.TopoDS import TopoDS_Compound

    shape, _, _ = _read_step(Path(source))
    if spacing_mm is None:
        bb = Bnd_Box()
        BRepBndLib.Add_s(shape, bb)
        spacing_mm = 1.5 * float(np.linalg.norm(_vec(bb.CornerMax()) - _vec(bb.CornerMin())))
    side = int(np.ceil(np.sqrt(copies)))
    compound, builder = TopoDS_Compound(), BRep_Builder()
    builder.MakeCompound(compound)
    for k in range(copies):
        move = gp_Trsf()
        move.SetTranslation(gp_Vec(spacing_mm * (k % side), spacing_mm * (k // side), 0.0))
        builder.Add(compound, BRepBuilderAPI_Transform(shape, move, True).Shape())
    writer = STEPControl_Writer()
    writer.Transfer(compound, STEPControl_AsIs)
    if writer.Write(str(out)) != IFSelect_RetDone:
        raise CadError(out, "could not write the STEP file")
    return Path(out)


def _face_entity_ids(path: Path, reader: Any, faces: list[Any]) -> list[int | None]:
    """The STEP entity id of each face, in time linear in the file: each face record of
    the file (`_face_records`) is transferred by its number (OpenCASCADE returns the face
    it already made for it) and matched to the model's faces by their shared geometry,
    whatever the placement of the instance (located copies of one face share its id)."""
    from OCP.collections import IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher
    from OCP.TopLoc import TopLoc_Location

    model = reader.StepModel()
    here = TopLoc_Location()
    transferred = IndexedMap_TopoDS_Shape_TopTools_ShapeMapHasher()
    ids: list[int] = []
    for number, ident in _face_records(path):
        if model.NextNumberForLabel(f"#{ident}", number - 1, True) != number:  # records out of the usual order
            number = model.NextNumberForLabel(f"#{ident}", 0, True)
        if number <= 0 or not reader.TransferOne(number):
            continue
        shape = reader.Shape(reader.NbShapes())
        if _is_null(shape):
            continue
        if transferred.Add(shape.Located(here)) > len(ids):
            ids.append(ident)
    found = [transferred.FindIndex(f.Located(here)) for f in faces]
    return [ids[k - 1] if k else None for k in found]


def _face_triangulation(face: Any, surf: Surface, sense: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (N, 3) mm on the exact surface, their UV (N, 2), triangles (M, 3) wound
    outward) of the library's triangulation of one face; empty arrays when it has none."""
    from OCP.BRep import BRep_Tool
    from OCP.TopLoc import TopLoc_Location

    loc = TopLoc_Location()
    tri = BRep_Tool.Triangulation_s(face, loc)
    if _is_null(tri) or tri.NbTriangles() == 0 or not tri.HasUVNodes():
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 3), np.int32)
    uv = np.array([(p.X(), p.Y()) for p in (tri.UVNode(i) for i in range(1, tri.NbNodes() + 1))])
    t = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)], dtype=np.int32) - 1
    v, n, _ = surf.evaluate(uv)  # nodes on the exact surface, in the model frame
    a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    out = sense * n[t].mean(axis=1)
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), out) < 0
    t[flip] = t[flip][:, [0, 2, 1]]
    return v, uv, t


def _face_mesh(face: Any, sense: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(vertices (N, 3) mm in the model frame, triangles (M, 3)) of a face that has only
    triangles (a tessellated STEP face), wound as the face is oriented; None without any."""
    from OCP.BRep import BRep_Tool
    from OCP.TopLoc import TopLoc_Location

    loc = TopLoc_Location()
    tri = BRep_Tool.Triangulation_s(face, loc)
    if _is_null(tri) or tri.NbTriangles() == 0:
        return None
    v = np.array([(p.X(), p.Y(), p.Z()) for p in (tri.Node(i) for i in range(1, tri.NbNodes() + 1))], np.float64)
    if not loc.IsIdentity():
        m = loc.Transformation()
        rot = np.array([[m.Value(r, c) for c in range(1, 4)] for r in range(1, 4)])
        v = v @ rot.T + np.array([m.Value(r, 4) for r in range(1, 4)])
    t = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)], dtype=np.int32) - 1
    if sense < 0:
        t = t[:, [0, 2, 1]]
    return v, t


# ------------------------------------------------------------------------------- meshes


class MeshSurface:
    """The triangles of one mesh face, with closest-point projection (Open3D)."""

    kind = "mesh"

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        import open3d as o3d

        self.vertices = vertices
        self.triangles = triangles
        n = np.cross(vertices[triangles[:, 1]] - vertices[triangles[:, 0]],
                     vertices[triangles[:, 2]] - vertices[triangles[:, 0]])
        self.areas = 0.5 * np.linalg.norm(n, axis=1)
        self.normals = n / np.maximum(2 * self.areas, 1e-300)[:, None]
        cpu = o3d.core.Device("CPU:0")
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32), o3d.core.float32, cpu),
                                  o3d.core.Tensor(triangles.astype(np.uint32), o3d.core.uint32, cpu))

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(uv (zeros), foot points, outward triangle normals, signed distance)."""
        import open3d as o3d

        query = o3d.core.Tensor(np.asarray(points, np.float32), o3d.core.float32, o3d.core.Device("CPU:0"))
        ans = self._scene.compute_closest_points(query)
        foot = ans["points"].numpy().astype(np.float64)
        n = self.normals[ans["primitive_ids"].numpy().astype(np.int64)]
        return np.zeros((len(points), 2)), foot, n, np.einsum("ij,ij->i", points - foot, n)

    def params(self) -> dict[str, Any]:
        return {"triangles": len(self.triangles)}


def _load_mesh(path: Path, unit: str) -> CadModel:
    import open3d as o3d
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    try:
        v, t = read_mesh(path)
    except FileRefused as exc:
        raise CadError(path, exc.problem) from None
    if len(t) == 0 or len(v) < 3:
        raise CadError(path, "no triangles could be read (unreadable or empty mesh)")
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t.astype(np.int32)))
    mesh.remove_duplicated_vertices()
    v = np.asarray(mesh.vertices, dtype=np.float64) * MESH_UNITS_MM[unit]
    t = np.asarray(mesh.triangles, dtype=np.int64)
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    area = 0.5 * np.linalg.norm(n, axis=1)
    keep = area > 0
    t, n, area = t[keep], n[keep], area[keep]
    n /= (2 * area)[:, None]
    # triangles sharing an edge with a turn below SHARP_EDGE_DEG belong to the same face
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    owner = np.tile(np.arange(len(t)), 3)
    key = np.sort(edges, axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    k, o = key[order], owner[order]
    same = np.all(k[1:] == k[:-1], axis=1)
    a, b = o[:-1][same], o[1:][same]
    smooth = np.einsum("ij,ij->i", n[a], n[b]) > np.cos(np.radians(SHARP_EDGE_DEG))
    graph = coo_matrix((np.ones(int(smooth.sum())), (a[smooth], b[smooth])), shape=(len(t), len(t)))
    n_faces, label = connected_components(graph, directed=False)
    order = np.argsort(-np.bincount(label, weights=area))  # largest face first
    rank = np.empty(n_faces, np.int64)
    rank[order] = np.arange(n_faces)
    label = rank[label]
    faces = []
    for i in range(n_faces):
        used, inv = np.unique(t[label == i], return_inverse=True)
        faces.append(_mesh_face(i, None, v[used], inv.reshape(-1, 3).astype(np.int32)))
    return CadModel(path=path, kind="mesh", unit=unit, faces=tuple(faces), tessellation=_tessellation(faces))


def _mesh_face(index: int, step_id: int | None, vertices: np.ndarray, triangles: np.ndarray) -> Face:
    """A face that is its triangles: a plane when every triangle is within 0.5 deg of their
    mean normal, else of type "mesh"."""
    ms = MeshSurface(vertices, triangles)
    flat = np.abs(ms.normals @ np.average(ms.normals, axis=0, weights=ms.areas)).min() > np.cos(np.radians(0.5))
    return Face(index=index, step_id=step_id, type="plane" if flat else "mesh", area_mm2=float(ms.areas.sum()),
                mesh=(vertices, triangles), surface=ms)
