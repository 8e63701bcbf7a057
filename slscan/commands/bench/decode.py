"""`slscan bench decode`: decode + reconstruction time and peak memory for one fringe stack, beside
its peers in the same run.

The stack is synthesised analytically (a tilted plane with a smooth bump, seen by a camera
of the requested size with the default rig's field of view, with shot and read noise), so
the figures do not depend on the simulator. Timing runs in a fresh child process whose
peak resident memory (VmHWM: interpreter, libraries, input stack and all working arrays)
is the reported peak; the median phase noise slscan predicts per pixel is reported too.

Peers (`peers.py`, run by their own Python made by `slscan bench decode --setup-peers` in
PEERS_VENV): OpenCV contrib's structured_light SinusoidalPattern PSP (wrapped phase and
spatial unwrapping) on three frames of the same scene and size, and, with `--fringes`, the
`fringes` package decoding its own 3 x 4 sequence at 1280 x 1024 (it reports a per-pixel
uncertainty, as slscan's phase_sigma does). The load average is printed with the figures.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from slscan.exit_codes import Exit

if TYPE_CHECKING:
    import numpy as np

    from scanner.geometry import RigModel
    from scanner.patterns import PatternSet

PEERS_VENV = Path(os.environ.get("SLSCAN_PEERS_VENV", "~/.cache/slscan/bench-peers")).expanduser()
PEER_PACKAGES = ("opencv-contrib-python-headless==5.0.0.93", "fringes==2.1.0")  # exact pins: the peers measured
PEER_SCRIPT = Path(__file__).with_name("peers.py")


def _vm_hwm_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _child(stack_path: str, rig_dict: dict, patterns_dict: dict, repeats: int, queue: mp.Queue) -> None:
    import numpy as np

    from scanner.decode import decode
    from scanner.geometry import RigModel
    from scanner.patterns import PatternSet
    from scanner.reconstruct import Triangulator, triangulate

    stack = np.load(stack_path)
    rig = RigModel.from_dict(rig_dict)
    patterns = PatternSet.from_dict(patterns_dict)
    t0 = time.perf_counter()
    tri = Triangulator(rig)
    tri.prepare(patterns.orientations)
    setup = time.perf_counter() - t0
    dec, rec = [], []
    for _ in range(repeats + 1):  # the first run warms caches and is not counted
        t0 = time.perf_counter()
        d = decode(stack, patterns, 12, rig.projector.size)
        t1 = time.perf_counter()
        cloud = triangulate(d, tri)
        t2 = time.perf_counter()
        dec.append(t1 - t0)
        rec.append(t2 - t1)
    sigma = d.maps[patterns.orientations[0]].phase_sigma
    peak = _vm_hwm_mb()  # before the floor's own buffers
    floor = _floor(stack, patterns)
    queue.put({"floor": floor, "setup_s": setup, "decode_s": statistics.median(dec[1:]),
               "reconstruct_s": statistics.median(rec[1:]),
               "valid_fraction": float(d.valid.mean()), "points": len(cloud), "peak_mb": peak,
               "median_phase_sigma_rad": float(np.nanmedian(sigma[::8, ::8]))})


def setup_peers() -> Path:
    """Make the peers' Python in PEERS_VENV with PEER_PACKAGES (downloads them)."""
    subprocess.run([sys.executable, "-m", "venv", str(PEERS_VENV)], check=True)
    pip = [str(PEERS_VENV / "bin" / "python"), "-m", "pip", "install", "-q"]
    subprocess.run(pip + list(PEER_PACKAGES), check=True)
    # fringes pulls the non-headless contrib wheel; the pinned headless one must own cv2
    subprocess.run([str(PEERS_VENV / "bin" / "python"), "-m", "pip", "uninstall", "-y", "-q",
                    "opencv-contrib-python"], check=False)
    subprocess.run(pip + ["--force-reinstall", "--no-deps", PEER_PACKAGES[0]], check=True)
    return PEERS_VENV


