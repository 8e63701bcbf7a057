"""Part programs, the station config and the calibration refusal rules."""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import replace
from pathlib import Path

import pytest
from session_support import small_rig_toml
from station_support import DEMO_PROGRAM, program_copy, station_config

from scanner.config import CONFIG_DIR
from scanner.errors import ConfigError
from scanner.rig import RigConfig
from sim.station_parts import CHARACTERISTIC_FACES
from slscan.station.calib import CalibrationInfo, refusals, rig_calibration
from slscan.station.measure import cad_faces
from slscan.station.program import load_program
from slscan.station.station_config import StationConfig

TODAY = dt.date(2026, 11, 23)


def test_demo_program_loads_with_faces_checked_in_the_cad() -> None:
    p = load_program(DEMO_PROGRAM, faces=cad_faces)
    assert p.name == "demo-part" and p.version == "2.0" and len(p.fingerprint) == 12
    assert [c.name for c in p.characteristics] == ["high_top_flatness", "low_top_flatness", "boss_cylindricity",
                                                   "high_top_profile", "high_top_sq"]
    assert p.characteristic("boss_cylindricity").method == "minimum_zone"
    assert p.characteristic("high_top_sq").method is None
    assert p.scan.views == 1 and p.scan.exposure_s == 0.010 and p.scan.pattern_set().n_frames == 12
    faces = cad_faces(p)
    assert p.face_check == "13 faces in demo_part.step, all 5 characteristics found" and len(faces) == 13
    assert (faces["#657"], faces["#158"], faces["#17"], faces["#105"]) == ("plane", "plane", "cylinder", "cone")


def test_demo_program_and_the_simulated_parts_name_the_same_faces() -> None:
    """The simulated parts' truth is keyed by characteristic name and imposed on STEP faces;
    the program must measure each characteristic on the face the simulator deformed."""
    assert {c.name: c.face for c in load_program(DEMO_PROGRAM).characteristics} == CHARACTERISTIC_FACES


@pytest.mark.parametrize("edit, key", [
    (('kind = "profile"', 'kind = "roundness"'), "characteristic[3].kind"),
    (('"minimum_zone"\ntolerance_mm = 0.05\n', '"minimum_zone"\ntolerance_mm = -0.05\n'),
     "characteristic[0].tolerance_mm"),
    (('"minimum_zone"\ntolerance_mm = 0.05\n', '"minimum_zone"\ntolerance_mm = inf\n'),  # issue 15
     "characteristic[0].tolerance_mm"),
    (("views = 1", "views = 1\n\n[control]\nsubgroup_size = 11"), "control.subgroup_size"),
    (("views = 1", "views = 1\n\n[control]\nsubgroup = 5"), "control.subgroup"),
    (('method = "minimum_zone"', 'method = "chebyshev"'), "characteristic[0].method"),
    (('kind = "sq"', 'kind = "sq"\nmethod = "least_squares"'), "characteristic[4].method"),
    (('name = "low_top_flatness"', 'name = "high_top_flatness"'), "characteristic[1].name"),
    (("views = 1", "views = 0"), "scan.views"),
    (("exposure_s = 0.010", 'exposure_s = "fast"'), "scan.exposure_s"),
    (("views = 1", "view = 1"), "scan.view"),
    (('id = "factory-sim-bench"', 'identity = "factory-sim-bench"'), "calibration.identity"),
    (('version = "2.0"\n', ""), "program.version"),
])
def test_bad_program_names_file_and_key(tmp_path: Path, edit: tuple[str, str], key: str) -> None:
    path = program_copy(tmp_path, edit)
    with pytest.raises(ConfigError) as err:
        load_program(path)
    assert err.value.key == key and str(path) in str(err.value)


def test_face_the_cad_does_not_have_is_refused(tmp_path: Path) -> None:
    path = program_copy(tmp_path, ('face = "#158"', 'face = "#999"'))
    with pytest.raises(ConfigError, match="face '#999' .* is not in demo_part.step; its faces are #17, #105") as err:
        load_program(path, faces=cad_faces)
    assert err.value.key == "characteristic[1].face"
    assert load_program(path).characteristics[1].face == "#999"  # the schema alone is fine


