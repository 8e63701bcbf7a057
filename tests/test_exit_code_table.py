"""The table "command x exit code" of issue 28: each command that judges parts run on a
conforming part, a non-conforming one, one not measured (or uncertain: no decision) and on bad
input, every cell a real run on the simulated bench (small camera where the command allows),
asserted against the README's "Exit codes" table and written to the test's folder and the
-s output:

    pytest -m slow -s tests/test_exit_code_table.py

A command is one row of `ROWS`: a case it cannot produce (the demo scans the bundled nominal
part only) is a cell with the reason instead of a run; a case whose code the README gives in
other words (`register`: "a pose not proven" is its failing case, exit 1)
is a run with those words.

The table's test is `acceptance` and `slow`: its runs take about ten minutes together on two
loaded cores (a demo, five inspections, a whole verification of 23 positions)."""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from registration_support import box_step, moved_view, write_ply
from session_support import small_rig_toml
from station_support import DEMO_PROGRAM, TRUTH_GAUGE, program_copy, station_config

from scanner.config import CONFIG_DIR, DEFAULT_RIG
from slscan import cli

CASES = ("conforming", "non-conforming", "not measured", "bad input")
MPES = ("PF", "PS", "SD", "F", "OL")  # the rig file's [acceptance.mpe] parameters
README = Path(__file__).resolve().parent.parent / "README.md"


def documented_code(words: str) -> int:
    """The one exit code whose meaning in the README's "Exit codes" table holds `words`."""
    section = README.read_text().split("## Exit codes", 1)[1].split("\n## ", 1)[0]
    rows = {int(code): meaning for code, meaning in re.findall(r"^\| (\d+) \| (.+) \|$", section, re.M)}
    found = [code for code, meaning in rows.items() if words in meaning]
    assert len(found) == 1, (words, found)
    return found[0]


def documented_codes() -> dict[str, int]:
    """The exit code the README's "Exit codes" table gives each case, found by its wording."""
    words = {"conforming": "success", "non-conforming": "a check fails", "not measured": "not measured",
             "bad input": "usage error"}
    return {case: documented_code(word) for case, word in words.items()}


@dataclass
class Bench:
    """The inputs the runs share, made as the runs go (the station's run stores the parts the
    batch and the inspections read)."""

    tmp: Path
    monkeypatch: pytest.MonkeyPatch
    rig: Path
    station: Path

    def parts(self) -> list[Path]:
        """The parts the station's non-conforming run stored: a nominal one, then one bowed 150 um."""
        parts = sorted((self.tmp / "stored" / "sessions").glob("*/*"))
        assert len(parts) == 2, parts
        return parts

    def program(self, name: str, edit: tuple[str, str] | None = None, all_tolerances: str | None = None) -> str:
        """The demo program copied into its own folder, with `edit` applied or every tolerance set."""
        folder = self.tmp / f"program-{name}"
        folder.mkdir(exist_ok=True)
        path = program_copy(folder, edit)
        if all_tolerances is not None:
            path.write_text(re.sub(r"^tolerance_mm = [0-9.]+", f"tolerance_mm = {all_tolerances}", path.read_text(),
                                   flags=re.M))
        return str(path)

    def base_program(self) -> str:
        """The demo program asking also for the flatness of the base (#711), which lies on the
        bench and no view sees: that characteristic is not measured, whatever the noise."""
        folder = self.tmp / "program-base"
        folder.mkdir(exist_ok=True)
        path = program_copy(folder)
        path.write_text(path.read_text() + '\n[[characteristic]]\nname = "base_flatness"\nface = "#711"\n'
                        'kind = "flatness"\nmethod = "minimum_zone"\ntolerance_mm = 0.05\n')
        return str(path)

    def random_part_view(self) -> tuple[str, str]:
        """(cloud, STEP) of a generated part (seed 11) seen from a random start: a view whose
        pose its evidence proves (tests/test_registration_proof.py)."""
        from inspection.cad import load_cad
        from sim.random_parts import random_part

        step = random_part(11).write(self.tmp / "part.step")
        scan, _ = moved_view(load_cad(step), (0.3, -0.2), seed=7)
        return str(write_ply(scan, self.tmp / "part.ply")), str(step)

    def block_view(self) -> tuple[str, str]:
        """(cloud, STEP) of a plain block from above: its half turn fits as well (ambiguous)."""
        from inspection.cad import load_cad

        step = box_step(self.tmp / "block.step")
        scan, _ = moved_view(load_cad(step), (0.35, 0.2), seed=3)
        return str(write_ply(scan, self.tmp / "block.ply")), str(step)

    def artefacts(self) -> str:
        """The bench's flat artefact alone (six positions: a complete test of that set, quick)."""
        text = (CONFIG_DIR / "artefacts" / "sim_bench.toml").read_text()
        path = self.tmp / "plane.toml"
        path.write_text('name = "plane alone"\n\n[plane]' + text.split("[plane]", 1)[1].split("\n[", 1)[0] + "\n")
        return str(path)

    def rig_with_mpes(self, name: str, mpe_mm: float, parameters: tuple[str, ...] = MPES) -> str:
        """The bench rig with the MPEs of `parameters` set to `mpe_mm`: far above what the
        simulated rig reads (a conforming test) or far below (non-conforming)."""
        text = DEFAULT_RIG.read_text().replace('artefacts = "../artefacts/', f'artefacts = "{CONFIG_DIR}/artefacts/')
        text = text.replace('patterns = "../patterns/', f'patterns = "{CONFIG_DIR}/patterns/')
        for p in parameters:
            text, n = re.subn(rf"^{p}_mm = [0-9.]+", f"{p}_mm = {mpe_mm}", text, flags=re.M)
            assert n == 1, p
        path = self.tmp / f"rig_{name}.toml"
        path.write_text(text)
        return str(path)


