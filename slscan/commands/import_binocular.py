"""`slscan import LEFT_FRAMES RIGHT_FRAMES`: a binocular capture made by another tool becomes a
binocular session (scanner/binocular_session.py) and a cloud.

    slscan import LEFT_FRAMES RIGHT_FRAMES --patterns P.toml --projector-size WxH
                  --calibration STEREO.yml [EXTRINSICS.yml] --out SESSION [--frames GLOB] [--bit-depth B]

Each folder is read as `slscan import` reads one (natural order, grey PNG/BMP/TIFF, hard-linked
into frames/<camera>/). The pattern set's missing conventions are detected from each camera's
frames on its own (scanner/convention_detection.py); both cameras saw the same patterns, so the two
must agree, or the import is refused naming the key. The stereo calibration (SLMaster's binocular
caliInfo.yml, OpenCV's stereo files, or slscan's: scanner/stereo_calibration_file.py) places the
cameras; no projector calibration is needed. The cloud is in the left (first) camera's frame, in mm,
as the PLY header says: outputs/cloud.ply.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanner.errors import SessionError
from slscan.commands.import_ import _store, bit_depth_of, cmd_import, list_frames, read_frames
from slscan.commands.import_ import register as register_import
from slscan.exit_codes import Exit

if TYPE_CHECKING:
    from scanner.geometry import Pinhole, RigModel
    from scanner.patterns import PatternSet

CAMERAS = ("left", "right")


def placeholder_model(camera: Pinhole, projector_size: tuple[int, int]) -> RigModel:
    """The camera with a nominal projector beside it: what a session's manifest needs to
    name the camera's image; never triangulated (the session says `projector_calibrated`: false)."""
    import numpy as np

    from scanner.geometry import Pinhole, RigModel, look_at

    return RigModel(camera, Pinhole.from_fov(*projector_size, 30.0),
                    look_at(np.array([100.0, 0.0, 0.0]), np.array([0.0, 0.0, 500.0])))


def _agreed(detections: list[Any]) -> PatternSet:
    """The pattern set both cameras' frames say they saw; SessionError naming the first key on
    which they disagree."""
    a, b = (d.patterns.conventions for d in detections)
    if a != b:
        diff = [k for k in a.__dataclass_fields__ if getattr(a, k) != getattr(b, k)]
        raise SessionError(f"the two cameras' frames disagree on the pattern set's conventions ({', '.join(diff)}: "
                           f"{[getattr(a, k) for k in diff]} in the left frames, {[getattr(b, k) for k in diff]} in "
                           f"the right): they were not captured with the same patterns, or a folder holds another "
                           f"capture")
    return detections[0].patterns


