"""The `hardware` rig driver: real devices named by a rig TOML (`rig.driver = "hardware"`).

    [camera]     driver = "uvc"      device = "/dev/video0", fps, gain
                 driver = "genicam"  cti = "<producer.cti>", serial, trigger_line, gain_db
    [projector]  driver = "lightcrafter4500"  source = "flash" | "video", flash_first_image,
                          flash_images_sha256, leds, led_currents, trig_out1_delays_us,
                          trig_out2_delay_us, trig_in1_delay_us, odd_row_shift, usb_serial,
                          video_display, refresh_hz, latency_frames (video source)
                 driver = "hdmi"     display, refresh_hz, latency_frames
    [trigger_box] port = "/dev/ttyACM0", boot_timeout_s   (wiring trigger_box only)
    [stage]      driver = "grbl", port, ... (optional: a turntable; see scanner/stage_model.py)
plus the geometry keys every rig has (see `scanner.rig.RigConfig`). Examples:
config/rigs/lightcrafter_uvc_box.toml, config/rigs/hdmi_genicam.toml.

Wirings (`rig.trigger`):
    software     camera software-triggered after `show(k)`; any projector
    projector    LightCrafter (flash, internal timing): TRIG_OUT1 -> camera trigger input,
                 camera on rising edge; HDMI: the window's trigger output calls the
                 camera's software trigger once each pattern is on display
    trigger_box  the box -> LightCrafter TRIG_IN1 (external trigger) and camera input
A wiring a device cannot do is refused here, naming the key, before anything opens.

`transports` (tests, or a caller with devices already open) replaces how each device is
reached: keys "camera", "projector", "trigger_box", "stage" (opener callables as the drivers
take) and "display" (an `hdmi.DisplayBackend`).
"""

from __future__ import annotations

import logging
from typing import Any, Callable

from scanner.config import get, get_table
from scanner.devices import Camera, Device, Projector, TriggerMode, TriggerSource, TriggerType
from scanner.drivers import lightcrafter_protocol as lcp
from scanner.errors import ConfigError, UnsupportedSetting
from scanner.rig import Rig, RigConfig
from scanner.stage import Stage

log = logging.getLogger(__name__)

CAMERA_DRIVERS = ("uvc", "genicam")
PROJECTOR_DRIVERS = ("lightcrafter4500", "hdmi")


def open_hardware_rig(config: RigConfig, transports: dict[str, Any] | None = None) -> Rig:
    """Open the devices of `config`; on any failure the ones already open are closed."""
    t = transports or {}
    p = config.path
    cam_driver = get(config.camera, "driver", str, p, prefix="camera")
    proj_driver = get(config.projector, "driver", str, p, prefix="projector")
    if cam_driver not in CAMERA_DRIVERS:
        raise ConfigError(p, "camera.driver", f"'{cam_driver}' is not one of {CAMERA_DRIVERS}")
    if proj_driver not in PROJECTOR_DRIVERS:
        raise ConfigError(p, "projector.driver", f"'{proj_driver}' is not one of {PROJECTOR_DRIVERS}")
    _check_wiring(config, cam_driver, proj_driver)
    opened: list[Device] = []
    try:
        projector = _open_projector(config, proj_driver, t)
        opened.append(projector)
        camera = _open_camera(config, cam_driver, t)
        opened.append(camera)
        trigger = None
        if config.trigger == "trigger_box":
            trigger = _open_trigger_box(config, t)
            opened.append(trigger)
        _configure_camera(config, camera, proj_driver)
        if config.trigger == "projector" and proj_driver == "hdmi":
            projector.connect_trigger_out(camera.trigger)  # type: ignore[attr-defined]
        stage = _open_stage(config, t)
        if stage is not None:
            opened.append(stage)
    except BaseException:
        for dev in reversed(opened):
            dev.shutdown()
        raise
    log.info("hardware rig %s opened: %s, %s, wiring %s", config.name, proj_driver, cam_driver, config.trigger)
    return Rig(config=config, camera=camera, projector=projector, trigger=trigger, model=config.nominal_model(),
               stage=stage)


def _check_wiring(config: RigConfig, cam_driver: str, proj_driver: str) -> None:
    p, wiring = config.path, config.trigger
    if wiring != "software" and cam_driver == "uvc" and not (wiring == "projector" and proj_driver == "hdmi"):
        raise ConfigError(p, "rig.trigger", f"a UVC camera has no trigger input, so wiring '{wiring}' cannot expose "
                                            f"it; use 'software' (or an HDMI projector with 'projector')")
    if proj_driver == "hdmi" and wiring == "trigger_box":
        raise ConfigError(p, "rig.trigger", "an HDMI projector has no trigger input; use 'software' or 'projector'")
    if proj_driver == "lightcrafter4500":
        source = get(config.projector, "source", str, p, "flash", "projector")
        if source == "video" and wiring != "software":
            raise ConfigError(p, "rig.trigger", "a LightCrafter on its video port runs wiring 'software' only; "
                                                "use projector.source = 'flash' for hardware-timed sequences")
    if wiring == "trigger_box" and "trigger_box" not in config.raw:
        raise ConfigError(p, "trigger_box", "wiring 'trigger_box' needs a [trigger_box] table with the port")


