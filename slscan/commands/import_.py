"""`slscan import`: a folder of fringe frames captured by any tool becomes a normal session.

    slscan import FRAMES --patterns PATTERNS.toml --projector-size WxH --out SESSION
                  [--calibration FILE [--projector-scale S]] [--frames GLOB] [--bit-depth B]

Frames are taken in natural order (`2.bmp` before `10.bmp`): 8- or 16-bit grey PNG, BMP or
TIFF (colour frames are converted to grey). They are hard-linked into the session (copied
across file systems; colour frames written as grey PNG), and the manifest names where each
came from (`import.sources`). Convention keys the pattern file leaves out are detected from the frames
(scanner/convention_detection.py); the manifest's `import.conventions` and the output say what was given,
detected or assumed and on what evidence. With `--calibration` (ours, SLMaster's
caliInfo.yml or procam's calibration_result.xml: scanner/foreign_calibration.py) the session
gets a cloud; without one, the decoded maps only. The session then decodes like any other
(`slscan decode SESSION` regenerates it).
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import os
import re
import shutil
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanner.errors import SessionError
from slscan.exit_codes import Exit
from slscan.options import add_json

if TYPE_CHECKING:
    import numpy as np

    from scanner.session import SessionWriter

IMAGE_SUFFIXES = (".png", ".bmp", ".tif", ".tiff")
BIT_DEPTHS = (10, 12, 14, 16)


def natural_key(name: str) -> list[Any]:
    """Sort key putting `2.bmp` before `10.bmp`: digit runs compare as numbers."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def list_frames(folder: Path, pattern: str | None) -> list[Path]:
    """The frame files of `folder` in natural order: those matching the glob `pattern`, or
    every PNG, BMP and TIFF file."""
    if not folder.is_dir():
        raise SessionError(f"{folder}: no such folder of frames")
    files = [p for p in folder.iterdir() if p.is_file() and
             (fnmatch.fnmatch(p.name, pattern) if pattern else p.suffix.lower() in IMAGE_SUFFIXES)]
    if not files:
        raise SessionError(f"{folder}: no frames" + (f" matching '{pattern}'" if pattern else
                                                     f" ({', '.join(IMAGE_SUFFIXES)})"))
    return sorted(files, key=lambda p: natural_key(p.name))


def read_frames(files: list[Path]) -> tuple[np.ndarray, list[bool]]:
    """(N, H, W) stack of grey frames and, per frame, whether it was converted from colour;
    SessionError naming the file that is unreadable or of another size or type."""
    import cv2
    import numpy as np

    stack, converted = None, []
    for k, path in enumerate(files):
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise SessionError(f"{path}: frame {k} unreadable (not a PNG, BMP or TIFF image?)")
        colour = img.ndim == 3
        if colour:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if img.dtype not in (np.uint8, np.uint16):
            raise SessionError(f"{path}: frame {k} is {img.dtype}; frames must be 8- or 16-bit")
        if stack is None:
            stack = np.empty((len(files), *img.shape), dtype=img.dtype)
        elif img.shape != stack.shape[1:] or img.dtype != stack.dtype:
            raise SessionError(f"{path}: frame {k} is {img.dtype} {img.shape[1]} x {img.shape[0]}, frame 0 is "
                               f"{stack.dtype} {stack.shape[2]} x {stack.shape[1]}")
        stack[k] = img
        converted.append(colour)
    assert stack is not None
    return stack, converted


def bit_depth_of(stack: np.ndarray) -> int:
    """8 for 8-bit frames; for 16-bit ones the least of 10, 12, 14, 16 bits holding the
    brightest value (cameras store 10- and 12-bit samples in 16-bit files)."""
    import numpy as np

    if stack.dtype == np.uint8:
        return 8
    top = int(stack.max())
    return next(b for b in BIT_DEPTHS if top <= 2 ** b - 1)


