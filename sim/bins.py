"""Simulated bins of thin parts, with ground truth (for instance extraction and pose
estimation; cluttered labelled clouds for region growing are in `sim.clutter`), of the
parts a part file describes (`inspection.bins.part_file.TabPart`):
  - `bin_scene`: 5-20 parts dropped one after another onto a tray (the scene's reference
    plane, z = tray distance in the camera frame), each at a random in-plane position and
    yaw, front or back up, with a small random tilt, lowered along +z (away from the
    camera) until it touches the tray or a part already placed: rays cast along +z from
    the new part's vertices against the parts below, and along -z from their vertices
    against the new part, give the free fall (no physics engine: parts rest where they
    first touch). The `sim.scene.Scene` holds the parts as meshes (ids 2, 3, … in drop
    order; the tray is id 1), so the simulator's ground truth gives per-pixel instance
    ids; the poses (part -> camera frame) and sides are returned beside it.
    `BinScene.occlusion` gives each part's hidden fraction (ray cast), `scan_bin` a quick
    simulated scan (ray-cast truth with depth noise and projector shadows).
  - a bin scanned by `slscan scan --scene bin:SEED[:N_PARTS]` (`bin_spec`; N_PARTS
    defaults to `default_parts(SEED)`, as `slscan bench pose` draws them) keeps its truth
    in the session: `BinTruth` in `bin_truth.json` (format below) beside the simulator's
    `ground_truth.npz`, whose `object_id` map holds the per-pixel instance ids.

Bin truth file (`BIN_TRUTH_FORMAT`, version 1; mm, 4x4 matrices mapping part-frame points
into the named frame): `seed`, `tray_mm`, `part` (the TabPart parameters),
`world_from_camera` (the rig's), `camera_mm` (the camera centre in the world frame, where
the occlusion was cast from) and per part, in drop order: `id` (its object id in
`ground_truth.npz`), `front_up`, `world_from_part`, `camera_from_part`, `occlusion` (the
hidden fraction of its camera-facing face, `BinScene.occlusion`).

Units: mm, rad.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
from pydantic import Field

from inspection.bins.part_file import TabPart, inside_loops, outline_loops, tab_part
from scanner import schema
from scanner.errors import ConfigError
from sim.scene import BIN_SCENE_PREFIX, Scene, SceneObject

if TYPE_CHECKING:
    from scanner.geometry import RigModel
    from scanner.pointcloud import OrganisedCloud

BIN_TRUTH_FILE = "bin_truth.json"
BIN_TRUTH_FORMAT = "slscan-bin-truth"
BIN_TRUTH_VERSION = 1
NICKEL_TAB = TabPart()  # the default part of a simulated bin: paper 001's nickel tab

def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """The 3x3 rotation by `angle` (rad) about the unit `axis` (Rodrigues)."""
    k = np.asarray(axis, float)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


# ------------------------------------------------------------------------------- bins


@dataclass(frozen=True, eq=False)
class BinScene:
    """A simulated bin: the scene (parts as meshes, ids 2.. in drop order; the tray is the
    reference plane, id 1), each part's pose (part frame -> camera frame, 4x4 mm) and
    whether its front face (part +z) faces the camera; `seed` it was drawn with."""

    scene: Scene
    part: TabPart
    poses: np.ndarray
    front_up: np.ndarray
    tray_mm: float
    seed: int = 0

    @property
    def object_ids(self) -> np.ndarray:
        return np.arange(2, 2 + len(self.poses))

    def occlusion(self, camera_mm: np.ndarray | None = None, spacing_mm: float = 0.2) -> np.ndarray:
        """Per part, the fraction (0..1) of its face toward the camera that other parts hide
        from the camera centre `camera_mm` (scene frame; None: its origin): rays from the camera
        to face samples every `spacing_mm`, hidden where another part is hit first."""
        import open3d as o3d

        camera_mm = np.zeros(3) if camera_mm is None else camera_mm
        verts, tris = self.part.mesh()
        lo, hi = verts[:, :2].min(axis=0), verts[:, :2].max(axis=0)
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0], spacing_mm), np.arange(lo[1], hi[1], spacing_mm))
        grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
        grid = grid[inside_loops(grid, outline_loops(self.part))]
        rc = o3d.t.geometry.RaycastingScene()
        cpu = o3d.core.Device("CPU:0")
        for o in self.scene.objects:
            rc.add_triangles(o3d.core.Tensor(o.world_vertices().astype(np.float32), o3d.core.float32, cpu),
                             o3d.core.Tensor(tris.astype(np.uint32), o3d.core.uint32, cpu))
        out = np.zeros(len(self.poses))
        for k, (T, up) in enumerate(zip(self.poses, self.front_up)):
            z = self.part.thickness_mm if up else 0.0
            face = np.c_[grid, np.full(len(grid), z)] @ T[:3, :3].T + T[:3, 3]
            d = face - camera_mm
            dist = np.linalg.norm(d, axis=1)
            rays = np.c_[np.broadcast_to(camera_mm, d.shape), d / dist[:, None]].astype(np.float32)
            ans = rc.cast_rays(o3d.core.Tensor(rays, o3d.core.float32, cpu))
            hit_t, geom = ans["t_hit"].numpy(), ans["geometry_ids"].numpy()
            out[k] = np.mean((hit_t < dist - 1e-3) & (geom != k))
        return out


def default_parts(seed: int) -> int:
    """Parts in the bin of `seed` when the count is not given: 5..20, as `slscan bench pose` draws them."""
    return 5 + seed % 16


def bin_spec(text: str) -> tuple[int, int] | None:
    """(seed, parts) of a bin scene named `bin:SEED[:N_PARTS]`, None for any other scene
    name (a scene TOML or mesh path)."""
    if not text.startswith(BIN_SCENE_PREFIX):
        return None
    fields_ = text[len(BIN_SCENE_PREFIX):].split(":")
    try:
        seed = int(fields_[0])
        parts = int(fields_[1]) if len(fields_) > 1 else default_parts(seed)
    except ValueError:
        seed, parts = -1, -1
    if len(fields_) > 2 or seed < 0 or not 1 <= parts <= 100:
        raise ConfigError("--scene", None, f"{text!r}: a bin scene is bin:SEED or bin:SEED:N_PARTS "
                                           "(SEED >= 0, 1 <= N_PARTS <= 100)")
    return seed, parts


class _TruthPart(schema.Schema):
    id: Annotated[int, Field(strict=True, ge=2)]
    front_up: schema.Bool
    world_from_part: schema.Matrix4
    camera_from_part: schema.Matrix4
    occlusion: Annotated[float, Field(strict=True, ge=0, le=1)]


class BinTruthFile(schema.Schema):
    """`bin_truth.json` (see the module docstring)."""

    format: Literal["slscan-bin-truth"]
    version: Literal[1]
    seed: Annotated[int, Field(strict=True, ge=0)]
    tray_mm: schema.PositiveFloat
    part: dict[str, float | list[float]]
    world_from_camera: schema.Matrix4
    camera_mm: schema.Vector3
    parts: Annotated[list[_TruthPart], Field(min_length=1)]


@dataclass(frozen=True, eq=False)
class BinTruth:
    """What a saved bin's poses are judged against: per part (drop order) its object id
    in the ground-truth id map, `camera_from_part` (K, 4, 4) mm, `front_up` and true
    `occlusion` (fraction of its camera-facing face hidden); the part, tray and seed."""

    seed: int
    part: TabPart
    tray_mm: float
    ids: np.ndarray
    camera_from_part: np.ndarray
    world_from_camera: np.ndarray
    front_up: np.ndarray
    occlusion: np.ndarray

    @classmethod
    def of(cls, b: BinScene, world_from_camera: np.ndarray) -> BinTruth:
        """The truth of bin `b` scanned by a camera placed in the world by `world_from_camera`."""
        W = np.asarray(world_from_camera, dtype=np.float64)
        return cls(b.seed, b.part, b.tray_mm, b.object_ids, np.linalg.inv(W) @ b.poses, W, np.asarray(b.front_up),
                   b.occlusion(W[:3, 3]))

    def save(self, path: Path) -> None:
        from scanner.session import write_json

        W = self.world_from_camera
        write_json(Path(path), {
            "format": BIN_TRUTH_FORMAT, "version": BIN_TRUTH_VERSION, "seed": self.seed, "tray_mm": self.tray_mm,
            "part": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self.part).items()},
            "world_from_camera": W, "camera_mm": W[:3, 3],
            "parts": [{"id": int(i), "front_up": bool(up), "world_from_part": W @ T, "camera_from_part": T,
                       "occlusion": float(o)}
                      for i, up, T, o in zip(self.ids, self.front_up, self.camera_from_part, self.occlusion)]})

    @classmethod
    def load(cls, path: Path) -> BinTruth:
        """The truth file `path` validated (a ConfigError naming the file and key otherwise)."""
        path = Path(path)
        try:
            raw = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ConfigError(path, None, f"not a readable bin truth file: {exc}") from None
        doc = schema.parse(BinTruthFile, raw, path)
        try:
            part = tab_part(doc.part)
        except (TypeError, ValueError) as exc:
            raise ConfigError(path, "part", str(exc)) from None
        return cls(doc.seed, part, doc.tray_mm, np.array([p.id for p in doc.parts]),
                   np.array([p.camera_from_part for p in doc.parts]), np.array(doc.world_from_camera),
                   np.array([p.front_up for p in doc.parts]), np.array([p.occlusion for p in doc.parts]))


def scan_bin(b: BinScene, model: RigModel, noise_mm: float = 0.01, seed: int = 0) -> tuple[OrganisedCloud, np.ndarray]:
    """A quick simulated scan of bin `b` with the rig `model` (`scanner.geometry.RigModel`):
    the simulator's ray-cast ground truth (no fringe rendering or decoding), Gaussian depth
    noise of `noise_mm` along each camera ray, pixels the projector does not light left
    invalid (as a fringe scan leaves shadows), normals from the noisy points as the scanner
    computes them. Returns (`OrganisedCloud` in the camera frame, object ids (H, W): 0
    nothing, 1 tray, 2.. parts in drop order)."""
    from scanner.pointcloud import OrganisedCloud, organised_normals
    from sim.render import compute_ground_truth

    gt = compute_ground_truth(model, b.scene)
    rng = np.random.default_rng(seed)
    ray = gt.points / np.linalg.norm(gt.points, axis=2, keepdims=True)
    pts = gt.points + rng.normal(0.0, noise_mm, gt.shape)[..., None] * ray
    pts[~gt.lit] = np.nan
    pts = pts.astype(np.float32)
    normals = organised_normals(pts[..., 0], pts[..., 1], pts[..., 2])
    ids = np.where(gt.lit, gt.object_id, 0).astype(np.int32)
    return OrganisedCloud(pts, np.zeros(gt.shape, np.uint8), normals), ids


def fringe_scan_bin(b: BinScene, seed: int = 0) -> tuple[OrganisedCloud, np.ndarray]:
    """Bin `b` scanned through the whole simulated chain on the default rig: its fringe
    patterns rendered with sensor noise and blur, decoded and triangulated (pixels that
    straddle a part's edge decode to depths mixed with what lies behind, as on a real
    scanner). Returns (`OrganisedCloud` in the camera frame, object ids (H, W) as
    `scan_bin`)."""
    from scanner.acquisition import AcquisitionSettings, acquire
    from scanner.decode import decode
    from scanner.patterns import PatternSet
    from scanner.reconstruct import Triangulator, triangulate
    from scanner.rig import RigConfig, open_rig

    config = RigConfig.load()
    patterns = PatternSet.load(config.patterns_path)
    with open_rig(config, scene=b.scene, seed=seed) as rig:
        stack = acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda k, f: None)
        cloud = triangulate(decode(stack, patterns, rig.camera.bit_depth, rig.model.projector.size),
                            Triangulator(rig.model))
        ids = np.asarray(rig.extras["ground_truth"].object_id).astype(np.int32)
    return cloud, ids


def bin_scene(n_parts: int, *, seed: int = 0, part: TabPart = NICKEL_TAB, tray_mm: float = 420.0,
              spread_mm: tuple[float, float] = (30.0, 24.0), max_tilt_rad: float = np.radians(6.0),
              drop_height_mm: float = 30.0) -> BinScene:
    """`n_parts` parts dropped at random onto a tray `tray_mm` from the camera, their
    positions uniform in ±`spread_mm` (x, y) around the camera axis (see the module
    docstring)."""
    import open3d as o3d

    if not 1 <= n_parts <= 100:
        raise ValueError(f"n_parts must be 1..100, got {n_parts}")
    rng = np.random.default_rng(seed)
    verts, tris = part.mesh()
    centre = np.r_[(verts[:, :2].min(axis=0) + verts[:, :2].max(axis=0)) / 2, 0.0]
    local = verts - centre   # part frame centred on the outline's box (for placing)
    placed_v: list[np.ndarray] = []
    placed_t: list[np.ndarray] = []
    poses, front = [], []
    for _ in range(n_parts):
        up = bool(rng.integers(2))
        base = np.diag([1.0, -1.0, -1.0]) if up else np.eye(3)   # front (+z) toward the camera (-z)
        axis = np.r_[rng.normal(size=2), 0.0]
        tilt = rotation_about(axis / np.linalg.norm(axis), rng.uniform(0, max_tilt_rad))
        R = tilt @ rotation_about(np.array([0.0, 0.0, 1.0]), rng.uniform(-np.pi, np.pi)) @ base
        xy = rng.uniform(-1, 1, 2) * np.asarray(spread_mm)
        world = local @ R.T
        world += np.r_[xy, tray_mm - drop_height_mm - world[:, 2].max()]
        fall = float(tray_mm - world[:, 2].max())   # down to the tray
        if placed_v:
            fall = min(fall, _free_fall(o3d, world, tris, placed_v, placed_t))
        world[:, 2] += fall
        placed_v.append(world)
        placed_t.append(tris)
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = world.mean(axis=0) - (local @ R.T).mean(axis=0) - R @ centre
        poses.append(T)
        front.append(up)
    objects = tuple(SceneObject(name=f"tab{i:02d}", kind="mesh", pose=T, albedo=0.6, vertices=verts, triangles=tris)
                    for i, T in enumerate(poses))
    tray = SceneObject(name="reference_plane", kind="plane", pose=_translation(0.0, 0.0, tray_mm), albedo=0.8,
                       size_mm=(400.0, 400.0))
    scene = Scene(objects=objects, reference_plane=tray, name=f"bin-{n_parts}-{seed}")
    return BinScene(scene, part, np.array(poses), np.array(front), tray_mm, seed)


def _free_fall(o3d: object, moving: np.ndarray, tris: np.ndarray, fixed_v: list[np.ndarray],
               fixed_t: list[np.ndarray]) -> float:
    """How far (mm) `moving` (a mesh's world vertices) can move along +z before it touches
    a fixed mesh: rays along +z from its vertices onto the fixed meshes, and along -z from
    the fixed vertices onto it (inf when nothing is below)."""
    core = o3d.core  # type: ignore[attr-defined]  # Open3D's stubs omit core
    below = o3d.t.geometry.RaycastingScene()  # type: ignore[attr-defined]  # stubs omit o3d.t
    for v, t in zip(fixed_v, fixed_t):
        below.add_triangles(core.Tensor(v.astype(np.float32)), core.Tensor(t.astype(np.uint32)))
    down = np.c_[moving, np.tile([0.0, 0.0, 1.0], (len(moving), 1))].astype(np.float32)
    hit_down = below.cast_rays(core.Tensor(down))["t_hit"].numpy()
    mine = o3d.t.geometry.RaycastingScene()  # type: ignore[attr-defined]  # stubs omit o3d.t
    mine.add_triangles(core.Tensor(moving.astype(np.float32)), core.Tensor(tris.astype(np.uint32)))
    fixed = np.concatenate(fixed_v)
    up = np.c_[fixed, np.tile([0.0, 0.0, -1.0], (len(fixed), 1))].astype(np.float32)
    hit_up = mine.cast_rays(core.Tensor(up))["t_hit"].numpy()
    return float(min(hit_down.min(), hit_up.min()))


def _translation(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T
