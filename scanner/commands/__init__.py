"""Sub-commands of `slscan` beyond the core scan workflow, one module per feature.

Each module listed in `MODULES` defines `register(subparsers)`, adding its sub-commands to
the `slscan` parser with `set_defaults(func=...)`; a command function takes the parsed
arguments and returns the exit code. Modules are imported when the parser is built, so they
import heavy libraries (OpenCASCADE, USB, ...) inside their command functions only.
"""

MODULES: tuple[str, ...] = ("scanner.commands.devices", "scanner.commands.station", "scanner.commands.calibrate", "scanner.commands.segment", "scanner.commands.inspect", "scanner.commands.pose")
