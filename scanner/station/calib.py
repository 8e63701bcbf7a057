"""The rig's calibration as the station sees it: which one, how old, for which image sizes,
and whether the station may measure with it.

A rig TOML names its calibration file with `rig.calibration` (a path relative to the rig
TOML; issue 3 writes these files). It is read through `CALIBRATION_ENTRY`, the calibration
package's loader, which checks the file's version and sizes; the station needs from what
it returns an `id`, a `date` (date or ISO text) and the camera and projector image sizes.

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
import importlib
from dataclasses import dataclass
from typing import Any

from ..config import get, resolve
from ..rig import RigConfig
from .program import PartProgram

CALIBRATION_ENTRY = "calibration.file:load_calibration"
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
    """The calibration the rig TOML refers to, or the factory geometry of a simulated rig."""
    ref = get(config.raw.get("rig", {}), "calibration", str, config.path, None, "rig")
    if ref is None:
        if config.driver == "sim":
            model = config.nominal_model()
            return CalibrationInfo(f"{FACTORY_PREFIX}{config.name}", None, (model.camera.width, model.camera.height),
                                   (model.projector.width, model.projector.height),
                                   f"factory: nominal geometry of {config.path.name} (simulator ground truth)")
        return CalibrationInfo(None, None, None, None, f"{config.path}: no rig.calibration",
                               problem="rig is uncalibrated: a hardware rig needs a calibration file "
                                       "(run `slscan calibrate`, then name the file as rig.calibration)")
    path = resolve(config.path, ref)
    module_name, attr = CALIBRATION_ENTRY.split(":")
    try:
        load = getattr(importlib.import_module(module_name), attr)
    except (ImportError, AttributeError):
        return CalibrationInfo(None, None, None, None, str(path),
                               problem=f"{path} cannot be read: {module_name}.{attr}() is not available yet "
                                       f"(calibration, issue 3)")
    try:
        cal = load(path)
    except Exception as exc:  # noqa: BLE001 — any failure to read it refuses measuring, with the reason
        return CalibrationInfo(None, None, None, None, str(path), problem=f"{path}: {exc}")
    return CalibrationInfo(str(cal.id), _date(cal.date), _size(cal, "camera"), _size(cal, "projector"), str(path))


def _date(value: Any) -> dt.date:
    if isinstance(value, dt.datetime):
        return value.date()
    if isinstance(value, dt.date):
        return value
    return dt.datetime.fromisoformat(str(value)).date()


def _size(cal: Any, device: str) -> tuple[int, int] | None:
    part = getattr(cal, device, None)
    if part is None or not hasattr(part, "width"):
        return None
    return int(part.width), int(part.height)


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
