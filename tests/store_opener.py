"""The child's side of tests that open one results database from several processes at once:
a module of its own, so a spawned child imports only this and the results store (~0.2 s
CPU), not the test module that starts it (its imports tripled each child's start-up)."""

from __future__ import annotations

from typing import Any


def open_store(path: str, results: Any) -> None:
    """Open the SQLite results database at `path`; put "ok" or the error on `results`."""
    from slscan.station.results import open_results

    try:
        with open_results(f"sqlite:{path}"):
            results.put("ok")
    except Exception as exc:  # reported to the test
        results.put(f"{type(exc).__name__}: {exc}")
