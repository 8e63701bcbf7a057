"""The decode's fault battery (docs/consistency.md), run on purpose:

    python -m tests.decode_battery [--clean 220] [--faults 3] [--outside 20] [--seed S] [--width 640]

On the simulated bench (config/rigs/sim_bench.toml) and turntable (sim_turntable.toml) rigs,
scenes drawn at random (the demo part at a random place and turn on a tilted plane; on the
turntable, turned about its axis), with the heterodyne or the Gray-code set, are scanned at
reduced camera resolution (the checks' statistics are medians, scales, shares and a Poisson
bound: resolution-independent). Each clean session is decoded (a refusal is a false refusal),
then faults drawn at random are made from it by permuting or replacing its frames, or editing
its manifest, as a faulty capture or a careless edit would, and decoded through the same path
(`scanner.pipeline.process`). A fault's outcome is "refused" (with the right reason when the
check that leads the refusal is one the fault can break: `RIGHT`; "by physics" when a check
of the frames or the rig fails, not only a checksum of the manifest), or exit 0, then "wrong"
when its cloud differs from the clean decode's beyond noise (median |Δz| > 3 x the clean
scan's noise or 1 % of the points off by more than 1 mm), else "harmless". Scenes outside the
measuring volume are rendered as such. Seeds are drawn fresh unless --seed is given, and printed.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import suppress
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from scanner.config import CONFIG_DIR
from scanner.decode_checks import LEAD, ConsistencyError
from scanner.errors import ScannerError
from scanner.patterns import PatternSet
from scanner.pipeline import ScanResult, process, scan
from scanner.rig import RigConfig, open_rig
from scanner.session import MANIFEST, Session

RIGS = {"bench": CONFIG_DIR / "rigs" / "sim_bench.toml", "turntable": CONFIG_DIR / "rigs" / "sim_turntable.toml"}
PATTERNS = {  # the sets drawn: the rigs' default, a Gray-code set, and both fringe orientations (epipolar)
    "heterodyne": lambda: PatternSet.load(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml"),
    "graycode": lambda: PatternSet.load(CONFIG_DIR / "patterns" / "graycode_4.toml"),
    "heterodyne_both": lambda: PatternSet("heterodyne", 4, (70.0, 64.0, 59.0), ("vertical", "horizontal")),
}
PHASE_CHECKS = {"phase_residual", "frequency_agreement", "frequency_offset", "gray_offset", "gray_edges", "direction",
                "fringe_orders", "ordering"}
TIES = {"rig_model", "pattern_set"}  # the checksums of what the manifest recorded at capture
RIGHT = {  # the checks whose refusal names a right reason for each fault
    "steps_reversed": {"direction", "frequency_offset", "gray_offset", "gray_edges"},
    "steps_rotated": {"frequency_offset", "gray_offset", "gray_edges", "fringe_orders"},
    "phase_frames_swapped": PHASE_CHECKS,
    "gray_frames_swapped": {"ordering", "projector_range", "gray_edges", "fringe_orders"},
    "frame_from_another_scan": PHASE_CHECKS | {"projector_range"},
    "wrong_period_count": PHASE_CHECKS | {"projector_range", "pattern_set"},
    "wrong_projector_size": {"rig_model"},
    "rig_model_perturbed": {"rig_model"},
    "scene_outside_volume": {"measurement_volume"},
}


@dataclass
class Outcome:
    fault: str
    rig: str
    patterns: str
    detail: str
    refused: bool
    lead: str | None
    wrong: bool
    seed: int
    physics: bool = False  # refused by a check of the frames or the rig, not only by a recorded checksum

    @property
    def right(self) -> bool:
        return self.refused and self.lead in RIGHT[self.fault]


def rig_config(name: str, width: int) -> RigConfig:
    """The rig at a camera `width` (height in proportion), same field of view."""
    cfg = RigConfig.load(RIGS[name])
    camera = {**cfg.raw["camera"], "width": width, "height": width * cfg.camera.height // cfg.camera.width}
    return RigConfig.from_toml({**cfg.raw, "camera": camera}, cfg.path)


def random_scene(rig: str, rng: np.random.Generator, outside: bool = False):  # -> sim.scene.Scene
    """The demo part on a tilted plane at a random place and turn (bench), or the turntable
    scene turned about its axis; `outside`: the whole scene moved beyond the volume."""
    from scipy.spatial.transform import Rotation

    from sim.scene import Scene, SceneObject, load_mesh

    shift = np.eye(4)
    if outside:
        shift[2, 3] = rng.uniform(100.0, 140.0) * rng.choice([-1.0, 1.0]) if rig == "bench" else \
            rng.uniform(100.0, 140.0)
    if rig == "turntable":
        scene = Scene.load(CONFIG_DIR / "scenes" / "turntable_demo.toml")
        axis = np.array([0.0, -0.766044443118978, -0.6427876096865394])
        point = np.array([0.0, 11.49066664678467, 409.6418141452981])
        turn = np.eye(4)
        turn[:3, :3] = Rotation.from_rotvec(axis * rng.uniform(0, 2 * np.pi)).as_matrix()
        turn[:3, 3] = point - turn[:3, :3] @ point
        objects = tuple(replace(o, pose=shift @ turn @ o.pose, albedo=float(rng.uniform(0.4, 0.9)))
                        for o in scene.objects)
        return Scene(objects, None, f"turntable-{rng.integers(1e9)}")
    distance = rng.uniform(405.0, 435.0)
    tilt = Rotation.from_euler("xy", rng.uniform(-0.15, 0.15, 2)).as_matrix()
    plane_pose = np.eye(4)
    plane_pose[:3, :3] = tilt
    plane_pose[:3, 3] = [0.0, 0.0, distance]
    plane = SceneObject("reference_plane", "plane", shift @ plane_pose, float(rng.uniform(0.5, 0.9)),
                        size_mm=(1000.0, 1000.0))
    mesh = CONFIG_DIR / "parts" / "demo_part.ply"
    vertices, triangles = load_mesh(mesh, mesh, None)
    part_pose = np.eye(4)
    part_pose[:3, :3] = tilt @ Rotation.from_euler("zx", [rng.uniform(0, 2 * np.pi), np.pi]).as_matrix()
    part_pose[:3, 3] = plane_pose[:3, :3] @ [*rng.uniform(-25.0, 25.0, 2), 0.0] + plane_pose[:3, 3]
    part = SceneObject("demo_part", "mesh", shift @ part_pose, float(rng.uniform(0.4, 0.9)), vertices=vertices,
                       triangles=triangles, source=mesh)
    return Scene((part,), plane, f"bench-{rng.integers(1e9)}")


def capture(rig: str, patterns: str, width: int, seed: int, out: Path, outside: bool = False) -> Path:
    rng = np.random.default_rng(seed)
    with (open_rig(rig_config(rig, width), scene=random_scene(rig, rng, outside), seed=seed) as r,
          suppress(ConsistencyError)):  # a refusal is judged by `judge` below; the session is complete
        scan(r, PATTERNS[patterns](), out, level="none")
    return out


def judge(folder: Path, **kwargs: object) -> tuple[ScanResult | None, list[str]]:
    """(the result, or None when refused; the failed checks, the lead first)."""
    try:
        return process(Session.open(folder), **kwargs), []  # type: ignore[arg-type]
    except ConsistencyError as exc:
        failed = sorted((c.name for c in exc.checks if c.passed is False),
                        key=lambda n: LEAD.index(n) if n in LEAD else len(LEAD))
        return None, failed
    except ScannerError as exc:  # refused before the checks (an unreadable manifest, no points)
        return None, [f"other: {str(exc)[-120:]}"]


def copy_session(src: Path, dst: Path) -> dict:
    """A copy of a session's frames (hard links) and manifest, for a fault to edit."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("outputs", "recording.rrd"), copy_function=os.link)
    (dst / MANIFEST).unlink()
    return json.loads((src / MANIFEST).read_text())


