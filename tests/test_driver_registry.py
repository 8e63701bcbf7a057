"""Drivers own their settings (docs/drivers.md): each driver module declares its name, the
schema of its keys and how it opens; the core schema keeps `driver` and the keys every
device of a kind has. A new driver is one new module: the registry finds it, a rig file
names it, its keys are validated at load, and the hardware rig opens it."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import scanner.drivers
from scanner.config import CONFIG_DIR
from scanner.drivers import registry
from scanner.drivers.testing import FakeDisplay
from scanner.errors import ConfigError
from scanner.rig import RigConfig, open_rig

RIGS = CONFIG_DIR / "rigs"
LCR, HDMI, BENCH, TURNTABLE = (RIGS / f"{n}.toml" for n in ("lightcrafter_uvc_box", "hdmi_genicam", "sim_bench",
                                                             "sim_turntable"))


def edited(tmp: Path, source: Path, *edits: tuple[str, str]) -> Path:
    text = source.read_text().replace('"../', f'"{CONFIG_DIR}/')
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp / source.name
    path.write_text(text)
    return path


def refused(path: Path) -> ConfigError:
    with pytest.raises(ConfigError) as exc:
        RigConfig.load(path)
    assert str(path) in str(exc.value) and "\n" not in str(exc.value)
    return exc.value


def test_the_existing_drivers_declare_themselves() -> None:
    found = {kind: set(registry.drivers(kind)) for kind in ("rig", "camera", "projector", "trigger_box", "stage")}
    assert found == {"rig": {"sim", "hardware"}, "camera": {"sim", "uvc", "genicam"},
                     "projector": {"sim", "hdmi", "lightcrafter4500"}, "trigger_box": {"sim", "triggerbox"},
                     "stage": {"sim", "grbl"}}
    assert set(registry.drivers("camera", "hardware")) == {"uvc", "genicam"}


def test_bundled_rigs_name_their_drivers_and_their_settings_are_typed() -> None:
    lcr = RigConfig.load(LCR).devices
    assert {k: d.driver.name for k, d in lcr.items()} == {"rig": "hardware", "camera": "uvc",
                                                         "projector": "lightcrafter4500", "trigger_box": "triggerbox"}
    assert lcr["camera"].settings.fps == 30.0 and lcr["projector"].settings.led_currents == [104, 135, 130]
    assert lcr["trigger_box"].settings.port == "/dev/ttyACM0"  # no driver key: the hardware rig's only trigger box
    bench = RigConfig.load(BENCH).devices  # a sim rig's tables name no driver: the sim rig's own
    assert bench["camera"].driver.name == "sim" and bench["camera"].settings.sensor.read_noise_e == 6.0
    assert bench["projector"].settings.blur_sigma_px == 0.8
    assert RigConfig.load(TURNTABLE).stage.driver == "sim"


@pytest.mark.parametrize("source, edits, key, words", [
    (LCR, [('driver = "uvc"', 'driver = "webcam"')], "camera.driver", "'webcam' is not one of ('genicam', 'uvc')"),
    (LCR, [('driver = "hardware"', 'driver = "robot"')], "rig.driver", "'robot' is not one of ('hardware', 'sim')"),
    (LCR, [('driver = "uvc"\n', '')], "camera.driver", "required key is missing"),
    (BENCH, [("width = 1280", 'driver = "uvc"\nwidth = 1280')], "camera.driver", "a sim rig drives a simulated camera"),
    (LCR, [('driver = "lightcrafter4500"', 'driver = "sim"')], "projector.driver",
     "a hardware rig drives a real projector; set driver = 'hdmi' or 'lightcrafter4500'"),
    (LCR, [("fps = 30.0", "fps = -30.0")], "camera.fps", "greater than 0"),
    (LCR, [("fps = 30.0", "fsp = 30.0")], "camera.fsp", "did you mean 'fps'?"),
    (LCR, [("bit_depth = 8", "bit_detph = 8")], "camera.bit_detph", "did you mean 'bit_depth'?"),
    (LCR, [('port = "/dev/ttyACM0"\n', "")], "trigger_box.port", "required key is missing"),
    (LCR, [('source = "flash"', 'source = "flesh"')], "projector.source", "'flash' or 'video'"),
    (BENCH, [("blur_sigma_px = 0.8", "blur_sigma_px = 80.0")], "projector.blur_sigma_px", "[0, 10]"),
    (BENCH, [("[camera.sensor]", "[sim.faults]\ndrop_frame = -1\n\n[camera.sensor]")], "sim.faults.drop_frame",
     "greater than or equal to 0"),
    (LCR, [("[trigger_box]", "[sim.faults]\ndrop_frame = 1\n\n[trigger_box]")], "sim", "unknown key"),
])
def test_driver_keys_are_the_drivers_and_refused_at_load(tmp_path: Path, source: Path, edits: list, key: str,
                                                         words: str) -> None:
    err = refused(edited(tmp_path, source, *edits))
    assert err.key == key and words in err.problem, err


def test_a_key_of_the_tables_former_driver_is_read_by_no_one_but_still_loads(tmp_path: Path, caplog) -> None:
    """A rig switched from a UVC to a GenICam camera keeps `device` and `fps`: it loads (as
    before drivers declared their keys), and the keys left unread are logged."""
    path = edited(tmp_path, LCR, ('driver = "uvc"', 'driver = "genicam"\ncti = "/x.cti"'))
    devices = RigConfig.load(path).devices
    assert devices["camera"].driver.name == "genicam" and devices["camera"].settings.cti == "/x.cti"
    assert "device, fps: keys of another camera driver, not read by 'genicam'" in caplog.text


def test_a_stage_driver_of_another_rig_is_refused_at_load(tmp_path: Path) -> None:
    err = refused(edited(tmp_path, TURNTABLE, ('driver = "sim"\nsettle_s', 'driver = "grbl"\nsettle_s')))
    assert err.key == "stage.driver" and "a sim rig drives a simulated stage; set driver = 'sim'" in err.problem


NEW_DRIVER = '''
"""A camera driver added to slscan as one module: this file and nothing else."""

import numpy as np

from scanner.drivers.registry import Driver, register
from scanner.drivers.testing import FakeCapture
from scanner.drivers.uvc import UvcCamera
from scanner.schema import Int, Schema


class GreySettings(Schema):
    level: Int = 128


def open_grey(config, settings, transports):
    lens = config.file.first_camera
    image = np.full((lens.height, lens.width, 3), settings.level, np.uint8)
    return UvcCamera(lambda: FakeCapture(lambda t: image), "grey-camera", lens.width, lens.height)


register(Driver("camera", "grey", "hardware", GreySettings, open_grey))
'''


def test_a_new_driver_is_one_new_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A driver module dropped into the drivers' package (here a second folder of it) is
    found, its keys validated, and the hardware rig opens it; the core is not edited."""
    folder = tmp_path / "more_drivers"
    folder.mkdir()
    (folder / "grey_camera.py").write_text(textwrap.dedent(NEW_DRIVER))
    monkeypatch.setattr(scanner.drivers, "__path__", [*scanner.drivers.__path__, str(folder)])
    monkeypatch.setattr(registry, "_DRIVERS", dict(registry._DRIVERS))
    monkeypatch.setattr(registry, "_scanned", False)
    monkeypatch.delitem(sys.modules, "scanner.drivers.grey_camera", raising=False)
    rig = edited(tmp_path, HDMI, ('driver = "genicam"', 'driver = "grey"\nlevel = 77'),
                 ("width = 2448", "width = 320"), ("height = 2048", "height = 256"),
                 ('cti = "/opt/mvIMPACT_Acquire/lib/x86_64/mvGenTLProducer.cti"', ""),
                 ('serial = ""', ""), ('trigger_line = "Line0"', ""), ("refresh_hz = 60.0", "refresh_hz = 500.0"),
                 ("exposure_s = 0.03", "exposure_s = 0.001"), ("bit_depth = 12", "bit_depth = 8"))
    config = RigConfig.load(rig)
    assert config.devices["camera"].settings.level == 77
    with open_rig(config, transports={"display": FakeDisplay((1920, 1080), 500.0)}) as opened:
        assert opened.camera.name == "grey-camera"
        opened.camera.arm(1)
        opened.camera.trigger()
        assert int(opened.camera.grab(5.0).image.mean()) == 77
    (tmp_path / rig.name).write_text(rig.read_text().replace("level = 77", "level = 7.5"))
    assert refused(rig).key == "camera.level"


def test_validating_a_rig_imports_no_device_library_nor_the_simulator() -> None:
    probe = ("import sys\nfrom scanner.rig import RigConfig\n"
             f"for rig in {[str(p) for p in (LCR, HDMI, BENCH, TURNTABLE)]}:\n    RigConfig.load(rig)\n"
             "print(sorted(m for m in ('harvesters', 'pygame', 'usb', 'sim') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.stdout.split() == ["[]"], out.stderr[-2000:]
