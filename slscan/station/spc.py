"""Statistical process control of a characteristic, computed as Minitab and Q-DAS do:
Shewhart control charts with limits from the data (or frozen from a baseline), Nelson's
eight run rules, and process capability Cp/Cpk (within) and Pp/Ppk (overall) with
confidence intervals, a normality test and a non-normal capability for figures bounded at 0.

Individuals and moving range (I-MR), one value per part (ISO 7870-2; AIAG SPC manual):

    moving ranges MR_i = |x_i - x_(i-1)|, MR-bar their mean; sigma-hat = MR-bar / d2(2)
    I chart   centre x-bar, limits x-bar +- 3 sigma-hat
    MR chart  centre MR-bar, UCL D4(2) MR-bar, LCL D3(2) MR-bar (= 0)

X-bar and R, for subgroups of n (2..10) consecutive parts (`[control] subgroup_size` in the
part program); an incomplete last subgroup is left out:

    sigma-hat = R-bar / d2(n); X-bar chart x-double-bar +- 3 sigma-hat / sqrt(n);
    R chart centre R-bar, limits D3(n) R-bar, D4(n) R-bar

d2(n) and d3(n) (mean and standard deviation of the range of n standard normal values)
are computed by numerical integration; D3 = max(0, 1 - 3 d3/d2), D4 = 1 + 3 d3/d2. (No c4:
neither chart uses a subgroup SD, and Minitab's overall sigma is the plain sample SD.)

Every figure is a width or a height: its natural lower bound is 0. A lower control limit
below 0 is set to 0 (`Limits.lcl_clipped`), as Minitab does for a characteristic with a
lower bound; no point can be beyond it. Limits need at least `MIN_INDIVIDUALS` values
(I-MR) or `MIN_SUBGROUPS` subgroups (X-bar R), the AIAG manual's minimum for a preliminary
study: fewer give no limits and a warning, never limits from 2 values.

Censored values. A figure below its detection limit L (noise alone could read that much)
is a left-censored value: its true value is somewhere in [0, L]. It is kept, plotted at L
and marked. The chart's centre and the capability's mean and overall sigma are the
maximum-likelihood estimates of a normal with the censored values entering through
P(X < L) (the Tobit likelihood; `normal_fit`); without censored values these are the
sample mean and standard deviation. The within sigma uses the moving ranges (or subgroup
ranges) whose values are all measured: a range with a censored value is not known.

Nelson's rules (Nelson 1984, Minitab's tests 1-8), on the location chart's points against
zones of the plotted statistic's sigma about the centre; a point is flagged with every
rule whose run ends at it (see `NELSON_RULES`; `DEFAULT_RULES` when none are chosen).
The share of in-control points (independent normal values, the limits known) each rule
flags, from 10^6 simulated points (seed 3633629677; tests/test_station_spc.py measures it
again on fresh draws):

    rule  pattern (the run ends at the flagged point)                      false alarms
    1     one point beyond a control limit (3 sigma)                       0.27 %
    2     nine in a row on one side of the centre                          0.39 %
    3     six in a row all increasing or all decreasing                    0.28 %
    4     fourteen in a row alternating up and down                        0.46 %
    5     two of three beyond 2 sigma on one side (the last one beyond)    0.20 %
    6     four of five beyond 1 sigma on one side (the last one beyond)    0.46 %
    7     fifteen in a row within 1 sigma (either side)                    0.34 %
    8     eight in a row beyond 1 sigma (either side)                      0.01 %

Any of the default set 1, 2, 5, 6 flags 1.25 % of in-control points (about one in 80), all
eight 2.3 %: a flag is a reason to look, not proof of a cause.

Capability (ISO 22514-2; Minitab's "Normal capability analysis"), against the upper limit
USL (the tolerance) and the natural lower bound 0:

    Cp  = USL / (6 sigma_within)     Cpk = (USL - mean) / (3 sigma_within)
    Pp  = USL / (6 sigma_overall)    Ppk = (USL - mean) / (3 sigma_overall)

Minitab leaves Cp and Pp out when the lower end is a natural bound; here they compare the
spread with the whole band 0..USL, so Cpk exceeds Cp when the process sits in the band's
lower half (where a form error should be). sigma_within from the chart (MR-bar / d2 or
R-bar / d2), sigma_overall the sample SD (n - 1 divisor, no c4: Minitab's default). 95 %
intervals: Cp and Pp from the chi-squared distribution, Cpk and Ppk by Bissell's
approximation, index +- z sqrt(1 / (9 n) + index^2 / (2 nu)); nu = n - 1 for the overall
sigma, and for the within sigma its effective degrees of freedom (Patnaik: Var(sigma-hat)
= sigma^2 / (2 nu)): about 0.6 (n - 1) for moving ranges, whose variance and neighbours'
covariance are known in closed form (`mr_dof`), k d2^2 / (2 d3^2) for k subgroup ranges
(`range_dof`). Normality: the Anderson-Darling test (statistic A^2 with the sample mean
and SD; p-value from A^2 (1 + 0.75 / n + 2.25 / n^2) by D'Agostino and Stephens' (1986)
table 4.9 formulas, as Minitab). A figure bounded at 0 near the bound is skewed: the non-normal
capability is a two-parameter Weibull (location 0) fitted by maximum likelihood (censored
values through its CDF), by the ISO 22514-2 percentile method:

    Pp = USL / (X99.865 - X0.135)    Ppk = (USL - X50) / (X99.865 - X50)

with 95 % intervals by the delta method on the fit's information matrix (`weibull_intervals`;
measured coverage 93-95 % on Weibull samples of 40 and 100, tests/test_station_spc.py).

The model the indices are read from (`Capability.model`): normal when the
Anderson-Darling test does not reject it at 5 %, else Weibull; with censored values (no
test is possible on them) the model of the higher likelihood (both have 2 parameters).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np

MIN_INDIVIDUALS = 25  # values needed before I-MR limits are computed (AIAG: 20-25 subgroups, >= 100 values)
MIN_SUBGROUPS = 20  # subgroups needed before X-bar R limits are computed
MIN_CAPABILITY_N = 30  # values below which capability indices carry a warning (their intervals are wide)
CONFIDENCE = 0.95
NORMALITY_ALPHA = 0.05  # the Anderson-Darling test's level: below it the normal model is rejected
MAX_SUBGROUP = 10
LOWER_BOUND = 0.0  # the natural lower bound of every figure (a zone width or a height, mm)
NELSON_RULES = {
    1: "1 point beyond a control limit",
    2: "9 in a row on one side of the centre",
    3: "6 in a row increasing or decreasing",
    4: "14 in a row alternating up and down",
    5: "2 of 3 beyond 2 sigma on one side",
    6: "4 of 5 beyond 1 sigma on one side",
    7: "15 in a row within 1 sigma",
    8: "8 in a row beyond 1 sigma, either side",
}
DEFAULT_RULES = (1, 2, 5, 6)  # the Western Electric set, in Nelson's numbering


@cache
def range_constants(n: int) -> tuple[float, float]:
    """(d2, d3): mean and standard deviation of the range R of `n` independent standard
    normal values (the published tables' source), by the trapezoidal rule on a grid over
    +-7 sigma: E[R] = int 1 - F(x)^n - (1 - F(x))^n dx and, with P(min < x, max > y)
    = 1 - F(y)^n - (1 - F(x))^n + (F(y) - F(x))^n for x < y, E[R^2] = 2 int int_(x<y) of it."""
    from scipy import integrate, stats  # scipy.stats takes ~0.6 s to import: only when charts are computed
    if not 2 <= n <= 25:
        raise ValueError(f"subgroup size must be 2..25, got {n}")
    g = np.linspace(-7.0, 7.0, 1401)
    f = stats.norm.cdf(g)
    d2 = float(integrate.trapezoid(1 - f ** n - (1 - f) ** n, g))
    fx, fy = f[:, None], f[None, :]
    upper = np.triu(np.ones((len(g), len(g))), 1) + 0.5 * np.eye(len(g))  # y > x; the diagonal half inside
    both = upper * (1 - fy ** n - (1 - fx) ** n + np.clip(fy - fx, 0, None) ** n)
    second = 2 * float(integrate.trapezoid(integrate.trapezoid(both, g, axis=1), g))
    return d2, float(np.sqrt(second - d2 * d2))


def chart_constants(n: int) -> tuple[float, float, float]:
    """(d2, D3, D4) of subgroups of size `n`."""
    d2, d3 = range_constants(n)
    return d2, max(0.0, 1 - 3 * d3 / d2), 1 + 3 * d3 / d2


@dataclass(frozen=True)
class Limits:
    """A chart's centre line and control limits (mm), the sigma of its plotted statistic
    (mm), and whether the LCL was raised to the natural bound 0."""

    centre: float
    lcl: float
    ucl: float
    sigma: float
    lcl_clipped: bool = False


@dataclass(frozen=True)
class ControlChart:
    """Limits of a location chart (individuals or subgroup means) and of its spread chart
    (moving ranges or subgroup ranges), the process sigma-hat (mm) they rest on, and how
    many chart points (values or subgroups) they were computed from."""

    kind: str  # "I-MR" or "Xbar-R"
    subgroup: int
    location: Limits
    spread: Limits
    sigma_within: float
    points: int = 0
    dof: float = 0.0  # effective degrees of freedom of sigma_within (`mr_dof`, `range_dof`; 0: not known)


def _clipped(centre: float, half: float, sigma: float) -> Limits:
    lcl = centre - half
    return Limits(centre, max(lcl, LOWER_BOUND), centre + half, sigma, lcl < LOWER_BOUND)


def _censored(x: np.ndarray, censored: Sequence[bool] | np.ndarray | None) -> np.ndarray:
    return np.zeros(x.shape, bool) if censored is None else np.asarray(censored, bool).reshape(x.shape)


def minimum_points(subgroup: int) -> int:
    """Chart points needed before limits are computed (values or subgroups)."""
    return MIN_INDIVIDUALS if subgroup == 1 else MIN_SUBGROUPS


def individuals_limits(x: Sequence[float], censored: Sequence[bool] | None = None) -> ControlChart:
    """I-MR limits from values in time order (censored values at their detection limit,
    `censored` marking them; module docstring). Any number of values >= 3: the minimum
    sample is the caller's (`minimum_points`)."""
    values = np.asarray(x, float)
    cens = _censored(values, censored)
    known = ~cens[1:] & ~cens[:-1]
    if known.sum() < 2:
        raise ValueError(f"I-MR limits need at least 2 moving ranges of measured values, got {int(known.sum())}")
    mr_bar = float(np.abs(np.diff(values))[known].mean())
    d2, d3_factor, d4_factor = chart_constants(2)
    sigma = mr_bar / d2
    mean = normal_fit(values, cens)[0]
    mr_sigma = mr_bar * range_constants(2)[1] / d2
    return ControlChart("I-MR", 1, _clipped(mean, 3 * sigma, sigma),
                        Limits(mr_bar, d3_factor * mr_bar, d4_factor * mr_bar, mr_sigma), sigma, len(x),
                        mr_dof(int(known.sum()), int((known[1:] & known[:-1]).sum())))


def subgroup_limits(groups: np.ndarray, censored: np.ndarray | None = None) -> ControlChart:
    """X-bar and R limits from subgroups (k, n) in time order (censored values at their
    limit, marked by `censored` (k, n)); R-bar over the subgroups without a censored value."""
    groups = np.asarray(groups, float)
    k, n = groups.shape
    cens = _censored(groups, censored)
    whole = ~cens.any(axis=1)
    if whole.sum() < 2:
        raise ValueError(f"X-bar R limits need at least 2 subgroups of measured values, got {int(whole.sum())}")
    r_bar = float(np.ptp(groups[whole], axis=1).mean())
    d2, d3_factor, d4_factor = chart_constants(n)
    sigma = r_bar / d2
    grand = normal_fit(groups.ravel(), cens.ravel())[0]
    spread = Limits(r_bar, d3_factor * r_bar, d4_factor * r_bar, r_bar * range_constants(n)[1] / d2)
    return ControlChart("Xbar-R", n, _clipped(grand, 3 * sigma / np.sqrt(n), sigma / np.sqrt(n)), spread, sigma, k,
                        range_dof(int(whole.sum()), n))


_MR_VAR = 2.0 - 4.0 / math.pi  # Var|x_i - x_(i-1)| / sigma^2
# Cov(|x_2 - x_1|, |x_3 - x_2|) / sigma^2: two differences of correlation -1/2, E|U||V| = 2 (2/pi)(sqrt(1 - r^2)
# + r asin r) for variance-2 normals of correlation r, less E|U| E|V| = 4/pi
_MR_COV = 4.0 / math.pi * (math.sqrt(0.75) + math.pi / 12) - 4.0 / math.pi


def mr_dof(ranges: int, adjacent: int) -> float:
    """Effective degrees of freedom of sigma = MR-bar / d2(2) from `ranges` moving ranges of
    which `adjacent` pairs share a value (correlated): nu with Var(sigma-hat) = sigma^2 /
    (2 nu), as a sample SD of nu + 1 values has (Patnaik); about 0.6 (m - 1) for m values."""
    var_mr_bar = (ranges * _MR_VAR + 2 * adjacent * _MR_COV) / ranges ** 2  # / sigma^2
    return (4.0 / math.pi) / (2 * var_mr_bar)  # d2(2)^2 = 4 / pi


def range_dof(k: int, n: int) -> float:
    """Effective degrees of freedom of sigma = R-bar / d2(n) from `k` independent subgroups
    of `n`: k d2^2 / (2 d3^2) (about 0.9 k (n - 1))."""
    d2, d3 = range_constants(n)
    return k * d2 * d2 / (2 * d3 * d3)


def _runs(ok: np.ndarray, length: int) -> np.ndarray:
    """Per point, whether it ends `length` consecutive True values of `ok`."""
    out = np.zeros(len(ok), bool)
    if len(ok) >= length:
        out[length - 1:] = np.lib.stride_tricks.sliding_window_view(ok, length).all(axis=1)
    return out


def _count_in(ok: np.ndarray, length: int, need: int) -> np.ndarray:
    """Per point, whether at least `need` of the `length` points ending at it are True."""
    out = np.zeros(len(ok), bool)
    if len(ok) >= length:
        out[length - 1:] = np.lib.stride_tricks.sliding_window_view(ok, length).sum(axis=1) >= need
    return out


def nelson(points: Sequence[float] | np.ndarray, limits: Limits,
           rules: Sequence[int] = DEFAULT_RULES) -> list[set[int]]:
    """Per point, the chosen Nelson rules (module docstring) whose run ends at it."""
    unknown = sorted(set(rules) - set(NELSON_RULES))
    if unknown:
        raise ValueError(f"no Nelson rule {unknown}; the rules are 1..8")
    x = np.asarray(points, float)
    z = (x - limits.centre) / limits.sigma if limits.sigma > 0 else np.zeros(len(x))
    step = np.sign(np.diff(x))
    up, down = np.r_[False, step > 0], np.r_[False, step < 0]
    alternate = np.r_[False, False, step[1:] * step[:-1] < 0]  # the step into this point reverses the last
    hits = {
        1: (x > limits.ucl) | (x < limits.lcl),
        2: _runs(z > 0, 9) | _runs(z < 0, 9),
        3: _runs(up, 5) | _runs(down, 5),  # 6 points: 5 steps one way
        4: _runs(alternate, 12),
        5: ((z > 2) & _count_in(z > 2, 3, 2)) | ((z < -2) & _count_in(z < -2, 3, 2)),
        6: ((z > 1) & _count_in(z > 1, 5, 4)) | ((z < -1) & _count_in(z < -1, 5, 4)),
        7: _runs(np.abs(z) < 1, 15),
        8: _runs(np.abs(z) > 1, 8),
    }
    flags: list[set[int]] = [set() for _ in x]
    for rule in sorted(set(rules)):
        for i in np.flatnonzero(hits[rule]):
            flags[i].add(rule)
    return flags


def normal_fit(x: np.ndarray, censored: np.ndarray | None = None) -> tuple[float, float, float]:
    """(mean, sigma, log-likelihood) of a normal: the sample mean and SD (n - 1 divisor)
    without censored values, else the maximum-likelihood fit with each censored value x_i
    entering as P(X < x_i) (the log-likelihood is the MLE's in both cases)."""
    from scipy import stats

    x = np.asarray(x, float)
    cens = _censored(x, censored)
    if cens.any():
        mu, sd = stats.norm.fit(stats.CensoredData(uncensored=x[~cens], left=x[cens]))
        mu, sd = float(mu), float(sd)
    else:
        mu, sd = float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else 0.0
    mle_sd = sd if cens.any() else float(x.std())
    if not mle_sd > 0:
        return mu, sd, -math.inf
    ll = float(stats.norm.logpdf(x[~cens], mu, mle_sd).sum() + stats.norm.logcdf(x[cens], mu, mle_sd).sum())
    return mu, sd, ll


def weibull_fit(x: np.ndarray, censored: np.ndarray | None = None) -> tuple[float, float, float]:
    """(shape, scale, log-likelihood) of a two-parameter Weibull (location 0) by maximum
    likelihood, censored values through its CDF."""
    from scipy import stats

    x = np.maximum(np.asarray(x, float), 1e-12)  # a zero value sits on the bound: the density there is finite
    cens = _censored(x, censored)
    data = stats.CensoredData(uncensored=x[~cens], left=x[cens]) if cens.any() else x
    shape, _, scale = stats.weibull_min.fit(data, floc=0)
    ll = float(stats.weibull_min.logpdf(x[~cens], shape, 0, scale).sum()
               + stats.weibull_min.logcdf(x[cens], shape, 0, scale).sum())
    return float(shape), float(scale), ll


_WEIBULL_P = np.array([0.00135, 0.5, 0.99865])  # the percentiles of the ISO 22514-2 method


def weibull_indices(theta: np.ndarray, usl: float) -> np.ndarray:
    """(Pp, Ppk) of a Weibull with theta = (log shape, log scale) (module docstring)."""
    shape, scale = np.exp(theta)
    q = scale * (-np.log1p(-_WEIBULL_P)) ** (1 / shape)  # X0.135, X50, X99.865
    return np.array([usl / (q[2] - q[0]), (usl - q[1]) / (q[2] - q[1])])


def weibull_intervals(x: np.ndarray, censored: np.ndarray, shape: float, scale: float,
                      usl: float) -> list[tuple[float, float]]:
    """95 % intervals of the Weibull Pp and Ppk by the delta method: the covariance of
    (log shape, log scale) from the log-likelihood's curvature at the fit (central
    differences; censored values through the CDF), carried through `weibull_indices`."""
    from scipy import stats

    x = np.maximum(np.asarray(x, float), 1e-12)

    def ll(theta: np.ndarray) -> float:
        k, lam = np.exp(theta)
        return float(stats.weibull_min.logpdf(x[~censored], k, 0, lam).sum()
                     + stats.weibull_min.logcdf(x[censored], k, 0, lam).sum())

    theta, h = np.log([shape, scale]), 1e-4
    steps = np.eye(2) * h
    hess = np.array([[(ll(theta + a + b) - ll(theta + a - b) - ll(theta - a + b) + ll(theta - a - b)) / (4 * h * h)
                      for b in steps] for a in steps])
    cov = np.linalg.inv(-hess)
    grad = np.array([(weibull_indices(theta + a, usl) - weibull_indices(theta - a, usl)) / (2 * h) for a in steps]).T
    half = float(stats.norm.ppf(1 - (1 - CONFIDENCE) / 2)) * np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", grad, cov,
                                                                                       grad), 0.0))
    mid = weibull_indices(theta, usl)
    return [(float(m - w), float(m + w)) for m, w in zip(mid, half)]


