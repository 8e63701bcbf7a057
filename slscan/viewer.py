"""Showing a recording: the native Rerun viewer when there is a display, otherwise a web
viewer served on loopback with the address to open and the ports to forward.

Rerun is imported only when a recording is shown (the command line imports this module
to build its parser)."""

from __future__ import annotations

import getpass
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any
from urllib.parse import quote

DEFAULT_WEB_PORT = 9090
DEFAULT_GRPC_PORT = 9876


def rerun_executable() -> list[str]:
    """The Rerun viewer binary of the installed rerun-sdk.

    The venv's `bin/rerun` is a Python wrapper that runs this binary as a child and does not
    pass a terminate signal on, so stopping the wrapper would orphan the viewer: run the
    binary itself when it is there."""
    override = os.environ.get("RERUN_CLI_PATH")
    if override:
        return [override]
    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).parent / ("rerun.exe" if sys.platform.startswith("win") else "rerun")
        if binary.is_file() and os.access(binary, os.X_OK):
            return [str(binary)]
    except ImportError:
        pass
    venv_bin = Path(sys.executable).parent / "rerun"
    if venv_bin.is_file():
        return [str(venv_bin)]
    found = shutil.which("rerun")
    if found:
        return [found]
    from scanner.session_recording import RecordingError

    raise RecordingError("cannot find the Rerun viewer: install rerun-sdk in this environment")


def has_display(env: Mapping[str, str] | None = None) -> bool:
    """True when a graphical session is reachable (X11 or Wayland)."""
    env = os.environ if env is None else env
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))


def recording_file(path: str | Path) -> Path:
    """The `.rrd` of a session folder, or `path` itself when it is a file."""
    from scanner.session_recording import RECORDING_NAME

    path = Path(path)
    return path / RECORDING_NAME if path.is_dir() else path


Paths = str | Path | Sequence[str | Path]


def _files(paths: Paths) -> list[Path]:
    return [recording_file(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths)]


def review_command(paths: Paths, *, display: bool | None = None, port: int = DEFAULT_WEB_PORT,
                   grpc_port: int = DEFAULT_GRPC_PORT, bind: str = "127.0.0.1",
                   blueprint: Path | None = None) -> list[str]:
    """The command line that shows recordings (one or several, opened together, with a
    blueprint `.rbl` when given): the native viewer when there is a display, otherwise a
    web viewer served over HTTP (`port`) fed by a gRPC server (`grpc_port`, which the native
    viewer opens too), both listening on `bind` (loopback by default: reach them through an
    SSH tunnel)."""
    files = [str(f) for f in _files(paths)] + ([str(blueprint)] if blueprint is not None else [])
    if has_display() if display is None else display:
        return [*rerun_executable(), *files, "--port", str(grpc_port)]  # it too listens for SDK connections
    return [*rerun_executable(), "--serve-web", *files, "--bind", bind,
            "--web-viewer-port", str(port), "--port", str(grpc_port)]


def web_url(port: int = DEFAULT_WEB_PORT, grpc_port: int = DEFAULT_GRPC_PORT, host: str = "localhost") -> str:
    """The browser address of a web viewer started by `review_command(display=False)`."""
    return f"http://{host}:{port}?url=" + quote(f"rerun+http://{host}:{grpc_port}/proxy", safe="")


def review_instructions(port: int = DEFAULT_WEB_PORT, grpc_port: int = DEFAULT_GRPC_PORT) -> str:
    """What to open, and how to tunnel both ports from another machine."""
    try:
        login = f"{getpass.getuser()}@{socket.gethostname()}"
    except Exception:  # only used in a hint
        login = "USER@HOST"
    return (f"No display here: serving the recording to a web browser.\n"
            f"  Open:  {web_url(port, grpc_port)}\n"
            f"  From another machine, first forward both ports over SSH:\n"
            f"    ssh -N -L {port}:localhost:{port} -L {grpc_port}:localhost:{grpc_port} {login}\n"
            f"  then open the same address there. Ctrl-C stops the server.")


def port_to_use(port: int | None, default: int, bind: str, what: str) -> int:
    """`port` if given and free (else RecordingError naming it); without one, `default` if
    it is free, else one the system picks free (a second `review` beside a first)."""
    from scanner.session_recording import RecordingError

    for candidate in ([port] if port is not None else [default, 0]):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((bind, candidate))
            except OSError as exc:
                if port is not None:
                    raise RecordingError(f"{what} port {port} on {bind}: {exc.strerror or exc}; choose another "
                                         f"or leave it out (a free one is taken)") from None
                continue
            return int(s.getsockname()[1])
    raise RecordingError(f"no free {what} port on {bind}")


def start_review(paths: Paths, *, display: bool | None = None, port: int | None = None,
                 grpc_port: int | None = None, bind: str = "127.0.0.1", blueprint: Path | None = None,
                 **popen_kw: Any) -> subprocess.Popen:
    """Start the viewer or web server on recordings and return at once (see `review`).
    `port`/`grpc_port`: the web viewer's HTTP port and the gRPC port feeding it; None: the
    defaults when free, else free ones."""
    from scanner.session_recording import RecordingError

    for rrd in _files(paths):
        if not rrd.is_file():
            part = rrd.with_name(rrd.name + ".part")
            hint = f"; {part.name} exists but was never closed (interrupted session)" if part.exists() else ""
            raise RecordingError(f"{rrd}: no recording to review{hint}")
    show = has_display() if display is None else display
    grpc_port = port_to_use(grpc_port, DEFAULT_GRPC_PORT, bind, "the viewer's gRPC")
    port = port_to_use(port, DEFAULT_WEB_PORT, bind, "the web viewer's HTTP") if not show else DEFAULT_WEB_PORT
    cmd = review_command(paths, display=show, port=port, grpc_port=grpc_port, bind=bind, blueprint=blueprint)
    if not show:
        print(review_instructions(port, grpc_port), flush=True)
    return subprocess.Popen(cmd, **popen_kw)


def review(paths: Paths, **kw: Any) -> int:
    """`slscan review`: show the recordings and block until the viewer or server ends;
    Ctrl-C (or SIGTERM) stops it. Returns its exit code. Keywords as `start_review`."""
    proc = start_review(paths, **kw)

    def _stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, _stop) if threading.current_thread() is threading.main_thread() else None
    try:
        return proc.wait()
    except KeyboardInterrupt:  # stop our child too, never leave a server running
        proc.terminate()
        try:
            return proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            return proc.wait()
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
