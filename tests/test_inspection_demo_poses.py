"""Registration of the demo part placed as on the station's bench (lying flat, seen from
straight above, turned and shifted on the table, its high top bowed), through the full
simulated scanner chain, against the true pose (the refused station part in the default run,
the random placements in the acceptance run: pytest -m acceptance -s).

The station run of issue 7 refused one part (high top bowed 20 um, turned 0.09 rad,
shifted (2, 2) mm, noise seed 4): its best pose fitted 69 % of the scan against a 70 %
floor. The cause was a wrong pose, not a threshold: from straight above the scan is two
parallel planes and a thin outline, every coarse pose from the descriptors had the planes
right but the part turned by 32 deg and shifted by 13 mm about their normal (the tops
overlap, the outline does not), and verification had nothing near the truth to prefer.
The dominant-plane hypotheses (`registration.plane_poses`: the scan's main plane laid on
each large model plane, turned every 10 deg) and the fitness exploration about verified
poses (`registration.explore`) give verification the right pose; this test holds that case
and random placements to it.
"""

from __future__ import annotations

import numpy as np
import pytest

from inspection.cad import load_cad
from inspection.measured_cloud import from_organised, isolate_part
from inspection.registration import ModelTarget, pose_difference, register
from scanner.acquisition import AcquisitionSettings, acquire
from scanner.config import CONFIG_DIR
from scanner.decode import decode
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from scanner.rig import RigConfig, open_rig
from sim.station_parts import make_part

_rng = np.random.default_rng(7)
# (bow mm, turn rad, shift mm, noise seed): the refused station part, then random placements
PLACEMENTS = [(0.020, 0.09, (2.0, 2.0), 4)] + [
    pytest.param(float(_rng.choice([0.0, 0.02, 0.15])), float(_rng.uniform(-np.pi, np.pi)),
                 tuple(_rng.uniform(-4, 4, 2)), 100 + k, marks=pytest.mark.acceptance)
    for k in range(7)]


@pytest.fixture(scope="module")
def target() -> ModelTarget:
    return ModelTarget.from_cad(load_cad(CONFIG_DIR / "parts" / "demo_part.step"))


@pytest.mark.parametrize("bow, turn, shift, seed", PLACEMENTS)
def test_bench_placement_registers(target: ModelTarget, bow: float, turn: float, shift: tuple, seed: int) -> None:
    """Registered, not refused, within 0.15 deg and 0.1 mm of the true pose (a 150 um bow
    pulls the best fit of the nominal model by ~0.1 deg; a nominal part: < 0.02 / 0.02)."""
    part = make_part("placed", bow_mm=bow, turn_rad=turn, shift_mm=shift)
    config = RigConfig.load()
    patterns = PatternSet.load(config.patterns_path)
    with open_rig(config, scene=part.scene(), seed=seed) as rig:
        stack = acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda k, f: None)
        cloud = triangulate(decode(stack, patterns, rig.camera.bit_depth, rig.model.projector.size),
                            Triangulator(rig.model))
        pose = rig.extras["scene"].objects[0].pose
    scan = isolate_part(from_organised(cloud, "bench"), target.diagonal_mm)
    reg = register(scan, target)
    angle, dist = pose_difference(reg.transform, np.linalg.inv(pose), scan.points.mean(axis=0))
    print(f"bow {bow * 1e3:.0f} um, turn {np.degrees(turn):.1f} deg: fitness {reg.fitness:.3f}, error "
          f"{angle:.4f} deg {dist * 1e3:.1f} um, {reg.timings_s['total']:.1f} s")
    assert reg.fitness > 0.95 and not reg.ambiguous
    assert (angle < 0.02 and dist < 0.02) if bow == 0 else (angle < 0.15 and dist < 0.1)
