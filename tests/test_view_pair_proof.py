"""No view-pair pose without proof, on the simulated turntable: a sphere, which any turn
about its centre maps onto itself, is refused naming the free motion and the alternatives
(the truth: the sphere's symmetry, written out in the scene here); the refusal's record is
JSON (`slscan register` prints it and exits 1), and Open3D's prints never reach stdout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from inspection.errors import RegistrationFailed
from inspection.measured_cloud import load_source
from inspection.views.pair_registration import PairNotProven, register_view_pair, weigh_view_pair
from inspection.views.quiet import stdout_to_stderr
from scanner.config import CONFIG_DIR
from slscan import cli

TURNTABLE = CONFIG_DIR / "rigs" / "sim_turntable.toml"
PLATTER = [[1.0, 0.0, 0.0, 0.0], [0.0, -0.6427876096865394, -0.766044443118978, 11.49832709121586],
           [0.0, 0.766044443118978, -0.6427876096865394, 409.648242021395], [0.0, 0.0, 0.0, 1.0]]


def sphere_views(tmp: Path) -> Path:
    """Two 640 x 512 views, 40 deg apart, of a 20 mm sphere resting on the platter's centre."""
    rig = tmp / "turntable.toml"
    text = TURNTABLE.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    rig.write_text(text.replace("width = 1280", "width = 640").replace("height = 1024", "height = 512")
                   .replace("speed_deg_s = 90.0", "speed_deg_s = 3600.0").replace("settle_s = 0.2", "settle_s = 0.0"))
    up = -np.array(PLATTER)[:3, 2]  # the platter's normal toward the camera side (the stage axis's direction)
    centre = np.array(PLATTER)[:3, 3] + 20.0 * up
    scene = tmp / "sphere.toml"
    scene.write_text(f'name = "sphere on the turntable"\n[[objects]]\nname = "ball"\nalbedo = 0.7\n'
                     f"sphere = {{ radius_mm = 20.0, center_mm = {centre.tolist()} }}\n"
                     f'[[objects]]\nname = "platter"\nplane = {{ size_mm = [160.0, 160.0] }}\nalbedo = 0.5\n'
                     f"pose = {{ matrix = {PLATTER} }}\n")
    out = tmp / "mv"
    assert cli.main(["scan", "--rig", str(rig), "--scene", str(scene), "--angles", "0,40", "--out", str(out),
                     "--no-merge"]) == 0
    return out


@pytest.mark.acceptance
def test_a_sphere_is_refused_with_its_free_turn_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    views = sphere_views(tmp_path)
    capsys.readouterr()
    assert cli.main(["register", str(views / "view_001"), str(views / "view_000"), "--json"]) == 1
    said = json.loads(capsys.readouterr().out)  # JSON alone on stdout, the refusal in it
    assert said["status"] == "refused" and said["transform"] is None and len(said["best_unproven"]) == 4
    assert said["refusals"] and said["alternatives"]
    source, target = load_source(views / "view_001"), load_source(views / "view_000")
    pair = weigh_view_pair(source, target, isolate=True)
    assert not pair.proven and pair.refusals
    assert any("does not fix" in why for why in pair.refusals)  # a turn about the centre is free: named
    assert pair.ambiguous and pair.spread[0] > 0.3  # poses turned about it fit alike
    record = json.loads(json.dumps(pair.as_dict()))
    assert record["proven"] is False and record["refusals"] and record["alternatives"]
    with pytest.raises(PairNotProven) as refused:
        register_view_pair(source, target, isolate=True)
    assert isinstance(refused.value, RegistrationFailed) and refused.value.pair.refusals == pair.refusals


def test_native_prints_inside_go_to_stderr(capfd: pytest.CaptureFixture[str]) -> None:
    """What C code writes to file descriptor 1 inside `stdout_to_stderr` lands on stderr."""
    import os

    with stdout_to_stderr():
        os.write(1, b"open3d says hello\n")
        print("python says hello")
    print("{}")
    out, err = capfd.readouterr()
    assert out == "{}\n" and "open3d says hello" in err and "python says hello" in err
