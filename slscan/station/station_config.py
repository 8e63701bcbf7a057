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
from typing import Annotated

from pydantic import Field

from scanner import schema
from scanner.config import CONFIG_DIR, resolve
from scanner.errors import ConfigError
from slscan.station.results import redact

DEFAULT_STATION = CONFIG_DIR / "station" / "sim_bench.toml"
SQLITE_NAME = "results.sqlite"

class StationTable(schema.Schema):
    name: schema.Str | None = None
    rig: schema.Str
    data_dir: schema.Str
    database: schema.Str = ""
    max_calibration_age_days: schema.NonNegativeFloat = 365.0
    operator: schema.Str = ""
    measurement: schema.Str = "inspection"


class SimTable(schema.Schema):
    seed: Annotated[int, Field(strict=True, ge=0)] = 0


class StationFile(schema.Schema):
    """A station config TOML (module docstring)."""

    station: StationTable
    sim: SimTable = SimTable()


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
        st = schema.load(StationFile, path)
        database = st.station.database
        if database and not database.startswith(("postgresql://", "postgres://", "sqlite:")):
            raise ConfigError(path, "station.database",
                              f"'{redact(database, database)}': give a postgresql:// URL, "
                              "a sqlite:PATH, or leave it empty for SQLite in the data folder")
        return cls(path=path, name=st.station.name or path.stem, rig_path=resolve(path, st.station.rig).resolve(),
                   data_dir=resolve(path, st.station.data_dir).resolve(), database=database,
                   max_calibration_age_days=st.station.max_calibration_age_days, operator=st.station.operator,
                   measurement=st.station.measurement, sim_seed=st.sim.seed)

    @property
    def database_url(self) -> str:
        """Where results go: the configured URL, else `sqlite:<data_dir>/results.sqlite`."""
        return self.database or f"sqlite:{self.data_dir / SQLITE_NAME}"

    @property
    def sessions_dir(self) -> Path:
        return self.data_dir / "sessions"
