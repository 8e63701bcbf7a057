"""Acquisition: show pattern k, trigger, grab, check that the frame is frame k, store it.

Three wirings (rig config `rig.trigger`): `software` (show, software-trigger, grab, per
pattern), `projector` (the projector runs the sequence and its trigger output exposes the
camera) and `trigger_box` (a pulse train advances the projector and exposes the camera).
A frame whose counter skips is a dropped frame; one that repeats an index or carries the
wrong pattern is out of order; either stops the scan rather than decoding a mixed
sequence. Every frame checked is stored before the next is awaited.

In the hardware-sequenced wirings the projector's sequence or the trigger box's train
returns a status (`scanner.status`); while frames are awaited its failure is raised as
itself (an HDMI projector whose display failed is reported as that, not as a camera that
saw no frame), and after the last frame the acquisition waits for it to finish.

Real cameras cannot say which pattern they saw (`Frame.pattern_index` is None), so two
more checks prove that frame k was taken under pattern k:
  - timestamps: frame k cannot have been exposed before pattern k was put up (after
    `show(k)` in the software wiring; `k` periods after the sequence started in the
    hardware wirings) and frames come in time order;
  - the intensity signature, once the sequence is complete: at well-lit pixels the N
    values must be what the N displayed patterns predict for one projector coordinate,
    up to an offset and a non-negative gain per fringe frequency (`check_signature`).
    A sequence shifted by a frame, or with a frame from elsewhere, does not fit and is
    refused (FrameOutOfOrder naming the worst frame) before anything is decoded.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from scanner.devices import Camera, Frame
from scanner.errors import FrameDropped, FrameError, FrameOutOfOrder, WaitTimeout
from scanner.pattern_families import FrameKind
from scanner.patterns import FrameSpec, PatternSet
from scanner.rig import Rig
from scanner.status import Status

log = logging.getLogger(__name__)

FrameCallback = Callable[[int, Frame], None]

TIMESTAMP_TOLERANCE = 0.25  # of a pattern period: clock offsets between camera and host
SIGNATURE_PIXELS = 1500  # well-lit pixels the signature check looks at
SIGNATURE_MAX_RESIDUAL = 0.05  # a frame's residual / fringe signal (true frames: <= 0.01, wrong ones: >= 0.09)
SIGNATURE_MIN_CONTRAST = 0.02  # of full scale: temporal std below this is too dark to judge
STATUS_CHECK_S = 0.1  # while a sequence drives the camera, a frame is awaited in slices this long (s)
EXPOSURE_PERIOD_MARGIN_S = 0.005  # a sequenced pattern stays up this much longer than a long exposure (s)


@dataclass(frozen=True)
class AcquisitionSettings:
    """`period_s`: pattern period for hardware-sequenced wirings; `timeout_s`: longest
    wait for any one frame."""

    period_s: float
    timeout_s: float

    @classmethod
    def for_rig(cls, rig: Rig) -> AcquisitionSettings:
        return cls(rig.config.period_s, rig.config.timeout_s)


def check_frame(k: int, frame: Frame, camera_name: str, shape: tuple[int, int], bit_depth: int) -> None:
    """Raise if `frame` is not a good frame k of this sequence."""
    if frame.index > k:
        raise FrameDropped(camera_name, f"frame {k} was dropped: the next frame arrived with index {frame.index}",
                           k, frame.index)
    if frame.index < k:
        raise FrameOutOfOrder(camera_name, f"expected frame {k}, got index {frame.index} again (stale buffer)",
                              k, frame.index)
    if frame.pattern_index is not None and frame.pattern_index != k:
        raise FrameOutOfOrder(camera_name, f"frame {k} was exposed under pattern {frame.pattern_index}, not {k}",
                              k, frame.index)
    if frame.image.shape != shape:
        raise FrameError(camera_name, f"frame {k} is {frame.image.shape[1]}x{frame.image.shape[0]}, the camera is "
                                      f"configured for {shape[1]}x{shape[0]}", k, frame.index)
    if frame.bit_depth != bit_depth or int(frame.image.max(initial=0)) >= 2 ** bit_depth:
        raise FrameError(camera_name, f"frame {k} does not hold {bit_depth}-bit data", k, frame.index)


def acquire(rig: Rig, patterns: PatternSet, settings: AcquisitionSettings, on_frame: FrameCallback) -> np.ndarray:
    """Capture every pattern of `patterns` (rendered for the rig's projector gamma) through
    the rig's wiring; `on_frame(k, frame)` is called (to store and log it) as soon as frame
    k has been checked; the complete stack must then fit the patterns (`check_signature`).
    Returns the (N, H, W) stack."""
    proj = rig.projector
    stack = acquire_images(rig, patterns.render(proj.width, proj.height, rig.model.projector_gamma), settings,
                           on_frame)
    check_signature(stack, patterns, (proj.height, proj.width), rig.camera.bit_depth, rig.camera.name)
    return stack


def acquire_images(rig: Rig, images: np.ndarray, settings: AcquisitionSettings,
                   on_frame: FrameCallback | None = None, wiring: str | None = None) -> np.ndarray:
    """Show each pre-rendered projector image (N, Hp, Wp) in turn and grab its frame, every
    frame checked (`check_frame`, `check_timing`) and passed to `on_frame` before the next
    is awaited. `wiring` overrides the rig's (e.g. "software" for lock-step frames of
    images no sequence check applies to; the camera must then be software-triggered).
    Returns the (N, H, W) stack."""
    callback = None if on_frame is None else (lambda camera, k, frame: on_frame(k, frame))
    return acquire_images_from(rig, [rig.camera], images, settings, callback, wiring)[0]


def acquire_all(rig: Rig, patterns: PatternSet, settings: AcquisitionSettings,
                on_frame: Callable[[str, int, Frame], None]) -> dict[str, np.ndarray]:
    """`acquire` for every camera of the rig together (`Rig.cameras`, by name): one sequence
    of patterns exposes them all; frame k is complete when every camera's frame k has been
    checked, and each camera's stack must fit the patterns. `on_frame(name, k, frame)`."""
    cameras = rig.cameras or {"camera": rig.camera}
    by_device = {c.name: n for n, c in cameras.items()}
    proj = rig.projector
    stacks = acquire_images_from(rig, list(cameras.values()),
                                 patterns.render(proj.width, proj.height, rig.model.projector_gamma), settings,
                                 lambda device, k, frame: on_frame(by_device[device], k, frame))
    for cam, stack in zip(cameras.values(), stacks):
        check_signature(stack, patterns, (proj.height, proj.width), cam.bit_depth, cam.name)
    return dict(zip(cameras, stacks))


