"""The `sim` driver: a complete virtual rig from a rig config (`scanner.rig.open_rig`).

Declared, with the rig-file keys it reads, in `scanner.drivers.simulator` (the core
cannot import this layer): [camera.sensor], projector.blur_sigma_px, [sim.faults].

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
from typing import Any

from scanner.devices import TriggerMode, TriggerType
from scanner.errors import ConfigError
from scanner.rig import Rig, RigConfig
from scanner.rig_schema import CameraTable
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
    blur = config.devices["projector"].settings.blur_sigma_px  # scanner.drivers.simulator: validated at load
    toml_faults = Faults.from_config(config)  # validated even when overridden
    faults = toml_faults if faults is None else faults
    scene = load_scene(scene, config.working_distance_mm)
    check_in_view(scene, model.camera, model.world_from_cam)  # the (first) camera's view
    projector = SimProjector("sim-projector", model.projector.width, model.projector.height)
    tables: tuple[CameraTable, ...] = config.cameras or (config.camera,)
    models = list(config.camera_models().values())
    cameras: dict[str, SimCamera] = {}
    renderers: dict[str, Renderer] = {}
    trigger = None
    try:
        for i, (name, table, cam_model) in enumerate(zip(config.camera_names, tables, models)):
            prefix = "camera" if not config.cameras else f"cameras.{name}"
            sensor = SensorModel.of(config.devices[prefix].settings.sensor)  # validated at load
            renderer = Renderer(cam_model, scene, sensor, blur)
            device = "sim-camera" if not config.cameras else f"sim-camera-{name}"
            camera = SimCamera(device, renderer, projector, faults=faults, seed=seed + 7919 * i)
            cameras[name], renderers[name] = camera, renderer
            _configure(camera, table, config, prefix)
        if config.trigger == "trigger_box":
            trigger = SimTriggerBox("sim-trigger-box")
            trigger.connect(projector.trigger_in)
        for camera in cameras.values():
            if config.trigger == "projector":
                projector.connect_trigger_out(camera.trigger_in)
            elif config.trigger == "trigger_box":
                trigger.connect(camera.trigger_in)  # type: ignore[union-attr]  # wiring 'box': a trigger box
    except BaseException:
        for dev in (*cameras.values(), projector, trigger):
            if dev is not None:
                dev.shutdown()
        raise
    first = next(iter(cameras))
    camera, renderer = cameras[first], renderers[first]
    log.info("simulated rig %s opened: scene %s, wiring %s, %d camera(s), %d-bit", config.name, scene.name,
             config.trigger, len(cameras), camera.bit_depth)
    extras: dict[str, Any] = {"ground_truth": renderer.ground_truth, "scene": scene, "renderer": renderer,
                              "sensor": renderer.sensor, "faults": faults, "seed": seed,
                              "session_files": [lambda root: Truth.of(extras["renderer"].ground_truth).save(
                                  Path(root) / GROUND_TRUTH_FILE)]}
    if config.cameras:  # every camera's truth and renderer by name
        extras |= {"renderers": renderers, "ground_truths": {n: r.ground_truth for n, r in renderers.items()}}
    rig = Rig(config=config, camera=camera, projector=projector, trigger=trigger, model=model, extras=extras,
              cameras=dict(cameras) if config.cameras else {})
    if config.stage is not None:
        try:
            rig.stage = open_sim_stage(config, rig, stage_faults)
        except BaseException:
            rig.shutdown()
            raise
    return rig


def _configure(camera: SimCamera, table: CameraTable, config: RigConfig, prefix: str) -> None:
    """Bit depth (default 12), exposure (default 10 ms) and trigger type of one simulated
    camera from its rig table."""
    p = config.path
    bits = 12 if table.bit_depth is None else table.bit_depth
    if bits not in SUPPORTED_BIT_DEPTHS:
        raise ConfigError(p, f"{prefix}.bit_depth", f"{bits} not supported by the simulated camera; use one of "
                                                    f"{SUPPORTED_BIT_DEPTHS}")
    camera.set_bit_depth(bits)
    try:
        camera.set_exposure(0.01 if table.exposure_s is None else table.exposure_s)
    except Exception as exc:
        raise ConfigError(p, f"{prefix}.exposure_s", str(exc)) from None
    if config.trigger == "software":
        camera.set_trigger(TriggerType.SOFTWARE, TriggerMode.ONCE)
    else:
        camera.set_trigger(TriggerType.RISING_EDGE, TriggerMode.ONCE)
