"""The registration's acceptance figures on the NIST CTC-01 and FTC-06 parts
(`studies.nist_registration`: simulated single-view scans from random starts, face labels
against the simulator's truth): no proven pose beyond the pose tolerance (0.05 deg / 0.05
mm: "wrong"), at least 98 % of the runs proven within it (a refusal of a right pose counts
against that), and the face labels right on 99 % of the points away from edges. Times and
the comparison with Open3D's pipeline and single descriptors are the benchmark command's
(`python -m studies.nist_registration`); nothing here asserts a time."""

from __future__ import annotations

import pytest

from studies.nist_registration import MAIN, METHODS, PARTS, format_table, run
from studies.registration_bench import NIST_DIR

pytestmark = pytest.mark.skipif(not NIST_DIR.is_dir(), reason=f"NIST STEP files not present ({NIST_DIR})")


def held_to_the_proof(name: str, *, views: int, n_starts: int) -> None:
    """The multivariate method on `views` views x `n_starts` starts of part `name`, held to
    what the proof promises (module docstring)."""
    summary = run(name, dict([METHODS["both"]]), views=views, n_starts=n_starts)
    print(format_table(summary))
    main = summary["methods"][MAIN]
    # the 0.02 success column is the benchmark's finer figure, printed, not the promise
    assert main["runs"] == views * n_starts and main["wrong_proven"] == 0
    assert main["proven_within_tolerance"] >= 0.98
    assert min(summary["face_label_agreement"]) >= 0.99


def test_nist_registration_quick() -> None:
    """The default run's version: CTC-01, one view, two starts."""
    held_to_the_proof("ctc01", views=1, n_starts=2)


@pytest.mark.acceptance
@pytest.mark.parametrize("name", PARTS)
def test_nist_registration_acceptance(name: str) -> None:
    """The acceptance figures: 5 views x 10 starts."""
    held_to_the_proof(name, views=5, n_starts=10)
