"""The simulated camera sensor: electrons to digital numbers, with shot noise, read noise,
quantisation and clipping.

  image = quantise((Poisson(electrons) + Normal(0, read noise)) / gain), gain =
      full_well / (2**bits - 1) e-/DN, clipped to 0 .. 2**bits - 1 (uint8 for 8 bits, else
      uint16).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from scanner.config import get, get_table
from scanner.errors import ConfigError

SUPPORTED_BIT_DEPTHS = (8, 10, 12)


@dataclass(frozen=True)
class SensorModel:
    """The simulated camera sensor and illumination levels ([camera.sensor] in the rig TOML).

    `flux_e_per_s`: electrons per second for an albedo-1 surface under full projector
    white at normal incidence; `ambient`: uniform ambient light as a fraction of that;
    `blur_sigma_px`: camera defocus (Gaussian sigma, camera pixels)."""

    full_well_e: float = 10500.0
    read_noise_e: float = 6.0
    flux_e_per_s: float = 900000.0
    ambient: float = 0.04
    blur_sigma_px: float = 0.0

    def __post_init__(self) -> None:
        if not self.full_well_e > 0 or self.read_noise_e < 0 or self.flux_e_per_s < 0:
            raise ValueError(f"implausible sensor: {self}")
        if self.ambient < 0 or self.blur_sigma_px < 0:
            raise ValueError(f"ambient and blur must be >= 0: {self}")

    @classmethod
    def from_table(cls, table: dict[str, Any], path: object, prefix: str = "camera.sensor") -> SensorModel:
        """From a [camera.sensor] table; errors name the file and key."""
        known = {"full_well_e", "read_noise_e", "flux_e_per_s", "ambient", "blur_sigma_px"}
        for k in table:
            if k not in known:
                raise ConfigError(path, f"{prefix}.{k}", f"unknown key; expected one of {sorted(known)}")
        d = cls()
        vals = {k: get(table, k, float, path, getattr(d, k), prefix) for k in sorted(known)}
        for k, lo in (("full_well_e", 1e-9), ("read_noise_e", 0.0), ("flux_e_per_s", 0.0), ("ambient", 0.0),
                      ("blur_sigma_px", 0.0)):
            if vals[k] < lo:
                raise ConfigError(path, f"{prefix}.{k}", f"must be {'> 0' if lo else '>= 0'}, got {vals[k]}")
        return cls(**vals)

    @classmethod
    def from_config(cls, config: Any) -> SensorModel:
        """From a `scanner.rig.RigConfig` (its [camera.sensor] table, optional)."""
        return cls.from_table(get_table(config.camera, "sensor", config.path, required=False, prefix="camera"),
                              config.path)

    @staticmethod
    def max_dn(bit_depth: int) -> int:
        check_bits(bit_depth)
        return (1 << bit_depth) - 1

    def gain_e_per_dn(self, bit_depth: int) -> float:
        """Electrons per digital number: the full well maps onto the full range."""
        return self.full_well_e / self.max_dn(bit_depth)

    def noise_sigma_dn(self, mean_dn: np.ndarray | float, bit_depth: int) -> np.ndarray:
        """Temporal noise (DN, one sigma) of a pixel whose mean signal is `mean_dn`:
        shot noise, read noise and quantisation (1/12 DN^2). Valid below saturation."""
        g = self.gain_e_per_dn(bit_depth)
        m = np.maximum(np.asarray(mean_dn, dtype=np.float64), 0.0)
        return np.sqrt(m / g + (self.read_noise_e / g) ** 2 + 1.0 / 12.0)

    def expose(self, mean_electrons: np.ndarray, bit_depth: int, rng: np.random.Generator) -> np.ndarray:
        """A noisy digitised image of a mean electron image."""
        g = self.gain_e_per_dn(bit_depth)
        lam = np.maximum(mean_electrons, 0.0)
        e = rng.poisson(lam).astype(np.float32)
        if self.read_noise_e > 0:
            e += rng.standard_normal(e.shape, dtype=np.float32) * np.float32(self.read_noise_e)
        dn = np.rint(e * np.float32(1.0 / g))
        np.clip(dn, 0, self.max_dn(bit_depth), out=dn)
        return dn.astype(np.uint8 if bit_depth == 8 else np.uint16)


def check_bits(bit_depth: int) -> None:
    """Refuse a bit depth the simulated sensor does not have."""
    if bit_depth not in SUPPORTED_BIT_DEPTHS:
        raise ValueError(f"bit depth {bit_depth} not supported; choose one of {SUPPORTED_BIT_DEPTHS}")
