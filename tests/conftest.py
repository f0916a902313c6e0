"""Shared fixtures: where the development data lives (../shared/data beside the repo)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("ATTITUDE_BRIDGE_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.fail(f"development data not found at {DATA_DIR} "
                    "(set ATTITUDE_BRIDGE_DATA to the shared/data folder)")
    return DATA_DIR
