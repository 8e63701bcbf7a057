"""`band_effects`: the blurred points' offsets and trends taken out of the pose's normal
equations, checked against the joint least-squares problem written out in full (pose and
every group's offset and trend coefficients as unknowns, the priors as extra equations)."""

from __future__ import annotations

import numpy as np
import pytest

from inspection.registration.band_effects import BandEffects


def _case(seed: int):
    """Random rows J (N, 6), weights, residuals and three groups: a 2-D patch, a strip of
    one pixel row, a lone point; the rest in no group."""
    rng = np.random.default_rng(seed)
    n = 60
    J = rng.normal(size=(n, 6))
    w = rng.uniform(0.3, 1.0, n)
    r = rng.normal(0, 0.01, n)
    face = rng.integers(0, 5, n)
    band = np.zeros(n, bool)
    band[:30] = True
    face[:12], face[12:29], face[29] = 7, 8, 9
    where = rng.uniform(0, 500, (n, 2))
    where[12:29, 1] = 40.0  # a strip along the image's rows: one trend direction
    loading = rng.uniform(0.2, 1.0, n)
    effects = BandEffects.of(face, band, where, loading=loading, variance_mm2=4e-4)
    return J, w, r, face, band, where, loading, effects


def _joint(J, w, r, face, band, where, loading, effects, sigma):
    """The pose part of the joint weighted least-squares solution, written out: unknowns
    (z, b_g, c_g1, c_g2) per group, residual model r_i = J_i z + l_i (b_g + c_g . t_i) (l_i
    the point's `loading`), each effect with its prior N(0, tau^2) as an extra equation of
    weight sigma^2 / tau^2; t_i the group's positions about their mean, whitened over the
    group."""
    groups = np.unique(face[band])
    cols = [J]
    prior = []
    for k, f in enumerate(groups):
        at = band & (face == f)
        d = where[at] - where[at].mean(axis=0)
        lam, vec = np.linalg.eigh(d.T @ d / at.sum())
        keep = lam > 1e-6 * max(lam.max(), 1e-12)
        t = d @ vec[:, keep] / np.sqrt(lam[keep])
        X = np.zeros((len(J), 1 + keep.sum()))
        X[at, 0] = 1.0
        X[np.flatnonzero(at)[:, None], 1 + np.arange(keep.sum())] = t
        cols.append(X * loading[:, None])
        prior += [effects.prior[k]] * X.shape[1]
    X = np.concatenate(cols, axis=1)
    P = np.zeros((X.shape[1], X.shape[1]))
    P[6:, 6:] = np.diag(sigma ** 2 / np.array(prior))
    N = X.T @ (X * w[:, None]) + P
    return -np.linalg.solve(N, X.T @ (w * r))[:6], np.linalg.inv(N)[:6, :6]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_schur_complement_is_the_joint_solution(seed: int) -> None:
    J, w, r, face, band, where, loading, effects = _case(seed)
    sigma = 0.01
    C = effects.rows(J, w, sigma)
    A = (C * w[:, None]).T @ J
    z = -np.linalg.solve(A, (C * w[:, None]).T @ r)
    z_joint, cov_joint = _joint(J, w, r, face, band, where, loading, effects, sigma)
    assert np.allclose(z, z_joint, rtol=1e-9, atol=1e-12)
    assert np.allclose(np.linalg.inv(A), cov_joint, rtol=1e-8, atol=1e-14)
    assert np.allclose(A, A.T, atol=1e-9 * np.abs(A).max())


def test_a_group_does_not_move_the_pose_by_its_own_offset_and_trend_beyond_the_prior() -> None:
    """Residuals that are exactly one group's offset plus trend: a group with a huge prior
    (the effect free) leaves the pose unmoved; the plain rows move it."""
    J, w, _, face, band, where, _, _ = _case(4)
    effects = BandEffects.of(face, band, where, loading=np.ones(len(face)), variance_mm2=1e6)
    at = band & (face == 8)
    r = np.where(at, 0.05 + 0.002 * (where[:, 0] - where[at, 0].mean()), 0.0)
    C = effects.rows(J, w, 0.01)
    z = np.linalg.solve((C * w[:, None]).T @ J, (C * w[:, None]).T @ r)
    plain = np.linalg.solve((J * w[:, None]).T @ J, (J * w[:, None]).T @ r)
    assert np.abs(z).max() < 1e-6 * np.abs(plain).max()


def test_no_band_leaves_the_rows_alone() -> None:
    J = np.random.default_rng(5).normal(size=(10, 6))
    effects = BandEffects.of(np.zeros(10, int), np.zeros(10, bool), np.zeros((10, 2)), loading=np.ones(10),
                             variance_mm2=1.0)
    assert effects.rows(J, np.ones(10), 0.01) is J
    assert not effects.trends(J, np.ones(10), np.ones(10)).any()


def test_the_trends_covariance_is_what_drawn_trends_do_to_the_pose() -> None:
    """`trends`: the pose's covariance from the groups' trend coefficients drawn with their
    variance, by Monte Carlo through the estimator itself (4000 draws: within 10 %)."""
    J, w, _, face, band, _, _, effects = _case(6)
    sigma = 0.01
    C = effects.rows(J, w, sigma)
    Ainv = np.linalg.inv((C * w[:, None]).T @ J)
    tau2 = np.where(band, 1e-4 * (1 + face % 3), 0.0)
    predicted = Ainv @ effects.trends(C, w, tau2) @ Ainv
    rng = np.random.default_rng(11)
    t = effects.design[:, 1:]
    draws = []
    for _ in range(4000):
        coef = rng.normal(size=(len(effects.prior), 2)) * np.sqrt(np.bincount(
            effects.group[band], weights=tau2[band]) / np.bincount(effects.group[band]))[:, None]
        r = np.where(band, np.einsum("na,na->n", t, coef[np.maximum(effects.group, 0)]), 0.0)
        draws.append(-Ainv @ ((C * w[:, None]).T @ r))
    empirical = np.cov(np.array(draws).T)
    assert np.allclose(np.diag(empirical), np.diag(predicted), rtol=0.1)
