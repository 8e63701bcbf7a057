"""`slscan inspect` on input it cannot measure: a scan of another part, a model in metres
against a scan in millimetres, an empty or unreadable STEP file. Each ends in a clear
error (exit 2, the message names the file and the problem) and writes no report: never a
number."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from registration_support import virtual_view

from inspection.cad import load_cad
from scanner.config import CONFIG_DIR
from sim.parts import lying_pose
from slscan import cli

STEP = CONFIG_DIR / "parts" / "demo_part.step"


@pytest.fixture(scope="module")
def cloud(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A camera-frame view of the demo part as a PLY cloud (mm)."""
    import open3d as o3d

    model = load_cad(STEP)
    view = virtual_view(model, lying_pose(model.tessellation.vertices, 0.3, 400.0, (0.4, 0.2)))
    path = tmp_path_factory.mktemp("failures") / "view.ply"
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(view.points))
    pc.normals = o3d.utility.Vector3dVector(view.normals)
    o3d.io.write_point_cloud(str(path), pc)
    return path


def _inspect_fails(cloud: Path, cad: Path, out: Path, capsys, *words: str, unit: str = "mm") -> None:
    code = cli.main(["inspect", str(cloud), "--cad", str(cad), "--cad-unit", unit, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "error" in err and all(w in err for w in words), err
    assert not out.exists()  # no report, not even its folder


def test_scan_of_another_part(cloud: Path, tmp_path: Path, capsys) -> None:
    """A plain block of the demo part's size (it shares the plate and a top with it)."""
    from OCP.BRepPrimAPI import BRepPrimAPI_MakeBox
    from OCP.gp import gp_Pnt

    from sim.parts_demo import write_step

    block = tmp_path / "block.step"
    write_step(BRepPrimAPI_MakeBox(gp_Pnt(-45, -30, 0), gp_Pnt(45, 30, 28)).Shape(), block)
    _inspect_fails(cloud, block, tmp_path / "out", capsys, "registration failed", "wrong part")


def test_model_in_metres(cloud: Path, tmp_path: Path, capsys) -> None:
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(CONFIG_DIR / "parts" / "demo_part.ply"))
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) / 1000.0)
    mesh.compute_triangle_normals()
    path = tmp_path / "part_m.stl"
    o3d.io.write_triangle_mesh(str(path), mesh)
    _inspect_fails(cloud, path, tmp_path / "out", capsys, "metres", "--cad-unit m")


@pytest.mark.parametrize("content, words", [
    (b"", "unreadable"),
    (b"\x00\x01 not STEP at all", "unreadable"),
    (b"ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nFILE_NAME('e','',(''),(''),'','','');\n"
     b"FILE_SCHEMA(('AUTOMOTIVE_DESIGN'));\nENDSEC;\nDATA;\nENDSEC;\nEND-ISO-10303-21;\n", "no shape")])
def test_empty_or_unreadable_step(cloud: Path, tmp_path: Path, capsys, content: bytes, words: str) -> None:
    step = tmp_path / "part.stp"
    step.write_bytes(content)
    _inspect_fails(cloud, step, tmp_path / "out", capsys, str(step), words)
