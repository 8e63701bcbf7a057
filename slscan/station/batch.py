"""Batch re-inspection: re-decode and re-measure stored parts after a calibration or program
change, in this process, on a local Dask cluster, or on a remote one.

A unit of work is one part: a part folder written by the station (its `view<k>/` session
folders, or its `multiview/` session of a program with stage angles) or a single session
folder. Each runs on a worker as `reinspect`: every session is opened (an incomplete one
fails that part only), decoded and reconstructed again from its raw frames (`outputs/`
regenerated; the recording and the manifest are left as they were), measured (a multi-view
session's views aligned and fused again first, its merged cloud measured), and judged
against the program. Given a rig TOML (`--rig`), the sessions are
reconstructed with that rig's geometry, i.e. its current calibration, instead of the one
recorded at capture; the calibration id stored with the result says which was used. A
part that fails is reported with its error; the batch goes on.
Units are independent, so the results do not depend on where or in which order they ran.
"""

from __future__ import annotations

import datetime as dt
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, TextIO

from scanner import __version__
from scanner.geometry import RigModel
from scanner.multiview import MultiViewSession, is_multiview
from scanner.pipeline import Progress, process
from scanner.rig import RigConfig
from scanner.session import Session, json_ready
from slscan.station import StationError
from slscan.station.calib import rig_calibration
from slscan.station.loop import MULTIVIEW_FOLDER, PART_RECORD
from slscan.station.measure import DEFAULT_MEASUREMENT, Measurement, cad_faces, load_measurement
from slscan.station.program import PartProgram, load_program
from slscan.station.quality import judge
from slscan.station.results import VERDICTS, PartStart, ValueRecord, open_results
from slscan.station.station_config import StationConfig


@dataclass(frozen=True)
class BatchItem:
    """One part's re-inspection: its folder, status (pass, fail, uncertain, error), message, values,
    serial (from the station's part record, else the folder name), the calibration it was
    reconstructed with (None: unknown, as captured), where it ran and how long it took (s);
    `truth` the simulated part's imposed defects when the sessions have them."""

    path: str
    status: str
    message: str
    values: tuple[ValueRecord, ...] = ()
    serial: str = ""
    calibration_id: str | None = None
    worker: str = ""
    seconds: float = 0.0
    truth: dict[str, Any] | None = None


@dataclass
class BatchSummary:
    program: str
    items: list[BatchItem] = field(default_factory=list)
    wall_s: float = 0.0
    where: str = ""

    @property
    def failures(self) -> list[BatchItem]:
        return [i for i in self.items if i.status == "error"]

    def counts(self) -> dict[str, int]:
        return {s: sum(i.status == s for i in self.items) for s in VERDICTS}


def part_sessions(path: Path) -> list[Path]:
    """The session folders of a part: `view<k>/` of a station part folder, or the folder itself."""
    views = sorted((p for p in path.glob("view*") if p.is_dir()), key=lambda p: int(p.name[4:] or 0))
    return views or [path]


@lru_cache(maxsize=8)
def _program(path: str) -> PartProgram:
    return load_program(path)


@lru_cache(maxsize=8)
def _rig(path: str) -> tuple[RigModel, str | None]:
    """A rig TOML's geometry (calibrated when it names a calibration file) and calibration id."""
    config = RigConfig.load(path)
    return config.model, rig_calibration(config).id


@lru_cache(maxsize=8)
def _measurement(entry: str) -> Measurement:
    return load_measurement(entry)


