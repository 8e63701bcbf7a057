"""Reading TOML configuration: the file's contents (validated by a schema, `scanner.schema`),
paths written in it, and where the shipped configuration lives."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from scanner.errors import ConfigError
from scanner.file_checks import FileRefused, read_regular

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
DEFAULT_RIG = CONFIG_DIR / "rigs" / "sim_bench.toml"  # the simulated bench rig, every command's default


MAX_TOML_BYTES = 16 * 1024 ** 2  # a config file of settings: kilobytes; this bounds what a reader holds


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a missing or malformed file raises ConfigError naming it."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(path, None, "file not found")
    try:
        return tomllib.loads(read_regular(path, limit=MAX_TOML_BYTES).decode())
    except FileRefused as exc:
        raise ConfigError(path, None, exc.problem) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(path, None, f"not valid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(path, None, f"cannot read the file: {exc.strerror or exc}") from None


def resolve(base_file: str | Path, relative: str) -> Path:
    """A path written in a config file, taken relative to that file's folder."""
    p = Path(relative)
    return p if p.is_absolute() else (Path(base_file).resolve().parent / p)
