"""Each job's defaults are written once, in its config dataclass: an option whose destination is a config field takes
its default from there (``pipelines.jobs.field_defaults``), never as a literal beside it, and parses to it."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import typing
from pathlib import Path

import pytest

from pipelines.cli import JOBS
from pipelines.jobs import job_parser
from pipelines.training import arguments


def _configs(module) -> dict[str, dataclasses.Field]:
    returned = typing.get_type_hints(module.config_from_args)["return"]
    fields: dict[str, dataclasses.Field] = {}
    for config in typing.get_args(returned) or (returned,):
        fields.update({f.name: f for f in dataclasses.fields(config) if f.default is not dataclasses.MISSING})
    return fields


def _actions(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found += _actions(sub)
        else:
            found.append(action)
    return found


def _literal_defaults(path: Path) -> list[tuple[int, str]]:
    """(line, destination) of every ``add_argument(..., default=<literal>)`` in ``path``."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
            keywords = {k.arg: k.value for k in node.keywords}
            options = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
            dest = keywords["dest"].value if isinstance(keywords.get("dest"), ast.Constant) else next(
                (o.lstrip("-").replace("-", "_") for o in options if o.startswith("--")), None)
            if "default" in keywords:
                try:
                    ast.literal_eval(keywords["default"])
                except ValueError:
                    continue
                found.append((node.lineno, dest))
    return found


@pytest.mark.parametrize("command", sorted(JOBS))
def test_no_option_writes_its_configs_default_again(command):
    module = importlib.import_module(JOBS[command].module)
    fields = _configs(module)
    job = JOBS[command]
    sources = {Path(inspect.getsourcefile(importlib.import_module(name))) for name in (job.module, job.options)}
    if command in ("train", "train-baseline"):
        sources.add(Path(inspect.getsourcefile(arguments)))
    twice = [f"{path.name}:{line} --{dest.replace('_', '-')}" for path in sources
             for line, dest in _literal_defaults(path) if dest in fields]
    assert not twice, f"defaults written beside their config's (take them from field_defaults): {twice}"


@pytest.mark.parametrize("command", sorted(JOBS))
def test_every_option_named_after_a_config_field_parses_to_its_default(command):
    module = importlib.import_module(JOBS[command].module)
    fields = _configs(module)
    for action in _actions(job_parser(module, f"radarseg {command}")):
        field = fields.get(action.dest)
        if field is None or action.default in (None, argparse.SUPPRESS) or isinstance(action.default, bool):
            continue
        default = tuple(action.default) if isinstance(action.default, list) else action.default
        assert default == field.default, f"--{action.dest}: {action.default!r}, its config says {field.default!r}"


def test_the_check_finds_a_literal_default(tmp_path):
    job = tmp_path / "job.py"
    job.write_text('def add_arguments(parser):\n    parser.add_argument("--seed", type=int, default=0)\n'
                   '    parser.add_argument("--split", default=defaults.split)\n')
    assert _literal_defaults(job) == [(2, "seed")]
