"""Dataset folders as shipped (issue 33 item 1): 16-bit depth beside its 8-bit previews, colour and
labels, whatever sorts first; the TUM RGB-D layout recognised by its structure, not its name."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import drivers
from drivers.errors import RecordingError
from drivers.formats import image_kinds
from drivers.formats.png_folder import write_png_folder
from tests.drivers.driverkit import REPO, SMALL, ramp_frames

INTR = "fx=61.5&fy=57.25&cx=30.25&cy=22.75"
# (16-bit depth name, 8-bit preview name): the preview sorts first (u8 < u16), then last
ORDERS = [
    ("sample{i}_depth_u16.png", "sample{i}_depth_u8.png"),
    ("sample{i}_depth_0.png", "sample{i}_depth_1.png"),
]


def read_all(spec: str) -> list[drivers.Frame]:
    with drivers.opened(drivers.create_driver(spec)) as driver:
        return list(drivers.iter_frames(driver))


def shipped_dataset(folder: Path, n: int, names: tuple[str, str]) -> list[np.ndarray]:
    """``n`` samples as a dataset ships them: 16-bit depth, its 8-bit preview, an RGB image and an
    8-bit label image each; returns the 16-bit depths (millimetres)."""
    folder.mkdir(exist_ok=True)
    want = [f.depth_mm for f in ramp_frames(n, accel=False)]
    for i, depth in enumerate(want):
        Image.fromarray(depth).save(folder / names[0].format(i=i))
        Image.fromarray((depth >> 8).astype(np.uint8)).save(folder / names[1].format(i=i))
        rgb = np.dstack([(depth >> 6).astype(np.uint8)] * 3)
        Image.fromarray(rgb).save(folder / f"sample{i}_rgb.png")
        Image.fromarray((depth % 7).astype(np.uint8)).save(folder / f"sample{i}_label.png")
    return want


@pytest.mark.parametrize("names", ORDERS, ids=["preview-first", "preview-last"])
def test_shipped_dataset_reads_the_16_bit_depth_and_says_what_it_skipped(tmp_path, caplog, names):
    want = shipped_dataset(tmp_path, 3, names)
    with caplog.at_level(logging.INFO, logger="drivers"):
        got = read_all(f"replay:{tmp_path}?rate=max&scale=1000&{INTR}")
    assert len(got) == 3
    for frame, depth in zip(got, want, strict=True):
        assert frame.depth_mm.dtype == np.uint16
        np.testing.assert_array_equal(frame.depth_mm, depth)  # bit for bit
        assert frame.intrinsics == SMALL
    said = [r.getMessage() for r in caplog.records if "skipped" in r.getMessage()]
    assert len(said) == 1, said
    assert "reading 3 depth images" in said[0] and "3 colour and 6 8-bit" in said[0]


@pytest.mark.parametrize("names", ORDERS, ids=["preview-first", "preview-last"])
def test_a_large_shipped_dataset_reads_few_headers(tmp_path, monkeypatch, names):
    """Past image_kinds.READ_EACH files of one name shape, one header per group is read (first
    and last): u16 and u8 are two groups, the sample number is the frame number."""
    n = image_kinds.READ_EACH  # 2n files of the depth shape
    want = shipped_dataset(tmp_path, n, names)
    opened: list[str] = []
    real = image_kinds.kind_of

    def counting(path: Path) -> str:
        opened.append(path.name)
        return real(path)

    monkeypatch.setattr(image_kinds, "kind_of", counting)
    got = read_all(f"replay:{tmp_path}?rate=max&scale=1000&{INTR}")
    assert len(got) == n
    for frame, depth in zip(got, want, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, depth)
    depth_shape = [name for name in opened if "_depth_" in name]
    assert len(depth_shape) == 4, depth_shape  # first and last of the u16 and the u8 group


def test_a_mixed_group_is_read_file_by_file(tmp_path):
    """Past READ_EACH files, a group whose first and last file differ has each file read."""
    n = image_kinds.READ_EACH + 2  # the last is 8-bit, the first 16-bit
    paths = []
    for i in range(n):
        path = tmp_path / f"{i}.png"
        pixels = np.zeros((4, 4), np.uint16 if i % 2 == 0 else np.uint8)
        Image.fromarray(pixels).save(path)
        paths.append(path)
    kinds = [kind for _, kind in image_kinds.image_kinds(paths)]
    assert kinds == ["depth" if i % 2 == 0 else "8-bit" for i in range(n)]


def tum_folder(folder: Path, header: str, rgb: bool = True) -> list[np.ndarray]:
    """A TUM-layout folder (5000 units per metre) with ``header`` atop depth.txt and no
    camera.toml; returns the depths in millimetres."""
    frames = ramp_frames(2, accel=False)
    write_png_folder(folder, frames, scale=5000.0)
    (folder / "camera.toml").unlink()
    index = folder / "depth.txt"
    entries = [line for line in index.read_text().splitlines() if not line.startswith("#")]
    index.write_text(header + "\n".join(entries) + "\n")
    if rgb:
        (folder / "rgb").mkdir()
        lines = []
        for i, frame in enumerate(frames):
            name = f"rgb/{i:06d}.png"
            Image.fromarray(np.dstack([(frame.depth_mm >> 6).astype(np.uint8)] * 3)).save(
                folder / name
            )
            lines.append(f"{frame.timestamp_s:.6f} {name}")
        text = "# color images\n# file: 'my_recording.bag'\n# timestamp filename\n"
        (folder / "rgb.txt").write_text(text + "\n".join(lines) + "\n")
    return [f.depth_mm for f in frames]


MY_BAG = "# depth maps\n# file: 'my_recording.bag'\n# timestamp filename\n"


def test_tum_layout_without_a_dataset_name_reads_at_5000_and_says_so(tmp_path, caplog):
    want = tum_folder(tmp_path / "tum", MY_BAG)
    with caplog.at_level(logging.INFO, logger="drivers"):
        got = read_all(f"replay:{tmp_path / 'tum'}?rate=max&{INTR}")  # intrinsics only
    for frame, depth in zip(got, want, strict=True):
        np.testing.assert_array_equal(frame.depth_mm, depth)
    said = [r.getMessage() for r in caplog.records if "TUM RGB-D folder" in r.getMessage()]
    assert len(said) == 1, said
    assert "5000 depth units per metre" in said[0] and "scale=" in said[0]


def test_tum_header_without_its_own_bag_line_is_tum_too(tmp_path):
    want = tum_folder(tmp_path / "tum", "# depth maps\n# timestamp filename\n")
    got = read_all(f"replay:{tmp_path / 'tum'}?rate=max&{INTR}")
    np.testing.assert_array_equal(got[1].depth_mm, want[1])


@pytest.mark.parametrize(
    ("header", "rgb", "says"),
    [
        (MY_BAG, False, "no rgb.txt and rgb/ beside it"),
        ("# depth maps written by depthnav\n# timestamp filename\n", True, "header is not TUM"),
        ("", True, "header is not TUM"),
    ],
)
def test_a_folder_partly_like_tum_is_refused_with_the_scale_hint(tmp_path, header, rgb, says):
    tum_folder(tmp_path / "t", header, rgb=rgb)
    with pytest.raises(RecordingError, match="depth scale is not stated") as info:
        read_all(f"replay:{tmp_path / 't'}?rate=max&{INTR}")
    assert "partly as TUM RGB-D" in str(info.value) and says in str(info.value)
    assert "scale=1000" in info.value.hint and "scale=5000" in info.value.hint
    assert len(read_all(f"replay:{tmp_path / 't'}?rate=max&scale=5000&{INTR}")) == 2


def test_depth_folder_without_depth_txt_still_needs_a_stated_scale(tmp_path):
    """Unchanged: TUM's folders without depth.txt are not recognised, the scale must be given."""
    tum_folder(tmp_path / "t", MY_BAG)
    (tmp_path / "t" / "depth.txt").unlink()
    with pytest.raises(RecordingError, match="depth scale is not stated") as info:
        read_all(f"replay:{tmp_path / 't'}?rate=max&{INTR}")
    assert "TUM" not in str(info.value)
    assert len(read_all(f"replay:{tmp_path / 't'}?rate=max&scale=5000&{INTR}")) == 2


def test_run_on_a_shipped_dataset_exits_0(tmp_path):
    shipped_dataset(tmp_path, 3, ORDERS[0])
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "depthnav_daemon",
            "run",
            "--device",
            f"replay:{tmp_path}?rate=max&scale=1000&{INTR}",
            "--sink",
            "stdout",
            "--max-frames",
            "2",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert [json.loads(line)["seq"] for line in lines] == [0, 1]
