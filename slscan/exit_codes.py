"""The exit codes of every `slscan` command, in one place (README "Exit codes").

    0  success: the command did what was asked and every measured part or check passed
    1  a measured part or a check fails: a face out of tolerance, a station part that fails,
       a calibration refused by its quality limits, results that disagree
    2  usage error or refused input: a bad option, a missing or invalid file, a session or
       cloud that cannot be used (argparse's own code for usage errors)
    3  a device fault: a camera, projector or trigger box that fails, times out or disconnects
  130  interrupted (Ctrl-C or SIGTERM); frames already captured are kept

Commands return these names, never bare numbers; `slscan.cli.main` maps an error that
escapes a command to its code with `for_error`.
"""

from __future__ import annotations

from enum import IntEnum


class Exit(IntEnum):
    """A command's exit status (see the module docstring)."""

    OK = 0
    FAILED = 1
    USAGE = 2
    DEVICE = 3
    INTERRUPTED = 130


SUMMARY = ("exit codes: 0 success; 1 a measured part or check fails; 2 usage error or refused input; "
           "3 device fault; 130 interrupted")
"""The one-line form `slscan --help` ends with."""

def for_error(exc: BaseException) -> Exit:
    """The exit code for an error that ended a command: device faults 3, a refused
    calibration (a check that fails) 1, any other refusal or usage error 2."""
    from calibration.errors import CalibrationRejected
    from scanner.errors import DeviceError

    if isinstance(exc, KeyboardInterrupt):
        return Exit.INTERRUPTED
    if isinstance(exc, DeviceError):
        return Exit.DEVICE
    if isinstance(exc, CalibrationRejected):
        return Exit.FAILED
    return Exit.USAGE
