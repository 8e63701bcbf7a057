"""The consistency model of a decode (docs/consistency.md): the statistics the physics of a
capture fixes, each judged against a threshold derived from a model with its false-refusal
rate, so that a decode that cannot be right is refused instead of handed on as a cloud.

Every check is a `Check` record: its statistic, threshold, what the model expects, whether
it passed (None: not judged, and why), the most likely cause of a failure and the stated
false-refusal rate. `scanner.decode` computes the checks its maps support (fit residual,
agreement between frequencies and with a Gray code, projector range, fringe orders, the
ordering of coordinates along each line), `scanner.pipeline` adds those that need the rig
(the coordinate's direction, the measuring volume, the epipolar geometry, the rig model's
tie to its calibration) and refuses the whole decode when any fails (`ConsistencyError`).

Four kinds of threshold, no constant tuned to a case:
- noise scales: a per-pixel statistic z² that the noise model makes χ²_k; the image's
  median z² over the χ²_k median must stay below the α = ALPHA quantile of that ratio's
  sampling distribution, widened by the noise model's stated accuracy (1 + u)²;
- discrete faults: a statistic whose alternatives are discrete (a phase step, a π/2
  origin) is judged at the midpoint between agreement and the smallest fault, with the
  false-refusal rate of its standard error there;
- majorities: a map that runs backwards or out of order, a cloud outside the volume, fringe
  orders failing: refused when most of what is judged says so (a scene can break these
  locally — an overhang, a thin object, a second light path — but not on most of it);
- impossibilities: a region of Gray codes naming pixels the projector does not have (a
  misread is an isolated pixel, masked; a wrong size or period count makes a region), a rig
  model other than the one recorded at capture.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from statistics import NormalDist
from typing import TYPE_CHECKING, Any, TypeGuard

import numpy as np

from scanner.errors import ConfigError, DecodeError

if TYPE_CHECKING:
    from scanner.camera_noise import CameraNoise
    from scanner.rig_schema import RecordedRig

ALPHA = 1e-4  # false-refusal rate of each noise-scale test when the noise model holds
SENSOR_MODEL = "sensor model"  # the noise sources the checks name (`noise_source`)
FITTED_MODEL = "noise model fitted to the frames"
SENSOR_MODEL_ACCURACY = 0.10  # relative accuracy of σ_I from a camera's photon-transfer table (EMVA 1288 gain)
FITTED_MODEL_ACCURACY = 0.25  # relative accuracy of σ_I fitted to the frames' own N-step residuals
PATTERN_ERROR = 2.0 / (255.0 * np.sqrt(12.0))
"""The displayed fringe's fixed error per frame, in units of its modulation B: 8-bit
patterns round each level to 1/255 of the white-black range, which is 2B (σ of a uniform
rounding, 1/(255·√12) of the range). It adds (2/N)·PATTERN_ERROR² rad² to each phase and
(PATTERN_ERROR·B)² DN² to each frame's residual, beside the camera's noise."""
ORDER_Z = 5.0  # a step back beyond 5 σ of the pair is no noise (one-sided 2.9e-7 per pair)
MIN_JUDGED = 200  # fewer pixels than this: a check has nothing to judge
MIN_LINES = 8  # fewer judged lines than this: the ordering has nothing to judge
ORDER_RUN = 3  # a step back counts when the next 3 valid pixels all lie below the 3 before it


@dataclass(frozen=True)
class Check:
    """One consistency check of one decode (module docstring). `statistic` and `threshold`
    are in `unit`; `passed` None: not judged (`note` says why)."""

    name: str
    scope: str  # "vertical", "horizontal", "cloud" or "session"
    statistic: float | None
    threshold: float | None
    unit: str
    expected: str
    passed: bool | None
    cause: str
    false_refusal: str
    judged: int = 0  # pixels, lines, points judged
    note: str = ""
    figures: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.passed is not None:
            object.__setattr__(self, "passed", bool(self.passed))  # not a numpy bool: `passed is False` holds
        for name in ("statistic", "threshold"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, float(value))

    def line(self) -> str:
        if self.passed is None:
            return f"{self.name} ({self.scope}): not judged: {self.note}"
        verdict = "ok" if self.passed else "FAILED"
        return (f"{self.name} ({self.scope}): {_fmt(self.statistic)} {self.unit}, limit {_fmt(self.threshold)} "
                f"{self.unit}: {verdict}" + (f" ({self.note})" if self.note else ""))

    def refusal(self) -> str:
        """One sentence for a failed check: the check, the figure, what was expected, the cause."""
        return (f"{self.name} ({self.scope}) failed: {_fmt(self.statistic)} {self.unit} where {self.expected} "
                f"(limit {_fmt(self.threshold)}); most likely: {self.cause}")

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _fmt(x: float | None) -> str:
    if x is None:
        return "-"
    return f"{x:.4g}"


class ConsistencyError(DecodeError):
    """A decode its own consistency checks refuse: `checks` holds every check, failed or not."""

    def __init__(self, where: str, checks: list[Check]) -> None:
        self.checks = checks
        lead, *more = sorted(failed(checks), key=lambda c: LEAD.index(c.name) if c.name in LEAD else len(LEAD))
        also = f" (also failed: {', '.join(f'{c.name} ({c.scope})' for c in more)})" if more else ""
        super().__init__(f"{where}refused by its consistency checks: {lead.refusal()}{also}; no cloud written, "
                         f"the frames are kept")


LEAD = ("rig_model", "pattern_set", "direction", "phase_residual", "frequency_offset", "gray_offset", "gray_edges",
        "ordering", "frequency_agreement", "projector_range", "fringe_orders", "measurement_volume", "epipolar")
"""The order in which failed checks name a refusal's cause: the most specific diagnosis
first (a map that runs backwards also spreads its frequencies and leaves the volume)."""


def failed(checks: list[Check]) -> list[Check]:
    return [c for c in checks if c.passed is False]


def not_judged(name: str, scope: str, unit: str, note: str) -> Check:
    return Check(name, scope, None, None, unit, "", None, "", "", 0, note)


# ---- noise-scale tests -------------------------------------------------------------------


def chi2_median(dof: int) -> float:
    return chi2_isf(dof, 0.5)


def chi2_isf(dof: int, p: float) -> float:
    """The χ²_dof value exceeded with probability p (scipy, imported on first use: 0.4 s)."""
    from scipy.special import chdtri

    return float(chdtri(dof, p))


def normal_isf(p: float) -> float:
    """The standard normal value exceeded with probability p."""
    return NormalDist().inv_cdf(1.0 - p)


def poisson_quantile(p: float, mean: float) -> float:
    """The least count k with P(X <= k) >= p for X ~ Poisson(mean) (scipy, on first use)."""
    from scipy.special import pdtrik

    return float(np.ceil(pdtrik(p, mean)))


def _chi2_pdf(x: float, dof: int) -> float:
    from math import exp, lgamma, log

    k = dof / 2.0
    return exp((k - 1) * log(x) - x / 2 - k * log(2.0) - lgamma(k))


def scale_threshold(dof: int, n: int, accuracy: float, alpha: float = ALPHA) -> float:
    """The largest median(z²)/median(χ²_dof) a consistent decode shows over n pixels with
    false-refusal rate `alpha`: the sample median's normal approximation (sd 1/(2 f(m) √n)),
    times (1 + accuracy)² for a noise model whose σ is known to ±accuracy."""
    m = chi2_median(dof)
    sd = 1.0 / (2.0 * _chi2_pdf(m, dof) * np.sqrt(max(n, 1)))
    return (1.0 + accuracy) ** 2 * (1.0 + normal_isf(alpha) * sd / m)


def scale_check(name: str, scope: str, z2: np.ndarray, *, dof: int, accuracy: float, noise_source: str,
                cause: str, what: str) -> Check:
    """A noise-scale test (module docstring) of per-pixel z² values that are χ²_dof under the model."""
    z2 = z2[np.isfinite(z2)]
    if z2.size < MIN_JUDGED:
        return not_judged(name, scope, "x noise", f"{z2.size} pixels to judge")
    statistic = float(np.median(z2)) / chi2_median(dof)
    threshold = scale_threshold(dof, z2.size, accuracy)
    flagged = float(np.mean(z2 > chi2_isf(dof, 1e-3)))
    return Check(name, scope, statistic, threshold, "x noise",
                 f"{what} is χ²_{dof} under the {noise_source} (ratio of medians 1)", statistic <= threshold, cause,
                 f"{ALPHA:g} with the noise model within ±{accuracy:.0%} in σ", int(z2.size),
                 figures={"flagged_fraction_at_1e-3": flagged})


# ---- discrete-fault tests ----------------------------------------------------------------


def offset_check(name: str, scope: str, offset: float, *, standard_error: float, fault: float, unit: str,
                 what: str, cause: str, judged: int) -> Check:
    """A common offset judged at the midpoint `fault`/2 between agreement (0) and the
    smallest fault's offset; the false-refusal rate is the normal tail of the offset's
    standard error there."""
    threshold = abs(fault) / 2.0
    z = threshold / max(standard_error, 1e-12)
    rate = 2.0 * NormalDist().cdf(-z)
    return Check(name, scope, abs(offset), threshold, unit, f"{what} is 0 (a one-step fault makes {abs(fault):.3g})",
                 abs(offset) <= threshold, cause, f"{rate:.1g} (offset's standard error {standard_error:.2g} {unit})",
                 judged, figures={"offset": offset})


def majority_check(name: str, scope: str, share: float | None, *, judged: int, unit: str, expected: str,
                   cause: str, note: str = "", below: bool = True, minimum: int = MIN_JUDGED) -> Check:
    """A share judged by majority: it fails when more than half (`below`: the share must
    stay at or below 0.5; else at or above it) of what is judged (at least `minimum`) says so."""
    if share is None or judged < minimum:
        return not_judged(name, scope, unit, note or f"{judged} judged")
    ok = share <= 0.5 if below else share >= 0.5
    return Check(name, scope, share, 0.5, unit, expected, ok, cause,
                 "a majority: the binomial tail at 0.5 for the judged count (negligible)", judged, note)


# ---- the coordinate map: ordering along each line ----------------------------------------


def line_steps(coordinate: np.ndarray, valid: np.ndarray, sigma: np.ndarray, orientation: str, every: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The valid pixels along every `every`-th line of the coded axis (rows for vertical
    fringes, columns for horizontal), in order: (line index, position, coordinate, sigma)."""
    if orientation == "horizontal":
        coordinate, valid, sigma = coordinate.T, valid.T, sigma.T
    lines, pos = np.nonzero(valid[::every])
    lines *= every
    return lines, pos, coordinate[lines, pos], sigma[lines, pos]


