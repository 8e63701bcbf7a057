"""The values of a part program as an AQDEF (Q-DAS ASCII transfer format) DFQ file, for
Q-DAS qs-STAT, solara and other AQDEF readers (`slscan results --dfq --out FILE.dfq`).

One key field per line, `Kxxxx/i value` for characteristic i (1-based), CR LF line ends:

    K0100           number of characteristics
    K1001, K1002    part number (the program's name) and description
    K2001/i         characteristic number (its name in the program)
    K2002/i         characteristic description (kind, method, face)
    K2101/i         nominal value (0: an ideal form, or the nominal surface itself)
    K2110/i         lower limit: 0, the natural bound of every figure here (a zone width
                    or a height, `program.KINDS`), not a specification limit
    K2111/i         upper specification limit (the tolerance, mm)
    K2120/i         type of the lower limit: 2, a natural boundary (AQDEF: 0 none, 1 a
                    specification limit, 2 a natural boundary), so capability is one-sided
                    (Cpk from the upper limit) as for a zero-bounded figure
    K2121/i         type of the upper limit: 1, a specification limit
    K2142/i         unit (mm)
    per value:
    K0001/i         the value (mm); a value below its detection limit is written as that limit
                    (the upper bound of the true value; the report's statistics treat it as
                    censored, which AQDEF has no field for)
    K0002/i         attribute: 0 a value to use, 255 a value the user left out (deactivated)
    K0004/i         date and time, dd.mm.yyyy/hh:mm:ss (UTC)
    K0008/i         operator
    K0014/i         part ident (the serial number)

The values are those the report's statistics use: each serial's last cycle with a verdict,
in time order, a part's values together; a characteristic that was not measured on a part
has no value line."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from slscan.station.program import PartProgram
from slscan.station.quality import chart_series
from slscan.station.results import ResultRow, ValueRecord

USED, DEACTIVATED = 0, 255  # K0002 attributes
SPECIFICATION_LIMIT, NATURAL_BOUNDARY = 1, 2  # K2120/K2121 limit types


def _text(value: str) -> str:
    """A text field on one line (AQDEF fields end at the line's end)."""
    return " ".join(str(value).split())


def dfq_text(program: PartProgram, rows: Sequence[ResultRow], values: dict[int, list[ValueRecord]],
             exclusions: Mapping[int, str] | None = None) -> tuple[str, int]:
    """The DFQ file's text (module docstring) and the number of values in it."""
    series = chart_series(program, rows, values, exclusions)
    operators = {r.id: r.operator for r in rows}
    lines = [f"K0100 {len(program.characteristics)}", f"K1001 {_text(program.name)}",
             f"K1002 {_text(program.description or program.name)} (program version {_text(program.version)})"]
    for i, c in enumerate(program.characteristics, 1):
        what = c.kind + (f" ({c.method.replace('_', ' ')})" if c.method else "")
        lines += [f"K2001/{i} {_text(c.name)}", f"K2002/{i} {_text(what)} {_text(program.face_names.get(c.face, ''))} "
                  f"{_text(c.face)}".replace("  ", " "), f"K2101/{i} 0", f"K2110/{i} 0",
                  f"K2111/{i} {c.tolerance_mm:g}", f"K2120/{i} {NATURAL_BOUNDARY}", f"K2121/{i} {SPECIFICATION_LIMIT}",
                  f"K2142/{i} mm"]
    n = 0
    per_part = zip(*(series[c.name] for c in program.characteristics))  # one part's points, in program order
    for part in per_part:
        for i, p in enumerate(part, 1):
            if p.charted_mm is None:
                continue
            lines += [f"K0001/{i} {p.charted_mm:.6f}", f"K0002/{i} {DEACTIVATED if p.excluded else USED}",
                      f"K0004/{i} {p.time:%d.%m.%Y/%H:%M:%S}", f"K0008/{i} {_text(operators.get(p.result_id, ''))}",
                      f"K0014/{i} {_text(p.serial)}"]
            n += 1
    return "\r\n".join(lines) + "\r\n", n
