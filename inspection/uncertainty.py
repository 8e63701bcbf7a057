"""Measurement uncertainty of every reported figure: the model, written down once.

Every figure x comes with an expanded uncertainty U = k·u, k = 2 (about 95 % for the
near-normal errors here), u² = u_noise² + u_fringe² + u_cal², from three sources. Where the
fringe systematic (2.) carries much of a least-squares figure's u, its error is not near
normal: a fixed function at a random offset is bounded and light-tailed, and k = 2 would
cover more than 95 % (a ball bar's length: 98.5 % of 200 repeat scans). Those figures take
the k that gives 95 % for the error's actual distribution, noise and calibration normal
and the fringe's values at every offset as they are (`coverage_factor`, GUM Supplement 1).

1. Noise (random, independent from pixel to pixel and from scan to scan). Per pixel, the
   decoder knows the fringe modulation B_i of each frequency and the background A; the
   camera's sensor model gives the intensity noise σ_I(A) (shot, read and quantisation
   noise, [camera.sensor] of the rig). An N-step phase has σ_φ = sqrt(2/N)·σ_I/B per
   frequency; the frequencies are combined by inverse variance, so the finest-fringe phase
   has σ_φ = sqrt(2/N)·σ_I/sqrt(Σ (B_i f_i/f_max)²); the projector coordinate
   σ_c = σ_φ·period/(2π); the depth σ_z = σ_c·|dz/dc| from the triangulation geometry.
   The point moves along its camera ray: δX = ray·δz (ray = (x/z, y/z, 1)). On the
   simulator this predicts the depth noise to 1 % (`sim.evaluate`, ratio 0.99-1.00).
   Without a sensor model (a cloud file, a rig without [camera.sensor]) σ is estimated from
   the data instead (fourth differences of the heights, `form.noise_sigma`), which also
   counts fine real texture as noise; the report says which source was used.

2. Fringe systematics. The projector shows 8-bit commands pre-compensated for its gamma,
   so the displayed fringes are sinusoids only to the nearest grey level: the decoded
   coordinate carries a fixed error that depends on the projector coordinate alone (the
   same all along a projector column). `fringe_error` computes it from the pattern set,
   the gamma and the projector's blur by running the decoder on the displayed profiles
   (RMS 0.0017 projector px on the bench rig, with structure from a pixel to a hundred).
   Where it lands on a part depends on where the part stands, which nobody knows to a
   projector pixel: it is treated as that error function at a uniformly random offset, so
   its spread and correlations are exactly the function's own.
   The camera's defocus blurs the complex fringe signal: where the decoded coordinate
   curves or the modulation changes across the blur, the phase moves (`defocus_bias`,
   first order in the blur's variance). At a silhouette that bias is large (the blur
   mixes the surface's fringes with the dark beyond): the artefact fits leave the
   outline band out (`inspection.acceptance.inner_pixels`; on the simulator it had made
   the radius of a 25 mm sphere read +0.56 µm noise-free, about one u). Inside, it is a
   low-pass on texture (Sq of a 1.5-4 mm texture read ~3 % low on the simulator). An
   inspection removes it from the surfaces it measures (`MeasurementModel.of_scan(...,
   defocus=True)` gives each point its modelled depth bias, `inspection.form` removes it
   and raises the point's noise by what the removal adds, `_correction_gain`); the rig
   states its camera's blur ([camera.sensor] blur_sigma_px; a rig that does not has
   none removed). The artefact fits of `slscan verify` do not: near a silhouette the
   first order fails the other way (on a sphere it moved the radius by -0.3 µm), so their
   inner variant leaves the outline band out instead.

3. Calibration. The rig's parameters (both devices' intrinsics and distortion, the
   extrinsics) carry the covariance the calibration solve found (`calibration.json`:
   "covariance"; older files and other tools' only one-sigmas, then taken as uncorrelated,
   which is stated). It is one error common to every point of a scan (and to every scan
   made with that calibration), never averaged over points: along each principal
   direction d of the covariance the points move together by δX_d,i = J_i δ_d
   (`calibration_jacobian`, the triangulation linearised; checked against
   re-triangulation), the figure by Σ_i g_i·δX_d,i, and only the directions add in
   quadrature. A rig with no calibration file uses its nominal geometry: on the simulator
   that is the truth (u_cal = 0); on a real rig it is unknown, and U then says it covers
   noise only.

Propagation. Least-squares figures (sphere centre and radius, plane, distances between
centres) are linear in the points to first order: each point's influence g_i = ∂x/∂X_i is
taken from the fit's normal equations, and u_noise² = Σ (g_i·ray_i)² σ_z,i²,
u_fringe² = σ_q² Σ_columns (Σ_{i in column} (g_i·ray_i) ∂z_i/∂c)², u_cal² = Σ_d (Σ_i g_i·δX_d,i)².
Zone, range and root-mean-square figures are not linear and are biased by noise (a zone
holds the noise's extremes, Sq² gains the noise variance): they are evaluated by a
parametric bootstrap — the same estimator run on the measured surface plus fresh draws of
the modelled noise and fringe systematics — whose spread gives u and whose mean shift is
the noise bias, removed from the reported value (a zone of the filtered form surface then
reads what the surface has, not what the noise adds). That shift is what noise adds to the
already noisy surface, which for a zone differs from what it added to the true one by a
fraction of itself, either way: the removed bias b enters u as |b|/sqrt(3) (a rectangular
distribution from none to twice b), with the draws' Monte Carlo error of it
(`inspection.form.from_draws`). For an extreme (a zone, the profile, a deviation
extreme) the draws' spread at the measured surface understates the error's where that
surface's extreme is itself partly noise (among competing extremes the noise has already
picked one), so u_noise is at least the first-order spread: the draws at the cells that
hold the extreme, weighted as they hold it (a zone's LP dual prices, `mz_zone_sensitivity`).
Sq has the modelled noise variance removed in quadrature, and u from the variance of a mean of
squares.

Detection. A figure that noise alone could produce is not distinguishable from zero: it
is reported as null with its detection limit x_limit_mm L (printed `< L`). The test has a
stated false-detection rate, FALSE_DETECTION = 5 %: on a truly flat, smooth surface at
most one scan in twenty reports a value.
  - zones (and the profile, the deviation extremes): L is the 95th percentile of the zone
    the modelled noise alone spans on that face (the draws' own zones); a value is
    reported only when it exceeds L after its noise bias is removed. A truly flat face's
    raw zone is that of its noise, above L in 5 % of scans; the removed bias is positive
    for a zone, so the reported value of such a face is above L in fewer (measured on
    smooth plates: `slscan coverage --case smooth-flatness`).
  - Sq: the estimate of Sq² (mean square less the noise's) of a smooth surface is a mean
    over thousands of cells, near normal with standard deviation u0 (the draws' spread);
    the noise model's own error (its relative bound on sigma, `PointNoise.rel_u`) can shift
    it by up to b = 2 rel_u <noise²>. It is reported when it exceeds 1.645 u0 + b (5 %
    one-sided for any model error within its bound: on the simulator's smooth plates 1.645
    u0 alone let 6 % through), so L = sqrt(1.645 u0 + b) and every reported Sq is above L.
An undetected figure's u is the figure's uncertainty at L (a value at the limit is
uncertain by that much): `inspection.tolerances.decide` judges "< L" as the interval
[0, L + U], so it conforms only when L + U is within the tolerance.

The coverage of this model — the true value inside ±U for 95 % of repeat scans with fresh
noise, and with the errors of independent simulated calibrations — is measured on the
simulator (`slscan coverage [--calibrated]`, `studies.repeat_scans`, tests/test_uncertainty_coverage.py).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from scanner.decode import DecodeResult, DecodeSettings, decode
from scanner.geometry import Pinhole, RigModel, perturbed_pose
from scanner.native_threads import native_threads
from scanner.patterns import PatternSet
from scanner.reconstruct import Triangulator

K = 2.0  # coverage factor of every expanded uncertainty
FALSE_DETECTION = 0.05  # the share of truly smooth / flat surfaces a figure is "detected" on (one-sided)
DETECTION_QUANTILE = 1.0 - FALSE_DETECTION
DETECTION_Z = 1.6448536  # the standard normal's DETECTION_QUANTILE
PROJECTOR_BITS = 8  # grey levels of the projector's command images

SensorNoise = Callable[[np.ndarray], np.ndarray]  # mean signal A (DN) -> intensity noise sigma (DN)


# ---------------------------------------------------------------------------- estimates


@dataclass(frozen=True)
class Estimate:
    """A figure in mm: `value` (None when it cannot be told from zero; otherwise above
    `limit`), its standard uncertainty `u` (k = 1; at the limit for a null value), its
    detection `limit` (None where the figure is not tested
    against zero), the noise `bias` already removed from the value and the coverage
    factor `k` of its U: K for near-normal errors, else what gives the same coverage for
    the error's known distribution (`coverage_factor`)."""

    value: float | None
    u: float
    limit: float | None = None
    bias: float = 0.0
    k: float = K

    @property
    def U(self) -> float:
        """Expanded uncertainty (mm), about 95 % coverage: k·u."""
        return self.k * self.u

    def value_or_raise(self) -> float:
        """`value` (mm) of a figure that has one: one not tested against zero always does;
        ValueError for a figure below its detection limit."""
        if self.value is None:
            raise ValueError(f"the figure has no value: below its detection limit {self.limit} mm")
        return self.value

    def fields(self, name: str) -> dict[str, float | None]:
        """JSON fields: `name_mm`, `name_u_mm` (U, about 95 %) and, when tested against zero,
        `name_limit_mm`. `name` without its unit suffix."""
        out: dict[str, float | None] = {f"{name}_mm": self.value, f"{name}_u_mm": self.U}
        if self.limit is not None:
            out[f"{name}_limit_mm"] = self.limit
        return out

    def text(self, digits: int = 1) -> str:
        """For people, in µm: "12.3 ± 2.1 µm", or "< 6.1 µm" below the detection limit."""
        if self.value is None:
            return f"< {_um(self.limit, digits)} µm" if self.limit is not None else "not measured"
        return f"{_um(self.value, digits)} ± {_um(self.U, digits)} µm"


