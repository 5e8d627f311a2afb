"""The suite's ``xdist_group`` marks take effect (``make test`` runs ``--dist loadgroup``): the Ray tests share one
worker, so one cluster at a time runs beside the other worker's tests (tests/conftest.py), and a module whose
fixture is costly builds it once. pytest 9.2 with pytest-xdist 3.8 silently ignores the marks (pytest-xdist issue
1386: xdist writes the node id's old field, which pytest 9.2 no longer reads), hence the pin in pyproject.toml."""

from __future__ import annotations

import subprocess
import sys

GROUPED = '''
import os
import pytest

pytestmark = pytest.mark.xdist_group("one")

@pytest.mark.parametrize("i", range(6))
def test_worker(i):
    assert os.environ["PYTEST_XDIST_WORKER"]
'''


def test_a_group_runs_on_one_worker(tmp_path):
    (tmp_path / "test_grouped.py").write_text(GROUPED)
    run = subprocess.run([sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v",
                          "-p", "no:cacheprovider", "test_grouped.py"], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    passed = [line.split()[0] for line in run.stdout.splitlines() if line.startswith("[gw") and "PASSED" in line]
    assert len(passed) == 6, run.stdout[-2000:]
    workers = set(passed)
    assert len(workers) == 1, f"the group's 6 tests ran on workers {sorted(workers)}"
