"""Issue 15 acceptance: a fuzz/fault suite (Hypothesis) over every config file kind, session
manifests and frames, and the command line. An input may be accepted or refused with a
ScannerError (one line, exit code 2 on the command line); any other exception is a
traceback. The counts of inputs tried and tracebacks found are printed at the end.

Bounded in time: `max_examples` per property, deadlines off (the machine is shared)."""

from __future__ import annotations

import io
import json
import math
import shutil
import traceback
from collections.abc import Callable
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from calibration.board import Board
from inspection.bins.instances import read_label_image, read_labelme
from inspection.tolerances import load_tolerances
from scanner.calibration_file import load_calibration
from scanner.config import CONFIG_DIR, load_toml
from scanner.errors import ScannerError
from scanner.patterns import PatternSet
from scanner.pipeline import process
from scanner.rig import DEFAULT_RIG, RigConfig
from scanner.session import MANIFEST, Session
from sim.scene import Scene
from slscan import cli
from slscan.station.program import load_program
from slscan.station.station_config import StationConfig

COUNTS = {"inputs": 0, "tracebacks": 0}
FOUND: list[str] = []
FUZZ = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def attempt(what: str, fn: Callable[[], Any]) -> None:
    """Run one input: acceptance or a ScannerError are fine; anything else is a traceback."""
    COUNTS["inputs"] += 1
    try:
        fn()
    except ScannerError as exc:
        assert "\n" not in str(exc).strip(), f"{what}: a multi-line error: {exc}"
    except Exception as exc:  # counted and reported
        COUNTS["tracebacks"] += 1
        FOUND.append(f"{what}: {type(exc).__name__}: {exc}"[:200])
        raise AssertionError(f"{what}: traceback\n{traceback.format_exc()}") from None


# ------------------------------------------------------------------ a tiny TOML writer for the generated files

def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(d: dict[str, Any]) -> str:
    """Every table inline: any nesting is valid TOML this way."""
    return "".join(f"{json.dumps(k)} = {toml_value(v)}\n" for k, v in d.items())


scalars = st.one_of(st.integers(-10 ** 12, 10 ** 12), st.floats(allow_nan=True, allow_infinity=True),
                    st.booleans(), st.text(max_size=12), st.just(0), st.just(-1.0), st.just(1e300))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=3)),
                      max_leaves=8)