Run = Callable[[Bench], list[str]]
Cell = Run | str | tuple[Run, str]  # a run, why the command cannot produce the case, or a run and the README's words


def _station(parts: int, measurement: str, out: str, program: Callable[[Bench], str] = lambda b: str(DEMO_PROGRAM)
             ) -> Run:
    return lambda b: ["station", program(b), "--config", str(b.station), "--out", str(b.tmp / out), "--auto",
                      "--parts", str(parts), "--measurement", measurement]


def _inspect(program: Callable[[Bench], str], name: str, part: int = 0) -> Run:
    return lambda b: ["inspect", str(b.parts()[part] / "view0"), "--tolerances", program(b), "--no-pdf", "--out",
                      str(b.tmp / f"inspect-{name}")]


def _skip_every_position(b: Bench) -> list[str]:
    """An operator who places no artefact: every position not tested (tests/test_verify.py's)."""
    from sim.artefact_scenes import SimArtefactBench

    b.monkeypatch.setattr(SimArtefactBench, "place", lambda self, position: False)
    return ["verify", "--artefacts", b.artefacts(), "--out", str(b.tmp / "verify-skipped")]


ROWS: dict[str, dict[str, Cell]] = {
    "station": {
        "conforming": _station(1, TRUTH_GAUGE, "station-one"),  # the first simulated part is nominal
        "non-conforming": _station(2, TRUTH_GAUGE, "stored"),   # the second is bowed 150 um
        "not measured": _station(1, "inspection", "station-inspected", Bench.base_program),  # the base: unseen
        "bad input": lambda b: ["station", str(b.tmp / "no-such-program.toml"), "--config", str(b.station), "--auto",
                                "--parts", "1"],
    },
    "batch": {
        "conforming": lambda b: ["batch", str(b.parts()[0]), "--program", str(DEMO_PROGRAM), "--workers", "0",
                                 "--measurement", TRUTH_GAUGE],
        "non-conforming": lambda b: ["batch", str(b.parts()[1]), "--program", str(DEMO_PROGRAM), "--workers", "0",
                                     "--measurement", TRUTH_GAUGE],
        "not measured": lambda b: ["batch", str(b.parts()[0]), "--program", b.base_program(), "--workers", "0",
                                   "--measurement", "inspection"],
        "bad input": lambda b: ["batch", str(b.tmp / "no-such-part"), "--program", str(DEMO_PROGRAM), "--workers", "0"],
    },
    "inspect": {
        "conforming": _inspect(lambda b: b.program("wide", all_tolerances="1.0"), "wide"),
        "non-conforming": _inspect(lambda b: b.program("tight-boss", ('kind = "cylindricity"\nmethod = "minimum_zone"\n'
                                                                      'tolerance_mm = 0.05', 'kind = "cylindricity"\n'
                                                                      'method = "minimum_zone"\ntolerance_mm = 0.005')),
                                   "tight"),
        "not measured": _inspect(lambda b: str(DEMO_PROGRAM), "demo"),
        "bad input": lambda b: ["inspect", str(b.tmp / "no-such-session"), "--tolerances", str(DEMO_PROGRAM)],
    },
    "verify": {
        # every artefact: a test passes only when every parameter is measured and conforming
        "conforming": lambda b: ["verify", "--rig", b.rig_with_mpes("wide", 5.0), "--out", str(b.tmp / "verify-wide")],
        "non-conforming": lambda b: ["verify", "--rig", b.rig_with_mpes("strict", 0.0001, ("F",)), "--artefacts",
                                     b.artefacts(), "--out", str(b.tmp / "verify-strict")],
        "not measured": _skip_every_position,
        "bad input": lambda b: ["verify", "--rig", str(b.tmp / "no-such-rig.toml"), "--out", str(b.tmp / "verify-x")],
    },
    "register": {
        "conforming": lambda b: ["register", *b.random_part_view(), "--seed", "2", "--no-isolate"],  # proven
        "non-conforming": "register judges a pose, not a part: a pose not proven is its failing case",
        "not measured": (lambda b: ["register", *b.block_view(), "--no-isolate"], "a pose not proven"),
        "bad input": lambda b: ["register", str(b.tmp / "no-such-cloud.ply"), str(CONFIG_DIR / "parts" /
                                                                                 "demo_part.step")],
    },
    "demo": {
        "conforming": "the demo scans the bundled nominal part only (its boss is not measured from above)",
        "non-conforming": "the demo scans the bundled nominal part only",
        "not measured": lambda b: ["demo", "--out", str(b.tmp / "demo")],
        "bad input": lambda b: ["demo", "--out", str(b.tmp)],  # a folder holding something: refused before the scan
    },
}


