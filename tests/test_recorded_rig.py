"""Issue 29: a session's recorded rig config (manifest.json `rig_config`) read through typed
tables (`Manifest.recorded_rig`, `scanner.rig_schema.RecordedRig`), on manifests written
here: the rig TOML as captured, an imported session's stand-in, an older session's tables
the current rig schema refuses, and malformed tables."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from scanner.config import load_toml
from scanner.decode_checks import Volume, sensor_noise_source, sensor_noise_terms
from scanner.errors import ConfigError, SessionError
from scanner.patterns import PatternSet
from scanner.pipeline import model_accuracy_px, recording_level
from scanner.rig import DEFAULT_RIG, RigConfig
from scanner.rig_schema import RigTable
from scanner.session import MANIFEST_VERSION, Session, json_ready
from slscan.measurement_model import recorded_measurement, rig_measurement, sensor_noise

CONFIG = RigConfig.load(DEFAULT_RIG)  # the simulated bench: 12-bit camera, [camera.sensor], [acceptance]
CAPTURED = load_toml(DEFAULT_RIG)
IMPORTED = {"name": "imported from frames/", "driver": "import"}  # what `slscan import` records


def manifest(rig_config: Any) -> dict[str, Any]:
    """A manifest as a capture writes it (one frame), recording `rig_config`."""
    model = CONFIG.nominal_model()
    frame = {"k": 0, "file": "frames/frame_000.png", "index": 0, "timestamp_s": 0.0, "bit_depth": 12,
             "shape": [model.camera.height, model.camera.width], "dtype": "uint16"}
    return {"slscan_manifest": MANIFEST_VERSION, "session_id": "s", "rig_config": rig_config,
            "rig_model": json_ready(model.to_dict()), "patterns": PatternSet.load(CONFIG.patterns_path).to_dict(),
            "frames": [frame]}


def opened(rig_config: Any, root: Path) -> Session:
    return Session.checked(root, manifest(rig_config))


def edited(**tables: Any) -> dict[str, Any]:
    """The captured config with these tables replaced."""
    return {**copy.deepcopy(CAPTURED), **tables}


def test_a_captured_config_reads_as_its_tables(tmp_path: Path) -> None:
    session = opened(CAPTURED, tmp_path)
    rig = session.manifest.recorded_rig
    assert (rig.rig.name, rig.rig.driver, rig.rig.working_distance_mm) == ("sim-bench", "sim", 400.0)
    assert rig.rig.period_s == CAPTURED["rig"]["period_s"] == 0.05
    assert rig.camera.bit_depth == 12 and rig.projector.blur_sigma_px == 0.8 and rig.recording.level == "display"
    assert rig.sensor is not None and (rig.sensor.full_well_e, rig.sensor.blur_sigma_px) == (10500.0, 0.6)
    assert rig is session.manifest.recorded_rig  # read once, kept
    volume = Volume.of_recorded(rig)
    assert (volume.near_mm, volume.far_mm) == (360.0, 440.0)
    g = 10500.0 / 4095
    assert sensor_noise_terms(rig.sensor, 12) == pytest.approx(((6.0 / g) ** 2 + 1 / 12, 1 / g))
    assert model_accuracy_px(session, CONFIG.nominal_model()) == 0.0  # the simulator's nominal geometry
    assert recording_level(session) == "display"
    measured = recorded_measurement(rig, CONFIG.nominal_model(), session.patterns, 12)
    assert measured.camera_blur_px == 0.6 and measured.sensor is not None


@pytest.mark.parametrize("config", [IMPORTED, {}], ids=["imported", "empty"])
def test_an_imported_or_empty_config_reads_as_the_defaults(tmp_path: Path, config: dict[str, Any]) -> None:
    session = opened(config, tmp_path)
    rig = session.manifest.recorded_rig
    assert (rig.rig.driver, rig.rig.working_distance_mm, rig.camera.bit_depth, rig.sensor) == (None, None, None, None)
    assert (rig.projector.blur_sigma_px, recording_level(session)) == (0.0, "display")
    assert rig.rig.period_s == RigTable.model_fields["period_s"].default  # what a capture sequences without one
    assert Volume.of_recorded(rig).near_mm is None and sensor_noise_terms(rig.sensor, 12) is None
    assert model_accuracy_px(session, CONFIG.nominal_model()) is None and sensor_noise(rig.sensor, 12) is None


def test_an_older_sessions_tables_read_though_the_rig_schema_refuses_them(tmp_path: Path) -> None:
    """Keys no reader after capture needs are ignored: a [rig] key since removed, a camera
    without its lens, an [acceptance] MPE the current schema refuses (E_mm)."""
    config = edited(rig={**CAPTURED["rig"], "retired_key": 1, "period_s": 0.1},
                    camera={"bit_depth": 12, "sensor": CAPTURED["camera"]["sensor"]},
                    acceptance={**CAPTURED["acceptance"], "mpe": {"E_mm": 0.1}})
    rig = opened(config, tmp_path).manifest.recorded_rig
    assert rig.rig.driver == "sim" and rig.camera.bit_depth == 12 and rig.acceptance.volume_mm == [130.0, 110.0, 80.0]
    assert rig.rig.period_s == 0.1


def test_a_sensor_table_the_schema_refuses_stops_its_readers_only(tmp_path: Path) -> None:
    config = edited(camera={**CAPTURED["camera"], "sensor": {"full_well_e": 5.0}})
    session = opened(config, tmp_path)  # opens: the frames' bit depth is checked apart from the sensor
    assert session.manifest.recorded_rig.camera.bit_depth == 12
    with pytest.raises(ConfigError, match=r"rig_config\.camera\.sensor\.full_well_e"):
        sensor_noise_terms(session.manifest.recorded_rig.sensor, 12)


def test_sensor_terms_take_what_the_measurement_model_assumes(tmp_path: Path) -> None:
    """Without full_well_e no photon transfer is stated; a read noise left out is the one the
    simulator rendered and the measurement model assumes (6 e-, the [camera.sensor] default),
    and the noise source says it is assumed; an empty table states no sensor."""
    def rig(sensor: dict[str, Any]) -> Any:
        return opened(edited(camera={**CAPTURED["camera"], "sensor": sensor}), tmp_path).manifest.recorded_rig

    assert sensor_noise_terms(rig({"read_noise_e": 6.0}).sensor, 12) is None
    assert sensor_noise_source(rig({"read_noise_e": 6.0}).sensor) is None
    assert rig({}).sensor is None
    gain = 10500.0 / (2 ** 12 - 1)  # e-/DN: the full well over the full scale
    for table, read_e in (({"full_well_e": 10500.0}, 6.0), ({"full_well_e": 10500.0, "read_noise_e": 2.0}, 2.0)):
        sensor = rig(table).sensor
        read, shot = sensor_noise_terms(sensor, 12)
        assert (read, shot) == pytest.approx(((read_e / gain) ** 2 + 1 / 12, 1 / gain), rel=1e-12)
        mean_dn = np.array([0.0, 40.0, 1500.0, 4000.0])
        assert np.sqrt(read + shot * mean_dn) == pytest.approx(sensor_noise(sensor, 12)(mean_dn), rel=1e-12)
    assert sensor_noise_source(rig({"full_well_e": 10500.0, "read_noise_e": 2.0}).sensor) == "sensor model"
    assumed = sensor_noise_source(rig({"full_well_e": 10500.0}).sensor)
    assert assumed == "sensor model (read noise 6 e- assumed: the rig file's [camera.sensor] states none)"


def test_a_malformed_value_is_refused_where_it_was_read(tmp_path: Path) -> None:
    with pytest.raises(SessionError, match=r"rig_config\.camera\.bit_depth.*expected a whole number"):
        opened(edited(camera={**CAPTURED["camera"], "bit_depth": "12"}), tmp_path)
    with pytest.raises(SessionError, match=r"rig_config\.camera.*expected a table"):
        opened(edited(camera="12-bit"), tmp_path)
    with pytest.raises(SessionError, match="camera.bit_depth is 16"):  # a mismatch, as before
        opened(edited(camera={**CAPTURED["camera"], "bit_depth": 16}), tmp_path)
    session = opened(edited(recording={"level": "most"}, projector={**CAPTURED["projector"], "blur_sigma_px": "0.8"}),
                     tmp_path)
    with pytest.raises(ConfigError, match=r"rig_config\.recording\.level"):
        recording_level(session)
    with pytest.raises(ConfigError, match=r"rig_config\.projector\.blur_sigma_px"):
        recorded_measurement(session.manifest.recorded_rig, CONFIG.nominal_model(), session.patterns, 12)


def test_an_error_names_the_sessions_manifest(tmp_path: Path) -> None:
    """Of many sessions, the one whose manifest is malformed: its folder's manifest.json is named,
    whether the key is refused on opening or when first read."""
    def written(name: str, **tables: Any) -> Path:
        root = tmp_path / name
        root.mkdir()
        (root / "manifest.json").write_text(json.dumps(manifest(edited(**tables))))
        return root

    refused = written("scan-0007", camera={**CAPTURED["camera"], "bit_depth": "12"})
    with pytest.raises(SessionError) as opening:
        Session.open(refused)
    assert str(opening.value).startswith(f"{refused / 'manifest.json'}, key 'rig_config.camera.bit_depth'")
    later = written("scan-0008", camera={**CAPTURED["camera"], "sensor": {"full_well_e": 5.0}})
    with pytest.raises(ConfigError) as reading:
        sensor_noise_terms(Session.open(later).manifest.recorded_rig.sensor, 12)
    assert str(reading.value).startswith(f"{later / 'manifest.json'}, key 'rig_config.camera.sensor.full_well_e'")


def test_a_malformed_rig_or_acceptance_table_declares_no_distance_as_before(tmp_path: Path) -> None:
    """The working distance and measuring volume only narrow a check: a malformed [rig] or
    [acceptance] reads as none (the session opens, judged at any distance), as before the
    tables were typed; the driver, which the checks rely on, is refused."""
    session = opened(edited(rig="sim-bench"), tmp_path)
    assert Volume.of_recorded(session.manifest.recorded_rig).near_mm is None
    with pytest.raises(ConfigError, match=r"rig_config\.rig.*expected a table"):
        model_accuracy_px(session, CONFIG.nominal_model())
    rig = opened(edited(acceptance={"volume_mm": [130.0, 110.0]}), tmp_path).manifest.recorded_rig
    assert Volume.of_recorded(rig).near_mm is None


def test_a_rig_toml_reads_through_the_same_tables() -> None:
    """`rig_measurement` on a rig TOML's content: errors name the key in that file."""
    model, patterns = CONFIG.nominal_model(), PatternSet.load(CONFIG.patterns_path)
    assert rig_measurement(CAPTURED, model, patterns, 12, DEFAULT_RIG).camera_blur_px == 0.6
    broken = edited(camera={**CAPTURED["camera"], "sensor": {"full_well_e": "many"}})
    with pytest.raises(ConfigError, match=r"key 'camera\.sensor\.full_well_e'"):
        rig_measurement(broken, model, patterns, 12, DEFAULT_RIG)
