"""CSV cells a spreadsheet will not run: every CSV slscan writes (the station's results
export, the inspection report's table) passes its cells through `csv_cell`, so a name
taken from a part program or typed by an operator (`=HYPERLINK(...)`) reaches the file as
text, not as a formula."""

from __future__ import annotations

import datetime as dt
from typing import Any

FORMULA_START = ("=", "+", "-", "@", "\t", "\r", "\n")


def csv_cell(value: Any) -> Any:
    """A text cell starting with = + - @, a tab or a line end gets a leading apostrophe;
    times become ISO 8601; numbers and everything else are left as they are."""
    if isinstance(value, dt.datetime):
        return value.isoformat()
    if isinstance(value, str) and value.startswith(FORMULA_START):
        return "'" + value
    return value
