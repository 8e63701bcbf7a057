"""The bench station: part programs, the operator loop, the results history and batch
re-inspection. An application layer above every package, like the CLI.

    config.py   station config TOML (rig, data folder, database, calibration policy)
    program.py  part programs (config/parts/*.toml): CAD, characteristics, scan settings
    calib.py    the rig's calibration: identity, date, sizes; the refusal rules
    measure.py  the measuring step: the typed seam and its one adapter onto `inspection`
    bench.py    what stands on the bench: the rig, and on the simulator the part in front of it
    quality.py  verdicts (values against tolerances) and running statistics
    loop.py     the operator loop as a state machine, independent of any user interface
    app.py      a station assembled from its config files; the non-interactive run (--auto)
    tui.py      the full-screen terminal view of the loop (curses)
    results.py  the results history on SQLite or PostgreSQL (SQLAlchemy Core), cycle ownership, CSV
    spc.py      control limits (I-MR, X-bar R), Nelson rules, capability (Cp/Cpk, Pp/Ppk, normality, Weibull)
    limits_file.py  control limits frozen into a file and read back
    dfq.py      the values as an AQDEF (Q-DAS) DFQ file
    charts.py   control charts: PNG images (matplotlib) and Rerun series
    paths.py    names from programs and serials made safe as file names
    history_report.py  the HTML report
    batch.py    re-decoding and re-inspecting stored sessions, locally or on a Dask cluster
"""

from scanner.errors import ScannerError

MEASUREMENT_NAMES = ("inspection", "simulator-truth")
"""The measuring steps a station config or `--measurement` can name (`measure.MEASUREMENTS`
maps each to its class), here so a command line lists them without importing numpy."""


class StationError(ScannerError):
    """Base of the station's errors: each names what failed and where (file, key, session)."""