def groups(manifest: dict) -> tuple[list[list[int]], list[int]]:
    """The phase frames' step groups (frame indices) and the Gray frames, in capture order."""
    ps = PatternSet.from_dict(manifest["patterns"])
    specs = ps.frames()
    phase: dict[tuple[str, int], list[int]] = defaultdict(list)
    for k, s in enumerate(specs):
        if s.kind == "phase":
            phase[(s.orientation, s.level)].append(k)
    return list(phase.values()), [k for k, s in enumerate(specs) if s.kind in ("gray", "gray_inverse")]


def permute(manifest: dict, order: list[int]) -> None:
    """Frame k of the session becomes the frame recorded at order[k] (file and checksum)."""
    frames = manifest["frames"]
    manifest["frames"] = [dict(frames[j], k=k) for k, j in enumerate(order)]


def make_fault(fault: str, src: Path, dst: Path, rng: np.random.Generator, other: Path | None) -> str:
    """Write session `dst`: `src` with `fault`; returns what exactly was done."""
    m = copy_session(src, dst)
    n = len(m["frames"])
    order = list(range(n))
    phase, gray = groups(m)
    detail = ""
    if fault == "steps_reversed":
        for g in phase:
            for a, b in zip(g, g[::-1]):
                order[a] = b
    elif fault == "steps_rotated":
        k = int(rng.integers(1, len(phase[0])))
        for g in phase:
            for i, a in enumerate(g):
                order[a] = g[(i + k) % len(g)]
        detail = f"by {k}"
    elif fault in ("phase_frames_swapped", "gray_frames_swapped"):
        pool = [k for g in phase for k in g] if fault == "phase_frames_swapped" else gray
        a, b = rng.choice(pool, 2, replace=False)
        order[a], order[b] = order[b], order[a]
        detail = f"{a}<->{b}"
    elif fault == "frame_from_another_scan":
        k = int(rng.integers(n))
        entry = json.loads((other / MANIFEST).read_text())["frames"][k]
        name = f"frames/foreign_{k:03d}.png"
        os.link(other / entry["file"], dst / name)
        m["frames"][k] = dict(entry, file=name)
        detail = f"frame {k}"
    elif fault == "wrong_period_count":
        f = m["patterns"]["fringes"]
        if m["patterns"]["family"] == "heterodyne":  # the same differences: still a heterodyne set, same frames
            d = int(rng.choice([-3, -2, -1, 1, 2, 3]))
            m["patterns"]["fringes"] = [x + d for x in f]
        else:  # the same number of Gray bits, so the same frame count
            bits = int(np.ceil(np.log2(f[0])))
            choices = [c for c in range(2 ** (bits - 1) + 1, 2 ** bits + 1) if c != f[0]]
            m["patterns"]["fringes"] = [float(rng.choice(choices))]
        detail = f"{f} -> {m['patterns']['fringes']}"
    elif fault == "wrong_projector_size":
        scale = float(rng.choice([-1, 1]) * rng.uniform(0.01, 0.1))
        p = m["rig_model"]["projector"]
        p["width"] = round(p["width"] * (1 + scale))
        p["height"] = round(p["height"] * (1 + scale))
        detail = f"{scale:+.1%}"
    elif fault == "rig_model_perturbed":
        detail = perturb(m["rig_model"], rng)
    permute(m, order)
    (dst / MANIFEST).write_text(json.dumps(m))
    return detail


