"""Shared fixtures: where the development data lives (../shared/data beside the repo)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _origin_checkout() -> Path | None:
    """For a local clone of a checkout: that checkout's folder (it has shared/ beside it)."""
    try:
        url = subprocess.run(["git", "-C", str(REPO), "config", "--get", "remote.origin.url"],
                             capture_output=True, text=True, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    path = Path(url.removeprefix("file://"))
    return path if url and path.is_absolute() and path.is_dir() else None


def _find_data_dir() -> Path:
    """ATTITUDE_BRIDGE_DATA, else ../shared/data beside this repo or beside its origin."""
    if "ATTITUDE_BRIDGE_DATA" in os.environ:
        return Path(os.environ["ATTITUDE_BRIDGE_DATA"])
    beside_repo = REPO.parent / "shared" / "data"
    origin = _origin_checkout()
    if not beside_repo.is_dir() and origin is not None:
        beside_origin = origin.parent / "shared" / "data"
        if beside_origin.is_dir():
            return beside_origin
    return beside_repo


DATA_DIR = _find_data_dir()


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA_DIR.is_dir():
        pytest.fail(f"development data not found at {DATA_DIR} "
                    "(set ATTITUDE_BRIDGE_DATA to the shared/data folder)")
    return DATA_DIR
