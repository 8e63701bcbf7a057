"""The depth noise a simulated scan must show, predicted in the tests from what the simulator
is told (its sensor model, the intensities it renders with, the rig's geometry), never from
the decoder's own estimates (its `background`, `modulation` or `phase_weight`).

Per camera pixel lit by the projector, for N-step phase shifting of displayed fringes
0.5 + 0.5 cos(phase):
  - mean level A = s (ambient + w / 2) and modulation of frequency i
    B_i = s w / 2 · exp(-2 pi^2 sigma_p^2 / P_i^2) · exp(-2 pi^2 sigma_c^2 |grad u|^2 / P_i^2), with
    s = exposure · flux / gain (DN per unit irradiance), w = albedo · cos(incidence) (the
    simulator's truth), P_i the fringe period in projector pixels, sigma_p the projector's
    and sigma_c the camera's defocus blur (pixels) and |grad u| projector pixels per camera
    pixel (from the true projector coordinates): the two blurs' transfer functions;
  - intensity noise sigma_I^2 = A / g + (read noise / g)^2 + 1/12 (DN^2: shot, read,
    quantisation; g electrons per DN, the full well over the full scale);
  - phase noise of the finest fringe, the frequencies combined by inverse variance (the
    best any decoder can do): sigma_phi = sqrt(2 / N) sigma_I / sqrt(sum_i (B_i f_i / f_max)^2);
  - projector coordinate sigma_c = sigma_phi P_finest / (2 pi), and depth
    sigma_z = sigma_c / |du/dz|, with du/dz the change of the projector column as the point
    slides along its camera ray, from the projection written out in `project` below.
"""

from __future__ import annotations

import numpy as np

from scanner.geometry import Pinhole
from scanner.patterns import PatternSet


def project(device: Pinhole, points: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of points (N, 3) in the device's frame (mm), written out from the
    Brown-Conrady model in OpenCV's convention (k1, k2, p1, p2, k3): independent of
    `Pinhole.project` and of the simulator's projection."""
    x, y = points[:, 0] / points[:, 2], points[:, 1] / points[:, 2]
    k1, k2, p1, p2, k3 = device.dist
    r2 = x ** 2 + y ** 2
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x ** 2)
    yd = y * radial + p1 * (r2 + 2 * y ** 2) + 2 * p2 * x * y
    K = device.K
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=1)


def projector_column_per_mm(rig_model: object, points: np.ndarray) -> np.ndarray:
    """|du/dz| (projector pixels per mm of depth) of camera-frame points (N, 3) moved along
    their camera rays (central difference of `project`, +-0.01 mm)."""
    P = rig_model.proj_from_cam  # type: ignore[attr-defined]
    rays = points / points[:, 2:3]
    h = 0.01
    u = [project(rig_model.projector, (points + s * h * rays) @ P[:3, :3].T + P[:3, 3])[:, 0]  # type: ignore[attr-defined]
         for s in (1.0, -1.0)]
    return np.abs(u[0] - u[1]) / (2 * h)


def depth_sigma(rig: object, patterns: PatternSet) -> np.ndarray:
    """Predicted depth noise sigma_z (mm) per camera pixel (H, W) of a scan of the open
    simulated `rig` with vertical-fringe phase-shift `patterns`; NaN where not lit."""
    gt, sensor = rig.extras["ground_truth"], rig.extras["sensor"]  # type: ignore[attr-defined]
    config, model = rig.config, rig.model  # type: ignore[attr-defined]
    if tuple(patterns.orientations) != ("vertical",):
        raise ValueError("depth_sigma: vertical fringes only")
    bits = config.camera.bit_depth or 12
    exposure = config.camera.exposure_s or 0.01
    gain = sensor.full_well_e / (2 ** bits - 1)
    s = exposure * sensor.flux_e_per_s / gain
    w = gt.albedo * gt.cos_incidence
    lit = np.isfinite(gt.proj_uv[..., 0])
    A = s * (sensor.ambient + w / 2)
    sigma_i = np.sqrt(A / gain + (sensor.read_noise_e / gain) ** 2 + 1.0 / 12.0)
    du_dx, du_dy = (np.gradient(gt.proj_uv[..., 0], axis=a) for a in (1, 0))
    grad = np.hypot(du_dx, du_dy)  # projector pixels per camera pixel
    sigma_p = rig.extras["renderer"].projector_blur_sigma_px  # type: ignore[attr-defined]
    extent = model.projector.width
    f_max = max(patterns.fringes)
    precision = np.zeros(lit.shape)
    for f in patterns.fringes:
        period = extent / f
        b = s * w / 2 * np.exp(-2 * np.pi ** 2 * (sigma_p ** 2 + sensor.blur_sigma_px ** 2 * grad ** 2) / period ** 2)
        precision += (b * f / f_max) ** 2
    sigma_phi = np.sqrt(2.0 / patterns.steps) * sigma_i[lit] / np.sqrt(precision[lit])
    sigma_u = sigma_phi * (extent / f_max) / (2 * np.pi)
    out = np.full(lit.shape, np.nan)
    out[lit] = sigma_u / projector_column_per_mm(model, gt.points[lit])
    return out
