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
TOP_OF_PIPELINES = "pipelines.cli"  # the one top-level module above the wings


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
    if module == TOP_OF_PIPELINES:
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
    assert "models.slimming.channel_surgery" in graph["models.detector.centre_detector"]
