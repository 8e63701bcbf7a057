"""Reading TOML configuration with errors that name the file and the key."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any, TypeVar

from scanner.errors import ConfigError
from scanner.file_checks import FileRefused, read_regular

T = TypeVar("T")

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


def get(table: dict[str, Any], key: str, kind: type[T] | tuple[type, ...], path: str | Path,
        default: Any = ..., prefix: str = "") -> T:
    """`table[key]` checked against `kind`; ints are accepted where floats are asked for,
    NaN and infinity are refused. (New loaders declare a `scanner.schema.Schema` instead.)

    `prefix` is the dotted name of `table` in the file, so errors name the full key."""
    full = f"{prefix}.{key}" if prefix else key
    if key not in table:
        if default is ...:
            raise ConfigError(path, full, "required key is missing")
        return default
    value = table[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if float in kinds and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
        names = " or ".join(k.__name__ for k in kinds)
        raise ConfigError(path, full, f"expected {names}, got {type(value).__name__} {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(path, full, f"must be a finite number, got {value!r}")
    return value  # type: ignore[return-value]  # checked against `kind` above; a tuple of kinds binds no T


def get_vector(table: dict[str, Any], key: str, n: int, path: str | Path, default: Any = ...,
               prefix: str = "") -> list[float]:
    """A list of exactly `n` finite numbers."""
    value = get(table, key, list, path, default, prefix)
    if len(value) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                                  for v in value):
        full = f"{prefix}.{key}" if prefix else key
        raise ConfigError(path, full, f"expected a list of {n} numbers, got {value!r}")
    return [float(v) for v in value]


def get_table(table: dict[str, Any], key: str, path: str | Path, required: bool = True,
              prefix: str = "") -> dict[str, Any]:
    """A sub-table; an absent optional one is empty."""
    return get(table, key, dict, path, ... if required else {}, prefix)


def resolve(base_file: str | Path, relative: str) -> Path:
    """A path written in a config file, taken relative to that file's folder."""
    p = Path(relative)
    return p if p.is_absolute() else (Path(base_file).resolve().parent / p)