@pytest.mark.parametrize("edit, problem", [
    (('face = "#158"', 'face = "#105"'), "flatness applies to plane faces; face #105 of demo_part.step is a cone"),
    (('face = "#17"', 'face = "#270"'),
     "cylindricity applies to cylinder faces; face #270 of demo_part.step is a plane"),
])
def test_characteristic_on_a_face_of_the_wrong_type_is_refused(tmp_path: Path, edit: tuple[str, str],
                                                               problem: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_program(program_copy(tmp_path, edit), faces=cad_faces)
    assert err.value.problem == problem


def test_mesh_face_of_no_known_type_is_refused_for_a_form_characteristic(tmp_path: Path) -> None:
    """A mesh CAD model has faces but no surface types: flatness on one is refused."""
    path = program_copy(tmp_path, ('face = "#657"', 'face = "F3"'), cad=f'"{CONFIG_DIR / "parts" / "demo_part.ply"}"')
    with pytest.raises(ConfigError) as err:
        load_program(path, faces=cad_faces)
    assert err.value.key == "characteristic[0].face"
    assert err.value.problem == ("flatness applies to plane faces; face F3 of demo_part.ply is a mesh face "
                                 "(a mesh face of no known surface type: use a STEP model)")


def test_missing_cad_file_is_named(tmp_path: Path) -> None:
    path = program_copy(tmp_path, ('cad = "', 'cad = "/nonexistent/'))
    with pytest.raises(ConfigError, match="CAD file not found") as err:
        load_program(path)
    assert err.value.key == "program.cad"


def test_station_config_errors_name_the_key(tmp_path: Path) -> None:
    good = StationConfig.load(station_config(tmp_path))
    assert good.database_url == f"sqlite:{tmp_path / 'data' / 'results.sqlite'}"
    for extra, key in (({"max_calibration_age_days": -1}, "station.max_calibration_age_days"),
                       ({"databse": "x"}, "station.databse")):
        with pytest.raises(ConfigError) as err:
            StationConfig.load(station_config(tmp_path, **extra))
        assert err.value.key == key
    with pytest.raises(ConfigError) as err:
        StationConfig.load(station_config(tmp_path, database="mysql://x"))
    assert err.value.key == "station.database"
    with pytest.raises(ConfigError) as err:  # issue 15: no message shows a password
        StationConfig.load(station_config(tmp_path, database="mysql://ana:s3cr3t@db/x"))
    assert "s3cr3t" not in str(err.value) and "mysql://ana:***@db/x" in str(err.value)


def test_simulated_rig_has_the_factory_calibration_and_it_matches_the_demo_program(tmp_path: Path) -> None:
    config = RigConfig.load(small_rig_toml(tmp_path))
    info = rig_calibration(config)
    assert info.id == "factory-sim-bench" and info.date is None and info.camera_size == (320, 256)
    assert refusals(info, config, load_program(DEMO_PROGRAM), 365, TODAY) == []


def test_calibration_mismatch_expiry_and_sizes_refuse_measuring(tmp_path: Path) -> None:
    config = RigConfig.load(small_rig_toml(tmp_path))
    program = load_program(DEMO_PROGRAM)  # expects factory-sim-bench, at most 180 days old
    dated = CalibrationInfo("factory-sim-bench", TODAY - dt.timedelta(days=200), (320, 256), (912, 1140), "cal.toml")
    [why] = refusals(dated, config, program, 365, TODAY)
    assert why.startswith("calibration expired") and "200 days old, the limit is 180 days" in why
    assert refusals(replace(dated, date=TODAY - dt.timedelta(days=100)), config, program, 365, TODAY) == []
    [why] = refusals(replace(dated, date=TODAY - dt.timedelta(days=100)), config, program, 90, TODAY)
    assert "limit is 90 days" in why  # the station's limit is stricter than the program's
    [why] = refusals(replace(dated, id="cal-2026-01", date=TODAY), config, program, 365, TODAY)
    assert "calibration mismatch" in why and "'factory-sim-bench'" in why and "'cal-2026-01'" in why
    [why] = refusals(replace(dated, date=TODAY, camera_size=(1280, 1024)), config, program, 365, TODAY)
    assert why == "calibration is for a 1280x1024 camera, rig.toml has 320x256"


def test_hardware_rig_without_calibration_file_is_uncalibrated(tmp_path: Path) -> None:
    config = RigConfig.load(small_rig_toml(tmp_path))
    hw = replace(config, driver="hardware")
    info = rig_calibration(hw)
    assert info.id is None and "uncalibrated" in info.problem
    assert refusals(info, hw, load_program(DEMO_PROGRAM), 365, TODAY) == [info.problem]


def test_calibration_file_named_by_the_rig_gives_its_id_and_date_and_can_expire(tmp_path: Path) -> None:
    from scanner.calibration_file import write_calibration

    rig = small_rig_toml(tmp_path)
    created = dt.datetime(2026, 4, 1, 9, 30, 5, tzinfo=dt.UTC)
    cal = write_calibration(tmp_path / "cal.json", RigConfig.load(rig).nominal_model(), {}, "sim-bench")
    cal.write_text(json.dumps({**json.loads(cal.read_text()), "created": created.isoformat()}))
    rig.write_text(rig.read_text().replace("[rig]\n", '[rig]\ncalibration = "cal.json"\n', 1))
    config = RigConfig.load(rig)
    info = rig_calibration(config)
    assert (info.id, info.date, info.camera_size, info.source) == ("sim-bench@2026-04-01T09:30:05", created.date(),
                                                                   (320, 256), str(tmp_path / "cal.json"))
    program = load_program(program_copy(tmp_path, ('id = "factory-sim-bench"', 'id = "sim-bench@2026-04-01T09:30:05"')))
    assert refusals(info, config, program, 365, dt.date(2026, 9, 1)) == []
    [why] = refusals(info, config, program, 365, TODAY)  # 236 days later: past the program's 180
    assert why == ("calibration expired: sim-bench@2026-04-01T09:30:05 dated 2026-04-01 is 236 days old, "
                   "the limit is 180 days")
    [why] = refusals(info, config, load_program(DEMO_PROGRAM), 365, dt.date(2026, 9, 1))
    assert why.startswith("calibration mismatch: demo_part.toml expects calibration.id 'factory-sim-bench'")


@pytest.mark.parametrize("edit, key, problem", [
    (("tolerance_mm = 0.05", "tolerence_mm = 0.05"), "characteristic[0].tolerence_mm", "did you mean 'tolerance_mm'"),
    (("tolerance_mm = 0.05", "tolerance_mm = nan"), "characteristic[0].tolerance_mm", "finite number"),
    (("views = 1", "veiws = 1"), "scan.veiws", "did you mean 'views'"),
    (('mesh_unit', 'mesh_unit'), None, None),
])
def test_program_on_the_schema_layer_names_the_nearest_key(tmp_path: Path, edit: tuple[str, str], key: str | None,
                                                           problem: str | None) -> None:
    """Issue 15 item D: part programs on the project's validation layer (scanner.schema)."""
    if key is None:  # the program may state a mesh unit; an unknown one is refused
        path = program_copy(tmp_path, ('version = "2.0"\n', 'version = "2.0"\nmesh_unit = "furlong"\n'))
        key, problem = "program.mesh_unit", "must be"
    else:
        path = program_copy(tmp_path, edit)
    with pytest.raises(ConfigError, match=problem) as err:
        load_program(path)
    assert err.value.key == key


def test_station_config_on_the_schema_layer(tmp_path: Path) -> None:
    for extra, key, problem in (({"max_calibration_age_days": float("nan")}, "station.max_calibration_age_days",
                                 "finite"),
                                ({"opertor": "ana"}, "station.opertor", "did you mean 'operator'")):
        path = station_config(tmp_path, **extra)
        path.write_text(path.read_text().replace("NaN", "nan"))
        with pytest.raises(ConfigError, match=problem) as err:
            StationConfig.load(path)
        assert err.value.key == key
