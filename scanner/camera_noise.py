"""The camera's temporal noise as the product models it: shot noise, read noise and
quantisation of a linear sensor whose full well maps onto the full digital range, from the rig's
[camera.sensor] table (`scanner.drivers.simulator.SensorTable`: its keys, ranges and defaults).

  sigma_DN(mean) = sqrt(mean / g + (read noise / g)^2 + 1/12), g = full well / (2**bits - 1) e-/DN

The decoder's noise maps and every uncertainty rest on it; the simulator's sensor
(`sim.render.SensorModel`) draws its images from the same model."""

from __future__ import annotations

import numpy as np

from scanner.drivers.simulator import SensorTable

MAX_BIT_DEPTH = 16  # the deepest camera frames a session stores (uint16)


class CameraNoise(SensorTable):
    """A [camera.sensor] table and the noise it gives a pixel (DN, one sigma)."""

    @staticmethod
    def max_dn(bit_depth: int) -> int:
        """The brightest digital number of `bit_depth`-bit frames."""
        if not 1 <= bit_depth <= MAX_BIT_DEPTH:
            raise ValueError(f"bit depth {bit_depth}: frames have 1..{MAX_BIT_DEPTH} bits")
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
