"""Data sources as typed options: each option and the documented one-string spelling give the same source."""

import argparse

import pytest

from pipelines.datasets.sources import DataSource, SourceKind, add_source_arguments, parse_source, source_from_args
from radar.errors import UserError

KINDS = (SourceKind.SIM, SourceKind.RECORDING, SourceKind.CARRADA)


def parse(argv: list[str]) -> str:
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_source_arguments(parser, KINDS)
    return source_from_args(parser.parse_args(argv), KINDS)


@pytest.mark.parametrize(("typed", "one_string"), [
    (["--sim"], ["--source", "sim"]),
    (["--recording", "data/rec"], ["--source", "recording:data/rec"]),
    (["--carrada", "/data/Carrada"], ["--source", "carrada:/data/Carrada"]),
])
def test_a_typed_option_and_the_documented_spelling_are_the_same_source(typed, one_string):
    assert parse(typed) == parse(one_string) == one_string[1]


def test_wrong_spellings_name_the_accepted_ones():
    for text in ("bogus", "recording", "sim:x", "store:s.zarr", "adc-recording:d"):
        with pytest.raises(UserError, match=r"--source must be 'sim', 'recording:DIR' or 'carrada:ROOT'"):
            parse_source(text, KINDS)
    assert parse_source("recording:a:b", KINDS) == DataSource(SourceKind.RECORDING, "a:b")  # a colon in a path


def test_exactly_one_source_option_is_required():
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_source_arguments(parser, KINDS)
    with pytest.raises(argparse.ArgumentError):
        parser.parse_args(["--sim", "--recording", "d"])
    with pytest.raises(SystemExit):  # argparse reports a missing required group by exiting
        parser.parse_args([])
