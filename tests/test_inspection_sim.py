"""Inspection end to end on the simulated rig: the demo part's STEP model, tessellated to
0.25 um, with known defects imposed analytically (a bow on the low top face, 3-lobe lobing
and a taper on the boss, a random texture on the high top face), scanned once with the
scanner's realistic noise into a session, then registered, segmented and evaluated.

Every figure is checked against the simulator's truth: the true pose, the true face of
every pixel (one scene object per CAD face), and the noise-free surface points. The truth
of a figure is computed in the test, never by `inspection.form`: over the region measured
(the pixels the simulator's face ids put on the face where the scan has a point, 1 mm edge
margin), the minimum zone of the noise-free points by a linear programme on every point
(`form_truth`), and Sq of the imposed texture's analytic heights through the ISO 16610-61
filter by FFT. A nominal face's true zone is 0: its figure must be below its detection
limit, or zero within its U.
"""

from __future__ import annotations

import io
import json
from collections.abc import Iterator
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from defective_part import defective_run, form_row, true_form
from registration_support import STEP, shared_inspections
from scipy.spatial import cKDTree

from inspection.cad import load_cad
from inspection.inspect_scan import inspect
from inspection.measured_cloud import from_organised
from inspection.registration import pose_difference, transform_points
from inspection.sampling import sample_model
from scanner.patterns import PatternSet
from scanner.recording_reader import read_summary
from scanner.rig import RigConfig, open_rig
from slscan import cli

BOW, LOBES, TAPER, TEXTURE = 0.06, 0.02, 0.0015, 0.07  # mm; the texture is 5x the ~14 um depth noise


@pytest.fixture(scope="module", autouse=True)
def _one_registration() -> Iterator[None]:
    """The module's four inspections of one session (here and by `slscan inspect`) register
    its cloud once, and the three by `slscan inspect` (the same noise model) measure each
    face once (`shared_inspections`)."""
    with shared_inspections():
        yield


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    return defective_run(tmp_path_factory.mktemp("defects") / "session", BOW, LOBES, TAPER, TEXTURE)


def test_registration_recovers_true_pose(run: SimpleNamespace) -> None:
    """The best fit of a deformed part to its nominal model is not its true placement: the
    60-70 um defects pull it by up to a few tens of um (the NIST parts, nominal, are held
    to 0.02 mm / 0.02 deg in test_inspection_registration.py)."""
    reg = run.report.registration
    angle, shift = pose_difference(reg.transform, np.linalg.inv(run.pose), run.cloud.points.mean(axis=0))
    print(f"pose error {angle:.4f} deg, {shift * 1e3:.1f} um; fitness {reg.fitness:.3f}, "
          f"RMSE {reg.rmse_mm * 1e3:.1f} um")
    assert angle < 0.05 and shift < 0.05
    assert reg.fitness > 0.95 and not reg.ambiguous


def test_segmentation_matches_true_faces(run: SimpleNamespace) -> None:
    """>= 99 % of the part's points farther than 0.5 mm from a face edge get their true face."""
    m, rep = run.model, run.report
    part = run.cloud.subset(rep.part_mask)
    truth = run.face_of_id[run.gt.object_id[part.pixels[:, 1], part.pixels[:, 0]]]
    # distance of every true surface point to the nearest point of another face (dense CAD samples)
    q = transform_points(np.linalg.inv(run.pose), run.gt.points[part.pixels[:, 1], part.pixels[:, 0]])
    samples = sample_model(m, 0.1)
    edge = np.full(len(q), np.inf)
    for face in m.faces:
        sel = truth == face.index
        if sel.any():
            lo, hi = q[sel].min(axis=0) - 1.0, q[sel].max(axis=0) + 1.0
            near = (samples.face != face.index) & np.all((samples.points > lo) & (samples.points < hi), axis=1)
            if near.any():  # within 0.07 mm (half the sample spacing's diagonal) of the true distance
                edge[sel] = cKDTree(samples.points[near]).query(q[sel])[0]
    inner = (truth >= 0) & (edge > 0.5)
    agree = np.mean(rep.segmentation.face[inner] == truth[inner])
    print(f"face labels agree on {agree:.4%} of {inner.sum()} points > 0.5 mm from an edge; "
          f"{np.mean(rep.segmentation.face == -1):.2%} of part points unassigned")
    assert inner.sum() > 100_000 and agree >= 0.99


