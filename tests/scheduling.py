"""How `-n 2 --dist loadfile` hands the tests to its workers (`conftest.pytest_xdist_make_scheduler`).

pytest-xdist's `loadfile` gives each worker whole modules, so a module's fixtures are made once,
and sends the modules out by their number of tests, most first. A test that takes minutes alone
in a module of few tests then starts late, and the run waits for it with the other core idle:
in CI's acceptance part the NIST FTC-06 and CTC-01 registrations (one module, 481 s and 271 s of
its 972 s at dcf4f22) ran one after the other on one worker. So the tests named in `LONG` each go
out alone, longest first, before every module. A worker keeps its last test until it is sent
another (pytest tears a test's fixtures down knowing the next), so a worker running one of them
is sent the smallest module left behind it, not the next large one, which would wait there while
the other worker runs dry; the rest as `loadfile` sends them.
"""

from __future__ import annotations

from xdist.scheduler import LoadFileScheduling
from xdist.workermanage import WorkerController

LONG = {  # test id -> its seconds in CI's run at dcf4f22 (docs/testing.md): the order they go out in
    "tests/test_inspection_benchmark.py::test_nist_registration_acceptance[ftc06]": 481.0,
    "tests/test_inspection_benchmark.py::test_nist_registration_acceptance[ctc01]": 271.0,
}


class LongestFirst(LoadFileScheduling):
    """`loadfile` with each test of `LONG` a work unit of its own, sent out before the modules."""

    def _split_scope(self, nodeid: str) -> str:
        return nodeid if nodeid in LONG else super()._split_scope(nodeid)

    def _assign_work_unit(self, node: WorkerController) -> None:
        for scope in sorted((s for s in self.workqueue if s in LONG), key=LONG.__getitem__):
            self.workqueue.move_to_end(scope, last=False)  # the longest ends up first
        if any(scope in LONG and not all(unit.values()) for scope, unit in self.assigned_work.get(node, {}).items()):
            self.workqueue.move_to_end(next(reversed(self.workqueue)), last=False)  # the smallest module
        super()._assign_work_unit(node)