def ordering(coordinate: np.ndarray, valid: np.ndarray, sigma: np.ndarray, period_px: float,
             orientation: str, every: int = 4) -> Check:
    """The ordering constraint: along an epipolar line (a row for vertical fringes on a rig
    whose baseline runs along the camera's x; a column for horizontal ones) one opaque
    surface seen by camera and projector keeps its order, so the coordinate never steps
    back beyond noise. A step back counts when the next ORDER_RUN valid pixels all lie more
    than ORDER_Z σ below the ORDER_RUN before it (a mixed pixel at an edge cannot do that).
    Scenes break this at some edges (overhangs, pockets), in some lines; decoded fringe
    orders out of sequence break it in most: the check refuses when most judged lines
    (every `every`-th, with 2·ORDER_RUN valid pixels) step back. The way the coordinate
    runs is the majority's (figure `rising_share`: of the steps between neighbours that
    move beyond noise and by less than half a period (1.5 px for a pixel code, whose
    coordinate steps by whole pixels), the share that rise), which `direction` compares
    with the rig."""
    lines, pos, u, s = line_steps(coordinate, valid, sigma, orientation, every)
    n, r = u.size, ORDER_RUN
    if n < 2 * r + 1:
        return not_judged("ordering", orientation, "of lines", "too few decoded pixels")
    step = np.diff(u)
    same = lines[1:] == lines[:-1]
    moving = same & (np.diff(pos) == 1) & (np.abs(step) < max(period_px / 2, 1.5)) & \
        (np.abs(step) > 3.0 * np.hypot(s[1:], s[:-1]))
    n_moving = int(np.count_nonzero(moving))
    rising = int(np.count_nonzero(moving & (step > 0)))
    v = u if 2 * rising >= n_moving else -u
    lo, hi = v[:n - 2].copy(), v[:n - 2].copy()  # lo[j], hi[j]: min and max of v[j .. j + r - 1]
    for k in range(1, r):
        np.minimum(lo, v[k:n - 2 + k], out=lo)
        np.maximum(hi, v[k:n - 2 + k], out=hi)
    i = np.arange(r - 1, n - r)
    span = lines[i - r + 1] == lines[i + r]  # the whole window on one line (lines are sorted)
    back = span & (hi[i + 1] < lo[i - r + 1] - np.float32(ORDER_Z) * np.hypot(s[i], s[i + 1]))
    counts = np.bincount(lines, minlength=int(lines.max()) + 1)
    judged = counts >= 2 * r
    stepping = np.zeros_like(judged)
    stepping[lines[i[back]]] = True
    n_judged = int(judged.sum())
    share = float((stepping & judged).sum() / n_judged) if n_judged else None
    line_name = "rows" if orientation == "vertical" else "columns"
    check = majority_check(
        "ordering", orientation, share, judged=n_judged, unit=f"of {line_name}",
        expected=f"the coordinate runs one way along each of the {line_name} "
                 "(steps back only at a scene's few overhangs)",
        cause="Gray-code frames out of order, a wrong fringe or period count, or frames from another scan?",
        minimum=MIN_LINES)
    return replace_figures(check, {"steps_back": int(back.sum()), "rising_share": rising / max(n_moving, 1)})


