"""The operator loop as plain Python, independent of any user interface.

One cycle (`Station.run_cycle`) measures one part:

    refuse?   the calibration is missing, expired or not the program's, or the measuring
              step is unavailable: nothing is scanned (`Refused`, with every reason)
    start     a result row `in_progress` is committed (serial, attempt, program version,
              calibration id, software version, operator, part folder, start time)
    scan      per view: the rig with the part in place; capture, decode, reconstruct into
              `<data>/sessions/<program>/<serial>-<time>/view<k>/` (a complete session each);
              with stage angles (`[scan] views = [0, 90, ...]`) the rig's stage turns the
              part to each, one multi-view session `<serial>-<time>/multiview/`
              (`scanner.multiview`: every view durable with its stage pose), whose views
              are then aligned and fused (`inspection.views.whole`; no mesh: the
              measurement does not use it)
    measure   the `Measurement` on the part's sessions (or on the merged cloud of its
              multi-view session, once); values judged against the program
    store     the row gets its status, message and values in one commit; `part.json` (the
              cycle's record) is written into the part folder, atomically, last

Nothing is lost on the way out: an operator abort (the `cancel` event, checked at every
frame), Ctrl-C, or a device fault store the cycle as `aborted` or `error`, and the
session folder keeps its frames without a manifest (incomplete, with `error.json`; a
multi-view session keeps its finished views and says in its `error.json` which view stopped). A
station killed outright leaves its row `in_progress`; `recover()` at the next start marks
it `incomplete`. A re-scan is a new cycle (attempt n + 1) of the same serial; earlier
attempts stay. Statistics use each serial's last cycle.
"""

from __future__ import annotations

import datetime as dt
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from scanner import __version__
from scanner.errors import ConfigError, ScannerError
from scanner.multiview import plan_views
from scanner.pipeline import Progress, scan
from scanner.rig import Rig, RigConfig
from scanner.schema import plain_text
from scanner.session import Session, ViewPlace, disk_problem, write_json
from slscan.station import StationError
from slscan.station.calib import describe as describe_calibration
from slscan.station.calib import refusals as calibration_refusals
from slscan.station.calib import rig_calibration
from slscan.station.hardware_bench import Bench
from slscan.station.measure import Measurement, MeasurementResult
from slscan.station.part_state import part_state
from slscan.station.paths import child, safe_name
from slscan.station.program import PartProgram
from slscan.station.quality import RunningStats, judge, running_stats
from slscan.station.results import PartStart, ResultsStore, ValueRecord, utcnow
from slscan.station.station_config import StationConfig

PART_RECORD = "part.json"
MULTIVIEW_FOLDER = "multiview"  # a part's multi-view session, in its part folder
STATS_WINDOW = 1000  # results the running statistics look back over


class Refused(StationError):
    """The station will not measure; `reasons` lists every cause."""

    def __init__(self, reasons: list[str]) -> None:
        super().__init__("refusing to measure: " + "; ".join(reasons))
        self.reasons = reasons


class OperatorAbort(StationError):
    """The operator aborted the cycle."""


def _quiet(stage: str, done: int, total: int) -> None:
    pass


@dataclass(frozen=True)
class CycleOutcome:
    """One stored cycle: its result row id, serial and attempt, status (pass, fail, error,
    aborted), message, judged values, the part folder and its sessions, the simulated
    part's truth (None on hardware) and the cycle's duration in s."""

    result_id: int
    serial: str
    attempt: int
    status: str
    message: str
    values: tuple[ValueRecord, ...]
    part_path: Path
    sessions: tuple[Path, ...]
    truth: dict[str, Any] | None = None
    seconds: float = 0.0


