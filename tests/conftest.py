"""Shared pytest setup."""

from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--depthnav-device",
        action="store",
        default=None,
        metavar="SPEC",
        help="also run the driver contract tests against this live device spec, e.g. kinect or openni://",
    )


@pytest.fixture
def live_spec(request: pytest.FixtureRequest) -> str:
    """The device spec given with --depthnav-device; skips the test without it."""
    spec = request.config.getoption("--depthnav-device")
    if not spec:
        pytest.skip("no live device (pass --depthnav-device SPEC)")
    return spec
