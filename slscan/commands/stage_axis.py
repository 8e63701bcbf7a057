"""`slscan calibrate --stage-axis`: where the rig's turntable axis is, from a board it turns
(`calibration.stage_axis`).

    slscan calibrate --stage-axis --rig config/rigs/sim_turntable.toml --out DIR [--angles -90,-60,...]

The board (the rig's [calibrate] board, or --board) lies on the platter; the stage turns it
to each angle and the camera takes it under full white. The camera's intrinsics are the
rig's (its calibration file's when it names one: calibrate the camera first). Writes
DIR/stage_axis.json; name it in the rig TOML under [stage] as `calibration = "..."`. On a
simulated rig the simulator puts the board on the turntable and the report ends with the
axis's error against the simulator's truth.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from scanner.config import CONFIG_DIR
from scanner.errors import ScannerError
from slscan.exit_codes import Exit

DEFAULT_BOARD = CONFIG_DIR / "boards" / "sim_charuco_7x5.toml"
DEFAULT_ANGLES_DEG = (-90.0, -60.0, -30.0, 0.0, 30.0, 60.0, 90.0)
TEXELS_PER_PX = 4.0


def cmd_stage_axis(args: argparse.Namespace) -> int:
    from calibration.board import Board
    from calibration.capture import show_images
    from calibration.stage_axis import calibrate_stage_axis, write_stage_axis
    from scanner.rig import RigConfig, open_rig
    from scanner.stage import AxisKind

    config = RigConfig.load(args.rig)
    if config.stage is None:
        raise ScannerError(f"{config.path}: --stage-axis needs a rig with a [stage]")
    axis = next((a for a in config.stage.axes if a.kind is AxisKind.ROTARY), None)
    if axis is None:
        raise ScannerError(f"{config.path}: the stage has no rotary axis to calibrate")
    board = Board.load(args.board or DEFAULT_BOARD)
    angles = [math.radians(a) for a in (_angles(args.angles) if args.angles else DEFAULT_ANGLES_DEG)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    options: dict[str, Any] = {}
    if config.driver == "sim":
        options = {"scene": _sim_scene(config, board), "seed": args.seed}
    model = config.model

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    with open_rig(config, **options) as rig:
        stage = rig.stage
        assert stage is not None
        white = np.full((1, rig.projector.height, rig.projector.width), 255, np.uint8)

        def image(q: float) -> np.ndarray:
            stage.move_to({axis.name: q}).wait(stage.action_deadline_s + 5.0)
            return show_images(rig, white)[0]

        solution = calibrate_stage_axis(image, angles, board, model.camera, model.world_from_cam, say)
    path = write_stage_axis(out / "stage_axis.json", solution, config.stage.nominal, axis.name)
    print(f"axis      {axis.name}: direction {np.round(solution.direction, 6).tolist()}, through "
          f"{np.round(solution.point_mm, 3).tolist()} mm; {solution.views} views, "
          f"residual {solution.residual_mm:.4f} mm RMS, "
          f"turns off by at most {max(abs(a) for a in solution.angle_residuals_deg):.4f} deg")
    if config.driver == "sim":
        truth = config.stage.nominal.axes[[a.name for a in config.stage.nominal.axes].index(axis.name)]
        tilt = math.degrees(math.acos(min(1.0, float(truth.direction @ solution.direction))))
        offset = solution.point_mm - truth.point_mm
        offset -= truth.direction * (truth.direction @ offset)
        print(f"truth     axis tilted {tilt:.4f} deg from the simulator's, its line {np.linalg.norm(offset):.4f} mm "
              f"away (at the axis point)")
    print(f"written   {path}; use it with  calibration = \"{path.resolve()}\"  under [stage] in {config.path}")
    return Exit.OK


def _angles(text: str) -> list[float]:
    try:
        return [float(a) for a in text.split(",") if a.strip()]
    except ValueError:
        raise ScannerError(f"--angles: expected degrees separated by commas, got {text!r}") from None


def _sim_scene(config: Any, board: Any) -> Any:
    from sim.calibration_bench import Target
    from sim.stage_bench import board_on_stage

    truth = config.nominal_model()
    footprint_mm = config.working_distance_mm / truth.camera.K[0, 0]
    target = Target(board.image(board.texture_density(TEXELS_PER_PX / footprint_mm)), board.size_mm,
                    board.image_origin_mm, board.object_points())
    return board_on_stage(target, config.stage.nominal)