def perturb(model: dict, rng: np.random.Generator) -> str:
    """One of: focal length ±0.5 %, principal point ±5 px, the extrinsic rotation ±0.2°."""
    from scipy.spatial.transform import Rotation

    kind = rng.choice(["focal", "principal", "extrinsic"])
    device = model[str(rng.choice(["camera", "projector"]))]
    K = np.array(device["K"], float)
    if kind == "focal":
        s = 1 + float(rng.choice([-1, 1])) * 0.005
        K[0, 0] *= s
        K[1, 1] *= s
        what = f"focal x{s}"
    elif kind == "principal":
        d = rng.choice([-1, 1], 2) * 5.0
        K[:2, 2] += d
        what = f"principal point {d} px"
    else:
        T = np.array(model["cam_from_proj"], float)
        axis = rng.normal(size=3)
        T[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(0.2)).as_matrix() @ T[:3, :3]
        model["cam_from_proj"] = T.tolist()
        return "extrinsic 0.2 deg"
    device["K"] = K.tolist()
    return what


def is_wrong(clean: ScanResult, result: ScanResult) -> bool:
    """Whether a decode that exited 0 differs from the clean one beyond noise: the same frames'
    noise decodes identically, so a median depth change over 20 µm or 1 % of the points moved
    by more than 0.2 mm is a fault's, not noise's."""
    a, b = clean.cloud.points[..., 2], result.cloud.points[..., 2]
    both = np.isfinite(a) & np.isfinite(b)
    if both.sum() < 100:
        return False
    dz = np.abs(a - b)[both]
    return bool(np.median(dz) > 0.02 or np.mean(dz > 0.2) > 0.01)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--clean", type=int, default=220, help="clean scans (half per rig)")
    p.add_argument("--faults", type=int, default=3, help="faults drawn per clean scan")
    p.add_argument("--outside", type=int, default=20, help="scans of scenes outside the volume")
    p.add_argument("--seed", type=int, help="the battery's seed (default: drawn fresh)")
    p.add_argument("--width", type=int, default=640, help="camera width (px); height in proportion")
    p.add_argument("--out", help="keep the sessions here (default: a temporary folder)")
    args = p.parse_args(argv)
    seed = args.seed if args.seed is not None else int(np.random.SeedSequence().entropy % 2 ** 31)
    print(f"decode battery: seed {seed}, {args.clean} clean scans at {args.width} px wide, {args.faults} faults "
          f"each, {args.outside} outside the volume; load average {os.getloadavg()[0]:.1f}", flush=True)
    rng = np.random.default_rng(seed)
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="decode-battery-"))
    root.mkdir(parents=True, exist_ok=True)
    outcomes: list[Outcome] = []
    false_refusals: list[str] = []
    clean_n: dict[str, int] = defaultdict(int)
    pool: dict[tuple[str, str], list[Path]] = defaultdict(list)
    faults = [f for f in RIGHT if f != "scene_outside_volume"]
    t0 = time.perf_counter()
    for i in range(args.clean):
        rig = "bench" if i % 2 == 0 else "turntable"
        patterns = str(rng.choice(list(PATTERNS)))
        s = int(rng.integers(2 ** 31))
        folder = capture(rig, patterns, args.width, s, root / f"clean_{i:03d}")
        result, failed = judge(folder)
        clean_n[rig] += 1
        if result is None:
            false_refusals.append(f"{folder.name} ({rig}, {patterns}, seed {s}): {failed}")
            continue
        others = pool[(rig, patterns)]
        for j in range(args.faults):
            fault = str(rng.choice(faults))
            if fault == "gray_frames_swapped" and patterns != "graycode":
                fault = "phase_frames_swapped"
            if fault == "frame_from_another_scan" and not others:
                fault = "steps_rotated"
            dst = root / f"fault_{i:03d}_{j}"
            fs = int(rng.integers(2 ** 31))
            detail = make_fault(fault, folder, dst, np.random.default_rng(fs), others[-1] if others else None)
            faulty, failed_f = judge(dst)
            wrong = faulty is not None and faulty.cloud is not None and is_wrong(result, faulty)
            outcomes.append(Outcome(fault, rig, patterns, detail, faulty is None, failed_f[0] if failed_f else None,
                                    wrong, fs, bool(set(failed_f) - TIES)))
            shutil.rmtree(dst, ignore_errors=True)
        others.append(folder)
        if len(others) > 2:
            shutil.rmtree(others.pop(0), ignore_errors=True) if not args.out else others.pop(0)
        if (i + 1) % 10 == 0:
            print(f"  {i + 1}/{args.clean} clean scans, {len(outcomes)} faults, {time.perf_counter() - t0:.0f} s, "
                  f"load {os.getloadavg()[0]:.1f}", flush=True)
        if (i + 1) % 50 == 0 and i + 1 < args.clean:  # the table so far, should the run be stopped
            print_table(outcomes, clean_n, false_refusals, seed, time.perf_counter() - t0)
    for i in range(args.outside):
        rig = "bench" if i % 2 == 0 else "turntable"
        patterns = str(rng.choice(list(PATTERNS)))
        s = int(rng.integers(2 ** 31))
        folder = capture(rig, patterns, args.width, s, root / f"outside_{i:03d}", outside=True)
        result, failed = judge(folder)
        outcomes.append(Outcome("scene_outside_volume", rig, patterns, "", result is None,
                                failed[0] if failed else None, result is not None, s, bool(set(failed) - TIES)))
    print_table(outcomes, clean_n, false_refusals, seed, time.perf_counter() - t0)
    if not args.out:
        shutil.rmtree(root, ignore_errors=True)
    return 0


