"""Command-line conventions (issue 14, "Command line"): the parser's command table walked
for help, examples and usage errors; --version; bare `slscan`; one spelling for methods and
output options with the old ones kept as warned aliases; exit codes from one module, and the
README's table of them; progress that reads in a log; `calibrate --from` leaving nothing
behind when it fails."""

from __future__ import annotations

import argparse
import io
import json
import re
import shlex
import shutil
import subprocess
import sys
import tomllib
from contextlib import redirect_stderr
from pathlib import Path

import pytest
from cli_support import run
from session_support import small_rig_toml
from station_support import DEMO_PROGRAM, station_config

from calibration.errors import CalibrationRejected
from scanner.errors import ConfigError, DeviceTimeout, FrameDropped, ScannerError
from slscan import cli
from slscan.exit_codes import Exit, for_error
from slscan.progress import ProgressLine

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = cli.commands(cli.build_parser())


def test_the_command_table_is_complete() -> None:
    names = set(COMMANDS)
    assert {"scan", "decode", "demo", "review", "export", "calibrate", "inspect", "station", "results",
            "devices lightcrafter-images"} <= names


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_help_has_an_example_and_every_option_help(name: str) -> None:
    code, out, _ = run(*name.split(), "--help")
    assert code == 0
    examples = out.split("examples:\n", 1)
    assert len(examples) == 2, f"slscan {name} --help has no examples"
    assert re.search(rf"^  slscan {re.escape(name)}\b", examples[1], re.M), f"no `slscan {name}` example"
    for action in COMMANDS[name]._actions:
        assert action.help, f"slscan {name}: {action.option_strings or action.dest} has no help text"
    for line in re.findall(rf"^  (slscan {re.escape(name)}\b.*)$", examples[1], re.M):
        command = re.split(r"\s{2,}", line)[0]  # an example may end with a note after two spaces
        err = io.StringIO()
        with redirect_stderr(err):
            cli.build_parser().parse_args(shlex.split(command)[1:])  # the example's options exist as written
        assert "deprecated" not in err.getvalue(), command


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_refuses_an_unknown_option_with_exit_2(name: str) -> None:
    code, _, err = run(*name.split(), "--no-such-option")
    assert code == Exit.USAGE == 2
    assert err.startswith("usage: slscan") and "error:" in err  # the option, or a missing argument, named


def test_bare_slscan_prints_the_help_and_exits_0() -> None:
    code, out, err = run()
    assert code == 0 and err == ""
    assert out.startswith("usage: slscan") and "exit codes:" in out
    for name in ("scan", "export", "review", "station"):
        assert f"\n    {name} " in out


def test_version_names_the_package_and_the_checkout() -> None:
    code, out, _ = run("--version")
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert code == 0 and out.startswith(f"slscan {pyproject['project']['version']}")
    git = shutil.which("git") and subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty", "--tags"],
                                                 capture_output=True, text=True)
    if git and git.returncode == 0:
        assert f"(git {git.stdout.strip()})" in out


def parse(*argv: str) -> tuple[argparse.Namespace, str]:
    err = io.StringIO()
    with redirect_stderr(err):
        args = cli.build_parser().parse_args(list(argv))
    return args, err.getvalue()


def test_one_spelling_for_methods_the_old_one_warned() -> None:
    args, err = parse("pose", "s", "--part", "p.toml")
    assert args.method == "sac-ia" and err == ""
    args, err = parse("pose", "s", "--part", "p.toml", "--method", "sacia")
    assert args.method == "sac-ia" and "'sacia' is deprecated; use 'sac-ia'" in err
    args, err = parse("register", "a", "b", "--coarse", "sacia")
    assert args.coarse == "sac-ia" and "deprecated" in err
    args, _ = parse("bench", "pose", "--methods", "sacia", "ndt")
    assert args.methods == ["sac-ia", "ndt"]
    assert "sacia" not in cli.commands(cli.build_parser())["pose"].format_help()


