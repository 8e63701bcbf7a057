"""Statistical process control of a characteristic: Shewhart control charts with limits
from the data, the Western Electric run rules, and process capability.

Individuals and moving range (I-MR), one value per part (ISO 7870-2; AIAG SPC manual):

    moving ranges MR_i = |x_i - x_(i-1)|, MR-bar their mean; sigma-hat = MR-bar / d2(2)
    I chart   centre x-bar, limits x-bar +- 3 sigma-hat
    MR chart  centre MR-bar, UCL D4(2) MR-bar, LCL D3(2) MR-bar (= 0)

X-bar and R, for subgroups of n (2..10) consecutive parts (`[control] subgroup_size` in the
part program); an incomplete last subgroup is left out:

    sigma-hat = R-bar / d2(n); X-bar chart x-double-bar +- 3 sigma-hat / sqrt(n);
    R chart centre R-bar, limits D3(n) R-bar, D4(n) R-bar

d2(n) and d3(n) (mean and standard deviation of the range of n standard normal values)
are computed by numerical integration; D3 = max(0, 1 - 3 d3/d2), D4 = 1 + 3 d3/d2.

Western Electric rules, on the chart's points against zones of sigma-hat about the centre
(sigma of the plotted statistic): 1 one point beyond 3 sigma; 2 two of three consecutive
beyond 2 sigma on one side; 3 four of five beyond 1 sigma on one side; 4 eight in a row on
one side of the centre. A point is flagged with every rule whose run it ends.

Parts that failed (out of tolerance) or could not be measured are assignable causes: they
are shown on the charts but left out of the limits and of the capability (the baseline).

Capability (ISO 22514-2, -4): every characteristic of a part program has an upper limit,
its tolerance, and the natural lower bound 0 (a zone width or a height is never
negative). So Cpk = Cpu = (USL - mean) / (3 sigma-hat) and Cp = (USL - 0) / (6 sigma-hat),
with sigma-hat the within-subgroup sigma of the chart above. 95 % confidence intervals:
Cp from the chi-squared distribution with n - 1 degrees of freedom, Cpk by Bissell's normal
approximation, Cpk +- z sqrt(1 / (9 n) + Cpk^2 / (2 (n - 1))). Below MIN_CAPABILITY_N
values the indices carry a warning: their intervals are too wide to act on (at n = 30 and
Cpk 1.33 the interval is about +-0.36).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence

import numpy as np

MIN_CAPABILITY_N = 30  # values below which capability indices are flagged as unreliable
MIN_LIMIT_POINTS = 2  # chart points needed before limits can be computed
CONFIDENCE = 0.95
MAX_SUBGROUP = 10


@lru_cache(maxsize=None)
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
    """A chart's centre line and control limits (mm), and the sigma of its plotted
    statistic (mm)."""

    centre: float
    lcl: float
    ucl: float
    sigma: float


@dataclass(frozen=True)
class ControlChart:
    """Limits of a location chart (individuals or subgroup means) and of its spread chart
    (moving ranges or subgroup ranges), and the process sigma-hat (mm) they rest on."""

    kind: str  # "I-MR" or "Xbar-R"
    subgroup: int
    location: Limits
    spread: Limits
    sigma_within: float


def individuals_limits(x: Sequence[float]) -> ControlChart:
    """I-MR limits from values in time order (at least MIN_LIMIT_POINTS)."""
    x = np.asarray(x, float)
    if len(x) < MIN_LIMIT_POINTS:
        raise ValueError(f"I-MR limits need at least {MIN_LIMIT_POINTS} values, got {len(x)}")
    mr_bar = float(np.abs(np.diff(x)).mean())
    d2, d3_factor, d4_factor = chart_constants(2)
    sigma = mr_bar / d2
    mean = float(x.mean())
    mr_sigma = mr_bar * range_constants(2)[1] / d2
    return ControlChart("I-MR", 1, Limits(mean, mean - 3 * sigma, mean + 3 * sigma, sigma),
                        Limits(mr_bar, d3_factor * mr_bar, d4_factor * mr_bar, mr_sigma), sigma)


def subgroup_limits(groups: np.ndarray) -> ControlChart:
    """X-bar and R limits from subgroups (k, n) in time order."""
    groups = np.asarray(groups, float)
    k, n = groups.shape
    if k < MIN_LIMIT_POINTS:
        raise ValueError(f"X-bar R limits need at least {MIN_LIMIT_POINTS} subgroups, got {k}")
    r_bar = float(np.ptp(groups, axis=1).mean())
    d2, d3_factor, d4_factor = chart_constants(n)
    sigma = r_bar / d2
    grand = float(groups.mean())
    half = 3 * sigma / np.sqrt(n)
    return ControlChart("Xbar-R", n, Limits(grand, grand - half, grand + half, sigma / np.sqrt(n)),
                        Limits(r_bar, d3_factor * r_bar, d4_factor * r_bar, r_bar * range_constants(n)[1] / d2), sigma)


def western_electric(points: Sequence[float], limits: Limits) -> list[set[int]]:
    """Per point, the Western Electric rules (1-4) whose run ends at it (module docstring)."""
    z = (np.asarray(points, float) - limits.centre) / limits.sigma if limits.sigma > 0 else \
        np.zeros(len(points))
    flags: list[set[int]] = [set() for _ in z]
    for i in range(len(z)):
        if abs(z[i]) > 3:
            flags[i].add(1)
        for rule, run, need, beyond in ((2, 3, 2, 2.0), (3, 5, 4, 1.0)):
            window = z[max(0, i - run + 1):i + 1]
            if len(window) == run:
                for side in (1, -1):
                    if side * z[i] > beyond and np.count_nonzero(side * window > beyond) >= need:
                        flags[i].add(rule)
        window = z[max(0, i - 7):i + 1]
        if len(window) == 8 and (np.all(window > 0) or np.all(window < 0)):
            flags[i].add(4)
    return flags


@dataclass(frozen=True)
class Capability:
    """Cp and Cpk of values against an upper limit (mm) with the natural lower bound 0,
    their 95 % confidence intervals, the number of values, and a warning when too few."""

    n: int
    mean: float
    sigma: float
    cp: float
    cp_ci: tuple[float, float]
    cpk: float
    cpk_ci: tuple[float, float]
    warning: str


def capability(values: Sequence[float], usl: float, sigma_within: float) -> Capability | None:
    """Capability of `values` (the baseline) with the chart's sigma-hat; None without spread."""
    from scipy import stats  # scipy.stats takes ~0.6 s to import: only when charts are computed
    x = np.asarray(values, float)
    n = len(x)
    if n < 2 or not sigma_within > 0:
        return None
    mean = float(x.mean())
    cp = usl / (6 * sigma_within)
    cpk = (usl - mean) / (3 * sigma_within)
    alpha = 1 - CONFIDENCE
    dof = n - 1
    cp_ci = (cp * np.sqrt(stats.chi2.ppf(alpha / 2, dof) / dof), cp * np.sqrt(stats.chi2.ppf(1 - alpha / 2, dof) / dof))
    half = stats.norm.ppf(1 - alpha / 2) * np.sqrt(1 / (9 * n) + cpk * cpk / (2 * dof))
    warning = (f"only {n} values (< {MIN_CAPABILITY_N}): the indices are too uncertain to act on"
               if n < MIN_CAPABILITY_N else "")
    return Capability(n, mean, sigma_within, float(cp), (float(cp_ci[0]), float(cp_ci[1])), float(cpk),
                      (float(cpk - half), float(cpk + half)), warning)
