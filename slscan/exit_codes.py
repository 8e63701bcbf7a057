"""The exit codes of every `slscan` command, in one place (README "Exit codes").

    0  success: the command did what was asked and every measured part or check passed
    1  a measured part or a check fails: a face out of tolerance, a station part that fails,
       a calibration refused by its quality limits, a pose not proven, results that disagree
    4  no decision: a part (or a characteristic of it) not measured or uncertain (within U of
       its limit, ISO 14253-1), none failing; re-measure or measure it another way
    2  usage error or refused input: a bad option, a missing or invalid file, a session or
       cloud that cannot be used (argparse's own code for usage errors)
    3  a device fault: a camera, projector or trigger box that fails, times out or disconnects
  130  interrupted (Ctrl-C or SIGTERM); frames already captured are kept

Commands return these names, never bare numbers; `slscan.cli.main` maps an error that
escapes a command to its code with `for_error`.
"""

from __future__ import annotations

from collections.abc import Iterable
from enum import IntEnum


class Exit(IntEnum):
    """A command's exit status (see the module docstring)."""

    OK = 0
    FAILED = 1
    USAGE = 2
    DEVICE = 3
    NO_DECISION = 4
    INTERRUPTED = 130


SUMMARY = ("exit codes: 0 success; 1 a measured part or check fails; 2 usage error or refused input; "
           "3 device fault; 4 no decision (a part not measured or uncertain); 130 interrupted")
"""The one-line form `slscan --help` ends with."""

def for_parts(statuses: Iterable[str]) -> Exit:
    """The exit code of parts judged together (a station run, a batch) from their statuses
    (`slscan.station.results.STATUSES`, or inspections' verdicts): 1 if any fails, else 4 if
    any has no decision (uncertain, not measured, an error or an aborted cycle), else 0."""
    from inspection.tolerances import DECISION_STATUS

    station = {"pass": "ok", "fail": "failed"}
    found = {DECISION_STATUS.get(s) or station.get(s, "no decision") for s in statuses}
    return Exit.FAILED if "failed" in found else Exit.NO_DECISION if "no decision" in found else Exit.OK


def status_of(code: Exit) -> str:
    """The JSON `status` that says what exit `code` says (`inspection.tolerances.DECISION_STATUS`'s
    words): "ok" 0, "failed" 1, "no decision" 4."""
    return {Exit.OK: "ok", Exit.FAILED: "failed", Exit.NO_DECISION: "no decision"}[code]


def for_verdict(verdict: str) -> Exit:
    """The exit code of one part's overall verdict (`inspection.tolerances.overall`), the
    same as the `status` its JSON states (`DECISION_STATUS`): conforming (or no tolerances to
    judge) 0, non-conforming 1, uncertain or not measured 4."""
    return for_parts([verdict])


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
