"""`slscan bench binocular`: binocular reconstruction measured on the simulated binocular rig
(config/rigs/sim_binocular.toml: two 1280 x 1024 cameras 200 mm apart, the bench projector),
each run on fresh random scenes (`sim.stereo_truth.random_scene`; the seeds are printed).

    accuracy   per scene: depth error RMS against the simulator's truth over the left camera's
               smooth lit pixels the right camera sees too, beside the predicted noise
               (`BinocularResult.depth_sigma_mm`); and the monocular reconstruction of the same
               left frames with the projector's true model (error RMS, the noise bound of
               `sim.evaluate.depth_noise_bound`) over the same pixels; points beyond 5 sigma
    wrong      the same scene with the projector's gamma compensated for 1.8 instead of its
               true 2.2 and its distortion taken as k1 = -0.02 instead of +0.02: binocular
               (which never uses either) beside monocular (which uses both)
    timing     decode + matching + triangulation of the 2 x 1.3 MP frames (both cameras decoded
               at once, as `slscan` does) beside one monocular decode + triangulation of the left
               frames, medians of --repeats, with the peak traced memory of each and the load
               average before and after; and each one's processor time (every thread's, medians):
               on a loaded machine the wall times say how the load was shared, the processor
               times what each path costs
    memory     each stage's peak resident memory (render scene, capture, decode, binocular, monocular:
               the process's high-water mark reset at the stage's start, so what earlier stages still
               hold is in it) and the resident set after each scene, its rig and arrays released

    import     a capture made as SLMaster makes one (its 12-step + complementary Gray-code rows on a
               1920 x 1080 projector, no gamma pre-compensation, 8-bit BMP) with its stereo caliInfo.yml,
               through `slscan import LEFT RIGHT`, conventions detected and given: cloud against truth

    slscan bench binocular [--scenes N] [--imports N] [--seed S] [--repeats R] [--json] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import tracemalloc
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slscan.bench_timing import median_times
from slscan.exit_codes import Exit
from slscan.options import add_json
from slscan.resident_memory import StagePeaks, release_memory, resident_mib

if TYPE_CHECKING:
    import numpy as np

RIG = "sim_binocular.toml"
WRONG_GAMMA = 1.8
WRONG_K1 = -0.02


def _capture(rig: Any, patterns: Any, gamma: float) -> dict[str, np.ndarray]:
    from scanner.acquisition import AcquisitionSettings, acquire_all

    compensated = replace(rig, model=replace(rig.model, projector_gamma=gamma))
    return acquire_all(compensated, patterns, AcquisitionSettings.for_rig(rig), lambda *a: None)


def _figures(err: np.ndarray, sigma: np.ndarray, sel: np.ndarray) -> dict[str, float]:
    import numpy as np

    e = err[sel].astype(np.float64)
    s = sigma[sel].astype(np.float64)
    return {"pixels": int(sel.sum()), "rms_um": float(np.sqrt(np.mean(e ** 2)) * 1e3),
            "mean_um": float(np.mean(e) * 1e3), "bound_um": float(np.sqrt(np.mean(s ** 2)) * 1e3)}


def _scene_run(config: Any, seed: int, peaks: StagePeaks) -> dict[str, Any]:
    """Both reconstructions of one fresh scene, right and wrong projector; each stage's peak
    resident memory into `peaks`."""
    import numpy as np

    from scanner.binocular import BinocularReconstructor
    from scanner.patterns import PatternSet
    from sim.evaluate import Truth, smooth_region
    from sim.stereo_truth import random_scene, seen_by
    from sim.virtual_rig import open_sim_rig

    rng = np.random.default_rng(seed)
    patterns = PatternSet.load(config.patterns_path)
    models = config.camera_models()
    left_model = models["left"]
    wrong_projector = replace(left_model.projector, dist=np.r_[WRONG_K1, left_model.projector.dist[1:]])
    stereo = config.stereo_model(nominal=True)
    bino = BinocularReconstructor(stereo)
    out: dict[str, Any] = {"seed": seed}
    with peaks.stage("render scene"):
        rig = open_sim_rig(config, scene=random_scene(rng), seed=int(rng.integers(2 ** 31)))
    with rig:
        truths = rig.extras["ground_truths"]
        gt = Truth.of(truths["left"])
        both = smooth_region(gt) & seen_by(truths["left"], truths["right"])
        for case, gamma, model in (("true projector", left_model.projector_gamma, left_model),
                                   ("wrong projector", WRONG_GAMMA, replace(left_model, projector=wrong_projector))):
            out.pop("stacks", None)
            out[case], out["stacks"] = _case(rig, patterns, gamma, model=model, bino=bino, gt=gt, both=both,
                                             peaks=peaks)
        out["lit_left_pixels"] = int(gt.lit.sum())
    return out


def _case(rig: Any, patterns: Any, gamma: float, *, model: Any, bino: Any, gt: Any, both: np.ndarray,
          peaks: StagePeaks) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """One scan of the open scene with the projector compensated for `gamma`, reconstructed
    binocularly and monocularly with `model`: the figures, and the frames (the case's arrays
    are freed on return: the next case never holds two scans' worth)."""
    import numpy as np

    from scanner.decode import decode
    from scanner.reconstruct import Triangulator, triangulate
    from sim.evaluate import depth_noise_bound

    left_model = rig.config.camera_models()["left"]
    sensor = rig.extras["renderers"]["left"].sensor
    with peaks.stage("capture"):
        stacks = _capture(rig, patterns, gamma)
    size = left_model.projector.size
    with peaks.stage("decode"):
        decoded = {n: decode(s, patterns, rig.camera.bit_depth, size) for n, s in stacks.items()}
    with peaks.stage("binocular"):
        b = bino.reconstruct(decoded["left"], decoded["right"])
    with peaks.stage("monocular"):
        mono = triangulate(decoded["left"], Triangulator(model))
    err_b = b.cloud.points[..., 2] - gt.depth
    err_m = mono.points[..., 2] - gt.depth
    bound_m = depth_noise_bound(decoded["left"], Triangulator(left_model), sensor)
    sel = both & b.cloud.valid & mono.valid
    return {"binocular": _figures(err_b, b.depth_sigma_mm, sel) | {
                "beyond_5_sigma": int((b.cloud.valid & ~(np.abs(err_b) <= 5 * b.depth_sigma_mm)).sum()),
                "over_1_mm": int((b.cloud.valid & ~(np.abs(err_b) <= 1.0)).sum()),
                "points": int(b.cloud.valid.sum()), "checks": b.checks},
            "monocular": _figures(err_m, bound_m, sel) | {
                "beyond_5_sigma": int((mono.valid & ~(np.abs(err_m) <= 5 * bound_m)).sum()),
                "over_1_mm": int((mono.valid & ~(np.abs(err_m) <= 1.0)).sum()),
                "points": int(mono.valid.sum())}}, stacks


def _timing(config: Any, stacks: dict[str, np.ndarray], repeats: int) -> dict[str, Any]:
    from concurrent.futures import ThreadPoolExecutor

    from scanner.binocular import BinocularReconstructor
    from scanner.decode import decode
    from scanner.patterns import PatternSet
    from scanner.reconstruct import Triangulator, triangulate

    patterns = PatternSet.load(config.patterns_path)
    model = config.camera_models()["left"]
    size, bits = model.projector.size, 12
    bino = BinocularReconstructor(config.stereo_model(nominal=True))
    tri = Triangulator(model)
    rect = bino.rectification  # its tables once per rig, as in a station, as the triangulator's:
    _ = rect.left.taps, rect.right.taps, rect.left_ray_planes
    tri.prepare(("vertical",))

    def mono() -> None:
        triangulate(decode(stacks["left"], patterns, bits, size), tri)

    def binocular() -> None:
        with ThreadPoolExecutor(2) as pool:
            d = list(pool.map(lambda s: decode(s, patterns, bits, size), (stacks["left"], stacks["right"])))
        bino.reconstruct(d[0], d[1])

    def measure(fn: Any) -> tuple[float, float, float]:
        tracemalloc.start()
        fn()
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        wall, cpu = median_times(fn, repeats)
        return wall, peak / 2 ** 20, cpu

    load0 = os.getloadavg()
    rounds = [(measure(mono), measure(binocular)) for _ in range(2)]  # interleaved: both see the same load
    m_t, b_t = (statistics.median([r[k][0] for r in rounds]) for k in (0, 1))
    m_cpu, b_cpu = (statistics.median([r[k][2] for r in rounds]) for k in (0, 1))
    return {"frames": int(stacks["left"].shape[0]), "size": list(stacks["left"].shape[1:][::-1]),
            "monocular_s": round(m_t, 3), "binocular_s": round(b_t, 3), "ratio": round(b_t / m_t, 2),
            "monocular_cpu_s": round(m_cpu, 3), "binocular_cpu_s": round(b_cpu, 3),
            "cpu_ratio": round(b_cpu / m_cpu, 2),
            "monocular_peak_mib": round(max(r[0][1] for r in rounds), 1),
            "binocular_peak_mib": round(max(r[1][1] for r in rounds), 1),
            "load_average_start": [round(x, 2) for x in load0],
            "load_average_end": [round(x, 2) for x in os.getloadavg()], "cores": os.cpu_count()}


def _import_run(seed: int, folder: Path) -> dict[str, Any]:
    """A binocular capture as SLMaster makes one (12-step phase + complementary Gray code on a
    1920 x 1080 projector, shown without gamma pre-compensation, 8-bit BMP frames) of a fresh
    scene, with its stereo caliInfo.yml (the rig's true geometry), imported: with the pattern
    file's conventions left to detection, then given; the cloud against the simulator's truth."""
    import cv2
    import numpy as np

    from scanner.config import CONFIG_DIR
    from scanner.errors import ScannerError
    from scanner.pointcloud import read_ply_pixels
    from scanner.rig import RigConfig
    from sim.evaluate import Truth, smooth_region
    from sim.foreign_patterns import slmaster_complementary
    from sim.stereo_bench import binocular_rig, render_rows, write_slmaster_caliinfo
    from sim.stereo_truth import random_scene, seen_by
    from sim.virtual_rig import open_sim_rig
    from slscan.commands.import_binocular import import_binocular

    rng = np.random.default_rng(seed)
    config = RigConfig.load(binocular_rig(folder, 1280, 1024, projector=(1920, 1080, 1.0)))
    with open_sim_rig(config, scene=random_scene(rng), seed=int(rng.integers(2 ** 31))) as rig:
        stacks = render_rows(rig, slmaster_complementary(1920), 8, rng)
        truths = rig.extras["ground_truths"]
    folders = []
    for name, stack in stacks.items():
        (folder / name).mkdir()
        for k, frame in enumerate(stack):
            cv2.imwrite(str(folder / name / f"{k + 1}.bmp"), frame)
        folders.append(folder / name)
    calib = write_slmaster_caliinfo(folder / "caliInfo.yml", config.stereo_model(nominal=True), (1280, 1024))
    given = CONFIG_DIR / "patterns" / "slmaster_complementary_12x32.toml"
    bare = folder / "slmaster_no_conventions.toml"
    bare.write_text(given.read_text().split("[conventions]")[0])
    out: dict[str, Any] = {"seed": seed}
    gt = Truth.of(truths["left"])
    both = smooth_region(gt) & seen_by(truths["left"], truths["right"])
    for case, patterns in (("conventions detected", bare), ("conventions given", given)):
        try:
            scan, detections = import_binocular(folders, patterns, (1920, 1080), folder / case.replace(" ", "_"),
                                                [calib])
        except ScannerError as exc:
            out[case] = {"refused": str(exc)}
            continue
        read = read_ply_pixels(scan.cloud_path)
        if read is None:
            out[case] = {"refused": f"{scan.cloud_path}: no pixel columns"}
            continue
        points, pixels = read.points, read.pixels
        depth = np.full(gt.depth.shape, np.nan)
        depth[pixels[:, 1], pixels[:, 0]] = points[:, 2]
        err = depth - gt.depth
        sel = both & np.isfinite(depth)
        out[case] = _figures(err, scan.result.depth_sigma_mm, sel) | {
            "points": len(points), "lit_left_pixels": int(gt.lit.sum()),
            "beyond_5_sigma": int((np.isfinite(depth) & ~(np.abs(err) <= 5 * scan.result.depth_sigma_mm)).sum()),
            "over_1_mm": int((np.isfinite(depth) & ~(np.abs(err) <= 1.0)).sum()),
            "conventions": {f.key: [f.value, f.source] for f in detections[0].findings},
            "checks": scan.result.checks}
    return out


def run_binobench(scenes: int, seed: int | None, repeats: int, *, imports: int = 0,
                  say: Any = print) -> dict[str, Any]:
    import numpy as np

    from scanner.config import CONFIG_DIR
    from scanner.rig import RigConfig

    config = RigConfig.load(CONFIG_DIR / "rigs" / RIG)
    root = np.random.SeedSequence(seed)
    say(f"binobench: root seed {root.entropy}")
    runs = []
    stacks = None
    peaks = StagePeaks()
    for k, child in enumerate(root.spawn(scenes)):
        s = int(child.generate_state(1)[0])
        stacks = None  # the last scene's frames go to the timing; no earlier scene's are kept
        r = _scene_run(config, s, peaks)
        stacks = r.pop("stacks")
        release_memory()  # the scene's rig and arrays, before the next scene is built
        r["resident_mib_after"] = round(resident_mib(), 1)
        runs.append(r)
        for case in ("true projector", "wrong projector"):
            b, m = r[case]["binocular"], r[case]["monocular"]
            say(f"scene {k} (seed {s}) {case}: binocular {b['rms_um']:.1f} um (bound {b['bound_um']:.1f}), "
                f"monocular {m['rms_um']:.1f} um (bound {m['bound_um']:.1f}) over {b['pixels']} px; beyond 5 sigma "
                f"{b['beyond_5_sigma']} / {m['beyond_5_sigma']}; points {b['points']} / {m['points']}")
        say(f"scene {k}: peak resident memory so far by stage (MiB): "
            + (f"not measured: {peaks.not_measured}" if peaks.not_measured else
               ", ".join(f"{n} {v:.0f}" for n, v in peaks.peaks.items() if v is not None))
            + f"; resident after {r['resident_mib_after']:.0f}")
    timing = _timing(config, stacks, repeats) if repeats > 0 and stacks is not None else None
    if timing:
        say(f"timing: binocular {timing['binocular_s']} s, monocular {timing['monocular_s']} s, ratio "
            f"{timing['ratio']} (processor time {timing['binocular_cpu_s']} / {timing['monocular_cpu_s']} s, ratio "
            f"{timing['cpu_ratio']}); peak {timing['binocular_peak_mib']} / {timing['monocular_peak_mib']} MiB; load "
            f"{timing['load_average_start']} -> {timing['load_average_end']}")
    imported = []
    for k, child in enumerate(root.spawn(imports)):
        s = int(child.generate_state(1)[0])
        with tempfile.TemporaryDirectory(prefix="binobench-import-") as tmp:
            r = _import_run(s, Path(tmp))
        imported.append(r)
        for case in ("conventions detected", "conventions given"):
            f = r[case]
            say(f"import {k} (seed {s}) {case}: " + (f"refused: {f['refused']}" if "refused" in f else
                f"{f['rms_um']:.1f} um (predicted {f['bound_um']:.1f}) over {f['pixels']} px, mean "
                f"{f['mean_um']:+.2f} um; points {f['points']} of {f['lit_left_pixels']} lit; beyond 5 sigma "
                f"{f['beyond_5_sigma']}, over 1 mm {f['over_1_mm']}"))
    return {"rig": str(config.path), "root_seed": root.entropy, "scenes": runs, "timing": timing,
            "imports": imported, "peak_resident_mib": peaks.peaks,
            "peak_resident_not_measured": peaks.not_measured}


def cmd_binobench(args: argparse.Namespace) -> int:
    report = run_binobench(args.scenes, args.seed, args.repeats, say=(lambda s: None) if args.json else print,
                           imports=args.imports)
    text = json.dumps(report, indent=1, default=float)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
    if args.json:
        print(text)
    return Exit.OK


def register(sub: Any) -> None:
    p = sub.add_parser("binocular")
    p.add_argument("--scenes", type=int, default=3, help="fresh random scenes (default 3)")
    p.add_argument("--seed", type=int, help="root seed (default: fresh, printed)")
    p.add_argument("--repeats", type=int, default=3, help="timed runs per round (0: no timing)")
    p.add_argument("--imports", type=int, default=1, help="binocular captures made as SLMaster makes them, imported "
                                                             "with its stereo file (default 1)")
    add_json(p)
    p.add_argument("--out", help="write the figures as JSON here")
    p.set_defaults(func=cmd_binobench)
