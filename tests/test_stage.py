"""The stage interface: one contract for the simulated stage and the GRBL driver on its
emulator; stage geometry against closed forms; the `[stage]` table; the simulated stage
turning the scene (against the scene's own geometry) and its injected faults; a hardware
rig opening its GRBL turntable."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from driver_rigs import LCR, lcr_transports, variant

from scanner.config import CONFIG_DIR
from scanner.drivers.grbl import GrblStage
from scanner.drivers.grbl_emulator import GrblEmulator
from scanner.drivers.testing import wait_bound_s
from scanner.errors import ConfigError, DeviceDisconnected, DeviceError, NotHomed, OutOfTravel, StageAlarm
from scanner.rig import RigConfig, open_rig
from scanner.stage import Axis, AxisKind, Stage
from scanner.stage_model import AxisGeometry, StageModel
from sim.virtual_stage import SimStage, StageFaults, turned_scene

TURNTABLE = CONFIG_DIR / "rigs" / "sim_turntable.toml"
TURNTABLE_SCENE = CONFIG_DIR / "scenes" / "turntable_demo.toml"
STAGE_METHODS = {"_do_move", "_do_home", "_do_position", "_do_stop", "_do_shutdown"}  # written out, not read
FAST = Axis("turntable", AxisKind.ROTARY, (math.radians(-400), math.radians(400)), math.radians(720))


@pytest.fixture(params=["sim", "grbl"])
def stage(request: pytest.FixtureRequest) -> Iterator[Stage]:
    if request.param == "sim":
        s: Stage = SimStage("sim-stage", [FAST], settle_s=0.05)
    else:
        emulator = GrblEmulator(rate=720.0)
        s = GrblStage(lambda: emulator, [FAST], {"turntable": "X"}, settle_s=0.05, timeout_s=0.2)
    yield s
    s.shutdown()


def test_every_driver_method_is_abstract() -> None:
    assert Stage.__abstractmethods__ == STAGE_METHODS


def test_contract_move_position_and_status(stage: Stage) -> None:
    for deg in (90.0, -45.0, 360.0):
        status = stage.move_to({"turntable": math.radians(deg)})
        assert stage.moving or status.done
        status.wait(wait_bound_s(1.0))
        assert status.success and not stage.moving
        assert math.degrees(stage.position()["turntable"]) == pytest.approx(deg, abs=0.01)


def test_contract_checks_come_before_the_driver(stage: Stage) -> None:
    with pytest.raises(OutOfTravel, match="turntable: target 500 deg is outside its travel -400 deg .. 400 deg"):
        stage.move_to({"turntable": math.radians(500)})
    with pytest.raises(DeviceError, match="no axis named 'x'"):
        stage.move_to({"x": 1.0})
    with pytest.raises(DeviceError, match="not a finite position"):
        stage.move_to({"turntable": math.nan})
    assert stage.position()["turntable"] == pytest.approx(0.0, abs=1e-6)  # nothing moved


def test_contract_one_move_at_a_time_and_stop(stage: Stage) -> None:
    status = stage.move_to({"turntable": math.radians(380)})  # 0.53 s at 720 deg/s
    with pytest.raises(DeviceError, match="still running"):
        stage.move_to({"turntable": 0.0})
    stage.stop()
    with pytest.raises(DeviceError, match="stopped before it had finished"):
        status.wait(wait_bound_s(1.0))
    stage.move_to({"turntable": 0.0}).wait(wait_bound_s(1.0))  # usable again


def test_contract_shutdown_is_idempotent_and_final(stage: Stage) -> None:
    status = stage.move_to({"turntable": math.radians(380)})
    stage.shutdown()
    stage.shutdown()
    with pytest.raises(DeviceDisconnected):
        status.wait(wait_bound_s(1.0))
    with pytest.raises(DeviceDisconnected):
        stage.position()
    stage.stop()  # harmless after shutdown


def test_settle_time_is_waited_after_the_motion() -> None:
    import threading

    ended = threading.Event()
    s = SimStage("sim-stage", [FAST], settle_s=0.3, on_moved=lambda q: ended.set())
    status = s.move_to({"turntable": math.radians(10)})
    assert ended.wait(wait_bound_s(1.0))
    assert not status.done  # the motion has ended, the settle time not yet (0.3 s >> a callback's return)
    status.wait(wait_bound_s(1.0))
    s.shutdown()


def test_simulated_stage_prepares_the_scene_before_the_moves_clock_starts() -> None:
    """The simulator renders the turned scene before a move's status (and its deadline)
    exists, so its own computing never times a move out; the motion's end swaps it in."""
    seen: list[tuple[dict[str, float], bool]] = []
    s = SimStage("sim-stage", [FAST], prepare=lambda goal: seen.append((goal, s.moving)),
                 on_moved=lambda q: seen.append((q, s.moving)))
    s.move_to({"turntable": math.radians(30)}).wait(wait_bound_s(1.0))
    s.home().wait(wait_bound_s(1.0))
    assert [(round(math.degrees(q["turntable"]), 9), moving) for q, moving in seen] == [
        (30.0, False), (30.0, True), (0.0, False), (0.0, True)]  # prepared while no action ran, then arrived
    s.shutdown()


