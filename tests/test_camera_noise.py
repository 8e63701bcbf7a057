"""The product's camera noise model (scanner/camera_noise.py) against its closed form and against
images drawn independently in the test (Poisson electrons, Gaussian read noise, rounding)."""

from __future__ import annotations

import numpy as np
import pytest

from scanner import schema
from scanner.camera_noise import CameraNoise
from scanner.errors import ConfigError


@pytest.mark.parametrize("bits", [8, 12, 16])
def test_noise_is_shot_read_and_quantisation(bits: int) -> None:
    """A 16-bit camera (which the simulator does not render) is modelled too; sigma matches the
    spread of frames drawn here from the same physics, to the 2 % a 250 000-pixel sample allows."""
    model = CameraNoise(full_well_e=20000.0, read_noise_e=7.0)
    gain = 20000.0 / (2 ** bits - 1)
    mean_e = 0.4 * 20000.0
    rng = np.random.default_rng(20261206)
    electrons = rng.poisson(mean_e, 250_000) + rng.normal(0.0, 7.0, 250_000)
    frames = np.rint(electrons / gain)
    expected = float(np.sqrt(mean_e / gain / gain + (7.0 / gain) ** 2 + 1 / 12))
    assert float(model.noise_sigma_dn(mean_e / gain, bits)) == pytest.approx(expected, rel=1e-12)
    assert frames.std() == pytest.approx(expected, rel=0.02)


def test_a_bit_depth_no_frame_has_is_refused() -> None:
    with pytest.raises(ValueError, match="1..16 bits"):
        CameraNoise().noise_sigma_dn(100.0, 17)


def test_a_table_outside_what_sensors_span_names_the_file_and_key() -> None:
    with pytest.raises(ConfigError, match=r"rig\.toml.*camera\.sensor\.read_noise_e"):
        schema.parse(CameraNoise, {"read_noise_e": 500.0}, "rig.toml", "camera.sensor")