def paths(d: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path (dict keys and list indices) down to a leaf or a table."""
    out = []
    items = d.items() if isinstance(d, dict) else enumerate(d) if isinstance(d, list) else []
    for k, v in items:
        out.append(prefix + (k,))
        out += paths(v, prefix + (k,))
    return out


@st.composite
def mutated(draw: st.DrawFn, base: dict[str, Any]) -> dict[str, Any]:
    """`base` with 1..3 edits: a value replaced, a key deleted, a key added or misspelt."""
    d = json.loads(json.dumps(base))
    for _ in range(draw(st.integers(1, 3))):
        all_paths = paths(d)
        if not all_paths:
            break
        path = draw(st.sampled_from(all_paths))
        parent = d
        for k in path[:-1]:
            parent = parent[k]
        op = draw(st.sampled_from(["replace", "delete", "add", "misspell"]))
        key = path[-1]
        if op == "replace":
            parent[key] = draw(values)
        elif op == "delete" and isinstance(parent, dict):
            del parent[key]
        elif op == "add" and isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=10))] = draw(values)
        elif op == "misspell" and isinstance(parent, dict) and isinstance(key, str) and len(key) > 2:
            i = draw(st.integers(0, len(key) - 2))
            parent[key[:i] + key[i + 1] + key[i] + key[i + 2:]] = parent.pop(key)
    return d


def absolute(d: dict[str, Any], base: Path) -> dict[str, Any]:
    """Relative paths of a config file made absolute, so the edited copy can live elsewhere."""
    text = json.dumps(d)
    return json.loads(text.replace('"../', f'"{base.parent.parent}/'))


# ------------------------------------------------------------------ every config file kind

CONFIGS: dict[str, tuple[Path, Callable[[Path], Any]]] = {
    "rig": (DEFAULT_RIG, RigConfig.load),
    "patterns": (CONFIG_DIR / "patterns" / "heterodyne_3x4.toml", PatternSet.load),
    "scene": (CONFIG_DIR / "scenes" / "sphere_plane.toml", Scene.load),
    "board": (CONFIG_DIR / "boards" / "sim_charuco_7x5.toml", Board.load),
    "tolerances": (Path(__file__).parent / "data" / "tolerance_file.toml",
                   lambda p: load_tolerances(p, {"#657": "plane", "#158": "plane", "#270": "plane",
                                                 "#17": "cylinder"})),
    "station": (CONFIG_DIR / "station" / "sim_bench.toml", StationConfig.load),
    "part program": (CONFIG_DIR / "parts" / "demo_part.toml", load_program),
}


@pytest.mark.parametrize("kind", list(CONFIGS))
def test_fuzz_config_files(kind: str, tmp_path: Path) -> None:
    base, load = CONFIGS[kind]
    original = absolute(load_toml(base), base)
    if kind == "part program":
        original["program"]["cad"] = str(CONFIG_DIR / "parts" / "demo_part.step")
    target = tmp_path / f"fuzz{base.suffix}"

    @FUZZ
    @given(mutated(original))
    def check(d: dict[str, Any]) -> None:
        target.write_text(to_toml(d))
        attempt(f"{kind} {d}", lambda: load(target))

    check()


@pytest.mark.parametrize("kind", list(CONFIGS) + ["calibration", "labelme", "label png"])
def test_fuzz_raw_bytes(kind: str, tmp_path: Path) -> None:
    """Files that are not what they claim: random bytes, random text, JSON of the wrong shape."""
    loaders: dict[str, Callable[[Path], Any]] = {k: v[1] for k, v in CONFIGS.items()}
    loaders |= {"calibration": load_calibration, "labelme": lambda p: read_labelme(p, (320, 256)),
                "label png": read_label_image}
    suffix = {"calibration": ".json", "labelme": ".json", "label png": ".png"}.get(kind, ".toml")
    target = tmp_path / f"fuzz{suffix}"

    @settings(max_examples=25, deadline=None, derandomize=True, database=None)
    @given(st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode),
                     values.map(lambda v: json.dumps(v).encode())))
    def check(data: bytes) -> None:
        target.write_bytes(data)
        attempt(f"{kind} bytes {data[:60]!r}", lambda: loaders[kind](target))

    check()


@FUZZ
@given(st.recursive(st.one_of(st.floats(), st.integers(-2 ** 40, 2 ** 40), st.text(max_size=5), st.none()),
                    lambda inner: st.lists(inner, max_size=4), max_leaves=10))
def test_fuzz_labelme_points(points: Any) -> None:
    """Labelme shapes with any points (huge, NaN, ragged) are drawn or refused, never a crash."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "l.json"
        path.write_text(json.dumps({"imageWidth": 64, "imageHeight": 48, "shapes": [
            {"label": "a", "points": points, "shape_type": t} for t in ("polygon", "rectangle", "circle")]}))
        attempt(f"labelme points {points!r}"[:200], lambda: read_labelme(path, (64, 48)))


# ------------------------------------------------------------------ sessions: manifests and frames

def test_fuzz_manifests(clean_session: Path, tmp_path: Path) -> None:
    original = json.loads((clean_session / MANIFEST).read_text())
    root = tmp_path / "s"
    shutil.copytree(clean_session, root)

    @settings(max_examples=40, deadline=None, derandomize=True, database=None)
    @given(mutated(original))
    def check(m: dict[str, Any]) -> None:
        (root / MANIFEST).write_text(json.dumps(m))
        attempt("manifest edit", lambda: process(Session.open(root)))

    check()


def test_fuzz_frame_bytes(clean_session: Path, tmp_path: Path) -> None:
    """Flipped bytes, truncated or emptied frames: always refused, naming the frame."""
    root = tmp_path / "s"

    @settings(max_examples=25, deadline=None, derandomize=True, database=None)
    @given(st.integers(0, 11), st.sampled_from(["flip", "truncate", "empty"]), st.integers(0, 10 ** 6))
    def check(k: int, how: str, where: int) -> None:
        if root.exists():
            shutil.rmtree(root)
        shutil.copytree(clean_session, root)
        f = root / "frames" / f"frame_{k:03d}.png"
        data = bytearray(f.read_bytes())
        if how == "flip":
            data[where % len(data)] ^= 0xFF
        f.write_bytes(bytes(data[: where % len(data)]) if how == "truncate" else b"" if how == "empty" else data)

        def refused() -> None:
            with pytest.raises(ScannerError, match=f"frame {k}"):
                Session.open(root).load_stack()

        attempt(f"frame {k} {how}", refused)

    check()


# ------------------------------------------------------------------ the command line

GARBAGE = st.one_of(st.text(max_size=20), st.sampled_from(["-1", "nan", "inf", "0", "1e309", "", "--", "-x"]))


def test_fuzz_cli(clean_session: Path, tmp_path: Path) -> None:
    """Subcommands that read files, given garbage files and garbage arguments: exit 0, 1 or
    2 with a one-line error, or argparse's usage error; never a traceback."""
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    (tmp_path / "junk.json").write_text("[1, 2")
    (tmp_path / "empty").mkdir()
    files = [str(clean_session), str(junk), str(tmp_path / "junk.json"), str(tmp_path / "empty"),
             str(tmp_path / "nope"), "/etc/passwd", str(tmp_path)]
    commands = {
        "decode": lambda f, g: ["decode", f] + (["--mode", g] if g else []),
        "segment": lambda f, g: ["segment", f, "--radius", g, "--no-log", "--out", str(tmp_path / "seg")],
        "segscore": lambda f, g: ["segscore", f, g or f],
        "pose": lambda f, g: ["pose", f, "--part", g, "--no-log",
                              "--out", str(tmp_path / "pose")],
        "calibrate": lambda f, g: ["calibrate", "--from", f, "--out", str(tmp_path / "cal")] + (
            ["--poses", g] if g else []),
        "scan": lambda f, g: ["scan", "--rig", f, "--out", str(tmp_path / "o"), "--patterns", g or f],
        "inspect": lambda f, g: ["inspect", f if f != str(clean_session) else str(junk), "--cad",
                                 str(CONFIG_DIR / "parts" / "demo_part.step"), "--out", str(tmp_path / "insp")]
        + (["--tolerances", g] if g else []),
    }

    @settings(max_examples=40, deadline=None, derandomize=True, database=None)
    @given(st.sampled_from(sorted(commands)), st.sampled_from(files), GARBAGE)
    def check(cmd: str, file: str, garbage: str) -> None:
        argv = commands[cmd](file, garbage)

        def run() -> None:
            err = io.StringIO()
            try:
                with redirect_stderr(err), redirect_stdout(io.StringIO()):
                    code = cli.main(argv)
            except SystemExit as exc:  # argparse refusing the arguments: a usage line, exit 2
                assert exc.code == 2, argv
                return
            assert code in (0, 1, 2), (argv, code)
            assert "Traceback" not in err.getvalue(), err.getvalue()

        attempt(f"slscan {' '.join(argv)}", run)

    check()


def test_fuzz_counts(capsys: pytest.CaptureFixture) -> None:
    """Runs last in this module: the counts over the properties above, printed for the report."""
    with capsys.disabled():
        print(f"\nfuzz: {COUNTS['inputs']} inputs tried, {COUNTS['tracebacks']} tracebacks found"
              + (": " + " | ".join(FOUND[:5]) if FOUND else ""))
    assert COUNTS["tracebacks"] == 0
