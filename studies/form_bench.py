"""Speed of the cylinder form figures (issue 29): `inspection.form.cylinder_ls` and
`cylindricity_mz` on fixed random cylinders, timed beside a peer measured in the same run
(numpy's lstsq plane fit of the same points, z = a x + b y + c), so that the ratio to the
peer can be compared between machines and loads.

    python -m studies.form_bench [--points 35000] [--repeats 7] [--seed 29]

Each input: a boss-like cylinder (radius 12 mm, 21.5 mm long, a 3-lobe 20 um form, a
2 um/mm taper and 14 um of noise, about the inspection's grid of the demo part's boss),
on an axis tilted 0.2 rad and off the origin, fitted from the nominal axis as the form
stage does. Prints per function the median over the repeats of the wall and CPU seconds
and the ratio of its median CPU to the peer's, with the load average before and after.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable

import numpy as np

from inspection.form import cylinder_ls, cylindricity_mz
from slscan.bench_timing import median_times


def boss(points: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (N, 3), nominal axis point, nominal axis direction) of one random boss."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.0, 2.0 * np.pi, points)
    z = rng.uniform(0.0, 21.5, points)
    r = 12.0 + 0.01 * np.cos(3.0 * t) + 0.002 * z + rng.normal(0.0, 0.014, points)
    a = 0.2
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    origin = np.array([20.0, -5.0, 3.0])
    p = np.stack([r * np.cos(t), r * np.sin(t), z], axis=1) @ tilt.T + origin
    return p, origin + 0.05, tilt[:, 2] + 0.01  # the nominal axis a little off the true one


def plane_peer(p: np.ndarray) -> None:
    """The peer: one least-squares plane through the same points."""
    np.linalg.lstsq(np.column_stack([p[:, 0], p[:, 1], np.ones(len(p))]), p[:, 2], rcond=None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=35000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--seed", type=int, default=29)
    args = ap.parse_args()
    p, o, n = boss(args.points, args.seed)
    load = os.getloadavg()
    cases: dict[str, Callable[[], object]] = {
        "plane lstsq (peer)": lambda: plane_peer(p),
        "cylinder_ls": lambda: cylinder_ls(p, o, n),
        "cylindricity_mz": lambda: cylindricity_mz(p, o, n),
    }
    times = {name: median_times(fn, args.repeats) for name, fn in cases.items()}
    peer = times["plane lstsq (peer)"][1]
    print(f"{args.points} points, seed {args.seed}, median of {args.repeats}; load average {load} before, "
          f"{os.getloadavg()} after")
    print(f"{'':20s} {'wall ms':>9s} {'CPU ms':>9s} {'CPU / peer':>10s}")
    for name, (wall, cpu) in times.items():
        print(f"{name:20s} {wall * 1e3:9.2f} {cpu * 1e3:9.2f} {cpu / peer:10.1f}")
    print(f"cylindricity_mz {cylindricity_mz(p, o, n):.12f} mm")


if __name__ == "__main__":
    main()
