"""The simulated camera sensor: electrons to digital numbers, with shot noise, read noise,
quantisation and clipping.

  image = quantise((Poisson(electrons) + Normal(0, read noise)) / gain), gain =
      full_well / (2**bits - 1) e-/DN, clipped to 0 .. 2**bits - 1 (uint8 for 8 bits, else
      uint16).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from scanner.camera_noise import CameraNoise
from scanner.drivers.simulator import SensorTable

if TYPE_CHECKING:
    from scanner.rig import RigConfig

SUPPORTED_BIT_DEPTHS = (8, 10, 12)


class SensorModel(CameraNoise):
    """The simulated camera sensor and illumination levels: a [camera.sensor] table of the
    rig TOML and what it does to an image (its noise: `scanner.camera_noise.CameraNoise`, the
    model the product's uncertainty uses).

    `flux_e_per_s`: electrons per second for an albedo-1 surface under full projector
    white at normal incidence; `ambient`: uniform ambient light as a fraction of that;
    `blur_sigma_px`: camera defocus (Gaussian sigma, camera pixels)."""

    @classmethod
    def of(cls, table: SensorTable | None) -> SensorModel:
        """The sensor of a validated [camera.sensor] table (None: the defaults)."""
        return cls() if table is None else cls.model_validate(table.model_dump())

    @classmethod
    def from_config(cls, config: RigConfig) -> SensorModel:
        """From a rig's camera ([camera.sensor], validated at load; optional)."""
        return cls.of(config.devices["camera"].settings.sensor)

    @staticmethod
    def max_dn(bit_depth: int) -> int:
        check_bits(bit_depth)
        return CameraNoise.max_dn(bit_depth)

    def expose(self, mean_electrons: np.ndarray, bit_depth: int, rng: np.random.Generator) -> np.ndarray:
        """A noisy digitised image of a mean electron image."""
        g = self.gain_e_per_dn(bit_depth)
        lam = np.maximum(mean_electrons, 0.0)
        e = rng.poisson(lam).astype(np.float32)
        if self.read_noise_e > 0:
            noise = rng.standard_normal(e.shape, dtype=np.float32)
            noise *= np.float32(self.read_noise_e)
            e += noise
        e *= np.float32(1.0 / g)  # in place, as above: no full-frame temporaries
        np.rint(e, out=e)
        np.clip(e, 0, self.max_dn(bit_depth), out=e)
        return e.astype(np.uint8 if bit_depth == 8 else np.uint16)


def check_bits(bit_depth: int) -> None:
    """Refuse a bit depth the simulated sensor does not have."""
    if bit_depth not in SUPPORTED_BIT_DEPTHS:
        raise ValueError(f"bit depth {bit_depth} not supported; choose one of {SUPPORTED_BIT_DEPTHS}")
