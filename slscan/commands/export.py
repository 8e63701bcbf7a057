"""`slscan export`: a session's cloud for other tools (scanner/exports.py): PLY, XYZ, CSV,
E57 or an STL mesh of the camera grid; `--aligned` in the CAD frame of the session's
inspection (the registration pose in outputs/inspection.json), `--deviations` with each
point's signed deviation from CAD (outputs/inspection_points.npz, only the points the
inspection put on a face)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanner.errors import ScannerError
from slscan.exit_codes import Exit
from slscan.options import add_json

if TYPE_CHECKING:
    import numpy as np

FORMATS = ("ply", "xyz", "csv", "e57", "stl")
"""`scanner.exports.FORMATS`, named here so the command line reads --format without numpy
(tests/test_cli.py checks the two agree)."""


def _format(args: argparse.Namespace) -> str:
    """--format, or the suffix of --out."""
    if args.format:
        return args.format
    suffix = Path(args.out).suffix.lower().lstrip(".") if args.out else ""
    if suffix not in FORMATS:
        raise ScannerError(f"give --format ({', '.join(FORMATS)}); --out {args.out or '(none)'} does not say it")
    return suffix


def _inspection(session: Any, why: str) -> dict[str, Any]:
    path = session.outputs / "inspection.json"
    if not path.is_file():
        raise ScannerError(f"{session.root}: {why} needs the session's inspection, and it has none "
                           f"({path.name} missing): run `slscan inspect {session.root} --cad MODEL` first")
    return json.loads(path.read_text())


def cmd_export(args: argparse.Namespace) -> int:
    import numpy as np

    from inspection.point_deviations import read_point_deviations
    from scanner.exports import read_session_cloud, write
    from scanner.session import Session

    fmt = _format(args)
    if args.deviations and fmt == "stl":
        raise ScannerError("--deviations: an STL mesh holds no per-point values; use ply, csv, xyz or e57")
    session = Session.open(args.session)
    ply = session.outputs / "cloud.ply"
    if not ply.is_file():
        raise ScannerError(f"{session.root}: no {ply.name}; run `slscan decode {session.root}` to make it")
    cloud = read_session_cloud(ply, str(session.root))
    if args.deviations:
        _inspection(session, "--deviations")
        dev = read_point_deviations(session.outputs, cloud.pixels)
        cloud = replace_deviations(cloud, dev)
    if args.aligned:
        report = _inspection(session, "--aligned")
        if report.get("pose_status", "ok") != "ok":  # no pose without proof (an inspection before proofs has none)
            print(f"slscan export: {session.root}: --aligned: the inspection's pose is not proven "
                  f"({report['pose_status']}: {report.get('status_note', '')}); no aligned cloud written",
                  file=sys.stderr)
            return Exit.FAILED
        transform = np.asarray(report["registration"]["transform"], dtype=np.float64)
        cloud = cloud.transformed(transform, f"CAD frame of {Path(report['model']).name} (the inspection's "
                                             f"registration)")
    out = Path(args.out) if args.out else session.outputs / f"export{'-cad' if args.aligned else ''}.{fmt}"
    summary = write(cloud, out, fmt, args.max_jump)
    if args.json:
        print(json.dumps({"status": "ok", "file": str(out), "format": fmt, "summary": summary, "unit": "mm",
                          "frame": cloud.frame, "deviations": bool(args.deviations)}))
        return Exit.OK
    print(f"export    {out}  ({fmt}, {summary}, mm, {cloud.frame}"
          + (", signed deviation from CAD per point" if args.deviations else "") + ")")
    return Exit.OK


def replace_deviations(cloud: Any, dev: np.ndarray) -> Any:
    """Only the points with a deviation (the part's, on a face), carrying it."""
    from dataclasses import replace

    import numpy as np

    keep = np.isfinite(dev)
    print(f"deviations for {int(keep.sum())} of {len(cloud)} points (the part's points on a CAD face)",
          file=sys.stderr)
    return replace(cloud.subset(keep), deviation_mm=dev[keep].astype(np.float64))


def register(sub: Any) -> None:
    e = sub.add_parser("export")
    e.add_argument("session", help="session folder (its outputs/cloud.ply; --aligned and --deviations also its "
                                   "inspection)")
    e.add_argument("--format", choices=FORMATS, help="file format (default: from --out's suffix)")
    e.add_argument("--aligned", action="store_true",
                   help="in the CAD model's frame, by the registration pose of the session's inspection")
    e.add_argument("--deviations", action="store_true",
                   help="each point's signed deviation from CAD (mm, + excess material): PLY property 'deviation', "
                        "CSV column, XYZ 4th column, E57 intensity; only the points on a CAD face")
    e.add_argument("--max-jump", type=float, metavar="MM",
                   help="stl: leave cells open whose corners' depths differ by more (default 8 x the point spacing)")
    e.add_argument("--out", help="file to write (default: SESSION/outputs/export[-cad].FORMAT)")
    add_json(e)
    e.set_defaults(func=cmd_export)
