"""The peers `slscan bench decode` measures beside slscan, run as a script by the peers' own Python
(`slscan bench decode --setup-peers` makes it: OpenCV contrib and `fringes` cannot share slscan's
environment, whose OpenCV has no contrib modules). It imports nothing from slscan; -I keeps
its folder (with a module named `inspect`) off the import path.

    python -I peers.py opencv_psp FRAMES.npy PROJ_W PROJ_H PERIODS REPEATS
        OpenCV contrib structured_light.SinusoidalPattern, PSP method: wrapped phase of three
        frames shifted by 2π/3 (computePhaseMap) and its spatial unwrapping (unwrapPhaseMap).
    python -I peers.py fringes WIDTH HEIGHT REPEATS
        The `fringes` package: it encodes its own 3-frequency x 4-step sequence at WIDTH x
        HEIGHT and decodes it (temporal unwrapping, with a per-pixel uncertainty); the first
        decode compiles it (numba) and is not counted.

Prints one JSON object: median seconds over REPEATS runs, megapixels per second, peak
resident memory (MB, the whole process) and the library version.
"""

from __future__ import annotations

import json
import resource
import statistics
import sys
import time

import numpy as np


def _peak_mb() -> float:
    """Peak resident memory of this process (MB; Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def opencv_psp(frames_path: str, proj_w: int, proj_h: int, periods: int, repeats: int) -> dict:
    import cv2

    frames = np.load(frames_path)
    imgs = [np.ascontiguousarray(f) for f in frames]
    sl = cv2.structured_light  # type: ignore[attr-defined]  # opencv-contrib's module, absent from the stubs
    p = sl.SinusoidalPattern.Params()
    p.width, p.height, p.nbrOfPeriods = proj_w, proj_h, periods
    p.methodId, p.shiftValue = sl.PSP, float(2 * np.pi / 3)
    sp = sl.SinusoidalPattern_create(p)
    size = (imgs[0].shape[1], imgs[0].shape[0])
    times = []
    for _ in range(repeats + 1):  # the first run warms caches and is not counted
        t0 = time.perf_counter()
        wrapped, shadow = sp.computePhaseMap(imgs)
        sp.unwrapPhaseMap(wrapped, size, shadowMask=shadow)
        times.append(time.perf_counter() - t0)
    s = statistics.median(times[1:])
    return {"peer": "opencv_contrib_psp", "version": cv2.__version__, "seconds": s,
            "mpx_per_s": size[0] * size[1] / s / 1e6, "peak_mb": _peak_mb(), "frames": len(imgs)}


def fringes_peer(width: int, height: int, repeats: int) -> dict:
    import fringes

    f = fringes.Fringes(X=width, Y=height, axes=(0,), K=3, N=4, v=(70.0, 64.0, 59.0))
    sequence = f.encode()
    f.decode(sequence)  # numba compiles here
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f.decode(sequence)
        times.append(time.perf_counter() - t0)
    s = statistics.median(times)
    return {"peer": "fringes", "version": fringes.__version__, "seconds": s,
            "mpx_per_s": width * height / s / 1e6, "peak_mb": _peak_mb(), "frames": int(np.shape(sequence)[0])}


if __name__ == "__main__":
    kind, rest = sys.argv[1], sys.argv[2:]
    if kind == "opencv_psp":
        out = opencv_psp(rest[0], int(rest[1]), int(rest[2]), int(rest[3]), int(rest[4]))
    elif kind == "fringes":
        out = fringes_peer(int(rest[0]), int(rest[1]), int(rest[2]))
    else:
        raise SystemExit(f"unknown peer {kind!r}")
    print(json.dumps(out))
