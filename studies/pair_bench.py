"""View pairs drawn at random on the simulated turntable, registered by
`inspection.views.pair_registration` and by Open3D's FPFH + RANSAC + ICP beside it (issue 26).

    python -m studies.pair_bench --out DIR [--placements 20] [--seed S] [--parts demo,ctc01,ftc06,random] [--only K]

A placement is a part standing on the platter of `config/rigs/sim_turntable.toml`: the demo
part, a NIST part of ../shared/data/step (scaled to the platter, as `slscan bench views
--part`), or a random prismatic part (`sim.random_parts`, scaled so that its diagonal is
60-140 mm: the platter is 160 mm), turned at random about the axis and shifted up to 10 mm
across it; three views at random stage angles, scanned through the whole fringe chain, give
three pairs. The truth is the simulator's stage pose of each view. A pair's true overlap is
the share of the source's part points lying within `OVERLAP_MM` of a target part point at
the true pose (part points: more than 0.05 mm above the platter's true plane).

Per pair: ours (proven or refused, the error of the pose against the truth at the source's
centre, why refused), Open3D's (its error: it always returns a pose), the true overlap, the
seeds; one JSON line each in DIR/pairs.jsonl, a summary at the end (success within
`SUCCESS_DEG` / `SUCCESS_MM`, wrong poses proven, proven poses farther from the truth than
their own stated spread, refusals, by overlap) with the load average. Every seed is
printed; a run draws new ones unless --seed is given. `--only K` (with --seed) reproduces
placement K of a run alone: the draws of the placements before it are made and discarded,
so K gets the same part, noise, placement and angles.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from scanner.config import CONFIG_DIR

TURNTABLE = CONFIG_DIR / "rigs" / "sim_turntable.toml"
STEP_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "step"
NIST = {"ctc01": ("nist_ctc_01_asme1_rd.stp", 0.12, (0.0, 0.0, 1.0)),  # as `slscan bench views --part`
        "ftc06": ("nist_ftc_06_asme1_rd.stp", 0.3, (0.0, 1.0, 0.0))}
SUCCESS_DEG, SUCCESS_MM = 0.3, 0.5  # the success for a view pair
OVERLAP_MM = 0.3  # a source point is in the overlap when a target point lies this near it at the true pose
ABOVE_PLATTER_MM = 0.05  # part points: this far above the platter's true plane


@dataclass(frozen=True)
class Part:
    """A part's tessellation (mm), its resting direction and a name."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    face: np.ndarray
    up: tuple[float, float, float]


def load_part(name: str, seed: int, out: Path) -> Part:
    """`demo`, `ctc01`, `ftc06`, or `random` (a `sim.random_parts` part of `seed`)."""
    from inspection.cad import load_cad

    if name == "demo":
        model = load_cad(CONFIG_DIR / "parts" / "demo_part.step", deflection_mm=0.01)
        up = (0.0, 0.0, 1.0)
    elif name in NIST:
        file, scale, up = NIST[name]
        model = load_cad(STEP_DIR / file, scale=scale, deflection_mm=0.01)
    else:
        from sim.random_parts import random_part

        part = random_part(seed)
        diagonal = float(np.random.default_rng(seed).uniform(60.0, 140.0))
        step = part.write(out / f"random_{seed}.step")
        model = load_cad(step, scale=diagonal / part.diagonal_mm, deflection_mm=0.01)
        up, name = (0.0, 0.0, 1.0), f"random:{seed}"
    t = model.tessellation
    return Part(name, t.vertices, t.triangles, t.face, up)


def turntable_config(out: Path, width: int, height: int) -> Any:
    from scanner.rig import RigConfig

    text = TURNTABLE.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    text = text.replace("width = 1280", f"width = {width}").replace("height = 1024", f"height = {height}")
    text = text.replace("speed_deg_s = 90.0", "speed_deg_s = 3600.0").replace("settle_s = 0.2", "settle_s = 0.0")
    path = out / "turntable.toml"
    path.write_text(text)
    return RigConfig.load(path)


@dataclass(frozen=True)
class Draw:
    """One placement's draws from the master generator, in the order they are made: the
    part's and the noise's seeds, the turn about the resting direction (rad), the shift
    across it (mm, three draws) and the three stage angles (deg)."""

    part_seed: int
    noise_seed: int
    turn_rad: float
    shift_mm: np.ndarray
    angles_deg: tuple[float, ...]


def draw_placement(rng: np.random.Generator) -> Draw:
    """The next placement's draws (`Draw`): the same draws whether it is scanned or skipped."""
    part_seed, noise_seed = (int(x) for x in rng.integers(0, 2 ** 31, 2))
    turn = float(rng.uniform(0.0, 2 * np.pi))
    shift = rng.uniform(-10.0, 10.0, 3)
    angles = tuple(sorted(float(a) for a in rng.uniform(0.0, 360.0, 3)))
    return Draw(part_seed, noise_seed, turn, shift, angles)


