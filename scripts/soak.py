#!/usr/bin/env python3
"""Soak the daemon: ``python3 scripts/soak.py [FRAMES] [--json]`` (default 100,000 frames).

Replays the bundled fixture at full speed through every sink for FRAMES frames and prints the
figures: frames, duration, RSS after warm-up and at the end, drops. Exit 0 when no frame was
dropped and RSS grew by less than 5 MB after warm-up. See depthnav_daemon/tools/soak.py.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from depthnav_daemon.tools.soak import main

if __name__ == "__main__":
    sys.exit(main())
