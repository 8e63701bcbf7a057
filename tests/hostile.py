"""The hostile-input harness (issue 32): every generated case runs in a worker process under a
memory cap (RLIMIT_AS: the worker's size after its imports plus CASE_MEMORY_BYTES) and a
timeout, and its outcome is judged against the truth the generator knows:

    refused right    the case must be refused and was, with one line (a ScannerError)
    accepted right   the case must be accepted and was, with what the generator put in it
    silent           accepted although it must be refused, or accepted with other content
    false refusal    refused although it must be accepted
    traceback        an exception that is not a refusal
    hang             no answer within the timeout (the worker is killed and restarted)
    oom              MemoryError under the cap, or the worker killed by a signal

`Campaign` runs cases and tallies them per area; `table()` prints the table the issue's
acceptance asks for (cases, refused right, accepted right, wrong by kind). The seed of each
campaign is random unless SLSCAN_HOSTILE_SEED is set, and printed, so a failure can be
replayed.
"""

from __future__ import annotations

import importlib
import io
import multiprocessing as mp
import os
import resource
import time
import traceback
from collections import Counter, defaultdict
from collections.abc import Callable
from contextlib import redirect_stderr, redirect_stdout, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

CASE_MEMORY_BYTES = 2 * 1024 ** 3  # what one case may add to the worker's address space
CASE_TIMEOUT_S = 60.0
WARM_IMPORTS = ("numpy", "cv2", "open3d", "OCP.STEPControl", "scanner.mesh_files", "scanner.session",
                "inspection.cad", "sim.evaluate", "slscan.cli")

GOOD = ("refused right", "accepted right")
KINDS = GOOD + ("silent", "false refusal", "traceback", "hang", "oom")


def campaign_seed() -> int:
    """SLSCAN_HOSTILE_SEED, or a fresh seed from the clock."""
    return int(os.environ.get("SLSCAN_HOSTILE_SEED") or time.time_ns() % 2 ** 31)


@dataclass(frozen=True)
class Case:
    """One generated input: `area` (the table row), `target` ("module:function" run in the
    worker with `args`), `refuse` (what the truth calls for), `expect` (when accepted, what
    the target must return; None: anything), `what` (for people)."""

    area: str
    target: str
    args: tuple[Any, ...]
    refuse: bool
    what: str
    expect: Any = None


def _vm_size_kib() -> int:
    """This process's address space (kiB)."""
    return int(Path("/proc/self/status").read_text().split("VmSize:")[1].split()[0])


def _worker(conn: Any) -> None:
    for name in WARM_IMPORTS:
        importlib.import_module(name)
    size = _vm_size_kib() * 1024
    resource.setrlimit(resource.RLIMIT_AS, (size + CASE_MEMORY_BYTES, size + CASE_MEMORY_BYTES))
    from scanner.errors import ScannerError

    conn.send(("ready", size))
    while True:
        job = conn.recv()
        if job is None:
            return
        module, name = job[0].split(":")
        try:
            with redirect_stdout(io.StringIO()), redirect_stderr(io.StringIO()):
                value = getattr(importlib.import_module(module), name)(*job[1])
            conn.send(("accepted", value))
        except ScannerError as exc:
            conn.send(("refused", str(exc)))
        except MemoryError as exc:
            vm = _vm_size_kib()
            conn.send(("oom", f"MemoryError {exc} (address space {int(vm) // 1024} MB, cap "
                              f"{(size + CASE_MEMORY_BYTES) // 2 ** 20} MB)\n{traceback.format_exc(limit=6)}"))
        except BaseException as exc:  # every other outcome is a traceback, reported
            conn.send(("traceback", f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=4)}"))


