"""The station's statistics as the quality engineer gets them: `slscan results --report`
with exclusions, rules, a baseline and frozen limits; the AQDEF (DFQ) export read back by
a parser written here from the format's description; the chart figure's axes and legend."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest

from scanner.config import CONFIG_DIR
from slscan import cli
from slscan.station.program import load_program
from slscan.station.quality import SpcOptions, running_stats
from slscan.station.results import PartStart, ValueRecord, open_results

PROGRAM = CONFIG_DIR / "parts" / "demo_part.toml"
T0 = dt.datetime(2026, 12, 1, 8, 0, tzinfo=dt.UTC)
LIMIT_MM = 0.009  # the detection limit of the censored values


def fill(db: Path, n: int, seed: int) -> dict[str, list[float | None]]:
    """`n` stored cycles of the demo program: each value drawn about a quarter of its
    tolerance, low_top_flatness below its detection limit whenever the draw is, and every
    tenth part's high-top flatness above its tolerance (the part fails). Returns the values
    put in, per characteristic (None: below the limit)."""
    program = load_program(PROGRAM)
    rng = np.random.default_rng(seed)
    put: dict[str, list[float | None]] = {c.name: [] for c in program.characteristics}
    with open_results(f"sqlite:{db}") as store:
        for k in range(n):
            start = PartStart(program.name, program.version, program.fingerprint, f"SN-{k + 1:04d}", "ana", "bench-1",
                              "sim-bench", "factory-sim-bench", "0.1.0", "inspection", f"/parts/{k}",
                              T0 + dt.timedelta(minutes=k))
            rid, _ = store.begin_part(start)
            records, status = [], "pass"
            for c in program.characteristics:
                v: float | None = abs(float(rng.normal(c.tolerance_mm / 4, c.tolerance_mm / 12)))
                if c.name == "high_top_flatness" and k % 10 == 9:
                    v, status = 1.2 * c.tolerance_mm, "fail"
                limit = None
                if c.name == "low_top_flatness" and v < LIMIT_MM:
                    v, limit = None, LIMIT_MM
                put[c.name].append(v)
                decision = "non-conforming" if v is not None and v > c.tolerance_mm else "conforming"
                records.append(ValueRecord(c.name, c.kind, c.face, v, c.tolerance_mm, decision == "conforming", 1000,
                                           "", 0.002, limit, decision, "guard-banded"))
            store.finish_part(rid, status, "", records, start.started_at + dt.timedelta(seconds=40))
    return put


def results(db: Path, *args: str) -> int:
    return cli.main(["results", "--db", f"sqlite:{db}", "--program", str(PROGRAM), *args])


def test_report_uses_every_value_the_users_exclusions_and_rules(tmp_path: Path, capsys) -> None:
    db = tmp_path / "results.sqlite"
    put = fill(db, 40, seed=1)
    assert results(db, "--report", "--out", str(tmp_path / "r"), "--exclude", "3=fixture loose", "--rules",
                   "all") == 0
    page = (tmp_path / "r" / "report.html").read_text()
    assert "fixture loose" in page and "SN-0003" in page
    assert "Nelson rules used: 1 (1 point beyond a control limit), 2" in page and "8 (8 in a row" in page
    program = load_program(PROGRAM)
    with open_results(f"sqlite:{db}", create=False) as store:
        rows = store.results()
        stats = running_stats(program, rows, store.values([r.id for r in rows]), SpcOptions(exclusions={3: "x"}))
    by = {s.name: s for s in stats.characteristics}
    high = np.array(put["high_top_flatness"], float)
    kept = np.delete(high, 2)  # result 3 left out by the user; the failed parts stay in
    assert by["high_top_flatness"].capability.n == 39
    assert by["high_top_flatness"].capability.ppk.value == pytest.approx((0.05 - kept.mean()) / (3 * kept.std(ddof=1)))
    low = by["low_top_flatness"]
    assert low.below_limit == sum(v is None for v in put["low_top_flatness"]) > 0 and low.n == 40


def test_limits_frozen_from_a_baseline_are_used_later(tmp_path: Path, capsys) -> None:
    db = tmp_path / "results.sqlite"
    fill(db, 40, seed=2)
    frozen = tmp_path / "limits.json"
    assert results(db, "--report", "--out", str(tmp_path / "a"), "--baseline", "1-30", "--save-limits",
                   str(frozen), "--exclude", "7=probe crash") == 0
    saved = json.loads(frozen.read_text())
    assert saved["program"] == "demo-part" and "ids 1..30" in saved["source"]
    assert "left out by the user: 7 (probe crash)" in saved["source"]
    program = load_program(PROGRAM)
    with open_results(f"sqlite:{db}", create=False) as store:
        rows = store.results()
        values = store.values([r.id for r in rows])
    base = running_stats(program, [r for r in rows if r.id <= 30], values, SpcOptions(exclusions={7: "x"}))
    for s in base.characteristics:
        assert saved["characteristics"][s.name]["location"]["ucl"] == pytest.approx(s.chart.location.ucl)
    assert results(db, "--report", "--out", str(tmp_path / "b"), "--limits", str(frozen)) == 0
    page = (tmp_path / "b" / "report.html").read_text()
    assert f"limits frozen ({frozen}" in page
    # a limits file of another program is refused with its file and key named
    saved["program"] = "other-part"
    frozen.write_text(json.dumps(saved))
    assert results(db, "--report", "--out", str(tmp_path / "c"), "--limits", str(frozen)) == 2
    assert "key 'program'" in capsys.readouterr().err


def test_options_that_need_a_report_are_refused_without_one(tmp_path: Path, capsys) -> None:
    db = tmp_path / "results.sqlite"
    fill(db, 3, seed=3)
    assert results(db, "--baseline", "1-2") == 2 and "--baseline applies to --report" in capsys.readouterr().err
    with pytest.raises(SystemExit) as bad:  # argparse refuses it with its usage line
        results(db, "--report", "--out", str(tmp_path / "r"), "--rules", "9")
    assert bad.value.code == 2 and "Nelson rules 1..8" in capsys.readouterr().err
    assert results(db, "--report", "--dfq", "--out", str(tmp_path / "r")) == 2


AQDEF_FIELDS = {"K0100": "number of characteristics", "K1001": "part number", "K1002": "part description",
                "K2001": "characteristic number", "K2002": "characteristic description", "K2101": "nominal value",
                "K2110": "lower specification limit", "K2111": "upper specification limit",
                "K2120": "type of lower limit", "K2121": "type of upper limit", "K2142": "unit",
                "K0001": "value", "K0002": "attribute", "K0004": "date/time", "K0008": "operator",
                "K0014": "part ident"}
"""The AQDEF (Q-DAS ASCII transfer format) fields slscan writes, by the format's field list;
K2120/K2121 coding: 0 no limit, 1 specification limit, 2 natural boundary."""


def parse_dfq(text: str) -> tuple[dict[str, str], list[dict[str, str]]]:
    """A DFQ file read from the AQDEF description: header fields K1xxx/K2xxx (with /i), and
    the value records, a new record for characteristic i starting at each K0001/i."""
    header: dict[str, str] = {}
    records: list[dict[str, str]] = []
    assert text.endswith("\r\n") and "\n" not in text.replace("\r\n", "")
    for line in text.split("\r\n")[:-1]:
        key, _, value = line.partition(" ")
        assert key.startswith("K") and key[1:5].isdigit(), line
        field, _, index = key.partition("/")
        assert field in AQDEF_FIELDS, f"{field} is not a field slscan is meant to write: {line}"
        if int(field[1:5]) < 100:  # K0001..K0099: a value's fields
            if field == "K0001":
                records.append({"i": index})
            assert records[-1]["i"] == index, line
            records[-1][field] = value
        else:
            header[key] = value
    return header, records


def test_dfq_export_has_every_value_censored_and_excluded_ones_marked(tmp_path: Path, capsys) -> None:
    db = tmp_path / "results.sqlite"
    put = fill(db, 12, seed=4)
    assert results(db) == 0  # the listing shows a censored value as below its limit
    assert f"low_top_flatness=<{LIMIT_MM:.4f}" in capsys.readouterr().out
    out = tmp_path / "values.dfq"
    assert results(db, "--dfq", "--out", str(out), "--exclude", "5=gauge dropped") == 0
    header, records = parse_dfq(out.read_bytes().decode("utf-8"))
    program = load_program(PROGRAM)
    assert header["K0100"] == str(len(program.characteristics)) and header["K1001"] == "demo-part"
    names = {header[f"K2001/{i}"]: str(i) for i in range(1, len(program.characteristics) + 1)}
    assert set(names) == {c.name for c in program.characteristics}
    for c in program.characteristics:
        i = names[c.name]
        assert float(header[f"K2111/{i}"]) == c.tolerance_mm and header[f"K2142/{i}"] == "mm"
        # a zero-bounded figure: lower limit 0 of type natural boundary, the upper a specification limit
        assert (float(header[f"K2110/{i}"]), header[f"K2120/{i}"], header[f"K2121/{i}"]) == (0.0, "2", "1")
        mine = [r for r in records if r["i"] == i]
        want = [LIMIT_MM if v is None else v for v in put[c.name]]
        assert [float(r["K0001"]) for r in mine] == pytest.approx(want, abs=1e-6)
        assert [r["K0014"] for r in mine] == [f"SN-{k + 1:04d}" for k in range(12)]
        assert [r["K0002"] for r in mine] == ["255" if k == 4 else "0" for k in range(12)]
        assert mine[0]["K0004"] == "01.12.2026/08:00:40" and mine[0]["K0008"] == "ana"


def test_the_chart_has_whole_part_numbers_and_its_legend_apart() -> None:
    """The part axis is labelled with whole numbers only, and the legend sits in its own
    cell: its box meets neither the values' axes nor the ranges' axes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from slscan.station.charts import draw_chart
    from slscan.station.quality import ChartPoint, characteristic_stats

    program = load_program(PROGRAM)
    c = program.characteristics[0]
    x = np.random.default_rng(5).normal(0.012, 0.003, 7)
    s = characteristic_stats(c, [ChartPoint(k + 1, f"S{k}", T0, float(v), "pass") for k, v in enumerate(x)])
    fig = draw_chart(c, s)
    FigureCanvasAgg(fig).draw()
    top, bottom = fig.axes[0], fig.axes[1]
    ticks = [t for t in bottom.get_xticks() if bottom.get_xlim()[0] <= t <= bottom.get_xlim()[1]]
    assert ticks and all(float(t).is_integer() for t in ticks)
    legend = next(ax.get_legend() for ax in fig.axes if ax.get_legend() is not None)
    box = legend.get_window_extent()
    for ax in (top, bottom):
        assert not box.overlaps(ax.get_window_extent())
    assert "no limits: 7 values, limits need 25" in fig._suptitle.get_text()


