#!/usr/bin/env bash
# The quick start's first command: install depthnav (scripts/install.sh), then run it on the
# bundled fixture and show what it finds: a readable line per frame, a rerun recording to open
# in the viewer, and one JSON line as robot software receives it.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
mkdir -p out
FIXTURE=fixtures/corridor_step
echo
echo "== depthnav run --device replay:$FIXTURE --sink text --sink rerun:out/corridor_step.rrd"
echo "   (a synthetic corridor: Kinect 0.55 m high, pitched 15 deg down; boxes left and right,"
echo "    a 20 cm hole 1.0 m ahead, a step down at 2.0 m)"
.venv/bin/depthnav run --device "replay:$FIXTURE?rate=max" --sink text --sink rerun:out/corridor_step.rrd -q
echo
echo "== the same, as JSON lines (first line, cut to 400 characters):"
.venv/bin/depthnav run --device "replay:$FIXTURE?rate=max" --sink stdout --max-frames 1 -q | cut -c1-400
echo
echo "== calibrate: the mount from the floor (the fixture's truth is 0.55 m, 15 deg, 0 deg)"
.venv/bin/depthnav calibrate --device "replay:$FIXTURE?rate=max" --frames 12 -q
echo
echo "Open the recording in the viewer with: .venv/bin/rerun out/corridor_step.rrd"
