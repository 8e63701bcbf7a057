"""The operator's full-screen terminal view of the station (stdlib curses).

The view only draws the station's state and turns keys into actions; the cycle itself
(`Station.run_cycle`) runs in a worker thread, so the screen stays live and an abort
takes effect at the next frame. Keys (shown on screen):

    READY    s / Enter / foot switch  scan the part with the serial shown
             e  enter serial number / part id     o  enter operator
             n  next part (new serial)            r  re-scan the last part (new attempt)
             q  quit
    BUSY     a / Esc  abort the cycle (frames kept, stored as aborted)
    ENTRY    type, Backspace, Enter to accept, Esc to cancel

Ctrl-C at any time aborts a running cycle and quits, storing the cycle as aborted.
"""

from __future__ import annotations

import curses
import textwrap
import threading
from dataclasses import dataclass, field
from typing import Any

from scanner.errors import ScannerError
from slscan.station.app import StationRun, outcome_lines
from slscan.station.loop import CycleOutcome
from slscan.station.quality import RunningStats
from slscan.station.results import VERDICTS
from slscan.station.spc import MIN_CAPABILITY_N

POLL_S = 0.1
KEYS_READY = "[s]/Enter scan  [e] serial  [o] operator  [n] next part  [r] re-scan  [q] quit"
KEYS_BUSY = "[a]/Esc abort"


@dataclass
class ViewState:
    """What the screen shows; changed by the UI thread and the worker (under `lock`)."""

    serial: str = ""
    operator: str = ""
    part: int = 0
    mode: str = "READY"  # READY | BUSY | ENTRY
    entry_label: str = ""
    entry_text: str = ""
    progress: str = ""
    message: str = ""
    last: CycleOutcome | None = None
    last_part: int | None = None
    measured: set[str] = field(default_factory=set)  # serials with a verdict in this run
    events: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def event(self, text: str) -> None:
        with self.lock:
            self.events = (self.events + [text])[-5:]