def _open_projector(config: RigConfig, driver: str, t: dict[str, Any]) -> Projector:
    p, table = config.path, config.projector
    width = get(table, "width", int, p, prefix="projector")
    height = get(table, "height", int, p, prefix="projector")
    if driver == "hdmi":
        from scanner.drivers.hdmi import HdmiProjector

        display = _display(config, "display", t)
        projector = HdmiProjector(display, "hdmi-projector")
        if (projector.width, projector.height) != (width, height):
            projector.shutdown()
            raise ConfigError(p, "projector.width", f"display {get(table, 'display', int, p, 1, 'projector')} is "
                                                    f"{projector.width}x{projector.height}, the rig says "
                                                    f"{width}x{height}; set the display mode or the TOML")
        return projector
    from scanner.drivers.lightcrafter import LightCrafter4500, open_usb

    if (width, height) != (lcp.WIDTH, lcp.HEIGHT):
        raise ConfigError(p, "projector.width", f"the LightCrafter 4500 DMD is {lcp.WIDTH}x{lcp.HEIGHT} (diamond "
                                                f"pixels); the rig says {width}x{height}")
    trigger = "external" if config.trigger == "trigger_box" else "internal"
    source = get(table, "source", str, p, "flash", "projector")
    video = _display(config, "video_display", t) if source == "video" else None
    currents = get(table, "led_currents", list, p, None, "projector")
    kw: dict[str, Any] = dict(
        source=source, trigger=trigger, period_s=config.period_s,
        flash_first_image=get(table, "flash_first_image", int, p, 0, "projector"),
        flash_images_sha256=get(table, "flash_images_sha256", str, p, None, "projector"),
        leds=get(table, "leds", str, p, "white", "projector"),
        led_currents=tuple(currents) if currents is not None else None,
        trig_out1_delays_us=tuple(get(table, "trig_out1_delays_us", list, p, [0.0, 0.0], "projector")),
        trig_out2_delay_us=get(table, "trig_out2_delay_us", float, p, 0.0, "projector"),
        trig_in1_delay_us=get(table, "trig_in1_delay_us", float, p, 0.0, "projector"),
        odd_row_shift=get(table, "odd_row_shift", float, p, 0.5, "projector"), video=video)
    opener = t.get("projector") or open_usb("lightcrafter4500", get(table, "usb_serial", str, p, None, "projector"))
    try:
        return LightCrafter4500(opener, "lightcrafter4500", **kw)
    except BaseException:
        if video is not None:
            video.close()
        raise


def _display(config: RigConfig, key: str, t: dict[str, Any]) -> Any:
    from scanner.drivers.hdmi import HdmiDisplay, PygameBackend

    p, table = config.path, config.projector
    index = get(table, key, int, p, 1, "projector")
    backend = t.get("display") or PygameBackend("hdmi-projector", index)
    return HdmiDisplay(backend, "hdmi-projector", get(table, "refresh_hz", float, p, 60.0, "projector"),
                       get(table, "latency_frames", int, p, 2, "projector"))


def _open_camera(config: RigConfig, driver: str, t: dict[str, Any]) -> Camera:
    p, table = config.path, config.camera
    width = get(table, "width", int, p, prefix="camera")
    height = get(table, "height", int, p, prefix="camera")
    if driver == "uvc":
        from scanner.drivers.uvc import UvcCamera, v4l2_opener

        fps = get(table, "fps", float, p, 30.0, "camera")
        device: str | int = get(table, "device", (str, int), p, "/dev/video0", "camera")
        opener: Callable[[], Any] = t.get("camera") or v4l2_opener("uvc-camera", device, width, height, fps)
        return UvcCamera(opener, "uvc-camera", width, height, fps, get(table, "gain", float, p, None, "camera"))
    from scanner.drivers.genicam import GenICamCamera, harvester_opener

    opener = t.get("camera") or harvester_opener("genicam-camera", get(table, "cti", str, p, prefix="camera"),
                                                   get(table, "serial", str, p, None, "camera"))
    return GenICamCamera(opener, "genicam-camera", width, height, get(table, "trigger_line", str, p, "Line0", "camera"),
                         get(table, "gain_db", float, p, None, "camera"))


def _open_trigger_box(config: RigConfig, t: dict[str, Any]) -> TriggerSource:
    from scanner.drivers.triggerbox import TriggerBox, serial_opener

    p = config.path
    table = get_table(config.raw, "trigger_box", p)
    opener = t.get("trigger_box") or serial_opener("trigger-box", get(table, "port", str, p, prefix="trigger_box"))
    return TriggerBox(opener, "trigger-box", get(table, "boot_timeout_s", float, p, 3.0, "trigger_box"))


def _open_stage(config: RigConfig, t: dict[str, Any]) -> Stage | None:
    if config.stage is None:
        return None
    if config.stage.driver != "grbl":
        raise ConfigError(config.path, "stage.driver", f"a hardware rig drives a real stage; set driver = 'grbl' "
                                                       f"(got '{config.stage.driver}')")
    from scanner.drivers.grbl import open_grbl_stage

    return open_grbl_stage(config.stage, t.get("stage"))


def _configure_camera(config: RigConfig, camera: Camera, proj_driver: str) -> None:
    p = config.path
    bits = get(config.camera, "bit_depth", int, p, camera.supported_bit_depths[0], "camera")
    exposure = get(config.camera, "exposure_s", float, p, 0.01, "camera")
    for key, apply in (("camera.bit_depth", lambda: camera.set_bit_depth(bits)),
                       ("camera.exposure_s", lambda: camera.set_exposure(exposure))):
        try:
            apply()
        except UnsupportedSetting as exc:
            raise ConfigError(p, key, str(exc)) from None
    if exposure > config.period_s and config.trigger != "software":
        raise ConfigError(p, "camera.exposure_s", f"exposure {exposure} s is longer than the pattern period "
                                                  f"{config.period_s} s: frames would mix two patterns")
    hardware = config.trigger == "trigger_box" or (config.trigger == "projector" and proj_driver == "lightcrafter4500")
    camera.set_trigger(TriggerType.RISING_EDGE if hardware else TriggerType.SOFTWARE, TriggerMode.ONCE)
