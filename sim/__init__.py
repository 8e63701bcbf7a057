"""The virtual rig: a ray-cast scene renderer with ground truth, and simulated camera,
projector and trigger box behind the same interfaces as the real drivers.

Modules:
    scene     scene TOML format and loader (meshes and analytic primitives)
    render    geometry ray casting, ground truth, projector/camera image formation, sensor noise
    devices   SimProjector, SimCamera, SimTriggerBox, Faults
    rig       open_sim_rig: the `sim` driver behind `scanner.rig.open_rig`
    make_demo_part  script writing config/parts/demo_part.ply
"""