def acquire_images_from(rig: Rig, cameras: list[Camera], images: np.ndarray, settings: AcquisitionSettings,
                        on_frame: Callable[[str, int, Frame], None] | None = None,
                        wiring: str | None = None) -> list[np.ndarray]:
    """`acquire_images` for several cameras exposed by the same patterns (the same trigger):
    frame k is awaited from every camera before pattern k + 1 is shown (software wiring) or
    before frame k + 1 is awaited; `on_frame(camera name, k, frame)`. One (N, H, W) stack per
    camera, in the order given."""
    proj = rig.projector
    n = len(images)
    proj.load_patterns(images)
    for cam in cameras:
        cam.arm(n)
    stacks: list[np.ndarray | None] = [None] * len(cameras)
    wiring = wiring or rig.config.trigger
    tolerance = TIMESTAMP_TOLERANCE * settings.period_s
    previous: list[Frame | None] = [None] * len(cameras)
    running: Status | None = None  # the sequence or pulse train driving the cameras
    names = ", ".join(c.name for c in cameras)
    log.info("%s: acquiring %d frames, wiring %s", names, n, wiring)
    try:
        started = time.monotonic()
        if wiring == "projector":
            running = proj.run_sequence(settings.period_s)
        elif wiring == "trigger_box":
            if rig.trigger is None:
                raise FrameError(cameras[0].name, "rig is wired for a trigger box but none is open", 0, None)
            rig.trigger.arm(n, settings.period_s)
            running = rig.trigger.start()
        for k in range(n):
            if wiring == "software":
                earliest = time.monotonic()
                proj.show(k)
                for cam in cameras:
                    cam.trigger()
            else:
                earliest = started + k * settings.period_s
            for i, cam in enumerate(cameras):
                frame = grab_while_running(cam, settings.timeout_s, running)
                check_frame(k, frame, cam.name, (cam.height, cam.width), cam.bit_depth)
                check_timing(k, frame, previous[i], earliest - tolerance, cam.name)
                stack = stacks[i]
                if stack is None:
                    stack = stacks[i] = np.empty((n, cam.height, cam.width), dtype=frame.image.dtype)
                stack[k] = frame.image
                if on_frame is not None:
                    on_frame(cam.name, k, frame)
                previous[i] = frame
            log.debug("%s: frame %d of %d checked", names, k, n)
        if running is not None:
            running.wait(settings.timeout_s)  # an error after the last frame surfaces too
        log.info("%s: %d frames acquired in %.3g s", names, n, time.monotonic() - started)
    except BaseException:
        release(rig, quiet=True, cameras=cameras)
        raise
    release(rig, quiet=False, cameras=cameras)
    filled = [s for s in stacks if s is not None]
    if len(filled) != len(cameras):
        raise FrameError(names, "no frames acquired: no patterns were given", 0, None)
    return filled