def _um(mm: float | None, digits: int) -> str:
    return "-" if mm is None else f"{mm * 1e3:.{digits}f}"


def combine(*u: float) -> float:
    """Root sum of squares of independent standard uncertainties."""
    return float(np.sqrt(sum(x * x for x in u)))


NORMAL_95 = 1.959964  # half-width of the central 95 % of a standard normal


def coverage_factor(u_normal: float, other: np.ndarray) -> float:
    """The coverage factor of an error that is a normal part of standard deviation
    `u_normal` plus an independent part equally likely to take each of the values `other`
    (zero mean; the fringe systematic at every placement, `FringeError.sums`), scaled so
    that a normal error keeps K: K times the half-width of the error's central 95 %
    (found from its distribution, GUM Supplement 1) over that of a normal error with the
    same standard deviation. A sum of a fixed function at a random offset is bounded and
    light-tailed: its 95 % interval is narrower than a normal one's (a sinusoid's is 1.41
    standard deviations, not 1.96), so where it dominates, k < K."""
    if len(other) == 0 or not np.std(other) > 0:
        return K
    from scipy.special import ndtr  # the standard normal's cdf as a bare ufunc: 60 bisections call it 120 times

    u = float(np.hypot(u_normal, np.std(other)))
    sigma = max(u_normal, 1e-9 * u)

    def inside(half: float) -> float:
        return float(np.mean(ndtr((half - other) / sigma) - ndtr((-half - other) / sigma)))

    lo, hi = 0.0, float(np.max(np.abs(other))) + 6.0 * sigma
    for _ in range(60):  # bisection to ~1e-18 of the span
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if inside(mid) < 0.95 else (lo, mid)
    return K * hi / (NORMAL_95 * u)


