"""Part isolation on an organised scan (`measured_cloud.part_mask`): a part of two blocks at
two heights on a table, the step's wall in its own shadow (a line of pixels without a point)
running on across the table to the image's border, as the demo part's raised block does at
some placements. Every point of both blocks is the part and no table point is, with the
pixels known and without them (but the blocks' outer corner pixels, mostly table about them,
which the table's removal takes with it); the truth is the scene's own construction."""

from __future__ import annotations

import numpy as np

from inspection.measured_cloud import ScanCloud, part_mask

H, W, PITCH_MM = 120, 160, 0.5


def _scene() -> tuple[ScanCloud, list[np.ndarray], float]:
    rng = np.random.default_rng(3)
    row, col = np.mgrid[0:H, 0:W]
    z = np.full((H, W), 500.0)  # the table, seen from the camera at the origin
    left = (row >= 40) & (row < 80) & (col >= 40) & (col < 80)
    right = (row >= 40) & (row < 80) & (col > 80) & (col < 110)
    z[left], z[right] = 480.0, 470.0
    valid = np.ones((H, W), bool)
    valid[:80, 80] = False  # the step's wall in shadow, and its shadow on across the table to the border
    part = left | right
    keep = valid.ravel()
    points = np.stack([(col - W / 2) * PITCH_MM, (row - H / 2) * PITCH_MM, z + rng.normal(0, 0.01, z.shape)],
                      axis=2).reshape(-1, 3)[keep]
    normals = np.tile([0.0, 0.0, -1.0], (int(keep.sum()), 1))
    pixels = np.stack([col.ravel(), row.ravel()], axis=1)[keep]
    scan = ScanCloud(points, normals, "two blocks", np.zeros(3), pixels, (H, W))
    extent = np.ptp(points[part.ravel()[keep]], axis=0) + [0.0, 0.0, 20.0]  # the blocks down to the table
    return scan, [left.ravel()[keep], right.ravel()[keep]], float(np.linalg.norm(extent))


def test_a_step_in_its_own_shadow_does_not_cut_the_part() -> None:
    scan, blocks, diagonal = _scene()
    organised = part_mask(scan, diagonal)
    bare = part_mask(ScanCloud(scan.points, scan.normals, scan.source, scan.viewpoint), diagonal)
    for mask in (organised, bare):
        assert not (mask & ~(blocks[0] | blocks[1])).any()
        for block in blocks:
            assert mask[block].sum() >= block.sum() - 4