def settings_for_exposure(settings: AcquisitionSettings, exposure_s: float) -> AcquisitionSettings:
    """`settings` with a pattern period long enough for `exposure_s` (s): a sequenced
    pattern must stay up for the whole exposure."""
    return replace(settings, period_s=max(settings.period_s, exposure_s + EXPOSURE_PERIOD_MARGIN_S))


def at_exposure(rig: Rig, exposure_s: float, grab: Callable[[], np.ndarray]) -> np.ndarray:
    """`grab()` with the camera at `exposure_s` (s), its exposure set back afterwards (also
    when `grab` fails: then a failure to set it back is logged, not raised over the error)."""
    cam = rig.camera
    before = cam.exposure_s
    cam.set_exposure(exposure_s)
    try:
        out = grab()
    except BaseException:
        try:
            cam.set_exposure(before)
        except Exception as exc:
            log.warning("%s: could not set the exposure back to %.4g s: %s", cam.name, before, exc)
        raise
    cam.set_exposure(before)
    return out


def acquire_exposures(rig: Rig, patterns: PatternSet, settings: AcquisitionSettings, exposures_s: Sequence[float],
                      on_frame: FrameCallback) -> list[np.ndarray]:
    """The whole pattern set captured once per exposure (s), in the order given; frame k of
    exposure i is passed to `on_frame` as i·n_frames + k, each exposure's stack checked like a
    single capture (`acquire`). The camera's exposure is set back afterwards."""
    n = patterns.n_frames
    stacks = []
    for i, t in enumerate(exposures_s):
        def shifted(k: int, frame: Frame, offset: int = i * n) -> None:
            on_frame(offset + k, frame)

        log.info("%s: exposure %d of %d, %.4g s", rig.camera.name, i + 1, len(exposures_s), t)
        stacks.append(at_exposure(rig, t, partial(acquire, rig, patterns, settings_for_exposure(settings, t), shifted)))
    return stacks


