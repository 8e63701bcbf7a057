"""`slscan pose`: poses of thin flat parts in a bin for a robot cell (paper 001); their
benchmark on simulated and saved bins is `slscan bench pose` (`slscan.commands.bench.pose`).

`slscan pose SESSION|CLOUD --part FILE [--masks PATH] [--method sac-ia|ndt]` finds the part
instances (from instance masks aligned with the camera image — label PNGs or Labelme JSON
— or, without masks, the flat patches above the tray: `inspection.bins.flat_patches`),
estimates each instance's pose (`inspection.bins.pose`), ranks the pickable ones
(`inspection.bins.picking`), writes the poses file (`<session>/outputs/poses.json`, or
`<cloud stem>.poses.json` beside a cloud file), prints the table and logs the bin to a
Rerun recording beside the poses file. A cloud file is placed on the camera image of the
rig (`--rig`, default the simulated bench rig), as slscan's own clouds are in its camera
frame; without `--rig` the poses file has no world frame (camera frame only), so a robot
cell never reads an identity it did not ask for. The part file is a TOML `[part]` table
(`kind = "tab"`: the parameters of `inspection.bins.part_file.TabPart`, see config/parts/nickel_tab.toml) or
a mesh (PLY, STL, OBJ, OFF; mm).
Exit code 0 when at least one part is pickable, 1 when none is (the file is written anyway).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slscan.exit_codes import Exit
from slscan.options import add_json, coarse_method

if TYPE_CHECKING:
    import numpy as np

MESH_SUFFIXES = (".ply", ".stl", ".obj", ".off")
POSE_METHODS = {"sac-ia": "sacia", "ndt": "ndt"}  # the command line's spelling -> inspection.bins' name


def register(sub: Any) -> None:
    p = sub.add_parser("pose")
    p.add_argument("input", help="a session folder or a point cloud file in the camera frame")
    p.add_argument("--part", required=True, help="part file: TOML with a [part] table (kind = \"tab\") or a mesh (mm)")
    p.add_argument("--masks", help="instance masks aligned with the camera image: a label PNG, a Labelme JSON, or "
                                   "a folder of them (default: the flat patches above the tray)")
    p.add_argument("--method", type=coarse_method, choices=tuple(POSE_METHODS), default="sac-ia",
                   help="coarse registration: FPFH + SAC-IA with the Huber score (default) or NDT")
    p.add_argument("--max-occlusion", type=float, default=0.15, metavar="FRACTION",
                   help="the most a part offered for picking may be covered: its occlusion estimate plus the "
                        "estimate's error bound (0.05) at most this (default 0.15)")
    p.add_argument("--rig", type=Path, help="rig TOML for a cloud file: its camera image and world frame (default: "
                                            "the simulated bench rig's camera, and no world frame: poses in the "
                                            "camera frame only)")
    p.add_argument("--out", help="poses file (.json); default <session>/outputs/poses.json or <cloud>.poses.json")
    p.add_argument("--no-log", action="store_true", help="do not write the Rerun recording")
    add_json(p)
    p.set_defaults(func=cmd_pose)

# ------------------------------------------------------------------------------ inputs


def load_part(path: str | Path) -> Any:
    """The `inspection.bins.part_model.ThinPartModel` of a part file (see the module
    docstring), with the grip point and approach a TOML part file names."""
    from dataclasses import replace

    from inspection.bins.part_model import ThinPartModel
    from inspection.errors import CadError

    path = Path(path)
    if not path.is_file():
        raise CadError(path, "no such part file")
    suffix = path.suffix.lower()
    if suffix == ".toml":
        from inspection.bins.part_file import load_part_file

        spec = load_part_file(path)
        model = ThinPartModel.from_mesh(*spec.part.mesh(), spec.name)
        return replace(model, grip_point_mm=spec.grip_point_mm, approach=spec.approach)
    if suffix in MESH_SUFFIXES:
        from scanner.mesh_files import read_mesh

        vertices, triangles = read_mesh(path)
        if len(triangles) == 0:
            raise CadError(path, "no triangles could be read (unreadable or empty mesh)")
        return ThinPartModel.from_mesh(vertices, triangles, path.stem)
    raise CadError(path, f"unsupported part file: expected .toml or a mesh ({', '.join(MESH_SUFFIXES)})")


def _organise(points: np.ndarray, normals: np.ndarray | None, camera: Any, where: str) -> Any:
    """An organised cloud on `camera`'s image from camera-frame points (nearest point per
    pixel), with normals from the organised points where none are given."""
    import numpy as np

    from inspection.errors import CloudError
    from scanner.pointcloud import OrganisedCloud, organised_normals

    px = np.rint(camera.project(points)).astype(np.int64)
    inside = (px[:, 0] >= 0) & (px[:, 0] < camera.width) & (px[:, 1] >= 0) & (px[:, 1] < camera.height)
    if not inside.any():
        raise CloudError(where, "no point projects into the rig's camera image: not a cloud in this rig's camera frame")
    order = np.argsort(-points[inside, 2])   # farthest first: the nearest point of a pixel is written last
    sel = np.flatnonzero(inside)[order]
    grid = np.full((camera.height, camera.width, 3), np.nan, np.float32)
    grid[px[sel, 1], px[sel, 0]] = points[sel]
    nrm = organised_normals(grid[..., 0], grid[..., 1], grid[..., 2])
    if normals is not None:
        nrm[px[sel, 1], px[sel, 0]] = normals[sel]
    return OrganisedCloud(grid, np.zeros(grid.shape[:2], np.uint8), nrm)


def load_scene(path: Path, rig: Path | None) -> tuple[Any, Any, Any]:
    """(organised cloud, rig model, session or None) of a session or a cloud file (placed
    on the camera of the rig TOML `rig`, default the simulated bench rig)."""
    import numpy as np

    from inspection.errors import CloudError
    from scanner.rig import RigConfig

    if path.is_dir():
        from scanner.pointcloud import OrganisedCloud, organised_normals
        from scanner.session import Session
        from slscan.commands.segment import _session_points

        session = Session.open(path)
        points, valid = _session_points(session)
        grid = np.full(valid.shape + (3,), np.nan, np.float32)
        grid[valid] = points
        cloud = OrganisedCloud(grid, np.zeros(valid.shape, np.uint8),
                               organised_normals(grid[..., 0], grid[..., 1], grid[..., 2]))
        return cloud, session.rig_model(), session
    if not path.exists():
        raise CloudError(path, "no such cloud file or session folder")
    from scanner.mesh_files import read_points

    points, normals = read_points(path)
    if len(points) == 0:
        raise CloudError(path, "no points could be read (unreadable or empty cloud)")
    model = RigConfig.load(rig).model if rig is not None else RigConfig.load().nominal_model()
    return _organise(points, normals, model.camera, str(path)), model, None


def load_masks(path: Path, cloud: Any) -> list[Any]:
    """Instances from a label PNG, a Labelme JSON, or a folder of them (ids numbered on
    across files)."""
    from inspection.bins.instances import instances_from_label_image, read_label_image, read_labelme
    from inspection.errors import MaskError

    files = sorted(f for f in path.iterdir() if f.suffix.lower() in (".png", ".json")) if path.is_dir() else [path]
    if not path.exists():
        raise MaskError(f"{path}: no such mask file or folder")
    if not files:
        raise MaskError(f"{path}: no label PNG or Labelme JSON files in the folder")
    h, w = cloud.valid.shape
    out: list[Any] = []
    for f in files:
        if f.suffix.lower() == ".json":
            ids, names = read_labelme(f, (w, h))
        elif f.suffix.lower() == ".png":
            ids, names = read_label_image(f), None
        else:
            raise MaskError(f"{f}: not a label PNG or a Labelme JSON file")
        try:
            found = instances_from_label_image(ids, cloud, names=names)
        except MaskError as exc:
            raise MaskError(f"{f}: {exc}") from None
        base = max((i.id for i in out), default=0)
        out += [type(i)(i.id + base, i.indices, i.points, i.normals, i.source, i.mask, i.label, i.score) for i in found]
    return out


# ------------------------------------------------------------------------------ pose


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """One BLAS and one OpenCV thread inside (restored after): the per-part matrices and
    grids are small, and a second thread costs more CPU than it saves (its start-up and
    waits are CPU time too), most of all on a busy machine. Results do not change. Both
    limits are process-wide: for the command line, not for a thread beside others."""
    from scanner.native_threads import native_threads, opencv_threads

    with opencv_threads(1), native_threads(1, openmp=True):
        yield


def pose_scene(cloud: Any, camera: Any, model: Any, settings: Any, instances: list[Any] | None = None) -> tuple:
    """(instances, poses) of a scanned bin, as `slscan pose` finds them: the given
    instances (from masks), or else the flat patches above the tray; each posed with the
    organised scan as context (`camera` projects camera-frame points onto its image), in
    `one_thread`."""
    from inspection.bins.flat_patches import instances_from_flat_patches
    from inspection.bins.instance_plane import SceneContext
    from inspection.bins.picking import merge_duplicates
    from inspection.bins.pose import estimate_poses

    with one_thread():
        if instances is None:
            instances = instances_from_flat_patches(cloud, model.thickness_mm)
        context = SceneContext.of_cloud(cloud, camera)
        return instances, merge_duplicates(estimate_poses(instances, model, context, settings), model)


def rig_of(rig_model: Any, session: Any, rig_file: Path | None) -> tuple[np.ndarray | None, dict[str, Any] | None]:
    """(world_from_camera, the poses file's `rig` entry) of a session (its rig), or of a
    cloud file with `--rig` (that rig); a cloud file without one has no world frame (None, None)."""
    import numpy as np

    calibration = rig_model.calibration or "nominal (uncalibrated)"
    if session is not None:
        name = session.manifest.recorded_rig.rig.name
        return (np.asarray(rig_model.world_from_cam, np.float64),
                {"name": name, "calibration": calibration, "session": session.id})
    if rig_file is None:
        return None, None
    from scanner.rig import RigConfig

    return (np.asarray(rig_model.world_from_cam, np.float64),
            {"name": RigConfig.load(rig_file).name, "calibration": calibration, "file": str(rig_file)})


def cmd_pose(args: argparse.Namespace) -> int:
    from inspection.bins.picking import poses_document, table, write_poses
    from inspection.bins.pose_settings import PoseSettings

    model = load_part(args.part)
    src = Path(args.input)
    cloud, rig_model, session = load_scene(src, args.rig)
    world_from_cam, rig = rig_of(rig_model, session, args.rig)
    if session is not None:
        out = Path(args.out) if args.out else session.outputs / "poses.json"
    else:
        out = Path(args.out) if args.out else src.with_name(src.stem + ".poses.json")
    if out.suffix != ".json":
        from scanner.errors import ScannerError

        raise ScannerError(f"{out}: the poses file must end in .json")
    masks = load_masks(Path(args.masks), cloud) if args.masks else None
    how = f"masks {args.masks}" if args.masks else "flat patches above the tray"
    settings = PoseSettings(method=POSE_METHODS[args.method], max_occlusion=args.max_occlusion)
    instances, poses = pose_scene(cloud, rig_model.camera, model, settings, masks)
    print(f"{len(instances)} instances in {src} ({how}); part {model.name}, method {args.method}", file=sys.stderr)
    message = ""
    if not instances:
        message = (f"no parts found in {src}: no instance in the masks" if args.masks else
                   f"no parts found in {src}: nothing stands above the tray plane")
    elif not any(p.ok for p in poses):
        message = f"no part recognised in {src}: none of the {len(poses)} instances fits {model.name}"
    doc = poses_document(poses, model, world_from_cam, str(src), rig=rig, max_occlusion=args.max_occlusion,
                         message=message)
    write_poses(out, doc)
    text = sys.stderr if args.json else sys.stdout  # --json: the document alone on stdout
    print(table(doc), file=text)
    print(f"poses     {out}", file=text)
    if not args.no_log:
        from inspection.bins.picking import log_poses
        from scanner.session_recording import SessionRecording

        rrd = out.with_name(out.stem + ".rrd")
        with SessionRecording(rrd, session.id if session is not None else src.stem, send_blueprint=False) as rec:
            rec.log_rig(rig_model)
            rec.log_cloud(cloud)
            log_poses(rec, doc, poses, instances, model)
        print(f"recording {rrd}", file=text)
    if args.json:
        print(json.dumps(doc, default=str))
    return Exit.OK if any(r["pick_rank"] is not None for r in doc["parts"]) else Exit.FAILED
