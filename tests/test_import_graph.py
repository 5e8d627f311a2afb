"""The import graph flows one way (radar <- models <- pipelines; service <- models + radar) with no cycle, and the
wings of ``pipelines/`` import downward only (datasets <- inference <- recordings <- evaluation <- training <- demo;
the top-level modules other than the CLI below every wing), counting imports inside functions too: read from the
source with ast, so nothing is imported to check."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("radar", "models", "pipelines", "service")
ALLOWED = {  # package -> the packages of ours it may import
    "radar": {"radar"},
    "models": {"radar", "models"},
    "pipelines": {"radar", "models", "pipelines"},
    "service": {"radar", "models", "service"},
}
WINGS = ("datasets", "inference", "recordings", "evaluation", "training", "demo")  # pipelines' wings, lowest first
TOP_OF_PIPELINES = "pipelines.cli"  # the one top-level package above the wings (the command line)


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """module -> the modules of ours it imports (anywhere in the file), resolved to existing modules."""
    files = {_module_name(p): p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                candidates = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                candidates = [f"{node.module}.{alias.name}" for alias in node.names] + [node.module]
            else:
                continue
            for candidate in candidates:
                while candidate and candidate not in files:  # a name inside a module: its module
                    candidate = candidate.rpartition(".")[0]
                if candidate and candidate != name:
                    targets.add(candidate)
                    break
        graph[name] = targets
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of module imports, or None (iterative depth-first search)."""
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    for root in sorted(graph):
        if state.get(root):
            continue
        stack, path = [(root, iter(sorted(graph[root])))], [root]
        state[root] = 1
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                state[node] = 2
                stack.pop()
                path.pop()
            elif state.get(child) == 1:
                return path[path.index(child):] + [child]
            elif not state.get(child):
                state[child] = 1
                stack.append((child, iter(sorted(graph.get(child, ())))))
                path.append(child)
    return None


def test_no_import_cycle_even_inside_functions():
    cycle = find_cycle(import_graph())
    assert cycle is None, " -> ".join(cycle)


def test_imports_flow_one_way_between_packages():
    wrong = sorted(f"{module} imports {target}" for module, targets in import_graph().items()
                   for target in targets if target.split(".")[0] not in ALLOWED[module.split(".")[0]])
    assert not wrong, wrong


def pipelines_level(module: str) -> int:
    """0 for a top-level module of ``pipelines`` (jobs, progress, figures), 1 + the wing's index inside a wing,
    one above the highest wing for the CLI."""
    parts = module.split(".")
    if module == TOP_OF_PIPELINES or module.startswith(f"{TOP_OF_PIPELINES}."):  # the CLI and its command groups
        return len(WINGS) + 1
    return 1 + WINGS.index(parts[1]) if len(parts) > 2 and parts[1] in WINGS else 0


def wrong_way_wing_imports(graph: dict[str, set[str]]) -> list[str]:
    return sorted(f"{module} imports {target}" for module, targets in graph.items() if module.startswith("pipelines")
                  for target in targets if target.startswith("pipelines.")
                  and pipelines_level(target) > pipelines_level(module))


def test_wings_of_pipelines_import_downward_only():
    wrong = wrong_way_wing_imports(import_graph())
    assert not wrong, wrong


def test_the_wing_checker_sees_an_upward_import():
    graph = {"pipelines.evaluation.compare": {"pipelines.training.baselines", "pipelines.datasets.store"},
             "pipelines.jobs": {"pipelines.cli"}, "pipelines.cli": {"pipelines.demo.demo"}}
    assert wrong_way_wing_imports(graph) == ["pipelines.evaluation.compare imports pipelines.training.baselines",
                                             "pipelines.jobs imports pipelines.cli"]


def test_the_checker_sees_a_cycle_and_a_function_level_import(tmp_path):
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    graph = import_graph()
    assert "models.channel_surgery" in graph["models.detector.centre_detector"]


# The rooms of models/ and radar/ (a subfolder, or a top-level module) floor by floor, lowest first: a room imports
# only rooms on lower floors. "*" stands for every top-level module not named elsewhere; those may import each other
# (the cycle test above still holds them), the named rooms of one floor may not.
FLOORS = {
    "models": (("*",), ("sparse",), ("channel_surgery",), ("detector", "segmenter", "baselines"), ("slimming",),
               ("erasenet",), ("export",), ("quantized",), ("runtime",)),
    "radar": (("errors",), ("profiles",), ("*",), ("simulate", "ti", "recorders"), ("io",), ("growing_sweep",)),
    # a request's way down: the server, the app factory, the routes, the app's state, then streams, accounting and
    # the inputs, the model pool and the settings among the loose modules, and what every answer is made of (http)
    "service": (("http",), ("*",), ("inputs", "protocols"), ("accounting",), ("streams",), ("deps",), ("routes",),
                ("main",), ("server",), ("__main__",)),
}
SERVICE_TOP_MODULES = 12  # at most, __init__ included: the rest lives in rooms by concern


def room_floor(package: str, room: str) -> int:
    floors = FLOORS[package]
    for level, rooms in enumerate(floors):
        if room in rooms:
            return level
    return next(level for level, rooms in enumerate(floors) if "*" in rooms)


def wrong_way_room_imports(graph: dict[str, set[str]], package: str) -> list[str]:
    """Imports between two rooms of ``package`` that do not go to a lower floor."""
    wrong = []
    for module, targets in graph.items():
        parts = module.split(".")
        if parts[0] != package or len(parts) < 2:
            continue
        for target in targets:
            target_parts = target.split(".")
            if target_parts[0] != package or len(target_parts) < 2 or target_parts[1] == parts[1]:
                continue
            here, there = room_floor(package, parts[1]), room_floor(package, target_parts[1])
            both_loose = "*" in FLOORS[package][here] and parts[1] not in FLOORS[package][here]
            both_loose = both_loose and "*" in FLOORS[package][there] and target_parts[1] not in FLOORS[package][there]
            if there > here or (there == here and not both_loose):
                wrong.append(f"{module} imports {target}")
    return sorted(wrong)


def test_rooms_of_models_radar_and_service_import_downward_only():
    graph = import_graph()
    wrong = [line for package in FLOORS for line in wrong_way_room_imports(graph, package)]
    assert not wrong, wrong


def test_the_top_of_service_holds_few_modules():
    top = sorted(p.name for p in (REPO / "service").glob("*.py"))
    assert len(top) <= SERVICE_TOP_MODULES, top


def test_every_room_is_on_a_floor_or_loose():
    """A new subfolder must be given its floor: only top-level modules may stand for "*"."""
    for package, floors in FLOORS.items():
        named = {room for rooms in floors for room in rooms}
        folders = {p.name for p in (REPO / package).iterdir() if (p / "__init__.py").is_file()}
        assert folders <= named, f"{package}: subfolders with no floor: {sorted(folders - named)}"
        stale = {room for room in named - {"*"} if not (REPO / package / room).is_dir()
                 and not (REPO / package / f"{room}.py").is_file()}
        assert not stale, f"{package}: floors name rooms that are gone: {sorted(stale)}"


def test_the_room_checker_sees_mutual_and_same_floor_imports():
    graph = {"models.detector.a": {"models.slimming.b", "models.sparse.c"}, "models.slimming.b": {"models.detector.a"},
             "models.segmenter.d": {"models.detector.a"}, "models.heap": {"models.layers"}}
    assert wrong_way_room_imports(graph, "models") == ["models.detector.a imports models.slimming.b",
                                                       "models.segmenter.d imports models.detector.a"]
