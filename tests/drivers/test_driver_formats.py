"""One fixture written in every format gives bit-identical depth through every reader."""

from __future__ import annotations

import hashlib

import drivers
from drivers.formats.fakenect import write_fakenect
from drivers.formats.oni import write_oni
from drivers.formats.png_folder import write_png_folder
from drivers.formats.recording_writer import write_recording
from drivers.kinect.freenect import find_library as find_freenect
from drivers.openni.native import find_library as find_openni
from tests.drivers.driverkit import contract_report_isolated, kinect_exact_frames, skip_without


def digest(depth) -> str:
    return hashlib.sha256(depth.tobytes()).hexdigest()[:16]


def test_every_format_replays_bit_identical_depth(tmp_path):
    # Depths are exact 11-bit disparity depths, so even fakenect's quantisation is lossless.
    frames = kinect_exact_frames(3)
    want = [digest(f.depth_mm) for f in frames]
    write_recording(tmp_path / "folder", frames)
    write_recording(tmp_path / "for_npz", frames)
    (tmp_path / "for_npz" / "frames.npz").rename(tmp_path / "bare.npz")
    write_png_folder(tmp_path / "png_mm", frames, scale=1000.0)
    write_png_folder(tmp_path / "png_tum", frames, scale=5000.0)
    write_fakenect(tmp_path / "fakenect", frames)
    specs = [
        f"replay:{tmp_path / name}?rate=max"
        for name in ("folder", "bare.npz", "png_mm", "png_tum", "fakenect")
    ]
    for spec in specs:
        with drivers.opened(drivers.create_driver(spec)) as driver:
            got = [digest(f.depth_mm) for f in drivers.iter_frames(driver)]
        assert got == want, spec
    skip_without(find_openni() is None, "libopenni2-0")
    skip_without(find_freenect(fakenect=True) is None, "libfreenect0.5")
    write_oni(tmp_path / "x.oni", frames)
    native = [
        f"replay:{tmp_path / 'x.oni'}?rate=max",
        f"kinect://0?fakenect={tmp_path / 'fakenect'}",
    ]
    for spec in native:
        report = contract_report_isolated(spec, 5)
        assert [f["sha"] for f in report["frames"]] == want, spec
