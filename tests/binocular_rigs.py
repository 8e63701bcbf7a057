"""config/rigs/sim_binocular.toml at another camera size (same lenses' field of view), written to a
test's folder, for tests that need the binocular rig quickly."""

from __future__ import annotations

import re
from pathlib import Path

from scanner.config import CONFIG_DIR

BINOCULAR = CONFIG_DIR / "rigs" / "sim_binocular.toml"


def binocular_rig(tmp: Path, width: int, height: int, *, projector: tuple[int, int, float] | None = None,
                  edits: dict[str, str] | None = None) -> Path:
    """The rig with `width` x `height` cameras; `projector` (width, height, pixel aspect) replaces
    the bench projector's size; `edits` are further text replacements."""
    text = BINOCULAR.read_text().replace("width = 1280", f"width = {width}")
    text = text.replace("height = 1024", f"height = {height}")
    text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
    text = text.replace('artefacts = "../artefacts/', f'artefacts = "{CONFIG_DIR}/artefacts/')
    if projector is not None:
        w, h, aspect = projector
        text = re.sub(r"\[projector\]\nwidth = 912\nheight = 1140\nhfov_deg = 26.0\npixel_aspect = 2.0",
                      f"[projector]\nwidth = {w}\nheight = {h}\nhfov_deg = 26.0\npixel_aspect = {aspect}", text)
    for old, new in (edits or {}).items():
        text = text.replace(old, new)
    path = tmp / "rig.toml"
    path.write_text(text)
    return path