class Worker:
    """One worker process (spawned, so no lock of the parent's threads is inherited)."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker, args=(child,), daemon=True)
        arenas = os.environ.get("MALLOC_ARENA_MAX")
        os.environ["MALLOC_ARENA_MAX"] = "2"  # each thread's malloc arena reserves 64 MB of the capped address space
        try:
            self.proc.start()
        finally:
            if arenas is None:
                del os.environ["MALLOC_ARENA_MAX"]
            else:
                os.environ["MALLOC_ARENA_MAX"] = arenas
        deadline = time.monotonic() + 180
        while not self.conn.poll(1):
            if not self.proc.is_alive() or time.monotonic() > deadline:
                self.kill()
                raise RuntimeError(f"the hostile-case worker did not start (exit {self.proc.exitcode})")
        self.conn.recv()

    def run(self, case: Case, timeout_s: float) -> tuple[str, Any]:
        self.conn.send((case.target, case.args))
        if not self.conn.poll(timeout_s):
            return "hang", f"no answer within {timeout_s:g} s"
        try:
            return self.conn.recv()
        except (EOFError, ConnectionError):
            self.proc.join(5)
            return "oom", f"worker died (exit {self.proc.exitcode})"

    def alive(self) -> bool:
        return self.proc.is_alive()

    def kill(self) -> None:
        self.proc.kill()
        self.proc.join(10)

    def close(self) -> None:
        if self.alive():
            with suppress(OSError):  # a worker already gone (BrokenPipeError is an OSError)
                self.conn.send(None)
            self.proc.join(10)
            if self.alive():
                self.kill()


@dataclass
class Campaign:
    """Cases run and judged (module docstring); `results[area]` counts outcomes, `wrong`
    lists the cases judged wrong with what happened."""

    seed: int
    timeout_s: float = CASE_TIMEOUT_S
    results: dict[str, Counter] = field(default_factory=lambda: defaultdict(Counter))
    wrong: list[str] = field(default_factory=list)
    _worker: Worker | None = None

    def run(self, cases: list[Case], check: Callable[[Case, Any], str | None] | None = None) -> None:
        """Run `cases`; `check(case, value)` may judge an accepted value (None: right, else
        what is wrong); by default it must equal `case.expect` when that is given."""
        for case in cases:
            if self._worker is None or not self._worker.alive():
                self._worker = Worker()
            outcome, detail = self._worker.run(case, self.timeout_s)
            if outcome in ("hang", "oom") and self._worker.alive():
                self._worker.kill()
            kind = self.judge(case, outcome, detail, check)
            self.results[case.area][kind] += 1
            if kind not in GOOD:
                self.wrong.append(f"[{case.area}] {case.what}: {kind}: {str(detail)[:300]}")

    @staticmethod
    def judge(case: Case, outcome: str, detail: Any, check: Callable[[Case, Any], str | None] | None) -> str:
        if outcome in ("hang", "oom", "traceback"):
            return outcome
        if outcome == "refused":
            if "\n" in str(detail).strip():
                return "traceback"  # a refusal must be one line
            return "refused right" if case.refuse else "false refusal"
        if case.refuse:
            return "silent"
        problem = check(case, detail) if check is not None else (
            None if case.expect is None or detail == case.expect else f"returned {detail!r}, expected {case.expect!r}")
        return "accepted right" if problem is None else "silent"

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()

    def table(self) -> str:
        """The acceptance table: per area, cases, refused right, accepted right and each wrong kind."""
        head = f"{'area':<22}{'cases':>7}{'refused right':>15}{'accepted right':>16}" + "".join(
            f"{k:>15}" for k in KINDS[2:])
        lines = [f"hostile inputs, seed {self.seed}", head]
        total: Counter = Counter()
        for area, c in sorted(self.results.items()):
            total.update(c)
            lines.append(f"{area:<22}{sum(c.values()):>7}{c['refused right']:>15}{c['accepted right']:>16}"
                         + "".join(f"{c[k]:>15}" for k in KINDS[2:]))
        lines.append(f"{'all':<22}{sum(total.values()):>7}{total['refused right']:>15}{total['accepted right']:>16}"
                     + "".join(f"{total[k]:>15}" for k in KINDS[2:]))
        return "\n".join(lines + self.wrong[:20])

    def n_wrong(self) -> int:
        return sum(c[k] for c in self.results.values() for k in KINDS[2:])
