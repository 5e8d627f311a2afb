"""Preprocessing splits: every requested non-zero split gets a sequence when there are enough, and a store that
cannot have one says so."""

from __future__ import annotations

import logging
from collections import Counter

import pytest

from pipelines.datasets.preprocess import DEFAULT_SPLIT_FRACTIONS, PreprocessConfig, _split_by_fractions, plan_job


def _counts(n: int, fractions=DEFAULT_SPLIT_FRACTIONS) -> Counter:
    return Counter(_split_by_fractions([f"seq_{i:03d}" for i in range(n)], fractions).values())


@pytest.mark.parametrize("n", [3, 4, 5, 7, 10])
def test_small_stores_get_every_default_split(n):
    counts = _counts(n)
    assert all(counts[split] >= 1 for split in ("train", "val", "test")), counts
    assert sum(counts.values()) == n and counts["train"] >= counts["val"]


def test_large_stores_follow_the_fractions_and_splits_are_contiguous_in_name_order():
    assert _counts(1000) == Counter(train=700, val=150, test=150)
    names = [f"seq_{i:03d}" for i in range(20)]
    assigned = list(_split_by_fractions(names, (0.5, 0.25, 0.25)).values())
    assert assigned == ["train"] * 10 + ["val"] * 5 + ["test"] * 5
    assert _counts(4, (0.5, 0.5, 0.0)) == Counter(train=2, val=2)  # a zero fraction stays empty


def test_too_few_sequences_for_the_requested_splits_is_a_warning_naming_them(tmp_path, caplog):
    cfg = PreprocessConfig(source="sim", out=str(tmp_path / "s.zarr"), preset="small", sequences=2, frames=1,
                           progress=False)
    with caplog.at_level(logging.WARNING, logger="pipelines.datasets.preprocess"):
        plan = plan_job(cfg)
    assert sorted(slot.split for slot in plan.frames) == sorted({0, 1})  # train and val, one sequence each
    (record,) = [r for r in caplog.records if "no sequence" in r.getMessage()]
    assert "'test'" in record.getMessage() and "at least 3 sequences" in record.getMessage()
