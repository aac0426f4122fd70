"""The import graph of dragd/ and sim/: no circles in either, the layers docs/ARCHITECTURE.md draws, and a daemon
whose parts never reach back to it.

Every import counts: at module level, inside functions and under ``TYPE_CHECKING`` (a circle of type imports is
still two modules that cannot be read, tested or changed one without the other). Read from the source (ast), so a
module that cannot be imported here (the ROS 2 node without rclpy) is judged too.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]


def _modules() -> dict[str, Path]:
    out = {}
    for root in ("dragd", "sim"):
        for p in (REPO / root).rglob("*.py"):
            parts = p.relative_to(REPO).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def import_graph() -> dict[str, set[str]]:
    """module -> the modules of dragd/ and sim/ it imports (``from pkg import mod`` names the module ``pkg.mod``;
    ``from pkg import name`` the package)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for m, path in mods.items():
        package = m if path.name == "__init__.py" else m.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]
            else:
                continue
            graph[m].update(n for n in names if n in mods and n != m)
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_the_circle_finder_finds_a_circle_of_type_imports() -> None:
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert circles(g) == [["a", "b", "c"]]
    assert circles({"a": {"b"}, "b": set()}) == []


@pytest.mark.parametrize("root", ["dragd", "sim"])
def test_no_import_circles(root: str) -> None:
    graph = import_graph()
    found = circles({m: {d for d in deps if d.startswith(root)}
                     for m, deps in graph.items() if m.startswith(root)})
    assert not found, "import circles (each a set of modules that import each other, type imports included): " + \
        "; ".join(" ↔ ".join(c) for c in found)


def test_the_layers_hold() -> None:
    graph = import_graph()
    wrong = []
    for m, deps in sorted(graph.items()):
        for d in sorted(deps):
            if m.startswith("dragd") and d.startswith("sim"):
                wrong.append(f"{m} imports {d} (the simulator's truth is never dragd's)")
            if m.startswith("dragd.control") and d.startswith(("dragd.hardware", "dragd.daemon")):
                wrong.append(f"{m} imports {d} (the control law knows no bus and no daemon)")
            if m.startswith("dragd.hardware") and d.startswith("dragd.daemon"):
                wrong.append(f"{m} imports {d} (the hardware side knows no daemon)")
    assert not wrong, "\n".join(wrong)


def test_the_daemons_parts_are_built_with_what_they_use_never_the_daemon() -> None:
    """Only the command table (the control socket's adapter, given the daemon to serve) names the Daemon."""
    graph = import_graph()
    reach_back = sorted(m for m, deps in graph.items() if "dragd.daemon.core" in deps
                        and m.startswith("dragd.daemon.") and m != "dragd.daemon.commands")
    assert not reach_back, f"daemon parts that import dragd/daemon/core.py: {reach_back}"


def test_the_daemon_never_imports_scipy() -> None:
    """The daemon's modules (and what they import, lazily included: every module of dragd/daemon, dragd/hardware,
    dragd/control, dragd/teach/program) leave scipy out of the 1 kHz process: its extension modules and OpenBLAS
    threads beside the cycle (the planner's splines run in dragd/teach/worker.py's process). A type shared with
    the planner once pulled scipy.interpolate in through dragd/teach/program.py."""
    import subprocess
    import sys

    code = ("import importlib, pkgutil, sys\n"
            "import dragd.daemon, dragd.hardware, dragd.control\n"
            "for pkg in (dragd.daemon, dragd.hardware, dragd.control):\n"
            "    for m in pkgutil.iter_modules(pkg.__path__):\n"
            "        importlib.import_module(f'{pkg.__name__}.{m.name}')\n"
            "import dragd.teach.program, dragd.__main__\n"
            "print(sorted(n for n in sys.modules if n == 'scipy' or n.startswith('scipy.')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", f"scipy modules imported by the daemon's modules: {out.stdout.strip()}"
