"""Scenes for the simulator: what stands in front of the rig.

A scene holds objects (triangle meshes from PLY/STL/OBJ files, or analytic primitives:
sphere, plane rectangle, box) and an optional reference plane, all placed in the rig's
world frame (= the camera frame: OpenCV convention, x right, y down, z forward; mm).

Object ids, used in the ground-truth id map:
    0      nothing (background: the ray leaves the scene)
    1      the reference plane (whether or not the scene has one, objects start at 2)
    2, 3…  the scene's objects, in the order they are listed

Scene TOML format (every path relative to the TOML file; every length in mm, angle in rad):

    name = "demo"                               # optional, default: file stem
    interreflection = false                     # optional: render one mirror bounce between surfaces

    [reference_plane]                           # optional: a large flat rectangle
    distance_mm = 420.0                         # plane z = distance, facing the camera …
    # pose = { rotation_rad = [rx, ry, rz], translation_mm = [x, y, z] }   # … or a pose
    size_mm = [1000.0, 1000.0]                  # optional, default 1000 x 1000
    albedo = 0.8                                # optional, default 0.8

    [[objects]]                                 # any number, ids 2, 3, … in this order
    name = "part"                               # optional
    mesh = "../parts/demo_part.ply"             # exactly one of: mesh, sphere, plane, box
    scale = 1.0                                 # mesh units -> mm (mesh only), default 1
    albedo = 0.7                                # 0..1, default 0.7
    # material = "polished_aluminium"           # optional: a preset of MATERIALS (albedo, specular,
                                                # roughness), each overridable by its own key
    # specular = 0.91                           # optional: normal-incidence reflectance F0 0..1, default 0
    # roughness = 0.12                          # optional: GGX roughness 0.02..1 (sqrt of alpha), default 0.5
    pose = { rotation_rad = [3.14159, 0, 0], translation_mm = [0, 0, 420] }
                                                # object -> world; or { matrix = 4x4 }; default identity

    [[objects]]
    sphere = { radius_mm = 20.0, center_mm = [0, 0, 400] }   # centre in the object frame (pose)

    [[objects]]
    plane = { size_mm = [100, 80] }             # rectangle on the object's z = 0, centred
    # plane = { size_mm = [100, 80], texture = "board.png" }   # optional albedo map (see below)

    [[objects]]
    box = { size_mm = [40, 30, 20] }            # axis-aligned in the object frame, centred

Materials (objects and the reference plane alike): the surface is Lambertian (`albedo`) plus,
when `specular` > 0, a Cook-Torrance GGX lobe of normal-incidence reflectance `specular` and
roughness `roughness` (see `sim.render.reflectance`); "matte" is the default (no lobe).

A pose places the object frame in the world: X_world = R X_object + t. A reference plane
given by `pose` is the rectangle on the pose's local z = 0 plane.

A plane may carry a texture: an albedo map stretched over its rectangle (image columns
along the object's +x, rows along +y, so texel (0, 0) sits at the (-w/2, -h/2) corner), and
the surface's albedo is `albedo` x texture. In a TOML scene the texture is a grey image
file (8- or 16-bit, full scale = 1); in code, `SceneObject.texture` is an (H, W) float
array in 0..1 (e.g. a calibration board's printed reflectance).

Primitives are exact (ray-cast analytically in float64): use them where a test needs a
surface known to better than a micrometre. Meshes are exact as meshes (each hit is
re-intersected with its triangle in float64).

A bare mesh file (no TOML) makes a bench scene: the part's own +z ("up" in CAD) turned to
face the camera (rotation of pi about x), its bounding box centred on the camera axis at
the rig's working distance, and a reference plane perpendicular to the camera axis that
touches the far side of the part (the table the part lies on).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, TypedDict

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from scanner import schema
from scanner.config import CONFIG_DIR, resolve
from scanner.errors import ConfigError
from scanner.geometry import pose_from_dict
from scanner.schema import Bool, Matrix4, Schema, Str, Vector3

DEFAULT_SCENE = CONFIG_DIR / "scenes" / "demo.toml"
BIN_SCENE_PREFIX = "bin:"  # a simulated bin of parts (`sim.bins.bin_spec`), not a scene file
MESH_SUFFIXES = (".ply", ".stl", ".obj")
KINDS = ("mesh", "sphere", "plane", "box")
BACKGROUND_ID = 0
REFERENCE_PLANE_ID = 1
FIRST_OBJECT_ID = 2

_DEFAULT_PLANE_SIZE = (1000.0, 1000.0)
MAX_LENGTH_MM = 100_000.0  # 100 m: every length and position of a bench scene lies within it
MIN_LENGTH_MM = 1e-3  # 1 um: a smaller object is below any camera pixel's footprint on the bench
MIN_ROUGHNESS = 0.02  # below this GGX is a numerical mirror (alpha ~ 4e-4) one ray per pixel cannot sample
DEFAULT_ROUGHNESS = 0.5


@dataclass(frozen=True)
class Material:
    """Surface reflectance: diffuse `albedo` 0..1, specular F0 `specular` 0..1 (0: matte),
    GGX `roughness` MIN_ROUGHNESS..1."""

    albedo: float
    specular: float = 0.0
    roughness: float = DEFAULT_ROUGHNESS


MATERIALS = {  # presets for `material = "..."` (F0 of the metals from their optical constants)
    "matte": Material(albedo=0.7),
    "polished_aluminium": Material(albedo=0.03, specular=0.91, roughness=0.12),
    "machined_aluminium": Material(albedo=0.12, specular=0.91, roughness=0.3),
    "stainless_steel": Material(albedo=0.06, specular=0.57, roughness=0.2),
}


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One object. `pose` maps object-frame points to the world frame (4x4, mm).

    `kind` is "mesh" (`vertices` (N, 3) float64 mm in the object frame, `triangles`
    (M, 3) int32), "sphere" (`radius_mm`, centred on the object-frame origin), "plane"
    (a `size_mm` = (w, h) rectangle on the object-frame z = 0, centred) or "box"
    (`size_mm` = (x, y, z), centred). A plane may have a `texture` (H, W) in 0..1 that
    multiplies its albedo (see the module docstring). `specular` (F0) and `roughness` add a
    specular lobe (`sim.render.reflectance`); `specular` = 0 is a matte surface."""

    name: str
    kind: str
    pose: np.ndarray
    albedo: float
    radius_mm: float | None = None
    size_mm: tuple[float, ...] | None = None
    vertices: np.ndarray | None = field(default=None, repr=False)
    triangles: np.ndarray | None = field(default=None, repr=False)
    source: Path | None = None
    texture: np.ndarray | None = field(default=None, repr=False)
    specular: float = 0.0
    roughness: float = DEFAULT_ROUGHNESS
    body: str | None = None  # the solid this object is one face of (sim.parts.part_scene): seen as one

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown object kind {self.kind!r}; known: {KINDS}")
        if not 0.0 <= self.albedo <= 1.0:
            raise ValueError(f"{self.name}: albedo {self.albedo} outside 0..1")
        if not 0.0 <= self.specular <= 1.0:
            raise ValueError(f"{self.name}: specular {self.specular} outside 0..1")
        if not MIN_ROUGHNESS <= self.roughness <= 1.0:
            raise ValueError(f"{self.name}: roughness {self.roughness} outside {MIN_ROUGHNESS}..1")
        pose = np.asarray(self.pose, dtype=np.float64)
        if pose.shape != (4, 4) or not _is_rigid(pose):
            raise ValueError(f"{self.name}: pose must be a rigid 4x4 transform")
        object.__setattr__(self, "pose", pose)
        if self.texture is not None:
            tex = np.asarray(self.texture, dtype=np.float32)
            if self.kind != "plane":
                raise ValueError(f"{self.name}: only planes take a texture, not a {self.kind}")
            if tex.ndim != 2 or min(tex.shape) < 2 or not np.isfinite(tex).all() or tex.min() < 0 or tex.max() > 1:
                raise ValueError(f"{self.name}: texture must be an (H, W) array of albedo in 0..1 (H, W >= 2)")
            tex.setflags(write=False)
            object.__setattr__(self, "texture", tex)

    def world_vertices(self) -> np.ndarray:
        """Mesh vertices in the world frame (mesh objects only)."""
        if self.vertices is None:
            raise ValueError(f"{self.name} is a {self.kind}, not a mesh")
        return self.vertices @ self.pose[:3, :3].T + self.pose[:3, 3]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """World-frame axis-aligned bounding box (lo, hi)."""
        if self.kind == "mesh":
            v = self.world_vertices()
            return v.min(axis=0), v.max(axis=0)
        if self.kind == "sphere":
            assert self.radius_mm is not None  # a sphere has its radius
            c, r = self.pose[:3, 3], float(self.radius_mm)
            return c - r, c + r
        assert self.size_mm is not None  # a plane or a box has its size
        half = np.array([*self.size_mm, *([0.0] if self.kind == "plane" else [])], dtype=np.float64) / 2
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
        w = corners @ self.pose[:3, :3].T + self.pose[:3, 3]
        return w.min(axis=0), w.max(axis=0)

    def plane_equation(self) -> np.ndarray:
        """(nx, ny, nz, c) with n·X + c = 0 for a plane object, n the unit normal turned
        toward the world origin (the camera)."""
        if self.kind != "plane":
            raise ValueError(f"{self.name} is a {self.kind}, not a plane")
        n = self.pose[:3, 2].copy()
        p = self.pose[:3, 3]
        if np.dot(n, -p) < 0:
            n = -n
        return np.array([*n, -np.dot(n, p)])


