"""Options that took another name: the old spelling stays known to the parser only to be refused with one line
naming the new one (exit code 2), so a command copied from an older page fails clearly instead of silently."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any


class _Renamed(argparse.Action):
    def __init__(self, option_strings: Sequence[str], dest: str, *, new: str, why: str = "", **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs="?", help=argparse.SUPPRESS, **kwargs)
        self.new, self.why = new, why

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        value = f" {values}" if values is not None else ""
        parser.error(f"{option_string} is now {self.new}{self.why}: use {self.new}{value}")


def add_renamed(parser: argparse.ArgumentParser, old: str, new: str, why: str = "") -> None:
    """Refuse ``old`` (taking one value or none, hidden from --help) with a line naming ``new``; ``why`` (such as
    "; --profile names a radar") follows the names."""
    parser.add_argument(old, action=_Renamed, new=new, why=why, dest=f"renamed_{old.lstrip('-').replace('-', '_')}",
                        default=argparse.SUPPRESS)
