"""Each point's expected precision from its decode: the depth noise the fringe modulation
and the triangulation geometry allow.

Per pixel (after `sim.evaluate`'s bound, which this follows without a sensor model): the
N-step phase noise is sigma_phi = sqrt(2/N) sigma_I / B, with B the modulation of the finest
fringes and sigma_I the image noise; for a shot-noise-limited camera sigma_I grows as
sqrt(A), A the mean intensity (the texture). The projector coordinate's noise is
sigma_c = sigma_phi period / (2 pi) and the depth's sigma_z = sigma_c |dz/dc| (the
triangulation's sensitivity, `scanner.reconstruct.Triangulator.depth_scale`). A depth error
moves the point along its camera ray by sigma_z |ray| (ray = (x/z, y/z, 1)); that whole
displacement is taken as the point's noise, not only its part along the surface normal,
which would favour grazing views whose points slide along the surface.

The figures are *relative*: proportional to the true noise for one camera (sigma_I taken as
sqrt(A) DN, i.e. one electron per DN), which is what weighting views against each other
needs. mm (up to that one scale).
"""

from __future__ import annotations

import numpy as np

from inspection.errors import CloudError
from scanner.reconstruct import Triangulator
from scanner.session import OUTPUTS_DIR, Session


def depth_sigma(session: Session) -> np.ndarray:
    """Relative depth noise sigma_z (H, W) of a processed session; NaN where no point."""
    path = session.root / OUTPUTS_DIR / "maps.npz"
    if not path.is_file():
        raise CloudError(session.root, f"no {OUTPUTS_DIR}/maps.npz; run `slscan decode {session.root}` to make it")
    patterns = session.patterns
    triangulator = Triangulator(session.rig_model())
    sizes = {"vertical": session.rig_model().projector.width, "horizontal": session.rig_model().projector.height}
    with np.load(path) as maps:
        texture, valid = maps["texture"].astype(np.float64), maps["valid"]
        inverse_variance = np.zeros(texture.shape)
        for orientation in patterns.orientations:
            coordinate = np.where(valid, maps[f"{orientation}/coordinate"], np.nan)
            modulation = maps[f"{orientation}/modulation"].astype(np.float64)
            _, dz_dc = triangulator.depth_scale(coordinate.astype(np.float32), orientation, sensitivity=True)
            period = sizes[orientation] / max(patterns.fringes)
            sigma_phi = np.sqrt(2.0 / patterns.steps) * np.sqrt(np.maximum(texture, 1.0)) / np.maximum(modulation, 1e-6)
            sigma = sigma_phi * period / (2 * np.pi) * dz_dc
            inverse_variance += np.where(np.isfinite(sigma), 1.0 / np.maximum(sigma, 1e-12) ** 2, 0.0)
    out = np.full(texture.shape, np.nan)
    ok = valid & (inverse_variance > 0)
    out[ok] = 1.0 / np.sqrt(inverse_variance[ok])  # both orientations: averaged by inverse variance, as triangulated
    return out


def ray_sigma(sigma_z: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The displacement noise (N,) of points (N, 3) (camera frame) whose depth noise is
    `sigma_z` (N,): sigma_z |ray|, the ray being the point's direction scaled to z = 1."""
    z = np.maximum(points[:, 2], 1e-9)
    return sigma_z * np.linalg.norm(points / z[:, None], axis=1)
