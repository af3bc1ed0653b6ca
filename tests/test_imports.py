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


#: the layers, bottom up: a package imports only from its own layer's declared neighbours and from below. protocol is
#: the wire contract; runtime what every service runs on; model the arms and their geometry (pure); then the
#: services, each with the other services it is built on; then the orchestration, each of its folders with the
#: others it is built on; the command line and bench may import anything. ``paths`` (where the repository's folders
#: are) is a leaf anyone may use.
BASE = {"protocol": set(), "services.paths": set(), "services.runtime": {"protocol"},
        "services.model": {"protocol", "services.runtime"}}
#: a service package and the other service packages it may import, with why
SERVICES = {
    "services.robot": set(),
    "services.robot_sim": {"services.robot"},        # the robot node on the simulated arm
    "services.robot_gateway": {"services.robot"},    # the robot node on a real arm's bus
    "services.vision": {"services.controller"},     # the teach's client moves the camera by the controller's task
    "services.controller": set(),
    "services.safety": set(),
    "services.camera": set(),
    "services.observe": set(),
    "services.tools": set(),
    "services.torque_controller": {"services.controller", "services.robot"},  # the torque laws; the bus cycle
    # the task, the e-stop, the frames, the teach, the person's stick (its mapping and stamps)
    "services.console": {"services.controller", "services.safety", "services.observe", "services.vision",
                         "services.jog"},
    "services.calibration": {"services.camera", "services.robot_sim"},  # the camera's files; the simulated rig
    # the task and the e-stop as `mfvs task` and `mfvs estop` reach them; the frames `mfvs view` names; a ROS 2
    # stick's mapping and stamps
    "services.ros2_bridge": {"services.controller", "services.safety", "services.observe", "services.jog"},
    "services.jog": {"services.controller"},         # the stick's resume button asks the controller's task
}

#: the orchestration's folders (what starts, runs and reports the services) and the others each is built on; any of
#: them may import every service package
ORCHESTRATION = {
    "services.stack": set(),                                         # starting a stack: profiles, processes
    "services.servo": {"services.stack"},                            # one servo task on a stack
    "services.experiments": {"services.servo", "services.stack"},    # the papers' experiments: many servo tasks
    "services.commissioning": {"services.stack"},                    # `mfvs check`, `mfvs doctor`
}
#: the top: parses the command line and calls any of the above
TOP = {"services.cli", "bench"}


def package_of(module: str) -> str:
    """The layer package a module belongs to (services.<package>, protocol or bench; a module directly in services/
    is its own)."""
    parts = module.split(".")
    if parts[0] in ("protocol", "bench"):
        return parts[0]
    return ".".join(parts[:2])


def allowed(importer: str) -> set[str] | None:
    """The packages ``importer`` may import besides its own (None: anything, the top)."""
    below = {"protocol", "services.paths"}
    if importer in BASE:
        return BASE[importer] | {"services.paths"} | set().union(*(BASE[b] for b in BASE[importer]))
    if importer in SERVICES:
        return below | {"services.runtime", "services.model"} | SERVICES[importer]
    if importer in ORCHESTRATION:
        return below | set(BASE) | set(SERVICES) | ORCHESTRATION[importer]
    if importer in TOP:
        return None
    return set()  # a module in no layer may import nothing: give it its place above


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    out = []
    for module, imported in sorted(graph.items()):
        importer = package_of(module)
        permitted = allowed(importer)
        if permitted is None:
            continue
        for target in sorted(imported):
            package = package_of(target)
            if package != importer and package not in permitted:
                out.append(f"{module} imports {target} ({importer} may import {', '.join(sorted(permitted))})")
    return out


def test_every_package_imports_only_from_its_layer_and_below():
    """issue 47: runtime does not reach into the robot, the geometry safety shares with the robot's DSP is the
    model's, a service does not import the launcher, and no service package imports another unless declared
    above with the reason."""
    assert layer_violations(import_graph()) == []


def test_every_service_package_has_its_place_in_the_layers():
    """Every folder of services/ has its place, and nothing else sits directly in services/ but where the
    repository's folders are (``paths``): the orchestration is in folders by role."""
    packages = {f"services.{d.name}" for d in (REPO / "services").iterdir()
                if d.is_dir() and any(d.glob("*.py"))}  # (namespace packages too: runtime, observe)
    assert packages == (set(BASE) | set(SERVICES) | set(ORCHESTRATION) | TOP) - {"protocol", "services.paths", "bench"}
    loose = {p.name for p in (REPO / "services").glob("*.py")}
    assert loose == {"__init__.py", "paths.py"}


def test_the_layer_check_sees_a_violation():
    graph = {"services.runtime.service": {"services.robot.node"}, "services.console.service": {"services.stack.local"},
             "services.safety.checks": {"services.model.zones"}, "services.stack.local": {"services.robot.node"},
             "services.stack.launcher": {"services.servo.run"}, "services.servo.run": {"services.cli.options"},
             "services.experiments.pool": {"services.servo.run", "services.stack.warm_start"}}
    violations = layer_violations(graph)
    assert [v.split(" (")[0] for v in violations] == [
        "services.console.service imports services.stack.local",
        "services.runtime.service imports services.robot.node",
        "services.servo.run imports services.cli.options",  # the orchestration does not import the command line
        "services.stack.launcher imports services.servo.run"]  # starting a stack knows nothing of servo tasks
    assert violations[1].endswith("(services.runtime may import protocol, services.paths)")


def test_robot_sim_in_api_mode_loads_no_python_can():
    """python-can (13 MB resident) is the actuator_bus mode's: robot_sim imports the bus module for its config in
    every mode, and python-can comes with the first bus opened."""
    import subprocess
    import sys

    probe = ("import sys, services.robot_sim.service; assert 'can' not in sys.modules; "
             "from services.robot.rs485_bus import BusConfig, RS485Bus; RS485Bus(BusConfig(channel='probe')).close(); "
             "assert 'can' in sys.modules")
    subprocess.run([sys.executable, "-c", probe], cwd=REPO, check=True, timeout=120)
