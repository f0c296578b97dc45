"""The package's import graph: no cycle between modules, and no import from a higher layer.

The layers are documented in ``docs/architecture.md``. Every import counts, also those inside a
function or under ``TYPE_CHECKING``: a deferred import is still a dependency.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import networkx as nx

ROOT = Path(__file__).resolve().parents[1] / "kimera_multi_py"

# Lowest first. Packages on one line are peers: they may not import each other.
LAYERS: list[tuple[str, ...]] = [
    ("core",),
    ("comms", "io", "viz"),
    ("mapping",),
    ("frontend", "alignment", "scene_graph", "people"),
    ("pgo",),
    ("mapshare",),
    ("agent",),
    ("server",),
    ("sim",),
    ("eval",),
    ("team",),
    ("workflow",),
    ("cli",),
]
LEVEL = {pkg: i for i, names in enumerate(LAYERS) for pkg in names}
MAX_LINES = 550


def _modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def import_graph() -> nx.DiGraph:
    """Module -> module for every ``kimera_multi_py`` import (package imports resolve to submodules)."""
    mods = _modules()
    graph = nx.DiGraph()
    graph.add_nodes_from(mods)
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    module = ".".join(base + ([node.module] if node.module else []))
                else:
                    module = node.module or ""
                targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in mods else module for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            for target in targets:
                if target in mods and target != name:
                    graph.add_edge(name, target)
    return graph


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_every_package_has_a_layer():
    packages = {_package(m) for m in _modules()} - {""}
    assert packages <= set(LEVEL), f"packages without a layer: {sorted(packages - set(LEVEL))}"


def test_no_import_cycles():
    graph = import_graph()
    graph.remove_nodes_from([n for n in list(graph) if n == "kimera_multi_py"])
    cycles = list(nx.simple_cycles(graph, length_bound=6))
    assert not cycles, f"import cycles: {cycles[:5]}"


def test_layers_point_down():
    wrong = []
    for a, b in import_graph().edges:
        pa, pb = _package(a), _package(b)
        if not pa or not pb or pa == pb:
            continue
        if LEVEL[pb] >= LEVEL[pa]:
            wrong.append(f"{a} -> {b}")
    assert not wrong, "imports from a higher or peer layer:\n" + "\n".join(sorted(wrong))


def test_modules_stay_small():
    long = {str(p.relative_to(ROOT.parent)): n for p in _modules().values()
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_an_agent_process_imports_neither_scipy_stats_nor_matplotlib() -> None:
    """What an agent process loads costs every robot memory and start-up time (docs/performance.md):
    scipy.stats (for a χ² quantile) and matplotlib (pulled in by igraph's drawing package) stay
    out, and matplotlib can still be imported afterwards."""
    code = ("import sys, kimera_multi_py.team.process, kimera_multi_py.cli.main, kimera_multi_py.core.clique as c\n"
            "assert c.igraph.Graph.Full(3).clique_number() == 3\n"
            "print(sorted(m for m in ('scipy.stats', 'matplotlib') if m in sys.modules))\n"
            "import matplotlib\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
