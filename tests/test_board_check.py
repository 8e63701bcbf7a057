"""The corners' noise model of `slscan.board_check` (`CornerNoise`) against residual fields
drawn from a known covariance: a Gaussian field on the 9 x 7 board grid whose three
components (camera x, camera y, coded projector coordinate) are mixed from independent
exponentially correlated fields, so the truth is C(h) = exp(-|h| / L) · M Mᵀ."""

from __future__ import annotations

import numpy as np

from slscan.board_check import CornerNoise

SQUARE_MM = 75.0
LENGTH_SQUARES = 1.5
MIX = np.array([[0.25, 0.0, 0.05], [0.03, 0.10, 0.0], [0.06, 0.0, 0.08]])  # px


def _grid() -> np.ndarray:
    x, y = np.meshgrid(np.arange(9), np.arange(7), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel()])


def _truth(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """E[r(a) r(b)ᵀ] (3, 3) of grid points a, b."""
    return np.exp(-np.linalg.norm(b - a) / LENGTH_SQUARES) * MIX @ MIX.T


def _views(n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    g = _grid()
    rho = np.exp(-np.linalg.norm(g[:, None] - g[None], axis=2) / LENGTH_SQUARES)
    L = np.linalg.cholesky(rho)
    obj = np.column_stack([g * SQUARE_MM, np.zeros(len(g))])
    out = []
    for _ in range(n):
        r = (L @ rng.standard_normal((len(g), 3))) @ MIX.T  # (N, 3): camera x, camera y, projector coded
        seen = rng.random(len(g)) > 0.1  # the projector misses some corners
        proj = np.column_stack([rng.normal(0.0, 5.0, len(g)), r[:, 2]])  # coded axis 1; axis 0 unrelated
        order = rng.permutation(int(seen.sum()))
        out.append((obj, r[:, :2], obj[seen][order], proj[seen][order]))
    return out


def test_corner_noise_recovers_a_known_correlated_anisotropic_field() -> None:
    # 1500 views: at the lags only edge corners span (e.g. 4 x 6 squares) a few pairs per view estimate the
    # difference of two independent residuals, whose spread needs this many to stay inside the tolerance
    noise = CornerNoise.from_residuals(_views(1500, np.random.default_rng(3)), axis=1, square_mm=SQUARE_MM)
    table = {tuple(k): c for k, c in zip(noise.lags, noise.covariances)}
    scale = np.sqrt(np.outer(np.diag(MIX @ MIX.T), np.diag(MIX @ MIX.T)))  # for relative comparison
    for lag in [(0, 0), (1, 0), (0, 1), (1, 1), (1, -1), (2, 0), (3, 2)]:
        truth = _truth(np.zeros(2), np.array(lag))
        assert np.all(np.abs(table[lag] - truth) < 0.06 * scale), (lag, table[lag], truth)
    # the joint covariance of an arbitrary subset of corners, in any order
    g = _grid()[np.random.default_rng(4).permutation(63)[:20]]
    full = noise.covariance(g)
    truth = np.array([[_truth(a, b) for b in g] for a in g]).transpose(0, 2, 1, 3)
    assert full.shape == (20, 3, 20, 3)
    assert np.max(np.abs(full - truth)) < 0.06 * np.max(scale)
    w = np.linalg.eigvalsh(full.reshape(60, 60))
    assert w.min() > -1e-12  # positive semi-definite


def test_a_distance_between_neighbours_sees_the_difference_of_correlated_errors() -> None:
    """Var(r_i − r_j) of the coded coordinate of adjacent corners, from the model, against
    its closed form 2·(1 − e^(−1/L))·(M Mᵀ)₂₂: far below the 2·(M Mᵀ)₂₂ of independent
    corners that an isotropic, independent model assumes."""
    noise = CornerNoise.from_residuals(_views(400, np.random.default_rng(5)), axis=1, square_mm=SQUARE_MM)
    cov = noise.covariance(np.array([[0, 0], [1, 0]]))
    model = cov[0, 2, 0, 2] + cov[1, 2, 1, 2] - 2.0 * cov[0, 2, 1, 2]
    var = (MIX @ MIX.T)[2, 2]
    assert abs(model / (2.0 * (1.0 - np.exp(-1.0 / LENGTH_SQUARES)) * var) - 1.0) < 0.1


def test_the_camera_error_carried_into_the_projector_coordinate_is_modelled_per_pose() -> None:
    """Residuals made as the bench makes them: camera errors e (a correlated field), the
    coded projector coordinate a·e + n with a the local fit's Jacobian row, which differs
    from view to view (the board's tilt), and n the decoding's own field. Given each view's
    Jacobians, the sources are recovered and re-mixed with a new pose's own: the measured
    covariance matches the closed form, where pooling (camera, coded) residuals as they are
    would give the new pose the views' average coupling."""
    rng = np.random.default_rng(8)
    g = _grid()
    rho = np.exp(-np.linalg.norm(g[:, None] - g[None], axis=2) / LENGTH_SQUARES)
    L = np.linalg.cholesky(rho)
    obj = np.column_stack([g * SQUARE_MM, np.zeros(len(g))])
    camera_mix, decoding_sd = np.array([[0.2, 0.0], [0.05, 0.1]]), 0.03
    views = []
    for _ in range(800):
        e = (L @ rng.standard_normal((len(g), 2))) @ camera_mix.T
        n = decoding_sd * (L @ rng.standard_normal(len(g)))
        a = rng.normal(0.0, 1.0, 2) + [0.2, 2.0]  # this view's coupling of the coded axis (1) to the camera
        jacobian = np.zeros((len(g), 2, 2))
        jacobian[:, 1, :] = a
        proj = np.column_stack([rng.normal(0.0, 5.0, len(g)), e @ a + n])
        views.append((obj, e, obj, proj, jacobian))
    noise = CornerNoise.from_residuals(views, axis=1, square_mm=SQUARE_MM)
    pair = np.array([[0, 0], [1, 0]])
    a_new = np.array([[1.5, -0.5], [1.4, -0.4]])
    cov = noise.covariance(pair, a_new)
    Ce = [camera_mix @ camera_mix.T * np.exp(-d / LENGTH_SQUARES) for d in (0.0, 1.0)]
    Cn = [decoding_sd ** 2 * np.exp(-d / LENGTH_SQUARES) for d in (0.0, 1.0)]
    for i, j in ((0, 0), (0, 1), (1, 1)):
        lag = abs(i - j)
        truth = np.zeros((3, 3))
        truth[:2, :2] = Ce[lag]
        truth[:2, 2] = Ce[lag] @ a_new[j]
        truth[2, :2] = a_new[i] @ Ce[lag]
        truth[2, 2] = a_new[i] @ Ce[lag] @ a_new[j] + Cn[lag]
        assert np.allclose(cov[i, :, j, :], truth, atol=0.08 * truth[2, 2]), (i, j, cov[i, :, j, :], truth)
