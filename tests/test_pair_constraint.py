"""The overlap's constraint on a pose (inspection/views/constraint.py) against closed forms:
a plane leaves three motions free, a cylinder two, a boss standing on a plate one (the turn
about the boss's axis, named with its axis), a box corner none."""

from __future__ import annotations

import numpy as np

from inspection.views.constraint import overlap_constraint
from scanner.stage_model import rotation_about


def grid(n: int) -> np.ndarray:
    """n values symmetric about 0 in [-1, 1]."""
    return np.linspace(-1.0, 1.0, n)


def test_plane_leaves_both_shifts_and_the_turn_about_its_normal_free() -> None:
    x, y = np.meshgrid(grid(21), grid(21))
    p = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]) * 30.0
    c = overlap_constraint(p, np.tile([0.0, 0.0, 1.0], (len(p), 1)))
    # scaled by L^2 = E[x^2 + y^2]: the tilts give E[x'^2] = E[y'^2] = 1/2, the shift along z 1
    np.testing.assert_allclose(c.eigenvalues, [0, 0, 0, 0.5, 0.5, 1.0], atol=1e-12)
    free = c.motions[:, :3]  # spans the turn about z and the shifts along x and y
    for motion in ([0, 0, 1, 0, 0, 0], [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0]):
        assert np.linalg.norm(free.T @ motion) > 1 - 1e-9
    assert c.weakest == 0.0


def test_cylinder_leaves_the_turn_about_and_the_shift_along_its_axis_free() -> None:
    r, h = 8.0, 10.0
    t, z = np.meshgrid(np.linspace(0, 2 * np.pi, 72, endpoint=False), grid(11) * h)
    n = np.column_stack([np.cos(t.ravel()), np.sin(t.ravel()), np.zeros(t.size)])
    p = r * n + np.outer(z.ravel(), [0, 0, 1])
    c = overlap_constraint(p, n)
    z2 = np.mean(z ** 2) / (r ** 2 + np.mean(z ** 2))  # E[z'^2]: z over L
    np.testing.assert_allclose(c.eigenvalues, np.sort([0, 0, 0.5, 0.5, z2 / 2, z2 / 2]), atol=1e-12)
    for motion in ([0, 0, 1, 0, 0, 0], [0, 0, 0, 0, 0, 1]):
        assert np.linalg.norm(c.motions[:, :2].T @ motion) > 1 - 1e-9


def test_boss_on_a_plate_leaves_only_the_turn_about_the_boss_axis_and_names_it() -> None:
    """A boss of radius 6 at (10, -5) standing on a ring of its plate, the whole turned and
    moved: one free motion, the turn about the boss's axis, described with that axis."""
    axis_at = np.array([10.0, -5.0])
    t, z = np.meshgrid(np.linspace(0, 2 * np.pi, 90, endpoint=False), np.linspace(0.5, 12.0, 12))
    radial = np.column_stack([np.cos(t.ravel()), np.sin(t.ravel()), np.zeros(t.size)])
    boss = np.column_stack([axis_at + 6.0 * radial[:, :2], z.ravel()])
    ring_t, ring_r = np.meshgrid(np.linspace(0, 2 * np.pi, 90, endpoint=False), np.linspace(7.0, 20.0, 8))
    ring = np.column_stack([axis_at + ring_r.ravel()[:, None] * np.column_stack([np.cos(ring_t.ravel()),
                                                                                 np.sin(ring_t.ravel())]),
                            np.zeros(ring_t.size)])
    p = np.vstack([boss, ring])
    n = np.vstack([radial, np.tile([0.0, 0.0, 1.0], (len(ring), 1))])
    R = rotation_about(np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0), 0.7)
    move = np.array([40.0, -15.0, 300.0])
    c = overlap_constraint(p @ R.T + move, n @ R.T)
    assert c.eigenvalues[0] < 1e-12 and c.eigenvalues[1] > 0.01
    a, b = c.motions[:3, 0], c.motions[3:, 0]
    assert abs(abs(a @ R[:, 2]) - np.linalg.norm(a)) < 1e-9 and np.linalg.norm(a) > np.linalg.norm(b)
    point = c.centre + c.length_mm * np.cross(a, b) / (a @ a)
    on_axis = R @ np.array([*axis_at, 0.0]) + move  # the screw axis is the boss's axis
    off = point - on_axis
    assert np.linalg.norm(off - (off @ R[:, 2]) * R[:, 2]) < 1e-6
    assert c.describe().startswith("rotation about the axis along")


def test_box_corner_fixes_every_motion_whatever_the_frame() -> None:
    u, v = np.meshgrid(np.linspace(0, 20, 15), np.linspace(0, 20, 15))
    u, v, o = u.ravel(), v.ravel(), np.zeros(u.size)
    p = np.vstack([np.column_stack([o, u, v]), np.column_stack([u, o, v]), np.column_stack([u, v, o])])
    n = np.repeat(np.eye(3), u.size, axis=0)
    c = overlap_constraint(p, n)
    assert c.weakest > 0.05
    R = rotation_about(np.array([0.0, 0.6, 0.8]), 1.1)
    moved = overlap_constraint(p @ R.T + [5.0, 7.0, 400.0], n @ R.T)
    np.testing.assert_allclose(moved.eigenvalues, c.eigenvalues, atol=1e-12)
