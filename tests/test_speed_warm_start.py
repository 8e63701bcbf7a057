"""Warm-started registration (inspection/registration/warm_start.py): the next part in the
same fixture is found from the previous part's pose, the same pose the global search
finds; a part put in turned fails the check and the global search runs. Truth: the
simulated views' exact poses (the views of test_inspection_registration.py)."""

from __future__ import annotations

import numpy as np
import pytest
from registration_support import STEP, virtual_view
from scipy.spatial.transform import Rotation

from inspection.cad import load_cad
from inspection.registration import ModelTarget, RegistrationSettings, pose_difference, register
from inspection.registration.warm_start import WARM_METHOD, register_from_prior, register_with_prior
from sim.parts import lying_pose


@pytest.fixture(scope="module")
def station():
    """The demo part, its target, and the first part's view and global registration."""
    model = load_cad(STEP)
    target = ModelTarget.from_cad(model)
    pose = lying_pose(model.tessellation.vertices, 0.35, 400.0, (0.2, 0.1))
    first = register(virtual_view(model, pose), target, RegistrationSettings(seed=0))
    return model, target, pose, first


def moved(pose: np.ndarray, degrees: float, shift_mm: tuple[float, float, float], about: np.ndarray) -> np.ndarray:
    """`pose` turned by `degrees` about the camera's z axis through `about` and shifted."""
    M = np.eye(4)
    M[:3, :3] = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    M[:3, 3] = about - M[:3, :3] @ about + np.asarray(shift_mm)
    return M @ pose


def test_next_part_in_the_fixture_is_found_from_the_prior(station) -> None:
    model, target, pose, first = station
    centre = pose[:3, 3]
    nxt = moved(pose, 1.5, (0.8, -0.5, 0.3), centre)  # re-seated: a little off the first part
    view = virtual_view(model, nxt, seed=1)
    warm = register_from_prior(view, target, first, RegistrationSettings(seed=0))
    assert warm is not None and warm.method == WARM_METHOD
    angle, shift = pose_difference(warm.transform, np.linalg.inv(nxt), view.points.mean(axis=0))
    assert angle < 0.02 and shift < 0.02, (angle, shift)
    cold = register(view, target, RegistrationSettings(seed=0))
    angle, shift = pose_difference(warm.transform, cold.transform, view.points.mean(axis=0))
    assert angle < 0.02 and shift < 0.02, (angle, shift)
    assert "coarse" not in warm.timings_s  # no global search ran


def test_part_put_in_turned_falls_back_to_the_global_search(station) -> None:
    model, target, pose, first = station
    turned = moved(pose, 90.0, (0.0, 0.0, 0.0), pose[:3, 3])
    view = virtual_view(model, turned, seed=2)
    assert register_from_prior(view, target, first, RegistrationSettings(seed=0)) is None
    reg = register_with_prior(view, target, first, RegistrationSettings(seed=0))
    assert reg.method != WARM_METHOD and "warm_start" in reg.timings_s
    angle, shift = pose_difference(reg.transform, np.linalg.inv(turned), view.points.mean(axis=0))
    assert angle < 0.02 and shift < 0.02, (angle, shift)
