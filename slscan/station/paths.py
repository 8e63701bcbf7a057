"""Names from part programs, characteristics and serials made safe as file names.

A program's `name`, a characteristic's `name` and an operator's serial become folder and
file names (`<data>/reports/<program>/`, `charts/<characteristic>.png`, the part folders).
They are user text: `safe_name` keeps one path component of it, and `child` refuses any
result that would leave its folder, so every output stays inside the folder it belongs to.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from slscan.station import StationError

NAME_LIMIT = 80  # characters kept of a name


def safe_name(text: str) -> str:
    """`text` as one file-name component: ASCII letters, digits, '-', '_' and '.' are kept,
    anything else becomes '_', leading dots are dropped (never '.' or '..'); when anything
    changed, 8 hex digits of the text's SHA-256 are appended, so two names that differ only
    in replaced characters never share a file."""
    kept = re.sub(r"[^A-Za-z0-9_.-]", "_", text)[:NAME_LIMIT].lstrip(".")
    if kept == text:
        return kept
    return f"{kept or '_'}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


def child(folder: Path, name: str, suffix: str = "") -> Path:
    """`folder/<safe_name(name)><suffix>`, checked to lie inside `folder`."""
    path = folder / f"{safe_name(name)}{suffix}"
    if path.resolve().parent != folder.resolve():
        raise StationError(f"{name!r}: not usable as a file name in {folder}")
    return path