# ------------------------------------------------------------------ geometry


def test_rotary_axis_motion_against_closed_forms() -> None:
    d = np.array([0.0, -math.sin(0.8), -math.cos(0.8)])
    p = np.array([5.0, 10.0, 400.0])
    model = StageModel((AxisGeometry("t", AxisKind.ROTARY, d * 3.0, p),))  # direction normalised on load
    T = model.world_from_stage({"t": math.radians(60)})
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    on_axis = p + 17.0 * d
    assert np.allclose(T[:3, :3] @ on_axis + T[:3, 3], on_axis)  # points on the axis stay
    u = np.cross(d, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    x = p + 20.0 * u  # a point 20 mm off the axis travels a chord 2 r sin(60/2)
    y = T[:3, :3] @ x + T[:3, 3]
    assert np.linalg.norm(y - x) == pytest.approx(2 * 20.0 * math.sin(math.radians(30)))
    assert np.dot(y - p, d) == pytest.approx(0.0, abs=1e-9)  # in the plane through p normal to the axis
    assert np.dot(np.cross(x - p, y - p), d) > 0  # right-handed about d
    T2 = model.world_from_stage({"t": math.radians(120)})
    assert np.allclose(T2, T @ T)


def test_linear_axis_carrying_a_turntable_composes_base_first() -> None:
    slide = AxisGeometry("slide", AxisKind.LINEAR, np.array([1.0, 0.0, 0.0]))
    table = AxisGeometry("table", AxisKind.ROTARY, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.0]))
    T = StageModel((slide, table)).world_from_stage({"slide": 30.0, "table": math.pi / 2})
    # the part point (10, 0, 0): turned about the table's axis to (0, 10, 0), then slid 30 mm along x
    assert np.allclose(T @ [10.0, 0.0, 0.0, 1.0], [30.0, 10.0, 0.0, 1.0])


def test_stage_table_errors_name_the_key(tmp_path: Path) -> None:
    base = TURNTABLE.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    cases = [('kind = "rotary"', 'kind = "spinning"', "stage.axes\\[0\\].kind"),
             ("speed_deg_s = 90.0", "speed_mm_s = 90.0", "stage.axes\\[0\\].speed_mm_s"),
             ('driver = "sim"\nsettle_s', 'driver = "cnc"\nsettle_s', "stage.driver"),
             ("settle_s = 0.2", "settle_s = 0.2\nsettle = 1", "stage.settle'"),
             ("direction = [0.0, -0.766044443118978, -0.6427876096865394]", "direction = [0.0, 0.0, 0.0]",
              "stage.axes\\[0\\]"),
             ("settle_s = 0.2", 'settle_s = 0.2\ncalibration = "missing.json"', "stage.calibration")]
    for old, new, key in cases:
        path = tmp_path / "rig.toml"
        assert old in base, old
        path.write_text(base.replace(old, new, 1))
        with pytest.raises(ConfigError, match=f"key '{key}"):
            RigConfig.load(path)


# ------------------------------------------------------------------ the simulated stage in a rig


def small_turntable(tmp: Path, extra: str = "") -> RigConfig:
    text = TURNTABLE.read_text().replace('"../patterns/', f'"{CONFIG_DIR}/patterns/')
    text = text.replace("width = 1280", "width = 320").replace("height = 1024", "height = 256")
    text = text.replace("speed_deg_s = 90.0", "speed_deg_s = 720.0").replace("settle_s = 0.2", "settle_s = 0.0")
    path = tmp / "turntable.toml"
    path.write_text(text + extra)
    return RigConfig.load(path)