def anderson_darling(x: np.ndarray) -> tuple[float, float]:
    """(A^2, p) of the Anderson-Darling normality test with mean and SD from the sample;
    p from the adjusted statistic by D'Agostino and Stephens' formulas (module docstring)."""
    from scipy import stats

    x = np.sort(np.asarray(x, float))
    n = len(x)
    cdf = stats.norm.cdf((x - x.mean()) / x.std(ddof=1))
    i = np.arange(1, n + 1)
    a2 = float(-n - np.mean((2 * i - 1) * (np.log(cdf) + np.log1p(-cdf[::-1]))))
    a = a2 * (1 + 0.75 / n + 2.25 / n ** 2)
    if a >= 0.6:
        p = math.exp(1.2937 - 5.709 * a + 0.0186 * a * a)
    elif a >= 0.34:
        p = math.exp(0.9177 - 4.279 * a - 1.38 * a * a)
    elif a >= 0.2:
        p = 1 - math.exp(-8.318 + 42.796 * a - 59.938 * a * a)
    else:
        p = 1 - math.exp(-13.436 + 101.14 * a - 223.73 * a * a)
    return a2, float(min(max(p, 0.0), 1.0))


@dataclass(frozen=True)
class Index:
    """A capability index and its 95 % interval (None: no interval for this method)."""

    value: float
    ci: tuple[float, float] | None = None

    def text(self) -> str:
        return f"{self.value:.2f}" + (f" [{self.ci[0]:.2f}, {self.ci[1]:.2f}]" if self.ci else "")