class Station:
    """A station running one part program on one bench; `on_stored` is called with every
    stored cycle (e.g. to extend the control charts)."""

    def __init__(self, program: PartProgram, config: StationConfig, bench: Bench, *, measurement: Measurement,
                 store: ResultsStore, operator: str,
                 on_stored: Callable[[CycleOutcome], None] | None = None) -> None:
        self.program = program
        self.config = config
        self.bench = bench
        self.measurement = measurement
        self.store = store
        self.operator = operator
        self.on_stored = on_stored
        self.calibration = rig_calibration(bench.config)
        self.patterns = program.scan.pattern_set()
        self.stage_plan = stage_plan(program, bench.config)

    # -- status

    def refusals(self, today: dt.date | None = None) -> list[str]:
        """Every reason the station must not measure now (empty: it may)."""
        today = today or dt.date.today()
        out = calibration_refusals(self.calibration, self.bench.config, self.program,
                                   self.config.max_calibration_age_days, today)
        missing = self.measurement.unavailable()
        if missing:
            out.append(f"measuring step ({self.measurement.name}) unavailable: {missing}")
        return out

    def status_lines(self, today: dt.date | None = None) -> list[tuple[str, str]]:
        """(label, text) lines for a status display."""
        today = today or dt.date.today()
        p = self.program
        return [("program", f"{p.name} v{p.version} [{p.fingerprint}] ({p.path.name}; faces {p.face_check})"),
                ("rig", self.bench.describe()),
                ("calibration", describe_calibration(self.calibration, today)),
                ("measuring", f"{self.measurement.name}: {self.measurement.unavailable() or 'ready'}"),
                ("results", self.store.where),
                ("operator", self.operator or "(none)")]

    def recover(self) -> list[int]:
        """Mark the cycles this station left in progress when it last died as incomplete,
        each with what its part folder really holds (`part_state`)."""
        return self.store.mark_interrupted(
            self.config.name, lambda part_path: f"the station stopped during this cycle; {part_state(part_path)}")

    def stats(self) -> RunningStats:
        rows = self.store.results(program=self.program.name, limit=STATS_WINDOW)
        return running_stats(self.program, rows, self.store.values([r.id for r in rows]))

    # -- one part

    def run_cycle(self, serial: str, part: int = 0, cancel: threading.Event | None = None,
                  progress: Progress = _quiet) -> CycleOutcome:
        """Scan, measure, judge and store one part (see the module docstring). `part` is
        the part's number in this run (the simulator's lineup position); `cancel` aborts."""
        serial = serial.strip()
        if not serial:
            raise StationError("no serial number / part id: enter one before scanning")
        for what, text in (("the serial number", serial), ("the operator's name", self.operator)):
            try:
                plain_text(text, what)
            except ValueError as exc:
                raise StationError(f"{exc}: nothing was scanned") from None
        reasons = self.refusals()
        if reasons:
            raise Refused(reasons)
        cancel = cancel or threading.Event()
        t0 = time.perf_counter()
        started = utcnow()
        folder = child(self.config.sessions_dir, self.program.name) / f"{safe_name(serial)}-{started:%Y%m%d-%H%M%S-%f}"
        result_id, attempt = self.store.begin_part(PartStart(
            program=self.program.name, program_version=self.program.version,
            program_fingerprint=self.program.fingerprint, serial=serial, operator=self.operator,
            station=self.config.name, rig=self.bench.config.name, calibration_id=self.calibration.id,
            software_version=__version__, measurement=self.measurement.name, part_path=str(folder), started_at=started))
        sessions: list[Path] = []
        measured: MeasurementResult | None = None  # kept for the part record (None: not measured)
        truth = None
        if self.bench.simulated:
            truth = self.bench.sim_part(part).as_dict()

        def finish(status: str, message: str, values: list[ValueRecord] | None = None) -> CycleOutcome:
            outcome = CycleOutcome(result_id, serial, attempt, status, message, tuple(values or ()), folder,
                                   tuple(sessions), truth, round(time.perf_counter() - t0, 3))
            self.store.finish_part(result_id, status, message, outcome.values, utcnow())
            try:
                folder.mkdir(parents=True, exist_ok=True)
                write_json(folder / PART_RECORD, _record(self, outcome, started, measured))
                if self.on_stored is not None:
                    self.on_stored(outcome)
            except OSError as exc:  # a full disk: the result is safe in the database, the station cannot go on
                raise StationError(f"{disk_problem(exc)}; {serial} (attempt {attempt}) is stored as {status} in "
                                   f"{self.store.where}; the station stops") from None
            return outcome

        def step(stage: str, done: int, total: int) -> None:
            if cancel.is_set():
                raise OperatorAbort(f"aborted by the operator during {stage}")
            progress(stage, done, total)

        try:
            with self.store.hold(result_id):
                measured = self._scan_and_measure(part, folder, sessions, step)
        except OperatorAbort as exc:
            return finish("aborted", str(exc))
        except KeyboardInterrupt as exc:
            finish("aborted", f"{str(exc) or 'interrupted (Ctrl-C)'}; frames already captured are kept")
            raise
        except Exception as exc:  # a device or measuring fault ends this cycle, stored
            return finish("error", f"{type(exc).__name__}: {exc}")
        status, values, message = judge(self.program, measured)
        return finish(status, message, values)

    def _scan_and_measure(self, part: int, folder: Path, sessions: list[Path],
                          step: Callable[[str, int, int], None]) -> MeasurementResult:
        """Scan every view of the part into `folder` (each session appended to `sessions`
        as it starts) and measure them."""
        if self.stage_plan is not None:
            return self._scan_whole(part, folder, sessions, step)
        views = self.program.scan.views
        scanned = []
        for k in range(views):
            where = f" (view {k + 1}/{views})" if views > 1 else ""
            step("place" + where, 0, 1)
            with self.bench.view(part, k, views) as rig:
                self._set_exposure(rig)
                sessions.append(folder / f"view{k}")

                def view_step(stage: str, done: int, total: int, where: str = where) -> None:
                    step(stage + where, done, total)

                scanned.append(scan(rig, self.patterns, sessions[-1], progress=view_step).session)
        return self._measured(lambda: self.measurement.measure(scanned, self.program), step)

    def _scan_whole(self, part: int, folder: Path, sessions: list[Path],
                    step: Callable[[str, int, int], None]) -> MeasurementResult:
        """Scan the part at every stage angle into one multi-view session (appended to
        `sessions` before the first view), align and fuse its views, measure the merged cloud."""
        from inspection.views.whole import whole_part
        from scanner.multiview import capture_views

        assert self.stage_plan is not None
        n = len(self.stage_plan)
        sessions.append(folder / MULTIVIEW_FOLDER)
        step("place", 0, 1)
        with self.bench.on_stage(part) as rig:
            self._set_exposure(rig)

            def scan_view(out: Path, place: ViewPlace) -> Session:
                where = f" (view {place.view + 1}/{n})"
                return scan(rig, self.patterns, out,
                            progress=lambda stage, done, total: step(stage + where, done, total), view=place).session

            views = capture_views(rig, self.stage_plan, sessions[-1], scan_view,
                                  lambda k, _, what: step(f"{what} (view {k + 1}/{n})", k, n))
        whole_part(views, mesh=False, progress=lambda stage, done, total: step(f"merge: {stage}", 0, 1))
        return self._measured(lambda: self.measurement.measure_whole(views, self.program), step)

    def _set_exposure(self, rig: Rig) -> None:
        if self.program.scan.exposure_s is not None:
            rig.camera.set_exposure(self.program.scan.exposure_s)

    @staticmethod
    def _measured(measure: Callable[[], MeasurementResult],
                  step: Callable[[str, int, int], None]) -> MeasurementResult:
        step("measure", 0, 1)
        measured = measure()
        step("measure", 1, 1)  # an abort pressed while measuring takes effect here
        return measured