def test_flatness_of_bowed_face(run: SimpleNamespace) -> None:
    true, got = true_form(run, "#158"), form_row(run, "#158")
    print(f"flatness MZ {got.flatness_mz.text()} (truth {true.flatness_mz_mm * 1e3:.2f} um, noise bias removed "
          f"{got.flatness_mz.bias * 1e3:.2f} um, detection limit {got.flatness_mz.limit * 1e3:.2f} um, cut-off "
          f"{got.form_cutoff_mm} mm)")
    assert 0.8 * BOW < true.flatness_mz_mm <= BOW + 1e-9  # the bow, seen over the visible region
    assert abs(got.flatness_mz.value - true.flatness_mz_mm) <= 0.005 + 0.02 * true.flatness_mz_mm
    raw = got.raw_deviation_max.value - got.raw_deviation_min.value
    assert raw > true.flatness_mz_mm + 0.05  # raw: noise adds > 50 um


def test_cylindricity_of_lobed_tapered_boss(run: SimpleNamespace) -> None:
    true, got = true_form(run, "#17"), form_row(run, "#17")
    print(f"cylindricity MZ {got.cylindricity_mz.text()} (truth {true.cylindricity_mz_mm * 1e3:.2f} um), "
          f"{got.points} points, detection limit {got.cylindricity_mz.limit * 1e3:.2f} um")
    assert true.cylindricity_mz_mm > 0.02
    assert abs(got.cylindricity_mz.value - true.cylindricity_mz_mm) <= 0.005 + 0.02 * true.cylindricity_mz_mm


def test_sq_of_textured_face(run: SimpleNamespace) -> None:
    true, got = true_form(run, "#657"), form_row(run, "#657")
    print(f"Sq {got.sq.text()} (truth {true.sq_mm * 1e3:.2f} um; before noise removal {got.sq_raw_mm * 1e3:.2f}, "
          f"noise {got.noise_mm * 1e3:.2f} um per point)")
    assert true.sq_mm > 0.06
    assert abs(got.sq.value - true.sq_mm) <= 0.05 * true.sq_mm


def test_nominal_faces_read_below_their_detection_limit(run: SimpleNamespace) -> None:
    got = form_row(run, "#270").flatness_mz  # the boss top: no defect imposed
    assert got.value is None or got.value <= got.U  # not told from zero, or zero within U


EXIT_CASES = {  # the part's verdict by its tolerances -> (exit code, JSON status); README "Exit codes"
    "conforming": ('[faces."#270"]\nflatness_mm = 0.5\n', 0, "ok"),  # the boss top: no defect imposed
    "not measured": ('[faces."#711"]\nflatness_mm = 0.05\n', 4, "no decision"),  # the base: out of view
    "refused input": ('[faces."#99999"]\nflatness_mm = 0.05\n', 2, None),  # the model has no such face
}  # "non-conforming" (exit 1, "failed"): the `inspected` run, whose 60 um bow fails a 20 um flatness limit
REPORT_TOLERANCES = ('[faces."#158"]\nflatness_mm = 0.02\n[faces."#270"]\nflatness_mm = 0.05\n'
                     '[faces."#657"]\nsq_mm = 0.2\n')


