"""A store's reproducibility promise (docs/reference/data.md) on this host, without Docker: the same small preprocess
run in subprocesses under OpenBLAS configurations that some machines set (OPENBLAS_CORETYPE, OPENBLAS_L2_SIZE).
Across configurations only ``input`` may differ, by one float16 step at the store's scale, and the comparison
refuses anything more. The compose stack's test (tests/deploy/) checks the same promise between a container and
the host."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from tests.pipelines.conftest import REPO
from tests.pipelines.datasets.store_agreement import assert_blas_promise, assert_same_store

pytestmark = pytest.mark.slow

PREPROCESS = ["--source", "sim", "--preset", "small", "--sequences", "2", "--frames", "1", "--seed", "3",
              "--split-fractions", "0.5", "0.5", "0", "--in-process", "--no-progress", "--json"]
# The machine's own choice, then two that differ from it on an x86-64 CPU: Haswell's kernels (AVX2 with FMA, what
# some CI machines force, with a smaller L2 blocking) and Sandy Bridge's (AVX without FMA: another rounding).
# An architecture that ignores a name runs its own kernel, and the promise holds trivially.
BLAS_CONFIGURATIONS = {
    "default": {},
    "haswell": {"OPENBLAS_CORETYPE": "Haswell", "OPENBLAS_L2_SIZE": "262144"},
    "sandybridge": {"OPENBLAS_CORETYPE": "SandyBridge"},
}


def _preprocess(out: Path, blas: dict[str, str]) -> Path:
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")}
    proc = subprocess.run([sys.executable, "-m", "pipelines.datasets.preprocess", *PREPROCESS, "--out", str(out)],
                          cwd=REPO, env={**env, **blas}, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    result = json.loads(next(line for line in proc.stdout.splitlines() if line.startswith('{"store"')))
    assert result["written"] == 2, result
    return out


def test_a_store_agrees_across_blas_configurations_within_one_float16_step_of_its_input(tmp_path):
    """(bit for bit in one configuration: test_preprocess.py's resumed and straight runs)"""
    stores = {name: _preprocess(tmp_path / f"{name}.zarr", blas) for name, blas in BLAS_CONFIGURATIONS.items()}
    pairs = [("default", "haswell"), ("default", "sandybridge"), ("haswell", "sandybridge")]
    measured = {pair: assert_blas_promise(stores[pair[0]], stores[pair[1]]) for pair in pairs}
    # what differed (shown with -rP): input values differing of 1,048,576, and by how much (dB)
    print({" vs ".join(pair): (d["input"].differing, d["input"].max_abs) for pair, d in measured.items()})


@pytest.mark.parametrize(("array", "change", "message"), [
    ("labels", lambda a: a.__setitem__((0, 0, 0, 0), a[0, 0, 0, 0] + 1), "only input may differ"),
    ("objects", lambda a: a.__setitem__((0, 0, 0), -1.0), "only input may differ"),  # an id, or NaN padding
    ("input", lambda a: a.__setitem__((0, 0, 0, 0), a[0, 0, 0, 0] + np.float16(0.25)), "more than one float16 step"),
    ("input", lambda a: a.__setitem__((0, slice(None)), np.nextafter(a[0], np.float16(np.inf))), "too many values"),
])
def test_the_promise_refuses_what_it_does_not_allow(small_store, tmp_path, array, change, message):
    """the comparison fails on a changed label or object, an input value two steps off, or many inputs a step off."""
    changed = tmp_path / "changed.zarr"
    shutil.copytree(small_store, changed)
    values = zarr.open_group(str(changed), mode="r+")[array]
    block = values[...]
    change(block)
    values[...] = block
    with pytest.raises(AssertionError, match=message):
        assert_blas_promise(small_store, changed)
    with pytest.raises(AssertionError):
        assert_same_store(small_store, changed)