def test_simulated_stage_turns_the_scene(tmp_path: Path) -> None:
    from sim.render import compute_ground_truth
    from sim.scene import load_scene

    config = small_turntable(tmp_path)
    with open_rig(config, scene=TURNTABLE_SCENE) as rig:
        assert isinstance(rig.stage, SimStage)
        before = rig.extras["ground_truth"].depth.copy()
        rig.stage.move_to({"turntable": math.radians(90)}).wait(wait_bound_s(5.0))
        after = rig.extras["ground_truth"]
        assert rig.camera.renderer is rig.extras["renderer"]
        # independently: the scene's part turned 90 degrees about the TOML's axis line, ray-cast afresh
        d = np.array([0.0, -0.766044443118978, -0.6427876096865394])
        p = np.array([0.0, 11.49066664678467, 409.6418141452981])
        K = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
        T = np.eye(4)
        T[:3, :3] = np.eye(3) + K + K @ K  # Rodrigues at 90 degrees: sin 1, 1 - cos 1
        T[:3, 3] = p - T[:3, :3] @ p
        expected = compute_ground_truth(rig.extras["renderer"].model, turned_scene(load_scene(TURNTABLE_SCENE), T))
        assert np.array_equal(np.isnan(after.depth), np.isnan(expected.depth))
        assert np.nanmax(np.abs(after.depth - expected.depth)) < 1e-9
        assert np.nanmax(np.abs(after.depth - before)) > 5.0  # and it did change
        assert np.allclose(rig.extras["world_from_stage"], T)


@pytest.mark.parametrize(("fault", "error", "message"), [
    ("alarm_at_move", StageAlarm, "alarm during move 1: limit switch triggered"),
    ("disconnect_at_move", DeviceDisconnected, "stage disconnected during a move")])
def test_simulated_stage_faults_give_named_errors_in_bounded_time(fault: str, error: type, message: str) -> None:
    s = SimStage("sim-stage", [FAST], faults=StageFaults(**{fault: 1}))
    s.move_to({"turntable": math.radians(45)}).wait(wait_bound_s(1.0))
    with pytest.raises(error, match=message):
        s.move_to({"turntable": math.radians(90)}).wait(wait_bound_s(1.0))
    if fault == "disconnect_at_move":
        with pytest.raises(DeviceDisconnected):
            s.position()
    else:
        assert 45 < math.degrees(s.position()["turntable"]) < 90  # stopped half-way
    s.shutdown()


def test_simulated_silent_stage_fails_at_the_move_deadline(monkeypatch: pytest.MonkeyPatch) -> None:
    from scanner import devices
    from scanner.errors import DeviceTimeout

    monkeypatch.setattr(devices, "SEQUENCE_DEADLINE_SLACK_S", 0.5)
    s = SimStage("sim-stage", [FAST], faults=StageFaults(silent_at_move=0))
    with pytest.raises(DeviceTimeout, match="move \\(turntable to 45 deg\\) not finished after 0.812 s; "
                                             "the device stopped advancing it"):
        s.move_to({"turntable": math.radians(45)}).wait(wait_bound_s(0.812))
    s.shutdown()


def test_homing_stage_refuses_moves_until_homed() -> None:
    axis = Axis("turntable", AxisKind.ROTARY, speed=math.radians(720), requires_homing=True)
    s = SimStage("sim-stage", [axis])
    with pytest.raises(NotHomed):
        s.move_to({"turntable": 1.0})
    s.home().wait(wait_bound_s(1.0))
    s.move_to({"turntable": 1.0}).wait(wait_bound_s(1.0))
    s.shutdown()


def test_hardware_rig_opens_its_grbl_turntable(tmp_path: Path) -> None:
    table = ('\n[stage]\ndriver = "grbl"\nport = "/dev/ttyUSB9"\nsettle_s = 0.0\n[[stage.axes]]\nname = "turntable"\n'
             'kind = "rotary"\ndirection = [0.0, -0.77, -0.64]\npoint_mm = [0.0, 10.0, 400.0]\nletter = "Z"\n'
             'units_per_turn = 360.0\nspeed_deg_s = 720.0\n')
    config = variant(tmp_path, LCR)
    path = tmp_path / "with_stage.toml"
    path.write_text(config.path.read_text() + table)
    emulator = GrblEmulator()
    with open_rig(RigConfig.load(path), transports={**lcr_transports(), "stage": lambda: emulator}) as rig:
        assert isinstance(rig.stage, GrblStage) and rig.stage.letters == {"turntable": "Z"}
        rig.stage.move_to({"turntable": math.radians(30)}).wait(wait_bound_s(1.0))
        assert "G21G90G0Z30.000" in emulator.lines
    assert rig.stage.is_shut_down
    path.write_text(config.path.read_text() + table.replace('"grbl"', '"sim"'))
    with pytest.raises(ConfigError, match="stage.driver.*a hardware rig drives a real stage"):
        open_rig(RigConfig.load(path), transports=lcr_transports())