def test_output_options_are_out_the_old_names_warned() -> None:
    args, err = parse("station", "prog.toml", "--data", "d")
    assert args.out == "d" and "--data is deprecated; use --out" in err
    args, err = parse("station", "prog.toml", "--out", "d")
    assert args.out == "d" and err == ""
    args, err = parse("results", "--csv", "r.csv")
    assert args.csv is True and args.out == "r.csv" and "--csv --out r.csv" in err
    args, err = parse("results", "--report", "--out", "rep")
    assert args.report is True and args.out == "rep" and err == ""
    for name, command in COMMANDS.items():  # no output folder under another visible name
        shown = {s for a in command._actions if a.help != argparse.SUPPRESS for s in a.option_strings}
        assert not {"--output", "--report-dir", "--out-dir"} & shown, name


@pytest.mark.parametrize("error, code", [
    (FrameDropped("camera sim", "frame 3 was dropped", 3, 4), 3),
    (DeviceTimeout("trigger box", "no reply", 1.0), 3),
    (CalibrationRejected("camera RMS 0.9 px > 0.5 px"), 1),
    (ConfigError("rig.toml", "rig.driver", "required key is missing"), 2),
    (ScannerError("a refused input"), 2),
    (KeyboardInterrupt(), 130),
])
def test_errors_map_to_the_documented_exit_codes(error: BaseException, code: int) -> None:
    assert for_error(error) == code


def test_readme_documents_every_exit_code() -> None:
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Exit codes", 1)
    assert len(section) == 2, "README has no '## Exit codes' section"
    table = section[1].split("\n## ", 1)[0]
    for code in Exit:
        assert re.search(rf"^\| {int(code)} \|", table, re.M), f"README's exit code table lacks {int(code)}"


def test_a_device_fault_in_a_command_exits_3(monkeypatch: pytest.MonkeyPatch) -> None:
    from slscan.commands import devices

    def unplugged(probe: bool) -> list[str]:
        raise DeviceTimeout("serial /dev/ttyACM0", "no reply to PING", 1.0)

    monkeypatch.setattr(devices, "serial_ports", unplugged)
    code, _, err = run("devices", "--probe")
    assert code == 3 and "Traceback" not in err
    assert "serial /dev/ttyACM0: device timeout: no reply to PING after 1 s" in err


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class LogStream(io.StringIO):
    def isatty(self) -> bool:
        return False


def test_progress_in_a_log_is_one_line_per_stage_start_and_finish() -> None:
    clock, log = Clock(), LogStream()
    progress = ProgressLine(log, clock)
    for k in range(24):  # a counted stage, as capture reports
        clock.t += 0.5
        progress("capture", k + 1, 24)
    for stage, seconds in (("load", 0.25), ("decode", 1.5), ("write", 0.75)):  # 0/1 stages, as the pipeline's
        progress(stage, 0, 1)
        clock.t += seconds
    progress("done", 1, 1)
    assert log.getvalue().splitlines() == [
        "capture     started, 24 steps",
        "capture     finished 24/24 steps in 11.50 s",
        "load        started",
        "load        finished in 0.25 s",
        "decode      started",
        "decode      finished in 1.50 s",
        "write       started",
        "write       finished in 0.75 s",
        "done        all stages in 14.50 s",
    ]
    assert "0/1" not in log.getvalue()


def test_calibrate_from_a_bad_folder_leaves_no_output_folder(tmp_path: Path) -> None:
    captures, out = tmp_path / "captures", tmp_path / "cal"
    captures.mkdir()  # no capture.json: refused
    code, _, err = run("calibrate", "--from", str(captures), "--out", str(out))
    assert code == 2 and "capture" in err
    assert not out.exists()
    out.mkdir()  # an empty folder the user made stays, empty
    code, _, err = run("calibrate", "--from", str(captures), "--out", str(out))
    assert code == 2 and "not empty" not in err  # the retry is not refused for the first run's leftovers
    assert out.is_dir() and not any(out.iterdir())