def _store(writer: SessionWriter, k: int, src: Path, image: np.ndarray, converted: bool, bit_depth: int,
           *, camera: str | None = None) -> bool:
    """Put frame k into the session: a hard link to `src` (a copy across file systems), or
    the grey image as PNG when it was converted from colour. Returns whether it is a link.
    `camera`: a frame of that camera of a binocular capture, under frames/<camera>/."""
    import cv2

    from scanner.session import FRAME_LOG, FRAMES_DIR, sha256

    linked = False
    folder = FRAMES_DIR if camera is None else f"{FRAMES_DIR}/{camera}"
    (writer.root / folder).mkdir(exist_ok=True)
    if converted:
        name = f"frame_{k:03d}.png"
        ok, png = cv2.imencode(".png", image)
        if not ok:
            raise SessionError(f"{src}: could not encode frame {k} as PNG")
        (writer.root / folder / name).write_bytes(png.tobytes())
    else:
        name = f"frame_{k:03d}{src.suffix.lower()}"
        dst = writer.root / folder / name
        try:
            os.link(src, dst)
            linked = True
        except OSError:
            shutil.copyfile(src, dst)
    entry = {"k": k, "file": f"{folder}/{name}", "index": k, "pattern_index": k, "timestamp_s": 0.0,
             "exposure_s": 0.0, "bit_depth": bit_depth, "shape": list(image.shape), "dtype": str(image.dtype),
             "sha256": sha256((writer.root / folder / name).read_bytes())}
    (writer.frames if camera is None else writer.camera_frames.setdefault(camera, [])).append(entry)
    with (writer.root / FRAME_LOG).open("a") as f:
        f.write(json.dumps(entry) + "\n")
    return linked


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 2 or int(m.group(2)) < 2:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, e.g. 1920x1080, got '{text}'")
    return int(m.group(1)), int(m.group(2))


def import_frames(folder: Path, patterns_path: Path, projector_size: tuple[int, int], out: Path,
                  *, calibration: Path | None = None, projector_scale: float = 1.0, frames_glob: str | None = None,
                  bit_depth: int | None = None, progress: Any = None) -> Any:
    """Import and process one capture (module docstring); returns (ScanResult, Detection)."""
    import numpy as np

    from scanner.convention_detection import detect
    from scanner.foreign_calibration import read_calibration
    from scanner.geometry import Pinhole, RigModel, look_at
    from scanner.patterns import PatternSet
    from scanner.pipeline import process
    from scanner.session import ImportedCalibration, ImportRecord, SessionWriter

    t0 = time.perf_counter()
    files = list_frames(folder, frames_glob)
    stack, converted = read_frames(files)
    depth = bit_depth or bit_depth_of(stack)
    if (stack.dtype == np.uint8 and depth != 8) or depth > 16 or int(stack.max()) > 2 ** depth - 1:
        raise SessionError(f"--bit-depth {depth} does not fit {stack.dtype} frames whose brightest value is "
                           f"{int(stack.max())}")
    camera_size = (stack.shape[2], stack.shape[1])
    patterns = PatternSet.load(patterns_path, detect=True)
    model, calibration_read = None, None
    if calibration is not None:
        model, source = read_calibration(calibration, camera_size, projector_size, projector_scale)
        calibration_read = ImportedCalibration(file=str(Path(calibration).resolve()), format=source,
                                               projector_scale=projector_scale)
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    detection = detect(stack, patterns, depth, projector_size, model)
    t_detect = time.perf_counter() - t0
    calibrated = model is not None
    if model is None:  # a nominal placeholder carrying the image sizes; never triangulated (calibrated: false)
        cam = Pinhole.from_fov(*camera_size, 40.0)
        model = RigModel(cam, Pinhole.from_fov(*projector_size, 30.0),
                         look_at(np.array([100.0, 0.0, 0.0]), np.array([0.0, 0.0, 500.0])))
    writer = SessionWriter.create(out)
    linked = [_store(writer, k, f, stack[k], c, depth) for k, (f, c) in enumerate(zip(files, converted))]
    info = ImportRecord(source_folder=str(folder.resolve()), sources=[str(f.resolve()) for f in files],
                        frames_glob=frames_glob, patterns_file=str(patterns_path), projector_size=list(projector_size),
                        bit_depth=depth, hard_linked=sum(linked), copied=len(linked) - sum(linked),
                        calibration=calibration_read, conventions=detection.record())
    writer.finish({"name": f"imported from {folder}", "driver": "import"}, model, detection.patterns, {},
                  {"read": round(t_read, 4), "detect": round(t_detect, 4)},
                  {"import": info, "calibrated": calibrated})
    from scanner.session import Session

    result = process(Session.open(writer.root), progress or (lambda *a: None))
    return result, detection


