"""Frozen control limits: the limits of every characteristic of a part program written to a
JSON file once (`slscan results --report --save-limits FILE`, usually from a baseline of
results), and read back in place of limits from the data (`--limits FILE`), so that later
parts are judged against the process as it was when the limits were set (Phase II).

    {"format": "slscan control limits 1", "program": name, "program_fingerprint": ...,
     "subgroup_size": n, "written_utc": ..., "source": "what the limits came from",
     "characteristics": {name: {"kind": "I-MR", "subgroup": 1, "points": 25, "sigma_within": s,
                                "location": {"centre", "lcl", "ucl", "sigma", "lcl_clipped"},
                                "spread": {...}}}}

Loading refuses a file of another program, subgroup size or format, and one that lacks a
characteristic of the program, naming it (mm throughout)."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

from scanner.errors import ConfigError
from scanner.session import write_atomic
from slscan.station.program import PartProgram
from slscan.station.spc import ControlChart, Limits

FORMAT = "slscan control limits 1"


def save_limits(path: Path, program: PartProgram, charts: Mapping[str, ControlChart | None], source: str) -> list[str]:
    """Write the limits of the characteristics that have some; returns the names without
    (too few values: not frozen, the caller says so)."""
    missing = [name for name, chart in charts.items() if chart is None]
    data = {"format": FORMAT, "program": program.name, "program_fingerprint": program.fingerprint,
            "subgroup_size": program.subgroup_size,
            "written_utc": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"), "source": source,
            "characteristics": {name: asdict(chart) for name, chart in charts.items() if chart is not None}}
    write_atomic(path, (json.dumps(data, indent=1) + "\n").encode())
    return missing


def load_limits(path: Path, program: PartProgram) -> tuple[dict[str, ControlChart], str]:
    """(name -> frozen chart, a line saying where they came from) for every characteristic of
    `program`; a file that does not fit the program is refused (module docstring)."""
    try:
        data = json.loads(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read the limits file: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(path, "", f"not a limits file (JSON error at line {exc.lineno})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ConfigError(path, "format", f"not a limits file of this slscan (format {FORMAT!r} expected)")
    for key, want in (("program", program.name), ("subgroup_size", program.subgroup_size)):
        if data.get(key) != want:
            raise ConfigError(path, key, f"the limits are for {key} {data.get(key)!r}; the program has {want!r}")
    charts = {}
    for c in program.characteristics:
        raw = data.get("characteristics", {}).get(c.name)
        if raw is None:
            raise ConfigError(path, f"characteristics.{c.name}", "no frozen limits for this characteristic "
                                                                 "(it had too few values when they were saved)")
        charts[c.name] = _chart(raw, path, c.name)
    return charts, f"{path}, written {data.get('written_utc', '?')} from {data.get('source', '?')}"


def _chart(raw: Any, path: Path, name: str) -> ControlChart:
    try:
        return ControlChart(kind=str(raw["kind"]), subgroup=int(raw["subgroup"]), location=Limits(**raw["location"]),
                            spread=Limits(**raw["spread"]), sigma_within=float(raw["sigma_within"]),
                            points=int(raw.get("points", 0)))
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(path, f"characteristics.{name}", f"malformed limits: {exc}") from None
