"""The drivers a rig TOML names, behind the device interfaces of `scanner.devices`.

One module per device family (`lightcrafter`, `hdmi`, `uvc`, `genicam`, `triggerbox`,
`grbl`), each declaring its driver, its keys of the rig file and how it opens in the
registry (`registry`, docs/drivers.md); the `hardware` rig driver that opens them
(`hardware_rig`); the simulator's declaration (`simulator`). Besides: the byte-level
protocols kept pure (`lightcrafter_protocol`), the transports that carry them
(`transport`), fakes and emulators for protocol tests (`testing`, `grbl_emulator`).
Optional libraries (harvesters, pygame, usb) are imported only when a device opens.
"""
