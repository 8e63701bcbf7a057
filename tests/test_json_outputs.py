"""Every command with `--json`, run as a robot cell or a script runs it (a fresh process, stdout
a pipe) on the cheapest valid input, at -v (Dask's INFO lines, Rerun's warnings and Open3D's
warnings all let through) and with an Open3D warning and a native line written to the
stdout descriptor provoked inside the command: the whole stdout parses as one JSON document.

Acceptance (`-m acceptance`): the commands take about five minutes together on two loaded
cores (each 2-40 s); the five whose cheapest run takes a minute or more are also `slow`."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from foreign_capture import CONFIG, PROJ, RIG, shoot, write_frames
from session_support import small_rig_toml
from station_support import DEMO_PROGRAM, TRUTH_GAUGE, station_config

from scanner.config import CONFIG_DIR
from sim.foreign_patterns import slmaster_complementary
from slscan import cli
from slscan.commands.bench.import_ import write_slmaster_calibration

STEP = CONFIG_DIR / "parts" / "demo_part.step"
NOISY = """\
import os, sys
from slscan import cli

run = cli._run


def noisy(args):
    command = args.func

    def provoked(a):
        import open3d  # at -v its warnings are on: one on the stdout descriptor, as in a registration

        open3d.io.read_triangle_mesh("/nonexistent/provoked.stl")
        os.write(1, b"[a native library] a line on the stdout descriptor\\n")
        return command(a)

    args.func = provoked
    return run(args)


cli._run = noisy
sys.exit(cli.main(sys.argv[1:]))
"""


@dataclass(frozen=True)
class Inputs:
    """What the commands read, made once: a small rig and a scan with it, a station folder
    with one stored part, a simulated bin scan."""

    tmp: Path
    rig: Path
    session: Path
    station: Path
    part: Path
    bin_session: Path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Inputs:
    tmp = tmp_path_factory.mktemp("json")
    rig = small_rig_toml(tmp)
    session, bins = tmp / "session", tmp / "bin"
    assert cli.main(["-q", "scan", "--rig", str(rig), "--out", str(session)]) == 0
    assert cli.main(["-q", "scan", "--rig", str(rig), "--scene", "bin:0:5", "--out", str(bins)]) == 0
    station = station_config(tmp, rig=rig)
    assert cli.main(["-q", "station", str(DEMO_PROGRAM), "--config", str(station), "--auto", "--parts", "1",
                     "--measurement", TRUTH_GAUGE]) in (0, 1)
    [part] = (tmp / "data" / "sessions").glob("*/*")
    return Inputs(tmp, rig, session, station, part, bins)


def _import_frames(i: Inputs) -> list[str]:
    """SLMaster's complementary capture of a plane as BMP files, with its calibration (`foreign_capture`)."""
    frames = i.tmp / "frames"
    if not frames.exists():
        stack = shoot(slmaster_complementary(PROJ[0]), seed=9)
        write_frames(frames, stack, [f"{k + 1}.bmp" for k in range(len(stack))])
        write_slmaster_calibration(i.tmp / "caliInfo.yml", RIG)
    return [str(frames), "--patterns", str(CONFIG / "slmaster_complementary_12x32.toml"), "--projector-size",
            f"{PROJ[0]}x{PROJ[1]}", "--calibration", str(i.tmp / "caliInfo.yml")]


def _labels(i: Inputs) -> list[str]:
    labels = i.tmp / "labels.npy"
    if not labels.exists():
        assert cli.main(["-q", "segment", str(i.session), "--out", str(labels), "--no-log"]) == 0
    return [str(labels), str(i.session / "ground_truth.npz")]


def _cloud(i: Inputs) -> str:
    return str(i.session / "outputs" / "cloud.ply")


SLOW = {"verify", "bench demo", "bench binocular", "bench views", "bench batch"}  # 50-110 s each on two loaded cores

