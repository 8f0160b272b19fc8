"""Imports run one way: msg_schemas <- node_support <- sim_bridge <- constrained_diffusion_ros,
and the ROS-free core (policy, sampling, zones, planning, runtime) imports neither the simulator
nor ROS; the method (planning and below) does not import the live runtime, nor ask the
operating system.

Every import is read from the source (module level and inside functions alike), so the test
needs neither ROS nor torch to run, and a lazy import cannot hide a dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("msg_schemas", "node_support", "sim_bridge", "constrained_diffusion_ros")
CORE = tuple(f"constrained_diffusion_ros.{layer}"
             for layer in ("policy", "sampling", "zones", "planning", "runtime"))
RUNTIME = "constrained_diffusion_ros.runtime"
# What asks the operating system for processes, priorities, sockets and terminals: the
# runtime's business (runtime/os_scheduling.py and the workers), never the method's.
OPERATING_SYSTEM = ("os", "subprocess", "socket", "fcntl", "termios", "signal", "resource",
                    "multiprocessing")
ROS = ("rclpy", "rcl_interfaces", "builtin_interfaces", "geometry_msgs", "nav_msgs", "std_msgs",
       "std_srvs", "visualization_msgs", "diagnostic_msgs", "ament_index_python")
# What each package may import of the others (the direction of the layers).
ALLOWED = {"msg_schemas": {"msg_schemas"}, "node_support": {"msg_schemas", "node_support"},
           "sim_bridge": {"msg_schemas", "node_support", "sim_bridge"},
           "constrained_diffusion_ros": set(PACKAGES)}


def module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(source: str, module: str, is_package: bool, known: set[str]) -> set[str]:
    """The modules `module` imports: a `from x import y` names x.y when that is a module."""
    found = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against this module's package
                anchor = module.split(".")[: len(module.split(".")) - node.level + is_package]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base)
    return found


def import_graph(root: Path) -> dict[str, set[str]]:
    """module -> the modules it imports, for every module of the three packages under root."""
    files = {module_name(p, root): p for package in PACKAGES for p in (root / package).rglob(
        "*.py")}
    known = set(files)
    return {name: imports_of(path.read_text(), name, path.name == "__init__.py", known)
            for name, path in files.items()}


def violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import against the layering, and every import circle, in words."""
    found = []
    for module, imported in sorted(graph.items()):
        package = module.split(".")[0]
        for target in sorted(imported):
            top = target.split(".")[0]
            if top in PACKAGES and top not in ALLOWED[package]:
                found.append(f"{module} imports {target}: {package} may not import {top}")
            if module.startswith(CORE) and (top in ROS or top == "sim_bridge"
                                            or top in ("msg_schemas", "node_support")):
                found.append(f"{module} imports {target}: the core is ROS-free and simulator-free")
            if module.startswith(CORE) and target.startswith("constrained_diffusion_ros.") \
                    and not target.startswith(CORE):
                found.append(f"{module} imports {target}: the core imports only the core")
            if module.startswith(CORE) and not module.startswith(RUNTIME) \
                    and target.startswith(RUNTIME):
                found.append(f"{module} imports {target}: the method does not import the "
                             f"live runtime")
            if module.startswith("constrained_diffusion_ros.planning") \
                    and top in OPERATING_SYSTEM:
                found.append(f"{module} imports {target}: the operating system is the "
                             f"runtime's")
    found += [f"import circle: {' -> '.join(cycle)}" for cycle in cycles(graph)]
    return found


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One circle per strongly connected group of modules (depth-first search)."""
    edges = {m: sorted(t for t in targets if t in graph and t != m) for m, targets in
             graph.items()}
    found, state = [], {}  # state: 1 on the current path, 2 finished

    def visit(module: str, path: list[str]) -> None:
        state[module] = 1
        for target in edges[module]:
            if state.get(target) == 1:
                found.append([*path[path.index(target):], target])
            elif target not in state:
                visit(target, [*path, target])
        state[module] = 2

    for module in sorted(edges):
        if module not in state:
            visit(module, [module])
    return found


def test_the_package_imports_run_one_way_without_circles() -> None:
    graph = import_graph(REPO)
    assert len(graph) > 40
    assert "constrained_diffusion_ros.planning.planners" in graph[
        "constrained_diffusion_ros.planning.chunk_loop"]
    assert violations(graph) == []


def test_the_check_catches_circles_and_imports_against_the_layers(tmp_path: Path) -> None:
    """The same check on a made-up tree with one fault of each kind: it names every one."""
    sources = {
        "msg_schemas/__init__.py": "",
        "msg_schemas/contract.py": "from sim_bridge import scene\n",
        "sim_bridge/__init__.py": "",
        "sim_bridge/scene.py": "def f():\n    import constrained_diffusion_ros.pusht\n",
        "constrained_diffusion_ros/__init__.py": "",
        "constrained_diffusion_ros/pusht.py": "import sim_bridge.scene\n",
        "constrained_diffusion_ros/zones/__init__.py": "",
        "constrained_diffusion_ros/zones/a.py": "from .b import x\nimport rclpy\n",
        "constrained_diffusion_ros/zones/b.py": "from constrained_diffusion_ros.zones import a\n",
        "constrained_diffusion_ros/planning/__init__.py": "",
        "constrained_diffusion_ros/planning/p.py": "from sim_bridge.scene import WALLS\n"
                                                   "from constrained_diffusion_ros import pusht\n"
                                                   "import os\n"
                                                   "from ..runtime import clock\n",
        "constrained_diffusion_ros/runtime/__init__.py": "",
        "constrained_diffusion_ros/runtime/clock.py": "import os\n",
    }
    for name, text in sources.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    found = "\n".join(violations(import_graph(tmp_path)))
    assert "msg_schemas.contract imports sim_bridge.scene" in found
    assert "sim_bridge.scene imports constrained_diffusion_ros.pusht" in found
    assert "constrained_diffusion_ros.zones.a imports rclpy" in found
    assert "constrained_diffusion_ros.planning.p imports sim_bridge.scene" in found
    assert "constrained_diffusion_ros.planning.p imports constrained_diffusion_ros.pusht" in found
    assert "planning.p imports os: the operating system is the runtime's" in found
    assert "planning.p imports constrained_diffusion_ros.runtime.clock: the method" in found
    assert "runtime.clock imports os" not in found
    assert "import circle: constrained_diffusion_ros.zones.a -> constrained_diffusion_ros.zones.b" \
        " -> constrained_diffusion_ros.zones.a" in found
    assert "import circle: constrained_diffusion_ros.pusht -> sim_bridge.scene -> " \
        "constrained_diffusion_ros.pusht" in found  # through a lazy import, too


def private_uses(source: str) -> list[str]:
    """Names starting with `_` that a module imports from the planning layer, or reads as an
    attribute of anything but `self` (another object's internals)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(
                "constrained_diffusion_ros.planning"):
            found += [f"{node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
        elif isinstance(node, ast.Attribute) and node.attr.startswith("_") \
                and not node.attr.startswith("__") \
                and not (isinstance(node.value, ast.Name) and node.value.id == "self"):
            found.append(ast.unparse(node))
    return found


def test_nodes_use_nothing_private_of_the_planning_layer() -> None:
    nodes = sorted((REPO / "constrained_diffusion_ros" / "nodes").glob("*.py"))
    assert len(nodes) >= 5
    found = {path.name: private_uses(path.read_text()) for path in nodes}
    assert {name: uses for name, uses in found.items() if uses} == {}
    assert private_uses("from constrained_diffusion_ros.planning.x import _hidden\n"
                        "self.loop._ask()\n") == ["constrained_diffusion_ros.planning.x._hidden",
                                                  "self.loop._ask"]


def test_one_chunk_loop_drives_the_evaluation_lockstep_and_the_live_node() -> None:
    """The evaluation's rollout and the policy node (both modes) run `ChunkLoop`; no other
    module keeps an action queue of its own, so there is one replan rule."""
    package = REPO / "constrained_diffusion_ros"
    for driver in ("evaluation/rollout.py", "nodes/policy_node_impl.py",
                   "runtime/live_loop.py"):
        assert "ChunkLoop" in {node.id for node in ast.walk(ast.parse(
            (package / driver).read_text())) if isinstance(node, ast.Name)}, driver
    queue_owners = {path.relative_to(package).as_posix() for path in package.rglob("*.py")
                    if any(isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                           and node.func.id == "ActionQueue"
                           for node in ast.walk(ast.parse(path.read_text())))}
    assert queue_owners == {"planning/chunk_loop.py"}
