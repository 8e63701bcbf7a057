"""Multi-view scans on the rig's stage: `slscan scan --views N` (or `--angles`) and what
`slscan decode` / `inspect` do with a multi-view folder.

    slscan scan --rig config/rigs/sim_turntable.toml --scene config/scenes/turntable_demo.toml \\
                --views 8 --out sessions/part-all-round

captures one session per view inside one multi-view folder (`scanner.multiview`), each
view durable as soon as it is captured, then aligns, fuses and meshes the views
(`inspection.views`) into the folder's outputs/ and its recording (`--no-merge`: capture
only). A failed move or capture keeps every earlier view; the command says which and exits
with the error.

`--stage-axis FILE` (a `slscan calibrate --stage-axis` file) gives the stage geometry the
views' poses are recorded and aligned with, in place of the rig's [stage] calibration;
`slscan decode MULTIVIEW --stage-axis FILE` aligns views captured before the axis was
calibrated again from the calibrated axis (their recorded stage positions are kept).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

from scanner.errors import ScannerError
from slscan.exit_codes import Exit
from slscan.progress import ProgressLine


def scan_views(args: argparse.Namespace, config: Any, patterns: Any, options: dict[str, Any],
               exposure: Any = None) -> int:
    """`slscan scan --views N | --angles A,B,...` (see the module docstring); `exposure` (an
    `scanner.exposure.ExposureRequest`, None: the rig's) applies to every view."""
    from scanner.multiview import capture_views, describe_incomplete, plan_views
    from scanner.pipeline import scan
    from scanner.rig import open_rig

    if config.stage is None:
        raise ScannerError(f"{config.path}: --views needs a rig with a [stage] (e.g. config/rigs/sim_turntable.toml)")
    angles = None
    if args.angles is not None:
        try:
            angles = [float(a) for a in args.angles.split(",") if a.strip()]
        except ValueError:
            raise ScannerError(f"--angles: expected degrees separated by commas, got {args.angles!r}") from None
    plan = plan_views(config.stage, args.views, angles)
    model = None
    if args.stage_axis is not None:
        from scanner.stage_model import load_stage_model

        model = load_stage_model(Path(args.stage_axis), config.stage.nominal, config.path, "--stage-axis")
    out = Path(args.out)
    print(f"rig {config.name} ({config.driver}), {len(plan)} views on {config.stage.axes[0].name}, "
          f"{patterns.family} {patterns.n_frames} frames each -> {out}", file=sys.stderr)
    line = ProgressLine()

    def view_progress(k: int, n: int, what: str) -> None:
        print(f"view {k + 1}/{n}: {what}", file=sys.stderr)

    with open_rig(config, **options) as rig:
        try:
            session = capture_views(rig, plan, out, lambda folder, place: scan(rig, patterns, folder, progress=line,
                                                                                exposure=exposure,
                                                                                view=place).session,
                                    view_progress, model)
        except (ScannerError, KeyboardInterrupt):
            if (out / "views.json").exists():
                print(describe_incomplete(out), file=sys.stderr)
            raise
    print(f"session   {session.root} ({len(session.views)} views)")
    if args.no_merge:
        return Exit.OK
    return report_whole(session, line)


def decode_views(args: argparse.Namespace) -> int:
    """`slscan decode MULTIVIEW`: every view's outputs again from its raw frames, then the
    whole part (alignment, merged cloud, mesh, recording)."""
    from scanner.multiview import MultiViewSession
    from scanner.pipeline import reprocess
    from scanner.session_lock import session_lock

    session = MultiViewSession.open(args.session)
    model = session.stage_axis_file(args.stage_axis) if args.stage_axis is not None else None
    line = ProgressLine()
    with session_lock(session.root, command="slscan decode"):
        for view in session.views:
            print(f"{view.name}: decode", file=sys.stderr)
            reprocess(view.session, line, mode=args.mode)
        return report_whole(session, line, model)


def report_whole(session: Any, progress: Any, stage_model: Any = None) -> int:
    """Align, fuse and mesh a multi-view session (priors from `stage_model` when given,
    `inspection.views.whole.whole_part`); print what it gave."""
    from inspection.views.recording import log_whole_part
    from inspection.views.whole import whole_part
    from scanner.session_recording import SessionRecording

    t0, load = time.perf_counter(), os.getloadavg()[0]
    whole = whole_part(session, progress=progress, stage_model=stage_model)
    wall = time.perf_counter() - t0
    with SessionRecording(session.recording_path, session.id, send_blueprint=False) as recording:
        log_whole_part(recording, whole)
    corrections = whole.alignment.corrections()
    out = session.outputs
    calibration = (stage_model or session.stage_model).calibration or "the rig's nominal axes"
    print(f"stage     priors from {calibration}")
    print(f"aligned   {len(whole.views)} views, {len(whole.alignment.edges)} pairs "
          f"({len(whole.alignment.refused)} refused); largest correction of the stage prior "
          f"{max(c[0] for c in corrections):.3f} deg / {max(c[1] for c in corrections):.3f} mm")
    print(f"merged    {out / 'merged.ply'}  ({len(whole.merged)} points, {int((whole.merged.views > 1).sum())} fused "
          f"from 2+ views, cell {whole.merged.cell_mm:.3f} mm)")
    if whole.mesh is not None:
        print(f"mesh      {out / 'mesh.ply'}, {out / 'mesh.stl'}: {whole.mesh.summary()}")
    print(f"recording {session.recording_path}   (views, poses, merged cloud and mesh; view: slscan review "
          f"{session.root})")
    t = whole.timings_s
    print("time      " + ", ".join(f"{k} {v:.1f} s" for k, v in t.items()) + f"; {wall:.1f} s wall at load "
          f"{load:.1f} (indicative)")
    return Exit.OK
