"""What two stores written by the same job with the same arguments promise to agree on (docs/reference/data.md,
"Reproducibility of a store"), measured array by array and asserted.

- On one machine and one BLAS configuration: every array bit for bit, and every attribute but the job's own
  (``job``: the output path; ``code_version``: the checkout).
- Across BLAS configurations (another CPU, or OpenBLAS told another kernel by ``OPENBLAS_CORETYPE``): the simulator
  synthesises the beat signal with a complex64 matrix product, whose last float32 bits depend on the BLAS kernel's
  summation order. So ``input`` (float16 dB) may differ in a few values, each by at most one float16 step at the
  store's scale (the spacing of float16 at the largest input value: 0.0625 dB below 128 dB), and the normalisation
  statistics computed from it by as much; every other array (labels, instances, masks, heatmap, object table,
  indices, splits) and every other content attribute stays bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zarr

# Across BLAS configurations at most this fraction of ``input`` values may differ: a systematic change (another
# seed, a changed simulator) changes most values, a kernel's rounding a few (0.03 % measured on the small preset).
INPUT_DIFFERING_AT_MOST = 0.01
# Attributes that describe the store's content, not the run that wrote it (``job`` names the output path and
# ``code_version`` the checkout); ``normalisation`` is compared apart, as the input it is computed from.
CONTENT_ATTRIBUTES = ("format", "version", "layout", "preset", "radar", "schema", "class_names", "splits",
                      "sequences", "object_fields", "class_voxel_counts", "report", "source", "split_rule",
                      "simulator")


@dataclass(frozen=True)
class ArrayDifference:
    """How one array of two stores differs: ``differing`` values of ``size`` (NaN equals NaN), by at most
    ``max_abs`` (0 where none differ; in the array's unit, dB for ``input``)."""

    name: str
    dtype: str
    size: int
    differing: int
    max_abs: float


def store_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of a zarr store by its path in the store (progress markers left out)."""
    group = zarr.open_group(str(path), mode="r")
    return {name: np.asarray(member[...]) for name, member in group.members(max_depth=None)
            if isinstance(member, zarr.Array) and not name.startswith("progress")}


def array_differences(left: dict[str, np.ndarray], right: dict[str, np.ndarray]) -> dict[str, ArrayDifference]:
    """The difference of every array the two stores share, by name."""
    differences = {}
    for name in sorted(set(left) & set(right)):
        a, b = left[name], right[name]
        assert a.shape == b.shape and a.dtype == b.dtype, (name, a.shape, b.shape, a.dtype, b.dtype)
        same = a == b
        if a.dtype.kind == "f":
            same |= np.isnan(a) & np.isnan(b)
        differing = int(a.size - np.count_nonzero(same))
        max_abs = float(np.abs(a[~same].astype(np.float64) - b[~same].astype(np.float64)).max()) if differing else 0.0
        differences[name] = ArrayDifference(name, str(a.dtype), int(a.size), differing, max_abs)
    return differences


def input_step(arrays: dict[str, np.ndarray]) -> float:
    """One float16 step at the store's scale: the spacing of float16 at the largest ``input`` value (dB)."""
    return float(np.spacing(np.abs(arrays["input"]).max().astype(np.float16)))


def assert_same_store(left: str | Path, right: str | Path) -> None:
    """The promise on one machine and BLAS configuration: every array and content attribute bit for bit."""
    a, b = store_arrays(left), store_arrays(right)
    assert a and sorted(a) == sorted(b), (sorted(a), sorted(b))
    differing = {name: d for name, d in array_differences(a, b).items() if d.differing}
    assert not differing, differing
    attrs_a, attrs_b = _attributes(left), _attributes(right)
    for name in (*CONTENT_ATTRIBUTES, "normalisation"):
        assert attrs_a.get(name) == attrs_b.get(name), name


def assert_blas_promise(left: str | Path, right: str | Path) -> dict[str, ArrayDifference]:
    """The promise across BLAS configurations (module docstring); returns what was measured, array by array."""
    a, b = store_arrays(left), store_arrays(right)
    assert a and sorted(a) == sorted(b), (sorted(a), sorted(b))
    differences = array_differences(a, b)
    exact = {name: d for name, d in differences.items() if name != "input" and d.differing}
    assert not exact, f"only input may differ across BLAS configurations: {exact}"
    step = max(input_step(a), input_step(b))
    found = differences["input"]
    assert found.max_abs <= step, f"input differs by more than one float16 step ({step} dB): {found}"
    assert found.differing <= INPUT_DIFFERING_AT_MOST * found.size, f"input differs in too many values: {found}"
    attrs_a, attrs_b = _attributes(left), _attributes(right)
    for name in CONTENT_ATTRIBUTES:
        assert attrs_a.get(name) == attrs_b.get(name), name
    stats_a, stats_b = attrs_a["normalisation"], attrs_b["normalisation"]
    assert sorted(stats_a) == sorted(stats_b), (sorted(stats_a), sorted(stats_b))
    for name in stats_a:  # a mean or a standard deviation moves by no more than the values it is taken of
        if isinstance(stats_a[name], float | list):
            np.testing.assert_allclose(stats_a[name], stats_b[name], rtol=0, atol=step, err_msg=name)
        else:  # frames, voxels, units, split
            assert stats_a[name] == stats_b[name], name
    return differences


def _attributes(path: str | Path) -> dict:
    return dict(zarr.open_group(str(path), mode="r").attrs)
