"""Reading a closed session recording (`.rrd`) back: its entities, their row counts,
timelines and components, and the values of one component (tests, tools).

Reading needs the file's footer (its chunk manifest): a recording that was not closed is
refused with `RecordingError`."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scanner.session_recording import CLOUD, TIMELINE_SCAN, RecordingError


@dataclass(frozen=True)
class EntitySummary:
    """What one entity holds: row counts (temporal and static), timelines, components."""

    rows: int = 0
    static_rows: int = 0
    timelines: frozenset[str] = frozenset()
    components: frozenset[str] = frozenset()


@dataclass(frozen=True)
class RecordingSummary:
    path: Path
    application_id: str
    recording_id: str
    blueprints: int
    entities: dict[str, EntitySummary] = field(default_factory=dict)

    @property
    def entity_paths(self) -> list[str]:
        return sorted(self.entities)

    @property
    def timelines(self) -> set[str]:
        return set().union(*(e.timelines for e in self.entities.values())) if self.entities else set()


def _open_store(path: str | Path) -> tuple[Any, Any, int]:
    from rerun.chunk import RrdReader

    path = Path(path)
    if not path.is_file():
        part = path.with_name(path.name + ".part")
        hint = f" (only {part.name} exists: the recording was never closed)" if part.exists() else ""
        raise RecordingError(f"{path}: no such recording{hint}")
    try:
        with warnings.catch_warnings():  # a missing footer is reported below, as an error
            warnings.simplefilter("ignore")
            reader = RrdReader(path)
        entries = reader.recordings()
        if not entries:
            raise RecordingError(f"{path}: the file holds no recording")
        return reader.store(store=entries[0]), entries[0], len(reader.blueprints())
    except RecordingError:
        raise
    except Exception as exc:  # rerun raises RuntimeError for a file without its footer
        raise RecordingError(f"{path}: cannot read the recording ({exc}); a file without its footer was not "
                             f"closed properly — `rerun rrd migrate` or the viewer can still load it") from exc


def _clean(entity_path: str) -> str:
    return entity_path.lstrip("/")


def read_summary(path: str | Path) -> RecordingSummary:
    """Entities of a closed `.rrd` with their row counts, timelines and components.

    Needs the file's footer (its chunk manifest): reading fails with `RecordingError`
    on a recording that was not closed."""
    store, entry, n_blueprints = _open_store(path)
    acc: dict[str, dict[str, Any]] = {}
    for chunk in store.stream():
        e = acc.setdefault(_clean(chunk.entity_path), {"rows": 0, "static": 0, "tl": set(), "cols": set()})
        if chunk.is_static:
            e["static"] += chunk.num_rows
        else:
            e["rows"] += chunk.num_rows
            e["tl"].update(chunk.timeline_names)
        for f in chunk.to_record_batch().schema:
            if (f.metadata or {}).get(b"rerun:kind") == b"data":
                e["cols"].add(f.name)
    entities = {k: EntitySummary(v["rows"], v["static"], frozenset(v["tl"]), frozenset(v["cols"]))
                for k, v in acc.items() if not k.startswith("__")}
    return RecordingSummary(Path(path), entry.application_id, entry.recording_id, n_blueprints, entities)


def entity_paths(path: str | Path) -> list[str]:
    """The entity paths of a closed `.rrd` (no leading '/')."""
    return read_summary(path).entity_paths


def read_component(path: str | Path, entity: str, component: str,
                   timeline: str | None = TIMELINE_SCAN) -> list[tuple[int | None, np.ndarray]]:
    """Every row of one component of one entity, as (time on `timeline`, flat numpy array),
    ordered by time; e.g. `read_component(p, CLOUD, "Points3D:positions")`."""
    import pyarrow as pa

    store, _, _ = _open_store(path)
    rows: list[tuple[int | None, np.ndarray]] = []
    for chunk in store.stream():
        if _clean(chunk.entity_path) != _clean(entity):
            continue
        batch = chunk.to_record_batch()
        if component not in batch.schema.names:
            continue
        col = batch.column(component)
        times = batch.column(timeline).to_pylist() if timeline and timeline in batch.schema.names else [None] * len(col)
        for t, cell in zip(times, col):
            if not cell.is_valid:
                continue
            values = cell.values
            while isinstance(values, (pa.ListArray, pa.FixedSizeListArray, pa.LargeListArray)):
                values = values.flatten()
            rows.append((t, values.to_numpy(zero_copy_only=False)))
    rows.sort(key=lambda r: (r[0] is None, r[0] if r[0] is not None else 0))
    return rows


def read_points(path: str | Path, entity: str = CLOUD) -> dict[int, np.ndarray]:
    """The (M, 3) points of each scan's cloud, keyed by scan index."""
    return {int(t) if t is not None else 0: a.reshape(-1, 3)
            for t, a in read_component(path, entity, "Points3D:positions", TIMELINE_SCAN)}