def _peer(args: list[str]) -> dict[str, Any]:
    python = PEERS_VENV / "bin" / "python"
    if not python.exists():
        return {"error": f"no peers' Python in {PEERS_VENV}: run `slscan bench decode --setup-peers` once"}
    done = subprocess.run([str(python), "-I", str(PEER_SCRIPT), *args], capture_output=True, text=True, timeout=1800,
                          check=False)
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def run_peers(rig: RigModel, patterns: PatternSet, width: int, *, height: int, repeats: int, with_fringes: bool,
              tmp: str) -> list[dict[str, Any]]:
    """The peers on the same scene: OpenCV's PSP on three frames of the finest frequency
    rendered with OpenCV's own conventions (a sine shifted by +2π/3, 8-bit), and `fringes`."""
    import numpy as np

    from scanner.conventions import NATIVE
    from scanner.patterns import PatternSet
    from sim.analytic_stack import synthetic_stack

    periods = int(max(patterns.fringes))
    psp = PatternSet("graycode", 3, (float(periods),)).with_conventions(
        replace(NATIVE, phase_origin=-np.pi / 2, pixel_centre=0.0))
    frames = synthetic_stack(rig, psp)[:3]
    path = os.path.join(tmp, "psp.npy")
    np.save(path, (frames >> 4).astype(np.uint8))
    peers = [_peer(["opencv_psp", path, str(rig.projector.width), str(rig.projector.height), str(periods),
                    str(repeats)])]
    if with_fringes:
        peers.append(_peer(["fringes", "1280", "1024", str(max(1, repeats // 2))]))
    return peers


def _floor(stack: np.ndarray, patterns: PatternSet, repeats: int = 3) -> dict[str, float]:
    """What bounds the decode on this machine: memory bandwidth (a 256 MB copy; GB/s of
    bytes read + written) and the minimal phase-shift kernel (every frequency's N-step sums
    and atan2 over the whole image, in bands on every core, as decode runs it)."""
    import numpy as np

    from scanner.decode import in_bands, phase_shift

    src = np.ones(64 * 2 ** 20, np.float32)
    dst = np.empty_like(src)
    copies = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        copies.append(time.perf_counter() - t0)
    blocks = [list(range(i * patterns.steps, (i + 1) * patterns.steps)) for i in range(len(patterns.fringes))]

    def kernel(rows: slice) -> None:
        for b in blocks:
            phase_shift([stack[k, rows] for k in b], patterns.steps, 0.0, 1)

    kernels = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        in_bands(stack.shape[1], kernel)
        kernels.append(time.perf_counter() - t0)
    return {"memory_copy_gb_s": 2 * src.nbytes / min(copies) / 1e9, "phase_kernel_s": min(kernels),
            "stack_mb": stack.nbytes / 1e6}


def run_bench(width: int, height: int, *, patterns_path: Path | None = None, rig_path: Path | None = None,
              repeats: int = 5, peers: bool = True, with_fringes: bool = False) -> dict:
    """Measure decode + reconstruction, and the peers; returns the figures (seconds, MB)."""
    import numpy as np

    from scanner.patterns import PatternSet
    from scanner.rig import RigConfig
    from sim.analytic_stack import synthetic_stack

    load0 = os.getloadavg()
    config = RigConfig.load(rig_path) if rig_path else RigConfig.load()
    patterns = PatternSet.load(patterns_path or config.patterns_path)
    rig = config.nominal_model().with_camera_size(width, height)
    stack = synthetic_stack(rig, patterns)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "stack.npy")
        np.save(path, stack)
        ctx = mp.get_context("spawn")
        queue = ctx.Queue()
        proc = ctx.Process(target=_child, args=(path, rig.to_dict(), patterns.to_dict(), repeats, queue))
        proc.start()
        result = queue.get(timeout=600)
        proc.join(timeout=60)
        peer_figures = run_peers(rig, patterns, width, height=height, repeats=repeats, with_fringes=with_fringes,
                                 tmp=tmp) if peers else []
    total = result["decode_s"] + result["reconstruct_s"]
    mpx = width * height / total / 1e6
    for p in peer_figures:
        if "mpx_per_s" in p:
            p["slscan_speedup"] = round(mpx / p["mpx_per_s"], 2)
    return {"width": width, "height": height, "frames": patterns.n_frames, "patterns": patterns.family,
            "decode_s": round(result["decode_s"], 4), "reconstruct_s": round(result["reconstruct_s"], 4),
            "total_s": round(total, 4), "mpx_per_s": round(mpx, 2),
            "peak_mb": round(result["peak_mb"], 1), "setup_s": round(result["setup_s"], 3),
            "valid_fraction": round(result["valid_fraction"], 4), "points": result["points"],
            "median_phase_sigma_rad": round(result["median_phase_sigma_rad"], 5),
            "floor": {k: round(v, 4) for k, v in result["floor"].items()},
            "repeats": repeats, "cores": os.cpu_count(), "load_average_start": load0,
            "load_average_end": os.getloadavg(), "peers": peer_figures}


def format_table(r: dict) -> str:
    rows = [("resolution", f"{r['width']} x {r['height']}"), ("pattern set", f"{r['patterns']}, {r['frames']} frames"),
            ("decode", f"{r['decode_s'] * 1e3:.0f} ms"), ("reconstruct", f"{r['reconstruct_s'] * 1e3:.0f} ms"),
            ("total", f"{r['total_s'] * 1e3:.0f} ms"), ("peak memory", f"{r['peak_mb']:.0f} MB (whole process)"),
            ("per-rig setup", f"{r['setup_s'] * 1e3:.0f} ms (once, cached)"),
            ("valid pixels", f"{r['valid_fraction'] * 100:.1f} %"),
            ("phase noise", f"{r['median_phase_sigma_rad']:.4f} rad median, predicted per pixel"),
            ("throughput", f"{r['mpx_per_s']:.1f} Mpx/s"),
            ("floor", f"memory copy {r['floor']['memory_copy_gb_s']:.1f} GB/s; the phase-shift kernel alone "
                      f"{r['floor']['phase_kernel_s'] * 1e3:.0f} ms on the {r['floor']['stack_mb']:.0f} MB stack"),
            ("median of", f"{r['repeats']} runs, {r['cores']} cores"),
            ("load average", f"{' '.join(f'{x:.2f}' for x in r['load_average_start'])} (start), "
                             f"{' '.join(f'{x:.2f}' for x in r['load_average_end'])} (end)")]
    for p in r["peers"]:
        rows.append((p.get("peer", "peer"), p["error"] if "error" in p else
                     f"{p['seconds'] * 1e3:.0f} ms, {p['mpx_per_s']:.1f} Mpx/s, peak {p['peak_mb']:.0f} MB "
                     f"(slscan {p['slscan_speedup']:.1f}x)"))
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{w}}  {v}" for k, v in rows)


if __name__ == "__main__":
    print(json.dumps(run_bench(2448, 2048)))


def cmd_bench(args: argparse.Namespace) -> int:
    if args.setup_peers:
        print(f"peers' Python ready in {setup_peers()}")
        return Exit.OK
    r = run_bench(args.width, args.height, patterns_path=Path(args.patterns) if args.patterns else None,
                  repeats=args.repeats, peers=not args.no_peers, with_fringes=args.fringes)
    print(json.dumps(r) if args.json else format_table(r))
    return Exit.OK


def register(sub: Any) -> None:
    b = sub.add_parser("decode")
    b.add_argument("--width", type=int, default=2448, help="camera image width in pixels (default 2448)")
    b.add_argument("--height", type=int, default=2048, help="camera image height in pixels (default 2048)")
    b.add_argument("--patterns", help="pattern set TOML (default: 3 frequencies x 4 steps)")
    b.add_argument("--repeats", type=int, default=5, help="timed runs per figure, median reported (default 5)")
    b.add_argument("--json", action="store_true", help="print a JSON object")
    b.add_argument("--no-peers", action="store_true", help="leave out the peers")
    b.add_argument("--fringes", action="store_true", help="also run the `fringes` peer (1280 x 1024; slow)")
    b.add_argument("--setup-peers", action="store_true", help=f"make the peers' Python in {PEERS_VENV} and exit")
    b.set_defaults(func=cmd_bench)
