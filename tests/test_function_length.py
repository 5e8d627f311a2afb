"""No function of ``radar/``, ``models/``, ``pipelines/``, ``service/`` or ``process/`` is longer than
:data:`MAX_LINES` lines: a long one is split along its seams. Measured with ``ast`` (from ``def`` to the last
line of the body, decorators excluded); ``python -m tests.test_function_length`` lists the longest."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("process", "radar", "models", "pipelines", "service")
MAX_LINES = 80


def function_lengths(packages: tuple[str, ...] = PACKAGES, *, root: Path = ROOT) -> list[tuple[int, str]]:
    """``(lines, "path:line name")`` of every function and method under ``root``'s ``packages``, longest first."""
    found = []
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    lines = node.end_lineno - node.lineno + 1
                    found.append((lines, f"{path.relative_to(root)}:{node.lineno} {node.name}"))
    return sorted(found, reverse=True)


def test_the_checker_finds_nested_functions_and_methods_in_subpackages(tmp_path):
    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    (tmp_path / "pkg" / "sub" / "mod.py").write_text(
        "class C:\n    @property\n    def m(self):\n        def inner():\n            return 1\n\n"
        "        return inner()\n")
    assert function_lengths(("pkg",), root=tmp_path) == [(5, "pkg/sub/mod.py:3 m"), (2, "pkg/sub/mod.py:4 inner")]


def test_no_function_is_over_the_limit():
    long = [f"{where} ({lines} lines)" for lines, where in function_lengths() if lines > MAX_LINES]
    assert not long, f"functions over {MAX_LINES} lines: {long}"


if __name__ == "__main__":
    for lines, where in function_lengths()[: int(sys.argv[1]) if len(sys.argv) > 1 else 15]:
        print(f"{lines:4d}  {where}")
