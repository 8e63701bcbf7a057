"""`slscan devices`: what is connected, what each device supports, and the LightCrafter's
flash images.

    slscan devices                         cameras, projectors, displays and serial ports found
    slscan devices --probe                 also ask each serial port whether it is a trigger box or a
                                           GRBL motion controller (a turntable: [stage] driver = "grbl")
    slscan devices --cti PRODUCER.cti      also list GenICam cameras through that producer
    slscan devices lightcrafter-images --rig RIG.toml --out DIR
                                           the 24-bit images to store in the LightCrafter's flash
"""

from __future__ import annotations

import argparse
import glob
import json
import logging
import os
from pathlib import Path
from typing import Any

from slscan.exit_codes import Exit
from slscan.options import add_json

log = logging.getLogger(__name__)


def register(sub: Any) -> None:
    d = sub.add_parser("devices")
    d.add_argument("--probe", action="store_true", help="ask every serial port whether it is an slscan trigger box "
                                                       "or a GRBL motion stage")
    d.add_argument("--cti", help="GenTL producer (.cti) to list GenICam cameras through (needs slscan[genicam])")
    add_json(d)
    d.set_defaults(func=cmd_devices)
    dsub = d.add_subparsers(dest="devices_command", metavar="ACTION",
                            help="lightcrafter-images (without it: the listing)")
    img = dsub.add_parser("lightcrafter-images", help="write the pattern images to store in the LightCrafter flash")
    img.add_argument("--rig", type=Path, required=True, help="rig TOML (its pattern set and projector)")
    img.add_argument("--patterns", type=Path, help="pattern set TOML (default: the rig's)")
    img.add_argument("--out", type=Path, required=True, help="folder for the BMP images and flash_images.json")
    img.set_defaults(func=cmd_lightcrafter_images)


def cmd_devices(args: argparse.Namespace) -> int:
    found = {"cameras (V4L2)": v4l2_cameras(), "GenICam cameras": genicam_cameras(args.cti),
             "USB projectors": usb_projectors(), "displays": displays(), "serial ports": serial_ports(args.probe)}
    if getattr(args, "json", False):
        print(json.dumps(found))
        return Exit.OK
    for title, lines in found.items():
        print(f"{title}:")
        for line in lines or ["(none found)"]:
            print(f"  {line}")
    return Exit.OK


def cmd_lightcrafter_images(args: argparse.Namespace) -> int:
    from scanner.drivers.lightcrafter import LightCrafterSettings
    from scanner.drivers.lightcrafter_images import diamond_resample, export_flash_images, pack_rgb24
    from scanner.drivers.lightcrafter_protocol import HEIGHT, WIDTH
    from scanner.errors import ConfigError
    from scanner.patterns import PatternSet
    from scanner.rig import RigConfig

    config = RigConfig.load(args.rig)
    if config.nominal_model().projector.size != (WIDTH, HEIGHT):
        raise ConfigError(config.path, "projector.width", f"the LightCrafter 4500 is {WIDTH}x{HEIGHT}")
    patterns = PatternSet.load(args.patterns or config.patterns_path)
    settings = config.devices["projector"].settings  # validated at load by the projector's driver
    if not isinstance(settings, LightCrafterSettings):  # another driver's projector of the LightCrafter's size
        settings = LightCrafterSettings()
    shift = settings.odd_row_shift
    stack = diamond_resample(patterns.render(WIDTH, HEIGHT, config.nominal_model().projector_gamma), shift)
    images = pack_rgb24(stack)
    manifest = export_flash_images(images, args.out)
    sha = json.loads(manifest.read_text())["flash_images_sha256"]
    print(f"{len(images)} images for {len(stack)} patterns in {args.out}")
    print("add them, in order, to the LightCrafter firmware with TI's LightCrafter 4500 GUI, then set in the rig TOML:")
    print(f'  flash_images_sha256 = "{sha}"')
    return Exit.OK