def exit_code(argv: list[str]) -> int:
    """`slscan argv` in this process: its exit code (argparse's SystemExit included)."""
    try:
        return int(cli.main(["-q", *argv]))
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 2


@pytest.mark.acceptance
@pytest.mark.slow
def test_exit_codes_of_every_command_and_case(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    expected = documented_codes()
    bench = Bench(tmp_path, monkeypatch, small_rig_toml(tmp_path), station_config(tmp_path))
    got: dict[str, dict[str, int | str]] = {}
    wanted: dict[tuple[str, str], int] = {}  # cells the README gives in other words
    for command, cells in ROWS.items():
        got[command] = {}
        for case in CASES:
            cell = cells[case]
            run, words = cell if isinstance(cell, tuple) else (cell, None)
            got[command][case] = run if isinstance(run, str) else exit_code(run(bench))
            if words is not None:
                wanted[(command, case)] = documented_code(words)
    table = ["| command | " + " | ".join(f"{c} (README: {expected[c]})" for c in CASES) + " |",
             "|---" * (len(CASES) + 1) + "|"]
    table += [f"| {command} | " + " | ".join(str(got[command][c]) if isinstance(got[command][c], int)
                                            else f"n/a: {got[command][c]}" for c in CASES) + " |" for command in ROWS]
    text = "\n".join(table)
    (tmp_path / "exit_codes.md").write_text(text + "\n")
    print("\n" + text)
    wrong = [f"{command} {case}: exit {code}, README {wanted.get((command, case), expected[case])}"
             for command in ROWS for case, code in got[command].items()
             if isinstance(code, int) and code != wanted.get((command, case), expected[case])]
    assert not wrong, "\n".join(wrong) + "\n" + text


def test_the_readme_table_names_one_code_per_case() -> None:
    assert documented_codes() == {"conforming": 0, "non-conforming": 1, "not measured": 4, "bad input": 2}


def test_every_row_has_every_case() -> None:
    assert all(set(cells) == set(CASES) for cells in ROWS.values())
