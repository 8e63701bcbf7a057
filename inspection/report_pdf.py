"""Headless Chromium (Debian's `chromium` package, installed by `./dev`) for the HTML
reports: print one to PDF, take a screenshot, or dump its DOM after its scripts ran. A
machine without Chromium gets None and a one-line reason on the log, never a failure: the
HTML report is the record, the PDF a copy of it."""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

log = logging.getLogger(__name__)
NAMES = ("chromium", "chromium-browser", "google-chrome")
PAPERS = ("A4", "Letter")  # the CSS page sizes a report prints on
PAPER: ContextVar[str] = ContextVar("PAPER", default="A4")
"""The paper reports print on while `on_paper` holds (a command's --paper); A4 otherwise."""
TIMEOUT_S = 180.0  # a loaded 2-core machine takes ~10 s for a page with a few MB of images


def chromium() -> str | None:
    """The headless browser's executable, or None when none is installed."""
    return next((p for p in map(shutil.which, NAMES) if p), None)


def _run(page: Path, *options: str) -> subprocess.CompletedProcess[str] | None:
    exe = chromium()
    if exe is None:
        log.warning("no PDF/screenshot of %s: Chromium is not installed (Debian package chromium)", page)
        return None
    with tempfile.TemporaryDirectory(prefix="slscan-chromium-") as profile:
        cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", f"--user-data-dir={profile}",
               "--allow-file-access-from-files", *options, Path(page).resolve().as_uri()]
        # its own process group: on a timeout the browser's helper processes go with it (they hold its pipes)
        with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                              start_new_session=True) as browser:
            try:
                out, err = browser.communicate(timeout=TIMEOUT_S)
            except subprocess.TimeoutExpired:  # a machine loaded far past its cores: the HTML stays the record
                os.killpg(browser.pid, signal.SIGKILL)
                browser.communicate()
                log.warning("no PDF/screenshot of %s: Chromium did not finish in %.0f s", page, TIMEOUT_S)
                return None
        return subprocess.CompletedProcess(cmd, browser.returncode, out, err)


@contextmanager
def on_paper(paper: str) -> Iterator[None]:
    """While held, reports print on `paper` (one of `PAPERS`) unless a call names another."""
    if paper not in PAPERS:
        raise ValueError(f"paper must be one of {', '.join(PAPERS)}, got {paper!r}")
    token = PAPER.set(paper)
    try:
        yield
    finally:
        PAPER.reset(token)


def print_pdf(page: Path, out: Path, paper: str | None = None) -> Path | None:
    """`page` (HTML) printed to `out` (PDF) on `paper` (one of `PAPERS`; default the one
    `on_paper` holds, else A4) with the page's print styles; None without Chromium or when
    it wrote nothing (the reason on the log). The paper size is set by a copy of the page
    beside it (its relative links resolve) with `@page {size: ...}` added, removed after printing."""
    paper = paper or PAPER.get()
    if paper not in PAPERS:
        raise ValueError(f"paper must be one of {', '.join(PAPERS)}, got {paper!r}")
    page = Path(page)
    text = page.read_text(encoding="utf-8")
    sized = f"<style>@page{{size:{paper}}}</style>"
    text = text.replace("</head>", sized + "</head>", 1) if "</head>" in text else sized + text
    copy = page.with_name(f".{page.stem}.{paper}.print.html")
    copy.write_text(text, encoding="utf-8")
    try:
        done = _run(copy, f"--print-to-pdf={Path(out).resolve()}", "--no-pdf-header-footer")
    finally:
        copy.unlink(missing_ok=True)
    if done is None:
        return None
    if done.returncode != 0 or not Path(out).is_file():
        log.warning("no PDF of %s: chromium exited %d: %s", page, done.returncode, done.stderr.strip()[-300:])
        return None
    return Path(out)


def screenshot(page: Path, out: Path, width: int, height: int) -> Path | None:
    """A PNG of the top `width` x `height` px of `page` as the browser lays it out."""
    done = _run(page, f"--screenshot={Path(out).resolve()}", f"--window-size={width},{height}")
    return Path(out) if done is not None and done.returncode == 0 and Path(out).is_file() else None


def dump_dom(page: Path, width: int, height: int) -> str | None:
    """The page's DOM after its scripts ran, laid out at `width` x `height` px."""
    done = _run(page, "--dump-dom", f"--window-size={width},{height}", "--virtual-time-budget=5000")
    return done.stdout if done is not None and done.returncode == 0 else None
