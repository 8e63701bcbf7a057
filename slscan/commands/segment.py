"""`slscan segment` and `slscan segscore`: context-free region growing (paper 002) of a point
cloud file or a session's scan, and the score of a segmentation against ground truth (α, β,
η per ground-truth segment); the benchmark on simulated cluttered clouds is `slscan bench
segment` (`slscan.commands.bench.segment`).

Label files are .npy int32 arrays. For a point cloud file: one label per point, in the
file's order (`<cloud stem>.segments.npy` beside it). For a session: an image of the
camera's size (`outputs/segments.npy`): the segment of the pixel's point, -1 for a point
no segment took, -2 (`NO_POINT`) for a pixel without a point. Segments are numbered in the
order they grew (smoothest seeds first). The Rerun recording (`<...>.segments.rrd`, the
session's id for a session, so it opens together with the session's own recording) has
the segmented points under `world/segments` and, for a session, the label image under
`maps/segments`.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slscan.exit_codes import Exit
from slscan.options import add_json

if TYPE_CHECKING:
    import numpy as np

SEGMENTS = "world/segments"
SEGMENT_MAP = "maps/segments"


def register(sub: Any) -> None:
    p = sub.add_parser("segment")
    p.add_argument("input", help="a point cloud file (PLY, PCD, XYZ ... as Open3D reads) or a session folder")
    p.add_argument("--radius", "-r", type=float, metavar="MM",
                   help="radius of interest r in mm: the coarsest detail that counts (features at 0.19 r .. r); "
                        "default 35 point spacings of the cloud")
    p.add_argument("--out", help="labels file (.npy); default beside the cloud, or <session>/outputs/segments.npy")
    p.add_argument("--no-log", action="store_true", help="do not write the Rerun recording")
    add_json(p)
    p.set_defaults(func=cmd_segment)

    s = sub.add_parser("segscore")
    s.add_argument("labels", help="labels .npy (from slscan segment)")
    s.add_argument("ground_truth", help="ground-truth labels .npy of the same shape (negative: no segment), or a "
                                        "simulated session's ground_truth.npz (its object ids)")
    add_json(s)
    s.set_defaults(func=cmd_segscore)


def cmd_segment(args: argparse.Namespace) -> int:
    import numpy as np

    from inspection.regions.region_growing import DEFAULT_RADIUS_SPACINGS, default_radius, segment
    from inspection.regions.segmetrics import NO_POINT
    from scanner.errors import ScannerError
    from scanner.pointcloud import read_ply_points

    src = Path(args.input)
    session = None
    if src.is_dir():
        from scanner.session import Session

        session = Session.open(src)
        points, valid = _session_points(session)
        out = Path(args.out) if args.out else session.outputs / "segments.npy"
        viewpoint: np.ndarray | None = np.zeros(3)   # the camera, in the camera frame
    elif src.is_file():
        try:
            points = read_ply_points(src)
        except Exception as exc:  # Open3D raises plain RuntimeErrors
            raise ScannerError(f"{src}: cannot read a point cloud: {exc}") from None
        valid, viewpoint = None, None
        out = Path(args.out) if args.out else src.with_name(src.stem + ".segments.npy")
    else:
        raise ScannerError(f"{src}: no such cloud file or session folder")
    if out.suffix != ".npy":
        raise ScannerError(f"{out}: the labels file must end in .npy")
    radius = args.radius if args.radius is not None else default_radius(points)
    how = "" if args.radius is not None else f" (default: {DEFAULT_RADIUS_SPACINGS:g} point spacings)"
    print(f"segmenting {len(points)} points of {src} with r = {radius:g} mm{how}", file=sys.stderr)
    seg = segment(points, radius, viewpoint)
    labels = seg.labels
    if valid is not None:
        image = np.full(valid.shape, NO_POINT, dtype=np.int32)
        image[valid] = labels
        labels_out = image
    else:
        labels_out = labels
    from scanner.session import write_atomic

    buffer = io.BytesIO()
    np.save(buffer, labels_out)
    write_atomic(out, buffer.getvalue())
    sizes = seg.sizes()
    big = np.sort(sizes)[::-1]
    rrd = None if args.no_log else out.with_name(out.stem + ".rrd")
    if rrd is not None:
        _log(rrd, session, points, labels=labels, image=labels_out if valid is not None else None,
             timings=seg.timings_s,
             recording_id=session.id if session is not None else src.stem)
    if args.json:
        print(json.dumps({"status": "ok", "labels": str(out), "radius_mm": radius, "points": len(points),
                          "subsampled": len(seg.subsample), "unsegmented_fraction": float((labels < 0).mean()),
                          "segments": seg.n_segments, "segments_over_1pct": int((sizes >= 0.01 * len(points)).sum()),
                          "largest": [int(s) for s in big[:8]], "timings_s": seg.timings_s,
                          "recording": None if rrd is None else str(rrd)}))
        return Exit.OK
    print(f"labels    {out}")
    print(f"points    {len(points)} ({len(seg.subsample)} after the 0.1 r subsample), "
          f"{(labels < 0).mean() * 100:.1f} % unsegmented")
    print(f"segments  {seg.n_segments} ({int((sizes >= 0.01 * len(points)).sum())} with >= 1 % of the points); "
          f"largest {', '.join(str(int(s)) for s in big[:8])}")
    print("timings   " + ", ".join(f"{k} {v:.2f} s" for k, v in seg.timings_s.items()))
    if rrd is not None:
        print(f"recording {rrd}" + (f"   (view with the session: rerun {session.recording_path} {rrd})"
                                   if session is not None else ""))
    return Exit.OK


def _session_points(session: Any) -> tuple[np.ndarray, np.ndarray]:
    """The scan's points (camera frame, mm) in pixel order and the (H, W) mask of pixels
    that have one, from the session's cloud and maps."""
    from scanner.errors import SessionError
    from scanner.file_checks import ArraySpec, load_npz
    from scanner.pointcloud import read_ply_points

    cloud, maps = session.outputs / "cloud.ply", session.outputs / "maps.npz"
    if not (cloud.exists() and maps.exists()):
        raise SessionError(f"{session.root}: no processed scan (outputs/cloud.ply, outputs/maps.npz); "
                           f"run `slscan decode {session.root}` first")
    valid = load_npz(maps, {"valid": ArraySpec("b", 2)}, what="decoded maps file")["valid"]
    points = read_ply_points(cloud)
    if len(points) != int(valid.sum()):
        raise SessionError(f"{cloud}: {len(points)} points but {int(valid.sum())} valid pixels in {maps}; "
                           f"regenerate both with `slscan decode {session.root}`")
    return points, valid