@dataclass(frozen=True, eq=False)
class Scene:
    """Objects (ids 2, 3, … in order) and an optional reference plane (id 1)."""

    objects: tuple[SceneObject, ...]
    reference_plane: SceneObject | None = None
    name: str = "scene"
    path: Path | None = None
    interreflection: bool = False  # render one mirror bounce off specular surfaces (`sim.render.light_paths`)

    def __post_init__(self) -> None:
        object.__setattr__(self, "objects", tuple(self.objects))
        if self.reference_plane is not None and self.reference_plane.kind != "plane":
            raise ValueError("the reference plane must be a plane object")

    def by_id(self) -> dict[int, SceneObject]:
        """Object id -> object, for every id present."""
        out = {FIRST_OBJECT_ID + i: o for i, o in enumerate(self.objects)}
        if self.reference_plane is not None:
            out[REFERENCE_PLANE_ID] = self.reference_plane
        return out

    @property
    def names(self) -> dict[int, str]:
        """Object id -> name (0 is "background")."""
        return {BACKGROUND_ID: "background", **{i: o.name for i, o in sorted(self.by_id().items())}}

    def id_of(self, name: str) -> int:
        for i, o in self.by_id().items():
            if o.name == name:
                return i
        raise KeyError(f"no object named {name!r} in scene {self.name!r}; names: {sorted(self.names.values())}")

    @classmethod
    def load(cls, path: str | Path, working_distance_mm: float = 400.0) -> Scene:
        """A scene TOML file, or a bare mesh file (placed at `working_distance_mm`)."""
        path = Path(path)
        if path.suffix.lower() in MESH_SUFFIXES:
            return cls.from_mesh(path, working_distance_mm)
        if path.suffix.lower() != ".toml":
            raise ConfigError(path, None, f"not a scene: expected a .toml scene or a mesh ({', '.join(MESH_SUFFIXES)})")
        return _load_toml_scene(path)

    @classmethod
    def from_mesh(cls, path: str | Path, working_distance_mm: float = 400.0, albedo: float = 0.7,
                  plane_albedo: float = 0.8, plane_size_mm: tuple[float, float] = _DEFAULT_PLANE_SIZE,
                  material: Material | None = None) -> Scene:
        """The bench scene for a bare part mesh (see the module docstring); `material`, if
        given, is the part's surface (its albedo replaces `albedo`)."""
        material = material or Material(albedo=albedo)
        path = Path(path)
        vertices, triangles = load_mesh(path, path, None)
        flip = np.diag([1.0, -1.0, -1.0, 1.0])  # rotation of pi about x: CAD up faces the camera
        turned = vertices @ flip[:3, :3].T
        lo, hi = turned.min(axis=0), turned.max(axis=0)
        pose = flip.copy()
        pose[:3, 3] = np.array([0.0, 0.0, working_distance_mm]) - (lo + hi) / 2
        part = SceneObject(name=path.stem, kind="mesh", pose=pose, albedo=material.albedo,
                           specular=material.specular, roughness=material.roughness, vertices=vertices,
                           triangles=triangles, source=path)
        far = working_distance_mm + (hi[2] - lo[2]) / 2
        plane = SceneObject(name="reference_plane", kind="plane", pose=_translation([0.0, 0.0, far]),
                            albedo=plane_albedo, size_mm=tuple(float(s) for s in plane_size_mm))
        return cls(objects=(part,), reference_plane=plane, name=path.stem, path=path)


