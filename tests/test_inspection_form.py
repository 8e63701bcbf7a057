"""Form evaluation against closed-form truths: minimum zone and least squares on exact
shapes, the ISO 16610-61 filter's transmission, noise handling, tolerance files. Where a
truth needs the filter itself (Sq after the L-filter, the noise floor after the form
filter), it comes from the test's own implementation (`form_truth`: FFT convolution),
itself checked here against the filter's closed-form transmission."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from form_truth import gaussian_mean, regression_filter, roughness_sq

from inspection.cad import load_cad
from inspection.errors import ToleranceError
from inspection.form import ALPHA, cylindricity_mz, evaluate_face, flatness_mz, gaussian_filter, noise_sigma, plane_ls
from inspection.sampling import sample_model
from inspection.segmentation import project_to_faces
from inspection.tolerances import decide, load_tolerances
from scanner.config import CONFIG_DIR
from sim.parts import Lobing, PlaneBow, Roughness, Taper
from sim.parts_demo import HIGH_TOP, PLATE_X, PLATE_Y, STEP_X

STEP = CONFIG_DIR / "parts" / "demo_part.step"
HIGH_TOP_INNER = ((PLATE_X[0] + 1.0, STEP_X - 1.0), (PLATE_Y[0] + 1.0, PLATE_Y[1] - 1.0))  # #657 less the 1 mm margin


def _rot(a: float, b: float) -> np.ndarray:
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    return np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]]) @ np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])


def test_flatness_of_points_between_two_tilted_planes() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (2000, 2))
    z = rng.uniform(0.0, 0.1, 2000)
    z[:4], z[4:8] = 0.0, 0.1  # the zone is touched on both sides
    R = _rot(0.3, -0.2)
    p = np.column_stack([xy, z]) @ R.T + [5.0, -3.0, 400.0]
    n = R[:, 2]
    assert flatness_mz(p, n) == pytest.approx(0.1, abs=1e-9)
    c, nn = plane_ls(p, n + 0.05)  # from a nominal normal 3 degrees off
    h = (p - c) @ nn
    assert h.max() - h.min() >= 0.1 - 1e-9 and abs(nn @ n) > 0.99999


def test_cylindricity_of_lobed_and_tapered_cylinders() -> None:
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    z = np.linspace(0, 30, 40)
    T, Z = np.meshgrid(t, z)
    for r, width in ((12.0 + 0.02 * np.cos(3 * T), 0.04), (12.0 + 0.002 * Z, 0.06)):
        p = np.stack([r * np.cos(T), r * np.sin(T), Z], -1).reshape(-1, 3) @ _rot(0.2, 0.1).T + [1, 2, 3]
        got = cylindricity_mz(p, np.array([1.0, 2.0, 3.0]), _rot(0.2, 0.1)[:, 2] + 0.01)
        assert got == pytest.approx(width, rel=1e-3)


def test_gaussian_filter_transmission_and_edges() -> None:
    g, cutoff = 0.1, 2.5
    x = np.arange(0, 60, g)
    X, Y = np.meshgrid(x, x)
    mask = np.ones_like(X, bool)
    inner = (slice(150, -150), slice(150, -150))
    for wavelength, expected in ((cutoff, 0.5), (3 * cutoff, np.exp(-np.pi * (ALPHA / 3) ** 2))):
        z = np.cos(2 * np.pi * X / wavelength)
        f = gaussian_filter(z, mask, cutoff, g, order=0)
        assert np.abs(f[inner]).max() == pytest.approx(expected, rel=0.01)  # ISO 16610-61 transmission
    quad = 1e-4 * (X - 10) ** 2 + 2e-4 * (X - 20) * (Y - 40) - 3e-4 * Y + 0.01
    f2 = gaussian_filter(quad, mask, 8.0, g, order=2)
    assert np.nanmax(np.abs(f2 - quad)) < 1e-9  # exact up to the edges and corners
    f0 = gaussian_filter(quad, mask, 8.0, g, order=0)
    assert np.abs(f0 - quad).max() > 1e-3  # the plain mean bends it there


def test_the_tests_own_filters_against_closed_forms() -> None:
    """`form_truth`'s FFT filters, the truths below rest on: the Gaussian mean transmits a
    cosine of wavelength L by exp(-pi (alpha lc / L)^2), and the second-order regression
    keeps a quadratic exactly, up to the edges of a masked region."""
    g = 0.1
    x = np.arange(0, 60, g)
    X, Y = np.meshgrid(x, x)
    full = np.ones_like(X, bool)
    inner = (slice(150, -150), slice(150, -150))
    for wavelength in (2.5, 7.5, 25.0):
        mean = gaussian_mean(np.cos(2 * np.pi * X / wavelength), full, 2.5, g)
        alpha = np.sqrt(np.log(2.0) / np.pi)  # ISO 16610-61
        assert np.abs(mean[inner]).max() == pytest.approx(np.exp(-np.pi * (alpha * 2.5 / wavelength) ** 2), rel=1e-6)
    mask = full.copy()
    mask[:100, :50] = False
    quad = 1e-4 * (X - 10) ** 2 + 2e-4 * (X - 20) * (Y - 40) - 3e-4 * Y + 0.01
    assert np.abs(regression_filter(mask, 8.0, g)(quad) - quad)[mask].max() < 1e-12


def test_noise_estimate_ignores_smooth_form() -> None:
    rng = np.random.default_rng(1)
    x = np.arange(0, 40, 0.125)
    X, Y = np.meshgrid(x, x)
    smooth = 0.07 * np.cos(2 * np.pi * X / 2.5) + 1e-4 * Y ** 2
    z = smooth + rng.normal(0, 0.014, X.shape)
    assert noise_sigma(z, np.ones_like(z, bool)) == pytest.approx(0.014, rel=0.05)


@pytest.fixture(scope="module")
def model():
    return load_cad(STEP)


def _face_points(model, label: str, defects: list, noise: float, seed: int = 0):
    face = model.by_label(label)
    c = sample_model(model, 0.125, seed=seed, faces=[face.index])
    p = c.points.copy()
    for d in defects:
        p += d.height(c.points)[:, None] * d.direction(c.points)
    p += c.normals * np.random.default_rng(seed).normal(0, noise, len(p))[:, None]
    uv, _, _, dev = project_to_faces(model, p, c.face)
    return face, p, dev, uv, c.points


def test_bow_flatness_through_noise(model) -> None:
    """A 60 um dome over the whole high top face, 14 um noise: truth = the dome's span over
    the face less its 1 mm edge margin, computed in closed form."""
    rho = np.hypot(17.5, 30.0)
    bow = PlaneBow(model.by_label("#657").index, (-27.5, 0.0, 22.0), (0, 0, 1), 0.06, rho)
    face, p, dev, uv, _ = _face_points(model, "#657", [bow], 0.014)
    r = evaluate_face(face, p, dev, uv=uv)
    inner_corner = np.hypot(17.5 - 1.0, 30.0 - 1.0)
    truth = 0.06 * inner_corner ** 2 / rho ** 2
    assert abs(r.flatness_mz.value - truth) <= 0.005 + 0.02 * truth
    assert r.flatness_mz.bias > 0 and 0 < r.flatness_mz.limit < 0.01  # noise bias removed, detection limit reported
    assert r.noise_mm == pytest.approx(0.014, rel=0.3)  # per point, estimated from the data (no noise model given)


def test_full_lobing_and_taper(model) -> None:
    boss = model.by_label("#17")
    lob = Lobing(boss.index, (20.0, 0.0, 0.0), (0, 0, 1), 1, lobes=3, amplitude_mm=0.02)
    face, p, dev, uv, _ = _face_points(model, "#17", [lob], 0.0)
    assert evaluate_face(face, p, dev, uv=uv).cylindricity_mz.value == pytest.approx(0.04, abs=0.001)
    tap = Taper(boss.index, (20.0, 0.0, 22.0), (0, 0, 1), 1, per_mm=0.002)
    face, p, dev, uv, _ = _face_points(model, "#17", [tap], 0.014)
    height = 35.0 - 1.5 - 10.0 - 2.0  # the boss's cylinder less the 1 mm margins
    assert evaluate_face(face, p, dev, uv=uv).cylindricity_mz.value == pytest.approx(0.002 * height, abs=0.005 + 0.001)


def test_sq_of_texture_with_noise_removed(model) -> None:
    """A random texture (Sq 70 um, wavelengths 2-4 mm) under 14 um of noise: Sq with the
    noise removed, against the texture's analytic heights on a 0.125 mm grid over the face
    inside its margin, less their Gaussian mean (8 mm) by the test's own FFT filter."""
    tex = Roughness(model.by_label("#657").index, (-27.5, 0.0, 22.0), (0, 0, 1), 0.07, (2.0, 4.0))
    face, p, dev, uv, _nominal = _face_points(model, "#657", [tex], 0.014)
    r = evaluate_face(face, p, dev, uv=uv)
    g = 0.125
    (x0, x1), (y0, y1) = HIGH_TOP_INNER
    X, Y = np.meshgrid(np.arange(x0 + g / 2, x1, g), np.arange(y0 + g / 2, y1, g))
    heights = tex.height(np.stack([X, Y, np.full_like(X, HIGH_TOP)], -1).reshape(-1, 3)).reshape(X.shape)
    exact = roughness_sq(heights, np.ones(X.shape, bool), 8.0, g)
    print(f"Sq {r.sq.value * 1e3:.2f} um (truth {exact * 1e3:.2f}, before noise removal {r.sq_raw_mm * 1e3:.2f})")
    assert r.sq.value == pytest.approx(exact, rel=0.05) and r.sq_raw_mm > r.sq.value