@pytest.fixture(scope="module")
def inspected(run: SimpleNamespace, tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """`slscan inspect` of the session against REPORT_TOLERANCES, into the session's outputs
    (report files with the PDF, and the recording): its exit code, stdout, stderr and
    inspection.json. One run (about 40 s) for the exit-code table's non-conforming row and
    the report's checks."""
    tol = tmp_path_factory.mktemp("tolerances") / "tol.toml"
    tol.write_text(REPORT_TOLERANCES)
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        code = cli.main(["inspect", str(run.session), "--cad", str(STEP), "--tolerances", str(tol)])
    data = json.loads((run.session / "outputs" / "inspection.json").read_text())
    return SimpleNamespace(code=code, out=out.getvalue(), err=err.getvalue(), data=data)


def test_exit_code_is_the_verdict(run: SimpleNamespace, inspected: SimpleNamespace, tmp_path: Path, capsys) -> None:
    """`slscan inspect` exits with its verdict, and inspection.json's status says the same;
    the table (command x case -> code) is printed."""
    assert inspected.code == 1, inspected.err
    assert inspected.data["verdict"] == "non-conforming" and inspected.data["status"] == "failed"
    table = [f"inspect  {'non-conforming':<15} exit {inspected.code}"]
    for case, (text, code, status) in EXIT_CASES.items():
        tol, out = tmp_path / f"{case}.toml", tmp_path / case.replace(" ", "_")
        tol.write_text(text)
        got = cli.main(["inspect", str(run.session), "--cad", str(STEP), "--tolerances", str(tol), "--out", str(out),
                        "--no-pdf"])
        err = capsys.readouterr().err
        table.append(f"inspect  {case:<15} exit {got}")
        data = json.loads((out / "inspection.json").read_text()) if status else None
        assert got == code, (case, err)
        assert status is None or (data["verdict"] == case and data["status"] == status)
    print("\n".join(table))


def test_inspect_command_writes_report_and_recording(run: SimpleNamespace, inspected: SimpleNamespace) -> None:
    code, out, data = inspected.code, inspected.out, inspected.data
    assert code == 1 and "#158" in out and "non-conforming" in out  # the 60 um bow fails a 20 um flatness limit
    rows = {r["label"]: r for r in data["faces"]}
    assert rows["#158"]["verdict_flatness"] == "non-conforming" and rows["#270"]["verdict_flatness"] == "conforming"
    assert rows["#657"]["verdict_sq"] == "conforming" and data["verdict"] == "non-conforming"
    assert rows["#158"]["flatness_mz_u_mm"] > 0 and "flatness_mz_limit_mm" in rows["#158"]
    assert (run.session / "outputs" / "inspection.csv").read_text().startswith("label,")
    assert "data:image/png;base64," in (run.session / "outputs" / "inspection.html").read_text()
    rec = read_summary(run.session / "outputs" / "inspection.rrd")
    assert {"world/inspection/cad", "world/inspection/deviation", "world/inspection/faces",
            "inspection/deviation_map", "inspection/report"} <= set(rec.entity_paths)


@pytest.mark.slow  # a known failure (xfail, not strict): its outcome cannot fail a run, so it runs on purpose
@pytest.mark.xfail(strict=False, reason="known, issue 12: with the interreflection mask on (issue 18) the nominal "
                   "boss top #270 reads flatness 4.7 +- 1.9 um where the truth is 0 (a coverage miss); with the mask "
                   "off, 2 of its 9852 pixels differ and it reads < 5.7 um (below its detection limit)")
def test_bundled_demo_scene_seen_from_above() -> None:
    """`slscan demo`'s scene (the nominal part lying flat, seen from straight above: only
    the outline and the step fix its turn): registered, and every face measured reads
    flat below its detection limit, and its profile zone well inside what the noise alone
    reaches on the raw points."""
    from scanner.acquisition import AcquisitionSettings, acquire
    from scanner.decode import decode
    from scanner.reconstruct import Triangulator, triangulate

    config = RigConfig.load()
    patterns = PatternSet.load(config.patterns_path)
    with open_rig(config, seed=2) as rig:  # the default scene: config/scenes/demo.toml
        stack = acquire(rig, patterns, AcquisitionSettings.for_rig(rig), lambda k, f: None)
        cloud = triangulate(decode(stack, patterns, rig.camera.bit_depth, rig.model.projector.size),
                            Triangulator(rig.model))
        pose = rig.extras["scene"].objects[0].pose
    report = inspect(from_organised(cloud, "demo"), load_cad(STEP))
    reg = report.registration.transform
    angle, shift = pose_difference(reg, np.linalg.inv(pose), np.array([0.0, 0.0, 400.0]))
    print(report.table())
    print(f"pose error {angle:.4f} deg, {shift * 1e3:.1f} um")
    assert report.fitness > 0.95 and angle < 0.3 and shift < 0.1
    flat = [r.form for r in report.faces if r.form.flatness_mz is not None]
    assert len(flat) >= 3 and all(f.flatness_mz.value is None for f in flat)  # nominal: below the detection limit
    for f in flat:  # the part is nominal: its true profile zone is 0
        raw = max(f.raw_deviation_min.limit, f.raw_deviation_max.limit)  # what the noise alone reaches on raw points
        print(f"profile {f.profile.text()} (raw points' noise reaches {raw * 1e3:.1f} um)")
        assert f.deviation_source == "form surface" and (f.profile.value or f.profile.limit) < raw / 1.5
