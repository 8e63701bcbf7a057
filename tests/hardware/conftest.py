"""Hardware-in-the-loop tests: run against real devices when they are present.

    pytest tests/hardware -m hardware --rig config/rigs/my_rig.toml
    SLSCAN_HARDWARE_RIG=config/rigs/my_rig.toml pytest tests      # with the whole suite

Every test here is marked `hardware`; without a rig (or with devices absent) each is
skipped with the reason. (`--rig` exists only when pytest starts in tests/hardware,
where this conftest is loaded early enough to add options; the variable works always.) The
marker is registered here because the project's pytest configuration lives in pyproject.toml.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--rig", action="store", default=None, help="rig TOML of the real rig for hardware tests")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "hardware: needs the real devices of the rig given with --rig")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    here = Path(__file__).parent
    for item in items:
        if here in Path(str(item.fspath)).parents:
            item.add_marker(pytest.mark.hardware)


@pytest.fixture(scope="session")
def hardware_rig_path(pytestconfig: pytest.Config) -> Path:
    rig = pytestconfig.getoption("--rig", default=None) or os.environ.get("SLSCAN_HARDWARE_RIG")
    if not rig:
        pytest.skip("hardware test: no real rig given (run with --rig <rig.toml> on the bench)")
    return Path(rig)
