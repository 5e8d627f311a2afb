"""Earlier frames of a frame's sequence, from a store (pipelines/datasets/history.py) and in its Dataset."""

import numpy as np
import pytest
import torch
import zarr

from pipelines.datasets.history import ABSENT, earlier_slots
from pipelines.datasets.store import StoreDataset, flip_angle, open_store
from radar.profiles import get_profile


def test_earlier_slots_follow_each_sequence_and_stop_at_its_start(small_store):
    root = open_store(small_store)  # 2 sequences x 3 frames: slots 0-2 and 3-5
    np.testing.assert_array_equal(earlier_slots(root, 2),
                                  [[ABSENT, ABSENT], [0, ABSENT], [1, 0], [ABSENT, ABSENT], [3, ABSENT], [4, 3]])
    assert earlier_slots(root, 0).shape == (6, 0)


def test_a_quarantined_frame_is_absent_from_the_history_of_the_next(small_store, tmp_path):
    import shutil

    copy = tmp_path / "store.zarr"
    shutil.copytree(small_store, copy)
    valid = zarr.open_array(str(copy / "valid"), mode="r+")
    valid[1] = False
    np.testing.assert_array_equal(earlier_slots(zarr.open_group(str(copy), mode="r"), 1)[:, 0],
                                  [ABSENT, 0, ABSENT, ABSENT, 3, 4])


def test_dataset_history_is_the_earlier_frames_input_and_flips_with_it(small_store):
    plain = StoreDataset(small_store, None, fields=("input", "objects"))
    dataset = StoreDataset(small_store, None, fields=("input", "objects"), history=2)
    sample = dataset[2]
    assert sample["history"].shape == (2, 32, 128, 128) and sample["history_present"].tolist() == [True, True]
    torch.testing.assert_close(sample["history"][0], plain[1]["input"])
    torch.testing.assert_close(sample["history"][1], plain[0]["input"])
    first = dataset[3]  # the second sequence's first frame: nothing earlier
    assert first["history_present"].tolist() == [False, False] and not first["history"].any()
    flipped = flip_angle(sample, get_profile("small"))
    torch.testing.assert_close(flip_angle({"input": sample["history"][0]}, get_profile("small"))["input"],
                               flipped["history"][0])


def test_history_drop_removes_whole_histories_at_random_and_reproducibly(small_store):
    everything = StoreDataset(small_store, None, fields=("input", "objects"), history=1, history_drop=1.0)
    assert not any(everything[i]["history_present"].any() or everything[i]["history"].any() for i in range(6))
    some = [StoreDataset(small_store, None, fields=("input", "objects"), history=1, history_drop=0.5, seed=3)[i]
            ["history_present"].tolist() for i in range(6)]
    again = [StoreDataset(small_store, None, fields=("input", "objects"), history=1, history_drop=0.5, seed=3)[i]
             ["history_present"].tolist() for i in range(6)]
    assert some == again
    with pytest.raises(ValueError, match="history_drop"):
        StoreDataset(small_store, None, history=1, history_drop=1.5)
    with pytest.raises(ValueError, match="'input'"):
        StoreDataset(small_store, None, fields=("objects",), history=1)