def cmd_import(args: argparse.Namespace) -> int:
    from slscan.progress import ProgressLine

    if len(args.frames_folder) > 1 or len(args.calibration or []) > 1:  # two: slscan/commands/import_binocular.py
        raise SessionError("one folder of frames and one --calibration, or two folders (left, right) of a binocular "
                           "capture and its stereo calibration")
    t0 = time.perf_counter()
    args.frames_folder, args.calibration = args.frames_folder[0], (args.calibration or [None])[0]
    result, detection = import_frames(Path(args.frames_folder), Path(args.patterns), args.projector_size,
                                      Path(args.out), calibration=Path(args.calibration) if args.calibration else None,
                                      projector_scale=args.projector_scale, frames_glob=args.frames,
                                      bit_depth=args.bit_depth, progress=ProgressLine())
    wall = time.perf_counter() - t0
    lines = sys.stderr if args.json else sys.stdout  # with --json: the JSON alone on stdout
    manifest = result.session.manifest
    assert manifest.imported is not None  # written by import_frames
    print(f"imported  {len(manifest.frames)} frames from {args.frames_folder} "
          f"({manifest.imported.hard_linked} hard-linked)", file=lines)
    print("conventions", file=lines)
    for f in detection.findings:
        print(f"  {f.line()}", file=lines)
    from slscan.commands.scan import report

    report(result, as_json=args.json)
    print(f"wall      {wall:.2f} s (import, detect, decode, reconstruct, write)", file=lines)
    return Exit.OK


def register(sub: Any) -> argparse.ArgumentParser:
    """`slscan import`'s parser (slscan/commands/import_binocular.py registers it, giving it the
    function that also takes two folders)."""
    p = sub.add_parser("import")
    p.add_argument("frames_folder", metavar="FRAMES", nargs="+",
                   help="folder of frames, taken in natural file-name order; two folders (left, right): a binocular "
                        "capture, reconstructed by matching the cameras (slscan/commands/import_binocular.py)")
    p.add_argument("--patterns", required=True, help="pattern set TOML (config/patterns/ has SLMaster's and "
                                                     "OpenCV's); convention keys left out are detected")
    p.add_argument("--projector-size", type=_size, required=True, metavar="WxH",
                   help="projector pixels, e.g. 1920x1080")
    p.add_argument("--out", required=True, help="new session folder")
    p.add_argument("--calibration", nargs="+", metavar="FILE",
                   help="calibration: slscan's calibration.json, SLMaster's caliInfo.yml or procam's "
                        "calibration_result.xml (without one: maps only, no cloud); binocular: the stereo calibration "
                        "(slscan's stereo_calibration.json, SLMaster's binocular caliInfo.yml, or OpenCV's "
                        "intrinsics.yml extrinsics.yml)")
    p.add_argument("--projector-scale", type=float, default=1.0, metavar="S",
                   help="the calibration's projector coordinates are S times the frames' (procam: its graycode_step)")
    p.add_argument("--frames", metavar="GLOB", help="only the files matching GLOB (default: every PNG, BMP, TIFF)")
    p.add_argument("--bit-depth", type=int, help="bits per sample of 16-bit frames (default: from the brightest)")
    add_json(p)
    p.set_defaults(func=cmd_import)
    return p

