"""``depthnav bench``: the report has every figure the issue asks for (no timing assertions)."""

from __future__ import annotations

import json

import pytest

from depthnav_daemon.cli import build_parser, main
from depthnav_daemon.commands.bench import stages as bench

STAGES = (
    "scan exact",
    "scan paper, whole band",
    "scan paper, params.yaml",
    "cliff, params.yaml",
    "cliff, 8 px blocks",
    "pose, daemon defaults",
    "pose: candidates + RANSAC 200 x 5000",
    "placement: scan + cliff to the base frame",
    "memory update, one view",
    "memory read-back",
    "merge two sensors",
    "pipeline per frame",
    "large mount change: all tables of a new mount",
)


def test_quick_bench_json_has_every_stage_latency_and_machine(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["bench", "--quick", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    names = [t["name"] for t in report["timings"]]
    assert names[0] == "np.copy(frame)"
    for stage in STAGES:
        assert any(n.startswith(stage) for n in names), stage
    for t in report["timings"]:
        assert 0 < t["best_s"] <= t["median_s"] <= t["p90_s"]
        assert t["ratio_to_copy"] > 0 and t["fps"] > 0
    assert report["resolution"] == "640x480" and report["frames"] == 12
    # the exact scan at the mounts and resolutions its target holds at, each against its own copy
    scans = [t["name"] for t in report["scan_mounts"]]
    for res in ("640x480", "1280x720"):
        for mount in ("0.55 m, 15 deg tilt, 0 deg roll", "0.8 m, 40 deg tilt, 5 deg roll"):
            assert f"scan exact, {res}, {mount}" in scans
        assert f"scan exact, {res}, 1.2 m, 50 deg tilt, -8 deg roll" in scans
    assert all(t["ratio_to_copy"] > 0 for t in report["scan_mounts"])
    lat = report["latency"]
    assert 0 < lat["p50_ms"] <= lat["p99_ms"] <= lat["max_ms"]
    assert lat["frames"] == 40
    # the whole loop, by sink set
    assert set(report["loop_ms"]) == {
        "null",
        "stdout + udp",
        "stdout + udp, datagrams not read",
        "stdout to a pipe + udp",
    }
    assert all(v > 0 for v in report["loop_ms"].values())
    assert set(report["loop_vs_pipeline"]) == set(report["loop_ms"])
    assert all(v > 0 for v in report["loop_vs_pipeline"].values())
    for key, (q1, q3) in report["loop_vs_pipeline_iqr"].items():  # how far a run's median moves
        assert 0 < q1 <= report["loop_vs_pipeline"][key] <= q3, key
    # where a frame's time goes inside the loop: the stages, and each sink of the set
    parts = report["loop_parts"]
    assert parts["null"].keys() == {"stages", "null"}
    assert parts["stdout + udp"].keys() == {"stages", "stdout", "udp"}
    assert parts["stdout + udp, datagrams not read"].keys() == {"stages", "stdout", "udp-unread"}
    assert parts["stdout to a pipe + udp"].keys() == {"stages", "pipe", "udp"}
    assert all(v > 0 for p in parts.values() for k, v in p.items() if k == "stages")
    assert {"cpu", "cores", "loadavg", "numpy", "numba"} <= set(report["machine"])
    sinks = [t["name"] for t in report["sinks"]]  # each output's per-frame work
    for output in ("stdout/udp JSON line", "rosbag sink, ROS 2", "rosbag sink, ROS 1", "ros2 sink"):
        assert any(n.startswith(output) for n in sinks), output
    assert any(n.startswith("foxglove sink") for n in sinks)
    assert all(t["median_s"] > 0 for t in report["sinks"])


def test_text_report_names_the_copy_reference_and_latency(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["bench", "--quick"]) == 0
    out = capsys.readouterr().out
    assert "np.copy(frame)" in out and "x np.copy" in out
    assert "UDP datagram sent" in out and "p99" in out
    assert "whole loop per frame" in out and "/ in-process pipeline" in out
    assert "inside the loop, median per frame: null: stages " in out and "udp " in out
    assert "outputs per frame" in out and "rosbag 1 ms, ros2 0.22 ms" in out
    assert "exact scan, synthetic corridor from the mounts" in out and "<= 6x np.copy" in out


def test_bench_options_parse() -> None:
    args = build_parser().parse_args(
        ["bench", "--cpu-30fps", "--resolutions", "--startup", "--rounds", "3"]
    )
    assert args.cpu_30fps == 20.0 and args.resolutions and args.startup and args.rounds == 3
    assert build_parser().parse_args(["bench"]).cpu_30fps == 0.0


def test_bad_rounds_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "--rounds", "0"]) == 2
    assert "--rounds" in capsys.readouterr().err


def test_resolutions_table_times_every_size() -> None:
    frames, mount = bench.synthetic_frames(bench.RESOLUTIONS["512x424 (Kinect v2)"], n=1)
    timings = bench.time_work(
        bench.stage_work(frames, mount, pipeline=False),
        [frames[0].depth_mm],
        rounds=1,
        samples=1,
        min_batch_s=0.0,
    )
    # np.copy, 7 stages, 4 pieces of the robot's view and a large mount change
    assert len(timings) == 13 and all(t.median_s > 0 for t in timings)


def test_a_recording_without_frames_is_a_one_line_error(
    tmp_path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "--quick", "--device", f"replay:{tmp_path / 'missing'}"]) != 0
    err = capsys.readouterr().err
    assert "Traceback" not in err and "depthnav: error" in err


def test_mount_option_times_frames_seen_from_that_mount(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["bench", "--quick", "--json", "--mount", "0.8,40,-6"]) == 0
    report = json.loads(capsys.readouterr().out)
    (name,) = report["resolutions"]
    assert name == "640x480 from 0.8 m, 40 deg tilt, -6 deg roll"
    names = [t["name"] for t in report["resolutions"][name]]
    assert any(n.startswith("scan exact") for n in names)
    _, mount = bench.synthetic_frames(bench.RESOLUTIONS["640x480 (Kinect v1)"], 1, mount=None)
    assert mount.tilt_deg == 15.0  # the default view stays


@pytest.mark.parametrize("value", ["0.5,x", "0.5,30", "0.5,95,0", "0,30,0"])
def test_a_bad_mount_is_a_one_line_usage_error(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "--quick", "--mount", value]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith("depthnav: error:") and "mount" in err
