"""What a pose covariance takes for a variance its scan measures poorly: the confidence
distribution of a variance estimated from a handful of faces (`law`) or from the few image
blocks that carry one motion (`VarianceLaw.scaled`, `sandwich_dof`), and the covariance
that holds the pose's error at 95 % as often as stated when the variances are drawn from
those distributions (`predictive`: each variance's Student-t `equivalent` shapes it, the
draws size it).

With one variance of pure scale this is Student's t: a variance s^2 on nu degrees of freedom
has the confidence distribution nu s^2 / chi-square(nu), the normal mixed over it is t(nu),
and its 95 % region is t's (Hotelling's F in k dimensions), of exact frequentist coverage.
Taking the distribution's mean instead (s^2 nu / (nu - 2)) overstates for small nu and is
infinite for nu <= 2: with the few faces of one view (6-10 on the demo part) a cap decided
it, and the pose U read ten times the error (issue 27: 98 of 99 fresh scans inside, median U
8.4 um against an error of 0.75 +- 0.73 um); taking the estimate as known understates where
one grazing strip of seven points fixes a turn (seed 140840 trial 28: 0.050 deg off, stated
U 0.031 deg)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LAW_POINTS = 1201  # points of the log grid a law is tabulated on, from 1e-12 of its cap to the cap
PREDICTIVE_DRAWS = 8000  # draws of (component, error) for the predictive coverage: its binomial sd 0.24 % at 95 %


@dataclass(frozen=True)
class VarianceLaw:
    """The confidence distribution of a variance component theta (mm^2): P(theta <= `grid`[j])
    = `below`[j], `grid` non-decreasing from 0 (an atom there: the faces' spread no more than
    their noise) to the most theta could be (its mass beyond taken there)."""

    grid: np.ndarray
    below: np.ndarray

    @classmethod
    def point(cls, value: float) -> VarianceLaw:
        """All mass at `value` (mm^2): a variance known, or taken as known."""
        return cls(np.array([value, value]), np.array([0.0, 1.0]))

    @classmethod
    def scaled(cls, dof: float) -> VarianceLaw:
        """The confidence distribution of a variance over its estimate when the estimate has
        `dof` degrees of freedom: nu / chi-square(nu) (the tails beyond 1e-9 left out)."""
        from scipy.stats import chi2

        t = np.geomspace(dof / chi2.isf(1e-9, dof), dof / chi2.ppf(1e-9, dof), LAW_POINTS)
        return cls(t, chi2.sf(dof / t, dof))

    def quantile(self, p: np.ndarray) -> np.ndarray:
        """theta at probabilities `p` (in [0, 1]), interpolated in log theta between the grid's
        points; 0 within the atom at 0."""
        positive = self.grid > 0.0
        if not positive.any():
            return np.zeros(np.shape(p))
        atom = float(self.below[~positive].max()) if (~positive).any() else 0.0
        value = np.exp(np.interp(p, self.below[positive], np.log(self.grid[positive])))
        return np.where(np.asarray(p) <= atom, 0.0, value)


def law(squares: np.ndarray, gain: np.ndarray, rest: np.ndarray, *, cap: float,
        weight: np.ndarray | None = None) -> VarianceLaw:
    """The confidence distribution of a variance component tau^2 (mm^2) at most `cap`, from
    the faces' mean residuals squared `squares`, each of variance s_f^2 = `gain`_f tau^2 +
    `rest`_f (the other components and the face's mean noise); their sum Q weighted by
    `weight` (default 1 each) is a weighted sum of chi-square(1) terms, taken as c
    chi-square(nu) (Satterthwaite on the terms a_f = weight_f s_f^2: c = sum a^2 / sum a,
    nu = (sum a)^2 / sum a^2); P(tau^2 > t) = P(Q <= the observed Q | tau^2 = t)."""
    from scipy.stats import chi2

    w = np.ones(len(squares)) if weight is None else weight
    q = float(np.sum(w * squares))
    if q <= 0.0 or cap <= 0.0:
        return VarianceLaw.point(0.0)
    t = np.concatenate([[0.0], np.geomspace(1e-12 * cap, cap, LAW_POINTS)])
    s2 = w * (gain * t[:, None] + rest)  # (grid, faces)
    total = s2.sum(axis=1)
    c = np.sum(s2 ** 2, axis=1) / np.maximum(total, 1e-300)
    above = np.where(total > 0.0, chi2.cdf(q / np.maximum(c, 1e-300), total / np.maximum(c, 1e-300)), 1.0)
    below = np.maximum.accumulate(1.0 - above)  # monotone against rounding
    grid = np.concatenate([t, [cap]])
    return VarianceLaw(grid, np.concatenate([below, [1.0]]))


def predictive(parts: tuple[np.ndarray, ...], laws: tuple[VarianceLaw, ...], *, basis: np.ndarray,
               level: float) -> np.ndarray:
    """The components theta_c (one per law) a covariance sum_c theta_c `parts`_c takes: each
    its law's `equivalent` at `level`, all scaled by the one factor at which the covariance
    holds the error inside its chi-square ellipsoid at `level` (over the directions `basis`
    (6, k) spans) as often as `level` when the error is normal of that covariance at theta
    drawn from the laws (independently; Monte Carlo, `PREDICTIVE_DRAWS` draws, seeded: the
    same covariance every run). Each component's own uncertainty shapes the covariance; the
    draws size it, so that components met together are not each taken at their own tail."""
    from scipy.stats import chi2

    shape = np.array([equivalent(lw, level=level) for lw in laws])
    k = basis.shape[1]
    if k == 0 or not np.any(shape > 0.0):
        return shape
    reduced = np.stack([basis.T @ m @ basis for m in parts])

    def covariance(theta: np.ndarray) -> np.ndarray:
        out = np.tensordot(theta, reduced, axes=(-1, 0))
        return 0.5 * (out + np.swapaxes(out, -1, -2))

    rng = np.random.default_rng(0)
    drawn = np.stack([lw.quantile(rng.uniform(size=PREDICTIVE_DRAWS)) for lw in laws], axis=1)
    w, v = np.linalg.eigh(covariance(drawn))  # each draw's error: its covariance's square root times a normal
    error = np.einsum("nij,nj->ni", v * np.sqrt(np.maximum(w, 0.0))[:, None, :],
                      rng.standard_normal((PREDICTIVE_DRAWS, k)))
    inv = np.linalg.pinv(covariance(shape), hermitian=True)
    d2 = np.einsum("ni,ij,nj->n", error, inv, error)  # each draw's distance at factor 1
    return shape * float(np.quantile(d2, level) / chi2.ppf(level, k))


def equivalent(law: VarianceLaw, *, level: float) -> float:
    """The variance (mm^2) whose normal interval at `level` is as wide as that of sqrt(theta) z
    with theta drawn from `law` and z standard normal (for nu / chi-square(nu) times s^2:
    (t_nu / z)^2 s^2, Student's t over the normal's quantile, squared)."""
    from scipy.optimize import brentq
    from scipy.special import ndtr
    from scipy.stats import norm

    theta = law.quantile((np.arange(2000) + 0.5) / 2000)  # the law by its quantiles
    if not np.any(theta > 0.0):
        return 0.0
    z = norm.isf(0.5 * (1.0 - level))

    def covered(t: float) -> float:
        with np.errstate(divide="ignore"):
            return float(np.mean(2.0 * ndtr(z * np.sqrt(t / theta)) - 1.0))

    lo, hi = np.log(1e-30 * float(theta.max())), np.log(float(theta.max()))  # below lo: a numerical zero
    if covered(float(np.exp(lo))) >= level:
        return 0.0
    if covered(float(np.exp(hi))) < level:
        return float(np.exp(hi))
    return float(np.exp(brentq(lambda x: covered(float(np.exp(x))) - level, lo, hi, xtol=1e-9)))


def sandwich_dof(directions: np.ndarray, sums: np.ndarray) -> np.ndarray:
    """The degrees of freedom (Satterthwaite) of a cluster sandwich's variance along each of
    `directions` (k, 6), the variance the sum over clusters of x_b = (direction . `sums`_b)^2
    (`sums` (G, 6): each cluster's summed influence on the pose, A^-1 s_b): (sum x)^2 / sum x^2,
    G for clusters of equal weight, 1 where one cluster decides (seven points of a grazing
    strip that alone fix a turn say little of their own spread)."""
    x = (sums @ directions.T) ** 2
    return np.sum(x, axis=0) ** 2 / np.maximum(np.sum(x ** 2, axis=0), 1e-300)
