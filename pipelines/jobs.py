"""The job contract: every job of ``pipelines/`` is a module with

- ``add_arguments(parser: argparse.ArgumentParser) -> None``: its options;
- ``config_from_args(args: argparse.Namespace) -> Config``: a frozen config from the parsed options;
- ``main(cfg: Config) -> dict``: the work, returning its figures (as Ray's batch jobs do);
- ``format_result(result: dict) -> str``: what the command line prints afterwards.

``radarseg JOB ...`` (:mod:`pipelines.cli`) and ``python -m pipelines.JOB ...`` (each module's
``__main__`` calls :func:`run_module`) both go through :func:`run_job`, so the two spellings take the
same arguments. A job module is imported only when its command runs: Ray and torch load with the job. Its
options (``add_arguments``, ``config_from_args`` and the config dataclass) are declared in a module that loads
neither torch nor zarr (``preprocess_options`` beside ``preprocess``, which re-exports them; a job module whose work
loads inside ``main`` is its own), so that ``--help`` and a wrong option answer at once
(tests/pipelines/test_help_is_light.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import logging
import shlex
import sys
from collections.abc import Callable, Sequence
from types import ModuleType, SimpleNamespace
from typing import Any

from models.environment import environment
from radar.errors import UserError
from radar.profiles import UnknownPresetError

CONTRACT = ("add_arguments", "config_from_args", "main", "format_result")
OPTIONS = CONTRACT[:2]  # what a job's options module declares

log = logging.getLogger(__name__)


def job_module(name: str, contract: Sequence[str] = CONTRACT) -> ModuleType:
    """Import a job module (``pipelines.datasets.preprocess``) and check that it follows the contract (with
    ``contract=OPTIONS``: a job's options module, ``pipelines.datasets.preprocess_options``)."""
    module = importlib.import_module(name)
    missing = [attr for attr in contract if not callable(getattr(module, attr, None))]
    if missing:
        raise TypeError(f"job module {name} lacks {', '.join(missing)} (see pipelines.jobs)")
    return module


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Every option's help ends with its default (``(default: 8)``), unless it has none to show (None, a flag's
    False) or its help already says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (not action.option_strings or action.default is None or action.default is argparse.SUPPRESS
                or isinstance(action.default, bool) or "default" in text):
            return text
        default = " ".join(map(str, action.default)) if isinstance(action.default, (list, tuple)) else "%(default)s"
        return f"{text} (default: {default})" if default else text


def with_defaults_shown(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``parser`` and every subparser below it formatting help with :class:`DefaultsHelpFormatter`."""
    parser.formatter_class = DefaultsHelpFormatter
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                with_defaults_shown(sub)
    return parser


def _with_json_option(parser: argparse.ArgumentParser) -> None:
    """``--json`` on every leaf parser (a job with subcommands takes it after its subcommand)."""
    subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subparsers:
        parser.add_argument("--json", action="store_true",
                            help="print the result as one JSON line (for machines) instead of the text summary")
    for action in subparsers:
        for sub in action.choices.values():
            _with_json_option(sub)


def field_defaults(config: type) -> SimpleNamespace:
    """The defaults of a config dataclass's fields by name: a job's options take theirs from here
    (``default=defaults.seed``), so each default is written once, in the config (tests/pipelines/test_defaults_once.py).
    """
    return SimpleNamespace(**{f.name: f.default for f in dataclasses.fields(config)
                              if f.default is not dataclasses.MISSING})


def job_parser(module: ModuleType, prog: str, description: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=description or (module.__doc__ or "").split("\n")[0])
    module.add_arguments(parser)
    _with_json_option(parser)
    return with_defaults_shown(parser)


def parse_job_args(module: ModuleType, argv: Sequence[str] | None, prog: str) -> argparse.Namespace:
    """The job's parsed options (exits with argparse's message on bad ones). The namespace also carries
    ``command_line``, the command as typed, for jobs that record it in their report."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = job_parser(module, prog).parse_args(argv)
    args.command_line = shlex.join([*prog.split(), *argv])
    return args


