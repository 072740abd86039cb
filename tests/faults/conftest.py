"""The fault and soak suite: ``--soak`` (or DEPTHNAV_SOAK=1) runs the soak's long form."""

from __future__ import annotations

import os

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    # only seen when pytest is started on tests/faults; DEPTHNAV_SOAK=1 works from anywhere
    parser.addoption(
        "--soak",
        action="store_true",
        default=False,
        help="run the 100,000-frame soak (10-15 minutes) instead of the short form",
    )


def pytest_configure(config: pytest.Config) -> None:
    # the fuzz tests read the environment when imported, after this
    try:
        if config.getoption("--soak"):
            os.environ["DEPTHNAV_SOAK"] = "1"
    except ValueError:
        pass


@pytest.fixture
def soak_long(request: pytest.FixtureRequest) -> bool:
    """True when the long soak was asked for."""
    try:
        flag = bool(request.config.getoption("--soak"))
    except ValueError:
        flag = False
    return flag or os.environ.get("DEPTHNAV_SOAK") == "1"
