"""The `sim` drivers: a simulated rig (`rig.driver = "sim"`) and the settings of its devices.

The simulator lives in the `sim` package, a layer above the scanner core, so the core can
neither import it nor find it by scanning this package: this module declares what the
simulator reads from a rig TOML, and names its open function, `sim.virtual_rig.open_sim_rig`,
which opens every device below itself.

    [camera] / [[cameras]]  sensor: the [camera.sensor] table (`SensorTable`)
    [projector]             blur_sigma_px: projector defocus, px
    [trigger_box]           nothing (the simulated box needs no port; the table is optional)
    [stage]                 driver = "sim": the simulated stage (`sim.virtual_stage`)
    [sim]                   faults: the [sim.faults] table (`FaultsTable`)
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

from scanner.drivers.registry import Driver, register
from scanner.schema import Bool, Schema

MAX_BLUR_SIGMA_PX = 10.0
"""The widest defocus (Gaussian sigma, px) a rig can take: a blur of sigma s keeps
exp(-2 pi^2 s^2 / p^2) of a fringe of period p px, so at s = 10 px even a 40 px fringe keeps
under 1 % of its modulation and nothing decodes; wider values are typing errors (a 1e6 px
sigma made the simulator's blur kernel take 19.5 GB)."""

FrameIndex = Annotated[int, Field(strict=True, ge=0)]
Blur = Annotated[float, Field(strict=True, ge=0.0, le=MAX_BLUR_SIGMA_PX)]  # Gaussian sigma, px


class SensorTable(Schema):
    """[camera.sensor] of a simulated rig (read by scanner.camera_noise.CameraNoise, the noise model,
    and sim.render.SensorModel, the simulated sensor), each key within the
    range real sensors span, refused outside it:

        full_well_e    1e3 .. 1e6 e-     (small-pixel CMOS ~2 000, large CCD pixels ~500 000)
        read_noise_e   0 .. 100 e-       (scientific CMOS ~1, CCDs 5-20, the noisiest webcams ~50)
        flux_e_per_s   1e2 .. 1e10 e-/s  (albedo-1 surface under full white, normal incidence)
        ambient        0 .. 1            (ambient light as a fraction of the projector's white;
                                          at 1 the fringes are under half the signal)
        blur_sigma_px  0 .. MAX_BLUR_SIGMA_PX px"""

    full_well_e: Annotated[float, Field(strict=True, ge=1e3, le=1e6)] = 10500.0
    read_noise_e: Annotated[float, Field(strict=True, ge=0.0, le=100.0)] = 6.0
    flux_e_per_s: Annotated[float, Field(strict=True, ge=1e2, le=1e10)] = 900000.0
    ambient: Annotated[float, Field(strict=True, ge=0.0, le=1.0)] = 0.04
    blur_sigma_px: Blur = 0.0


class FaultsTable(Schema):
    """[sim.faults] of a simulated rig (read by sim.virtual_devices.Faults): frame indices, s."""

    drop_frame: FrameIndex | None = None
    delay_frame: FrameIndex | None = None
    delay_s: Annotated[float, Field(strict=True, ge=0.0, le=3600.0)] = 0.0  # no longer than the longest rig timeout_s
    disconnect_after: FrameIndex | None = None
    stale_frame: FrameIndex | None = None
    repeat: Bool = False


class SimSettings(Schema):
    """[sim]: the simulated rig's own table."""

    faults: FaultsTable | None = None


class SimCameraSettings(Schema):
    sensor: SensorTable | None = None


class SimProjectorSettings(Schema):
    blur_sigma_px: Blur = 0.0


RIG = register(Driver("rig", "sim", "sim", SimSettings, "sim.virtual_rig:open_sim_rig", devices="simulated"))
CAMERA = register(Driver("camera", "sim", "sim", SimCameraSettings))
PROJECTOR = register(Driver("projector", "sim", "sim", SimProjectorSettings))
TRIGGER_BOX = register(Driver("trigger_box", "sim", "sim"))
STAGE = register(Driver("stage", "sim", "sim"))