def reinspect(part: str, program_path: str, measurement: str = DEFAULT_MEASUREMENT,
              rig_path: str | None = None) -> BatchItem:
    """Re-decode (with `rig_path`'s geometry when given) and re-measure one part (runs on a
    worker; never raises for the part's own faults: they come back as an `error` item)."""
    from sim.station_parts import TRUTH_FILE  # written only into simulated sessions

    t0 = time.perf_counter()
    root = Path(part)
    record = json.loads((root / PART_RECORD).read_text()) if (root / PART_RECORD).exists() else {}
    serial = record.get("serial", root.name)
    calibration = record.get("calibration_id")
    worker = _worker_name()
    truth = None
    try:
        model = None
        if rig_path is not None:
            model, calibration = _rig(rig_path)
        program = _program(program_path)
        measure = _measurement(measurement)
        missing = measure.unavailable()
        if missing:
            raise StationError(f"measuring step ({measure.name}) unavailable: {missing}")
        multiview = MultiViewSession.open(root / MULTIVIEW_FOLDER) if is_multiview(root / MULTIVIEW_FOLDER) else None
        sessions = []
        for folder in part_sessions(root) if multiview is None else [v.session.root for v in multiview.views]:
            session = Session.open(folder)
            if model is not None:
                session = _with_model(session, model)
            process(session)
            sessions.append(session)
            truth_file = folder / TRUTH_FILE
            if truth is None and truth_file.exists():
                truth = json.loads(truth_file.read_text())
        if multiview is None:
            measured = measure.measure(sessions, program)
        else:
            from inspection.views.whole import whole_part

            whole_part(multiview, mesh=False)
            measured = measure.measure_whole(multiview, program)
        status, values, message = judge(program, measured)
    except Exception as exc:  # one part's failure is reported, the batch goes on
        return BatchItem(part, "error", f"{type(exc).__name__}: {exc}", serial=serial, calibration_id=calibration,
                         worker=worker, seconds=round(time.perf_counter() - t0, 3), truth=truth)
    return BatchItem(part, status, message, tuple(values), serial, calibration, worker,
                     round(time.perf_counter() - t0, 3), truth)


def _with_model(session: Session, model: RigModel) -> Session:
    """The session as it would be with `model` as its rig geometry (in memory only); the
    camera and projector must be the ones it was captured with."""
    captured = session.rig_model()
    if captured.camera.size != model.camera.size or captured.projector.size != model.projector.size:
        raise StationError(f"{session.root}: captured with a {captured.camera.size} camera and a "
                           f"{captured.projector.size} projector; the rig given has {model.camera.size} and "
                           f"{model.projector.size}")
    return session.replaced(rig_model=json_ready(model.to_dict()))


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().name)
    except (ImportError, ValueError):
        return "local"


def run_batch(parts: Sequence[str | Path], program_path: str | Path, *, scheduler: str | None = None, workers: int = 2,
              store_config: StationConfig | None = None, progress: Progress | None = None,
              measurement: str | None = None, rig_path: str | Path | None = None) -> BatchSummary:
    """Re-inspect `parts`: serially in this process when `workers` is 0 and no `scheduler`
    is given; otherwise on the Dask scheduler at `scheduler`, or on a local cluster of
    `workers` processes started for the batch. With `rig_path`, sessions are reconstructed
    with that rig's geometry. With `store_config`, every item is stored in that station's
    results database (source 'batch')."""
    program_path = str(Path(program_path).resolve())
    program = load_program(program_path, faces=cad_faces)  # refuse a bad program (or rig) before any work is sent
    rig = None
    if rig_path is not None:
        rig = str(Path(rig_path).resolve())
        _rig(rig)
    entry = measurement or (store_config.measurement if store_config else DEFAULT_MEASUREMENT)
    paths = [str(Path(p).resolve()) for p in parts]
    progress = progress or (lambda *a: None)
    summary = BatchSummary(program.name)
    t0 = time.perf_counter()
    if scheduler is None and workers == 0:
        summary.where = "serial, this process"
        for k, p in enumerate(paths):
            summary.items.append(reinspect(p, program_path, entry, rig))
            progress("batch", k + 1, len(paths))
    else:
        try:
            from distributed import Client, LocalCluster, as_completed
        except ModuleNotFoundError:
            raise StationError("a parallel batch runs on Dask: pip install 'slscan[batch]' (or --workers 0 to run "
                               "the parts one after the other here)") from None

        cluster = None if scheduler else LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                                      dashboard_address=None)
        try:
            with Client(scheduler or cluster) as client:
                summary.where = f"dask {client.scheduler.address} ({len(client.scheduler_info()['workers'])} workers)"
                futures = {client.submit(reinspect, p, program_path, entry, rig, pure=False): p for p in paths}
                done: dict[str, BatchItem] = {}
                for k, fut in enumerate(as_completed(futures)):
                    try:
                        done[futures[fut]] = fut.result()
                    except Exception as exc:  # a lost worker fails its part, not the batch
                        done[futures[fut]] = BatchItem(futures[fut], "error", f"{type(exc).__name__}: {exc}")
                    progress("batch", k + 1, len(paths))
                summary.items = [done[p] for p in paths]
        finally:
            if cluster is not None:
                cluster.close()
    summary.wall_s = round(time.perf_counter() - t0, 3)
    if store_config is not None:
        _store(summary, program, store_config, entry)
    return summary