def replace_figures(check: Check, figures: dict[str, float]) -> Check:
    """`check` with more figures."""
    return replace(check, figures={**check.figures, **figures})


# ---- the rig: direction, volume, epipolar geometry, the model's tie ----------------------


def predicted_direction(rig: Any, orientation: str) -> int:
    """+1 when the rig's projector coordinate grows along the camera's rows (columns, for
    horizontal fringes), −1 when it falls, 0 when the geometry does not say (no depth puts
    the camera's centre in the projector's view)."""
    cam = rig.camera
    axis = 0 if orientation == "vertical" else 1
    centre = np.array([cam.K[0, 2], cam.K[1, 2]])
    step = np.zeros(2)
    step[axis] = 5.0
    rays = cam.normalized(np.stack([centre, centre + step]))
    votes = []
    proj_from_cam = rig.proj_from_cam
    for z in (200.0, 400.0, 800.0, 1500.0, 3000.0, 6000.0):
        pts = np.c_[rays * z, [z, z]]
        p = pts @ proj_from_cam[:3, :3].T + proj_from_cam[:3, 3]
        if (p[:, 2] <= 0).any():
            continue
        uv = rig.projector.project(p)
        size = rig.projector.size
        if 0 <= uv[0, 0] < size[0] and 0 <= uv[0, 1] < size[1]:
            votes.append(np.sign(uv[1, axis] - uv[0, axis]))
    return int(np.sign(sum(votes))) if votes else 0


