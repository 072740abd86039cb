"""Driver-test fixtures: every test must close the replay drivers it opens."""

from __future__ import annotations

import pytest

from drivers.replay import ReplayDriver


@pytest.fixture(autouse=True)
def no_leaked_replay_drivers():
    before = ReplayDriver.open_count
    yield
    assert ReplayDriver.open_count == before, "a test left a ReplayDriver open"
