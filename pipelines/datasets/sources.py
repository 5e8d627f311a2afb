"""Where a job's frames come from, as typed options: ``--sim``, ``--recording DIR``, ``--adc-recording DIR``,
``--carrada ROOT`` and ``--store STORE`` (each job accepts its own subset), or the one-string spelling the docs
have always used (``--source recording:DIR``), which parses to the same :class:`DataSource`.

A job's config keeps the source's canonical string (:meth:`DataSource.spelling`), so a store made with
``--recording DIR`` resumes with ``--source recording:DIR`` and the other way round.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

from radar.errors import UserError


class SourceKind(StrEnum):
    """What a source is; the value is its option name and the prefix of its one-string spelling."""

    SIM = "sim"  # the FMCW simulator, run inside the job's tasks (no location)
    RECORDING = "recording"  # a folder of RAD cubes (radar.io.recording)
    ADC_RECORDING = "adc-recording"  # a folder of raw ADC samples, processed on read
    CARRADA = "carrada"  # a CARRADA root (radar.io.carrada)
    STORE = "store"  # a preprocessed zarr store (pipelines.datasets.store)


METAVAR = {SourceKind.RECORDING: "DIR", SourceKind.ADC_RECORDING: "DIR", SourceKind.CARRADA: "ROOT",
           SourceKind.STORE: "STORE.zarr"}
HELP = {SourceKind.SIM: "the FMCW simulator, run inside the tasks (--preset, --sequences, --frames, --seed)",
        SourceKind.RECORDING: "a recording of RAD cubes", SourceKind.ADC_RECORDING:
        "a recording of raw ADC samples, processed in the tasks", SourceKind.CARRADA: "a CARRADA root with its "
        "split file", SourceKind.STORE: "a preprocessed store"}


@dataclass(frozen=True)
class DataSource:
    """A source of frames: its kind and, for all but ``sim``, its location (a path as given)."""

    kind: SourceKind
    location: str | None = None

    def spelling(self) -> str:
        """The one-string form (``sim``, ``recording:DIR``): what job configs and store attributes keep."""
        return str(self.kind) if self.location is None else f"{self.kind}:{self.location}"


def _dest(kind: SourceKind) -> str:
    """The argparse destination of a kind's typed option (``--adc-recording`` -> ``source_adc_recording``)."""
    return f"source_{kind.replace('-', '_')}"


def expected(kinds: Sequence[SourceKind]) -> str:
    """``'sim', 'recording:DIR' or 'carrada:ROOT'``: the spellings ``kinds`` accept, for messages and help."""
    spelled = [f"'{k}'" if k is SourceKind.SIM else f"'{k}:{METAVAR[k]}'" for k in kinds]
    return ", ".join(spelled[:-1]) + f" or {spelled[-1]}" if len(spelled) > 1 else spelled[0]


def parse_source(text: str, kinds: Sequence[SourceKind]) -> DataSource:
    """The :class:`DataSource` of a one-string spelling; UserError naming the accepted spellings otherwise."""
    kind, _, location = text.partition(":")
    if kind not in tuple(kinds) or (kind == SourceKind.SIM) != (location == ""):
        raise UserError(f"--source must be {expected(kinds)}, got {text!r}")
    return DataSource(SourceKind(kind), location or None)


def add_source_arguments(parser: argparse.ArgumentParser, kinds: Sequence[SourceKind]) -> None:
    """One required choice among ``--source TEXT`` and a typed option per kind in ``kinds``."""
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--source", help=f"the source in one string: {expected(kinds)}")
    for kind in kinds:
        if kind is SourceKind.SIM:
            group.add_argument(f"--{kind}", dest=_dest(kind), action="store_true", help=HELP[kind])
        else:
            group.add_argument(f"--{kind}", dest=_dest(kind), metavar=METAVAR[kind], help=HELP[kind])


def source_from_args(args: argparse.Namespace, kinds: Sequence[SourceKind]) -> str:
    """The canonical spelling of the source the options name (checked by :func:`parse_source` when given as
    ``--source``)."""
    if args.source is not None:
        return parse_source(args.source, kinds).spelling()
    for kind in kinds:
        value = getattr(args, _dest(kind))
        if value:
            return DataSource(kind, None if kind is SourceKind.SIM else value).spelling()
    raise UserError(f"a source is required: {expected(kinds)}")
