"""The header of an inspection report, as a metrology lab issues one: what was measured
(part, serial), against what (the part program and its SHA-256 fingerprint), by whom, when,
on which rig with which calibration, and by which software. The command that inspects
fills it from the session, the program and the rig (`slscan.commands.inspect.report_header`);
every field is text, "" when not known (shown as "not given"). The station's report of a
part program's results shows the same header (`header_html`)."""

from __future__ import annotations

import hashlib
import html
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

LABELS = {"part": "Part", "serial": "Serial number", "program": "Part program", "program_sha256": "Program SHA-256",
          "operator": "Operator", "date": "Date (UTC)", "rig": "Rig", "calibration_id": "Calibration id",
          "calibration_date": "Calibration date", "software_version": "Software"}


@dataclass(frozen=True)
class ReportHeader:
    """The report's identification; `date` ISO 8601 UTC, `program_sha256` of the program
    file as read (64 hex digits)."""

    part: str = ""
    serial: str = ""
    program: str = ""
    program_sha256: str = ""
    operator: str = ""
    date: str = ""
    rig: str = ""
    calibration_id: str = ""
    calibration_date: str = ""
    software_version: str = ""

    def rows(self) -> list[tuple[str, str]]:
        """(label, value) in reading order; "not given" for an empty field."""
        return [(LABELS[k], v or "not given") for k, v in asdict(self).items()]

    def as_dict(self) -> dict[str, str]:
        return asdict(self)


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes, 64 hex digits (the program's fingerprint)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


HEADER_CSS = ("#header table{width:100%;border-collapse:collapse}#header th,#header td{border:1px solid #ccc;"
              "padding:3px 7px;text-align:left}#header th{width:22%;background:#eef0f3}"
              "#header td{word-break:break-all}")


def header_html(header: ReportHeader, extra: Iterable[tuple[str, str]] = ()) -> str:
    """The header as an HTML section (`#header`, styled by `HEADER_CSS`): its rows, then
    `extra` (label, value) rows."""
    rows = [*header.rows(), *extra]
    return ("<section id='header'><table>" + "".join(
        f"<tr><th>{html.escape(k)}</th><td>{html.escape(str(v))}</td></tr>" for k, v in rows) + "</table></section>")
