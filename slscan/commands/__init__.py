"""The commands of `slscan`, one module per feature, and the one table naming them.

Each module defines `register(subparsers)`, adding its sub-commands to the `slscan` parser
with `set_defaults(func=...)`; a command function takes the parsed arguments and returns
the exit code. `COMMANDS` names each command's module and its one-line summary (the help's
list of commands); `BENCHES` those of the group `slscan bench NAME` (benchmarks and studies,
their modules in `slscan.commands.bench`, the only commands that may import `studies`; the
user's `slscan coverage`, which runs the repeat-scan study, has its module there too);
`MOVED` the commands' former names ("simbench", "bench coverage"), refused with the new
form named. The command
line imports only the module of the command it runs, after its arguments are read, so
`slscan --help`, `--version` and a usage error import none of them; modules still import
heavy libraries (OpenCASCADE, Open3D, USB, ...) inside their command functions only.
"""

from __future__ import annotations

from importlib import import_module
from types import ModuleType

GROUP = ""  # the module of a group command: none (slscan.cli makes its parser from its table)

COMMANDS: dict[str, tuple[str, str]] = {  # command -> (module in slscan.commands, summary)
    "scan": ("scan", "scan a part into a session folder (raw frames, cloud PLY, Rerun recording)"),
    "decode": ("scan", "regenerate every output of a session from its raw frames"),
    "demo": ("scan", "scan the bundled part on the default simulated rig and inspect it against its STEP model"),
    "import": ("import_binocular", "turn a folder of fringe frames from any tool into a session (conventions "
                                   "detected, other tools' calibrations read)"),
    "review": ("review", "open what slscan wrote (scan session, multi-view folder, station part, calibration, "
                         "poses.rrd, any folder with recordings) in the Rerun viewer (web when headless)"),
    "export": ("export", "write a session's cloud as PLY, XYZ, CSV, E57 or an STL mesh, in the camera or the CAD "
                         "frame, with per-point deviations"),
    "devices": ("devices", "list cameras, projectors and serial ports; export LightCrafter images"),
    "calibrate": ("calibrate", "calibrate the rig (camera, projector, stereo, gamma, phase-to-height), guided on "
                               "the bench or from captures on disk"),
    "verify": ("verify", "acceptance / reverification test (VDI/VDE 2634 Part 2): artefacts in the measuring volume "
                         "against the rig's maximum permissible errors"),
    "coverage": ("bench.coverage", "how often the truth lies within ±U: repeat scans on the simulated bench "
                                   "measured as scan/inspect/verify measure them"),
    "cad": ("inspect", "list a CAD model's faces by STEP id and surface type"),
    "register": ("inspect", "register a cloud to a CAD model, a mesh or another cloud"),
    "inspect": ("inspect", "register a scan to CAD, segment it by face, report form errors per face"),
    "pose": ("pose", "poses and pick order of thin flat parts in a bin (poses JSON for a robot cell)"),
    "segment": ("segment", "segment a cloud or a session's scan by region growing (one parameter, r)"),
    "segscore": ("segment", "score a segmentation against ground-truth labels (alpha, beta, eta)"),
    "station": ("station", "the operator loop for a part program (full-screen; --auto without operator)"),
    "results": ("station", "query the results history; export CSV; write the HTML report"),
    "batch": ("station", "re-decode and re-inspect stored sessions (in parallel, or on a Dask cluster)"),
    "bench": (GROUP, "benchmarks and studies: slscan timed, and measured against the simulator's truth "
                     "(slscan bench NAME; slscan bench --help lists them)"),
}
BENCHES: dict[str, tuple[str, str]] = {  # `slscan bench NAME` -> (module in slscan.commands.bench, summary)
    "decode": ("decode", "decode + reconstruction time and peak memory"),
    "import": ("import_", "per-rig table and import speed; real-capture flatness and scale"),
    "sim": ("simulator", "simulated frame time (with a peer) and sequence period on the bench rig"),
    "demo": ("demo", "scan-to-verdict of the demo part, stage by stage, as a station runs it"),
    "views": ("views", "multi-view acceptance figures on the simulated turntable"),
    "binocular": ("binocular", "binocular reconstruction on the simulated binocular rig: accuracy against truth "
                               "beside monocular, with a wrong projector model, and its speed"),
    "cad": ("cad", "STEP reading time for files of 1, 4, 16 copies of a part"),
    "pose": ("pose", "pose parts in simulated bins and score them against the truth (both methods, paper 001's "
                     "four cases)"),
    "segment": ("segment", "segment simulated cluttered clouds: time per cloud and alpha, beta, eta against their "
                           "ground truth"),
    "batch": ("batch", "time `slscan batch` serially and on a local Dask cluster; check the results agree"),
}
GROUPS = {"bench": BENCHES}  # a command whose words after it name one of its table's commands
MOVED = {  # a former command, as typed -> what it is now; the command line refuses the old name, naming this
    "bench": "bench decode", "importbench": "bench import", "simbench": "bench sim", "demobench": "bench demo",
    "viewbench": "bench views", "binobench": "bench binocular", "cadbench": "bench cad",
    "posebench": "bench pose", "segbench": "bench segment", "batchbench": "bench batch",
    "bench coverage": "coverage",
}


def table(group: str | None = None) -> dict[str, tuple[str, str]]:
    """The commands of `slscan` (group None) or of `slscan GROUP`."""
    return COMMANDS if group is None else GROUPS[group]


def command_module(name: str, group: str | None = None) -> ModuleType:
    """The module that registers command `name` (of `group`: `slscan GROUP NAME`)."""
    return import_module(_package(group) + table(group)[name][0])


def modules(group: str | None = None) -> list[ModuleType]:
    """Every command module (of `group`), each once, in the table's order; a group is no module's."""
    return [import_module(_package(group) + m)
            for m in dict.fromkeys(m for m, _ in table(group).values() if m != GROUP)]


def _package(group: str | None) -> str:
    return "slscan.commands." + (f"{group}." if group else "")