def check_in_view(scene: Scene, camera: Any, world_from_cam: np.ndarray) -> None:
    """ConfigError naming the object unless every object of `scene` can appear in `camera`'s
    image (a `Pinhole`, placed by `world_from_cam`): an object wholly behind the camera, or
    wholly outside one side of its field of view, would be scanned as if absent. Tested:
    no part of a sphere within the camera's viewing pyramid (`distance_to_pyramid`); a mesh
    (its vertices), a box or plane (the corners of its bounds) wholly beyond one plane of the
    pyramid (z = 0 or a side): an object is refused only when none of it can be seen, and
    the faces of one solid (`body`) only when none of them can (a face may lie out of view)."""
    cam_from_world = np.linalg.inv(world_from_cam)
    w, h = camera.width, camera.height
    rays = np.column_stack([camera.normalized(np.array([[-0.5, -0.5], [w - 0.5, -0.5], [w - 0.5, h - 0.5],
                                                         [-0.5, h - 0.5]], float)), np.ones(4)])
    sides = np.cross(rays, np.roll(rays, -1, axis=0))  # inward normals of the pyramid's four sides
    sides *= np.sign(sides @ rays.mean(axis=0))[:, None]
    planes = np.vstack([[0.0, 0.0, 1.0], sides])  # z > 0: in front of the camera
    planes /= np.linalg.norm(planes, axis=1)[:, None]
    unseen_faces: dict[str, list[tuple[int, str, bool]]] = {}
    for i, obj in enumerate(scene.objects):
        lo, hi = obj.bounds()
        if obj.kind == "sphere":  # exactly: seen when the centre lies within its radius of the pyramid
            centre = cam_from_world[:3, :3] @ obj.pose[:3, 3] + cam_from_world[:3, 3]
            r = float(obj.radius_mm)  # type: ignore[arg-type]  # a sphere: radius set
            unseen, behind = distance_to_pyramid(centre, rays, planes[1:]) > r, bool(centre[2] < -r)
            if not unseen and not sphere_on_a_pixel(centre, r, camera):
                raise ConfigError(scene.path or scene.name, f"objects[{i}]",
                                  f"'{obj.name}' (radius {r:g} mm at {np.linalg.norm(centre):.4g} mm) covers no "
                                  f"camera pixel's centre: the scan would not see it")
        else:  # a mesh by its vertices, a box or plane by its bounds' corners: wholly beyond one plane
            points = obj.world_vertices() if obj.kind == "mesh" else np.array(
                [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
            cam = points @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
            outside = (cam @ planes.T <= 0).all(axis=0)
            unseen, behind = bool(outside.any()), bool(outside[0])
        side = "behind the camera" if behind else "outside the camera's field of view"
        where = (f"'{obj.name}' lies wholly {side} (its bounds {np.round(lo, 1).tolist()} .. "
                 f"{np.round(hi, 1).tolist()} mm in the rig's world frame): the scan would not see it")
        if obj.body is not None:
            unseen_faces.setdefault(obj.body, []).append((i, where, unseen))
        elif unseen:
            raise ConfigError(scene.path or scene.name, f"objects[{i}]", where)
    for body, faces in unseen_faces.items():
        if all(unseen for _, _, unseen in faces):
            i, where, _ = faces[0]
            raise ConfigError(scene.path or scene.name, f"objects[{i}]", f"every face of '{body}' is unseen: {where}")


def sphere_on_a_pixel(centre: np.ndarray, r: float, camera: Any) -> bool:
    """Whether a sphere (camera frame, mm) covers the centre of at least one of `camera`'s
    pixels, as a rendering samples it: decided by casting the rays of the pixels within its
    image's bounds when it images smaller than SMALL_IMAGE_PX across (a larger one in view
    always covers some)."""
    distance = float(np.linalg.norm(centre))
    if centre[2] <= r or distance <= r:
        return True  # reaches the camera's plane: large in the image wherever it is seen
    f = float(max(camera.K[0, 0], camera.K[1, 1]))
    spread = f * r / (centre[2] - r)  # px: bounds the image's radius (a margin for the lens distortion added)
    if spread > SMALL_IMAGE_PX:
        return True
    u, v = camera.project(centre[None])[0]
    half = spread * 1.5 + 2
    cols = np.arange(max(int(np.floor(u - half)), 0), min(int(np.ceil(u + half)), camera.width - 1) + 1)
    rows = np.arange(max(int(np.floor(v - half)), 0), min(int(np.ceil(v + half)), camera.height - 1) + 1)
    if not len(cols) or not len(rows):
        return False
    uu, vv = np.meshgrid(cols, rows)
    d = np.column_stack([camera.normalized(np.stack([uu.ravel(), vv.ravel()], 1).astype(float)), np.ones(uu.size)])
    d /= np.linalg.norm(d, axis=1)[:, None]
    t = d @ centre
    return bool(np.any(distance ** 2 - t ** 2 <= r * r))


SMALL_IMAGE_PX = 8.0


def distance_to_pyramid(p: np.ndarray, rays: np.ndarray, sides: np.ndarray) -> float:
    """Distance (mm) from `p` to the viewing pyramid whose edge rays from the eye are `rays`
    (4, 3), in order, and whose sides have inward unit normals `sides` (4, 3), side k holding
    rays k and k + 1: 0 inside, else the nearest side's wedge (where the foot falls between
    its two rays) or the nearest edge ray."""
    if (sides @ p >= 0).all():
        return 0.0
    unit = rays / np.linalg.norm(rays, axis=1)[:, None]
    along = np.maximum(unit @ p, 0.0)
    best = float(np.linalg.norm(p - along[:, None] * unit, axis=1).min())  # the edge rays
    for k in range(4):
        a, b = unit[k], unit[(k + 1) % 4]
        foot = p - (sides[k] @ p) * sides[k]
        coef = np.linalg.lstsq(np.stack([a, b], axis=1), foot, rcond=None)[0]
        if (coef >= 0).all():
            best = min(best, abs(float(sides[k] @ p)))
    return best


def load_scene(scene: Scene | str | Path | None, working_distance_mm: float = 400.0) -> Scene:
    """A Scene as given, loaded from a TOML or mesh path, or the default demo scene."""
    if isinstance(scene, Scene):
        return scene
    return Scene.load(DEFAULT_SCENE if scene is None else scene, working_distance_mm)


def load_mesh(file: Path, where: Path, key: str | None, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float64 mm, triangles int32) of a PLY/STL/OBJ file; errors name `where`/`key`."""
    from scanner.file_checks import FileRefused
    from scanner.mesh_files import read_mesh

    if file.suffix.lower() not in MESH_SUFFIXES:
        raise ConfigError(where, key, f"{file.name}: unsupported mesh format; use {', '.join(MESH_SUFFIXES)}")
    if not file.exists():
        raise ConfigError(where, key, f"mesh file not found: {file}")
    try:
        v, t = read_mesh(file)
    except FileRefused as exc:
        raise ConfigError(where, key, str(exc)) from None
    if len(t) == 0 or len(v) < 3:
        raise ConfigError(where, key, f"{file}: no triangles could be read (unreadable or empty mesh)")
    v = v * scale
    if not np.isfinite(v).all():
        raise ConfigError(where, key, f"{file}: scale {scale:g} makes the vertices non-finite")
    return v, t.astype(np.int32)


def _translation(t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t
    return T


def _is_rigid(T: np.ndarray) -> bool:
    R = T[:3, :3]
    return bool(np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
                and np.allclose(T[3], [0, 0, 0, 1]) and np.isfinite(T).all())


Length = Annotated[float, Field(strict=True, ge=MIN_LENGTH_MM, le=MAX_LENGTH_MM)]  # mm
Fraction = Annotated[float, Field(strict=True, ge=0.0, le=1.0)]
Roughness = Annotated[float, Field(strict=True, ge=MIN_ROUGHNESS, le=1.0)]
Size2 = Annotated[list[Length], Field(min_length=2, max_length=2)]  # mm
Size3 = Annotated[list[Length], Field(min_length=3, max_length=3)]  # mm


class PoseTable(Schema):
    """A pose: `rotation_rad` (Rodrigues) and `translation_mm`, or a 4x4 `matrix`."""

    rotation_rad: Vector3 | None = None
    translation_mm: Vector3 | None = None
    matrix: Matrix4 | None = None

    @model_validator(mode="after")
    def _one_form(self) -> PoseTable:
        if self.matrix is not None and (self.rotation_rad is not None or self.translation_mm is not None):
            raise ValueError("give either 'matrix' or 'rotation_rad'/'translation_mm', not both")
        return self


class SurfaceTable(Schema):
    """What objects and the reference plane share: a pose and a material (a preset of
    MATERIALS, each of its values overridable by its own key)."""

    pose: PoseTable | None = None
    material: Str | None = None
    albedo: Fraction | None = None
    specular: Fraction | None = None
    roughness: Roughness | None = None

    @field_validator("material")
    @classmethod
    def _known(cls, name: str) -> str:
        if name not in MATERIALS:
            raise ValueError(f"unknown material {name!r}; known: {sorted(MATERIALS)}")
        return name


class ReferencePlaneTable(SurfaceTable):
    distance_mm: Length | None = None
    size_mm: Size2 = Field(default_factory=lambda: list(_DEFAULT_PLANE_SIZE))

    @model_validator(mode="after")
    def _placed(self) -> ReferencePlaneTable:
        if (self.distance_mm is None) == (self.pose is None):
            raise ValueError("give exactly one of 'distance_mm' or 'pose'")
        return self


class SphereShape(Schema):
    radius_mm: Length
    center_mm: Vector3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])  # in the object frame (its pose)


class PlaneShape(Schema):
    size_mm: Size2
    texture: Str | None = None  # a grey image file, relative to the scene TOML


class BoxShape(Schema):
    size_mm: Size3


class ObjectTable(SurfaceTable):
    """One [[objects]] table: exactly one of mesh, sphere, plane, box."""

    name: Str | None = None
    mesh: Str | None = None
    sphere: SphereShape | None = None
    plane: PlaneShape | None = None
    box: BoxShape | None = None
    scale: Annotated[float, Field(strict=True, ge=1e-6, le=1e6)] = 1.0  # mesh units -> mm

    @field_validator("scale")
    @classmethod
    def _mesh_only(cls, scale: float, info: ValidationInfo) -> float:
        if info.data.get("mesh") is None:
            raise ValueError("only meshes take a scale")
        return scale

    @model_validator(mode="after")
    def _one_kind(self) -> ObjectTable:
        if len(self.kinds) != 1:
            raise ValueError(f"give exactly one of {list(KINDS)}, got {self.kinds or 'none'}")
        return self

    @property
    def kinds(self) -> list[str]:
        return [k for k in KINDS if getattr(self, k) is not None]


class SceneFile(Schema):
    """A scene TOML (see the module docstring)."""

    name: Str | None = None
    interreflection: Bool = False
    reference_plane: ReferencePlaneTable | None = None
    objects: list[ObjectTable] = Field(default_factory=list)


def _pose(pose: PoseTable | None, path: Path, key: str) -> np.ndarray:
    if pose is None:
        return np.eye(4)
    try:
        T = pose_from_dict(pose.model_dump(exclude_none=True))
    except (ValueError, TypeError) as exc:
        raise ConfigError(path, key, f"invalid pose: {exc}") from None
    if not _is_rigid(T):
        raise ConfigError(path, key, "pose matrix is not a rigid transform "
                                     "(rotation must be orthonormal, last row 0 0 0 1)")
    return _position(T, path, key)


class _Surface(TypedDict):
    """A SceneObject's reflectance keywords."""

    albedo: float
    specular: float
    roughness: float


def _material(table: SurfaceTable, default_albedo: float) -> _Surface:
    """albedo, specular and roughness of an object table: its `material` preset (if given),
    each overridden by its own key."""
    base = MATERIALS[table.material] if table.material is not None else Material(albedo=default_albedo)
    return _Surface(albedo=base.albedo if table.albedo is None else table.albedo,
                    specular=base.specular if table.specular is None else table.specular,
                    roughness=base.roughness if table.roughness is None else table.roughness)


def _length(x: float, path: Path, key: str) -> float:
    """A size in mm within MIN_LENGTH_MM .. MAX_LENGTH_MM, else ConfigError naming the key and the range."""
    if not MIN_LENGTH_MM <= x <= MAX_LENGTH_MM:
        raise ConfigError(path, key, f"must lie within [{MIN_LENGTH_MM:g}, {MAX_LENGTH_MM:g}] mm, got {x!r}")
    return x


def _position(T: np.ndarray, path: Path, key: str) -> np.ndarray:
    """A pose whose translation lies within MAX_LENGTH_MM of the origin on every axis."""
    if np.abs(T[:3, 3]).max() > MAX_LENGTH_MM:
        raise ConfigError(path, key, f"translation {T[:3, 3].tolist()} mm: every coordinate must lie within "
                                     f"[-{MAX_LENGTH_MM:g}, {MAX_LENGTH_MM:g}] mm")
    return T


def _texture(file: Path, path: Path, key: str) -> np.ndarray:
    """A plane's texture image `file` as albedo 0..1 (grey; full scale of its bit depth = 1)."""
    import cv2

    from scanner.file_checks import MAX_IMAGE_BYTES, FileRefused, decode_image, read_regular

    try:
        data = read_regular(file, limit=MAX_IMAGE_BYTES)
    except FileRefused as exc:
        raise ConfigError(path, key, str(exc)) from None
    img, _ = decode_image(data, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    if img is None or img.dtype not in (np.uint8, np.uint16) or min(img.shape) < 2:
        raise ConfigError(path, key, f"{file}: not readable as an 8- or 16-bit grey image")
    return img.astype(np.float32) / np.float32(np.iinfo(img.dtype).max)


def _load_toml_scene(path: Path) -> Scene:
    file = schema.load(SceneFile, path)
    plane = None
    if file.reference_plane is not None:
        t = file.reference_plane
        pose = _pose(t.pose, path, "reference_plane.pose") if t.distance_mm is None else \
            _translation([0.0, 0.0, t.distance_mm])
        plane = SceneObject(name="reference_plane", kind="plane", pose=pose, **_material(t, 0.8),
                            size_mm=tuple(t.size_mm))
    objects = []
    for i, o in enumerate(file.objects):
        pre = f"objects[{i}]"
        pose = _pose(o.pose, path, f"{pre}.pose")
        material = _material(o, 0.7)
        if o.mesh is not None:
            source = resolve(path, o.mesh)
            v, tri = load_mesh(source, path, f"{pre}.mesh", o.scale)
            _length(float(np.ptp(v, axis=0).max()), path, f"{pre}.scale")  # the scaled part's size
            obj = SceneObject(name=o.name or source.stem, kind="mesh", pose=pose, **material, vertices=v,
                              triangles=tri, source=source)
        elif o.sphere is not None:
            pose = _position(pose @ _translation(o.sphere.center_mm), path, f"{pre}.sphere.center_mm")
            obj = SceneObject(name=o.name or f"sphere{i}", kind="sphere", pose=pose, radius_mm=o.sphere.radius_mm,
                              **material)
        else:
            kind, shape = ("plane", o.plane) if o.plane is not None else ("box", o.box)
            assert shape is not None  # ObjectTable holds exactly one kind
            texture = _texture(resolve(path, o.plane.texture), path, f"{pre}.plane.texture") \
                if o.plane is not None and o.plane.texture is not None else None
            obj = SceneObject(name=o.name or f"{kind}{i}", kind=kind, pose=pose, size_mm=tuple(shape.size_mm),
                              texture=texture, **material)
        objects.append(obj)
    names = [o.name for o in objects] + (["reference_plane"] if plane is not None else [])
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ConfigError(path, "objects", f"object names must be unique; repeated: {sorted(dup)}")
    if not objects and plane is None:
        raise ConfigError(path, "objects", "the scene is empty: give at least one object or a reference plane")
    return Scene(objects=tuple(objects), reference_plane=plane, name=file.name or path.stem, path=path,
                 interreflection=file.interreflection)
