"""A station assembled from its config files, and the non-interactive run (`--auto`).

`open_station` loads the part program and the station config, opens the results store,
the bench and the control-chart recording, and marks cycles a killed station left behind
as incomplete. After every stored cycle the control charts get the part's values and the
HTML report (`<data>/reports/<program>/report.html`) is rewritten, so both are current
even if the station is killed later.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import sys
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, TextIO

from scanner.pipeline import Progress
from scanner.rig import RigConfig
from slscan.exit_codes import Exit, for_parts, status_of
from slscan.station import StationError
from slscan.station.charts import ChartRecording
from slscan.station.hardware_bench import Bench
from slscan.station.history_report import write_report
from slscan.station.loop import STATS_WINDOW, CycleOutcome, Station, utcnow
from slscan.station.measure import Measurement, cad_faces, load_measurement
from slscan.station.paths import child
from slscan.station.program import PartProgram, load_program
from slscan.station.quality import DECISION_MARKS
from slscan.station.results import VERDICTS, ResultRow, ResultsStore, ValueRecord, open_results
from slscan.station.station_config import StationConfig

CHART_RECORDING = "control_charts.rrd"
log = logging.getLogger(__name__)


class StationRun:
    """An open station: `station` runs cycles; closing writes the report and the charts."""

    def __init__(self, program: PartProgram, config: StationConfig, operator: str,
                 measurement: Measurement | None = None, rig_path: Path | None = None) -> None:
        self.program = program
        self.config = config
        self.report_dir = child(config.data_dir / "reports", program.name)
        rig = RigConfig.load(rig_path or config.rig_path)
        self.store: ResultsStore = open_results(config.database_url)
        try:
            self.bench = Bench(rig, seed=config.sim_seed)
        except BaseException:
            self.store.close()
            raise
        try:
            self.station = Station(program, config, self.bench,
                                   measurement=measurement or load_measurement(config.measurement, config.path),
                                   store=self.store, operator=operator, on_stored=self._stored)
            self.recovered = self.station.recover()
            self.charts = ChartRecording(self.report_dir / CHART_RECORDING, program,
                                         f"station-{config.name}-{program.name}-{utcnow():%Y%m%d-%H%M%S}")
            self.charts.log_history(*self._history())
        except OSError as exc:
            self.bench.close()
            self.store.close()
            raise StationError(f"{exc.filename or config.data_dir}: {exc.strerror or exc} (the station's data "
                               f"folder must be writable)") from None
        except BaseException:
            self.bench.close()
            self.store.close()
            raise

    def __enter__(self) -> StationRun:
        return self

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        if exc is None:
            self.close()
            return
        try:  # the error that ended the run is the one line the operator sees, not one from closing after it
            self.close()
        except Exception as closing:  # any fault in closing is logged; the run's own error is raised
            log.info("closing the station after %s: %s", type(exc).__name__, closing)

    def _history(self) -> tuple[list[ResultRow], dict[int, list[ValueRecord]]]:
        rows = self.store.results(program=self.program.name, limit=STATS_WINDOW)
        return rows, self.store.values([r.id for r in rows])

    def _stored(self, outcome: CycleOutcome) -> None:
        self.charts.log(outcome.result_id, outcome.values)
        self.write_report()

    def write_report(self) -> Path:
        rows, values = self._history()
        return write_report(self.report_dir, self.program, rows, values, self.store.where)

    def close(self) -> None:
        try:
            try:
                rows, values = self._history()
            except StationError:  # the database is unreachable: the charts keep this run's own file
                self.charts.close()
            else:
                self.charts.close(rows, values)
        finally:
            self.bench.close()
            self.store.close()


def open_station(program_path: str | Path, config: StationConfig, operator: str = "",
                 measurement: Measurement | None = None, rig_path: Path | None = None) -> StationRun:
    """Load the program (faces checked against the CAD) and open the station."""
    program = load_program(program_path, faces=cad_faces)
    return StationRun(program, config, operator or config.operator, measurement, rig_path)


def override(config: StationConfig, data_dir: str | Path | None = None, database: str | None = None) -> StationConfig:
    """The station config with the data folder and/or database replaced."""
    if data_dir is not None:
        config = replace(config, data_dir=Path(data_dir).resolve())
    if database is not None:
        config = replace(config, database=database)
    return config


def expected_status(program: PartProgram, truth: dict[str, Any] | None) -> str | None:
    """The verdict a simulated part's imposed defects call for (None without a truth, or
    when the truth does not cover every characteristic)."""
    if not truth:
        return None
    imposed = truth.get("imposed_mm", {})
    if any(c.name not in imposed for c in program.characteristics):
        return None
    return "pass" if all(c.conforms(imposed[c.name]) for c in program.characteristics) else "fail"


def outcome_lines(program: PartProgram, o: CycleOutcome) -> list[str]:
    """A cycle as text: the verdict line, then one line per characteristic."""
    lines = [f"{o.serial} (attempt {o.attempt}): {o.status.upper()}" + (f" - {o.message}" if o.message else "")]
    for v in o.values:
        c = program.characteristic(v.characteristic)
        lines.append(f"    {v.characteristic:<22} {v.shown():>17} mm  <= {c.tolerance_mm:.3f}  "
                     f"{DECISION_MARKS.get(v.decision, v.decision or '--')}" + (f"  ({v.note})" if v.note else ""))
    return lines


def run_auto(run: StationRun, parts: int, out: TextIO | None = None, progress: Progress | None = None, *,
             as_json: bool = False) -> int:
    """Measure `parts` parts without an operator (serials AUTO-<time>-<k>); print each
    verdict and, on the simulator, the verdict the imposed defects call for (`as_json`: on
    stderr, and the run as one JSON document on stdout). Returns the exit code
    (`slscan.exit_codes.for_parts`): 0 when every part passed, 1 when any failed, else 4
    when any was uncertain, not measured, in error or aborted."""
    out = out or (sys.stderr if as_json else sys.stdout)
    station = run.station
    reasons = station.refusals()
    for label, text in station.status_lines():
        print(f"{label:<12} {text}", file=out)
    if run.recovered:
        print(f"recovered    results {run.recovered} left in progress by a stopped station: marked incomplete",
              file=out)
    if reasons:
        raise StationError("refusing to measure: " + "; ".join(reasons))
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    outcomes = []
    for k in range(parts):
        o = station.run_cycle(f"AUTO-{stamp}-{k + 1:03d}", part=k, progress=progress or (lambda *a: None))
        outcomes.append(o)
        expected = expected_status(run.program, o.truth)
        lines = outcome_lines(run.program, o)
        lines[0] = f"part {k + 1}/{parts}  " + lines[0] + f"  [{o.seconds:.1f} s]"
        if o.truth is not None:
            lines.append(f"    simulated part '{o.truth['name']}': {o.truth['description']}"
                         + (f" -> expected {expected.upper()}" if expected else ""))
        print("\n".join(lines), file=out, flush=True)
    judged = [(o, expected_status(run.program, o.truth)) for o in outcomes]
    counts = {s: sum(o.status == s for o in outcomes) for s in (*VERDICTS, "aborted")}
    print(f"\n{parts} parts: " + ", ".join(f"{n} {s}" for s, n in counts.items() if n), file=out)
    if counts["uncertain"]:
        print(f"{counts['uncertain']} uncertain: a value within U of its tolerance; neither passed nor failed, "
              "to be re-measured (a new attempt of the same serial)", file=out)
    with_truth = [(o, e) for o, e in judged if e is not None]
    if with_truth:
        agree = sum(o.status == e for o, e in with_truth)
        print(f"verdicts agreeing with the imposed defects: {agree}/{len(with_truth)}", file=out)
    print(f"results      {run.store.where}", file=out)
    print(f"report       {run.write_report()}", file=out)
    print(f"charts       {run.report_dir / CHART_RECORDING} (written when the station closes)", file=out)
    code = for_parts(o.status for o in outcomes) if len(outcomes) == parts else Exit.NO_DECISION
    if as_json:
        print(json.dumps({"status": status_of(code), "parts": parts, "counts": counts, "where": run.store.where,
                          "results": [{**asdict(o), "expected": e} for o, e in judged]}, default=str))
    return code