def _log(path: Path, session: Any, points: np.ndarray, *, labels: np.ndarray, image: np.ndarray | None,
         timings: dict[str, float], recording_id: str) -> None:
    import numpy as np
    import rerun as rr

    from scanner.session_recording import SessionRecording

    with SessionRecording(path, recording_id, send_blueprint=False) as rec:
        if session is not None:
            rec.log_rig(session.rig_model())
        world_from_cam = rec.world_from_cam   # identity for a bare cloud: its own frame
        pts = points @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]
        rec.at_scan(0)
        rec.stream.log(SEGMENTS, rr.Points3D(pts.astype(np.float32), class_ids=_class_ids(labels)), strict=True)
        if image is not None:
            rec.stream.log(SEGMENT_MAP, rr.SegmentationImage(_class_ids(image)), strict=True)
        rec.log_metrics({"segments": float(labels.max(initial=-1) + 1),
                         "unsegmented_fraction": float((labels < 0).mean()),
                         **{f"segment_{k}_s": v for k, v in timings.items()}})


def _class_ids(labels: np.ndarray) -> np.ndarray:
    """Rerun class ids: 0 for no segment, 1 + label otherwise (wrapping past 65535)."""
    import numpy as np

    return np.where(labels >= 0, 1 + labels % 65535, 0).astype(np.uint16)


def cmd_segscore(args: argparse.Namespace) -> int:
    from inspection.regions.segmetrics import score

    test = _load_labels(Path(args.labels))
    truth = _load_labels(Path(args.ground_truth))
    result = score(test, truth)
    print(json.dumps(result.as_dict(), indent=2) if args.json else result.table())
    return Exit.OK


def _load_labels(path: Path) -> np.ndarray:
    """An integer label array from .npy, or the object ids of a simulator ground truth
    .npz (0, background, becomes -1: no surface)."""
    import numpy as np

    from inspection.errors import SegmentationError

    if not path.is_file():
        raise SegmentationError(f"{path}: no such labels file")
    from scanner.file_checks import ArraySpec, FileRefused, load_npz, read_regular

    try:
        if path.suffix == ".npz":
            ids = load_npz(path, {"object_id": ArraySpec("iu", 2)}, what="simulator ground_truth.npz")["object_id"]
            return np.where(ids == 0, -1, ids.astype(np.int32))
        arr = np.load(io.BytesIO(read_regular(path)), allow_pickle=False)
    except FileRefused as exc:
        raise SegmentationError(str(exc)) from None
    except (OSError, ValueError, EOFError) as exc:
        raise SegmentationError(f"{path}: not a readable .npy/.npz labels file: {exc}") from None
    if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "iu":
        raise SegmentationError(f"{path}: not an integer label array")
    return arr
