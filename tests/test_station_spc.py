"""Control charts and capability (slscan/station/spc.py, quality.characteristic_stats):
limits, rules and indices against values computed here independently — published constants
(ASTM E2587 / AIAG tables), a worked example from the NIST/SEMATECH e-Handbook, formulas
written out in the test, series built to trigger each Nelson rule, and scipy's own
Anderson-Darling and maximum-likelihood fits."""

from __future__ import annotations

import datetime as dt
import math
from itertools import pairwise

import numpy as np
import pytest
from scipy import optimize, stats

from slscan.station.program import Characteristic
from slscan.station.quality import ChartPoint, characteristic_stats
from slscan.station.spc import (
    DEFAULT_RULES,
    MIN_CAPABILITY_N,
    MIN_INDIVIDUALS,
    MIN_SUBGROUPS,
    Limits,
    anderson_darling,
    capability,
    chart_constants,
    individuals_limits,
    mr_dof,
    nelson,
    normal_fit,
    range_constants,
    range_dof,
    subgroup_limits,
)

# published control chart constants (ASTM E2587 table): n -> (d2, d3, D3, D4, A2)
TABLE = {2: (1.128, 0.853, 0.0, 3.267, 1.880), 3: (1.693, 0.888, 0.0, 2.574, 1.023),
         4: (2.059, 0.880, 0.0, 2.282, 0.729), 5: (2.326, 0.864, 0.0, 2.114, 0.577),
         7: (2.704, 0.833, 0.076, 1.924, 0.419), 10: (3.078, 0.797, 0.223, 1.777, 0.308)}


@pytest.mark.parametrize("n", sorted(TABLE))
def test_range_constants_match_the_published_table(n: int) -> None:
    d2, d3, D3, D4, A2 = TABLE[n]
    got_d2, got_d3 = range_constants(n)
    assert got_d2 == pytest.approx(d2, abs=6e-4) and got_d3 == pytest.approx(d3, abs=6e-4)
    _, got_D3, got_D4 = chart_constants(n)
    assert got_D3 == pytest.approx(D3, abs=2e-3) and got_D4 == pytest.approx(D4, abs=2e-3)
    assert 3 / (got_d2 * np.sqrt(n)) == pytest.approx(A2, abs=2e-3)


def test_individuals_limits_by_hand() -> None:
    x = [0.021, 0.025, 0.019, 0.030, 0.024, 0.022, 0.027]
    mrs = [abs(b - a) for a, b in pairwise(x)]
    mr_bar = sum(mrs) / len(mrs)
    mean = sum(x) / len(x)
    chart = individuals_limits(x)
    assert chart.kind == "I-MR" and chart.location.centre == pytest.approx(mean)
    assert chart.location.ucl == pytest.approx(mean + 2.660 * mr_bar, rel=1e-3)  # 3 / d2(2) = 2.660
    assert chart.location.lcl == pytest.approx(mean - 2.660 * mr_bar, rel=1e-3)
    assert not chart.location.lcl_clipped
    assert chart.spread.centre == pytest.approx(mr_bar) and chart.spread.ucl == pytest.approx(3.267 * mr_bar, rel=1e-3)
    assert chart.spread.lcl == 0 and chart.sigma_within == pytest.approx(mr_bar / 1.128, rel=1e-3)


def test_nist_handbook_individuals_chart_example() -> None:
    """NIST/SEMATECH e-Handbook of Statistical Methods, section 6.3.2.2 "Individuals Control
    Charts": flow rate of the first 10 batches of a new process; the handbook gives x-bar
    50.81, MR-bar 1.8778, I chart limits 45.82 and 55.80, MR chart UCL 6.13."""
    flow = [49.6, 47.6, 49.9, 51.3, 47.8, 51.2, 52.6, 52.4, 53.6, 52.1]
    chart = individuals_limits(flow)
    assert chart.location.centre == pytest.approx(50.81, abs=0.005)
    assert chart.spread.centre == pytest.approx(1.8778, abs=5e-5)
    assert chart.location.lcl == pytest.approx(45.82, abs=0.005)
    assert chart.location.ucl == pytest.approx(55.80, abs=0.005)
    assert chart.spread.ucl == pytest.approx(6.13, abs=0.005)