def direction(ordering_check: Check, rig: Any, orientation: str, calibrated: bool) -> Check:
    """The coordinate must run along the camera's lines the way the rig's geometry says:
    a map that runs the other way was decoded mirrored (phase steps in reverse order, or a
    mirrored projector). Judged by majority of the steps between neighbours that move
    beyond noise (`ordering`'s rising share)."""
    name, unit = "direction", "of steps"
    rising = ordering_check.figures.get("rising_share")
    predicted = predicted_direction(rig, orientation) if calibrated else 0
    if rising is None or ordering_check.passed is None:
        return not_judged(name, orientation, unit, "no steps to judge")
    if predicted == 0:
        return not_judged(name, orientation, unit, "the rig has no calibrated geometry to predict which way the "
                                                   "coordinate runs (assumed: as the frames show)")
    share = rising if predicted > 0 else 1.0 - rising
    way = "rises" if predicted > 0 else "falls"
    return majority_check(name, orientation, share, judged=ordering_check.judged, unit=unit,
                          expected=f"the coordinate {way} along the camera's lines as the rig's geometry "
                                   "predicts (share 1)",
                          cause="phase steps in reverse order (or a mirrored projector, or the wrong rig model)?",
                          below=False, minimum=MIN_LINES)


@dataclass(frozen=True)
class Volume:
    """Where the rig measures: depth `near_mm`..`far_mm` along the camera's axis (None: not
    declared, only the common field of view is judged) and where it came from."""

    near_mm: float | None
    far_mm: float | None
    source: str

    @classmethod
    def of_recorded(cls, rig: RecordedRig) -> Volume:
        """The recorded rig file's declared measuring volume ([acceptance] volume_mm about
        [rig] working_distance_mm), or none: also when either table is malformed, as before
        the tables were typed (the volume only narrows a check)."""
        try:
            size, distance = rig.acceptance.volume_mm, rig.rig.working_distance_mm
        except ConfigError:
            size = distance = None
        if size is not None and distance is not None:
            depth = size[2]
            return cls(distance - depth / 2, distance + depth / 2,
                       f"the rig file's [acceptance] volume_mm {size} about its working distance {distance} mm")
        return cls(None, None, "no measuring volume declared (the rig file's [acceptance] volume_mm)")


