"""`slscan bench import`: how fast and how well other tools' captures come in.

1. Per-rig tables: building a new rig's triangulation tables (camera rays, projector
   undistortion) at 1280 x 1024, beside the per-pixel undistortion they replace.
2. Import speed: a 1.3 MP, 18-frame SLMaster-style capture (12 phase steps + 6 complementary
   Gray-code frames, BMP files, an SLMaster caliInfo.yml) through `slscan import` and then
   `slscan decode`, each as the user runs it (a fresh process; wall time; the median of
   `--runs` fresh sessions, every run shown), beside reading the same frames and starting the
   command line (the floor under both).
3. Real captures (`--procam DIR`, default ../shared/data/procam-graycode when present): every
   pose imported with the tool's own calibration_result.xml (projector scale 2, its
   graycode_step) and, with `--procam-calibration FILE`, with ours: per pose the plane-fit
   residual RMS of the board's cloud and the distances between neighbouring chessboard
   corners (rays through the corners met with the board's fitted plane) against the nominal
   square; and the rejected-pixel fractions per reason, beside what the old saturation rule
   (any frame clipped) would have rejected.

Timings depend on the machine's load; the load average is printed with them.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scanner.config import CONFIG_DIR
from slscan.exit_codes import Exit

if TYPE_CHECKING:
    import numpy as np

    from scanner.geometry import RigModel

PROCAM_DEFAULT = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "procam-graycode"
SLMASTER_PATTERNS = CONFIG_DIR / "patterns" / "slmaster_complementary_12x32.toml"
OPENCV_GRAYCODE = CONFIG_DIR / "patterns" / "opencv_graycode.toml"


def synthetic_rig(camera: tuple[int, int] = (1280, 1024), projector: tuple[int, int] = (1920, 1080)) -> RigModel:
    """A camera and projector 150 mm apart, converging at 600 mm, both with lens distortion;
    the projector lights ~95 % of the camera's view of `plane_coordinates`' plane."""
    import numpy as np

    from scanner.geometry import Pinhole, RigModel, look_at

    cam = Pinhole.from_fov(*camera, 26.0, dist=np.array([-0.12, 0.15, 0.0004, -0.0003, 0.0]))
    proj = Pinhole.from_fov(*projector, 34.0, principal=(projector[0] / 2 - 0.5, projector[1] * 0.5 - 0.5),
                            dist=np.array([0.05, -0.08, 0.0002, 0.0001, 0.0]))
    world_from_proj = look_at(np.array([150.0, 0.0, 0.0]), np.array([0.0, 0.0, 600.0]))
    return RigModel(cam, proj, world_from_proj)  # world = camera frame


def plane_coordinates(rig: RigModel, normal: tuple[float, float, float] = (0.15, -0.1, 1.0),
                      distance_mm: float = 600.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W, mm) of the plane n·X = distance seen by the rig's camera and the
    projector (u, v) of each of its points (distortion included)."""
    import numpy as np

    rays = rig.camera.ray_grid.astype(np.float64)
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    z = distance_mm / (rays @ n)
    pts = (rays * z[..., None]).reshape(-1, 3)
    p = (pts - rig.cam_from_proj[:3, 3]) @ rig.cam_from_proj[:3, :3]
    return z, rig.projector.project(p).reshape(*z.shape, 2)


def write_slmaster_calibration(path: Path, rig: RigModel) -> None:
    """`rig` as an SLMaster caliInfo.yml: M1/D1 camera, M4/D4 projector, Rlp/Tlp taking
    camera-frame points into the projector frame, S the camera size (w, h)."""
    import cv2
    import numpy as np

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    proj_from_cam = rig.proj_from_cam
    for key, value in (("M1", rig.camera.K), ("D1", rig.camera.dist.reshape(1, 5)), ("M4", rig.projector.K),
                       ("D4", rig.projector.dist.reshape(1, 5)), ("Rlp", proj_from_cam[:3, :3]),
                       ("Tlp", proj_from_cam[:3, 3].reshape(3, 1))):
        fs.write(key, np.asarray(value, np.float64))
    fs.write("S", np.array([[rig.camera.width], [rig.camera.height]], np.float64))
    fs.release()