def import_binocular(folders: list[Path], patterns_path: Path, projector_size: tuple[int, int], out: Path,
                     calibration: list[str | Path], *, frames_glob: str | None = None, bit_depth: int | None = None,
                     progress: Any = None) -> tuple[Any, list[Any]]:
    """Import and reconstruct one binocular capture (module docstring); returns (BinocularScan,
    the two cameras' convention detections)."""
    import numpy as np

    from scanner.binocular_pipeline import process_binocular
    from scanner.convention_detection import detect
    from scanner.patterns import PatternSet
    from scanner.session import ImportedCalibration, ImportRecord, Session, SessionWriter
    from scanner.stereo_calibration_file import read_stereo_calibration

    if not calibration:
        raise SessionError("a binocular import needs the stereo calibration (--calibration STEREO.yml)")
    t0 = time.perf_counter()
    files = [list_frames(f, frames_glob) for f in folders]
    if len(files[0]) != len(files[1]):
        raise SessionError(f"{folders[0]} holds {len(files[0])} frames, {folders[1]} {len(files[1])}: a binocular "
                           f"frame set needs every pattern from both cameras")
    read = [read_frames(f) for f in files]
    stacks = [r[0] for r in read]
    depths = [bit_depth or bit_depth_of(s) for s in stacks]
    for folder, stack, depth in zip(folders, stacks, depths):
        if (stack.dtype == np.uint8 and depth != 8) or depth > 16 or int(stack.max()) > 2 ** depth - 1:
            raise SessionError(f"{folder}: --bit-depth {depth} does not fit {stack.dtype} frames whose brightest value "
                               f"is {int(stack.max())}")
    sizes = [(s.shape[2], s.shape[1]) for s in stacks]
    stereo, source = read_stereo_calibration(calibration, sizes[0], sizes[1])
    stereo = type(stereo)(stereo.left, stereo.right, stereo.right_from_left, CAMERAS, stereo.epipolar_sigma_px,
                          stereo.calibration)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    patterns = PatternSet.load(patterns_path, detect=True)
    detections = [detect(s, patterns, d, projector_size) for s, d in zip(stacks, depths)]
    agreed = _agreed(detections)
    t_detect = time.perf_counter() - t0
    models = {name: placeholder_model(lens, projector_size) for name, lens in zip(CAMERAS, (stereo.left, stereo.right))}
    writer = SessionWriter.create(out)
    linked = 0
    for name, fs, (stack, converted), depth in zip(CAMERAS, files, read, depths):
        linked += sum(_store(writer, k, f, stack[k], c, depth, camera=name)
                      for k, (f, c) in enumerate(zip(fs, converted)))
    writer.frames = writer.camera_frames.pop(CAMERAS[0])
    info = ImportRecord(source_folders=[str(f.resolve()) for f in folders], frames_glob=frames_glob,
                        patterns_file=str(patterns_path), projector_size=list(projector_size), bit_depth=depths,
                        hard_linked=linked, copied=2 * len(files[0]) - linked,
                        calibration=ImportedCalibration(files=[str(Path(c).resolve()) for c in calibration],
                                                        format=source),
                        conventions={n: d.record() for n, d in zip(CAMERAS, detections)})
    writer.finish({"name": f"imported from {folders[0]} and {folders[1]}", "driver": "import"}, models["left"],
                  agreed, {}, {"read": round(t_read, 4), "detect": round(t_detect, 4)},
                  {"import": info, "calibrated": False, "cameras": list(CAMERAS),
                   "camera_frames": writer.camera_frames, "camera_models": {k: m.to_dict() for k, m in models.items()},
                   "projector_calibrated": False, "stereo_model": stereo.to_dict()})
    scan = process_binocular(Session.open(writer.root), progress or (lambda *a: None))
    return scan, detections


def cmd_import_binocular(args: argparse.Namespace) -> int:
    from scanner.binocular_pipeline import summary
    from slscan.progress import ProgressLine

    t0 = time.perf_counter()
    scan, detections = import_binocular([Path(f) for f in args.frames_folder], Path(args.patterns),
                                        args.projector_size, Path(args.out), [Path(c) for c in args.calibration or []],
                                        frames_glob=args.frames, bit_depth=args.bit_depth, progress=ProgressLine())
    wall = time.perf_counter() - t0
    n = len(scan.session.manifest.frames)
    print(f"imported  {n} frames per camera from {args.frames_folder[0]} (left) and {args.frames_folder[1]} (right)")
    print("conventions (left frames; the right agreed)")
    for f in detections[0].findings:
        print(f"  {f.line()}")
    s = summary(scan)
    print(f"points    {s['points']} of {s['of_pixels']} left pixels with a coordinate ({s['not_unique']} ambiguous, "
          f"{s['low_gradient']} with too little phase change along the epipolar line)")
    print(f"cloud     {scan.cloud_path} (left camera's frame, mm)")
    print(f"wall      {wall:.2f} s (import, detect, decode both cameras, match, write)")
    return Exit.OK


def cmd_import_frames(args: argparse.Namespace) -> int:
    """`slscan import`: two folders are a binocular capture, one goes to the monocular import."""
    return cmd_import_binocular(args) if len(args.frames_folder) == 2 else cmd_import(args)


def register(sub: Any) -> None:
    """`slscan import` (slscan/commands/import_.py's parser) taking LEFT_FRAMES RIGHT_FRAMES too."""
    register_import(sub).set_defaults(func=cmd_import_frames)
