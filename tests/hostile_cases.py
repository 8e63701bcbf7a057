"""What the hostile-input worker runs (`tests/hostile.py`): each target calls the entry point a
command uses on one generated file or value and returns a small summary the test compares
with the generator's truth. A refusal is a ScannerError (or argparse's usage exit, turned
into one here)."""

from __future__ import annotations

import io
from contextlib import redirect_stderr
from pathlib import Path
from typing import Any

from scanner.errors import ScannerError


def mesh_counts(path: str) -> tuple[int, int]:
    """(vertices, triangles) as `slscan cad`/`register`/scenes read a mesh file."""
    from scanner.mesh_files import read_mesh

    v, t = read_mesh(path)
    return len(v), len(t)


def point_count(path: str) -> int:
    """Points as `inspect`/`register`/`pose` read a cloud file (`scanner.mesh_files.read_points`)."""
    from scanner.mesh_files import read_points

    return len(read_points(path)[0])


def cad_faces(path: str) -> int:
    """Faces of a STEP file as `slscan cad` lists them."""
    from inspection.cad import load_cad

    return len(load_cad(path).faces)


def truth_shapes(path: str) -> tuple[tuple[int, ...], ...]:
    """The arrays of a simulator ground_truth.npz as `scan`/`pose`/`segscore` read it."""
    from sim.evaluate import Truth

    t = Truth.load(Path(path))
    return t.depth.shape, t.object_id.shape, t.proj_uv.shape


def session_frames(root: str) -> tuple[int, ...]:
    """The frame stack of a session as `decode` reads it."""
    from scanner.session import Session

    return Session.open(root).load_stack().shape


def rig_loads(path: str) -> str:
    """A rig TOML loaded as every command loads it, and its simulated sensor built."""
    from scanner.rig import RigConfig
    from sim.render import SensorModel

    config = RigConfig.load(path)
    SensorModel.from_config(config)
    return "ok"


def patterns_fit(rig_path: str) -> str:
    """The check `scan` makes before creating a session: the rig's patterns on its projector."""
    from scanner.patterns import PatternSet
    from scanner.rig import RigConfig
    from scanner.rig_schema import check_patterns_fit

    config = RigConfig.load(rig_path)
    check_patterns_fit(PatternSet.load(config.patterns_path), config.nominal_model().projector, config.path)
    return "ok"


def scene_opens(scene_path: str, rig_path: str) -> str:
    """A scene loaded and checked as the simulated rig opens it (`sim.virtual_rig`)."""
    from scanner.rig import RigConfig
    from sim.scene import Scene, check_in_view

    config = RigConfig.load(rig_path)
    model = config.nominal_model()
    check_in_view(Scene.load(scene_path, config.working_distance_mm), model.camera, model.world_from_cam)
    return "ok"


def station_config_loads(path: str) -> str:
    from slscan.station.station_config import StationConfig

    config = StationConfig.load(path)
    return config.operator


def program_text(path: str, which: str) -> str:
    """A part program's name, the high top's face name or its first characteristic's name."""
    from slscan.station.program import load_program

    program = load_program(path)
    return {"name": program.name, "face": program.face_names.get("#657", ""),
            "characteristic": program.characteristics[0].name}[which]


def cli_args(argv: list[str]) -> str:
    """The command line parsed as `slscan` parses it; argparse's refusal (exit 2) is a refusal."""
    from slscan.cli import build_parser

    try:
        with redirect_stderr(io.StringIO()) as err:
            build_parser().parse_args(argv)
    except SystemExit as exc:
        if exc.code == 2:
            raise ScannerError(err.getvalue().strip().splitlines()[-1]) from None
        raise
    return "ok"


def stored_serial(db: str, serial: str) -> tuple[bool, Any]:
    """A serial through the station's boundary into the results database and its CSV export:
    (read back unchanged, its CSV cell)."""
    import datetime as dt

    from scanner.schema import plain_text
    from slscan.station.results import PartStart, csv_cell, open_results

    try:
        plain_text(serial, "the serial number")
    except ValueError as exc:
        raise ScannerError(str(exc)) from None
    with open_results(f"sqlite:{db}") as store:
        rid, _ = store.begin_part(PartStart(program="p", program_version="1", program_fingerprint="f", serial=serial,
                                            operator="o", station="s", rig="r", calibration_id="c",
                                            software_version="v", measurement="m", part_path="",
                                            started_at=dt.datetime.now(dt.UTC)))
        back = store.result(rid).serial
    return back == serial, csv_cell(back)