def test_a_negative_lcl_is_raised_to_the_natural_bound() -> None:
    """A zone width cannot be negative: an LCL below 0 is 0 (and says so)."""
    x = [0.004, 0.012, 0.002, 0.015, 0.003, 0.011, 0.006]
    chart = individuals_limits(x)
    raw = np.mean(x) - 3 * np.mean(np.abs(np.diff(x))) / 1.128
    assert raw < 0 and chart.location.lcl == 0.0 and chart.location.lcl_clipped


def test_subgroup_limits_by_hand() -> None:
    groups = np.array([[1.0, 1.2, 0.9, 1.1, 1.0], [1.3, 1.1, 1.0, 1.2, 1.1], [0.8, 1.0, 1.1, 0.9, 1.0],
                       [1.1, 1.0, 1.2, 1.3, 1.0]])
    r_bar = np.mean([g.max() - g.min() for g in groups])
    grand = groups.mean()
    chart = subgroup_limits(groups)
    assert chart.location.ucl == pytest.approx(grand + 0.577 * r_bar, rel=1e-3)
    assert chart.location.lcl == pytest.approx(grand - 0.577 * r_bar, rel=1e-3)
    assert chart.spread.ucl == pytest.approx(2.114 * r_bar, rel=1e-3) and chart.spread.lcl == 0


# ------------------------------------------------------------------ Nelson's rules

ZONES = Limits(centre=0.0, lcl=-3.0, ucl=3.0, sigma=1.0)
QUIET = [0.3, -0.4, 0.5, -0.2]  # no rule's run can end in these


