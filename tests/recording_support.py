"""Letting go of the recordings the product gave up on (`scanner.session_recording.ABANDONED`):
after every test (tests/conftest.py) and, by a test that fills a disk, while that disk is there."""

from __future__ import annotations

import atexit
import sys
import threading

RELEASE_TIMEOUT_S = 30.0  # a healthy writer disconnects at once; a stuck one fails the test instead of hanging
STUCK: list[object] = []  # abandoned recordings whose disconnect never ended: whatever flushes them all would hang


def release_abandoned_recordings() -> None:
    """Disconnect the recordings the product gave up on (conftest's `_recordings_abandoned_by_the_test`);
    a test that fills a disk calls it while the disk still exists, with space made again."""
    recordings = sys.modules.get("scanner.session_recording")
    if recordings is None or not recordings.ABANDONED:
        return
    import rerun as rr

    stuck = []
    for stream in list(recordings.ABANDONED):
        recordings.ABANDONED.remove(stream)
        closing = threading.Thread(target=stream.disconnect, daemon=True)
        closing.start()
        closing.join(RELEASE_TIMEOUT_S)
        if closing.is_alive():
            stuck.append(stream)
    STUCK.extend(stuck)
    if not STUCK:
        atexit.unregister(rr.rerun_shutdown)  # registered once, as on import
        atexit.register(rr.rerun_shutdown)
    assert not stuck, "an abandoned recording's writer did not disconnect"
