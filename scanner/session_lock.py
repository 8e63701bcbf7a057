"""A session folder as a unit of integrity: one writer at a time, outputs only inside it.

`session_lock(root, command=...)` holds an exclusive lock on the session folder for as long
as a command writes into it (scan, decode, inspect, the station, batch): a second writer is
refused at once with the PID and command holding it ("in use by PID 4242 (slscan decode,
since 21:04:05)"). The lock is the kernel's (`flock` on `<root>/.slscan-lock`), so a writer
that is killed releases it with its last file descriptor: no stale lock survives a crash.
The same process may take it again (a scan whose inspection writes into the same session).
Whoever takes the lock removes what dead writers left (`leftovers`: temporary files
`write_atomic` and friends name `.<name>.<pid>-<random>.part...`, and older `*.part` names).

`output_dir(root, name)` is the folder `root/name`, created if missing, refused when it is a
symbolic link, or anything but a folder, or resolves outside the session's real folder:
nothing is written through a link planted in a session.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import os
import stat
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from scanner.errors import SessionError

LOCK_FILE = ".slscan-lock"
HOLDER_READ_S = 0.2  # how long a refused writer waits for the holder's record being written (s)
_held: dict[Path, int] = {}  # real session folder -> how many holders in this process
_fds: dict[Path, int] = {}
_guard = threading.Lock()


class SessionBusy(SessionError):
    """Another process is writing into the session."""


def _holder(fd: int) -> str:
    """Who holds the lock, from the record it writes just after taking it. Found empty or
    partial (taken an instant ago: two writers started together), the record is read again
    for up to HOLDER_READ_S, so the refusal still names the PID."""
    deadline = time.monotonic() + HOLDER_READ_S
    while True:
        try:
            info = json.loads(os.pread(fd, 4096, 0) or b"{}")
            pid = int(info["pid"])
            command, since = str(info.get("command", "?"))[:60], str(info.get("since", "?"))[:19]
            return f"PID {pid} ({command}, since {since})"
        except (OSError, ValueError, KeyError, TypeError):
            if time.monotonic() > deadline:
                return "another process"
            time.sleep(0.005)


def is_leftover(name: str) -> bool:
    """Whether a file name is a temporary file a writer leaves only when it is killed."""
    return (name.startswith(".") and ".part" in name) or name.endswith((".ply.part", ".npz.part"))


def leftovers(root: Path) -> list[Path]:
    """Temporary files dead writers left in the session folder and its frames/ and outputs/."""
    found = []
    for folder in (root, root / "frames", root / "outputs"):
        try:
            with os.scandir(folder) as entries:
                found += [Path(e.path) for e in entries if (is_leftover(e.name) and e.is_file(follow_symlinks=False))
                          or (is_leftover(e.name) and e.is_symlink())]
        except (FileNotFoundError, NotADirectoryError):
            continue
    return found


@contextmanager
def session_lock(root: str | Path, *, command: str) -> Iterator[Path]:
    """Hold the session folder `root` exclusively while `command` (e.g. "slscan decode")
    writes into it; yields its real path. SessionBusy when another process holds it."""
    real = Path(root).resolve()
    if not real.is_dir():
        raise SessionError(f"{root}: no such session folder")
    with _guard:
        if real in _held:
            _held[real] += 1
            fd = None
        else:
            fd = _acquire(real, root, command)
            _held[real], _fds[real] = 1, fd
    try:
        yield real
    finally:
        with _guard:
            _held[real] -= 1
            if _held[real] == 0:
                del _held[real]
                os.close(_fds.pop(real))  # releases the lock


def _acquire(real: Path, root: str | Path, command: str) -> int:
    try:
        fd = os.open(real / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise SessionError(f"{root}: cannot lock the session folder for writing ({exc.strerror})") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise SessionError(f"{real / LOCK_FILE}: not a regular file; remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise SessionBusy(f"{root}: in use by {_holder(fd)}; wait for it to finish, or stop it") from None
        record = {"pid": os.getpid(), "command": command, "since": dt.datetime.now().isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        for path in leftovers(real):
            path.unlink(missing_ok=True)
        return fd
    except BaseException:
        os.close(fd)
        raise


@contextmanager
def folder_lock(folder: str | Path, *, timeout_s: float = 30.0) -> Iterator[None]:
    """A short exclusive section among processes writing one shared file in `folder` (two
    stations replacing their reports): waits up to `timeout_s` for the other holder, then
    SessionBusy. Nothing is cleaned (other writers' temporary files in a shared folder are live)."""
    path = Path(folder) / LOCK_FILE
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise SessionBusy(f"{folder}: held by another writer for over {timeout_s:g} s") from None
                time.sleep(0.05)
        yield
    finally:
        os.close(fd)


def output_dir(root: str | Path, name: str) -> Path:
    """`root/name` as a real folder inside the session's real folder (created when missing);
    SessionError when it is a symbolic link or not a folder (nothing is written through it)."""
    real = Path(root).resolve()
    path = real / name
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        try:
            path.mkdir()
        except OSError as exc:
            raise SessionError(f"{path}: cannot create the folder ({exc.strerror})") from None
        return path
    if stat.S_ISLNK(st.st_mode):
        raise SessionError(f"{Path(root) / name}: is a symbolic link (to {os.readlink(path)}); slscan writes only "
                           f"inside the session folder: remove the link")
    if not stat.S_ISDIR(st.st_mode):
        raise SessionError(f"{Path(root) / name}: is not a folder; remove it")
    return path
