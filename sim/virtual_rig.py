"""The `sim` driver: a complete virtual rig from a rig config (`scanner.rig.open_rig`).

    rig = open_sim_rig(RigConfig.load(), scene="config/scenes/sphere_plane.toml", seed=1)
    rig.extras["ground_truth"]   # sim.render.GroundTruth of the scene for this rig
    rig.extras["scene"]          # sim.scene.Scene
    rig.extras["renderer"]       # sim.render.Renderer (noise-free images, sensor model)
    rig.extras["sensor"]         # sim.render.SensorModel
    rig.extras["faults"]         # sim.virtual_devices.Faults in effect
    rig.extras["session_files"]  # saves the ground truth (sim.evaluate.Truth) into each session
    rig.stage                    # a sim.virtual_stage.SimStage when the rig TOML has a [stage]:
                                 # each move re-renders the scene turned (the extras above follow it,
                                 # and each session also gets the stage's true pose, STAGE_TRUTH_FILE)

Trigger wiring (`rig.trigger` in the rig TOML):
    software     camera software-triggered; no trigger source, no cable
    projector    camera on rising edge, wired to the projector's trigger output
                 (pulsed per pattern by `projector.run_sequence`)
    trigger_box  camera on rising edge; a SimTriggerBox whose output drives the projector's
                 external trigger input (next pattern) and then the camera
"""

from __future__ import annotations

import logging
from pathlib import Path

from scanner.config import get
from scanner.devices import TriggerMode, TriggerType
from scanner.errors import ConfigError
from scanner.rig import Rig, RigConfig
from sim.evaluate import GROUND_TRUTH_FILE, Truth
from sim.render import SUPPORTED_BIT_DEPTHS, Renderer, SensorModel
from sim.scene import Scene, check_in_view, load_scene
from sim.virtual_devices import Faults, SimCamera, SimProjector, SimTriggerBox
from sim.virtual_stage import StageFaults, open_sim_stage

log = logging.getLogger(__name__)


def open_sim_rig(config: RigConfig, scene: Scene | str | Path | None = None, faults: Faults | None = None,
                 seed: int = 0, stage_faults: StageFaults | None = None) -> Rig:
    """Open the simulated devices of `config` looking at `scene` (a Scene, a scene TOML or
    a bare mesh path; default `config/scenes/demo.toml`). `faults` overrides the rig
    TOML's optional [sim.faults] table; `seed` makes the noise reproducible; `stage_faults`
    are the simulated stage's (`sim.virtual_stage`)."""
    model = config.nominal_model()
    p = config.path
    sensor = SensorModel.from_config(config)
    blur = get(config.projector, "blur_sigma_px", float, p, 0.0, "projector")
    if blur < 0:
        raise ConfigError(p, "projector.blur_sigma_px", f"must be >= 0, got {blur}")
    bits = get(config.camera, "bit_depth", int, p, 12, "camera")
    if bits not in SUPPORTED_BIT_DEPTHS:
        raise ConfigError(p, "camera.bit_depth", f"{bits} not supported by the simulated camera; use one of "
                                                 f"{SUPPORTED_BIT_DEPTHS}")
    exposure = get(config.camera, "exposure_s", float, p, 0.01, "camera")
    toml_faults = Faults.from_config(config)  # validated even when overridden
    faults = toml_faults if faults is None else faults
    scene = load_scene(scene, config.working_distance_mm)
    check_in_view(scene, model.camera, model.world_from_cam)

    renderer = Renderer(model, scene, sensor, blur)
    projector = SimProjector("sim-projector", model.projector.width, model.projector.height)
    camera = SimCamera("sim-camera", renderer, projector, faults=faults, seed=seed)
    trigger = None
    try:
        camera.set_bit_depth(bits)
        try:
            camera.set_exposure(exposure)
        except Exception as exc:
            raise ConfigError(p, "camera.exposure_s", str(exc)) from None
        if config.trigger == "software":
            camera.set_trigger(TriggerType.SOFTWARE, TriggerMode.ONCE)
        else:
            camera.set_trigger(TriggerType.RISING_EDGE, TriggerMode.ONCE)
            if config.trigger == "projector":
                projector.connect_trigger_out(camera.trigger_in)
            else:
                trigger = SimTriggerBox("sim-trigger-box")
                trigger.connect(projector.trigger_in)
                trigger.connect(camera.trigger_in)
    except BaseException:
        for dev in (camera, projector, trigger):
            if dev is not None:
                dev.shutdown()
        raise
    log.info("simulated rig %s opened: scene %s, wiring %s, %d-bit camera", config.name, scene.name,
             config.trigger, bits)
    extras = {"ground_truth": renderer.ground_truth, "scene": scene, "renderer": renderer, "sensor": sensor,
              "faults": faults, "seed": seed,
              "session_files": [lambda root: Truth.of(extras["renderer"].ground_truth).save(Path(root) / GROUND_TRUTH_FILE)]}
    rig = Rig(config=config, camera=camera, projector=projector, trigger=trigger, model=model, extras=extras)
    if config.stage is not None:
        try:
            rig.stage = open_sim_stage(config, rig, stage_faults)
        except BaseException:
            rig.shutdown()
            raise
    return rig
