"""Issue 15, items 6 and 7: every key of a rig or pattern TOML known, typed, in range and
finite; physically impossible rigs refused at load with the reason, before any capture."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from pydantic import Field

from scanner import schema
from scanner.config import CONFIG_DIR
from scanner.errors import ConfigError
from scanner.geometry import Pinhole, RigModel, look_at
from scanner.patterns import PatternSet
from scanner.rig import DEFAULT_RIG, RigConfig
from scanner.rig_schema import check_geometry, common_view

BENCH = DEFAULT_RIG.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
PATTERNS = (CONFIG_DIR / "patterns" / "heterodyne_3x4.toml").read_text()


def edited(tmp_path: Path, text: str, old: str, new: str, name: str = "rig.toml") -> Path:
    assert old in text, old
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return path


def refused(load, path: Path) -> ConfigError:
    with pytest.raises(ConfigError) as exc:
        load(path)
    message = str(exc.value)
    assert str(path) in message and "\n" not in message
    return exc.value


# ------------------------------------------------------------------ item 6: typos are refused, with the right name

@pytest.mark.parametrize("old, new, key, guess", [
    ("exposure_s = 0.010", "exposure = 0.050", "camera.exposure", "exposure_s"),
    ("bit_depth = 12", "bit_detph = 8", "camera.bit_detph", "bit_depth"),
    ("timeout_s = 2.0", "timout_s = 2.0", "rig.timout_s", "timeout_s"),
    ("period_s = 0.05", "perod_s = 0.05", "rig.perod_s", "period_s"),
    ("[camera]\n", "[camra]\n", "camra", "camera"),
    ("read_noise_e = 6.0", "read_nois_e = 6.0", "camera.sensor.read_nois_e", "read_noise_e"),
])
def test_rig_typo_is_refused_with_the_nearest_name(tmp_path: Path, old: str, new: str, key: str, guess: str) -> None:
    err = refused(RigConfig.load, edited(tmp_path, BENCH, old, new))
    assert err.key == key
    assert f"did you mean '{guess}'?" in str(err)


@pytest.mark.parametrize("old, new, key", [
    ("steps = 4", "stesp = 4", "stesp"),
    ("orientations = [\"vertical\"]", "orientation = [\"vertical\"]", "orientation"),
])
def test_pattern_typo_is_refused(tmp_path: Path, old: str, new: str, key: str) -> None:
    err = refused(PatternSet.load, edited(tmp_path, PATTERNS, old, new, "p.toml"))
    assert err.key == key and "did you mean" in err.problem


@pytest.mark.parametrize("old, new, key", [
    ("steps = 4", "steps = 4.0", "steps"),
    ("steps = 4", "steps = true", "steps"),
    ("fringes = [70, 64, 59]", "fringes = [70, nan, 59]", "fringes[1]"),
    ("fringes = [70, 64, 59]", "fringes = [70, inf, 59]", "fringes[1]"),
    ("fringes = [70, 64, 59]", "fringes = []", "fringes"),
    ("family = \"heterodyne\"", "family = \"heterodine\"", "family"),
])
def test_pattern_values_are_typed_and_finite(tmp_path: Path, old: str, new: str, key: str) -> None:
    assert refused(PatternSet.load, edited(tmp_path, PATTERNS, old, new, "p.toml")).key == key


# ------------------------------------------------- item 7: absurd geometry, refused at load with the reason

@pytest.mark.parametrize("old, new, key, words", [
    ("hfov_deg = 22.6 ", "K = [[0, 0, 640], [0, 0, 512], [0, 0, 1]] ", "camera", "focal lengths"),
    ("hfov_deg = 22.6 ", "K = [[-3000, 0, 640], [0, 3000, 512], [0, 0, 1]] ", "camera", "focal lengths"),
    ("hfov_deg = 22.6 ", "K = [[nan, 0, 640], [0, 3000, 512], [0, 0, 1]] ", "camera.K[0][0]", "finite"),
    ("dist = [-0.08, 0.10, 0.0005, -0.0003, 0.0]", "dist = [nan, 0.10, 0.0005, -0.0003, 0.0]", "camera.dist[0]",
     "finite"),
    ("position_mm = [145.6, 0.0, 0.0]", "position_mm = [nan, 0.0, 0.0]", "projector.position_mm[0]", "finite"),
    ("pixel_aspect = 2.0", "pixel_aspect = 0", "projector.pixel_aspect", "0.1"),
    ("working_distance_mm = 400.0", "working_distance_mm = -400", "rig.working_distance_mm",
     "must lie within [10, 100000], got -400"),
    ("working_distance_mm = 400.0", "working_distance_mm = nan", "rig.working_distance_mm", "finite"),
    ("read_noise_e = 6.0", "read_noise_e = nan", "camera.sensor.read_noise_e", "finite"),
    ("gamma = 2.2", "gamma = 0", "projector.gamma", "must lie within (0.2, 5), got 0"),
    ("look_at_mm = [0.0, 0.0, 400.0]", "look_at_mm = [1000.0, 0.0, -400.0]", "projector", "looks away"),
    ("look_at_mm = [0.0, 0.0, 400.0]", "look_at_mm = [2000.0, 0.0, 400.0]", "projector", "no field of view"),
    ("position_mm = [145.6, 0.0, 0.0]", "position_mm = [0.0, 0.0, 0.0]", "projector", "baseline"),
])
def test_impossible_rig_is_refused_at_load(tmp_path: Path, old: str, new: str, key: str, words: str) -> None:
    err = refused(RigConfig.load, edited(tmp_path, BENCH, old, new))
    assert err.key == key and words in err.problem
    assert "exposure" not in err.problem  # not the old advice to raise the exposure


def test_common_view_matches_an_independent_frustum_count(bench_model: RigModel) -> None:
    """The shared view at 400 mm counted by hand: camera pixel rays hit z = 400, each point
    projected with the projector's K (no distortion) inside its image."""
    model = RigModel(Pinhole(bench_model.camera.width, bench_model.camera.height, bench_model.camera.K),
                     Pinhole(bench_model.projector.width, bench_model.projector.height, bench_model.projector.K),
                     bench_model.cam_from_proj)
    grid = 24
    u, v = np.meshgrid(np.linspace(0, model.camera.width - 1, grid), np.linspace(0, model.camera.height - 1, grid))
    Kc, Kp = model.camera.K, model.projector.K
    rays = np.stack([(u - Kc[0, 2]) / Kc[0, 0], (v - Kc[1, 2]) / Kc[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    X = rays * 400.0
    P = (X - model.cam_from_proj[:3, 3]) @ model.cam_from_proj[:3, :3]  # R^T (X - t)
    px = P[:, :2] / P[:, 2:] * np.diag(Kp)[:2] + Kp[:2, 2]
    inside = (P[:, 2] > 0) & (px[:, 0] >= -0.5) & (px[:, 0] <= model.projector.width - 0.5) \
        & (px[:, 1] >= -0.5) & (px[:, 1] <= model.projector.height - 0.5)
    assert common_view(model, 400.0, grid) == pytest.approx(inside.mean(), abs=1e-12)
    assert 0.3 < inside.mean() <= 1.0


def test_projector_at_camera_or_turned_away_refused_in_a_model(bench_model: RigModel) -> None:
    at_camera = RigModel(bench_model.camera, bench_model.projector, np.eye(4))
    with pytest.raises(ConfigError, match="baseline"):
        check_geometry(at_camera, None, "m.json", "rig_model")
    away = RigModel(bench_model.camera, bench_model.projector, look_at(np.array([100.0, 0, 0]),
                                                                        np.array([100.0, 0, -400.0])))
    with pytest.raises(ConfigError, match="looks away"):
        check_geometry(away, None, "m.json", "rig_model")
    check_geometry(bench_model, None, "m.json", "rig_model")  # the bench rig itself is fine


def test_every_bundled_rig_and_pattern_loads() -> None:
    for rig in sorted((CONFIG_DIR / "rigs").glob("*.toml")):
        assert RigConfig.load(rig).path == rig
    for p in sorted((CONFIG_DIR / "patterns").glob("*.toml")):
        assert PatternSet.load(p).for_projector((1024, 768)).n_frames >= 3


# ------------------------------------------------------------------ the layer itself

def test_schema_error_names_file_key_and_value() -> None:
    class Table(schema.Schema):
        radius_mm: schema.PositiveFloat
        centre_mm: schema.Vector3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])

    class File(schema.Schema):
        objects: list[Table]

    cases = [({"objects": [{"radius_mm": 1}, {"radius_mm": -2}]}, "objects[1].radius_mm", "greater than 0, got -2"),
             ({"objects": [{"radius_mm": 1, "centre_mm": [0, 0]}]}, "objects[0].centre_mm", "list of 3 values"),
             ({"objects": [{"radius_mm": 1, "centr_mm": [0, 0, 1]}]}, "objects[0].centr_mm",
              "did you mean 'centre_mm'"),
             ({"objects": [{"radius_mm": "1"}]}, "objects[0].radius_mm", "expected a number, got '1'"),
             ({"objects": [{"radius_mm": float("inf")}]}, "objects[0].radius_mm", "finite")]
    for data, key, words in cases:
        with pytest.raises(ConfigError) as exc:
            schema.parse(File, data, "f.toml")
        assert exc.value.key == key and words in exc.value.problem, exc.value
        assert re.fullmatch(rf"f\.toml, key '{re.escape(key)}': .+", str(exc.value))
