"""Pattern images for the LightCrafter 4500's 912 x 1140 diamond-pixel DMD.

The DLP4500 mirrors are squares turned 45 degrees: 912 columns by 1140 rows, rows at half
the column pitch (so a rig model has fy = 2 fx), and every other row sits half a column
to the side of its neighbours (the zig-zag of TI's "diamond pixel" layout, described in
K. Guttag, "TI DLP Diamond Pixel", kguttag.com, 2012). A pattern computed on a square grid
therefore shows jagged fringes; `diamond_resample` re-samples each odd row at its true
position so a fringe is a smooth function of (column, row), the coordinates the rig model
and the decoder use.

Flash-stored sequences hold 8-bit patterns three to a 24-bit image, in green, red, blue
order (pattern numbers 0, 1, 2 of an 8-bit LUT entry; see `lightcrafter_protocol.LutEntry`).
`pack_rgb24` builds those images, `fingerprint` names a set of them so the driver can
refuse to run a sequence whose images are not the ones stored in flash.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np

from scanner.drivers.lightcrafter_protocol import HEIGHT, WIDTH

PATTERNS_PER_IMAGE = 3  # 8-bit patterns per 24-bit image


def diamond_resample(patterns: np.ndarray, odd_row_shift: float = 0.5) -> np.ndarray:
    """(N, 1140, 912) uint8 patterns re-sampled so odd rows show the value at column
    c + `odd_row_shift` (in column pitches; edges clamp). Rows that are constant along a
    row (horizontal fringes) are unchanged."""
    stack = np.asarray(patterns)
    if stack.ndim != 3 or stack.shape[1:] != (HEIGHT, WIDTH) or stack.dtype != np.uint8:
        raise ValueError(f"expected uint8 (N, {HEIGHT}, {WIDTH}) patterns, got {stack.dtype} {stack.shape}")
    out = stack.copy()
    if odd_row_shift == 0:
        return out
    x = np.clip(np.arange(WIDTH) + odd_row_shift, 0, WIDTH - 1)
    i0 = np.floor(x).astype(np.intp)
    i1 = np.minimum(i0 + 1, WIDTH - 1)
    w = (x - i0).astype(np.float32)
    odd = stack[:, 1::2, :].astype(np.float32)
    out[:, 1::2, :] = np.rint(odd[..., i0] * (1 - w) + odd[..., i1] * w).astype(np.uint8)
    return out


def pack_rgb24(patterns: np.ndarray) -> np.ndarray:
    """(ceil(N/3), 1140, 912, 3) RGB images: pattern 3i in green, 3i+1 in red, 3i+2 in
    blue; unused channels of the last image are black."""
    n = len(patterns)
    m = -(-n // PATTERNS_PER_IMAGE)
    images = np.zeros((m, HEIGHT, WIDTH, 3), dtype=np.uint8)
    for k in range(n):
        channel = (1, 0, 2)[k % PATTERNS_PER_IMAGE]  # green, red, blue as RGB channel indices
        images[k // PATTERNS_PER_IMAGE, :, :, channel] = patterns[k]
    return images


def fingerprint(images: np.ndarray) -> str:
    """SHA-256 (hex) of packed images: shape and bytes."""
    h = hashlib.sha256(repr(images.shape).encode())
    h.update(np.ascontiguousarray(images).tobytes())
    return h.hexdigest()


def export_flash_images(images: np.ndarray, out_dir: Path) -> Path:
    """Write the images as 24-bit BMPs (what TI's LightCrafter 4500 GUI adds to a firmware
    image) plus `flash_images.json` naming their fingerprint; returns the JSON path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for i, img in enumerate(images):
        name = f"slscan_{i:02d}.bmp"
        if not cv2.imwrite(str(out_dir / name), img[..., ::-1]):  # OpenCV writes BGR
            raise OSError(f"{out_dir / name}: could not write")
        names.append(name)
    manifest = out_dir / "flash_images.json"
    manifest.write_text(json.dumps({"flash_images_sha256": fingerprint(images), "images": names,
                                    "order": "store in flash in this order, starting at projector.flash_first_image"},
                                   indent=2) + "\n")
    return manifest
