"""slscan scanner core: devices, patterns, acquisition, sessions, decoding, reconstruction."""

import os

import cv2

__version__ = "0.1.0"

# Size OpenCV's thread pool to this machine explicitly: left at its default, the pool showed
# 3x run-to-run swings in decode time on a 2-core VM (measured with `slscan bench`).
cv2.setNumThreads(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))