# ----------------------------------------------------------------------- point noise


@dataclass(frozen=True, eq=False)
class FringeError:
    """The decoded coordinate's error (projector px) that the projector's quantised
    patterns make, as a function of the projector coordinate: `table[k]` at coordinate
    k·`step_px` (circular). Its placement relative to a part is unknown, so it is used as a
    random function: the table at a uniformly random offset."""

    table: np.ndarray
    step_px: float

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.table ** 2)))

    def scaled(self, factor: float) -> FringeError:
        return FringeError(self.table * factor, self.step_px)

    def at(self, coordinate: np.ndarray, offset_px: float) -> np.ndarray:
        """The error at `coordinate` (px) with the table moved by `offset_px`."""
        k = (coordinate + offset_px) / self.step_px
        i = np.floor(k).astype(np.int64)
        t = k - i
        n = len(self.table)
        return self.table[i % n] * (1.0 - t) + self.table[(i + 1) % n] * t

    def sums(self, coordinate: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """Σ_i weight_i·error(coordinate_i) at every offset of the table (its samples): the
        weights binned on the table's samples and cross-correlated with it (FFT)."""
        n = len(self.table)
        k = coordinate / self.step_px
        i = np.floor(k).astype(np.int64)
        t = k - i
        binned = np.bincount(i % n, weight * (1.0 - t), n) + np.bincount((i + 1) % n, weight * t, n)
        return np.fft.irfft(np.fft.rfft(binned).conj() * np.fft.rfft(self.table), n)

    def spread(self, coordinate: np.ndarray, weight: np.ndarray) -> float:
        """Standard deviation over all offsets of Σ_i weight_i·error(coordinate_i)."""
        return float(np.std(self.sums(coordinate, weight)))


# How well the decoder-and-sensor model knows σ_z (one-sigma, relative): on the simulator
# (whose sensor model is the camera's own), two scans of the textured plate at each of 120
# random placements (`studies.repeat_scans.noise_model_check`, ~62 thousand pixels each): their
# depth difference over sqrt(2)·σ_z had spread 0.9999 mean, 0.0031 standard deviation over
# the placements, of which 0.0029 is each placement's statistical precision; the model's own
# RMS error is below 0.196 % (95 % upper bound, tests/test_uncertainty_coverage.py checks it). It
# enters every figure whose noise is subtracted (Sq). An earlier estimate from six
# placements (0.5 %) made Sq's U cover the truth in 99-100 % of repeat scans.
# A real camera's [camera.sensor] table would need its own photon-transfer fit's uncertainty.
DECODER_MODEL_REL_U = 0.002


@dataclass(frozen=True, eq=False)
class PointNoise:
    """The modelled errors of N measured points. A point moves along its camera `ray`
    ((N, 3), (x/z, y/z, 1)) by δz: white noise of `sigma_z` (N,) mm, plus, per fringe
    orientation, the fringe systematic `fringe` (a FringeError) at that orientation's
    projector coordinate `columns[o]` (N,) px, reaching depth through `gains[o]` (N,)
    mm/px. `source` says where sigma_z came from, `rel_u` how well it is known (one-sigma
    relative uncertainty of sigma_z, from that source: `DECODER_MODEL_REL_U`). `defocus_dz`
    (N,) mm: the depth bias the camera's defocus put on each point (`defocus_bias`, NaN
    where it cannot be estimated: near edges), None when not modelled; removing it raises
    the noise of those points by `defocus_gain` (`defocus_removed`)."""

    sigma_z: np.ndarray
    ray: np.ndarray
    columns: tuple[np.ndarray, ...] = ()
    gains: tuple[np.ndarray, ...] = ()
    fringe: FringeError | None = None
    source: str = "decoder and sensor model"
    rel_u: float = DECODER_MODEL_REL_U
    defocus_dz: np.ndarray | None = None
    defocus_gain: float = 1.0

    def __len__(self) -> int:
        return len(self.sigma_z)

    def subset(self, mask: np.ndarray) -> PointNoise:
        return replace(self, sigma_z=self.sigma_z[mask], ray=self.ray[mask],
                       columns=tuple(c[mask] for c in self.columns), gains=tuple(g[mask] for g in self.gains),
                       defocus_dz=None if self.defocus_dz is None else self.defocus_dz[mask])

    def defocus_removed(self) -> tuple[np.ndarray, PointNoise]:
        """(the depth moves (N,) mm that remove the modelled defocus bias, 0 where it is not
        known; this model for the corrected points: their noise raised by `defocus_gain`,
        no defocus left to remove)."""
        if self.defocus_dz is None:
            return np.zeros(len(self)), self
        fix = np.isfinite(self.defocus_dz)
        return (np.where(fix, -self.defocus_dz, 0.0),
                replace(self, sigma_z=np.where(fix, self.sigma_z * self.defocus_gain, self.sigma_z), defocus_dz=None))

    def rotated(self, R: np.ndarray) -> PointNoise:
        """The same model with the rays turned by the rotation R (3, 3) into another frame."""
        return replace(self, ray=self.ray @ R.T)

    def scaled(self, factor: float) -> PointNoise:
        """The same model with every noise and systematic scaled by `factor` (to check that
        a coverage test notices an underestimated noise)."""
        return replace(self, sigma_z=self.sigma_z * factor,
                       fringe=None if self.fringe is None else self.fringe.scaled(factor))

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """`n` draws (n, N) of δz (mm): white noise plus the fringe systematic at a random
        offset per draw and orientation."""
        dz = rng.standard_normal((n, len(self)))
        dz *= self.sigma_z
        if self.fringe is not None:
            span = len(self.fringe.table) * self.fringe.step_px
            for col, gain in zip(self.columns, self.gains):
                for k in range(n):
                    dz[k] += self.fringe.at(col, rng.uniform(0.0, span)) * gain
        return dz

    def linear_u(self, influence: np.ndarray) -> tuple[float, np.ndarray]:
        """(u_noise, the fringe systematic's errors) of a figure linear in the points, with
        per-point influence (N, 3) = ∂figure/∂X_i: the fringe's at every offset of its
        table (one orientation), or at 8192 random pairs of offsets (two, independent)."""
        along = np.einsum("ij,ij->i", influence, self.ray)  # ∂figure/∂z_i
        u_noise = float(np.sqrt(np.sum((along * self.sigma_z) ** 2)))
        if self.fringe is None or not self.columns:
            return u_noise, np.zeros(0)
        each = [self.fringe.sums(col, along * gain) for col, gain in zip(self.columns, self.gains)]
        if len(each) == 1:
            return u_noise, each[0]
        rng = np.random.default_rng(0)
        draws = [e[rng.integers(0, len(e), 8192)] for e in each]
        pairs = sum(draws[1:], draws[0])
        exact = float(np.sqrt(sum(np.var(e) for e in each)))  # the pairs' shape, the exact spread
        return u_noise, pairs * (exact / max(float(np.std(pairs)), 1e-300))


@dataclass(frozen=True, eq=False)
class DepthNoise:
    """Per-pixel maps (H, W) of a decoded scan: depth noise `sigma_z` (mm), and per
    orientation the coordinate `coordinate[o]` (px) and the gain `gain[o]` (mm per px)
    through which an error of that coordinate reaches the (averaged) depth."""

    sigma_z: np.ndarray
    coordinate: dict[str, np.ndarray]
    gain: dict[str, np.ndarray]
    weight: dict[str, np.ndarray]  # each orientation's share of the averaged depth

    def at(self, pixels: np.ndarray, camera: Pinhole, fringe: FringeError | None, source: str) -> PointNoise:
        """The PointNoise of the points seen at `pixels` (N, 2) (column, row)."""
        c, r = pixels[:, 0], pixels[:, 1]
        return PointNoise(self.sigma_z[r, c].astype(np.float64), camera.ray_grid[r, c].astype(np.float64),
                          tuple(m[r, c].astype(np.float64) for m in self.coordinate.values()),
                          tuple(g[r, c].astype(np.float64) for g in self.gain.values()), fringe, source)


def depth_noise(decoded: DecodeResult, triangulator: Triangulator, sensor: SensorNoise | None) -> DepthNoise:
    """The depth noise the decoder predicts per pixel (see the module docstring, 1.; NaN
    without a `sensor` model). With both fringe orientations the depths are averaged with
    the weights `scanner.reconstruct.triangulate` uses (phase precision over the squared
    depth sensitivity, the sensor noise common to both), and σ_z is that average's."""
    precision, slope, coords, sigma = {}, {}, {}, {}
    for orientation, m in decoded.maps.items():
        coords[orientation] = np.where(decoded.valid, m.coordinate, np.nan)
        _, dz = triangulator.depth_scale(coords[orientation], orientation, sensitivity=True)
        slope[orientation] = dz.astype(np.float64)
        precision[orientation] = m.phase_weight.astype(np.float64) * m.period_px ** -2.0 / slope[orientation] ** 2
        if sensor is not None:
            sigma_i = sensor(m.background.astype(np.float64))
            sigma_phi = np.sqrt(2.0 / decoded.patterns.steps) * sigma_i / np.sqrt(np.maximum(m.phase_weight, 1e-12))
            sigma[orientation] = sigma_phi * m.period_px / (2.0 * np.pi) * slope[orientation]
    total = sum(precision.values())
    weight = {o: p / total for o, p in precision.items()}
    sigma_z = (np.sqrt(sum((weight[o] * sigma[o]) ** 2 for o in sigma)) if sigma
               else np.full(decoded.valid.shape, np.nan))
    return DepthNoise(sigma_z, coords, {o: weight[o] * slope[o] for o in slope}, weight)


def fringe_error(patterns: PatternSet, extent_px: int, gamma: float, blur_px: float = 0.0,
                 oversample: int = 8) -> FringeError:
    """The decoded coordinate's error (projector px) that `PROJECTOR_BITS`-bit commands
    pre-compensated for `gamma` make, on a projector of `extent_px` pixels along the coded
    axis whose optics blur by `blur_px` (Gaussian sigma, projector px): the displayed
    profiles, sampled every 1/`oversample` px away from the outer fringe periods, run
    through the scanner's own decoder."""
    one = PatternSet(patterns.family, patterns.steps, patterns.fringes, ("vertical",))
    commands = one.render(extent_px, 1, gamma)[:, 0, :].astype(np.float64)
    shown = (commands / (2 ** PROJECTOR_BITS - 1)) ** gamma
    if blur_px > 0:
        shown = ndimage.gaussian_filter1d(shown, blur_px, axis=1, mode="mirror")
    margin = extent_px / min(patterns.fringes)
    u = np.arange(margin, extent_px - margin, 1.0 / oversample)
    rows = np.zeros_like(u)
    samples = np.stack([ndimage.map_coordinates(np.stack([s, s]), [rows, u], order=3, mode="mirror")
                        for s in shown])
    scale = 2 ** 16 - 1
    frames = np.rint(samples * (0.5 * scale) + 0.25 * scale).astype(np.uint16)[:, None, :]
    result = decode(frames, one, 16, (extent_px, 1), DecodeSettings(spatial_check=False))
    err = result.maps["vertical"].coordinate[0].astype(np.float64) - u
    err = np.where(np.isfinite(err), err, 0.0)
    return FringeError(err - err.mean(), 1.0 / oversample)


# ----------------------------------------------------------------------- calibration


RIG_PARAMETERS = tuple(f"{dev}.{n}" for dev in ("camera", "projector")
                       for n in ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")) + \
    tuple(f"extrinsic.{n}" for n in ("rx", "ry", "rz", "tx", "ty", "tz"))


@dataclass(frozen=True, eq=False)
class CalibrationUncertainty:
    """The covariance (P, P) of the rig parameters `RIG_PARAMETERS` (px, unitless
    distortion; the extrinsic is proj_from_cam as a Rodrigues vector (rad) and a
    translation (mm)) and where it came from."""

    covariance: np.ndarray
    source: str

    @classmethod
    def none(cls, reason: str) -> CalibrationUncertainty:
        return cls(np.zeros((len(RIG_PARAMETERS),) * 2), reason)

    @classmethod
    def from_report(cls, data: dict[str, Any]) -> CalibrationUncertainty:
        """From a calibration file's content: its full "covariance" when it has one, else
        its one-sigmas ("uncertainty") taken as uncorrelated."""
        cov = data.get("covariance")
        if isinstance(cov, dict) and list(cov.get("parameters", ())) == list(RIG_PARAMETERS):
            return cls(np.asarray(cov["matrix"], dtype=np.float64), "the calibration's covariance")
        std = data.get("uncertainty") or {}
        sd = np.array([float(std.get(n, 0.0)) for n in RIG_PARAMETERS])
        return cls(np.diag(sd ** 2), "the calibration's one-sigmas, taken as uncorrelated (the file holds no "
                                     "covariance)")

    @property
    def is_zero(self) -> bool:
        return not np.any(self.covariance)

    def directions(self) -> np.ndarray:
        """Principal one-sigma perturbations (D, P) of the parameters, Σ = Σ_d δ_d δ_dᵀ;
        directions carrying no variance are left out."""
        scale = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        s = np.where(scale > 0, scale, 1.0)
        w, v = np.linalg.eigh(self.covariance / np.outer(s, s))
        keep = w > max(float(w.max()), 0.0) * 1e-12
        return (v[:, keep] * np.sqrt(w[keep])).T * s

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """One parameter perturbation (P,) drawn from N(0, covariance)."""
        d = self.directions()
        return rng.standard_normal(len(d)) @ d if len(d) else np.zeros(len(RIG_PARAMETERS))

    def shifts(self, points: np.ndarray, model: RigModel, weights: dict[str, np.ndarray]) -> np.ndarray | None:
        """Displacements (D, N, 3) mm of camera-frame `points` (N, 3) for each principal
        direction (`calibration_jacobian`); None when there is no calibration uncertainty."""
        if self.is_zero:
            return None
        return np.einsum("nip,dp->dni", calibration_jacobian(points, model, weights), self.directions())


def perturbed(model: RigModel, delta: np.ndarray) -> RigModel:
    """The rig with its parameters moved by `delta` (P,) (order of `RIG_PARAMETERS`)."""
    Q = perturbed_pose(model.proj_from_cam, delta[18:24])
    return replace(model, camera=model.camera.perturbed(delta[:9]), projector=model.projector.perturbed(delta[9:18]),
                   cam_from_proj=np.linalg.inv(Q), phase_to_height=None)


def _projection_jacobians(points: np.ndarray, model: RigModel) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's analytic derivatives of the camera's and the projector's projections of
    camera-frame `points` (N, 3): (N, 2, 15) each, columns (rvec, tvec, fx, fy, cx, cy,
    k1, k2, p1, p2, k3); the projector's pose is proj_from_cam."""
    X = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 3)
    cam, proj = model.camera, model.projector
    _, Jc = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    P = model.proj_from_cam
    _, Jp = cv2.projectPoints(X, cv2.Rodrigues(P[:3, :3])[0].ravel(), P[:3, 3], proj.K, proj.dist)
    return Jc.reshape(len(X), 2, -1), Jp.reshape(len(X), 2, -1)


def _constraints(Jc: np.ndarray, Jp: np.ndarray, model: RigModel, axis: int) -> np.ndarray:
    """A (N, 3, 3) = ∂(camera pixel, projector coordinate along `axis`)/∂X."""
    return np.concatenate([Jc[:, :, 3:6], (Jp[:, axis, 3:6] @ model.proj_from_cam[:3, :3])[:, None, :]], axis=1)


def calibration_jacobian(points: np.ndarray, model: RigModel, weights: dict[str, np.ndarray]) -> np.ndarray:
    """∂X/∂θ (N, 3, P): how camera-frame points (N, 3) triangulated from fixed camera
    pixels and decoded projector coordinates move with the rig parameters θ
    (`RIG_PARAMETERS`). A point satisfies π_cam(X; θ) = pixel and π_proj(X; θ)[axis] =
    coordinate per orientation; implicit differentiation with OpenCV's analytic projection
    derivatives gives ∂X/∂θ = −A⁻¹B per orientation, and with two orientations the depths
    are averaged with `weights` (N,) per orientation, as reconstruction does."""
    Jc, Jp = _projection_jacobians(points, model)
    n = len(Jc)
    out = np.zeros((n, 3, len(RIG_PARAMETERS)))
    for orientation, w in weights.items():
        axis = 0 if orientation == "vertical" else 1
        B = np.zeros((n, 3, len(RIG_PARAMETERS)))
        B[:, :2, 0:9] = Jc[:, :, 6:15]
        B[:, 2, 9:18] = Jp[:, axis, 6:15]
        B[:, 2, 18:24] = Jp[:, axis, 0:6]
        out -= w[:, None, None] * np.linalg.solve(_constraints(Jc, Jp, model, axis), B)
    return out


def measurement_jacobian(points: np.ndarray, model: RigModel, orientation: str = "vertical") -> np.ndarray:
    """∂X/∂(camera column, camera row, projector coordinate) (N, 3, 3) of camera-frame
    `points` (N, 3) triangulated from a camera pixel and one projector coordinate (along
    x for vertical fringes): A⁻¹ of the same constraints as `calibration_jacobian`."""
    Jc, Jp = _projection_jacobians(points, model)
    A = _constraints(Jc, Jp, model, 0 if orientation == "vertical" else 1)
    return np.linalg.inv(A)


# ------------------------------------------------------------------ a scan's uncertainty


@dataclass(frozen=True, eq=False)
class LinearU:
    """The standard uncertainties (mm) of a figure linear in the points, by source, and
    the figure's fringe errors over the placements of the fringe systematic (`fringe_errors`,
    its distribution, which is not normal; empty without one)."""

    noise: float
    fringe: float
    calibration: float
    fringe_errors: np.ndarray

    @property
    def components(self) -> dict[str, float]:
        return {"noise": self.noise, "fringe": self.fringe, "calibration": self.calibration}

    def estimate(self, value: float) -> Estimate:
        """The figure `value` with its u and the coverage factor of its error's distribution
        (noise and calibration normal, the fringe as it is: `coverage_factor`)."""
        return Estimate(value, combine(self.noise, self.fringe, self.calibration),
                        k=coverage_factor(float(np.hypot(self.noise, self.calibration)),
                                          self.fringe_errors - np.mean(self.fringe_errors)
                                          if len(self.fringe_errors) else self.fringe_errors))


@dataclass(frozen=True, eq=False)
class PointJacobian:
    """∂X/∂θ of points as the triangulation that made them gives it (a binocular rig's matcher,
    `scanner.binocular.BinocularResult.calibration_jacobian`, over the stereo calibration's 24
    parameters): `of(index)` (n, 3, P) for the points at `index` of that triangulation (flat left
    pixels), these points being at `index`."""

    of: Callable[[np.ndarray], np.ndarray]
    index: np.ndarray

    def subset(self, mask: np.ndarray) -> PointJacobian:
        return replace(self, index=self.index[mask])

    def __call__(self) -> np.ndarray:
        return self.of(self.index)


@dataclass(frozen=True, eq=False)
class ScanUncertainty:
    """What the figures measured on N points of a scan are propagated with: the points'
    noise model, the calibration's covariance, the rig model they were triangulated with
    and each point's share of the depth per fringe orientation (`weights`, (N,) each), or, where
    the triangulation gives it itself (a binocular rig), each point's ∂X/∂θ (`jacobian`)."""

    noise: PointNoise | None
    calibration: CalibrationUncertainty
    model: RigModel | None = None
    weights: dict[str, np.ndarray] | None = None
    jacobian: PointJacobian | None = None

    def subset(self, mask: np.ndarray) -> ScanUncertainty:
        w = None if self.weights is None else {o: v[mask] for o, v in self.weights.items()}
        return ScanUncertainty(None if self.noise is None else self.noise.subset(mask), self.calibration, self.model, w,
                               None if self.jacobian is None else self.jacobian.subset(mask))

    def shifts(self, points: np.ndarray) -> np.ndarray | None:
        """The points' (N, 3, camera frame) moves (D, N, 3) for each principal calibration
        direction; None without calibration uncertainty. One move of the calibration moves every
        point: a figure adds its points' moves before squaring (`linear_u`)."""
        if self.calibration.is_zero:
            return None
        if self.jacobian is not None:
            J = self.jacobian()
            if len(J) != len(points):
                raise ValueError(f"{len(points)} points, a Jacobian of {len(J)}")
            return np.einsum("nip,dp->dni", J, self.calibration.directions())
        if self.model is None or self.weights is None:
            return None
        return self.calibration.shifts(points, self.model, self.weights)

    def linear_u(self, points: np.ndarray, influence: np.ndarray, residual_rms: float = 0.0) -> LinearU:
        """The uncertainty of a figure linear in the points (N, 3), with per-point
        influence (N, 3) = ∂figure/∂X_i. Without a noise model the points' noise is taken
        as white along their rays with the fit's `residual_rms`."""
        noise = self.noise or PointNoise(np.full(len(points), residual_rms), points / points[:, 2:3],
                                         source="estimated from the fit's residuals",
                                         rel_u=1.0 / np.sqrt(2.0 * max(len(points), 1)))
        u_noise, fringe = noise.linear_u(influence)
        shifts = self.shifts(points)
        u_cal = 0.0 if shifts is None else float(np.sqrt(np.sum(np.einsum("dij,ij->d", shifts, influence) ** 2)))
        return LinearU(u_noise, float(np.std(fringe)) if len(fringe) else 0.0, u_cal, fringe)

    @classmethod
    def join(cls, parts: list[ScanUncertainty]) -> ScanUncertainty:
        """One model for the points of several parts of the same scan (or rig), in order."""
        first = parts[0]
        n = [p.noise for p in parts if p.noise is not None]
        noise = None
        if len(n) == len(parts):  # a noise model only when every part has one
            noise = PointNoise(np.concatenate([x.sigma_z for x in n]), np.concatenate([x.ray for x in n]),
                               tuple(np.concatenate(c) for c in zip(*(x.columns for x in n))),
                               tuple(np.concatenate(g) for g in zip(*(x.gains for x in n))), n[0].fringe,
                               n[0].source, n[0].rel_u)
        weights = None
        if first.weights is not None:
            w = [p.weights for p in parts if p.weights is not None]
            if len(w) != len(parts):
                raise ValueError("ScanUncertainty.join: the first part has depth weights, another has none")
            weights = {o: np.concatenate([x[o] for x in w]) for o in first.weights}
        jacobian = None
        if first.jacobian is not None:
            js = [p.jacobian for p in parts if p.jacobian is not None]
            if len(js) != len(parts) or any(j.of != first.jacobian.of for j in js):
                raise ValueError("ScanUncertainty.join: the parts' points come from different triangulations")
            jacobian = PointJacobian(first.jacobian.of, np.concatenate([j.index for j in js]))
        return cls(noise, first.calibration, first.model, weights, jacobian)


def scan_uncertainty(decoded: DecodeResult, model: RigModel, sensor: SensorNoise | None, fringe: FringeError | None,
                     calibration: CalibrationUncertainty, pixels: np.ndarray) -> ScanUncertainty:
    """The ScanUncertainty of the points a decoded scan gives at `pixels` (N, 2) (column,
    row), triangulated with `model`. Without a `sensor` noise model there is no noise
    model (None): the figures then estimate the noise from the data."""
    return MeasurementModel(sensor, fringe, calibration).of_scan(decoded, model)(pixels)


@dataclass(frozen=True, eq=False)
class MeasurementModel:
    """What a rig's figures are propagated with: the camera's intensity noise (`sensor`,
    None: not known), the projector's fringe error, the calibration's covariance and the
    camera's defocus (`camera_blur_px`, Gaussian sigma in camera pixels; 0: not known or
    none). One per rig; `slscan.measurement_model.rig_measurement` makes it from a rig
    file, and `scan`, `inspect`, `verify` and `slscan coverage` all use it so."""

    sensor: SensorNoise | None
    fringe: FringeError | None
    calibration: CalibrationUncertainty
    camera_blur_px: float = 0.0

    def of_scan(self, decoded: DecodeResult, model: RigModel, *, defocus: bool = False
                ) -> Callable[[np.ndarray], ScanUncertainty]:
        """ScanUncertainty of the points at camera pixels (N, 2) (column, row) of a scan
        triangulated with `model`; the per-pixel maps are made once. `defocus`: model the
        camera defocus's depth bias per point (`PointNoise.defocus_dz`; inspected surfaces
        remove it, the artefact fits leave their outlines out instead)."""
        maps = depth_noise(decoded, Triangulator(model), self.sensor)
        dz = None
        if defocus and self.camera_blur_px > 0 and self.sensor is not None:
            bias = defocus_bias(decoded, self.camera_blur_px)
            dz = sum(maps.gain[o] * bias[o] for o in bias)
        gain = _correction_gain(self.camera_blur_px) if dz is not None else 1.0

        def at(pixels: np.ndarray) -> ScanUncertainty:
            c, r = pixels[:, 0], pixels[:, 1]
            noise = None
            if self.sensor is not None:
                noise = replace(maps.at(pixels, model.camera, self.fringe, "decoder and sensor model"),
                                defocus_dz=None if dz is None else dz[r, c].astype(np.float64), defocus_gain=gain)
            return ScanUncertainty(noise, self.calibration, model, {o: w[r, c] for o, w in maps.weight.items()})

        return at


# ------------------------------------------------------------------------ camera defocus


_QUADRATIC = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))  # monomials x^a y^b of a local quadratic