def parse_config(module: ModuleType, argv: Sequence[str] | None, prog: str) -> Any:
    """The job's config from command-line arguments (see :func:`parse_job_args`)."""
    return config_of(module, parse_job_args(module, argv, prog))


def config_of(module: ModuleType, args: argparse.Namespace) -> Any:
    """``module.config_from_args(args)``; a ValueError there is the config refusing an argument: a UserError."""
    try:
        return module.config_from_args(args)
    except ValueError as exc:  # the config refused an argument: the user's mistake, whatever its type
        if isinstance(exc, UserError):
            raise
        raise UserError(str(exc)) from exc


# Smoke mode (RADARSEG_SMOKE=1): every job runs its command on tiny sizes, so that the documented commands run
# as written in seconds (tests/test_documented_commands.py). Each config declares the rule beside the field it
# applies to (``sequences: int | None = smoke(None, cap(4))``): renaming the field keeps its rule.
SMOKE = "smoke"  # the field metadata key of a field's smoke rule: its value -> its value in smoke mode


def smoke(default: Any, rule: Callable[[Any], Any]) -> Any:
    """A config field with ``default`` whose value becomes ``rule(value)`` in smoke mode (:func:`smoke_config`)."""
    return dataclasses.field(default=default, metadata={SMOKE: rule})


def cap(limit: int, *, fill: bool = False) -> Callable[[Any], Any]:
    """Smoke rule: a size capped at ``limit``; with ``fill`` an unset value (None or 0: "all", or "the recipe's")
    becomes ``limit`` too."""
    return lambda value: min(value, limit) if value else (limit if fill else value)


def always(smoke_value: Any) -> Callable[[Any], Any]:
    """Smoke rule: ``smoke_value`` whatever was asked (one torch thread, every shard in this process)."""
    return lambda value: smoke_value


def first(values: Sequence[Any]) -> tuple[Any, ...]:
    """Smoke rule: the first of several (one ratio of a sweep)."""
    return tuple(values[:1])


def smoke_mode() -> bool:
    """Whether ``RADARSEG_SMOKE`` asks for tiny sizes."""
    return environment().smoke


def smoke_config(cfg: Any) -> Any:
    """``cfg`` with every field that declares a smoke rule (:func:`smoke`) set by that rule."""
    if not dataclasses.is_dataclass(cfg):
        return cfg
    changes = {f.name: f.metadata[SMOKE](getattr(cfg, f.name)) for f in dataclasses.fields(cfg) if SMOKE in f.metadata}
    return dataclasses.replace(cfg, **changes)


def run_job(name: str, argv: Sequence[str] | None, prog: str, *,
            options: str | None = None) -> tuple[dict[str, Any], str]:
    """Parse, run and format one job: ``(result, printed summary)``; tiny sizes under ``RADARSEG_SMOKE=1``.
    The summary is text for people, or with ``--json`` the result as one JSON line for machines. The arguments are
    parsed by the job's ``options`` module (default: the job module) before the job module loads."""
    args = parse_job_args(job_module(options or name, OPTIONS), argv, prog)
    module = job_module(name)
    cfg = config_of(module, args)
    if smoke_mode():
        cfg = smoke_config(cfg)
    result = module.main(cfg)
    return result, json.dumps(result, default=str) if getattr(args, "json", False) else module.format_result(result)


def run_module(name: str, argv: Sequence[str] | None = None) -> int:
    """``python -m pipelines.JOB``: the same job as ``radarseg JOB``, errors as one line with exit code 2."""
    try:
        _, summary = run_job(name, argv, prog=f"python -m {name}")
    except USER_ERRORS as exc:
        return report_error(f"python -m {name}", exc)
    print(summary)
    return 0


# Reported as one line (exit status 2); any other exception, a plain ValueError included, is a bug: traceback.
USER_ERRORS = (UserError, FileExistsError, FileNotFoundError, UnknownPresetError)


def report_error(command: str, exc: BaseException) -> int:
    """One line on stderr naming the command and what was expected; exit code 2."""
    print(f"{command}: error: {exc}", file=sys.stderr)
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_module(sys.argv[1], sys.argv[2:]))
