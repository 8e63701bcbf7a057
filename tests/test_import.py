"""Importing other tools' captures: conventions detected from the frames against the
simulator's analytic geometry and a native scan of the same surface; wrong keys, counts,
orders and sizes refused by name; the self-check of every decode; other tools' calibrations.

Captures are rendered by sim.foreign_patterns from the tools' published formulas, not by
scanner.patterns, so a convention the decoder gets wrong cannot cancel out."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from foreign_capture import CONFIG, DEPTH, PROJ, RIG, UV, U, shoot, write_frames

from scanner.convention_detection import detect
from scanner.conventions import NATIVE, Conventions
from scanner.decode import DecodeSettings, decode
from scanner.errors import CalibrationFileError, ConfigError, DecodeError
from scanner.foreign_calibration import read_calibration
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator, triangulate
from sim.foreign_patterns import fringe_rows, opencv_graycode, slmaster_complementary, slmaster_heterodyne
from slscan.cli import main
from slscan.commands.bench.import_ import write_slmaster_calibration
from slscan.commands.import_ import natural_key


def unknown(family: str, steps: int, fringes: tuple[float, ...], **given) -> PatternSet:
    """A pattern set whose convention keys are all left out except `given`."""
    return PatternSet(family, steps, fringes, conventions=Conventions(**given))


def native_cloud(ps: PatternSet, gray: str | None) -> np.ndarray:
    rows = fringe_rows(PROJ[0], list(ps.fringes), ps.steps, gray=gray)
    d = decode(shoot(rows, U, seed=1), ps, 8, PROJ)
    return triangulate(d, Triangulator(RIG)).points[..., 2]


def imported_cloud(stack: np.ndarray, ps: PatternSet) -> tuple[np.ndarray, dict]:
    det = detect(stack, ps, 8, PROJ, RIG)
    d = decode(stack, det.patterns, 8, PROJ)
    return triangulate(d, Triangulator(RIG)).points[..., 2], {f.key: f for f in det.findings}


GRAY_CASES = {  # name: (fringe_rows keywords, the conventions that must be detected)
    "origin -pi": (dict(origin=-np.pi), dict(phase_origin=-np.pi)),
    "origin +pi/2": (dict(origin=np.pi / 2), dict(phase_origin=np.pi / 2)),
    "reversed step": (dict(sign=-1), dict(step_sign=-1)),
    "half-pixel offset": (dict(delta=0.0), dict(pixel_centre=0.0)),
    "Gray code before the phase": (dict(gray_position="before"), dict(gray_position="before")),
    "white and black first": (dict(references="first"), dict(references="first")),
    "OpenCV Gray code": (dict(gray="opencv", references="last"), dict(gray_code="opencv", references="last")),
    "SLMaster-like: -pi, centre 0, reversed": (dict(origin=-np.pi, delta=0.0, sign=-1),
                                               dict(phase_origin=-np.pi, pixel_centre=0.0, step_sign=-1)),
}


@pytest.mark.parametrize("case", GRAY_CASES)
def test_gray_phase_capture_conventions_detected_and_cloud_matches_native(case: str) -> None:
    """Every key the frames determine is detected; the pixel centre, which they cannot show,
    is given (as a tool's description gives it) or assumed (ours) and said so."""
    kwargs, expected = GRAY_CASES[case]
    kwargs = {"gray": "complementary", **kwargs}
    given = {"pixel_centre": expected["pixel_centre"]} if "pixel_centre" in expected else {}
    ps = unknown("graycode", 4, (64.0,), **given)
    stack = shoot(fringe_rows(PROJ[0], [64.0], 4, **kwargs), U, seed=2)
    z, found = imported_cloud(stack, ps)
    assert found["pixel_centre"].source == ("given" if given else "assumed"), found["pixel_centre"].line()
    assert found["step_offset"].source == "assumed"  # an origin and a rotation of the steps read alike
    assert found["period_rounding"].source == "assumed"  # the frames show a period's count, not its rounding
    for key, value in {**NATIVE.to_dict(), **expected}.items():
        if key in found and key not in ("pixel_centre", "step_offset", "period_rounding"):
            assert found[key].value == pytest.approx(value), f"{key}: {found[key].line()}"
            assert found[key].source == "detected", found[key].line()
    native = native_cloud(PatternSet("graycode", 4, (64.0,)), "complementary")
    both = np.isfinite(z) & np.isfinite(native)
    assert both.mean() > 0.85
    assert np.abs(z - DEPTH)[both].max() < 0.5  # mm, against the analytic plane
    # the same cloud as a native scan of the same surface, within the noise of either
    assert abs(np.median(z[both] - native[both])) < 0.01
    assert np.percentile(np.abs(z[both] - native[both]), 99) < 2 * np.percentile(np.abs(native - DEPTH)[both], 99)


HETERODYNE_CASES = {
    "origin -pi": (dict(origin=-np.pi), dict(phase_origin=-np.pi)),
    "step-major order": (dict(order="step-major"), dict(frame_order="step-major")),
    "references last": (dict(references="last"), dict(references="last")),
}


@pytest.mark.parametrize("case", HETERODYNE_CASES)
def test_heterodyne_capture_conventions_detected(case: str) -> None:
    kwargs, expected = HETERODYNE_CASES[case]
    ps = unknown("heterodyne", 4, (70.0, 64.0, 59.0))
    stack = shoot(fringe_rows(PROJ[0], [70.0, 64.0, 59.0], 4, **kwargs), U, seed=3)
    z, found = imported_cloud(stack, ps)
    for key, value in expected.items():
        assert found[key].value == pytest.approx(value) and found[key].source == "detected", found[key].line()
    assert found["pixel_centre"].source == "assumed"  # a phase-only set cannot show it: said so
    native = native_cloud(PatternSet("heterodyne", 4, (70.0, 64.0, 59.0)), None)
    both = np.isfinite(z) & np.isfinite(native)
    assert both.mean() > 0.9 and abs(np.median(z[both] - native[both])) < 0.01


def test_heterodyne_reversed_step_found_from_the_rig_geometry() -> None:
    ps = unknown("heterodyne", 4, (70.0, 64.0, 59.0))
    stack = shoot(fringe_rows(PROJ[0], [70.0, 64.0, 59.0], 4, sign=-1), U, seed=4)
    det = detect(stack, ps, 8, PROJ, RIG)
    found = {f.key: f for f in det.findings}
    assert found["step_sign"].value == -1 and found["step_sign"].source == "detected"
    without_rig = {f.key: f for f in detect(stack, ps, 8, PROJ).findings}
    assert without_rig["step_sign"].value == -1 and without_rig["step_sign"].source == "assumed"


def test_slmaster_sets_as_their_source_renders_them() -> None:
    """SLMaster's own formulas (8-bit truncation included), keys left out: detected as the
    shipped description files state them, coordinates within 0.1 px of the truth."""
    for rows, family, steps, fringes, shipped in (
            (slmaster_complementary(PROJ[0]), "graycode", 12, (32.0,), "slmaster_complementary_12x32.toml"),
            (slmaster_heterodyne(PROJ[0]), "heterodyne", 4, (32.0, 26.0, 21.0), "slmaster_heterodyne_3x4.toml")):
        stack = shoot(rows, U, seed=5)
        det = detect(stack, unknown(family, steps, fringes), 8, PROJ, RIG)
        described = PatternSet.load(CONFIG / shipped).conventions
        for f in det.findings:
            if f.source == "detected":
                assert f.value == pytest.approx(getattr(described, f.key)), f.line()
        m = decode(stack, PatternSet.load(CONFIG / shipped), 8, PROJ).maps["vertical"]
        err = (m.coordinate - U)[m.valid]
        # SLMaster truncates its patterns to 8 bits (not rounding): ~0.1 px of systematic error
        assert m.valid.mean() > 0.9 and np.percentile(np.abs(err), 99) < 0.15 and abs(np.median(err)) < 0.02


def test_native_decode_of_slmaster_frames_refuses_instead_of_a_wrong_cloud() -> None:
    """The issue's failure: decoded with our conventions, SLMaster's complementary set gave a
    cloud 10-100 mm wrong with exit 0 and its heterodyne set 0 % valid pixels; now both refuse."""
    comple = shoot(slmaster_complementary(PROJ[0]), U, seed=6)
    with pytest.raises(DecodeError,
                       match="gray_offset \\(vertical\\) failed: 3.0.* rad .*phase steps rotated by 6 of 12"):
        decode(comple, PatternSet("graycode", 12, (32.0,)), 8, PROJ)  # SLMaster's origin -π: six steps of 12
    het = shoot(slmaster_heterodyne(PROJ[0]), U, seed=6)
    with pytest.raises(DecodeError, match="consistency checks"):
        decode(het, PatternSet("heterodyne", 4, (32.0, 26.0, 21.0)), 8, PROJ)


@pytest.mark.parametrize("given, message", [
    (dict(phase_origin=0.0), "phase_origin = 0.000 contradicts the frames.* 2 whole step\\(s\\)"),
    (dict(phase_origin=0.7), "phase_origin = 0.700 contradicts the frames.* not a whole number of steps"),
    (dict(step_sign=1), "step_sign = \\+1 contradicts"),
])
def test_a_wrong_given_key_is_refused(given: dict, message: str) -> None:
    stack = shoot(fringe_rows(PROJ[0], [64.0], 4, gray="complementary", origin=-np.pi, sign=-1, delta=0.0), U)
    with pytest.raises(DecodeError, match=message):
        detect(stack, unknown("graycode", 4, (64.0,), **given), 8, PROJ, RIG)


def test_wrong_heterodyne_origin_and_frame_order_refused() -> None:
    stack = shoot(fringe_rows(PROJ[0], [70.0, 64.0, 59.0], 4, origin=-np.pi), U)
    with pytest.raises(DecodeError, match="phase_origin = 0.000 contradicts"):
        detect(stack, unknown("heterodyne", 4, (70.0, 64.0, 59.0), phase_origin=0.0), 8, PROJ, RIG)
    with pytest.raises(DecodeError, match="contradicts the frames: frequency-major"):
        detect(stack, unknown("heterodyne", 4, (70.0, 64.0, 59.0), frame_order="step-major"), 8, PROJ, RIG)


def test_wrong_period_count_refused_by_name() -> None:
    gray = shoot(fringe_rows(PROJ[0], [32.0], 4, gray="complementary"), U)
    with pytest.raises(DecodeError, match="10 frames.*needs 11/13/26/28 frames: wrong frame count, fringe/period"):
        detect(gray, unknown("graycode", 4, (64.0,)), 8, PROJ)
    het = shoot(fringe_rows(PROJ[0], [32.0, 26.0, 21.0], 4), U)
    with pytest.raises(DecodeError, match="no frame layout explains the frames"):
        detect(het, unknown("heterodyne", 4, (70.0, 64.0, 59.0)), 8, PROJ)


def test_wrong_projector_size_refused_by_name() -> None:
    cols, rows = opencv_graycode(*PROJ)
    stack = np.concatenate([shoot(cols, U), shoot(rows, UV[..., 1])])
    stack[-2:] = shoot(rows[-2:], UV[..., 1])  # white and black
    ps = PatternSet.load(CONFIG / "opencv_graycode.toml")
    d = decode(stack, ps, 8, PROJ)
    m = d.maps["vertical"]
    assert np.abs(m.coordinate - np.rint(U))[m.valid].max() <= 1.0
    with pytest.raises(DecodeError, match="needs"):  # another bit count: another frame count
        detect(stack, PatternSet.load(CONFIG / "opencv_graycode.toml", detect=True), 8, (800, 600))
    with pytest.raises(DecodeError, match="projector_range .* failed.*a wrong projector size"):  # codes beyond it
        decode(stack, ps, 8, (1100, 1080))


def test_masks_judge_saturation_on_phase_frames_and_report_reasons() -> None:
    rows = fringe_rows(PROJ[0], [64.0], 4, gray="complementary")
    stack = shoot(rows, U, dark=0.05, bright=0.97, noise=0.0)  # phase frames peak below full scale
    gray = stack[4:].astype(np.int32)
    stack[4:] = np.clip(gray * 1.3, 0, 255).astype(np.uint8)  # the binary frames clip
    ps = PatternSet("graycode", 4, (64.0,))
    m = decode(stack, ps, 8, PROJ).maps["vertical"]
    assert (stack[4:] == 255).mean() > 0.2 and not m.masks["saturated"].any()
    assert m.valid.mean() > 0.95 and np.abs(m.coordinate - U)[m.valid].max() < 0.2
    clipped = stack.copy()
    clipped[:4, :, :100] = np.clip(clipped[:4, :, :100].astype(np.int32) * 2, 0, 255)
    m2 = decode(clipped, ps, 8, PROJ).maps["vertical"]
    assert m2.masks["saturated"][:, :100].mean() > 0.3 and not m2.valid[m2.masks["saturated"]].any()


def test_order_tolerance_follows_each_pixels_noise() -> None:
    """A smooth systematic phase error of 0.6π in the heterodyne beat, where the noise is low,
    is no fringe-order error (the fixed 0.5π tolerance rejected such stripes); the fringe
    orders stay right, and in a noisy band the tolerance tightens."""
    ps = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0))
    rows = fringe_rows(PROJ[0], [70.0, 64.0, 59.0], 4)
    quiet = shoot(rows, U, bits=8, noise=0.001, seed=7)
    # the middle frequency shifted by s moves the heterodyne residuals by 11s and 11.7s: 0.6π
    wobble = shoot(fringe_rows(PROJ[0], [70.0, 64.0, 59.0], 4, origin=0.6 * np.pi / 11.0), U, bits=8, noise=0.001)
    stack = quiet.copy()
    stack[4:8] = wobble[4:8]
    m = decode(stack, ps, 8, PROJ, DecodeSettings(self_check=False)).maps["vertical"]
    assert m.valid.mean() > 0.95
    assert np.abs(m.coordinate - U)[m.valid].max() < m.period_px / 2  # no wrong order slipped through
    old = decode(stack, ps, 8, PROJ, DecodeSettings(self_check=False, order_tolerance_max=0.5)).maps["vertical"]
    assert old.masks["order_error"].mean() > 0.3  # what one constant did