def test_the_station_exits_1_after_a_failed_part(tmp_path: Path) -> None:
    """The simulated station's second part carries a defect that fails its program (the
    simulator's truth as the gauge, a 320 x 256 camera): one good part exits 0, two exit 1."""
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir(), two.mkdir()
    code, out, _ = run("station", str(DEMO_PROGRAM), "--config", str(station_config(one)), "--auto", "--parts", "1")
    assert code == 0 and "1 parts: 1 pass" in out
    code, out, err = run("station", str(DEMO_PROGRAM), "--config", str(station_config(two)), "--auto", "--parts", "2")
    assert code == 1 and "2 parts: 1 pass, 1 fail" in out
    code, out, err = run("station", str(DEMO_PROGRAM), "--config", str(station_config(two)), "--auto", "--parts", "1",
                         "--json")  # the same station again, for a cell: one JSON document, the lines on stderr
    doc = json.loads(out)
    assert code == 0 and doc["counts"]["pass"] == 1 and "1 parts: 1 pass" in err
    assert doc["status"] == "ok"  # what the exit code says
    code, out, _ = run("results", "--config", str(station_config(two)), "--json")
    stored = json.loads(out)["results"]
    assert code == 0 and [r["status"] for r in stored] == ["pass", "fail", "pass"]
    assert stored[2]["serial"] == doc["results"][0]["serial"] and stored[1]["values"]


def test_progress_on_a_terminal_is_one_live_line_per_stage() -> None:
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    clock, term = Clock(), Terminal()
    progress = ProgressLine(term, clock)
    for k in range(4):
        clock.t += 1.0
        progress("capture", k + 1, 4)
    progress("decode", 0, 1)
    clock.t += 2.0
    progress("done", 1, 1)
    lines = term.getvalue().split("\n")
    assert lines[0].split("\r")[-1].rstrip() == "capture     finished 4/4 steps in 3.00 s"  # the bar, then its summary
    assert "[####################] 4/4" in lines[0]
    assert lines[1].split("\r")[-1].rstrip() == "decode      finished in 2.00 s"
    assert lines[2].split("\r")[-1].rstrip() == "done        all stages in 6.00 s" and lines[3] == ""


def test_parts_judged_together_exit_by_their_worst_decision() -> None:
    """README "Exit codes": any part failing 1, else any without a decision 4, else 0."""
    from slscan.exit_codes import for_parts, for_verdict

    assert for_parts(["pass", "pass"]) == Exit.OK and for_parts([]) == Exit.OK
    assert for_parts(["pass", "uncertain", "fail"]) == Exit.FAILED
    assert for_parts(["pass", "uncertain"]) == for_parts(["error"]) == for_parts(["aborted"]) == Exit.NO_DECISION
    assert [for_verdict(v) for v in ("conforming", "no tolerances", "non-conforming", "uncertain", "not measured")] \
        == [0, 0, 1, 4, 4]


@pytest.mark.parametrize("group", [None, "bench"])
def test_the_command_table_names_what_each_module_registers(group: str | None) -> None:
    """slscan.commands.COMMANDS (and BENCHES, `slscan bench NAME`): each module registers
    exactly the commands the table gives it."""
    from slscan.commands import modules, table

    package = "slscan.commands." + (f"{group}." if group else "")
    for module in modules(group):
        parser = argparse.ArgumentParser()
        module.register(cli._Summarised(parser.add_subparsers(), table(group)))
        registered = set(cli.commands(parser)) - {n for n in cli.commands(parser) if " " in n}
        assert registered == {n for n, (m, _) in table(group).items() if package + m == module.__name__}