@pytest.mark.parametrize("rule, points", [
    (1, QUIET + [3.5]),                                            # beyond a control limit
    (1, QUIET + [-3.2]),
    (2, QUIET + [0.2] * 9),                                        # nine on one side
    (2, [-q for q in QUIET] + [-0.3] * 9),
    (3, QUIET + [-0.9, -0.5, -0.1, 0.2, 0.6, 0.9]),               # six increasing
    (3, QUIET + [0.9, 0.6, 0.2, -0.1, -0.5, -0.9]),               # six decreasing
    (4, [0.0, 0.1, 0.2] + [0.5 * (-1) ** k for k in range(13)]),   # fourteen alternating, from 0.2
    (5, QUIET + [2.5, 0.3, 2.2]),                                  # two of three beyond 2 sigma
    (5, QUIET + [-2.5, 0.1, -2.1]),
    (6, QUIET + [1.5, 1.2, 0.5, 1.1, 1.4]),                        # four of five beyond 1 sigma
    (7, [2.0, 1.5] + [0.5 * (-1) ** (k // 2) for k in range(15)]),  # fifteen within 1 sigma
    (8, QUIET + [1.5, -1.4, 1.6, -1.2, 1.3, -1.8, 1.1, -1.5]),    # eight beyond 1 sigma, either side
])
def test_each_nelson_rule_flags_the_point_that_ends_its_run(rule: int, points: list[float]) -> None:
    """Each series is built to complete the rule's pattern at its last point, and nowhere
    before: that point alone carries the rule."""
    flags = nelson(points, ZONES, rules=range(1, 9))
    assert rule in flags[-1], flags
    assert all(rule not in f for f in flags[:-1]), flags
    shorter = nelson(points[:-1], ZONES, rules=range(1, 9))
    assert all(rule not in f for f in shorter)  # one point less: the pattern is not complete


def test_only_the_chosen_rules_flag() -> None:
    alternating = [0.5, -0.5] * 10  # rules 4 (14 alternating) and 7 (15 within 1 sigma)
    assert all(not f for f in nelson(alternating, ZONES))  # the default set has neither
    assert DEFAULT_RULES == (1, 2, 5, 6)
    assert {r for f in nelson(alternating, ZONES, rules=range(1, 9)) for r in f} == {4, 7}
    assert {r for f in nelson(alternating, ZONES, rules=(4,)) for r in f} == {4}
    with pytest.raises(ValueError, match="no Nelson rule"):
        nelson(alternating, ZONES, rules=(9,))


def test_false_alarm_rates_are_those_stated() -> None:
    """On in-control normal values (fresh draws, seed printed) each rule flags about the
    share the module docstring states; binomial 5-sigma bands for 2 x 10^5 points."""
    seed = int(np.random.SeedSequence().entropy % 2 ** 32)
    print(f"seed {seed}")
    x = np.random.default_rng(seed).standard_normal(200_000)
    flags = nelson(x, ZONES, rules=range(1, 9))
    stated = {1: 0.0027, 2: 0.0039, 3: 0.0028, 4: 0.0046, 5: 0.0020, 6: 0.0046, 7: 0.0034, 8: 0.0001}
    for rule, p in stated.items():
        got = sum(rule in f for f in flags) / len(x)
        assert abs(got - p) < 5 * math.sqrt(p / len(x)) + 2e-4, (rule, got, p)


# ------------------------------------------------------------------ capability

def test_capability_and_intervals_by_hand() -> None:
    rng = np.random.default_rng(4)
    x = rng.normal(0.02, 0.004, 40)
    sigma = 0.0041
    cap = capability(x, 0.05, sigma)
    cpk = (0.05 - x.mean()) / (3 * sigma)
    cp = 0.05 / (6 * sigma)
    s = np.sqrt(np.sum((x - x.mean()) ** 2) / 39)
    assert cap.cpk.value == pytest.approx(cpk) and cap.cp.value == pytest.approx(cp) and cap.warning == ""
    assert cap.pp.value == pytest.approx(0.05 / (6 * s)) and cap.ppk.value == pytest.approx((0.05 - x.mean()) / (3 * s))
    half = 1.959964 * np.sqrt(1 / (9 * 40) + cpk ** 2 / (2 * 39))  # Bissell
    assert cap.cpk.ci == pytest.approx((cpk - half, cpk + half), rel=1e-5)
    lo, hi = stats.chi2.ppf([0.025, 0.975], 39)
    assert cap.cp.ci == pytest.approx((cp * np.sqrt(lo / 39), cp * np.sqrt(hi / 39)))
    small = capability(x[:MIN_CAPABILITY_N - 1], 0.05, sigma)
    assert "only 29 values" in small.warning
    assert small.cpk.ci[1] - small.cpk.ci[0] > cap.cpk.ci[1] - cap.cpk.ci[0]


def test_within_sigma_degrees_of_freedom_match_simulation() -> None:
    """The effective degrees of freedom of MR-bar / d2 and R-bar / d2 give the variance of
    sigma-hat that simulated normal series have (fresh draws, seed printed): Var = 1 / (2 nu)."""
    seed = int(np.random.SeedSequence().entropy % 2 ** 32)
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    m = 40
    s = np.abs(np.diff(rng.standard_normal((20_000, m)), axis=1)).mean(axis=1) / 1.128379
    assert s.var() == pytest.approx(1 / (2 * mr_dof(m - 1, m - 2)), rel=0.05)
    assert 0.55 * (m - 1) < mr_dof(m - 1, m - 2) < 0.65 * (m - 1)  # the textbook "about 0.6 (m - 1)"
    g = np.ptp(rng.standard_normal((20_000, 25, 5)), axis=2).mean(axis=1) / 2.325929
    assert g.var() == pytest.approx(1 / (2 * range_dof(25, 5)), rel=0.05)


@pytest.mark.slow
def test_interval_coverage_on_fresh_draws() -> None:
    """Measured coverage of the 95 % intervals of Cp, Cpk (I-MR within sigma) and Pp, Ppk
    over 2000 in-control normal series of 40 values (seed printed): each within 2.5 % of 95 %."""
    seed = int(np.random.SeedSequence().entropy % 2 ** 32)
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    mu, sigma, usl, n = 0.02, 0.004, 0.05, 40
    true = {"cp": usl / (6 * sigma), "cpk": (usl - mu) / (3 * sigma)}
    true.update(pp=true["cp"], ppk=true["cpk"])  # one sigma: within and overall are the same
    hits = {"cp": 0, "cpk": 0, "pp": 0, "ppk": 0}
    draws = 2000
    for _ in range(draws):
        x = rng.normal(mu, sigma, n)
        chart = individuals_limits(x)
        cap = capability(x, usl, chart.sigma_within, within_dof=chart.dof)
        for name, index in (("cp", cap.cp), ("cpk", cap.cpk), ("pp", cap.pp), ("ppk", cap.ppk)):
            hits[name] += index.ci[0] <= true[name] <= index.ci[1]
    coverage = {k: v / draws for k, v in hits.items()}
    print(coverage)
    assert all(abs(c - 0.95) < 0.025 for c in coverage.values()), coverage


@pytest.mark.slow
def test_weibull_interval_coverage_on_fresh_draws() -> None:
    """Measured coverage of the Weibull Pp and Ppk intervals (delta method) over 600
    Weibull samples of 40 values per shape (seed printed): 91-98 % (measured 93-95 %)."""
    from slscan.station.spc import weibull_fit, weibull_indices, weibull_intervals

    seed = int(np.random.SeedSequence().entropy % 2 ** 32)
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    for shape in (1.3, 2.5):
        true = weibull_indices(np.log([shape, 0.01]), 0.05)
        hits = np.zeros(2)
        for _ in range(600):
            x = 0.01 * rng.weibull(shape, 40)
            k, lam, _ = weibull_fit(x)
            hits += [lo <= t <= hi for (lo, hi), t in zip(weibull_intervals(x, np.zeros(40, bool), k, lam, 0.05), true)]
        print(shape, hits / 600)
        assert all(0.91 <= h / 600 <= 0.98 for h in hits), (shape, hits / 600)


T0 = dt.datetime(2026, 11, 23, tzinfo=dt.UTC)
FLAT = Characteristic("flat", "#1", "flatness", 0.05, "minimum_zone")


def _points(values: list[float | None], status: list[str] | None = None, limit: float | None = None,
            excluded: dict[int, str] | None = None) -> list[ChartPoint]:
    """Chart points with result ids 1.. ; None with `limit`: below the detection limit."""
    status = status or ["pass"] * len(values)
    return [ChartPoint(k + 1, f"S{k + 1}", T0, v, st, "", limit if v is None else None, (excluded or {}).get(k + 1, ""))
            for k, (v, st) in enumerate(zip(values, status))]


def test_every_measured_value_counts_whatever_the_parts_verdict() -> None:
    """The issue's case: 40 values, 10 % of them above the tolerance. Minitab and Q-DAS
    compute from all 40 (the parts that failed included); so does the station. Limits, Cp,
    Cpk, Pp, Ppk computed here with the published d2(2) = 1.128 and the sample SD."""
    rng = np.random.default_rng(11)
    x = rng.normal(0.030, 0.006, 40)
    x[::10] = 0.058  # every tenth part out of tolerance (0.05)
    status = ["fail" if v > 0.05 else "pass" for v in x]
    s = characteristic_stats(FLAT, _points(list(x), status))
    mr_bar = np.mean(np.abs(np.diff(x)))
    sigma_w, sd, mean = mr_bar / 1.128, np.std(x, ddof=1), np.mean(x)
    assert s.chart.location.centre == pytest.approx(mean) and s.chart.sigma_within == pytest.approx(sigma_w, rel=4e-4)
    assert s.chart.location.ucl == pytest.approx(mean + 3 * sigma_w, rel=4e-4)
    cap = s.capability
    assert cap.n == 40 and s.excluded == 0 and all(s.in_limits)
    assert cap.cp.value == pytest.approx(0.05 / (6 * sigma_w), rel=4e-4)
    assert cap.cpk.value == pytest.approx((0.05 - mean) / (3 * sigma_w), rel=4e-4)
    assert cap.pp.value == pytest.approx(0.05 / (6 * sd)) and cap.ppk.value == pytest.approx((0.05 - mean) / (3 * sd))
    good = x[x <= 0.05]  # what dropping the failed parts would give: a better-looking, wrong Ppk
    assert (0.05 - good.mean()) / (3 * good.std(ddof=1)) > cap.ppk.value + 0.2


def test_only_the_user_leaves_values_out() -> None:
    x = list(np.random.default_rng(12).normal(0.02, 0.003, 30))
    s = characteristic_stats(FLAT, _points(x, excluded={4: "fixture loose"}))
    kept = x[:3] + x[4:]
    assert s.excluded == 1 and s.in_limits[3] is False and sum(s.in_limits) == 29
    assert s.chart == individuals_limits(kept) and s.capability.n == 29
    assert s.capability.ppk.value == pytest.approx((0.05 - np.mean(kept)) / (3 * np.std(kept, ddof=1)))


def test_no_limits_below_the_minimum_sample() -> None:
    x = list(np.random.default_rng(13).normal(0.02, 0.003, MIN_INDIVIDUALS))
    few = characteristic_stats(FLAT, _points(x[:-1]))
    assert few.chart is None and few.capability is None and all(not f for f in few.location_flags)
    assert few.limits_note == f"no limits: {MIN_INDIVIDUALS - 1} values, limits need {MIN_INDIVIDUALS} (AIAG minimum)"
    assert characteristic_stats(FLAT, _points(x)).chart is not None
    groups = list(np.random.default_rng(14).normal(0.02, 0.003, 3 * MIN_SUBGROUPS))
    assert characteristic_stats(FLAT, _points(groups[:-3]), subgroup=3).chart is None
    assert characteristic_stats(FLAT, _points(groups), subgroup=3).chart.kind == "Xbar-R"


def test_limits_from_a_baseline_only() -> None:
    rng = np.random.default_rng(15)
    x = list(rng.normal(0.02, 0.002, 30)) + list(rng.normal(0.03, 0.002, 10))  # a shift after part 30
    s = characteristic_stats(FLAT, _points(x), baseline=set(range(1, 31)))
    assert s.chart == individuals_limits(x[:30]) and s.limits_note == "limits from 30 values of the baseline"
    assert sum(bool(f) for f in s.location_flags[30:]) >= 8  # the shift is flagged against the baseline's limits
    assert s.capability.n == 40  # capability over every value


def test_frozen_limits_are_used_as_given() -> None:
    x = list(np.random.default_rng(16).normal(0.02, 0.002, 10))
    frozen = individuals_limits(list(np.random.default_rng(17).normal(0.018, 0.002, 30)))
    s = characteristic_stats(FLAT, _points(x), frozen=frozen, frozen_source="limits.json")
    assert s.chart is frozen and s.limits_note == "limits frozen (limits.json)" and s.capability is not None


# ------------------------------------------------------------------ censored values

def test_values_below_the_detection_limit_are_kept_as_censored() -> None:
    """A capable process: most flatness values below the 9 um detection limit. They are
    charted at the limit, and the mean and overall sigma are the censored-normal maximum
    likelihood estimates, computed here by minimising the likelihood written out."""
    rng = np.random.default_rng(18)
    true = np.abs(rng.normal(0.010, 0.003, 40))
    limit = 0.009
    values = [None if t < limit else float(t) for t in true]
    s = characteristic_stats(FLAT, _points(values, limit=limit))
    cens = np.array([v is None for v in values])
    assert s.n == 40 and s.below_limit == cens.sum() > 5 and s.not_measured == 0
    assert [v for v, c in zip(s.location, s.censored) if c] == [limit] * int(cens.sum())
    x = np.where(cens, limit, true)

    def nll(p: np.ndarray) -> float:
        mu, log_sd = p
        sd = np.exp(log_sd)
        return -(stats.norm.logpdf(x[~cens], mu, sd).sum() + stats.norm.logcdf(limit, mu, sd) * cens.sum())

    mu, log_sd = optimize.minimize(nll, [x.mean(), np.log(x.std())], method="Nelder-Mead",
                                   options={"xatol": 1e-9, "fatol": 1e-12}).x
    cap = s.capability
    assert cap.mean == pytest.approx(mu, abs=2e-6) and cap.sigma_overall == pytest.approx(np.exp(log_sd), rel=2e-3)
    assert cap.censored == cens.sum() and "not tested" in cap.normality and "maximum likelihood" in cap.method
    # within sigma: only the moving ranges of two measured values are known
    known = ~cens[1:] & ~cens[:-1]
    assert s.chart.sigma_within == pytest.approx(np.abs(np.diff(x))[known].mean() / 1.128, rel=4e-4)


def test_every_value_below_the_limit_is_charted_and_said() -> None:
    """The issue's capable process: every value below the 9 um limit. Charted at the limit,
    counted, and no limits: there is no spread to estimate, said so."""
    s = characteristic_stats(FLAT, _points([None] * 30, limit=0.009))
    assert s.n == 30 and s.below_limit == 30 and list(s.location) == [0.009] * 30 and all(s.censored)
    assert s.chart is None and s.capability is None
    assert s.limits_note.startswith("no limits: all 30 values below their detection limit (<= 0.0090 mm)")
    empty = characteristic_stats(FLAT, [ChartPoint(1, "S1", T0, None, "error")])  # nothing measured: nothing to chart
    assert empty.n == 0 and empty.not_measured == 1 and empty.chart is None
    assert empty.limits_note == "no limits: 0 values, limits need 25 (AIAG minimum)"


def test_normal_fit_without_censoring_is_the_sample_mean_and_sd() -> None:
    x = np.random.default_rng(19).normal(5, 2, 50)
    mu, sd, _ = normal_fit(x)
    assert mu == pytest.approx(x.mean()) and sd == pytest.approx(x.std(ddof=1))


# ------------------------------------------------------------------ normality and the non-normal model

def test_anderson_darling_against_scipy() -> None:
    """The statistic is scipy's; the p-value (D'Agostino-Stephens formulas) agrees with a
    Monte Carlo p-value from scipy within its sampling error."""
    seed = int(np.random.SeedSequence().entropy % 2 ** 32)
    print(f"seed {seed}")
    rng = np.random.default_rng(seed)
    for x in (rng.normal(0, 1, 40), rng.weibull(1.3, 60), rng.lognormal(0, 0.4, 30)):
        a2, p = anderson_darling(x)
        ref = stats.anderson(x, method=stats.MonteCarloMethod(n_resamples=4000, rng=rng))
        assert a2 == pytest.approx(ref.statistic, rel=1e-9)
        assert abs(p - ref.pvalue) < 0.03 + 0.1 * ref.pvalue, (p, ref.pvalue)


def test_a_skewed_figure_is_read_from_the_weibull_model() -> None:
    """Flatness near its bound 0 is skewed: on Weibull values (shape 1.3) the normal is
    rejected and the Weibull Ppk by the ISO 22514-2 percentiles, computed here from scipy's
    own fit, is the one read."""
    x = 0.01 * np.random.default_rng(21).weibull(1.3, 120)
    cap = capability(x, 0.05, np.mean(np.abs(np.diff(x))) / 1.128)
    assert cap.ad_p < 0.05 and cap.model == "Weibull"
    shape, _, scale = stats.weibull_min.fit(x, floc=0)
    q = stats.weibull_min.ppf([0.00135, 0.5, 0.99865], shape, 0, scale)
    assert cap.weibull_ppk.value == pytest.approx((0.05 - q[1]) / (q[2] - q[1]), rel=1e-3)
    assert cap.weibull_pp.value == pytest.approx(0.05 / (q[2] - q[0]), rel=1e-3)
    assert cap.read_ppk is cap.weibull_ppk
    for index in (cap.weibull_pp, cap.weibull_ppk):  # an interval about the estimate, narrower with more values
        assert index.ci[0] < index.value < index.ci[1]
    more = capability(0.01 * np.random.default_rng(23).weibull(1.3, 480), 0.05, 0.005)
    assert more.weibull_ppk.ci[1] - more.weibull_ppk.ci[0] < 0.7 * (cap.weibull_ppk.ci[1] - cap.weibull_ppk.ci[0])
    normal = capability(np.random.default_rng(22).normal(0.02, 0.003, 60), 0.05, 0.003)
    assert normal.model == "normal" and normal.read_ppk is normal.ppk
