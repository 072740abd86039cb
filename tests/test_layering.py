"""The layout's import rules, read from the source (every import, also those inside functions).

- ``drivers`` never imports ``depthnav_daemon``.
- ``pipeline`` (the stages) imports nothing of the daemon, sinks, config, commands, tools or the
  drivers' I/O modules: only ``depthnav_daemon.errors``, itself and ``drivers.base``.
- sinks never import stage modules (scan, cliff, pose, their kernels, the mount planner): what
  they show comes on the Result. ``pipeline`` (for the Result type) and ``pipeline.geometry``
  (the frame conventions) are allowed.
- only the CLI and the commands import ``depthnav_daemon.commands``.
- no two modules of ``depthnav_daemon`` and ``drivers`` import each other, directly or round a
  longer loop (``test_no_import_circles_between_modules`` says how a package's __init__ counts).
And in a fresh interpreter, importing the pipeline loads no device, viewer or plotting library.
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "depthnav_daemon"


def _module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
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


def _import_statements(path: Path, root: Path = ROOT) -> Iterator[tuple[str, tuple[str, ...]]]:
    """(module, names) of every import ``path`` runs, the module absolute: ``import x.y`` gives
    ("x.y", ()), ``from x import y, z`` gives ("x", ("y", "z")); annotation-only ones are left
    out."""
    tree = ast.parse(path.read_text(), str(path))
    here = _module_name(path, root).split(".")
    if path.name != "__init__.py":
        here = here[:-1]
    for node in _runtime_nodes(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, ()
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(here[: len(here) - node.level + 1] + ([base] if base else []))
            yield base, tuple(alias.name for alias in node.names)


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports when it runs, as absolute names (``from x import y`` gives
    x and x.y); imports for type annotations only are left out."""
    out: set[str] = set()
    for base, names in _import_statements(path):
        out.add(base)
        out.update(f"{base}.{name}" for name in names)
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
    assert "depthnav_daemon.pipeline.scan_paper" in _imports(pkg)
    experiment = PACKAGE / "sim" / "paper_experiment.py"
    assert "depthnav_daemon.plots.experiment" in _imports(experiment)  # inside a function
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


# pipeline.params and pipeline.laser_scan hold data types only, no stage code; sinks name them in
# annotations only (under TYPE_CHECKING, which these rules skip), and the rule below admits no
# pipeline module but geometry at run time anyway.
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


# import circles ----------------------------------------------------------------------------------


def _module_named(name: str, root: Path = ROOT) -> str:
    """The module whose file ``name`` names: ``x.y.z`` itself if x/y/z.py or x/y/z/__init__.py
    exists, else the nearest parent that does (``x.y.SomeClass`` names ``x.y``)."""
    parts = name.split(".")
    while len(parts) > 1:
        stem = root.joinpath(*parts)
        if stem.with_suffix(".py").is_file() or (stem / "__init__.py").is_file():
            break
        parts.pop()
    return ".".join(parts)


def _runtime_edges(path: Path, root: Path = ROOT) -> set[str]:
    """The modules ``path`` names in the imports it runs: ``import a.b`` names a.b; ``from a.b
    import c`` names a.b.c if that is a module, else a.b (c is then a name a.b defines)."""
    out: set[str] = set()
    for base, names in _import_statements(path, root):
        if not names:
            out.add(_module_named(base, root))
        out.update(_module_named(f"{base}.{name}", root) for name in names)
    return out


def _import_graph(
    root: Path = ROOT, tops: tuple[str, ...] = ("depthnav_daemon", "drivers")
) -> dict[str, set[str]]:
    """Every module under ``tops`` -> the modules under ``tops`` it imports when it runs."""
    files = [path for top in tops for path in _sources(root / top)]
    nodes = {_module_name(path, root) for path in files}
    graph: dict[str, set[str]] = {}
    for path in files:
        me = _module_name(path, root)
        # a package's __init__ naming itself (``from . import name``) is no circle
        graph[me] = {m for m in _runtime_edges(path, root) if m in nodes and m != me}
    return graph


def _cycles(graph: Mapping[str, Iterable[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, without
    recursion), each sorted, in sorted order: every import circle lies inside one of them."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> Iterator[str]:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        return iter(sorted(graph.get(node, ())))

    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, visit(start))]
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    work.append((child, visit(child)))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:  # every child seen: node is done
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:  # node roots a component: it is on the stack
                    component = []
                    while not component or component[-1] != node:
                        component.append(stack.pop())
                        on_stack.discard(component[-1])
                    if len(component) > 1:
                        found.append(sorted(component))
    return sorted(found)


def _a_circle(graph: Mapping[str, Iterable[str]], component: list[str]) -> list[str]:
    """A shortest circle through the component's first module, as the path that ends where it
    begins (what a failure message shows beside the component)."""
    start, inside = component[0], set(component)
    came_from: dict[str, str] = {}
    frontier = [start]
    while frontier:
        reached = []
        for node in frontier:
            for child in sorted(graph.get(node, ())):
                if child == start:
                    path = [node]
                    while path[-1] != start:
                        path.append(came_from[path[-1]])
                    return [*reversed(path), start]
                if child in inside and child not in came_from:
                    came_from[child] = node
                    reached.append(child)
        frontier = reached
    return component


