"""The station config TOML (`config/station/*.toml`): which rig stands on the bench, where
the station keeps its sessions and results, and its calibration policy.

    [station]
    name = "bench-1"                      # stored with every result
    rig = "../rigs/sim_bench.toml"        # rig TOML, relative to this file
    data_dir = "../../sessions/station"   # sessions and the SQLite results file, relative to this file
    database = ""                         # "" = SQLite at <data_dir>/results.sqlite, or a postgresql:// URL
    max_calibration_age_days = 365        # a calibration older than this is expired (a part program may
                                          # ask for less); 0 = no expiry
    operator = ""                         # default operator name (the UI asks when empty)
    measurement = "inspection"            # the measuring step: a name in `measure.MEASUREMENTS`

    [sim]                                 # simulated rigs only
    seed = 0                              # noise seed of the first part; part k uses seed + k
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scanner.config import CONFIG_DIR, get, get_table, load_toml, resolve
from scanner.errors import ConfigError
from slscan.station.results import redact

DEFAULT_STATION = CONFIG_DIR / "station" / "sim_bench.toml"
SQLITE_NAME = "results.sqlite"

_STATION_KEYS = {"name", "rig", "data_dir", "database", "max_calibration_age_days", "operator", "measurement"}
_SIM_KEYS = {"seed"}


def check_keys(table: dict[str, Any], allowed: set[str], path: str | Path, prefix: str = "") -> None:
    """Refuse a key that is not in `allowed`, naming it (a misspelt key must not be ignored)."""
    for key in table:
        if key not in allowed:
            full = f"{prefix}.{key}" if prefix else key
            raise ConfigError(path, full, f"unknown key; expected one of {sorted(allowed)}")


@dataclass(frozen=True)
class StationConfig:
    """A parsed station config; paths resolved, ages in days."""

    path: Path
    name: str
    rig_path: Path
    data_dir: Path
    database: str
    max_calibration_age_days: float
    operator: str
    measurement: str
    sim_seed: int

    @classmethod
    def load(cls, path: str | Path = DEFAULT_STATION) -> StationConfig:
        path = Path(path)
        raw = load_toml(path)
        check_keys(raw, {"station", "sim"}, path)
        st = get_table(raw, "station", path)
        check_keys(st, _STATION_KEYS, path, "station")
        sim = get_table(raw, "sim", path, required=False)
        check_keys(sim, _SIM_KEYS, path, "sim")
        age = get(st, "max_calibration_age_days", float, path, 365.0, "station")
        if age < 0:
            raise ConfigError(path, "station.max_calibration_age_days", f"must be >= 0 (0 = no expiry), got {age}")
        database = get(st, "database", str, path, "", "station")
        if database and not database.startswith(("postgresql://", "postgres://", "sqlite:")):
            raise ConfigError(path, "station.database", f"'{redact(database, database)}': give a postgresql:// URL, "
                                                        f"a sqlite:PATH, or leave it empty for SQLite in the data folder")
        return cls(path=path, name=get(st, "name", str, path, path.stem, "station"),
                   rig_path=resolve(path, get(st, "rig", str, path, prefix="station")).resolve(),
                   data_dir=resolve(path, get(st, "data_dir", str, path, prefix="station")).resolve(),
                   database=database, max_calibration_age_days=age,
                   operator=get(st, "operator", str, path, "", "station"),
                   measurement=get(st, "measurement", str, path, "inspection", "station"),
                   sim_seed=get(sim, "seed", int, path, 0, "sim"))

    @property
    def database_url(self) -> str:
        """Where results go: the configured URL, else `sqlite:<data_dir>/results.sqlite`."""
        return self.database or f"sqlite:{self.data_dir / SQLITE_NAME}"

    @property
    def sessions_dir(self) -> Path:
        return self.data_dir / "sessions"