def test_a_chart_is_drawn_again_only_when_what_it_shows_or_its_file_changed(tmp_path: Path) -> None:
    """The report after a cycle that changed no chart keeps the PNG files; a chart whose
    values changed, or whose file someone replaced, is drawn again."""
    import dataclasses

    from slscan.station.charts import write_charts
    from slscan.station.quality import ChartPoint, RunningStats, characteristic_stats

    program = load_program(PROGRAM)
    program = dataclasses.replace(program, characteristics=program.characteristics[:2])
    x = np.random.default_rng(7).normal(0.012, 0.003, 6)

    def stats(n: int) -> RunningStats:
        per = [characteristic_stats(c, [ChartPoint(k + 1, f"S{k}", T0, float(v), "pass") for k, v in enumerate(x[:n])])
               for c in program.characteristics]
        return RunningStats(n, n, 0, 0, tuple(per))

    def stamps() -> list[tuple[int, int]]:
        return [(p.stat().st_ino, p.stat().st_mtime_ns) for p in files.values()]

    files = write_charts(tmp_path, program, stats(5))
    first = stamps()
    assert write_charts(tmp_path, program, stats(5)) == files and stamps() == first
    replaced = files[program.characteristics[1].name]
    replaced.write_bytes(b"not a chart")
    write_charts(tmp_path, program, stats(5))
    assert stamps()[0] == first[0] and replaced.read_bytes().startswith(b"\x89PNG")
    kept = stamps()
    write_charts(tmp_path, program, stats(6))
    assert all(a != b for a, b in zip(stamps(), kept))


