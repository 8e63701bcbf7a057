"""A screenshot of a page that draws itself late (the Rerun web viewer: WebAssembly, then
WebGL), taken by headless Chromium after a fixed wait. `chromium --screenshot` shoots as
soon as the page has loaded, which for the viewer is its "Loading Application Bundle"
splash; here the browser is driven over --remote-debugging-pipe (the DevTools protocol,
NUL-separated JSON on file descriptors 3 and 4) and shoots after `WAIT` seconds. WebGL
runs on SwiftShader (the viewer shows "Software rasterizer").

How docs/screenshots/review-demo-inspected.png was taken (review-bin-poses.png: the same on
`slscan scan --scene bin:3 --out /tmp/bin` after `slscan pose /tmp/bin --part config/parts/nickel_tab.toml`):

    slscan demo --out /tmp/demo
    slscan review /tmp/demo --port 9391 &        # web viewer on 9391, gRPC on 9876
    python docs/screenshots/web_screenshot.py \\
        'http://localhost:9391?url=rerun%2Bhttp%3A%2F%2Flocalhost%3A9876%2Fproxy' out.png 45

usage: web_screenshot.py URL OUT.png [WAIT_S] [WIDTH] [HEIGHT]"""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import time
from typing import Any


class Pipe:
    """The DevTools protocol over a pipe pair to one Chromium process."""

    def __init__(self, exe: str, width: int, height: int) -> None:
        to_browser, self._write = os.pipe()
        self._read, from_browser = os.pipe()

        def wire() -> None:
            os.dup2(to_browser, 3)
            os.dup2(from_browser, 4)

        self.process = subprocess.Popen(
            [exe, "--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
             "--hide-scrollbars", f"--window-size={width},{height}", "--remote-debugging-pipe", "about:blank"],
            pass_fds=(3, 4), preexec_fn=wire, stderr=subprocess.DEVNULL)
        os.close(to_browser)
        os.close(from_browser)
        self._buffer, self._id = b"", 0

    def call(self, method: str, params: dict[str, Any] | None = None, session: str | None = None) -> dict[str, Any]:
        """Send one command and return its result (events in between are skipped)."""
        self._id += 1
        message = {"id": self._id, "method": method, "params": params or {}}
        if session is not None:
            message["sessionId"] = session
        os.write(self._write, json.dumps(message).encode() + b"\0")
        while True:
            while b"\0" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self._id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply.get("result", {})
            chunk = os.read(self._read, 1 << 20)
            if not chunk:
                raise RuntimeError(f"{method}: Chromium closed the pipe")
            self._buffer += chunk


def shoot(url: str, out: str, wait_s: float = 45.0, width: int = 1600, height: int = 1000) -> None:
    """Open `url`, wait `wait_s` seconds (s), write the visible page to `out` (PNG)."""
    browser = Pipe("chromium", width, height)
    try:
        target = browser.call("Target.createTarget", {"url": url})["targetId"]
        session = browser.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        time.sleep(wait_s)
        png = browser.call("Page.captureScreenshot", {"format": "png"}, session)["data"]
        with open(out, "wb") as f:
            f.write(base64.b64decode(png))
        browser.call("Browser.close")
    finally:
        try:
            browser.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            browser.process.kill()


if __name__ == "__main__":
    if not 3 <= len(sys.argv) <= 6:
        sys.exit(__doc__.rsplit("usage: ", 1)[1])
    shoot(sys.argv[1], sys.argv[2], *(float(a) for a in sys.argv[3:4]), *(int(a) for a in sys.argv[4:]))
