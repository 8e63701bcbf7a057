"""Third-party libraries' own log output held to the level the command line asks for
(`-q`, `-v`, `--log-level`), set once before any of them is imported:

    Dask (distributed)  Python `logging`; it sets its loggers to INFO and, in processes
                        without a handler (its workers), adds its own: its level is set
                        through the environment (DASK_LOGGING__DISTRIBUTED), which the
                        workers inherit, so its records go through our handlers at our level
    Rerun               written by its Rust core to stderr (no Python logging to route
                        into): RUST_LOG, off below -v (its errors reach us as exceptions
                        when a recording closes), warnings at -v, its default at -vv
    Open3D              printed by its C++ core through Python's `sys.stdout` (no callback
                        to route): its verbosity set when it is first imported, errors only
                        below -v, warnings at -v, debug at -vv; `cli.json_stdout` sends its
                        lines to stderr under --json
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import logging
import os
import sys
from collections.abc import Callable, Sequence
from types import ModuleType


def hold_to(level: int) -> None:
    """Hold Rerun and Open3D to `level` (a `logging` level: what stderr shows), and Dask, whose
    records go through our handlers, to the root logger's level (lower with --log-file)."""
    python_level = min(level, logging.getLogger().getEffectiveLevel())
    os.environ["DASK_LOGGING__DISTRIBUTED"] = logging.getLevelName(python_level).lower()
    if "distributed" in sys.modules:  # already configured by its import: set its loggers directly
        logging.getLogger("distributed").setLevel(python_level)
    if level > logging.DEBUG:
        os.environ.setdefault("RUST_LOG", "off" if level > logging.INFO else "warn")
    after_import("open3d", lambda o3d: o3d.utility.set_verbosity_level(_open3d_level(o3d, level)))


def _open3d_level(o3d: ModuleType, level: int) -> object:
    verbosity = o3d.utility.VerbosityLevel
    return verbosity.Error if level > logging.INFO else verbosity.Warning if level > logging.DEBUG else verbosity.Debug


class _AfterImport(importlib.abc.MetaPathFinder):
    """Finds module `name` as the path finder does, its loader's `exec_module` followed by `then(module)`."""

    def __init__(self, name: str, then: Callable[[ModuleType], object]) -> None:
        self.name, self.then = name, then

    def find_spec(self, fullname: str, path: Sequence[str] | None,
                  target: ModuleType | None = None) -> importlib.machinery.ModuleSpec | None:
        if fullname != self.name:
            return None
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is not None and spec.loader is not None:
            load, then = spec.loader.exec_module, self.then

            def exec_module(module: ModuleType) -> None:
                load(module)
                then(module)

            spec.loader.exec_module = exec_module  # type: ignore[method-assign]  # this spec's own loader
        return spec


def after_import(name: str, then: Callable[[ModuleType], object]) -> None:
    """Call `then` with top-level module `name` when it is imported (at once if it is), replacing
    an earlier hook for the same module."""
    if name in sys.modules:
        then(sys.modules[name])
        return
    sys.meta_path[:] = [f for f in sys.meta_path if not (isinstance(f, _AfterImport) and f.name == name)]
    sys.meta_path.insert(0, _AfterImport(name, then))
