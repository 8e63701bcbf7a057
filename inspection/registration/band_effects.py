"""Blurred points' error as random effects of their face (`gauss_newton.MixedPixels`): the
points of one face within the camera's blur of an outline read off their surface by one
common offset plus a linear trend across the image, each point by its own loading l_i (its
share of light from beyond the outline over `MAX_SHARE`: a pixel reads the mix it sees),
l_i (b_g + t_i . c_g), b_g and each coefficient of c_g of variance tau^2 (mm^2), t_i the
point's image position whitened over its group (unit second moment along each direction the
group extends; none along a direction it does not, so a strip of one pixel row carries one
trend coefficient).

Why per point: a band's pixels two pixels inside the outline take under 1 % of their light
from beyond, those on it about a third. At the true pose of a random part (campaign
1435581477, part_029, bench blur 0.6 px against the 1 px assumed) a wall seen at 84 deg
read +0.2 +- 5.9 um on its outline pixels, -0.0 +- 2.4 um one pixel in and +0.2 +- 1.6 um
two pixels in, while the tops' outline pixels read +39 to +132 um (sd 550-740 um) and one
pixel in -1 to +3 um. One offset shared by the whole band at its mean loading made such a
wall's inner band pixels as uncertain as its outline: the wall fixed nothing, and the view
was refused as "fixed only by blurred pixels" (6 of that campaign's 43 scans).

Why a trend: at the true pose of the 1367 faces of two random-part campaigns
(`studies.face_offsets`, 1501789337 and 1435581477), the linear trend of a face's residuals
over its image positions spread as much as the faces' mean offsets (RMS 56-62 um against
59-74 um on faces of outline pixels only), and a strip of outline pixels that alone fixes
a turn turns the pose by it (the demo part, `slscan coverage --case pose --seed 55805`,
trial 1: an 11-point strip 25 um off at the truth turned the pose 0.061 deg, beyond the
tolerance, while proven). Per whitened direction the model's trend RMS over a group is
tau_g, as its offset's sd (measured ratio 0.76-1.04 on faces of outline pixels only).

The fit estimates the pose jointly with every group's effects under these priors and keeps
the pose's part (the Schur complement): with phi_i = (1, t_i), D_g = sum_(i in g) w_i phi_i
phi_i' + sigma^2 V_g^-1 and M_g = sum_(i in g) w_i phi_i J_i', each point's row in the
estimating equation becomes c_i = J_i - M_g' D_g^-1 phi_i (J_i outside any group), the
normal matrix sum w_i c_i J_i' = H - sum_g M_g' D_g^-1 M_g, and the pose's error is linear
in the residuals through the rows c_i (`evidence.pose_covariance` takes them so)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BandEffects:
    """Per point, `group` (N,) its group (its face's blurred points; -1: no group) and
    `design` (N, 3) phi_i = (1, t_i); per group, `prior` (G,) tau_g^2 (mm^2), the variance of
    its offset and of each trend coefficient."""

    group: np.ndarray
    design: np.ndarray
    prior: np.ndarray

    @classmethod
    def of(cls, face: np.ndarray, band: np.ndarray, where: np.ndarray, *, loading: np.ndarray,
           variance_mm2: float) -> BandEffects:
        """The effects of the points `band` flags (bool (N,)), one group per CAD face
        (`face` (N,)), at image positions `where` (N, 2 px), each point's effect times its own
        `loading` (N,); every group's tau^2 is `variance_mm2`."""
        group = np.full(len(face), -1)
        if not band.any():
            return cls(group, np.zeros((len(face), 3)), np.zeros(0))
        _, g = np.unique(face[band], return_inverse=True)
        g = g.ravel()
        group[band] = g
        d, second = image_spread(where[band].astype(np.float64), g, np.ones(len(g)))
        lam, vec = np.linalg.eigh(second)
        extends = lam > 1e-6 * np.maximum(lam.max(axis=1, keepdims=True), 1e-12)  # a numerical zero: no extent
        whiten = vec * np.where(extends, 1.0 / np.sqrt(np.maximum(lam, 1e-300)), 0.0)[:, None, :]
        design = np.zeros((len(face), 3))
        design[band, 0] = 1.0
        design[band, 1:] = np.einsum("na,nab->nb", d, whiten[g])
        design[band] *= loading[band, None]
        return cls(group, design, np.full(len(second), float(variance_mm2)))

    def subset(self, keep: np.ndarray) -> BandEffects:
        """The effects for the points `keep` (a mask or indices) of these, which must hold
        every point of a group (its design was whitened over all of them)."""
        return BandEffects(self.group[keep], self.design[keep], self.prior)

    def rows(self, J: np.ndarray, weight: np.ndarray, sigma: float) -> np.ndarray:
        """The estimating equation's rows c_i (N, k) for Jacobian rows `J` (N, k) under the
        points' `weight`s (N,) and the residuals' scale `sigma` (mm) (module docstring)."""
        inband = self.group >= 0
        if not inband.any():
            return J
        g, phi, w = self.group[inband], self.design[inband], weight[inband]
        G, k = len(self.prior), J.shape[1]
        wphi = phi * w[:, None]
        D = np.stack([np.stack([np.bincount(g, weights=wphi[:, a] * phi[:, b], minlength=G) for b in range(3)], 1)
                      for a in range(3)], 1)
        D += (sigma ** 2 / np.maximum(self.prior, 1e-30))[:, None, None] * np.eye(3)
        M = np.stack([np.stack([np.bincount(g, weights=wphi[:, a] * J[inband, c], minlength=G) for c in range(k)], 1)
                      for a in range(3)], 1)  # (G, 3, k)
        K = np.linalg.solve(D, M)  # D_g^-1 M_g
        C = J.copy()
        C[inband] -= np.einsum("na,nak->nk", phi, K[g])
        return C

    def trends(self, C: np.ndarray, weight: np.ndarray, variance: np.ndarray) -> np.ndarray:
        """sum_g sum_k tau_g^2 n_gk n_gk' (k, k): what the groups' trends put into the normal
        equations' right-hand side, n_gk = sum_(i in g) weight_i t_ik c_i (`C` (N, k) the
        estimator's rows, `rows`), each coefficient of variance `variance` (N,: each point's
        face's tau^2, mm^2, one per group used)."""
        inband = self.group >= 0
        k = C.shape[1]
        if not inband.any():
            return np.zeros((k, k))
        g, G = self.group[inband], len(self.prior)
        tau2 = np.zeros(G)
        tau2[g] = variance[inband]
        wt = self.design[inband, 1:] * weight[inband, None]
        n = np.stack([np.stack([np.bincount(g, weights=wt[:, a] * C[inband, c], minlength=G) for c in range(k)], 1)
                      for a in range(2)], 1)  # (G, 2, k)
        return np.einsum("g,gac,gad->cd", tau2, n, n)


def image_spread(where: np.ndarray, group: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d (N, 2), second (G, 2, 2)): each point's image position `where` (N, 2 px) about its
    `group`'s (N,) `weight`ed (N,) mean (0 where its weight is 0), and each group's weighted
    mean square of them (px^2): the spread a face's trend across the image runs over."""
    G = int(group.max()) + 1
    n = np.maximum(np.bincount(group, weights=weight, minlength=G), 1e-300)
    mean = np.stack([np.bincount(group, weights=weight * where[:, c], minlength=G) for c in range(2)], 1) / n[:, None]
    d = np.where(weight[:, None] > 0, where - mean[group], 0.0)
    second = np.stack([np.stack([np.bincount(group, weights=weight * d[:, a] * d[:, b], minlength=G)
                                 for b in range(2)], 1) for a in range(2)], 1) / n[:, None, None]
    return d, second