@dataclass(frozen=True)
class Capability:
    """Capability of a characteristic's values against its upper limit `usl` (mm) and the
    natural lower bound 0 (module docstring): `n` values of which `censored` below their
    detection limit; the normal model's mean and sigmas (mm) and Cp/Cpk (within), Pp/Ppk
    (overall); the Anderson-Darling test (None: not possible, `normality` says why); the
    Weibull model's Pp/Ppk (percentile method); `model` the one to read ("normal" or
    "Weibull") and `method` how it was chosen and how censored values were treated;
    `warning` when too few values for the indices to be acted on."""

    n: int
    censored: int
    usl: float
    mean: float
    sigma_within: float
    sigma_overall: float
    cp: Index
    cpk: Index
    pp: Index
    ppk: Index
    ad_statistic: float | None
    ad_p: float | None
    normality: str
    weibull_shape: float | None
    weibull_scale: float | None
    weibull_pp: Index | None
    weibull_ppk: Index | None
    model: str
    method: str
    warning: str = ""

    @property
    def read_ppk(self) -> Index:
        """The Ppk of the chosen model."""
        return self.weibull_ppk if self.model == "Weibull" and self.weibull_ppk is not None else self.ppk


def _chi2_ci(index: float, dof: float) -> tuple[float, float]:
    """The interval of an index c / sigma-hat, sigma-hat with `dof` degrees of freedom."""
    from scipy import stats

    alpha = 1 - CONFIDENCE
    lo, hi = stats.chi2.ppf([alpha / 2, 1 - alpha / 2], dof)
    return float(index * math.sqrt(lo / dof)), float(index * math.sqrt(hi / dof))


