#!/usr/bin/env bash
# Install everything (scripts/install.sh), then run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# the native sensor libraries were just installed: their tests must run, not skip
export DEPTHNAV_REQUIRE_NATIVE=1
exec .venv/bin/python -m pytest -q "$@"