def test_too_few_points_is_not_a_number(model) -> None:
    face, p, dev, uv, _ = _face_points(model, "#718", [], 0.0)
    r = evaluate_face(face, p[:30], dev[:30], uv=uv[:30])
    assert r.status == "too few points" and r.flatness_mz is None


def test_tolerance_files(tmp_path: Path, model) -> None:
    labels = {f.label: f.type for f in model.faces}
    good = tmp_path / "t.toml"
    good.write_text('[faces."#657"]\nflatness_mm = 0.05\n[default]\nprofile_mm = 1.0\n')
    t = load_tolerances(good, labels)
    assert t.for_face("#657") == {"profile_mm": 1.0, "flatness_mm": 0.05} and t.for_face("#17") == {"profile_mm": 1.0}
    for text, words in (('[faces."#9999"]\nflatness_mm = 0.1\n', "no such face"),
                        ('[faces."#17"]\nflatness_mm = 0.1\n', "applies to planes"),
                        ('[faces."#657"]\nflatness_mm = -1\n', "> 0"),
                        ('[faces."#657"]\nwaviness_mm = 1\n', "unknown characteristic"),
                        ("not toml [", "unreadable")):
        bad = tmp_path / "bad.toml"
        bad.write_text(text)
        with pytest.raises(ToleranceError, match=words):
            load_tolerances(bad, labels)
    assert decide(0.040, 0.005, 0.05) == "conforming" and decide(0.048, 0.005, 0.05) == "uncertain"
    assert decide(0.060, 0.005, 0.05) == "non-conforming" and decide(None, 0.0, 0.05) == "not measured"
