"""The variance laws a pose covariance takes poorly measured variances by
(`inspection.registration.variance_law`), against closed forms and frequentist coverage."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2, f, norm, t

from inspection.registration.variance_law import VarianceLaw, equivalent, law, predictive, sandwich_dof


def test_law_of_faces_without_noise_is_their_sum_over_chi_square() -> None:
    """K faces whose means carry all of their offset and no noise: their sum of squares Q is
    tau^2 chi-square(K), so tau^2's confidence distribution is Q / chi-square(K): its quantile
    p is Q / chi2.isf(p, K)."""
    rng = np.random.default_rng(14)
    squares = rng.uniform(0, 1e-6, 6)
    q = float(squares.sum())
    fitted = law(squares, np.ones(6), np.zeros(6), cap=1e3)
    for p in (0.1, 0.5, 0.9):
        assert fitted.quantile(np.array(p)) == pytest.approx(q / chi2.isf(p, 6), rel=2e-3)


def test_law_with_noise_above_the_spread_has_an_atom_at_zero() -> None:
    """Faces whose means spread less than their noise says: tau^2 = 0 is the likeliest (an atom
    there, P(Q <= q | tau = 0)), the law's upper quantiles still above 0 and at most the cap."""
    squares = np.full(6, 1e-6)
    fitted = law(squares, np.ones(6), np.full(6, 2e-6), cap=1e-4)
    assert fitted.below[0] == pytest.approx(chi2.sf(6e-6 / 2e-6, 6), rel=1e-6)  # P(Q > q | tau^2 = 0)
    assert fitted.quantile(np.array(0.5 * fitted.below[0])) == 0.0
    assert 0.0 < fitted.quantile(np.array(0.99)) <= 1e-4


@pytest.mark.parametrize("dof", [1.5, 3.0, 10.0, 40.0])
def test_equivalent_of_an_estimated_variance_is_students_t(dof: float) -> None:
    """A variance estimated on nu degrees of freedom: the normal interval as wide as the
    mixture's is Student's, the variance (t_nu / z)^2 times the estimate."""
    want = (t.isf(0.025, dof) / norm.isf(0.025)) ** 2
    assert equivalent(VarianceLaw.scaled(dof), level=0.95) == pytest.approx(want, rel=2e-3)


def test_predictive_region_covers_as_often_as_stated() -> None:
    """A 3-D error normal of covariance sigma^2 B, sigma^2 estimated anew each trial on 4
    degrees of freedom (s^2 = sigma^2 chi-square(4) / 4): the region `predictive` gives from
    s^2 and its law holds the error in 95 % of 3000 trials (binomial sd 0.4 %), where the
    estimate taken as known holds it far less often; its size is the exact F region's
    (Hotelling: d^2 / 3 ~ F(3, 4))."""
    rng = np.random.default_rng(21)
    B = np.diag([4.0, 1.0, 0.25])
    basis = np.eye(3)
    laws = (VarianceLaw.scaled(4.0),)
    factor = predictive((B,), laws, basis=basis, level=0.95)[0]  # the region per unit estimate
    assert factor * chi2.ppf(0.95, 3) == pytest.approx(3.0 * f.ppf(0.95, 3, 4), rel=0.03)
    inside, plugged = [], []
    for _ in range(3000):
        x = rng.multivariate_normal(np.zeros(3), B)  # sigma = 1
        s2 = rng.chisquare(4) / 4.0
        d2 = x @ np.linalg.solve(B, x) / s2
        inside.append(d2 <= factor * chi2.ppf(0.95, 3))
        plugged.append(d2 <= chi2.ppf(0.95, 3))
    assert abs(np.mean(inside) - 0.95) < 0.013, np.mean(inside)
    assert np.mean(plugged) < 0.88, np.mean(plugged)


def test_sandwich_dof_counts_clusters_that_carry_the_direction() -> None:
    """Equal clusters along a direction: as many degrees of freedom as clusters; one cluster
    carrying it all: one."""
    sums = np.zeros((20, 6))
    sums[:, 0] = 1.0
    sums[0, 1] = 5.0
    dof = sandwich_dof(np.eye(6)[:2], sums)
    assert dof == pytest.approx([20.0, 1.0])
