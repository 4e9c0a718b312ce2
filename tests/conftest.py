"""Shared test fixtures: paths to the real reference data beside the checkout."""

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
DATA = SHARED / "data"
GOLDEN = SHARED / "golden"


def pytest_configure(config):
    if not DATA.is_dir():
        raise pytest.UsageError(f"reference data not found at {DATA}: the tests need ../shared beside the checkout")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA


@pytest.fixture(scope="session")
def golden_dir() -> Path:
    return GOLDEN