def measurement_volume(points: np.ndarray, rig: Any, volume: Volume, orientations: tuple[str, ...]) -> Check:
    """The bulk of the cloud must lie where the rig measures: in front of the camera and the
    projector, inside the projector's image (its other coordinate, for one fringe
    orientation) and within the declared volume's depth. Refused when most points lie
    outside, naming the median depth found and the volume."""
    name = "measurement_volume"
    p = points.reshape(-1, 3)
    p = p[np.isfinite(p).all(axis=1)].astype(np.float64)
    if len(p) < MIN_JUDGED:
        return not_judged(name, "cloud", "of points", f"{len(p)} points")
    sample = p[:: max(1, len(p) // 200000)]
    q = sample @ rig.proj_from_cam[:3, :3].T + rig.proj_from_cam[:3, 3]
    inside = (sample[:, 2] > 0) & (q[:, 2] > 0)
    uv = rig.projector.project(np.where(inside[:, None], q, np.array([0.0, 0.0, 1.0])))
    w, h = rig.projector.size
    margin = 2.0  # px: a point triangulated from a coordinate at the edge, plus noise
    if orientations == ("vertical",):
        inside &= (uv[:, 1] > -0.5 - margin) & (uv[:, 1] < h - 0.5 + margin)
    elif orientations == ("horizontal",):
        inside &= (uv[:, 0] > -0.5 - margin) & (uv[:, 0] < w - 0.5 + margin)
    if volume.near_mm is not None:
        inside &= (sample[:, 2] >= volume.near_mm) & (sample[:, 2] <= volume.far_mm)
    share = float(inside.mean())
    depth = float(np.median(sample[:, 2]))
    where = (f"depth {volume.near_mm:.0f}..{volume.far_mm:.0f} mm" if volume.near_mm is not None
             else "the common field of view")
    check = majority_check(name, "cloud", share, judged=len(sample), unit="of points",
                           expected=f"most points lie in the measuring volume ({where}, {volume.source}); median depth "
                                    f"found {depth:.0f} mm",
                           cause="the part outside the measuring volume, or a decode the rig model cannot place "
                                 "(phase steps reversed, a wrong projector size or rig model)?", below=False)
    return replace_figures(check, {"median_depth_mm": depth})


def rig_model_tie(recorded: str | None, used: dict[str, Any], override: str | None,
                  calibration: tuple[str, str] | None = None, holds_its_calibration: bool = False) -> Check:
    """The rig model a decode uses must be the one the session was captured with (its
    SHA-256 in the manifest), unless the user gives another on purpose (`override`) or it
    is exactly the model the calibration file it names holds (`holds_its_calibration`: a
    re-decode with the rig's new calibration). `calibration`: (the file the recorded model
    came from, its SHA-256 at capture), to say when that file has changed since."""
    from scanner.session import calibration_sha256, rig_model_sha256

    name = "rig_model"
    actual = rig_model_sha256(used)
    note = ""
    if calibration is not None:
        now = calibration_sha256(calibration[0]).get("calibration_sha256")
        if now != calibration[1]:
            note = (f"the calibration file {calibration[0]} {'changed' if now else 'is gone'} since the capture; the "
                    f"session decodes with the model it recorded (--rig-model {calibration[0]} for the new one)")
    if override is not None:
        return Check(name, "session", None, None, "", "", None, "", "", 0,
                     f"given on purpose: {override} (sha256 {actual[:12]}), recorded {str(recorded)[:12]}")
    if recorded is None:
        return not_judged(name, "session", "", "the session records no rig-model checksum (written before them)")
    if actual != recorded and holds_its_calibration:
        return Check(name, "session", None, None, "", "", None, "", "", 0,
                     f"another model than recorded at capture: the one its calibration file {used.get('calibration')} "
                     f"holds (sha256 {actual[:12]})")
    ok = actual == recorded
    return Check(name, "session", float(ok), 1.0, "(1: the same)",
                 f"the rig model is the one recorded at capture (sha256 {recorded[:12]})", ok,
                 "the manifest's rig model was edited after the capture; give the model you mean with --rig-model "
                 "FILE", "0 (a checksum)", 1, note)


def pattern_set_tie(recorded: str | None, used: dict[str, Any]) -> Check:
    """The pattern set a decode reads the frames with must be the one recorded at capture (its
    SHA-256 in the manifest): a fringe count edited afterwards keeps the frame count and, for a
    Gray-code set, the frames' own consistency (code and phase agree under any count), and
    scales every coordinate."""
    from scanner.session import rig_model_sha256

    name = "pattern_set"
    if recorded is None:
        return not_judged(name, "session", "", "the session records no pattern-set checksum (written before them)")
    ok = rig_model_sha256(used) == recorded
    return Check(name, "session", float(ok), 1.0, "(1: the same)",
                 f"the pattern set is the one recorded at capture (sha256 {recorded[:12]})", ok,
                 "the manifest's pattern set was edited after the capture (a wrong fringe count or convention?)",
                 "0 (a checksum)", 1)


def sensor_noise_terms(sensor: CameraNoise | None, bit_depth: int) -> tuple[float, float] | None:
    """(read, shot) of the camera's intensity noise σ_I² = read + shot·A (DN², A in DN) from
    its photon-transfer table (the rig file's [camera.sensor]: full_well_e, read_noise_e):
    gain g = full well / full scale e-/DN, read = (read noise / g)² + 1/12 (quantisation),
    shot = 1/g. None when the rig file has no such table or it gives no full_well_e. A read
    noise left out is the table's default, as the simulator renders the frames and the
    measurement model assumes (`CameraNoise.noise_sigma_dn`); `sensor_noise_source` says so."""
    if not _transfer_stated(sensor):
        return None
    g = sensor.gain_e_per_dn(bit_depth)
    return (sensor.read_noise_e / g) ** 2 + 1.0 / 12.0, 1.0 / g


def sensor_noise_source(sensor: CameraNoise | None) -> str | None:
    """The noise source `sensor_noise_terms` stands for, as the checks report it: the sensor
    model, naming the read noise it assumes when the table states none; None without one."""
    if not _transfer_stated(sensor):
        return None
    if "read_noise_e" in sensor.model_fields_set:
        return SENSOR_MODEL
    return f"{SENSOR_MODEL} (read noise {sensor.read_noise_e:g} e- assumed: the rig file's [camera.sensor] states none)"


def _transfer_stated(sensor: CameraNoise | None) -> TypeGuard[CameraNoise]:
    """Whether the rig file states the sensor's photon transfer (its full well)."""
    return sensor is not None and "full_well_e" in sensor.model_fields_set


def epipolar(v_measured: np.ndarray, v_sigma: np.ndarray, v_from_u: np.ndarray, *, v_from_u_shifted: np.ndarray,
             u_sigma: np.ndarray, shift_px: float, accuracy: float, noise_source: str, model_px: float) -> Check:
    """With both fringe orientations on a calibrated rig, the two projector coordinates of a
    pixel must meet the epipolar geometry: the point the column u triangulates projects to
    the row v the horizontal fringes measured. Per pixel (arrays over the judged pixels),
    z² = (v − v(u))² / (σ_v² + (∂v/∂u)²·σ_u² + 2·model_px²), ∂v/∂u from `v_from_u_shifted`
    (u + shift_px), `model_px` the rig model's stated reprojection RMS (its error in the
    camera's and the projector's image), is χ²_1: a noise-scale test."""
    dvdu = (v_from_u_shifted - v_from_u) / shift_px
    z2 = np.square(v_measured - v_from_u) / (np.square(v_sigma) + np.square(dvdu * u_sigma) + 2 * model_px ** 2)
    return scale_check("epipolar", "cloud", z2.astype(np.float64), dof=1, accuracy=accuracy, noise_source=noise_source,
                       cause="the wrong rig model (intrinsics, principal points or the projector's pose), or a wrong "
                             "projector size?", what="the two coordinates' distance from the epipolar geometry")
