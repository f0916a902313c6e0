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


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Spread the tests marked ``realtime`` evenly over the first four fifths of the run.

    xdist hands the workers tests in collection order, so in file order all three
    workers run the same file's tests at once; in a file whose tests mostly wait (on a
    broker, a client, a timeout) they then all wait together and the two cores idle.
    Spread out, a waiting test overlaps tests that compute; none is left for the end,
    where a worker waiting alone would set the suite's time. Everything else keeps its
    order, and the order is the same on every worker and every run."""
    waiting = [item for item in items if item.get_closest_marker("realtime")]
    if not waiting or len(waiting) == len(items):
        return
    span = 0.8 * (len(items) - len(waiting)) / len(waiting)
    position: dict[int, float] = {}
    k = n = 0
    for item in items:
        if item.get_closest_marker("realtime"):
            position[id(item)] = (k + 0.5) * span
            k += 1
        else:
            position[id(item)] = n
            n += 1
    items.sort(key=lambda item: position[id(item)])
