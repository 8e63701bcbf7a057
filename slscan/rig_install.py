"""Naming a calibration file in a rig TOML (`slscan calibrate --install`): one key of its [rig]
table set to the file's absolute path, an earlier value replaced, the rest of the file as it was."""

from __future__ import annotations

import re
from pathlib import Path

from scanner.errors import ConfigError


def name_in_rig(rig_path: Path, key: str, file: Path) -> None:
    """Set `key` = "<file, absolute>" under [rig] in `rig_path` (replacing an earlier `key`)."""
    text = rig_path.read_text()
    line = f'{key} = "{file.resolve()}"'
    new, n = re.subn(rf"(?m)^{re.escape(key)}\s*=.*$", line, text, count=1)
    if not n:
        new, n = re.subn(r"(?m)^\[rig\][^\n]*\n", lambda m: m.group(0) + line + "\n", text, count=1)
    if not n:
        raise ConfigError(rig_path, "rig", f"no [rig] table to name the {key.replace('_', ' ')} in")
    rig_path.write_text(new)