def slmaster_capture(folder: Path, rig: RigModel, seed: int = 0) -> np.ndarray:
    """An SLMaster 12-step + 6-frame complementary Gray-code capture of a tilted plane
    written as frame_1.bmp … frame_18.bmp; returns the true projector column per pixel."""
    import cv2

    from sim.foreign_patterns import capture, slmaster_complementary

    _, uv = plane_coordinates(rig)
    lit = (uv[..., 1] > -0.5) & (uv[..., 1] < rig.projector.height - 0.5)
    frames = capture(slmaster_complementary(rig.projector.width), uv[..., 0], seed=seed, lit=lit)
    folder.mkdir(parents=True, exist_ok=True)
    for k, img in enumerate(frames):
        cv2.imwrite(str(folder / f"frame_{k + 1}.bmp"), img)
    return uv[..., 0]


def _run(args: list[str]) -> tuple[float, float, str]:
    """`slscan ARGS` in a fresh process: (wall s, CPU s of the process, all threads, user +
    system; on a quiet machine the wall time is at most this), its output."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[3])}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "slscan", *args], capture_output=True, text=True, env=env,
                          timeout=600, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"slscan {' '.join(args)} failed: {done.stderr.strip().splitlines()[-1:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, done.stdout


def table_timing(rig: RigModel) -> dict[str, float]:
    """Seconds to build the triangulation tables for both orientations, and to undistort
    every camera pixel one by one (what the rays cost before, the peer)."""
    import numpy as np

    from scanner.geometry import Pinhole, RigModel
    from scanner.reconstruct import Triangulator

    fresh = RigModel(Pinhole(rig.camera.width, rig.camera.height, rig.camera.K, rig.camera.dist), rig.projector,
                     rig.cam_from_proj)
    t0 = time.perf_counter()
    Triangulator(fresh).prepare(("vertical", "horizontal"))
    tables = time.perf_counter() - t0
    u, v = np.meshgrid(np.arange(rig.camera.width, dtype=np.float64), np.arange(rig.camera.height, dtype=np.float64))
    t0 = time.perf_counter()
    rig.camera.normalized(np.stack([u.ravel(), v.ravel()], axis=1))
    return {"tables_s": tables, "per_pixel_undistort_peer_s": time.perf_counter() - t0}


def import_timing(workdir: Path, runs: int = 3) -> dict[str, Any]:
    """Wall and CPU seconds of `slscan import` and `slscan decode` on the SLMaster-style
    capture, `runs` times each into a fresh session (the first run pays cold caches, as a
    user's first does: every run is kept, the median is the figure), with the floor: reading
    its frames, and starting the command line."""
    import cv2
    import numpy as np

    rig = synthetic_rig()
    frames = workdir / "frames"
    truth = slmaster_capture(frames, rig)
    cal = workdir / "caliInfo.yml"
    write_slmaster_calibration(cal, rig)
    walls: dict[str, list[float]] = {"import": [], "decode": []}
    cpus: dict[str, list[float]] = {"import": [], "decode": []}
    for k in range(runs):
        session = workdir / f"session-{k}"
        for step, argv in (("import", ["import", str(frames), "--patterns", str(SLMASTER_PATTERNS), "--projector-size",
                                       f"{rig.projector.width}x{rig.projector.height}", "--calibration", str(cal),
                                       "--out", str(session)]),
                           ("decode", ["decode", str(session)])):
            wall, cpu, _ = _run(argv)
            walls[step].append(wall)
            cpus[step].append(cpu)
    t_start, cpu_start, _ = _run(["--help"])
    t0 = time.perf_counter()
    for f in sorted(frames.iterdir()):
        cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
    t_read = time.perf_counter() - t0
    with np.load(session / "outputs" / "maps.npz") as m:
        err = m["vertical/coordinate"] - truth
    result = json.loads((session / "outputs" / "result.json").read_text())
    return {"runs": runs, "import_wall_s": float(np.median(walls["import"])),
            "decode_wall_s": float(np.median(walls["decode"])), "import_wall_runs_s": walls["import"],
            "decode_wall_runs_s": walls["decode"], "import_cpu_s": float(np.median(cpus["import"])),
            "decode_cpu_s": float(np.median(cpus["decode"])), "cli_start_peer_s": t_start,
            "cli_start_cpu_s": cpu_start, "read_frames_peer_s": t_read, "points": result["points"],
            "timings_s": result["timings_s"],
            "coordinate_error_px": {"median": float(np.nanmedian(err)),
                                    "p99_abs": float(np.nanpercentile(np.abs(err), 99))}}


def board_figures(session: Path, white: np.ndarray, model: RigModel, square_mm: float,
                  pattern: tuple[int, int] = (9, 7)) -> dict[str, Any]:
    """Flatness and scale of a chessboard's cloud: RMS of the residuals of the cloud's points
    inside the board's corners to their least-squares plane (mm), and the errors of the
    distances between neighbouring corners (mm), each corner placed where the camera ray
    through it meets that plane."""
    import cv2
    import numpy as np

    from scanner.pointcloud import read_ply_points

    found, corners = cv2.findChessboardCornersSB(white, pattern)
    if not found:
        return {"error": "chessboard not found"}
    corners = corners.reshape(-1, 2)
    hull = cv2.convexHull(corners.astype(np.float32)).reshape(-1, 2)
    with np.load(session / "outputs" / "maps.npz") as m:
        valid = m["valid"]
    pts = read_ply_points(session / "outputs" / "cloud.ply")
    rows, cols = np.nonzero(valid)
    if len(rows) != len(pts):
        return {"error": f"{len(pts)} points but {len(rows)} valid pixels"}
    mask = np.zeros(valid.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    inside = mask[rows, cols].astype(bool)
    board = pts[inside].astype(np.float64)
    centre = board.mean(axis=0)
    _, _, vt = np.linalg.svd(board - centre, full_matrices=False)
    normal = vt[2]
    residual = (board - centre) @ normal
    rays = np.c_[model.camera.normalized(corners), np.ones(len(corners))]
    depth = (centre @ normal) / (rays @ normal)
    corners3d = rays * depth[:, None]
    grid = corners3d.reshape(pattern[1], pattern[0], 3)
    d = np.concatenate([np.linalg.norm(np.diff(grid, axis=1), axis=2).ravel(),
                        np.linalg.norm(np.diff(grid, axis=0), axis=2).ravel()]) - square_mm
    n_inner = int(inside.sum())
    return {"board_points": n_inner, "board_valid_fraction": n_inner / max(int(mask.sum()), 1),
            "plane_rms_mm": float(np.sqrt(np.mean(residual ** 2))),
        "distance_mm": float(np.linalg.norm(centre)), "corner_pairs": int(d.size),
        "corner_error_mean_mm": float(d.mean()), "corner_error_rms_mm": float(np.sqrt(np.mean(d ** 2))),
        "corner_error_max_mm": float(np.abs(d).max())}


def procam_figures(root: Path, calibrations: list[tuple[str, Path, float]], workdir: Path) -> list[dict[str, Any]]:
    """Per pose and calibration: board figures and rejected-pixel fractions (module docstring)."""
    from slscan.commands.import_ import import_frames, list_frames, read_frames

    out = []
    for pose in sorted(p for p in root.glob("capture_*") if p.is_dir()):
        stack, _ = read_frames(list_frames(pose, None))
        old_saturated = float((stack.max(axis=0) >= 255).mean())  # the old rule: any frame clipped
        for name, cal, scale in calibrations:
            session = workdir / f"{pose.name}-{name}"
            result, _ = import_frames(pose, OPENCV_GRAYCODE, (1024, 768), session, calibration=cal,
                                      projector_scale=scale)
            model = result.session.rig_model()
            rejected = {k: v / result.decoded.valid.size for k, v in result.decoded.rejected().items() if v}
            out.append({"pose": pose.name, "calibration": name, "valid_fraction": float(result.decoded.valid.mean()),
                        "rejected_fraction": rejected, "old_rule_saturated_fraction": old_saturated,
                        **board_figures(session, stack[-2], model, 75.0)})
    return out


def cmd_importbench(args: argparse.Namespace) -> int:
    load0 = os.getloadavg()
    report: dict[str, Any] = {"load_average_start": load0}
    report["tables"] = table_timing(synthetic_rig())
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_import:
            report["import"] = import_timing(Path(tmp) / "slmaster", args.runs)
        procam = Path(args.procam) if args.procam else PROCAM_DEFAULT
        if procam.is_dir() and not args.skip_procam:
            cals = [("procam_xml_scale2", procam / "calibration_result.xml", 2.0)]
            if args.procam_calibration:
                cals.append(("slscan", Path(args.procam_calibration), 1.0))
            report["procam"] = procam_figures(procam, cals, Path(tmp) / "procam")
    report["load_average_end"] = os.getloadavg()
    if args.json:
        print(json.dumps(report, indent=1))
    else:
        print(format_report(report))
    return Exit.OK


def format_report(r: dict[str, Any]) -> str:
    lines = [f"load average {' '.join(f'{x:.2f}' for x in r['load_average_start'])} (start), "
             f"{' '.join(f'{x:.2f}' for x in r['load_average_end'])} (end)"]
    t = r["tables"]
    lines.append(f"per-rig tables 1280 x 1024: {t['tables_s']:.3f} s (peer: undistorting every camera pixel "
                 f"{t['per_pixel_undistort_peer_s']:.3f} s)")
    if "import" in r:
        i = r["import"]
        runs = {step: ", ".join(f"{t:.2f}" for t in i[f"{step}_wall_runs_s"]) for step in ("import", "decode")}
        lines.append(f"import 1.3 MP x 18 frames with a cloud, median of {i['runs']} fresh sessions: "
                     f"{i['import_wall_s']:.2f} s wall ({runs['import']}; {i['import_cpu_s']:.2f} s CPU), decode "
                     f"{i['decode_wall_s']:.2f} s wall ({runs['decode']}; {i['decode_cpu_s']:.2f} s CPU; with its "
                     f"Rerun recording) ({i['points']} points; last run's stages "
                     f"{i['timings_s']}); floor: command-line start {i['cli_start_peer_s']:.2f} s wall "
                     f"({i['cli_start_cpu_s']:.2f} s CPU), reading the frames "
                     f"{i['read_frames_peer_s']:.2f} s; coordinate error median "
                     f"{i['coordinate_error_px']['median']:+.3f}"
                     f" px, p99 {i['coordinate_error_px']['p99_abs']:.3f} px")
    for row in r.get("procam", []):
        if "error" in row:
            lines.append(f"{row['pose']} {row['calibration']}: {row['error']}")
            continue
        rej = ", ".join(f"{k} {v * 100:.1f} %" for k, v in row["rejected_fraction"].items())
        lines.append(f"{row['pose']} {row['calibration']:<18} plane RMS {row['plane_rms_mm']:.3f} mm at "
                     f"{row['distance_mm']:.0f} mm over {row['board_points']} points ("
                     f"{row['board_valid_fraction'] * 100:.0f} % of the board); corners ({row['corner_pairs']} pairs) "
                     f"error mean "
                     f"{row['corner_error_mean_mm']:+.3f} RMS {row['corner_error_rms_mm']:.3f} max "
                     f"{row['corner_error_max_mm']:.3f} mm; valid {row['valid_fraction'] * 100:.1f} %; rejected {rej}; "
                     f"old any-frame saturation rule {row['old_rule_saturated_fraction'] * 100:.1f} %")
    return "\n".join(lines)


def register(sub: Any) -> None:
    b = sub.add_parser("import")
    b.add_argument("--procam", help="the procam-calibration sample folder (default ../shared/data/procam-graycode)")
    b.add_argument("--procam-calibration", help="slscan's calibration of that capture (slscan calibrate --from …)")
    b.add_argument("--skip-import", action="store_true", help="leave out the import speed run")
    b.add_argument("--runs", type=int, default=3, help="fresh import + decode runs timed (median and every run shown)")
    b.add_argument("--skip-procam", action="store_true", help="leave out the real captures")
    b.add_argument("--json", action="store_true", help="print a JSON object")
    b.set_defaults(func=cmd_importbench)
