"""Regenerate the README's figures (docs/img/*.png) from depthnav's own outputs.

    python scripts/make_figures.py [--viewer] [OUT_DIR]    (default docs/img; needs depthnav[plot])

- mount_side.png: ``depthnav mount`` side view of the bundled fixture's mount (0.55 m, 15 deg down,
  Kinect) on a robot 0.9 m high;
- deadzone_sweep.png: the paper's fig. 6 for that sensor (``depthnav mount --sweep``);
- corridor_snapshot.png: ``depthnav snapshot`` of fixtures/corridor_step, frame 3;
- drive_snapshot.png: ``depthnav snapshot`` of fixtures/drive_step, frame 7 (the memory, with
  the frames' odometry: the frames up to it run through the daemon's loop);
- box_experiment.png: the box experiment of figs. 11-12 (``paper_experiment --plot``).

With ``--viewer`` also the rerun viewer's default layout rendered headless (rerun's ViewerClient;
needs a Vulkan driver, e.g. Debian's mesa-vulkan-drivers), cut below rerun's top bar (which warns
of the software rasterizer): viewer.png on the corridor's recording, viewer_drive.png on the drive
(the odometry frame: the robot in its memory) and viewer_untrusted.png on the corridor with a
wrong pinned mount (0.75 m, 12 deg: the floor contradicts it, everything amber).

The PNGs are reduced to a 256-colour palette so they stay small in the repository.
"""

from __future__ import annotations

import io
import os
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

from PIL import Image

from depthnav_daemon.commands.mount import mount_plan
from depthnav_daemon.commands.snapshot import grab
from depthnav_daemon.config.loader import build_config
from depthnav_daemon.plots import render
from depthnav_daemon.plots.mount_side import draw_side_view
from depthnav_daemon.plots.snapshot import draw_snapshot
from depthnav_daemon.plots.sweep import draw_sweep
from depthnav_daemon.sim import paper_experiment

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "fixtures" / "corridor_step"
DRIVE = ROOT / "fixtures" / "drive_step"
MOUNT = {"height_m": 0.55, "tilt_deg": 15.0, "sensor": "kinect", "robot_height_m": 0.9}
# width x height in pixels of every figure (tests/test_make_figures.py checks them)
SIZES = {
    "mount_side.png": (800, 302),
    "deadzone_sweep.png": (800, 390),
    "corridor_snapshot.png": (800, 460),
    "box_experiment.png": (800, 740),
}


# shown in docs/rerun-viewer.md rather than the README (tests/test_make_figures.py checks both)
DOC_SIZES = {"drive_snapshot.png": (800, 460)}


def write_png(fig, path: Path) -> None:
    """The figure as a palette PNG (a few tens of KB instead of a few hundred)."""
    with Image.open(io.BytesIO(render(fig, "png"))) as img:
        small = img.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT)
        small.save(path, optimize=True)


def figures() -> dict[str, object]:
    """Every figure by file name (SIZES and DOC_SIZES)."""
    plan = mount_plan(
        MOUNT["height_m"],
        MOUNT["tilt_deg"],
        MOUNT["sensor"],
        None,
        "0.5,1,1.5,2,3,4,5",
        MOUNT["robot_height_m"],
    )
    cfg = build_config([], [], {"device": f"replay:{FIXTURE}"})
    frame, result = grab(cfg, 3, threading.Event())
    drive_cfg = build_config([], [], {"device": f"replay:{DRIVE}?rate=max"})
    drive = grab(drive_cfg, 7, threading.Event())
    rows = paper_experiment.run()
    return {
        "mount_side.png": draw_side_view(plan),
        "deadzone_sweep.png": draw_sweep(plan, MOUNT["sensor"]),
        "corridor_snapshot.png": draw_snapshot(
            frame, result, cfg.scan.range_max_m, "fixtures/corridor_step", scan_params=cfg.scan
        ),
        "drive_snapshot.png": draw_snapshot(
            *drive, drive_cfg.scan.range_max_m, "fixtures/drive_step", scan_params=drive_cfg.scan
        ),
        "box_experiment.png": paper_experiment.draw(rows),
    }


VIEWER_SIZE = (1200, 653)  # 1920 x 1080 less rerun's top bar, scaled to 62.5 %
VIEWER_TOP_BAR_PX = 36  # rerun's top bar (menu, "Software rasterizer" warning) at 1920 x 1080
VIEWER_LOAD_S = 8.0  # the headless viewer loads the file and renders on the CPU
# name -> (recording, --set options, frame shown)
VIEWER_SHOTS = {
    "viewer.png": (FIXTURE, (), 11),
    "viewer_drive.png": (DRIVE, (), 7),
    "viewer_untrusted.png": (
        FIXTURE,
        ("mount.height_m=0.75", "mount.tilt_deg=12", "daemon.tilt_source=config"),
        11,
    ),
}


def viewer_png(path: Path, recording: Path, sets: tuple[str, ...], frame: int) -> None:
    """The viewer's default layout on a recording run through the daemon, at one frame."""
    import rerun_cli
    from rerun.experimental import ViewerClient

    from depthnav_daemon.daemon.loop import run

    with tempfile.TemporaryDirectory() as tmp:
        rrd = Path(tmp) / "run.rrd"
        device = f"replay:{recording}?rate=max"
        cfg = build_config([], list(sets), {"device": device, "sinks": [f"rerun:{rrd}"]})
        frames = run(cfg, threading.Event()).frames
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        binary = str(Path(rerun_cli.__file__).with_name("rerun"))
        with ViewerClient.spawn(
            headless=True, port=port, hide_welcome_screen=True, executable_path=binary
        ) as viewer:
            viewer.open(str(rrd))
            time.sleep(VIEWER_LOAD_S / 2)
            viewer.set_time("frame", sequence=min(frame, frames - 1), play_state="paused")
            time.sleep(VIEWER_LOAD_S / 2)
            shot = viewer.take_screenshot()
    with Image.open(io.BytesIO(shot)) as img:
        w, h = img.size
        top = round(VIEWER_TOP_BAR_PX * h / 1080)
        small = (
            img.convert("RGB").crop((0, top, w, h)).resize(VIEWER_SIZE, Image.Resampling.LANCZOS)
        )
        # octree keeps the small legend dots' colours (median cut merged green into blue)
        small.quantize(256, method=Image.Quantize.FASTOCTREE).save(path, optimize=True)


def main(argv: list[str]) -> int:
    viewer = "--viewer" in argv
    args = [a for a in argv if a != "--viewer"]
    out = Path(args[0]) if args else ROOT / "docs" / "img"
    out.mkdir(parents=True, exist_ok=True)
    for name, fig in figures().items():  # SIZES and DOC_SIZES
        write_png(fig, out / name)
        print(f"{out / name}: {(out / name).stat().st_size // 1024} KB")
    if viewer:
        os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.mkdtemp())
        for name, (recording, sets, frame) in VIEWER_SHOTS.items():
            viewer_png(out / name, recording, sets, frame)
            print(f"{out / name}: {(out / name).stat().st_size // 1024} KB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
