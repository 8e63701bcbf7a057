"""Issue 15, item 8 and the smaller ones: the other files slscan reads (scene, tolerances,
calibration file, instance masks, clouds) refuse what they cannot use with one error naming
the file (and key), never a traceback."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from inspection.bins.instances import read_label_image, read_labelme
from inspection.errors import CloudError, MaskError, SegmentationError, ToleranceError
from inspection.measured_cloud import make_scan
from inspection.regions.region_growing import check_radius
from inspection.tolerances import load_tolerances
from scanner.calibration_file import write_calibration
from scanner.config import CONFIG_DIR
from scanner.errors import ConfigError
from scanner.geometry import RigModel
from scanner.rig import DEFAULT_RIG, RigConfig
from sim.scene import Scene

SCENE = (CONFIG_DIR / "scenes" / "sphere_plane.toml").read_text()
LABELS = {"#657": "plane", "#17": "cylinder"}


@pytest.mark.parametrize("old, new, key", [
    ("center_mm = [0.0, 0.0, 400.0]", "center_mm = [0.0, nan, 400.0]", "objects[0].sphere.center_mm[1]"),
    ("radius_mm = 20.0", "radius_mm = inf", "objects[0].sphere.radius_mm"),
    ("distance_mm = 440.0", "distance_mm = nan", "reference_plane.distance_mm"),
    ("albedo = 0.7", "albedo = nan", "objects[0].albedo"),
    ("albedo = 0.7", "albdo = 0.7", "objects[0].albdo"),
])
def test_scene_refuses_non_finite_and_misspelt_keys(tmp_path: Path, old: str, new: str, key: str) -> None:
    path = tmp_path / "scene.toml"
    path.write_text(SCENE.replace(old, new, 1))
    with pytest.raises(ConfigError) as exc:
        Scene.load(path)
    assert exc.value.key == key and str(path) in str(exc.value)
    if "albdo" in new:
        assert "did you mean 'albedo'" in exc.value.problem


@pytest.mark.parametrize("text, words", [
    ('[faces."#657"]\nflatness_mm = inf\n', "finite number > 0"),
    ('[faces."#657"]\nflatness_mm = nan\n', "finite number > 0"),
    ('[faces."#657"]\nflatnes_mm = 0.05\n', "did you mean 'flatness_mm'"),
    ("faces = 3\n", "must be a table"),
])
def test_tolerances_refuse_infinite_limits_and_typos(tmp_path: Path, text: str, words: str) -> None:
    path = tmp_path / "t.toml"
    path.write_text(text)
    with pytest.raises(ToleranceError, match=words):
        load_tolerances(path, LABELS)


def rig_with_calibration(tmp_path: Path, model: RigModel) -> Path:
    cal = write_calibration(tmp_path / "cal.json", model, {}, "bench")
    text = DEFAULT_RIG.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    path = tmp_path / "rig.toml"
    path.write_text(text.replace("[rig]\n", f'[rig]\ncalibration = "{cal}"\n', 1))
    return path


@pytest.mark.parametrize("edit, words", [
    (lambda d: d["rig_model"].__setitem__("projector_gamma", 0), "projector_gamma"),
    (lambda d: d["rig_model"]["camera"]["K"][1].__setitem__(1, -100.0), "focal lengths"),
    (lambda d: d["rig_model"]["projector"]["dist"].__setitem__(0, float("nan")), "finite"),
    (lambda d: [r.__setitem__(3, 0.0) for r in d["rig_model"]["cam_from_proj"][:3]], "baseline"),
])
def test_calibration_file_with_impossible_geometry_is_refused_at_rig_load(tmp_path: Path, bench_model: RigModel,
                                                                          edit, words: str) -> None:
    rig = rig_with_calibration(tmp_path, bench_model)
    cal = tmp_path / "cal.json"
    data = json.loads(cal.read_text())
    edit(data)
    cal.write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=words) as exc:
        RigConfig.load(rig)
    assert exc.value.key == "rig.calibration" and "cal.json" in str(exc.value) and "\n" not in str(exc.value)


def test_calibration_file_of_the_bench_still_loads(tmp_path: Path, bench_model: RigModel) -> None:
    config = RigConfig.load(rig_with_calibration(tmp_path, replace(bench_model, projector_gamma=2.0)))
    assert config.model.projector_gamma == 2.0 and np.allclose(config.model.camera.K, bench_model.camera.K)


@pytest.mark.parametrize("doc, words", [
    ([{"shapes": []}], "not an object"),
    ({"imageWidth": 64, "imageHeight": 48, "shapes": ["polygon"]}, r"shapes\[0\] is a str"),
    ({"imageWidth": 64, "imageHeight": 48, "shapes": [{"points": [[0, 0], [1e12, 0], [0, 1e12]]}]}, "within"),
    ({"imageWidth": 64, "imageHeight": 48, "shapes": [{"points": [[0, 0], [float("nan"), 0], [0, 9]]}]}, "finite"),
    ({"imageWidth": 64, "imageHeight": 48, "shapes": [{"points": [[0, 0], [9, 0], [0, 9]], "group_id": [1]}]},
     "group_id"),
])
def test_labelme_files_that_cannot_be_drawn_are_refused(tmp_path: Path, doc: object, words: str) -> None:
    path = tmp_path / "l.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(MaskError, match=words):
        read_labelme(path, (64, 48))


def test_labelme_polygon_near_the_coordinate_limit_is_drawn(tmp_path: Path) -> None:
    """A triangle with a far vertex (1e5 px) still covers the image pixels below its edge."""
    path = tmp_path / "l.json"
    path.write_text(json.dumps({"imageWidth": 64, "imageHeight": 48, "shapes": [
        {"label": "a", "points": [[0, 0], [1e5, 0], [0, 1e5]]}]}))
    ids, names = read_labelme(path, (64, 48))
    assert names == {1: "a"} and ids.all()  # the whole image lies inside x + y < 1e5


def test_collinear_cloud_is_refused() -> None:
    t = np.linspace(0, 50, 2000)
    with pytest.raises(CloudError, match="on a line"):
        make_scan(np.stack([t, 0 * t, 400 + 0 * t], 1), None, "line.ply", None)


def test_segment_on_a_tiny_cloud_does_not_suggest_a_non_positive_radius() -> None:
    with pytest.raises(SegmentationError) as exc:
        check_radius(np.zeros((50, 3)), 5.0)
    assert "too small to segment" in str(exc.value) and "r <= 0" not in str(exc.value)


def test_label_image_of_floats_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "labels.tiff"
    cv2.imwrite(str(path), np.full((8, 8), np.nan, np.float32))
    with pytest.raises(MaskError, match="integer ids"):
        read_label_image(path)
