"""What every reader checks before it trusts a file: that it is a regular file (a FIFO or a
device would block the read forever, a directory is not a file), that its size is within a
cap (a reader must never be asked to hold more than memory allows), and for `.npz` archives
that each array's header agrees with the bytes the archive holds before anything is
allocated. Native libraries that report failures as text (Open3D on stdout, OpenCASCADE's
messenger) are read under `native_output`, which captures that text at the file-descriptor
level so it neither reaches the user's terminal nor a `--json` stream, and hands it to the
caller to judge.

Errors are `FileRefused` (a ScannerError: one line naming the file and the fault; exit code 2).
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
import threading
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from scanner.errors import ScannerError

if TYPE_CHECKING:
    import numpy as np

MAX_FILE_BYTES = 2 * 1024 ** 3
"""The largest model, cloud or array file read (2 GiB): its arrays take about as much memory
again, which keeps a reader within the ~4 GB a process may use here."""


MAX_IMAGE_BYTES = 512 * 1024 ** 2
"""The largest image file decoded (a label image, a texture): its pixels take a few times that."""


class FileRefused(ScannerError):
    """A file that cannot be read as what it claims to be, refused before it is used."""

    def __init__(self, path: object, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        self.problem = problem


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def regular_size(path: str | Path, *, limit: int = MAX_FILE_BYTES) -> int:
    """The size in bytes of `path`, which must be a regular file (links followed) of at most
    `limit` bytes; FileRefused otherwise. Never opens the file, so a FIFO cannot block."""
    try:
        st = os.stat(path)
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise FileRefused(path, f"cannot be read: {getattr(exc, 'strerror', None) or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise FileRefused(path, f"is {_kind(st.st_mode)}, not a file")
    if st.st_size > limit:
        raise FileRefused(path, f"{st.st_size / 1e6:.0f} MB is more than the {limit / 1e6:.0f} MB a file read here "
                                f"may hold")
    return st.st_size


def read_regular(path: str | Path, *, limit: int = MAX_FILE_BYTES) -> bytes:
    """The bytes of a regular file of at most `limit` bytes. Opened without blocking and
    checked on the open descriptor, so a FIFO swapped in after a check cannot hang the read."""
    regular_size(path, limit=limit)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise FileRefused(path, f"cannot be read: {exc.strerror}") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileRefused(path, f"is {_kind(st.st_mode)}, not a file")
        if st.st_size > limit:
            raise FileRefused(path, f"grew to {st.st_size / 1e6:.0f} MB while being read")
        try:
            data = f.read(st.st_size + 1)  # read(n) allocates n bytes first: never more than the file holds
        except OSError as exc:
            raise FileRefused(path, f"read failed: {exc.strerror}") from None
        if len(data) > limit:
            raise FileRefused(path, f"grew past {limit / 1e6:.0f} MB while being read")
        return data


def ascii_numbers(path: object, text: bytes, what: str) -> np.ndarray:
    """Every white-space separated number of `text` as float64 (one vectorised parse);
    FileRefused naming `what` when something in it is not a number."""
    import warnings

    import numpy as np

    if not text.strip():
        return np.empty(0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # numpy says "could not be read to its end" this way
        try:
            return np.fromstring(text.decode("latin-1"), dtype=np.float64, sep=" ")
        except (DeprecationWarning, ValueError):
            raise FileRefused(path, f"not a usable {what}: its data holds something that is not a number") from None


def decode_image(data: bytes, flags: int | None = None) -> tuple[np.ndarray | None, str]:
    """OpenCV's decode of an image file's bytes (`flags` default IMREAD_UNCHANGED) and what
    its codec said while decoding (libpng writes "libpng error: ..." to stderr, which would
    break a command's one-line error): (image or None, the codec's first line or "")."""
    import cv2
    import numpy as np

    if not data:
        return None, "empty file"
    with native_output() as said:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED if flags is None else flags)
    return img, said.lines[0] if said.lines else ""


# ------------------------------------------------------------------------------ .npz archives

@dataclass(frozen=True)
class ArraySpec:
    """What an .npz member must be: dtype kinds (numpy `dtype.kind` letters) and number of
    dimensions; `shape_of` names another member whose shape (first `ndim_shared` axes) it shares."""

    kinds: str
    ndim: int
    shape_of: str | None = None
    ndim_shared: int = 2


def _member_header(z: zipfile.ZipFile, info: zipfile.ZipInfo) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, header bytes) of an .npy member, from its header alone."""
    import numpy as np

    with z.open(info) as f:
        version = np.lib.format.read_magic(f)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, _, dtype = read(f)
        return tuple(int(s) for s in shape), dtype, f.tell()