def test_phase_noise_estimate_matches_the_actual_error() -> None:
    """The per-pixel phase noise decode predicts from its own noise model (no noise figure
    given) matches the coordinate error against the truth."""
    ps = PatternSet("heterodyne", 4, (70.0, 64.0, 59.0))
    stack = shoot(fringe_rows(PROJ[0], [70.0, 64.0, 59.0], 4), U, bits=12, noise=0.003, seed=8)
    m = decode(stack, ps, 12, PROJ).maps["vertical"]
    err = (m.coordinate - U)[m.valid]
    predicted = m.coordinate_sigma[m.valid]
    assert 0.8 < np.sqrt(np.mean(err ** 2)) / np.sqrt(np.mean(predicted ** 2)) < 1.25


@pytest.mark.parametrize("table, key", [
    ({"phase_origin": "pi"}, "conventions.phase_origin"),
    ({"step_sign": 2}, "conventions.step_sign"),
    ({"frame_order": "random"}, "conventions.frame_order"),
    ({"pixel_center": 0.5}, "conventions.pixel_center"),
    ({"pixel_centre": 1.5}, "conventions.pixel_centre"),
])
def test_bad_convention_key_named(table: dict, key: str, tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as e:
        PatternSet.from_dict({"family": "graycode", "steps": 4, "fringes": [64], "conventions": table},
                             tmp_path / "p.toml")
    assert e.value.key == key


def test_shipped_descriptions_load() -> None:
    for path in sorted(CONFIG.glob("*.toml")):
        ps = PatternSet.load(path)
        assert ps.conventions.complete, path


def test_slmaster_calibration_read_in_the_stated_direction(tmp_path: Path) -> None:
    path = tmp_path / "caliInfo.yml"
    write_slmaster_calibration(path, RIG)
    model, name = read_calibration(path, RIG.camera.size, RIG.projector.size)
    assert name == "slmaster"
    assert np.allclose(model.camera.K, RIG.camera.K) and np.allclose(model.projector.dist, RIG.projector.dist)
    assert np.allclose(model.cam_from_proj, RIG.cam_from_proj, atol=1e-9)
    with pytest.raises(CalibrationFileError, match="made for a camera of 320 x 256"):
        read_calibration(path, (640, 512), RIG.projector.size)


def test_procam_calibration_read_with_its_scale() -> None:
    xml = Path(__file__).resolve().parents[2] / "shared" / "data" / "procam-graycode" / "calibration_result.xml"
    if not xml.exists():
        pytest.skip("../shared/data/procam-graycode is not here (real data, CI has it)")
    fs = cv2.FileStorage(str(xml), cv2.FILE_STORAGE_READ)
    K, R, T = fs.getNode("proj_int").mat(), fs.getNode("roration").mat(), fs.getNode("translation").mat()
    fs.release()
    model, name = read_calibration(xml, (1280, 1024), (1024, 768), 2.0)
    assert name == "procam"
    assert model.projector.K[0, 0] == pytest.approx(K[0, 0] / 2)
    assert model.projector.K[1, 2] == pytest.approx(K[1, 2] / 2)
    p_cam = np.array([10.0, 20.0, 3000.0])  # a camera-frame point: X_p = R·X_c + T
    assert np.allclose(np.linalg.inv(model.cam_from_proj)[:3] @ np.r_[p_cam, 1], R @ p_cam + T.ravel())
    with pytest.raises(CalibrationFileError, match="projector scale"):  # read as published it cannot fit
        read_calibration(xml, (1280, 1024), (1024, 768))


def test_import_command_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """SLMaster's complementary capture as BMP files named 1..18 (natural order), its
    caliInfo.yml: a session with a cloud on the analytic plane; decode regenerates it."""
    stack = shoot(slmaster_complementary(PROJ[0]), U, seed=9)
    names = [f"{k + 1}.bmp" for k in range(len(stack))]
    write_frames(tmp_path / "frames", stack, names)
    cal = tmp_path / "caliInfo.yml"
    write_slmaster_calibration(cal, RIG)
    out = tmp_path / "session"
    args = ["import", str(tmp_path / "frames"), "--patterns", str(CONFIG / "slmaster_complementary_12x32.toml"),
            "--projector-size", f"{PROJ[0]}x{PROJ[1]}", "--calibration", str(cal), "--out", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "phase_origin = -3.14159" in text and "rejected" in text
    manifest = json.loads((out / "manifest.json").read_text())
    assert [Path(f).name for f in manifest["import"]["sources"]] == names  # 2.bmp before 10.bmp
    assert os.stat(out / manifest["frames"][0]["file"]).st_ino == os.stat(tmp_path / "frames" / "1.bmp").st_ino
    assert manifest["import"]["conventions"]["phase_origin"]["source"] == "given"
    result = json.loads((out / "outputs" / "result.json").read_text())
    assert result["rejected"] and result["points"] > 0.8 * U.size
    with np.load(out / "outputs" / "maps.npz") as m:
        first = m["vertical/coordinate"].copy()
        assert np.nanpercentile(np.abs(first - U), 99) < 0.15  # SLMaster's 8-bit truncation
    assert main(["decode", str(out)]) == 0
    with np.load(out / "outputs" / "maps.npz") as m:
        assert np.array_equal(m["vertical/coordinate"], first, equal_nan=True)


def test_decode_of_a_session_with_wrong_conventions_fails_without_a_cloud(tmp_path: Path) -> None:
    stack = shoot(slmaster_complementary(PROJ[0]), U, seed=10)
    write_frames(tmp_path / "frames", stack, [f"f{k:02d}.png" for k in range(len(stack))])
    out = tmp_path / "session"
    assert main(["import", str(tmp_path / "frames"), "--patterns", str(CONFIG / "slmaster_complementary_12x32.toml"),
                 "--projector-size", f"{PROJ[0]}x{PROJ[1]}", "--out", str(out)]) == 0
    assert not (out / "outputs" / "cloud.ply").exists()  # no calibration: maps only
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["patterns"].pop("conventions")  # as if decoded with ours
    (out / "manifest.json").write_text(json.dumps(manifest))
    (out / "outputs" / "maps.npz").unlink()
    assert main(["decode", str(out)]) == 2
    assert not (out / "outputs" / "maps.npz").exists()


def test_frames_16_bit_png_and_tiff_read_in_natural_order(tmp_path: Path) -> None:
    stack = shoot(fringe_rows(PROJ[0], [70.0, 64.0, 59.0], 4), U, bits=12, seed=11)
    names = [f"img{k}.{'tif' if k % 2 else 'png'}" for k in range(len(stack))]
    write_frames(tmp_path / "frames", stack, names)
    assert sorted(names, key=natural_key)[:3] == ["img0.png", "img1.tif", "img2.png"]
    out = tmp_path / "session"
    assert main(["import", str(tmp_path / "frames"), "--patterns", str(CONFIG / "heterodyne_3x4.toml"),
                 "--projector-size", f"{PROJ[0]}x{PROJ[1]}", "--out", str(out)]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["import"]["bit_depth"] == 12 and manifest["frames"][1]["file"].endswith(".tif")
    with np.load(out / "outputs" / "maps.npz") as m:
        assert np.nanpercentile(np.abs(m["vertical/coordinate"] - U), 99) < 0.08
