"""The project's modules import one another without a cycle: an algorithm never imports its service, and no
import hides inside a function to dodge one (every import statement counts, wherever it stands)."""
import ast
from pathlib import Path
from tests.helpers import REPO

PACKAGES = ("protocol", "services", "bench")


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """The project modules a file imports, wherever the import stands (``from a.b import c`` is a.b.c when c is
    a module, else a.b)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in modules else node.module
                     for alias in node.names]
        else:
            continue
        found.update(name for name in names if name in modules)
    return found


def import_graph() -> dict[str, set[str]]:
    files = {module_name(p): p for package in PACKAGES for p in (REPO / package).rglob("*.py")}
    modules = set(files)
    # a package's __init__ is not a dependency edge of its own submodules' imports
    return {name: imports_of(path, modules) - {name} for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles():
    graph = import_graph()
    assert len(graph) > 50 and "services.controller.laws" in graph["services.controller.service"]
    assert cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_robot_sim_in_api_mode_loads_no_python_can():
    """python-can (13 MB resident) is the actuator_bus mode's: robot_sim imports the bus module for its config in
    every mode, and python-can comes with the first bus opened."""
    import subprocess
    import sys

    probe = ("import sys, services.robot_sim.service; assert 'can' not in sys.modules; "
             "from services.robot.rs485_bus import BusConfig, RS485Bus; RS485Bus(BusConfig(channel='probe')).close(); "
             "assert 'can' in sys.modules")
    subprocess.run([sys.executable, "-c", probe], cwd=REPO, check=True, timeout=120)
