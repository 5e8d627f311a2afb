"""``radarseg JOB --help`` loads neither torch nor zarr: a job's options are declared in a light module
(:mod:`pipelines.jobs`), so help and a wrong option answer at once instead of after seconds of imports.

Each case runs the command line in a fresh interpreter and reads ``sys.modules`` once argparse has printed the help;
no wall time is asserted (the machine's load decides that), only what was imported."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from pipelines.cli import JOBS

HEAVY = ("torch", "zarr")

# Runs ``radarseg ARGS`` in process, then prints the heavy modules that are loaded, as JSON, on the last line.
PROBE = """
import json, sys
from pipelines.cli import main
for name in sys.argv[2:]:
    __import__(name)  # the control case: a module known to load torch
try:
    main(json.loads(sys.argv[1]))
except SystemExit:
    pass
print(json.dumps(sorted(m for m in {heavy!r} if m in sys.modules)))
"""


def loaded_after(argv: list[str], *imports: str) -> tuple[list[str], str]:
    """(the heavy modules loaded once ``radarseg ARGV`` returned, what it printed)."""
    done = subprocess.run([sys.executable, "-c", PROBE.format(heavy=HEAVY), json.dumps(argv), *imports],
                          capture_output=True, text=True, timeout=300, check=True)
    *printed, last = done.stdout.rstrip("\n").split("\n")
    return json.loads(last), "\n".join(printed)


@pytest.mark.parametrize("command", sorted(JOBS))
def test_help_of_a_job_loads_neither_torch_nor_zarr(command):
    heavy, printed = loaded_after([command, "--help"])
    assert f"usage: radarseg {command}" in printed
    assert heavy == [], f"radarseg {command} --help imported {heavy}"


def test_the_probe_sees_torch_when_it_is_loaded():
    heavy, printed = loaded_after(["train", "--help"], "pipelines.training.loop")
    assert "usage: radarseg train" in printed
    assert "torch" in heavy
