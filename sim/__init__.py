"""The virtual rig: a ray-cast scene renderer with ground truth, and simulated camera,
projector and trigger box behind the same interfaces as the real drivers.

Modules:
    scene             scene TOML format and loader (meshes and analytic primitives)
    render/           image formation: raytrace, projection, ground_truth, bspline, sensor, renderer
    virtual_devices   SimProjector, SimCamera, SimTriggerBox, Faults
    virtual_rig       open_sim_rig: the `sim` driver behind `scanner.rig.open_rig`
    evaluate          scan accuracy against the ground truth
    analytic_stack    fringe stacks of an analytic surface, without ray tracing (benchmarks)
    calibration_bench moving targets, plates and artefacts for `slscan calibrate` on the simulator
    parts             CAD parts on a table, one scene object per face, with imposed defects
    station_parts     the demo part with known defects, for the station
    bins              bins of thin parts (inspection.bins.part_file's tab part dropped; quick and fringe scans)
    clutter           cluttered labelled clouds (room corners) for region growing
    parts_demo        script writing config/parts/demo_part.step and .ply
"""
