"""Byte transports for the real drivers: USB HID reports (pyusb) and serial lines (pyserial).

A driver talks only through one of the two small protocols below, so its exchanges can be
asserted byte for byte against a fake (see `scanner.drivers.testing`), as pymeasure's
`expected_protocol` does. Each real transport maps the operating system's errors to the
scanner's: a permission error says exactly what to run, an unplugged device raises
DeviceDisconnected, a silent one DeviceTimeout. Every read has a finite timeout.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import time
from collections.abc import Callable
from typing import Any, Protocol

from scanner.config import CONFIG_DIR
from scanner.errors import DeviceDisconnected, DeviceError, DeviceTimeout

log = logging.getLogger(__name__)

UDEV_RULES = CONFIG_DIR / "udev" / "99-slscan.rules"


def usb_permission_advice() -> str:
    """What a user runs so that USB devices of the rig can be opened without root."""
    return (f"no permission to open the USB device; install the udev rules and replug it: "
            f"sudo cp {UDEV_RULES} /etc/udev/rules.d/ && sudo udevadm control --reload-rules && "
            f"sudo udevadm trigger (see {UDEV_RULES.parent / 'README.md'})")


def serial_permission_advice(port: str) -> str:
    """What a user runs so that a serial port can be opened without root."""
    return (f"no permission to open {port}; add yourself to the group owning it and log in again: "
            f"sudo usermod -aG dialout $USER (or install {UDEV_RULES}, see {UDEV_RULES.parent / 'README.md'})")


class HidLink(Protocol):
    """64-byte HID reports to and from one device."""

    def write(self, report: bytes, timeout_s: float) -> None: ...

    def read(self, timeout_s: float) -> bytes: ...

    def close(self) -> None: ...


class SerialLink(Protocol):
    """The subset of `serial.Serial` the drivers use (a real port or an in-memory fake)."""

    timeout: float | None

    def write(self, data: bytes) -> int | None: ...

    def readline(self) -> bytes: ...

    def reset_input_buffer(self) -> None: ...

    def close(self) -> None: ...


class PyUsbHid:
    """A HID interface driven through libusb (pyusb): interrupt OUT and IN endpoints.

    The kernel's usbhid driver is detached from the interface while it is open and
    reattached on close, so the device works again with other software afterwards."""

    def __init__(self, name: str, device: Any, interface: int = 0, ep_out: int = 0x01, ep_in: int = 0x81) -> None:
        self.name = name
        self._dev = device
        self._interface = interface
        self._ep_out = ep_out
        self._ep_in = ep_in
        self._reattach = False

    @classmethod
    def open(cls, name: str, vendor_id: int, product_id: int, *, serial_number: str | None = None,
             interface: int = 0, ep_out: int = 0x01, ep_in: int = 0x81) -> PyUsbHid:
        """Open the first device with these ids (and serial number, if given)."""
        import usb.core
        import usb.util

        try:
            devices = list(usb.core.find(find_all=True, idVendor=vendor_id, idProduct=product_id))
        except usb.core.NoBackendError:
            raise DeviceError(name, "libusb is not installed: sudo apt-get install libusb-1.0-0") from None
        if serial_number is not None:
            devices = [d for d in devices if _usb_serial(d) == serial_number]
        if not devices:
            which = f"{vendor_id:04x}:{product_id:04x}" + (f" serial {serial_number}" if serial_number else "")
            raise DeviceDisconnected(name, f"no USB device {which} found; check the cable and power "
                                           f"(`slscan devices` lists what is connected)")
        link = cls(name, devices[0], interface, ep_out, ep_in)
        try:
            if devices[0].is_kernel_driver_active(interface):
                devices[0].detach_kernel_driver(interface)
                link._reattach = True
            devices[0].set_configuration()
            usb.util.claim_interface(devices[0], interface)
        except usb.core.USBError as exc:
            raise link._error(exc, "opening", None) from None
        log.info("%s: USB device %04x:%04x opened", name, vendor_id, product_id)
        return link

    def write(self, report: bytes, timeout_s: float) -> None:
        import usb.core

        try:
            n = self._dev.write(self._ep_out, report, timeout=max(1, int(timeout_s * 1000)))
        except usb.core.USBError as exc:
            raise self._error(exc, "writing a report", timeout_s) from None
        if n != len(report):
            raise DeviceError(self.name, f"USB write sent {n} of {len(report)} bytes")

    def read(self, timeout_s: float) -> bytes:
        import usb.core

        try:
            return bytes(self._dev.read(self._ep_in, 64, timeout=max(1, int(timeout_s * 1000))))
        except usb.core.USBError as exc:
            raise self._error(exc, "reading a report", timeout_s) from None

    def close(self) -> None:
        import usb.core
        import usb.util

        try:
            usb.util.release_interface(self._dev, self._interface)
            if self._reattach:
                self._dev.attach_kernel_driver(self._interface)
        except usb.core.USBError as exc:
            log.debug("%s: releasing the USB interface failed (%s); the device is already gone", self.name, exc)
        usb.util.dispose_resources(self._dev)

    def _error(self, exc: Any, doing: str, timeout_s: float | None) -> DeviceError:
        code = getattr(exc, "errno", None) or getattr(exc, "backend_error_code", None)
        if code in (errno.EACCES, errno.EPERM, -3):  # -3: LIBUSB_ERROR_ACCESS
            return DeviceError(self.name, usb_permission_advice())
        if code in (errno.ETIMEDOUT, -7):  # -7: LIBUSB_ERROR_TIMEOUT
            return DeviceTimeout(self.name, f"no answer while {doing}", timeout_s,
                                 "power-cycle the device if this repeats")
        if code in (errno.ENODEV, errno.EIO, errno.EPIPE, errno.ENOENT, -4):  # -4: LIBUSB_ERROR_NO_DEVICE
            return DeviceDisconnected(self.name, f"USB device gone while {doing}; check the cable, then scan again "
                                                 f"(the driver reconnects)")
        return DeviceError(self.name, f"USB error while {doing}: {exc}")


def _usb_serial(device: Any) -> str | None:
    try:
        return device.serial_number
    except (ValueError, NotImplementedError, OSError):
        return None


def open_serial(name: str, port: str, baudrate: int, timeout_s: float) -> SerialLink:
    """Open a serial port (or a pyserial URL such as loop://) with a finite read timeout."""
    import serial

    try:
        return serial.serial_for_url(port, baudrate=baudrate, timeout=timeout_s, write_timeout=timeout_s)
    except serial.SerialException as exc:
        code = getattr(exc, "errno", None)
        if code in (errno.EACCES, errno.EPERM) or "Permission denied" in str(exc):
            raise DeviceError(name, serial_permission_advice(port)) from None
        if code in (errno.ENOENT, errno.ENODEV) or "No such file" in str(exc):
            raise DeviceDisconnected(name, f"serial port {port} not found; check the cable (`slscan devices` "
                                           f"lists the ports present)") from None
        raise DeviceError(name, f"cannot open serial port {port}: {exc}") from None


def write_serial(name: str, port: SerialLink, data: bytes, what: str) -> None:
    """Write `data` (`what`: the command, for the message); a vanished port raises
    DeviceDisconnected."""
    import serial

    try:
        port.write(data)
    except (serial.SerialException, OSError) as exc:  # what pyserial raises when the port vanishes
        raise DeviceDisconnected(name, f"serial link lost sending {what!r} ({exc}); check the cable, then scan "
                                       f"again (the driver reconnects)") from None


def read_serial_line(name: str, port: SerialLink) -> str:
    """One line as printable ASCII, its end and any boot noise (a bootloader's bytes before
    a banner) dropped; "" when the port's read timed out. A vanished port raises
    DeviceDisconnected."""
    import serial

    try:
        raw = port.readline()
    except (serial.SerialException, OSError) as exc:
        raise DeviceDisconnected(name, f"serial link lost ({exc}); check the cable, then scan again (the driver "
                                       f"reconnects)") from None
    return "".join(ch for ch in raw.decode("ascii", errors="ignore") if ch.isprintable()).strip()


def close_serial(name: str, port: SerialLink | None) -> None:
    """Close `port` (None: nothing to do); a vanished port has nothing left to release."""
    import serial

    if port is None:
        return
    log.info("%s: serial port closed", name)
    with contextlib.suppress(serial.SerialException, OSError):
        port.close()


class DropsLostPort:
    """Part of a serial driver (its `name`, open `_port` and `_open_port`): a write or read that
    finds the port gone closes and forgets it before raising DeviceDisconnected, so the driver's
    next call reopens the link; `_handshake` opens it and waits for the device's greeting."""

    name: str
    _port: SerialLink | None
    _open_port: Callable[[], SerialLink]

    def _handshake(self, probe: bytes, what: str, greeting: Callable[[str], bool | None], *, retry_s: float,
                   timeout_s: float, missing: str, advice: str) -> SerialLink:
        """The open port, opened now if it is not: `probe` (`what`: its name for messages) is sent
        every `retry_s` s until `greeting(line)` accepts a line (True; it raises on a device of the
        wrong kind) or asks for the probe again at once (False: the device has just booted). After
        `timeout_s` s without a greeting: DeviceTimeout(`missing`, `advice`). Any failure closes
        the port, so the next call starts afresh."""
        if self._port is not None:
            return self._port
        port = self._open_port()
        self._port = port
        end = time.monotonic() + timeout_s
        try:
            while True:
                self._write(port, probe, what)
                window_end = min(end, time.monotonic() + retry_s)
                while time.monotonic() < window_end:
                    accepted = greeting(self._readline(port))
                    if accepted:
                        return port
                    if accepted is False:
                        log.debug("%s: the device has just booted; sending %s again", self.name, what)
                        break
                if time.monotonic() >= end:
                    raise DeviceTimeout(self.name, missing, timeout_s, advice)
                log.debug("%s: no answer to %s yet; sending it again", self.name, what)
        except BaseException:
            self._drop()
            raise

    def _write(self, port: SerialLink, data: bytes, what: str) -> None:
        try:
            write_serial(self.name, port, data, what)
        except DeviceDisconnected:
            self._drop()
            raise

    def _readline(self, port: SerialLink) -> str:
        try:
            return read_serial_line(self.name, port)
        except DeviceDisconnected:
            self._drop()
            raise

    def _drop(self) -> None:
        port, self._port = self._port, None
        close_serial(self.name, port)
