"""Synchronisation checks for cameras that cannot say which pattern they saw: timestamps
and the intensity signature, on the simulated rig (all three wirings) and on sequences
made wrong on purpose."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from session_support import SCENE, small_rig_toml

from scanner.acquisition import AcquisitionSettings, acquire, check_signature, check_timing
from scanner.config import CONFIG_DIR
from scanner.devices import Camera, Frame, TriggerType
from scanner.errors import FrameOutOfOrder
from scanner.patterns import PatternSet
from scanner.pipeline import scan
from scanner.rig import RigConfig, open_rig
from scanner.session import ERROR

FAMILIES = ["heterodyne_3x4", "hierarchical_3x4", "graycode_4"]


class BlindCamera(Camera):
    """Wraps the simulated camera as a real one is: no pattern index. `lag` > 0 delivers,
    as frame k, the image exposed under pattern k - lag (a dark image before the first),
    with a fresh index and timestamp: only the intensity signature can tell."""

    def __init__(self, inner: Camera, lag: int = 0) -> None:
        super().__init__("blind-camera", inner.width, inner.height)
        self.inner, self.lag = inner, lag
        self._bit_depth = inner.bit_depth
        self._trigger_type = inner.trigger_type
        self._images: list[np.ndarray] = []

    def _do_set_bit_depth(self, bits: int) -> None:
        self.inner.set_bit_depth(bits)

    def _do_set_exposure(self, seconds: float) -> None:
        self.inner.set_exposure(seconds)

    def _do_set_trigger(self, ttype: TriggerType) -> None:
        self.inner.set_trigger(ttype)

    def _do_arm(self, n_frames: int) -> None:
        self._images = []
        self.inner.arm(n_frames)

    def _do_trigger(self) -> None:
        self.inner.trigger()

    def _do_disarm(self) -> None:
        self.inner.disarm()

    def _do_grab(self, timeout_s: float) -> Frame:
        f = self.inner.grab(timeout_s)
        self._images.append(f.image)
        k = len(self._images) - 1
        image = self._images[k - self.lag] if k >= self.lag else np.full_like(f.image, f.image.min())
        return dataclasses.replace(f, image=image, pattern_index=None)

    def _do_shutdown(self) -> None:
        self.inner.shutdown()


def blind_rig(tmp: Path, wiring: str, lag: int = 0, family: str = "heterodyne_3x4"):
    config = RigConfig.load(small_rig_toml(tmp, trigger=wiring, timeout_s=0.5))
    rig = open_rig(config, scene=SCENE)
    rig.camera = BlindCamera(rig.camera, lag)
    return rig, PatternSet.load(CONFIG_DIR / "patterns" / f"{family}.toml")


@pytest.mark.parametrize("wiring", ["software", "projector", "trigger_box"])
def test_true_sequence_passes_without_pattern_index(tmp_path: Path, wiring: str) -> None:
    rig, patterns = blind_rig(tmp_path, wiring)
    with rig:
        frames: list[Frame] = []
        stack = acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda k, f: frames.append(f))
    assert len(stack) == patterns.n_frames and all(f.pattern_index is None for f in frames)


@pytest.mark.parametrize("wiring", ["software", "projector", "trigger_box"])
def test_sequence_shifted_by_one_frame_is_refused_and_frames_kept(tmp_path: Path, wiring: str) -> None:
    rig, patterns = blind_rig(tmp_path, wiring, lag=1)
    with rig, pytest.raises(FrameOutOfOrder, match="frames do not follow the patterns: frame .* fits worst") as exc:
        scan(rig, patterns, tmp_path / "s")
    assert "blind-camera" in str(exc.value)
    assert len(list((tmp_path / "s" / "frames").glob("frame_*.png"))) == 12  # every frame kept
    assert (tmp_path / "s" / ERROR).exists() and not (tmp_path / "s" / "manifest.json").exists()


@pytest.fixture(scope="module")
def true_stacks(tmp_path_factory: pytest.TempPathFactory) -> dict[str, np.ndarray]:
    """A true sequence of every pattern family (acquired through every check)."""
    out = {}
    for family in FAMILIES:
        rig, patterns = blind_rig(tmp_path_factory.mktemp(family), "software", family=family)
        with rig:
            out[family] = acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda k, f: None)
    return out


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("fault", ["rolled", "dark_first", "repeated", "swapped"])
def test_mixed_sequences_are_refused(true_stacks: dict[str, np.ndarray], family: str, fault: str) -> None:
    stack = true_stacks[family]
    patterns = PatternSet.load(CONFIG_DIR / "patterns" / f"{family}.toml")
    bad = stack.copy()
    if fault == "rolled":
        bad = np.roll(stack, 1, axis=0)
    elif fault == "dark_first":
        bad[1:], bad[0] = stack[:-1], stack.min()
    elif fault == "repeated":
        bad[6] = stack[5]
    elif family != "graycode_4":  # a Gray bit swapped for another still reads as a code word: not judged
        bad[5] = stack[9]
    else:
        bad[1] = stack[2]
    check_signature(stack, patterns, (1140, 912), 12, "cam")  # the true one passes
    with pytest.raises(FrameOutOfOrder, match="fits worst"):
        check_signature(bad, patterns, (1140, 912), 12, "cam")


def test_timestamps_must_follow_the_patterns() -> None:
    img = np.zeros((2, 2), np.uint16)
    first = Frame(img, 0, None, 10.0, 0.01, 12)
    check_timing(0, first, None, 9.9, "cam")
    with pytest.raises(FrameOutOfOrder, match="frame 1 was exposed 0.5 s before pattern 1 was on display"):
        check_timing(1, Frame(img, 1, None, 10.5, 0.01, 12), first, 11.0, "cam")
    with pytest.raises(FrameOutOfOrder, match="not after frame 0"):
        check_timing(1, Frame(img, 1, None, 10.0, 0.01, 12), first, 9.0, "cam")


def test_dark_scene_cannot_be_verified() -> None:
    patterns = PatternSet.load(CONFIG_DIR / "patterns" / "heterodyne_3x4.toml")
    flat = np.full((12, 64, 64), 100, np.uint16)
    with pytest.raises(Exception, match="cannot verify that the frames follow the patterns"):
        check_signature(flat, patterns, (1140, 912), 12, "cam")
