"""Shared fixtures: where the development data lives (../shared/data beside the repo)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.sitl import shared_folder

#: ATTITUDE_BRIDGE_DATA, else ../shared/data beside this repo or beside its origin
DATA_DIR = shared_folder("data", "ATTITUDE_BRIDGE_DATA")


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.fail(f"development data not found at {DATA_DIR} "
                    "(set ATTITUDE_BRIDGE_DATA to the shared/data folder)")
    return DATA_DIR