def test_the_benches_are_one_group_and_their_old_names_are_refused() -> None:
    """`slscan --help` lists the user's commands and one `bench` entry; a bench's former
    top-level name is refused with one line naming the new form (exit 2); the former
    `slscan bench` (the decode benchmark) given its options is told to name a bench."""
    from slscan.commands import BENCHES, MOVED

    code, out, _ = run("--help")
    assert code == 0 and "\n    bench " in out and not any(f"\n    {old} " in out for old in MOVED if old != "bench")
    code, out, _ = run("bench")
    assert code == 0 and all(f"\n    {name} " in out for name in BENCHES)
    code, _, err = run("-v", "simbench", "--repeats", "1")
    assert code == 2 and err.strip().splitlines() == ["slscan: error: `slscan simbench` is now `slscan bench sim` "
                                                      "(slscan bench --help lists the benches)"]
    code, _, err = run("bench", "--width", "320")
    assert code == 2 and "`slscan bench decode`" in err.strip().splitlines()[-1]


def test_coverage_is_the_users_command_and_its_bench_form_is_refused() -> None:
    """`slscan coverage` (issue 27's command) is listed among the user's commands, not the
    benches; `slscan bench coverage` is refused with one line naming it (exit 2)."""
    code, out, _ = run("--help")
    assert code == 0 and "\n    coverage " in out
    code, out, _ = run("bench")
    assert code == 0 and "\n    coverage " not in out
    code, _, err = run("bench", "coverage", "--case", "plate-sq", "--scans", "1", "--seed", "1")
    assert code == 2 and err.strip().splitlines() == ["slscan: error: `slscan bench coverage` is now `slscan coverage` "
                                                      "(slscan --help lists the commands)"]


@pytest.mark.parametrize("argv", [["--version"], ["--help"], [], ["scan", "--bogus"], ["nosuchcommand"]])
def test_startup_imports_no_command_module_until_one_runs(argv: list[str]) -> None:
    """`--version`, `--help` and usage errors are answered before any command module (and the
    numeric libraries they bring) is imported; a usage error of a command imports its own only."""
    probe = ("import sys\nfrom slscan import cli\ntry:\n    cli.main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in sys.modules if m.startswith('slscan.commands.') or m in ('numpy', 'cv2')))")
    out = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True, text=True, timeout=60).stdout
    loaded = eval(out.strip().splitlines()[-1])
    commands = [m for m in loaded if m.startswith("slscan.")]
    assert commands == ["slscan.commands.scan"] if argv[:1] == ["scan"] else loaded == [], loaded