QUADRATIC_HALF_PX = 3  # local_quadratic's window half-width (px): 7 x 7


def local_quadratic(values: np.ndarray, valid: np.ndarray, half_px: int = QUADRATIC_HALF_PX, min_fraction: float = 0.5
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares quadratic of `values` (H, W) over the valid pixels of the
    (2·half_px+1)² window around each pixel: its gradient (∂/∂column, ∂/∂row, per px) and
    Laplacian at the pixel, NaN where fewer than `min_fraction` of the window is valid
    (`local_quadratics` of one image)."""
    return local_quadratics([values], valid, half_px=half_px, min_fraction=min_fraction)[0]


def local_quadratics(images: Sequence[np.ndarray], valid: np.ndarray, *, half_px: int = QUADRATIC_HALF_PX,
                     min_fraction: float = 0.5) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """`local_quadratic` of each of `images` (H, W) over the same `valid` pixels, whose
    window moments and normal equations are made once. The moments are correlations of the
    valid mask with monomial kernels, separable and exact (integer sums); each image's
    right-hand sides are 6 filters. A pixel whose whole window is valid shares one normal
    matrix (one product for all of them); the others take a batched 6 × 6 solve. BLAS runs
    on one thread: the product is thin and memory-bound, and a second thread only spins
    (0.6 s -> 0.02 s on a 1280 × 1024 scan, 2-core VM under load)."""
    o = np.arange(-half_px, half_px + 1, dtype=np.float64)
    ox, oy = np.meshgrid(o, o)
    mask = valid.astype(np.float64)
    moment = {(a, b): cv2.sepFilter2D(mask, cv2.CV_64F, o ** a, o ** b, borderType=cv2.BORDER_CONSTANT)
              for a in range(5) for b in range(5 - a)}
    enough = valid & (moment[(0, 0)] >= min_fraction * o.size ** 2)
    full = enough & (moment[(0, 0)] > o.size ** 2 - 0.5)  # whole window valid: one normal matrix for all
    part = np.flatnonzero(enough & ~full)
    at_part = {k: m.ravel()[part] for k, m in moment.items()}
    normal = np.stack([np.stack([at_part[(a + c, b + d)] for c, d in _QUADRATIC], -1) for a, b in _QUADRATIC], -2)
    whole = np.array([[np.sum(ox ** (a + c) * oy ** (b + d)) for c, d in _QUADRATIC] for a, b in _QUADRATIC])
    used = [1, 2, 3, 5]  # the coefficients of x, y, x² and y²
    out = []
    for values in images:
        data = np.where(valid, values, 0.0).astype(np.float64)
        rhs = np.empty((6,) + data.shape)
        for k, (a, b) in enumerate(_QUADRATIC):
            cv2.filter2D(data, cv2.CV_64F, ox ** a * oy ** b, dst=rhs[k], borderType=cv2.BORDER_CONSTANT)
        rhs = rhs.reshape(6, -1)
        with native_threads(1):
            coef = np.linalg.inv(whole)[used] @ rhs
        coef[:, ~full.ravel()] = np.nan
        coef[:, part] = np.linalg.solve(normal, rhs[:, part].T[..., None])[:, used, 0].T
        gx, gy, xx, yy = coef.reshape((4,) + data.shape)
        out.append((gx, gy, 2.0 * (xx + yy)))
    return out


def defocus_bias(decoded: DecodeResult, blur_sigma_px: float) -> dict[str, np.ndarray]:
    """The decoded coordinate's bias (projector px, (H, W) per orientation, NaN where it
    cannot be estimated) that a Gaussian camera defocus of `blur_sigma_px` (camera px)
    makes where the coordinate or the fringe modulation is not linear across the blur.

    Phase shifting measures the phase of the complex fringe signal s = B·e^{iφ} (B the
    modulation, the same shape for every frequency: albedo, shading and the projector's contrast;
    φ = 2π·f·c). The camera blur G of variance σ² is linear, so every frame, and hence s, is
    blurred alike; to first order G∗s = s + σ²/2·∇²s, and
        arg(G∗s) − φ = σ²·(∇ln B·∇φ + ½·∇²φ)
    (the real part of ∇²s/s only changes the modulation). In coordinate units the same
    for every frequency: δc = σ²·(∇ln B·∇c + ½·∇²c), derivatives in camera pixels. On a
    plane seen through a pinhole c is nearly linear and B nearly constant: no bias. On a
    sphere c curves and the shading falls toward the silhouette, both outward, so the
    coordinate — and the radius — is biased: +0.2-0.3 µm on a 25 mm sphere on the
    simulator's bench rig (σ = 0.6 px). Projector defocus blurs a sinusoid into the same
    sinusoid: no phase bias (only its quantisation residue, `fringe_error`). The
    derivatives come from local quadratic fits of the measured c and ln B
    (`local_quadratic`), which are themselves blurred: that is a σ⁴ effect.

    At an edge of the surface (a silhouette, a shadow) B steps to zero and the first
    order fails: the band of 3σ + 1 px along the valid region's edges is left out (NaN),
    and the fits use only the pixels inside it. Checked against the simulator (sphere,
    σ 0.6 px, noise-free, blurred minus unblurred decode): slope 0.94-0.97, correlation
    0.96 more than 8 px inside the silhouette; within 2 px of it the actual error is
    −0.19 px on average, which is why the artefact fits leave that band out
    (`inspection.acceptance.inner_pixels`). On a textured plate (Sq 7.5-7.9 µm, 1.5-4 mm
    wavelengths, 0.125 mm pixels) the blur makes Sq read 0.13-0.22 µm low; corrected
    with this bias, −0.01 to +0.04 µm."""
    out = {}
    s2 = blur_sigma_px ** 2
    edge = np.ones((2 * int(np.ceil(3.0 * blur_sigma_px)) + 3,) * 2, np.uint8)
    for orientation, m in decoded.maps.items():
        valid = cv2.erode((decoded.valid & np.isfinite(m.coordinate)).view(np.uint8), edge, borderValue=0) > 0
        (gc, rc, lc), (gb, rb, _) = local_quadratics(
            [m.coordinate, 0.5 * np.log(np.maximum(m.phase_weight, 1e-12))], valid)  # c and ln B + const
        out[orientation] = s2 * (gb * gc + rb * rc + 0.5 * lc)
    return out


def _correction_gain(blur_sigma_px: float) -> float:
    """How much removing the defocus bias (`defocus_bias`, estimated from the noisy
    coordinate itself) raises white coordinate noise (a factor ≥ 1): the corrected value
    is c − σ²/2·(L∗c) + ..., L the Laplacian of `local_quadratic`'s window fit, whose
    weights come from fitting a single unit impulse (1.005 at σ = 0.6 px; measured on the
    simulator's plate: noisy minus noise-free decode over the predicted σ_z 0.999 -> 1.004
    and 0.995 -> 1.000 at two placements). The gradient terms' share is second order."""
    h = QUADRATIC_HALF_PX
    impulse = np.zeros((4 * h + 1, 4 * h + 1))
    impulse[2 * h, 2 * h] = 1.0
    weights = local_quadratic(impulse, np.ones(impulse.shape, bool), h)[2][h:3 * h + 1, h:3 * h + 1]
    k = -0.5 * blur_sigma_px ** 2 * weights
    k[h, h] += 1.0
    return float(np.sqrt(np.sum(k ** 2)))
