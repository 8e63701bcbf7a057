"""Control charts and capability (slscan/station/spc.py, quality.characteristic_stats):
limits, rules and indices against values computed here independently — published constants
(ASTM E2587 / AIAG tables), formulas written out in the test, and sequences built to break
each Western Electric rule."""

from __future__ import annotations

import datetime as dt

import numpy as np
import pytest
from scipy import stats

from slscan.station.program import Characteristic
from slscan.station.quality import ChartPoint, characteristic_stats
from slscan.station.spc import (
    MIN_CAPABILITY_N,
    Limits,
    capability,
    chart_constants,
    individuals_limits,
    range_constants,
    subgroup_limits,
    western_electric,
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
    mrs = [abs(b - a) for a, b in zip(x, x[1:])]
    mr_bar = sum(mrs) / len(mrs)
    mean = sum(x) / len(x)
    chart = individuals_limits(x)
    assert chart.kind == "I-MR" and chart.location.centre == pytest.approx(mean)
    assert chart.location.ucl == pytest.approx(mean + 2.660 * mr_bar, rel=1e-3)  # 3 / d2(2) = 2.660
    assert chart.location.lcl == pytest.approx(mean - 2.660 * mr_bar, rel=1e-3)
    assert chart.spread.centre == pytest.approx(mr_bar) and chart.spread.ucl == pytest.approx(3.267 * mr_bar, rel=1e-3)
    assert chart.spread.lcl == 0 and chart.sigma_within == pytest.approx(mr_bar / 1.128, rel=1e-3)


def test_subgroup_limits_by_hand() -> None:
    groups = np.array([[1.0, 1.2, 0.9, 1.1, 1.0], [1.3, 1.1, 1.0, 1.2, 1.1], [0.8, 1.0, 1.1, 0.9, 1.0],
                       [1.1, 1.0, 1.2, 1.3, 1.0]])
    r_bar = np.mean([g.max() - g.min() for g in groups])
    grand = groups.mean()
    chart = subgroup_limits(groups)
    assert chart.location.ucl == pytest.approx(grand + 0.577 * r_bar, rel=1e-3)
    assert chart.location.lcl == pytest.approx(grand - 0.577 * r_bar, rel=1e-3)
    assert chart.spread.ucl == pytest.approx(2.114 * r_bar, rel=1e-3) and chart.spread.lcl == 0


ZONES = Limits(centre=0.0, lcl=-3.0, ucl=3.0, sigma=1.0)


@pytest.mark.parametrize("points, rule, at", [
    ([0.1, -0.2, 3.5, 0.0], 1, 2),                       # one beyond 3 sigma
    ([0.0, 2.5, 0.3, 2.2], 2, 3),                        # 2 of 3 beyond 2 sigma, same side
    ([0.0, 1.5, 1.2, 0.5, 1.1, 1.4], 3, 5),              # 4 of 5 beyond 1 sigma, same side
    ([-0.5] + [0.2] * 8, 4, 8),                          # 8 in a row on one side
    ([0.0, -2.5, 0.1, -2.1], 2, 3),                      # below the centre as well
])
def test_each_western_electric_rule_flags_the_point_that_ends_its_run(points: list[float], rule: int, at: int) -> None:
    flags = western_electric(points, ZONES)
    assert rule in flags[at]
    assert all(rule not in f for k, f in enumerate(flags) if k != at)


def test_no_rule_fires_on_points_alternating_about_the_centre() -> None:
    assert all(not f for f in western_electric([0.5, -0.5] * 10, ZONES))
    assert all(not f for f in western_electric([0.0, 2.5, -2.5, 0.0, -0.5, 2.5], ZONES))  # beyond 2 sigma, opposite sides


def test_capability_and_intervals_by_hand() -> None:
    rng = np.random.default_rng(4)
    x = rng.normal(0.02, 0.004, 40)
    sigma = 0.0041
    cap = capability(x, 0.05, sigma)
    cpk = (0.05 - x.mean()) / (3 * sigma)
    cp = 0.05 / (6 * sigma)
    assert cap.cpk == pytest.approx(cpk) and cap.cp == pytest.approx(cp) and cap.warning == ""
    half = 1.959964 * np.sqrt(1 / (9 * 40) + cpk ** 2 / (2 * 39))  # Bissell
    assert cap.cpk_ci == pytest.approx((cpk - half, cpk + half), rel=1e-5)
    lo, hi = stats.chi2.ppf([0.025, 0.975], 39)
    assert cap.cp_ci == pytest.approx((cp * np.sqrt(lo / 39), cp * np.sqrt(hi / 39)))
    small = capability(x[:MIN_CAPABILITY_N - 1], 0.05, sigma)
    assert "only 29 values" in small.warning
    assert small.cpk_ci[1] - small.cpk_ci[0] > cap.cpk_ci[1] - cap.cpk_ci[0]


T0 = dt.datetime(2026, 11, 23, tzinfo=dt.timezone.utc)


def test_failed_and_unmeasured_parts_are_shown_but_left_out_of_limits_and_capability() -> None:
    c = Characteristic("flat", "#1", "flatness", 0.05, "minimum_zone")
    good = [0.020, 0.024, 0.018, 0.022, 0.026, 0.021]
    points = [ChartPoint(k, f"S{k}", T0, v, "pass") for k, v in enumerate(good)]
    points.insert(3, ChartPoint(90, "BAD", T0, 0.150, "fail"))
    points.insert(5, ChartPoint(91, "ERR", T0, None, "error"))
    s = characteristic_stats(c, points)
    expected = individuals_limits(good)  # from the passed parts alone
    assert s.chart == expected
    assert s.n == 7 and s.excluded == 1 and s.not_measured == 1
    assert [v for v, b in zip(s.location, s.baseline) if not b] == [0.150]
    assert 1 in s.location_flags[3]  # the failed part is far beyond the limits: flagged, shown
    assert s.capability.n == 6 and s.capability.mean == pytest.approx(np.mean(good))
    assert s.capability.cpk == pytest.approx((0.05 - np.mean(good)) / (3 * expected.sigma_within))


def test_subgroups_give_xbar_r_limits() -> None:
    c = Characteristic("sq", "#1", "sq", 0.03)
    values = [1.0, 1.2, 0.9, 1.1, 1.3, 1.1, 1.0, 1.2, 0.8, 1.0, 1.1, 0.9, 1.05]  # 4 subgroups of 3, one left over
    points = [ChartPoint(k, f"S{k}", T0, v, "pass") for k, v in enumerate(values)]
    s = characteristic_stats(c, points, subgroup=3)
    groups = np.array(values[:12]).reshape(4, 3)
    assert s.chart == subgroup_limits(groups) and s.chart.kind == "Xbar-R"
    assert s.location == pytest.approx(groups.mean(axis=1).tolist())
    assert s.spread == pytest.approx((groups.max(axis=1) - groups.min(axis=1)).tolist())