def v4l2_cameras() -> list[str]:
    """Video capture nodes with their names (from sysfs), without opening them."""
    out = []
    for node in sorted(glob.glob("/dev/video*")):
        name_file = Path("/sys/class/video4linux") / Path(node).name / "name"
        name = name_file.read_text().strip() if name_file.exists() else "?"
        access = "" if os.access(node, os.R_OK | os.W_OK) else \
            "  [no permission: sudo usermod -aG video $USER, then log in again]"
        out.append(f"{node}: {name}  (driver uvc: 8-bit, software trigger, exposure/gain if the camera has them)"
                   f"{access}")
    return out


def genicam_cameras(cti: str | None) -> list[str]:
    if cti is None:
        return ["(pass --cti <producer.cti> to list them)"]
    try:
        from harvesters.core import Harvester
    except ImportError:
        return ["(needs the optional extra: pip install slscan[genicam])"]
    h = Harvester()
    try:
        h.add_file(cti, check_existence=True)
        h.update()
        return [f"{i.vendor} {i.model} serial {i.serial_number}  (driver genicam: hardware/software trigger, "
                f"Mono8..Mono16)" for i in h.device_info_list]
    finally:
        h.reset()


def usb_projectors() -> list[str]:
    from scanner.drivers import lightcrafter_protocol as p
    from scanner.drivers.transport import usb_permission_advice

    try:
        import usb.core

        found = list(usb.core.find(find_all=True, idVendor=p.VENDOR_ID, idProduct=p.PRODUCT_ID))
    except Exception as exc:  # no libusb backend, or the bus cannot be read
        log.debug("listing USB devices failed", exc_info=True)
        return [f"(cannot list USB devices: {exc})"]
    out = []
    for dev in found:
        try:
            serial = dev.serial_number
            note = ""
        except (ValueError, OSError, NotImplementedError):
            serial, note = "?", f"  [{usb_permission_advice()}]"
        out.append(f"TI DLP LightCrafter 4500 (USB {p.VENDOR_ID:04x}:{p.PRODUCT_ID:04x}, bus {dev.bus} address "
                   f"{dev.address}, serial {serial})  (driver lightcrafter4500: 8-bit pattern sequences from "
                   f"flash, TRIG_OUT1/2, TRIG_IN1, internal or external trigger){note}")
    return out


def displays() -> list[str]:
    try:
        import pygame
    except ImportError:
        return ["(HDMI projectors need the optional extra: pip install slscan[hdmi])"]
    try:
        pygame.display.init()
        sizes = pygame.display.get_desktop_sizes()
    except pygame.error as exc:
        return [f"(no display server: {exc})"]
    finally:
        pygame.display.quit()
    return [f"display {i}: {w}x{h}  (driver hdmi: fullscreen, vsync-locked)" for i, (w, h) in enumerate(sizes)]


def serial_ports(probe: bool) -> list[str]:
    from serial.tools import list_ports

    out = []
    for port in sorted(list_ports.comports(), key=lambda p: p.device):
        line = f"{port.device}: {port.description}"
        if not os.access(port.device, os.R_OK | os.W_OK):
            line += "  [no permission: sudo usermod -aG dialout $USER, then log in again]"
        elif probe:
            line += f"  {_probe_box(port.device)}"
        out.append(line)
    return out


def _probe_box(device: str) -> str:
    from scanner.drivers.triggerbox import TriggerBox, serial_opener
    from scanner.errors import DeviceError

    try:
        box = TriggerBox(serial_opener("probe", device, 0.2), "probe", boot_timeout_s=2.5)
    except DeviceError as exc:
        log.debug("%s is not a trigger box: %s", device, exc)
        return _probe_stage(device) or f"(not a trigger box: {str(exc).split(': ', 1)[-1][:60]})"
    try:
        return f"SLSCAN-TRIGGERBOX protocol {box.identity['protocol']} on {box.identity['board']}"
    finally:
        box.shutdown()


def _probe_stage(device: str, boot_timeout_s: float = 2.5) -> str | None:
    """What a GRBL motion controller on `device` says it is, or None."""
    from scanner.drivers.grbl import identify
    from scanner.errors import DeviceError

    try:
        firmware = identify(device, boot_timeout_s)
    except DeviceError as exc:
        log.debug("%s is not a GRBL controller: %s", device, exc)
        return None
    return f"{firmware} motion controller  (driver grbl: a turntable or slide; [stage] driver = \"grbl\")"
