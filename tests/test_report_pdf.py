"""Printing a report never fails the command: a browser that hangs gives no PDF and one log line."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from inspection import report_pdf


def test_a_browser_that_does_not_finish_gives_no_pdf_and_a_warning(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    """A Chromium that outlives the timeout (seen at load ~180 on 2 cores: `slscan demo` ended in a
    traceback and exit 1, the part's code) is stopped; print_pdf returns None and says why."""
    slow = tmp_path / "chromium"
    slow.write_text("#!/bin/sh\nsleep 30 &\nsleep 30\n")  # a helper process holding the pipes too
    slow.chmod(0o755)
    monkeypatch.setattr(report_pdf, "chromium", lambda: str(slow))
    monkeypatch.setattr(report_pdf, "TIMEOUT_S", 0.5)
    page = tmp_path / "report.html"
    page.write_text("<html><head></head><body>report</body></html>")
    with caplog.at_level(logging.WARNING, logger=report_pdf.__name__):
        assert report_pdf.print_pdf(page, tmp_path / "report.pdf") is None
    assert not (tmp_path / "report.pdf").exists()
    assert any("did not finish" in r.getMessage() for r in caplog.records)
    assert not list(tmp_path.glob(".*.print.html"))  # the sized copy is removed
