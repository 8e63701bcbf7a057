"""How far one rig model is from another (a calibration against the simulator's ground
truth): focal lengths in percent, principal points in pixels, the projector's pose in mm
and degrees."""

from __future__ import annotations

import numpy as np

from scanner.geometry import RigModel


def model_errors(estimated: RigModel, truth: RigModel) -> dict[str, float]:
    """Errors of `estimated` against `truth`: '<device>.fx_pct', '.fy_pct', '.cx_px', '.cy_px',
    'translation_mm' (norm of the difference of the projector centres, camera frame) and
    'rotation_deg' (angle of the relative rotation)."""
    out: dict[str, float] = {}
    for name in ("camera", "projector"):
        K, Kt = getattr(estimated, name).K, getattr(truth, name).K
        out[f"{name}.fx_pct"] = float((K[0, 0] / Kt[0, 0] - 1.0) * 100.0)
        out[f"{name}.fy_pct"] = float((K[1, 1] / Kt[1, 1] - 1.0) * 100.0)
        out[f"{name}.cx_px"] = float(K[0, 2] - Kt[0, 2])
        out[f"{name}.cy_px"] = float(K[1, 2] - Kt[1, 2])
    T, Tt = estimated.cam_from_proj, truth.cam_from_proj
    out["translation_mm"] = float(np.linalg.norm(T[:3, 3] - Tt[:3, 3]))
    R = T[:3, :3] @ Tt[:3, :3].T
    out["rotation_deg"] = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))
    return out


def error_lines(errors: dict[str, float]) -> list[str]:
    """The errors for people."""
    out = []
    for name in ("camera", "projector"):
        out.append(f"{name:<10} fx {errors[f'{name}.fx_pct']:+.4f} %  fy {errors[f'{name}.fy_pct']:+.4f} %  "
                   f"cx {errors[f'{name}.cx_px']:+.3f} px  cy {errors[f'{name}.cy_px']:+.3f} px")
    out.append(f"extrinsic  translation {errors['translation_mm']:.4f} mm  rotation {errors['rotation_deg']:.5f} deg")
    return out