def compare(a: BatchSummary, b: BatchSummary) -> tuple[list[str], float, str]:
    """Where two runs over the same parts differ: (one line per part whose status, message
    or set of measured characteristics differs; the largest difference of a value, mm;
    which part and characteristic it is, "" when none differs)."""
    differ, worst, where = [], 0.0, ""
    for x, y in zip(a.items, b.items, strict=True):
        vx = {v.characteristic: v.value_mm for v in x.values}
        vy = {v.characteristic: v.value_mm for v in y.values}
        if (x.status, x.message, vx.keys()) != (y.status, y.message, vy.keys()) \
                or any((vx[c] is None) != (vy[c] is None) for c in vx):
            differ.append(f"{x.path}: {x.status} '{x.message}' vs {y.status} '{y.message}'")
        for c in vx.keys() & vy.keys():
            u, v = vx[c], vy[c]
            if u is not None and v is not None and abs(u - v) > worst:
                worst, where = abs(u - v), f"{x.serial} {c}: {u:.6f} vs {v:.6f} mm"
    return differ, worst, where


def _store(summary: BatchSummary, program: PartProgram, config: StationConfig, entry: str) -> None:
    now = dt.datetime.now(dt.UTC)
    with open_results(config.database_url) as store:
        for item in summary.items:
            rid, _ = store.begin_part(PartStart(
                program=program.name, program_version=program.version, program_fingerprint=program.fingerprint,
                serial=item.serial, operator="batch", station=config.name, rig="", calibration_id=item.calibration_id,
                software_version=__version__, measurement=entry, part_path=item.path, started_at=now, source="batch"))
            store.finish_part(rid, item.status, item.message, item.values, now)


def print_summary(summary: BatchSummary, out: TextIO | None = None, json_out: bool = False) -> None:
    """Per-part lines, the failures, counts and wall time (or the whole summary as JSON)."""
    out = out or sys.stdout
    if json_out:
        from slscan.exit_codes import for_parts, status_of

        print(json.dumps({"status": status_of(for_parts(i.status for i in summary.items)),
                          "program": summary.program, "where": summary.where, "wall_s": summary.wall_s,
                          "counts": summary.counts(), "items": [asdict(i) for i in summary.items]}, indent=1),
              file=out)
        return
    for i in summary.items:
        vals = "  ".join(f"{v.characteristic}={v.shown()} {v.decision}" for v in i.values if v.value_mm is not None)
        print(f"{i.status.upper():<9} {i.serial:<28} {i.seconds:6.2f} s  {i.worker:<10} {vals}", file=out)
    for i in summary.failures:
        print(f"FAILED {i.path}: {i.message}", file=out)
    counts = summary.counts()
    print(f"{len(summary.items)} parts against {summary.program}: {counts['pass']} pass, {counts['fail']} fail, "
          f"{counts['uncertain']} uncertain (re-measure), {counts['error']} failed; wall time {summary.wall_s:.2f} s "
          f"on {summary.where}", file=out)
