"""A user's mistake is one line with exit status 2; any other exception, a plain ValueError included, is a bug
and keeps its traceback (pipelines.jobs, radar.errors)."""

from __future__ import annotations

import sys
import types

import pytest

from pipelines.jobs import run_module
from radar.errors import DataError, UserError


def _job(monkeypatch, error: Exception) -> str:
    """A job module whose config takes ``--bad`` (refused) and whose main raises ``error``."""
    module = types.ModuleType("fake_job")

    def config_from_args(args):
        if args.bad:
            raise ValueError("--bad must be 0")  # a config refusing an argument: the user's mistake
        return {}

    def main(cfg):
        raise error

    module.add_arguments = lambda parser: parser.add_argument("--bad", type=int, default=0)
    module.config_from_args, module.main, module.format_result = config_from_args, main, str
    monkeypatch.setitem(sys.modules, "fake_job", module)
    return "fake_job"


def test_user_errors_are_one_line_and_bugs_keep_their_traceback(monkeypatch, capsys):
    assert issubclass(DataError, UserError) and issubclass(UserError, ValueError)
    assert run_module(_job(monkeypatch, UserError("expected a store, got nothing")), []) == 2
    assert capsys.readouterr().err.strip() == "python -m fake_job: error: expected a store, got nothing"
    assert run_module(_job(monkeypatch, UserError("unused")), ["--bad", "1"]) == 2
    assert "--bad must be 0" in capsys.readouterr().err
    with pytest.raises(ValueError, match="a bug"):
        run_module(_job(monkeypatch, ValueError("a bug")), [])
