"""``--profile``, the one option that names the radar on every command that takes one: a preset's name (carrada, nxp,
small) or a .toml/.json profile file. ``--preset``, its former name on simulate, preprocess and models summary, is
still read, with a note that names ``--profile``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

RADAR_HELP = "the radar: a preset (carrada, nxp, small) or a .toml/.json profile file"


class _FormerName(argparse.Action):
    """``--preset VALUE``: stored as ``--profile`` would store it, with a note on stderr."""

    def __init__(self, option_strings: Sequence[str], dest: str, *, append: bool = False, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kwargs)
        self.append = append

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        print(f"note: {option_string} is now --profile: use --profile {values}", file=sys.stderr)
        if self.append:
            setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), values])
        else:
            setattr(namespace, self.dest, values)


def add_radar_option(parser: argparse.ArgumentParser, *, help: str = RADAR_HELP,  # noqa: A002 (argparse's name)
                     former: bool = False, append: bool = False, **kwargs: Any) -> None:
    """``--profile`` (``dest="profile"``); with ``former``, ``--preset`` too, read as ``--profile`` with a note.
    ``append`` collects repeated options into a list; other keyword arguments go to ``add_argument``."""
    parser.add_argument("--profile", help=help, action="append" if append else "store", **kwargs)
    if former:
        parser.add_argument("--preset", action=_FormerName, dest="profile", append=append, default=argparse.SUPPRESS,
                            **{k: v for k, v in kwargs.items() if k == "choices"})
