"""The operator screen through a real pseudo-terminal: keys in, screen text out.

`pexpect` runs `slscan station` in a pty; `pyte` (a VT100/xterm emulator) replays what the
program writes into rows of text, so the test reads the screen the operator sees. The
measuring step is the simulator's truth (`measure.SimulatorTruth`)."""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path

import pexpect
import pyte
from station_support import DEMO_PROGRAM, program_copy, station_config

from slscan.station.results import open_results
from slscan.station.station_config import StationConfig

ROWS, COLS = 40, 140
TESTS = Path(__file__).resolve().parent


class Terminal:
    """`slscan ...` in a pseudo-terminal, its screen kept up to date."""

    def __init__(self, *args: str) -> None:
        path = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")])
        # the pty's size, not COLUMNS/LINES inherited from the test run (pytest-xdist's workers set 80 x 24)
        env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
        env.update(TERM="xterm", PYTHONPATH=path)
        self.child = pexpect.spawn(sys.executable, ["-m", "slscan.cli", *args], env=env, dimensions=(ROWS, COLS),
                                   encoding="utf-8", codec_errors="replace")
        self.screen = pyte.Screen(COLS, ROWS)
        self.stream = pyte.Stream(self.screen)

    def pump(self, seconds: float = 0.05) -> None:
        try:
            while True:
                self.stream.feed(self.child.read_nonblocking(65536, timeout=seconds))
        except pexpect.TIMEOUT:
            pass

    def text(self) -> str:
        return "\n".join(line.rstrip() for line in self.screen.display)

    def wait(self, pattern: str, timeout_s: float = 60) -> str:
        """The screen text once `pattern` (a regex) is on it."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.pump()
            text = self.text()
            if re.search(pattern, text):
                return text
        raise AssertionError(f"not on the screen after {timeout_s} s: {pattern!r}\n{self.text()}")

    def keys(self, text: str) -> None:
        self.child.send(text)


def test_operator_screen_keys_in_screen_text_out(tmp_path: Path) -> None:
    cfg = station_config(tmp_path)
    term = Terminal("station", str(DEMO_PROGRAM), "--config", str(cfg), "--operator", "ana")
    try:
        screen = term.wait(r"READY\s+part 1\s+serial: \(none\)\s+operator: ana")
        assert "calibration  factory-sim-bench (undated, does not expire" in screen
        assert "measuring    simulator-truth: ready" in screen
        assert "[s]/Enter scan" in screen and "REFUSING" not in screen

        term.keys("e")
        term.wait(r"enter serial, Enter to accept")
        term.keys("SN-0042\r")
        term.wait(r"READY\s+part 1\s+serial: SN-0042")
        term.keys("s")
        screen = term.wait(r"LAST  SN-0042 \(attempt 1\): PASS")
        assert re.search(r"high_top_flatness\s+0\.0000 mm\s+<= 0\.050\s+ok", screen)
        assert "RUNNING STATISTICS  1 parts, 1 pass, 0 fail, 0 uncertain, 0 not measured, yield 100.0 %" in screen

        term.keys("n")  # the next part: the simulator brings the part with a 150 um bow
        term.keys("SN-0043\r")
        term.wait(r"READY\s+part 2\s+serial: SN-0043")
        term.keys("\r")
        screen = term.wait(r"LAST  SN-0043 \(attempt 1\): FAIL - out of tolerance: high_top_flatness")
        assert re.search(r"high_top_flatness\s+0\.1500 mm\s+<= 0\.050\s+OUT", screen)
        assert "2 parts, 1 pass, 1 fail" in screen and "yield 50.0 %" in screen

        term.keys("r")  # re-scan, aborted while it runs: the earlier result stays
        term.wait(r"BUSY")
        term.keys("a")
        screen = term.wait(r"LAST  SN-0043 \(attempt 2\): ABORTED - aborted by the operator")
        assert "2 parts, 1 pass, 1 fail" in screen
        term.keys("q")
        term.child.expect(pexpect.EOF, timeout=30)
    finally:
        term.child.close(force=True)
    assert term.child.exitstatus == 0
    with open_results(StationConfig.load(cfg).database_url) as store:
        assert [(r.serial, r.attempt, r.status, r.operator) for r in store.results()] == [
            ("SN-0042", 1, "pass", "ana"), ("SN-0043", 1, "fail", "ana"), ("SN-0043", 2, "aborted", "ana")]


def test_operator_screen_shows_a_mismatched_calibration_and_refuses_to_scan(tmp_path: Path) -> None:
    cfg = station_config(tmp_path)
    program = program_copy(tmp_path, ('id = "factory-sim-bench"', 'id = "sim-bench@2026-10-01T08:00:00"'))
    term = Terminal("station", str(program), "--config", str(cfg))
    try:
        screen = term.wait(r"REFUSING TO MEASURE: calibration mismatch")
        assert ("program.toml expects calibration.id 'sim-bench@2026-10-01T08:00:00', the rig has "
                "'factory-sim-bench'") in " ".join(screen.split())  # the whole reason, wrapped on the screen
        term.keys("eSN-1\rs")
        term.wait(r"REFUSED: calibration mismatch")
        term.keys("q")
        term.child.expect(pexpect.EOF, timeout=30)
    finally:
        term.child.close(force=True)
    with open_results(StationConfig.load(cfg).database_url) as store:
        assert store.results() == []
    assert not (tmp_path / "data" / "sessions").exists()


def test_without_a_terminal_the_station_says_to_use_auto(tmp_path: Path) -> None:
    import subprocess

    env = {**os.environ, "PYTHONPATH": str(TESTS)}
    p = subprocess.run([sys.executable, "-m", "slscan.cli", "station", str(DEMO_PROGRAM), "--config",
                        str(station_config(tmp_path))], env=env, stdin=subprocess.DEVNULL, capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2 and "needs a terminal; use --auto --parts N" in p.stderr