def _bissell_ci(index: float, n: int, dof: float) -> tuple[float, float]:
    """Bissell's interval of (USL - mean) / 3 sigma-hat: the mean of `n` values, sigma-hat
    with `dof` degrees of freedom."""
    from scipy import stats

    half = float(stats.norm.ppf(1 - (1 - CONFIDENCE) / 2)) * math.sqrt(1 / (9 * n) + index * index / (2 * dof))
    return index - half, index + half


def capability(values: Sequence[float], usl: float, sigma_within: float,
               censored: Sequence[bool] | None = None, within_dof: float = 0.0) -> Capability | None:
    """Capability of `values` (censored ones at their detection limit, marked by
    `censored`) with the chart's within sigma and its degrees of freedom (0: taken as
    n - 1); None without spread or with fewer than 2 measured values."""
    x = np.asarray(values, float)
    cens = _censored(x, censored)
    n = len(x)
    if n - int(cens.sum()) < 2 or not sigma_within > 0:
        return None
    mean, sd, normal_ll = normal_fit(x, cens)
    if not sd > 0:
        return None
    cp, cpk = usl / (6 * sigma_within), (usl - mean) / (3 * sigma_within)
    pp, ppk = usl / (6 * sd), (usl - mean) / (3 * sd)
    shape, scale, weibull_ll = weibull_fit(x, cens)
    w = weibull_indices(np.log([shape, scale]), usl)
    w_ci = weibull_intervals(x, cens, shape, scale, usl)
    w_pp, w_ppk = Index(float(w[0]), w_ci[0]), Index(float(w[1]), w_ci[1])
    if cens.any():
        a2 = p = None
        normality = f"not tested: {int(cens.sum())} of {n} values below their detection limit"
        model = "normal" if normal_ll >= weibull_ll else "Weibull"
        method = (f"censored values by maximum likelihood (normal and Weibull); {model}: the higher likelihood "
                  f"(log L normal {normal_ll:.1f}, Weibull {weibull_ll:.1f})")
    else:
        a2, p = anderson_darling(x)
        normality = f"Anderson-Darling A² {a2:.3f}, p {p:.3f}" + (" (not normal at 5 %)" if p < NORMALITY_ALPHA
                                                                   else "")
        model = "normal" if p >= NORMALITY_ALPHA else "Weibull"
        method = ("normal: the Anderson-Darling test does not reject it at 5 %" if model == "normal" else
                  "Weibull (location 0, ISO 22514-2 percentiles): the Anderson-Darling test rejects the normal at 5 %")
    warning = (f"only {n} values (< {MIN_CAPABILITY_N}): the indices are too uncertain to act on"
               if n < MIN_CAPABILITY_N else "")
    nu = within_dof or n - 1
    return Capability(n, int(cens.sum()), usl, mean, sigma_within, sd, Index(cp, _chi2_ci(cp, nu)),
                      Index(cpk, _bissell_ci(cpk, n, nu)), Index(pp, _chi2_ci(pp, n - 1)),
                      Index(ppk, _bissell_ci(ppk, n, n - 1)),
                      a2, p, normality, shape, scale, w_pp, w_ppk, model, method, warning)