RUNS: dict[str, Callable[[Inputs, Path], list[str]]] = {
    "scan": lambda i, out: ["--rig", str(i.rig), "--out", str(out / "s")],
    "decode": lambda i, out: [str(i.session)],
    "demo": lambda i, out: ["--no-inspect", "--out", str(out / "d")],
    "import": lambda i, out: [*_import_frames(i), "--out", str(out / "imported")],
    "export": lambda i, out: [str(i.session), "--out", str(out / "cloud.xyz")],
    "bench decode": lambda i, out: ["--width", "320", "--height", "256", "--repeats", "1", "--no-peers"],
    "bench binocular": lambda i, out: ["--scenes", "1", "--seed", "1", "--repeats", "0", "--imports", "0"],
    "bench import": lambda i, out: ["--skip-procam", "--runs", "1"],
    "bench sim": lambda i, out: ["--repeats", "1"],
    "bench demo": lambda i, out: ["--parts", "1"],
    "bench views": lambda i, out: ["--out", str(out / "v"), "--views", "3", "--no-pairs"],  # the stage axis: 3 views
    "devices": lambda i, out: [],
    "calibrate": lambda i, out: ["--stage-axis", "--rig", str(CONFIG_DIR / "rigs" / "sim_turntable.toml"),
                                 "--angles=-30,0,30", "--out", str(out / "axis")],
    "verify": lambda i, out: ["--out", str(out / "verify")],
    "coverage": lambda i, out: ["--case", "plate-flatness", "--scans", "2", "--seed", "1"],
    "cad": lambda i, out: [str(STEP)],
    "bench cad": lambda i, out: [str(STEP), "--copies", "1"],
    "register": lambda i, out: [_cloud(i), _cloud(i)],
    "inspect": lambda i, out: [str(i.session), "--cad", str(STEP), "--out", str(out / "inspection")],
    "pose": lambda i, out: [str(i.bin_session), "--part", str(CONFIG_DIR / "parts" / "nickel_tab.toml"), "--out",
                            str(out / "poses.json")],
    "bench pose": lambda i, out: ["--seeds", "0", "--methods", "sac-ia", "--size", "320", "256"],
    "segment": lambda i, out: [str(i.session), "--out", str(out / "segments.npy")],
    "bench segment": lambda i, out: ["--seeds", "0", "--spacing", "4"],
    "segscore": lambda i, out: _labels(i),
    "station": lambda i, out: [str(DEMO_PROGRAM), "--config", str(i.station), "--out", str(out / "data"), "--auto",
                               "--parts", "1", "--measurement", TRUTH_GAUGE],
    "results": lambda i, out: ["--config", str(i.station)],
    "batch": lambda i, out: [str(i.part), "--program", str(DEMO_PROGRAM), "--measurement", TRUTH_GAUGE,
                             "--workers", "2"],
    "bench batch": lambda i, out: [str(i.part), "--program", str(DEMO_PROGRAM), "--measurement", TRUTH_GAUGE,
                                  "--workers", "2"],
}


def test_every_command_with_json_has_a_run_here() -> None:
    with_json = {name for name, p in cli.commands(cli.build_parser()).items()
                 if any(a.dest == "json" for a in p._actions)}
    assert with_json == set(RUNS)


@pytest.mark.acceptance
@pytest.mark.parametrize("command", [pytest.param(c, marks=pytest.mark.slow) if c in SLOW else c for c in RUNS])
def test_json_alone_on_stdout_with_library_output_provoked(command: str, inputs: Inputs, tmp_path: Path) -> None:
    argv = ["-v", *command.split(), *RUNS[command](inputs, tmp_path), "--json"]
    proc = subprocess.run([sys.executable, "-c", NOISY, *argv], capture_output=True, text=True, timeout=900)
    assert proc.returncode in (0, 1, 4), f"slscan {' '.join(argv)}: exit {proc.returncode}\n{proc.stderr[-3000:]}"
    json.loads(proc.stdout)  # one document and nothing else
    assert "a line on the stdout descriptor" in proc.stderr and "[Open3D WARNING]" in proc.stderr