def release(rig: Rig, quiet: bool, cameras: list[Camera] | None = None) -> None:
    """Stop the sequence and the pulse train, disarm the cameras (default: the rig's camera),
    blank the projector: every step is tried. `quiet` (an error is already on its way): a
    failing step is logged, not raised over that error; otherwise the first failure is raised
    once all were tried."""
    proj, trigger = rig.projector, rig.trigger
    steps: list[Callable[[], None]] = [proj.stop_sequence, *[c.disarm for c in (cameras or [rig.camera])]]
    if trigger is not None:
        steps.insert(1, trigger.stop)
    if not proj.is_shut_down:
        steps.append(proj.blank)
    failures: list[Exception] = []
    for step in steps:
        try:
            step()
        except Exception as exc:
            log.log(logging.WARNING if quiet else logging.DEBUG, "releasing the rig after the acquisition: %s "
                    "failed: %s", step.__qualname__, exc)
            failures.append(exc)
    if failures and not quiet:
        raise failures[0]


def grab_while_running(cam: Camera, timeout_s: float, running: Status | None) -> Frame:
    """`cam.grab(timeout_s)`; while `running` (a sequence or pulse train) drives the camera,
    the frame is awaited in slices of STATUS_CHECK_S and the status's failure is raised as
    itself as soon as it is known (no frame would come of a failed sequence). The timeout is
    the sum of the slices the camera itself waited, so a camera that keeps its own clock (the
    simulator does not count its rendering time) is judged by that clock."""
    if running is None:
        return cam.grab(timeout_s)
    budget = timeout_s
    last: WaitTimeout | None = None
    while True:
        failure = running.exception()
        if failure is not None:
            raise failure
        if last is not None and budget <= 0:
            raise WaitTimeout(cam.name, last.awaited, timeout_s, last.hint)
        slice_s = min(max(budget, 1e-3), STATUS_CHECK_S)
        try:
            return cam.grab(slice_s)
        except WaitTimeout as exc:
            last = exc
            budget -= slice_s


def check_timing(k: int, frame: Frame, previous: Frame | None, earliest_s: float, camera_name: str) -> None:
    """Raise if frame k was exposed before pattern k could be on display (`earliest_s`,
    monotonic seconds) or not after the frame before it."""
    if frame.timestamp_s < earliest_s:
        raise FrameOutOfOrder(camera_name, f"frame {k} was exposed {earliest_s - frame.timestamp_s:.3g} s before "
                                           f"pattern {k} was on display: a stale or early frame", k, frame.index)
    if previous is not None and frame.timestamp_s <= previous.timestamp_s:
        raise FrameOutOfOrder(camera_name, f"frame {k} is stamped {frame.timestamp_s:.6f} s, not after frame "
                                           f"{k - 1} ({previous.timestamp_s:.6f} s): a repeated or reordered "
                                           f"buffer", k, frame.index)


def _orientation_groups(specs: list[FrameSpec], orientation: str) -> list[list[int]]:
    """Frame indices of one orientation, grouped by what shares an offset and a gain: the
    steps of one phase frequency, or all Gray-code bits."""
    groups: dict[tuple[str, int], list[int]] = {}
    for k, s in enumerate(specs):
        if s.orientation == orientation:
            groups.setdefault((s.kind, s.level if s.kind is FrameKind.PHASE else 0), []).append(k)
    return list(groups.values())