def load_npz(path: str | Path, specs: dict[str, ArraySpec], *, what: str, limit: int = MAX_FILE_BYTES,
             optional: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """The arrays `specs` names from an .npz `path` (`what` names the file kind for people),
    each checked before it is read: a regular file within `limit`, a zip archive, the member
    present (unless `optional`), no pickled objects, its header's shape times its item size
    equal to the bytes the member holds (a header cannot make the reader allocate more than
    the file holds), its dtype kind and dimensions as `specs` says, and shared shapes equal."""
    import numpy as np

    regular_size(path, limit=limit)
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as z:
            members = {i.filename: i for i in z.infolist()}
            if sum(i.file_size for i in members.values()) > 4 * limit:
                raise FileRefused(path, f"not a usable {what}: its members would unpack to more than "
                                        f"{4 * limit / 1e9:.0f} GB")
            for name, spec in specs.items():
                info = members.get(f"{name}.npy")
                if info is None:
                    if name in optional:
                        continue
                    raise FileRefused(path, f"not a usable {what}: no '{name}' array")
                shape, dtype, header = _member_header(z, info)
                where = f"not a usable {what}: '{name}'"
                if dtype.hasobject:
                    raise FileRefused(path, f"{where} holds Python objects, refused (only plain arrays are read)")
                if dtype.kind not in spec.kinds or len(shape) != spec.ndim:
                    raise FileRefused(path, f"{where} is {dtype} with {len(shape)} dimensions, expected "
                                            f"{spec.ndim} dimensions of kind {spec.kinds!r}")
                if header + int(np.prod(shape, dtype=np.float64)) * dtype.itemsize != info.file_size:
                    raise FileRefused(path, f"{where}: its header says {shape} {dtype}, which is not the "
                                            f"{info.file_size - header} bytes the archive holds for it")
                with z.open(info) as f:
                    out[name] = np.lib.format.read_array(f, allow_pickle=False)
    except FileRefused:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError, SyntaxError, TypeError,
            KeyError, NotImplementedError) as exc:  # a damaged archive or .npy header: zipfile and numpy say so
        raise FileRefused(path, f"not a usable {what}: {type(exc).__name__}: {str(exc)[:160]}") from None
    for name, spec in specs.items():
        ref = spec.shape_of
        if ref and name in out and ref in out and \
                out[name].shape[:spec.ndim_shared] != out[ref].shape[:spec.ndim_shared]:
            raise FileRefused(path, f"not a usable {what}: '{name}' is {out[name].shape}, '{ref}' {out[ref].shape}")
    return out


# ------------------------------------------------------------------------------ native libraries' messages

_CAPTURE_LOCK = threading.Lock()


@dataclass
class NativeOutput:
    """What a native library wrote to stdout/stderr while `native_output` held them."""

    text: str = ""
    lines: list[str] = field(default_factory=list)

    def failures(self, *words: str) -> list[str]:
        """The captured lines that contain any of `words` (case-insensitive)."""
        return [ln for ln in self.lines if any(w in ln.lower() for w in words)]


@contextmanager
def native_output() -> Iterator[NativeOutput]:
    """Hold file descriptors 1 and 2 while a native call runs, and give what it wrote to the
    caller (`NativeOutput`) instead of the terminal. Python's own buffered output is flushed
    first, so nothing of ours is caught; one capture at a time (a lock), since descriptors
    are process-wide."""
    result = NativeOutput()
    with _CAPTURE_LOCK, tempfile.TemporaryFile() as sink:
        for stream in (sys.stdout, sys.stderr):
            with suppress(OSError, ValueError):
                stream.flush()
        saved = []
        try:
            for fd in (1, 2):
                saved.append((fd, os.dup(fd)))
                os.dup2(sink.fileno(), fd)
            yield result
        finally:
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            result.text = sink.read(1 << 20).decode(errors="replace")
            result.lines = [ln.strip() for ln in result.text.splitlines() if ln.strip()]
