"""The layout's rules, checked on the source (docs/architecture.md, "Which way imports run"):
every import runs down the layers, no module imports itself back through others, and code is
imported as code, not by "module:attribute" strings (the rig's driver registry excepted).

Parsed with `ast` from the files themselves, so the check does not depend on the modules
importing cleanly."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("scanner", "calibration", "inspection", "sim", "slscan", "studies")
# package -> the project packages it may import (the layers, bottom up)
ALLOWED = {
    "scanner": set(),
    "calibration": {"scanner"},
    "inspection": {"scanner"},
    "sim": {"scanner", "inspection"},
    "slscan": {"scanner", "calibration", "inspection", "sim"},
    "studies": {"scanner", "calibration", "inspection", "sim", "slscan"},
}
# the benchmarks and studies of `slscan bench` may run the studies; the user's commands may not
BENCH_COMMANDS = "slscan.commands.bench"


def _allowed(module: str) -> set[str]:
    """The project packages `module` may import."""
    bench = module == BENCH_COMMANDS or module.startswith(BENCH_COMMANDS + ".")
    return ALLOWED[module.split(".")[0]] | ({"studies"} if bench else set())
# the places a module is named by a string: the registry of drivers (it finds the driver modules by a
# package scan, and the core cannot import the simulator it opens) and the command table (the command
# line imports only the module of the command it runs; test_cli checks the table against what each module registers)
STRING_IMPORTS_ALLOWED = {"scanner/drivers/registry.py", "slscan/commands/__init__.py"}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The project modules `name` imports (any depth in the file, lazy imports included)."""
    tree = ast.parse(path.read_text(), str(path))
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            candidates = [f"{target}.{a.name}" for a in node.names] + [target]
        elif isinstance(node, ast.Import):
            candidates = [a.name for a in node.names]
        else:
            continue
        for c in candidates:
            while c and c not in known:
                c = c.rpartition(".")[0]
            if c and c != name:
                found.add(c)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    return {name: _imports(name, path, known) for name, path in modules.items()}


def test_imports_run_down_the_layers() -> None:
    upward = sorted(f"{a} imports {b}" for a, targets in _graph().items() for b in targets
                    if b.split(".")[0] != a.split(".")[0] and b.split(".")[0] not in _allowed(a))
    assert upward == []


def test_import_graph_has_no_cycle() -> None:
    graph = _graph()
    # Tarjan's strongly connected components, iteratively
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))
    assert cycles == []


def test_code_is_imported_as_code_not_by_name_strings() -> None:
    offenders = []
    for path in _modules().values():
        rel = path.relative_to(ROOT).as_posix()
        if rel in STRING_IMPORTS_ALLOWED:
            continue
        for node in ast.walk(ast.parse(path.read_text(), rel)):
            if isinstance(node, ast.Call):
                f = node.func
                called = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
                if called in ("import_module", "__import__"):
                    offenders.append(f"{rel}:{node.lineno}")
    assert offenders == []


def test_one_module_name_means_one_thing() -> None:
    """Module names repeat only for the package markers, the per-package error hierarchies and
    the command modules (`slscan/commands/<command>.py` is named by the command it implements)."""
    by_name: dict[str, list[str]] = defaultdict(list)
    for name, path in _modules().items():
        if path.name not in ("__init__.py", "errors.py") and not name.startswith("slscan.commands."):
            by_name[path.stem].append(name)
    assert {k: v for k, v in by_name.items() if len(v) > 1} == {}
