"""The rig's calibration as the station sees it: which one, how old, for which image sizes,
and whether the station may measure with it.

A rig TOML names its calibration file with `rig.calibration` (issue 3's versioned JSON,
checked against the rig's image sizes when the rig config loads). The station reads it
through `CALIBRATION_ENTRY` (the calibration package's loader) for its identity: the
file's `id` if it has one, else `<rig>@<created, to the second>` (e.g.
`sim-bench@2026-11-23T16:40:12`), and its date (`created`).

A simulated rig without a calibration file uses its nominal geometry, which is the
simulator's ground truth: that counts as a "factory" calibration with the fixed id
`factory-<rig name>` and no date (it cannot drift, so it does not expire). A hardware rig
without a calibration file is uncalibrated and the station refuses to measure with it.

Refusal rules (`refusals`): the program's calibration id must match; the calibration's
image sizes must be the rig's; a dated calibration older than the stricter of the
station's and the program's age limits is expired.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from scanner.calibration_file import load_calibration
from scanner.rig import RigConfig
from slscan.station.program import PartProgram

FACTORY_PREFIX = "factory-"


@dataclass(frozen=True)
class CalibrationInfo:
    """`id` and `date` (None: undated factory geometry) of the calibration in use; image
    sizes (width, height) in px it was made for; `source` the file, or what stands in for one."""

    id: str | None
    date: dt.date | None
    camera_size: tuple[int, int] | None
    projector_size: tuple[int, int] | None
    source: str
    problem: str = ""  # why the calibration cannot be used at all (unreadable, missing)

    def age_days(self, today: dt.date) -> int | None:
        return None if self.date is None else (today - self.date).days


def rig_calibration(config: RigConfig) -> CalibrationInfo:
    """The calibration the rig TOML names, or the factory geometry of a simulated rig."""
    path = config.calibration_path
    if path is None:
        if config.driver == "sim":
            model = config.nominal_model()
            return CalibrationInfo(f"{FACTORY_PREFIX}{config.name}", None, model.camera.size, model.projector.size,
                                   f"factory: nominal geometry of {config.path.name} (simulator ground truth)")
        return CalibrationInfo(None, None, None, None, f"{config.path}: no rig.calibration",
                               problem="rig is uncalibrated: a hardware rig needs a calibration file "
                                       "(run `slscan calibrate`, then name the file as rig.calibration)")
    try:
        cal = load_calibration(path)
    except Exception as exc:  # any failure to read it refuses measuring, with the reason
        return CalibrationInfo(None, None, None, None, str(path), problem=f"{path}: {exc}")
    created = dt.datetime.fromisoformat(str(cal.data["created"]))
    ident = str(cal.data.get("id") or f"{cal.data.get('rig', config.name)}@{created:%Y-%m-%dT%H:%M:%S}")
    return CalibrationInfo(ident, created.date(), cal.camera_size, cal.projector_size, str(path))


def max_age_days(station_limit: float, program: PartProgram) -> float | None:
    """The age limit in force: the stricter of the station's (0 = none) and the program's."""
    limits = [a for a in (station_limit or None, program.max_calibration_age_days) if a]
    return min(limits) if limits else None


def refusals(info: CalibrationInfo, config: RigConfig, program: PartProgram, station_limit_days: float,
             today: dt.date) -> list[str]:
    """Why the station must not measure with this calibration (empty: it may)."""
    if info.problem:
        return [info.problem]
    out = []
    if info.id != program.calibration_id:
        out.append(f"calibration mismatch: {program.path.name} expects calibration.id '{program.calibration_id}', "
                   f"the rig has '{info.id}' ({info.source})")
    model = config.nominal_model()
    for device, have, want in (("camera", info.camera_size, (model.camera.width, model.camera.height)),
                               ("projector", info.projector_size, (model.projector.width, model.projector.height))):
        if have is not None and tuple(have) != want:
            out.append(f"calibration is for a {have[0]}x{have[1]} {device}, {config.path.name} has "
                       f"{want[0]}x{want[1]}")
    limit = max_age_days(station_limit_days, program)
    age = info.age_days(today)
    if limit is not None and age is not None and age > limit:
        out.append(f"calibration expired: {info.id} dated {info.date} is {age} days old, the limit is {limit:g} days")
    return out


def describe(info: CalibrationInfo, today: dt.date) -> str:
    """One line for the status display."""
    if info.problem:
        return f"NONE ({info.problem})"
    when = "undated, does not expire" if info.date is None else f"{info.date}, {info.age_days(today)} days old"
    return f"{info.id} ({when}; {info.source})"
