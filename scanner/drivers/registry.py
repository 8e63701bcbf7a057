"""The drivers a rig TOML may name, each declared by its own module (see docs/drivers.md).

A driver module declares itself at import with `register(Driver(...))`: its device kind
(the table whose `driver` key names it), its name, the rig driver that opens it, the
schema of its own keys in that table, and how it is opened. The core schema of a table
keeps the keys every device of its kind has; every other key of the table is the driver's,
validated by its `settings` schema (`scanner.rig_schema.device_settings`).

The registry finds the drivers by importing every module of this package the first time
one is looked up, so adding a driver is adding its module: nothing else names it. Driver
modules import only light libraries at the top (harvesters, pygame, usb are imported where
a device opens), so validating a rig file opens nothing. A driver living in a layer the
core cannot import (the simulator) is opened through a "module:function" string, resolved
when the rig opens.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from scanner import schema
from scanner.errors import ConfigError
from scanner.schema import Schema

log = logging.getLogger(__name__)

Kind = Literal["rig", "camera", "projector", "trigger_box", "stage"]


class NoSettings(Schema):
    """A driver without keys of its own."""


@dataclass(frozen=True)
class Triggers:
    """What a device's trigger lines can do in a wiring (`rig.trigger`): `input` a hardware
    trigger input (a camera exposes on its edge; a projector shows its next pattern);
    `output` a projector's per-pattern trigger: "pulse" on a line (the camera needs an
    input), "call" the camera's software trigger; `refusal` the one line refusing a wiring
    it cannot take part in ("{wiring}" is filled in)."""

    input: bool = False
    output: Literal["pulse", "call"] | None = None
    refusal: str = "wiring '{wiring}' needs a trigger line this device does not have; use 'software'"


@dataclass(frozen=True, eq=False)
class Driver:
    """One driver of a device `kind`. `rig`: the rig driver that opens it (a rig driver: its
    own name). `settings`: its keys of the kind's table (a rig driver: of the top-level table
    named after it). `open`: a callable, or "module:function" for a layer the core cannot
    import; None when its rig driver opens it itself. `triggers`: its trigger lines for
    given settings. `devices`: a rig driver's word for its devices ("real", "simulated")."""

    kind: Kind
    name: str
    rig: str
    settings: type[Schema] = NoSettings
    open: Callable[..., Any] | str | None = None
    triggers: Callable[[Any], Triggers] = lambda settings: Triggers()
    axis_settings: type[Schema] = NoSettings  # a stage driver: its keys of each [[stage.axes]] table
    devices: str = ""

    def opener(self) -> Callable[..., Any]:
        """The open function, imported now when given by name."""
        if self.open is None:
            raise TypeError(f"the {self.kind} driver '{self.name}' is opened by its rig driver '{self.rig}'")
        if isinstance(self.open, str):
            module, function = self.open.split(":")
            found: Callable[..., Any] = getattr(importlib.import_module(module), function)
            return found
        return self.open


_DRIVERS: dict[tuple[str, str], Driver] = {}
_scanned = False


def register(driver: Driver) -> Driver:
    """Declare `driver` (at the import of its module); a second driver of the same kind and
    name is a programming error."""
    key = (driver.kind, driver.name)
    if key in _DRIVERS and _DRIVERS[key] is not driver:
        raise ValueError(f"two {driver.kind} drivers named '{driver.name}'")
    _DRIVERS[key] = driver
    return driver


def drivers(kind: Kind, rig: str | None = None) -> dict[str, Driver]:
    """The drivers of `kind` by name (those `rig` opens, when given), sorted by name."""
    _scan()
    found = {d.name: d for (k, _), d in _DRIVERS.items() if k == kind and (rig is None or d.rig == rig)}
    return dict(sorted(found.items()))


def lookup(kind: Kind, name: str | None, rig: str | None, path: object, key: str) -> Driver:
    """The `kind` driver `name` for a rig whose driver is `rig` (None: `name` is a rig
    driver). ConfigError naming `key` and the known drivers when it is unknown or belongs
    to another rig driver; without a name, the one driver of `kind` that `rig` opens."""
    if rig is not None and name is None:
        own = drivers(kind, rig)
        if len(own) == 1:
            return next(iter(own.values()))
        raise ConfigError(path, key, f"required key is missing; the {rig} rig's {kind} drivers: {_names(own)}")
    found = drivers(kind).get(name or "")
    if found is None:
        known = drivers(kind, rig)
        raise ConfigError(path, key, f"'{name}' is not one of {tuple(known)}: no {kind} driver of that name")
    if rig is not None and found.rig != rig:
        own = drivers(kind, rig)
        rig_driver = drivers("rig").get(rig)
        what = f"{rig_driver.devices} " if rig_driver is not None and rig_driver.devices else ""
        raise ConfigError(path, key, f"a {rig} rig drives a {what}{kind.replace('_', ' ')}; set driver = "
                                     f"{_names(own, ' or ')} (got '{name}', a driver of '{found.rig}' rigs)")
    return found


def own_settings(driver: Driver, table: Mapping[str, Any], core: Iterable[str], path: str | Path, prefix: str,
                 axis: bool = False) -> Any:
    """The keys of `table` (named `prefix` in the file) beyond the `core` ones, validated by
    `driver`'s settings schema (with `axis`: its axis_settings, a [[stage.axes]] table). A key
    another driver of the kind declares is ignored and logged, so a table whose driver was
    switched still loads; any other key is refused with the nearest of the core's and the
    driver's names."""
    own_schema = driver.axis_settings if axis else driver.settings
    others = {k for d in drivers(driver.kind).values() if d is not driver
              for k in (d.axis_settings if axis else d.settings).model_fields} - set(own_schema.model_fields)
    core = set(core)
    own, ignored = {}, []
    for key, value in table.items():
        if key in core:
            continue
        if key in own_schema.model_fields:
            own[key] = value
        elif key in others:
            ignored.append(key)
        else:
            problem = schema.unknown_key_problem(key, core | set(own_schema.model_fields), prefix)
            raise ConfigError(path, f"{prefix}.{key}", f"{problem} (the {driver.kind.replace('_', ' ')} driver "
                                                       f"'{driver.name}')")
    if ignored:
        log.warning("%s: [%s] %s: keys of another %s driver, not read by '%s'", path, prefix, ", ".join(ignored),
                    driver.kind.replace("_", " "), driver.name)
    return schema.parse(own_schema, own, path, prefix)


def _names(found: dict[str, Driver], sep: str = ", ") -> str:
    return sep.join(f"'{n}'" for n in found) or "none"


def _scan() -> None:
    """Import every module of this package once: each registers the drivers it declares."""
    global _scanned
    if _scanned:
        return
    package = __name__.rpartition(".")[0]
    for module in pkgutil.iter_modules(importlib.import_module(package).__path__):
        importlib.import_module(f"{package}.{module.name}")
    _scanned = True