def scan_placement(config: Any, part: Part, draw: Draw, out: Path) -> Path:
    """Three views of `part` at the placement and stage angles of `draw` (a multi-view
    session in `out`)."""
    from scanner.multiview import capture_views, plan_views
    from scanner.native_threads import native_threads
    from scanner.patterns import PatternSet
    from scanner.pipeline import scan
    from scanner.rig import open_rig
    from scanner.stage_model import rotation_about
    from sim.stage_bench import part_on_stage

    placement = np.eye(4)
    placement[:3, :3] = rotation_about(np.asarray(part.up, float) / np.linalg.norm(part.up), draw.turn_rad)
    placement[:3, 3] = draw.shift_mm * (1.0 - np.abs(np.asarray(part.up, float)))
    scene = part_on_stage(part.vertices, part.triangles, part.face, part.up, config.stage.nominal, placement=placement)
    plan = plan_views(config.stage, angles_deg=list(draw.angles_deg))
    patterns = PatternSet.load(config.patterns_path)
    with native_threads(1), open_rig(config, scene=scene, seed=draw.noise_seed) as rig:
        capture_views(rig, plan, out, lambda folder, place: scan(rig, patterns, folder, level="none",
                                                                   view=place).session)
    return out


def view_truth(view: Path) -> np.ndarray:
    """part_from_cam of a view: the simulator's stage pose (the rig's world frame is the
    camera's: `sim_turntable.toml` has no world_from_cam)."""
    return np.linalg.inv(np.array(json.loads((view / "ground_truth_stage.json").read_text())["world_from_stage"]))


def true_overlap(source: Any, target: Any, truth: np.ndarray, part_from: tuple[np.ndarray, np.ndarray],
                 axis: Any) -> float:
    """The share of the source's part points within OVERLAP_MM of a target part point at the
    true pose `truth` (source -> target)."""
    from scipy.spatial import cKDTree

    def part(points: np.ndarray, T: np.ndarray) -> np.ndarray:
        h = (points @ T[:3, :3].T + T[:3, 3] - axis.point_mm) @ axis.direction
        return points[h > ABOVE_PLATTER_MM]

    s, t = part(source.points, part_from[0]), part(target.points, part_from[1])
    d, _ = cKDTree(t).query(s @ truth[:3, :3].T + truth[:3, 3], distance_upper_bound=OVERLAP_MM, workers=-1)
    return float(np.isfinite(d).mean())


def open3d_pair(source: Any, target: Any, seed: int) -> np.ndarray:
    """Open3D's own pipeline, one start: FPFH on both clouds on a voxel grid (diagonal / 150),
    RANSAC on feature matches (mutual filter), then point-to-plane ICP on clouds four times
    denser."""
    import open3d as o3d

    from inspection.views.quiet import stdout_to_stderr

    reg = o3d.pipelines.registration
    voxel = float(np.linalg.norm(np.ptp(target.points, axis=0))) / 150.0

    def cloud(s: Any, v: float) -> Any:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(s.points))
        pc.normals = o3d.utility.Vector3dVector(s.normals)
        return pc.voxel_down_sample(v)

    with stdout_to_stderr():
        src, dst = cloud(source, voxel), cloud(target, voxel)
        param = o3d.geometry.KDTreeSearchParamHybrid(5 * voxel, 100)
        fs, fd = reg.compute_fpfh_feature(src, param), reg.compute_fpfh_feature(dst, param)
        o3d.utility.random.seed(seed)
        ransac = reg.registration_ransac_based_on_feature_matching(
            src, dst, fs, fd, True, 1.5 * voxel, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
            reg.RANSACConvergenceCriteria(100000, 0.999))
        icp = reg.registration_icp(cloud(source, voxel / 4), cloud(target, voxel / 4), voxel, ransac.transformation,
                                   reg.TransformationEstimationPointToPlane())
    return np.asarray(icp.transformation)


def measure_pair(session: Path, i: int, j: int, seed: int, axis: Any) -> dict[str, Any]:
    """Ours and Open3D's on views i -> j of a multi-view session, against the truth."""
    from inspection.measured_cloud import load_source
    from inspection.registration import RegistrationSettings
    from inspection.views.align import pose_error
    from inspection.views.pair_registration import support_mask, weigh_view_pair

    views = sorted(p for p in session.iterdir() if p.name.startswith("view_"))
    S, V = load_source(views[i]), load_source(views[j])
    P = view_truth(views[i]), view_truth(views[j])
    truth = np.linalg.inv(P[1]) @ P[0]
    centre = S.points[support_mask(S, seed)].mean(axis=0)
    t0 = time.perf_counter()
    ours = weigh_view_pair(S, V, settings=RegistrationSettings(seed=seed), isolate=True)
    ours_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    theirs = open3d_pair(S.subset(support_mask(S, seed)), V.subset(support_mask(V, seed)), seed)
    theirs_s = time.perf_counter() - t0
    deg, mm = pose_error(truth, ours.transform, centre)
    tdeg, tmm = pose_error(truth, theirs, centre)
    return {"pair": [i, j], "true_overlap": true_overlap(S, V, truth, P, axis), "model_overlap": ours.overlap,
            "ours": {"proven": ours.proven, "deg": deg, "mm": mm, "refusals": list(ours.refusals),
                     "fitness": ours.fitness, "comparable": ours.comparable, "sigma_mm": ours.sigma_mm,
                     "spread": list(ours.spread), "weakest_sd": list(ours.weakest_sd),
                     "alternatives": len(ours.alternatives), "seconds": ours_s,
                     "timings_s": ours.timings_s},
            "open3d": {"deg": tdeg, "mm": tmm, "seconds": theirs_s}}


