"""What a part folder really holds, said when a restarted station closes a cycle that a
killed station left `in_progress`: each session complete (its manifest opens; with or
without its cloud), completable (every frame logged, no manifest: `slscan decode
--recover`), or incomplete (fewer frames than the patterns need: re-scan). A good capture is
never called incomplete."""

from __future__ import annotations

from pathlib import Path

from scanner.errors import ScannerError
from scanner.multiview import is_multiview
from scanner.session import FRAME_LOG, MANIFEST, OUTPUTS_DIR, Session
from scanner.session_recovery import capture_progress


def session_state(root: Path) -> str:
    """One session folder's state, for people (module docstring)."""
    if (root / MANIFEST).exists():
        try:
            Session.open(root)
        except ScannerError as exc:
            return f"{root.name}: its manifest does not open ({str(exc)[:120]})"
        if (root / OUTPUTS_DIR / "cloud.ply").exists():
            return f"{root.name}: complete (manifest and cloud)"
        return f"{root.name}: complete capture, not decoded (`slscan decode {root}` makes its cloud)"
    if not (root / FRAME_LOG).exists():
        return f"{root.name}: no frame stored"
    logged, needed = capture_progress(root)
    if needed is not None and logged == needed:
        return (f"{root.name}: all {needed} frames, no manifest (killed before it was written): "
                f"`slscan decode --recover {root}` completes it")
    of = f" of {needed}" if needed is not None else ""
    return f"{root.name}: {logged}{of} frames, no manifest: the capture did not finish; re-scan"


def part_state(folder: str | Path | None) -> str:
    """Every session of a part folder (views, or a multi-view folder's views), "; "-joined."""
    if not folder or not Path(folder).is_dir():
        return "no session was started"
    roots = []
    for child in sorted(p for p in Path(folder).iterdir() if p.is_dir()):
        if is_multiview(child):
            roots += sorted(p for p in child.iterdir() if p.is_dir() and p.name.startswith("view_"))
        else:
            roots.append(child)
    return "; ".join(session_state(r) for r in roots) or "no session was started"
