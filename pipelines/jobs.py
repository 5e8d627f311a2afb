"""The job contract: every job of ``pipelines/`` is a module with

- ``add_arguments(parser: argparse.ArgumentParser) -> None``: its options;
- ``config_from_args(args: argparse.Namespace) -> Config``: a frozen config from the parsed options;
- ``main(cfg: Config) -> dict``: the work, returning its figures (as Ray's batch jobs do);
- ``format_result(result: dict) -> str``: what the command line prints afterwards.

``radarseg JOB ...`` (:mod:`pipelines.cli`) and ``python -m pipelines.JOB ...`` (each module's
``__main__`` calls :func:`run_module`) both go through :func:`run_job`, so the two spellings take the
same arguments. A job module is imported only when its command runs: Ray and torch load with the job.
"""

from __future__ import annotations

import argparse
import importlib
import shlex
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import Any

from radar.io.errors import DataError
from radar.profiles import UnknownPresetError

CONTRACT = ("add_arguments", "config_from_args", "main", "format_result")


def job_module(name: str) -> ModuleType:
    """Import a job module (``pipelines.preprocess``) and check that it follows the contract."""
    module = importlib.import_module(name)
    missing = [attr for attr in CONTRACT if not callable(getattr(module, attr, None))]
    if missing:
        raise TypeError(f"job module {name} lacks {', '.join(missing)} (see pipelines.jobs)")
    return module


def job_parser(module: ModuleType, prog: str, description: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=description or (module.__doc__ or "").split("\n")[0])
    module.add_arguments(parser)
    return parser


def parse_config(module: ModuleType, argv: Sequence[str] | None, prog: str) -> Any:
    """The job's config from command-line arguments (exits with argparse's message on bad ones). The
    namespace also carries ``command_line``, the command as typed, for jobs that record it in their report."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = job_parser(module, prog).parse_args(argv)
    args.command_line = shlex.join([*prog.split(), *argv])
    return module.config_from_args(args)


def run_job(name: str, argv: Sequence[str] | None, prog: str) -> tuple[dict[str, Any], str]:
    """Parse, run and format one job: ``(result, printed summary)``."""
    module = job_module(name)
    result = module.main(parse_config(module, argv, prog))
    return result, module.format_result(result)


def run_module(name: str, argv: Sequence[str] | None = None) -> int:
    """``python -m pipelines.JOB``: the same job as ``radarseg JOB``, errors as one line with exit code 2."""
    try:
        _, summary = run_job(name, argv, prog=f"python -m {name}")
    except USER_ERRORS as exc:
        return report_error(f"python -m {name}", exc)
    print(summary)
    return 0


USER_ERRORS = (DataError, ValueError, FileExistsError, FileNotFoundError, UnknownPresetError)


def report_error(command: str, exc: BaseException) -> int:
    """One line on stderr naming the command and what was expected; exit code 2."""
    print(f"{command}: error: {exc}", file=sys.stderr)
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_module(sys.argv[1], sys.argv[2:]))
