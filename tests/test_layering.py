"""The layout's import rules, read from the source (every import, also those inside functions).

- ``drivers`` never imports ``depthnav_daemon``.
- ``pipeline`` (the stages) imports nothing of the daemon, sinks, config, commands, tools or the
  drivers' I/O modules: only ``depthnav_daemon.errors``, itself and ``drivers.base``.
- sinks never import stage modules (scan, cliff, pose, their kernels, the mount planner): what
  they show comes on the Result. ``pipeline`` (for the Result type) and ``pipeline.geometry``
  (the frame conventions) are allowed.
- only the CLI and the commands import ``depthnav_daemon.commands``.
And in a fresh interpreter, importing the pipeline loads no device, viewer or plotting library.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "depthnav_daemon"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _runtime_nodes(tree: ast.AST) -> list[ast.AST]:
    """Every node except those under ``if TYPE_CHECKING:`` (annotations only, never run)."""
    out: list[ast.AST] = []
    todo = [tree]
    while todo:
        node = todo.pop()
        out.append(node)
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and getattr(child.test, "id", "") == "TYPE_CHECKING":
                todo.extend(child.orelse)
                continue
            todo.append(child)
    return out


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports when it runs, as absolute names (``from x import y`` gives
    x and x.y); imports for type annotations only are left out."""
    tree = ast.parse(path.read_text(), str(path))
    here = _module_name(path).split(".")
    if path.name != "__init__.py":
        here = here[:-1]
    out: set[str] = set()
    for node in _runtime_nodes(tree):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(here[: len(here) - node.level + 1] + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{alias.name}" for alias in node.names)
    return out


def _sources(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.py") if "__pycache__" not in p.parts)


def _violations(folder: Path, allowed) -> list[str]:
    bad = []
    for path in _sources(folder):
        for name in sorted(_imports(path)):
            if not allowed(name):
                bad.append(f"{path.relative_to(ROOT)} imports {name}")
    return bad


def _ours(name: str) -> bool:
    return name.split(".", maxsplit=1)[0] in ("depthnav_daemon", "drivers")


def test_the_rule_reader_sees_imports_inside_functions_and_relative_ones(tmp_path: Path) -> None:
    pkg = ROOT / "depthnav_daemon" / "pipeline" / "scan.py"  # a real file: absolute imports
    assert "depthnav_daemon.pipeline.geometry" in _imports(pkg)
    assert "depthnav_daemon.pipeline.scan_paper" in _imports(pkg)  # imported inside a function
    fake = PACKAGE / "sinks" / "_layering_probe.py"
    fake.write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from ..pipeline.pose import PoseEstimate\n"
        "def f():\n    from .. import daemon\n    from ..pipeline import scan\n"
    )
    try:
        found = _imports(fake)
    finally:
        fake.unlink()
    assert {"depthnav_daemon.daemon", "depthnav_daemon.pipeline.scan"} <= found
    assert "depthnav_daemon.pipeline.pose" not in found  # annotations only


def test_drivers_never_import_depthnav_daemon() -> None:
    assert _violations(ROOT / "drivers", lambda n: n.split(".")[0] != "depthnav_daemon") == []


def test_pipeline_imports_only_itself_errors_and_driver_types() -> None:
    def allowed(name: str) -> bool:
        if not _ours(name):
            return True
        return (
            name.startswith("depthnav_daemon.pipeline")
            or name in ("depthnav_daemon.errors", "drivers.base")
            or name.startswith(("depthnav_daemon.errors.", "drivers.base."))
        )

    assert _violations(PACKAGE / "pipeline", allowed) == []


STAGE_MODULES = (
    "scan",
    "scan_paper",
    "scan_table",
    "cliff",
    "cliff_table",
    "pose",
    "pose_fit",
    "mount_planner",
)


def test_sinks_never_import_stage_code() -> None:
    def allowed(name: str) -> bool:
        parts = name.split(".")
        if parts[:2] != ["depthnav_daemon", "pipeline"] or len(parts) == 2:
            return not name.startswith(("depthnav_daemon.daemon", "depthnav_daemon.commands"))
        stage = parts[2]
        return stage == "geometry" or (
            stage not in STAGE_MODULES and not stage.endswith("_kernels") and stage[0].isupper()
        )

    assert _violations(PACKAGE / "sinks", allowed) == []


@pytest.mark.parametrize("folder", ["pipeline", "sinks", "daemon", "config", "sim", "tools"])
def test_only_the_cli_and_commands_import_commands(folder: str) -> None:
    def allowed(name: str) -> bool:
        return not name.startswith("depthnav_daemon.commands")

    assert _violations(PACKAGE / folder, allowed) == []


def test_importing_the_pipeline_loads_no_device_viewer_or_plot_library() -> None:
    code = (
        "import sys, depthnav_daemon.pipeline, depthnav_daemon.pipeline.pose, "
        "depthnav_daemon.pipeline.mount_planner\n"
        "bad = [m for m in ('openni', 'usb', 'serial', 'rerun', 'pymavlink', 'matplotlib', "
        "'PIL') if m in sys.modules]\n"
        "print(','.join(bad))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert proc.stdout.strip() == ""


def test_depthnav_run_loads_no_plot_library(tmp_path: Path) -> None:
    """The daemon with every drawing sink there is (the rerun file sink shares the figures'
    overlay geometry) never imports matplotlib: it is the optional ``plot`` extra."""
    rrd = tmp_path / "run.rrd"
    fixture = ROOT / "fixtures" / "corridor_step"
    code = (
        "import sys\n"
        "from depthnav_daemon.cli import main\n"
        f"rc = main(['-q', 'run', '--device', 'replay:{fixture}', '--sink', 'null', "
        f"'--sink', 'rerun:{rrd}', '--max-frames', '2'])\n"
        "print(rc, [m for m in sys.modules if m.split('.')[0] == 'matplotlib'])"
    )
    env = {**os.environ, "HOME": str(tmp_path)}  # rerun's config stays out of the real home
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env, check=True
    )
    assert proc.stdout.split() == ["0", "[]"], proc.stderr
    assert rrd.stat().st_size > 0
