"""The projector's response (gamma), measured from flat grey levels and compensated.

A projector displays command c (0..255) as roughly (c/255)^γ. Fringes rendered without the
inverse of that curve are not sinusoidal: the phase picks up an error at harmonics of the
fringe and a scanned plane comes out wavy, the most reported failure of open-source
scanners. The camera is linear, so the response is measured directly: the projector shows
flat grey levels on a matte surface, each pixel's readings are normalised between black and
white, n(c) = (I(c) − I(0)) / (I(255) − I(0)), and γ is fitted to the median curve over
well-lit pixels. The calibrated γ goes into the rig model; `PatternSet.render` then
pre-compensates every pattern with 1/γ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from calibration.errors import CalibrationError

DEFAULT_LEVELS = np.round(np.linspace(0, 255, 18)).astype(np.uint8)
MIN_CONTRAST = 0.2  # of the best pixels' white − black: dimmer pixels are left out
MIN_PIXELS = 500


@dataclass(frozen=True, eq=False)
class GammaFit:
    """`gamma` and its one-sigma `std`; `levels` (L,) commands, `response` (L,) the median
    normalised reading per level; `rms` of the power-law fit to it (fraction of white)."""

    gamma: float
    std: float
    levels: np.ndarray
    response: np.ndarray
    rms: float
    pixels: int

    def to_dict(self) -> dict[str, object]:
        return {"gamma": self.gamma, "std": self.std, "levels": self.levels.tolist(),
                "response": [round(float(r), 6) for r in self.response], "fit_rms": self.rms, "pixels": self.pixels}

    def summary(self) -> str:
        return (f"projector gamma {self.gamma:.3f} ± {self.std:.3f} (power-law fit RMS {self.rms * 100:.2f} % of "
                f"white over {self.pixels} px)")


def phase_error_rad(gamma: float, steps: int, compensated: bool) -> float:
    """Largest phase error (rad) of an N-step phase shift on a projector of response
    (c/255)^gamma, its fringes rendered as 8-bit commands with (`compensated`) or without
    the inverse response. N-step phase shifting cancels the fringe's harmonics except
    k = m·N ± 1, so the error depends on N (3 steps suffer most); with compensation what is
    left is the commands' 8-bit rounding."""
    phi = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)[:, None]
    delta = 2.0 * np.pi * np.arange(steps) / steps
    profile = 0.5 + 0.5 * np.cos(phi + delta)
    command = np.round(255.0 * (profile ** (1.0 / gamma) if compensated else profile))
    shown = (command / 255.0) ** gamma
    est = np.arctan2(-(shown * np.sin(delta)).sum(axis=1), (shown * np.cos(delta)).sum(axis=1))
    return float(np.abs(np.angle(np.exp(1j * (est - phi[:, 0])))).max())


def flat_images(levels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(L, height, width) uint8 flat projector images, one per level."""
    return np.broadcast_to(np.asarray(levels, dtype=np.uint8)[:, None, None], (len(levels), height, width)).copy()


def fit_gamma(levels: np.ndarray, images: np.ndarray, full_scale: float) -> GammaFit:
    """γ from camera `images` (L, H, W) of flat projector `levels` (L,) that include 0 and
    255; pixels saturated at white or too dim are left out."""
    levels = np.asarray(levels, dtype=np.float64)
    if levels.min() != 0 or levels.max() != 255 or len(levels) < 4:
        raise CalibrationError(f"gamma: need at least 4 levels including 0 and 255, got {levels.tolist()}")
    stack = images.reshape(len(levels), -1).astype(np.float64)
    black, white = stack[np.argmin(levels)], stack[np.argmax(levels)]
    span = white - black
    ok = (stack.max(axis=0) < full_scale) & (span > MIN_CONTRAST * np.percentile(span, 99))
    if ok.sum() < MIN_PIXELS:
        raise CalibrationError(f"gamma: only {int(ok.sum())} well-lit, unsaturated pixels (need {MIN_PIXELS}); "
                               f"point the projector at a matte, light surface and check the exposure")
    response = np.median((stack[:, ok] - black[ok]) / span[ok], axis=1)
    x = levels / 255.0
    inner = (x > 0) & (x < 1)

    def residual(p: np.ndarray) -> np.ndarray:
        return x[inner] ** p[0] - response[inner]

    sol = least_squares(residual, [2.0], bounds=([0.2], [5.0]))
    r = sol.fun
    dof = max(int(inner.sum()) - 1, 1)
    J = sol.jac
    std = float(np.sqrt(float(r @ r) / dof / max(float(J[:, 0] @ J[:, 0]), 1e-300)))
    return GammaFit(float(sol.x[0]), std, levels.astype(np.uint8), response, float(np.sqrt(np.mean(r ** 2))),
                    int(ok.sum()))
