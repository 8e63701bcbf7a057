"""The verdict before the faces no tolerance asks for (`inspection.inspect_scan.inspect`,
`on_verdict`), from the same figures as the full report, whatever the order the faces are
evaluated in.

The scan: the demo part's STEP model sampled from above (points, normals), with white
noise along the normals, one face (#158, the low top) lifted by a known offset. Truth:
with a 0.01 mm profile limit on that face, 0.1 mm of excess material is non-conforming
whatever the noise (profile = 2 max |d| >= 0.2 mm); the high top, nominal, has a
0.05 mm flatness limit far above the noise. The registration starts from the true pose
(identity: the points are in the model frame), as a station's warm start does.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from inspection import inspect_scan
from inspection.cad import load_cad
from inspection.measured_cloud import make_scan
from inspection.registration import Registration
from inspection.sampling import sample_model
from inspection.tolerances import NON_CONFORMING, Tolerances
from scanner.config import CONFIG_DIR

STEP = CONFIG_DIR / "parts" / "demo_part.step"
OFFSET_MM = 0.1  # the low top's excess material
NOISE_MM = 0.003


@pytest.fixture(scope="module")
def scene() -> tuple:
    model = load_cad(STEP)
    cloud = sample_model(model, 0.35, seed=3)
    up = cloud.normals[:, 2] > 0.3  # what a camera above the part sees
    pts, nrm, face = cloud.points[up], cloud.normals[up], cloud.face[up]
    rng = np.random.default_rng(4)
    pts = pts + nrm * rng.normal(0.0, NOISE_MM, len(pts))[:, None]
    pts[face == model.by_label("#158").index] += OFFSET_MM * np.array([0.0, 0.0, 1.0])
    scan = make_scan(pts, nrm, "sampled demo part", np.array([0.0, 0.0, 400.0]))
    tolerances = Tolerances({"#158": {"profile_mm": 0.01}, "#657": {"flatness_mm": 0.05}}, {})
    prior = Registration(np.eye(4), 0.99, NOISE_MM, 0.5, np.eye(4), "given")
    return model, scan, tolerances, prior


def _inspect(scene: tuple, on_verdict=None):
    model, scan, tolerances, prior = scene
    return inspect_scan.inspect(scan, model, tolerances, prior=prior, on_verdict=on_verdict)


def test_verdict_first_holds_the_asked_faces_and_agrees_with_the_full_report(scene: tuple,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    model = scene[0]
    shown = []
    report = _inspect(scene, lambda r: shown.append(r))
    assert len(shown) == 1  # once, before inspect returned
    first = shown[0]
    assert [r.label for r in first.faces] == [f.label for f in model.faces if f.label in ("#158", "#657")]
    assert first.verdict == report.verdict == NON_CONFORMING  # the lifted face: 0.2 mm profile > 0.01 mm
    row = {r.label: r for r in report.faces}
    assert row["#158"].verdicts["profile_mm"][1] == NON_CONFORMING
    assert row["#158"].form.profile.value >= 2 * OFFSET_MM - 0.02
    assert row["#657"].verdicts["flatness_mm"][1] != NON_CONFORMING
    # the full report has every face seen, in the model's order, the asked ones as shown first
    seen = [f.label for f in model.faces if np.any(report.segmentation.face == f.index)]
    assert [r.label for r in report.faces] == seen and len(seen) > 2
    for r in first.faces:
        assert _figures(r) == _figures(row[r.label])
    # one face at a time, in reverse order: the same figures (each face's depend on its points only)
    monkeypatch.setattr(inspect_scan, "_each_face",
                        lambda row_of, faces, seg: {f.index: row_of(f) for f in faces[::-1]})
    again = _inspect(scene)
    assert [_figures(r) for r in again.faces] == [_figures(r) for r in report.faces]


def _figures(row) -> str:
    return json.dumps(row.as_dict(), default=repr)  # NaN-safe exact comparison