def print_table(outcomes: list[Outcome], clean_n: dict[str, int], false_refusals: list[str], seed: int,
                seconds: float) -> None:
    print(f"\nfault class               trials  refused  right reason  by physics  wrong with exit 0  harmless exit 0"
          f"   (seed {seed}, {seconds:.0f} s)")
    for fault in RIGHT:
        rows = [o for o in outcomes if o.fault == fault]
        if not rows:
            continue
        print(f"{fault:<25} {len(rows):6d}  {sum(o.refused for o in rows):7d}  {sum(o.right for o in rows):12d}  "
              f"{sum(o.physics for o in rows):10d}  {sum(o.wrong for o in rows):17d}  "
              f"{sum(not o.refused and not o.wrong for o in rows):15d}")
    total = sum(clean_n.values())
    print(f"clean scans: {total} ({dict(clean_n)}), refused {len(false_refusals)} "
          f"({len(false_refusals) / max(total, 1):.2%})")
    for line in false_refusals:
        print(f"  false refusal: {line}")
    for o in outcomes:
        if o.wrong or (o.refused and not o.right):
            print(f"  {'WRONG exit 0' if o.wrong else 'other reason'}: {o.fault} {o.detail} ({o.rig}, {o.patterns}, "
                  f"seed {o.seed}) lead {o.lead}")
    leads: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for o in outcomes:
        leads[o.fault][o.lead or "-"] += 1
    print("lead check per fault: " + "; ".join(f"{f}: {dict(v)}" for f, v in leads.items()))


if __name__ == "__main__":
    sys.exit(main())
