"""Analytic fringe stacks: what the camera would see of a tilted plane with a smooth bump,
without ray tracing (for decode benchmarks and recording tests). Poisson shot noise and
Gaussian read noise in electrons, quantised to the bit depth."""

from __future__ import annotations

import numpy as np

from scanner.geometry import RigModel
from scanner.patterns import PatternSet


def synthetic_stack(rig: RigModel, patterns: PatternSet, bit_depth: int = 12, seed: int = 0) -> np.ndarray:
    """(N, H, W) frames of a tilted plane with a bump at the rig's working distance."""
    rays = rig.camera.ray_grid.astype(np.float64)
    n = np.array([0.15, -0.1, 1.0])
    n /= np.linalg.norm(n)
    z = 400.0 / (rays @ n)
    x, y = rays[..., 0] * z, rays[..., 1] * z
    z -= 8.0 * np.exp(-(x ** 2 + y ** 2) / (2 * 25.0 ** 2))
    pts = rays * z[..., None]
    p = (pts.reshape(-1, 3) - rig.cam_from_proj[:3, 3]) @ rig.cam_from_proj[:3, :3]
    uv = rig.projector.project(p).reshape(*z.shape, 2)
    rng = np.random.default_rng(seed)
    full = 2 ** bit_depth - 1
    specs = patterns.frames()
    out = np.empty((len(specs), *z.shape), dtype=np.uint16)
    size = (rig.projector.width, rig.projector.height)
    for i, s in enumerate(specs):
        axis = 0 if s.orientation == "vertical" else 1
        profile = patterns.profile(s, size[axis])
        c = np.clip(uv[..., axis], 0, size[axis] - 1)
        shown = np.interp(c, np.arange(size[axis]), profile)
        electrons = 400.0 + 7000.0 * shown
        frame = rng.poisson(electrons).astype(np.float64) + rng.normal(0.0, 6.0, z.shape)
        out[i] = np.clip(np.rint(frame / (10500.0 / full)), 0, full)
    return out