def stage_plan(program: PartProgram, rig: RigConfig) -> list[dict[str, float]] | None:
    """The stage positions of the program's stage angles on `rig` (None: the program gives
    a number of views). A rig without a [stage], or an angle beyond its travel, is refused
    here, when the station opens, naming the program's `scan.views`."""
    angles = program.scan.stage_angles_deg
    if angles is None:
        return None
    if rig.stage is None:
        raise ConfigError(program.path, "scan.views", f"stage angles need a rig with a [stage] to turn the part; "
                                                      f"{rig.path} has none (give a number of views, or use a rig "
                                                      f"with a turntable)")
    try:
        return plan_views(rig.stage, angles_deg=angles)
    except ScannerError as exc:
        raise ConfigError(program.path, "scan.views", str(exc)) from None


def _record(station: Station, outcome: CycleOutcome, started: dt.datetime,
            measured: MeasurementResult | None) -> dict[str, Any]:
    p = station.program
    return {"result_id": outcome.result_id, "program": p.name, "program_version": p.version,
            "program_fingerprint": p.fingerprint, "program_path": str(p.path), "serial": outcome.serial,
            "attempt": outcome.attempt, "status": outcome.status, "message": outcome.message,
            "operator": station.operator, "station": station.config.name, "rig": station.bench.config.name,
            "calibration_id": station.calibration.id, "software_version": __version__,
            "measurement": station.measurement.name, "started": started.isoformat(), "seconds": outcome.seconds,
            "sessions": [str(s) for s in outcome.sessions], "values": [asdict(v) for v in outcome.values],
            "measurement_result": None if measured is None else measured.as_dict(), "sim_truth": outcome.truth}
