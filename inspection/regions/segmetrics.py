"""Segmentation metrics of paper 002 (Dimitrov & Golparvar-Fard, "Validation metrics").

For a ground-truth segment G_i and a test segmentation T = {T_j}: the testing segment
T^i is the union of every T_j with at least k points in G_i, k = 5% of |G_i| (and at
least one point). Over all points of the cloud:
    TP = |G_i ∩ T^i|, FN = |G_i \\ T^i|, FP = |T^i \\ G_i|, TN = the rest;
    α = FP / (FP + TN)      false-positive rate (type I error)
    β = FN / (TP + FN)      false-negative rate (type II error)
    η = the number of T_j forming T^i (over-segmentation; 0 when none qualifies).
Labels are integers, one per point; a negative label means "in no segment" (ground
truth: noise or unseen; test: unsegmented). Every point counts in the totals, except
entries whose test label is `NO_POINT` (-2): an image of labels marks pixels without a
3D point so, and those are not points of the cloud.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from inspection.errors import SegmentationError

MIN_SHARE = 0.05   # the 5% rule forming T^i
NO_POINT = -2      # label of an image pixel that has no point


@dataclass(frozen=True)
class SegmentScore:
    """α, β (fractions) and η of one ground-truth segment, with its size and the
    test segments forming T^i."""

    label: int
    points: int
    alpha: float
    beta: float
    eta: int
    members: tuple[int, ...]


@dataclass(frozen=True)
class SegmentationScore:
    """Per ground-truth segment scores and their means."""

    segments: tuple[SegmentScore, ...]

    @property
    def mean_alpha(self) -> float:
        return float(np.mean([s.alpha for s in self.segments]))

    @property
    def mean_beta(self) -> float:
        return float(np.mean([s.beta for s in self.segments]))

    @property
    def mean_eta(self) -> float:
        return float(np.mean([s.eta for s in self.segments]))

    def as_dict(self) -> dict[str, object]:
        return {"mean_alpha": self.mean_alpha, "mean_beta": self.mean_beta, "mean_eta": self.mean_eta,
                "segments": [asdict(s) for s in self.segments]}

    def table(self) -> str:
        """A plain-text table: one line per ground-truth segment, then the means (α and β
        in percent)."""
        lines = [f"{'segment':>8} {'points':>9} {'alpha %':>9} {'beta %':>8} {'eta':>4}"]
        for s in self.segments:
            lines.append(f"{s.label:>8} {s.points:>9} {100 * s.alpha:>9.4f} {100 * s.beta:>8.2f} {s.eta:>4}")
        lines.append(f"{'mean':>8} {'':>9} {100 * self.mean_alpha:>9.4f} {100 * self.mean_beta:>8.2f} "
                     f"{self.mean_eta:>4.2f}")
        return "\n".join(lines)


def score(test: np.ndarray, truth: np.ndarray) -> SegmentationScore:
    """α, β, η for every ground-truth segment of `truth` against the segmentation `test`
    (integer label arrays of the same shape, one entry per point)."""
    t = np.asarray(test)
    g = np.asarray(truth)
    if t.shape != g.shape:
        raise SegmentationError(f"labels and ground truth differ in shape: {t.shape} vs {g.shape}; "
                                "they must give one label per point of the same cloud")
    if not (np.issubdtype(t.dtype, np.integer) and np.issubdtype(g.dtype, np.integer)):
        raise SegmentationError(f"labels must be integers, got {t.dtype} and {g.dtype}")
    t, g = t.ravel().astype(np.int64), g.ravel().astype(np.int64)
    points = t != NO_POINT
    t, g = t[points], g[points]
    if not (g >= 0).any():
        raise SegmentationError("the ground truth has no segment (every label is negative)")
    n = len(g)
    g_ids, g_idx = np.unique(g[g >= 0], return_inverse=True)
    t_ids, t_inv = np.unique(t, return_inverse=True)
    t_size = np.bincount(t_inv, minlength=len(t_ids))
    in_g = g >= 0
    # contingency of (ground-truth segment, test label) over the points of ground-truth segments
    pair = g_idx * len(t_ids) + t_inv[in_g]
    table = np.bincount(pair, minlength=len(g_ids) * len(t_ids)).reshape(len(g_ids), len(t_ids))
    is_segment = t_ids >= 0
    out = []
    for i, label in enumerate(g_ids):
        row = table[i]
        size = int(row.sum())
        k = max(MIN_SHARE * size, 1.0)
        members = np.flatnonzero(is_segment & (row >= k))
        tp = int(row[members].sum())
        fp = int(t_size[members].sum()) - tp
        fn = size - tp
        tn = n - size - fp
        out.append(SegmentScore(int(label), size, fp / (fp + tn) if fp + tn else 0.0, fn / size, len(members),
                                tuple(int(x) for x in t_ids[members])))
    return SegmentationScore(tuple(out))
