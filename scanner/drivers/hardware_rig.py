"""The `hardware` rig driver: real devices named by a rig TOML (`rig.driver = "hardware"`).

Each device table names its driver (`driver = "..."`; absent: the only one of its kind),
and every key of the table beyond the geometry every rig has (`scanner.rig_schema`) is that
driver's, declared and opened by its own module (docs/drivers.md):

    [camera]      driver = "uvc"               scanner/drivers/uvc.py
                  driver = "genicam"           scanner/drivers/genicam.py
    [projector]   driver = "lightcrafter4500"  scanner/drivers/lightcrafter.py
                  driver = "hdmi"              scanner/drivers/hdmi.py
    [trigger_box] driver = "triggerbox"        scanner/drivers/triggerbox.py (wiring trigger_box only)
    [stage]       driver = "grbl"              scanner/drivers/grbl.py (optional: see scanner/stage_model.py)

Examples: config/rigs/lightcrafter_uvc_box.toml, config/rigs/hdmi_genicam.toml.

Wirings (`rig.trigger`), checked against what each driver declares of its trigger lines
(`scanner.drivers.registry.Triggers`) before anything opens, naming the key:
    software     camera software-triggered after `show(k)`; any projector
    projector    the projector's trigger output per pattern: a pulse on a line (a
                 LightCrafter's TRIG_OUT1) into the camera's trigger input, camera on rising
                 edge; or a call of the camera's software trigger once each pattern is on
                 display (an HDMI window)
    trigger_box  the box -> the projector's trigger input and the camera's

`transports` (tests, or a caller with devices already open) replaces how each device is
reached: keys "camera", "projector", "trigger_box", "stage" (opener callables as the drivers
take) and "display" (an `hdmi.DisplayBackend`).
"""

from __future__ import annotations

import logging
from typing import Any

from scanner.devices import Camera, Device, Projector, TriggerMode, TriggerSource, TriggerType
from scanner.drivers.registry import Driver, Triggers, drivers, register
from scanner.errors import ConfigError, UnsupportedSetting
from scanner.rig import Rig, RigConfig
from scanner.stage import Stage

log = logging.getLogger(__name__)


def open_hardware_rig(config: RigConfig, transports: dict[str, Any] | None = None) -> Rig:
    """Open the devices of `config`; on any failure the ones already open are closed."""
    t = transports or {}
    cam, proj = config.devices["camera"], config.devices["projector"]
    _, proj_triggers = _check_wiring(config)
    opened: list[Device] = []
    try:
        projector: Projector = proj.driver.opener()(config, proj.settings, t)
        opened.append(projector)
        camera: Camera = cam.driver.opener()(config, cam.settings, t)
        opened.append(camera)
        trigger: TriggerSource | None = None
        if config.trigger == "trigger_box":
            box = config.devices["trigger_box"]
            trigger = box.driver.opener()(config, box.settings, t)
            opened.append(trigger)
        _configure_camera(config, camera, hardware=_camera_needs_input(config.trigger, proj_triggers))
        if config.trigger == "projector" and proj_triggers.output == "call":
            projector.connect_trigger_out(camera.trigger)  # type: ignore[attr-defined]  # declared output "call"
        stage = _open_stage(config, t)
        if stage is not None:
            opened.append(stage)
    except BaseException:
        for dev in reversed(opened):
            dev.shutdown()
        raise
    log.info("hardware rig %s opened: %s, %s, wiring %s", config.name, proj.driver.name, cam.driver.name,
             config.trigger)
    return Rig(config=config, camera=camera, projector=projector, trigger=trigger, model=config.nominal_model(),
               stage=stage)


def _camera_needs_input(wiring: str, projector: Triggers) -> bool:
    """Whether the camera exposes on a hardware edge: from the box, or from the projector's line."""
    return wiring == "trigger_box" or (wiring == "projector" and projector.output == "pulse")


def _check_wiring(config: RigConfig) -> tuple[Triggers, Triggers]:
    """The camera's and the projector's trigger lines, when they can run the rig's wiring;
    ConfigError naming `rig.trigger` (with the driver's own line) otherwise."""
    p, wiring = config.path, config.trigger
    cam, proj = config.devices["camera"], config.devices["projector"]
    cam_triggers, proj_triggers = cam.driver.triggers(cam.settings), proj.driver.triggers(proj.settings)
    if wiring == "software":
        return cam_triggers, proj_triggers
    if _camera_needs_input(wiring, proj_triggers) and not cam_triggers.input:
        raise ConfigError(p, "rig.trigger", cam_triggers.refusal.format(wiring=wiring))
    if not (proj_triggers.output if wiring == "projector" else proj_triggers.input):
        raise ConfigError(p, "rig.trigger", proj_triggers.refusal.format(wiring=wiring))
    if wiring == "trigger_box" and "trigger_box" not in config.devices:
        raise ConfigError(p, "trigger_box", "wiring 'trigger_box' needs a [trigger_box] table with the port")
    return cam_triggers, proj_triggers


def _open_stage(config: RigConfig, t: dict[str, Any]) -> Stage | None:
    if config.stage is None:
        return None
    opened: Stage = drivers("stage")[config.stage.driver].opener()(config, config.stage.settings, t)
    return opened


def _configure_camera(config: RigConfig, camera: Camera, hardware: bool) -> None:
    """Bit depth and exposure from the rig's [camera]; triggered on a rising edge when
    `hardware`, else by software."""
    lens = config.file.first_camera
    bits = lens.bit_depth if lens.bit_depth is not None else camera.supported_bit_depths[0]
    exposure = lens.exposure_s if lens.exposure_s is not None else 0.01
    p = config.path
    for key, apply in (("camera.bit_depth", lambda: camera.set_bit_depth(bits)),
                       ("camera.exposure_s", lambda: camera.set_exposure(exposure))):
        try:
            apply()
        except UnsupportedSetting as exc:
            raise ConfigError(p, key, str(exc)) from None
    if exposure > config.period_s and config.trigger != "software":
        raise ConfigError(p, "camera.exposure_s", f"exposure {exposure} s is longer than the pattern period "
                                                  f"{config.period_s} s: frames would mix two patterns")
    camera.set_trigger(TriggerType.RISING_EDGE if hardware else TriggerType.SOFTWARE, TriggerMode.ONCE)


DRIVER = register(Driver("rig", "hardware", "hardware", open=open_hardware_rig, devices="real"))
