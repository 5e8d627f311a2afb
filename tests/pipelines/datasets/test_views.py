"""The baselines' data side (views, frame windows) and their training job, on a tiny simulated store."""

import json

import numpy as np
import pytest
import torch

from pipelines.datasets.store import open_store
from pipelines.datasets.views import (
    ViewDataset,
    ViewStats,
    collate_views,
    frame_views,
    frame_windows,
    scored_frames,
    split_windows,
    view_class_counts,
)
from radar import transforms
from radar.input_kind import InputKind


def test_windows_stay_in_their_sequence_and_look_back_only():
    # slots:            0  1  2  3  4  5  6  7  8  9
    sequence_id = np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 1])
    frame_index = np.array([0, 1, 2, 3, 0, 1, 2, 3, 4, 5])
    available = np.ones(10, bool)
    available[7] = False  # a quarantined frame in sequence 1
    windows = frame_windows(sequence_id, frame_index, np.arange(10), available, 3)
    # targets 4, 5 lack history; 8, 9 would need the quarantined slot 7
    np.testing.assert_array_equal(windows, [[0, 1, 2], [1, 2, 3], [4, 5, 6]])
    for window in frame_windows(sequence_id, frame_index, np.arange(10), np.ones(10, bool), 3):
        assert len(set(sequence_id[window])) == 1
        np.testing.assert_array_equal(np.diff(frame_index[window]), 1)  # consecutive, the target last
    single = frame_windows(sequence_id, frame_index, np.arange(10), available, 1)
    np.testing.assert_array_equal(single[:, 0], [0, 1, 2, 3, 4, 5, 6, 8, 9])
    with pytest.raises(ValueError, match="n_frames"):
        frame_windows(sequence_id, frame_index, np.arange(10), available, 0)


def test_scored_frames_drop_the_first_frames_of_each_sequence(seq_store):
    for split in ("train", "val", "test"):
        assert scored_frames(seq_store, split, 1) == 6
        assert scored_frames(seq_store, split, 5) == 2  # as MVRSS: the first 4 frames of a sequence are not used
    root = open_store(seq_store)
    for window in split_windows(seq_store, "test", 5):
        assert len(set(root["sequence_id"][:][window])) == 1
        frame_index = root["frame_index"][:][window]
        np.testing.assert_array_equal(frame_index, frame_index[-1] - np.arange(4, -1, -1))  # earlier frames only


def test_views_samples_and_scaling(seq_store):
    stats = ViewStats.from_store(seq_store)
    dataset = ViewDataset(seq_store, "train", n_frames=5, stats=stats)
    assert len(dataset) == 2
    sample = dataset[1]
    assert sample["rd"].shape == (5, 128, 32) and sample["ra"].shape == (5, 128, 128)
    assert sample["ad"].shape == (5, 128, 32)
    assert sample["rd_mask"].shape == (128, 32) and sample["ra_mask"].dtype == torch.int64
    root = open_store(seq_store)
    window = dataset.windows[1]
    assert sample["frame"] == window[-1] and sample["frame_index"] == 5
    for t, slot in enumerate(window):  # oldest first, each frame's own views, scaled by the train min/max
        expected = transforms.ra_view(root["input"][int(slot)].astype(np.float32), kind=InputKind.log_power)
        np.testing.assert_allclose(sample["ra"][t].numpy(), stats.normalise("ra", expected), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(sample["ra_mask"].numpy(), root["ra_mask"][int(window[-1])])
    train_views = [frame_views(root["input"][int(s)]) for s in dataset.windows.ravel()]
    assert min(float(stats.normalise("rd", v["rd"]).min()) for v in train_views) >= 0.0
    assert ViewStats.from_dict(json.loads(json.dumps(stats.to_dict()))) == stats
    batch = collate_views([dataset[0], dataset[1]])
    assert batch["ra"].shape == (2, 5, 128, 128) and batch["rd_mask"].shape == (2, 128, 32)


def test_flips_mirror_the_whole_window_in_angle(seq_store):
    stats = ViewStats.from_store(seq_store)
    plain = ViewDataset(seq_store, "train", n_frames=5, stats=stats)[0]
    flipped = ViewDataset(seq_store, "train", n_frames=5, stats=stats, flip_prob=1.0)[0]
    assert flipped["flipped"]
    mirror = lambda t, axis: torch.roll(torch.flip(t, dims=(axis,)), 1, dims=axis)  # noqa: E731
    torch.testing.assert_close(flipped["ra"], mirror(plain["ra"], 2))
    torch.testing.assert_close(flipped["ad"], mirror(plain["ad"], 1))
    torch.testing.assert_close(flipped["ra_mask"], mirror(plain["ra_mask"], 1))
    torch.testing.assert_close(flipped["rd"], plain["rd"])


def test_class_counts_are_mask_pixels(seq_store):
    counts = view_class_counts(seq_store, "val")
    root = open_store(seq_store)
    val = root["split"][:] == 1
    np.testing.assert_array_equal(counts["ra"], np.bincount(root["ra_mask"][:][val].ravel(), minlength=4))
    np.testing.assert_array_equal(counts["rd"], np.bincount(root["rd_mask"][:][val].ravel(), minlength=4))
