#!/usr/bin/env bash
# Install everything (scripts/install.sh), then run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# lint first: the project's own ruff config, pinned in the dev extra
.venv/bin/ruff check --quiet .
.venv/bin/ruff format --check --quiet .
# the native sensor libraries were just installed: their tests must run, not skip
export DEPTHNAV_REQUIRE_NATIVE=1
# one worker per core (pytest-xdist), each test file on one worker: its module fixtures are made
# once, and the tests of a file that share a resource never run at once
exec .venv/bin/python -m pytest -q -n auto --dist loadfile "$@"