def summary(rows: list[dict[str, Any]]) -> str:
    def ok(deg: float, mm: float) -> bool:
        return deg <= SUCCESS_DEG and mm <= SUCCESS_MM

    lines = []
    for name, lo, hi in (("overlap >= 30 %", 0.3, 1.01), ("overlap 20-30 %", 0.2, 0.3), ("overlap < 20 %", 0.0, 0.2)):
        sel = [r for r in rows if lo <= r["true_overlap"] < hi]
        if not sel:
            continue
        proven = [r for r in sel if r["ours"]["proven"]]
        good = sum(ok(r["ours"]["deg"], r["ours"]["mm"]) for r in proven)
        o3d_good = sum(ok(r["open3d"]["deg"], r["open3d"]["mm"]) for r in sel)
        errs = np.array([[r["ours"]["deg"], r["ours"]["mm"]] for r in proven if ok(r["ours"]["deg"], r["ours"]["mm"])])
        tight = f"; proven errors median {np.median(errs[:, 0]):.4f} deg / {np.median(errs[:, 1]):.4f} mm, max " \
                f"{errs[:, 0].max():.4f} / {errs[:, 1].max():.4f}" if len(errs) else ""
        beyond = sum(r["ours"]["deg"] > r["ours"]["spread"][0] or r["ours"]["mm"] > r["ours"]["spread"][1]
                     for r in proven)
        lines.append(f"{name}: {len(sel)} pairs; ours {good} within {SUCCESS_DEG} deg / {SUCCESS_MM} mm "
                     f"({good / len(sel):.0%}), wrong with a proof {len(proven) - good}, proven beyond their own "
                     f"spread {beyond}, refused {len(sel) - len(proven)}{tight}; Open3D {o3d_good} within "
                     f"({o3d_good / len(sel):.0%}), {len(sel) - o3d_good} wrong")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m studies.pair_bench", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--placements", type=int, default=20)
    p.add_argument("--seed", type=int, help="master seed (default: drawn, and printed)")
    p.add_argument("--parts", default="demo,ctc01,ftc06,random")
    p.add_argument("--only", type=int, metavar="K",
                   help="scan and measure placement K alone (0-based; the draws of those before it are replayed)")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=1024)
    args = p.parse_args(argv)
    master = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2 ** 31)
    print(f"master seed {master}", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    config = turntable_config(args.out, args.width, args.height)
    axis = config.stage.nominal.axes[0]
    rng = np.random.default_rng(master)
    names = args.parts.split(",")
    rows: list[dict[str, Any]] = []
    with open(args.out / "pairs.jsonl", "a") as log:
        for k in range(args.placements if args.only is None else args.only + 1):
            draw = draw_placement(rng)
            if args.only is not None and k != args.only:
                continue
            name = names[k % len(names)]
            part_seed, noise_seed = draw.part_seed, draw.noise_seed
            print(f"placement {k}: {name}, part seed {part_seed}, noise seed {noise_seed}", flush=True)
            part = load_part(name, part_seed, args.out)
            session = scan_placement(config, part, draw, args.out / f"placement_{k:03d}")
            for i, j in ((0, 1), (1, 2), (0, 2)):
                row = {"placement": k, "part": part.name, "part_seed": part_seed, "noise_seed": noise_seed,
                       "master_seed": master, "load_average": os.getloadavg()[0]}
                try:
                    row.update(measure_pair(session, i, j, part_seed % 10_000, axis))
                except Exception as error:  # a crash is a figure too: recorded, counted, and the run goes on
                    row["error"] = f"{type(error).__name__}: {error}"
                    print(f"{k:3d} {part.name:>14} {i}->{j} ERROR {row['error']}", flush=True)
                    log.write(json.dumps(row) + "\n")
                    continue
                rows.append(row)
                log.write(json.dumps(row) + "\n")
                log.flush()
                o = row["ours"]
                print(f"{k:3d} {part.name:>14} {i}->{j} overlap {row['true_overlap']:.2f} (model "
                      f"{row['model_overlap']:.2f}): ours {'proven' if o['proven'] else 'refused'} "
                      f"{o['deg']:.3f} deg / {o['mm']:.3f} mm {o['seconds']:.0f} s; Open3D {row['open3d']['deg']:.3f} "
                      f"deg / {row['open3d']['mm']:.3f} mm" + ("" if o["proven"] else f"; {o['refusals']}"), flush=True)
    print(summary(rows))
    print(f"master seed {master}; load average {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