def test_exclusions_are_recorded_with_who_and_when_and_applied_later(tmp_path: Path, capsys) -> None:
    """`--exclude ID=REASON --by NAME` is stored in the results database (reason, who, when),
    listed by `--exclusions`, applied by every later export and report without being given
    again, and lifted by `--include ID`; an unknown result or a database that is not there
    is refused (exit 2) without writing anything."""
    db = tmp_path / "results.sqlite"
    fill(db, 12, seed=6)
    before = dt.datetime.now(dt.UTC)
    assert results(db, "--exclude", "5=gauge dropped", "--by", "ben") == 0
    assert "excluded  result 5: gauge dropped (ben, " in capsys.readouterr().err
    with open_results(f"sqlite:{db}", create=False) as store:
        [(rid, e)] = store.exclusions().items()
    assert (rid, e.reason, e.excluded_by) == (5, "gauge dropped", "ben")
    assert before <= e.excluded_at <= dt.datetime.now(dt.UTC)
    assert results(db, "--exclusions", "--json") == 0
    listed = json.loads(capsys.readouterr().out)["exclusions"]
    assert [(x["result_id"], x["serial"], x["reason"], x["excluded_by"]) for x in listed] == \
           [(5, "SN-0005", "gauge dropped", "ben")]
    out = tmp_path / "values.dfq"
    assert results(db, "--dfq", "--out", str(out)) == 0  # no --exclude given: the recorded one applies
    _, records = parse_dfq(out.read_bytes().decode("utf-8"))
    assert {r["K0014"] for r in records if r["K0002"] == "255"} == {"SN-0005"}
    assert results(db, "--report", "--out", str(tmp_path / "r")) == 0
    assert "gauge dropped" in (tmp_path / "r" / "report.html").read_text()
    assert results(db) == 0 and "[excluded: gauge dropped (ben, " in capsys.readouterr().out
    assert results(db, "--include", "5") == 0
    assert results(db, "--dfq", "--out", str(out)) == 0
    assert {r["K0002"] for r in parse_dfq(out.read_bytes().decode("utf-8"))[1]} == {"0"}
    capsys.readouterr()
    assert results(db, "--exclude", "99=no such part") == 2 and "no result 99" in capsys.readouterr().err
    missing = tmp_path / "elsewhere" / "results.sqlite"
    assert results(missing, "--exclude", "1=x") == 2 and not missing.parent.exists()