def test_every_command_reads_its_arguments_before_any_heavy_import() -> None:
    """A usage error of every command in `slscan.commands.COMMANDS` and `BENCHES` (an unknown option) is
    answered with its own module imported but not numpy, OpenCV or Open3D: the command
    modules import those inside their command functions. One process tries them in turn,
    naming the first command whose parser brought one in."""
    from slscan.commands import BENCHES, COMMANDS

    names = [*COMMANDS, *(f"bench/{name}" for name in BENCHES)]
    probe = ("import sys\nfrom slscan import cli\n"
             "for name in sys.argv[1:]:\n    try:\n        cli.main([*name.split('/'), '--no-such-option'])\n"
             "    except SystemExit as exc:\n        assert exc.code == 2, (name, exc.code)\n"
             "    print(name, *sorted(m for m in ('numpy', 'cv2', 'open3d', 'OCP') if m in sys.modules))\n")
    proc = subprocess.run([sys.executable, "-c", probe, *names], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [line.split() for line in proc.stdout.splitlines()]
    assert [line[0] for line in lines] == names
    heavy = [line for line in lines if len(line) > 1]
    assert not heavy, f"slscan {heavy[0][0]} --no-such-option imported {heavy[0][1:]}"


def test_light_names_agree_with_the_modules_they_stand_for() -> None:
    """Names the command line reads without importing numpy match the registries they mirror."""
    from scanner.exports import FORMATS
    from slscan.commands.export import FORMATS as COMMAND_LINE_FORMATS
    from slscan.station import MEASUREMENT_NAMES
    from slscan.station.measure import MEASUREMENTS

    assert COMMAND_LINE_FORMATS == FORMATS and tuple(MEASUREMENTS) == MEASUREMENT_NAMES


def test_quiet_and_log_file(tmp_path: Path, capsys) -> None:
    """-q: errors only, no progress lines; --log-file: info and up in the file while stderr keeps
    its level; an unwritable log file is a usage error of one line."""
    import logging

    from slscan.progress import ProgressLine

    log = tmp_path / "slscan.log"
    args = cli.build_parser(["devices"]).parse_args(["devices", "--log-file", str(log)])
    handler = cli.configure_logging(args)
    try:
        logging.getLogger("slscan.test").info("an info line for the file")
        logging.getLogger("slscan.test").debug("a debug line for nobody")
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()
    assert "INFO slscan.test: an info line for the file" in log.read_text() and "debug" not in log.read_text()
    assert "an info line" not in capsys.readouterr().err
    quiet = cli.build_parser(["devices"]).parse_args(["-q", "devices"])
    assert cli.log_level(quiet) == logging.ERROR
    try:
        cli.configure_logging(quiet)
        ProgressLine()("load", 0, 1)
        assert capsys.readouterr().err == ""
    finally:
        ProgressLine.quiet = False
    code, _, err = run("devices", "--log-file", str(tmp_path / "no" / "such.log"))
    assert code == 2 and err.strip().endswith("cannot write: No such file or directory") and len(err.split("\n")) <= 3


def test_json_alone_on_stdout_whatever_libraries_write_there(tmp_path: Path) -> None:
    """`slscan scan --json` and `decode --json` as a cell runs them (a pipe): stdout parses as one
    JSON document, although a native library writes to the stdout descriptor meanwhile (as
    Open3D does its warnings); the scan's own lines go to stderr."""
    rig = small_rig_toml(tmp_path)
    noisy = ("import os, sys\nfrom slscan import cli\nimport scanner.pipeline as p\nwrite = p.write_json\n"
             "def loud(*a, **k):\n    os.write(1, b'[Open3D WARNING] a library line on fd 1\\n')\n"
             "    return write(*a, **k)\np.write_json = loud\nsys.exit(cli.main(sys.argv[1:]))\n")
    for argv in (["scan", "--rig", str(rig), "--out", str(tmp_path / "s"), "--json"],
                 ["decode", str(tmp_path / "s"), "--json"]):
        proc = subprocess.run([sys.executable, "-c", noisy, *argv], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        doc = json.loads(proc.stdout)  # one document, nothing else
        assert doc["status"] == "ok" and doc["points"] > 1000 and Path(doc["cloud"]).is_file()
        assert doc["accuracy"]["rms_mm"] < 0.1 and {c["name"] for c in doc["checks"]} >= {"phase_residual"}
        assert "a library line on fd 1" in proc.stderr


@pytest.mark.parametrize("command", ["demo", "scan"])
def test_a_used_output_folder_is_refused_before_the_slow_start(command: str, tmp_path: Path) -> None:
    """`demo` and `scan` into a folder that holds something: one line and exit 2 before the
    rig opens, the CAD loads or Open3D is imported (it took 79 s of a demo before)."""
    (tmp_path / "earlier.txt").write_text("an earlier session")
    probe = ("import sys\nfrom slscan import cli\ncode = cli.main(sys.argv[1:])\n"
             "print(code, 'open3d' in sys.modules, 'OCP' in sys.modules)")
    p = subprocess.run([sys.executable, "-c", probe, command, "--out", str(tmp_path)], capture_output=True,
                       text=True, timeout=120)
    assert p.stdout.split() == ["2", "False", "False"], p.stderr
    assert "output folder exists and is not empty" in p.stderr and (tmp_path / "earlier.txt").exists()


@pytest.mark.parametrize("verbose", [[], ["-v"]])
def test_dask_and_open3d_log_at_the_level_asked(verbose: list[str]) -> None:
    """Dask's INFO lines (35 in a default `slscan batch` before) and Open3D's warnings (on
    stdout) show only from -v on; Dask's go through our log format. The command here is
    `slscan devices` with the libraries imported after the command line set the levels,
    as a command imports them."""
    probe = ("import logging, sys\nfrom slscan import cli\nfrom slscan.commands import devices\n"
             "def run(args):\n    import distributed, open3d\n"
             "    logging.getLogger('distributed.scheduler').info('a dask info line')\n"
             "    open3d.io.read_triangle_mesh('/nonexistent/mesh.stl')\n    return 0\n"
             "devices.cmd_devices = run\nsys.exit(cli.main(sys.argv[1:]))\n")
    proc = subprocess.run([sys.executable, "-c", probe, *verbose, "devices"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    shown = bool(verbose)
    assert ("INFO distributed.scheduler: a dask info line" in proc.stderr) == shown, proc.stderr
    assert ("[Open3D WARNING]" in proc.stdout) == shown, proc.stdout


def test_json_stdout_keeps_open3d_lines_off_the_document() -> None:
    """Open3D prints its warnings through Python's `sys.stdout` (pybind11), which `--json`
    points at the real stdout for the command's document: its lines go to stderr, whole."""
    probe = ("from slscan import cli\nimport open3d\n"
             "open3d.utility.set_verbosity_level(open3d.utility.VerbosityLevel.Warning)\n"
             "with cli.json_stdout():\n    open3d.io.read_triangle_mesh('/nonexistent/mesh.stl')\n"
             "    print('{\"status\": \"ok\"}')\n")
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert json.loads(proc.stdout) == {"status": "ok"}
    assert "[Open3D WARNING]" in proc.stderr and proc.stderr.endswith("\n")


def test_paper_chosen_on_the_command_line_sizes_the_pdf(tmp_path: Path) -> None:
    """`--paper a4|letter` on the commands that print a PDF report (inspect, demo): held
    around the report's writing, it sets the PDF's page size (points: A4 595 x 842, Letter
    612 x 792, read from the PDF's MediaBox)."""
    from inspection.report_pdf import chromium, print_pdf
    from slscan.options import on_paper

    for command in (["inspect", "session"], ["demo"]):
        assert cli.build_parser(command).parse_args([*command, "--paper", "letter"]).paper == "letter"
        assert cli.build_parser(command).parse_args(command).paper == "a4"
    code, _, err = run("demo", "--paper", "legal")
    assert code == 2 and "invalid choice: 'legal'" in err
    if chromium() is None:
        pytest.skip("no Chromium: the PDF's size is not checked")
    page = tmp_path / "page.html"
    page.write_text("<html><head></head><body><h1>a report</h1></body></html>")
    for paper, size in (("letter", (612, 792)), ("a4", (595, 842))):
        with on_paper(paper):
            pdf = print_pdf(page, tmp_path / f"{paper}.pdf")
        assert pdf is not None
        boxes = re.findall(rb"/MediaBox \[0 0 ([0-9.]+) ([0-9.]+)\]", pdf.read_bytes())
        assert boxes and all(abs(float(w) - size[0]) < 1.5 and abs(float(h) - size[1]) < 1.5 for w, h in boxes), boxes


@pytest.mark.parametrize("command", [["batch"], ["bench", "batch"]])
def test_a_part_folder_that_is_not_there_is_bad_input(command: list[str], tmp_path: Path) -> None:
    """`batch` and `bench batch` given a folder that does not exist: one line and exit 2
    before any work (a folder that exists but cannot be measured is that part's error)."""
    code, _, err = run(*command, str(tmp_path / "no-such-part"), "--program", "config/parts/demo_part.toml")
    assert code == 2 and err.strip().endswith("no-such-part: no such part or session folder"), err
