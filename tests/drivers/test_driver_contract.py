"""One Driver contract, run over every backend: each replay format, OpenNI2 .oni playback,
the Kinect driver on Debian's fakenect, and a live device given with --depthnav-device."""

from __future__ import annotations

import itertools

import pytest

from drivers.formats.fakenect import write_fakenect
from drivers.formats.oni import write_oni
from drivers.formats.png_folder import write_png_folder
from drivers.formats.recording_writer import write_recording
from drivers.kinect.freenect import find_library as find_freenect
from drivers.openni.native import find_library as find_openni
from tests.drivers.driverkit import (
    contract_report,
    contract_report_isolated,
    kinect_exact_frames,
    ramp_frames,
    skip_without,
)

N = 3


def _folder(tmp):
    write_recording(tmp / "rec", ramp_frames(N))
    return f"replay:{tmp / 'rec'}?rate=max", False


def _npz(tmp):
    import numpy as np

    frames = ramp_frames(N)
    np.savez(
        tmp / "x.npz",
        depth_mm=np.stack([f.depth_mm for f in frames]),
        intrinsics=frames[0].intrinsics.as_array(),
        timestamp_s=[f.timestamp_s for f in frames],
    )
    return f"replay:{tmp / 'x.npz'}?rate=max", False


def _png(tmp):
    write_png_folder(tmp / "png", ramp_frames(N, accel=False))
    return f"replay:{tmp / 'png'}?rate=max", False


def _fakenect_replay(tmp):
    write_fakenect(tmp / "fk", kinect_exact_frames(N))
    return f"replay:{tmp / 'fk'}?rate=max", False


def _oni(tmp):
    skip_without(find_openni() is None, "libopenni2-0")
    write_oni(tmp / "x.oni", ramp_frames(N))
    return f"openni:{tmp / 'x.oni'}", True


def _kinect_fakenect(tmp):
    skip_without(find_freenect(fakenect=True) is None, "libfreenect0.5")
    write_fakenect(tmp / "fk", kinect_exact_frames(N))
    return f"kinect://0?fakenect={tmp / 'fk'}", True


BACKENDS = {
    "replay-folder": _folder,
    "replay-npz": _npz,
    "replay-png": _png,
    "replay-fakenect": _fakenect_replay,
    "openni-oni": _oni,
    "kinect-fakenect": _kinect_fakenect,
}


def check_contract(report: dict, finite: bool, n_expected: int | None) -> None:
    assert report["problems"] == []
    seqs = [f["seq"] for f in report["frames"]]
    assert seqs == list(range(len(seqs))) and seqs, report
    stamps = [f["t"] for f in report["frames"]]
    assert all(b >= a for a, b in itertools.pairwise(stamps)), stamps
    if finite:
        assert report.get("ended") and report.get("after_end"), (
            "a finite source ends with None, and stays ended"
        )
    if n_expected is not None:
        assert len(seqs) == n_expected


@pytest.mark.parametrize("backend", list(BACKENDS))
def test_contract(tmp_path, backend):
    spec, native = BACKENDS[backend](tmp_path)
    report = contract_report_isolated(spec, N + 2) if native else contract_report(spec, N + 2)
    check_contract(report, finite=True, n_expected=N)


def test_contract_live(live_spec):
    report = contract_report_isolated(live_spec, 10)
    check_contract(report, finite=False, n_expected=None)