class StationTUI:
    """The curses view over an open `StationRun`; `max_parts` ends the run once that many
    parts (serials) have a verdict."""

    def __init__(self, run: StationRun, max_parts: int | None = None) -> None:
        self.run = run
        self.station = run.station
        self.max_parts = max_parts
        self.state = ViewState(operator=self.station.operator)
        self.cancel = threading.Event()
        self.worker: threading.Thread | None = None
        self.quit = False
        self._status: tuple[list[tuple[str, str]], list[str], RunningStats] | None = None

    def _snapshot(self) -> tuple[list[tuple[str, str]], list[str], RunningStats]:
        """Status lines, refusals and statistics, recomputed after each cycle (not per frame)."""
        if self._status is None:
            self._status = (self.station.status_lines(), self.station.refusals(), self.station.stats())
        return self._status

    # -- actions

    def start(self, serial: str, part: int) -> None:
        st = self.state
        if not serial:
            self.begin_entry("serial")
            return
        reasons = self.station.refusals()
        if reasons:
            st.message = "REFUSED: " + "; ".join(reasons)
            return
        self.cancel.clear()
        self.station.operator = st.operator
        st.mode, st.message, st.progress = "BUSY", "", "starting"
        self.worker = threading.Thread(target=self._cycle, args=(serial, part), daemon=True)
        self.worker.start()

    def _cycle(self, serial: str, part: int) -> None:
        st = self.state

        def progress(stage: str, done: int, total: int) -> None:
            with st.lock:
                st.progress = f"{stage} {done}/{total}"

        try:
            outcome = self.station.run_cycle(serial, part, self.cancel, progress)
            with st.lock:
                st.last, st.last_part = outcome, part
                if outcome.status in VERDICTS:
                    st.measured.add(outcome.serial)
            st.event(f"{outcome.serial} attempt {outcome.attempt}: {outcome.status.upper()} "
                     f"(result {outcome.result_id})")
        except ScannerError as exc:  # refused, or no serial: said on screen
            st.message = str(exc)
        except Exception as exc:  # shown, never a dead screen
            st.message = f"error: {type(exc).__name__}: {exc}"
        finally:
            self._status = None
            self.run.bench.start_pressed()  # a press during the cycle does not start another
            with st.lock:
                st.mode, st.progress = "READY", ""

    def begin_entry(self, what: str) -> None:
        st = self.state
        st.mode, st.entry_label = "ENTRY", what
        st.entry_text = st.serial if what == "serial" else st.operator

    def key(self, ch: int) -> None:
        st = self.state
        if st.mode == "BUSY":
            if ch in (ord("a"), 27):
                self.cancel.set()
                st.message = "aborting at the next frame ..."
            return
        if st.mode == "ENTRY":
            if ch in (10, 13, curses.KEY_ENTER):
                text = st.entry_text.strip()
                if st.entry_label == "serial":
                    st.serial = text
                else:
                    st.operator = text
                st.mode = "READY"
            elif ch == 27:
                st.mode = "READY"
            elif ch in (curses.KEY_BACKSPACE, 127, 8):
                st.entry_text = st.entry_text[:-1]
            elif 32 <= ch < 127 and len(st.entry_text) < 40:
                st.entry_text += chr(ch)
            return
        if ch in (ord("s"), 10, 13, curses.KEY_ENTER):
            self.start(st.serial, st.part)
        elif ch == ord("e"):
            self.begin_entry("serial")
        elif ch == ord("o"):
            self.begin_entry("operator")
        elif ch == ord("n"):
            st.part += 1 if st.last_part == st.part else 0
            st.serial, st.message = "", ""
            self.begin_entry("serial")
        elif ch == ord("r"):
            if st.last is None:
                st.message = "nothing to re-scan yet"
            else:
                self.start(st.last.serial, st.last_part or 0)
        elif ch == ord("q"):
            self.quit = True

    # -- drawing

    def draw(self, scr: Any) -> None:
        st = self.state
        scr.erase()
        h, w = scr.getmaxyx()
        row = 0

        def put(text: str, attr: int = 0, wrap: bool = False) -> None:
            nonlocal row
            lines = textwrap.wrap(text, w - 1, subsequent_indent="    ", break_on_hyphens=False) if wrap else [text]
            for line in lines:
                if row < h - 1:
                    scr.addnstr(row, 0, line, w - 1, attr)
                row += 1

        p = self.station.program
        status, reasons, s = self._snapshot()
        put(f"slscan station - {p.name} v{p.version}   station {self.run.config.name}", curses.A_BOLD)
        for label, text in status:
            put(f"{label:<12} {text}")
        if self.run.bench.input_problem:
            put(f"{'foot switch':<12} {self.run.bench.input_problem}; start with s or Enter", wrap=True)
        put("-" * (w - 1))
        with st.lock:
            if reasons:
                put("REFUSING TO MEASURE: " + "; ".join(reasons), curses.A_BOLD, wrap=True)
            serial = (st.entry_text + "_") if st.mode == "ENTRY" and st.entry_label == "serial" else st.serial
            oper = (st.entry_text + "_") if st.mode == "ENTRY" and st.entry_label == "operator" else st.operator
            put(f"{st.mode:<6} part {st.part + 1}   serial: {serial or '(none)'}   operator: {oper or '(none)'}",
                curses.A_BOLD)
            if st.mode == "ENTRY":
                put(f"enter {st.entry_label}, Enter to accept, Esc to cancel")
            else:
                put(KEYS_BUSY + "   " + st.progress if st.mode == "BUSY" else KEYS_READY)
            if st.message:
                put(st.message, wrap=True)
            put("-" * (w - 1))
            if st.last is not None:
                lines = outcome_lines(p, st.last)
                put("LAST  " + lines[0], curses.A_BOLD)
                for line in lines[1:]:
                    put(line)
                put("-" * (w - 1))
            events = list(st.events)
        put(f"RUNNING STATISTICS  {s.parts} parts, {s.passed} pass, {s.failed} fail, {s.uncertain} uncertain, "
            f"{s.errors} not measured"
            + (f", yield {s.yield_percent:.1f} %" if s.yield_percent is not None else ""))
        for c in s.characteristics:
            if c.n:
                cap = c.capability
                put(f"    {c.name:<22} n {c.n:<4} mean {c.mean_mm:.4f}  max {c.max_mm:.4f}"
                    + (f"  Cpk {cap.cpk.text()}  Ppk {cap.ppk.text()}"
                       + (f" (n {cap.n} < {MIN_CAPABILITY_N}: unreliable)" if cap.warning else "") if cap else ""))
        for e in events:
            put("event  " + e)
        scr.refresh()

    def busy(self) -> bool:
        return self.worker is not None and self.worker.is_alive()

    def tick(self, ch: int) -> bool:
        """One pass of the loop with key `ch` (-1: none): when the station is READY and idle,
        a foot-switch press starts a scan as `s` does. True when the run is over."""
        if ch == -1 and not self.busy() and self.state.mode == "READY" and self.run.bench.start_pressed():
            ch = ord("s")
        if ch != -1:
            self.key(ch)
        done = self.max_parts is not None and len(self.state.measured) >= self.max_parts
        return (self.quit or done) and not self.busy()

    def loop(self, scr: Any) -> None:
        curses.curs_set(0)
        scr.idlok(False)  # plain repaints: no terminal scrolling tricks
        scr.timeout(int(POLL_S * 1000))
        try:
            while True:
                self.draw(scr)
                if self.tick(scr.getch()):
                    self.draw(scr)
                    return
        except KeyboardInterrupt:  # Ctrl-C: abort the cycle (stored as aborted), then quit
            self.cancel.set()
            if self.worker is not None:
                self.worker.join()
            raise


def run_tui(run: StationRun, max_parts: int | None = None) -> int:
    """Run the operator loop full-screen until the operator quits (or `max_parts` are done)."""
    tui = StationTUI(run, max_parts)
    curses.wrapper(tui.loop)
    return 0