def check_signature(stack: np.ndarray, patterns: PatternSet, projector_shape: tuple[int, int], bit_depth: int,
                    camera_name: str) -> None:
    """Raise FrameOutOfOrder unless the frames fit the displayed patterns.

    Per orientation, at the best-lit pixels, the model I_k = a_g + b_g * P_k(u) (offset
    a_g and gain b_g >= 0 per group g of frames sharing a frequency, one projector
    coordinate u for all groups, searched on a half-pixel grid) must explain the
    temporal variance: every frame's residual at the best coordinate must stay below
    SIGNATURE_MAX_RESIDUAL of the fringe signal (median over pixels). A pattern set
    without redundancy (three frames) fits anything and is not judged; a Gray-code bit
    replaced by another still reads as a valid code word and is not caught here."""
    specs = patterns.frames()
    full = float(2 ** bit_depth - 1)
    for orientation in patterns.orientations:
        groups = _orientation_groups(specs, orientation)
        ks = [k for g in groups for k in g]
        if len(ks) <= 3:
            continue  # three frames fit any coordinate: nothing to judge
        extent = projector_shape[1] if orientation == "vertical" else projector_shape[0]
        values = stack[ks].reshape(len(ks), -1)
        step = max(1, int(np.sqrt(values.shape[1] / (20 * SIGNATURE_PIXELS))))
        sub = values[:, ::step].astype(np.float32)
        lit = (sub.max(axis=0) < full) & (sub.min(axis=0) > 0)  # not clipped
        spread = np.where(lit, sub.std(axis=0), 0.0)
        order = np.argsort(spread)[::-1][:SIGNATURE_PIXELS]
        order = order[spread[order] > SIGNATURE_MIN_CONTRAST * full]
        if len(order) < SIGNATURE_PIXELS // 10:
            raise FrameError(camera_name, f"cannot verify that the frames follow the patterns: only {len(order)} "
                                          f"pixels show fringe contrast above {SIGNATURE_MIN_CONTRAST:.0%} of full "
                                          f"scale; raise the exposure or the projector brightness", 0, None)
        pixels = {k: sub[i, order] for i, k in enumerate(ks)}
        grid = np.arange(0.0, extent - 1 + 1e-9, 0.5)
        c = np.arange(extent, dtype=np.float64)
        explained = np.zeros((len(order), len(grid)), dtype=np.float64)
        for g in groups:
            intensity = np.stack([pixels[k] for k in g], axis=1)
            intensity -= intensity.mean(axis=1, keepdims=True)
            model = np.stack([np.interp(grid, c, patterns.profile(specs[k], extent)) for k in g])
            model -= model.mean(axis=0, keepdims=True)
            var = (model ** 2).sum(axis=0)
            share = intensity @ model
            np.maximum(share, 0.0, out=share)  # gains are non-negative
            np.square(share, out=share)
            share /= np.where(var > 1e-12, var, np.inf)  # in place (P x 2 extent doubles); 0 where no signal
            explained += share
        scores = _frame_scores(pixels, groups, grid[explained.argmax(axis=1)], c=c, patterns=patterns, specs=specs,
                               extent=extent)
        worst = max(scores, key=scores.__getitem__)
        if scores[worst] > SIGNATURE_MAX_RESIDUAL:
            raise FrameOutOfOrder(camera_name, (
                f"the {orientation} frames do not follow the patterns: frame {worst} fits worst, its residual is "
                f"{scores[worst]:.2f} of the fringe signal where a true frame stays below {SIGNATURE_MAX_RESIDUAL}; "
                f"a shifted or mixed sequence is refused rather than decoded; check the trigger wiring (and the "
                f"projector gamma in the rig TOML) and scan again"),
                worst, None)


def _frame_scores(pixels: dict[int, np.ndarray], groups: list[list[int]], u: np.ndarray, *, c: np.ndarray,
                  patterns: PatternSet, specs: list[FrameSpec], extent: int) -> dict[int, float]:
    """Per frame: the median, over pixels, of its squared residual at the pixel's best
    coordinate `u`, relative to the mean squared fringe signal of a frame of its group."""
    scores: dict[int, float] = {}
    for g in groups:
        intensity = np.stack([pixels[k] for k in g], axis=1).astype(np.float64)
        model = np.stack([np.interp(u, c, patterns.profile(specs[k], extent)) for k in g], axis=1)
        ic = intensity - intensity.mean(axis=1, keepdims=True)
        mc = model - model.mean(axis=1, keepdims=True)
        gain = np.maximum((ic * mc).sum(axis=1), 0.0) / np.maximum((mc ** 2).sum(axis=1), 1e-12)
        err = ic - gain[:, None] * mc
        signal = np.maximum((ic ** 2).mean(axis=1), 1e-12)
        for j, k in enumerate(g):
            scores[k] = float(np.median(err[:, j] ** 2 / signal))
    return scores
