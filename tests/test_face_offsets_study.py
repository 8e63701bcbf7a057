"""The face-offset study (`studies.face_offsets`) recovers the offset model it measures:
faces drawn with offsets of variance (kappa x share)^2 + floor^2 plus the noise's, the
study's pooled kappa and floor against the generator's, its z scores per eighth of the shares
against 1 and its tail against the normal's 5 %. Offsets that do not follow the share (the
same spread for every face) show as a floor with kappa near 0, and their z scores per eighth
stray from 1 where the model's form is wrong."""

import secrets

import numpy as np
import pytest

from studies.face_offsets import FaceOffset, findings


def drawn_faces(rng: np.random.Generator, *, faces: int, kappa_mm: float, floor_mm: float) -> list[FaceOffset]:
    share = np.where(rng.random(faces) < 0.15, 0.2263, rng.uniform(0.001, 0.23, faces))  # some faces all outline
    points = rng.integers(10, 3000, faces)
    se = 0.006 / np.sqrt(points)  # 6 um noise per point
    mean = rng.normal(0.0, np.sqrt((kappa_mm * share) ** 2 + floor_mm**2 + se**2))
    return [FaceOffset("drawn", i, int(n), float(m), float(s), float(a))
            for i, (n, m, s, a) in enumerate(zip(points, mean, se, share, strict=True))]


def test_the_study_recovers_the_offset_model_it_measures() -> None:
    seed = secrets.randbits(32)  # fresh every run, printed on failure
    rng = np.random.default_rng(seed)
    kappa, floor = rng.uniform(0.1, 0.35), rng.uniform(0.0005, 0.003)
    f = findings(drawn_faces(rng, faces=4000, kappa_mm=kappa, floor_mm=floor), {"0": [1e-3]}, blur_px=0.6)
    # kappa from ~4000 faces: relative standard error about sqrt(2 / 4000) x (the share-weighted spread) < 5 %
    assert abs(f.kappa_mm / kappa - 1.0) < 0.1, (seed, f.kappa_mm, kappa)
    assert all(abs(o.z_rms - 1.0) < 0.15 for o in f.octiles), (seed, [o.z_rms for o in f.octiles])  # 500 each: +-0.03
    assert 0.035 < f.beyond_1_96 < 0.065, (seed, f.beyond_1_96)  # 5 % +- 4.5 standard errors
    assert f.faces == 4000 and len(f.octiles) == 8 and sum(o.faces for o in f.octiles) == 4000


def test_offsets_that_do_not_grow_with_the_share_show_as_the_floor() -> None:
    rng = np.random.default_rng(20261207)
    f = findings(drawn_faces(rng, faces=4000, kappa_mm=0.0, floor_mm=0.004), {"0": [1e-3]}, blur_px=0.6)
    assert abs(f.floor_mm / 0.004 - 1.0) < 0.1 and f.kappa_mm < 0.02, (f.floor_mm, f.kappa_mm)


def test_a_model_of_the_wrong_form_shows_in_the_eighths_z_scores() -> None:
    """Offsets growing with the share's square root, not the share: the pooled fit cannot
    follow both ends, and an eighth's z RMS strays from 1 by more than 5 of its +-0.03 spread."""
    rng = np.random.default_rng(20261208)
    faces = drawn_faces(rng, faces=4000, kappa_mm=0.0, floor_mm=0.0)
    wrong = [FaceOffset(x.scan, x.face, x.points, float(rng.normal(0.0, 0.03 * np.sqrt(x.share / 0.23))),
                        x.noise_se_mm, x.share) for x in faces]
    f = findings(wrong, {"0": [1e-3]}, blur_px=0.6)
    assert max(abs(o.z_rms - 1.0) for o in f.octiles) > 0.15, [o.z_rms for o in f.octiles]


def test_a_faces_trend_is_its_residuals_linear_part_across_the_image() -> None:
    """Two faces whose residuals are exactly a + b . (u, v): the trend's RMS is |b| times the
    RMS of the positions about their mean along b (closed form); a one-row strip's trend
    across its width is none; points not `ok` do not count."""
    from studies.face_offsets import _trend_rms

    u, v = np.meshgrid(np.arange(20.0), np.arange(5.0))
    area = np.stack([u.ravel(), v.ravel()], 1)
    strip = np.stack([np.arange(30.0), np.full(30, 7.0)], 1)
    where = np.concatenate([area, strip])
    f = np.concatenate([np.zeros(len(area), int), np.ones(len(strip), int)])
    r = np.where(f == 0, 0.01 + 0.002 * where[:, 0] - 0.001 * where[:, 1], -0.02 + 0.0005 * where[:, 0])
    ok = np.ones(len(r), bool)
    ok[3] = False
    r[3] = 5.0  # an outlier left out
    got = _trend_rms(where, r, f, ok)
    d = area[ok[: len(area)]] - area[ok[: len(area)]].mean(axis=0)
    assert got[0] == pytest.approx(np.sqrt(np.mean((d @ [0.002, -0.001]) ** 2)), rel=1e-9)
    assert got[1] == pytest.approx(0.0005 * np.std(strip[:, 0]), rel=1e-9)
