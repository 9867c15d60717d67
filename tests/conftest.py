"""Shared test settings: where the real data is, and opt-in slow tests."""

from pathlib import Path

import pytest

from data_root import MOCAP


def pytest_addoption(parser):
    parser.addoption("--run-slow", action="store_true", help="also run tests marked slow (full-collection loads)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--run-slow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --run-slow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def mocap() -> Path:
    if not MOCAP.is_dir():
        pytest.skip(f"real mocap data not found at {MOCAP}")
    return MOCAP
