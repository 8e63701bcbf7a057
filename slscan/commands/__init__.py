"""The commands of `slscan`, one module per feature.

Each module defines `register(subparsers)`, adding its sub-commands to the `slscan` parser
with `set_defaults(func=...)`; a command function takes the parsed arguments and returns
the exit code. Modules are imported when the parser is built, so they import heavy
libraries (OpenCASCADE, Open3D, USB, ...) inside their command functions only.
"""

from slscan.commands import (
    bench,
    calibrate,
    coverage,
    demobench,
    devices,
    export,
    import_,
    importbench,
    inspect,
    pose,
    review,
    scan,
    segment,
    simbench,
    station,
    verify,
    viewbench,
)

COMMANDS = (scan, import_, review, export, bench, importbench, simbench, demobench, viewbench, devices, calibrate,
            verify, coverage, inspect, pose, segment, station)
