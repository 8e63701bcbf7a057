"""Fringe frames with known truth: what an ideal camera sees of a pattern set (no blur)."""

from __future__ import annotations

import numpy as np

from scanner.patterns import PatternSet


def fringe_stack(u: np.ndarray, patterns: PatternSet, extent: int, amplitude: float = 1200.0,
                 offset: float = 1500.0, noise: float = 0.0, seed: int = 0, bits: int = 12) -> np.ndarray:
    """Frames for projector coordinates `u` (H, W) along the coded axis, as the camera
    would see them (no blur), with Gaussian noise of `noise` DN."""
    rng = np.random.default_rng(seed)
    out = []
    for s in patterns.frames():
        profile = patterns.profile(s, extent)
        shown = np.interp(u, np.arange(extent), profile)
        img = offset + amplitude * (2 * shown - 1) + rng.normal(0, noise, u.shape) if noise else \
            offset + amplitude * (2 * shown - 1)
        out.append(np.clip(np.rint(img), 0, 2 ** bits - 1).astype(np.uint16))
    return np.stack(out)
