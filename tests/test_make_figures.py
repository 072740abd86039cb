"""scripts/make_figures.py regenerates the README's figures: valid PNGs of the expected sizes
(pixels are never compared: fonts and matplotlib versions move them)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")
from PIL import Image  # after the skip: the figures need the plot extra

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
# scripts/ is not a package
from make_figures import DOC_SIZES, SIZES, VIEWER_SHOTS, VIEWER_SIZE  # noqa: E402

MAX_TOTAL_BYTES = 400 * 1024  # the committed figures stay small


def check_pngs(folder: Path, sizes: dict[str, tuple[int, int]] = SIZES) -> int:
    total = 0
    for name, size in sizes.items():
        path = folder / name
        with Image.open(path) as img:
            assert img.format == "PNG", name
            img.verify()
        with Image.open(path) as img:
            assert img.size == size, name
            img.load()  # decodes whole: a cut-off file fails here
        total += path.stat().st_size
    return total


def test_script_writes_every_figure(tmp_path: Path) -> None:
    out = tmp_path / "img"
    p = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "make_figures.py"), str(out)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
    )
    assert p.returncode == 0, p.stderr
    assert sorted(f.name for f in out.iterdir()) == sorted({**SIZES, **DOC_SIZES})
    assert check_pngs(out) < MAX_TOTAL_BYTES
    assert check_pngs(out, DOC_SIZES) < MAX_TOTAL_BYTES / 4


def test_committed_figures_are_the_scripts_and_the_readme_shows_them() -> None:
    img = ROOT / "docs" / "img"
    assert check_pngs(img) + (img / "viewer.png").stat().st_size < MAX_TOTAL_BYTES
    with Image.open(img / "viewer.png") as shot:  # made by --viewer: needs a Vulkan driver
        assert shot.format == "PNG" and shot.size == VIEWER_SIZE
    readme = (ROOT / "README.md").read_text()
    for name in [*SIZES, "viewer.png"]:
        assert f"](docs/img/{name})" in readme, name
    # the drive (memory, odometry frame) and a wrong pinned mount, shown in the viewer's page
    others = {name: VIEWER_SIZE for name in VIEWER_SHOTS if name != "viewer.png"}
    assert check_pngs(img, DOC_SIZES) + check_pngs(img, others) < MAX_TOTAL_BYTES
    page = (ROOT / "docs" / "rerun-viewer.md").read_text()
    for name in [*DOC_SIZES, *others]:
        assert f"](img/{name})" in page, name
