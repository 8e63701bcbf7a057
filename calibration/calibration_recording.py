"""Rerun logging of a calibration, into a `scanner.session_recording.SessionRecording`'s stream.

Entity paths (stable, like the scanner's), on the `view` timeline (the view's index)
unless marked static:

    calibration/camera/image              the board under white light (8-bit)
    calibration/camera/image/corners      Points2D: detected corners
    calibration/camera/image/residuals    Arrows2D: reprojection error x RESIDUAL_SCALE
    calibration/projector/corners         Points2D: corners in projector pixels
    calibration/projector/residuals       Arrows2D: reprojection error x RESIDUAL_SCALE
    calibration/camera/coverage           Image: corners so far per grid cell
    calibration/projector/coverage        Image: the same for the projector
    calibration/errors/camera             Scalars: the view's RMS reprojection error (px)
    calibration/errors/projector          Scalars: the same for the projector
    calibration/gamma/response            Scalars on the `gamma_level` timeline (command 0..255)
    calibration/gamma/fit                 Scalars: the fitted power law, same timeline
    calibration/phase_to_height/<method>  Scalars: RMS height error (mm) on the `plate` timeline
    world/calibration/board/<view>        Points3D: the board's corners in the world (static)
    world/calibration/artefact            Points3D: the validation scan (static)
    world/camera, world/projector, rig    the calibrated rig (`SessionRecording.log_rig`)
    metrics/calibration/<name>            final figures (`SessionRecording.log_metrics`)
    events                                what happened, in words (`SessionRecording.log_event`)
"""

from __future__ import annotations

import numpy as np
import rerun as rr

from calibration.coverage import Coverage
from calibration.detect import to_uint8
from calibration.gamma import GammaFit
from calibration.phase_height import PhaseHeightFit
from calibration.solve import Solution
from calibration.views import Correspondence
from scanner.geometry import RigModel
from scanner.pointcloud import OrganisedCloud
from scanner.session_recording import SessionRecording

TIMELINE_VIEW = "view"
TIMELINE_GAMMA = "gamma_level"
TIMELINE_PLATE = "plate"
ROOT = "calibration"
RESIDUAL_SCALE = 100.0  # residual arrows are drawn this many times longer than the error


class CalibrationRecording:
    """Calibration content for one recording (see the module docstring)."""

    def __init__(self, recording: SessionRecording) -> None:
        self.rec = recording
        self.stream = recording.stream

    def _at_view(self, index: int) -> None:
        self.stream.reset_time()
        self.stream.set_time(TIMELINE_VIEW, sequence=int(index))

    def event(self, text: str, level: str = "INFO") -> None:
        self.rec.log_event(text, level=level)

    def view(self, index: int, image: np.ndarray, corr: Correspondence | None, camera: Coverage,
             projector: Coverage) -> None:
        """One captured view: its image, what was found in it, and the coverage so far."""
        self._at_view(index)
        log = self.stream.log
        log(f"{ROOT}/camera/image", rr.Image(to_uint8(image)), strict=True)
        if corr is not None:
            log(f"{ROOT}/camera/image/corners", rr.Points2D(corr.camera.image_points + 0.5, radii=2.0,
                                                            colors=(40, 220, 40)), strict=True)
            log(f"{ROOT}/projector/corners", rr.Points2D(corr.projector.image_points + 0.5, radii=2.0,
                                                         colors=(230, 120, 30)), strict=True)
        log(f"{ROOT}/camera/coverage", rr.Image(camera.image()), strict=True)
        log(f"{ROOT}/projector/coverage", rr.Image(projector.image()), strict=True)

    def solution(self, solution: Solution, model: RigModel) -> None:
        """Per-view errors and residuals, board poses in 3D, and the rig."""
        s = solution.stereo
        self.rec.log_rig(model)
        for i, name in enumerate(solution.names):
            self._at_view(i)
            corr = solution.correspondences[i]
            for device, res, corr_pts in (("camera", s.camera_residuals[i], corr.camera),
                                          ("projector", s.projector_residuals[i], corr.projector)):
                self.stream.log(f"{ROOT}/errors/{device}", rr.Scalars(float(np.sqrt(np.mean(np.sum(res ** 2, 1))))),
                                strict=True)
                path = f"{ROOT}/camera/image/residuals" if device == "camera" else f"{ROOT}/projector/residuals"
                self.stream.log(path, rr.Arrows2D(origins=corr_pts.image_points + 0.5,
                                                  vectors=res * RESIDUAL_SCALE), strict=True)
            T = model.world_from_cam @ s.board_poses[i]
            X = corr.camera.object_points
            self.stream.log(f"world/calibration/board/{name}", rr.Points3D(X @ T[:3, :3].T + T[:3, 3], radii=0.4),
                            static=True, strict=True)

    def gamma(self, fit: GammaFit) -> None:
        for level, value in zip(fit.levels, fit.response):
            self.stream.reset_time()
            self.stream.set_time(TIMELINE_GAMMA, sequence=int(level))
            self.stream.log(f"{ROOT}/gamma/response", rr.Scalars(float(value)), strict=True)
            self.stream.log(f"{ROOT}/gamma/fit", rr.Scalars(float((level / 255.0) ** fit.gamma)), strict=True)

    def phase_height(self, fit: PhaseHeightFit) -> None:
        for k, e in enumerate(fit.errors):
            self.stream.reset_time()
            self.stream.set_time(TIMELINE_PLATE, sequence=k)
            for method, value in (("eq17", e.eq17_mm), ("per_pixel", e.per_pixel_mm),
                                  ("triangulation", e.triangulation_mm)):
                self.stream.log(f"{ROOT}/phase_to_height/{method}", rr.Scalars(value), strict=True)

    def artefact(self, cloud: OrganisedCloud, model: RigModel) -> None:
        pts, _, _ = cloud.flat()
        T = model.world_from_cam
        self.stream.log("world/calibration/artefact", rr.Points3D(pts @ T[:3, :3].T.astype(np.float32)
                                                                  + T[:3, 3].astype(np.float32)),
                        static=True, strict=True)

    def metrics(self, values: dict[str, float]) -> None:
        self.rec.log_metrics({f"calibration/{k}": v for k, v in values.items()})
