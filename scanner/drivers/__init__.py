"""Real-hardware drivers behind the device interfaces of `scanner.devices`.

One module per device family (`lightcrafter`, `hdmi`, `uvc`, `genicam`, `triggerbox`), the
byte-level protocols kept pure (`lightcrafter_protocol`), the transports that carry them
(`transport`), fakes for protocol tests (`testing`), and the `hardware` rig factory
(`rig.open_hardware_rig`). Optional libraries (harvesters, pygame) are imported only by
the driver that needs them.
"""