def test_the_cycle_finder_finds_a_three_cycle_and_nothing_else() -> None:
    graph = {
        "a": {"b"},
        "b": {"c", "x"},
        "c": {"a"},  # a -> b -> c -> a
        "tail": {"a"},  # reaches the circle but is not on it
        "x": {"y", "z"},  # a diamond: two ways to z, no way back
        "y": {"z"},
        "z": set(),
    }
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _a_circle(graph, ["a", "b", "c"]) == ["a", "b", "c", "a"]
    assert _cycles({k: v - {"a"} for k, v in graph.items()}) == []  # c -> a gone: no circle
    two = {"p": {"q"}, "q": {"p", "r"}, "r": {"s"}, "s": {"r"}}  # two circles, one edge between
    assert _cycles(two) == [["p", "q"], ["r", "s"]]


def test_the_import_graph_counts_a_package_init_only_where_it_is_named(tmp_path: Path) -> None:
    """``from pkg.sub import Name`` (a name the __init__ defines) is an edge to pkg.sub's __init__:
    with the __init__ importing the module back, that is a circle (the name may not exist yet).
    ``from pkg.sub import module`` and ``from pkg.sub.module import x`` name the module only:
    Python runs pkg.sub's __init__ on the way, but finishes the module even while the __init__
    is half done, so that is no circle."""
    sub = tmp_path / "pkg" / "sub"
    sub.mkdir(parents=True)
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (sub / "__init__.py").write_text(
        "from pkg.sub.stage import run\nfrom pkg.sub import fine, finer\nclass Result: ...\n"
    )
    (sub / "stage.py").write_text("def run():\n    from pkg.sub import Result\n")
    (sub / "fine.py").write_text("from pkg.sub import helper\n")
    (sub / "finer.py").write_text("from pkg.sub.helper import X\nfrom . import helper\n")
    (sub / "helper.py").write_text("X = 1\n")
    graph = _import_graph(tmp_path, ("pkg",))
    assert graph["pkg.sub.fine"] == {"pkg.sub.helper"}
    assert graph["pkg.sub.finer"] == {"pkg.sub.helper"}
    assert _cycles(graph) == [["pkg.sub", "pkg.sub.stage"]]


def test_no_import_circles_between_modules() -> None:
    """No module of depthnav_daemon/ or drivers/ imports, when it runs (at the top or inside a
    function; ``if TYPE_CHECKING:`` blocks aside), a module that imports it back, directly or
    round a longer loop. An edge goes to the module an import names: ``from a.b import c`` to
    a.b.c if that is a module, else to a.b (its __init__). So a stage importing a name from its
    own package's __init__, which imports the stage, IS a circle; importing a sibling module
    (which runs the package's __init__ on the way) is not."""
    graph = _import_graph()
    circles = [f"{', '.join(c)} (e.g. {' -> '.join(_a_circle(graph, c))})" for c in _cycles(graph)]
    assert circles == [], "import circles:\n" + "\n".join(circles)


# --- the tree's shape: a newcomer finds each family from the folders ---------------------------

MAX_MODULE_LINES = 500
SINK_FAMILIES = ("json", "mavlink", "rerun", "ros")


def test_no_module_is_over_500_lines() -> None:
    sizes = {
        p.relative_to(ROOT): len(p.read_text().splitlines())
        for folder in (PACKAGE, ROOT / "drivers")
        for p in _sources(folder)
    }
    assert {p: n for p, n in sizes.items() if n > MAX_MODULE_LINES} == {}


def test_sinks_are_grouped_by_family() -> None:
    """``sinks/`` keeps its registry, ``base`` and the one-module sinks; each family of several
    modules is a subpackage, and every registered sink lives in its family's folder."""
    from depthnav_daemon.sinks import SINKS

    sinks = PACKAGE / "sinks"
    modules = sorted(p.name for p in sinks.glob("*.py"))
    packages = sorted(p.name for p in sinks.iterdir() if (p / "__init__.py").is_file())
    assert len(modules) <= 8, modules
    assert packages == sorted(SINK_FAMILIES)
    for scheme, (module, _) in SINKS.items():
        parts = module.split(".")  # depthnav_daemon.sinks[.family].module
        assert parts[:2] == ["depthnav_daemon", "sinks"] and len(parts) in (3, 4), scheme
        assert len(parts) == 3 or parts[2] in SINK_FAMILIES, scheme


def test_process_takes_the_frame_the_mount_state_the_params_and_a_clock() -> None:
    """The mount, its source, its trust and the floor estimate travel as one MountState."""
    import inspect

    from depthnav_daemon.pipeline import process

    names = list(inspect.signature(process).parameters)
    assert names == ["frame", "mount_state", "params", "clock"]
